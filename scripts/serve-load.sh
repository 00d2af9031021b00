#!/usr/bin/env bash
# Load test of `brickyard serve` on loopback (bounded: CLIENTS clients for
# SECONDS seconds, random inner chunks of a generated 256³ u16 store), then
# remote against local brick-read throughput (`bench remote`).
#
# Usage: bash scripts/serve-load.sh [BINARY] [CLIENTS] [SECONDS]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
BIN=${1:-target/release/brickyard}
CLIENTS=${2:-16}
SECONDS_=${3:-10}
DIR=$(mktemp -d)
trap 'kill $PID 2>/dev/null || true; rm -rf "$DIR"' EXIT
"$BIN" generate mandelbulb "$DIR/m.ome.zarr" --size 256 --dtype u16 --quiet --brick 32 --shard 128
"$BIN" serve "$DIR/m.ome.zarr" --port 0 --quiet 2> "$DIR/serve.log" &
PID=$!
for _ in $(seq 50); do grep -q "serving" "$DIR/serve.log" 2>/dev/null && break; sleep 0.1; done
PORT=$(head -1 "$DIR/serve.log" | sed -E 's/.*127\.0\.0\.1:([0-9]+).*/\1/')
python3 scripts/serve-load.py "$DIR/m.ome.zarr" "$PORT" "$PID" --clients "$CLIENTS" --seconds "$SECONDS_"
kill -TERM $PID
wait $PID 2>/dev/null || true
"$BIN" bench remote --size 256 --dtype u16 --dir "$DIR/bench"
