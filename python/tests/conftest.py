"""Shared fixtures: NIfTI files written by nibabel, imported into stores once per session."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

import strata

nib = pytest.importorskip("nibabel")

#: The repository's shared test scans (absent in a fresh clone: those tests skip, saying so).
SHARED_DATA = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "data"


def oblique_affine() -> np.ndarray:
    """A RAS affine with a rotation, anisotropic spacing and an origin far from 0."""
    angle = np.deg2rad(17.0)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    a = np.eye(4)
    a[:3, :3] = rotation @ np.diag([0.8, 0.7, 1.5])
    a[:3, 3] = [-40.5, 22.25, 13.0]
    return a


@pytest.fixture(scope="session")
def nifti_int16(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    """An int16 NIfTI (x, y, z) = (70, 45, 38): several bricks per axis, 3 levels."""
    rng = np.random.default_rng(7)
    data = rng.integers(-1200, 3000, size=(70, 45, 38), dtype=np.int16)
    data[10:30, 5:20, 3:9] = 0  # a constant block
    img = nib.Nifti1Image(data, oblique_affine())
    img.set_qform(oblique_affine(), code=1)
    img.set_sform(oblique_affine(), code=1)
    path = tmp_path_factory.mktemp("nifti") / "int16.nii.gz"
    nib.save(img, path)
    return path


@pytest.fixture(scope="session")
def store_int16(nifti_int16: pathlib.Path, tmp_path_factory: pytest.TempPathFactory) -> strata.Volume:
    return strata.import_file(nifti_int16, tmp_path_factory.mktemp("stores") / "int16.strata", progress=False)
