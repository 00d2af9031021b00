"""Read a region, render a view and save it as a PNG.

    pip install ./python
    python python/examples/quickstart.py [STORE.ome.zarr] [OUT.png]

Without a store, a 96³ test volume is written first (brickyard.from_numpy) and
processed (brickyard.process, gauss(1.5)|sobel into its derived/edges); a store
given is only read.
"""

import os
import sys
import tempfile

import numpy as np

import brickyard


def main() -> None:
    generated = len(sys.argv) <= 1
    if not generated:
        path = sys.argv[1]
    else:
        path = os.path.join(tempfile.mkdtemp(prefix="brickyard-example-"), "blob.ome.zarr")
        z, y, x = np.mgrid[-1:1:96j, -1:1:96j, -1:1:96j]
        blob = np.exp(-4 * (x**2 + y**2 + z**2)) * (1 + 0.3 * np.sin(12 * x) * np.cos(9 * y))
        print(brickyard.from_numpy((blob * 1000).astype(np.uint16), path, spacing=(1.0, 1.0, 1.0), progress=False))
    out = sys.argv[2] if len(sys.argv) > 2 else "brickyard-example.png"

    store = brickyard.open(path)
    print(store)
    for level, (shape, scale) in enumerate(zip(store.shapes, store.scales)):
        print(f"  level {level}: {shape}, scale {scale}")

    # Any region, through the loader and host cache (never the whole volume).
    z0 = store.shapes[0][0] // 2
    block = store.read(level=0, region=np.s_[z0:z0 + 16, 0:64, 0:64])
    print(f"region {block.shape} {block.dtype}: min {block.min()}, max {block.max()}, mean {block.mean():.1f}")
    coarse = store.level(store.levels - 1)[...]
    print(f"coarsest level {coarse.shape}: mean {coarse.mean():.1f}")

    if generated:
        # What `brickyard process STORE "gauss(1.5)|sobel" --out edges` writes.
        edges = brickyard.process(store, "gauss(1.5)|sobel", out="edges", progress=False)
        print(f"{edges}: max gradient {edges.read(0).max():.1f}")

    # The same image `brickyard render STORE --mode dvr --tf hot --out OUT`
    # writes: returned as an array, and written as the PNG (`out`), with
    # nothing besides the package installed.
    rgba = brickyard.render(store, mode="dvr", tf="hot", size=(384, 384), azimuth=35, elevation=25,
                            out=out)
    print(f"wrote {out}: {rgba.shape} {rgba.dtype}, {int((rgba[..., :3].max(axis=-1) > 0).sum())} pixels lit")


if __name__ == "__main__":
    main()
