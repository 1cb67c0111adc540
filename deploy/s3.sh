#!/usr/bin/env bash
# A real S3-protocol server (s3s-fs: S3 over a directory) for tests and local clusters.
#
#   deploy/s3.sh install          build s3s-fs from crates.io into target/tools (once)
#   deploy/s3.sh start [DIR]      start it on loopback with DIR (default target/s3/data) as data
#                                 and print the environment to use it (eval "$(deploy/s3.sh start)")
#   deploy/s3.sh stop             stop the server started by `start`
#   deploy/s3.sh env              print the environment again
#   deploy/s3.sh mb BUCKET        create a bucket (a folder of the data directory)
#
# Settings: NEUVOLEX_S3_PORT (default 8014), NEUVOLEX_S3_BUCKET (default neuvolex, created on
# start), AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY (default neuvolex / neuvolex-secret),
# NEUVOLEX_S3_STATE (default target/s3: pid, log, and the data directory `data`).
# Nothing is downloaded at run time: `install` uses cargo and the crates.io registry only.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
TOOLS="$ROOT/target/tools"
BIN="$TOOLS/bin/s3s-fs"
STATE=${NEUVOLEX_S3_STATE:-$ROOT/target/s3}
PORT=${NEUVOLEX_S3_PORT:-8014}
BUCKET=${NEUVOLEX_S3_BUCKET:-neuvolex}
KEY=${AWS_ACCESS_KEY_ID:-neuvolex}
SECRET=${AWS_SECRET_ACCESS_KEY:-neuvolex-secret}
# Pinned: s3s-fs 0.14.1 is the newest release that builds with the workspace's Rust (1.95).
VERSION=0.14.1

# shellcheck source=deploy/proc.sh
. deploy/proc.sh

install() {
  if [ -x "$BIN" ] && "$BIN" --version 2>/dev/null | grep -q "$VERSION"; then
    return 0
  fi
  echo "building s3s-fs $VERSION into target/tools (once; about 3-5 minutes on 2 cores)" >&2
  cargo install --quiet --locked "s3s-fs@$VERSION" --features binary --root "$TOOLS" \
    --target-dir "$TOOLS/build" >&2
  rm -rf "$TOOLS/build"
}

print_env() {
  cat <<EOF
export AWS_ENDPOINT_URL=http://127.0.0.1:$PORT
export AWS_ACCESS_KEY_ID=$KEY
export AWS_SECRET_ACCESS_KEY=$SECRET
export AWS_REGION=us-east-1
export AWS_ALLOW_HTTP=true
export NEUVOLEX_S3_BUCKET=$BUCKET
EOF
}

start() {
  install
  local data=${1:-$STATE/data}
  mkdir -p "$data/$BUCKET" "$STATE"
  if running "$STATE/pid"; then
    print_env
    return 0
  fi
  "$BIN" --host 127.0.0.1 --port "$PORT" --access-key "$KEY" --secret-key "$SECRET" "$data" \
    >"$STATE/server.log" 2>&1 &
  echo $! >"$STATE/pid"
  for _ in $(seq 1 100); do
    if (exec 3<>"/dev/tcp/127.0.0.1/$PORT") 2>/dev/null; then
      echo "s3s-fs listening on 127.0.0.1:$PORT, data in $data (pid $(cat "$STATE/pid"))" >&2
      print_env
      return 0
    fi
    if ! running "$STATE/pid"; then
      echo "s3s-fs exited: $(tail -5 "$STATE/server.log")" >&2
      exit 1
    fi
    sleep 0.1
  done
  echo "s3s-fs did not listen on 127.0.0.1:$PORT within 10 s (see $STATE/server.log)" >&2
  exit 1
}

stop() {
  if [ -f "$STATE/pid" ]; then
    kill "$(cat "$STATE/pid")" 2>/dev/null || true
    rm -f "$STATE/pid"
  fi
}

case "${1:-}" in
  install) install; echo "$BIN" ;;
  start) shift; start "$@" ;;
  stop) stop ;;
  env) print_env ;;
  mb) mkdir -p "$STATE/data/${2:?bucket name}" ;;
  *) sed -n '2,15p' "$0"; exit 2 ;;
esac
