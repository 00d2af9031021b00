#!/bin/bash
# Instructions of one warm CPU DVR frame (deterministic, unlike wall time on
# a shared machine): callgrind dumps before every frame; the last complete
# frame's total and its heaviest functions are printed.
#
#   scripts/callgrind-frame.sh BIN BENCH_DIR [IMAGE] [extra bench render args]
set -euo pipefail
B=$(realpath "${1:?usage: callgrind-frame.sh BIN BENCH_DIR [IMAGE] [args]}")
D=$(realpath "${2:?}")
S=${3:-512}
shift 3 || shift $#
W=$(mktemp -d)
cd "$W"
valgrind --tool=callgrind --dump-before='brickyard_render::cpu::render_tiles' "$B" bench render \
  --size 256 --dtype u8 --dir "$D" --image "$S" --threads 1 --repeat 3 --no-reference "$@" \
  > /dev/null 2>&1
last=$(ls -v callgrind.out.* | tail -2 | head -1)
echo "$last: $(grep -m1 '^summary' "$last")"
callgrind_annotate --inclusive=yes "$last" 2>/dev/null | grep -E 'dvr_in|Entries|pixel_ray' | head -6
