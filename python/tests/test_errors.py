"""Bad inputs raise the right exceptions, with messages that say what is wrong."""

import re
import warnings

import numpy as np
import pytest

import brickyard
from conftest import volume


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    dst = tmp_path_factory.mktemp("errors") / "e.ome.zarr"
    brickyard.from_numpy(volume((20, 24, 28), "uint8"), dst, brick=16, shard=32, progress=False)
    return dst


def test_missing_store(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.ome.zarr"):
        brickyard.open(tmp_path / "nowhere.ome.zarr")
    with pytest.raises(FileNotFoundError, match="nowhere"):
        brickyard.render(tmp_path / "nowhere", backend="cpu")
    with pytest.raises(FileNotFoundError, match="nowhere.tif"):
        brickyard.convert(tmp_path / "nowhere.tif", tmp_path / "out.ome.zarr", progress=False)
    # As the CLI says it: an unknown scheme, what an interrupted conversion left.
    with pytest.raises(FileNotFoundError, match="ftp:// is no scheme stores are read from"):
        brickyard.open("ftp://127.0.0.1/x.ome.zarr")
    (tmp_path / "kc.ome.zarr.partial").mkdir()
    with pytest.raises(FileNotFoundError, match="is what an interrupted conversion of it wrote"):
        brickyard.open(tmp_path / "kc.ome.zarr")


def test_not_a_store(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises((ValueError, OSError), match="empty"):
        brickyard.open(tmp_path / "empty")


def test_wrong_regions(store):
    s = brickyard.open(store)
    with pytest.raises(IndexError, match="outside axis z of length 20"):
        s[20]
    with pytest.raises(IndexError, match="at most 3 axes"):
        s.read(region=np.s_[0, 0, 0, 0])
    with pytest.raises(ValueError, match="step cannot be zero"):
        s[::0]
    with pytest.raises(TypeError, match="must be integers or None"):
        s[0:2.5]
    with pytest.raises(TypeError, match="expected an int or a slice"):
        s["a"]
    with pytest.raises(IndexError, match="level: 9 asked for but the store has"):
        s.read(level=9)
    with pytest.raises(IndexError, match="channel: 1 asked for but the store has 1 channel"):
        s.read(channel=1)
    # The native layer checks too (the Python layer is bypassed here).
    with pytest.raises(ValueError, match="outside level 0"):
        s._native.read(0, 0, (0, 0, 0), (21, 1, 1))


class _Lazy:
    """An array read region by region (as dask or zarr arrays are)."""

    def __init__(self, a):
        self.a, self.shape, self.dtype = a, a.shape, a.dtype

    def __getitem__(self, key):
        return self.a[key]


def test_wrong_dtype_and_shape(tmp_path):
    with pytest.raises(TypeError, match="dtype complex128 is not stored by brickyard"):
        brickyard.from_numpy(np.zeros((4, 4, 4), np.complex128), tmp_path / "c.ome.zarr", progress=False)
    # 64-bit integers whose values do not fit 32 bits: named, nothing written.
    big = np.zeros((4, 4, 4), np.int64)
    big[1, 2, 3] = 1 << 40
    with pytest.raises(ValueError, match="int64 value 1099511627776 does not fit int32"):
        brickyard.from_numpy(big, tmp_path / "b.ome.zarr", progress=False)
    with pytest.raises(ValueError, match=r"value 1099511627776 in \[0:4, 0:4, 0:4\] of channel 0 does not fit"):
        brickyard.from_numpy(_Lazy(big), tmp_path / "b.ome.zarr", progress=False)
    assert not (tmp_path / "b.ome.zarr").exists()
    with pytest.raises(ValueError, match="expected \\(z, y, x\\) or \\(c, z, y, x\\)"):
        brickyard.from_numpy(np.zeros((4, 4)), tmp_path / "d.ome.zarr", progress=False)
    for bad in ("gzip", "zstd:abc", "zstd:99"):
        with pytest.raises(ValueError, match="compression: expected lz4"):
            brickyard.from_numpy(np.zeros((4, 4, 4), np.uint8), tmp_path / "z.ome.zarr", compression=bad,
                                 progress=False)


def test_spacing_and_origin_that_are_no_geometry(tmp_path):
    # Spacings not positive and origins not finite were written as 1 and as
    # null (invalid OME-Zarr); nothing is left behind.
    a = np.zeros((4, 4, 4), np.uint8)
    for kw, field in [({"spacing": 0}, "spacing"), ({"spacing": (-1, 1, 1)}, "spacing"),
                      ({"spacing": float("nan")}, "spacing"), ({"origin": float("inf")}, "origin")]:
        dst = tmp_path / f"{field}.ome.zarr"
        with pytest.raises(ValueError, match=field):
            brickyard.from_numpy(a, dst, progress=False, **kw)
        assert not dst.exists()


def test_existing_output_is_refused(store, tmp_path):
    with pytest.raises((ValueError, OSError), match="exists"):
        brickyard.from_numpy(np.zeros((4, 4, 4), np.uint8), store, progress=False)


def test_bad_render_options(store):
    with pytest.raises(ValueError, match="mode: expected dvr, mip or slice"):
        brickyard.render(store, mode="iso")
    with pytest.raises(ValueError, match="backend: expected auto, cpu or gpu"):
        brickyard.render(store, backend="tpu")
    with pytest.raises(ValueError, match="tf: "):
        brickyard.render(store, tf="nonsense", backend="cpu")
    with pytest.raises(ValueError, match="opacity"):
        brickyard.render(store, tf={"window": [0, 1], "opacity": [[2.0, 1.0]]}, backend="cpu")
    with pytest.raises(ValueError, match="size"):
        brickyard.render(store, size=(0, 10), backend="cpu")
    with pytest.raises(IndexError, match="level: the store has"):
        brickyard.render(store, level=40, backend="cpu")
    with pytest.raises(TypeError, match="unexpected keyword argument 'no_such_option'"):
        brickyard.render(store, backend="cpu", no_such_option=3)


def test_level_and_channel_outside_the_store_are_index_errors(store, tmp_path):
    # As for reads: IndexError with the CLI's message in `process` and
    # `render` too (they raised ValueError), and for negative or huge
    # numbers also (they raised OverflowError, or a parse error of the
    # flag), naming the option.
    def proc(**kw):
        brickyard.process(store, "sobel", out="s", progress=False, **kw)

    with pytest.raises(IndexError, match="level 2 asked for but the image has 2 levels"):
        proc(level=2)
    with pytest.raises(IndexError, match="channel: 1 asked for but .* has 1 channel"):
        proc(channel=1)
    with pytest.raises(IndexError, match="channel: 1 asked for but the store has 1 channel"):
        brickyard.render(store, channel=1, backend="cpu")
    with pytest.raises(IndexError, match="channel: 3 asked for but the store has 1 channel"):
        brickyard.render(store, channel=["0:red", "3:green"], backend="cpu")
    with pytest.raises(IndexError, match="channel_levels: .*the store has 2 levels"):
        brickyard.render(store, channel=[0], channel_levels={0: (0, 5)}, backend="cpu")
    with pytest.raises(IndexError, match="level 7 asked for but the image has 2 levels"):
        brickyard.convert(store, tmp_path / "c.ome.zarr", level=7, progress=False)
    for bad in (-1, -(2**70), 2**64, 2**70):
        for what, call in [("level", lambda v: proc(level=v)), ("channel", lambda v: proc(channel=v)),
                           ("level", lambda v: brickyard.render(store, level=v, backend="cpu")),
                           ("channel", lambda v: brickyard.render(store, channel=v, backend="cpu")),
                           ("channel", lambda v: brickyard.render(store, channel=[f"{v}:red"], backend="cpu")),
                           ("level", lambda v: brickyard.convert(store, tmp_path / "c.ome.zarr", level=v,
                                                                 progress=False))]:
            with pytest.raises(IndexError, match=f"^{what}: {bad} is outside the store"):
                call(bad)
    # Not integers at all: TypeError, as for reads.
    with pytest.raises(TypeError, match="level: expected an integer"):
        proc(level=1.5)
    with pytest.raises(TypeError, match="channel: expected an integer"):
        proc(channel="0")
    assert not (store / "derived").exists() and not (tmp_path / "c.ome.zarr").exists()


def test_messages_name_python_keywords(store, tmp_path):
    # The CLI's messages name its flags; from Python they name the
    # keyword arguments instead (the rest of the text is the CLI's).
    with pytest.raises(ValueError) as e:
        brickyard.from_numpy(np.zeros((4, 4, 4), np.uint8), store, progress=False)
    assert str(e.value) == f"{store}: output exists; pass overwrite=True to replace it"
    brickyard.from_numpy(np.zeros((4, 4, 4), np.uint8), tmp_path / "a--b.ome.zarr", progress=False)
    with pytest.raises(ValueError) as e:
        brickyard.convert(tmp_path / "a--b.ome.zarr", tmp_path / "a--b.ome.zarr", progress=False)
    # (A path is left as it is.)
    assert str(e.value).endswith("a--b.ome.zarr: output exists; pass overwrite=True to replace it"), e.value
    with pytest.raises(ValueError) as e:
        brickyard.render(store, memory="10MiB", pool="9MiB", backend="cpu")
    # (The images take over a quarter of the budget: a smaller one helps too.)
    assert re.search(r"; raise memory= \(\d+MiB holds it\) or lower pool=/host= or draw a smaller image$", str(e.value)), e.value
    with pytest.raises(ValueError) as e:
        brickyard.render(store, channel=[0], channel_tf={1: "hot"}, backend="cpu")
    assert str(e.value) == ("channel_tf: transfer functions per channel are for dvr of several channels; this "
                            "store has one channel: give its transfer function with tf="), e.value
    with pytest.raises(ValueError) as e:
        brickyard.render(store, derive="gauss(1)", channel=[0, 0], backend="cpu")
    assert str(e.value) == "derive: a derived channel is computed from one channel; give at most one channel="
    # The command line's parser: the option by its keyword, no advice about --help.
    with pytest.raises(ValueError) as e:
        brickyard.render(store, size=16, backend="cpu", lod_bias="x")
    assert str(e.value) == "lod_bias: invalid value 'x': invalid float literal", e.value
    with pytest.raises(ValueError) as e:
        brickyard.render(store, size=16, backend="cpu", turntable=0)
    assert str(e.value) == "turntable: expected 1 to 3600 views, found 0", e.value
    with pytest.raises(ValueError) as e:
        brickyard.render(store, size=16, backend="cpu", memory=-5)
    assert str(e.value).startswith("memory: expected a size"), e.value
    # Whole numbers, file names and sequences checked as Python has them.
    for k, v in (("level", "x"), ("level", 1.5), ("turntable", True), ("read_delay_ms", 2.0)):
        with pytest.raises(TypeError, match=f"^{k}: expected a whole number, found"):
            brickyard.render(store, size=16, backend="cpu", **{k: v})
    with pytest.raises(ValueError, match="^read_delay_ms: expected a whole number, 0 or more, found -1"):
        brickyard.render(store, size=16, backend="cpu", read_delay_ms=-1)
    with pytest.raises(TypeError, match="^save_camera: expected a file name, found dict"):
        brickyard.render(store, size=16, backend="cpu", save_camera={})
    with pytest.raises(ValueError, match="^only_labels, hide_labels: give one or the other"):
        brickyard.render(store, size=16, backend="cpu", only_labels=[1], hide_labels=[2])
    with pytest.raises(ValueError, match="^threads: expected 1 to 1024 threads, found 0"):
        brickyard.render(store, size=16, backend="cpu", threads=0)
    np.testing.assert_array_equal(brickyard.render(store, size=16, backend="cpu", window=np.array([0, 90])),
                                  brickyard.render(store, size=16, backend="cpu", window=(0, 90), threads=1))
    with pytest.raises(TypeError) as e:
        brickyard.render(store, backend="cpu", no_such_option=3)
    assert str(e.value) == "render: unexpected keyword argument 'no_such_option'", e.value
    # A flag with its value: the keyword with that value.
    with pytest.raises(ValueError) as e:
        brickyard.render(store, mode="slice", ortho=True, backend="cpu")
    assert str(e.value).startswith('ortho: applies to mode="dvr" and mip only; a slice is seen face on (move '
                                   'its plane with slice_z=, slice_origin= or slice_normal=, or give the camera '
                                   'with camera=)'), e.value
    # A message about a flag starts with its keyword; a placeholder and a
    # preset are the keyword's value; a command line in backquotes is
    # left as the command it is.
    with pytest.raises(ValueError) as e:
        brickyard.render(store, mode="slice", label_opacity=2, backend="cpu")
    assert str(e.value).startswith("label_opacity: applies with labels=NAME"), e.value
    with pytest.raises(ValueError) as e:
        brickyard.render(store, only_labels=[1], backend="cpu")
    assert str(e.value) == ('only_labels: applies to a label image\'s colours (a store\'s labels/NAME, '
                            'tf="labels", or labels=NAME over a slice)'), e.value
    with pytest.raises(ValueError) as e:
        brickyard.render(store, mode="slice", derive="gauss(1)|label(6)", backend="cpu")
    assert "`brickyard process STORE PIPELINE --out NAME`" in str(e.value), e.value


def test_every_render_flag_is_translated(cli):
    # Messages name flags by the table of brickyard/__init__.py: each of
    # `brickyard render`'s flags (every one a keyword of `render`) is in
    # it, as are those of `convert` and `process` that are keywords there.
    import re

    text = cli("render", "--help")
    flags = set(re.findall(r"^\s+(?:-\w, )?--([a-z][a-z0-9-]*)", text, re.M))
    assert {"mode", "out", "memory", "raw-f32"} <= flags, flags
    # (The command line's own, global flags are not `render`'s.)
    flags -= {"help", "threads", "s3-endpoint", "s3-region", "s3-anonymous"}
    assert flags <= brickyard._FLAGS, sorted(flags - brickyard._FLAGS)
    keywords = {"brick", "shard", "compression", "labels", "memory", "overwrite", "spacing", "origin", "unit",
                "level", "out", "channel", "stats", "backend"}
    assert keywords <= brickyard._FLAGS
    # The switches: the flags that `--help` shows without a value.
    switches = set(re.findall(r"^\s+--([a-z][a-z0-9-]*)\s*$", text, re.M))
    assert {"ortho", "raw-f32"} <= switches == brickyard._SWITCHES["render"] <= flags, switches
    assert brickyard._SWITCHES["convert"] == {"overwrite", "labels"}
    assert brickyard._SWITCHES["process"] == {"overwrite"}


def test_a_store_replaced_since_it_was_opened_is_refused_not_mixed(tmp_path):
    # A handle kept across `from_numpy(..., overwrite=True)`: its cached
    # bricks were the old store's, the rest came from the new one (or
    # failed as "corrupt" chunks). Now: an OSError saying to open it again.
    p = tmp_path / "r.zarr"
    a = np.random.default_rng(0).integers(0, 1000, (96, 96, 96), dtype=np.uint16)
    brickyard.from_numpy(a, p, compression="none", progress=False)
    s = brickyard.open(p)
    assert (s.read(region=np.s_[0:1, 0:1, 0:1]) == a[0:1, 0:1, 0:1]).all()
    brickyard.from_numpy(a + 5000, p, compression="none", overwrite=True, progress=False)
    with pytest.raises(OSError, match="replaced or removed since it was opened"):
        s.read()
    # Opened again: the new store, whole.
    assert (brickyard.open(p).read() == a + 5000).all()


def test_render_says_when_bricks_could_not_be_loaded(tmp_path):
    # A damaged store: the image comes back (drawn from what could be
    # read), with a RuntimeWarning saying what is missing; it used to come
    # back silently.
    p = tmp_path / "d.zarr"
    v = (np.random.default_rng(0).random((96, 96, 96)) * 255).astype(np.uint8)
    brickyard.from_numpy(v, p, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        brickyard.render(p, backend="cpu", size=32, level=0)
    for f in (p / "0").rglob("*"):
        if f.is_file() and f.name != "zarr.json":
            with open(f, "r+b") as fh:
                fh.truncate(10)
    with pytest.warns(RuntimeWarning, match="could not be loaded"):
        brickyard.render(p, backend="cpu", size=32, level=0)
    # Every level damaged: nothing to draw from, an error (it was a black
    # image).
    for f in p.rglob("*"):
        if f.is_file() and f.name != "zarr.json" and "_brickyard" not in f.parts:
            with open(f, "r+b") as fh:
                fh.truncate(10)
    with pytest.raises(ValueError, match="no data at any level"):
        brickyard.render(p, backend="cpu", size=32, level=0)


def test_render_takes_paths_that_start_with_a_dash_and_checks_its_size(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    brickyard.from_numpy(np.full((24, 24, 24), 200, np.uint8), "-dash.zarr", progress=False)
    img = brickyard.render("-dash.zarr", backend="cpu", size=16)
    assert img.shape == (16, 16, 4)
    for bad in ["64x64", (1, 2, 3), (-5, 10), (16.5, 16), True]:
        with pytest.raises(ValueError, match="size: expected N or"):
            brickyard.render("-dash.zarr", backend="cpu", size=bad)


def test_ctrl_c_in_a_progress_callback_stops_the_conversion(tmp_path):
    # A KeyboardInterrupt raised while the callback runs (here: raised by
    # it) used to be printed and the conversion went on to the end.
    v = np.random.default_rng(1).integers(0, 60000, (128, 256, 256), dtype=np.uint16)
    dst = tmp_path / "c.zarr"
    calls = []

    def progress(kind, n):
        calls.append(kind)
        if kind == "inc":
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt, match="conversion interrupted$"):
        brickyard.from_numpy(v, dst, progress=progress, memory=64 << 20)
    assert calls.count("inc") == 1, calls
    assert not dst.exists() and not (tmp_path / "c.zarr.partial").exists()


def test_an_exception_in_a_progress_callback_cancels_the_job_and_is_raised(store, tmp_path):
    # A notebook's or GUI's cancel button raises from the callback: the job
    # stops, nothing is published, and the callback's own exception comes
    # out (it used to be printed while the job went on and published).
    class Cancel(Exception):
        pass

    calls = []

    def cancel(kind, n):
        calls.append(kind)
        if kind == "inc":
            raise Cancel("cancelled by the user")

    v = np.random.default_rng(2).integers(0, 60000, (128, 256, 256), dtype=np.uint16)
    dst = tmp_path / "n.ome.zarr"
    with pytest.raises(Cancel, match="cancelled by the user"):
        brickyard.from_numpy(v, dst, progress=cancel, memory=64 << 20)
    assert calls.count("inc") == 1, calls
    assert not dst.exists() and not (tmp_path / "n.ome.zarr.partial").exists()
    before = sorted(p.relative_to(store) for p in store.rglob("*"))
    calls.clear()
    with pytest.raises(Cancel, match="cancelled by the user"):
        brickyard.process(store, "gauss(1)", out="cancelled", progress=cancel)
    assert "inc" in calls, calls
    assert sorted(p.relative_to(store) for p in store.rglob("*")) == before
    # The store takes the same job afterwards.
    brickyard.process(store, "gauss(1)", out="cancelled", progress=False)
    assert (store / "derived" / "cancelled").is_dir()


def test_a_shard_file_gone_is_an_oserror(tmp_path):
    # As the README says for a file gone (it was a ValueError).
    p = tmp_path / "g.zarr"
    v = np.random.default_rng(2).integers(1, 200, (64, 64, 64), dtype=np.uint8)
    brickyard.from_numpy(v, p, progress=False)
    s = brickyard.open(p)
    for f in (p / "0" / "c").rglob("*"):
        if f.is_file():
            f.unlink()
    with pytest.raises(OSError, match="the file is missing, but the statistics say"):
        s.read()


def test_render_names_dicts_as_given_not_by_their_temporary_files(store):
    cam = {"eye": [float("nan"), 0, 0], "target": [0, 0, 0], "up": [0, 0, 1]}
    with pytest.raises(ValueError, match="camera: Out of range float values"):
        brickyard.render(store, backend="cpu", size=16, camera=cam)
    with pytest.raises(ValueError) as e:
        brickyard.render(store, backend="cpu", size=16, tf={"foo": 1})
    assert "the tf given" in str(e.value) and "brickyard-render-" not in str(e.value), e.value


def test_open_and_read_name_arguments_of_the_wrong_kind(store):
    for kw, exc in [({"cache": -1}, ValueError), ({"threads": -1}, ValueError), ({"threads": 0}, ValueError),
                    ({"brick": 0}, ValueError),
                    ({"brick": 1}, ValueError), ({"brick": 1024}, ValueError),
                    ({"cache": "lots"}, ValueError), ({"brick": 32.5}, TypeError)]:
        with pytest.raises(exc, match=next(iter(kw))):
            brickyard.open(store, **kw)
    s = brickyard.open(store)
    for kw in [{"level": True}, {"level": "0"}, {"level": 1.0}, {"channel": False}]:
        with pytest.raises(TypeError, match=f"{next(iter(kw))}: expected a whole number"):
            s.read(**kw)


def test_conversion_options_of_the_wrong_sign_or_kind_are_named(tmp_path):
    v = np.zeros((8, 8, 8), np.uint8)
    for kw, exc, what in [({"brick": -64}, ValueError, "brick"), ({"shard": (0, 64, 64)}, ValueError, "shard"),
                          ({"memory": -1}, ValueError, "memory"), ({"compression": None}, TypeError, "compression")]:
        with pytest.raises(exc, match=f"^{what}: "):
            brickyard.from_numpy(v, tmp_path / "o.zarr", progress=False, **kw)
    assert not (tmp_path / "o.zarr").exists()


def test_a_region_larger_than_the_machine_is_refused_with_its_size(tmp_path):
    # A 65536³ store (all fill value: its metadata alone): reading it whole
    # would need 256 TiB; the MemoryError says so (it had no message).
    import json as _json

    p = tmp_path / "huge.zarr"
    root = {"zarr_format": 3, "node_type": "group", "attributes": {"ome": {"version": "0.5", "multiscales": [
        {"axes": [{"name": a, "type": "space"} for a in "zyx"],
         "datasets": [{"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 1]}]}]}]}}}
    arr = {"zarr_format": 3, "node_type": "array", "shape": [65536, 65536, 65536], "data_type": "uint8",
           "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [64, 64, 64]}},
           "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
           "fill_value": 0, "codecs": [{"name": "bytes", "configuration": {"endian": "little"}}]}
    (p / "0").mkdir(parents=True)
    (p / "zarr.json").write_text(_json.dumps(root))
    (p / "0" / "zarr.json").write_text(_json.dumps(arr))
    s = brickyard.open(p)
    with pytest.raises(MemoryError, match=r"region: \(0, 0, 0\)\.\.\(65536, 65536, 65536\) of level 0 is 281474976710656 bytes"):
        s.read()
    assert s.read(region=np.s_[0:2, 0:2, 0:2]).sum() == 0


def test_budgets_are_taken_as_the_cli_writes_them(store, tmp_path):
    s = brickyard.open(store, cache="8MiB", chunk_cache="1MiB")
    assert s.cache_stats()["budget"] == 8 << 20
    brickyard.from_numpy(np.zeros((8, 8, 8), np.uint8), tmp_path / "m.zarr", memory="64MiB", progress=False)
    with pytest.raises(ValueError, match="^memory: "):
        brickyard.from_numpy(np.zeros((8, 8, 8), np.uint8), tmp_path / "n.zarr", memory="a lot", progress=False)
    # A budget that is no whole number of bytes is a TypeError in render as
    # in process (render took 1.5 for 1 byte); a fractional size with a
    # unit is bytes.
    for kw in ("memory", "pool", "host", "upload"):
        with pytest.raises(TypeError, match=f"^{kw}: expected bytes"):
            brickyard.render(store, size=8, **{kw: 1.5})
    with pytest.raises(TypeError, match="^memory: expected bytes"):
        brickyard.process(store, "gauss(1)", "g", memory=1.5)
    with pytest.raises(ValueError, match="whole number of bytes"):
        brickyard.render(store, size=8, memory="1.5")


def test_types_stored_as_convert_reads_them(tmp_path):
    # bool as uint8, float16 as float32, int64 and uint64 as 32-bit
    # integers where every value fits: in memory and read region by region
    # (a strided view), each read back equal to the array.
    rng = np.random.default_rng(3)
    cases = {
        "bool": (rng.random((6, 5, 7)) > 0.5, "uint8"),
        "float16": (rng.standard_normal((6, 5, 7)).astype(np.float16), "float32"),
        "int64": (rng.integers(-(1 << 31), 1 << 31, (6, 5, 7)), "int32"),
        "uint64": (rng.integers(0, 1 << 32, (6, 5, 7), dtype=np.uint64), "uint32"),
    }
    for name, (a, stored) in cases.items():
        for view, arr in (("memory", a), ("strided", a[:, :, ::-1]), ("lazy", a[::-1])):
            out = tmp_path / f"{name}-{view}.ome.zarr"
            brickyard.from_numpy(_Lazy(arr) if view == "lazy" else arr, out, progress=False)
            s = brickyard.open(out)
            assert s.dtype == stored, (name, view, s.dtype)
            np.testing.assert_array_equal(s[:], arr.astype(stored), err_msg=f"{name} {view}")
            s.close()
    # Labels as skimage.measure.label returns them (int64).
    lab = np.zeros((8, 8, 8), np.int64)
    lab[1:3, 1:3, 1:3], lab[5:7, 5:7, 5:7] = 1, 2
    brickyard.from_numpy(lab, tmp_path / "lab.ome.zarr", labels=True, progress=False)
    s = brickyard.open(tmp_path / "lab.ome.zarr")
    assert s.dtype == "int32"
    np.testing.assert_array_equal(s[:], lab)


def test_a_brick_that_does_not_divide_512_takes_the_default_shard_as_the_cli_does(tmp_path):
    # The shard default was 512 whatever the brick: brick=48 was refused
    # ("shard [512, 512, 512] must be a multiple of the brick"), as the CLI
    # rounds the default up to a multiple of it.
    a = np.arange(50 * 60 * 70, dtype=np.uint16).reshape(50, 60, 70)
    brickyard.from_numpy(a, tmp_path / "b.zarr", brick=48, progress=False)
    assert np.array_equal(brickyard.open(tmp_path / "b.zarr")[:, :, :], a)
    with pytest.raises(ValueError, match="shard"):
        brickyard.from_numpy(a, tmp_path / "c.zarr", brick=48, shard=500, progress=False)


def test_convert_refuses_a_level_of_an_input_that_has_none(tmp_path):
    # level= picks a level of a Zarr input; a TIFF's was ignored (its level
    # 0 converted), where the CLI refuses --level.
    import tifffile  # (in the test environment: scripts/interop/requirements.txt)
    tif = tmp_path / "s.tif"
    tifffile.imwrite(tif, np.arange(4 * 8 * 8, dtype=np.uint16).reshape(4, 8, 8), photometric="minisblack")
    with pytest.raises(ValueError, match=r"s\.tif: level: picks a level of a Zarr/OME-Zarr input, .* a TIFF file"):
        brickyard.convert(tif, tmp_path / "t.ome.zarr", level=1, progress=False)
    assert not (tmp_path / "t.ome.zarr").exists()
    brickyard.convert(tif, tmp_path / "t.ome.zarr", level=0, progress=False)


def test_budgets_and_sizes_of_the_wrong_kind_are_type_errors(tmp_path):
    # convert and from_numpy took a float budget by its whole part (1.5
    # became 1 byte), iterated text ("64" as two values) and passed 2**70
    # to the native side, which named an internal field.
    a = np.zeros((8, 8, 8), np.uint8)
    out = tmp_path / "o.zarr"
    for kw, err, msg in [
        ({"memory": 1.5e9}, TypeError, "memory: expected bytes"),
        ({"memory": None}, TypeError, "memory: expected bytes"),
        ({"memory": 2**70}, ValueError, "memory: expected a number of bytes"),
        ({"brick": "64"}, TypeError, "brick: expected a number or three numbers"),
        ({"brick": 2**70}, ValueError, "brick: expected sizes below"),
        ({"spacing": "0.5"}, TypeError, "spacing: expected a number or three numbers"),
        ({"spacing": "1,2,3"}, TypeError, "spacing: expected a number or three numbers"),
        ({"unit": 5}, TypeError, "unit: expected a name"),
    ]:
        with pytest.raises(err, match=msg):
            brickyard.from_numpy(a, out, progress=False, **kw)
        assert not out.exists()
    brickyard.from_numpy(a, out, progress=False, memory=1 << 26)
    with pytest.raises(TypeError, match="memory: expected bytes"):
        brickyard.convert(out, tmp_path / "c.zarr", memory=1.5, progress=False)


def test_process_refuses_a_closed_store_as_render_does(tmp_path):
    p = tmp_path / "s.zarr"
    brickyard.from_numpy(np.arange(16**3, dtype=np.uint16).reshape(16, 16, 16), p, progress=False)
    s = brickyard.open(p)
    s.close()
    with pytest.raises(ValueError, match="the store is closed"):
        brickyard.process(s, "gauss(1)", out="g", progress=False)
    assert not (p / "derived").exists()


def test_the_conversions_notes_are_warnings(tmp_path):
    # A file without voxel spacing: the CLI's note ("1 unit per voxel")
    # went to fd 2 only, unseen in a notebook; now a UserWarning. An
    # array without spacing is the rule and gets none, nor a file given
    # its spacing.
    import tifffile
    tif = tmp_path / "s.tif"
    tifffile.imwrite(tif, np.arange(4 * 8 * 8, dtype=np.uint16).reshape(4, 8, 8), photometric="minisblack")
    with pytest.warns(UserWarning, match=r"t\.ome\.zarr: the input gives no voxel spacing: 1 unit per voxel"):
        brickyard.convert(tif, tmp_path / "t.ome.zarr", progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        brickyard.convert(tif, tmp_path / "u.ome.zarr", spacing=(1.0, 2.0, 2.0), progress=False)
        brickyard.from_numpy(np.zeros((8, 8, 8), np.uint8), tmp_path / "v.ome.zarr", progress=False)
    # A mask that came out empty: the note is a warning too.
    with pytest.warns(UserWarning, match=r"no voxel is in the mask \(threshold\(100000\)\)"):
        brickyard.process(tmp_path / "u.ome.zarr", "threshold(100000)", out="none", progress=False)


def test_what_render_says_on_stderr_is_a_python_warning(tmp_path):
    """Labels past 2^24 were said on stderr only, where a script does not
    see them: now a RuntimeWarning (the CLI still prints them)."""
    lab = np.zeros((16, 16, 16), np.uint32)
    lab[4:12, 4:12, 4:12] = (1 << 25) + 3
    dst = tmp_path / "big-ids.ome.zarr"
    brickyard.from_numpy(lab, dst, labels=True, progress=False)
    with pytest.warns(RuntimeWarning, match=r"labels reach 33554435; labels beyond 16777216"):
        img = brickyard.render(dst, size=24, backend="cpu")
    assert img[..., 3].max() > 0


def test_a_label_image_without_a_table_warns(tmp_path):
    """A label image holding a negative id gets no table of label statistics:
    said in the report only, where a script did not see it."""
    lab = np.zeros((8, 8, 8), np.int32) - 1
    lab[2:5, 2:5, 2:5] = 3
    with pytest.warns(UserWarning, match=r"no table of label statistics \(voxel \[0, 0, 0\].* holds -1"):
        report = brickyard.from_numpy(lab, tmp_path / "neg.ome.zarr", labels=True, progress=False)
    assert "; note: no table of label statistics" in report
