//! Store format 2 (a codec per store, required features) next to format 1: the old writer path
//! (lz4, no codec field) still produces format-1 stores, which keep opening; headers this build
//! cannot read are refused naming the command that rebuilds the store.

use std::path::Path;
use std::time::Duration;

use crate::common;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::store::STORE_FORMAT_VERSION;
use strata_storage::{BrickCodec, StorageError, Store};
use strata_types::BrickId;

fn write(path: &Path, size: u64, codec: BrickCodec) -> strata_storage::import::ImportReport {
    let options = ImportOptions {
        codec,
        ..Default::default()
    };
    Phantom::cube(size).write_store(path, &options).unwrap()
}

/// [`write`] as a format-2 (sled) store, whose header [`edit_header`] edits.
fn write_v2(path: &Path, size: u64, codec: BrickCodec) {
    let options = ImportOptions {
        codec,
        ..Default::default()
    };
    Phantom::cube(size)
        .write_store_as_format(path, &options, 2)
        .unwrap();
}

/// Every brick of every level of `store`.
fn all_bricks(store: &Store) -> Vec<(BrickId, Vec<u16>)> {
    common::all_brick_ids(store)
        .into_iter()
        .map(|id| (id, store.read_brick(id).unwrap()))
        .collect()
}

/// Decodes every brick record of `store` through C zstd (the native decoder) and through ruzstd
/// (what a build without `local`, the browser viewer's, decodes with) and asserts the same
/// voxels; returns how many records held zstd frames (kinds 4-9).
fn assert_ruzstd_decodes_as_c_zstd(store: &Store, what: &str) -> usize {
    let layout = store.layout().clone();
    let mut zstd_records = 0;
    for level in 0..layout.level_count() {
        let n = layout.bricks_in_level(level);
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let id = BrickId::new(level as u8, [x, y, z]);
                    let record = store.read_brick_record(id).unwrap();
                    let c = strata_storage::brick::decode_brick(id, &record).unwrap();
                    let pure = strata_storage::brick::decode_brick_pure_rust(id, &record);
                    assert_eq!(pure.as_ref(), Ok(&c), "{what} {id:?} (kind {})", record[0]);
                    zstd_records += usize::from(record[0] >= 4);
                }
            }
        }
    }
    zstd_records
}

/// A store's records decode to the same voxels through ruzstd as through C zstd, in every
/// codec (phantom: u16 kinds; the 8-bit MR test below does the u8 kinds).
#[test]
fn ruzstd_decodes_every_record_of_a_store_as_c_zstd_does() {
    let dir = tempfile::tempdir().unwrap();
    for codec in BrickCodec::ALL {
        let path = dir.path().join(codec.name());
        write(&path, 40, codec);
        let store = Store::open(&path).unwrap();
        let zstd_records = assert_ruzstd_decodes_as_c_zstd(&store, codec.name());
        if codec == BrickCodec::Dense {
            assert!(zstd_records > 0, "a dense u16 store holds zstd records");
        }
    }
}

/// Rewrites the header JSON of a closed store (what another build of Strata could have written).
fn edit_header(path: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    let db = loop {
        match sled::open(path.join("db")) {
            Ok(db) => break db,
            // sled lets go of its file lock a moment after the last handle drops.
            Err(_) if std::time::Instant::now() < deadline => {
                std::thread::sleep(Duration::from_millis(20))
            }
            Err(e) => panic!("{e}"),
        }
    };
    let meta = db.open_tree("meta").unwrap();
    let mut header: serde_json::Value =
        serde_json::from_slice(&meta.get("header").unwrap().unwrap()).unwrap();
    edit(&mut header);
    meta.insert("header", serde_json::to_vec(&header).unwrap())
        .unwrap();
    db.flush().unwrap();
}

#[test]
fn format_1_stores_from_the_old_writer_path_keep_opening_with_the_same_voxels() {
    let dir = tempfile::tempdir().unwrap();
    let (old, new) = (dir.path().join("old.strata"), dir.path().join("new.strata"));
    let old_report = write(&old, 70, BrickCodec::Lz4);
    let new_report = write(&new, 70, BrickCodec::Fast);
    // The old writer path writes what format 1 was: version 1 and no codec field.
    assert_eq!(old_report.header.format_version, 1);
    let json = serde_json::to_value(&old_report.header).unwrap();
    assert!(json.get("codec").is_none(), "{json}");
    assert!(json.get("required_features").is_none(), "{json}");
    let marker = std::fs::read_to_string(old.join("STRATA-STORE")).unwrap();
    assert!(marker.starts_with("strata store format 1\n"), "{marker}");
    assert_eq!(new_report.header.format_version, STORE_FORMAT_VERSION);
    assert_eq!(new_report.header.codec, BrickCodec::Fast);

    let old_store = Store::open(&old).unwrap();
    let new_store = Store::open(&new).unwrap();
    assert_eq!(old_store.header().codec, BrickCodec::Lz4);
    assert_eq!(all_bricks(&old_store), all_bricks(&new_store));
    assert!(old_store.verify(|_, _| {}).unwrap().is_empty());
    assert!(new_store.verify(|_, _| {}).unwrap().is_empty());
}

