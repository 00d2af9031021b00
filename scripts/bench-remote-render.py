#!/usr/bin/env python3
"""Remote rendering over loopback: `brickyard serve STORE --render` and one
client (websocket-client) that asks for a view, then turns the camera N
times; per view: the time to the first frame, to the final PNG, the frames
streamed and their bytes. Beside it, in the same run, `brickyard render` of
the first view (a whole process from cold) for scale.

Usage: python scripts/bench-remote-render.py BIN STORE [--size 512] [--turns 8]
       [--backend cpu]    (needs `pip install websocket-client`)
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time

import websocket  # websocket-client


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("bin")
    ap.add_argument("store")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--turns", type=int, default=8)
    ap.add_argument("--backend", default="cpu")
    a = ap.parse_args()
    name = os.path.basename(os.path.normpath(a.store))
    srv = subprocess.Popen([a.bin, "serve", a.store, "--port", "0", "--render", "--quiet",
                            "--backend", a.backend, "--max-fps", "60"],
                           stderr=subprocess.PIPE, text=True)
    try:
        srv.stderr.readline()
        line = srv.stderr.readline()
        port = int(re.search(r":(\d+)/render", line).group(1))
        ws = websocket.create_connection(f"ws://127.0.0.1:{port}/render")
        rows = []
        for turn in range(a.turns + 1):
            view = {"store": name, "mode": "dvr", "tf": "soft", "size": [a.size, a.size],
                    "azimuth": 30 + 15 * turn, "elevation": 20}
            t0 = time.perf_counter()
            ws.send(json.dumps(view))
            first, frames, nbytes, per = None, 0, 0, []
            while True:
                m = json.loads(ws.recv())
                img = ws.recv()
                frames += 1
                per.append([round(m["ms"], 1), round(m["completeness"], 3),
                            round(time.perf_counter() - t0, 3)])
                nbytes += len(img)
                if first is None:
                    first = time.perf_counter() - t0
                if m["final"]:
                    break
            rows.append({"view": turn, "first_frame_ms": first * 1e3,
                         "final_ms": (time.perf_counter() - t0) * 1e3, "frames": frames,
                         "bytes": nbytes, "complete": m["complete"],
                         "per_frame_ms_completeness_at": per})
            print(json.dumps(rows[-1]))
        ws.close()
    finally:
        srv.terminate()
        srv.wait()
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        subprocess.run([a.bin, "render", a.store, "--size", str(a.size), "--tf", "soft",
                        "--backend", a.backend, "--quiet", "--out", os.path.join(d, "x.png")],
                       check=True, stdout=subprocess.DEVNULL)
        cli = (time.perf_counter() - t0) * 1e3
    warm = sorted(r["final_ms"] for r in rows[1:])
    print(json.dumps({"summary": True, "first_view_final_ms": rows[0]["final_ms"],
                      "first_view_first_frame_ms": rows[0]["first_frame_ms"],
                      "turned_views_final_ms_median": warm[len(warm) // 2] if warm else None,
                      "turned_views_first_frame_ms_median":
                          sorted(r["first_frame_ms"] for r in rows[1:])[len(warm) // 2] if warm else None,
                      "render_cli_cold_ms": cli}))


if __name__ == "__main__":
    sys.exit(main())
