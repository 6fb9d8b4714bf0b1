//! Foreign OME-Zarr pyramids (written by zarr-python 3, no `strata` attribute) streamed in
//! place: float32 quantised over the `omero` window's data range (then level 0 equals the
//! import's, which maps the same range) or, without one, over the coarsest level's range
//! (level-0 values outside it clamped, within the quantisation step otherwise); a pyramid
//! without Strata's level shapes refused with the URL and the remedy; blosc-compressed chunks
//! (ome-zarr-py's default) imported and streamed.

use crate::common;

use std::path::Path;

use common::*;
use strata_omezarr::import::{import_zarr, ImportZarrOptions};
use strata_omezarr::streaming::OmeZarrSource;
use strata_omezarr::{ObjectLocation, ObjectStoreOptions};
use strata_source::VolumeSource;
use strata_storage::import::ImportOptions;
use strata_storage::Store;

fn folder(path: &Path) -> ObjectLocation {
    ObjectLocation::open(
        path.to_str().unwrap(),
        &ObjectStoreOptions::default(),
        false,
    )
    .unwrap()
}

fn import(zarr: &Path, store: &Path) -> Store {
    import_zarr(
        folder(zarr),
        store,
        &ImportZarrOptions::default(),
        &|_, _| {},
        &ImportOptions::default(),
    )
    .unwrap();
    Store::open(store).unwrap()
}

/// float32 (z, y, x) = (40, 36, 50) with a Strata-shaped float pyramid (2 levels); `omero`
/// window with the exact data range when argv[3] is "omero"; level 0 also as raw float32.
const WRITE_FLOAT: &str = r#"
import sys, json, numpy as np, zarr
path, raw, mode = sys.argv[1], sys.argv[2], sys.argv[3]
rng = np.random.default_rng(11)
data = (rng.standard_normal((40, 36, 50)) * 3.0 + 0.25).astype("float32")
data[5:20, 4:30, 10:40] += 40.0
def halve(a):
    pad = [(0, s % 2) for s in a.shape]
    b = np.pad(a, pad, mode="edge")
    return (sum(b[i::2, j::2, k::2] for i in (0, 1) for j in (0, 1) for k in (0, 1)) / 8).astype("float32")
levels = [data, halve(data)]
g = zarr.open_group(path, mode="w", zarr_format=3)
datasets = []
for l, level in enumerate(levels):
    a = g.create_array(str(l), shape=level.shape, chunks=(16, 16, 16), dtype="float32",
                       dimension_names=["z", "y", "x"])
    a[:] = level
    f = 2.0 ** l
    datasets.append({"path": str(l), "coordinateTransformations": [
        {"type": "scale", "scale": [f, f, f]}]})
ome = {"version": "0.5", "multiscales": [{"axes": ["z", "y", "x"], "datasets": datasets}]}
if mode == "omero":
    ome["omero"] = {"channels": [{"window": {"min": float(data.min()), "max": float(data.max()),
                                             "start": 0.0, "end": 30.0}}]}
g.attrs["ome"] = ome
data.tofile(raw)
print(json.dumps([float(levels[-1].min()), float(levels[-1].max())]))
"#;

