"""Random 64³ region reads from Python: brickyard.open(...).read against
zarr-python on the same brickyard store (level 0).

Usage: python scripts/bench-python-read.py [--size N] [--reads K] [--store PATH]
Writes a N³ uint16 test volume with brickyard.from_numpy unless --store is given.
Each reader reads the same K regions twice: a first pass (its own caches cold,
the OS page cache warm for both) and a second pass (its caches warm).
"""

import argparse
import os
import tempfile
import time

import numpy as np
import zarr

import brickyard


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--reads", type=int, default=200)
    ap.add_argument("--store")
    ap.add_argument("--cache", type=int, default=256 << 20)
    a = ap.parse_args()
    path = a.store
    if path is None:
        path = os.path.join(tempfile.mkdtemp(prefix="brickyard-bench-"), "bench.ome.zarr")
        n = a.size
        z, y, x = np.ogrid[:n, :n, :n]
        vol = ((np.sin(z / 9.0) + np.cos(y / 7.0) * np.sin(x / 11.0) + 2) * 12000).astype(np.uint16)
        vol += np.random.default_rng(0).integers(0, 500, vol.shape, dtype=np.uint16)
        print(brickyard.from_numpy(vol, path, progress=False))
        del vol
    store = brickyard.open(path, cache=a.cache)
    ref = zarr.open_array(f"{path}/0", mode="r")
    shape = store.shapes[0]
    rng = np.random.default_rng(1)
    regions = [tuple(slice(int(o), int(o) + 64) for o in (rng.integers(0, s - 64 + 1) for s in shape))
               for _ in range(a.reads)]
    for r in regions[:5]:
        assert np.array_equal(store.read(region=r), ref[r])
    store = brickyard.open(path, cache=a.cache)
    results = {}
    for name, read in [("brickyard", lambda r: store.read(region=r)), ("zarr-python", lambda r: ref[r])]:
        for p in ("first pass", "second pass"):
            times = []
            for r in regions:
                t = time.perf_counter()
                read(r)
                times.append(time.perf_counter() - t)
            t = np.array(times) * 1e3
            results[(name, p)] = t
            mb = a.reads * 64**3 * 2 / t.sum() * 1e3 / 2**20
            print(f"{name:12s} {p:11s}: median {np.median(t):7.2f} ms, p90 {np.percentile(t, 90):7.2f} ms, "
                  f"{mb:7.1f} MiB/s")
    print(f"store {path}: level 0 {shape} uint16, {a.reads} random 64³ regions; brickyard cache "
          f"{a.cache >> 20} MiB, {os.cpu_count()} CPUs")


if __name__ == "__main__":
    main()
