//! DICOM Segmentation (SEG) objects: a layer written as one BINARY SEG (PS3.3 A.51, C.8.20).
//!
//! One frame per segment per k-slice where that segment has voxels, ordered by slice then segment
//! number, each frame's pixels 1 bit, packed with no padding between frames (what
//! `strata_storage`'s SEG reader and highdicom read). Frames name their segment
//! (SegmentIdentificationSequence) and plane (PlanePositionSequence); orientation and pixel
//! measures are shared. The first and last slice always have a frame (an empty one of the lowest
//! segment where that slice has no voxels): readers that take the grid from the frames, Strata's
//! included, then see the layer's whole extent and load it back on the same grid.
//!
//! Segments: label value = SegmentNumber, name = SegmentLabel, colour as
//! RecommendedDisplayCIELabValue (sRGB → CIELab D65, the inverse of
//! `strata_storage::readers::dicom_lab_to_srgb`), category and type codes from the segment
//! (default SCT 85756007 "Tissue" for both), algorithm MANUAL. Values that occur in the voxels
//! but not in the segment table are written as "segment N". Given the source series' UIDs and
//! one SOP instance UID per k-slice ([`SegSource`]), the SEG joins the source's study and frame
//! of reference, lists the series (ReferencedSeriesSequence) and each frame its source image
//! (DerivationImageSequence).
//!
//! A reader orders slices along row × column direction; for a left-handed grid (k against that
//! cross product) the same voxels load back in the opposite k order, at the same patient positions.
//!
//! Limits, each a [`SegmentError::FormatLimit`]: 65 535 segments (SegmentNumber is a US), and a
//! PixelData of under 4 GiB (its 32-bit length): frames × rows × columns / 8 bytes. The packed
//! frames are held in memory until written (1/16 of a u16 label volume per segment that
//! occurs), the labels themselves are read one slice at a time. Checked against highdicom,
//! pydicom and Strata's own SEG reader in `segment/tests/peers.rs`.
//!
//! The object is built in memory ([`dicom_seg_bytes`]: the browser page's download, wasm32,
//! where dicom-rs builds without its C codecs, none of which a BINARY SEG needs); only
//! [`write_dicom_seg`] touches a file (`local`). The clock and the entropy its new UIDs come
//! from are the caller's ([`SegStamp`]): wasm32 has no system clock or process id in `std`.

use std::path::Path;

use dicom_core::value::{DataSetSequence, PrimitiveValue};
use dicom_core::{DataElement, Tag, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_object::meta::FileMetaTableBuilder;
use dicom_object::{FileDicomObject, InMemDicomObject};
use strata_types::VolumeGeometry;

#[cfg(feature = "local")]
use crate::io::atomic::write_file_atomically;
use crate::{Code, Label, LabelRead, SegmentCategory, SegmentError, MAX_SEGMENTS};

type Obj = InMemDicomObject;

/// When a SEG is made (its dates and times) and the entropy its new UIDs are drawn from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SegStamp {
    /// UTC time, nanoseconds since 1970.
    pub unix_nanos: u128,
    /// Distinguishes makers at the same instant: the process id on the desktop, a random
    /// number in the page.
    pub unique: u64,
}

impl SegStamp {
    /// Now, by the system clock, and this process.
    #[cfg(feature = "local")]
    pub fn now() -> Self {
        SegStamp {
            unix_nanos: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos()),
            unique: u64::from(std::process::id()),
        }
    }
}

/// PixelData's length is a 32-bit even number; 0xFFFF_FFFF means "undefined".
const MAX_PIXEL_DATA_BYTES: u64 = 0xFFFF_FFFE;

/// The DICOM series a segmentation was drawn on.
#[derive(Clone, Debug, Default)]
pub struct SegSource {
    pub study_instance_uid: String,
    pub series_instance_uid: String,
    pub frame_of_reference_uid: String,
    /// SOP class of the source images (e.g. CT Image Storage).
    pub sop_class_uid: String,
    /// The source image of each k-slice of the label grid (same grid as the source's).
    pub slice_sop_instance_uids: Vec<String>,
    pub patient_name: String,
    pub patient_id: String,
}

