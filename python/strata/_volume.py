"""Volumes and their levels: a store's metadata, and lazy numpy reads brick by brick."""

from __future__ import annotations

import json
import operator
import os
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from . import _strata

#: Voxels per brick core along each axis: the natural chunk of a level (reads of whole,
#: aligned 32³ blocks decode each brick once).
BRICK_CORE = 32

# The store header's names of the source sample types.
_SAMPLE_TYPES = {
    "U8": np.dtype(np.uint8),
    "I8": np.dtype(np.int8),
    "U16": np.dtype(np.uint16),
    "I16": np.dtype(np.int16),
    "U32": np.dtype(np.uint32),
    "I32": np.dtype(np.int32),
    "F32": np.dtype(np.float32),
    "F64": np.dtype(np.float64),
}


@dataclass(frozen=True)
class ValueMapping:
    """What a stored sample means: ``physical = slope * stored + intercept`` (in ``unit``).

    ``unit`` is ``"HU"`` for CT and empty when the scale is arbitrary (MR).
    """

    slope: float
    intercept: float
    unit: str

    def physical(self, stored: Any) -> Any:
        """The physical values of stored samples (a number or an array), as float64."""
        return np.asarray(stored, dtype=np.float64) * self.slope + self.intercept


@dataclass(frozen=True)
class WindowPreset:
    """A display window the source named (centre and width in physical units)."""

    name: str
    center: float
    width: float


def _physical_dtype(header: dict[str, Any], mapping: ValueMapping) -> np.dtype:
    """The dtype physical values are returned in (see :class:`Level`)."""
    source = _SAMPLE_TYPES.get(str(header.get("source_sample_type")), np.dtype(np.float64))
    if source.kind == "f":
        return source
    # Integers: the source's own type when the mapping is an integer shift and every stored
    # value maps into it (every import of an integer source without rescaling), else float64
    # (a rescaled source, as nibabel's get_fdata returns it).
    if mapping.slope == 1.0 and float(mapping.intercept).is_integer():
        top = 255 if header.get("stored") == "U8" else 65535
        lo, hi = mapping.intercept, top + mapping.intercept
        info = np.iinfo(source)
        if info.min <= lo and hi <= info.max:
            return source
        lo, hi = (mapping.physical(v) for v in header.get("stored_range", [0, top]))
        if info.min <= lo and hi <= info.max:
            return source
    return np.dtype(np.float64)


def _to_physical(stored: np.ndarray, mapping: ValueMapping, dtype: np.dtype, owned: bool = False) -> np.ndarray:
    """Stored u16 samples to physical values of ``dtype`` (exact for integer dtypes).

    ``owned``: ``stored`` views a buffer only this read holds, which the int16 mapping may then
    overwrite instead of allocating a second array (docs/bench-runs/python-read-2026-12-06.md:
    a fresh 256 MB array costs 0.2-0.5 s on a 2-core VM, more than its decode).
    """
    if dtype.kind in "iu":
        shift = int(mapping.intercept)
        if shift == 0:
            return stored.astype(dtype, copy=False)
        if dtype == np.int16 and shift == -32768:
            if owned and stored.flags.writeable:
                np.bitwise_xor(stored, np.uint16(0x8000), out=stored)
                return stored.view(np.int16)
            return (stored ^ np.uint16(0x8000)).view(np.int16)
        if dtype == np.int8 and shift == -128:
            return (stored.astype(np.uint8) ^ np.uint8(0x80)).view(np.int8)
        wide = stored.astype(np.int64)
        wide += shift
        return wide.astype(dtype)
    out = stored.astype(np.float64)
    if mapping.slope != 1.0:
        out *= mapping.slope
    if mapping.intercept != 0.0:
        out += mapping.intercept
    return out.astype(dtype, copy=False)


