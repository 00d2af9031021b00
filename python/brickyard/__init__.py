"""brickyard: out-of-core reads, rendering, processing and conversion of huge OME-Zarr volumes.

    import brickyard, numpy as np
    store = brickyard.open("volume.ome.zarr")          # or "http://host:8000/volume.ome.zarr"
    block = store.read(level=0, region=np.s_[0:64, 100:228, 100:228])
    rgba = brickyard.render(store, mode="dvr", tf="soft", size=(512, 512))
    edges = brickyard.process(store, "gauss(1.5)|sobel", out="edges")

Reads go through brickyard's loader and a host cache of bounded size, so any
region of a store larger than memory can be read. `render` draws exactly what
`brickyard render` draws for the same options, and `process` writes what
`brickyard process` writes.
"""

from __future__ import annotations

import builtins
import contextlib
import json
import difflib
import os
import re
import sys
import tempfile
import warnings
from typing import Any, Optional, Sequence, Tuple, Union

import numpy as np

from . import _native

__all__ = ["open", "Store", "Level", "render", "convert", "from_numpy", "process"]

_MODES = ("dvr", "mip", "slice")
_BACKENDS = ("auto", "cpu", "gpu")
_DTYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")


def _region(region: Any, shape: Sequence[int]) -> Tuple[Tuple[int, int, int], Tuple[int, int, int], tuple]:
    """A region (`np.s_[z0:z1:step, y0:y1, x0:x1]`, ints, or None) as the box
    to read (lo, hi) and the index that then takes from that box what NumPy
    would: every step (negative ones too), an integer's axis dropped.
    Slices clip to the axis as NumPy's do; a slice that selects nothing
    gives an empty box (lo == hi on that axis) and an empty array."""
    if region is None:
        region = ()
    if not isinstance(region, tuple):
        region = (region,)
    if sum(r is Ellipsis for r in region) > 1:
        raise IndexError("an index can only have a single ellipsis ('...')")
    if any(r is Ellipsis for r in region):
        i = next(k for k, r in enumerate(region) if r is Ellipsis)
        fill = 3 - (len(region) - 1)
        region = region[:i] + (slice(None),) * fill + region[i + 1 :]
    if len(region) > 3:
        raise IndexError(f"region: expected at most 3 axes (z, y, x), got {len(region)}")
    region = tuple(region) + (slice(None),) * (3 - len(region))
    lo, hi, take = [], [], []
    for axis, (r, n) in enumerate(zip(region, shape)):
        name = "zyx"[axis]
        if isinstance(r, (int, np.integer)) and not isinstance(r, bool):
            i = int(r)
            if i < 0:
                i += n
            if not 0 <= i < n:
                raise IndexError(f"region: index {int(r)} is outside axis {name} of length {n}")
            lo.append(i)
            hi.append(i + 1)
            take.append(0)
        elif isinstance(r, slice):
            for part in (r.start, r.stop, r.step):
                if part is not None and (not isinstance(part, (int, np.integer)) or isinstance(part, bool)):
                    raise TypeError(f"region: axis {name}: slice bounds and steps must be integers or None, "
                                    f"got {part!r}")
            if r.step is not None and int(r.step) == 0:
                raise ValueError(f"region: axis {name}: slice step cannot be zero")
            a, b, step = r.indices(n)
            k = len(range(a, b, step))
            if k == 0:
                lo.append(0)
                hi.append(0)
                take.append(slice(None))
            elif step > 0:
                lo.append(a)
                hi.append(a + (k - 1) * step + 1)
                take.append(slice(None, None, step))
            else:
                # Read from the last index taken up to the first; the box is
                # then walked backwards from its end.
                lo.append(a + (k - 1) * step)
                hi.append(a + 1)
                take.append(slice(None, None, step))
        elif isinstance(r, (list, np.ndarray, bool, np.bool_)):
            # (NumPy's advanced indexing: a copy of chosen voxels, which the
            # array read does as well.)
            raise TypeError(f"region: axis {name}: lists, arrays and boolean masks do not index a store (NumPy's "
                            f"advanced indexing); read the box and index the array, e.g. store[lo:hi][[1, 5, 2]]")
        else:
            raise TypeError(f"region: axis {name}: expected an int or a slice, got {type(r).__name__}")
    return (lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2]), tuple(take)


# The most of a region's box a read with steps holds at once, beside the
# result.
_PIECE = 32 << 20


def _pieces(idx: np.ndarray, unit: int):
    """Runs of the indices `idx` (one axis of a region with steps, in the
    result's order) whose span takes at most `_PIECE` bytes at `unit` bytes
    an index (a run of one index whatever its size): `(run in the result,
    lo, hi, the run's indices in [lo, hi) less lo)`."""
    i = 0
    while i < len(idx):
        j = i + 1
        while j < len(idx) and (abs(int(idx[j]) - int(idx[i])) + 1) * unit <= _PIECE:
            j += 1
        a, b = min(int(idx[i]), int(idx[j - 1])), max(int(idx[i]), int(idx[j - 1])) + 1
        yield slice(i, j), a, b, idx[i:j] - a
        i = j


def _indexed_shape(channels: int, zyx: Sequence[int]) -> tuple:
    """The shape a store or level indexes by: `(z, y, x)` for one channel,
    `(c, z, y, x)` for several."""
    return tuple(zyx) if channels == 1 else (channels,) + tuple(zyx)


def _index(store: "Store", level: int, key: Any) -> np.ndarray:
    """`store[key]` at `level`, as NumPy indexes an array of the indexed
    shape: for several channels the first axis is the channel (an integer,
    negative from the end, or a slice: the channels taken are stacked)."""
    # (`read` takes None for the whole volume; in an index NumPy reads it
    # as a new axis, which a store does not make.)
    if key is None or (isinstance(key, tuple) and any(k is None for k in key)):
        raise IndexError("None (np.newaxis) in an index is not supported: add the axis to the array read, "
                         "e.g. store[...][np.newaxis]")
    if store.channels == 1:
        return store.read(level, 0, key)
    if not isinstance(key, tuple):
        key = (key,)
    if sum(k is Ellipsis for k in key) > 1:
        raise IndexError("an index can only have a single ellipsis ('...')")
    if any(k is Ellipsis for k in key):
        i = next(j for j, k in enumerate(key) if k is Ellipsis)
        key = key[:i] + (slice(None),) * (4 - (len(key) - 1)) + key[i + 1:]
    if len(key) > 4:
        raise IndexError(f"too many indices: {len(key)} for shape {_indexed_shape(store.channels, store.shapes[level])} "
                         "(c, z, y, x)")
    c, rest = (key[0] if key else slice(None)), key[1:]
    if isinstance(c, slice):
        for part in (c.start, c.stop, c.step):
            if part is not None and (not isinstance(part, (int, np.integer)) or isinstance(part, bool)):
                raise TypeError(f"channel: slice bounds and steps must be integers or None, got {part!r}")
        if c.step is not None and int(c.step) == 0:
            raise ValueError("channel: slice step cannot be zero")
        chosen = range(*c.indices(store.channels))
        if len(chosen) == 0:
            # The shape NumPy gives, without reading anything.
            one = _region(rest, store.shapes[level])
            box = tuple(h - l for l, h in zip(one[0], one[1]))
            return np.empty((0,) + np.empty(box, dtype=store.dtype)[one[2]].shape, dtype=store.dtype)
        return np.stack([store.read(level, k, rest) for k in chosen])
    return store.read(level, _channel_index(c, store.channels, "store"), rest)


