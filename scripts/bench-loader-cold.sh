#!/usr/bin/env bash
# Cold scans of level 0 with and without the loader's read-ahead hints, at
# the kernel read-ahead sizes given, beside tensorstore's batched cold read
# and `cat` of the level's shard files (the disk's buffered rate), in one run.
# Needs root: it drops the page cache and sets the block device's
# read_ahead_kb (restored at the end).
#
# usage: scripts/bench-loader-cold.sh BRICKYARD [DIR] [PYTHON] [DEV] [KBS] [ROUNDS]
#   BRICKYARD  the brickyard binary (release)
#   DIR        where the 1024³ u8 Mandelbulb stores are made once (default /tmp/bench-loader)
#   PYTHON     a Python with tensorstore and numpy (default python3)
#   DEV        the block device under DIR (default: found with findmnt/lsblk)
#   KBS        kernel read-ahead sizes to measure, KiB (default "128 8192")
#   ROUNDS     alternating rounds per case (default 3)
set -euo pipefail
BY=${1:?usage: bench-loader-cold.sh BRICKYARD [DIR] [PYTHON] [DEV] [KBS] [ROUNDS]}
DIR=${2:-/tmp/bench-loader}
PY=${3:-python3}
HERE=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$DIR"
if [ -n "${4:-}" ]; then
    DEV=$4
else
    SRC=$(findmnt -no SOURCE --target "$DIR")
    DEV=$(lsblk -no PKNAME "$SRC" 2> /dev/null | head -1)
    [ -z "$DEV" ] && DEV=$(basename "$SRC")
fi
KBS=${5:-128 8192}
ROUNDS=${6:-3}
RA=/sys/block/$DEV/queue/read_ahead_kb
OLD=$(cat "$RA")
trap 'echo "$OLD" > "$RA"' EXIT

echo "# $(date -u +%FT%TZ) $(uname -n) $(nproc) CPUs, $(lscpu | sed -n 's/^Model name: *//p'); device $DEV (read_ahead_kb $OLD)"
echo "# load average: $(cut -d' ' -f1-3 /proc/loadavg)"
for comp in none lz4; do
    "$BY" bench loader --size 1024 --dtype u8 --dir "$DIR" --compression "$comp" --loader-threads 1 > /dev/null
done
NONE=$DIR/mandelbulb-1024x1024x1024-u8-none.ome.zarr
SHARDS=$(find "$NONE/0/c" -type f | sort)
echo "# uncompressed store: level 0 in $(echo "$SHARDS" | wc -l) shard files, $(cat $SHARDS | wc -c) bytes"
for kb in $KBS; do
    echo "$kb" > "$RA"
    echo "## read_ahead_kb $kb"
    for comp in none lz4; do
        for round in $(seq "$ROUNDS"); do
            for ahead in 0 32; do
                "$BY" bench loader --size 1024 --dtype u8 --dir "$DIR" --compression "$comp" \
                    --loader-threads "$(nproc)" --repeat 1 --cold --read-ahead "$ahead" \
                    | sed "s/^/{\"read_ahead_kb\": $kb, \"round\": $round, \"line\": /; s/\$/}/"
            done
        done
    done
    for round in $(seq "$ROUNDS"); do
        sync
        echo 3 > /proc/sys/vm/drop_caches
        "$PY" "$HERE/bench-loader-ts.py" "$NONE" --threads "$(nproc)" --modes batched --cold \
            | sed "s/^/{\"read_ahead_kb\": $kb, \"round\": $round, \"line\": /; s/\$/}/"
    done
    sync
    echo 3 > /proc/sys/vm/drop_caches
    t0=$(date +%s.%N)
    cat $SHARDS > /dev/null
    t1=$(date +%s.%N)
    echo "{\"read_ahead_kb\": $kb, \"reader\": \"cat, cold\", \"seconds\": $(echo "$t1 - $t0" | bc -l)}"
done
BIG="$DIR/dd-seq.bin"
[ -f "$BIG" ] || dd if=/dev/urandom of="$BIG" bs=16M count=32 status=none
echo "# dd O_DIRECT of a 512 MiB file: $(dd if="$BIG" of=/dev/null bs=16M iflag=direct 2>&1 | tail -1)"
echo "# load average: $(cut -d' ' -f1-3 /proc/loadavg)"
