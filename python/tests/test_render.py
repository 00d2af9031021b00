"""render() against `brickyard render` of the same view, bit for bit."""

import json
import warnings

import numpy as np
import pytest

import brickyard
from conftest import read_png, volume


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    dst = tmp_path_factory.mktemp("render") / "v.ome.zarr"
    brickyard.from_numpy(volume((48, 56, 64), "uint16", seed=5), dst, spacing=(1.5, 1.0, 1.0), brick=16,
                         shard=32, progress=False)
    return dst


@pytest.mark.parametrize("mode,tf", [("dvr", "soft"), ("dvr", "hot"), ("mip", "viridis"), ("slice", "linear")])
def test_render_equals_cli(store, cli, tmp_path, mode, tf):
    out = tmp_path / "cli.png"
    cli("render", store, "--mode", mode, "--size", "64x48", "--backend", "cpu", "--tf", tf, "--quiet",
        "--out", out)
    want = read_png(out)
    got = brickyard.render(brickyard.open(store), mode=mode, tf=tf, size=(64, 48), backend="cpu")
    assert got.shape == (48, 64, 4) and got.dtype == np.uint8
    assert want.any(), "the CLI's image is black: the test would prove nothing"
    np.testing.assert_array_equal(got, want)


def test_render_camera_and_tf_dicts_equal_cli_files(store, cli, tmp_path):
    cam_file, out = tmp_path / "cam.json", tmp_path / "cli.png"
    cli("render", store, "--size", "40x40", "--backend", "cpu", "--azimuth", "70", "--elevation=-15",
        "--save-camera", cam_file, "--out", tmp_path / "first.png", "--quiet")
    tf_file = tmp_path / "tf.json"
    # A transfer function as JSON: the preset the CLI would build, edited.
    tf = {"window": [10000.0, 50000.0], "colormap": "hot",
          "opacity": [[0.0, 0.0], [0.5, 0.1], [1.0, 0.8]]}
    tf_file.write_text(json.dumps(tf))
    try:
        cli("render", store, "--size", "40x40", "--backend", "cpu", "--camera", cam_file, "--tf", tf_file,
            "--out", out, "--quiet")
    except RuntimeError as e:
        pytest.fail(f"the transfer-function JSON of this test is not the CLI's format: {e}")
    want = read_png(out)
    camera = json.loads(cam_file.read_text())
    got = brickyard.render(str(store), camera=camera, tf=tf, size=40, backend="cpu")
    np.testing.assert_array_equal(got, want)
    # The same as JSON text.
    got2 = brickyard.render(str(store), camera=json.dumps(camera), tf=json.dumps(tf), size=40, backend="cpu")
    np.testing.assert_array_equal(got2, want)


def test_render_options_pass_through(store, cli, tmp_path):
    out = tmp_path / "cli.png"
    cli("render", store, "--mode", "mip", "--size", "32x32", "--backend", "cpu", "--window", "0,40000",
        "--level", "1", "--out", out, "--quiet")
    got = brickyard.render(store, mode="mip", size=(32, 32), backend="cpu", window=(0, 40000), level=1)
    np.testing.assert_array_equal(got, read_png(out))
    f = brickyard.render(store, mode="mip", size=(32, 32), backend="cpu", window=(0, 40000), level=1,
                         dtype="float32")
    assert f.dtype == np.float32 and f.shape == (32, 32, 4)
    assert 0.0 <= f.min() and f.max() <= 1.0 and f[..., 3].max() > 0


def test_render_negative_option_values(store, cli, tmp_path):
    out = tmp_path / "cli.png"
    cli("render", store, "--size", "24x24", "--backend", "cpu", "--elevation=-40", "--lod-bias=-1", "--out", out,
        "--quiet")
    got = brickyard.render(store, size=24, backend="cpu", elevation=-40, lod_bias=-1)
    np.testing.assert_array_equal(got, read_png(out))


def test_render_per_channel_options_equal_cli(tmp_path, cli):
    # Two channels in DVR, channel 1 with a transfer function of its own
    # and drawn at level 1 only: dicts and lists give the CLI's flags.
    dst = tmp_path / "two.ome.zarr"
    vol = np.stack([volume((40, 48, 56), "uint8", seed=3), volume((40, 48, 56), "uint8", seed=4)])
    brickyard.from_numpy(vol, dst, brick=16, shard=32, progress=False)
    tf = {"window": [0.0, 255.0], "colormap": "hot", "opacity": [[0.0, 0.0], [0.5, 0.0], [1.0, 0.6]]}
    tf_file = tmp_path / "tf1.json"
    tf_file.write_text(json.dumps(tf))
    out = tmp_path / "cli.png"
    cli("render", dst, "--size", "48x40", "--backend", "cpu", "--channel", "0:green", "--channel", "1:magenta",
        "--channel-tf", f"1={tf_file}", "--channel-levels", "1=1-1", "--out", out, "--quiet")
    want = read_png(out)
    assert want.any(), "the CLI's image is black: the test would prove nothing"
    got = brickyard.render(dst, size=(48, 40), backend="cpu", channel=["0:green", "1:magenta"],
                           channel_tf={1: tf}, channel_levels={1: (1, 1)})
    np.testing.assert_array_equal(got, want)
    got2 = brickyard.render(dst, size=(48, 40), backend="cpu", channel=["0:green", "1:magenta"],
                            channel_tf=[f"1={tf_file}"], channel_levels=["1=1-1"])
    np.testing.assert_array_equal(got2, want)
    # The level range changes the image.
    full = brickyard.render(dst, size=(48, 40), backend="cpu", channel=["0:green", "1:magenta"],
                            channel_tf={1: tf})
    assert (full != want).any()


