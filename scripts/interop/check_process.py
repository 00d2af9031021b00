#!/usr/bin/env python3
"""`brickyard process` against scipy.ndimage, read back with zarr-python.

Usage: check_process.py BRICKYARD_BIN WORKDIR CASE

CASE is one of
  generated  a generated u16 volume (odd sizes, bricks of 16)
  nuclei     ../shared/data/nuclei-confocal-u16.tif (a real confocal stack)
  crash      jobs killed at random points leave the store as it was; reruns complete

Filters must equal scipy.ndimage (float64 input, mode="nearest",
truncate=4) within |ours - scipy| <= 1e-5 * max|scipy| (results are float32,
computed in float64). Labels must equal scipy.ndimage.label exactly up to a
permutation of the label numbers, be numbered in raster order of their
first voxel, and the per-label counts and boxes in the statistics must equal
those computed with numpy.
"""
import csv
import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import scipy.ndimage as ndi
import zarr

BIN, WORK, CASE = sys.argv[1], sys.argv[2], sys.argv[3]
ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
DATA = os.path.join(ROOT, "..", "shared", "data")
TOL = 1e-5
failures = []


def fail(msg):
    print("  - " + msg)
    failures.append(msg)


def by(*args, check=True):
    print("+ brickyard " + " ".join(map(str, args)), flush=True)
    r = subprocess.run([BIN, *map(str, args)], capture_output=True, text=True)
    sys.stdout.write(r.stdout)
    sys.stdout.write(r.stderr)
    if check and r.returncode != 0:
        raise SystemExit(f"brickyard exited {r.returncode}")
    return r


def write_raw(path, vol):
    vol.tofile(path)
    z, y, x = vol.shape
    return f"{x}x{y}x{z}"


def convert(vol, store, brick):
    raw = store + ".raw"
    dims = write_raw(raw, vol)
    by("convert", raw, store, "--dims", dims, "--dtype", vol.dtype.name, "--brick", brick,
       "--shard", brick * 2, "--quiet", "--overwrite")


def level0(path):
    g = zarr.open_group(path, mode="r")
    return g["0"][...], g


def check_filter(store, vol, pipeline, name, ref):
    by("process", store, pipeline, "--out", name, "--quiet")
    got, g = level0(os.path.join(store, "derived", name))
    if got.dtype != np.float32:
        fail(f"{pipeline}: dtype {got.dtype}, expected float32")
    if got.shape != ref.shape:
        fail(f"{pipeline}: shape {got.shape} != {ref.shape}")
        return
    scale = float(np.abs(ref).max()) or 1.0
    err = float(np.abs(got.astype(np.float64) - ref).max())
    print(f"{pipeline}: max |ours - scipy| = {err:.3g} ({err / scale:.2e} of max {scale:.4g})")
    if not err <= TOL * scale:
        fail(f"{pipeline}: max error {err:.3g} > {TOL} * {scale:.4g}")
    ms = g.attrs["ome"]["multiscales"][0]
    if len(ms["datasets"]) < 2 and max(vol.shape) > 32:
        fail(f"{pipeline}: only {len(ms['datasets'])} level(s) written")


def read_stats(path):
    with open(path) as f:
        return {int(r["label"]): r for r in csv.DictReader(f)}


