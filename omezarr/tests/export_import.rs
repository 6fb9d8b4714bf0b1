//! Store → OME-Zarr → store, checked three ways: zarr-python 3 reads level 0 as Strata's voxels
//! and ome-zarr-models validates the multiscales; every level streams back brick for brick
//! (aprons at shard boundaries and the volume's edge included); the re-imported store has
//! identical bricks at every level and an identical geometry. A foreign OME-Zarr written by
//! zarr-python (float, a channel axis, no orientation, levels that do not halve) imports to the
//! same store as the same samples imported from raw.

use crate::common;

use std::path::Path;

use common::*;
use strata_omezarr::export::{export, ExportOptions};
use strata_omezarr::import::{import_zarr, ImportZarrOptions};
use strata_omezarr::streaming::OmeZarrSource;
use strata_omezarr::{ObjectLocation, ObjectStoreOptions};
use strata_source::VolumeSource;
use strata_storage::import::{import_source, ImportOptions};
use strata_storage::phantom::Phantom;
use strata_storage::Store;

fn folder(path: &Path, create: bool) -> ObjectLocation {
    ObjectLocation::open(
        path.to_str().unwrap(),
        &ObjectStoreOptions::default(),
        create,
    )
    .unwrap()
}

fn export_folder(store: &Store, dest: &Path, expose: bool) -> strata_omezarr::export::ExportReport {
    let options = ExportOptions {
        expose_identifiers: expose,
        ..ExportOptions::default()
    };
    export(store, &folder(dest, true), &options, &|_, _| {}).unwrap()
}

/// Bytes of every file under a folder.
fn report_bytes(dir: &Path) -> u64 {
    let mut total = 0;
    for entry in std::fs::read_dir(dir).unwrap() {
        let entry = entry.unwrap();
        let meta = entry.metadata().unwrap();
        total += if meta.is_dir() {
            report_bytes(&entry.path())
        } else {
            meta.len()
        };
    }
    total
}

/// The full round trip on one store; returns the re-imported store.
fn round_trip(store: &Store, work: &Path) -> Store {
    let zarr = work.join("x.ome.zarr");
    let report = export_folder(store, &zarr, true);
    assert_eq!(report.levels, store.layout().level_count());
    // Streaming the export gives every brick of the store, aprons included.
    let streamed = OmeZarrSource::open(folder(&zarr, false)).unwrap();
    assert_eq!(streamed.header(), store.header());
    assert_same_bricks(store, &streamed);
    assert_eq!(streamed.skeleton(), store.skeleton());
    // Every chunk is some brick's own and its neighbours' apron source: with the range cache
    // each crosses the wire about once (merged gaps and metadata on top).
    let counters = streamed.transfer_counters();
    let stored = report_bytes(&zarr);
    assert!(
        counters.bytes() as f64 <= 1.3 * stored as f64,
        "streamed {} bytes for an export of {stored} bytes",
        counters.bytes()
    );
    // The bytes of the inner chunks those bricks needed (each once; absent chunks of fill-only
    // regions count nothing): all of the export but its metadata and shard indices.
    let needed = streamed.needed_chunk_bytes().unwrap();
    assert!(
        needed > 0 && needed <= stored,
        "needed {needed} of {stored}"
    );
    assert!(
        counters.bytes() as f64 <= 1.3 * needed as f64,
        "streamed {} bytes for {needed} bytes of chunks needed",
        counters.bytes()
    );
    let bricks = store.layout().total_bricks();
    println!(
        "streamed every brick: {} requests for {bricks} bricks, {} bytes of {stored} stored, {} cache hits",
        counters.requests(),
        counters.bytes(),
        counters.cache_hits()
    );
    // Import rebuilds the same store.
    let back = work.join("back.strata");
    let report = import_zarr(
        folder(&zarr, false),
        &back,
        &ImportZarrOptions::default(),
        &|_, _| {},
        &ImportOptions::default(),
    )
    .unwrap();
    assert!(report.strata_export);
    let back = Store::open(&back).unwrap();
    assert_eq!(back.header().geometry, store.header().geometry);
    assert_eq!(back.header().value_mapping, store.header().value_mapping);
    assert_eq!(back.header().stored, store.header().stored);
    assert_eq!(back.header().modality, store.header().modality);
    assert_eq!(back.header().windows, store.header().windows);
    assert_eq!(
        back.header().quantization_error,
        store.header().quantization_error
    );
    assert_eq!(
        back.header().source_sample_type,
        store.header().source_sample_type
    );
    assert_eq!(back.skeleton(), store.skeleton());
    assert_same_bricks(store, &back);
    back
}

