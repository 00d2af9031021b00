#!/usr/bin/env python3
"""An external check of the DVR: `brickyard render` beside VTK's CPU ray
caster (vtkFixedPointVolumeRayCastMapper) on the same volume, camera and
transfer function, compared by SSIM and mean absolute difference.

Usage: compare-vtk.py BRICKYARD_BIN BENCH_DIR N [SIZE]

BENCH_DIR holds what `scripts/bench-vs-vtk.sh` makes: the N³ Mandelbulb store
(`mandelbulb-NxNxN-u8.ome.zarr`), the same volume as raw (`mb-N.raw`) and the
camera (`cam-N.json`). Needs `vtk`, `numpy`, `scipy` and `Pillow` in the
Python environment, and xvfb-run (VTK renders off screen through OpenGL).
Runs outside `.ci/run` (VTK is heavy); results go in BENCHMARKS.md.

Both images are compared as RGB over black, 0..255. SSIM is the mean of the
standard windowed SSIM (Gaussian window σ 1.5, K1 0.01, K2 0.03) over the
three channels.
"""
import json
import os
import subprocess
import sys
import tempfile

import numpy as np
import scipy.ndimage as ndi
from PIL import Image

BIN, DIR, N = sys.argv[1], sys.argv[2], int(sys.argv[3])
S = int(sys.argv[4]) if len(sys.argv) > 4 else 512
HERE = os.path.dirname(os.path.abspath(__file__))
store = os.path.join(DIR, f"mandelbulb-{N}x{N}x{N}-u8.ome.zarr")
raw = os.path.join(DIR, f"mb-{N}.raw")
cam = os.path.join(DIR, f"cam-{N}.json")
for p in (store, raw, cam):
    if not os.path.exists(p):
        sys.exit(f"{p}: missing; run scripts/bench-vs-vtk.sh first")
tmp = tempfile.mkdtemp()
ours_png = os.path.join(tmp, "brickyard.png")
vtk_png = os.path.join(tmp, "vtk.png")
subprocess.run([BIN, "render", store, "--camera", cam, "--size", str(S), "--tf", "soft",
                "--window", "0,255", "--level", "0", "--backend", "cpu", "--quiet",
                "--out", ours_png], check=True, stdout=subprocess.DEVNULL)
subprocess.run(["xvfb-run", "-a", sys.executable, os.path.join(HERE, "bench-vtk-render.py"),
                raw, "--dims", str(N), str(N), str(N), "--camera", cam, "--size", str(S),
                "--repeat", "1", "--png", vtk_png], check=True, stdout=subprocess.DEVNULL)


def rgb_over_black(p):
    a = np.asarray(Image.open(p).convert("RGBA")).astype(np.float64)
    return a[..., :3] * (a[..., 3:4] / 255.0)


def ssim(x, y):
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    f = lambda v: ndi.gaussian_filter(v, 1.5)
    mx, my = f(x), f(y)
    sxx, syy, sxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
    m = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(m.mean())


a, b = rgb_over_black(ours_png), rgb_over_black(vtk_png)
if a.shape != b.shape:
    sys.exit(f"sizes differ: {a.shape} vs {b.shape}")
lit = float((a.max(axis=2) > 8).mean())
if lit < 0.02:
    sys.exit(f"brickyard's image is almost blank ({lit:.3f} lit): nothing to compare")
print(json.dumps({
    "n": N, "size": S,
    "ssim": round(float(np.mean([ssim(a[..., c], b[..., c]) for c in range(3)])), 4),
    "mean_abs_diff": round(float(np.abs(a - b).mean()), 3),
    "max_abs_diff": round(float(np.abs(a - b).max()), 1),
    "lit_fraction": round(lit, 3),
    "images": [ours_png, vtk_png],
}))
