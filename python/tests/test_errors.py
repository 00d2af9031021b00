"""Bad inputs raise the right exceptions, with messages that say what is wrong."""

import numpy as np
import pytest

import brickyard
from conftest import volume


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    dst = tmp_path_factory.mktemp("errors") / "e.ome.zarr"
    brickyard.from_numpy(volume((20, 24, 28), "uint8"), dst, brick=16, shard=32, progress=False)
    return dst


def test_missing_store(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.ome.zarr"):
        brickyard.open(tmp_path / "nowhere.ome.zarr")
    with pytest.raises(FileNotFoundError, match="nowhere"):
        brickyard.render(tmp_path / "nowhere", backend="cpu")
    with pytest.raises(FileNotFoundError, match="nowhere.tif"):
        brickyard.convert(tmp_path / "nowhere.tif", tmp_path / "out.ome.zarr", progress=False)


def test_not_a_store(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises((ValueError, OSError), match="empty"):
        brickyard.open(tmp_path / "empty")


def test_wrong_regions(store):
    s = brickyard.open(store)
    with pytest.raises(IndexError, match="outside axis z of length 20"):
        s[20]
    with pytest.raises(IndexError, match="selects nothing"):
        s[5:5]
    with pytest.raises(IndexError, match="outside length 24"):
        s[:, 0:25]
    with pytest.raises(IndexError, match="at most 3 axes"):
        s.read(region=np.s_[0, 0, 0, 0])
    with pytest.raises(ValueError, match="only step 1"):
        s[::2]
    with pytest.raises(TypeError, match="expected an int or a slice"):
        s["a"]
    with pytest.raises(IndexError, match="level: 9 asked for but the store has"):
        s.read(level=9)
    with pytest.raises(IndexError, match="channel: 1 asked for but the store has 1 channel"):
        s.read(channel=1)
    # The native layer checks too (the Python layer is bypassed here).
    with pytest.raises(ValueError, match="outside level 0"):
        s._native.read(0, 0, (0, 0, 0), (21, 1, 1))


def test_wrong_dtype_and_shape(tmp_path):
    with pytest.raises(TypeError, match="dtype complex128 is not stored by brickyard"):
        brickyard.from_numpy(np.zeros((4, 4, 4), np.complex128), tmp_path / "c.ome.zarr", progress=False)
    with pytest.raises(TypeError, match="dtype bool"):
        brickyard.from_numpy(np.zeros((4, 4, 4), bool), tmp_path / "b.ome.zarr", progress=False)
    with pytest.raises(ValueError, match="expected \\(z, y, x\\) or \\(c, z, y, x\\)"):
        brickyard.from_numpy(np.zeros((4, 4)), tmp_path / "d.ome.zarr", progress=False)
    with pytest.raises(ValueError, match="shape .* needs 1024 bytes, 8 given"):
        from brickyard import _native
        _native.from_bytes(b"\0" * 8, (1, 4, 16, 16), "uint8", str(tmp_path / "x"),
                           {"brick": (16,) * 3, "shard": (32,) * 3, "compression": "lz4", "labels": False,
                            "memory": 1 << 28, "overwrite": False, "spacing": None, "origin": None, "unit": None})
    for bad in ("gzip", "zstd:abc", "zstd:99"):
        with pytest.raises(ValueError, match="compression: expected lz4"):
            brickyard.from_numpy(np.zeros((4, 4, 4), np.uint8), tmp_path / "z.ome.zarr", compression=bad,
                                 progress=False)


def test_spacing_and_origin_that_are_no_geometry(tmp_path):
    # Spacings not positive and origins not finite were written as 1 and as
    # null (invalid OME-Zarr); nothing is left behind.
    a = np.zeros((4, 4, 4), np.uint8)
    for kw, field in [({"spacing": 0}, "spacing"), ({"spacing": (-1, 1, 1)}, "spacing"),
                      ({"spacing": float("nan")}, "spacing"), ({"origin": float("inf")}, "origin")]:
        dst = tmp_path / f"{field}.ome.zarr"
        with pytest.raises(ValueError, match=field):
            brickyard.from_numpy(a, dst, progress=False, **kw)
        assert not dst.exists()


def test_existing_output_is_refused(store, tmp_path):
    with pytest.raises((ValueError, OSError), match="exists"):
        brickyard.from_numpy(np.zeros((4, 4, 4), np.uint8), store, progress=False)


def test_bad_render_options(store):
    with pytest.raises(ValueError, match="mode: expected dvr, mip or slice"):
        brickyard.render(store, mode="iso")
    with pytest.raises(ValueError, match="backend: expected auto, cpu or gpu"):
        brickyard.render(store, backend="tpu")
    with pytest.raises(ValueError, match="tf: "):
        brickyard.render(store, tf="nonsense", backend="cpu")
    with pytest.raises(ValueError, match="opacity"):
        brickyard.render(store, tf={"window": [0, 1], "opacity": [[2.0, 1.0]]}, backend="cpu")
    with pytest.raises(ValueError, match="size"):
        brickyard.render(store, size=(0, 10), backend="cpu")
    with pytest.raises(ValueError, match="level: the store has"):
        brickyard.render(store, level=40, backend="cpu")
    with pytest.raises(ValueError, match="unexpected argument"):
        brickyard.render(store, backend="cpu", no_such_option=3)
