#!/usr/bin/env python3
"""tensorstore's reads of level 0 of an OME-Zarr store, for scripts/bench-loader.sh.

Prints one JSON line per mode:
  chunk    one read per inner chunk, each waited for before the next
  batched  one read per inner chunk, all in flight at once (ts.Batch)
  whole    the whole level in one read
GB/s is bytes of level 0 (decoded voxels) per second. No cache pool, so every
run decodes every chunk; `--cold` drops the store's files from the page cache
before each mode (posix_fadvise DONTNEED, no root needed).

usage: bench-loader-ts.py STORE [--modes chunk,batched,whole] [--cold] [--threads N]
"""

import argparse
import json
import os
import sys
import time

import numpy as np
import tensorstore as ts

try:
    from importlib.metadata import version

    TS_VERSION = version("tensorstore")
except Exception:  # noqa: BLE001
    TS_VERSION = "?"


def drop_from_page_cache(root):
    """posix_fadvise(DONTNEED) every file under root; returns bytes dropped."""
    n = 0
    for d, _, files in os.walk(root):
        for f in files:
            p = os.path.join(d, f)
            fd = os.open(p, os.O_RDONLY)
            try:
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
                n += os.fstat(fd).st_size
            finally:
                os.close(fd)
    return n


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("store")
    ap.add_argument("--modes", default="chunk,batched,whole")
    ap.add_argument("--cold", action="store_true")
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    a = ap.parse_args()
    level = os.path.join(a.store, "0")
    meta = json.load(open(os.path.join(level, "zarr.json")))
    inner = meta["chunk_grid"]["configuration"]["chunk_shape"]
    for c in meta.get("codecs", []):
        if c["name"] == "sharding_indexed":
            inner = c["configuration"]["chunk_shape"]
    spec = {
        "driver": "zarr3",
        "kvstore": {"driver": "file", "path": level},
        "context": {
            "cache_pool": {"total_bytes_limit": 0},
            "data_copy_concurrency": {"limit": a.threads},
            "file_io_concurrency": {"limit": a.threads},
        },
    }
    arr = ts.open(spec, read=True).result()
    shape = list(arr.shape)
    nbytes = int(np.prod(shape)) * arr.dtype.numpy_dtype.itemsize
    boxes = []
    for z in range(0, shape[-3], inner[-3]):
        for y in range(0, shape[-2], inner[-2]):
            for x in range(0, shape[-1], inner[-1]):
                boxes.append((slice(z, min(z + inner[-3], shape[-3])),
                              slice(y, min(y + inner[-2], shape[-2])),
                              slice(x, min(x + inner[-1], shape[-1]))))
    for mode in a.modes.split(","):
        if a.cold:
            drop_from_page_cache(a.store)
        arr = ts.open(spec, read=True).result()
        t = time.perf_counter()
        if mode == "chunk":
            for b in boxes:
                arr[b].read().result()
        elif mode == "batched":
            with ts.Batch() as batch:
                futs = [arr[b].read(batch=batch) for b in boxes]
            for f in futs:
                f.result()
        elif mode == "whole":
            arr.read().result()
        else:
            sys.exit(f"unknown mode {mode}")
        s = time.perf_counter() - t
        print(json.dumps({"reader": f"tensorstore {TS_VERSION}", "mode": mode, "cold": a.cold,
                          "threads": a.threads, "chunks": len(boxes), "bytes": nbytes,
                          "seconds": round(s, 4), "gb_s": round(nbytes / 1e9 / s, 3)}), flush=True)


if __name__ == "__main__":
    main()
