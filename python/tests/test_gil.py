"""The GIL is released while brickyard reads: Python keeps running beside it."""

import threading
import time

import numpy as np

import brickyard


def test_read_releases_the_gil(tmp_path):
    a = (np.arange(256 * 256 * 256, dtype=np.uint32) % 65521).astype(np.uint16).reshape(256, 256, 256)
    dst = tmp_path / "gil.ome.zarr"
    brickyard.from_numpy(a, dst, brick=32, shard=128, compression="zstd", progress=False)
    # A small cache and brick: the whole-volume read decodes every brick.
    s = brickyard.open(dst, brick=16, cache=1 << 20, threads=1)
    done = threading.Event()
    result = {}

    def read():
        t = time.perf_counter()
        result["a"] = s.read(0)
        result["seconds"] = time.perf_counter() - t
        done.set()

    th = threading.Thread(target=read)
    th.start()
    gaps, last = [], time.perf_counter()
    while not done.is_set():
        sum(range(200))
        now = time.perf_counter()
        gaps.append(now - last)
        last = now
    th.join()
    np.testing.assert_array_equal(result["a"], a)
    assert result["seconds"] > 0.1, "the read was too short to tell"
    # With the GIL held for the whole call, this loop would stall for all of it.
    assert max(gaps) < 0.5 * result["seconds"], (max(gaps), result["seconds"])
    assert len(gaps) > 100
