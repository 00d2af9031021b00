"""from_numpy on lazy arrays (dask, zarr, duck-typed): read region by region, never whole."""

import numpy as np
import pytest
import zarr

import brickyard
from conftest import volume


class Counted:
    """A lazy array over `data` that counts what is fetched and refuses
    to be materialised whole (no __array__; a fetch larger than `limit`
    elements fails)."""

    def __init__(self, data, limit):
        self._data = data
        self.shape = data.shape
        self.ndim = data.ndim
        self.dtype = data.dtype
        self.limit = limit
        self.calls = []

    def __getitem__(self, key):
        block = self._data[key]
        assert block.size <= self.limit, f"fetched {block.size} elements at once (limit {self.limit})"
        self.calls.append(block.size)
        return block.copy()

    def __array__(self, *args, **kwargs):
        raise AssertionError("the whole array was asked for")


@pytest.mark.parametrize("shape", [(70, 45, 52), (2, 33, 40, 41)])
def test_duck_typed_array_is_read_in_regions(tmp_path, shape):
    a = volume(shape[-3:], "uint16", seed=4)
    if len(shape) == 4:
        a = np.stack([a, volume(shape[-3:], "uint16", seed=5)])
    # At most a slab of one brick's planes: 16 planes of (y, x).
    limit = 16 * shape[-2] * shape[-1]
    lazy = Counted(a, limit)
    dst = tmp_path / "lazy.ome.zarr"
    brickyard.from_numpy(lazy, dst, brick=16, shard=32, progress=False)
    assert len(lazy.calls) > 1
    assert max(lazy.calls) <= limit < a.size
    # Every voxel fetched once.
    assert sum(lazy.calls) == a.size
    s = brickyard.open(dst)
    for c in range(a.shape[0] if a.ndim == 4 else 1):
        np.testing.assert_array_equal(s.read(0, c), a[c] if a.ndim == 4 else a)
    # The same pyramid as from the array in memory.
    ref = tmp_path / "eager.ome.zarr"
    brickyard.from_numpy(a, ref, brick=16, shard=32, progress=False)
    e = brickyard.open(ref)
    assert e.shapes == s.shapes
    for level in range(s.levels):
        np.testing.assert_array_equal(s.read(level), e.read(level))


def test_zarr_array_and_memmap(tmp_path):
    a = volume((40, 36, 50), "float32", seed=6)
    z = zarr.create_array(str(tmp_path / "in.zarr"), shape=a.shape, dtype=a.dtype, chunks=(8, 18, 25))
    z[...] = a
    brickyard.from_numpy(zarr.open_array(str(tmp_path / "in.zarr"), mode="r"), tmp_path / "z.ome.zarr", brick=16,
                         progress=False)
    np.testing.assert_array_equal(brickyard.open(tmp_path / "z.ome.zarr").read(0), a)
    m = np.memmap(tmp_path / "raw.bin", dtype=">i2", mode="w+", shape=(20, 30, 40))
    m[...] = volume((20, 30, 40), "int16", seed=7)
    m.flush()
    brickyard.from_numpy(m, tmp_path / "m.ome.zarr", brick=16, progress=False)
    got = brickyard.open(tmp_path / "m.ome.zarr").read(0)
    assert got.dtype == np.int16
    np.testing.assert_array_equal(got, np.asarray(m))


def test_dask_array_is_not_computed_whole(tmp_path):
    da = pytest.importorskip("dask.array")
    a = volume((64, 48, 56), "uint8", seed=8)
    computed = []
    # 8 chunks of 8 planes, each computed through a function that records
    # it; the builder reads slabs of 16 planes (two chunks).
    lazy = da.from_array(a, chunks=(8, 48, 56)).map_blocks(
        lambda b: (computed.append(b.size) if b.size else None, b)[1], dtype=a.dtype)
    at_first_slab = []

    def progress(kind, n):
        if kind == "inc" and not at_first_slab:
            at_first_slab.append(len(computed))

    dst = tmp_path / "dask.ome.zarr"
    brickyard.from_numpy(lazy, dst, brick=16, shard=32, progress=progress)
    # Computed whole, all 8 chunks would be done before the first slab is
    # written; region by region, at most the first two slabs are (the
    # reader fetches one slab ahead).
    assert at_first_slab and at_first_slab[0] <= 4, at_first_slab
    assert len(computed) == 8 and sum(computed) == a.size
    s = brickyard.open(dst)
    assert s.shapes[0] == a.shape
    np.testing.assert_array_equal(s.read(0), a)
    # A materialising call would have computed the chunks all at once.
    computed.clear()
    np.asarray(lazy)
    assert len(computed) == 8


def test_lazy_errors(tmp_path):
    a = volume((20, 20, 20), "uint8")

    class Broken(Counted):
        def __getitem__(self, key):
            if key[0].start >= 16:
                raise KeyError("chunk 1 is missing")
            return super().__getitem__(key)

    with pytest.raises(ValueError, match=r"Broken of shape \(20, 20, 20\).*channel 0, \[16:20") as e:
        brickyard.from_numpy(Broken(a, a.size), tmp_path / "b.ome.zarr", brick=16, progress=False)
    assert isinstance(e.value.__cause__, KeyError)
    assert not (tmp_path / "b.ome.zarr").exists()

    class Wrong(Counted):
        def __getitem__(self, key):
            return super().__getitem__(key)[:, :1]

    with pytest.raises(ValueError, match="has shape"):
        brickyard.from_numpy(Wrong(a, a.size), tmp_path / "w.ome.zarr", brick=16, progress=False)
    c = Counted(a.astype(np.complex64), a.size)
    with pytest.raises(TypeError, match="dtype complex64 is not stored"):
        brickyard.from_numpy(c, tmp_path / "c.ome.zarr", progress=False)
    assert c.calls == []


def test_numpy_arrays_not_in_c_order_or_native_bytes(tmp_path):
    # A strided, transposed, reversed or byte-swapped NumPy array is read
    # region by region (a C-contiguous one in place): each gives the
    # pyramid of its C-ordered, native copy, level by level.
    a = np.stack([volume((30, 34, 38), "float32", seed=6), volume((30, 34, 38), "float32", seed=7)])
    ref = tmp_path / "ref.ome.zarr"
    brickyard.from_numpy(np.ascontiguousarray(a), ref, brick=16, shard=32, progress=False)
    e = brickyard.open(ref)
    cases = {
        "fortran": np.asfortranarray(a),
        "reversed": a[:, ::-1, :, ::-1].copy()[:, ::-1, :, ::-1],
        "big-endian": a.astype(a.dtype.newbyteorder(">")),
        "transposed": np.ascontiguousarray(a.transpose(0, 3, 2, 1)).transpose(0, 3, 2, 1),
    }
    for name, x in cases.items():
        assert not (x.flags.c_contiguous and x.dtype.isnative), name
        np.testing.assert_array_equal(x, a)
        dst = tmp_path / f"{name}.ome.zarr"
        brickyard.from_numpy(x, dst, brick=16, shard=32, progress=False)
        s = brickyard.open(dst)
        assert s.dtype == np.float32 and s.shapes == e.shapes, name
        for level in range(s.levels):
            for c in range(2):
                np.testing.assert_array_equal(s.read(level, c), e.read(level, c), err_msg=name)
        np.testing.assert_array_equal(s.read(0, 1), a[1], err_msg=name)