def _normalise_key(key: Any, shape: tuple[int, ...]) -> tuple[list[tuple[int, int, int]], list[bool]]:
    """Per axis ``(start, stop, step)`` with ``0 <= start <= stop <= n`` and ``step >= 1``,
    and whether the axis is dropped (an integer index).

    Raises IndexError for an index or slice bound outside the axis (numpy would clamp a slice;
    a volume read outside its extent is far more often a bug), a zero or negative step, too
    many indices, and anything but integers, slices and one Ellipsis.
    """
    ndim = len(shape)
    if not isinstance(key, tuple):
        key = (key,)
    if sum(k is Ellipsis for k in key) > 1:
        raise IndexError("an index can only have a single ellipsis ('...')")
    if any(k is Ellipsis for k in key):
        at = next(i for i, k in enumerate(key) if k is Ellipsis)
        fill = ndim - (len(key) - 1)
        if fill < 0:
            raise IndexError(f"too many indices: {len(key) - 1} for {ndim} dimensions")
        key = key[:at] + (slice(None),) * fill + key[at + 1 :]
    if len(key) > ndim:
        raise IndexError(f"too many indices: {len(key)} for {ndim} dimensions")
    key = key + (slice(None),) * (ndim - len(key))
    ranges: list[tuple[int, int, int]] = []
    dropped: list[bool] = []
    for axis, (k, n) in enumerate(zip(key, shape)):
        if isinstance(k, slice):
            step = 1 if k.step is None else operator.index(k.step)
            if step <= 0:
                raise IndexError(
                    f"axis {axis}: step {step}: only positive steps are supported "
                    "(read forwards, then reverse the numpy array)"
                )

            def bound(v: Any, default: int, what: str) -> int:
                if v is None:
                    return default
                v = operator.index(v)
                if v < -n or v > n:
                    raise IndexError(f"axis {axis}: slice {what} {v} is outside 0..{n}")
                return v + n if v < 0 else v

            start = bound(k.start, 0, "start")
            stop = max(start, bound(k.stop, n, "stop"))
            if step > 1 and stop > start:
                stop = start + (stop - start - 1) // step * step + 1
            ranges.append((start, stop, step))
            dropped.append(False)
        elif k is None or isinstance(k, (bool, np.bool_)):
            raise IndexError("only integers, slices and '...' index a level (no newaxis or booleans)")
        else:
            try:
                i = operator.index(k)
            except TypeError:
                raise IndexError(
                    f"axis {axis}: {type(k).__name__} is not an index: only integers, "
                    "slices and '...' index a level"
                ) from None
            if i < -n or i >= n:
                raise IndexError(f"axis {axis}: index {i} is outside 0..{n - 1}")
            i = i + n if i < 0 else i
            ranges.append((i, i + 1, 1))
            dropped.append(True)
    return ranges, dropped


