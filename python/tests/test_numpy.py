"""from_numpy → open round trips, and import_file's progress."""

from __future__ import annotations

import pathlib
import warnings

import numpy as np
import pytest

import strata
from conftest import oblique_affine


@pytest.mark.parametrize("dtype", ["uint8", "int8", "uint16", "int16"])
def test_from_numpy_round_trips_exactly(tmp_path: pathlib.Path, dtype: str) -> None:
    info = np.iinfo(dtype)
    rng = np.random.default_rng(5)
    a = rng.integers(info.min, info.max, size=(33, 40, 65), endpoint=True, dtype=dtype)
    a[0, 0, 0], a[-1, -1, -1] = info.min, info.max
    lps = np.diag([-1.0, -1.0, 1.0, 1.0]) @ oblique_affine()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        vol = strata.from_numpy(a, affine=lps, dst=tmp_path / "a.strata")
    got = vol[...]
    assert got.dtype == a.dtype
    np.testing.assert_array_equal(got, a)
    np.testing.assert_allclose(vol.affine, lps, rtol=0, atol=1e-12)
    assert vol.quantization_error == 0.0


def test_from_numpy_spacing_and_integer_valued_floats(tmp_path: pathlib.Path) -> None:
    a = (np.arange(20 * 30 * 40, dtype=np.float32) % 5000 - 1000).reshape(20, 30, 40)
    vol = strata.from_numpy(a, spacing=(2.0, 0.5, 0.25), dst=tmp_path / "f.strata")
    assert vol.dtype == np.float32 and vol.quantization_error == 0.0
    np.testing.assert_array_equal(vol[...], a)
    assert vol.spacing == (2.0, 0.5, 0.25)
    np.testing.assert_array_equal(vol.affine, np.diag([0.25, 0.5, 2.0, 1.0]))


def test_from_numpy_4d_round_trips(tmp_path: pathlib.Path) -> None:
    a = np.random.default_rng(2).integers(-500, 500, size=(3, 10, 34, 12), dtype=np.int16)
    vol = strata.from_numpy(a, dst=tmp_path / "t.strata")
    assert vol.frames == 3
    np.testing.assert_array_equal(vol.level(0)[...], a)


def test_from_numpy_warns_when_it_must_quantise(tmp_path: pathlib.Path) -> None:
    a = np.random.default_rng(9).normal(size=(8, 9, 10))
    with pytest.warns(UserWarning, match="scaled onto 16 bits"):
        vol = strata.from_numpy(a, dst=tmp_path / "q.strata")
    assert vol.dtype == np.float64
    assert 0 < vol.quantization_error < 1e-3
    assert np.max(np.abs(vol[...] - a)) <= vol.quantization_error * (1 + 1e-9)


def test_from_numpy_refuses_bad_arguments(tmp_path: pathlib.Path) -> None:
    with pytest.raises(ValueError, match="3-D"):
        strata.from_numpy(np.zeros((4, 4)), dst=tmp_path / "x.strata")
    with pytest.raises(ValueError, match="not importable"):
        strata.from_numpy(np.zeros((4, 4, 4), dtype=np.complex64), dst=tmp_path / "x.strata")
    with pytest.raises(ValueError, match="disagrees"):
        strata.from_numpy(np.zeros((4, 4, 4)), spacing=2.0, affine=np.eye(4), dst=tmp_path / "x.strata")
    with pytest.raises(ValueError, match="spacing"):
        strata.from_numpy(np.zeros((4, 4, 4)), spacing=0.0, dst=tmp_path / "x.strata")


def test_import_file_reports_progress(nifti_int16: pathlib.Path, tmp_path: pathlib.Path) -> None:
    calls: list[tuple[int, int]] = []
    vol = strata.import_file(nifti_int16, tmp_path / "p.strata", progress=lambda d, t: calls.append((d, t)))
    assert calls and calls[-1][0] == calls[-1][1] > 0
    assert vol.shape == (38, 45, 70)
