#!/bin/bash
# One-shot renders from cold: `brickyard render` (batch) beside VTK's CPU ray
# caster reading the raw volume and rendering once, alternating the two.
#
#   scripts/bench-oneshot.sh OUT_DIR [BENCH_DIR] [SIZES]
#
# Needs: a release build (target/release/brickyard), a Python environment with
# `vtk` active (scripts/bench-vtk-render.py), xvfb-run and GNU time. Inputs
# (stores, raw volumes, cameras) are made in BENCH_DIR as scripts/bench-vs-vtk.sh
# makes them. The page cache is dropped before every cold run when this
# process may (root, /proc/sys/vm/drop_caches writable); the JSON says which.
# One JSON line per run goes to OUT_DIR/runs.jsonl; a table is printed.
set -euo pipefail
OUT=${1:?usage: bench-oneshot.sh OUT_DIR [BENCH_DIR] [SIZES]}
DIR=${2:-bench-data}
SIZES=${3:-256 512 1024}
B=${BRICKYARD:-target/release/brickyard}
mkdir -p "$OUT" "$DIR"
RUNS="$OUT/runs.jsonl"
: > "$RUNS"
drop() {
  sync
  if echo 3 > /proc/sys/vm/drop_caches 2>/dev/null; then echo dropped; else echo warm; fi
}
for n in $SIZES; do
  [ -d "$DIR/mandelbulb-${n}x${n}x${n}-u8.ome.zarr" ] ||
    "$B" bench render --size "$n" --dtype u8 --dir "$DIR" --image 64 --repeat 1 --no-reference > /dev/null
  [ -f "$DIR/mb-$n.raw" ] || "$B" generate mandelbulb "$DIR/mb-$n.raw" --size "$n" --quiet
  [ -f "$DIR/cam-$n.json" ] || "$B" render "$DIR/mandelbulb-${n}x${n}x${n}-u8.ome.zarr" \
    --azimuth 30 --elevation 20 --fov 35 --size 32 --out "$DIR/cam-$n.png" \
    --save-camera "$DIR/cam-$n.json" --window 0,255 > /dev/null
done
# ours N S CACHE [extra...]: one cold render; JSON summary + wall + peak.
ours() {
  local n=$1 s=$2 cache=$3
  shift 3
  local t0 t1 line
  t0=$(date +%s.%N)
  line=$(/usr/bin/time -f '%M' -o "$OUT/time.txt" "$B" render "$DIR/mandelbulb-${n}x${n}x${n}-u8.ome.zarr" \
    --camera "$DIR/cam-$n.json" --size "$s" --tf soft --window 0,255 --backend cpu --json \
    --out "$OUT/ours-$n-$s.png" "$@" | grep '"summary"')
  t1=$(date +%s.%N)
  python3 -c 'import json,sys; d=json.loads(sys.argv[1]); d.update(tool="brickyard", n=int(sys.argv[2]), image=int(sys.argv[3]), cache=sys.argv[4], wall_s=float(sys.argv[5]), max_rss_bytes=int(open(sys.argv[6]).read().strip().splitlines()[-1])*1024, args=sys.argv[7]); print(json.dumps(d))' \
    "$line" "$n" "$s" "$cache" "$(echo "$t1 - $t0" | bc)" "$OUT/time.txt" "$*" >> "$RUNS"
}
vtk() {
  local n=$1 s=$2 cache=$3 t0 t1 line
  t0=$(date +%s.%N)
  line=$(/usr/bin/time -f '%M' -o "$OUT/time.txt" xvfb-run -a python scripts/bench-vtk-render.py "$DIR/mb-$n.raw" \
    --dims "$n" "$n" "$n" --camera "$DIR/cam-$n.json" --size "$s" --repeat 0 --png "$OUT/vtk-$n-$s.png" 2>/dev/null | tail -1)
  t1=$(date +%s.%N)
  python3 -c 'import json,sys; d=json.loads(sys.argv[1]); d.update(n=int(sys.argv[2]), image=int(sys.argv[3]), cache=sys.argv[4], wall_s=float(sys.argv[5]), max_rss_bytes=int(open(sys.argv[6]).read().strip().splitlines()[-1])*1024); print(json.dumps(d))' \
    "$line" "$n" "$s" "$cache" "$(echo "$t1 - $t0" | bc)" "$OUT/time.txt" >> "$RUNS"
}
for n in $SIZES; do
  for s in 512 1024; do
    c=$(drop); vtk "$n" "$s" "$c"
    c=$(drop); ours "$n" "$s" "$c"
    c=$(drop); ours "$n" "$s" "$c" --memory 128MiB
    ours "$n" "$s" warm
    ours "$n" "$s" warm --stream
  done
done
python3 - "$RUNS" <<'PY'
import json, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
print(f"{'tool':<10}{'n':>6}{'image':>7}{'cache':>9}{'wall s':>9}{'inner s':>9}{'frames':>8}{'peak MiB':>10}  args")
for r in rows:
    inner = r.get("seconds") if r.get("tool") == "brickyard" else r["cold_ms"] / 1e3
    print(f"{r['tool']:<10}{r['n']:>6}{r['image']:>7}{r['cache']:>9}{r['wall_s']:>9.2f}{inner:>9.2f}"
          f"{r.get('frames', 1):>8}{r['max_rss_bytes'] / 2**20:>10.0f}  {r.get('args', '')}")
PY