class Level:
    """One resolution level of a volume: a lazy, read-only numpy-like array.

    Axes are numpy's order ``(z, y, x)`` — x (the store's index axis i) varies fastest — with
    a leading frame axis ``t`` when the volume is 4-D and no single frame was chosen. Indexing
    with integers, slices (steps ≥ 1, negative bounds counted from the end) and ``...`` reads
    just the bricks the region touches and returns a new numpy array.

    Values: physical values (``stored * slope + intercept``) in :attr:`dtype` — the source's
    own type for integer sources imported without rescaling (so a NIfTI ``int16`` reads back
    as ``int16``, exactly), the source's float type for float sources, else ``float64`` — or,
    for a level made with ``stored=True``, the stored samples themselves (``uint8``/``uint16``)
    with :attr:`Volume.value_mapping` to interpret them. Coarser levels hold 2×2×2 averages
    of the level below at cell centres (see :attr:`affine`).

    ``shape``, ``dtype``, ``ndim``, ``chunks`` and ``__array__`` make it acceptable to
    ``dask.array.from_array`` and napari; ``np.asarray(level)`` reads the whole level.
    """

    def __init__(self, volume: Volume, index: int, frame: int | None, stored: bool) -> None:
        self._volume = volume
        self._index = index
        self._frame = frame
        self._stored = stored
        x, y, z = volume._header["layout"]["level_dims"][index]
        spatial = (int(z), int(y), int(x))
        self._frames_axis = frame is None and volume.frames > 1
        self.shape: tuple[int, ...] = ((volume.frames,) if self._frames_axis else ()) + spatial
        """Voxels per axis: ``(z, y, x)``, or ``(t, z, y, x)`` for all frames of a 4-D volume."""
        self.dtype: np.dtype = volume.stored_dtype if stored else volume.dtype
        """The dtype reads return (see the class's description)."""

    @property
    def level(self) -> int:
        """This level's number (0 = full resolution)."""
        return self._index

    @property
    def ndim(self) -> int:
        """3, or 4 for all frames of a 4-D volume."""
        return len(self.shape)

    @property
    def size(self) -> int:
        """Number of voxels."""
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        """Bytes the whole level takes as a numpy array of :attr:`dtype`."""
        return self.size * self.dtype.itemsize

    @property
    def chunks(self) -> tuple[int, ...]:
        """The brick core (32) per spatial axis, capped by the level's size; 1 frame."""
        spatial = tuple(min(BRICK_CORE, n) for n in self.shape[-3:])
        return ((1,) if self._frames_axis else ()) + spatial

    @property
    def spacing(self) -> tuple[float, float, float]:
        """Voxel size in mm, ``(z, y, x)``: level 0's times 2**level."""
        s = 2.0**self._index
        return tuple(v * s for v in self._volume.spacing)  # type: ignore[return-value]

    @property
    def affine(self) -> np.ndarray:
        """4×4 index ``(i, j, k, 1)`` → LPS mm of this level's voxel centres (as
        :attr:`Volume.affine`; level voxel ``i`` is centred at level-0 index
        ``(i + 0.5)·2**level − 0.5``)."""
        s = 2.0**self._index
        scale = np.diag([s, s, s, 1.0])
        scale[:3, 3] = 0.5 * s - 0.5
        return self._volume.affine @ scale

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        kind = "stored" if self._stored else "physical"
        return (
            f"<strata.Level {self._index} of {self._volume.location}: shape {self.shape}, "
            f"{self.dtype} ({kind})>"
        )

    def __getitem__(self, key: Any) -> np.ndarray:
        ranges, dropped = _normalise_key(key, self.shape)
        spatial = ranges[-3:]
        if self._frames_axis:
            t0, t1, tstep = ranges[0]
            frames = list(range(t0, t1, tstep))
        else:
            frames = [self._frame or 0]
        blocks = [self._read(f, spatial) for f in frames]
        if self._frames_axis:
            shape = (len(frames),) + tuple(b - a for a, b, _ in spatial)
            out = np.stack(blocks) if blocks else np.empty(shape, np.uint16)
        else:
            out = blocks[0]
        steps = tuple(slice(None, None, s) for _, _, s in ranges[-3:])
        out = out[((slice(None),) if self._frames_axis else ()) + steps]
        if any(dropped):
            out = out[tuple(0 if d else slice(None) for d in dropped)]
        if not self._stored:
            out = _to_physical(out, self._volume.value_mapping, self.dtype, owned=True)
        elif self.dtype != out.dtype:
            out = out.astype(self.dtype)
        return np.ascontiguousarray(out)

    def _read(self, frame: int, spatial: list[tuple[int, int, int]]) -> np.ndarray:
        (z0, z1, _), (y0, y1, _), (x0, x1, _) = spatial
        buf = self._volume._native().read_region(self._index, frame, [x0, y0, z0], [x1, y1, z1])
        return np.frombuffer(buf, dtype=np.uint16).reshape(z1 - z0, y1 - y0, x1 - x0)

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> np.ndarray:
        out = self[...]
        return out if dtype is None else out.astype(dtype, copy=False)

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(self.shape[0]):
            yield self[i]