def check_labels(store, pipeline, name, mask, conn, intensity=None):
    """Compare labels/NAME with scipy.ndimage.label(mask)."""
    stats_file = os.path.join(WORK, f"{name}.csv")
    by("process", store, pipeline, "--out", name, "--stats", stats_file, "--quiet", "--overwrite")
    lpath = os.path.join(store, "labels", name)
    got, g = level0(lpath)
    lg = zarr.open_group(os.path.join(store, "labels"), mode="r")
    if name not in lg.attrs["ome"]["labels"]:
        fail(f"{name} not listed in labels/zarr.json: {lg.attrs['ome']}")
    if "image-label" not in g.attrs["ome"]:
        fail(f"{name}: no image-label metadata")
    if got.dtype != np.uint32:
        fail(f"{pipeline}: dtype {got.dtype}, expected uint32")
    structure = ndi.generate_binary_structure(3, 1 if conn == 6 else 3)
    ref, n = ndi.label(mask, structure=structure)
    m = int(got.max())
    print(f"{pipeline}: {m} labels, scipy {n}")
    if m != n:
        fail(f"{pipeline}: {m} labels, scipy.ndimage.label finds {n}")
        return
    # Same partition: (ours, ref) pairs are one-to-one.
    fg = ref > 0
    if not np.array_equal(got > 0, fg):
        fail(f"{pipeline}: foreground differs in {int(np.sum((got > 0) != fg))} voxels")
        return
    pairs = np.unique(np.stack([got[fg], ref[fg]]), axis=1)
    if pairs.shape[1] != n or len(np.unique(pairs[0])) != n or len(np.unique(pairs[1])) != n:
        fail(f"{pipeline}: labels are not a permutation of scipy's ({pairs.shape[1]} pairs for {n} labels)")
        return
    # Numbering: raster order of the first voxel.
    flat = got.ravel()
    u, first = np.unique(flat, return_index=True)
    order = u[1:][np.argsort(first[1:])]
    if not np.array_equal(order, np.arange(1, n + 1)):
        fail(f"{pipeline}: labels are not numbered in raster order of their first voxel")
    # Statistics against numpy.
    compare_stats(pipeline, read_stats(stats_file), got, intensity)
    # Coarser levels are labels too: values taken from level 0 (mode).
    if len(g.attrs["ome"]["multiscales"][0]["datasets"]) > 1:
        l1 = g["1"][...]
        if not set(np.unique(l1)).issubset(set(np.unique(got))):
            fail(f"{pipeline}: level 1 holds values that level 0 does not (not a mode downsampling)")
    return got


def compare_stats(what, stats, got, intensity=None):
    """The statistics table's rows (voxels, box, centroid, mean) against
    numpy and scipy.ndimage on the label volume `got`."""
    ids = np.unique(got)
    ids = ids[ids > 0]
    n = len(ids)
    if sorted(stats) != list(map(int, ids)):
        fail(f"{what}: statistics of labels {sorted(stats)[:5]}..., the volume has {list(ids[:5])}...")
        return
    flat = got.ravel()
    counts = np.bincount(flat)
    boxes = ndi.find_objects(got)
    centroids = ndi.center_of_mass(np.ones_like(got, dtype=np.float64), got, index=ids)
    bad = 0
    for i, lab in enumerate(map(int, ids)):
        r = stats[lab]
        sl = boxes[lab - 1]
        want = [counts[lab]] + [s.start for s in sl] + [s.stop - 1 for s in sl]
        have = [int(r[k]) for k in ("voxels", "min_z", "min_y", "min_x", "max_z", "max_y", "max_x")]
        c = [float(r[k]) for k in ("centroid_z", "centroid_y", "centroid_x")]
        if want != have or max(abs(a - b) for a, b in zip(c, centroids[i])) > 1e-9 * max(got.shape):
            bad += 1
            if bad <= 3:
                fail(f"{what}: label {lab}: stats {have} {c}, numpy {want} {list(centroids[i])}")
    if intensity is not None:
        means = ndi.mean(intensity.astype(np.float64), got, index=ids)
        worst = max(abs(float(stats[int(l)]["mean"]) - means[i]) / max(abs(means[i]), 1)
                    for i, l in enumerate(ids))
        if worst > 1e-9:
            fail(f"{what}: mean intensity differs from numpy by {worst:.3g} (relative)")
    if bad:
        fail(f"{what}: {bad} labels with wrong statistics")
    else:
        print(f"{what}: statistics of {n} labels (voxels, box, centroid{', mean' if intensity is not None else ''}) equal numpy's")


def smooth_volume(shape, seed):
    rng = np.random.default_rng(seed)
    v = ndi.gaussian_filter(rng.random(shape), 1.2, mode="nearest")
    v = (v - v.min()) / (v.max() - v.min())
    return (v * 60000).astype(np.uint16)


