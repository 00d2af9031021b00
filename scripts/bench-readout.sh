#!/usr/bin/env bash
# The viewer's readout over its 3D view: how long the readout's thread takes
# to find the point a pixel shows (MIP maximum, DVR half-opacity point) and
# read it out, over 20 pixels in each mode, from the viewer's `--log`.
#   scripts/bench-readout.sh STORE [BIN]
# STORE: a path or an http(s) URL (`brickyard serve`). Needs a display or
# xvfb-run. Prints, per mode: answers, median and longest milliseconds,
# and how many pixels show a point.
set -euo pipefail
store=$1
bin=${2:-target/release/brickyard}
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT
{
  printf 'size 3d 400 300\nmode mip\nwait-complete 120\n'
  for i in $(seq 1 20); do printf 'hover 3d %d.5 %d.5\nwait-probe 60\n' $((100 + i * 10)) $((80 + i * 7)); done
  printf 'mode dvr\nwait-complete 120\n'
  for i in $(seq 1 20); do printf 'hover 3d %d.5 %d.5\nwait-probe 60\n' $((100 + i * 10)) $((80 + i * 7)); done
  printf 'quit\n'
} > "$dir/script.txt"
run=("$bin" view "$store" --backend cpu --script "$dir/script.txt" --log "$dir/log.jsonl")
if [ -z "${DISPLAY:-}" ]; then run=(xvfb-run -a "${run[@]}"); fi
XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp} "${run[@]}" >/dev/null
python3 - "$dir/log.jsonl" <<'PY'
import json, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
for how in ["MIP", "DVR"]:
    sel = [r["probe"] for r in rows if "probe" in r and r["probe"]["seen"] and how in r["probe"]["seen"]["how"]]
    hits = [p for p in sel if p["seen"]["hit"]]
    ms = sorted(p["ms"] for p in hits)
    print(f"{how}: {len(sel)} answers, {len(hits)} pixels show a point, "
          f"median {ms[len(ms) // 2]:.2f} ms, longest {ms[-1]:.2f} ms")
PY
