#!/usr/bin/env python3
"""`s3://` stores against an independent S3 server (moto's, in process).

Usage: check_s3.py BRICKYARD_BIN WORKDIR

A store with absent (empty) chunks is generated locally, uploaded object by
object with boto3 under a key prefix, and read back by brickyard through
`--s3-endpoint` (path style, signed with the environment's key pair, and
anonymous): `info --json` must equal the local store's, a rendered image
must equal the local render byte for byte, and a missing store must fail
with an error naming the s3:// location. The signature itself is checked
against Amazon's documented example in brickyard-store's unit tests (moto
does not check presigned requests).
"""
import json
import os
import subprocess
import sys

import boto3
from moto.server import ThreadedMotoServer

BIN, WORK = sys.argv[1], sys.argv[2]
os.makedirs(WORK, exist_ok=True)
failures = []


def fail(msg):
    print("  - " + msg)
    failures.append(msg)


def by(args, env=None):
    e = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
    e.update(env or {})
    print("+ brickyard " + " ".join(args), flush=True)
    return subprocess.run([BIN] + args, capture_output=True, text=True, env=e, timeout=600)


def info(loc, extra, env=None):
    r = by(["info", loc, "--json"] + extra, env)
    if r.returncode != 0:
        fail(f"info {loc}: {r.stderr.strip()}")
        return None
    v = json.loads(r.stdout)
    v["path"] = None
    for lv in v["levels"]:
        lv["bytes_on_disk"] = None
    return v


store = os.path.join(WORK, "m.ome.zarr")
r = by(["generate", "mandelbulb", store, "--size", "96", "--dtype", "u16",
        "--brick", "16", "--shard", "32", "--quiet"])
assert r.returncode == 0, r.stderr
files = []
for d, _, fs in os.walk(store):
    for f in fs:
        files.append(os.path.join(d, f))
print(f"store: {len(files)} files")

srv = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
srv.start()
host, port = srv.get_host_and_port()
ep = f"http://{host}:{port}"
keys = {"AWS_ACCESS_KEY_ID": "AKIDEXAMPLE",
        "AWS_SECRET_ACCESS_KEY": "wJalrXUtnFEMI/K7MDENG+bPxRfiCYEXAMPLEKEY"}
try:
    s3 = boto3.client("s3", endpoint_url=ep, region_name="us-east-1",
                      aws_access_key_id=keys["AWS_ACCESS_KEY_ID"],
                      aws_secret_access_key=keys["AWS_SECRET_ACCESS_KEY"])
    s3.create_bucket(Bucket="volumes")
    for f in files:
        key = "lab/2026/" + os.path.relpath(f, os.path.dirname(store))
        s3.upload_file(f, "volumes", key)
    loc = "s3://volumes/lab/2026/m.ome.zarr"
    local = info(store, [])
    flags = ["--s3-endpoint", ep]
    # Private: an unsigned read is refused, and the error says why.
    r = by(["info", loc, "--s3-anonymous"] + flags)
    if r.returncode == 0 or "403" not in r.stderr or "unsigned" not in r.stderr:
        fail(f"anonymous read of a private bucket: exit {r.returncode}, {r.stderr.strip()!r}")
    else:
        print("private bucket, unsigned: " + r.stderr.strip())
    # Then public for reading (a bucket policy), as open data buckets are.
    s3.put_bucket_policy(Bucket="volumes", Policy=json.dumps({
        "Version": "2012-10-17",
        "Statement": [{"Effect": "Allow", "Principal": "*", "Action": "s3:GetObject",
                       "Resource": "arn:aws:s3:::volumes/*"}]}))
    for name, env, extra in [("signed", keys, flags),
                             ("anonymous, public bucket", {}, flags + ["--s3-anonymous"]),
                             ("endpoint from AWS_ENDPOINT_URL",
                              dict(keys, AWS_ENDPOINT_URL=ep, AWS_REGION="eu-central-1"), [])]:
        remote = info(loc, extra, env)
        if remote is not None and remote != local:
            fail(f"{name}: info of {loc} differs from the local store's")
        a, b = os.path.join(WORK, "local.png"), os.path.join(WORK, f"s3-{len(failures)}.png")
        common = ["--size", "96x80", "--backend", "cpu", "--quiet", "--pool", "4MiB"]
        r1 = by(["render", store, "-o", a] + common)
        r2 = by(["render", loc, "-o", b] + common + extra, env)
        if r1.returncode or r2.returncode:
            fail(f"{name}: render failed: {r1.stderr.strip()} {r2.stderr.strip()}")
            continue
        if "could not load" in r2.stdout:
            fail(f"{name}: bricks failed over S3: {r2.stdout.strip()}")
        pa, pb = open(a, "rb").read(), open(b, "rb").read()
        if pa != pb:
            fail(f"{name}: the image read over S3 differs from the local one")
        else:
            print(f"{name}: info and a 96x80 render equal the local store's")
    r = by(["info", "s3://volumes/lab/none.ome.zarr"] + flags, keys)
    if r.returncode == 0 or "s3://volumes/lab/none.ome.zarr" not in r.stderr:
        fail(f"a missing store: exit {r.returncode}, {r.stderr.strip()!r}")
finally:
    srv.stop()

if failures:
    print(f"check_s3: FAILED ({len(failures)})")
    for f in failures:
        print("  - " + f)
    sys.exit(1)
print("check_s3: ok")