class Store:
    """An OME-Zarr store opened for out-of-core reading (see `brickyard.open`)."""

    def __init__(self, path: Union[str, os.PathLike], cache: int = 256 << 20, chunk_cache: int = 64 << 20,
                 brick: int = 64, threads: Optional[int] = None):
        if threads is None:
            threads = min(8, os.cpu_count() or 1)
        # Budgets as the CLI takes them ("512MiB") or in bytes.
        cache, chunk_cache = (_bytes(v, what) for v, what in ((cache, "cache"), (chunk_cache, "chunk_cache")))
        for what, v, least in (("cache", cache, 0), ("chunk_cache", chunk_cache, 0), ("brick", brick, 1),
                               ("threads", threads, 1)):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool):
                raise TypeError(f"{what}: expected a whole number, got {type(v).__name__} {v!r}")
            if v < least:
                raise ValueError(f"{what}: expected at least {least}, got {v}")
        self._path = os.fsdecode(path)
        self._args = (self._path, int(cache), int(chunk_cache), int(brick), int(threads))
        self._native = _native.NativeStore(*self._args)
        # Fixed for the store's life: asked of the native side once, not per read.
        self._shapes = [tuple(s) for s in self._native.shapes]
        self._channels = self._native.channels
        self._dtype = np.dtype(self._native.dtype)

    def _open(self):
        if self._native is None:
            raise ValueError(f"{self._path}: the store is closed")
        return self._native

    def close(self) -> None:
        """Let the loader's threads and caches go; reads afterwards are a
        ValueError. (`with brickyard.open(p) as s:` closes at the end.)"""
        self._native = None

    def __enter__(self) -> "Store":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __reduce__(self):
        # Pickled (for another process) or copied: opened again there from
        # its path and budgets.
        return (Store, self._args)

    @property
    def path(self) -> str:
        """The store's path, or its URL as given."""
        return self._path

    @property
    def levels(self) -> int:
        return len(self._shapes)

    @property
    def shapes(self) -> list:
        """Shape `(z, y, x)` of every level, level 0 first."""
        return list(self._shapes)

    @property
    def shape(self) -> tuple:
        """Level 0's shape as it indexes: `(z, y, x)` for a store of one
        channel, `(c, z, y, x)` for several."""
        return _indexed_shape(self.channels, self.shapes[0])

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def channels(self) -> int:
        return self._channels

    @property
    def dtype(self) -> np.dtype:
        return self._dtype

    @property
    def scales(self) -> list:
        """The OME `scale` of every level (one number per axis), None where absent."""
        return self._open().scales

    @property
    def translations(self) -> list:
        return self._open().translations

    @property
    def axes(self) -> list:
        return self._open().axes

    @property
    def units(self) -> list:
        return self._open().units

    @property
    def channel_names(self) -> list:
        """One name per channel: the store's OME `omero` labels (as a
        conversion from a named source or `from_numpy(channel_names=...)`
        wrote them), else "channel i"."""
        return self._open().channel_names

    def cache_stats(self) -> dict:
        """The host cache: bytes held, budget, hits, misses; bytes read from the store."""
        held, budget, hits, misses = self._open().cache_stats()
        return {"bytes": held, "budget": budget, "hits": hits, "misses": misses,
                "bytes_read": self._open().bytes_read()}

    def level(self, level: int) -> "Level":
        if not isinstance(level, (int, np.integer)) or isinstance(level, bool):
            raise TypeError(f"level: expected an integer, found {level!r}")
        if not 0 <= level < self.levels:
            raise IndexError(f"level: {level} asked for but the store has {self.levels} level(s)")
        return Level(self, level)

    def read(self, level: int = 0, channel: int = 0, region: Any = None) -> np.ndarray:
        """The region (`np.s_[z0:z1, y0:y1, x0:x1]`; None = the whole level) of
        one level and channel, through the loader and host cache."""
        shapes = self._shapes
        for what, v in (("level", level), ("channel", channel)):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool):
                raise TypeError(f"{what}: expected a whole number, got {type(v).__name__} {v!r}")
        if not 0 <= level < len(shapes):
            raise IndexError(f"level: {level} asked for but the store has {len(shapes)} level(s)")
        if not 0 <= channel < self._channels:
            raise IndexError(f"channel: {channel} asked for but the store has {self._channels} channel(s)")
        lo, hi, take = _region(region, shapes[level])
        box = (hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])
        if 0 in box:
            # Nothing selected (NumPy's empty slices): nothing to read.
            return np.empty(box, dtype=self._dtype)[take]
        stepped = any(isinstance(t, slice) and t.step is not None and abs(t.step) > 1 for t in take)
        item = np.dtype(self._dtype).itemsize
        shape = [len(range(n)[t]) for n, t in zip(box, take) if isinstance(t, slice)]
        need = int(np.prod(shape, dtype=object)) * item
        ram = _physical_memory()
        if ram and need > ram:
            raise MemoryError(f"region: {tuple(lo)}..{tuple(hi)} of level {level} is {need} bytes, more than this "
                              f"machine's memory ({ram} bytes): read it in parts")
        if stepped:
            return self._read_stepped(int(level), int(channel), lo, hi, take)
        buf = self._open().read(int(level), int(channel), lo, hi)
        a = np.frombuffer(buf, dtype=self._dtype).reshape(box)[take]
        # (A step of -1 walks the box backwards: a view of it, no larger.)
        if any(isinstance(t, slice) and t.step not in (None, 1) for t in take):
            a = np.ascontiguousarray(a)
        return a

    def _read_stepped(self, level: int, channel: int, lo: Sequence[int], hi: Sequence[int], take: tuple) -> np.ndarray:
        """A region with steps (`store[::8]`), read in pieces of the box it
        spans of at most `_PIECE` bytes (runs of planes, or of rows of one
        plane), each taking what the steps select: memory holds the result
        and one piece, not the whole box (a 2 MiB `store[::256]` of a
        576 MiB level read all of it)."""
        native = self._open()
        dt = np.dtype(self._dtype)
        sel = [np.arange(a, b)[t if isinstance(t, slice) else slice(0, 1)] for a, b, t in zip(lo, hi, take)]
        out = np.empty(tuple(len(x) for x in sel), dtype=dt)
        row = (hi[2] - lo[2]) * dt.itemsize
        plane = (hi[1] - lo[1]) * row
        tx = sel[2] - lo[2]

        def read(z0, z1, y0, y1):
            buf = native.read(level, channel, (z0, y0, lo[2]), (z1, y1, hi[2]))
            return np.frombuffer(buf, dtype=dt).reshape(z1 - z0, y1 - y0, hi[2] - lo[2])

        for zs, z0, z1, tz in _pieces(sel[0], plane):
            if (z1 - z0) * plane <= _PIECE:
                out[zs] = read(z0, z1, lo[1], hi[1])[np.ix_(tz, sel[1] - lo[1], tx)]
                continue
            # One plane larger than a piece: by runs of rows.
            for ys, y0, y1, ty in _pieces(sel[1], row):
                out[zs, ys] = read(z0, z1, y0, y1)[np.ix_(tz, ty, tx)]
        # An integer's axis dropped, as NumPy does.
        return out[tuple(slice(None) if isinstance(t, slice) else 0 for t in take)]

    def __getitem__(self, key: Any) -> np.ndarray:
        """Level 0 indexed as NumPy indexes an array of `shape`:
        `store[z0:z1, y0:y1, x0:x1]` for one channel, `store[c, z0:z1, ...]`
        for several (the channel an integer or a slice; `store[1]` is
        channel 1 whole)."""
        return _index(self, 0, key)

    def __len__(self) -> int:
        """The length of the first axis of `shape`, as NumPy's `len`."""
        return self.shape[0]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        """`np.asarray(store)`: level 0 whole, read (a new array always)."""
        return _as_array(self[...], dtype, copy)

    def __repr__(self) -> str:
        return (f"<brickyard.Store {self.path!r}: {self.levels} levels, level 0 {self.shapes[0]}, "
                f"{self.channels} channel(s), {self.dtype}>")


