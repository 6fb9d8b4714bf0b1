"""Strata from Python: open brick stores, read regions as numpy, import files and arrays.

>>> import strata
>>> vol = strata.open("scan.strata")              # a store `strata import` wrote
>>> vol = strata.open("http://host:8080/v1/stores/scan", token=...)  # or one strata serve serves
>>> vol.shape, vol.spacing, vol.dtype              # (z, y, x), mm, the physical dtype
>>> block = vol.level(0)[100:164, 200:300, :]      # numpy, read brick by brick
>>> vol.affine                                     # index (i, j, k, 1) → LPS mm
>>> image = strata.render(vol, azimuth=30, size=256)  # (256, 256, 4) RGBA, as `strata render`

Errors are :class:`StrataError` subclasses carrying the Rust library's message; bad indices
raise ``IndexError``, bad arguments ``ValueError``.
"""

from __future__ import annotations

from ._import import export_omezarr, from_numpy, import_file
from ._render import render
from ._serve import Server, serve
from ._strata import (
    DamagedStoreError,
    RemoteError,
    RenderError,
    SourceError,
    StoreError,
    StoreInUseError,
    StoreNotFoundError,
    StrataError,
    TokenError,
    __version__,
)
from ._volume import BRICK_CORE, Level, ValueMapping, Volume, WindowPreset, open
from .widget import Viewer  # a Jupyter widget; needs anywidget only when used

__all__ = [
    "BRICK_CORE",
    "DamagedStoreError",
    "Level",
    "RemoteError",
    "RenderError",
    "Server",
    "SourceError",
    "StoreError",
    "StoreInUseError",
    "StoreNotFoundError",
    "StrataError",
    "TokenError",
    "ValueMapping",
    "Viewer",
    "Volume",
    "WindowPreset",
    "__version__",
    "export_omezarr",
    "from_numpy",
    "import_file",
    "open",
    "render",
    "serve",
]
