"""napari's reader for Strata volumes (npe2; the manifest is ``napari.yaml`` beside this file).

``get_reader(path)`` accepts a store folder (``strata import``), a URL ``strata serve`` serves,
or an OME-Zarr Strata exported (its group carries the ``strata`` attribute); anything else is
left to other readers. The layer is a multiscale image built from the volume's lazy levels
(:class:`strata.Level`: numpy slicing, brick by brick), so napari reads only what it shows,
whatever the volume's size. Nothing here imports napari.

Geometry: napari's world axes are the volume's ``(z, y, x)`` in patient LPS millimetres:
``scale`` is the voxel spacing, ``translate`` the centre of voxel (0, 0, 0), and ``rotate`` the
direction cosines when the volume is oblique (a proper rotation; a mirrored grid keeps its
axis-aligned scale and says so in ``metadata["notes"]``). ``contrast_limits`` span the stored
value range in physical units.
"""

from __future__ import annotations

import builtins
import json
import os
from typing import Any, Callable

import numpy as np

from ._volume import Volume, open

#: A layer as napari's readers return it: (data, metadata, layer type).
LayerData = tuple[Any, dict[str, Any], str]


def _is_strata_store(path: str) -> bool:
    return os.path.isfile(os.path.join(path, "STRATA-STORE"))


def _is_strata_omezarr(path: str) -> bool:
    """A local OME-Zarr whose group carries Strata's geometry (a ``strata export``)."""
    try:
        with builtins.open(os.path.join(path, "zarr.json"), encoding="utf-8") as f:
            group = json.load(f)
    except (OSError, ValueError):
        return False
    attributes = group.get("attributes", {}) if isinstance(group, dict) else {}
    return isinstance(attributes, dict) and "strata" in attributes and "ome" in attributes


def _accepts(path: str) -> bool:
    if path.startswith(("http://", "https://")):
        return "/v1/stores/" in path and "/zarr" not in path
    path = path.rstrip("/")
    return os.path.isdir(path) and (_is_strata_store(path) or _is_strata_omezarr(path))


def get_reader(path: str | list[str]) -> Callable[[str | list[str]], list[LayerData]] | None:
    """npe2's reader contract: the function that reads ``path``, or ``None`` when it is not a
    Strata volume (a store folder, a served store's URL, or a Strata OME-Zarr export)."""
    if isinstance(path, (list, tuple)):
        if not path or not all(isinstance(p, (str, os.PathLike)) and _accepts(os.fspath(p)) for p in path):
            return None
        return read_layers
    if not isinstance(path, (str, os.PathLike)) or not _accepts(os.fspath(path)):
        return None
    return read_layers


def read_layers(path: str | list[str]) -> list[LayerData]:
    """Every path as one multiscale image layer (see the module's description). A served store
    that needs a token reads it from ``STRATA_TOKEN``."""
    paths = path if isinstance(path, (list, tuple)) else [path]
    return [layer_data(open(os.fspath(p), token=_token_for(os.fspath(p)))) for p in paths]


def _token_for(location: str) -> str | None:
    if location.startswith(("http://", "https://")):
        return os.environ.get("STRATA_TOKEN") or None
    return None


def _name(vol: Volume) -> str:
    tail = vol.location.rstrip("/").rsplit("/", 1)[-1]
    for suffix in (".strata", ".ome.zarr", ".zarr"):
        if tail.endswith(suffix):
            return tail[: -len(suffix)]
    return tail


def layer_data(vol: Volume) -> LayerData:
    """``vol`` as napari's layer data: ``([level 0, level 1, …], metadata, "image")``."""
    levels = [vol.level(k) for k in range(vol.levels)]
    # napari's (z, y, x) world from the index (i, j, k) = (x, y, z) affine: reverse both.
    direction_zyx = vol.direction[::-1, ::-1]
    translate = tuple(float(v) for v in vol.origin[::-1])
    scale = tuple(float(v) for v in vol.spacing)
    # A 4-D volume's levels lead with the frame axis: one step per frame, no offset.
    time = vol.frames > 1
    meta: dict[str, Any] = {
        "name": _name(vol),
        "scale": ((1.0,) if time else ()) + scale,
        "translate": ((0.0,) if time else ()) + translate,
        "multiscale": True,
        "metadata": {
            "strata_location": vol.location,
            "strata_affine_lps": vol.affine,
            "notes": list(vol.notes),
        },
    }
    if not np.allclose(direction_zyx, np.eye(3), atol=1e-9):
        if np.linalg.det(direction_zyx) > 0:
            rotate = np.eye(4) if time else direction_zyx
            if time:
                rotate[1:, 1:] = direction_zyx
            meta["rotate"] = rotate
        else:
            meta["metadata"]["notes"].append(
                "the grid is mirrored (its direction cosines are no rotation): shown axis-aligned"
            )
    lo, hi = (float(v) for v in vol.value_mapping.physical(np.array(vol.stored_range)))
    meta["contrast_limits"] = (min(lo, hi), max(lo, hi) if hi != lo else lo + 1.0)
    if time:
        meta["metadata"]["notes"].append(f"{vol.frames} frames: the first axis is time")
    return (levels, meta, "image")