def case_generated():
    vol = smooth_volume((37, 45, 51), 1)
    store = os.path.join(WORK, "gen.zarr")
    convert(vol, store, 16)
    f = vol.astype(np.float64)
    check_filter(store, vol, "gauss(1.5)", "g", ndi.gaussian_filter(f, 1.5, mode="nearest"))
    check_filter(store, vol, "gauss(0.8,2,1.3)", "ga",
                 ndi.gaussian_filter(f, (1.3, 2.0, 0.8), mode="nearest"))
    check_filter(store, vol, "gradmag(1.2)", "gm",
                 ndi.gaussian_gradient_magnitude(f, 1.2, mode="nearest"))
    check_filter(store, vol, "sobel", "s",
                 ndi.generic_gradient_magnitude(f, ndi.sobel, mode="nearest"))
    # Medians: the box 2R+1 across (x, y, z radii given x-first), blocks of 16
    # with halos across brick edges; exact (a median is one of the values).
    check_filter(store, vol, "median(1)", "m", ndi.median_filter(f, size=3, mode="nearest"))
    check_filter(store, vol, "median(2,0,1)", "m2",
                 ndi.median_filter(f, size=(3, 1, 5), mode="nearest"))
    check_filter(store, vol, "gauss(1)|median(1)", "gm1",
                 ndi.median_filter(ndi.gaussian_filter(f, 1.0, mode="nearest").astype(np.float32)
                                   .astype(np.float64), size=3, mode="nearest"))
    t = int(np.percentile(vol, 80))
    check_labels(store, f"threshold({t})|label(26)", "l26", vol > t, 26, intensity=vol)
    check_labels(store, f"threshold({t})|label(6)", "l6", vol > t, 6, intensity=vol)
    lo, hi = int(np.percentile(vol, 40)), int(np.percentile(vol, 55))
    check_labels(store, f"window({lo},{hi})|label(6)", "w6", (vol >= lo) & (vol <= hi), 6)
    # Smoothing, then labelling: the mask is scipy's threshold of our smoothed
    # result as stored (float32), so that the comparison is exact.
    g, _ = level0(os.path.join(store, "derived", "g"))
    check_labels(store, f"gauss(1.5)|threshold({t})|label(26)", "gl", g.astype(np.float64) > t, 26)
    # --level 1: the filter runs on the stored level-1 data.
    l1 = zarr.open_group(store, mode="r")["1"][...]
    by("process", store, "sobel", "--out", "s1", "--level", "1", "--quiet")
    got, _ = level0(os.path.join(store, "derived", "s1"))
    ref = ndi.generic_gradient_magnitude(l1.astype(np.float64), ndi.sobel, mode="nearest")
    err = float(np.abs(got - ref).max()) if got.shape == ref.shape else float("inf")
    print(f"sobel --level 1 {l1.shape}: max |ours - scipy| = {err:.3g}")
    if not err <= TOL * float(np.abs(ref).max()):
        fail(f"sobel --level 1: shape {got.shape} vs {ref.shape}, max error {err:.3g}")
    # ome-zarr-py finds the label images through the labels spec.
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader
    found = {}
    for node in Reader(parse_url(store))():
        kinds = [type(sp).__name__ for sp in node.specs]
        if "Label" in kinds:
            found[os.path.basename(str(node.zarr.path).rstrip("/"))] = node.data[0].shape
    print(f"ome-zarr-py label images: {found}")
    for name in ("l26", "l6", "w6", "gl"):
        if found.get(name) != vol.shape:
            fail(f"ome-zarr-py does not find label image {name} of shape {vol.shape}: {found}")


