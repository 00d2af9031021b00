#!/usr/bin/env python3
"""Baseline for the rendering benchmark: VTK's CPU ray caster on the same
volume, camera and transfer function as `brickyard bench render`.

Usage:
    bench-vtk-render.py RAWFILE --dims X Y Z --camera CAMERA.json
                        [--size 512] [--repeat 5] [--window 0 255]
                        [--png OUT.png] [--mip]

What it does:
  * reads RAWFILE (uint8, x fastest) whole into a vtkImageData (the volume is
    in RAM: VTK's mapper is in-core), voxel centres at (i + 0.5) world units
    as in brickyard;
  * vtkFixedPointVolumeRayCastMapper: one ray per pixel
    (ImageSampleDistance 1, no auto-adjustment), one sample per voxel
    (SampleDistance 1), trilinear interpolation, front-to-back with early
    ray termination, all cores (its own thread pool);
  * transfer function = brickyard's "soft" preset over --window: opacity 0
    up to 15 % of the window, then linear to 0.35 at its top, opacity unit
    distance one voxel; colours of the "bone" colour map;
  * camera from a brickyard camera JSON (`brickyard render --save-camera`):
    eye, target, up, vertical field of view;
  * renders off screen (needs an OpenGL context, e.g. Xvfb + Mesa) and
    reports the best of --repeat frames after a first one, which is timed
    apart: reading the file plus that first frame is the one-shot cost
    ("cold_ms"), reported with the process's peak RSS.

Prints one JSON line: {"tool": "vtk", "vtk": VERSION, "frame_ms": BEST, ...}
"""
import argparse
import json
import resource
import time

import numpy as np
import vtk
from vtk.util import numpy_support

from vtk_view import frames, mapper_of, window, write_png

BONE = [
    (0.0, 0.0, 0.0, 0.0),
    (0.365079, 0.319444, 0.319444, 0.444444),
    (0.746032, 0.652778, 0.777778, 0.777778),
    (1.0, 1.0, 1.0, 1.0),
]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("raw")
    ap.add_argument("--dims", type=int, nargs=3, required=True, metavar=("X", "Y", "Z"))
    ap.add_argument("--camera", required=True)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--window", type=float, nargs=2, default=[0.0, 255.0])
    ap.add_argument("--png")
    ap.add_argument("--mip", action="store_true",
                    help="maximum intensity projection (VTK's MaximumIntensityBlend) instead of DVR")
    ap.add_argument("--threads", type=int, default=0, help="worker threads (0: VTK's default, all cores)")
    a = ap.parse_args()

    t_read = time.perf_counter()
    x, y, z = a.dims
    data = np.fromfile(a.raw, dtype=np.uint8, count=x * y * z)
    img = vtk.vtkImageData()
    img.SetDimensions(x, y, z)
    img.SetSpacing(1.0, 1.0, 1.0)
    img.SetOrigin(0.5, 0.5, 0.5)
    arr = numpy_support.numpy_to_vtk(data, deep=True, array_type=vtk.VTK_UNSIGNED_CHAR)
    img.GetPointData().SetScalars(arr)
    read_ms = (time.perf_counter() - t_read) * 1e3

    w0, w1 = a.window
    span = w1 - w0
    opacity = vtk.vtkPiecewiseFunction()
    opacity.AddPoint(w0, 0.0)
    opacity.AddPoint(w0 + 0.15 * span, 0.0)
    opacity.AddPoint(w1, 0.35)
    color = vtk.vtkColorTransferFunction()
    for p, r, g, b in BONE:
        color.AddRGBPoint(w0 + p * span, r, g, b)
    prop = vtk.vtkVolumeProperty()
    prop.SetScalarOpacity(opacity)
    prop.SetColor(color)
    prop.SetInterpolationTypeToLinear()
    prop.ShadeOff()
    prop.SetScalarOpacityUnitDistance(1.0)

    mapper = mapper_of(img, a.threads)
    if a.mip:
        mapper.SetBlendModeToMaximumIntensity()
    win = window(mapper, prop, a.camera, a.size)
    first_ms, times = frames(win, a.repeat)
    if a.png:
        write_png(win, a.png)
    print(json.dumps({
        "tool": "vtk", "vtk": vtk.vtkVersion.GetVTKVersion(),
        "mapper": "vtkFixedPointVolumeRayCastMapper", "blend": "mip" if a.mip else "composite",
        "size": [x, y, z], "image": [a.size, a.size],
        "threads": mapper.GetNumberOfThreads(),
        "frame_ms": min(times) if times else None, "all_ms": times,
        "read_ms": read_ms, "first_frame_ms": first_ms,
        "cold_ms": read_ms + first_ms,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
    }))


if __name__ == "__main__":
    main()