const CHECK_WITH_ZARR_PYTHON: &str = r#"
import sys, json, numpy as np, zarr
path, raw, meta = sys.argv[1], sys.argv[2], json.load(open(sys.argv[3]))
g = zarr.open_group(path, mode="r")
ms = g.attrs["ome"]["multiscales"][0]
assert g.attrs["ome"]["version"] == "0.5"
a = g["0"]
assert a.metadata.dimension_names == ("z", "y", "x"), a.metadata.dimension_names
dims = meta["dims"]
expected = np.fromfile(raw, dtype=meta["dtype"]).reshape(dims[2], dims[1], dims[0])
got = a[:]
assert got.dtype == expected.dtype, (got.dtype, expected.dtype)
assert np.array_equal(got, expected), "level 0 differs from Strata's voxels"
codecs = a.metadata.to_dict()["codecs"]
assert codecs[0]["name"] == "sharding_indexed", codecs
cfg = codecs[0]["configuration"]
assert list(cfg["chunk_shape"]) == [32, 32, 32], cfg
assert [c["name"] for c in cfg["codecs"]] == ["bytes", "zstd"], cfg
assert [c["name"] for c in cfg["index_codecs"]] == ["bytes", "crc32c"], cfg
for level, ds in enumerate(ms["datasets"]):
    arr = g[ds["path"]]
    assert list(arr.shape) == meta["level_shapes"][level], (arr.shape, level)
    scale = ds["coordinateTransformations"][0]["scale"]
    assert np.allclose(scale, meta["scales"][level]), (scale, level)
from ome_zarr_models.v05.image import Image
Image.from_zarr(g)
print("ok", a.shape, len(ms["datasets"]))
"#;

#[test]
fn export_is_read_by_zarr_python_and_validates_and_round_trips() {
    let work = tempfile::tempdir().unwrap();
    // Odd sizes and 300 voxels along x: two shards at level 0 (256 + 44), partial bricks, edges.
    let phantom = Phantom {
        size: [300, 70, 45],
    };
    let store_path = work.path().join("p.strata");
    phantom
        .write_store(&store_path, &ImportOptions::default())
        .unwrap();
    let store = Store::open(&store_path).unwrap();
    let back = round_trip(&store, work.path());
    drop(back);

    // zarr-python 3 reads level 0 as Strata's voxels; ome-zarr-models validates the group.
    let zarr = work.path().join("x.ome.zarr");
    let (level0, dims) = level_voxels(&store, 0);
    let raw = work.path().join("level0.raw");
    write_u16(&raw, &level0);
    let layout = store.layout();
    let spacing = store.header().geometry.spacing_mm;
    let meta = serde_json::json!({
        "dims": dims,
        "dtype": "<u2",
        "level_shapes": layout.level_dims.iter().map(|d| vec![d[2], d[1], d[0]]).collect::<Vec<_>>(),
        "scales": (0..layout.level_count()).map(|l| {
            let f = f64::from(1u32 << l);
            vec![spacing[2] * f, spacing[1] * f, spacing[0] * f]
        }).collect::<Vec<_>>(),
    });
    let meta_path = work.path().join("meta.json");
    std::fs::write(&meta_path, meta.to_string()).unwrap();
    let out = run_python(CHECK_WITH_ZARR_PYTHON, &[&zarr, &raw, &meta_path]);
    assert!(out.starts_with("ok"), "{out}");

    // Orientation labels (the phantom is axis-aligned LPS) and the withheld identifiers.
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(zarr.join("zarr.json")).unwrap()).unwrap();
    let axes = &doc["attributes"]["ome"]["multiscales"][0]["axes"];
    assert_eq!(axes[2]["orientation"]["value"], "right-to-left");
    assert_eq!(axes[1]["orientation"]["value"], "anterior-to-posterior");
    assert_eq!(axes[0]["orientation"]["value"], "inferior-to-superior");
    let exported_description = doc["attributes"]["strata"]["header"]["description"].clone();
    assert_eq!(exported_description, store.header().description.as_str());

    // Without --expose-identifiers: no description, no input paths.
    let private = work.path().join("private.ome.zarr");
    export_folder(&store, &private, false);
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(private.join("zarr.json")).unwrap()).unwrap();
    let header = &doc["attributes"]["strata"]["header"];
    assert_eq!(header["description"], "");
    assert_eq!(header["provenance"]["inputs"], serde_json::json!([]));
    assert!(!private
        .join(strata_omezarr::export::IN_PROGRESS_KEY)
        .exists());
}

