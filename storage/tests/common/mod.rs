//! The reader tests' shared setup: the attributes every synthetic greyscale DICOM image
//! repeats, and writing a data set as a Part 10 file. A test states the attributes that make
//! its case (geometry, rescale, frames) and goes through these for the rest.
#![allow(dead_code)]

use std::path::Path;

use dicom_core::{PrimitiveValue, Tag, VR};
use dicom_dictionary_std::tags;
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};

/// The Image Pixel module of a one-sample greyscale (MONOCHROME2) image of `rows` × `columns`
/// 16-bit words with `bits_stored` of them used (the high bit just below), unsigned or two's
/// complement. `put` sets one attribute (the test's own closure over its data set).
pub fn put_grey_pixel_module<R>(
    put: &mut impl FnMut(Tag, VR, PrimitiveValue) -> R,
    [rows, columns]: [u16; 2],
    bits_stored: u16,
    signed: bool,
) {
    put(tags::ROWS, VR::US, PrimitiveValue::from(rows));
    put(tags::COLUMNS, VR::US, PrimitiveValue::from(columns));
    put(tags::SAMPLES_PER_PIXEL, VR::US, PrimitiveValue::from(1u16));
    put(
        tags::PHOTOMETRIC_INTERPRETATION,
        VR::CS,
        "MONOCHROME2".into(),
    );
    put(tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(16u16));
    put(tags::BITS_STORED, VR::US, PrimitiveValue::from(bits_stored));
    put(
        tags::HIGH_BIT,
        VR::US,
        PrimitiveValue::from(bits_stored - 1),
    );
    put(
        tags::PIXEL_REPRESENTATION,
        VR::US,
        PrimitiveValue::from(u16::from(signed)),
    );
}

/// `obj` written to `path` as a Part 10 file: instance `sop_instance` of `sop_class`, encoded
/// in `transfer_syntax`.
pub fn write_part10(
    obj: InMemDicomObject,
    transfer_syntax: &str,
    sop_class: &str,
    sop_instance: &str,
    path: &Path,
) {
    obj.with_meta(
        FileMetaTableBuilder::new()
            .transfer_syntax(transfer_syntax)
            .media_storage_sop_class_uid(sop_class)
            .media_storage_sop_instance_uid(sop_instance),
    )
    .unwrap()
    .write_to_file(path)
    .unwrap();
}

/// Every node of every level of `store`'s octree, in layout order (level, then z, y, x).
pub fn all_brick_ids(store: &strata_storage::Store) -> Vec<strata_types::BrickId> {
    let layout = store.layout().clone();
    let mut out = Vec::new();
    for level in 0..layout.level_count() {
        let n = layout.bricks_in_level(level);
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    out.push(strata_types::BrickId::new(level as u8, [x, y, z]));
                }
            }
        }
    }
    out
}

/// Every voxel value of an opened scan, i fastest (as the file stores them, through the
/// reader's slice path).
pub fn all_values(src: &strata_storage::OpenedSource) -> Vec<f64> {
    let mut out = Vec::new();
    let mut slice = Vec::new();
    for k in 0..src.data.dims[2] {
        src.data.read_slice_f64(k, &mut slice);
        out.extend_from_slice(&slice);
    }
    out
}

/// Runs a python snippet (a reference reader) and returns its stdout; fails the test with
/// `install`, the command that installs what it needs, when python or a module is missing.
pub fn python(code: &str, install: &str) -> String {
    let out = std::process::Command::new("python3")
        .arg("-c")
        .arg(code)
        .output()
        .unwrap_or_else(|e| {
            panic!("python3 not runnable ({e}); needed for reference data: {install}")
        });
    assert!(
        out.status.success(),
        "python3 failed (missing modules? {install}):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}
