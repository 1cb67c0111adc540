#!/usr/bin/env bash
# Every head-to-head comparison with the tool a user would pick instead, run one after the
# other, each interleaving both sides round by round, into one table:
#   renderer against VTK's fixed-point CPU ray caster (512^2 and 256^2, still and orbiting
#   camera), k-means against scikit-learn (plain Lloyd and bounded), the random forest against
#   scikit-learn (100 and 1000 trees), the INR on the CPU against PyTorch.
# Usage: benches/compare.sh [--quick]   (--quick: fewer rounds, 256^2 only, 100 trees; for a try)
# Writes target/compare/<UTC date-time>/{provenance.txt,<bench>.log,table.md} and prints the
# table. Needs ../shared/data (each bench says SKIP for a missing volume). Creates
# target/benchenv with the pinned references below (PyPI) on first use, and again whenever an
# installed version differs from its pin. Run it on an otherwise idle machine: the ratios come
# from interleaved rounds, but the absolute times do not.
#
# Every run records where its figures come from (provenance.txt, printed first and at the head
# of table.md): the commit and whether the tree had uncommitted changes, the machine (CPU model,
# cores, memory, load), the Rust toolchain, and the version of every reference (numpy, SciPy,
# scikit-learn, threadpoolctl with its BLAS, VTK, PyTorch, nibabel; the NVIDIA driver and CUDA
# where present).
set -euo pipefail
cd "$(dirname "$0")/.."
quick=false
[ "${1:-}" = "--quick" ] && quick=true
env=target/benchenv
# The references, pinned: the versions of the 2026-11-26 runs in BENCHMARKS.md (scipy and
# joblib are scikit-learn's own dependencies, pinned so its solver does not change under it;
# scipy 1.17.1 is the newest for the machine's Python 3.11).
pins=(numpy==2.4.6 scipy==1.17.1 joblib==1.6.0 scikit-learn==1.9.1 threadpoolctl==3.8.0
  vtk==9.7.2 nibabel==5.4.2 torch==2.15.0)
pinned() { # true when every pin is installed at its version
  "$env/bin/python" - "${pins[@]}" <<'PY' >/dev/null 2>&1
import sys
from importlib.metadata import version
sys.exit(any(version(n) != v for n, v in (p.split("==") for p in sys.argv[1:])))
PY
}
if ! pinned; then
  echo "installing the pinned reference implementations into $env: ${pins[*]}"
  [ -x "$env/bin/python" ] || python3 -m venv "$env"
  "$env/bin/pip" install -q "${pins[@]}"
  pinned || { echo "the references in $env do not match their pins" >&2; exit 1; }
fi
py=$PWD/$env/bin/python
export NEUVOLEX_VTK_PYTHON=$py NEUVOLEX_SKLEARN_PYTHON=$py NEUVOLEX_TORCH_PYTHON=$py
out=target/compare/$(date -u +%F-%H%M)
mkdir -p "$out"
{
  commit=$(git rev-parse HEAD)
  dirty=$(git status --porcelain --untracked-files=no | wc -l)
  if [ "$dirty" -eq 0 ]; then state=clean; else state="dirty ($dirty tracked files modified)"; fi
  echo "commit: $commit ($(git log -1 --format=%cs "$commit")), $state"
  echo "machine: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) threads" \
    "($(grep -c ^processor /proc/cpuinfo) logical CPUs), $(awk '/MemTotal/ {printf "%.0f GiB", $2 / 1048576}' /proc/meminfo)," \
    "load $(cut -d' ' -f1-3 /proc/loadavg), $(uname -sr)"
  echo "rust: $(rustc --version)"
  "$py" - <<'PY'
from importlib.metadata import version
import threadpoolctl
names = ["numpy", "scipy", "scikit-learn", "threadpoolctl", "vtk", "torch", "nibabel"]
print("references: " + ", ".join(f"{n} {version(n)}" for n in names))
import numpy  # noqa: F401 (loads its BLAS for threadpoolctl)
blas = [f"{i['internal_api']} {i['version']} ({i.get('threading_layer', '')})"
        for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]
print("blas: " + (", ".join(blas) or "none found"))
import torch
print(f"torch: cuda {torch.version.cuda}, available {torch.cuda.is_available()}")
PY
  if command -v nvidia-smi >/dev/null 2>&1; then
    echo "gpu: $(nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | head -1)"
  else
    echo "gpu: none (no nvidia-smi)"
  fi
} | tee "$out/provenance.txt"
cargo bench -p neuvolex-benches --no-run --bench render --bench kmeans --bench forest --bench inr
run() { # NAME BENCH ARGS...
  local name=$1 bench=$2
  shift 2
  echo "== $name: cargo bench -p neuvolex-benches --bench $bench -- $*"
  cargo bench -q -p neuvolex-benches --bench "$bench" -- "$@" 2>&1 | tee "$out/$name.log"
}
if $quick; then
  run render-256 render --size 256 --frames 3 --no-vtk-gpu
  run kmeans kmeans --rounds 1
  run forest-100 forest --trees 100 --rounds 2
  run inr inr --only torch --rounds 1
else
  run render-512 render --size 512 --frames 7 --no-vtk-gpu
  run render-256 render --size 256 --frames 7 --no-vtk-gpu
  run kmeans kmeans --rounds 3
  run forest-100 forest --trees 100 --rounds 5
  run forest-1000 forest --trees 1000 --rounds 3
  run inr inr --only torch --rounds 3 --torch-steps 100
fi
{
  echo "Head-to-head comparisons, $(date -u '+%F %H:%M') UTC, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) threads. Ratios: the reference's time / ours, per interleaved round, median [min-max]; above 1, neuvolex is faster."
  echo
  sed 's/^/    /' "$out/provenance.txt"
  echo
  echo "| comparison | conditions (work, timed regions, threads, rounds) | neuvolex | reference | reference / neuvolex | equivalence |"
  echo "|---|---|---|---|---|---|"
  grep -h '^summary: ' "$out"/*.log | sed 's/^summary: //'
} >"$out/table.md"
echo
cat "$out/table.md"
echo "logs and table: $out"
