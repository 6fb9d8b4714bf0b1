//! DICOM as PACS export it: compressed transfer syntaxes (JPEG extended 12-bit, JPEG 2000,
//! JPEG-LS) checked against pydicom's bundled test files and pydicom's own decode (pylibjpeg
//! plugins), RT Dose frame spacing and dose scaling, and unusable PixelSpacing.
//!
//! The reference files are pydicom's test files: those bundled in its wheel and those of the
//! `pydicom-data` package (PyPI), both found offline by `pydicom.data.get_testdata_file`.
//! Without them these tests FAIL with the install command, as CI installs them (.ci/run).

use std::path::{Path, PathBuf};

use crate::common;
use strata_storage::import::{import_source, ImportOptions};
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::{OpenedSource, SampleType, Store};

const INSTALL: &str = "pip install pydicom pydicom-data pylibjpeg pylibjpeg-libjpeg pylibjpeg-openjpeg numpy (CI: .ci/run)";

/// Runs a python snippet and returns its stdout; fails the test with the install hint when
/// python or pydicom is missing.
fn python(code: &str) -> String {
    common::python(code, INSTALL)
}

/// The path of one of pydicom's test files (its own or pydicom-data's).
fn pydicom_file(name: &str) -> PathBuf {
    pydicom_files(&[name]).remove(0)
}

/// Paths of several of pydicom's test files, looked up in one python run (each run costs
/// seconds on a loaded machine).
fn pydicom_files(names: &[&str]) -> Vec<PathBuf> {
    let printed = python(&format!(
        "from pydicom.data import get_testdata_file\nfor n in {names:?}: print(get_testdata_file(n) or '-')"
    ));
    let paths: Vec<PathBuf> = printed.lines().map(PathBuf::from).collect();
    assert_eq!(paths.len(), names.len(), "{printed}");
    for (p, name) in paths.iter().zip(names) {
        assert!(
            p.is_file(),
            "pydicom test file {name} not found offline: {INSTALL}"
        );
    }
    paths
}

/// pydicom's decode of `path` (all frames, i fastest), through its pylibjpeg plugins.
fn pydicom_pixels(path: &Path) -> Vec<f64> {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("pixels.f64");
    python(&format!(
        "import pydicom, numpy as np; ds = pydicom.dcmread(r'{}'); np.asarray(ds.pixel_array, '<f8').tofile(r'{}')",
        path.display(),
        out.display()
    ));
    std::fs::read(&out)
        .unwrap()
        .chunks_exact(8)
        .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
        .collect()
}