class Level:
    """One level of a store: `store.level(l)[z0:z1, y0:y1, x0:x1]`."""

    def __init__(self, store: Store, level: int):
        self.store = store
        self.index = level

    @property
    def shape(self) -> tuple:
        """As `Store.shape`: `(z, y, x)`, or `(c, z, y, x)` for several channels."""
        return _indexed_shape(self.store.channels, self.store.shapes[self.index])

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def dtype(self) -> np.dtype:
        return self.store.dtype

    def read(self, channel: int = 0, region: Any = None) -> np.ndarray:
        return self.store.read(self.index, channel, region)

    def __getitem__(self, key: Any) -> np.ndarray:
        """As `Store.__getitem__`, at this level."""
        return _index(self.store, self.index, key)

    def __len__(self) -> int:
        return self.shape[0]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        """`np.asarray(level)`: the level whole, read (a new array always)."""
        return _as_array(self[...], dtype, copy)

    def __repr__(self) -> str:
        return f"<brickyard.Level {self.index} of {self.store.path!r}: {self.shape}>"


def _as_array(a: np.ndarray, dtype: Any, copy: Any) -> np.ndarray:
    """What `__array__` returns of `a`, freshly read: in `dtype` if given;
    `copy=False` (no copy) cannot be had of a store."""
    if copy is False:
        raise ValueError("a store is read into a new array: np.asarray(store, copy=False) cannot avoid a copy")
    return a if dtype is None else a.astype(dtype, copy=False)


def _bytes(value: Any, what: str) -> Any:
    """A budget given as the CLI takes it (`"512MiB"`) in bytes; other values as they are."""
    if isinstance(value, str):
        try:
            return _native.parse_bytes(value)
        except ValueError as e:
            raise ValueError(f"{what}: {e}") from None
    return value


