#!/usr/bin/env python3
"""Self-test of the interop checkers (no brickyard needed).

1. Compares check_output.reference_downsample against a deliberately slow,
   pure-Python per-voxel implementation (Fractions for the integer rounding,
   collections.Counter for the mode) on random arrays of odd shapes, every
   ratio combination, signed/unsigned/float dtypes and tie-heavy labels.
2. Writes tiny OME-Zarr 0.5 sharded pyramids with zarr-python (the layout
   brickyard is meant to produce), checks that check_output.py accepts them,
   and that it rejects corrupted copies (one wrong voxel, wrong rounding,
   bad scale) with a clear message.

Usage: selftest.py [WORKDIR]     prints "selftest: N passed, M failed"
"""
from __future__ import annotations

import collections
import itertools
import json
import math
import shutil
import subprocess
import sys
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import check_output as co  # noqa: E402


def slow_downsample(a: np.ndarray, r, labels: bool) -> np.ndarray:
    lead = a.shape[:-3]
    Z, Y, X = a.shape[-3:]
    rz, ry, rx = r
    out_shape = lead + (math.ceil(Z / rz), math.ceil(Y / ry), math.ceil(X / rx))
    out = np.zeros(out_shape, dtype=a.dtype)
    for idx in np.ndindex(*out_shape):
        li = idx[:-3]
        z, y, x = idx[-3:]
        vals = []
        for dz in range(rz):
            for dy in range(ry):
                for dx in range(rx):
                    zz, yy, xx = z * rz + dz, y * ry + dy, x * rx + dx
                    if zz < Z and yy < Y and xx < X:
                        vals.append(a[li + (zz, yy, xx)].item())
        if labels:
            c = collections.Counter(vals)
            best = max(c.values())
            out[idx] = min(v for v, n in c.items() if n == best)
        elif a.dtype.kind == "f":
            out[idx] = sum(float(v) for v in vals) / len(vals)
        else:
            out[idx] = math.floor(Fraction(sum(vals), len(vals)) + Fraction(1, 2))
    return out


class Tally:
    def __init__(self):
        self.passed = 0
        self.failed = 0

    def __call__(self, cond: bool, msg: str):
        if cond:
            self.passed += 1
            print(f"selftest ok    {msg}", flush=True)
        else:
            self.failed += 1
            print(f"selftest FAIL  {msg}", flush=True)


def test_reference(t: Tally):
    rng = np.random.default_rng(12345)
    ratios = [r for r in itertools.product((1, 2), repeat=3) if r != (1, 1, 1)]
    cases = []
    for dt in (np.uint8, np.int8, np.uint16, np.int16, np.uint32, np.int32):
        info = np.iinfo(dt)
        a = rng.integers(info.min, info.max, size=(5, 7, 9), dtype=np.int64, endpoint=True).astype(dt)
        cases.append((f"{np.dtype(dt).name} full range", a, False))
    # many exact .5 cases: values 0/1 -> means k/2, k/4, k/8
    cases.append(("u8 0/1 halves", rng.integers(0, 2, size=(7, 5, 3)).astype(np.uint8), False))
    cases.append(("i16 -1/0 halves (negative rounding)", -rng.integers(0, 2, size=(6, 5, 3)).astype(np.int16), False))
    for dt in (np.float32, np.float64):
        cases.append((f"{np.dtype(dt).name}", (rng.standard_normal((5, 6, 7)) * 100).astype(dt), False))
    cases.append(("u16 labels ties", rng.integers(0, 3, size=(7, 6, 5)).astype(np.uint16), True))
    cases.append(("i32 labels ties negative", rng.integers(-2, 2, size=(5, 5, 5)).astype(np.int32), True))
    cases.append(("u8 labels 2ch", rng.integers(0, 4, size=(2, 5, 4, 3)).astype(np.uint8), True))
    cases.append(("u16 mean 2ch", rng.integers(0, 65535, size=(2, 3, 5, 7)).astype(np.uint16), False))
    cases.append(("1-voxel axes", rng.integers(0, 255, size=(1, 1, 5)).astype(np.uint8), False))
    for name, a, labels in cases:
        for r in ratios:
            exp = slow_downsample(a, r, labels)
            got = co.reference_downsample(a, r, labels=labels, slab_out_z=2)
            if a.dtype.kind == "f":
                ok = got.dtype == exp.dtype and np.allclose(got, exp, rtol=1e-12, atol=0)
            else:
                ok = got.dtype == exp.dtype and np.array_equal(got, exp)
            if not ok:
                bad = np.argwhere(got != exp)[:3]
                t(False, f"reference_downsample {name} ratio {r}: differs at {bad.tolist()}")
                break
        else:
            t(True, f"reference_downsample == slow loop: {name} {a.shape}, all 7 ratios")


