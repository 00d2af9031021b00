"""brickyard: out-of-core reads, rendering and conversion of huge OME-Zarr volumes.

    import brickyard, numpy as np
    store = brickyard.open("volume.ome.zarr")
    block = store.read(level=0, region=np.s_[0:64, 100:228, 100:228])
    rgba = brickyard.render(store, mode="dvr", tf="soft", size=(512, 512))

Reads go through brickyard's loader and a host cache of bounded size, so any
region of a store larger than memory can be read. `render` draws exactly what
`brickyard render` draws for the same options.
"""

from __future__ import annotations

import builtins
import json
import os
import tempfile
from typing import Any, Optional, Sequence, Tuple, Union

import numpy as np

from . import _native

__all__ = ["open", "Store", "Level", "render", "convert", "from_numpy"]

_MODES = ("dvr", "mip", "slice")
_BACKENDS = ("auto", "cpu", "gpu")
_DTYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")


def _region(region: Any, shape: Sequence[int]) -> Tuple[Tuple[int, int, int], Tuple[int, int, int], Tuple[bool, bool, bool]]:
    """A region (`np.s_[z0:z1, y0:y1, x0:x1]`, ints, or None) as lo, hi and
    which axes an integer index drops."""
    if region is None:
        region = ()
    if not isinstance(region, tuple):
        region = (region,)
    if any(r is Ellipsis for r in region):
        i = next(k for k, r in enumerate(region) if r is Ellipsis)
        fill = 3 - (len(region) - 1)
        region = region[:i] + (slice(None),) * fill + region[i + 1 :]
    if len(region) > 3:
        raise IndexError(f"region: expected at most 3 axes (z, y, x), got {len(region)}")
    region = tuple(region) + (slice(None),) * (3 - len(region))
    lo, hi, drop = [], [], []
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
            drop.append(True)
        elif isinstance(r, slice):
            if r.step not in (None, 1):
                raise ValueError(f"region: axis {name}: only step 1 is supported, got {r.step}")
            a, b, _ = r.indices(n)
            if b <= a:
                raise IndexError(f"region: axis {name}: {r.start}:{r.stop} selects nothing of length {n}")
            if (r.start is not None and not -n <= r.start <= n) or (r.stop is not None and not -n <= r.stop <= n):
                raise IndexError(f"region: axis {name}: {r.start}:{r.stop} is outside length {n}")
            lo.append(a)
            hi.append(b)
            drop.append(False)
        else:
            raise TypeError(f"region: axis {name}: expected an int or a slice, got {type(r).__name__}")
    return (lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2]), (drop[0], drop[1], drop[2])