/// A volume that is air (stored 0) except for a block in its first 32 x columns.
struct CornerBlock {
    dims: [u64; 3],
}

impl strata_storage::import::SliceProducer for CornerBlock {
    fn dims(&self) -> [u64; 3] {
        self.dims
    }
    fn stored_slice(&self, k: u64, out: &mut [u16]) -> strata_storage::Result<()> {
        for (i, v) in out.iter_mut().enumerate() {
            let x = i as u64 % self.dims[0];
            *v = if x < 20 && k < 10 {
                1000 + (i % 7) as u16
            } else {
                0
            };
        }
        Ok(())
    }
    fn source_bytes_per_slice(&self) -> u64 {
        self.dims[0] * self.dims[1] * 2
    }
}

#[test]
fn fill_only_shards_are_not_written_and_a_foreign_folder_is_refused() {
    let work = tempfile::tempdir().unwrap();
    // 300 voxels along x: level 0 has two shards along x (256 + 44); the second is all air.
    let dims = [300u64, 40, 40];
    let mut meta = Phantom::cube(40).meta();
    meta.geometry = strata_types::VolumeGeometry::axis_aligned([300, 40, 40], [1.0; 3]);
    let store_path = work.path().join("p.strata");
    strata_storage::import::import_slices(
        &CornerBlock { dims },
        meta,
        &store_path,
        &ImportOptions::default(),
    )
    .unwrap();
    let store = Store::open(&store_path).unwrap();
    assert_eq!(store.header().stored_range[0], 0);
    let dest = work.path().join("out.ome.zarr");
    let report = export_folder(&store, &dest, false);
    // Level 0: shard (0,0,0) written, shard (0,0,1) air only; coarser levels: one shard each.
    assert_eq!(report.shards_skipped, 1, "{report:?}");
    assert_eq!(report.shards_written, store.layout().level_count() as u64);
    assert!(dest.join("0/c/0/0/0").exists());
    assert!(!dest.join("0/c/0/0/1").exists());
    // The left-out shard reads as the fill value (air) through the streaming source.
    let streamed = OmeZarrSource::open(folder(&dest, false)).unwrap();
    assert_same_bricks(&store, &streamed);
    // Absent inner chunks (air) in the written shards count nothing in the chunks needed.
    let needed = streamed.needed_chunk_bytes().unwrap();
    assert!(needed > 0 && needed < report_bytes(&dest), "{needed}");
    // Exporting again replaces the previous export.
    let again = export_folder(&store, &dest, false);
    assert_eq!(again, report);
    // A folder holding something else is refused, and left alone.
    let other = work.path().join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("notes.txt"), "mine").unwrap();
    let err = export(
        &store,
        &folder(&other, true),
        &ExportOptions::default(),
        &|_, _| {},
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("not a Strata export"), "{err}");
    assert!(other.join("notes.txt").exists());
}

#[test]
fn real_scans_round_trip_with_their_geometry() {
    let Some(data) = shared_data("real_scans_round_trip_with_their_geometry") else {
        return;
    };
    for name in ["niivue/FLAIR.nrrd", "niivue/chris_t1.nii.gz"] {
        let input = data.join(name);
        if !input.exists() {
            println!("SKIP {name}: absent");
            continue;
        }
        let work = tempfile::tempdir().unwrap();
        let opened = strata_storage::readers::open_source(&input, &Default::default()).unwrap();
        let store_path = work.path().join("s.strata");
        import_source(opened, &store_path, &ImportOptions::default()).unwrap();
        let store = Store::open(&store_path).unwrap();
        round_trip(&store, work.path());
        println!(
            "{name}: round trip identical at all {} levels",
            store.layout().level_count()
        );
    }
}

const WRITE_FOREIGN: &str = r#"
import sys, numpy as np, zarr
path, raw = sys.argv[1], sys.argv[2]
rng = np.random.default_rng(7)
c, z, y, x = 2, 21, 34, 47
data = (rng.standard_normal((c, z, y, x)) * 100.0 + 20.0).astype("float32")
data[1, 3:9, 5:20, 10:30] += 500.0
g = zarr.open_group(path, mode="w", zarr_format=3)
a0 = g.create_array("s0", shape=data.shape, chunks=(1, 16, 16, 16), dtype="float32",
                    dimension_names=["c", "z", "y", "x"])
