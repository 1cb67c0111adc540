#!/usr/bin/env bash
# Packages the GPU benchmarks for a machine with an NVIDIA GPU but no Rust toolchain and no
# network (the device machine of /work/.library/device/README.md): the `inr_gpu`,
# `classify_gpu`, `cluster`, `rounds` and `render` bench binaries (built here, stripped,
# xz-compressed), nats-server, benches/inr_torch.py and benches/render_vtk.py, the volumes they
# read, and the Vulkan loader .deb packages; the device
# side is benches/gpu_device_run.sh. Everything goes into two git-ignored folders of the repository
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
# round, then 3 interleaved rounds of 400 steps x 16384 samples each side (about 3 minutes),
# both sides from neuvolex's initial parameters (init.f32, checked by inr_torch.py against
# neuvolex's heads on the first samples). neuvolex runs one side per fused block size
# (`--paths fused,fused32,fused16`: 64, 32 and 16 samples per workgroup; the ratios are of the
# first, the default), and one per f16 path with blocks of 64 and 32 (`fused-f16`,
# `fused32-f16`: the GEMM tiles on the tensor cores where the NVIDIA driver reports cooperative
# matrices, labelled [f16-tensor-cores], else [f16-rounded]); the launch-path x batch sweep runs
# layered, the three fused blocks and the two f16 paths (`--sweep-paths`), the extraction sweep
# the `--paths` paths at inference micro-batches of 32768, 65536 and 262144, the agreement check
# compares the f16 paths with the layered f32 path and the tensor cores with the same f16
# inputs on the f32 units, and the per-kernel profile uses GPU timestamps where the adapter has
# them.
# The report is rewritten after every stage, so a run cut short keeps what it measured.
# `--only torch` runs that comparison alone (a shorter device call).
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)

device_command() {
  # The device side is benches/gpu_device_run.sh (it travels with the working tree): the
  # classify part (about 1 minute) and the inr part (capped at 7 minutes) fit one 10-minute
  # device call; the cluster part goes in a second call on the warm machine.
  echo 'bash benches/gpu_device_run.sh classify inr'
}

if [ "${1:-}" = "--command" ]; then
  device_command
  exit 0
fi

for d in /.gpubench/ /.gl/; do
  grep -qxF "$d" .git/info/exclude 2>/dev/null || echo "$d" >>"$(git rev-parse --git-path info/exclude)"
done

# Each bench binary, built in release with the GPU features, stripped of debug information and
# xz-compressed (the device call carries at most 64 MiB; gpu_device_run.sh unpacks them).
bench_exe() {
  cargo bench -p neuvolex-benches --bench "$1" --features gpu --no-run --message-format=json 2>/dev/null |
    python3 -c 'import json,sys
for l in sys.stdin:
    m = json.loads(l)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == sys.argv[1] and m.get("executable"):
        print(m["executable"])' "$1" | tail -1
}
rm -rf .gpubench
mkdir -p .gpubench/data
for bench in inr_gpu classify_gpu cluster rounds render; do
  echo "building the $bench bench binary (release, --features gpu)"
  exe=$(bench_exe "$bench")
  [ -x "$exe" ] || { echo "no $bench executable was built" >&2; exit 1; }
  cp "$exe" ".gpubench/$bench"
  strip ".gpubench/$bench"
done
# The cluster part needs nats-server (deploy/cluster.sh installs it here).
nats=$(command -v nats-server || true)
if [ -n "$nats" ]; then
  cp "$nats" .gpubench/nats-server
else
  echo "note: no nats-server here (deploy/cluster.sh install); the cluster part will not run" >&2
fi
cp benches/inr_torch.py benches/render_vtk.py .gpubench/
# Where the figures come from: the device copy has no git history, so the commit, the dirty
# flag and the build machine are recorded here and printed by the device command (with the
# device's CPU, GPU, driver, and the versions of PyTorch, CUDA and numpy it runs against).
dirty=$(git status --porcelain --untracked-files=no | wc -l)
{
  echo "commit: $(git rev-parse HEAD) ($(git log -1 --format=%cs)), $([ "$dirty" -eq 0 ] && echo clean || echo "dirty ($dirty tracked files modified)")"
  echo "built: $(date -u '+%F %H:%M') UTC on $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(rustc --version)"
  for bench in inr_gpu classify_gpu cluster rounds render; do
    echo "$bench sha256: $(sha256sum ".gpubench/$bench" | cut -c1-16)"
  done
} >.gpubench/provenance.txt
cat .gpubench/provenance.txt
data="${NEUVOLEX_DATA:-$root/../shared/data}"
for rel in tooth/tooth.nhdr tooth/tooth.raw abdomen_ct/ct.nii.gz abdomen_ct/labels.nii.gz scivis/bonsai.nii.gz; do
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

xz -T0 -6 -f .gpubench/inr_gpu .gpubench/classify_gpu .gpubench/cluster .gpubench/rounds .gpubench/render
[ -f .gpubench/nats-server ] && xz -T0 -6 -f .gpubench/nats-server
du -sh .gpubench .gl
echo
echo "device run: carry [\".gpubench\", \".gl\"], timeout_s 600, command (then, on the warm"
echo "machine, 'bash benches/gpu_device_run.sh rounds', '... cluster' and '... render'"
echo "with the time left):"
device_command
