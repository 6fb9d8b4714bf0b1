//! Real scans from ../shared/data (skipped with a printed reason when absent): each imports into
//! a store whose level 0 equals the source voxel for voxel (in physical units), whose coarser
//! levels and aprons follow the octree definition, and whose geometry puts the patient where
//! the source says.

use std::path::{Path, PathBuf};

use strata_e2e::{check_store_against, shared_data, VoxelReader};
use strata_storage::import::{import_source, ImportOptions};
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::Store;

fn import(input: &Path, dir: &Path) -> Store {
    let opened = open_source(input, &ReadOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    let store_path = dir.join(format!(
        "{}.strata",
        input.file_name().unwrap().to_string_lossy()
    ));
    import_source(opened, &store_path, &ImportOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    Store::open(&store_path).unwrap()
}

/// Level 0 of the store equals the source in physical units (exactly for integer sources;
/// within the recorded quantisation error otherwise), then the whole octree is checked.
fn round_trip(input: &Path) {
    let dir = tempfile::tempdir().unwrap();
    let store = import(input, dir.path());
    let opened = open_source(input, &ReadOptions::default()).unwrap();
    let h = store.header().clone();
    assert_eq!(h.geometry, opened.info.geometry, "{}", input.display());
    let [nx, ny, nz] = h.geometry.dims_u64();
    let tolerance = h.quantization_error * (1.0 + 1e-9) + 1e-9;
    let mut reader = VoxelReader::new(&store);
    let mut slice = Vec::new();
    let mut level0 = Vec::with_capacity((nx * ny * nz) as usize);
    for k in 0..nz {
        opened.data.read_slice_f64(k, &mut slice);
        for j in 0..ny {
            for i in 0..nx {
                let source =
                    opened.info.slope * slice[(i + nx * j) as usize] + opened.info.intercept;
                let stored = reader.stored([i, j, k]);
                let physical = h.value_mapping.physical(stored);
                assert!(
                    (physical - source).abs() <= tolerance * source.abs().max(1.0),
                    "{}: voxel ({i},{j},{k}) stored {physical}, source {source}",
                    input.display()
                );
                level0.push(stored);
            }
        }
    }
    check_store_against(&store, level0);
    assert!(store.verify(|_, _| {}).unwrap().is_empty());
}

#[test]
fn every_real_file_round_trips() {
    let Some(data) = shared_data("every_real_file_round_trips") else {
        return;
    };
    let n = data.join("niivue");
    for file in [
        "FLAIR.nrrd",
        "mha.mha",
        "chris_t1.nii.gz",
        "enh.dcm",
        "dicom-mr-3slices",
        "nifti_space/RAS.nii.gz",
    ] {
        let path = n.join(file);
        if !path.exists() {
            // nifti_space names are checked by the orientation test; take any one of them here.
            continue;
        }
        round_trip(&path);
    }
    let any_space = first_nifti_space(&n);
    round_trip(&any_space[0]);
}

fn first_nifti_space(niivue: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(niivue.join("nifti_space"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.to_string_lossy().ends_with(".nii.gz") || p.to_string_lossy().ends_with(".nii")
        })
        .collect();
    files.sort();
    files
}

/// The 48 axis orders and flips of one brain describe the same image in patient space: the
/// value at each voxel centre of the first file, looked up by patient position in every other
/// file's store, is identical.
#[test]
fn nifti_axis_orders_agree_in_patient_space() {
    let Some(data) = shared_data("nifti_axis_orders_agree_in_patient_space") else {
        return;
    };
    let files = first_nifti_space(&data.join("niivue"));
    assert_eq!(files.len(), 48, "expected the 48 orientations");
    let dir = tempfile::tempdir().unwrap();
    let stores: Vec<Store> = files.iter().map(|f| import(f, dir.path())).collect();
    let reference = &stores[0];
    let g0 = reference.header().geometry.clone();
    let mut readers: Vec<VoxelReader> = stores.iter().map(VoxelReader::new).collect();
    let mut compared = 0;
    let [nx, ny, nz] = g0.dims_u64();
    for k in (0..nz).step_by(3) {
        for j in (0..ny).step_by(3) {
            for i in (0..nx).step_by(2) {
                let p = g0.patient_from_index([i as f64, j as f64, k as f64]);
                let want = readers[0].physical([i, j, k]);
                for (f, reader) in readers.iter_mut().enumerate().skip(1) {
                    let g = &stores[f].header().geometry;
                    let idx = g.index_from_patient(p);
                    let rounded = idx.round().to_array();
                    for a in 0..3 {
                        assert!(
                            (idx[a] - rounded[a]).abs() < 1e-3,
                            "{}: voxel centres do not line up: {idx:?}",
                            files[f].display()
                        );
                        assert!(
                            rounded[a] >= 0.0 && (rounded[a] as u64) < u64::from(g.dims[a]),
                            "{}: point outside",
                            files[f].display()
                        );
                    }
                    let got = reader.physical(rounded.map(|v| v as u64));
                    assert_eq!(
                        got,
                        want,
                        "{} differs from {} at patient {p:?}",
                        files[f].display(),
                        files[0].display()
                    );
                    compared += 1;
                }
            }
        }
    }
    assert!(compared > 100_000, "compared {compared}");
}

#[test]
fn headers_keep_geometry_through_the_store() {
    let Some(data) = shared_data("headers_keep_geometry_through_the_store") else {
        return;
    };
    let n = data.join("niivue");
    let dir = tempfile::tempdir().unwrap();

    let flair = import(&n.join("FLAIR.nrrd"), dir.path());
    let g = &flair.header().geometry;
    assert_eq!(g.dims, [124, 160, 140]);
    let off_axis = g
        .direction
        .iter()
        .flatten()
        .filter(|v| v.abs() > 1e-3 && (v.abs() - 1.0).abs() > 1e-3)
        .count();
    assert!(
        off_axis >= 2,
        "FLAIR's oblique directions were lost: {:?}",
        g.direction
    );

    let mha = import(&n.join("mha.mha"), dir.path());
    let g = &mha.header().geometry;
    assert_eq!(g.dims, [64, 64, 37]);
    for (a, s) in [3.4375, 3.4375, 3.8].iter().enumerate() {
        assert!(
            (g.spacing_mm[a] - s).abs() < 1e-6,
            "spacing {:?}",
            g.spacing_mm
        );
    }
    assert!(
        g.direction.iter().any(|d| d.iter().any(|&v| v < -0.5)),
        "mha's flipped axis lost: {:?}",
        g.direction
    );

    let dicom = import(&n.join("dicom-mr-3slices"), dir.path());
    let g = &dicom.header().geometry;
    assert_eq!(g.dims, [512, 512, 3]);
    assert!(
        (g.spacing_mm[2] - 1.5).abs() < 1e-3,
        "slice spacing from positions: {:?}",
        g.spacing_mm
    );

    let enh = import(&n.join("enh.dcm"), dir.path());
    assert_eq!(enh.header().geometry.dims[2], 6, "enhanced DICOM frames");
}
