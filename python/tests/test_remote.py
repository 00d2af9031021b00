"""brickyard.open on http:// URLs: a store served by `brickyard serve` reads as it does from disk."""

import re
import subprocess

import numpy as np
import pytest
import zarr

import brickyard
from conftest import brickyard_bin, volume


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A store on disk and its URL, served by `brickyard serve` on a free loopback port."""
    root = tmp_path_factory.mktemp("serve")
    local = root / "remote.ome.zarr"
    a = np.stack([volume((41, 50, 67), "int16", seed=21), volume((41, 50, 67), "int16", seed=22)])
    brickyard.from_numpy(a, local, spacing=(2.0, 0.5, 0.5), brick=16, shard=32, progress=False)
    p = subprocess.Popen([str(brickyard_bin()), "serve", str(local), "--port", "0", "--quiet"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        first = p.stderr.readline()
        m = re.search(r"at (http://127\.0\.0\.1:\d+)/", first)
        assert m, f"brickyard serve printed {first!r}"
        yield a, local, f"{m.group(1)}/remote.ome.zarr"
    finally:
        p.terminate()
        p.wait(timeout=10)


def test_url_reads_equal_local_reads(served):
    a, local, url = served
    s = brickyard.open(url, brick=16, cache=1 << 20)
    here = brickyard.open(local, brick=16)
    assert s.path == url
    assert s.shapes == here.shapes and s.levels >= 3
    assert s.channels == 2 and s.dtype == np.int16
    assert s.scales == here.scales and s.axes == here.axes
    np.testing.assert_array_equal(s.read(0, 1), a[1])
    rng = np.random.default_rng(3)
    for level in range(s.levels):
        ref = zarr.open_array(str(local / str(level)), mode="r")
        shape = s.shapes[level]
        for _ in range(5):
            lo = [int(rng.integers(0, n)) for n in shape]
            hi = [int(rng.integers(l + 1, n + 1)) for l, n in zip(lo, shape)]
            r = tuple(slice(l, h) for l, h in zip(lo, hi))
            c = int(rng.integers(0, 2))
            got = s.read(level, c, r)
            np.testing.assert_array_equal(got, here.read(level, c, r))
            np.testing.assert_array_equal(got, ref[(c,) + r])
    assert s.cache_stats()["bytes_read"] > 0


def test_url_renders_as_local(served):
    _, local, url = served
    kw = dict(mode="mip", backend="cpu", size=(48, 40), channel=["0:red", "1:green"])
    np.testing.assert_array_equal(brickyard.render(url, **kw), brickyard.render(local, **kw))


def test_missing_url_names_it(served):
    _, _, url = served
    bad = url.replace("remote.ome.zarr", "nowhere.ome.zarr")
    with pytest.raises(FileNotFoundError, match=re.escape(bad) + ".*404"):
        brickyard.open(bad)


def test_a_server_gone_mid_session_is_an_os_error(tmp_path):
    # The store cannot be read any more: OSError, as when `open` cannot
    # reach it (a read raised ValueError), within a bounded time.
    import time

    local = tmp_path / "gone.ome.zarr"
    a = volume((40, 48, 64), "uint16", seed=5)
    brickyard.from_numpy(a, local, brick=16, shard=32, progress=False)
    p = subprocess.Popen([str(brickyard_bin()), "serve", str(local), "--port", "0", "--quiet"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        m = re.search(r"at (http://127\.0\.0\.1:\d+)/", p.stderr.readline())
        assert m
        s = brickyard.open(f"{m.group(1)}/gone.ome.zarr", brick=16, cache=1 << 20)
        np.testing.assert_array_equal(s.read(0, 0, np.s_[0:8, 0:8, 0:8]), a[0:8, 0:8, 0:8])
    finally:
        p.terminate()
        p.wait(timeout=10)
    t0 = time.monotonic()
    with pytest.raises(OSError, match="gone.ome.zarr"):
        s.read(0, 0, np.s_[30:40, 40:48, 48:64])
    assert time.monotonic() - t0 < 30


def test_open_of_a_server_that_never_answers_is_interruptible():
    # A server that takes connections and never answers: `open` waited for
    # it (about 65 s) and Ctrl-C did nothing meanwhile.
    import signal
    import socket
    import threading
    import time
    import _thread

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    held = []

    def accept():
        while True:
            try:
                held.append(server.accept()[0])
            except OSError:
                return

    threading.Thread(target=accept, daemon=True).start()
    url = f"http://127.0.0.1:{server.getsockname()[1]}/hung.ome.zarr"
    # Python's own SIGINT handler, whatever the test runner inherited.
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(1.0, _thread.interrupt_main)
    t0 = time.monotonic()
    try:
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            brickyard.open(url)
        seconds = time.monotonic() - t0
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, old)
        try:
            server.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        server.close()
        for c in held:
            c.close()
    assert held, "open never reached the server: the test would prove nothing"
    assert 0.9 < seconds < 5, f"KeyboardInterrupt after {seconds:.1f} s"