def case_nuclei():
    tif = os.path.join(DATA, "nuclei-confocal-u16.tif")
    if not os.path.exists(tif):
        raise SystemExit(f"FAIL: {tif} is missing (the real volumes live in ../shared/data/)")
    import tifffile
    vol = tifffile.imread(tif)
    store = os.path.join(WORK, "nuclei.zarr")
    by("convert", tif, store, "--brick", 32, "--shard", 64, "--quiet", "--overwrite")
    f = vol.astype(np.float64)
    check_filter(store, vol, "gauss(2)", "g", ndi.gaussian_filter(f, 2.0, mode="nearest"))
    check_filter(store, vol, "gradmag(1.5)", "gm",
                 ndi.gaussian_gradient_magnitude(f, 1.5, mode="nearest"))
    check_filter(store, vol, "sobel", "s",
                 ndi.generic_gradient_magnitude(f, ndi.sobel, mode="nearest"))
    g, _ = level0(os.path.join(store, "derived", "g"))
    t = float(np.percentile(g, 85))  # about the published foreground fraction (17 %)
    t = round(t)
    got = check_labels(store, f"gauss(2)|threshold({t})|label(26)", "nuclei",
                       g.astype(np.float64) > t, 26, intensity=vol)
    check_labels(store, f"threshold({t})|label(6)", "raw6", vol > t, 6, intensity=vol)
    # The published segmentation converted into the store's labels: its
    # statistics table is made from its voxels, with the image's means.
    gt_path = os.path.join(DATA, "nuclei-labels-u32.tif")
    published = os.path.join(store, "labels", "published")
    by("convert", "--labels", gt_path, published, "--brick", 32, "--shard", 64, "--quiet")
    gt = tifffile.imread(gt_path)
    compare_stats("convert --labels", read_stats(os.path.join(published, "_brickyard", "labels.csv")),
                  gt, intensity=vol)
    # A sanity figure (not a test): against the published segmentation.
    if got is not None and os.path.exists(gt_path):
        gt = tifffile.imread(gt_path)
        ious = []
        for lab in range(1, int(gt.max()) + 1):
            m = gt == lab
            if not m.any():
                continue
            ours = got[m]
            ours = ours[ours > 0]
            if ours.size == 0:
                ious.append(0.0)
                continue
            best = np.bincount(ours).argmax()
            o = got == best
            ious.append(float(np.sum(m & o)) / float(np.sum(m | o)))
        print(f"sanity: gauss(2)|threshold({t})|label(26) finds {int(got.max())} objects, "
              f"the published segmentation {len(ious)}; mean best-match IoU {np.mean(ious):.3f}, "
              f"{sum(i > 0.5 for i in ious)} of {len(ious)} matched with IoU > 0.5")


def tree_hashes(store):
    """sha256 of every file of the store outside the result's directories."""
    out = {}
    for d, dirs, files in os.walk(store):
        rel = os.path.relpath(d, store)
        if rel.startswith("labels"):
            continue
        for f in files:
            p = os.path.join(d, f)
            out[os.path.relpath(p, store)] = hashlib.sha256(open(p, "rb").read()).hexdigest()
    return out