class Volume:
    """An open Strata volume: its geometry, value mapping and levels.

    Open one with :func:`strata.open`: a store folder, a store ``strata serve`` serves (a URL),
    or an OME-Zarr read in place; each reads alike. Axis conventions: shapes, spacings and chunks are in
    numpy's order ``(z, y, x)``; the affines map an index ``(i, j, k, 1)`` = ``(x, y, z, 1)``
    to patient LPS millimetres (the convention of DICOM, ITK and nibabel's ``affine`` — nibabel's
    is RAS: ``diag(-1, -1, 1, 1) @ vol.affine``). ``vol[...]`` reads level 0 as
    ``vol.level(0)[...]`` does. A volume is a context manager; :meth:`close` releases the store.
    """

    def __init__(self, native: Any) -> None:
        self._handle = native
        self._header: dict[str, Any] = json.loads(native.header_json())
        h = self._header
        vm = h["value_mapping"]
        self.value_mapping = ValueMapping(float(vm["slope"]), float(vm["intercept"]), str(vm.get("unit", "")))
        """physical = slope · stored + intercept, and its unit."""
        self.dtype: np.dtype = _physical_dtype(h, self.value_mapping)
        """The dtype of physical reads (see :class:`Level`)."""
        self.stored_dtype: np.dtype = np.dtype(np.uint8 if h["stored"] == "U8" else np.uint16)
        """The dtype of the stored samples (``level(k, stored=True)``)."""

    def _native(self) -> Any:
        return self._handle

    @property
    def path(self) -> os.PathLike[str] | None:
        """The store's (or OME-Zarr's) folder; ``None`` for a URL."""
        return self._handle.path

    @property
    def location(self) -> str:
        """The path or URL the volume was opened from (never with its token)."""
        return self._handle.location

    @property
    def url(self) -> str | None:
        """The URL of a served store or a remote OME-Zarr; ``None`` for a folder."""
        return None if self._handle.path is not None else self._handle.location

    @property
    def kind(self) -> str:
        """``"store"`` (a folder ``strata import`` wrote), ``"served"`` (a URL ``strata serve``
        serves) or ``"ome-zarr"`` (read in place)."""
        return self._handle.kind

    @property
    def notes(self) -> list[str]:
        """What was assumed to read the volume: a foreign OME-Zarr's orientation, levels or
        value mapping (empty for Strata's own stores and exports)."""
        return list(self._handle.notes())

    @property
    def header(self) -> dict[str, Any]:
        """The store's whole header (a copy), as the Rust library writes it."""
        return json.loads(json.dumps(self._header))

    @property
    def shape(self) -> tuple[int, int, int]:
        """Level 0's voxels, ``(z, y, x)`` (frames not included: see :attr:`frames`)."""
        x, y, z = self._header["geometry"]["dims"]
        return (int(z), int(y), int(x))

    @property
    def level_shapes(self) -> list[tuple[int, int, int]]:
        """Every level's voxels, ``(z, y, x)``, level 0 first."""
        return [(int(z), int(y), int(x)) for x, y, z in self._header["layout"]["level_dims"]]

    @property
    def levels(self) -> int:
        """Number of levels (level 0 is full resolution; the last fits one brick)."""
        return len(self._header["layout"]["level_dims"])

    @property
    def frames(self) -> int:
        """Volumes in the store (time points of a 4-D source); 1 otherwise. A served 4-D
        store reads as its first frame (``strata serve`` serves that one)."""
        return int(self._handle.frame_count())

    @property
    def spacing(self) -> tuple[float, float, float]:
        """Voxel size in mm, ``(z, y, x)``."""
        sx, sy, sz = self._header["geometry"]["spacing_mm"]
        return (float(sz), float(sy), float(sx))

    @property
    def origin(self) -> tuple[float, float, float]:
        """LPS position (mm) of the centre of voxel (0, 0, 0)."""
        return tuple(float(v) for v in self._header["geometry"]["origin_lps_mm"])  # type: ignore[return-value]

    @property
    def direction(self) -> np.ndarray:
        """3×3: column ``a`` is the unit LPS direction of index axis ``a`` (i, j, k)."""
        return np.array(self._header["geometry"]["direction"], dtype=np.float64).T

    @property
    def affine(self) -> np.ndarray:
        """4×4 float64: index ``(i, j, k, 1)`` (i = x, the fastest axis) → LPS mm."""
        a = np.eye(4)
        a[:3, :3] = self.direction * np.array(self._header["geometry"]["spacing_mm"], dtype=np.float64)
        a[:3, 3] = self.origin
        return a

    @property
    def affine_ras(self) -> np.ndarray:
        """:attr:`affine` in RAS (nibabel's and NIfTI's convention)."""
        return np.diag([-1.0, -1.0, 1.0, 1.0]) @ self.affine

    @property
    def description(self) -> str:
        """The source's description, with the import's notes."""
        return str(self._header.get("description", ""))

    @property
    def modality(self) -> str:
        """``"CT"``, ``"MR"``, … or empty."""
        return str(self._header.get("modality", ""))

    @property
    def windows(self) -> list[WindowPreset]:
        """The display windows the source named."""
        return [WindowPreset(str(w["name"]), float(w["center"]), float(w["width"])) for w in self._header.get("windows", [])]

    @property
    def quantization_error(self) -> float:
        """Worst-case physical error of the import's quantisation (0.0: exact)."""
        return float(self._header.get("quantization_error", 0.0))

    @property
    def stored_range(self) -> tuple[int, int]:
        """Lowest and highest stored sample at level 0."""
        lo, hi = self._header["stored_range"]
        return (int(lo), int(hi))

    def level(self, k: int = 0, *, frame: int | None = None, stored: bool = False) -> Level:
        """Level ``k`` (0 = full resolution; negative counts from the coarsest) as a lazy
        array. ``frame`` picks one volume of a 4-D store (else a 4-D store's level has a
        leading frame axis); ``stored=True`` reads stored samples instead of physical values.
        """
        n = self.levels
        k = operator.index(k)
        if not -n <= k < n:
            raise IndexError(f"level {k} of a volume with {n} levels")
        if frame is not None:
            frame = operator.index(frame)
            if not -self.frames <= frame < self.frames:
                raise IndexError(f"frame {frame} of a volume with {self.frames} frames")
            frame %= self.frames
        return Level(self, k % n, frame, stored)

    def __getitem__(self, key: Any) -> np.ndarray:
        return self.level(0)[key]

    def close(self) -> None:
        """Releases the store (other handles of this process to it stay open)."""
        self._handle.close()

    def __enter__(self) -> Volume:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        frames = f", {self.frames} frames" if self.frames > 1 else ""
        return (
            f"<strata.Volume {self.location}: {self.shape} (z, y, x){frames}, {self.dtype}, "
            f"spacing {self.spacing} mm, {self.levels} levels>"
        )


