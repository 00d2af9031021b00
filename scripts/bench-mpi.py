#!/usr/bin/env python3
"""MPI scaling of brickyard (the `mpi` feature): conversion, image- and
data-parallel rendering on 1 and 2 ranks, and sort-last compositing time per
frame against image size and rank count. Prints one JSON line per
measurement; BENCHMARKS.md has the tables made from them.

Usage: python3 scripts/bench-mpi.py BRICKYARD WORKDIR [REPEATS]

`mpirun -n N` binds each rank to a core when N is at most the core count
(OpenMPI's default), so one rank draws on one core and two ranks on two:
that is the 1 → 2 scaling measured here. One process without mpirun (all
cores, threads) is measured beside it for reference.
"""
import json
import os
import resource
import re
import statistics
import subprocess
import sys
import time

B, WORK = sys.argv[1], sys.argv[2]
REPEATS = int(sys.argv[3]) if len(sys.argv) > 3 else 3
ENV = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
os.makedirs(WORK, exist_ok=True)


CPU = [0.0]


def run(cmd):
    """Wall time and stdout; CPU[0] gets the CPU seconds (user + system) of
    the command and everything it started (the ranks)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.run(cmd, env=ENV, capture_output=True, text=True)
    wall = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    CPU[0] = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    if p.returncode != 0:
        sys.exit(f"failed: {' '.join(cmd)}\n{p.stdout}\n{p.stderr}")
    return wall, p.stdout


def mpi(n, args):
    return ["mpirun", "--oversubscribe", "-n", str(n), B] + args


def emit(**kw):
    print(json.dumps(kw), flush=True)


def median_of(fn):
    def with_cpu():
        v = fn()
        v["cpu_s"] = CPU[0]
        return v
    vals = [with_cpu() for _ in range(REPEATS)]
    out = {k: statistics.median(v[k] for v in vals) for k in vals[0]}
    out["load_avg"] = os.getloadavg()[0]
    return out


# The volume: a 1024³ u8 Mandelbulb (1 GiB), shards of 256: level 0 has 4×4
# shard columns, the first pass (levels 0 and 1) 2×2 columns of equal size.
raw = os.path.join(WORK, "m1024.raw")
if not os.path.exists(raw):
    run([B, "generate", "mandelbulb", raw, "--size", "1024", "--dtype", "u8", "--quiet"])
conv = ["--brick", "64", "--shard", "256", "--columns", "4", "--quiet", "--json", "--overwrite"]


def convert(prefix, out):
    def one():
        wall, so = run(prefix + ["convert", raw, out] + conv)
        return {"wall_s": wall, "builder_s": json.loads(so)["seconds"]}
    return median_of(one)


single = convert([B], os.path.join(WORK, "c-single.ome.zarr"))
emit(what="convert", ranks="process (2 threads)", **single)
by_n = {}
for n in (1, 2):
    r = convert(mpi(n, []), os.path.join(WORK, f"c-{n}.ome.zarr"))
    by_n[n] = r
    emit(what="convert", ranks=n, **r)
emit(what="convert", efficiency_builder=by_n[1]["builder_s"] / (2 * by_n[2]["builder_s"]),
     efficiency_wall=by_n[1]["wall_s"] / (2 * by_n[2]["wall_s"]),
     work_ratio_cpu=by_n[1]["cpu_s"] / by_n[2]["cpu_s"])
same = subprocess.run(["diff", "-rq", os.path.join(WORK, "c-single.ome.zarr"), os.path.join(WORK, "c-2.ome.zarr")],
                      capture_output=True, text=True)
emit(what="convert", byte_identical_1_process_vs_2_ranks=same.returncode == 0)

store = os.path.join(WORK, "c-single.ome.zarr")
png = os.path.join(WORK, "r.png")


def seconds_line(so):
    m = re.search(r"view 0: .*?; (\d+) frames, ([0-9.]+) s", so)
    return float(m.group(2)) if m else float("nan")


def render(prefix, extra):
    def one():
        wall, so = run(prefix + ["render", store, "--size", "1024x1024", "--out", png, "--quiet"] + extra)
        c = re.search(r"composited \d+ ranks \(.*?\) in ([0-9.]+) ms", so)
        return {"wall_s": wall, "draw_s": seconds_line(so), "composite_ms": float(c.group(1)) if c else 0.0}
    return median_of(one)


for mode in ("dvr", "mip"):
    base = ["--mode", mode]
    r = render([B], base + ["--backend", "cpu"])
    emit(what="render", split="process (2 threads)", mode=mode, **r)
    for split, extra in (("image", []), ("data", ["--no-early-termination"])):
        res = {}
        for n in (1, 2):
            res[n] = render(mpi(n, []), base + ["--distribute", split] + (extra if n == 1 else []))
            emit(what="render", split=split, mode=mode, ranks=n, **res[n])
        emit(what="render", split=split, mode=mode,
             efficiency_wall=res[1]["wall_s"] / (2 * res[2]["wall_s"]),
             efficiency_draw=res[1]["draw_s"] / (2 * res[2]["draw_s"]),
             work_ratio_cpu=res[1]["cpu_s"] / res[2]["cpu_s"])

# Compositing per frame: a small store (rendering is quick), DVR sort-last.
small = os.path.join(WORK, "m128.ome.zarr")
if not os.path.exists(small):
    run([B, "generate", "mandelbulb", small, "--size", "128", "--dtype", "u16", "--quiet"])
for n in (2, 3, 4):
    for size in (256, 512, 1024, 2048):
        def one():
            wall, so = run(mpi(n, ["render", small, "--size", f"{size}x{size}", "--distribute", "data",
                                   "--out", png, "--quiet"]))
            c = re.search(r"composited \d+ ranks \((.*?)\) in ([0-9.]+) ms", so)
            return {"composite_ms": float(c.group(2))}
        r = median_of(one)
        emit(what="composite", ranks=n, pixels=size * size, schedule="binary swap" if n in (2, 4) else "direct send", **r)
