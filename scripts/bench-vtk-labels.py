#!/usr/bin/env python3
"""Baseline for 3D views of label images: VTK's label-map surfaces on the
same labels and camera as `brickyard render STORE/labels/NAME`.

Usage:
    bench-vtk-labels.py RAWFILE --dims X Y Z --camera CAMERA.json
                        [--size 1024] [--repeat 3] [--png OUT.png]

What it does (the usual VTK pipeline for a label map's 3D view):
  * reads RAWFILE (uint32 labels, x fastest) whole into a vtkImageData,
    voxel centres at (i + 0.5) world units as in brickyard;
  * vtkSurfaceNets3D extracts every label's boundary (label 0 is the
    background), smoothed as the filter does by default; each face coloured
    by the label it bounds through a lookup table of random colours;
  * renders the mesh off screen (needs an OpenGL context: Xvfb + Mesa here,
    a software rasteriser) through the camera of a brickyard camera JSON.

Prints one JSON line: read, surface-extraction and first-frame times (their
sum is the one-shot cost, set beside `brickyard render`'s wall time), the
best of --repeat frames after the first, the triangle count and the peak RSS.
"""
import argparse
import json
import resource
import time

import numpy as np
import vtk
from vtk.util import numpy_support


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("raw")
    ap.add_argument("--dims", type=int, nargs=3, required=True, metavar=("X", "Y", "Z"))
    ap.add_argument("--camera", required=True)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--png")
    a = ap.parse_args()

    t0 = time.perf_counter()
    x, y, z = a.dims
    data = np.fromfile(a.raw, dtype=np.uint32, count=x * y * z)
    img = vtk.vtkImageData()
    img.SetDimensions(x, y, z)
    img.SetSpacing(1.0, 1.0, 1.0)
    img.SetOrigin(0.5, 0.5, 0.5)
    img.GetPointData().SetScalars(
        numpy_support.numpy_to_vtk(data, deep=True, array_type=vtk.VTK_UNSIGNED_INT))
    n_labels = int(data.max())
    read_ms = (time.perf_counter() - t0) * 1e3

    t1 = time.perf_counter()
    nets = vtk.vtkSurfaceNets3D()
    nets.SetInputData(img)
    nets.SetBackgroundLabel(0)
    nets.GenerateLabels(n_labels, 1, n_labels)
    nets.Update()
    mesh = nets.GetOutput()
    extract_ms = (time.perf_counter() - t1) * 1e3

    lut = vtk.vtkLookupTable()
    lut.SetNumberOfTableValues(n_labels + 1)
    rng = np.random.default_rng(1)
    for i in range(n_labels + 1):
        r, g, b = rng.uniform(0.3, 1.0, 3)
        lut.SetTableValue(i, r, g, b, 1.0)
    lut.SetTableRange(0, n_labels)
    lut.Build()
    mapper = vtk.vtkPolyDataMapper()
    mapper.SetInputData(mesh)
    mapper.SetLookupTable(lut)
    mapper.SetScalarRange(0, n_labels)
    mapper.SetScalarModeToUseCellData()
    actor = vtk.vtkActor()
    actor.SetMapper(mapper)
    ren = vtk.vtkRenderer()
    ren.AddActor(actor)
    ren.SetBackground(0, 0, 0)
    win = vtk.vtkRenderWindow()
    win.SetOffScreenRendering(1)
    win.AddRenderer(ren)
    win.SetSize(a.size, a.size)
    cam = json.load(open(a.camera))
    c = ren.GetActiveCamera()
    c.SetPosition(*cam["eye"])
    c.SetFocalPoint(*cam["target"])
    c.SetViewUp(*cam["up"])
    c.SetViewAngle(cam["projection"]["fov_y_deg"])
    ren.ResetCameraClippingRange()
    t2 = time.perf_counter()
    win.Render()
    first_ms = (time.perf_counter() - t2) * 1e3
    times = []
    for i in range(a.repeat):
        c.Azimuth(0.5 if i % 2 == 0 else -0.5)
        t = time.perf_counter()
        win.Render()
        times.append((time.perf_counter() - t) * 1e3)
    if a.png:
        w2i = vtk.vtkWindowToImageFilter()
        w2i.SetInput(win)
        w2i.Update()
        png = vtk.vtkPNGWriter()
        png.SetFileName(a.png)
        png.SetInputConnection(w2i.GetOutputPort())
        png.Write()
    print(json.dumps({
        "tool": "vtk", "vtk": vtk.vtkVersion.GetVTKVersion(), "filter": "vtkSurfaceNets3D",
        "labels": n_labels, "triangles": mesh.GetNumberOfCells(),
        "read_ms": round(read_ms, 1), "extract_ms": round(extract_ms, 1),
        "first_frame_ms": round(first_ms, 1),
        "one_shot_ms": round(read_ms + extract_ms + first_ms, 1),
        "frame_ms": round(min(times), 1) if times else None,
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }))


if __name__ == "__main__":
    main()