#[derive(Clone, Debug)]
pub struct SegOptions {
    pub series_description: String,
    pub content_label: String,
    pub source: Option<SegSource>,
}

impl Default for SegOptions {
    fn default() -> Self {
        SegOptions {
            series_description: "Strata segmentation".into(),
            content_label: "SEGMENTATION".into(),
            source: None,
        }
    }
}

/// What a write produced.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SegSummary {
    pub segments: usize,
    pub frames: usize,
    pub sop_instance_uid: String,
}

/// SCT 85756007 "Tissue": the default category and type of a segment.
pub fn tissue() -> SegmentCategory {
    let code = Code {
        value: "85756007".into(),
        scheme: "SCT".into(),
        meaning: "Tissue".into(),
    };
    SegmentCategory {
        category: code.clone(),
        kind: code,
    }
}

/// A new UID under the UUID-derived root 2.25 (PS3.5 B.2): a 128-bit number from the clock,
/// the process and a counter, hashed.
#[cfg(feature = "local")]
pub fn new_uid() -> String {
    new_uid_at(&SegStamp::now())
}

/// A new UID under 2.25 from `stamp` and a counter (distinct UIDs from one stamp), hashed.
pub fn new_uid_at(stamp: &SegStamp) -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let mut seed = Vec::with_capacity(32);
    seed.extend_from_slice(&stamp.unix_nanos.to_le_bytes());
    seed.extend_from_slice(&stamp.unique.to_le_bytes());
    seed.extend_from_slice(&COUNTER.fetch_add(1, Ordering::Relaxed).to_le_bytes());
    format!("2.25.{}", xxhash_rust::xxh3::xxh3_128(&seed))
}

/// sRGB to DICOM's scaled CIELab (D65), PS3.3 C.10.7.1.1.
pub fn srgb_to_dicom_lab(rgb: [u8; 3]) -> [u16; 3] {
    let lin = rgb.map(|c| {
        let c = f64::from(c) / 255.0;
        if c <= 0.040_45 {
            c / 12.92
        } else {
            ((c + 0.055) / 1.055).powf(2.4)
        }
    });
    let x = (0.412_4 * lin[0] + 0.357_6 * lin[1] + 0.180_5 * lin[2]) / 0.950_47;
    let y = 0.212_6 * lin[0] + 0.715_2 * lin[1] + 0.072_2 * lin[2];
    let z = (0.019_3 * lin[0] + 0.119_2 * lin[1] + 0.950_5 * lin[2]) / 1.088_83;
    let delta: f64 = 6.0 / 29.0;
    let f = |t: f64| {
        if t > delta * delta * delta {
            t.cbrt()
        } else {
            t / (3.0 * delta * delta) + 4.0 / 29.0
        }
    };
    let (fx, fy, fz) = (f(x), f(y), f(z));
    let l = 116.0 * fy - 16.0;
    let a = 500.0 * (fx - fy);
    let b = 200.0 * (fy - fz);
    [
        (l.clamp(0.0, 100.0) * 65535.0 / 100.0).round() as u16,
        ((a + 128.0).clamp(0.0, 255.0) * 65535.0 / 255.0).round() as u16,
        ((b + 128.0).clamp(0.0, 255.0) * 65535.0 / 255.0).round() as u16,
    ]
}

/// A DS (decimal string) value of at most 16 characters.
fn ds(x: f64) -> String {
    for precision in (0..=10).rev() {
        let s = format!("{x:.precision$}");
        let s = if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        };
        if s.len() <= 16 {
            return if s == "-0" { "0".into() } else { s };
        }
    }
    format!("{x:.6e}")
}

