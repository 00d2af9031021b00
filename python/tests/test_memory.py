"""Reading a store larger than the host cache keeps memory bounded."""

import subprocess
import sys
import textwrap

import numpy as np

import brickyard

READER = textwrap.dedent("""
    import sys, numpy as np, brickyard

    def rss(field):
        for line in open("/proc/self/status"):
            if line.startswith(field):
                return int(line.split()[1]) * 1024

    s = brickyard.open(sys.argv[1], cache=8 << 20, chunk_cache=4 << 20, brick=32)
    depth = s.shapes[0][0]
    first = s.read(0, 0, np.s_[0:16])
    base = rss("VmRSS:")
    total = 0
    for z in range(0, depth, 16):
        total += int(s.read(0, 0, np.s_[z:z + 16]).sum(dtype=np.int64))
    stats = s.cache_stats()
    print(total, base, rss("VmHWM:"), stats["bytes"], stats["budget"], stats["bytes_read"])
""")


def _pattern_volume() -> np.ndarray:
    """48 MiB of uint16 (the readers' caches: 12 MiB), from a pattern."""
    z = np.arange(384, dtype=np.uint32)[:, None, None]
    y = np.arange(256, dtype=np.uint32)[None, :, None]
    x = np.arange(256, dtype=np.uint32)[None, None, :]
    return ((z * 7919 + y * 104729 + x * 31) % 65521).astype(np.uint16)


def test_reading_more_than_the_cache_stays_bounded(tmp_path):
    a = _pattern_volume()
    dst = tmp_path / "big.ome.zarr"
    brickyard.from_numpy(a, dst, brick=32, shard=128, progress=False)
    expected = int(a.sum(dtype=np.int64))
    volume_bytes = a.nbytes
    del a
    out = subprocess.run([sys.executable, "-c", READER, str(dst)], capture_output=True, text=True, check=True)
    total, base, peak, held, budget, read = map(int, out.stdout.split())
    assert total == expected, "the slabs read do not add up to the volume"
    assert read >= volume_bytes, "the whole volume was read from the store"
    assert held <= budget == 8 << 20
    growth = peak - base
    # Caches (12 MiB) + one slab (2 MiB) + slack: well under the 48 MiB
    # volume (a cache that kept every brick would grow by more than that).
    assert growth < 20 << 20, f"RSS grew by {growth / 2**20:.1f} MiB reading a {volume_bytes / 2**20:.0f} MiB volume"


STEPPED = textwrap.dedent("""
    import sys, numpy as np, brickyard

    def rss(field):
        for line in open("/proc/self/status"):
            if line.startswith(field):
                return int(line.split()[1]) * 1024

    brickyard._PIECE = 4 << 20
    s = brickyard.open(sys.argv[1], cache=8 << 20, chunk_cache=4 << 20, brick=32)
    s.read(0, 0, np.s_[0:16])
    base = rss("VmRSS:")
    a = s[::8]
    b = s[::-5, ::4, 1::3]
    print(a.nbytes, b.nbytes, rss("VmHWM:") - base, int(a.sum(dtype=np.int64)), int(b.sum(dtype=np.int64)))
""")


def test_reads_with_steps_hold_a_piece_of_the_box_not_all_of_it(tmp_path):
    """`store[::8]` read the whole box its steps span (all 48 MiB here) to
    keep an eighth of it; it now reads pieces of the box (4 MiB here)."""
    a = _pattern_volume()
    dst = tmp_path / "big.ome.zarr"
    brickyard.from_numpy(a, dst, brick=32, shard=128, progress=False)
    want_a, want_b = a[::8], a[::-5, ::4, 1::3]
    out = subprocess.run([sys.executable, "-c", STEPPED, str(dst)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    na, nb, growth, sa, sb = map(int, out.stdout.split())
    assert (na, nb) == (want_a.nbytes, want_b.nbytes)
    assert (sa, sb) == (int(want_a.sum(dtype=np.int64)), int(want_b.sum(dtype=np.int64)))
    # Caches (12 MiB) + a piece (4 MiB) + the results (9 MiB) + slack,
    # against the 48 MiB box.
    assert growth < 34 << 20, f"RSS grew by {growth / 2**20:.1f} MiB reading steps of a {a.nbytes >> 20} MiB volume"


WRITER = textwrap.dedent("""
    import sys, numpy as np, brickyard

    def rss(field):
        for line in open("/proc/self/status"):
            if line.startswith(field):
                return int(line.split()[1]) * 1024

    def reset_peak():
        # The peak so far is forgotten (Linux: 5 > clear_refs), so that
        # VmHWM is the peak of what follows.
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")

    def check(a, dst):
        s = brickyard.open(dst, cache=8 << 20, chunk_cache=4 << 20)
        assert s.shape == a.shape and s.dtype == a.dtype, (s.shape, s.dtype)
        for z in range(0, a.shape[0], 32):
            np.testing.assert_array_equal(s.read(0, 0, np.s_[z:z + 32]), a[z:z + 32])

    # 256 MiB of uint16, written a plane at a time (no temporary of its size).
    a = np.empty((128, 1024, 1024), np.uint16)
    plane = np.arange(1024 * 1024, dtype=np.uint32).reshape(1024, 1024)
    for z in range(a.shape[0]):
        a[z] = (plane * 31 + z * 7919) % 65521
    del plane
    out = []
    # A C-contiguous array, and a view that is not (every other column of
    # a 256 MiB array, byte-swapped: 128 MiB read through that view).
    b = a.view(a.dtype.newbyteorder()).reshape(128, 1024, 1024)[:, :, ::2]
    for name, x in [("contiguous", a), ("strided", b)]:
        reset_peak()
        base = rss("VmRSS:")
        brickyard.from_numpy(x, sys.argv[1] + "/" + name + ".ome.zarr", brick=32, shard=128, memory=64 << 20,
                             progress=False)
        out.append(rss("VmHWM:") - base)
        check(x.astype(x.dtype.newbyteorder("=")) if name == "strided" else x, sys.argv[1] + "/" + name + ".ome.zarr")
    print(a.nbytes, b.nbytes, *out)
""")


def test_from_numpy_does_not_copy_the_array(tmp_path):
    # The array was copied whole (`tobytes`) before the conversion: the
    # peak was twice the array. The builder's own memory is 64 MiB here.
    out = subprocess.run([sys.executable, "-c", WRITER, str(tmp_path)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    nbytes, view_bytes, growth, view_growth = map(int, out.stdout.split())
    assert nbytes == 256 << 20 and view_bytes == 128 << 20
    assert growth < nbytes // 2, f"RSS grew by {growth / 2**20:.0f} MiB converting a {nbytes >> 20} MiB array"
    assert view_growth < view_bytes // 2, (
        f"RSS grew by {view_growth / 2**20:.0f} MiB converting a {view_bytes >> 20} MiB strided view")
