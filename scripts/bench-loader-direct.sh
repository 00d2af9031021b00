#!/usr/bin/env bash
# Cold scans of level 0 read through the page cache (with the loader's
# read-ahead hints) and around it (`--direct-io`), beside tensorstore's
# batched cold read and the disk's own rates (`cat` of the level's shard
# files through the page cache; `dd` with O_DIRECT), in one run, rounds
# alternating. Needs root: it drops the page cache before each cold read.
#
# usage: scripts/bench-loader-direct.sh BRICKYARD [DIR] [PYTHON] [ROUNDS] [THREADS]
#   BRICKYARD  the brickyard binary (release)
#   DIR        where the 1024³ u8 Mandelbulb stores are made once (default /tmp/bench-loader)
#   PYTHON     a Python with tensorstore and numpy (default python3; "" to leave it out)
#   ROUNDS     alternating rounds (default 3)
#   THREADS    loader thread counts, each read both ways (default "2 4")
set -euo pipefail
BY=${1:?usage: bench-loader-direct.sh BRICKYARD [DIR] [PYTHON] [ROUNDS] [THREADS]}
DIR=${2:-/tmp/bench-loader}
PY=${3-python3}
ROUNDS=${4:-3}
THREADS=${5:-2 4}
HERE=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$DIR"
cold() { sync; echo 3 > /proc/sys/vm/drop_caches; }
tag() { sed "s/^/{\"round\": $1, \"line\": /; s/\$/}/"; }

echo "# $(date -u +%FT%TZ) $(uname -n) $(nproc) CPUs, $(lscpu | sed -n 's/^Model name: *//p')"
echo "# load average: $(cut -d' ' -f1-3 /proc/loadavg)"
for comp in none lz4; do
    "$BY" bench loader --size 1024 --dtype u8 --dir "$DIR" --compression "$comp" --loader-threads 1 > /dev/null
done
NONE=$DIR/mandelbulb-1024x1024x1024-u8-none.ome.zarr
SHARDS=$(find "$NONE/0/c" -type f | sort)
echo "# uncompressed store: level 0 in $(echo "$SHARDS" | wc -l) shard files, $(cat $SHARDS | wc -c) bytes"
BIG="$DIR/dd-seq.bin"
[ -f "$BIG" ] || dd if=/dev/urandom of="$BIG" bs=16M count=32 status=none
for round in $(seq "$ROUNDS"); do
    for comp in none lz4; do
        # The whole level kept (a first fill), and a 64 MiB host cache
        # (bricks' memory reused, as a long scan or a moving view).
        for host in "" 64MiB; do
            H=()
            [ -n "$host" ] && H=(--host-cache "$host")
            for t in $THREADS; do
                "$BY" bench loader --size 1024 --dtype u8 --dir "$DIR" --compression "$comp" \
                    --loader-threads "$t" --repeat 1 --cold "${H[@]}" | tag "$round"
                "$BY" --direct-io bench loader --size 1024 --dtype u8 --dir "$DIR" --compression "$comp" \
                    --loader-threads "$t" --repeat 1 --cold "${H[@]}" | tag "$round"
            done
        done
    done
    if [ -n "$PY" ]; then
        cold
        "$PY" "$HERE/bench-loader-ts.py" "$NONE" --threads "$(nproc)" --modes batched --cold | tag "$round"
    fi
    cold
    t0=$(date +%s.%N)
    cat $SHARDS > /dev/null
    t1=$(date +%s.%N)
    echo "{\"round\": $round, \"reader\": \"cat of the shards, cold\", \"seconds\": $(echo "$t1 - $t0" | bc -l | sed 's/^\./0./')}"
    for bs in 1M 16M; do
        echo "{\"round\": $round, \"reader\": \"dd O_DIRECT bs=$bs, 512 MiB\", \"dd\": \"$(dd if="$BIG" of=/dev/null bs=$bs iflag=direct 2>&1 | tail -1)\"}"
    done
done
echo "# load average: $(cut -d' ' -f1-3 /proc/loadavg)"