a0[:] = data
# a coarser level that does not halve (x binned by 3): must not be taken as Strata's level 1
a1 = g.create_array("s1", shape=(c, z, y, x // 3), chunks=(1, 16, 16, 16), dtype="float32",
                    dimension_names=["c", "z", "y", "x"])
a1[:] = data[:, :, :, ::3][:, :, :, : x // 3]
g.attrs["ome"] = {"version": "0.5", "multiscales": [{
    "name": "foreign",
    "axes": [{"name": "c", "type": "channel"},
             {"name": "z", "type": "space", "unit": "micrometer"},
             {"name": "y", "type": "space", "unit": "micrometer"},
             {"name": "x", "type": "space", "unit": "micrometer"}],
    "datasets": [
        {"path": "s0", "coordinateTransformations": [
            {"type": "scale", "scale": [1.0, 4.0, 2.0, 1.5]},
            {"type": "translation", "translation": [0.0, 100.0, 50.0, 25.0]}]},
        {"path": "s1", "coordinateTransformations": [
            {"type": "scale", "scale": [1.0, 4.0, 2.0, 4.5]}]}]}]}
data[1].tofile(raw)
print("written")
"#;

#[test]
fn foreign_ome_zarr_from_zarr_python_imports_like_the_same_raw_samples() {
    let work = tempfile::tempdir().unwrap();
    let zarr = work.path().join("foreign.ome.zarr");
    let raw = work.path().join("channel1.raw");
    run_python(WRITE_FOREIGN, &[&zarr, &raw]);

    let store_path = work.path().join("f.strata");
    let report = import_zarr(
        folder(&zarr, false),
        &store_path,
        &ImportZarrOptions {
            channel: Some(1),
            ..ImportZarrOptions::default()
        },
        &|_, _| {},
        &ImportOptions::default(),
    )
    .unwrap();
    assert!(!report.strata_export);
    let notes = report.notes.join("\n");
    assert!(notes.contains("took 1"), "{notes}");
    assert!(notes.contains("assumed x runs right-to-left"), "{notes}");
    let store = Store::open(&store_path).unwrap();
    let g = &store.header().geometry;
    assert_eq!(g.dims, [47, 34, 21]);
    // micrometres → millimetres, array axes (z, y, x) → index axes (i, j, k)
    let close = |a: [f64; 3], b: [f64; 3]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-12);
    assert!(
        close(g.spacing_mm, [1.5e-3, 2.0e-3, 4.0e-3]),
        "{:?}",
        g.spacing_mm
    );
    assert!(
        close(g.origin_lps_mm, [25.0e-3, 50.0e-3, 100.0e-3]),
        "{:?}",
        g.origin_lps_mm
    );
    assert_eq!(
        g.direction,
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    );

    // The same float samples through the raw reader: the same quantisation, the same bricks.
    let spec = strata_storage::readers::RawSpec {
        dims: [47, 34, 21],
        sample_type: strata_storage::SampleType::F32,
        spacing_mm: g.spacing_mm,
        byte_order: strata_storage::ByteOrder::Little,
        header_bytes: 0,
    };
    let opened = strata_storage::readers::open_source(
        &raw,
        &strata_storage::readers::ReadOptions {
            raw: Some(spec),
            ..Default::default()
        },
    )
    .unwrap();
    let raw_store_path = work.path().join("raw.strata");
    import_source(opened, &raw_store_path, &ImportOptions::default()).unwrap();
    let raw_store = Store::open(&raw_store_path).unwrap();
    assert_eq!(
        store.header().value_mapping.mapping,
        raw_store.header().value_mapping.mapping
    );
    assert!(store.header().quantization_error > 0.0);
    assert_same_bricks(&store, &raw_store);

    // A channel out of range is a clear error.
    let err = import_zarr(
        folder(&zarr, false),
        &work.path().join("bad.strata"),
        &ImportZarrOptions {
            channel: Some(5),
            ..ImportZarrOptions::default()
        },
        &|_, _| {},
        &ImportOptions::default(),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(err.contains("--channel 5 is out of range"), "{err}");
}
