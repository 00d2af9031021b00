"""brickyard.process against the CLI (bit for bit) and scipy.ndimage (within tolerance)."""

import os
import warnings
import re
import shutil
import signal
import subprocess
import threading
import time

import numpy as np
import pytest
import scipy.ndimage as ndi
import zarr

import brickyard
from conftest import brickyard_bin, volume

# As scripts/interop/check_process.py: float32 results computed in float64
# within |ours - scipy| <= 1e-5 * max|scipy| (mode="nearest", truncate=4).
TOL = 1e-5


def levels(path):
    """Every level of an OME-Zarr image, read with zarr-python."""
    g = zarr.open_group(str(path), mode="r")
    n = len(g.attrs["ome"]["multiscales"][0]["datasets"])
    return [g[str(k)][...] for k in range(n)]


def bits(a):
    """The array's bytes, so that NaN and -0.0 compare bit for bit."""
    return a.view(np.dtype(f"u{a.dtype.itemsize}"))


@pytest.fixture(scope="module")
def vol():
    return volume((37, 45, 52), "uint16", seed=11)


@pytest.fixture()
def two_stores(tmp_path, vol):
    """The same store twice: one for the CLI, one for the bindings."""
    a = tmp_path / "cli.ome.zarr"
    brickyard.from_numpy(vol, a, spacing=(2.0, 1.0, 1.0), unit="micrometer", brick=16, shard=32, progress=False)
    b = tmp_path / "py.ome.zarr"
    shutil.copytree(a, b)
    return a, b


def test_filters_equal_cli_and_scipy(two_stores, vol, cli):
    a, b = two_stores
    pipe = "gauss(1.5)|sobel"
    cli("process", a, pipe, "--out", "edges", "--quiet")
    seen = []
    res = brickyard.process(b, pipe, out="edges", progress=lambda kind, n: seen.append(kind))
    assert isinstance(res, brickyard.Store)
    assert os.path.samefile(res.path, b / "derived" / "edges")
    assert "start:writing" in seen and "inc" in seen
    got, want = levels(b / "derived" / "edges"), levels(a / "derived" / "edges")
    assert len(got) == len(want) >= 2
    for k, (g, w) in enumerate(zip(got, want)):
        assert g.dtype == w.dtype == np.float32 and g.shape == w.shape
        assert np.array_equal(bits(g), bits(w)), f"level {k} differs from the CLI's"
    # The returned store reads the same voxels.
    np.testing.assert_array_equal(res.read(0), got[0])
    # Independent reference: scipy in float64.
    ref = ndi.generic_gradient_magnitude(ndi.gaussian_filter(vol.astype(np.float64), 1.5, mode="nearest"),
                                         ndi.sobel, mode="nearest")
    err = float(np.abs(got[0].astype(np.float64) - ref).max())
    assert err <= TOL * float(np.abs(ref).max()), err
    # A wrong result would be far off: the reference is not trivially close.
    assert float(np.abs(ref).max()) > 1000


def test_physical_sigma_and_level_1(two_stores, vol, cli):
    a, b = two_stores
    # σ = 2 µm on a spacing of (2, 1, 1) µm: (1, 2, 2) voxels (z, y, x).
    cli("process", a, "gauss(2um)", "--out", "g", "--quiet")
    brickyard.process(b, "gauss(2um)", out="g", progress=False)
    got = levels(b / "derived" / "g")
    for g, w in zip(got, levels(a / "derived" / "g")):
        assert np.array_equal(bits(g), bits(w))
    ref = ndi.gaussian_filter(vol.astype(np.float64), (1.0, 2.0, 2.0), mode="nearest")
    assert float(np.abs(got[0] - ref).max()) <= TOL * float(np.abs(ref).max())
    cli("process", a, "sobel", "--out", "s1", "--level", "1", "--quiet")
    r = brickyard.process(b, "sobel", out="s1", level=1, memory=64 << 20, progress=False)
    l1 = zarr.open_array(str(b / "1"), mode="r")[...]
    assert r.shapes[0] == l1.shape
    assert np.array_equal(bits(r.read(0)), bits(levels(a / "derived" / "s1")[0]))
    ref = ndi.generic_gradient_magnitude(l1.astype(np.float64), ndi.sobel, mode="nearest")
    assert float(np.abs(r.read(0) - ref).max()) <= TOL * float(np.abs(ref).max())


