#!/usr/bin/env bash
# Build what scripts/gpu-bench.sh needs on a machine with a GPU but no Rust
# toolchain and no network, into dist/ (ignored by git; carry it along):
#   dist/brickyard         the release binary, stripped (glibc >= 2.35)
#   dist/vulkan/           this machine's Vulkan loader, used only where the
#                          target machine has none
# Usage: bash scripts/pack-gpu-bench.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
cargo build --release -p brickyard
mkdir -p dist/vulkan
strip -o dist/brickyard target/release/brickyard
loader=$(ldconfig -p | awk '/libvulkan\.so\.1 / && !p {p = $NF} END {print p}')
if [ -n "$loader" ]; then
    cp -L "$loader" dist/vulkan/libvulkan.so.1
else
    echo "pack-gpu-bench: no Vulkan loader here (apt-get install libvulkan1); dist/vulkan stays empty" >&2
fi
du -sh dist