fn raw_f32(path: &Path) -> Vec<f32> {
    std::fs::read(path)
        .unwrap()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

#[test]
fn float32_streams_over_the_omero_range_like_the_import_and_else_over_the_coarsest_range() {
    let work = tempfile::tempdir().unwrap();
    // With the omero window (the exact data range): level 0 streams as import stores it.
    let zarr = work.path().join("f.ome.zarr");
    let raw = work.path().join("f.raw");
    run_python(WRITE_FLOAT, &[&zarr, &raw, Path::new("omero")]);
    let streamed = OmeZarrSource::open(folder(&zarr)).unwrap();
    let notes = streamed.notes().join("\n");
    assert!(notes.contains("omero window"), "{notes}");
    let imported = import(&zarr, &work.path().join("f.strata"));
    assert_eq!(streamed.layout(), imported.layout());
    assert_eq!(
        streamed.header().value_mapping,
        imported.header().value_mapping
    );
    assert!(streamed.header().quantization_error > 0.0);
    assert_eq!(
        level_voxels(&streamed, 0).0,
        level_voxels(&imported, 0).0,
        "level 0 streamed differs from level 0 imported"
    );

    // Without: the coarsest level's range; values outside are clamped, inside within half a
    // quantisation step.
    let zarr = work.path().join("g.ome.zarr");
    let out = run_python(WRITE_FLOAT, &[&zarr, &raw, Path::new("none")]);
    let [lo, hi]: [f64; 2] = serde_json::from_str(out.trim()).unwrap();
    let streamed = OmeZarrSource::open(folder(&zarr)).unwrap();
    let notes = streamed.notes().join("\n");
    assert!(notes.contains("coarsest level's range"), "{notes}");
    assert!(notes.contains("strata import"), "{notes}");
    let mapping = streamed.header().value_mapping.mapping;
    let step = mapping.slope.abs();
    let (level0, _) = level_voxels(&streamed, 0);
    let samples = raw_f32(&raw);
    assert_eq!(level0.len(), samples.len());
    let mut clamped = 0;
    for (&stored, &sample) in level0.iter().zip(&samples) {
        let expected = f64::from(sample).clamp(lo, hi);
        clamped += usize::from(expected != f64::from(sample));
        let got = mapping.physical(f64::from(stored));
        assert!(
            (got - expected).abs() <= 0.5 * step * (1.0 + 1e-9) + 1e-12,
            "sample {sample} streamed as {got} (range [{lo}, {hi}])"
        );
    }
    assert!(
        clamped > 0,
        "the test should have values outside the coarse range"
    );
}

const WRITE_NOT_HALVING: &str = r#"
import sys, numpy as np, zarr
path = sys.argv[1]
data = (np.arange(40 * 36 * 50) % 3000 - 1000).astype("int16").reshape(40, 36, 50)
g = zarr.open_group(path, mode="w", zarr_format=3)
for name, level in [("full", data), ("binned", data[::1, ::3, ::3])]:
    a = g.create_array(name, shape=level.shape, chunks=(16, 16, 16), dtype="int16",
                       dimension_names=["z", "y", "x"])
    a[:] = level
g.attrs["ome"] = {"version": "0.5", "multiscales": [{"axes": ["z", "y", "x"], "datasets": [
    {"path": "full", "coordinateTransformations": [{"type": "scale", "scale": [1.0, 1.0, 1.0]}]},
    {"path": "binned", "coordinateTransformations": [{"type": "scale", "scale": [1.0, 3.0, 3.0]}]}]}]}
print("ok")
"#;

#[test]
fn a_pyramid_without_strata_level_shapes_is_refused_with_the_remedy_and_imports() {
    let work = tempfile::tempdir().unwrap();
    let zarr = work.path().join("n.ome.zarr");
    run_python(WRITE_NOT_HALVING, &[&zarr]);
    let err = OmeZarrSource::open(folder(&zarr))
        .err()
        .expect("a pyramid without Strata's level 1 must not stream")
        .to_string();
    let place = zarr.to_str().unwrap();
    assert!(err.contains(place), "{err}");
    assert!(
        err.contains(&format!("strata import {place}")),
        "the remedy is missing: {err}"
    );
    assert!(err.contains("passed over: `binned`"), "{err}");
    // The remedy works: import rebuilds the pyramid from level 0 (int16 stored exactly).
    let store = import(&zarr, &work.path().join("n.strata"));
    assert_eq!(store.header().value_mapping.mapping.intercept, -32768.0);
    let (level0, _) = level_voxels(&store, 0);
    assert_eq!(level0[0], (-1000i32 + 32768) as u16);
    assert_eq!(level0[1], (-999i32 + 32768) as u16);
}

/// uint16 compressed with blosc (zstd, byte shuffle), as ome-zarr-py writes by default; one
/// 32³-or-smaller level, which is Strata's whole octree, so it also streams.
const WRITE_BLOSC: &str = r#"
import sys, numpy as np, zarr
from zarr.codecs import BloscCodec
path, raw = sys.argv[1], sys.argv[2]
rng = np.random.default_rng(5)
data = rng.integers(0, 4000, size=(25, 30, 20), dtype="uint16")
g = zarr.open_group(path, mode="w", zarr_format=3)
a = g.create_array("0", shape=data.shape, chunks=(16, 16, 16), dtype="uint16",
                   dimension_names=["z", "y", "x"],
                   compressors=[BloscCodec(cname="zstd", clevel=5, shuffle="shuffle")])
a[:] = data
assert a.metadata.to_dict()["codecs"][1]["name"] == "blosc", a.metadata.to_dict()["codecs"]
g.attrs["ome"] = {"version": "0.5", "multiscales": [{"axes": ["z", "y", "x"], "datasets": [
    {"path": "0", "coordinateTransformations": [{"type": "scale", "scale": [1.0, 1.0, 1.0]}]}]}]}
data.tofile(raw)
print("ok")
"#;

#[test]
fn blosc_compressed_chunks_import_and_stream() {
    let work = tempfile::tempdir().unwrap();
    let zarr = work.path().join("b.ome.zarr");
    let raw = work.path().join("b.raw");
    run_python(WRITE_BLOSC, &[&zarr, &raw]);
    let expected: Vec<u16> = std::fs::read(&raw)
        .unwrap()
        .chunks_exact(2)
        .map(|b| u16::from_le_bytes([b[0], b[1]]))
        .collect();
    let store = import(&zarr, &work.path().join("b.strata"));
    assert_eq!(level_voxels(&store, 0).0, expected);
    let streamed = OmeZarrSource::open(folder(&zarr)).unwrap();
    assert_same_bricks(&store, &streamed);
}
