#!/usr/bin/env bash
# Build the web client: the brickyard-web crate for wasm32-unknown-unknown,
# its JavaScript glue by wasm-bindgen (the CLI at the crate's exact
# version, installed once from crates.io into target/tools), and the page,
# into target/web/ (what `brickyard serve --web` serves; any static server
# does too). Also installs the headless-browser test's driver
# (playwright-core, pinned in crates/brickyard-web/browser/package-lock.json)
# when npm is there.
#
# Usage: bash scripts/build-web.sh [--tools-only]
#   --tools-only: install the tools (the wasm target, wasm-bindgen-cli) and
#   stop (scripts/test.sh runs this in the background during its build).
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

WASM_BINDGEN_VERSION=0.2.130
TARGET_DIR="${CARGO_TARGET_DIR:-target}"
TOOLS="$TARGET_DIR/tools"
OUT="$TARGET_DIR/web"

if command -v rustup >/dev/null 2>&1; then
    rustup target add wasm32-unknown-unknown >/dev/null
fi
if ! "$TOOLS/bin/wasm-bindgen" --version 2>/dev/null | grep -q " $WASM_BINDGEN_VERSION\$"; then
    echo "== installing wasm-bindgen-cli $WASM_BINDGEN_VERSION into $TOOLS"
    # Without its default TLS (rustls, ring): the test runner talks to
    # chromedriver on loopback over plain HTTP. A fifth less to compile.
    cargo install wasm-bindgen-cli --version "$WASM_BINDGEN_VERSION" --root "$TOOLS" \
        --target-dir "$TARGET_DIR/tools-build" --no-default-features --quiet
fi
if [ "${1:-}" = --tools-only ]; then
    exit 0
fi

echo "== cargo build --release --target wasm32-unknown-unknown -p brickyard-web"
cargo build --release --target wasm32-unknown-unknown -p brickyard-web

rm -rf "$OUT.tmp"
mkdir -p "$OUT.tmp"
"$TOOLS/bin/wasm-bindgen" --target web --no-typescript --out-dir "$OUT.tmp" \
    "$TARGET_DIR/wasm32-unknown-unknown/release/brickyard_web.wasm"
cp crates/brickyard-web/www/index.html crates/brickyard-web/www/app.js "$OUT.tmp/"
rm -rf "$OUT"
mv "$OUT.tmp" "$OUT"
echo "web client in $OUT: $(du -k "$OUT/brickyard_web_bg.wasm" | cut -f1) KiB of WebAssembly"

if command -v npm >/dev/null 2>&1; then
    (cd crates/brickyard-web/browser && npm ci --no-audit --no-fund --silent)
fi
