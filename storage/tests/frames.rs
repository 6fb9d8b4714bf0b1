//! 4-D import: a 4-D NIfTI (written by nibabel) imports every time point as a frame of one
//! store; each frame's level-0 voxels equal the source's, frame 0 reads exactly as a single
//! volume does, and the header names the frames and the feature older builds refuse. Without
//! nibabel this FAILS with the install command (CI installs it: .ci/run).

use std::path::Path;

use crate::common;
use strata_storage::import::{import_source, ImportOptions};
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::store::FEATURE_FRAMES;
use strata_storage::Store;
use strata_types::BrickId;
use strata_types::{BRICK_APRON, BRICK_PAYLOAD};

const DIMS: [usize; 4] = [6, 5, 4, 3];

/// The source value at voxel (i, j, k) of time point t: frames differ everywhere, and later
/// frames lie outside frame 0's range (one value mapping must cover them all).
fn value(i: usize, j: usize, k: usize, t: usize, float: bool) -> f64 {
    let v = (i + 10 * j + 100 * k) as f64 + 1000.0 * t as f64;
    if float {
        v * 0.25 - 7.0
    } else {
        v
    }
}

fn write_nifti(path: &Path, float: bool) {
    let script = format!(
        "import nibabel as nib, numpy as np\n\
         d = np.zeros({dims:?}, np.{ty})\n\
         for i in range({a}):\n  for j in range({b}):\n    for k in range({c}):\n      for t in range({e}):\n        \
         v = i + 10*j + 100*k + 1000.0*t\n        d[i, j, k, t] = v * 0.25 - 7.0 if {float} else v\n\
         img = nib.Nifti1Image(d, np.diag([0.8, 0.9, 2.0, 1.0]))\n\
         nib.save(img, r'{path}')\n",
        dims = DIMS,
        ty = if float { "float32" } else { "int16" },
        a = DIMS[0],
        b = DIMS[1],
        c = DIMS[2],
        e = DIMS[3],
        float = if float { "True" } else { "False" },
        path = path.display()
    );
    let out = std::process::Command::new("python3")
        .args(["-c", &script])
        .output()
        .expect("python3 needed");
    assert!(
        out.status.success(),
        "nibabel needed: pip install nibabel (CI: .ci/run)\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn a_4d_nifti_imports_every_volume_as_a_frame() {
    let dir = tempfile::tempdir().unwrap();
    for (name, float) in [
        ("series.nii", false),
        ("series.nii.gz", false),
        ("float.nii.gz", true),
    ] {
        let source = dir.path().join(name);
        write_nifti(&source, float);
        let opened = open_source(&source, &ReadOptions::default()).unwrap();
        assert_eq!(opened.info.frames, DIMS[3] as u32, "{name}");
        assert_eq!(opened.info.geometry.dims, [6, 5, 4], "{name}");
        let store_path = dir.path().join(format!("{name}.strata"));
        import_source(opened, &store_path, &ImportOptions::default()).unwrap();
        let leftovers: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().contains("importing"))
            .collect();
        assert!(
            leftovers.is_empty(),
            "temporary frame stores left: {leftovers:?}"
        );
        let store = Store::open(&store_path).unwrap();
        let header = store.header();
        assert_eq!(store.frame_count(), DIMS[3] as u32);
        assert_eq!(header.frames, DIMS[3] as u32);
        assert!(header.required_features.iter().any(|f| f == FEATURE_FRAMES));
        // Integers import exactly; floats within the stated quantisation error (one mapping
        // for all frames, so frame 2's values are not clamped to frame 0's range).
        let tolerance = header.quantization_error + 1e-9;
        let payload = BRICK_PAYLOAD as usize;
        let a = BRICK_APRON as usize;
        for t in 0..DIMS[3] {
            let brick = store
                .read_frame_brick(t as u32, BrickId::new(0, [0, 0, 0]))
                .unwrap();
            if t == 0 {
                assert_eq!(
                    brick,
                    store.read_brick(BrickId::new(0, [0, 0, 0])).unwrap(),
                    "frame 0 is the single-volume layout"
                );
            }
            for k in 0..DIMS[2] {
                for j in 0..DIMS[1] {
                    for i in 0..DIMS[0] {
                        let stored = brick[(i + a) + payload * ((j + a) + payload * (k + a))];
                        let got = header.value_mapping.physical(stored);
                        let want = value(i, j, k, t, float);
                        assert!(
                            (got - want).abs() <= tolerance,
                            "{name} frame {t} voxel ({i},{j},{k}): {got} vs {want} (±{tolerance})"
                        );
                    }
                }
            }
            let skeleton = store.frame_skeleton(t as u32).unwrap();
            let range = skeleton.node(BrickId::new(0, [0, 0, 0])).unwrap();
            let lo = header.value_mapping.physical(range.min);
            assert!(
                (lo - value(0, 0, 0, t, float)).abs() <= tolerance,
                "{name} frame {t}: its own skeleton ({lo})"
            );
        }
        assert!(store
            .read_frame_brick(DIMS[3] as u32, BrickId::new(0, [0, 0, 0]))
            .is_err());
        assert!(store.verify(|_, _| {}).unwrap().is_empty(), "{name}");
        // Damage in a later frame is found by verify, naming the frame.
        drop(store);
        let last = DIMS[3] as u32 - 1;
        Store::corrupt_frame_brick_for_tests(&store_path, last, BrickId::new(0, [0, 0, 0]), 40)
            .unwrap();
        let problems = Store::open(&store_path).unwrap().verify(|_, _| {}).unwrap();
        assert_eq!(problems.len(), 1, "{name}: {problems:?}");
        assert!(
            problems[0].contains(&format!("frame {last}")),
            "{name}: {problems:?}"
        );
    }
}

