#!/usr/bin/env bash
# The GPU benchmark, for a Linux machine with a real GPU, no Rust toolchain
# and no network. It runs the binary packed by scripts/pack-gpu-bench.sh
# (dist/brickyard), brings the Vulkan loader along when the machine has
# none, generates its data locally, and prints one JSON line per scenario:
#   - the adapter and the cache-management kernels (LRU compaction,
#     request list) beside their CPU twins, and brick uploads one call
#     each against all in one staging buffer;
#   - DVR at 1920x1080 of a 1024^3 Mandelbulb, full view and zoomed in, on
#     the GPU: warm frame time, cache management per frame, upload GB/s,
#     time to a complete view from disk (page cache dropped when root) and
#     from the host cache;
#   - the same at 512^3 on the CPU and the GPU side by side;
#   - 16 frames of shaded sample accumulation on the GPU;
#   - label surfaces of the $SMALL^3 store's parts (all, and one alone) on
#     the CPU and the GPU;
#   - the processing filters gauss(2) and sobel of a generated PROC^3 u16
#     volume (default 512) on the CPU and the GPU side by side, with the
#     largest difference beside the stated tolerance;
#   - multi-view super-slices and stereo DVR;
#   - DVR through the residency octree beside the page tables for 1, 4, 16
#     and 64 channels of a generated banded OCT^3 volume (default 192) at
#     1920x1080 on the GPU (a table).
# Everything runs under timeouts that add up to about 13 minutes; BUDGET
# (below) fits the run to a shorter lease.
# Usage: [BUDGET=SECONDS] [ADAPTER=NAME] [STEPS=KEYS] bash scripts/gpu-bench.sh [DATA_DIR]   (default /tmp/brickyard-gpu-bench)
# BIG, SMALL and PROC (default 1024, 512 and 512) set the volume edges, e.g.
# to try the script on a software adapter first.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
BIN=${BRICKYARD_BIN:-dist/brickyard}
DATA=${1:-/tmp/brickyard-gpu-bench}
mkdir -p "$DATA"
[ -x "$BIN" ] || { echo "gpu-bench: $BIN missing: run scripts/pack-gpu-bench.sh where Rust is" >&2; exit 2; }

# The Vulkan loader: the system's, else the packed copy.
if ! ldconfig -p 2>/dev/null | grep 'libvulkan\.so\.1 ' >/dev/null; then
    export LD_LIBRARY_PATH="$PWD/dist/vulkan${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    echo "gpu-bench: using the packed Vulkan loader" >&2
fi
# The NVIDIA driver's Vulkan entry: the driver's own manifest where the
# machine mounts it outside the loader's search path, else one written here
# that names the driver library.
nv_icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
if [ -f "$nv_icd" ]; then
    export VK_DRIVER_FILES="$nv_icd" VK_ICD_FILENAMES="$nv_icd"
    echo "gpu-bench: using $nv_icd" >&2