class Store:
    """An OME-Zarr store opened for out-of-core reading (see `brickyard.open`)."""

    def __init__(self, path: Union[str, os.PathLike], cache: int = 256 << 20, chunk_cache: int = 64 << 20,
                 brick: int = 64, threads: Optional[int] = None):
        threads = threads or min(8, os.cpu_count() or 1)
        self._native = _native.NativeStore(os.fspath(path), int(cache), int(chunk_cache), int(brick), int(threads))

    @property
    def path(self) -> str:
        return os.fspath(self._native.path)

    @property
    def levels(self) -> int:
        return len(self._native.shapes)

    @property
    def shapes(self) -> list:
        """Shape `(z, y, x)` of every level, level 0 first."""
        return [tuple(s) for s in self._native.shapes]

    @property
    def shape(self) -> tuple:
        """`(c, z, y, x)` of level 0."""
        return (self.channels,) + self.shapes[0]

    @property
    def channels(self) -> int:
        return self._native.channels

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(self._native.dtype)

    @property
    def scales(self) -> list:
        """The OME `scale` of every level (one number per axis), None where absent."""
        return self._native.scales

    @property
    def translations(self) -> list:
        return self._native.translations

    @property
    def axes(self) -> list:
        return self._native.axes

    @property
    def units(self) -> list:
        return self._native.units

    def cache_stats(self) -> dict:
        """The host cache: bytes held, budget, hits, misses; bytes read from the store."""
        held, budget, hits, misses = self._native.cache_stats()
        return {"bytes": held, "budget": budget, "hits": hits, "misses": misses,
                "bytes_read": self._native.bytes_read()}

    def level(self, level: int) -> "Level":
        if not 0 <= level < self.levels:
            raise IndexError(f"level: {level} asked for but the store has {self.levels} level(s)")
        return Level(self, level)

    def read(self, level: int = 0, channel: int = 0, region: Any = None) -> np.ndarray:
        """The region (`np.s_[z0:z1, y0:y1, x0:x1]`; None = the whole level) of
        one level and channel, through the loader and host cache."""
        if not isinstance(level, (int, np.integer)) or not 0 <= level < self.levels:
            raise IndexError(f"level: {level} asked for but the store has {self.levels} level(s)")
        if not isinstance(channel, (int, np.integer)) or not 0 <= channel < self.channels:
            raise IndexError(f"channel: {channel} asked for but the store has {self.channels} channel(s)")
        lo, hi, drop = _region(region, self.shapes[level])
        buf = self._native.read(int(level), int(channel), lo, hi)
        a = np.frombuffer(buf, dtype=self.dtype).reshape(tuple(h - l for l, h in zip(lo, hi)))
        index = tuple(0 if d else slice(None) for d in drop)
        return a[index]

    def __getitem__(self, key: Any) -> np.ndarray:
        """`store[c, z0:z1, y0:y1, x0:x1]` (level 0); with three axes, channel 0."""
        if not isinstance(key, tuple):
            key = (key,)
        if len(key) == 4:
            c = key[0]
            if not isinstance(c, (int, np.integer)):
                raise TypeError("store[c, z, y, x]: the channel must be an integer")
            return self.read(0, int(c) % self.channels if c < 0 else int(c), key[1:])
        return self.read(0, 0, key)

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
        return self.store.shapes[self.index]

    @property
    def dtype(self) -> np.dtype:
        return self.store.dtype

    def read(self, channel: int = 0, region: Any = None) -> np.ndarray:
        return self.store.read(self.index, channel, region)

    def __getitem__(self, key: Any) -> np.ndarray:
        if not isinstance(key, tuple):
            key = (key,)
        if len(key) == 4:
            return self.store.read(self.index, int(key[0]), key[1:])
        return self.store.read(self.index, 0, key)

    def __repr__(self) -> str:
        return f"<brickyard.Level {self.index} of {self.store.path!r}: {self.shape}>"


def open(path: Union[str, os.PathLike], cache: int = 256 << 20, chunk_cache: int = 64 << 20,
         brick: int = 64, threads: Optional[int] = None) -> Store:
    """Open an OME-Zarr store. `cache` bounds the host cache of decoded bricks
    and `chunk_cache` the decoded store chunks (bytes)."""
    return Store(path, cache=cache, chunk_cache=chunk_cache, brick=brick, threads=threads)


def _json_arg(value: Any, what: str, tmp: str) -> str:
    """A dict or JSON text written to a file for the CLI's options; a path as is."""
    if isinstance(value, dict):
        text = json.dumps(value)
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


def render_args(store: Union[Store, str, os.PathLike], mode: str = "dvr", camera: Any = None, tf: Any = "soft",
                size: Union[int, Tuple[int, int]] = (512, 512), backend: str = "auto", tmpdir: str = ".",
                **options: Any) -> list:
    """The `brickyard render` arguments for these options (files for dicts are written in `tmpdir`)."""
    path = store.path if isinstance(store, Store) else os.fspath(store)
    if mode not in _MODES:
        raise ValueError(f"mode: expected dvr, mip or slice, found {mode!r}")
    if backend not in _BACKENDS:
        raise ValueError(f"backend: expected auto, cpu or gpu, found {backend!r}")
    if isinstance(size, (int, np.integer)):
        size = (int(size), int(size))
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
    for k, v in options.items():
        flag = "--" + k.replace("_", "-")
        if v is True:
            args.append(flag)
        elif v is False or v is None:
            continue
        elif isinstance(v, (list, tuple)) and k == "channel":
            for c in v:
                args.append(f"{flag}={c}")
        elif isinstance(v, (list, tuple)):
            args.append(f"{flag}=" + ",".join(str(x) for x in v))
        else:
            # `--flag=value`: a negative number is a value, not an option.
            args.append(f"{flag}={v}")
    return args


