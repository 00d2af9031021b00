#!/usr/bin/env python3
"""Benchmark: `brickyard process` against scipy.ndimage and cc3d, one volume.

Usage: bench-process.py BRICKYARD_BIN WORKDIR [SIZE]   (SIZE: edge of a cube, default 256)
       bench-process.py BRICKYARD_BIN WORKDIR --out-of-core SIZE [MEMORY]
         (brickyard only: a generated SIZE³ u8 Mandelbulb store, gauss(2) and
          gauss(1)|threshold(100)|label(26) under --memory MEMORY, default 1GiB)

Makes a smooth random u16 cube (many blobs), converts it to a store (64³
bricks), then times, each in its own process so that peak RSS is its own:
  - brickyard process STORE "gauss(2)" / "sobel" / "threshold(T)|label(26)"
    (reads the store, computes, writes the whole pyramid, lz4; --memory 1GiB)
  - scipy.ndimage.gaussian_filter(v, 2, mode="nearest", output=float32),
    generic_gradient_magnitude(v as float32, sobel, mode="nearest"),
    label(v > T, 26-connectivity); cc3d.connected_components(v > T, 26);
    SimpleITK (all threads): DiscreteGaussian(variance 4, no spacing),
    SobelEdgeDetection (float32), ConnectedComponent(v > T, fully connected)
    (in core: the volume is loaded from the raw file first; the time is the
    operation's, the peak RSS the whole process's).
Prints one JSON line per run. SKIP="brickyard:gauss,sitk:sobel,..." leaves
runs out (tools: brickyard, scipy, cc3d, sitk; ops: gauss, sobel, label), e.g.
SimpleITK's Sobel at 1024³, which needs about 40 GiB.
"""
import json
import os
import subprocess
import sys
import time

BIN, WORK = sys.argv[1], sys.argv[2]
if len(sys.argv) > 3 and sys.argv[3] == "--out-of-core":
    n = int(sys.argv[4])
    mem = sys.argv[5] if len(sys.argv) > 5 else "1GiB"
    os.makedirs(WORK, exist_ok=True)
    st = os.path.join(WORK, f"mandelbulb{n}.zarr")

    def run(cmd):
        t0 = time.time()
        r = subprocess.run(["/usr/bin/time", "-f", "RSS %M", *cmd], capture_output=True, text=True)
        if r.returncode != 0:
            raise SystemExit(f"{cmd}: exit {r.returncode}\n{r.stderr}")
        rss = int([l for l in r.stderr.splitlines() if l.startswith("RSS ")][-1].split()[1]) / 1024
        return time.time() - t0, rss, r.stdout

    if not os.path.exists(st):
        w, rss, _ = run([BIN, "generate", "mandelbulb", st, "--size", str(n), "--memory", mem,
                         "--quiet"])
        print(json.dumps({"tool": "brickyard generate", "n": n, "wall_s": round(w, 1),
                          "peak_rss_mib": round(rss, 1)}), flush=True)
    for pipe, name in [("gauss(2)", "g"), ("gauss(1)|threshold(100)|label(26)", "l")]:
        w, rss, out = run([BIN, "process", st, pipe, "--out", name, "--overwrite", "--quiet",
                           "--json", "--memory", mem])
        j = json.loads(out.strip().splitlines()[-1])
        print(json.dumps({"tool": "brickyard process", "op": pipe, "n": n, "memory": mem,
                          "wall_s": round(w, 1), "peak_rss_mib": round(rss, 1),
                          "labels": j.get("labels"), "voxels_per_s": round(n ** 3 / w)}),
              flush=True)
    sys.exit(0)
N = int(sys.argv[3]) if len(sys.argv) > 3 else 256
PY = sys.executable
os.makedirs(WORK, exist_ok=True)
raw = os.path.join(WORK, f"cube{N}.raw")
store = os.path.join(WORK, f"cube{N}.zarr")

if not os.path.exists(raw):
    import numpy as np
    import scipy.ndimage as ndi
    rng = np.random.default_rng(5)
    v = ndi.gaussian_filter(rng.random((N, N, N), dtype=np.float32), 3.0, mode="nearest")
    v = (v - v.min()) / (v.max() - v.min())
    (v * 60000).astype(np.uint16).tofile(raw)
    del v
