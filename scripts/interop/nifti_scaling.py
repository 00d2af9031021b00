#!/usr/bin/env python3
"""NIfTI scl_slope/scl_inter: brickyard's values against nibabel's get_fdata().

Usage: nifti_scaling.py BRICKYARD_BIN WORKDIR

Writes NIfTI files with nibabel whose headers ask for a rescale
(value = scl_slope * stored + scl_inter), converts each with
`brickyard convert`, reads level 0 of the OME-Zarr back with zarr-python and
compares it exactly with what nibabel reads:

  * int16 CT, slope 1, intercept -1024: integer values equal to get_fdata(),
    and the type stays int16 (the stored numbers 0..4095 leave room);
  * int16, slope 0.5, intercept 3.25: float32 equal to get_fdata() as float32;
  * uint8, slope 2, intercept -1024: int16 (widened, exact);
  * uint8, slope 1, intercept 10 over 0..200: uint8 kept;
  * int16, slope 0: no scaling (nibabel's rule), the stored numbers;
  * float32, slope 2, intercept -1: float32;
  * NIfTI-2 int16, slope 0.1 (float64 header field): float32;
  * gzip-compressed CT;
  * `--raw-values`: the stored numbers and type, unscaled;
and that the conversion report (text and --json) says what was done.
Exit 0 on success, 1 on any mismatch.
"""
from __future__ import annotations

import gzip
import json
import subprocess
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import zarr

sys.path.insert(0, str(Path(__file__).resolve().parent))
import check_output as co  # noqa: E402

SHAPE_XYZ = (11, 9, 7)
# numpy type names and brickyard's short names (the --json report's).
SHORT = {"uint8": "u8", "int8": "i8", "uint16": "u16", "int16": "i16", "uint32": "u32",
         "int32": "i32", "float32": "f32", "float64": "f64"}


def write_nifti(path: Path, stored_xyz: np.ndarray, slope: float, inter: float,
                version: int = 1) -> None:
    """Write `stored_xyz` as is (no rescaling by nibabel) with the given
    scl_slope/scl_inter in the header."""
    hdr = nib.Nifti1Header() if version == 1 else nib.Nifti2Header()
    hdr.set_data_dtype(stored_xyz.dtype)
    hdr.set_data_shape(stored_xyz.shape)
    hdr.set_zooms((0.8, 0.9, 2.5))
    hdr.set_xyzt_units("mm")
    affine = np.diag([0.8, 0.9, 2.5, 1.0])
    affine[:3, 3] = [-10.0, 20.0, 5.5]
    hdr.set_sform(affine, code=1)
    hdr.set_qform(affine, code=1)
    # set_slope_inter refuses some values (slope 0): write the fields directly.
    hdr["scl_slope"] = slope
    hdr["scl_inter"] = inter
    raw = path.with_suffix("") if path.suffix == ".gz" else path
    with open(raw, "wb") as f:
        hdr.write_to(f)
        # rescale=False: write the numbers as they are; the header written
        # above keeps its slope and intercept.
        hdr.data_to_fileobj(stored_xyz, f, rescale=False)
    if path.suffix == ".gz":
        path.write_bytes(gzip.compress(raw.read_bytes()))
        raw.unlink()


def convert(bin_: str, src: Path, out: Path, *extra: str) -> tuple[str, dict]:
    """Convert twice (text report, then --json) and return both reports."""
    args = [bin_, "convert", str(src), str(out), "--brick", "8", "--shard", "16",
            "--quiet", "--overwrite", *extra]
    print("+", " ".join(args), flush=True)

    def run(a: list[str]) -> str:
        r = subprocess.run(a, capture_output=True, text=True)
        if r.returncode:
            print(r.stdout + r.stderr, end="")
            raise SystemExit(f"nifti_scaling: FAILED: brickyard exited with {r.returncode}")
        return r.stdout

    text = run(args)
    print(text, end="")
    return text, json.loads(run(args + ["--json"]))


def level0(store: Path) -> np.ndarray:
    grp = zarr.open_group(str(store), mode="r", zarr_format=3)
    ms = grp.attrs["ome"]["multiscales"][0]
    return np.asarray(grp[ms["datasets"][0]["path"]][...])


