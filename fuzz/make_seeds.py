#!/usr/bin/env python3
"""Write the seed inputs of the fuzz targets into fuzz/seeds/<target>/.

Seeds are small valid (and a few half-valid) inputs, so that the fuzzer starts
from inputs that reach deep into each parser: crafted files of every format,
and the first bytes of the real volumes in ../shared/data (beside the
repository) when that folder is there. Only the Python standard library is
used. Usage: python3 fuzz/make_seeds.py
"""

import gzip
import json
import os
import struct
import sys
import zlib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEEDS = os.path.join(ROOT, "fuzz", "seeds")
DATA = os.path.join(ROOT, "..", "shared", "data")


def put(target, name, data):
    d = os.path.join(SEEDS, target)
    os.makedirs(d, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


def shared(name):
    p = os.path.join(DATA, name)
    if not os.path.exists(p):
        print(f"make_seeds: {p} missing, its seeds are skipped", file=sys.stderr)
        return None
    with open(p, "rb") as f:
        return f.read()


def gz(b):
    return gzip.compress(b, mtime=0)


def ramp(n, size=2, endian="<"):
    fmt = {1: "B", 2: "H", 4: "I"}[size]
    return b"".join(struct.pack(endian + fmt, (i * 7) % (1 << (8 * size))) for i in range(n))


# --------------------------------------------------------------------- NRRD
def nrrd():
    t = "nrrd_header"
    hdr = (
        "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 6 5 4\nendian: little\n"
        "encoding: {enc}\nspace: left-posterior-superior\n"
        "space directions: (0.5,0,0) (0,-0.5,0) (0,0,2)\nspace origin: (1,2,3)\n"
        "kinds: domain domain domain\n# a comment\nkey:=value\n\n"
    )
    v = ramp(6 * 5 * 4)
    put(t, "raw-u16.nrrd", hdr.format(enc="raw").encode() + v)
    put(t, "gzip-u16.nrrd", hdr.format(enc="gzip").encode() + gz(v))
    four = (
        "NRRD0005\ntype: float\ndimension: 4\nsizes: 2 4 3 2\nendian: big\nencoding: gzip\n"
        "kinds: vector domain domain domain\nspacings: nan 1 1 3\nspace units: \"mm\" \"mm\" \"mm\"\n"
        "space dimension: 3\nbyte skip: 0\n\n"
    )
    put(t, "four-d-f32.nrrd", four.encode() + gz(b"\x3f\x80\x00\x00" * (2 * 4 * 3 * 2)))
    two = "NRRD0001\ntype: uchar\ndimension: 2\nsizes: 8 3\nencoding: raw\nline skip: 1\nbyte skip: -1\n\n"
    put(t, "two-d-u8.nrrd", two.encode() + b"junk line\n" + bytes(range(24)))
    det = (
        "NRRD0004\ntype: short\ndimension: 3\nsizes: 4 4 3\nendian: little\nencoding: raw\n"
        "data file: slice%03d.raw 1 3 1 2\n"
    )
    put(t, "detached.nhdr", det)
    real = shared("mr-brain-i16.nrrd")
    if real:
        put(t, "mr-brain-head.nrrd", real[:2048])


# -------------------------------------------------------------------- NIfTI
def nifti1(dims, datatype, bitpix, be=False, vox_offset=352, pair=False, scl=(0.0, 0.0)):
    e = ">" if be else "<"
    h = bytearray(348)
    struct.pack_into(e + "i", h, 0, 348)
    d = [len(dims)] + list(dims) + [1] * (7 - len(dims))
    struct.pack_into(e + "8h", h, 40, *d)
    struct.pack_into(e + "hh", h, 70, datatype, bitpix)
    struct.pack_into(e + "8f", h, 76, 1, 0.5, 0.5, 2.0, 1, 1, 1, 1)
    struct.pack_into(e + "f", h, 108, vox_offset)
    struct.pack_into(e + "ff", h, 112, *scl)
    h[123] = 2  # millimetres
    struct.pack_into(e + "hh", h, 252, 1, 1)  # qform_code, sform_code
    struct.pack_into(e + "3f", h, 268, 10, 20, 30)
    for i, row in enumerate([(0.5, 0, 0, -5), (0, 0.5, 0, -6), (0, 0, 2, -7)]):
        struct.pack_into(e + "4f", h, 280 + 16 * i, *row)
    h[344:348] = b"ni1\0" if pair else b"n+1\0"
    return bytes(h) + b"\0\0\0\0"


def nifti2(dims, datatype, bitpix, vox_offset=544):
    h = bytearray(540)
    struct.pack_into("<i", h, 0, 540)
    h[4:12] = b"n+2\0\r\n\x1a\n"
    struct.pack_into("<hh", h, 12, datatype, bitpix)
    d = [len(dims)] + list(dims) + [1] * (7 - len(dims))
    struct.pack_into("<8q", h, 16, *d)
    struct.pack_into("<8d", h, 104, 1, 1, 1, 1, 1, 1, 1, 1)
    struct.pack_into("<q", h, 168, vox_offset)
    struct.pack_into("<dd", h, 176, 2.0, -1.0)
    struct.pack_into("<i", h, 500, 3)
    return bytes(h) + b"\0\0\0\0"


def nifti():
    t = "nifti_header"
    n = 4 * 3 * 2
    put(t, "i16-le.nii", nifti1((4, 3, 2), 4, 16) + ramp(n))
    put(t, "i16-be.nii", nifti1((4, 3, 2), 4, 16, be=True) + ramp(n, 2, ">"))
    put(t, "u8-4d.nii.gz", gz(nifti1((4, 3, 2, 2), 2, 8, scl=(2.0, 1.0)) + ramp(2 * n, 1)))
    put(t, "f32-nifti2.nii", nifti2((3, 2, 2), 16, 32) + struct.pack("<12f", *range(12)))
    put(t, "header-only-pair.nii", nifti1((4, 3, 2), 512, 16, pair=True))
    for name in ["colin27-t1-0.5mm.nii.gz", "mni152-t1-u8.nii.gz"]:
        real = shared(name)
        if real:
            head = gzip.GzipFile(fileobj=__import__("io").BytesIO(real)).read(1024)
            put(t, name.replace(".nii.gz", "-head.nii"), head)


# --------------------------------------------------------------------- TIFF
def tiff_file(pages, big=False, be=False):
    """pages: list of (tags, chunks) where tags is a list of (tag, type,
    values) and chunks a list of byte strings (strips or tiles); offsets and
    byte counts are filled in (tags 273/279 or 324/325 given as None)."""
    e = ">" if be else "<"
    out = bytearray(b"MM" if be else b"II")
    if big:
        out += struct.pack(e + "HHHQ", 43, 8, 0, 0)
        first_ptr = 8
    else:
        out += struct.pack(e + "HI", 42, 0)
        first_ptr = 4
    sizes = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 16: 8}
    fmts = {1: "B", 2: "B", 3: "H", 4: "I", 16: "Q"}
    prev_ptr = first_ptr
    for tags, chunks in pages:
        offs = []
        for c in chunks:
            offs.append(len(out))
            out += c
        if len(out) % 2:
            out += b"\0"
        full = []
        for tag, typ, vals in tags:
            if vals is None:
                vals = offs if tag in (273, 324) else [len(c) for c in chunks]
            full.append((tag, typ, list(vals)))
        full.sort()
        # Out-of-line values first.
        entries = []
        inline = 8 if big else 4
        for tag, typ, vals in full:
            if typ == 2:
                raw = bytes(vals)
            else:
                raw = b"".join(struct.pack(e + fmts[typ], v) for v in vals)
            if len(raw) > inline:
                pos = len(out)
                out += raw
                if len(out) % 2:
                    out += b"\0"
                val = struct.pack(e + ("Q" if big else "I"), pos)
            else:
                val = raw.ljust(inline, b"\0")
            entries.append((tag, typ, len(vals), val))
        ifd = len(out)
        if big:
            out += struct.pack(e + "Q", len(entries))
            for tag, typ, n, val in entries:
                out += struct.pack(e + "HHQ", tag, typ, n) + val
            nxt = len(out)
            out += struct.pack(e + "Q", 0)
            struct.pack_into(e + "Q", out, prev_ptr, ifd)
        else:
            out += struct.pack(e + "H", len(entries))
            for tag, typ, n, val in entries:
                out += struct.pack(e + "HHI", tag, typ, n) + val
            nxt = len(out)
            out += struct.pack(e + "I", 0)
            struct.pack_into(e + "I", out, prev_ptr, ifd)
        prev_ptr = nxt
    return bytes(out)


