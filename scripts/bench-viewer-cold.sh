#!/usr/bin/env bash
# The viewer's 3D view from cold, two builds side by side: the time to its
# first frame and how long that frame took, the time to complete, and the
# same after a drag into a new view. CPU back end under Xvfb, 1200×800 DVR,
# no sample accumulation; rounds alternate between the builds.
#
# Usage: bash scripts/bench-viewer-cold.sh STORE ROUNDS BIN_A BIN_B
set -euo pipefail
STORE=$1 ROUNDS=$2; shift 2
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
cat > "$W/s.txt" <<'S'
size 3d 1200 800
wait-complete 300
drag 3d left 200 0
wait-complete 300
quit
S
for r in $(seq "$ROUNDS"); do
  for bin in "$@"; do
    rm -f "$W/log.jsonl"
    xvfb-run -a "$bin" view "$STORE" --backend cpu --accumulate 0 --script "$W/s.txt" \
      --log "$W/log.jsonl" --window-size 1400x900 >/dev/null 2>&1
    python3 - "$W/log.jsonl" "$bin" "$r" <<'P'
import json, sys
rows = [json.loads(l) for l in open(sys.argv[1])]
out = []
for version in sorted({j["version"] for j in rows if j.get("view") == "3d"}):
    f = [j for j in rows if j.get("view") == "3d" and j["version"] == version]
    done = next((j for j in f if j["settled"]), f[-1])
    out.append(f"v{version}: first frame at {f[0]['since_change_ms']:.0f} ms "
               f"(drawn in {f[0]['render_ms']:.0f} ms, {'preview' if f[0].get('preview') else 'whole'}, "
               f"{100 * f[0]['completeness']:.0f} %), complete at {done['since_change_ms']:.0f} ms, "
               f"{len(f)} frames")
print(f"round {sys.argv[3]} {sys.argv[2]}: " + "; ".join(out))
P
  done
done
