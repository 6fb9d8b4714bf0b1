//! DICOM Segmentation (SEG) objects as label maps: one label value per segment.
//!
//! A SEG holds one frame per (segment, plane): BINARY frames are 1 bit per pixel, packed with
//! no padding between frames (a 7×5 frame is 35 bits, so the next frame starts mid-byte);
//! FRACTIONAL frames are 8 bits, a fraction of MaximumFractionalValue. Each frame names its
//! segment (SegmentIdentificationSequence) and its plane (PlanePositionSequence) in its own
//! per-frame functional group; frames come in any order and planes where a segment is empty
//! are usually left out. The label grid is the SEG's own: its orientation and pixel spacing,
//! slices along the plane normal from the lowest to the highest frame position, one slice per
//! SpacingBetweenSlices (else the smallest gap between frame positions). Slices no frame names
//! stay background (0). The viewer resamples the label map into the primary scan's space.
//!
//! Rules (also in docs/viewer.md): where several segments cover a voxel the highest segment
//! number wins; a FRACTIONAL frame's pixel belongs to its segment where the fraction is at
//! least 0.5 (2 · stored ≥ MaximumFractionalValue), so both types give labels. Segment names and
//! RecommendedDisplayCIELabValue colours (converted to sRGB, D65) go to [`SourceInfo::labels`].
//!
//! The SEG file is read whole (its pixel data is bit-packed, so small; dicom_bounds has checked
//! every length against the file first); the output is written to staging one slice at a time.

use std::io::{BufWriter, Write};
use std::path::Path;

use dicom_core::Tag;
use dicom_dictionary_std::{tags, uids};
use dicom_object::{InMemDicomObject, OpenFileOptions};

use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::readers::common::{cross, dot, norm};
use crate::readers::ReadOptions;
use crate::source::{ByteOrder, LabelInfo, OpenedSource, RawVolume, SampleType, SourceInfo};
use crate::staging::new_staging;

type Obj = InMemDicomObject;

/// Relative tolerance on frame positions against the slice grid and the in-plane origin
/// (scanners and SEG writers round positions to ~1e-5 mm; a misplaced frame is ≥ 1 % off).
const POSITION_TOL: f64 = 0.01;

/// True for a SEG (by SOP class or modality).
pub(crate) fn is_segmentation(sop_class: &str, modality: &str) -> bool {
    sop_class == uids::SEGMENTATION_STORAGE || modality == "SEG"
}

fn text(obj: &Obj, tag: Tag) -> Option<String> {
    let s = obj.get(tag)?.to_str().ok()?;
    let s = s.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    (!s.is_empty()).then(|| s.to_string())
}

fn int(obj: &Obj, tag: Tag) -> Option<i64> {
    obj.get(tag)?.to_int::<i64>().ok()
}

fn floats(obj: &Obj, tag: Tag) -> Option<Vec<f64>> {
    let v = obj.get(tag)?.to_multi_float64().ok()?;
    (!v.is_empty() && v.iter().all(|x| x.is_finite())).then_some(v)
}

fn seq_item(obj: &Obj, seq: Tag) -> Option<&Obj> {
    obj.get(seq)?.items()?.first()
}

/// The first item of a code sequence as a code (all three parts present, or none).
fn code(obj: &Obj, seq: Tag) -> Option<strata_types::Code> {
    let item = seq_item(obj, seq)?;
    Some(strata_types::Code {
        value: text(item, tags::CODE_VALUE)?,
        scheme: text(item, tags::CODING_SCHEME_DESIGNATOR)?,
        meaning: text(item, tags::CODE_MEANING)?,
    })
}

/// A segment's category and type codes, when it has both.
fn segment_category(item: &Obj) -> Option<strata_types::SegmentCategory> {
    Some(strata_types::SegmentCategory {
        category: code(item, tags::SEGMENTED_PROPERTY_CATEGORY_CODE_SEQUENCE)?,
        kind: code(item, tags::SEGMENTED_PROPERTY_TYPE_CODE_SEQUENCE)?,
    })
}

/// `attr` of the functional group `seq`: the frame's own group first, then the shared one.
fn group_floats(groups: [Option<&Obj>; 2], seq: Tag, attr: Tag) -> Option<Vec<f64>> {
    groups
        .into_iter()
        .flatten()
        .find_map(|g| seq_item(g, seq).and_then(|item| floats(item, attr)))
}

