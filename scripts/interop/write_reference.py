#!/usr/bin/env python3
"""Write reference input stores made by the Python ecosystem, for brickyard to read.

Usage: write_reference.py OUTDIR

For every case NAME it writes
    OUTDIR/NAME.zarr   the store (input for `brickyard convert`)
    OUTDIR/NAME.npy    the expected level-0 data, shape ((c,) z, y, x), native byte order
    OUTDIR/NAME.json   {"name", "description", "dtype", "shape", "channels",
                        "spacing_xyz" (expected level-0 spacing after conversion),
                        "unit" (or null)}
and prints the store paths, one per line, on stdout.

Cases
  ome04_v2_u16      OME-Zarr 0.4 / Zarr v2 pyramid written by ome-zarr-py
                    (write_image, fmt=FormatV04(), Blosc lz4 compressor,
                    chunks 16^3, "/" dimension separator), 70x45x33 u16
                    (x,y,z), spacing x,y,z = 0.5, 0.5, 1.25 micrometer,
                    dataset paths s0, s1, s2 (nearest-neighbour levels).
  v3_plain_u16      plain Zarr v3 array (no OME metadata, no sharding),
                    chunks x,y,z = 16x20x7, zstd.
  v3_sharded_u16    plain Zarr v3 array, sharding_indexed: shards x,y,z
                    32x24x16, inner chunks 8^3, blosc zstd + bitshuffle.
  ome05_2ch_u8      (extra) OME-Zarr 0.5 written by ome-zarr-py, axes c,z,y,x
                    with 2 channels, sharded (1,16,16,16) in (1,32,32,32).
  v3_f32_be         (extra) plain Zarr v3 float32 array with bytes(endian=big)
                    and gzip, 29x23x17.
  v2_i16_be_F       (extra) plain Zarr v2 array, dtype >i2, order F, Blosc
                    zstd, 31x26x19.
"""
from __future__ import annotations

import json
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np


