"""Type stubs of the extension module `brickyard._native` (use `brickyard`'s API)."""

from os import PathLike
from pathlib import Path
from typing import Any, Callable, Optional, Sequence, Tuple, TypedDict, Union

class ConvertOptions(TypedDict):
    brick: Tuple[int, int, int]
    shard: Tuple[int, int, int]
    compression: str
    labels: bool
    memory: int
    overwrite: bool
    spacing: Optional[Tuple[float, float, float]]
    origin: Optional[Tuple[float, float, float]]
    unit: Optional[str]

# progress(kind, n): kind "start" (or "start:PHASE" for a named phase) with the total, "inc" with the amount done
Progress = Callable[[str, int], None]

class NativeStore:
    # path: a directory or an http(s):// URL
    def __init__(self, path: Union[str, PathLike], cache_bytes: int, chunk_bytes: int, brick: int,
                 threads: int) -> None: ...
    # a pathlib.Path (a URL loses its '//' there: brickyard.Store keeps the text given)
    @property
    def path(self) -> Path: ...
    @property
    def shapes(self) -> list[Tuple[int, int, int]]: ...
    @property
    def channels(self) -> int: ...
    @property
    def dtype(self) -> str: ...
    @property
    def scales(self) -> list[Optional[list[float]]]: ...
    @property
    def translations(self) -> list[Optional[list[float]]]: ...
    @property
    def axes(self) -> list[str]: ...
    @property
    def units(self) -> list[Optional[str]]: ...
    def cache_stats(self) -> Tuple[int, int, int, int]: ...
    def bytes_read(self) -> int: ...
    def read(self, level: int, channel: int, lo: Sequence[int], hi: Sequence[int]) -> bytearray: ...

# (views, width, height, pixels): every view's pixels one after the other; with out, each view written as a PNG
def render(args: Sequence[str], float: bool = False, write: bool = False) -> Tuple[int, int, int, bytearray, list]: ...
def convert(src: Union[str, PathLike], dst: Union[str, PathLike], options: ConvertOptions, zarr_level: int = 0,
            progress: Optional[Progress] = None) -> str: ...
# array: a C-contiguous, native-endian NumPy array (c, z, y, x), read in place
def from_array(array: Any, dtype: str, dst: Union[str, PathLike], options: ConvertOptions,
               progress: Optional[Progress] = None) -> str: ...
def from_lazy(read: Callable[[int, int, int, int, int, int, int], bytes], name: str,
              shape: Tuple[int, int, int, int], dtype: str, chunk: Optional[Tuple[int, int, int]],
              dst: Union[str, PathLike], options: ConvertOptions, progress: Optional[Progress] = None) -> str: ...
def process(store: Union[str, PathLike], pipeline: str, out: str, memory: str, level: int = 0, channel: int = 0,
            stats: Union[str, PathLike, None] = None, overwrite: bool = False, backend: str = "cpu",
            progress: Optional[Progress] = None) -> Tuple[Path, Optional[int], str]: ...
