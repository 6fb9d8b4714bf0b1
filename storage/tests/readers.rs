//! Format readers against real public scans (skipped with a message when absent) and against
//! small corrupt files written on the fly.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::common;
use strata_storage::readers::{open_source, RawSpec, ReadOptions};
use strata_storage::{ByteOrder, OpenedSource, SampleType};

fn data_dir() -> Option<PathBuf> {
    let d = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/niivue");
    if d.is_dir() {
        Some(d)
    } else {
        eprintln!(
            "SKIP: real test data not found at {} (see shared/data/SOURCES.md)",
            d.display()
        );
        None
    }
}

fn open(p: &Path) -> OpenedSource {
    open_source(p, &ReadOptions::default()).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

fn err_of(p: &Path, options: &ReadOptions) -> String {
    match open_source(p, options) {
        Ok(_) => panic!("{} opened although it is invalid", p.display()),
        Err(e) => e.to_string(),
    }
}

/// Every voxel value of the volume, i fastest.
fn all_values(src: &OpenedSource) -> Vec<f64> {
    common::all_values(src)
}

#[test]
fn flair_nrrd_keeps_oblique_directions() {
    let Some(d) = data_dir() else { return };
    let s = open(&d.join("FLAIR.nrrd"));
    let g = &s.info.geometry;
    assert_eq!(g.dims, [124, 160, 140]);
    assert_eq!(s.info.sample_type, SampleType::U8);
    assert_eq!(s.info.format, "nrrd");
    // space is LPS, so the header's first direction vector is kept as written.
    assert!(
        close(g.direction[0][0], -0.993592, 1e-5),
        "{:?}",
        g.direction
    );
    assert!(
        close(g.direction[0][1], 0.049705, 1e-5),
        "{:?}",
        g.direction
    );
    assert!(
        close(g.direction[2][1], -0.305367, 1e-5),
        "{:?}",
        g.direction
    );
    assert!(
        g.direction
            .iter()
            .flatten()
            .filter(|v| v.abs() > 1e-3 && v.abs() < 0.999)
            .count()
            >= 6
    );
    assert!(close(g.origin_lps_mm[0], 64.898239, 1e-4));
    assert!(close(g.spacing_mm[0], 1.0, 1e-3), "{:?}", g.spacing_mm);
    let v = all_values(&s);
    assert_eq!(v.len(), 124 * 160 * 140);
    assert!(v.iter().any(|&x| x > 0.0));
}

#[test]
fn mha_has_flipped_axis_and_anisotropic_spacing() {
    let Some(d) = data_dir() else { return };
    let s = open(&d.join("mha.mha"));
    let g = &s.info.geometry;
    assert_eq!(g.dims, [64, 64, 37]);
    assert_eq!(s.info.sample_type, SampleType::I16);
    assert!(
        close(g.spacing_mm[0], 3.4375, 1e-6)
            && close(g.spacing_mm[1], 3.4375, 1e-6)
            && close(g.spacing_mm[2], 3.8, 1e-6)
    );
    assert_eq!(g.direction[0], [1.0, 0.0, 0.0]);
    assert_eq!(g.direction[1], [0.0, -1.0, 0.0]);
    assert_eq!(g.direction[2], [0.0, 0.0, 1.0]);
    assert!(close(g.origin_lps_mm[0], -108.281, 1e-6));
    assert!(all_values(&s).iter().any(|&x| x != 0.0));
}

#[test]
fn dicom_three_slice_series() {
    let Some(d) = data_dir() else { return };
    let s = open(&d.join("dicom-mr-3slices"));
    let g = &s.info.geometry;
    assert_eq!(g.dims, [512, 512, 3]);
    assert!(close(g.spacing_mm[2], 1.5, 1e-3), "{:?}", g.spacing_mm);
    assert!(
        close(g.spacing_mm[0], 0.41, 0.005) && close(g.spacing_mm[1], 0.41, 0.005),
        "{:?}",
        g.spacing_mm
    );
    assert_eq!(s.info.modality, "MR");
    assert!(matches!(
        s.info.sample_type,
        SampleType::U16 | SampleType::I16
    ));
    let listing = strata_storage::readers::list_dicom_series(&d.join("dicom-mr-3slices")).unwrap();
    assert_eq!(listing.len(), 1);
    assert_eq!(listing[0].slice_count, 3);
    assert_eq!(listing[0].description, s.info.description);
    // The slice axis must be the orientation's normal, increasing with k.
    let n = g.direction[2];
    let r = g.direction[0];
    let c = g.direction[1];
    let cr = [
        r[1] * c[2] - r[2] * c[1],
        r[2] * c[0] - r[0] * c[2],
        r[0] * c[1] - r[1] * c[0],
    ];
    assert!(close(n[0] * cr[0] + n[1] * cr[1] + n[2] * cr[2], 1.0, 1e-4));
    // Single files of the same series open on their own, and the middle one is the middle slice.
    let one = open(&d.join("dicom-mr-3slices/1-002.dcm"));
    assert_eq!(one.info.geometry.dims, [512, 512, 1]);
    let mut a = Vec::new();
    let mut b = Vec::new();
    one.data.read_slice_f64(0, &mut a);
    let sorted_mid = (0..3)
        .find(|&k| {
            s.data.read_slice_f64(k, &mut b);
            a == b
        })
        .expect("slice of 1-002.dcm not found in the series");
    let p = one.info.geometry.origin_lps_mm;
    let q = s
        .info
        .geometry
        .patient_from_index([0.0, 0.0, sorted_mid as f64]);
    assert!((0..3).all(|i| close(p[i], q[i], 1e-3)), "{p:?} vs {q:?}");
    assert!(a.iter().any(|&x| x != 0.0));
}

#[test]
fn enhanced_multiframe_dicom() {
    let Some(d) = data_dir() else { return };
    let s = open(&d.join("enh.dcm"));
    let g = &s.info.geometry;
    assert_eq!(g.dims, [64, 64, 6]);
    // Per-frame PlanePositionSequence: z from -5.40356 in steps of 2.4 mm.
    assert!(close(g.spacing_mm[2], 2.4, 1e-4), "{:?}", g.spacing_mm);
    assert!(close(g.spacing_mm[0], 3.375, 1e-6), "{:?}", g.spacing_mm);
    assert!(
        close(g.origin_lps_mm[2], -5.40356, 1e-5) && close(g.origin_lps_mm[0], -109.79, 1e-5),
        "{:?}",
        g.origin_lps_mm
    );
    assert_eq!(s.info.modality, "MR");
    assert!(all_values(&s).iter().any(|&x| x != 0.0));
}

#[test]
fn chris_t1_nifti_gz() {
    let Some(d) = data_dir() else { return };
    let s = open(&d.join("chris_t1.nii.gz"));
    let g = &s.info.geometry;
    assert_eq!(g.dims, [188, 256, 190]);
    assert_eq!(s.info.sample_type, SampleType::U8);
    assert_eq!(s.info.format, "nifti-1");
    for sp in g.spacing_mm {
        assert!(close(sp, 0.88, 0.01), "{:?}", g.spacing_mm);
    }
    assert!(all_values(&s).iter().any(|&x| x > 0.0));
}

/// All 48 axis orders/flips of the same brain map to the same voxel values in patient space.
#[test]
fn nifti_space_files_agree_in_patient_space() {
    let Some(d) = data_dir() else { return };
    let mut files: Vec<PathBuf> = std::fs::read_dir(d.join("nifti_space"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.to_string_lossy().ends_with(".nii.gz"))
        .collect();
    files.sort();
    assert_eq!(files.len(), 48);
    let reference = open(&files[0]);
    let rg = reference.info.geometry.clone();
    let rv = all_values(&reference);
    assert!(rv.iter().any(|&x| x > 0.0));
    // Every 3rd voxel centre of the reference, as patient points.
    let mut points = Vec::new();
    for k in (0..rg.dims[2]).step_by(3) {
        for j in (0..rg.dims[1]).step_by(3) {
            for i in (0..rg.dims[0]).step_by(3) {
                let idx = (i + rg.dims[0] * (j + rg.dims[1] * k)) as usize;
                points.push((
                    rg.patient_from_index([i as f64, j as f64, k as f64]),
                    rv[idx],
                ));
            }
        }
    }
    for f in &files[1..] {
        let s = open(f);
        let g = &s.info.geometry;
        assert_eq!(g.voxel_count(), rg.voxel_count(), "{}", f.display());
        let v = all_values(&s);
        let dims = g.dims_u64();
        let mut mismatches = 0;
        for (p, expected) in &points {
            let idx = g.index_from_patient(*p);
            let r: Vec<i64> = idx.to_array().iter().map(|x| x.round() as i64).collect();
            assert!(
                (0..3).all(|a| r[a] >= 0
                    && (r[a] as u64) < dims[a]
                    && (idx[a] - r[a] as f64).abs() < 1e-3),
                "{}: point {p:?} lands at index {idx:?}",
                f.display()
            );
            let lin = (r[0] as u64 + dims[0] * (r[1] as u64 + dims[1] * r[2] as u64)) as usize;
            if v[lin] != *expected {
                mismatches += 1;
            }
        }
        assert_eq!(
            mismatches,
            0,
            "{}: {mismatches} of {} patient points differ",
            f.display(),
            points.len()
        );
    }
}

// ---------------------------------------------------------------- synthetic files

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::File::create(&p).unwrap().write_all(bytes).unwrap();
    p
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// A minimal little-endian NIfTI-1 header (sform in RAS with the given srow).
fn nifti1_header(dims: [i16; 3], datatype: i16, bitpix: i16, srow: [[f32; 4]; 3]) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    let dim = [3i16, dims[0], dims[1], dims[2], 1, 1, 1, 1];
    for (i, d) in dim.iter().enumerate() {
        h[40 + 2 * i..42 + 2 * i].copy_from_slice(&d.to_le_bytes());
    }
    h[70..72].copy_from_slice(&datatype.to_le_bytes());
    h[72..74].copy_from_slice(&bitpix.to_le_bytes());
    let pixdim = [1f32, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0];
    for (i, p) in pixdim.iter().enumerate() {
        h[76 + 4 * i..80 + 4 * i].copy_from_slice(&p.to_le_bytes());
    }
    h[108..112].copy_from_slice(&352f32.to_le_bytes());
    h[254..256].copy_from_slice(&1i16.to_le_bytes());
    for (r, row) in srow.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            h[280 + 16 * r + 4 * c..284 + 16 * r + 4 * c].copy_from_slice(&v.to_le_bytes());
        }
    }
    h[344..348].copy_from_slice(b"n+1\0");
    h
}

