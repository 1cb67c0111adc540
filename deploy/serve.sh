#!/usr/bin/env bash
# The main command: build neuvolex and serve the browser UI and HTTP API. With no arguments it
# generates the labelled phantom (the embedded default) into out/serve/data and opens it first;
# the volumes in ../shared/data are offered beside it where that folder exists. Any argument is
# passed to `neuvolex serve` (a volume file, --data-root DIR, --port N, --host ADDR, ...).
# Built with the GPU engines: where a hardware GPU exists the INR trains and frames render on it
# (`--backend cpu` keeps both on the CPU; the UI's badge shows which runs).
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -q -p neuvolex --features gpu
exec ./target/release/neuvolex serve "$@"
