//! FreeSurfer MGH/MGZ against nibabel: files written by nibabel in the test (every data type,
//! oblique and flipped axes, .mgh and .mgz, 4-D), voxels compared exactly and geometry in
//! patient space (nibabel's RAS affine converted to LPS). Without nibabel these tests FAIL with
//! the install command, as CI installs it (.ci/run).

use std::io::Write;
use std::path::Path;

use crate::common;
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::{OpenedSource, SampleType};

const INSTALL: &str = "pip install nibabel numpy (CI: .ci/run)";

fn python(code: &str) -> String {
    common::python(code, INSTALL)
}

fn all_values(src: &OpenedSource) -> Vec<f64> {
    common::all_values(src)
}

/// Writes `name` with nibabel (dims, numpy dtype, a rotation about an oblique axis plus one
/// flipped axis, anisotropic voxels, an off-centre position), and returns nibabel's own reading
/// of it: the voxels of the first frame (i fastest) and the 4×4 RAS affine, row by row.
fn write_with_nibabel(path: &Path, dims: &str, dtype: &str) -> (Vec<f64>, Vec<f64>) {
    let values = path.with_extension("values");
    let printed = python(&format!(
        r#"
import numpy as np, nibabel as nib
dims = {dims}
rng = np.random.default_rng(7)
info = np.iinfo('{dtype}') if np.dtype('{dtype}').kind in 'iu' else None
if info is None:
    data = rng.normal(0, 1000, dims).astype('{dtype}')
else:
    data = rng.integers(info.min, info.max, dims, endpoint=True).astype('{dtype}')
a, b = 0.3, -0.2
rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
m = rz @ rx @ np.diag([-0.9, 1.1, 2.5])
aff = np.eye(4); aff[:3, :3] = m; aff[:3, 3] = [12.5, -30.25, 7.0]
nib.save(nib.MGHImage(data, aff), r'{path}')
img = nib.load(r'{path}')
d = np.asanyarray(img.dataobj)
if d.ndim == 4: d = d[..., 0]
np.asarray(d, '<f8').ravel(order='F').tofile(r'{values}')
print(' '.join(repr(float(x)) for x in img.affine.ravel()))
"#,
        path = path.display(),
        values = values.display()
    ));
    let affine: Vec<f64> = printed
        .split_whitespace()
        .map(|t| t.parse().unwrap())
        .collect();
    assert_eq!(affine.len(), 16, "{printed}");
    let voxels = std::fs::read(&values)
        .unwrap()
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
        .collect();
    (voxels, affine)
}

/// Strata's geometry must be nibabel's affine in LPS: index axis a's LPS vector is column a of
/// the affine with x and y negated, the origin the translation column likewise.
fn assert_geometry_matches(s: &OpenedSource, affine: &[f64], what: &str) {
    let g = &s.info.geometry;
    // nibabel multiplies the float32 header fields (Mdc · voxel size) in float32, Strata in
    // float64: they agree to float32 precision (~6e-8 relative), so 1e-6 relative.
    let tol = 1e-6;
    let flip = [-1.0, -1.0, 1.0];
    for a in 0..3 {
        for c in 0..3 {
            let lps = flip[c] * affine[c * 4 + a];
            let ours = g.direction[a][c] * g.spacing_mm[a];
            assert!(
                (lps - ours).abs() <= tol * lps.abs().max(1.0),
                "{what}: axis {a} component {c}: nibabel {lps}, strata {ours} ({g:?})"
            );
        }
    }
    for c in 0..3 {
        let lps = flip[c] * affine[c * 4 + 3];
        let ours = g.origin_lps_mm[c];
        assert!(
            (lps - ours).abs() <= tol * lps.abs().max(1.0),
            "{what}: origin component {c}: nibabel {lps}, strata {ours}"
        );
    }
}

