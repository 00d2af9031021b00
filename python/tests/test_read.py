"""Reads through the bindings against zarr-python, and from_numpy round trips."""

import numpy as np
import pytest
import zarr

import brickyard
from conftest import volume

DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64"]


def zarr_level(path, level, channel=0):
    a = zarr.open_array(f"{path}/{level}", mode="r")
    return a[channel] if a.ndim == 4 else a


def random_regions(shape, n, rng):
    for _ in range(n):
        lo = [int(rng.integers(0, s)) for s in shape]
        hi = [int(rng.integers(l + 1, s + 1)) for l, s in zip(lo, shape)]
        yield tuple(slice(l, h) for l, h in zip(lo, hi))


@pytest.mark.parametrize("dtype", DTYPES)
def test_read_equals_zarr_python_every_level(tmp_path, dtype):
    a = volume((37, 70, 91), dtype, seed=DTYPES.index(dtype))
    dst = tmp_path / f"{dtype}.ome.zarr"
    brickyard.from_numpy(a, dst, spacing=(2.0, 1.0, 1.0), brick=16, shard=32, progress=False)
    # A small engine brick and host cache: reads cross many bricks and evict.
    s = brickyard.open(dst, brick=16, cache=1 << 20)
    assert s.dtype == np.dtype(dtype)
    assert s.shapes[0] == a.shape and s.channels == 1
    assert s.levels >= 3
    # from_numpy then read: exactly the array given.
    np.testing.assert_array_equal(s.read(0), a)
    rng = np.random.default_rng(7)
    for level in range(s.levels):
        ref = zarr_level(dst, level)
        assert s.shapes[level] == ref.shape
        whole = s.read(level=level)
        assert whole.dtype == ref.dtype
        np.testing.assert_array_equal(whole, ref[...])
        for region in random_regions(ref.shape, 6, rng):
            np.testing.assert_array_equal(s.read(level, 0, region), ref[region], err_msg=f"level {level} {region}")
            np.testing.assert_array_equal(s.level(level)[region], ref[region])


def test_store_slicing_and_metadata(tmp_path):
    a = np.stack([volume((20, 33, 40), "uint16", seed=1), volume((20, 33, 40), "uint16", seed=2)])
    dst = tmp_path / "two.ome.zarr"
    brickyard.from_numpy(a, dst, spacing=(3.0, 0.5, 0.5), brick=16, shard=32, progress=False)
    s = brickyard.open(dst, brick=16)
    assert s.channels == 2 and s.shape == (2, 20, 33, 40)
    assert s.scales[0][-3:] == [3.0, 0.5, 0.5]
    np.testing.assert_array_equal(s[1, 2:9, :, 5:17], a[1, 2:9, :, 5:17])
    # Several channels: the channel first, as `shape` says. Fewer indices
    # read channel 0 at z where NumPy would take a channel (s[1] was z 1
    # of channel 0): refused, with the way to say it.
    for key in (np.s_[1], np.s_[5, -3:, 7], np.s_[..., 0]):
        with pytest.raises(IndexError, match=r"store\[c, z, y, x\]"):
            s[key]
    np.testing.assert_array_equal(s[1, :, :, :], a[1])
    np.testing.assert_array_equal(s[0, 5, -3:, 7], a[0, 5, -3:, 7])
    np.testing.assert_array_equal(s.read(channel=1, region=np.s_[..., 3]), a[1, :, :, 3])
    for c in range(2):
        np.testing.assert_array_equal(s.read(0, c), zarr_level(dst, 0, c)[...])
        np.testing.assert_array_equal(s.read(1, c), zarr_level(dst, 1, c)[...])
    # Channels index as NumPy does: negative from the end, out of range an
    # IndexError (a channel of -4 of 2 wrapped around), floats a TypeError,
    # the same through a Level.
    np.testing.assert_array_equal(s[-1, 3, :, :], a[-1, 3])
    np.testing.assert_array_equal(s.level(0)[-2, 3, :, :], a[0, 3])
    for bad in (-3, 2, -7):
        with pytest.raises(IndexError, match="channel"):
            s[bad, 0, 0, :]
        with pytest.raises(IndexError, match="channel"):
            s.level(0)[bad, 0, 0, :]
    with pytest.raises(TypeError, match="channel"):
        s.level(0)[1.9, 0, 0, :]
    with pytest.raises(TypeError, match="level"):
        s.level(1.5)