/// One 3×2 MR slice at height `z` of phase `phase` (0-based), telling its phase by `tag`.
fn write_phase_slice(path: &Path, z: f64, phase: usize, tag: dicom_core::Tag) {
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::{tags, uids};
    use dicom_object::InMemDicomObject;
    let sop_uid = format!("1.2.3.{}.{}", phase + 1, (z * 10.0) as i64 + 100);
    let mut obj = InMemDicomObject::new_empty();
    let mut put = |tag, vr, v: PrimitiveValue| obj.put(DataElement::new(tag, vr, v));
    put(tags::SOP_CLASS_UID, VR::UI, uids::MR_IMAGE_STORAGE.into());
    put(tags::SOP_INSTANCE_UID, VR::UI, sop_uid.clone().into());
    put(tags::MODALITY, VR::CS, "MR".into());
    put(tags::SERIES_INSTANCE_UID, VR::UI, "1.2.840.7".into());
    put(
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        format!("0\\0\\{z}").into(),
    );
    put(
        tags::IMAGE_ORIENTATION_PATIENT,
        VR::DS,
        "1\\0\\0\\0\\1\\0".into(),
    );
    put(tags::PIXEL_SPACING, VR::DS, "0.5\\0.25".into());
    common::put_grey_pixel_module(&mut put, [2, 3], 16, false);
    // Trigger times in ms; identifiers and acquisition numbers count from 1.
    let phase_value = if tag == tags::TRIGGER_TIME {
        format!("{}", 40.5 * phase as f64)
    } else {
        format!("{}", phase + 1)
    };
    let vr = if tag == tags::TRIGGER_TIME {
        VR::DS
    } else {
        VR::IS
    };
    put(tag, vr, phase_value.into());
    let px: Vec<u16> = (0..6u16)
        .map(|i| 1000 * phase as u16 + 10 * z as u16 + i)
        .collect();
    put(tags::PIXEL_DATA, VR::OW, PrimitiveValue::U16(px.into()));
    common::write_part10(
        obj,
        uids::EXPLICIT_VR_LITTLE_ENDIAN,
        uids::MR_IMAGE_STORAGE,
        &sop_uid,
        path,
    );
}

