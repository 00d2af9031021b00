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


def test_reading_more_than_the_cache_stays_bounded(tmp_path):
    shape = (384, 256, 256)  # 48 MiB of uint16 (the reader's caches: 12 MiB)
    z = np.arange(shape[0], dtype=np.uint32)[:, None, None]
    y = np.arange(shape[1], dtype=np.uint32)[None, :, None]
    x = np.arange(shape[2], dtype=np.uint32)[None, None, :]
    a = ((z * 7919 + y * 104729 + x * 31) % 65521).astype(np.uint16)
    dst = tmp_path / "big.ome.zarr"
    brickyard.from_numpy(a, dst, brick=32, shard=128, progress=False)
    expected = int(a.sum(dtype=np.int64))
    volume_bytes = a.nbytes
    del a, z, y, x
    out = subprocess.run([sys.executable, "-c", READER, str(dst)], capture_output=True, text=True, check=True)
    total, base, peak, held, budget, read = map(int, out.stdout.split())
    assert total == expected, "the slabs read do not add up to the volume"
    assert read >= volume_bytes, "the whole volume was read from the store"
    assert held <= budget == 8 << 20
    growth = peak - base
    # Caches (12 MiB) + one slab (2 MiB) + slack: well under the 48 MiB
    # volume (a cache that kept every brick would grow by more than that).
    assert growth < 20 << 20, f"RSS grew by {growth / 2**20:.1f} MiB reading a {volume_bytes / 2**20:.0f} MiB volume"
