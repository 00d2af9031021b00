#!/bin/bash
# Multi-channel DVR beside VTK's CPU ray caster with independent components:
# one store, one camera, 1024², ROUNDS alternating rounds of VTK and each
# brickyard build given.
#
#   PY=/path/to/python-with-vtk-and-zarr bash scripts/bench-vs-vtk-channels.sh STORE OUT ROUNDS BIN...
#
# brickyard: `render STORE --json` from a fresh process (page cache warm): the
# complete frame's own time (its "image" pass, every brick resident) and the
# whole one-shot render; VTK (scripts/bench-vtk-channels.py): the best of 5
# frames after a first, and the read plus first frame. Needs xvfb-run.
set -euo pipefail
STORE=${1:?usage: bench-vs-vtk-channels.sh STORE OUT ROUNDS BIN...}
OUT=${2:?}
ROUNDS=${3:?}
shift 3
PY=${PY:-python3}
HERE=$(cd "$(dirname "$0")" && pwd)
mkdir -p "$OUT"
"$1" render "$STORE" --out "$OUT/camera.png" --size 1024x1024 --save-camera "$OUT/camera.json" >/dev/null 2>&1
for r in $(seq "$ROUNDS"); do
  v=$(xvfb-run -a "$PY" "$HERE/bench-vtk-channels.py" "$STORE" --camera "$OUT/camera.json" \
    --size 1024 --threads 2 --png "$OUT/vtk.png")
  echo "$r vtk $(echo "$v" | "$PY" -c 'import sys,json; d=json.load(sys.stdin); print("frame %.0f ms, read + first frame %.0f ms" % (d["frame_ms"], d["cold_ms"]))')"
  for b in "$@"; do
    n=$(basename "$b")
    o=$("$b" render "$STORE" --out "$OUT/$n.png" --size 1024x1024 --camera "$OUT/camera.json" \
      --threads 2 --json 2>&1)
    f=$(echo "$o" | grep '"image"' | tail -1 | "$PY" -c 'import sys,json; print("%.0f" % json.load(sys.stdin)["render_ms"])')
    t=$(echo "$o" | grep '"summary"' | "$PY" -c 'import sys,json; d=json.load(sys.stdin); print("%s, %d frames, %.2f s" % (d["stop"], d["frames"], d["seconds"]))')
    echo "$r $n frame $f ms, one-shot $t, $(md5sum < "$OUT/$n.png" | cut -c1-8)"
  done
done
