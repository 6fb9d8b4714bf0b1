"""Reading stores: voxels, shape and affine against nibabel; regions; levels; frames."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

import strata
from conftest import SHARED_DATA, nib


def nibabel_zyx(img: "nib.Nifti1Image") -> np.ndarray:
    """nibabel's (x, y, z[, t]) voxels in strata's (z, y, x) / (t, z, y, x) order."""
    data = np.asanyarray(img.dataobj)
    return data.transpose(tuple(reversed(range(data.ndim))))


def test_voxels_shape_affine_against_nibabel(nifti_int16: pathlib.Path, store_int16: strata.Volume) -> None:
    img = nib.load(nifti_int16)
    vol = store_int16
    expected = nibabel_zyx(img)
    assert vol.shape == expected.shape == (38, 45, 70)
    assert vol.frames == 1
    assert vol.dtype == np.int16
    got = vol[...]
    assert got.dtype == np.int16
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(np.asarray(vol.level(0)), expected)
    np.testing.assert_allclose(vol.affine_ras, img.affine, rtol=0, atol=1e-9)
    np.testing.assert_allclose(vol.spacing, img.header.get_zooms()[::-1], rtol=1e-6)
    assert vol.value_mapping.slope == 1.0 and vol.value_mapping.intercept == -32768.0
    # The stored samples and the mapping give the same values.
    stored = vol.level(0, stored=True)[...]
    assert stored.dtype == np.uint16
    np.testing.assert_array_equal(vol.value_mapping.physical(stored), expected.astype(np.float64))


def test_level_objects_describe_themselves(store_int16: strata.Volume) -> None:
    vol = store_int16
    assert vol.levels == 3
    assert vol.level_shapes == [(38, 45, 70), (19, 23, 35), (10, 12, 18)]
    level = vol.level(1)
    assert level.shape == (19, 23, 35) and level.ndim == 3 and level.dtype == np.int16
    assert level.chunks == (19, 23, 32)
    assert vol.level(-1).level == 2
    assert level.nbytes == 19 * 23 * 35 * 2
    # Level voxel i is centred at level-0 index (i + 0.5)·2 − 0.5.
    np.testing.assert_allclose(level.affine @ [0, 0, 0, 1], vol.affine @ [0.5, 0.5, 0.5, 1])
    assert "Level 1" in repr(level) and "Volume" in repr(vol)


def test_level_1_is_the_rounded_mean_of_level_0(store_int16: strata.Volume) -> None:
    # Stored samples: level 1 voxel = mean of the 2×2×2 level-0 voxels (indices clamped),
    # rounded halves up: the octree's definition.
    s0 = store_int16.level(0, stored=True)[...].astype(np.int64)
    z, y, x = s0.shape
    padded = np.pad(s0, [(0, z % 2), (0, y % 2), (0, x % 2)], mode="edge")
    blocks = padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2, padded.shape[2] // 2, 2)
    expected = (blocks.sum(axis=(1, 3, 5)) + 4) // 8
    np.testing.assert_array_equal(store_int16.level(1, stored=True)[...], expected)


@pytest.mark.parametrize(
    "key",
    [
        np.s_[3:37, 10:44, 30:69],
        np.s_[31:33, 31:33, 31:65],
        np.s_[0:1, :, :],
        np.s_[5, :, 7],
        np.s_[-5:, -10:-2, -1],
        np.s_[::3, 1::5, 2:60:7],
        np.s_[..., 33],
        np.s_[12],
        np.s_[4:4, :, :],
        np.s_[20:10, :, :],
        np.s_[-38, -45, -70],
    ],
)
def test_a_region_equals_the_same_region_of_the_whole_level(store_int16: strata.Volume, key: object) -> None:
    level = store_int16.level(0)
    whole = np.asarray(level)
    got = level[key]
    np.testing.assert_array_equal(got, whole[key])
    assert got.dtype == whole.dtype


@pytest.mark.parametrize("k", [1, 2])
@pytest.mark.parametrize("key", [np.s_[2:9, 3:11, 5:18], np.s_[::2, -3:, 1], np.s_[..., 17:], np.s_[-1]])
def test_a_region_of_a_coarser_level(store_int16: strata.Volume, k: int, key: object) -> None:
    level = store_int16.level(k)
    np.testing.assert_array_equal(level[key], np.asarray(level)[key])


@pytest.mark.parametrize(
    "key, message",
    [
        (np.s_[38], "outside"),
        (np.s_[-39], "outside"),
        (np.s_[:, 45], "outside"),
        (np.s_[0:39], "outside"),
        (np.s_[:, :, -71:], "outside"),
        (np.s_[::-1], "step"),
        (np.s_[:, ::0], "step"),
        (np.s_[0, 0, 0, 0], "too many"),
        (np.s_[..., 0, ...], "ellipsis"),
        (np.s_[None], "newaxis"),
        (np.s_[1.5], "not an index"),
        (np.s_[[1, 2]], "not an index"),
    ],
)
def test_a_bad_slice_raises_index_error(store_int16: strata.Volume, key: object, message: str) -> None:
    with pytest.raises(IndexError, match=message):
        store_int16.level(0)[key]


def test_bad_level_or_frame_raises_index_error(store_int16: strata.Volume) -> None:
    with pytest.raises(IndexError, match="level 3 of a volume with 3 levels"):
        store_int16.level(3)
    with pytest.raises(IndexError, match="frame 1 of a volume with 1 frames"):
        store_int16.level(0, frame=1)


def test_scaled_float_nifti_reads_as_nibabel_get_fdata(tmp_path: pathlib.Path) -> None:
    rng = np.random.default_rng(3)
    data = rng.integers(0, 4000, size=(40, 33, 20), dtype=np.int16)
    img = nib.Nifti1Image(data, np.diag([0.5, 0.5, 2.0, 1.0]))
    img.header.set_slope_inter(0.25, -100.0)
    nib.save(img, tmp_path / "scaled.nii")
    img = nib.load(tmp_path / "scaled.nii")
    vol = strata.import_file(tmp_path / "scaled.nii", tmp_path / "scaled.strata", progress=False)
    assert vol.dtype == np.float64
    np.testing.assert_array_equal(vol[...], img.get_fdata().transpose(2, 1, 0))


def test_a_4d_store_reads_its_frames(tmp_path: pathlib.Path) -> None:
    rng = np.random.default_rng(11)
    data = rng.integers(0, 255, size=(36, 20, 9, 4), dtype=np.uint8)
    img = nib.Nifti1Image(data, np.diag([1.0, 1.2, 3.0, 1.0]))
    nib.save(img, tmp_path / "4d.nii.gz")
    vol = strata.import_file(tmp_path / "4d.nii.gz", tmp_path / "4d.strata", progress=False)
    assert vol.frames == 4 and vol.shape == (9, 20, 36)
    expected = nibabel_zyx(img)  # (t, z, y, x)
    level = vol.level(0)
    assert level.shape == (4, 9, 20, 36) and level.chunks == (1, 9, 20, 32)
    np.testing.assert_array_equal(level[...], expected)
    np.testing.assert_array_equal(level[1:4:2, 2:7, :, 30:], expected[1:4:2, 2:7, :, 30:])
    np.testing.assert_array_equal(level[-1, 3], expected[-1, 3])
    for t in range(4):
        np.testing.assert_array_equal(vol.level(0, frame=t)[...], expected[t])


def shared_niftis() -> list[pathlib.Path]:
    niivue = SHARED_DATA / "niivue"
    if not niivue.is_dir():
        return []
    return sorted(niivue.glob("*.nii.gz")) + sorted((niivue / "nifti_space").glob("*.nii.gz"))[:8]


@pytest.mark.parametrize("path", shared_niftis() or [None], ids=lambda p: p.name if p else "absent")
def test_shared_nifti_scans_against_nibabel(path: pathlib.Path | None, tmp_path: pathlib.Path) -> None:
    if path is None:
        reason = f"{SHARED_DATA.resolve()} is absent (a fresh clone has no ../shared): real-scan checks not run"
        print(f"SKIP: {reason}")
        pytest.skip(reason)
    img = nib.load(path)
    vol = strata.import_file(path, tmp_path / "scan.strata", progress=False)
    expected = img.get_fdata().transpose(tuple(reversed(range(len(img.shape)))))
    got = vol.level(0)[...].astype(np.float64)
    assert got.shape == expected.shape
    tolerance = vol.quantization_error * (1 + 1e-9) + 1e-9
    np.testing.assert_allclose(got, expected, rtol=0, atol=tolerance)
    np.testing.assert_allclose(vol.affine_ras, img.affine, rtol=0, atol=1e-4)