def packbits(b):
    out = bytearray()
    for i in range(0, len(b), 128):
        part = b[i : i + 128]
        out.append(len(part) - 1)
        out += part
    return bytes(out)


def tiff():
    t = "tiff_header"
    w, h = 8, 6

    def page(bits, fmt, data_fn, compression=1, rows=3, spp=1, planar=1, photometric=1):
        chunks = []
        planes = spp if planar == 2 else 1
        per = spp if planar == 1 else 1
        for p in range(planes):
            for r0 in range(0, h, rows):
                n = min(rows, h - r0) * w * per * bits // 8
                chunks.append(data_fn(n, p, r0))
        tags = [
            (256, 3, [w]),
            (257, 3, [h]),
            (258, 3, [bits] * spp),
            (259, 3, [compression]),
            (262, 3, [photometric]),
            (273, 4, None),
            (277, 3, [spp]),
            (278, 3, [rows]),
            (279, 4, None),
            (284, 3, [planar]),
            (339, 3, [fmt] * spp),
        ]
        return tags, chunks

    plain = lambda n, p, r0: bytes((r0 * 31 + i + p) % 256 for i in range(n))
    put(t, "u8-2pages.tif", tiff_file([page(8, 1, plain), page(8, 1, plain)]))
    put(t, "u16-be.tif", tiff_file([page(16, 1, plain)], be=True))
    put(t, "f32.tif", tiff_file([page(32, 3, lambda n, p, r0: b"\0\0\x80\x3f" * (n // 4))]))
    put(t, "i16-bigtiff.tif", tiff_file([page(16, 2, plain)] * 2, big=True))
    put(t, "deflate.tif", tiff_file([page(8, 1, lambda n, p, r0: zlib.compress(plain(n, p, r0)), 8)]))
    put(t, "packbits.tif", tiff_file([page(8, 1, lambda n, p, r0: packbits(plain(n, p, r0)), 32773)]))
    put(t, "rgb-chunky.tif", tiff_file([page(8, 1, plain, spp=3, photometric=2)]))
    put(t, "rgb-planar.tif", tiff_file([page(8, 1, plain, spp=3, planar=2, photometric=2)]))
    tiles = [
        (256, 3, [w]),
        (257, 3, [h]),
        (258, 3, [8]),
        (259, 3, [1]),
        (262, 3, [1]),
        (277, 3, [1]),
        (322, 3, [16]),
        (323, 3, [16]),
        (324, 4, None),
        (325, 4, None),
    ]
    put(t, "tiled.tif", tiff_file([(tiles, [bytes(range(256))])]))
    reduced = page(8, 1, plain)
    put(t, "with-thumbnail.tif", tiff_file([([(254, 4, [1])] + reduced[0], reduced[1]), page(8, 1, plain)]))
    real = shared("nuclei-labels-u32.tif")
    if real:
        # The first pages whose IFD and strips lie in the first 8 KB, with
        # the IFD chain cut after them.
        cut = 8192
        b = bytearray(real[:cut])

        def longs(entry_at):
            typ, count, value = struct.unpack("<HII", b[entry_at + 2 : entry_at + 12])
            size = {3: 2, 4: 4}[typ]
            if count * size <= 4:
                return list(struct.unpack("<" + "HI"[size == 4] * count, b[entry_at + 8 : entry_at + 8 + count * size]))
            return list(struct.unpack("<" + "HI"[size == 4] * count, b[value : value + count * size]))

        off = struct.unpack("<I", b[4:8])[0]
        last_next = None
        while off and off + 2 <= cut:
            n = struct.unpack("<H", b[off : off + 2])[0]
            end = off + 2 + 12 * n + 4
            if end > cut:
                break
            tags = {struct.unpack("<H", b[off + 2 + 12 * i : off + 4 + 12 * i])[0]: off + 2 + 12 * i for i in range(n)}
            ends = [o + c for o, c in zip(longs(tags[273]), longs(tags[279]))]
            if max(ends) > cut:
                break
            last_next = end - 4
            off = struct.unpack("<I", b[end - 4 : end])[0]
        if last_next:
            struct.pack_into("<I", b, last_next, 0)
            put(t, "nuclei-labels-head.tif", bytes(b))


# ---------------------------------------------------------------------- raw
def raw():
    t = "raw_sidecar"
    put(t, "u16.json", json.dumps({"dims": [16, 16, 8], "dtype": "u16", "endian": "big", "spacing": [1, 1, 2]}))
    put(t, "f32-channels.json", json.dumps({
        "dims": [8, 8, 4], "dtype": "f32", "channels": 2, "header_bytes": 16,
        "origin": [0.5, 1.5, 2.5], "unit": "micrometer"}))
    put(t, "u8-small.json", json.dumps({"dims": [4, 4, 4], "dtype": "u8"}))
    put(t, "fixed-size.json", json.dumps({"dims": [16, 16, 16], "dtype": "u8"}))


# --------------------------------------------------------------- (OME-)Zarr
def crc32c(data):
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF


def shard(chunks, end=True, crc=True, be=False):
    """A shard of the given inner chunks (None: absent)."""
    e = ">" if be else "<"
    n = len(chunks)
    ib = 16 * n + (4 if crc else 0)
    body = bytearray()
    index = bytearray()
    base = 0 if end else ib
    for c in chunks:
        if c is None:
            index += struct.pack(e + "QQ", 2**64 - 1, 2**64 - 1)
        else:
            index += struct.pack(e + "QQ", base + len(body), len(c))
            body += c
    if crc:
        index += struct.pack("<I", crc32c(bytes(index)))
    return bytes(body + index) if end else bytes(index + body)


def level_array(shape, shard_shape, inner, dtype="uint16", inner_codecs=None, index_location="end", crc=True):
    index_codecs = [{"name": "bytes", "configuration": {"endian": "little"}}]
    if crc:
        index_codecs.append({"name": "crc32c"})
    return {
        "zarr_format": 3,
        "node_type": "array",
        "shape": shape,
        "data_type": dtype,
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": shard_shape}},
        "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
        "fill_value": 0,
        "codecs": [{
            "name": "sharding_indexed",
            "configuration": {
                "chunk_shape": inner,
                "codecs": inner_codecs or [{"name": "bytes", "configuration": {"endian": "little"}}],
                "index_codecs": index_codecs,
                "index_location": index_location,
            },
        }],
        "dimension_names": ["z", "y", "x"][-len(shape):],
        "attributes": {},
    }


def zarr():
    t = "omezarr_meta"
    datasets = [
        {"path": str(i), "coordinateTransformations": [
            {"type": "scale", "scale": [2.0 ** i * 6.5, 2.0 ** i * 0.78, 2.0 ** i * 0.78]},
            {"type": "translation", "translation": [1.0, -2.0, 3.0]}]}
        for i in range(3)
    ]
    axes = [{"name": a, "type": "space", "unit": "millimeter"} for a in "zyx"]
    group = {
        "zarr_format": 3, "node_type": "group",
        "attributes": {
            "ome": {"version": "0.5", "multiscales": [
                {"name": "mr-brain", "axes": axes, "datasets": datasets, "type": "mean"}]},
            "brickyard": {"version": 1, "complete": True, "brick": [32, 32, 32], "labels": False,
                          "stats": "_brickyard/stats", "ratios": [[1, 1, 1], [1, 2, 2], [2, 2, 2]]},
        },
    }
    put(t, "group-0.5.json", json.dumps(group, indent=1))
    v04 = {"multiscales": [{"version": "0.4", "axes": [{"name": "c", "type": "channel"}] + axes,
                            "datasets": datasets[:1]}]}
    put(t, "zattrs-0.4.json", json.dumps(v04))
    put(t, "old-no-axes.json", json.dumps({"multiscales": [{"version": "0.3", "axes": ["z", "y", "x"],
                                                            "datasets": [{"path": "0"}]}]}))

    t = "zarr_array"
    le = lambda vals: b"".join(struct.pack("<H", v % 65536) for v in vals)
    inner = [le(range(k * 8, k * 8 + 8)) for k in range(8)]
    inner[3] = None
    put(t, "sharded-u16", json.dumps(level_array([4, 4, 4], [4, 4, 4], [2, 2, 2])).encode()
        + b"\0" + shard(inner))
    put(t, "sharded-start-edge", json.dumps(level_array([3, 5, 4], [4, 4, 4], [2, 2, 2], index_location="start")).encode()
        + b"\0" + shard(inner, end=False))
    put(t, "sharded-nocrc", json.dumps(level_array([4, 4, 4], [4, 4, 4], [2, 2, 2], crc=False)).encode()
        + b"\0" + shard(inner, crc=False))
    gzc = [{"name": "bytes", "configuration": {"endian": "little"}}, {"name": "gzip", "configuration": {"level": 1}}]
    put(t, "sharded-gzip", json.dumps(level_array([2, 2, 4], [2, 2, 4], [1, 2, 4], inner_codecs=gzc)).encode()
        + b"\0" + shard([gz(le(range(8))), gz(le(range(8, 16)))]))
    put(t, "sharded-gzip-nocrc", json.dumps(level_array([2, 2, 4], [2, 2, 4], [1, 2, 4], inner_codecs=gzc, crc=False)).encode()
        + b"\0" + shard([gz(le(range(8))), gz(le(range(8, 16)))], crc=False))
    plain = {
        "zarr_format": 3, "node_type": "array", "shape": [2, 3, 4, 5], "data_type": "float32",
        "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [2, 3, 4, 5]}},
        "chunk_key_encoding": {"name": "default"}, "fill_value": "NaN",
        "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}],
        "dimension_names": ["c", "z", "y", "x"],
    }
    put(t, "plain-f32-channels", json.dumps(plain).encode() + b"\0" + struct.pack("<120f", *range(120)))
    v2 = {"zarr_format": 2, "shape": [3, 4, 5], "chunks": [3, 4, 5], "dtype": "<i2",
          "compressor": {"id": "gzip", "level": 1}, "fill_value": 0, "order": "C", "filters": None}
    put(t, "v2-gzip-i16", json.dumps(v2).encode() + b"\0" + gz(struct.pack("<60h", *range(-30, 30))))

    t = "shard_index"
    # Byte 0: bit 0 index at the start, bit 1 big-endian, bit 2 no CRC;
    # bytes 1-2: number of inner chunks.
    put(t, "end-crc", bytes([0]) + struct.pack("<H", 8) + shard(inner))
    put(t, "start-crc", bytes([1]) + struct.pack("<H", 8) + shard(inner, end=False))
    put(t, "end-be-nocrc", bytes([6]) + struct.pack("<H", 8) + shard(inner, crc=False, be=True))
    put(t, "all-absent", bytes([0]) + struct.pack("<H", 4) + shard([None] * 4))


if __name__ == "__main__":
    nrrd()
    nifti()
    tiff()
    raw()
    zarr()
    total = 0
    for d, _, files in os.walk(SEEDS):
        for f in files:
            total += os.path.getsize(os.path.join(d, f))
    print(f"make_seeds: {total} bytes of seeds in {SEEDS}")
