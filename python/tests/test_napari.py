"""The napari reader through npe2's reader contract (no GUI, no napari): the installed
package's manifest is found through its entry point, and npe2.read returns the multiscale
layer built from the lazy levels, with scale, translate and contrast limits from the volume."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

import strata

try:
    import npe2
except ImportError:  # a missing peer fails, saying how to install it
    npe2 = None

NPE2_HINT = "npe2 is missing: pip install npe2 (as .ci/run's python stage does)"


@pytest.fixture(scope="module")
def plugin_manager() -> "npe2.PluginManager":
    if npe2 is None:
        pytest.fail(NPE2_HINT)
    pm = npe2.PluginManager.instance()
    pm.discover()
    assert "strata" in {m.name for m in pm.iter_manifests()}, (
        "the installed strata package declares no napari manifest: reinstall it (pip install ./python)"
    )
    return pm


@pytest.fixture(scope="module")
def oblique_store(tmp_path_factory: pytest.TempPathFactory) -> tuple[np.ndarray, np.ndarray, pathlib.Path]:
    rng = np.random.default_rng(3)
    a = rng.integers(-500, 1500, size=(36, 50, 66), dtype=np.int16)
    angle = np.deg2rad(20.0)
    c, s = np.cos(angle), np.sin(angle)
    affine = np.eye(4)
    affine[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([0.5, 0.6, 1.5])
    affine[:3, 3] = [12.0, -7.5, 40.0]
    dst = tmp_path_factory.mktemp("napari") / "knee.strata"
    strata.from_numpy(a, affine=affine, dst=dst).close()
    return a, affine, dst


def check_layer(layer: tuple, a: np.ndarray, affine: np.ndarray, name: str) -> None:
    data, meta, kind = layer
    assert kind == "image"
    assert meta["multiscale"] is True and meta["name"] == name
    assert [d.shape for d in data] == [a.shape, (18, 25, 33), (9, 13, 17)]
    assert all(isinstance(d, strata.Level) for d in data)
    np.testing.assert_array_equal(data[0][10:20, 5:45, 30:66], a[10:20, 5:45, 30:66])
    np.testing.assert_allclose(meta["scale"], (1.5, 0.6, 0.5))
    np.testing.assert_allclose(meta["translate"], (40.0, -7.5, 12.0))
    # napari's world point R·(scale·index) + translate is the volume's affine, axes reversed.
    index_zyx = np.array([7.0, 11.0, 13.0])
    world_zyx = meta["rotate"] @ (np.array(meta["scale"]) * index_zyx) + np.array(meta["translate"])
    lps = affine @ np.array([13.0, 11.0, 7.0, 1.0])
    np.testing.assert_allclose(world_zyx, lps[2::-1], atol=1e-9)
    assert meta["contrast_limits"] == (float(a.min()), float(a.max()))


def test_npe2_reads_a_store_folder(plugin_manager, oblique_store) -> None:
    a, affine, dst = oblique_store
    [layer] = npe2.read([str(dst)], stack=False, plugin_name="strata")
    check_layer(layer, a, affine, "knee")


def test_npe2_reads_a_served_store_and_a_strata_omezarr(plugin_manager, oblique_store, tmp_path) -> None:
    a, affine, dst = oblique_store
    with strata.serve(dst) as urls:
        [layer] = npe2.read([urls[0]], stack=False, plugin_name="strata")
        check_layer(layer, a, affine, "knee")
    figures = strata.export_omezarr(dst, tmp_path / "knee.ome.zarr")
    assert figures["levels"] == 3 and figures["shards_written"] > 0
    [layer] = npe2.read([str(tmp_path / "knee.ome.zarr")], stack=False, plugin_name="strata")
    check_layer(layer, a, affine, "knee")


def test_the_reader_declines_what_is_not_a_strata_volume(plugin_manager, tmp_path) -> None:
    from strata.napari import get_reader

    (tmp_path / "empty").mkdir()
    assert get_reader(str(tmp_path / "empty")) is None
    assert get_reader(str(tmp_path / "scan.nii.gz")) is None
    assert get_reader("https://example.org/data.zarr") is None
    foreign = tmp_path / "foreign.zarr"
    foreign.mkdir()
    (foreign / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group", "attributes": {"ome": {}}}')
    assert get_reader(str(foreign)) is None
    with pytest.raises(ValueError):
        npe2.read([str(tmp_path / "empty")], stack=False, plugin_name="strata")


def test_the_manifest_is_valid_and_names_the_reader() -> None:
    if npe2 is None:
        pytest.fail(NPE2_HINT)
    manifest = npe2.PluginManifest.from_file(pathlib.Path(strata.__file__).parent / "napari.yaml")
    assert manifest.name == "strata"
    [reader] = manifest.contributions.readers
    [command] = manifest.contributions.commands
    assert command.python_name == "strata.napari:get_reader" and reader.command == command.id
    assert reader.accepts_directories
