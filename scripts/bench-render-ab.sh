#!/usr/bin/env bash
# One-shot `brickyard render` (batch, the CLI's default) of two builds side by
# side: for each store and image size, ROUNDS alternating rounds of both
# builds, with the page cache warm (the store's files read before) and, where
# this process may drop it (root), cold. Prints one JSON line per run (the
# render's own `seconds` and `frames` from its --json summary) and checks that
# both builds wrote the same PNG bytes.
#
# usage: scripts/bench-render-ab.sh BEFORE AFTER OUT_DIR "STORE..." ["SIZES"] [ROUNDS]
#   BEFORE, AFTER  brickyard binaries (release)
#   OUT_DIR        where the images go
#   STORE...       OME-Zarr stores (e.g. made by `brickyard convert` from ../shared/data)
#   SIZES          image sizes, WxH (default "1024x1024 1920x1080 3840x2160")
#   ROUNDS         alternating rounds per case (default 3)
set -euo pipefail
A=${1:?usage: bench-render-ab.sh BEFORE AFTER OUT_DIR "STORE..." [SIZES] [ROUNDS]}
B=${2:?after}
OUT=${3:?out dir}
STORES=${4:?stores}
SIZES=${5:-1024x1024 1920x1080 3840x2160}
ROUNDS=${6:-3}
mkdir -p "$OUT"
drop() {
    sync
    if echo 3 > /proc/sys/vm/drop_caches 2> /dev/null; then echo cold; else echo none; fi
}
echo "# $(date -u +%FT%TZ) $(uname -n) $(nproc) CPUs, $(lscpu | sed -n 's/^Model name: *//p'); load $(cut -d' ' -f1-3 /proc/loadavg)"
for st in $STORES; do
    name=$(basename "$st" .ome.zarr)
    for size in $SIZES; do
        for round in $(seq "$ROUNDS"); do
            for cache in warm cold; do
                for which in before after; do
                    bin=$A
                    [ "$which" = after ] && bin=$B
                    if [ "$cache" = cold ]; then
                        [ "$(drop)" = cold ] || continue
                    else
                        cat $(find "$st" -type f) > /dev/null
                    fi
                    png="$OUT/$name-$size-$which.png"
                    line=$("$bin" render "$st" --size "$size" --threads "$(nproc)" --json \
                        --out "$png" | grep '"summary"' || true)
                    python3 -c 'import json,sys
d = json.loads(sys.argv[1]) if sys.argv[1] else {}
s = d
print(json.dumps({"store": sys.argv[2], "size": sys.argv[3], "round": int(sys.argv[4]), "cache": sys.argv[5], "build": sys.argv[6], "seconds": s.get("seconds"), "frames": s.get("frames"), "complete": s.get("completeness")}))' \
                        "$line" "$name" "$size" "$round" "$cache" "$which"
                done
            done
        done
        if cmp -s "$OUT/$name-$size-before.png" "$OUT/$name-$size-after.png"; then
            echo "# $name $size: the same image bytes"
        else
            echo "# $name $size: THE IMAGES DIFFER"
        fi
    done
done
