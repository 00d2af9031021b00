"""What the VTK baselines share (scripts/bench-vtk-render.py,
scripts/bench-vtk-channels.py): the mapper as brickyard samples (one ray per
pixel, one sample per voxel, no auto-adjustment), the camera of a brickyard
camera JSON in an off-screen window, frame timing and the PNG."""
import json
import time

import vtk


def mapper_of(img, threads):
    """vtkFixedPointVolumeRayCastMapper of `img`: ImageSampleDistance 1,
    SampleDistance 1, `threads` worker threads (0: VTK's default)."""
    mapper = vtk.vtkFixedPointVolumeRayCastMapper()
    mapper.SetInputData(img)
    mapper.AutoAdjustSampleDistancesOff()
    if threads > 0:
        mapper.SetNumberOfThreads(threads)
    mapper.SetSampleDistance(1.0)
    mapper.SetImageSampleDistance(1.0)
    mapper.SetInteractiveSampleDistance(1.0)
    return mapper


def window(mapper, prop, camera_json, size):
    """An off-screen size×size window drawing the volume of `mapper` and
    `prop` through the camera of `camera_json` (`brickyard render
    --save-camera`: eye, target, up, perspective field of view or
    orthographic height)."""
    volume = vtk.vtkVolume()
    volume.SetMapper(mapper)
    volume.SetProperty(prop)
    ren = vtk.vtkRenderer()
    ren.AddVolume(volume)
    ren.SetBackground(0, 0, 0)
    win = vtk.vtkRenderWindow()
    win.SetOffScreenRendering(1)
    win.AddRenderer(ren)
    win.SetSize(size, size)
    cam = json.load(open(camera_json))
    c = ren.GetActiveCamera()
    c.SetPosition(*cam["eye"])
    c.SetFocalPoint(*cam["target"])
    c.SetViewUp(*cam["up"])
    proj = cam["projection"]
    if proj.get("type") == "orthographic":
        c.ParallelProjectionOn()
        c.SetParallelScale(proj["height"] / 2.0)
    else:
        c.SetViewAngle(proj["fov_y_deg"])
    ren.ResetCameraClippingRange()
    return win


def frames(win, repeat):
    """The first frame's time (set-up included: the one-shot cost) and the
    times of `repeat` frames after it, in ms."""
    t = time.perf_counter()
    win.Render()
    first_ms = (time.perf_counter() - t) * 1e3
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        win.Render()
        times.append((time.perf_counter() - t) * 1e3)
    return first_ms, times


def write_png(win, path):
    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(win)
    grab.Update()
    wr = vtk.vtkPNGWriter()
    wr.SetFileName(path)
    wr.SetInputConnection(grab.GetOutputPort())
    wr.Write()
