#!/usr/bin/env python3
"""Baseline for benchmarks: the raw -> OME-Zarr pyramid conversion done with ome-zarr-py.

Usage:
    bench-python-convert.py RAWFILE --dims X Y Z --dtype u8 --out DIR
                            [--endian little|big] [--header-bytes N]
                            [--chunk 64] [--shard 256] [--brick 64]
                            [--method local_mean|nearest|resize]

What it does (the closest ome-zarr-py equivalent of `brickyard convert`):
  * maps RAWFILE with numpy.memmap ((z, y, x), x fastest), wraps it in a dask
    array (no full read into memory up front);
  * ome_zarr.writer.write_image(fmt=FormatV05()) -> OME-Zarr 0.5 / Zarr v3,
    axes z, y, x (unit micrometer, scale 1), every level sharded:
    inner chunks 64^3 in 256^3 shards (storage_options chunks/shards per
    level; on levels smaller than a shard the shard shrinks to the level
    size rounded up to whole chunks), codecs bytes + blosc lz4 shuffle;
  * pyramid levels: all three axes halved per level (cumulative
    scale_factors 2, 4, 8, ...) until the coarsest level fits in one
    --brick (64^3) brick, as brickyard does for isotropic input;
  * downsampling: Methods.LOCAL_MEAN (skimage.transform.downscale_local_mean
    per dask block, cast back to the input dtype: truncates instead of
    rounding, and ome-zarr-py floors odd sizes (s // 2), unlike brickyard's
    ceil + edge-aware mean). So output values and the last row of odd-sized
    levels differ from brickyard; it is a speed / memory baseline only.
  * dask's default threaded scheduler (all cores).

Prints one JSON line:
  {"tool": "ome-zarr-py", "wall_s": ..., "peak_rss_mb": ..., "levels": N, ...}
peak_rss_mb is resource.getrusage(RUSAGE_SELF).ru_maxrss (KiB on Linux) / 1024.
"""
from __future__ import annotations

import argparse
import json
import resource
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np

DTYPES = {"u8": "u1", "i8": "i1", "u16": "u2", "i16": "i2", "u32": "u4", "i32": "i4",
          "f32": "f4", "f64": "f8"}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("raw", type=Path)
    ap.add_argument("--dims", type=int, nargs=3, metavar=("X", "Y", "Z"), required=True)
    ap.add_argument("--dtype", required=True, choices=sorted(DTYPES))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--endian", choices=["little", "big"], default="little")
    ap.add_argument("--header-bytes", type=int, default=0)
    ap.add_argument("--chunk", type=int, default=64)
    ap.add_argument("--shard", type=int, default=256)
    ap.add_argument("--brick", type=int, default=64, help="stop when the coarsest level fits in brick^3")
    ap.add_argument("--method", default="local_mean", choices=["local_mean", "nearest", "resize"])
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    import dask.array as da
    import zarr
    from ome_zarr.format import FormatV05
    from ome_zarr.scale import Methods
    from ome_zarr.writer import write_image
    from zarr.codecs import BloscCodec

    x, y, z = args.dims
    dt = np.dtype(("<" if args.endian == "little" else ">") + DTYPES[args.dtype])
    mm = np.memmap(args.raw, dtype=dt, mode="r", offset=args.header_bytes, shape=(z, y, x))
    # dask blocks of whole shards keep memory bounded and match the shard grid
    image = da.from_array(mm, chunks=(args.shard,) * 3)
    if dt.byteorder == ">":
        image = image.astype(dt.newbyteorder("="))

    factors = []
    f = 1
    while any(-(-n // f) > args.brick for n in (z, y, x)):
        f *= 2
        factors.append({"z": f, "y": f, "x": f})

    out = args.out
    if out.exists():
        shutil.rmtree(out)

    def opts(shape):
        # per level: chunk^3 inner chunks; shard^3 shards, shrunk (in whole
        # chunks) to cover small levels, as brickyard does not write empty space
        ch = (args.chunk,) * 3
        sh = tuple(min(-(-s // args.chunk), -(-args.shard // args.chunk)) * args.chunk for s in shape)
        return {"chunks": ch, "shards": sh,
                "compressors": [BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")]}

    shapes = [(z, y, x)]
    for fac in factors:
        f = fac["z"]
        shapes.append(tuple(max(1, n // f) for n in (z, y, x)))

    grp = zarr.open_group(str(out), mode="w", zarr_format=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_image(
            image, grp, fmt=FormatV05(), axes="zyx",
            scale={"z": 1.0, "y": 1.0, "x": 1.0},
            axes_units={"z": "micrometer", "y": "micrometer", "x": "micrometer"},
            scale_factors=factors,
            method=Methods(args.method),
            storage_options=[opts(s) for s in shapes],
        )
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps({"tool": "ome-zarr-py", "wall_s": round(wall, 3), "peak_rss_mb": round(peak, 1),
                      "levels": len(shapes), "shapes": shapes, "method": args.method,
                      "out": str(out)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