def test_convert_from_zarr_equals_source(tmp_path):
    a = volume((30, 40, 50), "int16", seed=3)
    src = tmp_path / "plain.zarr"
    z = zarr.create_array(str(src), shape=a.shape, dtype=a.dtype, chunks=(10, 20, 25))
    z[...] = a
    dst = tmp_path / "converted.ome.zarr"
    report = brickyard.convert(src, dst, brick=16, shard=32, progress=False)
    assert "levels" in report
    s = brickyard.open(dst)
    np.testing.assert_array_equal(s.read(0), a)
    for level in range(1, s.levels):
        np.testing.assert_array_equal(s.read(level), zarr_level(dst, level)[...])


def test_a_store_closes_and_pickles_by_reopening(tmp_path):
    import copy
    import multiprocessing
    import pickle

    p = tmp_path / "p.zarr"
    v = np.random.default_rng(3).integers(0, 255, (40, 40, 40), dtype=np.uint8)
    brickyard.from_numpy(v, p, progress=False)
    with brickyard.open(p, cache=8 << 20) as s:
        assert (s.read() == v).all()
        t = pickle.loads(pickle.dumps(s))
        assert (t.read() == v).all() and t.path == s.path
        assert (copy.deepcopy(s)[0:4, 0:4, 0:4] == v[0:4, 0:4, 0:4]).all()
        # In another process (as a multiprocessing pool hands it out).
        with multiprocessing.get_context("spawn").Pool(1) as pool:
            got = pool.apply(_first_plane_sum, (s,))
        assert got == int(v[0].astype(np.int64).sum())
    with pytest.raises(ValueError, match="the store is closed"):
        s.read()
    # Rendering a closed handle is refused as its reads are.
    with pytest.raises(ValueError, match="the store is closed"):
        brickyard.render(s, size=16, backend="cpu")
    assert (t.read(region=np.s_[0:1, 0:1, 0:2]) == v[0:1, 0:1, 0:2]).all()


def _first_plane_sum(s):
    return int(s.read(region=np.s_[0:1, :, :]).astype(np.int64).sum())


def test_a_replaced_store_is_refused_by_render_as_by_reads(tmp_path):
    # The handle's reads refuse a store replaced since it was opened;
    # `render` took its path and drew whatever was there now.
    p = tmp_path / "r.zarr"
    brickyard.from_numpy(volume((24, 24, 24), "uint8", seed=1), p, progress=False)
    s = brickyard.open(p)
    assert brickyard.render(s, size=16, backend="cpu").shape == (16, 16, 4)
    import shutil
    shutil.rmtree(p)
    brickyard.from_numpy(volume((30, 20, 10), "uint16", seed=2), p, progress=False)
    with pytest.raises(OSError, match="replaced"):
        s.read()
    with pytest.raises(OSError, match="replaced"):
        brickyard.render(s, size=16, backend="cpu")
    # A path, or a handle opened again, draws the new store.
    assert brickyard.render(brickyard.open(p), size=16, backend="cpu").shape == (16, 16, 4)


def test_spacing_errors_name_the_values_as_given():
    with pytest.raises(ValueError, match=r"spacing: expected positive numbers \(z, y, x\), got \(3\.0, 2\.0, -1\.0\)"):
        brickyard.from_numpy(np.zeros((8, 8, 8), np.uint8), "never.zarr", spacing=(3, 2, -1), progress=False)
    with pytest.raises(ValueError, match="origin: expected finite"):
        brickyard.from_numpy(np.zeros((8, 8, 8), np.uint8), "never.zarr", origin=(0, float("nan"), 0), progress=False)