#[test]
fn mgh_and_mgz_of_every_type_match_nibabel_in_voxels_and_patient_space() {
    let t = tempfile::tempdir().unwrap();
    for (name, dtype, expect) in [
        ("u8.mgz", "uint8", SampleType::U8),
        ("i16.mgh", "int16", SampleType::I16),
        ("i32.mgz", "int32", SampleType::I32),
        ("f32.mgh", "float32", SampleType::F32),
        ("f32.mgz", "float32", SampleType::F32),
    ] {
        let p = t.path().join(name);
        let (voxels, affine) = write_with_nibabel(&p, "(7, 5, 4)", dtype);
        let s = open_source(&p, &ReadOptions::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(s.info.sample_type, expect, "{name}");
        assert_eq!(s.data.dims, [7, 5, 4], "{name}");
        assert_eq!(s.info.format, &name[name.len() - 3..], "{name}");
        assert_eq!(
            all_values(&s),
            voxels,
            "{name}: voxels differ from nibabel's"
        );
        assert_geometry_matches(&s, &affine, name);
    }
}

#[test]
fn four_dimensional_mgz_reads_its_first_frame() {
    let t = tempfile::tempdir().unwrap();
    let p = t.path().join("series.mgz");
    let (voxels, affine) = write_with_nibabel(&p, "(6, 5, 3, 4)", "int16");
    let s = open_source(&p, &ReadOptions::default()).unwrap();
    assert_eq!(s.data.dims, [6, 5, 3]);
    assert_eq!(all_values(&s), voxels);
    assert_geometry_matches(&s, &affine, "series.mgz");
    assert!(
        s.info.description.contains("first of 4 frames"),
        "{}",
        s.info.description
    );
}

/// A minimal MGH written byte by byte (big-endian), for the cases nibabel does not write.
fn mgh_bytes(dims: [i32; 4], kind: i32, good_ras: i16, data: &[u8]) -> Vec<u8> {
    let mut h = Vec::new();
    for v in [1, dims[0], dims[1], dims[2], dims[3], kind, 0] {
        h.extend_from_slice(&i32::to_be_bytes(v));
    }
    h.extend_from_slice(&good_ras.to_be_bytes());
    let floats = [
        2.0f32, 3.0, 4.0, // voxel size
        1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, // Mdc (RAS axes)
        10.0, 20.0, 30.0, // centre
    ];
    for f in floats {
        h.extend_from_slice(&f.to_be_bytes());
    }
    h.resize(284, 0);
    h.extend_from_slice(data);
    h
}

#[test]
fn mgh_without_ras_information_uses_freesurfers_default_and_says_so() {
    let t = tempfile::tempdir().unwrap();
    let p = t.path().join("noras.mgh");
    std::fs::write(&p, mgh_bytes([2, 2, 2, 1], 0, 0, &[1, 2, 3, 4, 5, 6, 7, 8])).unwrap();
    let s = open_source(&p, &ReadOptions::default()).unwrap();
    let g = &s.info.geometry;
    assert_eq!(g.spacing_mm, [1.0, 1.0, 1.0]);
    // LIA in RAS is x → -R (= +L), y → -S, z → +A (= -P) in LPS.
    assert_eq!(
        g.direction,
        [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]]
    );
    assert!(
        s.info.description.contains("goodRASflag 0"),
        "{}",
        s.info.description
    );
    assert_eq!(all_values(&s), [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]);

    // With the flag: centre (10, 20, 30) RAS minus half the extent along each axis.
    std::fs::write(&p, mgh_bytes([2, 2, 2, 1], 0, 1, &[0; 8])).unwrap();
    let s = open_source(&p, &ReadOptions::default()).unwrap();
    let g = &s.info.geometry;
    assert_eq!(g.spacing_mm, [2.0, 3.0, 4.0]);
    assert_eq!(g.origin_lps_mm, [-(10.0 - 2.0), -(20.0 - 3.0), 30.0 - 4.0]);
}

