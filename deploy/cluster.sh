#!/usr/bin/env bash
# A local neuvolex cluster on one machine: nats-server with JetStream (a store directory),
# the S3 server where the project has one (deploy/s3.sh), and N `neuvolex worker` processes.
#
#   deploy/cluster.sh start [N]   start nats-server, the S3 server and N workers (default 3)
#   deploy/cluster.sh status      what runs
#   deploy/cluster.sh stop        stop the workers (after their current task), S3 and NATS
#
# Then any brick stage runs on the workers, e.g.
#   target/release/neuvolex classify STORE --scribbles S.nii.gz --cluster nats://127.0.0.1:4222
#
# or, on the S3 server: source out/cluster/s3.env, then STORE=s3://neuvolex/NAME.zarr.
#
# Settings: NVX_CLUSTER_DIR (default out/cluster: logs, pids, the JetStream store, the S3
# server's state and data in s3/), NVX_NATS_PORT (4222), NEUVOLEX_S3_PORT (8014),
# NVX_WORKER_THREADS (threads per worker; default cores / N, at least 1), NVX_WORKER_ARGS (more
# `neuvolex worker` arguments, e.g. "--ack-wait 10"), NVX_BIN (default target/release/neuvolex).
# `start` again restarts whatever died (the server on its port and JetStream store, workers).
set -euo pipefail
cd "$(dirname "$0")/.."
DIR=${NVX_CLUSTER_DIR:-out/cluster}
mkdir -p "$DIR"
DIR=$(cd "$DIR" && pwd)
PORT=${NVX_NATS_PORT:-4222}
URL="nats://127.0.0.1:$PORT"
BIN=${NVX_BIN:-target/release/neuvolex}
# The S3 server's pid, log and data live with the cluster.
export NEUVOLEX_S3_STATE="$DIR/s3"
cmd=${1:-start}
n=${2:-3}

need_nats() {
  if command -v nats-server >/dev/null 2>&1 || [ -x /usr/sbin/nats-server ]; then return; fi
  SUDO=""
  [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && SUDO="sudo -n"
  echo "installing nats-server (Debian package, JetStream included)"
  $SUDO apt-get install -y -q nats-server >/dev/null 2>&1 ||
    { $SUDO apt-get update -q >/dev/null 2>&1 && $SUDO apt-get install -y -q nats-server >/dev/null 2>&1; } ||
    { echo "cannot install nats-server" >&2; exit 1; }
}

nats_bin() { command -v nats-server 2>/dev/null || echo /usr/sbin/nats-server; }

# shellcheck source=deploy/proc.sh
. deploy/proc.sh
alive() { running "$1"; }

case "$cmd" in
start)
  [[ "$n" =~ ^[0-9]+$ ]] && [ "$n" -ge 1 ] && [ "$n" -le 256 ] || { echo "N must be 1..256" >&2; exit 2; }
  need_nats
  mkdir -p "$DIR/nats"
  [ -x "$BIN" ] || cargo build --release -p neuvolex
  if ! alive "$DIR/nats.pid"; then
    cat > "$DIR/nats.conf" <<CONF
listen: 127.0.0.1:$PORT
max_payload: 8MB
jetstream {
  store_dir: "$(cd "$DIR/nats" && pwd)"
}
CONF
    "$(nats_bin)" -c "$DIR/nats.conf" >>"$DIR/nats.log" 2>&1 &
    echo $! > "$DIR/nats.pid"
    for _ in $(seq 100); do
      (exec 3<>"/dev/tcp/127.0.0.1/$PORT") 2>/dev/null && break
      sleep 0.1
    done
    echo "nats-server: $URL (JetStream store $DIR/nats, log $DIR/nats.log)"
  fi
  # The S3 server; its AWS_* environment goes to the workers (and is printed for the
  # coordinator's shell), so stores given as s3://neuvolex/NAME.zarr work everywhere.
  if [ -x deploy/s3.sh ] && s3env=$(deploy/s3.sh start); then
    eval "$s3env"
    echo "$s3env" > "$DIR/s3.env"
    echo "S3 server: $AWS_ENDPOINT_URL; for s3:// stores run: source $DIR/s3.env"
  else
    echo "the S3 server did not start (stores on shared paths still work)"
  fi
  cores=$(nproc 2>/dev/null || echo 2)
  threads=${NVX_WORKER_THREADS:-$(( cores / n > 0 ? cores / n : 1 ))}
  for i in $(seq 1 "$n"); do
    pid="$DIR/worker-$i.pid"
    alive "$pid" && continue
    # shellcheck disable=SC2086 # NVX_WORKER_ARGS is a list of arguments
    "$BIN" worker --nats "$URL" --name "w$i" --threads "$threads" --quiet ${NVX_WORKER_ARGS:-} \
      >>"$DIR/worker-$i.log" 2>&1 &
    echo $! > "$pid"
  done
  echo "$n workers ($threads threads each), logs $DIR/worker-*.log"
  echo "run a stage on them with --cluster $URL, e.g."
  echo "  $BIN classify STORE --scribbles S.nii.gz --cluster $URL"
  ;;
status)
  alive "$DIR/nats.pid" && echo "nats-server: running ($URL)" || echo "nats-server: stopped"
  for p in "$DIR"/worker-*.pid; do
    [ -f "$p" ] || continue
    w=$(basename "$p" .pid)
    alive "$p" && echo "$w: running" || echo "$w: stopped"
  done
  ;;
stop)
  if alive "$DIR/nats.pid" && [ -x "$BIN" ]; then
    "$BIN" worker --stop-all --nats "$URL" --quiet >/dev/null 2>&1 || true
  fi
  for p in "$DIR"/worker-*.pid; do
    [ -f "$p" ] || continue
    pid=$(cat "$p")
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    kill "$pid" 2>/dev/null || true
    rm -f "$p"
  done
  [ -x deploy/s3.sh ] && deploy/s3.sh stop >/dev/null 2>&1 || true
  if alive "$DIR/nats.pid"; then kill "$(cat "$DIR/nats.pid")"; fi
  rm -f "$DIR/nats.pid"
  echo "cluster stopped"
  ;;
*)
  echo "usage: $0 start [N] | status | stop" >&2
  exit 2
  ;;
esac
