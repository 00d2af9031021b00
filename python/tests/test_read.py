"""Reads through the bindings against zarr-python, and from_numpy round trips."""

import os
import warnings

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
    # Several channels: indexed as NumPy indexes an array of `shape`, the
    # channel first (s[1] is channel 1 whole, not z 1 of channel 0), by
    # an integer or a slice, through the store and its levels alike.
    l1 = zarr_level(dst, 1, 0)
    ref1 = np.stack([zarr_level(dst, 1, c)[...] for c in range(2)])
    assert s.level(1).shape == ref1.shape and s.ndim == 4
    for key in (np.s_[1], np.s_[1, 5], np.s_[..., 0], np.s_[:, 4, -3:, 7], np.s_[::-1, 2:9:3, 5],
                np.s_[1:, ..., ::7], np.s_[5:, 1], np.s_[-1, -1, -1, -1], np.s_[:]):
        np.testing.assert_array_equal(s[key], a[key], err_msg=str(key))
        assert s[key].shape == a[key].shape, key
        np.testing.assert_array_equal(s.level(1)[key], ref1[key], err_msg=str(key))
    assert l1.shape == ref1.shape[1:]
    with pytest.raises(IndexError, match="channel: 5 asked for"):
        s[5, -3:, 7]
    with pytest.raises(IndexError, match="too many indices"):
        s[0, 0, 0, 0, 0]
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


@pytest.mark.parametrize("piece", [32 << 20, 3000, 100])
def test_slices_clip_step_and_select_nothing_as_numpy_does(tmp_path, monkeypatch, piece):
    """Slices out of range clip, empty ones give empty arrays of NumPy's
    shape, and steps (negative ones too) take what NumPy takes: every
    selection against the same one of the array in memory; also where a
    read with steps goes in pieces of a few planes (3000 bytes) or of a
    few rows of a plane (100)."""
    monkeypatch.setattr(brickyard, "_PIECE", piece)
    a = volume((19, 24, 31), "uint16", seed=5)
    dst = tmp_path / "steps.ome.zarr"
    brickyard.from_numpy(a, dst, brick=8, shard=16, progress=False)
    s = brickyard.open(dst, brick=8)
    keys = [
        np.s_[5:5], np.s_[:, 0:25], np.s_[-100:100, 30:, :40], np.s_[::2], np.s_[::-1],
        np.s_[3:17:4, ::-5, 30:2:-7], np.s_[18:0:-3, 7, ::9], np.s_[2, 10:3], np.s_[..., ::-2],
        np.s_[0:19:100, -1::-23, 1::30], np.s_[:, 24:, 0], np.s_[7:3:1, :, :], np.s_[1::2, 3::-1, 5],
        np.s_[::3, ::3, ::3], np.s_[4, ::-2, ::2],
    ]
    for key in keys:
        got = s[key]
        want = a[key]
        assert got.shape == want.shape, key
        assert got.dtype == want.dtype, key
        np.testing.assert_array_equal(got, want, err_msg=str(key))
    # A store of several channels, and a coarser level through Level.
    b = np.stack([a, a[::-1] + 1])
    dst2 = tmp_path / "steps2.ome.zarr"
    brickyard.from_numpy(b, dst2, brick=8, shard=16, progress=False)
    t = brickyard.open(dst2, brick=8)
    np.testing.assert_array_equal(t[1, ::-2, 3:50:5, -4:], b[1, ::-2, 3:50:5, -4:])
    ref = t.read(1, 1)
    np.testing.assert_array_equal(t.level(1)[1, ::3, ::-1, 1:99], ref[::3, ::-1, 1:99])



def test_channel_names_are_written_and_read(tmp_path):
    """Names given to from_numpy (and convert) come back as
    Store.channel_names, and zarr-python reads the same labels from the
    omero metadata; a store without names has "channel i"."""
    a = np.stack([volume((9, 10, 11), "uint8", seed=s) for s in range(3)])
    named = tmp_path / "named.ome.zarr"
    brickyard.from_numpy(a, named, brick=8, shard=8, progress=False, channel_names=["DAPI", "GFP", "RFP"])
    s = brickyard.open(named)
    assert s.channel_names == ["DAPI", "GFP", "RFP"]
    g = zarr.open_group(str(named), mode="r")
    assert [c["label"] for c in g.attrs["ome"]["omero"]["channels"]] == ["DAPI", "GFP", "RFP"]
    again = tmp_path / "again.ome.zarr"
    brickyard.convert(named, again, progress=False, channel_names="a, b,c")
    assert brickyard.open(again).channel_names == ["a", "b", "c"]
    plain = tmp_path / "plain.ome.zarr"
    brickyard.from_numpy(a, plain, brick=8, shard=8, progress=False)
    assert brickyard.open(plain).channel_names == ["channel 0", "channel 1", "channel 2"]
    with pytest.raises(ValueError, match="2 name\\(s\\) given for 3 channel"):
        brickyard.from_numpy(a, tmp_path / "x.ome.zarr", progress=False, channel_names=["a", "b"])
    with pytest.raises(ValueError, match="given twice"):
        brickyard.from_numpy(a, tmp_path / "y.ome.zarr", progress=False, channel_names=["a", "b", "a"])
    with pytest.raises(ValueError, match="is empty"):
        brickyard.convert(named, tmp_path / "z.ome.zarr", progress=False, channel_names="a,,c")
    assert not (tmp_path / "x.ome.zarr").exists() and not (tmp_path / "z.ome.zarr").exists()