def test_render_out_writes_the_png(store, cli, tmp_path):
    # `out` writes the file `brickyard render --out` writes (it was passed
    # on and nothing was written), and the array returned is its pixels.
    out = tmp_path / "py.png"
    got = brickyard.render(store, mode="mip", tf="hot", size=(40, 32), backend="cpu", out=out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(read_png(out), got)
    assert got.any(), "a black image: the test would prove nothing"
    cli("render", store, "--mode", "mip", "--tf", "hot", "--size", "40x32", "--backend", "cpu", "--quiet",
        "--out", tmp_path / "cli.png")
    assert out.read_bytes() == (tmp_path / "cli.png").read_bytes()
    # The CLI's checks of the name hold.
    with pytest.raises(ValueError, match="expected a name ending in .png"):
        brickyard.render(store, size=16, backend="cpu", out=tmp_path / "x.jpg")
    with pytest.raises(ValueError, match="is not an existing folder"):
        brickyard.render(store, size=16, backend="cpu", out=tmp_path / "nowhere" / "x.png")


def test_render_without_out_needs_no_writable_folder(store, monkeypatch):
    # Without `out` nothing is written: a notebook started in a folder it
    # cannot write (here /proc, which no one can create files in) renders.
    monkeypatch.chdir("/proc")
    got = brickyard.render(store, mode="mip", size=(40, 32), backend="cpu")
    assert got.shape == (32, 40, 4) and got.any()
    with pytest.raises(ValueError, match="cannot create a file in"):
        brickyard.render(store, mode="mip", size=(40, 32), backend="cpu", out="x.png")


def test_turntable_returns_every_view(store, cli, tmp_path):
    n = 3
    kw = dict(mode="dvr", tf="hot", size=(36, 28), backend="cpu")
    frames = brickyard.render(store, turntable=n, out=tmp_path / "py.png", **kw)
    assert frames.shape == (n, 28, 36, 4) and frames.dtype == np.uint8
    for i in range(n):
        for j in range(i):
            assert (frames[i] != frames[j]).any(), f"views {j} and {i} are the same image"
    # The first view is the camera's own view; each is what the CLI writes.
    np.testing.assert_array_equal(frames[0], brickyard.render(store, **kw))
    cli("render", store, "--mode", "dvr", "--tf", "hot", "--size", "36x28", "--backend", "cpu", "--quiet",
        "--turntable", n, "--out", tmp_path / "cli.png")
    for i in range(n):
        np.testing.assert_array_equal(frames[i], read_png(tmp_path / f"cli-{i:04}.png"))
        np.testing.assert_array_equal(frames[i], read_png(tmp_path / f"py-{i:04}.png"))
    assert not (tmp_path / "py.png").exists()
    f = brickyard.render(store, turntable=n, dtype="float32", **kw)
    assert f.shape == (n, 28, 36, 4) and f.dtype == np.float32
    # One view asked for is still a sequence of views.
    assert brickyard.render(store, turntable=1, **kw).shape == (1, 28, 36, 4)


def test_label_images_render_as_the_cli_draws_them(tmp_path, cli):
    # Five balls over noise, labelled by `process`.
    z, y, x = np.mgrid[0:24, 0:32, 0:40]
    img = np.random.default_rng(3).integers(0, 8000, (24, 32, 40)).astype(np.uint16)
    for cz, cy, cx in [(12, 8, 8), (12, 8, 30), (12, 24, 10), (12, 24, 30), (6, 16, 20)]:
        img[(z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2 <= 25] = 50000
    dst = tmp_path / "img.ome.zarr"
    brickyard.from_numpy(img, dst, brick=16, shard=32, progress=False)
    brickyard.process(brickyard.open(dst), "threshold(25000)|label(26)", out="blobs")
    labels = brickyard.open(dst / "labels" / "blobs")
    n = int(labels.read(level=0).max())
    assert n >= 3, f"{n} labels: the test would prove little"
    for what, store, extra, opts in [
        ("labels alone", dst / "labels" / "blobs", [], {}),
        ("over the image", dst, ["--labels", "blobs", "--label-opacity", "0.7"],
         {"labels": "blobs", "label_opacity": 0.7}),
        ("some labels over the image", dst, ["--labels", "blobs", "--only-labels", "1,3"],
         {"labels": "blobs", "only_labels": [1, 3]}),
        ("all labels but one", dst / "labels" / "blobs", ["--hide-labels", "2"],
         {"hide_labels": 2}),
    ]:
        out = tmp_path / "cli.png"
        cli("render", store, "--mode", "slice", "--size", "48x40", "--backend", "cpu", "--quiet",
            "--out", out, *extra)
        want = read_png(out)
        got = brickyard.render(str(store), mode="slice", size=(48, 40), backend="cpu", **opts)
        np.testing.assert_array_equal(got, want, err_msg=what)
    # Without `tf` a label image's slice takes its labels' colours: few
    # distinct colours (the labels and black), unlike a grey ramp.
    alone = brickyard.render(labels, mode="slice", size=(48, 40), backend="cpu")
    colours = {tuple(p) for p in alone.reshape(-1, 4)}
    assert 3 <= len(colours) <= n + 1, len(colours)
    # One label drawn: its colour and black, on fewer pixels than all.
    # (a label of the middle plane, which the slice shows)
    k = int(labels.read(level=0)[..., 12, :, :].max())
    one = brickyard.render(labels, mode="slice", size=(48, 40), backend="cpu", only_labels=[k])
    lit = lambda im: int((im[..., :3].max(axis=-1) > 0).sum())
    assert len({tuple(p) for p in one.reshape(-1, 4)}) == 2
    assert 0 < lit(one) < lit(alone)
    ramp = brickyard.render(labels, mode="slice", size=(48, 40), backend="cpu", tf="linear")
    assert (ramp != alone).any()
    with pytest.raises(ValueError, match="no label image"):
        brickyard.render(str(dst), mode="slice", labels="nope", size=16)


def test_render_refuses_unknown_options_and_channels_that_are_no_integers(store):
    s = brickyard.open(store)
    with pytest.raises(TypeError, match="unexpected keyword argument 'channels' \\(did you mean channel=\\?\\)"):
        brickyard.render(s, size=16, backend="cpu", channels=[0])
    with pytest.raises(TypeError, match="unexpected keyword argument 'colour'"):
        brickyard.render(s, size=16, backend="cpu", colour="red")
    for bad in (1.0, True, [0, 1.5]):
        with pytest.raises(TypeError, match="channel: expected an integer"):
            brickyard.render(s, size=16, backend="cpu", channel=bad)
    # Flags the CLI takes pass.
    assert brickyard.render(s, size=16, backend="cpu", lod_bias=0.5).shape == (16, 16, 4)


@pytest.mark.parametrize("kind", ["frame", "progressive"])
def test_ctrl_c_stops_a_long_render(tmp_path, kind):
    # One frame of 2048² at 8 samples per voxel takes seconds (8 s on two
    # cores); Ctrl-C stops it within a band of its tiles. An accumulation
    # of 48 frames at 256² takes 19 s: Ctrl-C stops it between frames
    # (it used to wait for the last).
    import os
    import signal
    import threading
    import time
    p = tmp_path / "long.ome.zarr"
    brickyard.from_numpy(volume((96, 96, 96), "uint16", seed=1), p, progress=False)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGINT))
    t0 = time.monotonic()
    try:
        timer.start()
        with pytest.raises(KeyboardInterrupt, match="interrupted"):
            if kind == "frame":
                brickyard.render(p, size=2048, samples_per_voxel=8, backend="cpu")
            else:
                brickyard.render(p, size=256, progressive=48, backend="cpu")
        seconds = time.monotonic() - t0
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, old)
    assert seconds < 1.0 + 3, f"KeyboardInterrupt {seconds - 1.0:.1f} s after SIGINT"