def render(store: Union[Store, str, os.PathLike], mode: str = "dvr", camera: Any = None, tf: Any = "soft",
           size: Union[int, Tuple[int, int]] = (512, 512), backend: str = "auto", dtype: str = "uint8",
           **options: Any) -> np.ndarray:
    """Render one view, exactly as `brickyard render` does with the same options.

    `camera` and `tf` are dicts, JSON text or JSON files as the CLI writes them
    (`tf` may also name a preset: linear, soft, hot, viridis, coolwarm, opaque).
    Further options are the CLI's, with `_` for `-` (`window=(0, 1000)`,
    `level=2`, `memory="1GiB"`, `channel=["0:red", "1:green"]`, ...).
    Returns `(h, w, 4)` RGBA: uint8 over black as the PNG holds it, or with
    `dtype="float32"` the premultiplied linear image."""
    if dtype not in ("uint8", "float32"):
        raise ValueError(f"dtype: expected uint8 or float32, found {dtype!r}")
    with tempfile.TemporaryDirectory(prefix="brickyard-render-") as tmp:
        args = render_args(store, mode, camera, tf, size, backend, tmp, **options)
        w, h, buf = _native.render(args, dtype == "float32")
    return np.frombuffer(buf, dtype=np.dtype(dtype)).reshape(h, w, 4)


def _progress_callback(progress: Any, what: str):
    """A tqdm bar when `progress` is True and tqdm is installed; a callable is used as is."""
    if callable(progress):
        return progress, None
    if not progress:
        return None, None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None, None
    bar = tqdm(total=0, unit="B", unit_scale=True, desc=what)

    def cb(kind: str, n: int) -> None:
        if kind == "start":
            bar.reset(total=n)
        else:
            bar.update(n)

    return cb, bar


def _options(brick, shard, compression, labels, memory, overwrite, spacing, origin, unit) -> dict:
    def three(v, what, kind):
        if v is None:
            return None
        if isinstance(v, (int, float, np.number)):
            v = (v, v, v)
        v = tuple(kind(x) for x in v)
        if len(v) != 3:
            raise ValueError(f"{what}: expected three values (z, y, x), got {len(v)}")
        return v

    if isinstance(memory, str):
        raise TypeError("memory: give a number of bytes")
    return {"brick": three(brick, "brick", int), "shard": three(shard, "shard", int),
            "compression": compression, "labels": bool(labels), "memory": int(memory),
            "overwrite": bool(overwrite), "spacing": three(spacing, "spacing", float),
            "origin": three(origin, "origin", float), "unit": unit}


def convert(src: Union[str, os.PathLike], dst: Union[str, os.PathLike], *, brick=64, shard=512,
            compression: str = "lz4", labels: bool = False, memory: int = 1 << 30, overwrite: bool = False,
            spacing=None, origin=None, unit: Optional[str] = None, level: int = 0, progress: Any = True) -> str:
    """Convert any input `brickyard convert` reads into a brickyard OME-Zarr
    pyramid at `dst`. Returns a one-line report."""
    cb, bar = _progress_callback(progress, "convert")
    try:
        return _native.convert(os.fspath(src), os.fspath(dst),
                               _options(brick, shard, compression, labels, memory, overwrite, spacing, origin, unit),
                               int(level), cb)
    finally:
        if bar is not None:
            bar.close()


def from_numpy(array: Any, dst: Union[str, os.PathLike], *, spacing=None, origin=None, unit: Optional[str] = None,
               brick=64, shard=512, compression: str = "lz4", labels: bool = False, memory: int = 1 << 30,
               overwrite: bool = False, progress: Any = True) -> str:
    """Write a `(z, y, x)` or `(c, z, y, x)` array (NumPy, or anything
    `np.asarray` takes, a dask array computed) as a brickyard OME-Zarr pyramid."""
    a = np.asarray(array)
    if a.ndim == 3:
        a = a[np.newaxis]
    if a.ndim != 4:
        raise ValueError(f"array: expected (z, y, x) or (c, z, y, x), got {a.ndim} dimension(s) of shape {a.shape}")
    if a.dtype.name not in _DTYPES:
        raise TypeError(f"array: dtype {a.dtype} is not stored by brickyard (one of {', '.join(_DTYPES)})")
    a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("="))
    cb, bar = _progress_callback(progress, "from_numpy")
    try:
        return _native.from_bytes(a.tobytes(), tuple(int(x) for x in a.shape), a.dtype.name, os.fspath(dst),
                                  _options(brick, shard, compression, labels, memory, overwrite, spacing, origin, unit),
                                  cb)
    finally:
        if bar is not None:
            bar.close()
