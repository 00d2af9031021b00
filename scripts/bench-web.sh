#!/usr/bin/env bash
# The web client's figures beside the native renderer's, in one run:
# bundle size; in headless Chromium over loopback (`serve --web`): time to
# the first frame and to complete, bytes fetched, full-redraw frame times,
# on the CPU with a pool of 256 MiB and of 4 MiB, and through WebGPU; natively, the same view by
# `brickyard render` on the CPU with 1 and 2 threads (frame times from
# --json), and on the device (lavapipe here) when there is one.
#
# Usage: bash scripts/bench-web.sh [BRICKYARD] [WORKDIR]
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
BIN="${1:-target/release/brickyard}"
WORK="${2:-/tmp/bench-web}"
mkdir -p "$WORK"
STORE="$WORK/mni.ome.zarr"
[ -d "$STORE" ] || "$BIN" convert ../shared/data/mni152-t1-u8.nii.gz "$STORE" --quiet
echo "bundle: $(stat -c %s target/web/brickyard_web_bg.wasm) bytes of WebAssembly, $(gzip -9 -c target/web/brickyard_web_bg.wasm | wc -c) gzipped; glue $(stat -c %s target/web/brickyard_web.js) bytes"
"$BIN" serve --web --quiet --port 0 "$STORE" 2> "$WORK/serve.log" &
SRV=$!
trap 'kill $SRV' EXIT
sleep 1
PORT=$(head -1 "$WORK/serve.log" | sed -E 's/.*127\.0\.0\.1:([0-9]+).*/\1/')
VIEW="az=40&el=25&size=512x512&tf=soft&window=0,255"
for pool in 256 4; do
    echo "== browser, CPU (WebAssembly), pool $pool MiB"
    node crates/brickyard-web/browser/bench.mjs chromium "http://127.0.0.1:$PORT/web/#store=..%2Fmni.ome.zarr%2F&pool=$pool&backend=cpu&$VIEW" 3
done
echo "== browser, WebGPU (the browser's adapter), pool 32 MiB"
node crates/brickyard-web/browser/bench.mjs chromium "http://127.0.0.1:$PORT/web/#store=..%2Fmni.ome.zarr%2F&pool=32&backend=gpu&$VIEW" 1
for threads in 1 2; do
    echo "== native render, CPU, $threads thread(s)"
    "$BIN" --threads "$threads" render "$STORE" --size 512x512 --azimuth 40 --elevation 25 --tf soft --window 0,255 \
        --brick 32 --backend cpu --json -o "$WORK/native.png" | tail -1
done
echo "== native render, device"
"$BIN" render "$STORE" --size 512x512 --azimuth 40 --elevation 25 --tf soft --window 0,255 \
    --brick 32 --backend gpu --json -o "$WORK/native-gpu.png" | tail -1 || echo "(no device)"