def exact(chk: co.Checker, what: str, want: np.ndarray, got: np.ndarray) -> None:
    if got.shape != want.shape:
        chk.fail(f"{what}: shape {got.shape} != {want.shape}")
        return
    same = np.array_equal(got, want, equal_nan=want.dtype.kind == "f")
    detail = ""
    if not same:
        bad = np.argwhere(got != want)
        i = tuple(bad[0])
        detail = f"{len(bad)} voxels differ, first at (z, y, x) {i}: got {got[i]!r}, want {want[i]!r}"
    chk.check(same, f"{what}: level 0 equals nibabel exactly", detail)


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        print(__doc__)
        return 2
    bin_, work = argv[1], Path(argv[2])
    work.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1234)
    chk = co.Checker("nifti_scaling")

    ct = rng.integers(0, 4096, SHAPE_XYZ, dtype=np.int16)
    frac = rng.integers(-2000, 2000, SHAPE_XYZ, dtype=np.int16)
    u8 = rng.integers(0, 256, SHAPE_XYZ, dtype=np.uint8)
    u8_low = rng.integers(0, 201, SHAPE_XYZ, dtype=np.uint8)
    f32 = rng.standard_normal(SHAPE_XYZ).astype(np.float32) * 100

    # name, stored, slope, inter, file name, NIfTI version, expected dtype,
    # expected report words
    cases = [
        ("ct_i16", ct, 1.0, -1024.0, "ct.nii", 1, np.int16, "(int16 kept"),
        ("ct_i16_gz", ct, 1.0, -1024.0, "ct_gz.nii.gz", 1, np.int16, "(int16 kept"),
        ("frac_i16", frac, 0.5, 3.25, "frac.nii", 1, np.float32, "(int16 → float32)"),
        ("u8_widened", u8, 2.0, -1024.0, "u8w.nii", 1, np.int16, "(uint8 → int16, exact"),
        ("u8_kept", u8_low, 1.0, 10.0, "u8k.nii", 1, np.uint8, "(uint8 kept"),
        ("slope0", ct, 0.0, -1024.0, "slope0.nii", 1, np.int16, None),
        ("f32", f32, 2.0, -1.0, "f32.nii", 1, np.float32, "(float32 kept)"),
        ("nifti2_i16", frac, 0.1, 0.0, "n2.nii", 2, np.float32, "(int16 → float32)"),
    ]
    for name, stored, slope, inter, fname, version, want_dtype, words in cases:
        print(f"-- {name}: {stored.dtype} slope {slope} inter {inter} (NIfTI-{version})")
        src = work / fname
        write_nifti(src, stored, slope, inter, version)
        img = nib.load(str(src))
        s, i = img.dataobj.slope, img.dataobj.inter
        if slope == 0:
            chk.check((s, i) == (1.0, 0.0), f"{name}: nibabel reads slope 0 as no scaling", f"{s}, {i}")
        else:
            chk.check(np.isclose(s, slope) and np.isclose(i, inter),
                      f"{name}: nibabel reads the header's slope/intercept", f"{s}, {i}")
        fdata = img.get_fdata()  # float64, scaled
        out = work / f"{name}.ome.zarr"
        text, js = convert(bin_, src, out)
        got = level0(out)
        chk.check(got.dtype == want_dtype, f"{name}: output type {np.dtype(want_dtype).name}",
                  f"got {got.dtype}")
        want = fdata.astype(got.dtype if got.dtype.kind == "f" else np.float64).transpose(2, 1, 0)
        if got.dtype.kind != "f":
            # Integer output: the exact values of get_fdata().
            chk.check(np.array_equal(fdata, np.round(fdata)), f"{name}: nibabel values are integers")
            got_cmp = got.astype(np.float64)
        else:
            got_cmp = got
        exact(chk, name, want, got_cmp)
        values = js.get("values")
        if words is None:
            chk.check(values is None and "scaled by" not in text,
                      f"{name}: no rescale reported", f"values {values}")
        else:
            chk.check(words in text, f"{name}: text report says {words!r}", text.strip())
            chk.check(values is not None and values.get("applied") is True
                      and values.get("dtype") == SHORT[np.dtype(want_dtype).name]
                      and values.get("slope") == slope and values.get("inter") == inter,
                      f"{name}: --json report gives the rescale", json.dumps(values))

    # --raw-values: the stored numbers and type.
    print("-- raw values")
    out = work / "ct_raw.ome.zarr"
    text, js = convert(bin_, work / "ct.nii", out, "--raw-values")
    got = level0(out)
    unscaled = np.asanyarray(nib.load(str(work / "ct.nii")).dataobj.get_unscaled())
    chk.check(got.dtype == np.int16, "raw values: int16", f"got {got.dtype}")
    exact(chk, "raw values", unscaled.transpose(2, 1, 0), got)
    chk.check("not applied" in text, "raw values: text report says the rescale is not applied", text.strip())
    v = js.get("values") or {}
    chk.check(v.get("applied") is False and v.get("slope") == 1 and v.get("inter") == -1024,
              "raw values: --json report gives the rescale, not applied", json.dumps(v))
    return chk.finish()


if __name__ == "__main__":
    sys.exit(main(sys.argv))