def _physical_memory() -> Optional[int]:
    """The machine's memory in bytes, where the system says."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def _channel_index(c: Any, channels: int, what: str) -> int:
    """Channel `c` of `channels` as NumPy indexes: an integer, negative
    from the end, IndexError out of range."""
    if not isinstance(c, (int, np.integer)) or isinstance(c, bool):
        raise TypeError(f"{what}[c, z, y, x]: the channel must be an integer, found {c!r}")
    if not -channels <= c < channels:
        raise IndexError(f"channel: {c} asked for but the store has {channels} channel(s)")
    return int(c) % channels


def _index_option(value: Any, what: str) -> int:
    """A level or channel option of `process`, `render` or `convert`: an
    integer (TypeError otherwise); a negative one, or one beyond any store,
    is an IndexError here (the native layer's unsigned numbers would raise
    OverflowError)."""
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool):
        raise TypeError(f"{what}: expected an integer, found {value!r}")
    value = int(value)
    if not 0 <= value <= sys.maxsize:
        raise IndexError(f"{what}: {value} is outside the store (the first {what} is 0)")
    return value


# The command line's flags, as `brickyard render`, `convert` and `process`
# name them in messages (each is a keyword argument here, `-` as `_`), and
# those that are switches, per command (`--overwrite` is `overwrite=True`;
# render's `--labels` takes a name, convert's is a switch).
_FLAGS = frozenset((
    "azimuth", "backend", "brick", "camera", "channel", "channel-levels", "channel-tf", "compression", "debug",
    "derive", "distribute", "elevation", "eye-separation", "fov", "gpu-update", "hide-labels", "host", "json",
    "label-opacity", "labels", "level", "loader-threads", "lod-bias", "max-frames", "memory", "mode", "multiplex",
    "no-early-termination", "octree-depth", "only-labels", "origin", "ortho", "out", "overwrite", "parallax", "pool",
    "progressive", "quiet", "raw-f32", "read-delay-ms", "region-weights", "requests",
    "samples-per-voxel", "save-camera", "shard", "size", "slice-at", "slice-normal", "slice-origin", "slice-z",
    "spacing", "stats", "stereo", "stream", "tf", "traversal", "turntable", "unit", "upload", "views",
    "window"))
_SWITCHES = {
    "render": frozenset(("json", "no-early-termination", "ortho", "quiet", "raw-f32", "stream")),
    "convert": frozenset(("labels", "overwrite")),
    "process": frozenset(("overwrite",)),
}
# Words that are a flag's value when they follow it ("use --backend cpu").
_CHOICES = {"backend": ("auto", "cpu", "gpu"), "mode": ("dvr", "mip", "slice"),
            "tf": ("labels", "linear", "soft", "hot", "viridis", "coolwarm", "opaque")}
# A flag in a message: as clap quotes it ('--level <LEVEL>'), or in the
# text, with the value that follows it if there is one (a number, with or
# without a unit: "--memory 56MiB").
_FLAG_RE = re.compile(r"'--(?P<quoted>[a-z][a-z0-9-]*)(?: <[A-Z_]+>)?'"
                      r"|--(?P<flag>[a-z][a-z0-9]*(?:-[a-z0-9]+)*)"
                      r"(?P<value> [0-9][\w.]*| [a-z]+| [A-Z][A-Z_]*\b)?")
# A message that starts with the flag it is about ("label-opacity: ...").
_PREFIX_RE = re.compile(r"^(?P<flag>[a-z][a-z0-9]*(?:-[a-z0-9]+)+):")


# Phrases of the CLI's messages said as Python says them: its coordinates
# are (z, y, x), and raw data comes in through NumPy.
_PHRASES = (
    ("--spacing X,Y,Z", "spacing=(z, y, x)"),
    ("--origin X,Y,Z", "origin=(z, y, x)"),
    ("for raw data give --dims, --dtype (and --endian, --spacing) or write a sidecar",
     "raw data: brickyard.from_numpy(np.memmap(path, dtype, mode=\"r\", shape=(z, y, x))), or write a sidecar"),
)


def _keywords(message: str, command: str) -> str:
    """A message of the CLI's code with its flags as this module's keyword
    arguments (of `command`: render, convert or process): `--overwrite` is
    `overwrite=True`, `--memory` `memory=`,
    `--memory 56MiB` `memory="56MiB"`, `'--level <LEVEL>'` `'level'`. Only
    known flags that stand as words, and flags quoted as the command line's
    parser quotes them, are changed (not a path's `a--b`); of
    the command line parser's messages, only the first paragraph is kept
    (its usage line and advice about --help are the CLI's)."""
    if message.startswith("error: "):
        message = message.split("\n\n", 1)[0]
        # The parser's "error: invalid value '0' for '--turntable <N>': why"
        # as this module's own messages say it: "turntable: why".
        bad = re.match(r"error: invalid value '(?P<v>.*)' for '(?:--)?(?P<n>[a-z][a-z0-9-]*)(?: <[A-Z_]+>)?': "
                       r"(?P<why>.*)$", message, re.S)
        if bad:
            why = bad.group("why").strip()
            if bad.group("v") not in why:
                why = f"invalid value {bad.group('v')!r}: {why}"
            message = f"{bad.group('n')}: {why}"
    for cli, py in _PHRASES:
        message = message.replace(cli, py)
    p = _PREFIX_RE.match(message)
    if p and p.group("flag") in _FLAGS:
        message = p.group("flag").replace("-", "_") + message[p.end("flag"):]
    # A command line quoted as such (`brickyard process ... --out NAME`)
    # is left whole: it is advice to run that command.
    quoted = [q.span() for q in re.finditer(r"`[^`]*`", message)]

    def word(m: "re.Match") -> str:
        at = m.start()
        if any(a < at < b for a, b in quoted):
            return m.group(0)
        before = message[at - 1] if at else " "
        name = m.group("quoted") or m.group("flag")
        # "--pool/--host": a flag after a flag and a slash.
        after_flag = before == "/" and re.search(r"--[a-z0-9-]+/$", message[:at])
        key = name.replace("-", "_")
        # (Quoted, the parser's unknown flags too: "unexpected argument '--x'".)
        if m.group("quoted"):
            return f"'{key}'"
        if name not in _FLAGS or not (before in " \t\n(\"'" or after_flag):
            return m.group(0)
        # "--memory: expected a size" is about the option, not a value of it.
        if not m.group("value") and message[m.end():m.end() + 1] == ":":
            return key
        value = (m.group("value") or "").strip()
        if name in _SWITCHES[command]:
            return f"{key}=True" + (m.group("value") or "")
        if value and (value[0].isdigit() or value in _CHOICES.get(name, ())):
            return f"{key}={value}" if re.fullmatch(r"[0-9]+(\.[0-9]+)?", value) else f'{key}="{value}"'
        # A placeholder: "--labels NAME" is labels=NAME.
        if value and value[0].isupper():
            return f"{key}={value}"
        return f"{key}=" + (m.group("value") or "")

    return _FLAG_RE.sub(word, message)


# The CLI's messages for a level or channel outside the store (raised as
# ValueError by the shared code): IndexError here, as for reads.
_OUT_OF_RANGE = re.compile(
    r"^level: the store has \d+ levels$"
    r"|^(derive: )?channel:? \d+ asked for but .* has \d+ channel\(s\)$"
    r"|: level \d+ asked for but the image has \d+ levels$"
    r"|^channel_levels: .*\(the store has \d+ levels\)$", re.S)


@contextlib.contextmanager
def _cli_errors(command: str):
    """Errors of the CLI's shared code (that of `brickyard COMMAND`) as
    Python gives them: flags named as keyword arguments (`_keywords`), a
    level or channel outside the store an IndexError."""
    try:
        yield
    except Exception as e:
        if len(e.args) != 1 or not isinstance(e.args[0], str):
            raise
        message = _keywords(e.args[0], command)
        if type(e) is ValueError and _OUT_OF_RANGE.search(message):
            raise IndexError(message).with_traceback(e.__traceback__) from e.__cause__
        e.args = (message,)
        raise


def open(path: Union[str, os.PathLike], cache: int = 256 << 20, chunk_cache: int = 64 << 20,
         brick: int = 64, threads: Optional[int] = None) -> Store:
    """Open an OME-Zarr store: a directory, or an `http://` / `https://` URL
    (e.g. one `brickyard serve` serves), read with ranged requests. `cache`
    bounds the host cache of decoded bricks and `chunk_cache` the decoded
    store chunks (bytes)."""
    return Store(path, cache=cache, chunk_cache=chunk_cache, brick=brick, threads=threads)


def _json_arg(value: Any, what: str, tmp: str) -> str:
    """A dict or JSON text written to a file for the CLI's options; a path as is."""
    if isinstance(value, dict):
        try:
            text = json.dumps(value, allow_nan=False)
        except ValueError as e:
            raise ValueError(f"{what}: {e} (NaN and infinities are not numbers JSON holds)") from None
    elif isinstance(value, str) and value.lstrip().startswith("{"):
        text = value
    elif isinstance(value, (str, os.PathLike)):
        return os.fspath(value)
    else:
        raise TypeError(f"{what}: expected a dict, JSON text or a file name, got {type(value).__name__}")
    path = os.path.join(tmp, f"{what}.json")
    with builtins.open(path, "w") as f:
        f.write(text)
    return path


# CLI flags given once per value (lists: one flag each), and those of the
# form C=VALUE per channel (dicts {C: VALUE}).
_REPEATED = ("channel", "channel_tf", "channel_levels")
_PER_CHANNEL = ("channel_tf", "channel_levels")


# render's budgets, in bytes or as sizes ("1GiB"): whole numbers only.
_BUDGETS = ("memory", "pool", "host", "upload")
# render's options that take a whole number (0 or more; the CLI says which
# range), and those that take a file name.
_WHOLE = ("level", "brick", "requests", "progressive", "views", "loader_threads", "read_delay_ms", "max_frames",
          "turntable", "octree_depth")
_PATHS = ("save_camera", "out")


def render_args(store: Union[Store, str, os.PathLike], mode: str = "dvr", camera: Any = None, tf: Any = None,
                size: Union[int, Tuple[int, int]] = (512, 512), backend: str = "auto", tmpdir: str = ".",
                **options: Any) -> list:
    """The `brickyard render` arguments for these options (files for dicts are written in `tmpdir`)."""
    path = store.path if isinstance(store, Store) else os.fspath(store)
    if path.startswith("-"):
        # (A store named "-x.zarr" is a path, not an option.)
        path = os.path.join(".", path)
    if mode not in _MODES:
        raise ValueError(f"mode: expected dvr, mip or slice, found {mode!r}")
    if backend not in _BACKENDS:
        raise ValueError(f"backend: expected auto, cpu or gpu, found {backend!r}")
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        size = (int(size), int(size))
    if not (isinstance(size, (tuple, list)) and len(size) == 2
            and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v > 0 for v in size)):
        raise ValueError(f"size: expected N or (width, height), positive whole numbers, found {size!r}")
    w, h = size
    args = ["brickyard", "render", path, "--mode", mode, "--size", f"{int(w)}x{int(h)}", "--backend", backend]
    if camera is not None:
        args += ["--camera", _json_arg(camera, "camera", tmpdir)]
    if tf is not None:
        if isinstance(tf, str) and not tf.lstrip().startswith("{") and not tf.endswith(".json"):
            args += ["--tf", tf]
        else:
            p = _json_arg(tf, "tf", tmpdir)
            if not p.endswith(".json"):
                raise ValueError(f"tf: a transfer-function file must end in .json, got {p!r}")
            args += ["--tf", p]
    if options.get("only_labels") is not None and options.get("hide_labels") is not None:
        raise ValueError("only_labels, hide_labels: give one or the other (the labels drawn, or those hidden)")
    for k, v in options.items():
        flag = "--" + k.replace("_", "-")
        if k.replace("_", "-") not in _FLAGS:
            near = difflib.get_close_matches(k, [f.replace("-", "_") for f in _FLAGS], n=1)
            hint = f" (did you mean {near[0]}=?)" if near else ""
            raise TypeError(f"render: unexpected keyword argument {k!r}{hint}")
        if k in _BUDGETS and v is not None and (
                isinstance(v, bool) or not isinstance(v, (int, np.integer, str))):
            # (As `process` and `convert` say of a budget that is no whole
            # number of bytes.)
            raise TypeError(f"{k}: expected bytes or a size such as \"1GiB\", got {v!r}")
        if isinstance(v, np.ndarray):
            v = v.tolist()
        elif isinstance(v, np.generic):
            v = v.item()
        if k in _WHOLE and v is not None and v is not False and (isinstance(v, bool) or not isinstance(v, int)):
            # (The CLI's parser said "invalid digit found in string" of 1.5.)
            raise TypeError(f"{k}: expected a whole number, found {v!r}")
        if k in _WHOLE and v is not None and v is not False and v < 0:
            raise ValueError(f"{k}: expected a whole number, 0 or more, found {v}")
        if k in _PATHS and v is not None and not isinstance(v, (str, os.PathLike)):
            raise TypeError(f"{k}: expected a file name, found {type(v).__name__} {v!r}")
        if isinstance(v, dict) and k not in _PER_CHANNEL:
            raise TypeError(f"{k}: a dict is no value of this option, found {v!r}")
        if v is True:
            args.append(flag)
        elif v is False or v is None:
            continue
        elif isinstance(v, (list, tuple)) and k in _REPEATED:
            for c in v:
                args.append(f"{flag}={c}")
        elif isinstance(v, dict) and k in _PER_CHANNEL:
            # {C: value}: `--channel-tf C=FILE`, `--channel-levels C=LO-HI`.
            for c, x in v.items():
                if k == "channel_levels" and isinstance(x, (list, tuple)):
                    x = "-".join(str(int(i)) for i in x)
                elif k == "channel_tf":
                    x = _json_arg(x, f"channel-tf-{int(c)}", tmpdir)
                args.append(f"{flag}={int(c)}={x}")
        elif isinstance(v, (list, tuple)):
            args.append(f"{flag}=" + ",".join(str(x) for x in v))
        elif isinstance(v, os.PathLike):
            args.append(f"{flag}={os.fspath(v)}")
        else:
            # `--flag=value`: a negative number is a value, not an option.
            args.append(f"{flag}={v}")
    return args


def _channel_options(channel: Any) -> None:
    """The channels of render's `channel` (an int, "C[:COLOR[:LO,HI]]" or a
    list of them): a negative one, or one beyond any store, is an
    IndexError (the CLI parses them as unsigned numbers)."""
    for c in channel if isinstance(channel, (list, tuple)) else (channel,):
        if not isinstance(c, (str, int, np.integer)) or isinstance(c, bool):
            raise TypeError(f"channel: expected an integer or \"C[:COLOR[:LO,HI]]\" text, found {c!r}")
        if isinstance(c, str) and re.fullmatch(r"\s*[+-]?[0-9]+\s*", c.split(":", 1)[0]):
            c = int(c.split(":", 1)[0])
        if isinstance(c, (int, np.integer)) and not isinstance(c, bool):
            _index_option(c, "channel")


def render(store: Union[Store, str, os.PathLike], mode: str = "dvr", camera: Any = None, tf: Any = None,
           size: Union[int, Tuple[int, int]] = (512, 512), backend: str = "auto", dtype: str = "uint8",
           out: Union[str, os.PathLike, None] = None, **options: Any) -> np.ndarray:
    """Render one view, or a turntable's views, exactly as `brickyard render` does with the same options.

    `camera` and `tf` are dicts, JSON text or JSON files as the CLI writes them
    (`tf` may also name a preset: linear, soft, hot, viridis, coolwarm, opaque;
    `labels` for a slice of a label image in its labels' colours). Without
    `tf`: soft, or `labels` for slices of a label image (a store's
    `labels/NAME`); `labels="NAME"` lays the store's `labels/NAME` over a
    slice (`label_opacity`, default 0.5); `only_labels=[3, 17]` or
    `hide_labels=[5]` draw only those labels of a label image, or all but
    them (in 3D the rays pass through the others).
    Further options are the CLI's, with `_` for `-` (`window=(0, 1000)`,
    `level=2`, `memory="1GiB"`, `channel=["0:red", "1:green"]`, ...).
    Returns `(h, w, 4)` RGBA: uint8 over black as the PNG holds it, or with
    `dtype="float32"` the premultiplied linear image. With `turntable=N`,
    all N views: `(N, h, w, 4)`, view 0 the camera's own. `out` also writes
    the PNG the CLI writes (`--out`; a turntable's views as
    `STEM-0000.png`, `STEM-0001.png`, ... beside it)."""
    if dtype not in ("uint8", "float32"):
        raise ValueError(f"dtype: expected uint8 or float32, found {dtype!r}")
    threads = options.pop("threads", None)
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, (int, np.integer))):
        raise TypeError(f"threads: expected a whole number of threads, found {threads!r}")
    if threads is not None and not 1 <= threads <= 1024:
        raise ValueError(f"threads: expected 1 to 1024 threads, found {threads}")
    level = options.get("level")
    if isinstance(level, (int, np.integer)) and not isinstance(level, bool):
        _index_option(level, "level")
    if options.get("channel") is not None:
        _channel_options(options["channel"])
    turntable = options.get("turntable")
    numbered = turntable is not None and turntable is not False
    if out is not None:
        out = os.fspath(out)
        options["out"] = out
    if isinstance(store, Store):
        # A closed handle, or one whose store was replaced or removed, is
        # refused as its reads are (the path would draw what is there now).
        store._open().check()
    with tempfile.TemporaryDirectory(prefix="brickyard-render-") as tmp:
        args = render_args(store, mode, camera, tf, size, backend, tmp, **options)
        try:
            with _cli_errors("render"):
                n, w, h, buf, notes = _native.render(args, dtype == "float32", out is not None,
                                                     None if threads is None else int(threads))
        except Exception as e:
            # The files written for dicts and JSON text are named as what
            # they were given as, not by their temporary names.
            if len(e.args) == 1 and isinstance(e.args[0], str) and tmp in e.args[0]:
                e.args = (re.sub(re.escape(tmp) + r"/([\w-]+)\.json", r"the \1 given", e.args[0]),)
            raise
    # Views drawn without some of their data (bricks that could not be
    # read: a damaged store, a server gone), or with less detail than asked
    # for (a coarser level or bias where the memory given holds no more,
    # fewer frames of samples) are returned, and said so.
    for note in notes:
        # What the CLI says on stderr beside its lines (labels past 2^24,
        # label ids filtered as intensities, damaged brick statistics).
        told = re.match(r"(warning|note): ", note)
        if told:
            warnings.warn(f"render: {_keywords(note[told.end():], 'render')}",
                          RuntimeWarning if told.group(1) == "warning" else UserWarning, stacklevel=2)
            continue
        if (any(m in note for m in ("could not be loaded", "stopped at", "(asked ", "volume's diagonal"))
                or re.search(r"\b\d+ of the \d+ frames", note)):
            # (Without `out`, no file was written: the line's file name,
            # the CLI's default, is left out.)
            if out is None and ": " in note:
                note = note.split(": ", 1)[1]
            warnings.warn(f"render: {note}", RuntimeWarning, stacklevel=2)
    views = np.frombuffer(buf, dtype=np.dtype(dtype)).reshape(n, h, w, 4)
    return views if numbered else views[0]


