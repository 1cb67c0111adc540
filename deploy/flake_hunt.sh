#!/usr/bin/env bash
# Hunts flaky tests: runs integration test suites N times each while the machine is kept busy
# (a busy loop per core and a writer that syncs to disk, as a loaded CI machine is), and
# reports every test that failed at least once, with the run and the failure's first lines.
#
#   deploy/flake_hunt.sh [-n RUNS] [-l LOAD_PER_CORE] [SUITE...]
#
# FLAKE_HUNT_HOG_GIB=N adds a process holding N GiB. SUITEs are integration test targets of the workspace (default: serve api history access
# crash cli; the timing-sensitive ones). Built once with the CI feature set (`cargo test
# --workspace --release --features neuvolex-tests/gpu,neuvolex/gpu --no-run`), then each
# suite's binary runs RUNS times (default 5) from its package folder, as cargo runs it. The load
# lives only while the hunt runs: each generator is bounded by `timeout` (the hunt's own
# limit, 2 hours) and killed on exit. The report goes to target/flake-hunt/report.txt and the
# log of every failed run beside it; the exit status is 1 when any test failed.
set -euo pipefail
cd "$(dirname "$0")/.."
runs=5
per_core=1
while getopts "n:l:" o; do
  case $o in
    n) runs=$OPTARG ;;
    l) per_core=$OPTARG ;;
    *) echo "usage: $0 [-n RUNS] [-l LOAD_PER_CORE] [SUITE...]" >&2; exit 2 ;;
  esac
done
shift $((OPTIND - 1))
suites=("$@")
[ ${#suites[@]} -gt 0 ] || suites=(serve api history access crash cli)
out=$(pwd)/target/flake-hunt
rm -rf "$out"
mkdir -p "$out"

echo "building the test binaries (release, the CI feature set)"
cargo test --workspace --release --features neuvolex-tests/gpu,neuvolex/gpu --no-run \
  --message-format=json 2>/dev/null | python3 -c '
import json, sys
for l in sys.stdin:
    m = json.loads(l)
    t = m.get("target", {})
    if m.get("reason") == "compiler-artifact" and m.get("executable") and "test" in t.get("kind", []):
        print(t["name"], m["executable"], m["manifest_path"])' >"$out/binaries.txt"

limit=7200
pids=()
stop_load() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  rm -f "$out"/load*.bin
}
trap stop_load EXIT
cores=$(nproc)
for _ in $(seq 1 $((cores * per_core))); do
  timeout "$limit" sh -c 'while :; do :; done' &
  pids+=($!)
done
# Writers that sync 64 MiB at a time, as the linker and other jobs on a CI machine do: one per
# busy loop, so a test's own fsync waits behind theirs.
for w in $(seq 1 $((cores * per_core))); do
  timeout "$limit" sh -c "while :; do dd if=/dev/zero of=$out/load$w.bin bs=1M count=64 conv=fsync 2>/dev/null; done" &
  pids+=($!)
done
# Memory pressure, as a CI machine's link steps make it: a process that holds and touches
# FLAKE_HUNT_HOG_GIB GiB (default: none), so the page cache the tests read through is evicted.
hog=${FLAKE_HUNT_HOG_GIB:-0}
if [ "$hog" -gt 0 ]; then
  timeout "$limit" python3 -c "
import time
b = bytearray($hog << 30)
while True:
    for i in range(0, len(b), 4096):
        b[i] = (b[i] + 1) & 255
    time.sleep(0.5)
" &
  pids+=($!)
fi
echo "load: $((cores * per_core)) busy loops on $cores cores, as many syncing writers, ${hog} GiB held"

failed=0
: >"$out/report.txt"
for s in "${suites[@]}"; do
  line=$(awk -v s="$s" '$1 == s' "$out/binaries.txt" | head -1)
  if [ -z "$line" ]; then
    echo "no test suite named $s" | tee -a "$out/report.txt"
    failed=1
    continue
  fi
  read -r _ exe manifest <<<"$line"
  clean=0
  for r in $(seq 1 "$runs"); do
    log="$out/$s-run$r.log"
    if (cd "$(dirname "$manifest")" && timeout 900 "$exe" >"$log" 2>&1); then
      clean=$((clean + 1))
      rm -f "$log"
    else
      failed=1
      names=$(grep -E '^test .* FAILED$' "$log" | sed 's/^test //; s/ \.\.\. FAILED$//' | tr '\n' ' ' || true)
      echo "$s run $r: FAILED ${names:-(no test named; see $log)}" | tee -a "$out/report.txt"
      grep -m3 -A2 "panicked at" "$log" | sed 's/^/    /' | tee -a "$out/report.txt" || true
    fi
  done
  echo "$s: $clean of $runs runs clean" | tee -a "$out/report.txt"
done
echo "report: $out/report.txt"
exit "$failed"