def test_labels_equal_cli_and_scipy(two_stores, vol, cli, tmp_path):
    a, b = two_stores
    t = float(np.percentile(vol, 80))
    pipe = f"gauss(1.5)|threshold({t})|label(26)"
    cli("process", a, pipe, "--out", "cells", "--quiet", "--stats", tmp_path / "cli.csv")
    res = brickyard.process(b, pipe, out="cells", stats=tmp_path / "py.csv", progress=False)
    assert os.path.samefile(res.path, b / "labels" / "cells")
    assert zarr.open_group(str(b / "labels"), mode="r").attrs["ome"]["labels"] == ["cells"]
    got = levels(b / "labels" / "cells")
    for g, w in zip(got, levels(a / "labels" / "cells")):
        assert g.dtype == np.uint32 and np.array_equal(g, w)
    assert (tmp_path / "py.csv").read_text() == (tmp_path / "cli.csv").read_text()
    # scipy: the same partition of the same mask.
    mask = ndi.gaussian_filter(vol.astype(np.float64), 1.5, mode="nearest") > t
    ref, n = ndi.label(mask, structure=np.ones((3, 3, 3), bool))
    lab = got[0]
    assert n > 1 and int(lab.max()) == n
    assert np.array_equal(lab > 0, ref > 0)
    pairs = np.unique(np.stack([lab[ref > 0], ref[ref > 0]]), axis=1)
    assert pairs.shape[1] == n


def test_filtering_label_ids_warns_and_a_mask_of_them_does_not(two_stores, vol):
    _, b = two_stores
    t = float(np.percentile(vol, 80))
    cells = brickyard.process(b, f"threshold({t})|label(26)", out="cells", progress=False)
    with pytest.warns(UserWarning, match=r"is a label image: gauss\(1\) treats its label ids as intensities"):
        brickyard.process(cells, "gauss(1)", out="smooth", progress=False)
    # threshold(0): the mask of every label, smoothed: no warning, and the
    # values are those of the mask's own Gaussian.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = brickyard.process(cells, "threshold(0)|gauss(1)", out="m", progress=False)
    lab = levels(cells.path)[0]
    want = ndi.gaussian_filter((lab > 0).astype(np.float64), 1.0, mode="nearest")
    got = levels(r.path)[0]
    assert np.abs(got - want).max() <= TOL


def cli_error(*args):
    r = subprocess.run([str(brickyard_bin()), *map(str, args)], capture_output=True, text=True)
    assert r.returncode != 0
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("error: "), r.stderr
    return line[len("error: "):]


@pytest.mark.parametrize("pipe", ["gauss(1.5)|", "blur(2)", "label(26)|gauss(1)", "gauss(", "threshold(x)",
                                  "gauss(1,2)", "label(8)"])
def test_bad_pipeline_has_the_cli_message(two_stores, pipe):
    _, b = two_stores
    want = cli_error("process", b, pipe, "--out", "x", "--quiet")
    assert want.startswith("pipeline")
    with pytest.raises(ValueError) as e:
        brickyard.process(b, pipe, out="x", progress=False)
    assert str(e.value) == want
    assert not (b / "derived").exists() and not (b / "labels").exists()


def test_bad_arguments(two_stores, tmp_path):
    _, b = two_stores
    with pytest.raises(FileNotFoundError, match="nowhere.ome.zarr"):
        brickyard.process(tmp_path / "nowhere.ome.zarr", "sobel", out="s", progress=False)
    with pytest.raises(ValueError, match="out: expected a plain name"):
        brickyard.process(b, "sobel", out="a/b", progress=False)
    with pytest.raises(ValueError, match="stats: only a pipeline that ends in label"):
        brickyard.process(b, "sobel", out="s", stats=tmp_path / "s.csv", progress=False)
    with pytest.raises(IndexError, match="channel: 3 asked for"):
        brickyard.process(b, "sobel", out="s", channel=3, progress=False)
    with pytest.raises(ValueError, match="memory: unknown unit"):
        brickyard.process(b, "sobel", out="s", memory="2 parsecs", progress=False)
    with pytest.raises(ValueError, match="a remote store is read-only"):
        brickyard.process("http://127.0.0.1:9/x.ome.zarr", "sobel", out="s", progress=False)
    brickyard.process(b, "sobel", out="s", progress=False)
    with pytest.raises(ValueError, match="exists; pass overwrite=True"):
        brickyard.process(b, "sobel", out="s", progress=False)
    before = levels(b / "derived" / "s")[0]
    r = brickyard.process(b, "gauss(1)", out="s", overwrite=True, progress=False)
    assert not np.array_equal(r.read(0), before)
    assert sorted(os.listdir(b / "derived")) == ["s", "zarr.json"]


@pytest.mark.parametrize("pipe,phase", [("gauss(2)|sobel", "writing"),
                                        ("gauss(2)|threshold(30000)|label(26)", "labelling")])