def test_a_render_drawn_coarser_than_asked_says_so(tmp_path):
    # A pool too small for level 0: the image comes back at a coarser
    # level, and a RuntimeWarning says which (it came back silently, the
    # note only in what the CLI prints).
    p = tmp_path / "c.zarr"
    v = (np.random.default_rng(1).random((128, 128, 128)) * 255).astype(np.uint8)
    brickyard.from_numpy(v, p, progress=False)
    with pytest.warns(RuntimeWarning, match=r"at level [1-9]\d* \(asked level 0\)"):
        img = brickyard.render(p, backend="cpu", size=256, level=0, pool="1MiB", mode="mip")
    assert img.shape == (256, 256, 4) and img[..., :3].max() > 0
    # Where the pool holds the view: no warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        brickyard.render(p, backend="cpu", size=64, level=0, mode="mip")


def test_the_quickstart_runs_with_the_package_alone(tmp_path):
    # The README's example, as a new user runs it after `pip install
    # ./python`: it needed matplotlib (or imageio) to write its PNG.
    import pathlib
    import re
    import subprocess
    import sys

    ex = pathlib.Path(__file__).resolve().parents[1] / "examples" / "quickstart.py"
    r = subprocess.run([sys.executable, str(ex)], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    m = re.search(r"wrote brickyard-example\.png: \(384, 384, 4\) uint8, (\d+) pixels lit", r.stdout)
    assert m and int(m.group(1)) > 1000, r.stdout
    assert (tmp_path / "brickyard-example.png").stat().st_size > 1000