#[test]
fn the_codec_is_recorded_and_dense_is_smaller_than_fast_smaller_than_lz4() {
    let dir = tempfile::tempdir().unwrap();
    let mut sizes = Vec::new();
    let mut bricks = Vec::new();
    for codec in BrickCodec::ALL {
        let path = dir.path().join(format!("{}.strata", codec.name()));
        let report = write(&path, 80, codec);
        sizes.push(report.stats.compressed_bytes);
        let store = Store::open(&path).unwrap();
        assert_eq!(store.header().codec, codec);
        assert!(store.verify(|_, _| {}).unwrap().is_empty());
        bricks.push(all_bricks(&store));
    }
    assert_eq!(bricks[0], bricks[1]);
    assert_eq!(bricks[1], bricks[2]);
    // The phantom is 12-bit CT with noise: shuffling its bytes helps both codecs.
    assert!(sizes[1] < sizes[0], "fast {} vs lz4 {}", sizes[1], sizes[0]);
    assert!(
        sizes[2] < sizes[1],
        "dense {} vs fast {}",
        sizes[2],
        sizes[1]
    );
}

#[test]
fn a_newer_format_is_refused_naming_the_rebuild_command() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("future.strata");
    write_v2(&path, 40, BrickCodec::Fast);
    edit_header(&path, |h| {
        h["format_version"] = serde_json::json!(STORE_FORMAT_VERSION + 1);
        h["provenance"]["inputs"] = serde_json::json!(["/scans/head.nii.gz"]);
    });
    let err = Store::open(&path).err().unwrap();
    let message = err.to_string();
    assert!(matches!(err, StorageError::Unsupported { .. }), "{message}");
    assert!(message.contains("future.strata"), "{message}");
    assert!(
        message.contains(&format!("format version {}", STORE_FORMAT_VERSION + 1)),
        "{message}"
    );
    assert!(
        message.contains("strata import --replace '/scans/head.nii.gz'"),
        "{message}"
    );
}

#[test]
fn an_unknown_required_feature_is_refused_and_a_known_header_still_opens() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sparse.strata");
    write_v2(&path, 40, BrickCodec::Dense);
    edit_header(&path, |h| {
        h["required_features"] = serde_json::json!(["sparse-skeleton-v9"]);
    });
    let message = Store::open(&path).err().unwrap().to_string();
    assert!(message.contains("sparse-skeleton-v9"), "{message}");
    assert!(message.contains("strata import"), "{message}");
    edit_header(&path, |h| {
        h["required_features"] = serde_json::json!([]);
    });
    let store = Store::open(&path).unwrap();
    assert_eq!(store.header().codec, BrickCodec::Dense);
}

#[test]
fn a_format_1_header_naming_a_format_2_codec_is_damage() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("mixed.strata");
    write_v2(&path, 40, BrickCodec::Fast);
    edit_header(&path, |h| h["format_version"] = serde_json::json!(1));
    let err = Store::open(&path).err().unwrap();
    assert!(matches!(err, StorageError::Corrupted { .. }), "{err}");
    assert!(err.to_string().contains("fast"), "{err}");
}

#[test]
fn a_flipped_byte_in_a_brick_of_each_codec_is_found_by_read_and_verify() {
    let dir = tempfile::tempdir().unwrap();
    for codec in BrickCodec::ALL {
        let path = dir.path().join(format!("flip-{}.strata", codec.name()));
        write(&path, 40, codec);
        // A brick holding the phantom's body (not constant): its kind byte, checksum, body.
        let centre = BrickId::new(0, [0, 0, 0]);
        for byte in [0usize, 1, 9, 30, 1000] {
            Store::corrupt_brick_for_tests(&path, centre, byte).unwrap();
            let store = Store::open(&path).unwrap();
            let err = store.read_brick(centre).unwrap_err().to_string();
            assert!(err.contains(&format!("flip-{}", codec.name())), "{err}");
            let problems = store.verify(|_, _| {}).unwrap();
            assert_eq!(problems.len(), 1, "{}: {problems:?}", codec.name());
            drop(store);
            // Undo it (the flip is an XOR) for the next position.
            Store::corrupt_brick_for_tests(&path, centre, byte).unwrap();
        }
        let store = Store::open(&path).unwrap();
        assert!(store.verify(|_, _| {}).unwrap().is_empty());
    }
}