/// DICOM's scaled CIELab (L 0..65535 → 0..100, a and b 0..65535 → -128..127) to sRGB (D65).
pub fn dicom_lab_to_srgb(value: [u16; 3]) -> [u8; 3] {
    let l = f64::from(value[0]) * 100.0 / 65535.0;
    let a = f64::from(value[1]) * 255.0 / 65535.0 - 128.0;
    let b = f64::from(value[2]) * 255.0 / 65535.0 - 128.0;
    let fy = (l + 16.0) / 116.0;
    let (fx, fz) = (fy + a / 500.0, fy - b / 200.0);
    let delta: f64 = 6.0 / 29.0;
    let finv = |t: f64| {
        if t > delta {
            t * t * t
        } else {
            3.0 * delta * delta * (t - 4.0 / 29.0)
        }
    };
    let (x, y, z) = (0.950_47 * finv(fx), finv(fy), 1.088_83 * finv(fz));
    let linear = [
        3.240_6 * x - 1.537_2 * y - 0.498_6 * z,
        -0.968_9 * x + 1.875_8 * y + 0.041_5 * z,
        0.055_7 * x - 0.204_0 * y + 1.057_0 * z,
    ];
    linear.map(|c| {
        let c = c.clamp(0.0, 1.0);
        let g = if c <= 0.003_130_8 {
            12.92 * c
        } else {
            1.055 * c.powf(1.0 / 2.4) - 0.055
        };
        (g * 255.0).round() as u8
    })
}

/// One frame's segment and its plane's distance along the normal.
#[derive(Clone, Copy)]
struct SegFrame {
    index: usize,
    segment: u32,
    slice: u64,
}