fn text(tag: Tag, vr: VR, value: &str) -> DataElement<Obj> {
    DataElement::new(tag, vr, PrimitiveValue::from(value))
}

fn decimals(tag: Tag, values: &[f64]) -> DataElement<Obj> {
    DataElement::new(
        tag,
        VR::DS,
        PrimitiveValue::Strs(values.iter().map(|v| ds(*v)).collect()),
    )
}

fn us(tag: Tag, values: &[u16]) -> DataElement<Obj> {
    DataElement::new(
        tag,
        VR::US,
        PrimitiveValue::U16(values.iter().copied().collect()),
    )
}

fn ul(tag: Tag, values: &[u32]) -> DataElement<Obj> {
    DataElement::new(
        tag,
        VR::UL,
        PrimitiveValue::U32(values.iter().copied().collect()),
    )
}

fn sequence(tag: Tag, items: Vec<Obj>) -> DataElement<Obj> {
    DataElement::new(tag, VR::SQ, DataSetSequence::from(items))
}

fn code_item(code: &Code) -> Obj {
    Obj::from_element_iter([
        text(tags::CODE_VALUE, VR::SH, &code.value),
        text(tags::CODING_SCHEME_DESIGNATOR, VR::SH, &code.scheme),
        text(tags::CODE_MEANING, VR::LO, &code.meaning),
    ])
}

/// One frame: its segment and slice.
struct Frame {
    segment: Label,
    slice: u32,
}

/// Writes `labels` as a BINARY DICOM SEG at `path` (replaced only once complete).
#[cfg(feature = "local")]
pub fn write_dicom_seg(
    labels: &dyn LabelRead,
    path: &Path,
    options: &SegOptions,
) -> Result<SegSummary, SegmentError> {
    use std::io::Write;
    let (file, summary) = dicom_seg_object(labels, path, options, &SegStamp::now())?;
    write_file_atomically(path, |out| {
        file.write_all(&mut *out).map_err(|e| SegmentError::Io {
            path: path.to_path_buf(),
            source: std::io::Error::other(e.to_string()),
        })?;
        out.flush().map_err(|e| SegmentError::Io {
            path: path.to_path_buf(),
            source: e,
        })
    })?;
    Ok(summary)
}

/// The bytes of the file [`write_dicom_seg`] writes, in memory (the page's download); `name`
/// is what errors call it.
pub fn dicom_seg_bytes(
    labels: &dyn LabelRead,
    name: &Path,
    options: &SegOptions,
    stamp: &SegStamp,
) -> Result<(Vec<u8>, SegSummary), SegmentError> {
    let (file, summary) = dicom_seg_object(labels, name, options, stamp)?;
    let mut bytes = Vec::new();
    file.write_all(&mut bytes)
        .map_err(|e| SegmentError::Format {
            path: name.to_path_buf(),
            message: format!("DICOM encoding: {e}"),
        })?;
    Ok((bytes, summary))
}

