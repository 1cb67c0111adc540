#!/usr/bin/env bash
# The fuzzers (cargo-fuzz / libFuzzer) on the stable toolchain. cargo-fuzz passes nightly-only
# flags (-Zsanitizer=address, sanitizer coverage); RUSTC_BOOTSTRAP=1 (set for cargo fuzz only)
# lets the stable compiler accept them. cargo-fuzz itself is installed from crates.io when missing.
#
#   fuzz/run.sh build              build every target (release, debug assertions, ASan)
#                                  FUZZ_SANITIZER=none: no ASan (4-40x faster per input; the
#                                  -malloc_limit_mb check is then off, -rss_limit_mb stays),
#                                  for the long runs; each sanitizer has its own target folder
#   fuzz/run.sh seeds              write the seed corpora into fuzz/corpus/ (from ../shared/data
#                                  and files the project writes; never committed)
#   fuzz/run.sh ci [SECONDS]       build, seed, run every target SECONDS (default 15); fails on
#                                  any crash, leak, out-of-memory or timeout
#   fuzz/run.sh replay             without cargo-fuzz, nightly or sanitizers (what CI runs, inside
#                                  `cargo test --workspace`): the crate's `replay` test writes the
#                                  seeds and runs every target over every seed and every saved
#                                  finding (fuzz/regressions/); fails on any panic
#   fuzz/run.sh long [RUNS] [T..]  RUNS executions (default 10000000) of each target (or the
#                                  ones named), one at a time at nice 19; logs and a summary in
#                                  fuzz/runs/; FUZZ_MAX_SECONDS bounds each target's run in time
#
# Every run uses -malloc_limit_mb=512 and -rss_limit_mb=2048: an allocation driven by a header's
# claimed size (before it is checked against the file) fails the run.
set -euo pipefail
cd "$(dirname "$0")"
export CARGO_TERM_COLOR=never
TARGETS=(nifti nifti_gz nrrd raw omezarr strokes tf classes session checkpoint)
SANITIZER="${FUZZ_SANITIZER:-address}"
case "$SANITIZER" in
  address) TARGET_DIR=target ;;
  none) TARGET_DIR=target/no-sanitizer ;;
  *)
    echo "FUZZ_SANITIZER must be address or none, not '$SANITIZER'" >&2
    exit 2
    ;;
esac
CARGO_FUZZ_VERSION=0.13.2

dict_of() {
  case "$1" in
    nifti | nifti_gz) echo dicts/nifti.dict ;;
    nrrd) echo dicts/nrrd.dict ;;
    raw) echo dicts/raw.dict ;;
    omezarr) echo dicts/omezarr.dict ;;
    checkpoint) echo dicts/checkpoint.dict ;;
    *) echo dicts/json.dict ;;
  esac
}

max_len_of() {
  case "$1" in
    omezarr) echo 65536 ;;
    checkpoint | nrrd | nifti | nifti_gz | raw) echo 32768 ;;
    *) echo 16384 ;;
  esac
}

ensure_cargo_fuzz() {
  if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "installing cargo-fuzz $CARGO_FUZZ_VERSION from crates.io"
    cargo install --locked --version "$CARGO_FUZZ_VERSION" cargo-fuzz
  fi
}

build() {
  ensure_cargo_fuzz
  # -O: optimised; -a: debug assertions and overflow checks; ASan (the default sanitizer).
  # RUSTC_BOOTSTRAP only here: build scripts (proc-macro2's) watch it, so it must not reach the
  # workspace's target folder (it would rebuild, then thrash, the compiled dependencies there).
  # The libFuzzer binaries need the `fuzzing` feature; their own target folder (fuzz/target)
  # keeps the sanitizer builds apart from the workspace's.
  if [ "$SANITIZER" = none ]; then
    # Only the targets: without ASan's runtime nothing defines the coverage hooks for the
    # `seeds` binary (no libFuzzer in it), so it would not link; `seeds` below falls back to the
    # workspace build of it.
    for t in "${TARGETS[@]}"; do
      RUSTC_BOOTSTRAP=1 cargo fuzz build -O -a -s none --features fuzzing \
        --target-dir "$TARGET_DIR" "$t"
    done
  else
    RUSTC_BOOTSTRAP=1 cargo fuzz build -O -a --features fuzzing --target-dir "$TARGET_DIR"
  fi
}