elif ! ls /usr/share/vulkan/icd.d/*nvidia* /etc/vulkan/icd.d/*nvidia* >/dev/null 2>&1; then
    lib=$(ldconfig -p 2>/dev/null | awk '/libGLX_nvidia\.so\.0 / && !p {p = $NF} END {print p}')
    if [ -n "$lib" ]; then
        mkdir -p "$DATA/icd"
        printf '{"file_format_version":"1.0.0","ICD":{"library_path":"%s","api_version":"1.3.0"}}\n' "$lib" > "$DATA/icd/nvidia_icd.json"
        export VK_DRIVER_FILES="$DATA/icd/nvidia_icd.json" VK_ICD_FILENAMES="$DATA/icd/nvidia_icd.json"
        echo "gpu-bench: wrote an ICD manifest for $lib" >&2
    fi
fi
BIG=${BIG:-1024}
SMALL=${SMALL:-512}
PROC=${PROC:-512}
OCT=${OCT:-192}

# BUDGET (seconds, default 900) bounds the whole run: each step's timeout is
# cut to what is left, and steps that would get under 10 s are skipped. The
# steps run most wanted first. STEPS (keys, e.g. "kernels small prog")
# runs only those steps; "prog" needs the store "small" makes.
END=$(( $(date +%s) + ${BUDGET:-900} ))
step() { # KEY NAME SECONDS ARGS...
    local key=$1 name=$2 secs=$3; shift 3
    if [ -n "${STEPS:-}" ] && [[ " $STEPS " != *" $key "* ]]; then
        return
    fi
    local t0=$(date +%s)
    local left=$(( END - t0 ))
    if [ "$left" -lt 10 ]; then
        echo "gpu-bench: $name: skipped, the budget is spent" >&2
        return
    fi
    [ "$secs" -gt "$left" ] && secs=$left
    timeout "$secs" "$BIN" "$@"
    local rc=$?
    echo "gpu-bench: $name: exit $rc after $(( $(date +%s) - t0 )) s" >&2
}

nproc >&2; nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null >&2 || true
step kernels "cache kernels" 60 bench cache-kernels --repeat 20 | tee "$DATA/cache-kernels.jsonl"
# ADAPTER (e.g. NVIDIA): stop here unless the adapter's name holds it, so a
# lease is not spent on a software adapter.
if [ -n "${ADAPTER:-}" ] && ! grep -qi "\"adapter\":\"[^\"]*$ADAPTER" "$DATA/cache-kernels.jsonl"; then
    echo "gpu-bench: the adapter is not $ADAPTER; stopping" >&2
    exit 3
fi
# Data: generated and converted here (kept between runs).
step small "$SMALL^3, CPU, GPU, GPU with host updates" 120 bench render --size "$SMALL" --dtype u8 --dir "$DATA" --image 1920x1080 --zoom 1 --repeat 5 --backend all --no-reference
# Sample accumulation, shaded, on the store the $SMALL^3 step made: 16
# frames on the GPU (each frame's time on stdout).
echo '{"preset": "soft", "window": [0, 255], "shading": true}' > "$DATA/shaded.json"
step prog "progressive 16 frames, shaded, $SMALL^3 at 1024^2, GPU" 30 render "$DATA/mandelbulb-${SMALL}x${SMALL}x${SMALL}-u8.ome.zarr" --out "$DATA/progressive.png" --size 1024x1024 --tf "$DATA/shaded.json" --progressive 16 --backend gpu
# Label images in 3D: the $SMALL^3 store's parts (threshold(100)|label(26),
# written by `process` into its labels/parts), their surfaces at 1920x1080
# on the CPU and the GPU, all labels and one alone (--only-labels: the rays
# pass through the others, crossing the bricks and cells that hold none).
SMALL_STORE="$DATA/mandelbulb-${SMALL}x${SMALL}x${SMALL}-u8.ome.zarr"
step labels "labels of $SMALL^3: process" 90 process "$SMALL_STORE" "threshold(100)|label(26)" --out parts --overwrite --quiet
step labels "label surfaces of $SMALL^3 at 1920x1080, CPU and GPU" 120 bench render --store "$SMALL_STORE/labels/parts" --image 1920x1080 --repeat 5 --backend both --no-reference
step labels "one label (11) of $SMALL^3 at 1920x1080, CPU and GPU" 120 bench render --store "$SMALL_STORE/labels/parts" --only-labels 11 --image 1920x1080 --repeat 5 --backend both --no-reference
step big "$BIG^3 full view, GPU" 160 bench render --size "$BIG" --dtype u8 --dir "$DATA" --image 1920x1080 --zoom 1 --repeat 20 --backend gpu --no-reference --cold
# A one-shot render of the big store from the host's page cache, frame by
# frame (what a user runs first).
step oneshot "$BIG^3 one-shot render at 1920x1080, GPU" 60 render "$DATA/mandelbulb-${BIG}x${BIG}x${BIG}-u8.ome.zarr" --out "$DATA/big.png" --size 1920x1080 --backend gpu
# The residency octree vs page tables on the device, 1 to 64 channels (the
# paper's Table 1: 4.6-14 ms for one channel, 25.7 ms for 16 on a GTX 1080).
step octree "octree vs page tables, 1-64 channels of $OCT^3 at 1920x1080, GPU" 90 bench octree --size "$OCT" --dir "$DATA" --image 1920x1080 --channels 1,4,16,64 --repeat 5 --backend gpu
step filters "process filters $PROC^3, CPU and GPU" 35 bench process-filters --size "$PROC" --dtype u16 --backend both --repeat 2
# Multi-view: an 8-view super-slice (Δx = 4, Δz = 1) at 1920x1080 per view
# against one view alone and the 8 views one by one; stereo against mono
# DVR (the thesis: 30 ms per 8-view image on a Titan X).
step views "views: 8-view super-slice and stereo DVR, $SMALL^3 at 1920x1080, CPU and GPU" 120 bench views --size "$SMALL" --dtype u8 --dir "$DATA" --image 1920x1080 --views 8 --repeat 5 --backend both
step zoom "$BIG^3 zoomed in, GPU" 90 bench render --size "$BIG" --dtype u8 --dir "$DATA" --image 1920x1080 --zoom 4 --repeat 20 --backend gpu --no-reference --cold
step procedural "4096^3 procedural (64 GiB of u8, computed brick by brick), GPU" 100 bench render --size 4096 --procedural --dtype u8 --image 1920x1080 --zoom 1 --repeat 20 --backend gpu --no-reference