def test_ctrl_c_leaves_the_store_as_it_was(tmp_path, pipe, phase):
    a = volume((128, 128, 128), "uint16", seed=5)
    dst = tmp_path / "big.ome.zarr"
    brickyard.from_numpy(a, dst, brick=16, shard=64, progress=False)
    before = sorted(os.listdir(dst))
    seen = []

    def progress(kind, n):
        # SIGINT at the first piece of work of the phase (the labelling
        # reports from worker threads, the writing from the job's thread).
        if kind.startswith("start"):
            seen.append(kind)
        elif seen and seen[-1].startswith(f"start:{phase}"):
            seen.append("sent")
            os.kill(os.getpid(), signal.SIGINT)

    # Python's own SIGINT handler, whatever the test runner inherited (a
    # shell that starts it in the background ignores SIGINT).
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt, match="as it was"):
            brickyard.process(dst, pipe, out="x", progress=progress)
    finally:
        signal.signal(signal.SIGINT, old)
    assert "sent" in seen, seen
    if phase == "labelling":
        assert not any(k.startswith("start:writing") for k in seen), seen
    assert sorted(os.listdir(dst)) == before



@pytest.mark.parametrize("job", ["median", "zstd"])
def test_ctrl_c_is_answered_within_a_slow_region(tmp_path, job):
    # One region of a slow stage takes tens of seconds (median(3) of this
    # volume: about 30 s on two cores in one region); zstd:19 takes 1.5 s
    # or more a slab of 64 planes, 4.3 s for these 160 planes on an idle
    # two-core machine (64 planes ended before the signal): Ctrl-C must
    # not wait for the region's or the job's end.
    depth = 64 if job == "median" else 160
    a = np.random.default_rng(0).integers(0, 4000, (depth, 512, 512), dtype=np.uint16)
    src = tmp_path / "s.ome.zarr"
    brickyard.from_numpy(a, src, progress=False)
    before = sorted(os.listdir(src))
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(1.5, lambda: os.kill(os.getpid(), signal.SIGINT))
    t0 = time.monotonic()
    try:
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            if job == "median":
                brickyard.process(src, "median(3)", out="med", progress=False)
            else:
                brickyard.from_numpy(a, tmp_path / "z.ome.zarr", compression="zstd:19", progress=False)
        seconds = time.monotonic() - t0
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, old)
    # (A median's block is given up row by row: its wait was 2.2-2.7 s for
    # median(7); zstd's slab is not.)
    assert seconds < 1.5 + (1 if job == "median" else 3), f"KeyboardInterrupt {seconds - 1.5:.1f} s after SIGINT"
    assert sorted(os.listdir(src)) == before
    assert not (tmp_path / "z.ome.zarr").exists()


def test_process_releases_the_gil(tmp_path):
    dst = tmp_path / "gil.ome.zarr"
    # Large enough that the job lasts well over the 0.1 s this test needs
    # to tell anything (96x128x128 took 0.09 s on an idle 2-core machine).
    brickyard.from_numpy(volume((192, 256, 256), "float32", seed=9), dst, brick=32, progress=False)
    done = threading.Event()
    result = {}

    def job():
        t = time.perf_counter()
        result["store"] = brickyard.process(dst, "gauss(3)|sobel", out="g", progress=False)
        result["seconds"] = time.perf_counter() - t
        done.set()

    th = threading.Thread(target=job)
    th.start()
    gaps, last = [], time.perf_counter()
    while not done.is_set():
        sum(range(200))
        now = time.perf_counter()
        gaps.append(now - last)
        last = now
    th.join()
    assert result["seconds"] > 0.1, "the job was too short to tell"
    assert max(gaps) < 0.5 * result["seconds"], (max(gaps), result["seconds"])
    assert len(gaps) > 100


def test_tqdm_bars_per_phase(two_stores, vol, monkeypatch):
    """progress=True: one tqdm bar per phase, each run to its total."""
    import sys
    import types

    bars = []

    class FakeTqdm:
        def __init__(self, total, unit, unit_scale, desc):
            self.desc, self.unit, self.total, self.n, self.closed = desc, unit, total, 0, False
            bars.append(self)

        def reset(self, total):
            self.total, self.n = total, 0

        def update(self, n):
            self.n += n

        def close(self):
            self.closed = True

    monkeypatch.setitem(sys.modules, "tqdm.auto", types.SimpleNamespace(tqdm=FakeTqdm))
    _, b = two_stores
    brickyard.process(b, "gauss(1)|threshold(30000)|label(6)", out="l")
    assert [(x.desc, x.unit) for x in bars] == [("process: labelling (pass 1, voxels)", "vox"),
                                                 ("process: writing", "B")]
    assert bars[0].total == bars[0].n == vol.size
    assert bars[1].total == bars[1].n > 0
    assert all(x.closed for x in bars)