def volume(shape_zyx, dtype, seed):
    """Deterministic, smooth-plus-noise volume spanning most of the dtype range."""
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*[np.arange(n, dtype=np.float64) for n in shape_zyx], indexing="ij")
    smooth = (np.sin(x / 5.0) + np.cos(y / 7.0) * np.sin(z / 3.0) + 2.0) / 4.0  # 0..1
    noise = rng.random(shape_zyx)
    v = 0.8 * smooth + 0.2 * noise
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return ((v - 0.5) * 2000.0).astype(dt)
    info = np.iinfo(dt)
    out = info.min + np.floor(v * (float(info.max) - float(info.min))).astype(np.int64)
    out = np.clip(out, info.min, info.max).astype(dt)
    # sprinkle extreme values (tests range handling / signedness)
    flat = out.reshape(-1)
    idx = rng.choice(flat.size, size=max(1, flat.size // 500), replace=False)
    flat[idx[0::2]] = info.max
    flat[idx[1::2]] = info.min
    return out


def save_meta(outdir: Path, name: str, data: np.ndarray, description: str,
              spacing_xyz, unit, channels: int):
    np.save(outdir / f"{name}.npy", np.ascontiguousarray(data.astype(data.dtype.newbyteorder("="))))
    meta = {
        "name": name,
        "description": description,
        "dtype": np.dtype(data.dtype).newbyteorder("=").name,
        "shape": list(data.shape),
        "channels": channels,
        "spacing_xyz": spacing_xyz,
        "unit": unit,
    }
    (outdir / f"{name}.json").write_text(json.dumps(meta, indent=1) + "\n")
    print(outdir / f"{name}.zarr", flush=True)


def fresh(p: Path) -> Path:
    if p.exists():
        shutil.rmtree(p)
    return p


def write_ome04_v2(outdir: Path):
    import zarr
    from numcodecs import Blosc
    from ome_zarr.format import FormatV04
    from ome_zarr.scale import Methods
    from ome_zarr.writer import write_image

    name = "ome04_v2_u16"
    data = volume((33, 45, 70), np.uint16, seed=1)
    store = fresh(outdir / f"{name}.zarr")
    grp = zarr.open_group(str(store), mode="w", zarr_format=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_image(
            data, grp, fmt=FormatV04(), axes="zyx",
            scale={"z": 1.25, "y": 0.5, "x": 0.5},
            axes_units={"z": "micrometer", "y": "micrometer", "x": "micrometer"},
            scale_factors=[{"y": 2, "x": 2}, {"z": 2, "y": 4, "x": 4}],
            method=Methods.NEAREST,
            storage_options={"chunks": (16, 16, 16),
                             "compressor": Blosc(cname="lz4", clevel=5, shuffle=Blosc.SHUFFLE)},
        )
    # sanity: it really is v2 / OME 0.4
    assert (store / ".zgroup").is_file(), "ome-zarr-py did not write a Zarr v2 group"
    attrs = json.loads((store / ".zattrs").read_text())
    assert attrs["multiscales"][0].get("version") == "0.4", attrs
    p0 = attrs["multiscales"][0]["datasets"][0]["path"]
    back = zarr.open_array(str(store / p0), mode="r", zarr_format=2)[...]
    assert np.array_equal(back, data)
    save_meta(outdir, name, data,
              "OME-Zarr 0.4 / Zarr v2 written by ome-zarr-py (Blosc lz4, chunks 16^3)",
              [0.5, 0.5, 1.25], "micrometer", 1)


def write_v3_plain(outdir: Path):
    import zarr
    from zarr.codecs import ZstdCodec

    name = "v3_plain_u16"
    data = volume((33, 45, 70), np.uint16, seed=2)
    store = fresh(outdir / f"{name}.zarr")
    arr = zarr.create_array(str(store), shape=data.shape, dtype=data.dtype,
                            chunks=(7, 20, 16), compressors=[ZstdCodec(level=3)],
                            zarr_format=3, fill_value=0, dimension_names=["z", "y", "x"])
    arr[...] = data
    save_meta(outdir, name, data, "plain Zarr v3 array, chunks x,y,z=16x20x7, zstd",
              [1.0, 1.0, 1.0], None, 1)


def write_v3_sharded(outdir: Path):
    import zarr
    from zarr.codecs import BloscCodec

    name = "v3_sharded_u16"
    data = volume((33, 45, 70), np.uint16, seed=3)
    store = fresh(outdir / f"{name}.zarr")
    arr = zarr.create_array(str(store), shape=data.shape, dtype=data.dtype,
                            chunks=(8, 8, 8), shards=(16, 24, 32),
                            compressors=[BloscCodec(cname="zstd", clevel=3, shuffle="bitshuffle")],
                            zarr_format=3, fill_value=0)
    arr[...] = data
    meta = json.loads((store / "zarr.json").read_text())
    assert meta["codecs"][0]["name"] == "sharding_indexed", meta["codecs"]
    save_meta(outdir, name, data,
              "plain Zarr v3 sharded array (shards x,y,z=32x24x16, inner 8^3, blosc zstd)",
              [1.0, 1.0, 1.0], None, 1)


def write_ome05_2ch(outdir: Path):
    import zarr
    from zarr.codecs import BloscCodec
    from ome_zarr.format import FormatV05
    from ome_zarr.scale import Methods
    from ome_zarr.writer import write_image

    name = "ome05_2ch_u8"
    data = np.stack([volume((21, 30, 41), np.uint8, seed=4),
                     volume((21, 30, 41), np.uint8, seed=5)[::-1].copy()])
    store = fresh(outdir / f"{name}.zarr")
    grp = zarr.open_group(str(store), mode="w", zarr_format=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        write_image(
            data, grp, fmt=FormatV05(), axes="czyx",
            scale={"c": 1.0, "z": 2.0, "y": 1.0, "x": 1.0},
            axes_units={"z": "micrometer", "y": "micrometer", "x": "micrometer"},
            scale_factors=[{"y": 2, "x": 2}],
            method=Methods.NEAREST,
            storage_options={"chunks": (1, 16, 16, 16), "shards": (1, 32, 32, 32),
                             "compressors": [BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")]},
        )
    save_meta(outdir, name, data,
              "OME-Zarr 0.5 written by ome-zarr-py, 2 channels (czyx), sharded",
              [1.0, 1.0, 2.0], "micrometer", 2)


def write_v3_f32_be(outdir: Path):
    import zarr
    from zarr.codecs import BytesCodec, GzipCodec

    name = "v3_f32_be"
    data = volume((17, 23, 29), np.float32, seed=6)
    store = fresh(outdir / f"{name}.zarr")
    arr = zarr.create_array(str(store), shape=data.shape, dtype=data.dtype, chunks=(8, 8, 8),
                            serializer=BytesCodec(endian="big"), compressors=[GzipCodec(level=5)],
                            zarr_format=3, fill_value=0.0)
    arr[...] = data
    save_meta(outdir, name, data, "plain Zarr v3 float32, bytes(endian=big) + gzip",
              [1.0, 1.0, 1.0], None, 1)


def write_v2_i16_be_F(outdir: Path):
    import zarr
    from numcodecs import Blosc

    name = "v2_i16_be_F"
    data = volume((19, 26, 31), np.int16, seed=7)
    store = fresh(outdir / f"{name}.zarr")
    arr = zarr.create_array(str(store), shape=data.shape, dtype=">i2", chunks=(8, 10, 12),
                            compressors=Blosc(cname="zstd", clevel=3, shuffle=Blosc.SHUFFLE),
                            zarr_format=2, order="F", fill_value=0)
    arr[...] = data
    zm = json.loads((store / ".zarray").read_text())
    assert zm["order"] == "F" and zm["dtype"] == ">i2", zm
    save_meta(outdir, name, data, "plain Zarr v2 array, >i2, order F, Blosc zstd",
              [1.0, 1.0, 1.0], None, 1)


def write_v2_u16_zlib(outdir: Path):
    import zarr
    from numcodecs import Zlib

    name = "v2_u16_zlib"
    data = volume((17, 23, 29), np.uint16, seed=11)
    store = fresh(outdir / f"{name}.zarr")
    arr = zarr.create_array(str(store), shape=data.shape, dtype="<u2", chunks=(9, 11, 13),
                            compressors=Zlib(level=6), zarr_format=2, fill_value=0)
    arr[...] = data
    zm = json.loads((store / ".zarray").read_text())
    assert zm["compressor"]["id"] == "zlib", zm
    save_meta(outdir, name, data, "plain Zarr v2 array, <u2, numcodecs Zlib",
              [1.0, 1.0, 1.0], None, 1)


def write_v2_i16_bz2(outdir: Path):
    """numcodecs BZ2 (a compressor of older Zarr v2 stores)."""
    import zarr
    from numcodecs import BZ2

    name = "v2_i16_bz2"
    data = volume((19, 22, 25), np.int16, seed=19)
    store = fresh(outdir / f"{name}.zarr")
    arr = zarr.create_array(str(store), shape=data.shape, dtype="<i2", chunks=(8, 9, 10),
                            compressors=BZ2(level=5), zarr_format=2, fill_value=0)
    arr[...] = data
    zm = json.loads((store / ".zarray").read_text())
    assert zm["compressor"]["id"] == "bz2", zm
    save_meta(outdir, name, data, "plain Zarr v2 array, <i2, numcodecs BZ2",
              [1.0, 1.0, 1.0], None, 1)


def write_v2_i16_lz4(outdir: Path):
    """numcodecs LZ4 (a compressor of older Zarr v2 stores: a length header
    and an LZ4 block, not Blosc)."""
    import zarr
    from numcodecs import LZ4

    name = "v2_i16_lz4"
    data = volume((21, 17, 26), np.int16, seed=23)
    store = fresh(outdir / f"{name}.zarr")
    arr = zarr.create_array(str(store), shape=data.shape, dtype="<i2", chunks=(8, 7, 10),
                            compressors=LZ4(acceleration=1), zarr_format=2, fill_value=0)
    arr[...] = data
    zm = json.loads((store / ".zarray").read_text())
    assert zm["compressor"]["id"] == "lz4", zm
    save_meta(outdir, name, data, "plain Zarr v2 array, <i2, numcodecs LZ4",
              [1.0, 1.0, 1.0], None, 1)


def write_v3_u16_lz4(outdir: Path):
    """numcodecs LZ4 in a Zarr v3 array (zarr-python names it numcodecs.lz4)."""

    import zarr
    try:
        from zarr.codecs.numcodecs import LZ4
    except ImportError:  # zarr-python before 3.1.3
        from numcodecs.zarr3 import LZ4

    name = "v3_u16_lz4"
    data = volume((18, 23, 20), np.uint16, seed=29)
    store = fresh(outdir / f"{name}.zarr")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        arr = zarr.create_array(str(store), shape=data.shape, dtype="uint16", chunks=(7, 9, 8),
                                compressors=[LZ4(acceleration=2)], zarr_format=3, fill_value=0)
        arr[...] = data
    zm = json.loads((store / "zarr.json").read_text())
    assert any(c["name"] == "numcodecs.lz4" for c in zm["codecs"]), zm
    save_meta(outdir, name, data, "plain Zarr v3 array, uint16, numcodecs.lz4",
              [1.0, 1.0, 1.0], None, 1)


def write_v2_u64(outdir: Path):
    """uint64 (v2 type string "<u8": 8 bytes, not uint8), values up to ~4e9:
    stored as uint32, so the expected array is uint32."""
    import zarr

    name = "v2_u64"
    data = volume((13, 21, 26), np.uint32, seed=13)
    store = fresh(outdir / f"{name}.zarr")
    arr = zarr.create_array(str(store), shape=data.shape, dtype="<u8", chunks=(5, 8, 9),
                            zarr_format=2, fill_value=0)
    arr[...] = data.astype(np.uint64)
    zm = json.loads((store / ".zarray").read_text())
    assert zm["dtype"] == "<u8", zm
    save_meta(outdir, name, data, "plain Zarr v2 array, <u8 (uint64), values below 2^32",
              [1.0, 1.0, 1.0], None, 1)


def write_v3_i64_sharded(outdir: Path):
    """int64 in shards, values within int32: stored as int32."""
    import zarr

    name = "v3_i64_sharded"
    data = volume((15, 18, 22), np.int32, seed=17)
    store = fresh(outdir / f"{name}.zarr")
    arr = zarr.create_array(str(store), shape=data.shape, dtype="int64", chunks=(4, 6, 6),
                            shards=(8, 12, 12), fill_value=0)
    arr[...] = data.astype(np.int64)
    save_meta(outdir, name, data, "sharded Zarr v3 array, int64, values within int32",
              [1.0, 1.0, 1.0], None, 1)


CASES = [write_ome04_v2, write_v3_plain, write_v3_sharded,
         write_ome05_2ch, write_v3_f32_be, write_v2_i16_be_F, write_v2_u16_zlib,
         write_v2_i16_bz2, write_v2_i16_lz4, write_v3_u16_lz4, write_v2_u64, write_v3_i64_sharded]


def main(argv):
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    outdir = Path(argv[1])
    outdir.mkdir(parents=True, exist_ok=True)
    for case in CASES:
        case(outdir)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
