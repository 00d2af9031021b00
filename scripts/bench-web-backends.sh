#!/usr/bin/env bash
# The web page's two back ends on the browser's own WebGPU adapter, in one
# run: the MNI152 brain (one channel, T1; and three, T1 + grey + white
# matter) as a 320x240 DVR, through WebGPU (backend=gpu) and by the
# default (auto: on a software adapter such as SwiftShader, the CPU in
# WebAssembly). Prints per page the adapter, time to complete, frames and
# the last frame's time (browser/canvas.mjs's report).
#
# Usage: bash scripts/bench-web-backends.sh [BRICKYARD] [WORKDIR]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
BIN="$(realpath "${1:-target/release/brickyard}")"
WORK="${2:-/tmp/bench-web-backends}"
. scripts/web-mni3-served.sh
B="http://127.0.0.1:$PORT/web/#store=..%2Fstores%2Fmni3.ome.zarr%2F"
V="az=40&el=25&size=320x240"
node crates/brickyard-web/browser/canvas.mjs chromium "$WORK/out" \
    "gpu-3ch=$B&backend=gpu&$V" "auto-3ch=$B&$V" \
    "gpu-1ch=$B&backend=gpu&channel=0&$V" "auto-1ch=$B&channel=0&$V"
python3 - "$WORK/out/canvas.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
for k, v in r.items():
    s = v["status"]
    print(f"{k:9} on {v['device'] or 'the CPU (WebAssembly)'}: complete in {s['first_complete_ms'] / 1000:.1f} s, "
          f"{s['frames']} frames, last frame {s['frame_ms']:.1f} ms")
PY