bin_dir() {
  echo "$TARGET_DIR/$(rustc -vV | sed -n 's/^host: //p')/release"
}

seeds() {
  local data="${NVX_DATA:-../../shared/data}"
  if [ ! -d "$data" ] && [ "${CI:-}" = "true" ]; then
    echo "fuzz seeds: $data is missing (CI=true requires the real volumes)" >&2
    exit 1
  fi
  if [ -x "$(bin_dir)/seeds" ]; then
    "$(bin_dir)/seeds" "$data" corpus
  else
    (cd .. && cargo run --release -q -p neuvolex-fuzz --bin seeds -- "fuzz/$data" fuzz/corpus)
  fi
}

# run TARGET ARGS...: one libFuzzer run over the target's corpus.
run() {
  local t="$1"
  shift
  mkdir -p "corpus/$t" "artifacts/$t"
  "$(bin_dir)/$t" "corpus/$t" \
    -artifact_prefix="artifacts/$t/" \
    -dict="$(dict_of "$t")" \
    -max_len="$(max_len_of "$t")" \
    -malloc_limit_mb=512 -rss_limit_mb=2048 -timeout=10 \
    -print_final_stats=1 "$@"
}

# replay: every target over its seeds and saved findings, without libFuzzer, nightly or
# sanitizers: the `replay` test of this crate, a workspace member, so it shares the workspace's
# compiled dependencies (deploy/test.sh runs it with the rest of the suite).
replay() {
  (cd .. && cargo test --release -p neuvolex-fuzz --test replay -- --nocapture)
}

case "${1:-ci}" in
  build) build ;;
  replay) replay ;;
  seeds) seeds ;;
  ci)
    secs="${2:-15}"
    build
    seeds
    for t in "${TARGETS[@]}"; do
      echo "== fuzz $t for ${secs}s"
      mkdir -p runs
      set +e
      run "$t" -max_total_time="$secs" >"runs/ci-$t.log" 2>&1
      rc=$?
      set -e
      grep -E "^stat::number_of_executed_units|^stat::peak_rss_mb|ERROR|panicked|SUMMARY" "runs/ci-$t.log" || true
      if [ "$rc" -ne 0 ]; then
        tail -40 "runs/ci-$t.log" >&2
        echo "fuzz $t: FAILED (reproducer in fuzz/artifacts/$t/)" >&2
        exit 1
      fi
    done
    echo "fuzz: every target ran ${secs}s without a finding"
    ;;
  long)
    runs="${2:-10000000}"
    shift $(( $# >= 2 ? 2 : $# ))
    [ "$#" -gt 0 ] && TARGETS=("$@")
    mkdir -p runs
    for t in "${TARGETS[@]}"; do
      mkdir -p "corpus/$t" "artifacts/$t"
      log="runs/$t.log"
      start=$(date +%s)
      set +e
      nice -n 19 "$(bin_dir)/$t" "corpus/$t" \
        -artifact_prefix="artifacts/$t/" -dict="$(dict_of "$t")" -max_len="$(max_len_of "$t")" \
        -malloc_limit_mb=512 -rss_limit_mb=2048 -timeout=10 -print_final_stats=1 \
        -runs="$runs" -max_total_time="${FUZZ_MAX_SECONDS:-0}" >"$log" 2>&1
      rc=$?
      set -e
      end=$(date +%s)
      execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -1 || true)
      peak=$(sed -n 's/^stat::peak_rss_mb: *//p' "$log" | tail -1 || true)
      cov=$(grep -Eo 'cov: [0-9]+' "$log" | tail -1 | awk '{print $2}' || true)
      echo "$t sanitizer=$SANITIZER runs=${execs:-?} seconds=$((end - start)) exit=$rc peak_rss_mb=${peak:-?} cov=${cov:-?} $(date -u +%FT%TZ)" | tee -a runs/summary.txt
    done
    ;;
  *)
    echo "usage: fuzz/run.sh build|seeds|replay|ci [SECONDS]|long [RUNS] [TARGET...]" >&2
    exit 2
    ;;
esac