pub(crate) fn open_dicom_seg(path: &Path, options: &ReadOptions) -> Result<OpenedSource> {
    let invalid = |m: String| StorageError::invalid(path, m);
    crate::readers::dicom_bounds::check_element_lengths(path)?;
    let file = OpenFileOptions::new()
        .open_file(path)
        .map_err(|e| invalid(format!("unreadable DICOM SEG: {e}")))?;
    let transfer_syntax = file.meta().transfer_syntax().trim_end_matches('\0');
    if !matches!(
        transfer_syntax,
        uids::EXPLICIT_VR_LITTLE_ENDIAN | uids::IMPLICIT_VR_LITTLE_ENDIAN
    ) {
        return Err(StorageError::unsupported(
            path,
            format!(
                "DICOM SEG with compressed or big-endian pixel data (transfer syntax {transfer_syntax}); only uncompressed little-endian SEGs are read"
            ),
        ));
    }
    let obj: &Obj = &file;
    let (rows, cols) = match (int(obj, tags::ROWS), int(obj, tags::COLUMNS)) {
        (Some(r), Some(c)) if (1..=65535).contains(&r) && (1..=65535).contains(&c) => {
            (r as u64, c as u64)
        }
        (r, c) => {
            return Err(invalid(format!(
                "DICOM SEG frame size {c:?}x{r:?} (Columns x Rows) is missing or out of range"
            )))
        }
    };
    let seg_type = text(obj, tags::SEGMENTATION_TYPE).unwrap_or_default();
    let bits = int(obj, tags::BITS_ALLOCATED).unwrap_or(0);
    let max_fraction = match (seg_type.as_str(), bits) {
        ("BINARY", 1) => None,
        ("FRACTIONAL", 8) => match int(obj, tags::MAXIMUM_FRACTIONAL_VALUE) {
            Some(m) if (1..=255).contains(&m) => Some(m as u32),
            m => {
                return Err(invalid(format!(
                    "FRACTIONAL DICOM SEG with MaximumFractionalValue {m:?} (must be 1..=255)"
                )))
            }
        },
        (t, b) => {
            return Err(StorageError::unsupported(
                path,
                format!(
                    "DICOM SEG of SegmentationType '{t}' with BitsAllocated {b} (BINARY is 1-bit, FRACTIONAL 8-bit)"
                ),
            ))
        }
    };
    let n_frames = match int(obj, tags::NUMBER_OF_FRAMES) {
        Some(n) if n >= 1 && (n as u64) <= crate::geometry::MAX_AXIS_VOXELS => n as usize,
        n => {
            return Err(invalid(format!(
                "DICOM SEG NumberOfFrames {n:?} is missing or absurd"
            )))
        }
    };

    // Segments: number → name and colour. Label values are the segment numbers.
    let mut labels: Vec<LabelInfo> = Vec::new();
    for item in obj
        .get(tags::SEGMENT_SEQUENCE)
        .and_then(|e| e.items())
        .unwrap_or(&[])
    {
        let number = match int(item, tags::SEGMENT_NUMBER) {
            Some(n) if (1..=65535).contains(&n) => n as u32,
            n => {
                return Err(invalid(format!(
                    "SegmentSequence item with SegmentNumber {n:?} (must be 1..=65535)"
                )))
            }
        };
        if labels.iter().any(|l| l.value == number) {
            return Err(invalid(format!(
                "SegmentSequence names segment {number} twice"
            )));
        }
        let rgb = obj_u16s(item, tags::RECOMMENDED_DISPLAY_CIE_LAB_VALUE)
            .filter(|v| v.len() == 3)
            .map(|v| dicom_lab_to_srgb([v[0], v[1], v[2]]));
        labels.push(LabelInfo {
            value: number,
            name: text(item, tags::SEGMENT_LABEL).unwrap_or_else(|| format!("segment {number}")),
            rgb,
            category: segment_category(item),
        });
    }
    if labels.is_empty() {
        return Err(invalid("DICOM SEG without a SegmentSequence".into()));
    }
    labels.sort_by_key(|l| l.value);

    let shared = seq_item(obj, tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE);
    let per_frame: &[Obj] = obj
        .get(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE)
        .and_then(|e| e.items())
        .unwrap_or(&[]);
    if per_frame.len() != n_frames {
        return Err(invalid(format!(
            "DICOM SEG has {} PerFrameFunctionalGroupsSequence items for {n_frames} frames",
            per_frame.len()
        )));
    }
    let groups = |f: usize| [per_frame.get(f), shared];
    let iop = group_floats(
        groups(0),
        tags::PLANE_ORIENTATION_SEQUENCE,
        tags::IMAGE_ORIENTATION_PATIENT,
    )
    .filter(|v| v.len() == 6)
    .ok_or_else(|| invalid("DICOM SEG without ImageOrientationPatient".into()))?;
    let pixel_spacing = group_floats(
        groups(0),
        tags::PIXEL_MEASURES_SEQUENCE,
        tags::PIXEL_SPACING,
    )
    .filter(|v| v.len() == 2 && v.iter().all(|s| *s > 0.0))
    .ok_or_else(|| invalid("DICOM SEG without a usable PixelSpacing".into()))?;
    let row_dir = [iop[0], iop[1], iop[2]];
    let col_dir = [iop[3], iop[4], iop[5]];
    let normal = cross(row_dir, col_dir);
    if (norm(row_dir) - 1.0).abs() > 1e-3
        || (norm(col_dir) - 1.0).abs() > 1e-3
        || dot(row_dir, col_dir).abs() > 1e-3
    {
        return Err(invalid(format!(
            "DICOM SEG ImageOrientationPatient {iop:?} is not two orthogonal unit vectors"
        )));
    }

    // Each frame's segment and plane.
    let mut positions = Vec::with_capacity(n_frames);
    let mut segments = Vec::with_capacity(n_frames);
    for f in 0..n_frames {
        if let Some(o) = group_floats(
            groups(f),
            tags::PLANE_ORIENTATION_SEQUENCE,
            tags::IMAGE_ORIENTATION_PATIENT,
        ) {
            if o.len() != 6 || o.iter().zip(&iop).any(|(a, b)| (a - b).abs() > 1e-4) {
                return Err(invalid(format!(
                    "DICOM SEG frame {} has orientation {o:?}, frame 1 {iop:?}: one grid per SEG is read",
                    f + 1
                )));
            }
        }
        let ipp = group_floats(
            groups(f),
            tags::PLANE_POSITION_SEQUENCE,
            tags::IMAGE_POSITION_PATIENT,
        )
        .filter(|v| v.len() == 3)
        .ok_or_else(|| {
            invalid(format!(
                "DICOM SEG frame {} has no ImagePositionPatient",
                f + 1
            ))
        })?;
        let segment = per_frame
            .get(f)
            .and_then(|g| seq_item(g, tags::SEGMENT_IDENTIFICATION_SEQUENCE))
            .and_then(|s| int(s, tags::REFERENCED_SEGMENT_NUMBER))
            .ok_or_else(|| {
                invalid(format!(
                    "DICOM SEG frame {} names no segment (SegmentIdentificationSequence)",
                    f + 1
                ))
            })?;
        if !labels.iter().any(|l| i64::from(l.value) == segment) {
            return Err(invalid(format!(
                "DICOM SEG frame {} refers to segment {segment}, which the SegmentSequence does not describe",
                f + 1
            )));
        }
        positions.push([ipp[0], ipp[1], ipp[2]]);
        segments.push(segment as u32);
    }

    // The slice grid along the normal.
    let along: Vec<f64> = positions.iter().map(|p| dot(*p, normal)).collect();
    let lowest = (0..n_frames)
        .min_by(|&a, &b| along[a].total_cmp(&along[b]))
        .unwrap_or(0);
    let d0 = along[lowest];
    let d1 = along.iter().copied().fold(f64::MIN, f64::max);
    let stated_gap = group_floats(
        groups(0),
        tags::PIXEL_MEASURES_SEQUENCE,
        tags::SPACING_BETWEEN_SLICES,
    )
    .and_then(|v| v.first().copied())
    .filter(|g| *g > 0.0);
    let mut sorted = along.clone();
    sorted.sort_by(f64::total_cmp);
    let smallest_gap = sorted
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|g| *g > 1e-4)
        .fold(f64::INFINITY, f64::min);
    let gap = stated_gap
        .or(smallest_gap.is_finite().then_some(smallest_gap))
        .or_else(|| {
            group_floats(
                groups(0),
                tags::PIXEL_MEASURES_SEQUENCE,
                tags::SLICE_THICKNESS,
            )
            .and_then(|v| v.first().copied())
            .filter(|g| *g > 0.0)
        })
        .unwrap_or(1.0);
    let span_slices = ((d1 - d0) / gap).round();
    if !span_slices.is_finite() || span_slices + 1.0 > crate::geometry::MAX_AXIS_VOXELS as f64 {
        return Err(invalid(format!(
            "DICOM SEG frames span {} mm at {gap} mm per slice: absurd",
            d1 - d0
        )));
    }
    let n_slices = span_slices as u64 + 1;
    let origin = positions[lowest];
    let mut seg_frames = Vec::with_capacity(n_frames);
    for f in 0..n_frames {
        let offset = [
            positions[f][0] - origin[0],
            positions[f][1] - origin[1],
            positions[f][2] - origin[2],
        ];
        let k = (along[f] - d0) / gap;
        let in_row = dot(offset, row_dir) / pixel_spacing[1];
        let in_col = dot(offset, col_dir) / pixel_spacing[0];
        if (k - k.round()).abs() > POSITION_TOL
            || in_row.abs() > POSITION_TOL
            || in_col.abs() > POSITION_TOL
        {
            return Err(invalid(format!(
                "DICOM SEG frame {} at {:?} lies off the grid of frame {} ({gap} mm slices): shifted or tiled frames are not read",
                f + 1,
                positions[f],
                lowest + 1
            )));
        }
        seg_frames.push(SegFrame {
            index: f,
            segment: segments[f],
            slice: k.round() as u64,
        });
    }
    // Slice order, then ascending segment number so a higher one overwrites a lower one.
    seg_frames.sort_by_key(|f| (f.slice, f.segment, f.index));

    let geometry = VolumeGeometry {
        dims: crate::geometry::checked_dims([cols, rows, n_slices], path)?,
        spacing_mm: [pixel_spacing[1], pixel_spacing[0], gap],
        origin_lps_mm: origin,
        direction: [row_dir, col_dir, normal],
    };

    let pixel_data = obj
        .get(tags::PIXEL_DATA)
        .ok_or_else(|| invalid("DICOM SEG without PixelData".into()))?
        .to_bytes()
        .map_err(|e| invalid(format!("DICOM SEG PixelData unreadable: {e}")))?;
    let frame_pixels = rows * cols;
    let bits_per_pixel = if max_fraction.is_some() { 8 } else { 1 };
    let needed_bytes = (frame_pixels * n_frames as u64 * bits_per_pixel).div_ceil(8);
    if (pixel_data.len() as u64) < needed_bytes {
        return Err(invalid(format!(
            "DICOM SEG PixelData holds {} bytes, {n_frames} frames of {cols}x{rows} need {needed_bytes}",
            pixel_data.len()
        )));
    }
    let covered = |frame: usize, pixel: u64| -> bool {
        match max_fraction {
            None => {
                let bit = frame as u64 * frame_pixels + pixel;
                pixel_data[(bit / 8) as usize] >> (bit % 8) & 1 == 1
            }
            Some(max) => {
                let stored = pixel_data[(frame as u64 * frame_pixels + pixel) as usize];
                2 * u32::from(stored) >= max
            }
        }
    };

    let wide = labels.iter().any(|l| l.value > 255);
    let sample_type = if wide {
        SampleType::U16
    } else {
        SampleType::U8
    };
    let slice_pixels = frame_pixels as usize;
    let staging_bytes = geometry
        .dims_u64()
        .iter()
        .fold(sample_type.size_bytes() as u64, |acc, &d| {
            acc.saturating_mul(d)
        });
    let mut staging = new_staging(path, options.staging_dir.as_deref(), staging_bytes)?;
    {
        let mut out = BufWriter::with_capacity(1 << 20, staging.as_file_mut());
        let mut slice = vec![0u16; slice_pixels];
        let mut bytes = Vec::with_capacity(slice_pixels * sample_type.size_bytes());
        let mut next = 0;
        for k in 0..n_slices {
            slice.fill(0);
            while next < seg_frames.len() && seg_frames[next].slice == k {
                let f = seg_frames[next];
                for (p, v) in slice.iter_mut().enumerate() {
                    if covered(f.index, p as u64) {
                        *v = f.segment as u16;
                    }
                }
                next += 1;
            }
            bytes.clear();
            if wide {
                bytes.extend(slice.iter().flat_map(|v| v.to_le_bytes()));
            } else {
                bytes.extend(slice.iter().map(|&v| v as u8));
            }
            out.write_all(&bytes)
                .map_err(|e| StorageError::io(path, e))?;
        }
        out.flush().map_err(|e| StorageError::io(path, e))?;
    }
    let data = RawVolume::from_staging(
        staging,
        path,
        sample_type,
        ByteOrder::Little,
        geometry.dims_u64(),
    )?;
    let mut description = text(obj, tags::SERIES_DESCRIPTION)
        .or_else(|| text(obj, tags::CONTENT_LABEL))
        .unwrap_or_else(|| "segmentation".into());
    description.push_str(&format!(
        "; DICOM SEG ({seg_type}{}), {} segment(s), {n_frames} frames; label = segment number, the highest wins where segments overlap",
        if max_fraction.is_some() {
            ", fraction ≥ 0.5 labelled"
        } else {
            ""
        },
        labels.len()
    ));
    Ok(OpenedSource {
        info: SourceInfo {
            path: path.to_path_buf(),
            format: "dicom-seg".into(),
            geometry,
            sample_type,
            slope: 1.0,
            intercept: 0.0,
            modality: "SEG".into(),
            windows: Vec::new(),
            description,
            inputs: vec![path.to_path_buf()],
            labels,
            frames: 1,
        },
        data,
    })
}

/// An unsigned 16-bit multi-value (US VR) attribute.
fn obj_u16s(obj: &Obj, tag: Tag) -> Option<Vec<u16>> {
    obj.get(tag)?.to_multi_int::<u16>().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reference values from highdicom's CIELabColor (0.28): orange and a few primaries, ±1 for
    /// rounding in the two conversions.
    #[test]
    fn cielab_to_srgb_matches_highdicom() {
        for (lab, rgb) in [
            ([49107u16, 39048, 53188], [255u8, 165, 0]),
            ([38010, 43176, 40606], [215, 109, 89]),
            ([45874, 20046, 43176], [89, 192, 95]),
            ([26214, 38036, 17476], [19, 90, 194]),
            ([65535, 32896, 32896], [255, 255, 255]),
            ([0, 32896, 32896], [0, 0, 0]),
        ] {
            let got = dicom_lab_to_srgb(lab);
            for c in 0..3 {
                assert!(
                    (i32::from(got[c]) - i32::from(rgb[c])).abs() <= 1,
                    "{lab:?}: {got:?} vs {rgb:?}"
                );
            }
        }
    }
}
