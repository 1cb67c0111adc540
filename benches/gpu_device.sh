#!/usr/bin/env bash
# Packages the GPU benchmark for a machine with an NVIDIA GPU but no Rust toolchain and no
# network (the device machine of /work/.library/device/README.md): the `inr_gpu` bench binary
# (built here, with the wgpu renderer), benches/inr_torch.py, the volumes it reads, and the
# Vulkan loader .deb packages. Everything goes into two git-ignored folders of the repository
# root, `.gpubench/` and `.gl/`, which the device call carries; nothing here is committed.
#
#   benches/gpu_device.sh            # build and package (prints the device command)
#   benches/gpu_device.sh --command  # only print the device command
#
# On the device machine (carry [".gpubench", ".gl"]), the printed command unpacks the loader,
# points Vulkan at NVIDIA's ICD and runs the bench with PyTorch on CUDA in the same run,
# writing the JSON report, the log and provenance.txt (commit, dirty flag, build and device
# machines, driver, PyTorch, CUDA and numpy versions) under $OUT. The comparison with PyTorch (inr_gpu.rs's
# `vs_torch_gpu`) uses the device's python3 (which holds torch), .gpubench/inr_torch.py, and
# one persistent PyTorch process: compile and CUDA-graph capture of every variant, a screening
# round, then 3 interleaved rounds of 400 steps x 16384 samples each side (about 3 minutes).
# `--only torch` runs that comparison alone (a shorter device call).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)

device_command() {
  # nvidia-smi samples utilisation and memory every second beside the bench (smi.csv); the
  # bench is capped so the whole command ends inside one 10-minute device call.
  cat <<'EOF'
cat .gpubench/provenance.txt | tee $OUT/provenance.txt; echo "device: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) threads, $(awk '/MemTotal/ {printf "%.0f GiB", $2 / 1048576}' /proc/meminfo), $(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | head -1)" | tee -a $OUT/provenance.txt; python3 -c 'import torch, numpy; print(f"device references: torch {torch.__version__} (CUDA {torch.version.cuda}, cuDNN {torch.backends.cudnn.version()}), numpy {numpy.__version__}")' | tee -a $OUT/provenance.txt; for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig; export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json; export NEUVOLEX_DATA=$PWD/.gpubench/data NEUVOLEX_TORCH_SCRIPT=$PWD/.gpubench/inr_torch.py NEUVOLEX_TORCH_PYTHON=python3 BENCH_DATE=$(date -u +%F); nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee $OUT/gpu.txt; nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader -l 1 >$OUT/smi.csv 2>&1 & set -o pipefail; timeout 540 .gpubench/inr_gpu --cap-s 60 --sweep-s 8 --torch-steps 400 --rounds 3 --cpu-s 5 --out $OUT/inr_gpu.json 2>&1 | tee $OUT/inr_gpu.log; kill %1 2>/dev/null; awk -F', ' '{u=$2+0; s+=u; n++; if(u>0){b++}} END {if(n) printf "nvidia-smi: %d samples, mean utilisation %.0f %%, busy in %d\n", n, s/n, b}' $OUT/smi.csv
EOF
}

if [ "${1:-}" = "--command" ]; then
  device_command
  exit 0
fi

for d in /.gpubench/ /.gl/; do
  grep -qxF "$d" .git/info/exclude 2>/dev/null || echo "$d" >>"$(git rev-parse --git-path info/exclude)"
done

echo "building the inr_gpu bench binary (release, --features gpu)"
exe=$(cargo bench -p neuvolex-benches --bench inr_gpu --features gpu --no-run --message-format=json 2>/dev/null |
  python3 -c 'import json,sys
for l in sys.stdin:
    m = json.loads(l)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "inr_gpu" and m.get("executable"):
        print(m["executable"])' | tail -1)
[ -x "$exe" ] || { echo "no inr_gpu executable was built" >&2; exit 1; }

rm -rf .gpubench
mkdir -p .gpubench/data
cp "$exe" .gpubench/inr_gpu
# Without debug information: the device call carries at most 64 MiB.
strip .gpubench/inr_gpu
cp benches/inr_torch.py .gpubench/
# Where the figures come from: the device copy has no git history, so the commit, the dirty
# flag and the build machine are recorded here and printed by the device command (with the
# device's CPU, GPU, driver, and the versions of PyTorch, CUDA and numpy it runs against).
dirty=$(git status --porcelain --untracked-files=no | wc -l)
{
  echo "commit: $(git rev-parse HEAD) ($(git log -1 --format=%cs)), $([ "$dirty" -eq 0 ] && echo clean || echo "dirty ($dirty tracked files modified)")"
  echo "built: $(date -u '+%F %H:%M') UTC on $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(rustc --version)"
  echo "inr_gpu sha256: $(sha256sum .gpubench/inr_gpu | cut -c1-16)"
} >.gpubench/provenance.txt
cat .gpubench/provenance.txt
data="${NEUVOLEX_DATA:-$root/../shared/data}"
for rel in tooth/tooth.nhdr tooth/tooth.raw abdomen_ct/ct.nii.gz scivis/bonsai.nii.gz; do
  if [ -f "$data/$rel" ]; then
    mkdir -p ".gpubench/data/$(dirname "$rel")"
    cp "$data/$rel" ".gpubench/data/$rel"
  else
    echo "note: $data/$rel is missing; the bench skips that volume" >&2
  fi
done

if ! ls .gl/libvulkan1_*.deb >/dev/null 2>&1; then
  echo "downloading the Vulkan loader packages (amd64) into .gl/"
  mkdir -p .gl /tmp/amd64/partial
  o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
  # shellcheck disable=SC2086
  apt-get $o update >/dev/null
  # shellcheck disable=SC2086
  (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
fi

du -sh .gpubench .gl
echo
echo "device run: carry [\".gpubench\", \".gl\"], timeout_s 600, command:"
device_command