def open(  # noqa: A001 - the package's verb
    path_or_url: str | os.PathLike[str], token: str | None = None, *, timeout_s: float = 20.0
) -> Volume:
    """Opens a volume: a Strata store (a folder ``strata import`` wrote), a store served by
    ``strata serve`` (``http(s)://HOST:PORT/v1/stores/NAME``, with the server's ``token`` when
    it needs one), or an OME-Zarr read in place (a ``.zarr`` folder or URL, ``s3://…``; Strata's
    exports exactly, foreign pyramids as :attr:`Volume.notes` say).

    The token is sent as ``Authorization: Bearer …``, as ``strata serve`` expects, and appears
    in no ``repr``, message or log. ``STRATA_TLS_CA`` names a PEM certificate to trust besides
    the system's for https, as for the ``strata`` commands. ``timeout_s`` bounds how long
    opening or reading a URL keeps retrying a server that does not answer.

    Raises :class:`strata.StoreNotFoundError` when there is no store there (or the server has
    no store of that name), :class:`strata.DamagedStoreError` for a damaged or unfinished one,
    :class:`strata.StoreInUseError` when another process holds it,
    :class:`strata.TokenError` when the server requires a token or refuses the one given,
    :class:`strata.RemoteError` when a server cannot be reached (after ``timeout_s``) or
    refuses otherwise, :class:`strata.StoreError` for any other reason, and ``ValueError`` for
    a token with a folder; the message is the library's and names the volume. Opening the same
    store folder twice in one process shares it.
    """
    location = os.fspath(path_or_url)
    if not isinstance(location, str):
        location = os.fsdecode(location)
    return Volume(_strata.open_store(location, token, float(timeout_s)))
