"""Fixtures of the brickyard Python tests: the release binary and stores."""

import os
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


def brickyard_bin() -> Path:
    """The CLI the bindings are compared with: $BRICKYARD_BIN, else the
    release binary of the target directory."""
    if os.environ.get("BRICKYARD_BIN"):
        return Path(os.environ["BRICKYARD_BIN"])
    target = Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target"))
    return target / "release" / "brickyard"


@pytest.fixture(scope="session")
def cli():
    exe = brickyard_bin()
    if not exe.exists():
        raise FileNotFoundError(f"{exe}: build it first (cargo build --release -p brickyard) or set BRICKYARD_BIN")

    def run(*args):
        r = subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"brickyard {' '.join(map(str, args))} failed:\n{r.stdout}\n{r.stderr}")
        return r.stdout

    return run


def read_png(path) -> np.ndarray:
    """An 8-bit RGBA PNG (as brickyard writes them) as an (h, w, 4) array."""
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path}: not a PNG"
    pos, idat, w = 8, b"", None
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        if kind == b"IHDR":
            w, h, depth, colour = struct.unpack(">IIBB", body[:10])
            assert (depth, colour) == (8, 6), f"{path}: expected 8-bit RGBA"
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    raw = zlib.decompress(idat)
    stride = w * 4
    out = np.zeros((h, stride), dtype=np.uint8)
    prev = np.zeros(stride, dtype=np.int32)
    for y in range(h):
        f = raw[y * (stride + 1)]
        line = np.frombuffer(raw, dtype=np.uint8, count=stride, offset=y * (stride + 1) + 1).astype(np.int32)
        cur = np.zeros(stride, dtype=np.int32)
        for x in range(stride):
            a = cur[x - 4] if x >= 4 else 0
            b = prev[x]
            c = prev[x - 4] if x >= 4 else 0
            if f == 0:
                p = 0
            elif f == 1:
                p = a
            elif f == 2:
                p = b
            elif f == 3:
                p = (a + b) // 2
            elif f == 4:
                pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                p = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            else:
                raise ValueError(f"{path}: bad PNG filter {f}")
            cur[x] = (line[x] + p) & 0xFF
        out[y] = cur
        prev = cur
    return out.reshape(h, w, 4)


def volume(shape, dtype, seed=0):
    """A smooth field plus noise over the dtype's range (so that every level
    differs and the values reach both ends)."""
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*[np.linspace(0, 1, n) for n in shape], indexing="ij")
    f = 0.5 + 0.35 * np.sin(6 * x + 3 * y) * np.cos(5 * z) + 0.15 * rng.random(shape)
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return (f * 2000 - 500).astype(dt)
    info = np.iinfo(dt)
    return (info.min + f * (float(info.max) - info.min)).clip(info.min, info.max).astype(dt)
