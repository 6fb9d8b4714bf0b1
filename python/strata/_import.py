"""Imports: files through ``strata import``'s readers, and numpy arrays."""

from __future__ import annotations

import os
import sys
import tempfile
import warnings
from typing import Any, Callable, Union

import numpy as np

from . import _strata
from ._volume import Volume, open

#: ``progress=``: True (a tqdm bar when tqdm is installed, in notebooks too, else a line on
#: stderr), False/None (quiet), or a callable ``f(done_bytes, total_bytes)``.
Progress = Union[bool, None, Callable[[int, int], object]]


def _progress_callback(progress: Progress, label: str) -> tuple[Callable[[int, int], object] | None, Callable[[], None]]:
    """The callback the native import calls about ten times a second, and a closer."""
    if progress is None or progress is False:
        return None, lambda: None
    if callable(progress):
        return progress, lambda: None
    try:
        from tqdm.auto import tqdm
    except ImportError:
        tqdm = None
    if tqdm is not None:
        bar = tqdm(total=0, unit="B", unit_scale=True, desc=label)

        def update(done: int, total: int) -> None:
            if total and bar.total != total:
                bar.total = total
            bar.n = done
            bar.refresh()

        return update, bar.close
    last = [-1]

    def line(done: int, total: int) -> None:
        percent = int(100 * done / total) if total else 0
        if percent != last[0]:
            last[0] = percent
            sys.stderr.write(f"\r{label}: {percent:3d} % of {total / 1e6:.1f} MB")
            sys.stderr.flush()

    def end() -> None:
        if last[0] >= 0:
            sys.stderr.write("\n")

    return line, end


def import_file(
    src: str | os.PathLike[str],
    dst: str | os.PathLike[str],
    progress: Progress = True,
    *,
    codec: str = "fast",
    memory_mib: int = 1024,
    series: str | None = None,
) -> Volume:
    """Imports ``src`` into a new store at ``dst`` and opens it, as ``strata import SRC DST``.

    ``src``: a DICOM folder or file, NIfTI (.nii, .nii.gz), NRRD, MetaImage, FreeSurfer MGH/MGZ
    — the readers of ``strata import``. An existing store at ``dst`` is replaced. ``codec``:
    ``"fast"`` (default) or ``"dense"``; ``memory_mib`` bounds the import's buffers;
    ``series`` picks a DICOM series (SeriesInstanceUID or index) in a folder holding several.
    The GIL is released while it runs; Ctrl-C cancels it (``KeyboardInterrupt``).

    Raises :class:`strata.SourceError` when ``src`` cannot be read, and a
    :class:`strata.StoreError` when ``dst`` cannot be written.
    """
    callback, close = _progress_callback(progress, "importing")
    try:
        _strata.import_file(os.fspath(src), os.fspath(dst), callback, memory_mib, codec, series)
    finally:
        close()
    return open(dst)


_IMPORTABLE = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")


def _geometry(
    spacing: Any, affine: Any
) -> tuple[list[float], list[float], list[list[float]]]:
    """(spacing x, y, z; origin LPS; direction rows = index axes) from the arguments."""
    if affine is None:
        s = np.broadcast_to(np.asarray(1.0 if spacing is None else spacing, dtype=np.float64), (3,))
        return [float(v) for v in s[::-1]], [0.0, 0.0, 0.0], np.eye(3).tolist()
    a = np.asarray(affine, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise ValueError(f"affine must be a finite 4×4 matrix (index i, j, k → LPS mm), got shape {a.shape}")
    linear = a[:3, :3]
    norms = np.linalg.norm(linear, axis=0)
    if np.any(norms == 0):
        raise ValueError("affine: an index axis has zero length")
    if spacing is not None:
        given = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (3,))[::-1]
        if not np.allclose(given, norms, rtol=1e-9, atol=0):
            raise ValueError(
                f"spacing {tuple(given[::-1])} (z, y, x) disagrees with the affine's "
                f"{tuple(norms[::-1])}: give one of them"
            )
    direction = linear / norms
    return [float(v) for v in norms], [float(v) for v in a[:3, 3]], direction.T.tolist()


