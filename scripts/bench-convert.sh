#!/usr/bin/env bash
# Side-by-side conversion benchmark: brickyard vs ome-zarr-py on the same raw
# Mandelbulb volumes (64³ chunks in 256³ shards, blosc-lz4, page cache warm).
# Prints one JSON line per run. Usage: bash scripts/bench-convert.sh [DATA_DIR]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
DIR="${1:-bench-data}"
BIN=target/release/brickyard
cargo build --release -p brickyard -q
bash scripts/setup-python.sh >/dev/null
mkdir -p "$DIR"
for spec in "1024x1024x1024 u8" "2048x2048x512 u16"; do
    set -- $spec
    size=$1 dtype=$2
    raw="$DIR/mandelbulb-$size-$dtype.raw"
    # Generate once (and warm the page cache) through the brickyard bench itself.
    $BIN bench convert --size "$size" --dtype "$dtype" --dir "$DIR" --shard 256 --repeat 3
    IFS=x read -r X Y Z <<<"$size"
    .venv/bin/python scripts/bench-python-convert.py "$raw" --dims "$X" "$Y" "$Z" --dtype "$dtype" \
        --out "$DIR/ome-zarr-py-out" --chunk 64 --shard 256
    rm -rf "$DIR/ome-zarr-py-out"
done
