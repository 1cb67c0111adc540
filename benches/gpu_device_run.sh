#!/usr/bin/env bash
# The device side of benches/gpu_device.sh: runs on the lent GPU machine (no Rust toolchain, no
# network) from the repository root, with `.gpubench/` and `.gl/` carried, and writes under
# $OUT. It records where the figures come from (provenance.txt: commit, build and device
# machines, driver, PyTorch, CUDA), puts the Vulkan loader in place, samples nvidia-smi beside
# the benches (smi.csv), and runs the parts named, each under its own time limit so a part that
# overruns leaves the next its time and its own partial report:
#
#   classify  benches/classify_gpu.rs: the filter bank and the forest on the GPU, streamed by
#             brick over the 512x512x452 phantom, beside the CPU path (issue 49)
#   inr       benches/inr_gpu.rs: INR training and extraction on the GPU against PyTorch from
#             the same initial weights, on the f32 paths and the f16 ones (tensor cores), the
#             launch-path sweep, the kernel profile, the f16 paths' agreement (issue 46)
#   cluster   benches/cluster.rs: classification of the 512x512x452 phantom in one process and
#             on 2 and 16 one-thread workers over nats-server (the serial part, issue 49)
#   rounds    benches/rounds.rs: whole session rounds of the 512x512x452 phantom predicted on
#             the GPU (streamed blocks), then on the CPU for the ratio, with nothing kept in the
#             store and then with the features kept (issue 49; about 6 minutes)
#   render    benches/render.rs: the wgpu renderer against VTK's GPU mapper
#             (vtkGPUVolumeRayCastMapper, offscreen EGL) and fixed-point caster on the same card
#             and CPU, bonsai and the abdomen CT at 512^2 and 1024^2, still and orbiting, with the
#             image check; VTK where the device's python3 imports vtk and nibabel, else the
#             log says why and the renderers of ours run alone (issue 50; about 4 minutes)
#
#   bash benches/gpu_device_run.sh classify inr     # one device call (about 8 minutes)
#   bash benches/gpu_device_run.sh cluster          # a second call on the warm machine
#   bash benches/gpu_device_run.sh rounds           # a third
#   bash benches/gpu_device_run.sh render           # a fourth
#
# At most 8 files come back from a device call: provenance.txt, smi.csv, and a JSON report and
# a log per part.
set -uo pipefail
: "${OUT:?OUT must name the folder whose files come back}"
b=.gpubench
for x in "$b"/*.xz; do
  [ -e "$x" ] && xz -d -k -f "$x" && chmod +x "${x%.xz}"
done
{
  cat "$b/provenance.txt"
  echo "device: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) threads, $(awk '/MemTotal/ {printf "%.0f GiB", $2 / 1048576}' /proc/meminfo), $(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | head -1)"
  python3 -c 'import torch, numpy; print(f"device references: torch {torch.__version__} (CUDA {torch.version.cuda}, cuDNN {torch.backends.cudnn.version()}), numpy {numpy.__version__}")' 2>&1
  echo "parts: $*; started $(date -u '+%F %T') UTC"
} | tee -a "$OUT/provenance.txt"
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
export NEUVOLEX_DATA=$PWD/$b/data NEUVOLEX_TORCH_SCRIPT=$PWD/$b/inr_torch.py NEUVOLEX_TORCH_PYTHON=python3
BENCH_DATE=$(date -u +%F)
export BENCH_DATE
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader -l 1 >>"$OUT/smi.csv" 2>&1 &
smi=$!
for part in "$@"; do
  echo "== $part: $(date -u '+%T') UTC" | tee -a "$OUT/provenance.txt"
  case "$part" in
    classify)
      # shellcheck disable=SC2086
      timeout "${CLASSIFY_S:-110}" "$b/classify_gpu" ${CLASSIFY_ARGS:-} --out "$OUT/classify_gpu.json" 2>&1 | tee "$OUT/classify_gpu.log"
      rc=${PIPESTATUS[0]}
      ;;
    inr)
      # The f16 paths run on the tensor cores where the driver reports cooperative matrices
      # (the log's path labels say [f16-tensor-cores] or [f16-rounded]); the agreement check
      # compares them with the f32 path and with their own arithmetic on the f32 units.
      timeout 420 "$b/inr_gpu" --cap-s 60 --sweep-s 6 --sweep-paths layered,fused,fused32,fused16,fused-f16,fused32-f16 \
        --paths fused,fused32,fused16,fused-f16,fused32-f16 --torch-steps 400 --rounds 3 --cpu-s 5 \
        --out "$OUT/inr_gpu.json" 2>&1 | tee "$OUT/inr_gpu.log"
      rc=${PIPESTATUS[0]}
      ;;
    cluster)
      # The bench's helper looks for nats-server in /usr/sbin, /usr/bin and /usr/local/bin.
      cp "$b/nats-server" /usr/local/bin/nats-server
      NEUVOLEX_BENCH_STAGES=classify NEUVOLEX_BENCH_WORKERS="${CLUSTER_WORKERS:-2,16}" \
        NEUVOLEX_BENCH_WORKER_THREADS=1 NEUVOLEX_BENCH_OUT="$OUT/cluster.json" \
        timeout "${CLUSTER_S:-240}" "$b/cluster" --bench 2>&1 | tee "$OUT/cluster.log"
      rc=${PIPESTATUS[0]}
      ;;
    rounds)
      NEUVOLEX_BENCH_GPU=1 NEUVOLEX_BENCH_ONLY_PHANTOM=1 \
        NEUVOLEX_BENCH_PHANTOM_WHOLE="${ROUNDS_WHOLE:-3}" NEUVOLEX_BENCH_PHANTOM_CPU="${ROUNDS_CPU:-1}" \
        NEUVOLEX_BENCH_PHANTOM_STORED=1 \
        timeout "${ROUNDS_S:-540}" "$b/rounds" 2>&1 | tee "$OUT/rounds.log"
      rc=${PIPESTATUS[0]}
      ;;
    render)
      { python3 -c 'import vtk, nibabel; print(f"VTK {vtk.vtkVersion.GetVTKVersion()}, nibabel {nibabel.__version__}")' 2>/dev/null ||
        echo "no vtk or nibabel in the device's python3: the VTK rows are skipped"; } |
        tee -a "$OUT/provenance.txt"
      rc=0
      for size in ${RENDER_SIZES:-512 1024}; do
        NEUVOLEX_VTK_PYTHON=python3 NEUVOLEX_VTK_SCRIPT="$PWD/$b/render_vtk.py" \
          timeout "${RENDER_S:-120}" "$b/render" --size "$size" --frames "${RENDER_FRAMES:-5}" 2>&1 |
          tee -a "$OUT/render.log"
        r=${PIPESTATUS[0]}
        [ "$r" -ne 0 ] && rc=$r
      done
      ;;
    *) echo "unknown part $part (classify, inr, cluster, rounds, render)"; rc=2 ;;
  esac
  echo "== $part ended $(date -u '+%T') UTC (exit $rc)" | tee -a "$OUT/provenance.txt"
done
kill "$smi" 2>/dev/null
awk -F', ' '{u=$2+0; s+=u; n++; if(u>0){b++}} END {if(n) printf "nvidia-smi: %d samples, mean utilisation %.0f %%, busy in %d\n", n, s/n, b}' "$OUT/smi.csv" | tee -a "$OUT/provenance.txt"