const RAS_2MM: [[f32; 4]; 3] = [
    [2.0, 0.0, 0.0, 10.0],
    [0.0, 2.0, 0.0, 20.0],
    [0.0, 0.0, 2.0, 30.0],
];

#[test]
fn synthetic_nifti_sform_converts_ras_to_lps_and_maps_data() {
    let t = tempfile::tempdir().unwrap();
    let mut bytes = nifti1_header([4, 3, 2], 512, 16, RAS_2MM);
    for v in 0u16..24 {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    let p = write(t.path(), "a.nii", &bytes);
    let s = open(&p);
    let g = &s.info.geometry;
    assert_eq!(g.dims, [4, 3, 2]);
    assert_eq!(s.info.sample_type, SampleType::U16);
    assert_eq!(g.spacing_mm, [2.0, 2.0, 2.0]);
    assert_eq!(g.origin_lps_mm, [-10.0, -20.0, 30.0]);
    assert_eq!(
        g.direction,
        [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
    );
    let mut v = Vec::new();
    s.data.read_slice_f64(1, &mut v);
    assert_eq!(v, (12..24).map(|x| x as f64).collect::<Vec<_>>());
    // The gzipped twin gives the same voxels through staging.
    let pz = write(t.path(), "a.nii.gz", &gzip(&bytes));
    let sz = open(&pz);
    assert_eq!(all_values(&sz), all_values(&s));
    assert_eq!(sz.info.geometry, s.info.geometry);

    // Staging goes to the requested folder and is removed with the volume.
    let stage = tempfile::tempdir().unwrap();
    let opts = ReadOptions {
        staging_dir: Some(stage.path().to_path_buf()),
        ..Default::default()
    };
    let staged = open_source(&pz, &opts).unwrap();
    assert_eq!(std::fs::read_dir(stage.path()).unwrap().count(), 1);
    drop(staged);
    assert_eq!(std::fs::read_dir(stage.path()).unwrap().count(), 0);
}

#[test]
fn synthetic_nifti_qform_matches_equivalent_sform() {
    let t = tempfile::tempdir().unwrap();
    // qform: 180° about z (b=c=0, d=1) → x and y flipped in RAS, i.e. identity in LPS.
    let mut h = nifti1_header([2, 2, 2], 2, 8, RAS_2MM);
    h[254..256].copy_from_slice(&0i16.to_le_bytes());
    h[252..254].copy_from_slice(&1i16.to_le_bytes());
    h[264..268].copy_from_slice(&1f32.to_le_bytes());
    h[268..272].copy_from_slice(&5f32.to_le_bytes());
    for i in 1..4 {
        h[76 + 4 * i..80 + 4 * i].copy_from_slice(&1.5f32.to_le_bytes());
    }
    h.extend_from_slice(&[0u8; 8]);
    let s = open(&write(t.path(), "q.nii", &h));
    let g = &s.info.geometry;
    for a in 0..3 {
        for c in 0..3 {
            let expected = if a == c { 1.0 } else { 0.0 };
            assert!(
                close(g.direction[a][c], expected, 1e-6),
                "{:?}",
                g.direction
            );
        }
    }
    assert_eq!(g.spacing_mm, [1.5, 1.5, 1.5]);
    assert!(close(g.origin_lps_mm[0], -5.0, 1e-6));

    // 90° about x (b = sin 45°) with qfac = −1: in RAS i → +x, j → +z, k → −(−y) = +y.
    let h45 = std::f32::consts::FRAC_1_SQRT_2;
    h[256..260].copy_from_slice(&h45.to_le_bytes());
    h[264..268].copy_from_slice(&0f32.to_le_bytes());
    h[76..80].copy_from_slice(&(-1f32).to_le_bytes());
    let s = open(&write(t.path(), "q2.nii", &h));
    let expected = [[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]];
    let got = s.info.geometry.direction;
    assert!(
        got.iter()
            .flatten()
            .zip(expected.iter().flatten())
            .all(|(g, e)| close(*g, *e, 1e-6)),
        "{got:?}"
    );
}

#[test]
fn synthetic_nrrd_detached_and_ras() {
    let t = tempfile::tempdir().unwrap();
    write(t.path(), "vol.raw", &(0u8..24).collect::<Vec<_>>());
    let hdr = "NRRD0004\ntype: uint8\ndimension: 3\nspace: right-anterior-superior\nsizes: 4 3 2\n\
space directions: (0,0,-2) (0,1.5,0) (3,0,0)\nspace origin: (1,2,3)\nencoding: raw\ndata file: vol.raw\n";
    let p = write(t.path(), "vol.nhdr", hdr.as_bytes());
    let s = open(&p);
    let g = &s.info.geometry;
    assert_eq!(g.spacing_mm, [2.0, 1.5, 3.0]);
    assert_eq!(
        g.direction,
        [[-0.0, -0.0, -1.0], [-0.0, -1.0, 0.0], [-1.0, -0.0, 0.0]]
    );
    assert_eq!(g.origin_lps_mm, [-1.0, -2.0, 3.0]);
    assert_eq!(
        all_values(&s),
        (0..24).map(|x| x as f64).collect::<Vec<_>>()
    );

    // Attached, gzip, big-endian shorts, spacings only.
    let mut body = Vec::new();
    for v in 0i16..8 {
        body.extend_from_slice(&(v - 4).to_be_bytes());
    }
    let mut f =
        b"NRRD0004\ntype: short\ndimension: 3\nsizes: 2 2 2\nspacings: 1 -2 0.5\nendian: big\nencoding: gzip\n\n"
            .to_vec();
    f.extend_from_slice(&gzip(&body));
    let s = open(&write(t.path(), "b.nrrd", &f));
    assert_eq!(s.info.geometry.spacing_mm, [1.0, 2.0, 0.5]);
    assert_eq!(s.info.geometry.direction[1], [0.0, -1.0, 0.0]);
    assert_eq!(
        all_values(&s),
        (-4..4).map(|x| x as f64).collect::<Vec<_>>()
    );

    // Detached data behind two text lines and a byte skip; and data at the end (byte skip -1).
    let mut data = b"line one\nline two\n???".to_vec();
    data.extend(0u8..8);
    write(t.path(), "skip.dat", &data);
    let h = "NRRD0005\r\ntype: uchar\r\ndimension: 3\r\nsizes: 2 2 2\r\nencoding: raw\r\nline skip: 2\r\nbyte skip: 3\r\ndata file: skip.dat\r\n";
    let s = open(&write(t.path(), "skip.nhdr", h.as_bytes()));
    assert_eq!(all_values(&s), (0..8).map(|x| x as f64).collect::<Vec<_>>());
    let h = "NRRD0005\ntype: uchar\ndimension: 3\nsizes: 2 2 2\nencoding: raw\nbyte skip: -1\ndata file: skip.dat\n";
    let s = open(&write(t.path(), "end.nhdr", h.as_bytes()));
    assert_eq!(all_values(&s), (0..8).map(|x| x as f64).collect::<Vec<_>>());

    // ascii encoding, staged as little-endian samples; too few values is an error.
    let f =
        "NRRD0004\ntype: float\ndimension: 3\nsizes: 2 2 1\nencoding: ascii\n\n1.5 -2\n3e2,\t4\n";
    let s = open(&write(t.path(), "text.nrrd", f.as_bytes()));
    assert_eq!(all_values(&s), vec![1.5, -2.0, 300.0, 4.0]);
    let f = "NRRD0004\ntype: float\ndimension: 3\nsizes: 2 2 2\nencoding: ascii\n\n1 2 3\n";
    let e = err_of(
        &write(t.path(), "short.nrrd", f.as_bytes()),
        &ReadOptions::default(),
    );
    assert!(e.contains("short.nrrd") && e.contains("truncated"), "{e}");
}

#[test]
fn synthetic_metaimage_mhd_and_compressed_mha() {
    let t = tempfile::tempdir().unwrap();
    let mut body = Vec::new();
    for v in 0u16..8 {
        body.extend_from_slice(&(v * 100).to_le_bytes());
    }
    write(t.path(), "v.raw", &body);
    let hdr = "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementType = MET_USHORT\nElementSpacing = 0.5 0.5 2\n\
Offset = 1 2 3\nTransformMatrix = 0 1 0 -1 0 0 0 0 1\nElementDataFile = v.raw\n";
    let s = open(&write(t.path(), "v.mhd", hdr.as_bytes()));
    let g = &s.info.geometry;
    assert_eq!(
        g.direction,
        [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    );
    assert_eq!(g.origin_lps_mm, [1.0, 2.0, 3.0]);
    assert_eq!(all_values(&s)[7], 700.0);

    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
    z.write_all(&body).unwrap();
    let mut f = b"ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementType = MET_USHORT\nCompressedData = True\nElementDataFile = LOCAL\n".to_vec();
    f.extend_from_slice(&z.finish().unwrap());
    let s2 = open(&write(t.path(), "v.mha", &f));
    assert_eq!(all_values(&s2), all_values(&s));
}

#[test]
fn raw_with_spec() {
    let t = tempfile::tempdir().unwrap();
    let mut bytes = vec![9u8; 16];
    for v in 0i16..24 {
        bytes.extend_from_slice(&v.to_be_bytes());
    }
    let p = write(t.path(), "x.vol", &bytes);
    let spec = RawSpec {
        dims: [4, 3, 2],
        sample_type: SampleType::I16,
        spacing_mm: [1.0, 1.0, 2.5],
        byte_order: ByteOrder::Big,
        header_bytes: 16,
    };
    let opts = ReadOptions {
        raw: Some(spec.clone()),
        ..Default::default()
    };
    let s = open_source(&p, &opts).unwrap();
    assert_eq!(
        all_values(&s),
        (0..24).map(|x| x as f64).collect::<Vec<_>>()
    );
    let bad = ReadOptions {
        raw: Some(RawSpec {
            dims: [4, 3, 3],
            ..spec
        }),
        ..Default::default()
    };
    let e = err_of(&p, &bad);
    assert!(
        e.contains("x.vol") && e.contains("size mismatch") && e.contains("88") && e.contains("64"),
        "{e}"
    );
}

#[test]
fn bad_inputs_fail_with_file_and_reason() {
    let t = tempfile::tempdir().unwrap();
    let d = t.path();
    let o = ReadOptions::default();
    let check = |p: &Path, needle: &str| {
        let e = err_of(p, &o);
        let name = p.file_name().unwrap().to_string_lossy().to_string();
        assert!(e.contains(&name), "error does not name {name}: {e}");
        assert!(
            e.to_lowercase().contains(&needle.to_lowercase()),
            "error for {name} lacks '{needle}': {e}"
        );
    };

    // NIfTI: truncated data, truncated gzip data, unknown type, zero and absurd dims, NaN spacing.
    let mut good = nifti1_header([4, 4, 4], 2, 8, RAS_2MM);
    good.extend_from_slice(&[1u8; 64]);
    check(&write(d, "trunc.nii", &good[..352 + 30]), "truncated");
    check(
        &write(d, "trunc.nii.gz", &gzip(&good[..352 + 30])),
        "truncated",
    );
    let mut gz = gzip(&good);
    gz.truncate(gz.len() - 20);
    check(&write(d, "cut.nii.gz", &gz), "truncated");
    // Cut inside the voxel stream of a larger, incompressible volume.
    let mut big = nifti1_header([32, 32, 32], 2, 8, RAS_2MM);
    let mut x = 12345u32;
    big.extend((0..32 * 32 * 32).map(|_| {
        x = x.wrapping_mul(1664525).wrapping_add(1013904223);
        (x >> 24) as u8
    }));
    let gz = gzip(&big);
    check(
        &write(d, "cutdata.nii.gz", &gz[..gz.len() / 2]),
        "truncated or corrupt after",
    );
    check(&write(d, "short.nii", &good[..200]), "header");
    let mut unk = good.clone();
    unk[70..72].copy_from_slice(&32i16.to_le_bytes());
    check(&write(d, "complex.nii", &unk), "datatype 32");
    let mut magic = good.clone();
    magic[344..348].copy_from_slice(b"xyz\0");
    check(&write(d, "magic.nii", &magic), "magic");
    let mut zero = good.clone();
    zero[44..46].copy_from_slice(&0i16.to_le_bytes());
    check(&write(d, "zero.nii", &zero), "zero dimension");
    let mut huge = nifti1_header([32000, 32000, 32000], 2, 8, RAS_2MM);
    huge.extend_from_slice(&[0u8; 64]);
    check(&write(d, "huge.nii", &huge), "absurd");
    let nan = RAS_2MM.map(|r| r.map(|_| f32::NAN));
    let mut nanf = nifti1_header([4, 4, 4], 2, 8, nan);
    nanf.extend_from_slice(&[1u8; 64]);
    assert!(err_of(&write(d, "nan.nii", &nanf), &o).contains("nan.nii"));

    // NRRD: NaN spacing, unknown type, size mismatch with detached data, truncated gzip.
    let nrrd = |body: &str| format!("NRRD0004\ndimension: 3\nencoding: raw\n{body}\n\n");
    let mut f = nrrd("type: uint8\nsizes: 2 2 2\nspacings: nan 1 1").into_bytes();
    f.extend_from_slice(&[0u8; 8]);
    check(&write(d, "nan.nrrd", &f), "nan");
    let mut f = nrrd("type: quaternion\nsizes: 2 2 2").into_bytes();
    f.extend_from_slice(&[0u8; 8]);
    check(&write(d, "type.nrrd", &f), "quaternion");
    write(d, "small.raw", &[0u8; 7]);
    let h =
        "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\ndata file: small.raw\n";
    let e = err_of(&write(d, "mismatch.nhdr", h.as_bytes()), &o);
    assert!(e.contains("small.raw") && e.contains("truncated"), "{e}");
    let mut f = nrrd("type: uint8\nsizes: 3 2 2\nkinds: RGB-color domain domain").into_bytes();
    f.extend_from_slice(&[0u8; 12]);
    check(&write(d, "rgb.nrrd", &f), "RGB-color");
    let mut f = nrrd("type: uint8\nsizes: 0 2 2").into_bytes();
    f.extend_from_slice(&[0u8; 8]);
    check(&write(d, "zero.nrrd", &f), "zero");
    let mut f =
        b"NRRD0004\ntype: uint16\ndimension: 3\nsizes: 8 8 8\nendian: little\nencoding: gzip\n\n"
            .to_vec();
    f.extend_from_slice(&gzip(&[0u8; 100]));
    check(&write(d, "short.nrrd", &f), "truncated");

    // MetaImage: unknown type, size mismatch.
    let m = "NDims = 3\nDimSize = 4 4 4\nElementType = MET_FANCY\nElementDataFile = LOCAL\n";
    check(&write(d, "type.mha", m.as_bytes()), "MET_FANCY");
    let mut m =
        b"NDims = 3\nDimSize = 4 4 4\nElementType = MET_SHORT\nElementDataFile = LOCAL\n".to_vec();
    m.extend_from_slice(&[0u8; 100]);
    check(&write(d, "trunc.mha", &m), "truncated");
    let m = "NDims = 3\nDimSize = 4 4 4\nElementSpacing = 1 NaN 1\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n";
    let mut mb = m.as_bytes().to_vec();
    mb.extend_from_slice(&[0u8; 64]);
    check(&write(d, "nan.mha", &mb), "spacing");

    // Missing paths, unknown extension.
    check(&d.join("missing.nii"), "does not exist");
    check(&d.join("missing_dir"), "does not exist");
    check(&write(d, "data.xyz", &[0u8; 10]), "supported");

    // DICOM: folder without images, non-image DICOM file.
    let empty = d.join("no_images");
    std::fs::create_dir(&empty).unwrap();
    write(&empty, "readme.txt", b"hello");
    check(&empty, "no DICOM");
    let fake = write(d, "fake.dcm", &[0u8; 300]);
    assert!(err_of(&fake, &o).contains("fake.dcm"));
}

/// Builds a minimal DICOM file in memory via dicom-object.
fn write_dicom(
    path: &Path,
    series_uid: &str,
    description: &str,
    z: f64,
    with_pixels: bool,
    slope: f64,
) {
    write_dicom_at(
        path,
        series_uid,
        description,
        [0.0, 0.0, z],
        with_pixels,
        slope,
    )
}

fn write_dicom_at(
    path: &Path,
    series_uid: &str,
    description: &str,
    pos: [f64; 3],
    with_pixels: bool,
    slope: f64,
) {
    let z = pos[2];
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::{tags, uids};
    use dicom_object::InMemDicomObject;
    let sop_uid = format!("1.2.3.{}", (z * 10.0) as i64 + 100);
    let mut obj = InMemDicomObject::new_empty();
    let mut put = |tag, vr, v: PrimitiveValue| obj.put(DataElement::new(tag, vr, v));
    put(tags::SOP_CLASS_UID, VR::UI, uids::MR_IMAGE_STORAGE.into());
    put(tags::SOP_INSTANCE_UID, VR::UI, sop_uid.clone().into());
    put(tags::MODALITY, VR::CS, "MR".into());
    put(tags::PATIENT_NAME, VR::PN, "Secret^Person".into());
    put(tags::SERIES_INSTANCE_UID, VR::UI, series_uid.into());
    put(tags::SERIES_DESCRIPTION, VR::LO, description.into());
    if with_pixels {
        put(
            tags::IMAGE_POSITION_PATIENT,
            VR::DS,
            format!("{}\\{}\\{z}", pos[0], pos[1]).into(),
        );
        put(
            tags::IMAGE_ORIENTATION_PATIENT,
            VR::DS,
            "1\\0\\0\\0\\1\\0".into(),
        );
        put(tags::PIXEL_SPACING, VR::DS, "0.5\\0.25".into());
        common::put_grey_pixel_module(&mut put, [2, 3], 12, true);
        put(tags::RESCALE_SLOPE, VR::DS, format!("{slope}").into());
        put(tags::RESCALE_INTERCEPT, VR::DS, "-10".into());
        put(tags::WINDOW_CENTER, VR::DS, "40\\400".into());
        put(tags::WINDOW_WIDTH, VR::DS, "80\\2000".into());
        // 12 bits stored, two's complement, with a stray bit above them (as overlays leave).
        let px: Vec<u16> = (0..6)
            .map(|i| ((z as i16 * 10 + i as i16 - 3) as u16) & 0x0fff | 0x2000)
            .collect();
        put(tags::PIXEL_DATA, VR::OW, PrimitiveValue::U16(px.into()));
    }
    common::write_part10(
        obj,
        uids::EXPLICIT_VR_LITTLE_ENDIAN,
        uids::MR_IMAGE_STORAGE,
        &sop_uid,
        path,
    );
}

#[test]
fn synthetic_dicom_series_sorting_selection_and_errors() {
    let t = tempfile::tempdir().unwrap();
    let d = t.path().join("series");
    std::fs::create_dir(&d).unwrap();
    // Written out of order; file names do not follow position.
    for (name, z) in [("a.dcm", 4.0), ("b.dcm", 0.0), ("c.dcm", 2.0)] {
        write_dicom(&d.join(name), "1.2.840.1", "Axial T1", z, true, 1.0);
    }
    write(&d, "notes.txt", b"not dicom");
    let s = open(&d);
    let g = &s.info.geometry;
    assert_eq!(g.dims, [3, 2, 3]);
    assert_eq!(g.spacing_mm, [0.25, 0.5, 2.0]);
    assert_eq!(g.origin_lps_mm, [0.0, 0.0, 0.0]);
    assert_eq!(s.info.sample_type, SampleType::I16);
    assert!(!s.info.description.contains("Secret"));
    let mut v = Vec::new();
    s.data.read_slice_f64(0, &mut v);
    assert_eq!(
        v,
        vec![-3.0, -2.0, -1.0, 0.0, 1.0, 2.0],
        "12-bit signed values must be sign-extended"
    );
    s.data.read_slice_f64(2, &mut v);
    assert_eq!(v[3], 40.0);
    assert_eq!((s.info.slope, s.info.intercept), (1.0, -10.0));
    assert_eq!(s.info.windows.len(), 2);
    assert_eq!(
        (s.info.windows[1].center, s.info.windows[1].width),
        (400.0, 2000.0)
    );

    // Per-slice rescale: stored as physical f32 values with an identity mapping.
    write_dicom(&d.join("a.dcm"), "1.2.840.1", "Axial T1", 4.0, true, 2.0);
    let s = open(&d);
    assert_eq!(s.info.sample_type, SampleType::F32);
    assert_eq!((s.info.slope, s.info.intercept), (1.0, 0.0));
    s.data.read_slice_f64(0, &mut v);
    assert_eq!(v[0], -13.0);
    s.data.read_slice_f64(2, &mut v);
    assert_eq!(v[3], 2.0 * 40.0 - 10.0);
    write_dicom(&d.join("a.dcm"), "1.2.840.1", "Axial T1", 4.0, true, 1.0);

    // Two slices at one position: several stacks, not a volume.
    write_dicom(
        &d.join("dup.dcm"),
        "1.2.840.1",
        "Axial T1",
        2.00001,
        true,
        1.0,
    );
    let e = err_of(&d, &ReadOptions::default());
    assert!(e.contains("same position") && e.contains("dup.dcm"), "{e}");
    std::fs::remove_file(d.join("dup.dcm")).unwrap();

    // Without the 128-byte preamble (and without an extension) the file is still DICOM.
    let bytes = std::fs::read(d.join("b.dcm")).unwrap();
    let nopre = write(t.path(), "nopreamble", &bytes[128..]);
    let one = open(&nopre);
    assert_eq!(one.info.geometry.dims, [3, 2, 1]);
    assert_eq!(all_values(&one), vec![-3.0, -2.0, -1.0, 0.0, 1.0, 2.0]);

    // A gap: remove the middle slice and add one further away.
    write_dicom(&d.join("d.dcm"), "1.2.840.1", "Axial T1", 10.0, true, 1.0);
    let e = err_of(&d, &ReadOptions::default());
    assert!(
        e.contains("series") && e.contains("non-uniform") && e.contains("6.0000"),
        "{e}"
    );
    std::fs::remove_file(d.join("d.dcm")).unwrap();

    // Evenly spaced along the normal but shifted in-plane: not one block.
    write_dicom_at(
        &d.join("c.dcm"),
        "1.2.840.1",
        "Axial T1",
        [5.0, 0.0, 2.0],
        true,
        1.0,
    );
    let e = err_of(&d, &ReadOptions::default());
    assert!(e.contains("off the line") && e.contains("c.dcm"), "{e}");
    write_dicom(&d.join("c.dcm"), "1.2.840.1", "Axial T1", 2.0, true, 1.0);

    // A second series: listed in the error, selectable by UID or index.
    write_dicom(&d.join("e.dcm"), "1.2.840.2", "Localizer", 0.0, true, 1.0);
    let e = err_of(&d, &ReadOptions::default());
    assert!(
        e.contains("1.2.840.1")
            && e.contains("1.2.840.2")
            && e.contains("Localizer")
            && e.contains("3 slices"),
        "{e}"
    );
    let by_uid = ReadOptions {
        dicom_series: Some("1.2.840.2".into()),
        ..Default::default()
    };
    assert_eq!(
        open_source(&d, &by_uid).unwrap().info.geometry.dims,
        [3, 2, 1]
    );
    let listing = strata_storage::readers::list_dicom_series(&d).unwrap();
    let idx = listing.iter().position(|s| s.uid == "1.2.840.1").unwrap();
    let by_idx = ReadOptions {
        dicom_series: Some(idx.to_string()),
        ..Default::default()
    };
    assert_eq!(
        open_source(&d, &by_idx).unwrap().info.geometry.dims,
        [3, 2, 3]
    );
    let e = err_of(
        &d,
        &ReadOptions {
            dicom_series: Some("7".into()),
            ..Default::default()
        },
    );
    assert!(e.contains("no DICOM series '7'"), "{e}");

    // Gantry tilt: positions step along a line that is not the slice normal. Voxel (0,0,k) must
    // still land on slice k's ImagePositionPatient.
    let tilt = t.path().join("tilt");
    std::fs::create_dir(&tilt).unwrap();
    let positions: Vec<[f64; 3]> = (0..4)
        .map(|k| [0.0, 0.5 * k as f64, 2.0 * k as f64])
        .collect();
    for (k, p) in positions.iter().enumerate() {
        write_dicom_at(
            &tilt.join(format!("{}.dcm", 3 - k)),
            "1.2.840.9",
            "tilted",
            *p,
            true,
            1.0,
        );
    }
    let s = open(&tilt);
    for (k, p) in positions.iter().enumerate() {
        let q = s.info.geometry.patient_from_index([0.0, 0.0, k as f64]);
        assert!(
            (0..3).all(|c| close(p[c], q[c], 1e-9)),
            "slice {k}: {q:?} vs {p:?}"
        );
    }

    // Non-image DICOM: a file alone errors; a folder of only such files errors.
    let ni = t.path().join("noimg");
    std::fs::create_dir(&ni).unwrap();
    write_dicom(&ni.join("sr.dcm"), "1.2.840.3", "report", 0.0, false, 1.0);
    let e = err_of(&ni.join("sr.dcm"), &ReadOptions::default());
    assert!(e.contains("sr.dcm") && e.contains("no image"), "{e}");
    let e = err_of(&ni, &ReadOptions::default());
    assert!(
        e.contains("noimg") && e.contains("none of the 1 DICOM files"),
        "{e}"
    );
}

/// NIfTI-2, big-endian, with an sform rotated 90° about z, and a 4-D series (first volume read).
#[test]
fn synthetic_nifti2_big_endian_4d() {
    let t = tempfile::tempdir().unwrap();
    let mut h = vec![0u8; 544];
    h[0..4].copy_from_slice(&540i32.to_be_bytes());
    h[4..12].copy_from_slice(b"n+2\0\r\n\x1a\n");
    h[12..14].copy_from_slice(&4i16.to_be_bytes()); // int16
    h[14..16].copy_from_slice(&16i16.to_be_bytes());
    for (i, d) in [4i64, 4, 3, 2, 2, 1, 1, 1].iter().enumerate() {
        h[16 + 8 * i..24 + 8 * i].copy_from_slice(&d.to_be_bytes());
    }
    h[168..176].copy_from_slice(&544i64.to_be_bytes());
    h[176..184].copy_from_slice(&2f64.to_be_bytes()); // slope
    h[184..192].copy_from_slice(&(-1f64).to_be_bytes());
    h[348..352].copy_from_slice(&2i32.to_be_bytes()); // sform_code
                                                      // RAS: i → +y (anterior), j → −x (right), k → +z; 1, 2, 3 mm.
    let srow = [
        [0.0, -2.0, 0.0, 5.0],
        [1.0, 0.0, 0.0, 6.0],
        [0.0, 0.0, 3.0, 7.0],
    ];
    for (r, row) in srow.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            h[400 + 32 * r + 8 * c..408 + 32 * r + 8 * c].copy_from_slice(&f64::to_be_bytes(*v));
        }
    }
    for v in 0i16..48 {
        h.extend_from_slice(&(v - 24).to_be_bytes());
    }
    let s = open(&write(t.path(), "n2.nii", &h));
    let g = &s.info.geometry;
    assert_eq!(s.info.format, "nifti-2");
    assert_eq!(g.dims, [4, 3, 2]);
    assert_eq!(g.spacing_mm, [1.0, 2.0, 3.0]);
    assert_eq!(
        g.direction,
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    );
    assert_eq!(g.origin_lps_mm, [-5.0, -6.0, 7.0]);
    assert_eq!((s.info.slope, s.info.intercept), (2.0, -1.0));
    // Both time points, one after the other (each a frame of the store: storage/tests/frames.rs).
    assert_eq!(s.info.frames, 2);
    assert_eq!(
        all_values(&s),
        (-24..24).map(|x| x as f64).collect::<Vec<_>>()
    );

    // The same header as a .hdr/.img pair (magic ni2, data from offset 0 of the .img).
    let mut hdr = h[..540].to_vec();
    hdr[4..12].copy_from_slice(b"ni2\0\r\n\x1a\n");
    hdr[168..176].copy_from_slice(&0i64.to_be_bytes());
    write(t.path(), "pair.img", &h[544..]);
    let p = open(&write(t.path(), "pair.hdr", &hdr));
    assert_eq!(all_values(&p), all_values(&s));
    std::fs::remove_file(t.path().join("pair.img")).unwrap();
    let e = err_of(&t.path().join("pair.hdr"), &ReadOptions::default());
    assert!(e.contains("pair.hdr") && e.contains("pair.img"), "{e}");
}

/// RLE Lossless (an encapsulated transfer syntax) decodes through dicom-pixeldata, 16-bit.
#[test]
fn synthetic_dicom_rle_lossless() {
    use dicom_core::value::PixelFragmentSequence;
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::{tags, uids};
    use dicom_object::InMemDicomObject;
    let t = tempfile::tempdir().unwrap();
    let values: [u16; 6] = [0, 1, 300, 65535, 4096, 7];
    // RLE: one segment per byte plane, most significant first; each a literal run of 6 bytes.
    let mut frag = vec![0u8; 64];
    frag[0..4].copy_from_slice(&2u32.to_le_bytes());
    frag[4..8].copy_from_slice(&64u32.to_le_bytes());
    frag[8..12].copy_from_slice(&72u32.to_le_bytes());
    for shift in [8, 0] {
        frag.push(5);
        frag.extend(values.iter().map(|v| (v >> shift) as u8));
        frag.push(0); // pad the segment to even length
    }
    let mut obj = InMemDicomObject::new_empty();
    let mut put = |tag, vr, v: PrimitiveValue| obj.put(DataElement::new(tag, vr, v));
    put(tags::SOP_CLASS_UID, VR::UI, uids::CT_IMAGE_STORAGE.into());
    put(tags::SOP_INSTANCE_UID, VR::UI, "1.2.3.4".into());
    put(tags::MODALITY, VR::CS, "CT".into());
    put(tags::SERIES_INSTANCE_UID, VR::UI, "1.2.3".into());
    common::put_grey_pixel_module(&mut put, [2, 3], 16, false);
    obj.put(DataElement::new(
        tags::PIXEL_DATA,
        VR::OB,
        PixelFragmentSequence::new(Vec::<u32>::new(), vec![frag]),
    ));
    let p = t.path().join("rle.dcm");
    common::write_part10(
        obj,
        uids::RLE_LOSSLESS,
        uids::CT_IMAGE_STORAGE,
        "1.2.3.4",
        &p,
    );
    let s = open(&p);
    assert_eq!(s.info.sample_type, SampleType::U16);
    assert_eq!(
        all_values(&s),
        values.iter().map(|&v| v as f64).collect::<Vec<_>>()
    );
}

/// A one-slice DICOM (the series writer's) changed by `edit`, written with transfer syntax
/// `ts` (its pixels stay uncompressed).
fn edited_dicom(
    dir: &Path,
    name: &str,
    ts: &str,
    edit: impl FnOnce(&mut dicom_object::InMemDicomObject),
) -> PathBuf {
    use dicom_dictionary_std::uids;
    let base = dir.join(format!("{name}.base"));
    write_dicom(&base, "1.2.3", "edited", 0.0, true, 1.0);
    let mut obj = dicom_object::open_file(&base).unwrap().into_inner();
    std::fs::remove_file(&base).unwrap();
    edit(&mut obj);
    let p = dir.join(format!("{name}.dcm"));
    common::write_part10(obj, ts, uids::MR_IMAGE_STORAGE, "1.2.3.100", &p);
    p
}

/// Issue 38, finding 8: header values a scanner cannot mean. A stated PixelSpacing of 0, -1,
/// NaN or 1e309 becomes 1 mm with a warning (in the description, where the import prints it
/// from); PixelRepresentation 255, a compressed transfer syntax over uncompressed pixels, and
/// MetaImage spacing ≤ 0 / not finite or several channels are refused naming the file. Before
/// the fix all of these opened silently.
#[test]
fn header_values_no_scanner_means_are_warned_or_refused() {
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::{tags, uids};
    let t = tempfile::tempdir().unwrap();
    let d = t.path();
    for (n, spacing) in ["0\\0", "-1\\-1", "NaN\\NaN", "1e309\\1e309"]
        .iter()
        .enumerate()
    {
        let p = edited_dicom(
            d,
            &format!("spacing{n}"),
            uids::EXPLICIT_VR_LITTLE_ENDIAN,
            |o| {
                o.put(DataElement::new(
                    tags::PIXEL_SPACING,
                    VR::DS,
                    PrimitiveValue::from(*spacing),
                ));
            },
        );
        let s = open(&p);
        let warnings = s.info.warnings();
        assert!(
            warnings
                .iter()
                .any(|w| w.contains("PixelSpacing") && w.contains("1 mm")),
            "PixelSpacing {spacing}: no warning in {:?}",
            s.info.description
        );
        assert_eq!(s.info.geometry.spacing_mm[0], 1.0, "PixelSpacing {spacing}");
    }
    let good = open(&edited_dicom(
        d,
        "good",
        uids::EXPLICIT_VR_LITTLE_ENDIAN,
        |_| {},
    ));
    assert!(
        good.info.warnings().is_empty(),
        "{:?}",
        good.info.description
    );

    let p = edited_dicom(d, "pixrep", uids::EXPLICIT_VR_LITTLE_ENDIAN, |o| {
        o.put(DataElement::new(
            tags::PIXEL_REPRESENTATION,
            VR::US,
            PrimitiveValue::from(255u16),
        ));
    });
    let e = err_of(&p, &ReadOptions::default());
    assert!(
        e.contains("pixrep.dcm") && e.contains("PixelRepresentation 255"),
        "{e}"
    );

    for (name, ts) in [
        ("jpeg", uids::JPEG_BASELINE8_BIT),
        ("j2k", uids::JPEG2000_LOSSLESS),
        ("rle", uids::RLE_LOSSLESS),
        ("htj2k", uids::HTJ2K_LOSSLESS),
        ("jpegls", uids::JPEGLS_LOSSLESS),
    ] {
        let p = edited_dicom(d, name, ts, |_| {});
        let e = err_of(&p, &ReadOptions::default());
        assert!(
            e.contains(&format!("{name}.dcm")) && e.contains("uncompressed"),
            "{name}: {e}"
        );
    }

    let mut body = Vec::new();
    for v in 0u16..8 {
        body.extend_from_slice(&v.to_le_bytes());
    }
    write(d, "m.raw", &body);
    for (n, line) in [
        "ElementSpacing = -1 1 1",
        "ElementSpacing = 0 1 1",
        "ElementSpacing = 1 nan 1",
        "ElementSpacing = 1 1 inf",
        "ElementNumberOfChannels = 3",
    ]
    .iter()
    .enumerate()
    {
        let hdr = format!(
            "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementType = MET_USHORT\n{line}\nElementDataFile = m.raw\n"
        );
        let p = write(d, &format!("m{n}.mhd"), hdr.as_bytes());
        let e = err_of(&p, &ReadOptions::default());
        assert!(e.contains(&format!("m{n}.mhd")), "{line}: {e}");
    }
}
