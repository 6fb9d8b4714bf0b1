"""Type stubs of the native module (python/src/lib.rs); the documented API is strata's."""

import os
from typing import Callable

__version__: str

class StrataError(Exception): ...
class StoreError(StrataError): ...
class StoreNotFoundError(StoreError): ...
class DamagedStoreError(StoreError): ...
class StoreInUseError(StoreError): ...
class SourceError(StrataError): ...

class NativeStore:
    @property
    def path(self) -> os.PathLike[str]: ...
    def header_json(self) -> str: ...
    def stats_json(self) -> str: ...
    def close(self) -> None: ...
    def read_region(self, level: int, frame: int, lo: list[int], hi: list[int]) -> bytearray: ...

def open_store(path: str) -> NativeStore: ...
def import_file(
    src: str,
    dst: str,
    progress: Callable[[int, int], object] | None = None,
    memory_mib: int = 1024,
    codec: str = "fast",
    series: str | None = None,
) -> str: ...
def import_raw(
    raw: str,
    dst: str,
    dims: list[int],
    frames: int,
    dtype: str,
    little_endian: bool,
    spacing: list[float],
    origin: list[float],
    direction: list[list[float]],
    slope: float,
    intercept: float,
    modality: str,
    description: str,
    progress: Callable[[int, int], object] | None = None,
    memory_mib: int = 1024,
    codec: str = "fast",
) -> str: ...
