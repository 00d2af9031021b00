#!/bin/bash
# 3D views of a label image from cold: `brickyard render STORE/labels/NAME`
# (label surfaces, one process from the store to the PNG) beside VTK's
# label-map pipeline (scripts/bench-vtk-labels.py: read the raw labels,
# vtkSurfaceNets3D, render the mesh once), alternating the two.
#
#   scripts/bench-labels-vs-vtk.sh OUT_DIR [BENCH_DIR] [SIZES] [ROUNDS]
#
# The labels: the Mandelbulb of `brickyard generate` at N³ (u8), labelled by
# `brickyard process "threshold(100)|label(26)"` (its connected parts: one
# large body and thousands of small ones). Needs a release build
# (target/release/brickyard), VTKPY: a Python with `vtk` (9.3 or later, for
# vtkSurfaceNets3D), BYPY: a Python with the brickyard package (to write the
# raw labels VTK reads), xvfb-run and GNU time. One JSON line per run goes to
# OUT_DIR/runs.jsonl. The page cache is dropped before every run when this
# process may.
set -euo pipefail
OUT=${1:?usage: bench-labels-vs-vtk.sh OUT_DIR [BENCH_DIR] [SIZES] [ROUNDS]}
DIR=${2:-bench-data}
SIZES=${3:-256 512}
ROUNDS=${4:-3}
B=${BRICKYARD:-target/release/brickyard}
VTKPY=${VTKPY:-python3}
BYPY=${BYPY:-python3}
mkdir -p "$OUT" "$DIR"
RUNS="$OUT/runs.jsonl"
: > "$RUNS"
drop() {
  sync
  if echo 3 > /proc/sys/vm/drop_caches 2>/dev/null; then echo dropped; else echo warm; fi
}
for n in $SIZES; do
  s="$DIR/mb-$n.ome.zarr"
  if [ ! -d "$s/labels/parts" ]; then
    "$B" generate mandelbulb "$s" --size "$n" --quiet --overwrite
    "$B" process "$s" "threshold(100)|label(26)" --out parts --quiet
  fi
  [ -f "$DIR/parts-$n.raw" ] || "$BYPY" -c 'import sys, brickyard
brickyard.open(sys.argv[1]).read(level=0).tofile(sys.argv[2])' "$s/labels/parts" "$DIR/parts-$n.raw"
  [ -f "$DIR/lcam-$n.json" ] || "$B" render "$s/labels/parts" --azimuth 30 --elevation 20 \
    --fov 35 --size 32 --out "$DIR/lcam-$n.png" --save-camera "$DIR/lcam-$n.json" > /dev/null
done
record() { # JSON line, then key=value pairs added
  "$BYPY" -c 'import json, sys
d = json.loads(sys.argv[1])
for kv in sys.argv[2:]:
    k, v = kv.split("=", 1)
    try:
        v = float(v)
    except ValueError:
        pass
    d[k] = v
print(json.dumps(d))' "$@" >> "$RUNS"
}
for r in $(seq "$ROUNDS"); do
  for n in $SIZES; do
    for size in 1024; do
      c=$(drop)
      t0=$(date +%s.%N)
      line=$(/usr/bin/time -f '%M' -o "$OUT/time.txt" xvfb-run -a "$VTKPY" scripts/bench-vtk-labels.py \
        "$DIR/parts-$n.raw" --dims "$n" "$n" "$n" --camera "$DIR/lcam-$n.json" --size "$size" \
        --png "$OUT/vtk-$n.png" 2>/dev/null | tail -1)
      t1=$(date +%s.%N)
      record "$line" round="$r" n="$n" image="$size" cache="$c" wall_s="$(echo "$t1 - $t0" | bc)" \
        max_rss_mib="$(( $(tail -1 "$OUT/time.txt") / 1024 ))"
      for mem in default 256MiB; do
        c=$(drop)
        extra=()
        [ "$mem" = default ] || extra=(--memory "$mem")
        t0=$(date +%s.%N)
        line=$(/usr/bin/time -f '%M' -o "$OUT/time.txt" "$B" render "$DIR/mb-$n.ome.zarr/labels/parts" \
          --camera "$DIR/lcam-$n.json" --size "$size" --backend cpu --json --out "$OUT/ours-$n.png" \
          "${extra[@]}" | grep '"summary"')
        t1=$(date +%s.%N)
        record "$line" tool=brickyard round="$r" n="$n" image="$size" cache="$c" memory="$mem" \
          wall_s="$(echo "$t1 - $t0" | bc)" max_rss_mib="$(( $(tail -1 "$OUT/time.txt") / 1024 ))"
      done
    done
  done
done
"$BYPY" - "$RUNS" <<'EOF'
import json, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
print("| n | tool | memory | wall s (runs) | peak RSS MiB | detail |")
print("|---|---|---|---|---|---|")
keys = sorted({(r["n"], r["tool"], r.get("memory", "")) for r in rows})
for n, tool, mem in keys:
    rs = [r for r in rows if (r["n"], r["tool"], r.get("memory", "")) == (n, tool, mem)]
    walls = " / ".join(f'{r["wall_s"]:.2f}' for r in rs)
    rss = max(r["max_rss_mib"] for r in rs)
    if tool == "vtk":
        d = rs[-1]
        detail = f'read {d["read_ms"]:.0f} ms, surfaces {d["extract_ms"]:.0f} ms ({d["triangles"]} triangles), first frame {d["first_frame_ms"]:.0f} ms, next {d["frame_ms"]} ms'
    else:
        d = rs[-1]
        detail = f'{d["stop"]}, LOD bias {d["lod_bias"]}, {d["frames"]} frames'
    print(f"| {int(n)} | {tool} | {mem} | {walls} | {rss} | {detail} |")
EOF
