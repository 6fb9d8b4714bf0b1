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
class RemoteError(StrataError): ...
class TokenError(RemoteError): ...
class RenderError(StrataError): ...

class NativeStore:
    @property
    def path(self) -> os.PathLike[str] | None: ...
    @property
    def location(self) -> str: ...
    @property
    def kind(self) -> str: ...
    def notes(self) -> list[str]: ...
    def frame_count(self) -> int: ...
    def header_json(self) -> str: ...
    def stats_json(self) -> str: ...
    def close(self) -> None: ...
    def read_region(self, level: int, frame: int, lo: list[int], hi: list[int]) -> bytearray: ...

def open_store(location: str, token: str | None = None, timeout_s: float = 20.0) -> NativeStore: ...
def export_omezarr(volume: NativeStore, dest: str) -> tuple[int, int, int, int, int]: ...
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

class NativeServer:
    @property
    def base_url(self) -> str: ...
    def stores(self) -> list[tuple[str, str]]: ...
    def stop(self) -> None: ...

def serve(
    paths: list[str],
    port: int = 0,
    host: str = "127.0.0.1",
    token: str | None = None,
    web_viewer: str | None = None,
    frame_ancestors: str | None = None,
) -> NativeServer: ...

def render(
    store: NativeStore,
    *,
    width: int,
    height: int,
    azimuth: float,
    elevation: float,
    zoom: float,
    mode: str,
    tf: str | None,
    step: float,
    level: int,
    up_front: bool,
    max_frames: int,
    quality: float,
    reference: bool,
    shading: bool,
    iso: float,
    orthographic: bool,
    jitter: bool,
    smooth: bool,
    exact_trilinear: bool,
    oracle_epsilon: float,
    traversal: str | None,
    gpu_mib: int | None,
    shadows: str,
    light_dir: list[float] | None,
    shadow_step: float,
    light_cache_res: float,
    occlusion: float | None,
    scattering: float | None,
    scattering_blend: float,
    progressive: int | None,
) -> tuple[int, int, bytearray, list[str]]: ...