class _Bars:
    """tqdm bars for a native call's progress: one bar per phase ("start:PHASE"
    begins a new one; a plain "start" sets the total of the current one)."""

    def __init__(self, tqdm, what: str):
        self._tqdm = tqdm
        self._what = what
        self._bar = None

    def _open(self, desc: str, unit: str):
        self.close()
        self._bar = self._tqdm(total=0, unit=unit, unit_scale=True, desc=desc)

    def __call__(self, kind: str, n: int) -> None:
        if kind.startswith("start"):
            if ":" in kind or self._bar is None:
                phase = kind.split(":", 1)[1] if ":" in kind else ""
                self._open(f"{self._what}: {phase}" if phase else self._what,
                           "vox" if "voxels" in phase else "B")
            self._bar.reset(total=n)
        elif self._bar is not None:
            self._bar.update(n)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


def _progress_callback(progress: Any, what: str):
    """tqdm bars when `progress` is True and tqdm is installed; a callable is used as is."""
    if callable(progress):
        return progress, None
    if not progress:
        return None, None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None, None
    bars = _Bars(tqdm, what)
    return bars, bars


def _options(brick, shard, compression, labels, memory, overwrite, spacing, origin, unit, channel_names=None) -> dict:
    def three(v, what, kind):
        if v is None:
            return None
        if isinstance(v, (int, float, np.number)) and not isinstance(v, bool):
            v = (v, v, v)
        # (Text was taken letter by letter: "64" as two values, "1,2,3" as
        # a number that could not be read.)
        if isinstance(v, (str, bytes, bool)) or not hasattr(v, "__iter__"):
            raise TypeError(f"{what}: expected a number or three numbers (z, y, x), got {v!r}")
        try:
            v = tuple(kind(x) for x in v)
        except (TypeError, ValueError):
            raise TypeError(f"{what}: expected a number or three numbers (z, y, x), got {v!r}") from None
        if kind is int and any(x >= 1 << 63 for x in v):
            raise ValueError(f"{what}: expected sizes below 2^63 voxels, got {v}")
        if len(v) != 3:
            raise ValueError(f"{what}: expected three values (z, y, x), got {len(v)}")
        if kind is int and any(x < 1 for x in v):
            raise ValueError(f"{what}: expected sizes of at least 1 voxel, got {v}")
        # (Said here in the order given: the converter names x, y, z.)
        if what == "spacing" and not all(np.isfinite(x) and x > 0 for x in v):
            raise ValueError(f"spacing: expected positive numbers (z, y, x), got {v}")
        if what == "origin" and not all(np.isfinite(x) for x in v):
            raise ValueError(f"origin: expected finite numbers (z, y, x), got {v}")
        return v

    memory = _bytes(memory, "memory")
    if not isinstance(compression, str):
        raise TypeError(f"compression: expected a name such as lz4, zstd or none, got {compression!r}")
    # Whole bytes, as process() and render() take them (a float was cut to
    # its whole part: 1.5 became 1 byte).
    if isinstance(memory, bool) or not isinstance(memory, (int, np.integer)):
        raise TypeError(f"memory: expected bytes or a size such as \"1GiB\", got {memory!r}")
    if memory < 0 or memory >= 1 << 64:
        raise ValueError(f"memory: expected a number of bytes from 0 to 2^64 - 1, got {memory}")
    if unit is not None and not isinstance(unit, str):
        raise TypeError(f"unit: expected a name such as micrometer, got {unit!r}")
    # (shard None: `convert`'s default for the brick, as without --shard.)
    return {"brick": three(brick, "brick", int), "shard": three(shard, "shard", int),
            "compression": compression, "labels": bool(labels), "memory": int(memory),
            "overwrite": bool(overwrite), "spacing": three(spacing, "spacing", float),
            "origin": three(origin, "origin", float), "unit": unit,
            "channel_names": _channel_names(channel_names)}