/// An 8-bit MR (a real scan of SOURCES.md; skipped when absent): every codec stores the same
/// voxels, the predicted u8 kinds make fast and dense smaller than lz4, the header names the
/// feature those kinds need, and a build without that feature would refuse the store.
#[test]
fn an_8_bit_mr_stores_the_same_voxels_smaller_under_the_predicted_kinds() {
    let scan = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/niivue/nifti_space/RAS.nii.gz");
    if !scan.exists() {
        println!(
            "SKIP: {} absent (see shared/data/SOURCES.md)",
            scan.display()
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut sizes = Vec::new();
    let mut bricks = Vec::new();
    for codec in BrickCodec::ALL {
        let path = dir.path().join(format!("{}.strata", codec.name()));
        let report = import_with_codec(&scan, &path, codec);
        sizes.push(report.stats.compressed_bytes);
        let store = Store::open(&path).unwrap();
        assert_eq!(store.header().stored, strata_storage::StoredScalar::U8);
        let features = &store.header().required_features;
        let mut expected = codec.required_features(true);
        if codec != BrickCodec::Lz4 {
            expected.push(strata_storage::store::FEATURE_SPARSE_SKELETON.to_string());
        }
        assert_eq!(features, &expected, "{}", codec.name());
        if codec != BrickCodec::Lz4 {
            assert!(features.contains(&strata_storage::brick::PREDICTED_U8_FEATURE.to_string()));
        }
        assert!(store.verify(|_, _| {}).unwrap().is_empty());
        // The u8 kinds (8 and 9 hold zstd frames) through ruzstd as through C zstd.
        let zstd_records = assert_ruzstd_decodes_as_c_zstd(&store, codec.name());
        assert_eq!(
            zstd_records > 0,
            codec != BrickCodec::Lz4,
            "{}",
            codec.name()
        );
        bricks.push(all_bricks(&store));
    }
    assert_eq!(bricks[0], bricks[1]);
    assert_eq!(bricks[0], bricks[2]);
    assert!(sizes[1] < sizes[0], "fast {} vs lz4 {}", sizes[1], sizes[0]);
    assert!(
        sizes[2] < sizes[0],
        "dense {} vs lz4 {}",
        sizes[2],
        sizes[0]
    );
}

/// Imports the scan at `scan` into a store at `path` in `codec`.
fn import_with_codec(
    scan: &Path,
    path: &Path,
    codec: BrickCodec,
) -> strata_storage::import::ImportReport {
    let opened = strata_storage::readers::open_source(
        scan,
        &strata_storage::readers::ReadOptions::default(),
    )
    .unwrap();
    let options = ImportOptions {
        codec,
        ..Default::default()
    };
    strata_storage::import::import_source(opened, path, &options).unwrap()
}

/// A `dense` u8 store holds kind-8 bricks and a `fast` one kind-9 bricks, and each says so: a
/// build that knows the store features up to `predicted-u8-bricks` only (the one before kinds 8
/// and 9) refuses it with the rebuild command, while this build opens it. Skipped when the scan
/// is absent.
#[test]
fn a_build_without_kinds_8_and_9_refuses_a_predicted_u8_store_cleanly() {
    let scan = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/niivue/nifti_space/LPI.nii.gz");
    if !scan.exists() {
        println!(
            "SKIP: {} absent (see shared/data/SOURCES.md)",
            scan.display()
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    for (codec, feature) in [
        (
            BrickCodec::Dense,
            strata_storage::brick::LINEAR3D_U8_FEATURE,
        ),
        (
            BrickCodec::Fast,
            strata_storage::brick::COLUMN_DELTA_U8_FEATURE,
        ),
    ] {
        let path = dir.path().join(format!("{}-u8.strata", codec.name()));
        import_with_codec(&scan, &path, codec);
        let store = Store::open(&path).unwrap();
        let header = store.header().clone();
        assert!(header.required_features.iter().any(|f| f == feature));
        let older = [
            strata_storage::brick::PREDICTED_U8_FEATURE,
            strata_storage::store::FEATURE_FRAMES,
        ];
        let err = strata_storage::store::check_format_knowing(&path, &header, &older).unwrap_err();
        let message = err.to_string();
        assert!(matches!(err, StorageError::Unsupported { .. }), "{message}");
        assert!(message.contains(feature), "{message}");
        assert!(message.contains("strata import"), "{message}");
        strata_storage::store::check_format_knowing(
            &path,
            &header,
            strata_storage::store::KNOWN_STORE_FEATURES,
        )
        .unwrap();
        assert!(store.verify(|_, _| {}).unwrap().is_empty());
    }
}
