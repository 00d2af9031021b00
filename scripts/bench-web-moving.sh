#!/usr/bin/env bash
# A view dragged with the mouse in the web page (browser/moving.mjs), on
# the CPU in WebAssembly: the MNI152 brain as a DVR of one channel (T1) and
# of three (T1 + grey + white matter) at 512x512 and 800x600. Prints per
# page the full-size redraw the drag's first frame measured (what each
# frame of a moving view cost when it was drawn at full size), the size the moving frames
# were drawn at and their times, and the view at rest afterwards: its
# redraw's time and parts, and the page's long tasks (over 50 ms) from
# letting go until it is complete. BRICKYARD_WEB_DIST picks the web client
# served (default: target/web).
#
# Usage: bash scripts/bench-web-moving.sh [BRICKYARD] [WORKDIR]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
BIN="$(realpath "${1:-target/release/brickyard}")"
WORK="${2:-/tmp/bench-web-moving}"
. scripts/web-mni3-served.sh
B="http://127.0.0.1:$PORT/web/#store=..%2Fstores%2Fmni3.ome.zarr%2F&backend=cpu&az=40&el=25"
for page in "1ch-512:channel=0&size=512x512" "3ch-512:size=512x512" \
            "1ch-800:channel=0&size=800x600" "3ch-800:size=800x600"; do
  name=${page%%:*}
  mkdir -p "$WORK/$name"
  node crates/brickyard-web/browser/moving.mjs chromium "$WORK/$name" "$B&${page#*:}"
  python3 - "$name" "$WORK/$name/moving.json" <<'PY'
import json, statistics, sys
name, r = sys.argv[1], json.load(open(sys.argv[2]))
b, d, e = r["before"], r["during"], r["end"]
moving = [s for s in d if s["scale"] < 1]
ms = [s["frame_ms"] for s in moving] or [s["frame_ms"] for s in d]
scale = moving[0]["scale"] if moving else 1.0
full = moving[0]["full_ms"] if moving else b["full_ms"]
print(f"{name}: full-size redraw {full:.0f} ms; while moving {len(moving)}/{len(d)} samples at "
      f"{100 * scale:.0f} % size, frames {min(ms):.0f}-{max(ms):.0f} ms (median {statistics.median(ms):.0f}); "
      f"at rest again: scale {e['scale']}, complete {e['complete']}, last frame {e['frame_ms']:.0f} ms "
      f"in {e.get('full_parts', 1)} part(s); the page's tasks over 50 ms from letting go to complete: "
      f"{[round(x) for x in r.get('rest_long_tasks', [])]}")
PY
done
