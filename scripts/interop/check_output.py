#!/usr/bin/env python3
"""Independent verification of a brickyard OME-Zarr 0.5 pyramid with zarr-python.

Usage:
    check_output.py STORE --raw FILE --dims X Y Z --dtype u16
                    [--channels N] [--endian little|big] [--header-bytes N]
                    [--labels] [--sidecar FILE.json]
                    [--spacing X Y Z] [--brick N] [--shard N]
                    [--compression lz4|zstd|none] [--no-ome-zarr-py]
    check_output.py STORE --npy FILE.npy [...]      (expected level 0 from .npy)

What is checked
  * metadata: root zarr.json is a Zarr v3 group, attributes.ome.version == "0.5",
    multiscales[0].axes are (c,) z, y, x with the right types and a valid
    space unit; every dataset path is a v3 array with matching ndim, dtype,
    dimension_names; coordinateTransformations: a scale (and optionally a
    translation) per level; the ratio scale[k]/scale[k-1] is 1 or 2 per spatial
    axis (1 on c) and shape[k] == ceil(shape[k-1] / ratio); translations (if
    present) put each level's voxel 0 at the centre of the box it averages;
    the codec chain is sharding_indexed(bytes little + blosc/zstd/none) and,
    with --brick/--shard, the inner/outer chunk shapes.
  * level 0 equals the raw file (or .npy) bit-exactly.
  * every level k >= 1 equals a naive numpy reference downsample of the level
    k-1 *as stored* (so an error is reported at the first level it appears):
    box mean over the (1|2)^3 block, only over voxels that exist at the
    volume edge; integers round half up, floor(sum/count + 1/2), computed
    exactly in int64; floats mean in float64 then cast (compared with
    rtol 1e-6); --labels: mode, ties -> smallest value.
  * (default) ome-zarr-py's Reader can open the store and reads level 0.

Exit status 0 when everything matched, 1 on any mismatch (with a clear message
saying which level / voxel / expected / got), 2 on usage errors.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

DTYPES = {
    "u8": np.uint8, "uint8": np.uint8,
    "i8": np.int8, "int8": np.int8,
    "u16": np.uint16, "uint16": np.uint16,
    "i16": np.int16, "int16": np.int16,
    "u32": np.uint32, "uint32": np.uint32,
    "i32": np.int32, "int32": np.int32,
    "f32": np.float32, "float32": np.float32,
    "f64": np.float64, "float64": np.float64,
}

# Units allowed for space axes by the OME-NGFF 0.5 spec (UDUNITS-2 names).
SPACE_UNITS = {
    "angstrom", "attometer", "centimeter", "decimeter", "exameter", "femtometer",
    "foot", "gigameter", "hectometer", "inch", "kilometer", "megameter", "meter",
    "micrometer", "mile", "millimeter", "nanometer", "parsec", "petameter",
    "picometer", "terameter", "yard", "yoctometer", "yottameter", "zeptometer",
    "zettameter",
}


def parse_dtype(name: str) -> np.dtype:
    try:
        return np.dtype(DTYPES[name.strip().lower()])
    except KeyError:
        raise SystemExit(f"check_output: unknown dtype {name!r} (one of {sorted(set(DTYPES))})")


# --------------------------------------------------------------------------
# Result bookkeeping
# --------------------------------------------------------------------------
class Checker:
    def __init__(self, name: str = "check_output"):
        self.name = name
        self.failures: list[str] = []
        self.warnings: list[str] = []
        self.passes = 0

    def ok(self, msg: str) -> None:
        self.passes += 1
        print(f"  ok    {msg}", flush=True)

    def info(self, msg: str) -> None:
        print(f"  info  {msg}", flush=True)

    def warn(self, msg: str) -> None:
        self.warnings.append(msg)
        print(f"  WARN  {msg}", flush=True)

    def fail(self, msg: str) -> None:
        self.failures.append(msg)
        print(f"  FAIL  {msg}", flush=True)

    def check(self, cond: bool, msg: str, detail: str = "") -> bool:
        if cond:
            self.ok(msg)
        else:
            self.fail(msg + (f": {detail}" if detail else ""))
        return bool(cond)

    def finish(self) -> int:
        for w in self.warnings:
            print(f"{self.name}: warning: {w}")
        if self.failures:
            print(f"{self.name}: FAILED ({len(self.failures)} problem(s), {self.passes} check(s) ok)")
            for f in self.failures:
                print(f"  - {f}")
            return 1
        print(f"{self.name}: OK ({self.passes} checks)")
        return 0


# --------------------------------------------------------------------------
# Reference downsampling (independent of brickyard; naive, pad + mask)
# --------------------------------------------------------------------------
def _blocks(a: np.ndarray, ratios: tuple[int, int, int], fill) -> np.ndarray:
    """Pad the last three axes of `a` up to a multiple of `ratios` with `fill`
    and return a view shaped (..., Zo, Yo, Xo, rz*ry*rx)."""
    lead = a.shape[:-3]
    z, y, x = a.shape[-3:]
    rz, ry, rx = ratios
    zo, yo, xo = -(-z // rz), -(-y // ry), -(-x // rx)
    pad = [(0, 0)] * len(lead) + [(0, zo * rz - z), (0, yo * ry - y), (0, xo * rx - x)]
    p = np.pad(a, pad, mode="constant", constant_values=fill)
    p = p.reshape(lead + (zo, rz, yo, ry, xo, rx))
    n = len(lead)
    # (..., zo, rz, yo, ry, xo, rx) -> (..., zo, yo, xo, rz, ry, rx)
    order = list(range(n)) + [n, n + 2, n + 4, n + 1, n + 3, n + 5]
    p = p.transpose(order)
    return p.reshape(lead + (zo, yo, xo, rz * ry * rx))


def _downsample_slab(a: np.ndarray, ratios, labels: bool) -> np.ndarray:
    dtype = a.dtype
    valid = _blocks(np.ones(a.shape[-3:], dtype=bool), ratios, False)  # (Zo,Yo,Xo,B)
    count = valid.sum(axis=-1).astype(np.int64)  # >= 1 everywhere
    assert count.min() >= 1
    if labels:
        if dtype.kind == "f":
            v = _blocks(a.astype(np.float64), ratios, np.nan)
        else:
            v = _blocks(a.astype(np.int64), ratios, 0)
        vmask = np.broadcast_to(valid, v.shape)
        B = v.shape[-1]
        # counts[..., j] = number of valid k with v[k] == v[j]
        counts = np.zeros(v.shape, dtype=np.int64)
        for j in range(B):
            cj = np.zeros(v.shape[:-1], dtype=np.int64)
            for k in range(B):
                cj += ((v[..., k] == v[..., j]) & vmask[..., k]).astype(np.int64)
            counts[..., j] = cj
        counts = np.where(vmask, counts, -1)
        best = counts.max(axis=-1, keepdims=True)
        if dtype.kind == "f":
            cand = np.where(counts == best, v, np.inf)
        else:
            cand = np.where(counts == best, v, np.iinfo(np.int64).max)
        out = cand.min(axis=-1)
        return out.astype(dtype)
    if dtype.kind == "f":
        v = _blocks(a.astype(np.float64), ratios, 0.0)
        s = v.sum(axis=-1)
        return (s / count).astype(dtype)
    # integers: exact. floor(sum/count + 1/2) == floor((2*sum + count) / (2*count))
    v = _blocks(a.astype(np.int64), ratios, 0)
    s = v.sum(axis=-1)
    out = np.floor_divide(2 * s + count, 2 * count)
    info = np.iinfo(dtype)
    assert out.min() >= info.min and out.max() <= info.max, "mean out of dtype range"
    return out.astype(dtype)


def reference_downsample(a: np.ndarray, ratios, labels: bool = False,
                         slab_out_z: int = 16) -> np.ndarray:
    """Box mean (or mode) of the last three axes of `a` by `ratios` (1 or 2 each)."""
    ratios = tuple(int(r) for r in ratios)
    assert len(ratios) == 3 and all(r in (1, 2) for r in ratios), ratios
    z = a.shape[-3]
    rz = ratios[0]
    zo = -(-z // rz)
    parts = []
    for o0 in range(0, zo, slab_out_z):
        o1 = min(zo, o0 + slab_out_z)
        parts.append(_downsample_slab(a[..., o0 * rz: min(z, o1 * rz), :, :], ratios, labels))
    return np.concatenate(parts, axis=-3)


# --------------------------------------------------------------------------
# Comparison with precise mismatch reports
# --------------------------------------------------------------------------
def _fmt_idx(idx, names) -> str:
    return "(" + ", ".join(f"{n}={int(i)}" for n, i in zip(names, idx)) + ")"


def compare_arrays(chk: Checker, what: str, expected: np.ndarray, got: np.ndarray,
                   axis_names, exact: bool = True, rtol: float = 1e-6,
                   atol: float = 0.0, context=None) -> bool:
    if expected.shape != got.shape:
        chk.fail(f"{what}: shape mismatch, expected {expected.shape} got {got.shape}")
        return False
    if expected.dtype != got.dtype:
        chk.fail(f"{what}: dtype mismatch, expected {expected.dtype} got {got.dtype}")
        return False
    e = np.ascontiguousarray(expected)
    g = np.ascontiguousarray(got)
    if exact:
        if e.dtype.kind == "f":
            # bit-exact, NaN/-0.0 aware
            u = np.dtype(f"u{e.dtype.itemsize}")
            bad = e.view(u) != g.view(u)
        else:
            bad = e != g
        how = "bit-exact"
    else:
        bad = ~np.isclose(g.astype(np.float64), e.astype(np.float64), rtol=rtol, atol=atol,
                          equal_nan=True)
        how = f"allclose(rtol={rtol:g}, atol={atol:g})"
    nbad = int(np.count_nonzero(bad))
    if nbad == 0:
        chk.ok(f"{what}: {e.size} voxels equal ({how})")
        return True
    idxs = np.argwhere(bad)
    lines = [f"{what}: {nbad} of {e.size} voxels differ ({how}); first ones:"]
    for idx in idxs[:10]:
        t = tuple(idx)
        extra = ""
        if context is not None:
            extra = " " + context(t)
        lines.append(f"      at {_fmt_idx(t, axis_names)} expected {e[t].item()!r} got {g[t].item()!r}{extra}")
    # summary of where the errors are (helps spot edge-only bugs)
    lo = idxs.min(axis=0)
    hi = idxs.max(axis=0)
    lines.append(f"      mismatches span {_fmt_idx(lo, axis_names)} .. {_fmt_idx(hi, axis_names)}"
                 f" of shape {e.shape}")
    chk.fail("\n".join(lines))
    return False


# --------------------------------------------------------------------------
# Store reading & metadata checks
# --------------------------------------------------------------------------
def read_json(p: Path):
    with open(p) as f:
        return json.load(f)


def open_pyramid(chk: Checker, store: Path, channels: int | None, dtype: np.dtype | None,
                 space_unit: str | None = None):
    """Check the metadata; return dict with axis names, list of levels
    (path, array, scale, translation) or None when unusable."""
    import zarr

    root_meta = store / "zarr.json"
    if not chk.check(root_meta.is_file(), f"{root_meta} exists"):
        return None
    meta = read_json(root_meta)
    chk.check(meta.get("zarr_format") == 3 and meta.get("node_type") == "group",
              "root zarr.json is a Zarr v3 group",
              f"zarr_format={meta.get('zarr_format')!r} node_type={meta.get('node_type')!r}")
    try:
        grp = zarr.open_group(str(store), mode="r", zarr_format=3)
    except Exception as ex:  # noqa: BLE001
        chk.fail(f"zarr.open_group({store}, zarr_format=3) failed: {type(ex).__name__}: {ex}")
        return None
    chk.ok("zarr-python opens the root group (zarr_format=3)")
    attrs = dict(grp.attrs)
    ome = attrs.get("ome")
    if not chk.check(isinstance(ome, dict), "attributes.ome present",
                     f"attribute keys: {sorted(attrs)}"):
        return None
    chk.check(ome.get("version") == "0.5", 'attributes.ome.version == "0.5"',
              f"got {ome.get('version')!r}")
    ms_list = ome.get("multiscales")
    if not chk.check(isinstance(ms_list, list) and len(ms_list) >= 1,
                     "attributes.ome.multiscales is a non-empty list"):
        return None
    ms = ms_list[0]
    if "version" in ms:
        chk.info(f"multiscales[0] has a 'version' key ({ms['version']!r}); OME 0.5 keeps it in ome.version only")

    axes = ms.get("axes")
    if not chk.check(isinstance(axes, list) and all(isinstance(a, dict) for a in axes),
                     "multiscales[0].axes is a list of objects", f"got {axes!r}"):
        return None
    names = [a.get("name") for a in axes]
    # a c axis is required for >1 channel and allowed (size 1) for one channel
    has_c = (channels is not None and channels > 1) or "c" in names
    want_names = (["c"] if has_c else []) + ["z", "y", "x"]
    chk.check(names == want_names, f"axes names {names}", f"expected {want_names}")
    for a in axes:
        n = a.get("name")
        if n == "c":
            chk.check(a.get("type") == "channel", "axis c has type channel", f"got {a.get('type')!r}")
            chk.check("unit" not in a, "axis c has no unit", f"got {a.get('unit')!r}")
        elif n in ("z", "y", "x"):
            chk.check(a.get("type") == "space", f"axis {n} has type space", f"got {a.get('type')!r}")
            unit = a.get("unit")
            if unit is None and space_unit is None:
                # NGFF 0.5: a space axis "SHOULD" have a unit; not a hard error
                chk.warn(f"axis {n} has no unit")
            else:
                chk.check(unit in SPACE_UNITS, f"axis {n} unit {unit!r} is an NGFF space unit")
            if space_unit is not None:
                chk.check(unit == space_unit, f"axis {n} unit == {space_unit!r}", f"got {unit!r}")
    ndim = len(names)

    datasets = ms.get("datasets")
    if not chk.check(isinstance(datasets, list) and len(datasets) >= 1,
                     "multiscales[0].datasets is a non-empty list"):
        return None
    paths = [d.get("path") for d in datasets]
    chk.info(f"{len(datasets)} levels, paths {paths}")
    if paths != [str(i) for i in range(len(paths))]:
        chk.info(f"dataset paths are not 0,1,2,...: {paths}")
    if "coordinateTransformations" in ms:
        chk.info(f"multiscale-level coordinateTransformations: {ms['coordinateTransformations']}")

    levels = []
    for k, d in enumerate(datasets):
        p = d.get("path")
        arr_meta_path = store / p / "zarr.json"
        if not chk.check(arr_meta_path.is_file(), f"level {k}: {p}/zarr.json exists"):
            return None
        am = read_json(arr_meta_path)
        chk.check(am.get("zarr_format") == 3 and am.get("node_type") == "array",
                  f"level {k}: {p} is a Zarr v3 array")
        try:
            arr = grp[p]
        except Exception as ex:  # noqa: BLE001
            chk.fail(f"level {k}: zarr-python cannot open array {p}: {type(ex).__name__}: {ex}")
            return None
        chk.check(arr.ndim == ndim, f"level {k}: ndim {arr.ndim} == number of axes {ndim}")
        if dtype is not None:
            chk.check(arr.dtype == dtype, f"level {k}: dtype {arr.dtype}", f"expected {dtype}")
        dn = am.get("dimension_names")
        chk.check(dn == names, f"level {k}: dimension_names {dn}", f"expected {names}")
        cts = d.get("coordinateTransformations")
        scale = None
        translation = None
        if not chk.check(isinstance(cts, list) and len(cts) >= 1,
                         f"level {k}: coordinateTransformations present"):
            return None
        chk.check(cts[0].get("type") == "scale", f"level {k}: first transform is a scale",
                  f"got {cts[0]!r}")
        for t in cts:
            if t.get("type") == "scale":
                scale = [float(v) for v in t.get("scale", [])]
            elif t.get("type") == "translation":
                translation = [float(v) for v in t.get("translation", [])]
            else:
                chk.fail(f"level {k}: unexpected transform {t!r}")
        chk.check(len(cts) <= 2 and (len(cts) < 2 or cts[1].get("type") == "translation"),
                  f"level {k}: transforms are scale (+ translation)", f"got {cts!r}")
        if not chk.check(scale is not None and len(scale) == ndim and all(s > 0 for s in scale),
                         f"level {k}: scale {scale} has {ndim} positive entries"):
            return None
        if translation is not None:
            chk.check(len(translation) == ndim, f"level {k}: translation has {ndim} entries",
                      f"got {translation}")
        levels.append({"path": p, "array": arr, "meta": am, "scale": scale,
                       "translation": translation, "shape": tuple(arr.shape)})
    return {"axis_names": names, "levels": levels, "group": grp, "multiscale": ms}


def check_codecs(chk: Checker, levels, axis_names, brick: int | None, shard: int | None,
                 compression: str | None) -> None:
    for k, lv in enumerate(levels):
        am = lv["meta"]
        shape = lv["shape"]
        codecs = am.get("codecs", [])
        grid = am.get("chunk_grid", {})
        outer = grid.get("configuration", {}).get("chunk_shape")
        if not chk.check(len(codecs) == 1 and codecs[0].get("name") == "sharding_indexed",
                         f"level {k}: codecs == [sharding_indexed]",
                         f"got {[c.get('name') for c in codecs]}"):
            continue
        cfg = codecs[0].get("configuration", {})
        inner = cfg.get("chunk_shape")
        inner_codecs = cfg.get("codecs", [])
        names = [c.get("name") for c in inner_codecs]
        chk.info(f"level {k}: shape {shape} shard {outer} inner chunk {inner} codecs {names} "
                 f"index {[c.get('name') for c in cfg.get('index_codecs', [])]}")
        if outer and inner:
            chk.check(len(outer) == len(inner) == len(shape) and
                      all(o % i == 0 for o, i in zip(outer, inner)),
                      f"level {k}: inner chunk divides shard shape")
        if inner_codecs:
            b = inner_codecs[0]
            chk.check(b.get("name") == "bytes" and
                      b.get("configuration", {}).get("endian", "little") == "little",
                      f"level {k}: inner codec[0] is bytes(little)", f"got {b!r}")
        if compression is not None:
            rest = inner_codecs[1:]
            if compression == "none":
                chk.check(rest == [], f"level {k}: no compression codec", f"got {rest!r}")
            elif compression == "lz4":
                bc = rest[0].get("configuration", {}) if rest else {}
                # byte shuffle is a no-op for 1-byte types, so noshuffle is fine there
                shuffles = ("shuffle", "bitshuffle") + (("noshuffle",) if lv["array"].dtype.itemsize == 1 else ())
                ok = (len(rest) == 1 and rest[0].get("name") == "blosc" and
                      bc.get("cname") == "lz4" and bc.get("shuffle") in shuffles)
                chk.check(ok, f"level {k}: blosc lz4 + shuffle", f"got {rest!r}")
            elif compression == "zstd":
                ok = (len(rest) == 1 and (
                    rest[0].get("name") == "zstd" or
                    (rest[0].get("name") == "blosc" and
                     rest[0].get("configuration", {}).get("cname") == "zstd")))
                chk.check(ok, f"level {k}: zstd compression", f"got {rest!r}")
        for size, label, got in ((brick, "inner chunk", inner), (shard, "shard", outer)):
            if size is None or not got:
                continue
            bad = []
            for ax, (n, g, s) in enumerate(zip(axis_names, got, shape)):
                if n == "c":
                    continue
                if not (g == size or (s < size and g >= s)):
                    bad.append(f"{n}: {g}")
            chk.check(not bad, f"level {k}: {label} is {size} on spatial axes",
                      f"got {got} for shape {shape} ({', '.join(bad)})")


def check_geometry(chk: Checker, levels, axis_names, brick: int | None):
    """Check scale ratios / shapes / translations; return per-level spatial ratios."""
    ratios = [None]
    s0 = levels[0]["scale"]
    t0 = levels[0]["translation"] or [0.0] * len(s0)
    for k in range(1, len(levels)):
        prev, cur = levels[k - 1], levels[k]
        r = []
        good = True
        for a, n in enumerate(axis_names):
            q = cur["scale"][a] / prev["scale"][a]
            rq = round(q)
            if abs(q - rq) > 1e-6 * max(1.0, q) or rq not in ((1,) if n == "c" else (1, 2)):
                chk.fail(f"level {k}: axis {n} scale ratio {cur['scale'][a]}/{prev['scale'][a]} = {q}"
                         f" is not {'1' if n == 'c' else '1 or 2'}")
                good = False
                rq = 1
            exp = -(-prev["shape"][a] // rq)
            if cur["shape"][a] != exp:
                chk.fail(f"level {k}: axis {n} size {cur['shape'][a]} != ceil({prev['shape'][a]}/{rq}) = {exp}")
                good = False
            if n != "c":
                r.append(int(rq))
        if good:
            chk.ok(f"level {k}: shape {cur['shape']} scale {cur['scale']} consistent (ratio z,y,x = {r})")
        if all(x == 1 for x in r):
            chk.fail(f"level {k}: ratio is 1 on every axis (level adds nothing)")
        ratios.append(tuple(r))
        if cur["translation"] is not None or levels[0]["translation"] is not None:
            t = cur["translation"] or [0.0] * len(s0)
            # centre of the box of cum voxels starting at voxel 0 of level 0
            want = [t0[a] + (cur["scale"][a] - s0[a]) / 2.0 for a in range(len(s0))]
            chk.check(all(math.isclose(t[a], want[a], rel_tol=1e-9, abs_tol=1e-9 * max(1.0, abs(s0[a])))
                          for a in range(len(s0))),
                      f"level {k}: translation {t} puts voxel 0 at the box centre",
                      f"expected {want}")
    if brick is not None:
        sp = [i for i, n in enumerate(axis_names) if n != "c"]
        last = levels[-1]["shape"]
        chk.check(all(last[a] <= brick for a in sp),
                  f"coarsest level {last} fits in one {brick}^3 brick")
        if len(levels) >= 2:
            prev = levels[-2]["shape"]
            chk.check(any(prev[a] > brick for a in sp),
                      f"level before the coarsest {prev} does not fit in one brick (no superfluous level)")
    return ratios


def check_levels(chk: Checker, pyr, level0_expected: np.ndarray, labels: bool) -> None:
    levels = pyr["levels"]
    names = pyr["axis_names"]
    ratios = check_geometry(chk, levels, names, None)
    prev = None
    for k, lv in enumerate(levels):
        try:
            got = lv["array"][...]
        except Exception as ex:  # noqa: BLE001
            chk.fail(f"level {k} ({lv['path']}): zarr-python failed to read the data: "
                     f"{type(ex).__name__}: {ex}")
            return
        got = np.asarray(got)
        if k == 0:
            exp = level0_expected
            compare_arrays(chk, f"level 0 ({lv['path']}) vs input", exp, got, names, exact=True)
        else:
            r = ratios[k]
            exp = reference_downsample(prev, r, labels=labels)
            is_float = got.dtype.kind == "f" and not labels
            atol = 0.0
            if is_float:
                m = float(np.nanmax(np.abs(prev))) if prev.size else 0.0
                atol = 1e-6 * m  # cancellation in sums of mixed-sign values
            lead = prev.ndim - 3

            def ctx(t, prev=prev, r=r, lead=lead):
                zo, yo, xo = t[lead:]
                sl = tuple(t[:lead]) + (slice(zo * r[0], zo * r[0] + r[0]),
                                        slice(yo * r[1], yo * r[1] + r[1]),
                                        slice(xo * r[2], xo * r[2] + r[2]))
                return f"[source block at level {k-1}: {prev[sl].ravel().tolist()}]"

            compare_arrays(chk, f"level {k} ({lv['path']}) vs reference "
                                f"{'mode' if labels else 'mean'} of level {k-1} ratio {r}",
                           exp, got, names, exact=not is_float, rtol=1e-6, atol=atol, context=ctx)
        prev = got


def check_with_ome_zarr_py(chk: Checker, store: Path, level0: np.ndarray) -> None:
    try:
        from ome_zarr.io import parse_url
        from ome_zarr.reader import Reader
    except Exception as ex:  # noqa: BLE001
        chk.fail(f"ome-zarr-py import failed: {ex}")
        return
    try:
        loc = parse_url(str(store), mode="r")
        if loc is None:
            chk.fail(f"ome-zarr-py: parse_url({store}) returned None (not recognised as OME-Zarr)")
            return
        nodes = list(Reader(loc)())
        if not nodes:
            chk.fail("ome-zarr-py: Reader found no nodes")
            return
        node = nodes[0]
        data = node.data
        chk.check(len(data) >= 1, f"ome-zarr-py reads {len(data)} levels")
        l0 = np.asarray(data[0])
        if l0.shape == level0.shape:
            same = np.array_equal(l0, level0, equal_nan=level0.dtype.kind == "f")
        else:
            same = False
        chk.check(same, "ome-zarr-py level 0 equals expected data",
                  f"shape {l0.shape} vs {level0.shape}")
    except Exception as ex:  # noqa: BLE001
        chk.fail(f"ome-zarr-py failed to read {store}: {type(ex).__name__}: {ex}")


def load_raw(path: Path, dims_xyz, dtype: np.dtype, channels: int, endian: str,
             header_bytes: int, chk: Checker) -> np.ndarray:
    x, y, z = dims_xyz
    n = x * y * z * channels
    dt = dtype.newbyteorder("<" if endian == "little" else ">")
    size = path.stat().st_size
    want = header_bytes + n * dt.itemsize
    if size != want:
        msg = f"raw file {path} is {size} bytes, expected {want} (header {header_bytes} + {n} x {dt.itemsize})"
        if size < want:
            raise SystemExit(f"check_output: {msg}")
        chk.info(msg + " (trailing bytes ignored)")
    a = np.fromfile(path, dtype=dt, count=n, offset=header_bytes)
    a = a.astype(dtype.newbyteorder("="))
    shape = ((channels,) if channels > 1 else ()) + (z, y, x)
    return a.reshape(shape)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("store", type=Path)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--raw", type=Path, help="raw input file (level 0 expected data)")
    src.add_argument("--npy", type=Path, help=".npy with expected level 0 ((c,) z, y, x)")
    ap.add_argument("--dims", type=int, nargs=3, metavar=("X", "Y", "Z"))
    ap.add_argument("--dtype")
    ap.add_argument("--channels", type=int, default=None)
    ap.add_argument("--endian", choices=["little", "big"], default=None)
    ap.add_argument("--header-bytes", type=int, default=None)
    ap.add_argument("--sidecar", type=Path, help="raw sidecar JSON; fills/cross-checks dims etc.")
    ap.add_argument("--spacing", type=float, nargs=3, metavar=("X", "Y", "Z"),
                    help="expected level-0 spacing (scale of z,y,x = Z,Y,X)")
    ap.add_argument("--unit", default=None, help="expected unit of the space axes")
    ap.add_argument("--labels", action="store_true", help="levels are modes, not means")
    ap.add_argument("--brick", type=int, default=None, help="expected inner chunk size / coarsest-level bound")
    ap.add_argument("--shard", type=int, default=None, help="expected shard size")
    ap.add_argument("--compression", choices=["lz4", "zstd", "none"], default=None,
                    help="expected compression of the inner chunks")
    ap.add_argument("--no-ome-zarr-py", action="store_true", help="skip the ome-zarr-py reader check")
    args = ap.parse_args(argv)

    chk = Checker("check_output")
    print(f"check_output: {args.store}")

    if args.raw is not None:
        side = {}
        if args.sidecar is not None:
            side = read_json(args.sidecar)
            chk.info(f"sidecar {args.sidecar}: {side}")
        def pick(cli, key, default):
            sv = side.get(key)
            if cli is not None and sv is not None and cli != sv:
                chk.fail(f"sidecar {key}={sv!r} disagrees with command line {cli!r}")
            return cli if cli is not None else (sv if sv is not None else default)
        dims = pick(list(args.dims) if args.dims else None, "dims", None)
        dtype_name = pick(args.dtype, "dtype", None)
        if dims is None or dtype_name is None:
            ap.error("--dims and --dtype (or a --sidecar that has them) are required with --raw")
        channels = int(pick(args.channels, "channels", 1))
        endian = pick(args.endian, "endian", "little")
        header = int(pick(args.header_bytes, "header_bytes", 0))
        if args.spacing is None and side.get("spacing") is not None:
            args.spacing = [float(s) for s in side["spacing"]]
        dtype = parse_dtype(dtype_name)
        expected0 = load_raw(args.raw, dims, dtype, channels, endian, header, chk)
        chk.info(f"raw {args.raw}: dims x,y,z={dims} dtype={dtype} channels={channels} "
                 f"endian={endian} header={header}")
    else:
        expected0 = np.load(args.npy)
        expected0 = expected0.astype(expected0.dtype.newbyteorder("="))
        dtype = expected0.dtype
        channels = expected0.shape[0] if expected0.ndim == 4 else 1
        chk.info(f"npy {args.npy}: shape {expected0.shape} dtype {dtype}")

    rc = run_checks(chk, args.store, expected0, labels=args.labels, channels=channels,
                    spacing_xyz=args.spacing, unit=args.unit, brick=args.brick,
                    shard=args.shard, compression=args.compression,
                    ome_zarr_py=not args.no_ome_zarr_py)
    return rc


def run_checks(chk: Checker, store: Path, expected0: np.ndarray, labels: bool,
               channels: int | None, spacing_xyz=None, unit=None, brick=None, shard=None,
               compression=None, ome_zarr_py: bool = True) -> int:
    store = Path(store)
    pyr = open_pyramid(chk, store, channels, expected0.dtype, space_unit=unit)
    if pyr is None:
        return chk.finish()
    levels = pyr["levels"]
    names = pyr["axis_names"]
    # c axis present with a single channel: compare against (1, z, y, x)
    if "c" in names and expected0.ndim == 3:
        expected0 = expected0[np.newaxis]
    chk.check(levels[0]["shape"] == expected0.shape,
              f"level 0 shape {levels[0]['shape']} == input shape {expected0.shape}")
    if spacing_xyz is not None:
        want = list(reversed([float(s) for s in spacing_xyz]))  # z, y, x
        got = [s for s, n in zip(levels[0]["scale"], names) if n != "c"]
        chk.check(all(math.isclose(g, w, rel_tol=1e-9) for g, w in zip(got, want)),
                  f"level 0 spatial scale (z,y,x) {got} == input spacing {want}")
    if "c" in names:
        ci = names.index("c")
        chk.check(all(lv["scale"][ci] == 1.0 for lv in levels), "c axis scale is 1 on every level")
    if brick is not None:
        sp = [i for i, n in enumerate(names) if n != "c"]
        last = levels[-1]["shape"]
        chk.check(all(last[a] <= brick for a in sp),
                  f"coarsest level {last} fits in one {brick}^3 brick")
        if len(levels) >= 2:
            prev = levels[-2]["shape"]
            chk.check(any(prev[a] > brick for a in sp),
                      f"level before the coarsest {prev} does not fit in one brick (no superfluous level)")
    check_codecs(chk, levels, names, brick, shard, compression)
    check_levels(chk, pyr, expected0, labels)
    if ome_zarr_py:
        check_with_ome_zarr_py(chk, store, expected0)
    return chk.finish()


if __name__ == "__main__":
    sys.exit(main())