def plan(dims_zyx, spacing_zyx, brick):
    """The plan brickyard documents: halve an axis when its spacing < sqrt2 * min."""
    levels = [(tuple(dims_zyx), tuple(spacing_zyx), (1, 1, 1))]
    while not all(d <= brick for d in levels[-1][0]):
        d, s, _ = levels[-1]
        smin = min(s[a] for a in range(3) if d[a] > 1)
        r = tuple(2 if (d[a] > 1 and s[a] < smin * math.sqrt(2) * (1 - 1e-9)) else 1 for a in range(3))
        levels.append((tuple(-(-d[a] // r[a]) for a in range(3)),
                       tuple(s[a] * r[a] for a in range(3)), r))
    return levels


def write_store(path: Path, level0: np.ndarray, spacing_zyx, labels: bool, brick=8, shard=16,
                corrupt=None, channels_axis=False):
    import zarr
    from zarr.codecs import BloscCodec, BytesCodec

    if path.exists():
        shutil.rmtree(path)
    grp = zarr.open_group(str(path), mode="w", zarr_format=3)
    spatial = level0.shape[-3:]
    pl = plan(spatial, spacing_zyx, brick)
    data = level0
    datasets = []
    names = (["c"] if channels_axis else []) + ["z", "y", "x"]
    for k, (d, s, r) in enumerate(pl):
        if k > 0:
            data = slow_downsample(data, r, labels)
            if corrupt == "rounding" and k == 1 and data.dtype.kind in "ui":
                # emulate round-half-down / truncation on one level
                prev = prev_data
                data = co.reference_downsample(prev, r, labels=False)
                v = co._blocks(prev.astype(np.int64), r, 0).sum(-1)
                cnt = co._blocks(np.ones(prev.shape[-3:], bool), r, False).sum(-1)
                data = (v // cnt).astype(data.dtype)
        lvl = data.copy()
        if corrupt == "voxel" and k == len(pl) - 1:
            idx = tuple(i // 2 for i in lvl.shape)
            lvl[idx] = lvl[idx] + 1
        chunks = ((1,) if channels_axis else ()) + (brick,) * 3
        shards = ((1,) if channels_axis else ()) + (shard,) * 3
        arr = grp.create_array(
            str(k), shape=lvl.shape, dtype=lvl.dtype, chunks=chunks, shards=shards,
            serializer=BytesCodec(endian="little"),
            compressors=[BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")],
            dimension_names=names, fill_value=0)
        arr[...] = lvl
        scale = ([1.0] if channels_axis else []) + list(s)
        if corrupt == "scale" and k == 1:
            scale[-1] *= 1.5
        trans = ([0.0] if channels_axis else []) + [(s[a] - spacing_zyx[a]) / 2 for a in range(3)]
        datasets.append({"path": str(k), "coordinateTransformations": [
            {"type": "scale", "scale": scale}, {"type": "translation", "translation": trans}]})
        prev_data = data
    axes = ([{"name": "c", "type": "channel"}] if channels_axis else []) + [
        {"name": n, "type": "space", "unit": "micrometer"} for n in ("z", "y", "x")]
    grp.attrs["ome"] = {"version": "0.5", "multiscales": [{"name": "selftest", "axes": axes,
                                                           "datasets": datasets}]}
    return pl


def run_checker(args) -> tuple[int, str]:
    p = subprocess.run([sys.executable, str(HERE / "check_output.py")] + [str(a) for a in args],
                       capture_output=True, text=True)
    return p.returncode, p.stdout + p.stderr


def test_stores(t: Tally, work: Path):
    rng = np.random.default_rng(7)
    # u16 raw, anisotropic (z spacing 3 -> first ratio (1,2,2))
    X, Y, Z = 37, 21, 13
    vol = rng.integers(0, 65535, size=(Z, Y, X), dtype=np.uint16)
    raw = work / "vol_u16.raw"
    vol.astype("<u2").tofile(raw)
    store = work / "good_u16.zarr"
    pl = write_store(store, vol, (3.0, 1.0, 1.0), labels=False)
    base = [store, "--raw", raw, "--dims", X, Y, Z, "--dtype", "u16", "--spacing", 1, 1, 3,
            "--brick", 8, "--shard", 16, "--compression", "lz4", "--unit", "micrometer"]
    rc, out = run_checker(base)
    t(rc == 0, f"check_output accepts a correct u16 pyramid ({len(pl)} levels, ratios {[p[2] for p in pl[1:]]})")
    if rc != 0:
        print(out)

    for corrupt, needle in (("voxel", "voxels differ"), ("rounding", "voxels differ"),
                            ("scale", "scale ratio")):
        bad = work / f"bad_{corrupt}.zarr"
        write_store(bad, vol, (3.0, 1.0, 1.0), labels=False, corrupt=corrupt)
        rc, out = run_checker([bad] + base[1:])
        t(rc == 1 and needle in out, f"check_output rejects corruption '{corrupt}' (rc={rc})")
        if corrupt == "voxel":
            lines = [l for l in out.splitlines() if "expected" in l and " at (" in l]
            print("    e.g.:", lines[0].strip() if lines else out[-500:])

    # big-endian, header, 2 channels, i16
    vol2 = rng.integers(-32768, 32767, size=(2, 9, 10, 11), dtype=np.int16)
    raw2 = work / "vol_i16be.raw"
    with open(raw2, "wb") as f:
        f.write(b"H" * 100)
        f.write(vol2.astype(">i2").tobytes())
    store2 = work / "good_i16_2ch.zarr"
    write_store(store2, vol2, (1.0, 1.0, 1.0), labels=False, brick=4, shard=8, channels_axis=True)
    rc, out = run_checker([store2, "--raw", raw2, "--dims", 11, 10, 9, "--dtype", "i16",
                           "--channels", 2, "--endian", "big", "--header-bytes", 100,
                           "--brick", 4, "--shard", 8])
    t(rc == 0, "check_output accepts 2-channel big-endian i16 with header")
    if rc != 0:
        print(out)

    # labels with ties
    lab = rng.integers(0, 3, size=(10, 12, 14)).astype(np.uint8)
    raw3 = work / "labels.raw"
    lab.tofile(raw3)
    (work / "labels.raw.json").write_text(json.dumps(
        {"dims": [14, 12, 10], "dtype": "u8", "endian": "little", "spacing": [1, 1, 1],
         "channels": 1, "header_bytes": 0}))
    store3 = work / "good_labels.zarr"
    write_store(store3, lab, (1.0, 1.0, 1.0), labels=True, brick=4, shard=8)
    rc, out = run_checker([store3, "--raw", raw3, "--sidecar", work / "labels.raw.json", "--labels"])
    t(rc == 0, "check_output accepts a labels (mode) pyramid via sidecar")
    if rc != 0:
        print(out)
    rc, out = run_checker([store3, "--raw", raw3, "--sidecar", work / "labels.raw.json"])
    t(rc == 1, "check_output rejects a mode pyramid when checking as mean")

    # float32
    vf = (rng.standard_normal((7, 9, 11)) * 1000).astype(np.float32)
    rawf = work / "f32.raw"
    vf.tofile(rawf)
    storef = work / "good_f32.zarr"
    write_store(storef, vf, (1.0, 1.0, 1.0), labels=False, brick=4, shard=8)
    rc, out = run_checker([storef, "--raw", rawf, "--dims", 11, 9, 7, "--dtype", "f32"])
    t(rc == 0, "check_output accepts a float32 pyramid")
    if rc != 0:
        print(out)


def main():
    work = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="brickyard-selftest-"))
    work.mkdir(parents=True, exist_ok=True)
    t = Tally()
    test_reference(t)
    test_stores(t, work)
    print(f"selftest: {t.passed} passed, {t.failed} failed")
    if len(sys.argv) <= 1:
        shutil.rmtree(work, ignore_errors=True)
    return 1 if t.failed else 0


if __name__ == "__main__":
    sys.exit(main())