def _channel_names(names: Any) -> Optional[list]:
    """`channel_names` as `convert --channel-names` takes them: one string per
    channel (a sequence, or one comma-separated string), none empty, none
    twice; the count is checked against the input's channels."""
    if names is None:
        return None
    if isinstance(names, str):
        names = names.split(",")
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise TypeError(f"channel_names: expected a list of strings, got {names!r}")
    names = [n.strip() for n in names]
    for i, n in enumerate(names):
        if not n:
            raise ValueError(f"channel_names: name {i + 1} of {names!r} is empty")
        if n in names[:i]:
            raise ValueError(f"channel_names: {n!r} given twice (names {names.index(n) + 1} and {i + 1}); "
                             "each channel needs a name of its own")
    return names


def convert(src: Union[str, os.PathLike, Sequence[Union[str, os.PathLike]]], dst: Union[str, os.PathLike], *,
            brick=64, shard=None, compression: str = "lz4", labels: bool = False, memory: int = 1 << 30,
            overwrite: bool = False, spacing=None, origin=None, unit: Optional[str] = None, level: int = 0,
            progress: Any = True, channel_names=None) -> str:
    """Convert any input `brickyard convert` reads into a brickyard OME-Zarr
    pyramid at `dst`. Returns a one-line report. `src` may be a list of
    inputs of one grid: they become the store's channels, in order, as
    `brickyard convert IN1 IN2 ... OUT` stacks them. `channel_names` (one per
    channel, as `--channel-names`) replaces the names the inputs give."""
    level = _index_option(level, "level")
    srcs = [src] if isinstance(src, (str, bytes, os.PathLike)) else list(src)
    cb, bar = _progress_callback(progress, "convert")
    try:
        with _cli_errors("convert"):
            return _warn_notes(dst, _native.convert([os.fspath(s) for s in srcs], os.fspath(dst),
                                   _options(brick, shard, compression, labels, memory, overwrite, spacing, origin,
                                            unit, channel_names),
                                   level, cb))
    finally:
        if bar is not None:
            bar.close()