fn open(p: &Path) -> OpenedSource {
    open_source(p, &ReadOptions::default()).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// Stored samples, i fastest (the physical values divided back by slope/intercept would hide
/// nothing here: these files have slope 1, intercept 0 unless a test says otherwise).
fn all_values(src: &OpenedSource) -> Vec<f64> {
    common::all_values(src)
}

/// Imports into a store and returns the description `strata info` prints.
fn stored_description(src: OpenedSource) -> String {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("s.strata");
    import_source(src, &store, &ImportOptions::default()).unwrap();
    Store::open(&store).unwrap().header().description.clone()
}

#[test]
fn lossless_jpeg2000_and_jpegls_import_to_the_voxels_of_their_uncompressed_twin() {
    for (plain, twins) in [
        // MR 64x64, one frame.
        (
            "MR_small.dcm",
            &[
                "MR_small_jp2klossless.dcm",
                "MR_small_jpeg_ls_lossless.dcm",
                "MR_small_RLE.dcm",
            ][..],
        ),
        // Enhanced MR, 10 frames of 64x64: frames found per fragment.
        (
            "emri_small.dcm",
            &[
                "emri_small_jpeg_2k_lossless.dcm",
                "emri_small_jpeg_ls_lossless.dcm",
                "emri_small_RLE.dcm",
                // Only the pixel data's 8-byte sequence delimiter is missing at the end of the
                // file (pydicom refuses it): every fragment is whole, so are the voxels.
                "emri_small_jpeg_2k_lossless_too_short.dcm",
            ][..],
        ),
        // NEMA WG04: CT 512x512 (14 bits stored), JPEG 2000 reversible. (MR2_J2KR, 1024x1024,
        // also matches its MR2_UNCR twin, but takes ~20 s to decode in a debug test run.)
        ("693_UNCR.dcm", &["693_J2KR.dcm"][..]),
    ] {
        let mut paths = pydicom_files(&[&[plain][..], twins].concat());
        let plain_source = open(&paths.remove(0));
        let reference = all_values(&plain_source);
        assert!(
            reference.iter().any(|&v| v != reference[0]),
            "{plain} is flat"
        );
        for (twin, path) in twins.iter().zip(&paths) {
            let s = open(path);
            assert_eq!(s.info.sample_type, plain_source.info.sample_type, "{twin}");
            assert_eq!(s.info.geometry, plain_source.info.geometry, "{twin}");
            assert_eq!(
                all_values(&s),
                reference,
                "{twin}: voxels differ from {plain}"
            );
            assert!(
                !s.info.description.contains("lossy"),
                "{twin}: {}",
                s.info.description
            );
        }
    }
}

/// A JPEG 2000 codestream whose signedness disagrees with PixelRepresentation (pydicom's
/// J2K_pixelrep_mismatch.dcm, CT 512x512, 13 bits stored): pydicom follows the DICOM header.
#[test]
fn jpeg2000_with_signedness_mismatch_matches_pydicom() {
    let p = pydicom_file("J2K_pixelrep_mismatch.dcm");
    let s = open(&p);
    assert_eq!(s.info.sample_type, SampleType::I16);
    assert_eq!(all_values(&s), pydicom_pixels(&p));
}

#[test]
fn jpeg2000_lossy_matches_pydicom_and_says_lossy() {
    for name in ["JPEG2000.dcm", "693_J2KI.dcm"] {
        let p = pydicom_file(name);
        let s = open(&p);
        // Both decoders are OpenJPEG (openjp2 is its Rust port): the same samples exactly.
        assert_eq!(all_values(&s), pydicom_pixels(&p), "{name}");
        assert!(
            s.info.description.contains("lossy JPEG 2000 source"),
            "{name}: {}",
            s.info.description
        );
        if name == "JPEG2000.dcm" {
            assert_eq!(s.info.sample_type, SampleType::I16);
            let d = stored_description(s);
            assert!(d.contains("lossy JPEG 2000 source"), "store says: {d}");
        }
    }
}

#[test]
fn jpegls_near_lossless_matches_pydicom_and_says_lossy() {
    for name in ["JPEGLSNearLossless_16.dcm", "JPEGLSNearLossless_08.dcm"] {
        let p = pydicom_file(name);
        let s = open(&p);
        // JPEG-LS decoding is exact arithmetic: CharLS and pylibjpeg-libjpeg agree bit for bit.
        assert_eq!(all_values(&s), pydicom_pixels(&p), "{name}");
        assert!(
            s.info
                .description
                .contains("lossy JPEG-LS near-lossless source"),
            "{name}: {}",
            s.info.description
        );
    }
}

#[test]
fn jpeg_extended_12bit_matches_pydicom_and_says_lossy() {
    let p = pydicom_file("JPGExtended.dcm");
    let s = open(&p);
    assert_eq!(s.info.sample_type, SampleType::U16);
    assert_eq!(s.data.dims, [256, 1024, 1]);
    let ours = all_values(&s);
    let theirs = pydicom_pixels(&p);
    assert_eq!(ours.len(), theirs.len());
    // libjpeg-turbo and pydicom's libjpeg (Thomas Richter's) use different inverse DCTs, each
    // within the standard's accuracy (ISO 10918-2): rounding may differ by one step. Measured:
    // 3612 of 262144 samples (1.4 %) differ, none by more than 1. A real defect (wrong tables,
    // shifted blocks, 8-bit truncation) differs by far more, in far more samples.
    let differing = ours.iter().zip(&theirs).filter(|(a, b)| a != b).count();
    let worst = ours
        .iter()
        .zip(&theirs)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(worst <= 1.0, "largest difference to pydicom: {worst}");
    assert!(
        differing < ours.len() / 20,
        "{differing} of {} samples differ from pydicom",
        ours.len()
    );
    assert!(theirs.iter().any(|&v| v > 255.0), "not a >8-bit image");
    assert!(
        s.info
            .description
            .contains("lossy JPEG extended (12-bit) source"),
        "{}",
        s.info.description
    );
}

#[test]
fn rt_dose_frames_are_spaced_by_grid_frame_offsets_and_scaled_to_dose() {
    // pydicom's rtdose.dcm: 15 frames, GridFrameOffsetVector 0, 5, ..., 70, no SliceThickness
    // or SpacingBetweenSlices, DoseGridScaling 1e-6, DoseUnits RELATIVE.
    let p = pydicom_file("rtdose.dcm");
    let s = open(&p);
    let g = &s.info.geometry;
    assert_eq!(g.dims, [10, 10, 15]);
    assert_eq!(g.spacing_mm, [10.0, 10.0, 5.0]);
    assert_eq!(g.origin_lps_mm, [189.43125, 199.43125, -761.87]);
    assert!(
        (s.info.slope - 1e-6).abs() < 1e-18,
        "slope {}",
        s.info.slope
    );
    assert!(
        s.info.description.contains("dose in RELATIVE"),
        "{}",
        s.info.description
    );
    let stored = all_values(&s);
    assert_eq!(stored, pydicom_pixels(&p));
}

/// A classic multi-frame dose grid written here: `offsets` as GridFrameOffsetVector,
/// `between` as SpacingBetweenSlices.
fn synthetic_dose(path: &Path, offsets: Option<&str>, between: Option<&str>, pixel_spacing: &str) {
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::{tags, uids};
    use dicom_object::InMemDicomObject;
    let mut obj = InMemDicomObject::new_empty();
    let mut put = |tag, vr, v: PrimitiveValue| obj.put(DataElement::new(tag, vr, v));
    put(tags::SOP_CLASS_UID, VR::UI, uids::RT_DOSE_STORAGE.into());
    put(tags::SOP_INSTANCE_UID, VR::UI, "1.2.3.9".into());
    put(tags::MODALITY, VR::CS, "RTDOSE".into());
    put(tags::SERIES_INSTANCE_UID, VR::UI, "1.2.3".into());
    put(tags::IMAGE_POSITION_PATIENT, VR::DS, "-10\\-20\\30".into());
    put(
        tags::IMAGE_ORIENTATION_PATIENT,
        VR::DS,
        "1\\0\\0\\0\\1\\0".into(),
    );
    put(tags::PIXEL_SPACING, VR::DS, pixel_spacing.into());
    if let Some(o) = offsets {
        put(tags::GRID_FRAME_OFFSET_VECTOR, VR::DS, o.into());
    }
    if let Some(b) = between {
        put(tags::SPACING_BETWEEN_SLICES, VR::DS, b.into());
    }
    put(tags::NUMBER_OF_FRAMES, VR::IS, "3".into());
    put(tags::DOSE_GRID_SCALING, VR::DS, "0.001".into());
    put(tags::DOSE_UNITS, VR::CS, "GY".into());
    common::put_grey_pixel_module(&mut put, [2, 2], 16, false);
    let px: Vec<u16> = (0..12).map(|i| i * 1000).collect();
    put(tags::PIXEL_DATA, VR::OW, PrimitiveValue::U16(px.into()));
    common::write_part10(
        obj,
        uids::EXPLICIT_VR_LITTLE_ENDIAN,
        uids::RT_DOSE_STORAGE,
        "1.2.3.9",
        path,
    );
}

#[test]
fn rt_dose_spacing_comes_from_the_file_or_is_said_to_be_assumed() {
    let t = tempfile::tempdir().unwrap();
    let p = t.path().join("dose.dcm");

    // Absolute offsets (first entry not 0) and SpacingBetweenSlices disagreeing: the offsets win.
    synthetic_dose(&p, Some("30\\32.5\\35"), Some("9"), "4\\3");
    let s = open(&p);
    assert_eq!(s.info.geometry.spacing_mm, [3.0, 4.0, 2.5]);
    assert_eq!(s.info.geometry.origin_lps_mm, [-10.0, -20.0, 30.0]);
    assert!((s.info.slope - 0.001).abs() < 1e-15);
    assert!(
        s.info.description.contains("dose in GY"),
        "{}",
        s.info.description
    );
    assert!(
        !s.info.description.contains("assumed"),
        "{}",
        s.info.description
    );
    let dose: Vec<f64> = all_values(&s).iter().map(|v| v * s.info.slope).collect();
    assert!((dose[11] - 11.0).abs() < 1e-9, "{dose:?}");

    // No offsets: SpacingBetweenSlices.
    synthetic_dose(&p, None, Some("2"), "4\\3");
    let s = open(&p);
    assert_eq!(s.info.geometry.spacing_mm[2], 2.0);
    assert!(
        !s.info.description.contains("assumed"),
        "{}",
        s.info.description
    );

    // Neither: 1 mm, and the description (hence the store and `strata info`) says so.
    synthetic_dose(&p, None, None, "4\\3");
    let s = open(&p);
    assert_eq!(s.info.geometry.spacing_mm[2], 1.0);
    assert!(
        s.info.description.contains("1 mm apart assumed"),
        "{}",
        s.info.description
    );
    let d = stored_description(s);
    assert!(d.contains("1 mm apart assumed"), "store says: {d}");

    // Non-uniform offsets are not one regular volume.
    synthetic_dose(&p, Some("0\\5\\20"), None, "4\\3");
    let e = open_source(&p, &ReadOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("dose.dcm") && e.contains("non-uniform"), "{e}");
    // A vector that does not fit the frames is an error, not a guess.
    synthetic_dose(&p, Some("0\\5"), None, "4\\3");
    let e = open_source(&p, &ReadOptions::default())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("GridFrameOffsetVector has 2 entries"), "{e}");
}

