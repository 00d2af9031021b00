"""Random 64³ region reads from Python on one brickyard store (level 0), in one run:
brickyard.open(...).read against tensorstore and zarr-python, and the bindings'
overhead: the same reads through the native loader without Python.

Usage: python scripts/bench-python-read.py [--size N] [--reads K] [--store PATH]
           [--cache BYTES] [--native PATH/TO/read_regions] [--readers LIST]

Requirements: the repo venv (scripts/setup-python.sh) with the wheel of
scripts/python-bindings.sh, plus `pip install tensorstore` (not in the CI
requirements: a 66 MB wheel; tensorstore 0.1.86 was measured). Without
tensorstore that reader is left out and said so.

--native: the example python/examples/read_regions.rs (brickyard's loader and the
extension's own read_region, no Python), built with the flags maturin uses:
    PYO3_BUILD_EXTENSION_MODULE=1 PYO3_PYTHON=$PWD/.venv/bin/python \\
      cargo build --release --manifest-path python/Cargo.toml \\
      --features pyo3/extension-module --example read_regions
    --native $CARGO_TARGET_DIR/release/examples/read_regions

Writes a N³ uint16 test volume with brickyard.from_numpy unless --store is given.
Each reader opens the store afresh and reads the same K regions twice: a first
pass (its own caches cold, the OS page cache warm for all) and a second pass
(its caches warm). brickyard and tensorstore get the same cache budget.
"""

import argparse
import os
import subprocess
import tempfile
import time

import numpy as np
import zarr

import brickyard

THREADS = min(8, os.cpu_count() or 1)  # brickyard.open's default


def checksum(a):
    return int(np.frombuffer(np.ascontiguousarray(a).tobytes(), dtype=np.uint8).sum(dtype=np.uint64))


def timed(read, regions):
    times = []
    for r in regions:
        t = time.perf_counter()
        read(r)
        times.append(time.perf_counter() - t)
    return np.array(times) * 1e3


def native(exe, path, regions, cache, passes, want):
    """The reads through read_regions (no Python): per-pass times in ms."""
    with tempfile.NamedTemporaryFile("w", suffix=".txt", prefix="py2-regions-", delete=False) as f:
        for r in regions:
            f.write(" ".join(str(s.start) for s in r) + " " + " ".join(str(s.stop) for s in r) + "\n")
    try:
        out = subprocess.run([exe, path, f.name, str(cache), str(64 << 20), "64", str(THREADS), str(passes)],
                             check=True, capture_output=True, text=True).stdout
    finally:
        os.unlink(f.name)
    times = [[] for _ in range(passes)]
    for line in out.splitlines():
        p, i, ms, s = line.split()
        if int(s) != want[int(i)]:
            raise SystemExit(f"read_regions: region {i} has checksum {s}, Python read {want[int(i)]}")
        times[int(p)].append(float(ms))
    return [np.array(t) for t in times]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--reads", type=int, default=200)
    ap.add_argument("--store")
    ap.add_argument("--cache", type=int, default=256 << 20)
    ap.add_argument("--native", help="the read_regions example binary (see the docstring)")
    ap.add_argument("--readers", default="brickyard,native,tensorstore,zarr-python")
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
    dtype = store.dtype
    rng = np.random.default_rng(1)
    regions = [tuple(slice(int(o), int(o) + 64) for o in (rng.integers(0, s - 64 + 1) for s in shape))
               for _ in range(a.reads)]
    want = [checksum(ref[r]) for r in regions]
    for r, w in list(zip(regions, want))[:5]:
        assert checksum(store.read(region=r)) == w

    readers = a.readers.split(",")
    passes = ("first pass", "second pass")
    results = {}

    def report(name, p, t):
        results[(name, p)] = t
        mb = len(t) * 64**3 * dtype.itemsize / t.sum() * 1e3 / 2**20
        print(f"{name:12s} {p:11s}: median {np.median(t):7.3f} ms, p90 {np.percentile(t, 90):7.3f} ms, "
              f"{mb:8.1f} MiB/s", flush=True)

    for name in readers:
        if name == "brickyard":
            s = brickyard.open(path, cache=a.cache)
            read = lambda r: s.read(region=r)  # noqa: E731
        elif name == "native":
            if not a.native:
                print("native      : left out (no --native binary given)")
                continue
            for p, t in zip(passes, native(a.native, path, regions, a.cache, 2, want)):
                report(name, p, t)
            continue
        elif name == "tensorstore":
            try:
                import tensorstore as ts
            except ImportError:
                print("tensorstore : left out (not installed: pip install tensorstore)")
                continue
            spec = {"driver": "zarr3", "kvstore": {"driver": "file", "path": f"{path}/0"},
                    "context": {"cache_pool": {"total_bytes_limit": a.cache},
                                "data_copy_concurrency": {"limit": THREADS},
                                "file_io_concurrency": {"limit": THREADS}},
                    "recheck_cached_data": False}
            t_arr = ts.open(spec, read=True).result()
            for r, w in list(zip(regions, want))[:5]:
                assert checksum(t_arr[r].read().result()) == w, "tensorstore reads other voxels"
            t_arr = ts.open(spec, read=True).result()
            read = lambda r: t_arr[r].read().result()  # noqa: E731
        elif name == "zarr-python":
            z = zarr.open_array(f"{path}/0", mode="r")
            read = lambda r: z[r]  # noqa: E731
        else:
            raise SystemExit(f"--readers: unknown reader {name!r}")
        for p in passes:
            report(name, p, timed(read, regions))

    print(f"store {path}: level 0 {shape} {dtype}, {a.reads} random 64³ regions; cache {a.cache >> 20} MiB "
          f"(brickyard host cache, tensorstore cache_pool), {THREADS} threads, {os.cpu_count()} CPUs")
    base = "zarr-python"
    for p in passes:
        if (base, p) not in results:
            continue
        b = np.median(results[(base, p)])
        line = ", ".join(f"{n} {b / np.median(results[(n, q)]):.2f}×" for (n, q) in results if q == p and n != base)
        print(f"{p}: median speed vs zarr-python: {line}")
        if ("brickyard", p) in results and ("native", p) in results:
            d = np.median(results[("brickyard", p)]) - np.median(results[("native", p)])
            print(f"{p}: binding overhead (median brickyard - median native): {d * 1e3:.0f} µs per read "
                  f"({np.median(results[('brickyard', p)]) / np.median(results[('native', p)]):.2f}×)")


if __name__ == "__main__":
    main()
