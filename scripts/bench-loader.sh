#!/usr/bin/env bash
# The loader beside tensorstore on the same store, in one run: the disk's
# sequential bandwidth (dd with O_DIRECT over the shard files), then
# `brickyard bench loader` and tensorstore's reads of level 0
# (scripts/bench-loader-ts.py), page cache warm and then cold.
#
# Cold without root: every file of the store is dropped from the page
# cache with posix_fadvise(DONTNEED) before each cold run (fincore checks
# it); with root, /proc/sys/vm/drop_caches is used by the loader bench.
#
# usage: scripts/bench-loader.sh BRICKYARD [SIZE] [DTYPE] [DIR] [PYTHON] [BASE]
#   BRICKYARD  the brickyard binary (release)
#   SIZE       volume edge (default 1024), DTYPE u8 | u16 | f32 (default u8)
#   DIR        where the Mandelbulb store is made once (default /tmp/bench-loader)
#   PYTHON     a Python with tensorstore and numpy (default python3)
#   BASE       optional: an older brickyard binary, measured warm the same way
#              (its `bench loader` has no --loader-threads: it runs 1, 2 and 4 threads)
set -euo pipefail
BY=${1:?usage: bench-loader.sh BRICKYARD [SIZE] [DTYPE] [DIR] [PYTHON] [BASE]}
N=${2:-1024}
DT=${3:-u8}
DIR=${4:-/tmp/bench-loader}
PY=${5:-python3}
BASE=${6:-}
HERE=$(cd "$(dirname "$0")" && pwd)
THREADS=$(nproc)

echo "# $(date -u +%FT%TZ) $(uname -n) $(nproc) CPUs, $(lscpu | sed -n 's/^Model name: *//p')"
echo "# load average: $(cut -d' ' -f1-3 /proc/loadavg)"
# Make the store (once) with a one-thread warm run.
"$BY" bench loader --size "$N" --dtype "$DT" --dir "$DIR" --loader-threads 1 > /dev/null
STORE=$(ls -d "$DIR"/mandelbulb-"$N"x"$N"x"$N"-*"$DT"*.ome.zarr 2> /dev/null | head -1)
[ -z "$STORE" ] && STORE=$(ls -dt "$DIR"/mandelbulb-"$N"x"$N"x"$N"-*.ome.zarr | head -1)
SHARDS=$(find "$STORE/0/c" -type f | sort)
SBYTES=$(cat $SHARDS | wc -c)
echo "# store $STORE: level 0 in $(echo "$SHARDS" | wc -l) shard files, $SBYTES bytes"

echo "## disk: sequential reads"
BIG="$DIR/dd-seq.bin"
[ -f "$BIG" ] || dd if=/dev/urandom of="$BIG" bs=16M count=32 status=none
t0=$(date +%s.%N)
dd if="$BIG" of=/dev/null bs=16M iflag=direct status=none
t1=$(date +%s.%N)
BB=$(stat -c %s "$BIG")
echo "{\"reader\": \"dd O_DIRECT bs=16M, one 512 MiB file\", \"bytes\": $BB, \"seconds\": $(echo "$t1 - $t0" | bc -l), \"gb_s\": $(echo "$BB / 1000000000 / ($t1 - $t0)" | bc -l)}"
t0=$(date +%s.%N)
for f in $SHARDS; do dd if="$f" of=/dev/null bs=16M iflag=direct status=none; done
t1=$(date +%s.%N)
echo "{\"reader\": \"dd O_DIRECT bs=16M\", \"bytes\": $SBYTES, \"seconds\": $(echo "$t1 - $t0" | bc -l), \"gb_s\": $(echo "$SBYTES / 1000000000 / ($t1 - $t0)" | bc -l)}"
"$PY" - "$STORE" << 'EOF'
import os, sys
for d, _, fs in os.walk(sys.argv[1]):
    for f in fs:
        fd = os.open(os.path.join(d, f), os.O_RDONLY)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        os.close(fd)
EOF
echo "# cached after fadvise: $(fincore -b -n -o RES $SHARDS 2> /dev/null | awk '{s+=$1} END {print s+0}') bytes"
t0=$(date +%s.%N)
cat $SHARDS > /dev/null
t1=$(date +%s.%N)
echo "{\"reader\": \"cat (buffered, after fadvise)\", \"bytes\": $SBYTES, \"seconds\": $(echo "$t1 - $t0" | bc -l), \"gb_s\": $(echo "$SBYTES / 1000000000 / ($t1 - $t0)" | bc -l)}"

echo "## warm (page cache holds the store)"
cat $SHARDS > /dev/null
"$BY" bench loader --size "$N" --dtype "$DT" --dir "$DIR" --loader-threads "1,$THREADS" --repeat 2
"$PY" "$HERE/bench-loader-ts.py" "$STORE" --threads "$THREADS"
"$PY" "$HERE/bench-loader-ts.py" "$STORE" --threads "$THREADS" --modes batched,whole
if [ -n "$BASE" ]; then
    echo "## warm, older binary $BASE"
    "$BASE" bench loader --size "$N" --dtype "$DT" --dir "$DIR"
fi

echo "## cold (store dropped from the page cache before each run)"
"$BY" bench loader --size "$N" --dtype "$DT" --dir "$DIR" --loader-threads "$THREADS" --repeat 2 --cold
"$PY" "$HERE/bench-loader-ts.py" "$STORE" --threads "$THREADS" --modes batched,whole --cold
"$PY" "$HERE/bench-loader-ts.py" "$STORE" --threads "$THREADS" --modes batched,whole --cold
echo "# load average: $(cut -d' ' -f1-3 /proc/loadavg)"