/// A single-frame CR-like image with the given spacing attributes.
fn synthetic_cr(path: &Path, pixel_spacing: Option<&str>, imager: Option<&str>) {
    use dicom_core::{DataElement, PrimitiveValue, VR};
    use dicom_dictionary_std::{tags, uids};
    use dicom_object::InMemDicomObject;
    let mut obj = InMemDicomObject::new_empty();
    let mut put = |tag, vr, v: PrimitiveValue| obj.put(DataElement::new(tag, vr, v));
    put(
        tags::SOP_CLASS_UID,
        VR::UI,
        uids::COMPUTED_RADIOGRAPHY_IMAGE_STORAGE.into(),
    );
    put(tags::SOP_INSTANCE_UID, VR::UI, "1.2.3.7".into());
    put(tags::MODALITY, VR::CS, "CR".into());
    put(tags::SERIES_INSTANCE_UID, VR::UI, "1.2.3".into());
    if let Some(s) = pixel_spacing {
        put(tags::PIXEL_SPACING, VR::DS, s.into());
    }
    if let Some(s) = imager {
        put(tags::IMAGER_PIXEL_SPACING, VR::DS, s.into());
    }
    common::put_grey_pixel_module(&mut put, [2, 3], 12, false);
    let px: Vec<u16> = (0..6).map(|i| i * 100).collect();
    put(tags::PIXEL_DATA, VR::OW, PrimitiveValue::U16(px.into()));
    common::write_part10(
        obj,
        uids::EXPLICIT_VR_LITTLE_ENDIAN,
        uids::COMPUTED_RADIOGRAPHY_IMAGE_STORAGE,
        "1.2.3.7",
        path,
    );
}