def test_too_little_memory_names_the_keyword_and_the_least_that_runs(tmp_path):
    dst = tmp_path / "m.ome.zarr"
    brickyard.from_numpy(volume((48, 48, 48), "uint16", seed=2), dst, brick=16, shard=32, progress=False)
    store = brickyard.open(dst)
    with pytest.raises(ValueError, match=r'give memory="\d+MiB" or more') as e:
        brickyard.process(store, "gauss(6)", out="g", memory=2 << 20, progress=False)
    least = int(re.search(r'memory="(\d+)MiB"', str(e.value)).group(1))
    assert "--" not in str(e.value), str(e.value)
    # The size it names runs; a MiB less does not.
    with pytest.raises(ValueError, match="too small"):
        brickyard.process(store, "gauss(6)", out="g", memory=f"{least - 1}MiB", progress=False)
    r = brickyard.process(store, "gauss(6)", out="g", memory=f"{least}MiB", progress=False)
    assert r.levels >= 1


def test_labels_from_numpy_into_an_image_are_published_with_their_table(tmp_path):
    """A segmentation written from NumPy into an image's labels/NAME is a
    label image of that image, as `brickyard convert --labels` makes one:
    listed, on the image's grid (its spacing taken), with the statistics
    table of its voxels (counts and boxes against numpy, means of the
    image under each label)."""
    img = volume((20, 24, 28), "uint16", seed=3)
    store = tmp_path / "img.ome.zarr"
    brickyard.from_numpy(img, store, spacing=(0.5, 0.25, 2.0), unit="micrometer", brick=16,
                         progress=False)
    seg = ((img > np.percentile(img, 70)) * (1 + np.arange(28) // 7)[None, None, :]).astype(np.uint32)
    with pytest.raises(ValueError, match="labels"):
        brickyard.from_numpy(seg, store / "labels" / "nolab", brick=16, progress=False)
    r = brickyard.from_numpy(seg, store / "labels" / "seg", labels=True, brick=16, progress=False)
    assert "image's grid" not in r, r
    # Off the image's grid (shifted, or cut): listed, and the report says
    # it is not drawn over the image.
    for name, kw in [("shifted", dict(spacing=(0.5, 0.25, 2.0), unit="micrometer",
                                      origin=(0.0, 5.0, 0.0))),
                     ("cut", dict())]:
        part = seg if kw else seg[:, :10]
        with pytest.warns(UserWarning, match="a label image off its image's grid: it is listed, but drawn over the image"):
            r = brickyard.from_numpy(part, store / "labels" / name, labels=True, brick=16,
                                     progress=False, **kw)
        assert "only on the image's grid" in r, (name, r)
    g = zarr.open_group(str(store / "labels"), mode="r")
    assert "seg" in g.attrs["ome"]["labels"]
    with brickyard.open(store / "labels" / "seg") as s, brickyard.open(store) as i:
        assert s.scales[0] == i.scales[0]
    rows = {}
    with open(store / "labels" / "seg" / "_brickyard" / "labels.csv") as f:
        next(f)
        for line in f:
            c = line.strip().split(",")
            rows[int(c[0])] = c
    ids = [int(v) for v in np.unique(seg) if v]
    assert sorted(rows) == ids
    counts = np.bincount(seg.ravel())
    means = ndi.mean(img.astype(np.float64), seg, index=ids)
    for k, lab in enumerate(ids):
        zz, yy, xx = np.nonzero(seg == lab)
        want = [counts[lab], zz.min(), yy.min(), xx.min(), zz.max(), yy.max(), xx.max()]
        assert [int(v) for v in rows[lab][1:8]] == want, lab
        assert abs(float(rows[lab][11]) - means[k]) <= 1e-9 * means[k]


def test_a_label_image_of_several_channels_is_refused_before_anything_is_written(tmp_path):
    """A label image has one channel: from_numpy(labels=True) of a (c, z, y,
    x) array with c > 1 is refused, with or without geometry given, and
    leaves no labels group behind; float labels likewise."""
    img = volume((8, 9, 10), "uint16", seed=4)
    store = tmp_path / "img.ome.zarr"
    brickyard.from_numpy(img, store, brick=8, progress=False)
    two = np.stack([img.astype(np.uint32), img.astype(np.uint32)])
    for kw in (dict(), dict(spacing=(1.0, 1.0, 1.0))):
        with pytest.raises(ValueError, match="one channel"):
            brickyard.from_numpy(two, store / "labels" / "two", labels=True, brick=8, progress=False, **kw)
        assert not (store / "labels").exists()
    with pytest.raises(ValueError, match="integers"):
        brickyard.from_numpy(img.astype(np.float32), store / "labels" / "f", labels=True, brick=8,
                             progress=False, spacing=(1.0, 1.0, 1.0))
    assert not (store / "labels").exists()