def _warn_notes(dst: Any, report: str, command: str = "convert") -> str:
    """`report` as written, with its notes (no voxel spacing in the input; a
    label image off its image's grid: listed, but not drawn over it; no
    table of label statistics) also raised as UserWarnings, which a script
    sees where a note inside the returned text goes unread, their flags as
    keyword arguments. Which input became which channel is said in the
    report only (it warns of nothing)."""
    for note in report.split("; note: ")[1:]:
        if re.match(r"channels? \d+(, \d+)* from ", note):
            continue
        warnings.warn(f"{os.fspath(dst)}: {_keywords(note, command)}", UserWarning, stacklevel=3)
    return report


def _chunk_of(array: Any) -> Optional[Tuple[int, int, int]]:
    """The `(z, y, x)` chunk a lazy array reads best: dask's `chunksize`,
    zarr's or h5py's `chunks`; None when it has none."""
    for attr in ("chunksize", "chunks"):
        c = getattr(array, attr, None)
        if isinstance(c, tuple) and len(c) >= 3 and all(isinstance(v, (int, np.integer)) for v in c):
            return tuple(int(v) for v in c[-3:])
    return None


def _lazy_dtype(array: Any) -> Optional[np.dtype]:
    """The NumPy dtype of an array that is read region by region (anything
    with `shape`, `dtype` and `__getitem__` that is not an in-memory NumPy
    array: dask, zarr, h5py, np.memmap); None for anything else."""
    if isinstance(array, np.ndarray) and not isinstance(array, np.memmap):
        return None
    if not all(hasattr(array, a) for a in ("shape", "dtype", "__getitem__")):
        return None
    try:
        return np.dtype(array.dtype)
    except TypeError:
        return None


def from_numpy(array: Any, dst: Union[str, os.PathLike], *, spacing=None, origin=None, unit: Optional[str] = None,
               brick=64, shard=None, compression: str = "lz4", labels: bool = False, memory: int = 1 << 30,
               overwrite: bool = False, progress: Any = True, channel_names=None) -> str:
    """Write a `(z, y, x)` or `(c, z, y, x)` array as a brickyard OME-Zarr pyramid.
    `channel_names`: one per channel (else "channel 0", "channel 1", ...),
    stored in the OME `omero` metadata and read back as `Store.channel_names`.

    Every type `convert` stores is taken (uint8, int8, uint16, int16,
    uint32, int32, float32, float64), and as `convert` reads them: bool as
    uint8, float16 as float32, int64 and uint64 as int32 and uint32 where
    every value fits (`skimage.measure.label`'s labels, NumPy's default
    integers); a value that does not fit is a ValueError naming it.

    A C-contiguous NumPy array in the machine's byte order is read where it
    lies (no copy); any other NumPy array (a strided view, a transposed or
    byte-swapped one) region by region, as a lazy array is. A lazy array
    (dask, zarr, h5py, `np.memmap`, anything with `shape`, `dtype` and
    `__getitem__`) is never materialised whole: the builder asks for one
    region at a time (slabs of `brick` planes, at most what `memory`
    allows) and each is fetched with `array[c, z0:z1, y0:y1, x0:x1]` (a dask
    region is computed then). Other inputs go through `np.asarray`."""
    options = _options(brick, shard, compression, labels, memory, overwrite, spacing, origin, unit, channel_names)
    dt = _lazy_dtype(array)
    if dt is None:
        return _from_memory(np.asarray(array), dst, options, progress)
    name = f"<{type(array).__module__}.{type(array).__name__} of shape {tuple(int(n) for n in array.shape)}>"
    return _from_regions(array, dt, name, dst, options, progress)


# Types stored as another that holds every value as `convert` reads them:
# booleans as uint8, float16 as float32; 64-bit integers as 32-bit ones
# when every value fits (else an error naming a value that does not).
_STORED_AS = {"bool": "uint8", "float16": "float32", "int64": "int32", "uint64": "uint32"}