/// The SEG of `labels` as a DICOM file object (meta and data set); `path` is what errors name.
pub fn dicom_seg_object(
    labels: &dyn LabelRead,
    path: &Path,
    options: &SegOptions,
    stamp: &SegStamp,
) -> Result<(FileDicomObject<Obj>, SegSummary), SegmentError> {
    let g = labels.geometry().clone();
    let limit = |what: &str, limit: u64, requested: u64| SegmentError::FormatLimit {
        path: path.to_path_buf(),
        format: "DICOM SEG (BINARY)",
        what: what.to_string(),
        limit,
        requested,
    };
    let [nx, ny, nz] = g.dims;
    if nx > u32::from(u16::MAX) || ny > u32::from(u16::MAX) {
        return Err(limit(
            "rows and columns per frame",
            u64::from(u16::MAX),
            u64::from(nx.max(ny)),
        ));
    }
    if let Some(src) = &options.source {
        if src.slice_sop_instance_uids.len() != nz as usize {
            return Err(SegmentError::Format {
                path: path.to_path_buf(),
                message: format!(
                    "the source series has {} images for {nz} label slices: a SEG references one source image per slice",
                    src.slice_sop_instance_uids.len()
                ),
            });
        }
    }
    let frame_pixels = u64::from(nx) * u64::from(ny);
    let plane = frame_pixels as usize;

    // One pass over the slices: which segments each has, their frames packed as they come.
    let mut slice: Vec<Label> = vec![0; plane];
    let mut present = vec![false; usize::from(Label::MAX) + 1];
    let mut frames: Vec<Frame> = Vec::new();
    let mut bits: Vec<u8> = Vec::new();
    let mut bit_len: u64 = 0;
    let mut in_slice: Vec<Label> = Vec::new();
    for k in 0..nz {
        labels.read_slice_k(k, &mut slice)?;
        for &v in &slice {
            present[usize::from(v)] = true;
        }
        in_slice.clear();
        // Present in this slice: scan once per slice for its distinct labels.
        let mut seen = std::collections::BTreeSet::new();
        for &v in &slice {
            if v != 0 {
                seen.insert(v);
            }
        }
        in_slice.extend(seen);
        if in_slice.is_empty() && (k == 0 || k == nz - 1) {
            // Pin the grid's extent with an empty frame (see the module doc); 0 stands for the
            // lowest segment number, known once every slice has been read.
            in_slice.push(0);
        }
        for &segment in &in_slice {
            let needed = (bit_len + frame_pixels).div_ceil(8);
            if needed > MAX_PIXEL_DATA_BYTES {
                return Err(limit(
                    "bytes of 1-bit PixelData (frames × rows × columns / 8)",
                    MAX_PIXEL_DATA_BYTES,
                    needed,
                ));
            }
            bits.resize(needed as usize, 0);
            for (p, &v) in slice.iter().enumerate() {
                if segment != 0 && v == segment {
                    let bit = bit_len + p as u64;
                    bits[(bit / 8) as usize] |= 1 << (bit % 8);
                }
            }
            bit_len += frame_pixels;
            frames.push(Frame { segment, slice: k });
        }
    }
    if bits.len() % 2 == 1 {
        bits.push(0);
    }

    // The segments: the table's, plus any value found in the voxels without an entry.
    let mut numbers: Vec<Label> = labels.segments().iter().map(|s| s.value).collect();
    for v in 1..=Label::MAX {
        if present[usize::from(v)] && labels.segments().get(v).is_none() {
            numbers.push(v);
        }
    }
    numbers.sort_unstable();
    if numbers.is_empty() {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: "no segments to save: a DICOM SEG needs at least one".into(),
        });
    }
    for f in frames.iter_mut().filter(|f| f.segment == 0) {
        f.segment = numbers[0];
    }
    if numbers.len() > MAX_SEGMENTS {
        return Err(limit("segments", MAX_SEGMENTS as u64, numbers.len() as u64));
    }
    let segment_items: Vec<Obj> = numbers
        .iter()
        .map(|&n| {
            let s = labels.segments().get(n);
            let name = s.map_or_else(|| format!("segment {n}"), |s| s.name.clone());
            let rgb = s.map_or_else(|| crate::segments::label_colour(i64::from(n)), |s| s.rgb);
            let category = s.and_then(|s| s.category.clone()).unwrap_or_else(tissue);
            Obj::from_element_iter([
                us(tags::SEGMENT_NUMBER, &[n]),
                text(tags::SEGMENT_LABEL, VR::LO, &name),
                text(tags::SEGMENT_ALGORITHM_TYPE, VR::CS, "MANUAL"),
                sequence(
                    tags::SEGMENTED_PROPERTY_CATEGORY_CODE_SEQUENCE,
                    vec![code_item(&category.category)],
                ),
                sequence(
                    tags::SEGMENTED_PROPERTY_TYPE_CODE_SEQUENCE,
                    vec![code_item(&category.kind)],
                ),
                us(
                    tags::RECOMMENDED_DISPLAY_CIE_LAB_VALUE,
                    &srgb_to_dicom_lab(rgb),
                ),
            ])
        })
        .collect();

    let obj = build_dataset(&g, options, stamp, segment_items, &frames, bits)?;
    let sop_instance_uid = obj
        .element(tags::SOP_INSTANCE_UID)
        .ok()
        .and_then(|e| e.to_str().ok())
        .map(|s| s.to_string())
        .unwrap_or_default();
    let file = obj
        .with_meta(FileMetaTableBuilder::new().transfer_syntax(uids::EXPLICIT_VR_LITTLE_ENDIAN))
        .map_err(|e| SegmentError::Format {
            path: path.to_path_buf(),
            message: format!("DICOM file meta: {e}"),
        })?;
    Ok((
        file,
        SegSummary {
            segments: numbers.len(),
            frames: frames.len(),
            sop_instance_uid,
        },
    ))
}

