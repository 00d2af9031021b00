#!/bin/bash
# Two builds of brickyard beside VTK's CPU ray caster, alternating, for the
# four cases of scripts/bench-vs-vtk.sh (256³/512³ at 512²/1024², 2 threads):
# per case three rounds of VTK, BEFORE, AFTER; best warm frame of 5 each.
#
#   scripts/bench-vs-vtk-ab.sh BEFORE_BIN AFTER_BIN OUT_DIR [BENCH_DIR]
#
# BENCH_DIR must hold what scripts/bench-vs-vtk.sh makes there (the stores,
# mb-N.raw and cam-N.json); needs a Python with `vtk` as `python` (or $PY).
# MODE=mip compares maximum intensity projections (VTK's MaximumIntensityBlend);
# WINDOW=LO,HI sets brickyard's transfer-function window (VTK's cost does not
# depend on it).
set -euo pipefail
BEFORE=${1:?usage: bench-vs-vtk-ab.sh BEFORE_BIN AFTER_BIN OUT_DIR [BENCH_DIR]}
AFTER=${2:?}
OUT=${3:?}
D=${4:-bench-data}
PY=${PY:-python}
MODE=${MODE:-dvr}
VTK_MODE=()
[ "$MODE" = mip ] && VTK_MODE=(--mip)
WIN=()
[ -n "${WINDOW:-}" ] && WIN=(--window "$WINDOW")
mkdir -p "$OUT"
for cfg in "256 512" "256 1024" "512 512" "512 1024"; do
  set -- $cfg
  for r in 1 2 3; do
    xvfb-run -a "$PY" scripts/bench-vtk-render.py "$D/mb-$1.raw" --dims "$1" "$1" "$1" \
      --camera "$D/cam-$1.json" --size "$2" --repeat 5 --threads 2 "${VTK_MODE[@]}" 2>&1 | tail -1 > "$OUT/vtk-$1-$2-$r.json"
    for b in before after; do
      bin=$BEFORE
      [ "$b" = after ] && bin=$AFTER
      "$bin" bench render --size "$1" --dtype u8 --dir "$D" --image "$2" --threads 2 --repeat 5 \
        --mode "$MODE" "${WIN[@]}" --no-reference 2>/dev/null | tail -1 > "$OUT/$b-$1-$2-$r.json"
    done
  done
done
python3 - "$OUT" <<'PY'
import json, sys
o = sys.argv[1]
ld = lambda f: json.loads(open(f"{o}/{f}").read())
for c in ["256-512", "256-1024", "512-512", "512-1024"]:
    v = [ld(f"vtk-{c}-{r}.json")["frame_ms"] for r in (1, 2, 3)]
    b = [ld(f"before-{c}-{r}.json")["warm_frame_ms"] for r in (1, 2, 3)]
    a = [ld(f"after-{c}-{r}.json")["warm_frame_ms"] for r in (1, 2, 3)]
    print(c, "vtk", [round(x, 1) for x in v], "before", [round(x, 1) for x in b],
          "after", [round(x, 1) for x in a], "vtk/after %.2f" % (min(v) / min(a)),
          "before/after %.2f" % (min(b) / min(a)))
PY
