#!/usr/bin/env bash
# The full benchmark (about 10 minutes on the 2-core machine). Runs `python -m tools.bench
# --quick` (default transports, then --shm), then the full `python -m tools.bench` (IKONOS-size
# scenes, 10 pairs through the live node over DDS, open-loop at the sensor rate: the publisher
# never waits for the node), and rewrites bench/BENCHMARKS.md from that run (tables, machine,
# date, targets met or not), with the JSON beside it (bench/last_quick.json,
# bench/last_quick_shm.json, bench/last_run.json). Extra arguments go to the full run (e.g.
# --pairs 3, --shm for the shared-memory profile, --paced for the former flow control,
# --node-param streaming=false).
# py-spy, when on PATH or named by PY_SPY, samples the node during the live part.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${PARPROJ_VENV:-$ROOT/.venv}"
cd "$ROOT"

# DDS stays on this machine, in a domain of its own.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-71}"
export ROS_LOG_DIR="${ROS_LOG_DIR:-$ROOT/build/ros_log}"
mkdir -p "$ROS_LOG_DIR"

"$ROOT/dev" setup

spy=()
PY_SPY="${PY_SPY:-$(command -v py-spy || true)}"
if [ -n "$PY_SPY" ]; then
  spy=(--py-spy "$PY_SPY")
fi

echo "== quick run (python -m tools.bench --quick --json)" >&2
start=$SECONDS
"$VENV/bin/python" -m tools.bench --quick --json > "$ROOT/bench/last_quick.json"
echo "== quick run took $((SECONDS - start)) s" >&2

# The same with the Fast DDS shared-memory profile (config/fastdds_shm.xml), for its effect.
echo "== quick run with the shared-memory profile (--shm)" >&2
"$VENV/bin/python" -m tools.bench --quick --json --shm --no-offline \
  > "$ROOT/bench/last_quick_shm.json"

echo "== full run" >&2
start=$SECONDS
"$VENV/bin/python" -m tools.bench --json --markdown "$ROOT/bench/BENCHMARKS.md" \
  --include-quick "$ROOT/bench/last_quick.json" ${spy[@]+"${spy[@]}"} "$@" \
  > "$ROOT/bench/last_run.json"
echo "== full run took $((SECONDS - start)) s; report: bench/BENCHMARKS.md" >&2
