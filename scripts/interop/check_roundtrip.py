#!/usr/bin/env python3
"""Check a brickyard conversion of a reference store written by write_reference.py.

Usage: check_roundtrip.py REF_STORE CONVERTED [--brick N] [--shard N]
                          [--compression lz4|zstd|none] [--level0-only]

REF_STORE is OUTDIR/NAME.zarr from write_reference.py; OUTDIR/NAME.npy holds the
expected level-0 data and OUTDIR/NAME.json the expected channels/spacing/unit.

Checks that CONVERTED (brickyard's OME-Zarr 0.5 output):
  * level 0 equals NAME.npy bit-exactly (the round trip),
  * level-0 scale equals the reference's spacing (voxel size preserved),
and, unless --level0-only, everything check_output.py checks: OME 0.5 metadata,
and every level k >= 1 against an independent numpy reference downsample.
Exit 0 on success, 1 on any mismatch.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import check_output as co  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reference", type=Path, help="OUTDIR/NAME.zarr written by write_reference.py")
    ap.add_argument("converted", type=Path, help="brickyard output store")
    ap.add_argument("--brick", type=int, default=None)
    ap.add_argument("--shard", type=int, default=None)
    ap.add_argument("--compression", choices=["lz4", "zstd", "none"], default=None)
    ap.add_argument("--level0-only", action="store_true",
                    help="only compare level 0 with the .npy (no metadata / pyramid checks)")
    args = ap.parse_args(argv)

    ref = args.reference
    stem = ref.with_suffix("")
    npy, meta_path = Path(f"{stem}.npy"), Path(f"{stem}.json")
    for p in (npy, meta_path):
        if not p.is_file():
            print(f"check_roundtrip: missing {p} (was {ref} written by write_reference.py?)")
            return 2
    expected = np.load(npy)
    meta = json.loads(meta_path.read_text())
    chk = co.Checker("check_roundtrip")
    print(f"check_roundtrip: {ref.name} -> {args.converted}")
    chk.info(f"reference: {meta['description']}; expected shape {expected.shape} dtype {expected.dtype}")

    if args.level0_only:
        import zarr
        try:
            grp = zarr.open_group(str(args.converted), mode="r", zarr_format=3)
            ms = grp.attrs["ome"]["multiscales"][0]
            names = [a["name"] for a in ms["axes"]]
            got = np.asarray(grp[ms["datasets"][0]["path"]][...])
        except Exception as ex:  # noqa: BLE001
            chk.fail(f"cannot read level 0 of {args.converted}: {type(ex).__name__}: {ex}")
            return chk.finish()
        exp = expected[np.newaxis] if ("c" in names and expected.ndim == 3) else expected
        co.compare_arrays(chk, "level 0 vs reference .npy", exp, got, names, exact=True)
        return chk.finish()

    return co.run_checks(chk, args.converted, expected, labels=False,
                         channels=int(meta.get("channels", 1)),
                         spacing_xyz=meta.get("spacing_xyz"), unit=meta.get("unit"),
                         brick=args.brick, shard=args.shard, compression=args.compression)


if __name__ == "__main__":
    sys.exit(main())