def _narrow(block: np.ndarray, to: np.dtype, where: str) -> np.ndarray:
    """`block` as `to` (see `_STORED_AS`); a ValueError where a 64-bit
    integer does not fit."""
    if block.dtype.kind in "iu" and block.size:
        lo, hi = block.min(), block.max()
        info = np.iinfo(to)
        if lo < info.min or hi > info.max:
            bad = lo if lo < info.min else hi
            raise ValueError(f"array: {block.dtype} value {bad}{where} does not fit {to} ({info.min} to {info.max}), "
                             "the 32-bit type brickyard stores 64-bit integers as; rescale it, or store it as "
                             "float32/float64 (array.astype(np.float64))")
    return block.astype(to)


def _from_regions(array: Any, dt: np.dtype, name: str, dst, options: dict, progress) -> str:
    """The conversion of an array read region by region (`from_numpy`)."""
    shape = tuple(int(n) for n in array.shape)
    if len(shape) not in (3, 4):
        raise ValueError(f"array: expected (z, y, x) or (c, z, y, x), got {len(shape)} dimension(s) of shape {shape}")
    given = dt
    if dt.name in _STORED_AS:
        dt = np.dtype(_STORED_AS[dt.name])
    if dt.name not in _DTYPES:
        raise TypeError(f"array: dtype {dt} is not stored by brickyard (one of {', '.join(_DTYPES)}, "
                        f"or {', '.join(_STORED_AS)} stored as such)")
    native = dt.newbyteorder("=")
    four = len(shape) == 4

    def read(c: int, z0: int, z1: int, y0: int, y1: int, x0: int, x1: int) -> bytes:
        key = (slice(z0, z1), slice(y0, y1), slice(x0, x1))
        block = array[(c,) + key] if four else array[key]
        block = np.asarray(block)
        if block.shape != (z1 - z0, y1 - y0, x1 - x0):
            raise ValueError(f"array: [{z0}:{z1}, {y0}:{y1}, {x0}:{x1}] of channel {c} has shape {block.shape}")
        if given.name in _STORED_AS:
            block = _narrow(block, native, f" in [{z0}:{z1}, {y0}:{y1}, {x0}:{x1}] of channel {c}")
        return np.ascontiguousarray(block, dtype=native).tobytes()

    c4 = shape if four else (1,) + shape
    cb, bar = _progress_callback(progress, "from_numpy")
    try:
        with _cli_errors("convert"):
            return _warn_notes(dst, _native.from_lazy(read, name, c4, native.name, _chunk_of(array), os.fspath(dst), options, cb))
    finally:
        if bar is not None:
            bar.close()


def _from_memory(a: np.ndarray, dst, options: dict, progress) -> str:
    if a.ndim == 3:
        a = a[np.newaxis]
    if a.ndim != 4:
        raise ValueError(f"array: expected (z, y, x) or (c, z, y, x), got {a.ndim} dimension(s) of shape {a.shape}")
    if a.dtype.name in _STORED_AS:
        # One pass for the range of 64-bit integers, then the copy in the
        # narrower type (which takes half their memory, or the same for
        # booleans as bytes, a float16 array twice its own).
        a = _narrow(a, np.dtype(_STORED_AS[a.dtype.name]), "")
    if a.dtype.name not in _DTYPES:
        raise TypeError(f"array: dtype {a.dtype} is not stored by brickyard (one of {', '.join(_DTYPES)}, "
                        f"or {', '.join(_STORED_AS)} stored as such)")
    if not (a.flags.c_contiguous and a.dtype.isnative):
        # Read region by region (each converted to C order and the native
        # byte order as it is read): a whole copy would double the memory.
        return _from_regions(a, a.dtype, "<numpy array>", dst, options, progress)
    cb, bar = _progress_callback(progress, "from_numpy")
    try:
        with _cli_errors("convert"):
            return _warn_notes(dst, _native.from_array(a, a.dtype.name, os.fspath(dst), options, cb))
    finally:
        if bar is not None:
            bar.close()


def process(store: Union[Store, str, os.PathLike], pipeline: str, out: str, *, level: int = 0, channel: int = 0,
            memory: Union[int, str] = "1GiB", stats: Union[str, os.PathLike, None] = None, overwrite: bool = False,
            backend: str = "cpu", progress: Any = True, open_result: bool = True) -> Union[Store, str]:
    """Run a pipeline over a level of a store and write the result into the
    store at every level, exactly as `brickyard process STORE PIPELINE --out
    OUT` does (the same stages, syntax, messages and output).

    `pipeline` is e.g. `"gauss(1.5)|sobel"` or
    `"gauss(1.5)|threshold(300)|label(26)"`: stages gauss(σ), gradmag(σ),
    sobel, median(r), threshold(t), window(lo,hi), label(6|26); σ in voxels, or with a
    unit (`1.5um`). Labels and masks go to `STORE/labels/OUT`, other results
    to `STORE/derived/OUT`. `stats` also writes the per-label statistics of
    a labelling to a .csv or .json file. `backend` is cpu, gpu or auto (the
    filter stages; labelling runs on the CPU). Returns the result opened
    (a `Store`), or its path with `open_result=False`. Bad pipeline text
    raises ValueError with the CLI's message, a level or channel outside
    the store IndexError; Ctrl-C stops the job and leaves the store as it
    was."""
    if isinstance(store, Store):
        # A closed handle, or one whose store was replaced or removed, is
        # refused as render() and reads refuse it (the path would process
        # what is there now).
        store._open().check()
    path = store.path if isinstance(store, Store) else os.fspath(store)
    if not isinstance(pipeline, str):
        raise TypeError(f"pipeline: expected text such as \"gauss(1.5)|sobel\", got {type(pipeline).__name__}")
    if not isinstance(out, str):
        raise TypeError(f"out: expected a name, got {type(out).__name__}")
    if isinstance(memory, bool) or not isinstance(memory, (int, np.integer, str)):
        raise TypeError(f"memory: expected bytes or a size such as \"1GiB\", got {memory!r}")
    if backend not in ("cpu", "gpu", "auto"):
        raise ValueError(f"backend: expected cpu, gpu or auto, found {backend!r}")
    level = _index_option(level, "level")
    channel = _index_option(channel, "channel")
    cb, bar = _progress_callback(progress, "process")
    try:
        with _cli_errors("process"):
            result, _labels, _line = _native.process(path, pipeline, out, str(memory), level, channel,
                                                     None if stats is None else os.fspath(stats), bool(overwrite),
                                                     backend, cb)
    finally:
        if bar is not None:
            bar.close()
    result = os.fspath(result)
    # What the CLI's report says of the result (label ids filtered as
    # intensities, labels off the image's grid), as UserWarnings.
    _warn_notes(result, _line, "process")
    return open(result) if open_result else result
