#!/usr/bin/env python3
"""Write the non-Zarr test inputs used by run.sh (raw variants, NRRD, NIfTI, TIFF).

Usage: make_inputs.py OUTDIR

Files (dims are x,y,z; numpy arrays are ((c,) z, y, x)):
  be_i16_2ch.raw        i16, big-endian, 128-byte header of 'H', 2 planar channels,
                        37x29x21 (no sidecar: run.sh passes flags, spacing 1,1,3)
  f32.raw + .json       f32 little, 40x33x17, sidecar spacing [0.5,0.5,0.5]
  ties_u16.raw + .json  u16 labels in 0..3 (many ties), 45x38x27
  vol.nrrd  + vol_nrrd.npy   int16 big-endian gzip NRRD, 33x28x19, spacings 0.8 0.8 2.0
  vol.nii   + vol_nii.npy    NIfTI-1 (.nii) uint16, 30x26x22, pixdim 1.5 1.5 1.5
  vol.tif   + vol_tif.npy    multi-page (z-stack) uint8 TIFF, 35x27x15 (tifffile)
  vol_f16.tif + vol_f16_tif.npy  float16 TIFF, 17x21x9, strips of 5 rows (tifffile);
                        the .npy holds the expected float32 values
"""
from __future__ import annotations

import gzip
import json
import struct
import sys
from pathlib import Path

import numpy as np


def sidecar(path: Path, dims, dtype, spacing, channels=1, endian="little", header=0):
    Path(f"{path}.json").write_text(json.dumps({
        "dims": list(dims), "dtype": dtype, "endian": endian, "spacing": list(spacing),
        "channels": channels, "header_bytes": header}) + "\n")


def write_nifti(path: Path, data_zyx: np.ndarray, pixdim_xyz):
    code = {np.dtype(np.uint8): 2, np.dtype(np.int16): 4, np.dtype(np.int32): 8,
            np.dtype(np.float32): 16, np.dtype(np.float64): 64, np.dtype(np.int8): 256,
            np.dtype(np.uint16): 512, np.dtype(np.uint32): 768}[data_zyx.dtype]
    z, y, x = data_zyx.shape
    hdr = bytearray(348)
    struct.pack_into("<i", hdr, 0, 348)
    struct.pack_into("<8h", hdr, 40, 3, x, y, z, 1, 1, 1, 1)
    struct.pack_into("<hhh", hdr, 70, code, data_zyx.dtype.itemsize * 8, 0)
    struct.pack_into("<8f", hdr, 76, 1.0, *pixdim_xyz, 1.0, 1.0, 1.0, 1.0)
    struct.pack_into("<f", hdr, 108, 352.0)          # vox_offset
    struct.pack_into("<ff", hdr, 112, 0.0, 0.0)      # scl_slope 0 = no scaling
    hdr[123] = 3                                     # xyzt_units: micrometer
    hdr[148:148 + 20] = b"brickyard interop\0\0\0"
    struct.pack_into("<hh", hdr, 252, 0, 0)          # qform_code, sform_code
    hdr[344:348] = b"n+1\0"
    with open(path, "wb") as f:
        f.write(hdr)
        f.write(b"\0\0\0\0")                         # no extensions
        f.write(data_zyx.astype(data_zyx.dtype.newbyteorder("<")).tobytes())


def main(argv):
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    out = Path(argv[1])
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(2024)

    # 1. big-endian i16, 2 planar channels, 128-byte header
    a = rng.integers(-32768, 32767, size=(2, 21, 29, 37), endpoint=True).astype(np.int16)
    with open(out / "be_i16_2ch.raw", "wb") as f:
        f.write(b"H" * 128)
        f.write(a.astype(">i2").tobytes())

    # 2. float32 with sidecar
    z, y, x = np.meshgrid(np.arange(17), np.arange(33), np.arange(40), indexing="ij")
    f = (np.sin(x / 4.0) * np.cos(y / 6.0) * 1000.0 + z * 0.1
         + rng.standard_normal((17, 33, 40))).astype(np.float32)
    f.tofile(out / "f32.raw")
    sidecar(out / "f32.raw", (40, 33, 17), "f32", (0.5, 0.5, 0.5))

    # 3. labels with many ties
    lab = rng.integers(0, 4, size=(27, 38, 45)).astype(np.uint16)
    lab[:, :10, :10] = 3           # a homogeneous region
    lab.astype("<u2").tofile(out / "ties_u16.raw")
    sidecar(out / "ties_u16.raw", (45, 38, 27), "u16", (1, 1, 1))

    # 4. NRRD, int16 big-endian gzip
    n = rng.integers(-3000, 3000, size=(19, 28, 33)).astype(np.int16)
    hdr = ("NRRD0004\n# brickyard interop\ntype: int16\ndimension: 3\nsizes: 33 28 19\n"
           "spacings: 0.8 0.8 2.0\nendian: big\nencoding: gzip\n\n")
    with open(out / "vol.nrrd", "wb") as fh:
        fh.write(hdr.encode("ascii"))
        fh.write(gzip.compress(n.astype(">i2").tobytes()))
    np.save(out / "vol_nrrd.npy", n)

    # 5. NIfTI-1 uint16
    v = rng.integers(0, 65535, size=(22, 26, 30), endpoint=True).astype(np.uint16)
    write_nifti(out / "vol.nii", v, (1.5, 1.5, 1.5))
    np.save(out / "vol_nii.npy", v)

    # 6. multi-page TIFF uint8
    t = rng.integers(0, 255, size=(15, 27, 35), endpoint=True).astype(np.uint8)
    try:
        import tifffile
        tifffile.imwrite(out / "vol.tif", t)
        np.save(out / "vol_tif.npy", t)
        # float16 with infinities, NaN and subnormals: read as float32, exactly
        h = (rng.standard_normal(size=(9, 21, 17)) * 300).astype(np.float16)
        h.flat[:6] = [np.inf, -np.inf, np.nan, 6e-8, -0.0, 65504]
        tifffile.imwrite(out / "vol_f16.tif", h, rowsperstrip=5)
        np.save(out / "vol_f16_tif.npy", h.astype(np.float32))
    except ImportError:
        print("make_inputs: tifffile not installed, no TIFF written", file=sys.stderr)

    for p in sorted(out.iterdir()):
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