def test_several_inputs_become_channels_as_the_cli_stacks_them(tmp_path, cli):
    """convert([a, b], out) stacks inputs of one grid as channels, in
    order, as `brickyard convert A B OUT` does; names may be given."""
    a, b = volume((9, 10, 11), "uint16", seed=1), volume((9, 10, 11), "uint16", seed=2)
    pa, pb = tmp_path / "a.ome.zarr", tmp_path / "b.ome.zarr"
    brickyard.from_numpy(a, pa, brick=8, shard=8, progress=False)
    brickyard.from_numpy(b, pb, brick=8, shard=8, progress=False)
    two = tmp_path / "two.ome.zarr"
    brickyard.convert([pa, str(pb)], two, brick=8, shard=8, progress=False, channel_names=["first", "second"])
    s = brickyard.open(two)
    assert s.shape == (2, 9, 10, 11)
    np.testing.assert_array_equal(s[0], a)
    np.testing.assert_array_equal(s[1], b)
    assert s.channel_names == ["first", "second"]
    cli("convert", pa, pb, tmp_path / "cli.ome.zarr", "--brick", "8", "--shard", "8", "--quiet")
    c = brickyard.open(tmp_path / "cli.ome.zarr")
    for level in range(s.levels):
        np.testing.assert_array_equal(s.level(level)[:], c.level(level)[:])
    with pytest.raises(ValueError, match="3 name\\(s\\) given for 2 channel"):
        brickyard.convert((pa, pb), tmp_path / "x.ome.zarr", progress=False, channel_names=["a", "b", "c"])
    with pytest.raises(FileNotFoundError, match="nowhere.ome.zarr"):
        brickyard.convert([pa, tmp_path / "nowhere.ome.zarr"], tmp_path / "y.ome.zarr", progress=False)
    other = tmp_path / "other.ome.zarr"
    brickyard.from_numpy(volume((9, 10, 12), "uint16", seed=3), other, progress=False)
    with pytest.raises(ValueError):
        brickyard.convert([pa, other], tmp_path / "z.ome.zarr", progress=False)
    assert not any((tmp_path / n).exists() for n in ("x.ome.zarr", "y.ome.zarr", "z.ome.zarr"))


def test_none_in_an_index_is_refused(tmp_path):
    """NumPy reads None as a new axis; a store does not make one, and says
    so rather than reading the whole volume without it."""
    p = tmp_path / "n.ome.zarr"
    brickyard.from_numpy(volume((4, 5, 6), "uint8", seed=1), p, progress=False)
    s = brickyard.open(p)
    for key in (None, (None,), (0, None), (Ellipsis, None)):
        with pytest.raises(IndexError, match="np.newaxis"):
            s[key]
        with pytest.raises(IndexError, match="np.newaxis"):
            s.level(0)[key]
    assert s.read(0, 0, None).shape == (4, 5, 6)


def test_a_store_is_sized_and_converted_as_numpy_arrays_are_and_advanced_indexing_is_refused(tmp_path):
    """`len` and `np.asarray` as NumPy has them for an array of `shape`;
    lists, integer arrays and boolean masks are refused by name (NumPy's
    advanced indexing), as are two ellipses."""
    a = volume((9, 10, 11), "uint16", seed=2)
    dst = tmp_path / "n.ome.zarr"
    brickyard.from_numpy(a, dst, brick=8, shard=8, progress=False)
    s = brickyard.open(os.fsencode(dst))
    assert len(s) == 9 and len(s.level(1)) == len(s.level(1)[...])
    np.testing.assert_array_equal(np.asarray(s), a)
    assert np.asarray(s, dtype=np.float32).dtype == np.float32
    np.testing.assert_array_equal(np.asarray(s.level(1)), s.read(1))
    with pytest.raises(ValueError, match="copy=False"):
        s.__array__(copy=False)
    for key in ([1, 5, 2], np.array([1, 2]), a[:, 0, 0] > 3, True, (slice(None), [0, 1])):
        with pytest.raises(TypeError, match="advanced indexing"):
            s[key]
    with pytest.raises(IndexError, match="single ellipsis"):
        s[..., ...]


def test_a_pattern_of_slices_converts_as_the_cli_converts_it(tmp_path):
    """`convert("slices/img_*.tif")` was refused as a missing file."""
    import tifffile

    a = volume((6, 12, 10), "uint8", seed=4)
    for z in range(6):
        tifffile.imwrite(tmp_path / f"img_{z}.tif", a[z])
    dst = tmp_path / "g.ome.zarr"
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        brickyard.convert(str(tmp_path / "img_*.tif"), dst, progress=False)
    np.testing.assert_array_equal(brickyard.open(dst)[...], a)
    # The note on the missing spacing speaks Python: (z, y, x).
    assert any("spacing=(z, y, x)" in str(x.message) for x in w), [str(x.message) for x in w]
    with pytest.raises(Exception, match="img_x"):
        brickyard.convert(str(tmp_path / "img_x*.tif"), tmp_path / "h.ome.zarr", progress=False)