/// A multi-phase DICOM series (two slices at each of three positions, told apart by
/// TemporalPositionIdentifier, TriggerTime or AcquisitionNumber) imports both phases as
/// frames in phase order, each with its own voxels, on phase 1's grid.
#[test]
fn a_multi_phase_dicom_series_imports_each_phase_as_a_frame() {
    use dicom_dictionary_std::tags;
    let dir = tempfile::tempdir().unwrap();
    for (n, tag) in [
        tags::TEMPORAL_POSITION_IDENTIFIER,
        tags::TRIGGER_TIME,
        tags::ACQUISITION_NUMBER,
    ]
    .into_iter()
    .enumerate()
    {
        let series = dir.path().join(format!("series-{n}"));
        std::fs::create_dir(&series).unwrap();
        // Files named so that their order says nothing: phase 1's last slice first.
        for (name, z, phase) in [
            ("a.dcm", 4.0, 1),
            ("b.dcm", 0.0, 0),
            ("c.dcm", 2.0, 1),
            ("d.dcm", 4.0, 0),
            ("e.dcm", 0.0, 1),
            ("f.dcm", 2.0, 0),
        ] {
            write_phase_slice(&series.join(name), z, phase, tag);
        }
        let opened = open_source(&series, &ReadOptions::default()).unwrap();
        assert_eq!(opened.info.frames, 2, "{tag:?}");
        assert_eq!(opened.info.geometry.dims, [3, 2, 3]);
        assert_eq!(opened.info.geometry.spacing_mm, [0.25, 0.5, 2.0]);
        let store_path = dir.path().join(format!("series-{n}.strata"));
        import_source(opened, &store_path, &ImportOptions::default()).unwrap();
        let store = Store::open(&store_path).unwrap();
        assert_eq!(store.frame_count(), 2);
        let payload = BRICK_PAYLOAD as usize;
        let a = BRICK_APRON as usize;
        for phase in 0..2usize {
            let brick = store
                .read_frame_brick(phase as u32, BrickId::new(0, [0, 0, 0]))
                .unwrap();
            for k in 0..3 {
                for j in 0..2 {
                    for i in 0..3 {
                        let stored = brick[(i + a) + payload * ((j + a) + payload * (k + a))];
                        let want = 1000 * phase + 10 * (2 * k) + (3 * j + i);
                        assert_eq!(
                            store.header().value_mapping.physical(stored),
                            want as f64,
                            "{tag:?} phase {phase} voxel ({i},{j},{k})"
                        );
                    }
                }
            }
        }
    }
}

/// Every brick of every level of `store`'s octree.
fn all_ids(store: &Store) -> Vec<BrickId> {
    common::all_brick_ids(store)
}

/// Every frame of `a` holds the same records and skeleton as the same frame of `b`.
fn assert_same_frames(a: &Store, b: &Store, what: &str) {
    assert_eq!(a.frame_count(), b.frame_count(), "{what}");
    assert_eq!(a.header().stored_range, b.header().stored_range, "{what}");
    for f in 0..a.frame_count() {
        assert_eq!(
            a.frame_skeleton(f),
            b.frame_skeleton(f),
            "{what}: frame {f}"
        );
        for id in all_ids(a) {
            assert_eq!(
                a.read_frame_brick_record(f, id).unwrap(),
                b.read_frame_brick_record(f, id).unwrap(),
                "{what}: frame {f} {id:?}"
            );
        }
    }
}