def from_numpy(
    array: Any,
    *,
    dst: str | os.PathLike[str],
    spacing: float | tuple[float, float, float] | None = None,
    affine: Any = None,
    modality: str = "",
    description: str = "",
    progress: Progress = False,
    codec: str = "fast",
) -> Volume:
    """Imports a numpy array into a new store at ``dst`` and opens it.

    ``array``: ``(z, y, x)``, or ``(t, z, y, x)`` for a 4-D store of ``t`` frames, of dtype
    uint8, int8, uint16, int16, uint32, int32, float32 or float64 (bool is stored as uint8).
    Geometry: ``spacing`` in mm ``(z, y, x)`` (or one number), or ``affine``, a 4×4 index
    ``(i, j, k, 1)`` → LPS mm matrix (:attr:`Volume.affine`'s convention; the spacing is its
    columns' lengths). Without either: 1 mm, origin 0, axis-aligned.

    Round trip: ``from_numpy(a, ...)[...]`` equals ``a`` exactly, values and dtype, and
    ``.affine`` equals ``affine``, for (u)int8 and (u)int16 arrays, and for the other types
    when every value is an integer and they span at most 65 536 values. Otherwise the values
    are scaled onto 16 bits; a ``UserWarning`` then names the worst-case error
    (:attr:`Volume.quantization_error`).
    """
    a = np.asarray(array)
    if a.dtype == np.bool_:
        a = a.astype(np.uint8)
    if a.ndim not in (3, 4):
        raise ValueError(f"from_numpy needs a 3-D (z, y, x) or 4-D (t, z, y, x) array, got {a.ndim}-D")
    if a.dtype.name not in _IMPORTABLE:
        raise ValueError(f"dtype {a.dtype} is not importable (use one of {', '.join(_IMPORTABLE)})")
    if a.size == 0:
        raise ValueError(f"an empty array {a.shape}")
    a = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("="))
    frames = a.shape[0] if a.ndim == 4 else 1
    z, y, x = a.shape[-3:]
    spacing_xyz, origin, direction = _geometry(spacing, affine)
    dst = os.fspath(dst)
    parent = os.path.dirname(os.path.abspath(dst))
    os.makedirs(parent, exist_ok=True)
    callback, close = _progress_callback(progress, "importing")
    raw = tempfile.NamedTemporaryFile(prefix=".strata-from-numpy-", suffix=".raw", dir=parent, delete=False)
    try:
        with raw:
            a.tofile(raw)
        _strata.import_raw(
            raw.name,
            dst,
            [x, y, z],
            frames,
            a.dtype.name,
            sys.byteorder == "little",
            spacing_xyz,
            origin,
            direction,
            1.0,
            0.0,
            modality,
            description,
            callback,
            1024,
            codec,
        )
    finally:
        close()
        try:
            os.unlink(raw.name)
        except FileNotFoundError:
            pass
    vol = open(dst)
    if vol.quantization_error > 0:
        warnings.warn(
            f"{dst}: the array's values were scaled onto 16 bits; worst-case error "
            f"{vol.quantization_error:g}",
            UserWarning,
            stacklevel=2,
        )
    return vol


def export_omezarr(volume: Volume | str | os.PathLike[str], dest: str | os.PathLike[str]) -> dict[str, int]:
    """Exports a volume as OME-Zarr 0.5 (Zarr v3, sharded), as ``strata export`` does: every
    level an array of the multiscale, the Strata geometry under the group's ``strata``
    attribute, identifiers (description, input paths) left out. ``volume`` is a
    :class:`Volume` or anything :func:`strata.open` opens; ``dest`` a folder (created; a
    previous Strata export there is replaced) or ``s3://BUCKET/PREFIX``. zarr-python, napari
    and ``strata.open`` read the result; Ctrl-C cancels.

    Returns the export's figures: ``levels``, ``shards_written``, ``shards_skipped`` (fill
    only), ``shard_bytes``, ``metadata_bytes``. Raises :class:`strata.StoreError` when the
    destination cannot be written.
    """
    vol = volume if isinstance(volume, Volume) else open(volume)
    try:
        levels, written, skipped, shard_bytes, metadata_bytes = _strata.export_omezarr(vol._native(), os.fspath(dest))
    finally:
        if vol is not volume:
            vol.close()
    return {
        "levels": levels,
        "shards_written": written,
        "shards_skipped": skipped,
        "shard_bytes": shard_bytes,
        "metadata_bytes": metadata_bytes,
    }