def case_crash():
    vol = smooth_volume((96, 100, 104), 3)
    store = os.path.join(WORK, "crash.zarr")
    convert(vol, store, 16)
    pipeline = "gauss(2)|threshold(33000)|label(26)"
    before = tree_hashes(store)
    data0 = zarr.open_group(store, mode="r")["0"][...]
    # The reference run, in a copy, for its duration and result.
    ref_store = os.path.join(WORK, "crash_ref.zarr")
    convert(vol, ref_store, 16)
    t0 = time.time()
    by("process", ref_store, pipeline, "--out", "cells", "--quiet", "--memory", "64MiB")
    dur = time.time() - t0
    ref = zarr.open_group(os.path.join(ref_store, "labels", "cells"), mode="r")["0"][...]
    print(f"full run: {dur:.2f} s, {int(ref.max())} labels")
    rnd = random.Random(7)
    for k in range(4):
        delay = rnd.uniform(0.05, 0.9) * dur
        p = subprocess.Popen([BIN, "process", store, pipeline, "--out", "cells", "--quiet",
                              "--memory", "64MiB"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        if k == 3:
            # Kill as soon as the pyramid is being written aside.
            partial = os.path.join(store, "labels", ".cells.new.partial", "0")
            t1 = time.time()
            while not os.path.exists(partial) and time.time() - t1 < 60:
                time.sleep(0.002)
            delay = time.time() - t1
        else:
            time.sleep(delay)
        sig = signal.SIGKILL if k % 2 == 0 or k == 3 else signal.SIGTERM
        p.send_signal(sig)
        out = p.communicate()[0].decode()
        print(f"kill {k}: {sig.name} after {delay:.2f} s -> exit {p.returncode}; {out.strip()[-300:]}")
        if sig == signal.SIGTERM and p.returncode == 0:
            print("  (the job had finished)")
        # The store opens and its existing arrays are unchanged.
        if tree_hashes(store) != before:
            fail(f"kill {k}: files outside labels/ changed")
        if not np.array_equal(zarr.open_group(store, mode="r")["0"][...], data0):
            fail(f"kill {k}: the image reads differently")
        lab = os.path.join(store, "labels")
        if os.path.exists(os.path.join(lab, "zarr.json")):
            listed = zarr.open_group(lab, mode="r").attrs["ome"]["labels"]
            for name in listed:
                if not os.path.exists(os.path.join(lab, name, "zarr.json")):
                    fail(f"kill {k}: labels/zarr.json lists {name}, which does not exist")
        visible = [n for n in os.listdir(lab) if not n.startswith(".")] if os.path.exists(lab) else []
        hidden_after_kill = [n for n in os.listdir(lab) if n.startswith(".")] if os.path.exists(lab) else []
        print(f"  left: {visible + hidden_after_kill}")
        if k == 3 and not hidden_after_kill:
            fail("kill 3 (while writing) left no partial output to clean up: was it killed in time?")
        if sig == signal.SIGTERM and p.returncode != 0:
            if os.path.exists(lab):
                fail(f"kill {k}: SIGTERM left {lab} ({os.listdir(lab)}): the store is not as it was")
            if "as it was" not in out:
                fail(f"kill {k}: SIGTERM: the message does not say the store is as it was: {out!r}")
        # A rerun completes (with --overwrite only if the killed job had published).
        extra = ["--overwrite"] if "cells" in visible else []
        r = by("process", store, pipeline, "--out", "cells", "--memory", "64MiB", "--quiet", *extra)
        if hidden_after_kill and "interrupted run" not in r.stderr:
            fail(f"kill {k}: the rerun did not say what it cleaned up: {r.stderr!r}")
        got = zarr.open_group(os.path.join(lab, "cells"), mode="r")["0"][...]
        if not np.array_equal(got, ref):
            fail(f"kill {k}: the rerun's labels differ from an uninterrupted run")
        left = [n for n in os.listdir(lab) if n.startswith(".")]
        if left:
            fail(f"kill {k}: leftovers after the rerun: {left}")
        # Start the next round from a store without the result.
        subprocess.run(["rm", "-rf", os.path.join(lab)], check=True)
    # Replacing needs --overwrite; the refusal changes nothing.
    by("process", store, pipeline, "--out", "cells", "--quiet")
    r = by("process", store, pipeline, "--out", "cells", "--quiet", check=False)
    if r.returncode == 0 or "--overwrite" not in r.stderr:
        fail(f"a second run without --overwrite: exit {r.returncode}, {r.stderr.strip()!r}")
    # Bad input: a clear error and a non-zero exit, never a panic.
    for args, want in [
        ([store, "gauss(1)|treshold(3)", "--out", "x"], "treshold"),
        ([store, "gauss(-2)", "--out", "x"], "-2"),
        ([os.path.join(WORK, "nope.zarr"), "sobel", "--out", "x"], "nope.zarr"),
        ([store, "sobel", "--out", "../x"], "--out"),
        ([store, "sobel", "--out", "x", "--level", "9"], "level"),
        ([store, "gauss(1um)", "--out", "x"], "unit"),
        ([store, "sobel", "--out", "x", "--stats", "s.csv"], "--stats"),
    ]:
        r = by("process", *args, check=False)
        if r.returncode == 0 or want not in r.stderr or "panicked" in r.stderr:
            fail(f"process {' '.join(args)}: exit {r.returncode}, stderr {r.stderr.strip()!r} "
                 f"(expected a non-zero exit and an error naming {want!r})")


os.makedirs(WORK, exist_ok=True)
{"generated": case_generated, "nuclei": case_nuclei, "crash": case_crash}[CASE]()
if failures:
    print(f"process_{CASE}: FAILED")
    for f in failures:
        print("  - " + f)
    sys.exit(1)
print(f"process_{CASE}: ok")