/// Issue 48: a 4-D source imports to format 3 (frames in the packs, their skeletons in the
/// index) reading every frame record for record as its format-2 import does; `store upgrade`
/// of the 4-D format-2 store equals the fresh format-3 import; a new version of a frame-0
/// brick and a compaction keep every frame.
#[test]
fn a_4d_store_in_format_3_reads_each_frame_as_format_2_and_upgrade_edit_and_compaction_keep_them() {
    use strata_storage::brick::{encode_brick, value_range, BrickCodec};
    use strata_storage::import::import_source_as_format;
    use strata_storage::store::{append_brick_versions, compact_store, upgrade_store};
    let dir = tempfile::tempdir().unwrap();
    let source = dir.path().join("series.nii");
    write_nifti(&source, false);
    let open = || open_source(&source, &ReadOptions::default()).unwrap();
    let v3 = dir.path().join("v3.strata");
    let v2 = dir.path().join("v2.strata");
    import_source(open(), &v3, &ImportOptions::default()).unwrap();
    import_source_as_format(open(), &v2, &ImportOptions::default(), 2).unwrap();
    {
        let (a, b) = (Store::open(&v3).unwrap(), Store::open(&v2).unwrap());
        assert_eq!((a.format_version(), b.format_version()), (3, 2));
        assert_eq!(a.frame_count(), DIMS[3] as u32);
        assert!(a.verify(|_, _| {}).unwrap().is_empty());
        assert_same_frames(&a, &b, "v3 against v2");
    }
    let names = |dir: &Path| -> Vec<String> {
        let mut n: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        n.sort();
        n
    };
    assert_eq!(names(dir.path()), ["series.nii", "v2.strata", "v3.strata"]);

    let report = upgrade_store(&v2).unwrap();
    assert!(report.problems.is_empty(), "{:?}", report.problems);
    assert_eq!(names(dir.path()), ["series.nii", "v2.strata", "v3.strata"]);
    let upgraded = Store::open(&v2).unwrap();
    assert_eq!(upgraded.format_version(), 3);
    assert_same_frames(
        &upgraded,
        &Store::open(&v3).unwrap(),
        "upgraded against fresh",
    );
    drop(upgraded);

    // A new version of frame 0's level-0 brick (the same voxels in another codec).
    let id = BrickId::new(0, [0, 0, 0]);
    let before = Store::open(&v3).unwrap();
    let voxels = before.read_brick(id).unwrap();
    let record = encode_brick(id, &voxels, value_range(&voxels), false, BrickCodec::Lz4);
    assert_ne!(record, before.read_brick_record(id).unwrap());
    append_brick_versions(&v3, &[(id, record.clone())]).unwrap();
    let edited = Store::open(&v3).unwrap();
    assert_eq!(edited.frame_count(), DIMS[3] as u32);
    assert_eq!(edited.brick_version(id), Some(2));
    assert_eq!(edited.read_brick_record(id).unwrap(), record);
    for f in 1..DIMS[3] as u32 {
        assert_eq!(
            edited.frame_skeleton(f),
            before.frame_skeleton(f),
            "frame {f}"
        );
        assert_eq!(
            edited.read_frame_brick(f, id).unwrap(),
            before.read_frame_brick(f, id).unwrap(),
            "frame {f}"
        );
    }
    assert!(edited.verify(|_, _| {}).unwrap().is_empty());
    drop((before, edited));

    let compacted = compact_store(&v3).unwrap();
    assert!(compacted.bytes_after < compacted.bytes_before);
    let store = Store::open(&v3).unwrap();
    assert_eq!(store.brick_version(id), Some(2));
    assert_eq!(store.read_brick_record(id).unwrap(), record);
    assert!(store.verify(|_, _| {}).unwrap().is_empty());
    let reference = Store::open(&v2).unwrap();
    for f in 1..DIMS[3] as u32 {
        for id in all_ids(&store) {
            assert_eq!(
                store.read_frame_brick_record(f, id).unwrap(),
                reference.read_frame_brick_record(f, id).unwrap(),
                "compacted frame {f} {id:?}"
            );
        }
    }
}