#[test]
fn bad_mgh_headers_fail_naming_the_file() {
    let t = tempfile::tempdir().unwrap();
    let check = |name: &str, bytes: Vec<u8>, expect: &str| {
        let p = t.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        let e = match open_source(&p, &ReadOptions::default()) {
            Ok(_) => panic!("{name} opened"),
            Err(e) => e.to_string(),
        };
        assert!(e.contains(name) && e.contains(expect), "{name}: {e}");
    };
    let good = mgh_bytes([2, 2, 2, 1], 0, 1, &[0; 8]);
    let mut bad_version = good.clone();
    bad_version[3] = 2;
    check("version.mgh", bad_version, "version 2");
    check(
        "type.mgh",
        mgh_bytes([2, 2, 2, 1], 2, 1, &[0; 64]),
        "data type 2",
    );
    check(
        "zero.mgh",
        mgh_bytes([2, 0, 2, 1], 0, 1, &[]),
        "height is 0",
    );
    check(
        "neg.mgh",
        mgh_bytes([2, 2, -5, 1], 0, 1, &[]),
        "depth is -5",
    );
    check(
        "short.mgh",
        mgh_bytes([2, 2, 2, 1], 0, 1, &[0; 7]),
        "truncated",
    );
    check(
        "frames.mgh",
        mgh_bytes([2, 2, 2, 3], 0, 1, &[0; 16]),
        "truncated",
    );
    check("header.mgh", good[..50].to_vec(), "truncated");
    // A header claiming 2^31 · 2^31 · 2^31 voxels allocates nothing: refused from the header.
    let huge = mgh_bytes([i32::MAX, i32::MAX, i32::MAX, 1], 3, 1, &[]);
    check("huge.mgh", huge.clone(), "");
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    gz.write_all(&huge).unwrap();
    check("huge.mgz", gz.finish().unwrap(), "");
    let mut zero_size = good.clone();
    zero_size[30..34].copy_from_slice(&0f32.to_be_bytes());
    check("size.mgh", zero_size, "voxel sizes");
}

/// A real scan (chris_t1, see shared/data/SOURCES.md) converted to MGZ by nibabel opens with the
/// same voxels and the same patient-space geometry as the NIfTI it came from (the NIfTI reader
/// agrees with SimpleITK and nibabel). Skipped when the data folder is absent.
#[test]
fn real_scan_as_mgz_matches_its_nifti() {
    let nii =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/niivue/chris_t1.nii.gz");
    if !nii.is_file() {
        eprintln!("SKIP: real test data not found at {}", nii.display());
        return;
    }
    let t = tempfile::tempdir().unwrap();
    let mgz = t.path().join("chris_t1.mgz");
    python(&format!(
        "import nibabel as nib, numpy as np; i = nib.load(r'{}'); d = np.asanyarray(i.dataobj); t = d.dtype if d.dtype in (np.uint8, np.int16, np.int32, np.float32) else np.float32; nib.save(nib.MGHImage(d.astype(t), i.affine), r'{}')",
        nii.display(),
        mgz.display()
    ));
    let a = open_source(&nii, &ReadOptions::default()).unwrap();
    let b = open_source(&mgz, &ReadOptions::default()).unwrap();
    assert_eq!(a.data.dims, b.data.dims);
    let (ga, gb) = (&a.info.geometry, &b.info.geometry);
    // MGH stores float32 directions, sizes and centre: agreement to float32 precision.
    for axis in 0..3 {
        for c in 0..3 {
            let (x, y) = (
                ga.direction[axis][c] * ga.spacing_mm[axis],
                gb.direction[axis][c] * gb.spacing_mm[axis],
            );
            assert!((x - y).abs() < 1e-5, "axis {axis}: {ga:?} vs {gb:?}");
        }
        assert!(
            (ga.origin_lps_mm[axis] - gb.origin_lps_mm[axis]).abs() < 1e-3,
            "origin: {ga:?} vs {gb:?}"
        );
    }
    let scale = |s: &OpenedSource| -> Vec<f64> {
        all_values(s)
            .iter()
            .map(|v| v * s.info.slope + s.info.intercept)
            .collect()
    };
    assert_eq!(scale(&a), scale(&b));
}
