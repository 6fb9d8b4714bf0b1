"""Region reads from Python: strata's lazy level against nibabel and zarr-python, same data.

A synthetic int16 volume (a smooth phantom: nested ellipsoids in HU-like values, plus noise)
is written three ways, then read back, each timing the median of ``--repeats`` runs (all
files in the page cache: what is compared is decoding and copying, not the disk):

- a Strata store made by ``strata.from_numpy`` (codec "fast"), read with ``vol.level(0)[...]``;
- the same array as NIfTI written by nibabel, uncompressed (``.nii``) and gzipped
  (``.nii.gz``), loaded without a memory map (``mmap=False``: a memory map's pages would be
  read only when touched, after the clock stopped) and read with ``img.dataobj[...]`` (a
  sub-region) and ``np.asarray(img.dataobj)`` / ``img.get_fdata()`` (the whole volume);
- the store's OME-Zarr export (``strata.export_omezarr``, what ``strata export`` writes:
  zstd in 32³ inner chunks, shards of up to 256³) read with zarr-python 3 ``group["0"][...]``,
  its stored uint16 samples mapped to int16 as the ``strata`` attribute's value mapping says
  (intercept −32768: the sign bit flipped, as strata's own reader does).

Every read's voxels are checked equal to the array's before timing counts.

    python python/bench/read_bench.py --size 512 --region 64 --repeats 3 --workdir /tmp/strata-bench
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import statistics
import time
from typing import Callable

import numpy as np


def phantom(n: int, seed: int = 5) -> np.ndarray:
    """n³ int16, (z, y, x): air, a body ellipsoid, organs, bone, noise (σ 20)."""
    rng = np.random.default_rng(seed)
    c = (np.arange(n, dtype=np.float32) - n / 2) / (n / 2)
    z, y, x = c[:, None, None], c[None, :, None], c[None, None, :]
    out = np.full((n, n, n), -1000, dtype=np.int16)
    body = (x / 0.85) ** 2 + (y / 0.7) ** 2 + (z / 0.95) ** 2 < 1
    out[body] = 40
    organ = ((x - 0.25) / 0.3) ** 2 + (y / 0.25) ** 2 + ((z - 0.1) / 0.4) ** 2 < 1
    out[organ] = 80
    bone = np.abs(((x + 0.3) / 0.12) ** 2 + (y / 0.12) ** 2 - 1) < 0.35
    out[bone & body] = 900
    del body, organ, bone
    noise = rng.normal(0, 20, size=out.shape).astype(np.int16)
    out[out > -1000] += noise[out > -1000]
    return out


def median_s(read: Callable[[], np.ndarray], expected: np.ndarray, repeats: int) -> float:
    got = read()
    assert got.shape == expected.shape and np.array_equal(got, expected), "a reader returned other voxels"
    del got
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        got = read()
        times.append(time.perf_counter() - t0)
        del got
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--region", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=pathlib.Path, default=pathlib.Path("/tmp/strata-read-bench"))
    args = parser.parse_args()

    import nibabel as nib
    import zarr

    import strata

    n, r = args.size, args.region
    args.workdir.mkdir(parents=True, exist_ok=True)
    a = phantom(n)
    spacing = (0.6, 0.5, 0.5)
    affine_ras = np.diag([-spacing[2], -spacing[1], spacing[0], 1.0])
    store = args.workdir / "phantom.strata"
    nii = args.workdir / "phantom.nii"
    niigz = args.workdir / "phantom.nii.gz"
    ome = args.workdir / "phantom.ome.zarr"
    t0 = time.perf_counter()
    if not store.exists():
        strata.from_numpy(a, spacing=spacing, dst=store, progress=False).close()
    t_store = time.perf_counter() - t0
    for path in (nii, niigz):
        if not path.exists():
            nib.save(nib.Nifti1Image(np.ascontiguousarray(a.transpose(2, 1, 0)), affine_ras), path)
    t0 = time.perf_counter()
    if not ome.exists():
        strata.export_omezarr(store, ome)
    t_export = time.perf_counter() - t0

    vol = strata.open(store)
    level0 = vol.level(0)
    group = zarr.open_group(str(ome), mode="r")
    array0 = group["0"]
    mapping = group.attrs["strata"]["header"]["value_mapping"]
    assert mapping["slope"] == 1.0 and mapping["intercept"] == -32768.0, mapping

    def zarr_read(key: tuple[slice, ...]) -> np.ndarray:
        return (array0[key] ^ np.uint16(0x8000)).view(np.int16)
    # A region off the brick grid (starts at 100, not a multiple of 32) inside the body.
    o = min(100, n - r - 7)
    sub = (slice(o, o + r), slice(o, o + r), slice(o + 7, o + 7 + r))
    sub_xyz = sub[::-1]
    rows = []

    def add(what: str, reader: str, read: Callable[[], np.ndarray], expected: np.ndarray) -> None:
        s = median_s(read, expected, args.repeats)
        rows.append((what, reader, s))
        print(f"{what:<14} {reader:<46} {s * 1000:10.1f} ms", flush=True)

    expected_sub = a[sub]
    add(f"{r}³ region", "strata vol.level(0)[...]", lambda: level0[sub], expected_sub)
    add(f"{r}³ region", "nibabel .nii dataobj[...] (region read)", lambda: nib.load(nii, mmap=False).dataobj[sub_xyz].T, expected_sub)
    add(f"{r}³ region", "nibabel .nii.gz dataobj[...]", lambda: nib.load(niigz).dataobj[sub_xyz].T, expected_sub)
    add(f"{r}³ region", "zarr-python 3 group['0'][...]", lambda: zarr_read(sub), expected_sub)
    add(f"{n}³ whole", "strata vol.level(0)[...]", lambda: level0[...], a)
    add(f"{n}³ whole", "nibabel .nii np.asarray(dataobj)", lambda: np.asarray(nib.load(nii, mmap=False).dataobj).T, a)
    add(f"{n}³ whole", "nibabel .nii get_fdata() (float64)", lambda: nib.load(nii, mmap=False).get_fdata().T, a)
    add(f"{n}³ whole", "nibabel .nii.gz np.asarray(dataobj)", lambda: np.asarray(nib.load(niigz).dataobj).T, a)
    add(f"{n}³ whole", "nibabel .nii.gz get_fdata() (float64)", lambda: nib.load(niigz).get_fdata().T, a)
    add(f"{n}³ whole", "zarr-python 3 group['0'][...]", lambda: zarr_read((slice(None),) * 3), a)
    # Where strata's time goes: the native read alone (bricks decoded and copied into a
    # bytearray of stored uint16), then the stored level (plus numpy's view), then physical.
    native = vol._native()
    stored = vol.level(0, stored=True)
    stored_a = (a.view(np.uint16) ^ np.uint16(0x8000))
    add(f"{n}³ whole", "strata native read_region (bytes)", lambda: np.frombuffer(native.read_region(0, 0, [0, 0, 0], [n, n, n]), np.uint16).reshape(n, n, n), stored_a)
    add(f"{n}³ whole", "strata level(0, stored=True)[...]", lambda: stored[...], stored_a)

    sizes = {p.name: sum(f.stat().st_size for f in (p.rglob("*") if p.is_dir() else [p]) if f.is_file()) for p in (store, nii, niigz, ome)}
    print()
    print(f"conditions: {platform.machine()}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}, "
          f"python {platform.python_version()}, numpy {np.__version__}, nibabel {nib.__version__}, "
          f"zarr {zarr.__version__}, strata {strata.__version__}; median of {args.repeats} after one checked read")
    print(f"made: store {t_store:.1f} s, OME-Zarr export {t_export:.1f} s; sizes (MB): "
          + ", ".join(f"{k} {v / 1e6:.0f}" for k, v in sizes.items()))
    vol.close()


if __name__ == "__main__":
    main()