#[test]
fn zero_pixel_spacing_is_treated_like_a_missing_one() {
    let t = tempfile::tempdir().unwrap();
    let p = t.path().join("cr.dcm");
    for ps in [Some("0\\0"), None] {
        // ImagerPixelSpacing first (row spacing, column spacing).
        synthetic_cr(&p, ps, Some("0.2\\0.1"));
        let s = open(&p);
        assert_eq!(s.info.geometry.spacing_mm[..2], [0.1, 0.2], "{ps:?}");
        assert!(
            s.info
                .description
                .contains("ImagerPixelSpacing 0.2\\0.1 mm used"),
            "{ps:?}: {}",
            s.info.description
        );
        // Then 1 mm, said.
        synthetic_cr(&p, ps, None);
        let s = open(&p);
        assert_eq!(s.info.geometry.spacing_mm[..2], [1.0, 1.0], "{ps:?}");
        assert!(
            s.info.description.contains("1 mm pixels assumed"),
            "{ps:?}: {}",
            s.info.description
        );
        assert_eq!(all_values(&s), [0.0, 100.0, 200.0, 300.0, 400.0, 500.0]);
    }
    synthetic_cr(&p, Some("0\\0"), None);
    let s = open(&p);
    assert!(
        s.info
            .description
            .contains("PixelSpacing [0.0, 0.0] unusable"),
        "{}",
        s.info.description
    );
    // A usable PixelSpacing is taken as it is, with no note.
    synthetic_cr(&p, Some("0.5\\0.25"), Some("0.2\\0.1"));
    let s = open(&p);
    assert_eq!(s.info.geometry.spacing_mm[..2], [0.25, 0.5]);
    assert!(
        !s.info.description.contains("PixelSpacing"),
        "{}",
        s.info.description
    );
}

/// NEMA's NM1_JPLY (pydicom's JPEG-lossy.dcm) has Se = 0 in its sequential scan header, which
/// libjpeg and GDCM ignore with a warning and pydicom refuses; JPGExtended.dcm is the same file
/// with that byte fixed. Strata repairs the field, says so, and must decode exactly the fixed
/// file's voxels (the same decoder on the same entropy-coded data).
#[test]
fn jpeg_with_invalid_sequential_scan_header_decodes_like_its_fixed_copy() {
    let s = open(&pydicom_file("JPEG-lossy.dcm"));
    let fixed = open(&pydicom_file("JPGExtended.dcm"));
    assert_eq!(all_values(&s), all_values(&fixed));
    assert!(
        s.info.description.contains("JPEG scan header repaired"),
        "{}",
        s.info.description
    );
    assert!(
        !fixed.info.description.contains("repaired"),
        "{}",
        fixed.info.description
    );
}