fn build_dataset(
    g: &VolumeGeometry,
    options: &SegOptions,
    stamp: &SegStamp,
    segment_items: Vec<Obj>,
    frames: &[Frame],
    pixel_data: Vec<u8>,
) -> Result<Obj, SegmentError> {
    let [nx, ny, _] = g.dims;
    let now = u64::try_from(stamp.unix_nanos / 1_000_000_000).unwrap_or(u64::MAX);
    let (date, time) = civil_date_time(now);
    let src = options.source.as_ref();
    let new_uid = || new_uid_at(stamp);
    let study_uid = src.map_or_else(new_uid, |s| s.study_instance_uid.clone());
    let frame_of_reference = src.map_or_else(new_uid, |s| s.frame_of_reference_uid.clone());
    let sop_uid = new_uid();
    let dimension_uid = new_uid();
    let mut obj = Obj::new_empty();
    for e in [
        text(tags::SOP_CLASS_UID, VR::UI, uids::SEGMENTATION_STORAGE),
        text(tags::SOP_INSTANCE_UID, VR::UI, &sop_uid),
        text(tags::STUDY_DATE, VR::DA, &date),
        text(tags::SERIES_DATE, VR::DA, &date),
        text(tags::CONTENT_DATE, VR::DA, &date),
        text(tags::STUDY_TIME, VR::TM, &time),
        text(tags::SERIES_TIME, VR::TM, &time),
        text(tags::CONTENT_TIME, VR::TM, &time),
        text(tags::ACCESSION_NUMBER, VR::SH, ""),
        text(tags::MODALITY, VR::CS, "SEG"),
        text(tags::MANUFACTURER, VR::LO, "Strata"),
        text(tags::REFERRING_PHYSICIAN_NAME, VR::PN, ""),
        text(
            tags::SERIES_DESCRIPTION,
            VR::LO,
            &options.series_description,
        ),
        text(tags::MANUFACTURER_MODEL_NAME, VR::LO, "strata"),
        text(
            tags::PATIENT_NAME,
            VR::PN,
            src.map_or("", |s| &s.patient_name),
        ),
        text(tags::PATIENT_ID, VR::LO, src.map_or("", |s| &s.patient_id)),
        text(tags::PATIENT_BIRTH_DATE, VR::DA, ""),
        text(tags::PATIENT_SEX, VR::CS, ""),
        text(tags::DEVICE_SERIAL_NUMBER, VR::LO, "1"),
        text(tags::SOFTWARE_VERSIONS, VR::LO, env!("CARGO_PKG_VERSION")),
        text(tags::STUDY_INSTANCE_UID, VR::UI, &study_uid),
        text(tags::SERIES_INSTANCE_UID, VR::UI, &new_uid()),
        text(tags::STUDY_ID, VR::SH, ""),
        text(tags::SERIES_NUMBER, VR::IS, "300"),
        text(tags::INSTANCE_NUMBER, VR::IS, "1"),
        text(tags::FRAME_OF_REFERENCE_UID, VR::UI, &frame_of_reference),
        text(tags::POSITION_REFERENCE_INDICATOR, VR::LO, ""),
        us(tags::SAMPLES_PER_PIXEL, &[1]),
        text(tags::PHOTOMETRIC_INTERPRETATION, VR::CS, "MONOCHROME2"),
        text(tags::NUMBER_OF_FRAMES, VR::IS, &frames.len().to_string()),
        us(tags::ROWS, &[ny as u16]),
        us(tags::COLUMNS, &[nx as u16]),
        us(tags::BITS_ALLOCATED, &[1]),
        us(tags::BITS_STORED, &[1]),
        us(tags::HIGH_BIT, &[0]),
        us(tags::PIXEL_REPRESENTATION, &[0]),
        text(tags::LOSSY_IMAGE_COMPRESSION, VR::CS, "00"),
        DataElement::new(
            tags::IMAGE_TYPE,
            VR::CS,
            PrimitiveValue::Strs(
                ["DERIVED".to_string(), "PRIMARY".to_string()]
                    .into_iter()
                    .collect(),
            ),
        ),
        text(tags::CONTENT_LABEL, VR::CS, &options.content_label),
        text(
            tags::CONTENT_DESCRIPTION,
            VR::LO,
            "Segmentation made in Strata",
        ),
        text(tags::CONTENT_CREATOR_NAME, VR::PN, ""),
        text(tags::SEGMENTATION_TYPE, VR::CS, "BINARY"),
        text(tags::SEGMENTS_OVERLAP, VR::CS, "NO"),
        sequence(tags::SEGMENT_SEQUENCE, segment_items),
    ] {
        obj.put(e);
    }

    // Dimensions: segment number, then plane position (as highdicom organises a SEG).
    obj.put(sequence(
        tags::DIMENSION_ORGANIZATION_SEQUENCE,
        vec![Obj::from_element_iter([text(
            tags::DIMENSION_ORGANIZATION_UID,
            VR::UI,
            &dimension_uid,
        )])],
    ));
    let pointer = |index: Tag, group: Tag| {
        Obj::from_element_iter([
            text(tags::DIMENSION_ORGANIZATION_UID, VR::UI, &dimension_uid),
            DataElement::new(
                tags::DIMENSION_INDEX_POINTER,
                VR::AT,
                PrimitiveValue::Tags([index].into_iter().collect()),
            ),
            DataElement::new(
                tags::FUNCTIONAL_GROUP_POINTER,
                VR::AT,
                PrimitiveValue::Tags([group].into_iter().collect()),
            ),
        ])
    };
    obj.put(sequence(
        tags::DIMENSION_INDEX_SEQUENCE,
        vec![
            pointer(
                tags::REFERENCED_SEGMENT_NUMBER,
                tags::SEGMENT_IDENTIFICATION_SEQUENCE,
            ),
            pointer(tags::IMAGE_POSITION_PATIENT, tags::PLANE_POSITION_SEQUENCE),
        ],
    ));

    let [row_dir, col_dir, _] = g.direction;
    let slice_thickness = g.spacing_mm[2];
    obj.put(sequence(
        tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE,
        vec![Obj::from_element_iter([
            sequence(
                tags::PLANE_ORIENTATION_SEQUENCE,
                vec![Obj::from_element_iter([decimals(
                    tags::IMAGE_ORIENTATION_PATIENT,
                    &[
                        row_dir[0], row_dir[1], row_dir[2], col_dir[0], col_dir[1], col_dir[2],
                    ],
                )])],
            ),
            sequence(
                tags::PIXEL_MEASURES_SEQUENCE,
                vec![Obj::from_element_iter([
                    // PixelSpacing is row spacing (along j), then column spacing (along i).
                    decimals(tags::PIXEL_SPACING, &[g.spacing_mm[1], g.spacing_mm[0]]),
                    decimals(tags::SLICE_THICKNESS, &[slice_thickness]),
                    decimals(tags::SPACING_BETWEEN_SLICES, &[slice_thickness]),
                ])],
            ),
        ])],
    ));

    let per_frame: Vec<Obj> = frames
        .iter()
        .map(|f| {
            let ipp = g.patient_from_index([0.0, 0.0, f64::from(f.slice)]);
            let mut item = Obj::from_element_iter([
                sequence(
                    tags::FRAME_CONTENT_SEQUENCE,
                    vec![Obj::from_element_iter([ul(
                        tags::DIMENSION_INDEX_VALUES,
                        &[u32::from(f.segment), f.slice + 1],
                    )])],
                ),
                sequence(
                    tags::PLANE_POSITION_SEQUENCE,
                    vec![Obj::from_element_iter([decimals(
                        tags::IMAGE_POSITION_PATIENT,
                        &[ipp.x, ipp.y, ipp.z],
                    )])],
                ),
                sequence(
                    tags::SEGMENT_IDENTIFICATION_SEQUENCE,
                    vec![Obj::from_element_iter([us(
                        tags::REFERENCED_SEGMENT_NUMBER,
                        &[f.segment],
                    )])],
                ),
            ]);
            if let Some(s) = src {
                let image = &s.slice_sop_instance_uids[f.slice as usize];
                item.put(sequence(
                    tags::DERIVATION_IMAGE_SEQUENCE,
                    vec![Obj::from_element_iter([
                        sequence(
                            tags::SOURCE_IMAGE_SEQUENCE,
                            vec![Obj::from_element_iter([
                                text(tags::REFERENCED_SOP_CLASS_UID, VR::UI, &s.sop_class_uid),
                                text(tags::REFERENCED_SOP_INSTANCE_UID, VR::UI, image),
                                sequence(
                                    tags::PURPOSE_OF_REFERENCE_CODE_SEQUENCE,
                                    vec![code_item(&Code {
                                        value: "121322".into(),
                                        scheme: "DCM".into(),
                                        meaning: "Source image for image processing operation"
                                            .into(),
                                    })],
                                ),
                            ])],
                        ),
                        sequence(
                            tags::DERIVATION_CODE_SEQUENCE,
                            vec![code_item(&Code {
                                value: "113076".into(),
                                scheme: "DCM".into(),
                                meaning: "Segmentation".into(),
                            })],
                        ),
                    ])],
                ));
            }
            item
        })
        .collect();
    obj.put(sequence(
        tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE,
        per_frame,
    ));

    if let Some(s) = src {
        let instances = s
            .slice_sop_instance_uids
            .iter()
            .map(|uid| {
                Obj::from_element_iter([
                    text(tags::REFERENCED_SOP_CLASS_UID, VR::UI, &s.sop_class_uid),
                    text(tags::REFERENCED_SOP_INSTANCE_UID, VR::UI, uid),
                ])
            })
            .collect();
        obj.put(sequence(
            tags::REFERENCED_SERIES_SEQUENCE,
            vec![Obj::from_element_iter([
                text(tags::SERIES_INSTANCE_UID, VR::UI, &s.series_instance_uid),
                sequence(tags::REFERENCED_INSTANCE_SEQUENCE, instances),
            ])],
        ));
    }
    obj.put(DataElement::new(
        tags::PIXEL_DATA,
        VR::OB,
        PrimitiveValue::from(pixel_data),
    ));
    Ok(obj)
}

/// UTC seconds since 1970 as DICOM DA (YYYYMMDD) and TM (HHMMSS) (Howard Hinnant's
/// civil-from-days).
fn civil_date_time(secs: u64) -> (String, String) {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    (
        format!("{y:04}{m:02}{d:02}"),
        format!("{:02}{:02}{:02}", rem / 3600, rem / 60 % 60, rem % 60),
    )
}