if not os.path.exists(store):
    subprocess.run([BIN, "convert", raw, store, "--dims", f"{N}x{N}x{N}", "--dtype", "u16",
                    "--quiet"], check=True)
T = 33000


def timed(cmd):
    """Run cmd under /usr/bin/time: wall seconds and peak RSS (MiB)."""
    t0 = time.time()
    r = subprocess.run(["/usr/bin/time", "-f", "RSS %M", *cmd], capture_output=True, text=True)
    wall = time.time() - t0
    if r.returncode != 0:
        raise SystemExit(f"{cmd}: exit {r.returncode}\n{r.stdout}\n{r.stderr}")
    rss = int([l for l in r.stderr.splitlines() if l.startswith("RSS ")][-1].split()[1]) / 1024
    return wall, rss, r.stdout


SCIPY = r"""
import sys, time, json, numpy as np, scipy.ndimage as ndi
op, raw, n, t = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
v = np.fromfile(raw, dtype=np.uint16).reshape(n, n, n)
t0 = time.time()
if op == "gauss":
    r = ndi.gaussian_filter(v, 2.0, mode="nearest", output=np.float32)
elif op == "sobel":
    r = ndi.generic_gradient_magnitude(v.astype(np.float32), ndi.sobel, mode="nearest")
elif op == "label":
    r, k = ndi.label(v > t, structure=np.ones((3, 3, 3)))
elif op.startswith("sitk"):
    import SimpleITK as sitk
    img = sitk.GetImageFromArray(v)
    t0 = time.time()
    if op == "sitk-gauss":
        r = sitk.DiscreteGaussian(sitk.Cast(img, sitk.sitkFloat32), variance=4.0,
                                  maximumKernelWidth=64, maximumError=0.001,
                                  useImageSpacing=False)
    elif op == "sitk-sobel":
        r = sitk.SobelEdgeDetection(sitk.Cast(img, sitk.sitkFloat32))
    else:
        r = sitk.ConnectedComponent(img > t, True)
        k = int(sitk.GetArrayViewFromImage(r).max())
elif op == "cc3d":
    import cc3d
    r = cc3d.connected_components(v > t, connectivity=26)
    k = int(r.max())
dt = time.time() - t0
print(json.dumps({"op_seconds": dt, "labels": int(k) if op in ("label", "cc3d", "sitk-label") else None}))
"""

runs = [
    ("gauss(2)", "gauss", "g"),
    ("sobel", "sobel", "s"),
    (f"threshold({T})|label(26)", "label", "l"),
]
SKIP = set(x for x in os.environ.get("SKIP", "").split(",") if x)
for pipe, op, name in runs:
    if f"brickyard:{op}" not in SKIP:
        wall, rss, out = timed([BIN, "process", store, pipe, "--out", name, "--overwrite",
                                "--quiet", "--json", "--memory", "1GiB"])
        j = json.loads(out.strip().splitlines()[-1])
        print(json.dumps({"tool": "brickyard process", "op": pipe, "n": N,
                          "wall_s": round(wall, 3), "peak_rss_mib": round(rss, 1),
                          "labels": j.get("labels")}), flush=True)
    ops = [op] + (["cc3d"] if op == "label" else []) + [f"sitk-{op}"]
    for o in ops:
        tool_key = ("cc3d" if o == "cc3d" else "sitk" if o.startswith("sitk") else "scipy")
        if f"{tool_key}:{op}" in SKIP:
            continue
        wall, rss, out = timed([PY, "-c", SCIPY, o, raw, str(N), str(T)])
        j = json.loads(out.strip().splitlines()[-1])
        tool = ("cc3d 26" if o == "cc3d" else "SimpleITK" if o.startswith("sitk")
                else f"scipy.ndimage {o}")
        print(json.dumps({"tool": tool, "op": pipe, "n": N, "wall_s": round(wall, 3),
                          "op_s": round(j["op_seconds"], 3), "peak_rss_mib": round(rss, 1),
                          "labels": j["labels"]}), flush=True)
