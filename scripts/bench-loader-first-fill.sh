#!/bin/bash
# A loader's first fill beside its steady state and beside what the fresh
# memory of a first fill costs on this machine, in one run:
# per round, scripts/fresh-pages.c over the first fill's new memory (the
# decoded bricks and the chunk cache), a new process's first scan of level 0
# (the whole level stays in the host cache), and the later scans of a
# process whose host cache (64 MiB) is smaller than the level (evicted
# bricks' memory reused).
#
#   scripts/bench-loader-first-fill.sh BIN BENCH_DIR [ROUNDS] [FRESH_MIB]
#
# BENCH_DIR: where `BIN bench loader --size 1024 --dtype u8 --dir BENCH_DIR`
# made (or makes, on the first call) its store.
set -euo pipefail
B=${1:?usage: bench-loader-first-fill.sh BIN BENCH_DIR [ROUNDS] [FRESH_MIB]}
D=${2:?}
ROUNDS=${3:-3}
MIB=${4:-504}
cc -O2 -o /tmp/fresh-pages "$(dirname "$0")/fresh-pages.c"
L=(bench loader --size 1024 --dtype u8 --dir "$D" --loader-threads 2)
for r in $(seq "$ROUNDS"); do
  /tmp/fresh-pages "$MIB" 1 | head -1
  "$B" "${L[@]}" --repeat 1 2>/dev/null | tail -1 | python3 -c '
import json, sys
d = json.loads(sys.stdin.read())
print("first fill: %.3f s, %.2f GB/s, user %.2f s, sys %.2f s, %d faults" % (d["seconds"], d["decoded_gb_s"], d["cpu_user_s"], d["cpu_sys_s"], d["minor_faults"]))'
  "$B" "${L[@]}" --repeat 3 --host-cache 64MiB 2>/dev/null | python3 -c '
import json, sys
runs = [json.loads(l) for l in sys.stdin if l.startswith("{")][1:]
print("steady state (runs 2-3): " + ", ".join("%.3f s (%.2f GB/s, sys %.2f s)" % (d["seconds"], d["decoded_gb_s"], d["cpu_sys_s"]) for d in runs))'
done
