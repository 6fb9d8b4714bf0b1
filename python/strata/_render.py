"""strata.render: one headless frame of a volume, the frame `strata render` draws."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from . import _strata

if TYPE_CHECKING:
    from ._volume import Volume

_log = logging.getLogger("strata")


def _size(size: int | Sequence[int] | str) -> tuple[int, int]:
    """``512``, ``(width, height)`` or ``"512x384"`` as (width, height)."""
    if isinstance(size, str):
        w, sep, h = size.lower().partition("x")
        if not sep:
            raise ValueError(f"size={size!r}: expected WIDTHxHEIGHT such as '512x512'")
        try:
            return int(w), int(h)
        except ValueError:
            raise ValueError(f"size={size!r}: expected WIDTHxHEIGHT such as '512x512'") from None
    if isinstance(size, (int, np.integer)):
        return int(size), int(size)
    parts = tuple(size)
    if len(parts) != 2 or not all(isinstance(p, (int, np.integer)) for p in parts):
        raise ValueError(f"size={size!r}: expected an int or (width, height)")
    return int(parts[0]), int(parts[1])


def render(
    volume: Volume,
    *,
    azimuth: float = 0.0,
    elevation: float = 0.0,
    size: int | Sequence[int] | str = 512,
    mode: str = "dvr",
    tf: str | None = None,
    shading: bool = False,
    shadows: str = "off",
    zoom: float = 1.0,
    step: float = 0.5,
    level: int = 0,
    up_front: bool = False,
    max_frames: int = 400,
    quality: float = 1.0,
    reference: bool = False,
    iso: float = 300.0,
    orthographic: bool = False,
    jitter: bool = True,
    smooth: bool = True,
    exact_trilinear: bool = False,
    oracle_epsilon: float = 0.001,
    traversal: str | None = None,
    gpu_mib: int | None = None,
    light_dir: Sequence[float] | None = None,
    shadow_step: float = 1.0,
    light_cache_res: float = 2.0,
    occlusion: float | None = None,
    scattering: float | None = None,
    scattering_blend: float = 0.5,
    progressive: int | None = None,
) -> np.ndarray:
    """One frame of ``volume`` as a ``(height, width, 4)`` uint8 RGBA array (premultiplied
    alpha, rows top to bottom): the frame ``strata render`` draws with the same options, from
    the same code (its PNG is this image's RGB over black).

    Each option is the command line's flag of the same name (``up_front`` is ``--up-front``,
    ``jitter=False`` is ``--no-jitter``, ``smooth=False`` is ``--no-smooth``), with its default:

    - ``azimuth``, ``elevation``: the orbit angles in degrees (0, 0 looks from anterior);
      ``zoom``; ``orthographic``.
    - ``size``: ``512``, ``(width, height)`` or ``"WIDTHxHEIGHT"``, each 1..8192.
    - ``mode``: ``"dvr"``, ``"mip"``, ``"iso"`` (at ``iso``, physical units), ``"adaptive"``
      or ``"adaptive-mip"``; ``tf``: a preset (ct-bone, ct-soft-tissue, ct-lung, ct-vessels,
      mr-default) or a JSON file, by default by modality.
    - Streaming (the default) until converged or ``max_frames``, refining to ``quality``; or
      the fixed cut of ``level`` with ``up_front=True`` (and always for ``reference``,
      adaptive modes and ``progressive``).
    - ``reference=True``: the f64 CPU reference instead of the GPU.
    - Lighting: ``shading``, ``shadows`` (``"off"``, ``"exact"``, ``"cache"``), ``light_dir``
      (x, y, z, camera-relative), ``shadow_step``, ``light_cache_res``, ``occlusion`` (mm),
      ``scattering`` (g) and ``scattering_blend``; ``progressive``: the mean of N frames.
    - ``step`` (finest voxels), ``traversal`` (``"flat"``, ``"octree"``), ``gpu_mib``,
      ``exact_trilinear``, ``oracle_epsilon``.

    The GIL is released while it renders. Raises ``ValueError`` for an option out of range or
    options that do not combine (the message names the command line's flag), and
    :class:`RenderError` when no usable GPU adapter exists (the message says what to install)
    or the GPU fails; a store that cannot be read raises its :class:`StoreError`.
    """
    width, height = _size(size)
    for name, value, lo, hi in (
        ("level", level, 0, 255),
        ("max_frames", max_frames, 1, 2**32),
        ("progressive", progressive, 1, 2**32 - 1),
        ("gpu_mib", gpu_mib, 1, 2**44),
    ):
        if value is not None and not lo <= int(value) <= hi:
            raise ValueError(f"{name}={value}: expected {lo}..={hi}")
    out = _strata.render(
        volume._native(),
        width=width,
        height=height,
        azimuth=float(azimuth),
        elevation=float(elevation),
        zoom=float(zoom),
        mode=str(mode),
        tf=None if tf is None else str(tf),
        step=float(step),
        level=int(level),
        up_front=bool(up_front),
        max_frames=int(max_frames),
        quality=float(quality),
        reference=bool(reference),
        shading=bool(shading),
        iso=float(iso),
        orthographic=bool(orthographic),
        jitter=bool(jitter),
        smooth=bool(smooth),
        exact_trilinear=bool(exact_trilinear),
        oracle_epsilon=float(oracle_epsilon),
        traversal=traversal,
        gpu_mib=gpu_mib,
        shadows=str(shadows),
        light_dir=None if light_dir is None else [float(c) for c in light_dir],
        shadow_step=float(shadow_step),
        light_cache_res=float(light_cache_res),
        occlusion=None if occlusion is None else float(occlusion),
        scattering=None if scattering is None else float(scattering),
        scattering_blend=float(scattering_blend),
        progressive=progressive,
    )
    w, h, rgba, notes = out
    for note in notes:
        _log.debug("strata.render: %s", note)
    return np.frombuffer(rgba, dtype=np.uint8).reshape(h, w, 4)
