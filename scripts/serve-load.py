#!/usr/bin/env python3
"""Load test of `brickyard serve` on loopback: N clients (threads, one
keep-alive connection each) fetch random inner chunks (byte ranges read
from the shard indexes) of a served store for T seconds. Prints one JSON
line: requests, errors, bytes, p50/p99/max latency, and the server's peak
RSS (VmHWM of its process).

Usage: serve-load.py STORE_DIR PORT SERVER_PID [--clients 16] [--seconds 10]
"""
import argparse, http.client, json, os, random, struct, threading, time

ap = argparse.ArgumentParser()
ap.add_argument("store")
ap.add_argument("port", type=int)
ap.add_argument("pid", type=int)
ap.add_argument("--clients", type=int, default=16)
ap.add_argument("--seconds", type=float, default=10.0)
a = ap.parse_args()

name = os.path.basename(os.path.normpath(a.store))
chunks = []  # (url path, offset, length)
for root, _, files in os.walk(a.store):
    if "/c" not in root.replace(a.store, "") or "_brickyard" in root:
        continue
    for f in files:
        p = os.path.join(root, f)
        data = open(p, "rb").read()
        # Count entries: the index (16 B each + 4 B CRC) at the end, found
        # by the entries that lie inside the file.
        rel = "/" + name + "/" + os.path.relpath(p, a.store)
        size = len(data)
        for n in (512, 64, 8, 1):
            ib = n * 16 + 4
            if ib > size:
                continue
            idx = data[size - ib : size - 4]
            ents = [struct.unpack_from("<QQ", idx, 16 * i) for i in range(n)]
            ok = [e for e in ents if e != (2**64 - 1, 2**64 - 1)]
            if ok and all(o + l <= size - ib for o, l in ok):
                chunks += [(rel, o, l) for o, l in ok]
                break
assert chunks, "no chunks found under " + a.store

lat, errors, nbytes = [], [0], [0]
lock = threading.Lock()
stop = time.time() + a.seconds


def client(seed):
    rnd = random.Random(seed)
    conn = http.client.HTTPConnection("127.0.0.1", a.port, timeout=30)
    mine, errs, got = [], 0, 0
    while time.time() < stop:
        path, o, l = rnd.choice(chunks)
        t = time.perf_counter()
        try:
            conn.request("GET", path, headers={"Range": f"bytes={o}-{o + l - 1}"})
            r = conn.getresponse()
            body = r.read()
            if r.status != 206 or len(body) != l:
                errs += 1
            got += len(body)
        except Exception:
            errs += 1
            conn.close()
            conn = http.client.HTTPConnection("127.0.0.1", a.port, timeout=30)
        mine.append(time.perf_counter() - t)
    with lock:
        lat.extend(mine)
        errors[0] += errs
        nbytes[0] += got


ts = [threading.Thread(target=client, args=(i,)) for i in range(a.clients)]
t0 = time.time()
for t in ts:
    t.start()
for t in ts:
    t.join()
wall = time.time() - t0
lat.sort()
q = lambda f: lat[min(len(lat) - 1, int(f * len(lat)))] * 1e3
hwm = None
for line in open(f"/proc/{a.pid}/status"):
    if line.startswith("VmHWM:"):
        hwm = int(line.split()[1]) / 1024
print(json.dumps({
    "scenario": "serve-load", "clients": a.clients, "seconds": round(wall, 2),
    "chunks": len(chunks), "requests": len(lat), "errors": errors[0],
    "requests_per_s": round(len(lat) / wall, 1), "mb_per_s": round(nbytes[0] / wall / 1e6, 1),
    "p50_ms": round(q(0.5), 2), "p99_ms": round(q(0.99), 2), "max_ms": round(lat[-1] * 1e3, 2),
    "server_peak_rss_mib": hwm,
}))
