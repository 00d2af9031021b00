#!/usr/bin/env python3
"""Baseline for multi-channel DVR: VTK's CPU ray caster with independent
components on the same channels, camera and transfer functions as
`brickyard render STORE` draws them by default.

Usage:
    bench-vtk-channels.py STORE.ome.zarr --camera CAMERA.json
                          [--size 1024] [--repeat 5] [--threads 2]
                          [--png OUT.png]

What it does:
  * reads level 0 of every channel of the OME-Zarr store (zarr-python) into
    one vtkImageData of C components (in RAM: VTK's mapper is in-core),
    voxel centres at (i + 0.5) world units, as brickyard places them for a
    store of unit spacing;
  * per channel the transfer function brickyard gives a channel in DVR by
    default (`ChannelStyle::dvr_tf`): its `omero` colour over its `omero`
    window, opacity 0 up to a tenth of the window, then linear to 0.45;
  * vtkFixedPointVolumeRayCastMapper with IndependentComponentsOn (at most
    four channels), one ray per pixel, one sample per voxel, trilinear,
    early ray termination, --threads worker threads;
  * VTK mixes independent components its own way (a weighted sum of the
    components' colours and opacities), not brickyard's coincident media:
    the images differ, the work per sample is comparable;
  * reports the best of --repeat frames after a first one, which is timed
    apart with the read ("cold_ms").

Prints one JSON line: {"tool": "vtk", "channels": C, "frame_ms": BEST, ...}
"""
import argparse
import json
import resource
import time

import numpy as np
import vtk
import zarr
from vtk.util import numpy_support

from vtk_view import frames, mapper_of, window, write_png


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("store")
    ap.add_argument("--camera", required=True)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=0, help="worker threads (0: VTK's default, all cores)")
    ap.add_argument("--png")
    a = ap.parse_args()

    t_read = time.perf_counter()
    group = zarr.open_group(a.store, mode="r")
    ome = group.attrs["ome"]
    level0 = ome["multiscales"][0]["datasets"][0]["path"]
    data = np.asarray(group[level0][:])  # [c, z, y, x]
    if data.ndim != 4 or data.dtype != np.uint8:
        raise SystemExit(f"{a.store}: expected a [c, z, y, x] uint8 level 0, found {data.shape} {data.dtype}")
    c, z, y, x = data.shape
    if not 1 <= c <= 4:
        raise SystemExit(f"{a.store}: {c} channels; VTK's independent components take 1 to 4")
    # x fastest, the components interleaved per voxel.
    inter = np.ascontiguousarray(np.moveaxis(data, 0, -1)).reshape(-1, c)
    img = vtk.vtkImageData()
    img.SetDimensions(x, y, z)
    img.SetSpacing(1.0, 1.0, 1.0)
    img.SetOrigin(0.5, 0.5, 0.5)
    arr = numpy_support.numpy_to_vtk(inter, deep=True, array_type=vtk.VTK_UNSIGNED_CHAR)
    arr.SetNumberOfComponents(c)
    img.GetPointData().SetScalars(arr)
    read_ms = (time.perf_counter() - t_read) * 1e3

    prop = vtk.vtkVolumeProperty()
    prop.IndependentComponentsOn()
    channels = ome.get("omero", {}).get("channels", [])
    for i in range(c):
        ch = channels[i] if i < len(channels) else {}
        hexc = ch.get("color", "FFFFFF")
        rgb = [int(hexc[k : k + 2], 16) / 255.0 for k in (0, 2, 4)]
        win = ch.get("window", {})
        w0, w1 = float(win.get("start", 0.0)), float(win.get("end", 255.0))
        span = w1 - w0
        opacity = vtk.vtkPiecewiseFunction()
        opacity.AddPoint(w0, 0.0)
        opacity.AddPoint(w0 + 0.1 * span, 0.0)
        opacity.AddPoint(w1, 0.45)
        color = vtk.vtkColorTransferFunction()
        color.AddRGBPoint(w0, *rgb)
        color.AddRGBPoint(w1, *rgb)
        prop.SetScalarOpacity(i, opacity)
        prop.SetColor(i, color)
        prop.SetComponentWeight(i, 1.0)
        prop.SetScalarOpacityUnitDistance(i, 1.0)
    prop.SetInterpolationTypeToLinear()
    prop.ShadeOff()

    mapper = mapper_of(img, a.threads)
    win = window(mapper, prop, a.camera, a.size)
    first_ms, times = frames(win, a.repeat)
    if a.png:
        write_png(win, a.png)
    print(
        json.dumps(
            {
                "tool": "vtk",
                "vtk": vtk.vtkVersion.GetVTKVersion(),
                "channels": c,
                "dims": [x, y, z],
                "size": a.size,
                "frame_ms": min(times),
                "median_ms": sorted(times)[len(times) // 2],
                "cold_ms": read_ms + first_ms,
                "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            }
        )
    )


if __name__ == "__main__":
    main()
