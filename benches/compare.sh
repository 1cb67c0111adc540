#!/usr/bin/env bash
# Every head-to-head comparison with the tool a user would pick instead, run one after the
# other, each interleaving both sides round by round, into one table:
#   renderer against VTK's fixed-point CPU ray caster (512^2 and 256^2, still and orbiting
#   camera), k-means against scikit-learn (plain Lloyd and bounded), the random forest against
#   scikit-learn (100 and 1000 trees), the INR on the CPU against PyTorch.
# Usage: benches/compare.sh [--quick]   (--quick: fewer rounds, 256^2 only, 100 trees; for a try)
# Writes target/compare/<UTC date-time>/{<bench>.log,table.md} and prints the table. Needs
# ../shared/data (each bench says SKIP for a missing volume). Creates target/benchenv (numpy,
# scikit-learn, threadpoolctl, vtk, nibabel, torch from PyPI) on first use. Run it on an
# otherwise idle machine: the ratios come from interleaved rounds, but the absolute times do not.
set -euo pipefail
cd "$(dirname "$0")/.."
quick=false
[ "${1:-}" = "--quick" ] && quick=true
env=target/benchenv
if ! "$env/bin/python" -c 'import numpy, sklearn, threadpoolctl, vtk, nibabel, torch' >/dev/null 2>&1; then
  echo "installing the reference implementations into $env (once)"
  python3 -m venv "$env"
  "$env/bin/pip" install -q numpy scikit-learn threadpoolctl vtk nibabel torch
fi
py=$PWD/$env/bin/python
export NEUVOLEX_VTK_PYTHON=$py NEUVOLEX_SKLEARN_PYTHON=$py NEUVOLEX_TORCH_PYTHON=$py
out=target/compare/$(date -u +%F-%H%M)
mkdir -p "$out"
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
  echo "| comparison | conditions (work, timed regions, threads, rounds) | neuvolex | reference | reference / neuvolex | equivalence |"
  echo "|---|---|---|---|---|---|"
  grep -h '^summary: ' "$out"/*.log | sed 's/^summary: //'
} >"$out/table.md"
echo
cat "$out/table.md"
echo "logs and table: $out"
