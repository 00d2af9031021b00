#!/bin/bash
# CPU renderer beside VTK's CPU ray caster (vtkFixedPointVolumeRayCastMapper),
# alternating the two so that both see the same periods of a noisy machine.
#
#   scripts/bench-vs-vtk.sh OUT_DIR [BENCH_DIR]
#
# Needs: a release build (target/release/brickyard), a Python environment with
# `vtk` active (scripts/bench-vtk-render.py) and xvfb-run. Inputs are made in
# BENCH_DIR when missing: the store (by the first `bench render`), the same
# volume as raw for VTK (`brickyard generate`) and the benchmark's camera
# (`brickyard render --save-camera`). One JSON line per run goes to OUT_DIR.
set -euo pipefail
OUT=${1:?usage: bench-vs-vtk.sh OUT_DIR [BENCH_DIR]}
DIR=${2:-bench-data}
B=${BRICKYARD:-target/release/brickyard}
mkdir -p "$OUT"
vtk() { # N S THREADS
  xvfb-run -a python scripts/bench-vtk-render.py "$DIR/mb-$1.raw" --dims "$1" "$1" "$1" \
    --camera "$DIR/cam-$1.json" --size "$2" --repeat 5 --threads "$3" 2>&1 | tail -1
}
ours() { # N S THREADS [extra]
  local n=$1 s=$2 t=$3
  shift 3
  "$B" bench render --size "$n" --dtype u8 --dir "$DIR" --image "$s" --threads "$t" "$@" 2>/dev/null | tail -1
}
T=$(nproc)
for n in 256 512 1024; do
  ours "$n" 64 "$T" --repeat 1 --no-reference > /dev/null # makes the store
  [ -f "$DIR/mb-$n.raw" ] || "$B" generate mandelbulb "$DIR/mb-$n.raw" --size "$n"
  [ -f "$DIR/cam-$n.json" ] || "$B" render "$DIR/mandelbulb-${n}x${n}x${n}-u8.ome.zarr" \
    --azimuth 30 --elevation 20 --fov 35 --size 32 --out "$DIR/cam-$n.png" \
    --save-camera "$DIR/cam-$n.json" > /dev/null
done
for cfg in "256 512" "256 1024" "512 512" "512 1024"; do
  set -- $cfg
  ours "$1" "$2" "$T" --repeat 3 --cold > "$OUT/cold-$1-$2.json"
  for r in 1 2 3; do
    vtk "$1" "$2" "$T" > "$OUT/vtk-$1-$2-$r.json"
    ours "$1" "$2" "$T" --repeat 5 --no-reference > "$OUT/ours-$1-$2-$r.json"
  done
done
ours 1024 512 "$T" --repeat 1 --cold --no-reference > "$OUT/cold-1024-512.json"
ours 1024 512 "$T" --repeat 1 --cold --no-reference --pool 128MiB > "$OUT/cold-1024-512-p128.json"
for r in 1 2 3; do
  vtk 256 512 1 > "$OUT/vtk1-$r.json"
  ours 256 512 1 --repeat 5 --no-reference > "$OUT/ours1-$r.json"
done
python3 - "$OUT" <<'PY'
import json, sys
o = sys.argv[1]
ld = lambda f: json.loads(open(f"{o}/{f}").read())
for c in ["256-512", "256-1024", "512-512", "512-1024"]:
    print(c, "ours", [round(ld(f"ours-{c}-{r}.json")["warm_frame_ms"], 1) for r in (1, 2, 3)],
          "vtk", [round(ld(f"vtk-{c}-{r}.json")["frame_ms"], 1) for r in (1, 2, 3)])
print("256-512, 1 thread: ours", [round(ld(f"ours1-{r}.json")["warm_frame_ms"], 1) for r in (1, 2, 3)],
      "vtk", [round(ld(f"vtk1-{r}.json")["frame_ms"], 1) for r in (1, 2, 3)])
PY
