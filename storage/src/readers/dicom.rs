//! DICOM: a folder holding one or more series of single-frame slices, or one file (classic or
//! enhanced multi-frame). Headers are read without pixel data first; the pixels are then decoded
//! one slice (frame) at a time, in patient order, into a staging file.
//!
//! Slice spacing from the positions, then GridFrameOffsetVector, SpacingBetweenSlices,
//! SliceThickness; PixelSpacing falls back to ImagerPixelSpacing, then 1 mm. Anything assumed is
//! written into the description, as are lossy sources; RT Dose is scaled. Compressed pixel data
//! goes through dicom-pixeldata (RLE, JPEG 8-bit and lossless, JPEG 2000 via openjp2, JPEG-LS
//! via CharLS built through `cc` by the patched `vendor/charls-sys`; 12-bit JPEG: `jpeg12.rs`).

use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use dicom_core::value::Value as DicomValue;
use dicom_core::Tag;
use dicom_dictionary_std::{tags, uids};
use dicom_object::mem::InMemElement;
use dicom_object::{DefaultDicomObject, InMemDicomObject, OpenFileOptions};
use dicom_pixeldata::PixelDecoder;

use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::readers::common::{cross, dot, norm, split_axis};
use crate::readers::{has_dicom_preamble, ReadOptions};
use crate::source::{ByteOrder, OpenedSource, RawVolume, SampleType, SourceInfo, WindowPreset};
use crate::staging::new_staging;

/// Folders nested deeper than this are not searched (exports are rarely more than a few deep).
const MAX_DEPTH: usize = 8;
/// Relative and absolute tolerance on slice gaps: scanners round positions to ~1e-5 mm, and a
/// missing slice shows up as a 100 % jump, far outside this.
const GAP_REL_TOL: f64 = 0.01;
const GAP_ABS_TOL_MM: f64 = 1e-3;

/// One series found in a folder.
#[derive(Clone, Debug, PartialEq)]
pub struct DicomSeriesSummary {
    pub uid: String,
    pub series_number: Option<i64>,
    pub description: String,
    pub modality: String,
    /// Image frames (slices) in the series.
    pub slice_count: usize,
}

/// One 2-D image: a file's frame.
#[derive(Clone, Debug)]
struct FrameInfo {
    /// Index into the header list.
    file: usize,
    frame: u32,
    ipp: Option<[f64; 3]>,
    iop: Option<[f64; 6]>,
    pixel_spacing: Option<[f64; 2]>,
    slope: f64,
    intercept: f64,
    instance: i64,
    /// What tells the volumes of a multi-phase series apart, for this frame:
    /// TemporalPositionIndex / TemporalPositionIdentifier, TriggerTime, AcquisitionNumber.
    phase: [Option<f64>; 3],
}

/// The header of one image file (pixel data not read).
#[derive(Clone, Debug)]
struct ImageHeader {
    path: PathBuf,
    series_uid: String,
    series_number: Option<i64>,
    series_description: String,
    modality: String,
    /// SOPClassUID (a DICOM SEG is read by `dicom_seg`).
    sop_class: String,
    rows: u32,
    cols: u32,
    bits_allocated: u16,
    bits_stored: u16,
    signed: bool,
    samples_per_pixel: u16,
    photometric: String,
    windows: Vec<WindowPreset>,
    /// Slice spacing when positions cannot tell, and where it came from (for the description).
    gap_hint: Option<(f64, &'static str)>,
    /// The pixel data's transfer syntax UID.
    transfer_syntax: String,
    /// LossyImageCompression "01": the pixels went through a lossy codec at some point.
    lossy_history: bool,
    /// What the reader assumed or derived for this file (fallback spacings), for the description.
    notes: Vec<String>,
    /// RT Dose: DoseGridScaling (dose = stored · scaling) and DoseUnits ("GY", "RELATIVE").
    dose: Option<(f64, String)>,
    frames: Vec<FrameInfo>,
    /// File offset of uncompressed little-endian pixel data, when found: frames are then read
    /// straight from the file, so a multi-gigabyte multi-frame file never sits in memory.
    native_offset: Option<u64>,
}

type Obj = InMemDicomObject;

fn text(obj: &Obj, tag: Tag) -> Option<String> {
    let s = obj.get(tag)?.to_str().ok()?;
    let s = s.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    (!s.is_empty()).then(|| s.to_string())
}

fn floats(e: Option<&InMemElement>) -> Option<Vec<f64>> {
    let v = e?.to_multi_float64().ok()?;
    (!v.is_empty() && v.iter().all(|x| x.is_finite())).then_some(v)
}

fn int(obj: &Obj, tag: Tag) -> Option<i64> {
    obj.get(tag)?.to_int::<i64>().ok()
}

/// First item of sequence `seq` in `obj`.
fn seq_item(obj: &Obj, seq: Tag) -> Option<&Obj> {
    obj.get(seq)?.items()?.first()
}

/// An attribute of a functional group macro: per-frame item first, then the shared one, then the
/// top-level data set (classic images keep it there).
fn fg_attr<'a>(
    top: &'a Obj,
    groups: &[Option<&'a Obj>],
    seq: Tag,
    attr: Tag,
) -> Option<&'a InMemElement> {
    for g in groups.iter().flatten() {
        if let Some(e) = seq_item(g, seq).and_then(|item| item.get(attr)) {
            return Some(e);
        }
    }
    top.get(attr)
}

fn windows_from(obj: &Obj) -> Vec<WindowPreset> {
    let (Some(c), Some(w)) = (
        floats(obj.get(tags::WINDOW_CENTER)),
        floats(obj.get(tags::WINDOW_WIDTH)),
    ) else {
        return Vec::new();
    };
    let names: Vec<String> = text(obj, tags::WINDOW_CENTER_WIDTH_EXPLANATION)
        .map(|s| s.split('\\').map(|p| p.trim().to_string()).collect())
        .unwrap_or_default();
    c.iter()
        .zip(w.iter())
        .enumerate()
        .filter(|(_, (_, &w))| w > 0.0)
        .map(|(i, (&center, &width))| WindowPreset {
            name: names
                .get(i)
                .filter(|n| !n.is_empty())
                .cloned()
                .unwrap_or_else(|| format!("DICOM window {}", i + 1)),
            center,
            width,
        })
        .collect()
}

fn open_header(path: &Path) -> Result<DefaultDicomObject> {
    // Before dicom-rs, which would allocate whatever a damaged length field claims.
    crate::readers::dicom_bounds::check_element_lengths(path)?;
    OpenFileOptions::new()
        .read_until(tags::PIXEL_DATA)
        .open_file(path)
        .map_err(|e| StorageError::invalid(path, format!("unreadable DICOM file: {e}")))
}

/// Reads the image header of `path`; `Ok(None)` when the file holds no image (SR, DICOMDIR, ...).
fn read_header(path: &Path) -> Result<Option<ImageHeader>> {
    let obj = open_header(path)?;
    let (Some(rows), Some(cols)) = (int(&obj, tags::ROWS), int(&obj, tags::COLUMNS)) else {
        return Ok(None);
    };
    if rows <= 0 || cols <= 0 || rows > u32::MAX as i64 || cols > u32::MAX as i64 {
        return Err(StorageError::invalid(
            path,
            format!("DICOM image size {cols}x{rows}"),
        ));
    }
    let bits_allocated = int(&obj, tags::BITS_ALLOCATED).unwrap_or(16);
    let bits_stored = int(&obj, tags::BITS_STORED).unwrap_or(bits_allocated);
    if !(1..=bits_allocated).contains(&bits_stored) {
        return Err(StorageError::invalid(
            path,
            format!("BitsStored {bits_stored} must lie in 1..=BitsAllocated ({bits_allocated})"),
        ));
    }
    // Absent means one frame; present, it must be a positive number (0, -1 or text is damage,
    // and guessing "1" would import one frame of many).
    let n_frames = match obj.get(tags::NUMBER_OF_FRAMES) {
        None => 1,
        Some(e) => match e.to_int::<i64>() {
            Ok(n) if n >= 1 => n,
            _ => {
                return Err(StorageError::invalid(
                    path,
                    format!(
                        "NumberOfFrames {:?} is not a positive number",
                        e.to_str().map(|t| t.trim().to_string()).unwrap_or_default()
                    ),
                ))
            }
        },
    };
    if n_frames as u64 > crate::geometry::MAX_AXIS_VOXELS {
        return Err(StorageError::invalid(
            path,
            format!("absurd NumberOfFrames {n_frames}"),
        ));
    }
    let shared: Option<&Obj> = seq_item(&obj, tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE);
    let per_frame: &[Obj] = obj
        .get(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE)
        .and_then(|e| e.items())
        .unwrap_or(&[]);
    let instance = int(&obj, tags::INSTANCE_NUMBER).unwrap_or(0);

    let mut frames = Vec::with_capacity(n_frames as usize);
    for f in 0..n_frames as usize {
        let groups = [per_frame.get(f), shared];
        let ipp = floats(fg_attr(
            &obj,
            &groups,
            tags::PLANE_POSITION_SEQUENCE,
            tags::IMAGE_POSITION_PATIENT,
        ))
        .filter(|v| v.len() == 3)
        .map(|v| [v[0], v[1], v[2]]);
        let iop = floats(fg_attr(
            &obj,
            &groups,
            tags::PLANE_ORIENTATION_SEQUENCE,
            tags::IMAGE_ORIENTATION_PATIENT,
        ))
        .filter(|v| v.len() == 6)
        .map(|v| [v[0], v[1], v[2], v[3], v[4], v[5]]);
        let pixel_spacing = floats(fg_attr(
            &obj,
            &groups,
            tags::PIXEL_MEASURES_SEQUENCE,
            tags::PIXEL_SPACING,
        ))
        .filter(|v| v.len() == 2)
        .map(|v| [v[0], v[1]])
        .filter(|v| usable_spacing(*v));
        let slope = floats(fg_attr(
            &obj,
            &groups,
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_SLOPE,
        ))
        .and_then(|v| v.first().copied())
        .filter(|s| *s != 0.0)
        .unwrap_or(1.0);
        let intercept = floats(fg_attr(
            &obj,
            &groups,
            tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE,
            tags::RESCALE_INTERCEPT,
        ))
        .and_then(|v| v.first().copied())
        .unwrap_or(0.0);
        let temporal = per_frame
            .get(f)
            .and_then(|g| seq_item(g, tags::FRAME_CONTENT_SEQUENCE))
            .and_then(|c| int(c, tags::TEMPORAL_POSITION_INDEX))
            .or_else(|| int(&obj, tags::TEMPORAL_POSITION_IDENTIFIER))
            .map(|v| v as f64);
        let trigger = per_frame
            .get(f)
            .and_then(|g| seq_item(g, tags::CARDIAC_SYNCHRONIZATION_SEQUENCE))
            .and_then(|c| floats(c.get(tags::NOMINAL_CARDIAC_TRIGGER_DELAY_TIME)))
            .or_else(|| floats(obj.get(tags::TRIGGER_TIME)))
            .and_then(|v| v.first().copied());
        let acquisition = int(&obj, tags::ACQUISITION_NUMBER).map(|v| v as f64);
        frames.push(FrameInfo {
            file: 0,
            frame: f as u32,
            ipp,
            iop,
            pixel_spacing,
            slope,
            intercept,
            instance,
            phase: [temporal, trigger, acquisition],
        });
    }
    // In-plane spacing: a missing PixelSpacing and a zero one ("0\0", seen on CR) are treated
    // alike: ImagerPixelSpacing (at the detector) first, then 1 mm, saying so either way.
    let spacing_element = fg_attr(
        &obj,
        &[per_frame.first(), shared],
        tags::PIXEL_MEASURES_SEQUENCE,
        tags::PIXEL_SPACING,
    );
    let stated_spacing = floats(spacing_element);
    // Present but not numbers (NaN, 1e309 read as infinite, text): stated, and unusable.
    let stated_text = spacing_element
        .filter(|_| stated_spacing.is_none())
        .and_then(|e| e.to_str().ok())
        .map(|t| t.trim().to_string())
        .filter(|t| !t.is_empty());
    let mut notes = Vec::new();
    if frames.iter().any(|f| f.pixel_spacing.is_none()) {
        let what = match (&stated_spacing, &stated_text) {
            (Some(v), _) => format!("PixelSpacing {v:?} unusable"),
            (None, Some(t)) => format!("PixelSpacing '{t}' unusable"),
            (None, None) => "no PixelSpacing".to_string(),
        };
        let imager = floats(obj.get(tags::IMAGER_PIXEL_SPACING))
            .filter(|v| v.len() == 2)
            .map(|v| [v[0], v[1]])
            .filter(|v| usable_spacing(*v));
        let fallback = match imager {
            Some(v) => {
                notes.push(format!(
                    "{what}: ImagerPixelSpacing {}\\{} mm used (at the detector, not corrected for magnification)",
                    v[0], v[1]
                ));
                v
            }
            // A stated value no scanner means (zero, negative, not finite) is a warning, printed
            // by the import and kept in the description; an absent one is only a note.
            None if stated_spacing.is_some() || stated_text.is_some() => {
                notes.push(format!("{WARNING_PREFIX}{what}: 1 mm pixels assumed"));
                [1.0, 1.0]
            }
            None => {
                notes.push(format!("{what}: 1 mm pixels assumed"));
                [1.0, 1.0]
            }
        };
        for f in frames.iter_mut().filter(|f| f.pixel_spacing.is_none()) {
            f.pixel_spacing = Some(fallback);
        }
    }

    let groups0 = [per_frame.first(), shared];
    let positive = |tag: Tag| {
        floats(fg_attr(&obj, &groups0, tags::PIXEL_MEASURES_SEQUENCE, tag))
            .and_then(|v| v.first().copied())
            .filter(|v| *v > 0.0)
    };
    let gap_hint = positive(tags::SPACING_BETWEEN_SLICES)
        .map(|g| (g, "SpacingBetweenSlices"))
        .or_else(|| positive(tags::SLICE_THICKNESS).map(|g| (g, "SliceThickness")));

    // RT Dose and other classic multi-frame objects: GridFrameOffsetVector gives each frame's
    // offset along the slice normal (relative to the first frame when it starts at 0, absolute
    // otherwise; the difference to the first entry is right either way).
    let frame_offsets = floats(obj.get(tags::GRID_FRAME_OFFSET_VECTOR));
    if let Some(off) = &frame_offsets {
        if n_frames > 1 && off.len() != n_frames as usize {
            return Err(StorageError::invalid(
                path,
                format!(
                    "GridFrameOffsetVector has {} entries for {n_frames} frames",
                    off.len()
                ),
            ));
        }
    }

    // Classic multi-frame (NM, US, old MR, RT Dose) states one position for the whole stack;
    // step along the slice normal by the frame offsets or the slice gap so the frames still sort
    // and space correctly. Without either, 1 mm is assumed and said.
    if n_frames > 1 && per_frame.is_empty() {
        if let (Some(ipp), Some(iop)) = (frames[0].ipp, frames[0].iop) {
            let normal = cross([iop[0], iop[1], iop[2]], [iop[3], iop[4], iop[5]]);
            let step = |k: usize| -> f64 {
                match (&frame_offsets, gap_hint) {
                    (Some(off), _) => off[k] - off[0],
                    (None, Some((g, _))) => g * k as f64,
                    (None, None) => k as f64,
                }
            };
            for (k, fr) in frames.iter_mut().enumerate() {
                let d = step(k);
                fr.ipp = Some([
                    ipp[0] + normal[0] * d,
                    ipp[1] + normal[1] * d,
                    ipp[2] + normal[2] * d,
                ]);
            }
            if frame_offsets.is_none() && gap_hint.is_none() {
                notes.push(
                    "frames 1 mm apart assumed (no GridFrameOffsetVector, SpacingBetweenSlices or SliceThickness)"
                        .to_string(),
                );
            }
        }
    }

    let dose = if text(&obj, tags::MODALITY).as_deref() == Some("RTDOSE")
        || obj.get(tags::DOSE_GRID_SCALING).is_some()
    {
        let scaling = floats(obj.get(tags::DOSE_GRID_SCALING))
            .and_then(|v| v.first().copied())
            .filter(|s| *s != 0.0);
        let units = text(&obj, tags::DOSE_UNITS).unwrap_or_else(|| "unknown units".into());
        if let Some(s) = scaling {
            for f in frames.iter_mut() {
                // DoseGridScaling is the slope; RescaleSlope (rare in RT Dose) would multiply.
                f.slope *= s;
                f.intercept *= s;
            }
        }
        Some((scaling.unwrap_or(1.0), units))
    } else {
        None
    };

    let mut windows = shared
        .and_then(|s| seq_item(s, tags::FRAME_VOILUT_SEQUENCE))
        .map(windows_from)
        .unwrap_or_default();
    if windows.is_empty() {
        windows = per_frame
            .first()
            .and_then(|s| seq_item(s, tags::FRAME_VOILUT_SEQUENCE))
            .map(windows_from)
            .unwrap_or_default();
    }
    if windows.is_empty() {
        windows = windows_from(&obj);
    }

    let bytes_per_sample = (bits_allocated.max(0) as u64).div_ceil(8);
    let samples = int(&obj, tags::SAMPLES_PER_PIXEL).unwrap_or(1).max(1) as u64;
    let native_offset = if matches!(bits_allocated, 8 | 16 | 32) {
        (rows as u64)
            .checked_mul(cols as u64)
            .and_then(|n| n.checked_mul(bytes_per_sample * samples))
            .and_then(|n| n.checked_mul(n_frames as u64))
            .and_then(|len| locate_native_pixel_data(path, obj.meta().transfer_syntax(), len))
    } else {
        None
    };

    Ok(Some(ImageHeader {
        native_offset,
        transfer_syntax: obj
            .meta()
            .transfer_syntax()
            .trim_end_matches('\0')
            .to_string(),
        lossy_history: text(&obj, tags::LOSSY_IMAGE_COMPRESSION).as_deref() == Some("01"),
        notes,
        dose,
        path: path.to_path_buf(),
        series_uid: text(&obj, tags::SERIES_INSTANCE_UID).unwrap_or_default(),
        series_number: int(&obj, tags::SERIES_NUMBER),
        series_description: text(&obj, tags::SERIES_DESCRIPTION).unwrap_or_default(),
        modality: text(&obj, tags::MODALITY).unwrap_or_default(),
        sop_class: text(&obj, tags::SOP_CLASS_UID).unwrap_or_default(),
        rows: rows as u32,
        cols: cols as u32,
        bits_allocated: bits_allocated.clamp(0, u16::MAX as i64) as u16,
        bits_stored: bits_stored.clamp(0, u16::MAX as i64) as u16,
        signed: pixel_representation(path, &obj)?,
        samples_per_pixel: int(&obj, tags::SAMPLES_PER_PIXEL)
            .unwrap_or(1)
            .clamp(0, u16::MAX as i64) as u16,
        photometric: text(&obj, tags::PHOTOMETRIC_INTERPRETATION).unwrap_or_default(),
        windows,
        gap_hint,
        frames,
    }))
}

/// PixelRepresentation: 0 (unsigned) or 1 (two's complement); absent reads as 0. Any other
/// value is not something a scanner writes and says nothing about the sign, so it is refused.
fn pixel_representation(path: &Path, obj: &DefaultDicomObject) -> Result<bool> {
    match int(obj, tags::PIXEL_REPRESENTATION) {
        None | Some(0) => Ok(false),
        Some(1) => Ok(true),
        Some(other) => Err(StorageError::invalid(
            path,
            format!("PixelRepresentation {other} (only 0, unsigned, or 1, signed, exist)"),
        )),
    }
}

/// Transfer syntaxes whose PixelData is encapsulated (compressed fragments): the JPEG family
/// (baseline, extended, lossless, JPEG-LS, JPEG 2000, HTJ2K, JPEG XL, MPEG) and RLE.
fn is_encapsulated_transfer_syntax(uid: &str) -> bool {
    uid.starts_with("1.2.840.10008.1.2.4.") || uid == "1.2.840.10008.1.2.5"
}

/// Finds uncompressed pixel data by its element header at the end of the file, where Part 10
/// writers put it. dicom-object exposes no byte offsets, and this check (tag, VR and exact
/// length must all match) cannot mistake anything else for it; when it fails the file is
/// simply read through dicom-object instead.
fn locate_native_pixel_data(path: &Path, transfer_syntax: &str, len: u64) -> Option<u64> {
    use std::io::{Read, Seek, SeekFrom};
    let explicit = match transfer_syntax {
        uids::IMPLICIT_VR_LITTLE_ENDIAN => false,
        uids::EXPLICIT_VR_LITTLE_ENDIAN => true,
        _ => return None,
    };
    let header_len: u64 = if explicit { 12 } else { 8 };
    let file_len = std::fs::metadata(path).ok()?.len();
    // An odd-length value is padded to even length; the element's length field says which.
    for value_len in [len, len + 1] {
        let Some(start) = file_len
            .checked_sub(value_len)
            .filter(|s| *s >= header_len + 132)
        else {
            continue;
        };
        let mut f = crate::regular_file::open(path).ok()?;
        f.seek(SeekFrom::Start(start - header_len)).ok()?;
        let mut h = [0u8; 12];
        f.read_exact(&mut h[..header_len as usize]).ok()?;
        let len_field = (value_len as u32).to_le_bytes();
        let ok = if explicit {
            h[..4] == [0xE0, 0x7F, 0x10, 0x00]
                && (h[4..6] == *b"OW" || h[4..6] == *b"OB")
                && h[6..8] == [0, 0]
                && h[8..12] == len_field
        } else {
            h[..4] == [0xE0, 0x7F, 0x10, 0x00] && h[4..8] == len_field
        };
        if ok && u32::try_from(value_len).is_ok() {
            return Some(start);
        }
    }
    None
}

/// Most files a folder scan looks at: a whole study is a few thousand; beyond this the folder is
/// not a series (a home directory, a symlink farm) and the scan stops with an error.
const MAX_SCANNED_FILES: usize = 200_000;

/// Lists the regular files under `dir` (sorted, at most [`MAX_DEPTH`] deep). Follows a symlink
/// to a folder only once per real folder, so link cycles and fan-outs cost nothing; FIFOs,
/// sockets and devices are never opened (reading a FIFO blocks forever).
fn collect_files(
    dir: &Path,
    depth: usize,
    seen_dirs: &mut std::collections::HashSet<PathBuf>,
    out: &mut Vec<PathBuf>,
) -> Result<()> {
    let real = std::fs::canonicalize(dir).map_err(|e| StorageError::io(dir, e))?;
    if !seen_dirs.insert(real) {
        return Ok(());
    }
    let rd = std::fs::read_dir(dir).map_err(|e| StorageError::io(dir, e))?;
    let mut entries: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).collect();
    entries.sort();
    for p in entries {
        // Follows symlinks: a link to a slice is a slice; a dangling link is skipped.
        let Ok(meta) = std::fs::metadata(&p) else {
            continue;
        };
        if meta.is_dir() {
            if depth < MAX_DEPTH {
                collect_files(&p, depth + 1, seen_dirs, out)?;
            }
        } else if meta.is_file() {
            if out.len() >= MAX_SCANNED_FILES {
                return Err(StorageError::invalid(
                    dir,
                    format!("more than {MAX_SCANNED_FILES} files under this folder: point the import at the series' own folder"),
                ));
            }
            out.push(p);
        }
    }
    Ok(())
}

/// Scans a folder: image headers grouped by series, in listing order, and the errors of the
/// DICOM files that could not be read.
fn scan_folder(dir: &Path) -> Result<(Vec<Vec<ImageHeader>>, Vec<StorageError>)> {
    let mut files = Vec::new();
    collect_files(dir, 0, &mut Default::default(), &mut files)?;
    let mut dicom_files = 0usize;
    let mut headers = Vec::new();
    let mut unreadable: Vec<StorageError> = Vec::new();
    for f in &files {
        // Anything without the Part 10 preamble (READMEs, thumbnails, .DS_Store) is not ours.
        if !has_dicom_preamble(f) {
            continue;
        }
        dicom_files += 1;
        // A broken file is skipped rather than fatal: if it was a slice of the chosen series,
        // the gap it leaves is reported when the series is assembled.
        match read_header(f) {
            Ok(Some(h)) => headers.push(h),
            Ok(None) => {}
            Err(e) => unreadable.push(e),
        }
    }
    if headers.is_empty() {
        let mut message = if dicom_files == 0 {
            format!(
                "no DICOM files in this folder ({} files checked)",
                files.len()
            )
        } else {
            format!("none of the {dicom_files} DICOM files in this folder is an image")
        };
        if let Some(e) = unreadable.first() {
            message.push_str(&format!(
                "; {} could not be read, e.g. {e}",
                unreadable.len()
            ));
        }
        return Err(StorageError::invalid(dir, message));
    }
    let mut series: Vec<Vec<ImageHeader>> = Vec::new();
    for h in headers {
        match series.iter_mut().find(|s| s[0].series_uid == h.series_uid) {
            Some(s) => s.push(h),
            None => series.push(vec![h]),
        }
    }
    series.sort_by(|a, b| {
        (a[0].series_number.unwrap_or(i64::MAX), &a[0].series_uid)
            .cmp(&(b[0].series_number.unwrap_or(i64::MAX), &b[0].series_uid))
    });
    Ok((series, unreadable))
}

fn summary(s: &[ImageHeader]) -> DicomSeriesSummary {
    DicomSeriesSummary {
        uid: s[0].series_uid.clone(),
        series_number: s[0].series_number,
        description: s[0].series_description.clone(),
        modality: s[0].modality.clone(),
        slice_count: s.iter().map(|h| h.frames.len()).sum(),
    }
}

/// The image series in a DICOM folder, in the order `ReadOptions::dicom_series` indexes them.
pub fn list_dicom_series(dir: &Path) -> Result<Vec<DicomSeriesSummary>> {
    Ok(scan_folder(dir)?.0.iter().map(|s| summary(s)).collect())
}

pub(crate) fn open_series_dir(dir: &Path, options: &ReadOptions) -> Result<OpenedSource> {
    let (mut series, unreadable) = scan_folder(dir)?;
    // Which series an unreadable file belonged to is unknown, so any of them may be a missing
    // slice (a gap at either end of a series is invisible): never import around it silently.
    if let Some(first) = unreadable.first() {
        return Err(StorageError::invalid(
            dir,
            format!(
                "{} DICOM file(s) in this folder cannot be read, and may be slices of the series: {first}; repair or move them out of the folder to import the rest",
                unreadable.len()
            ),
        ));
    }
    let chosen = if series.len() == 1 {
        0
    } else {
        let listing = series
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let m = summary(s);
                format!(
                    "  [{i}] {} \"{}\" {} ({} slices)",
                    m.uid, m.description, m.modality, m.slice_count
                )
            })
            .collect::<Vec<_>>()
            .join("\n");
        match &options.dicom_series {
            None => {
                return Err(StorageError::invalid(
                    dir,
                    format!(
                        "folder holds {} DICOM series; choose one by UID or index:\n{listing}",
                        series.len()
                    ),
                ))
            }
            Some(sel) => {
                let sel = sel.trim();
                match series.iter().position(|s| s[0].series_uid == sel) {
                    Some(i) => i,
                    None => match sel.parse::<usize>() {
                        Ok(i) if i < series.len() => i,
                        _ => {
                            return Err(StorageError::invalid(
                                dir,
                                format!(
                                    "no DICOM series '{sel}' in this folder; it holds:\n{listing}"
                                ),
                            ))
                        }
                    },
                }
            }
        }
    };
    let headers = series.swap_remove(chosen);
    if let [h] = headers.as_slice() {
        if crate::readers::dicom_seg::is_segmentation(&h.sop_class, &h.modality) {
            return crate::readers::dicom_seg::open_dicom_seg(&h.path, options);
        }
    }
    assemble(dir, headers, options)
}

pub(crate) fn open_dicom_file(path: &Path, options: &ReadOptions) -> Result<OpenedSource> {
    match read_header(path)? {
        Some(h) if crate::readers::dicom_seg::is_segmentation(&h.sop_class, &h.modality) => {
            crate::readers::dicom_seg::open_dicom_seg(path, options)
        }
        Some(h) => assemble(path, vec![h], options),
        None => {
            let sop = open_header(path)
                .ok()
                .and_then(|o| text(&o, tags::SOP_CLASS_UID))
                .unwrap_or_default();
            Err(StorageError::invalid(
                path,
                format!("DICOM file holds no image (no Rows/Columns/PixelData; SOP class {sop})"),
            ))
        }
    }
}

/// Splits a series with several slices at each position into phases: by the first of
/// TemporalPositionIndex/Identifier, TriggerTime and AcquisitionNumber that every frame has and
/// that groups the frames into phases of equal size, each with every position once. Phase 0
/// (the lowest value) stays in `frames`; the others are returned in order. Nothing changes when
/// positions are distinct or no attribute splits them (the caller then names the duplicate).
fn split_phases(
    frames: &mut Vec<FrameInfo>,
    pos: &dyn Fn(&FrameInfo) -> f64,
) -> Vec<Vec<FrameInfo>> {
    let key = |p: f64| (p * 1e4).round() as i64;
    let mut positions: Vec<i64> = frames.iter().map(|f| key(pos(f))).collect();
    positions.sort_unstable();
    positions.dedup();
    if positions.len() == frames.len() || positions.is_empty() {
        return Vec::new();
    }
    for attr in 0..3 {
        if frames.iter().any(|f| f.phase[attr].is_none()) {
            continue;
        }
        let mut values: Vec<f64> = frames.iter().filter_map(|f| f.phase[attr]).collect();
        values.sort_by(f64::total_cmp);
        values.dedup();
        if values.len() < 2 || values.len() * positions.len() != frames.len() {
            continue;
        }
        let groups: Vec<Vec<FrameInfo>> = values
            .iter()
            .map(|v| {
                frames
                    .iter()
                    .filter(|f| f.phase[attr] == Some(*v))
                    .cloned()
                    .collect()
            })
            .collect();
        let complete = groups.iter().all(|g| {
            let mut p: Vec<i64> = g.iter().map(|f| key(pos(f))).collect();
            p.sort_unstable();
            p == positions
        });
        if complete {
            let mut groups = groups.into_iter();
            *frames = groups.next().unwrap_or_default();
            return groups.collect();
        }
    }
    Vec::new()
}

/// A pixel spacing that can enter the geometry: positive and finite ("0\0" is not).
/// Begins a description note that the import prints as a warning (see
/// [`crate::source::SourceInfo::warnings`]).
pub(crate) const WARNING_PREFIX: &str = crate::source::WARNING_PREFIX;

fn usable_spacing(v: [f64; 2]) -> bool {
    v.iter().all(|s| s.is_finite() && *s > 0.0)
}

/// The codec name of a transfer syntax whose pixels are lossy by definition, for the
/// description; JPEG-LS near-lossless (.81) counts because its error bound is above zero in
/// practice (a zero bound would have been written as .80).
fn lossy_transfer_syntax(uid: &str) -> Option<&'static str> {
    Some(match uid {
        uids::JPEG_BASELINE8_BIT => "JPEG baseline",
        uids::JPEG_EXTENDED12_BIT => "JPEG extended (12-bit)",
        uids::JPEG2000 => "JPEG 2000",
        uids::JPEG2000MC => "JPEG 2000 multi-component",
        uids::JPEGLS_NEAR_LOSSLESS => "JPEG-LS near-lossless",
        uids::HTJ2K => "HTJ2K",
        uids::JPEGXL => "JPEG XL",
        _ => return None,
    })
}

/// The pixel source of the file being decoded.
enum Loaded {
    Native(std::fs::File, u64),
    Object(Box<DefaultDicomObject>),
}

/// How the decoded samples are written to staging.
#[derive(Clone, Copy)]
enum Output {
    /// Stored integers, little-endian, bits above BitsStored cleared (sign-extended if signed).
    Stored(SampleType),
    /// Rescale differs between slices: physical values as f32, so one slope/intercept fits all.
    Physical,
}

fn sample_type_of(h: &ImageHeader) -> Result<SampleType> {
    if h.samples_per_pixel != 1 {
        return Err(StorageError::unsupported(
            &h.path,
            format!(
                "colour DICOM ({} samples per pixel); only greyscale volumes",
                h.samples_per_pixel
            ),
        ));
    }
    Ok(match (h.bits_allocated, h.signed) {
        (8, false) => SampleType::U8,
        (8, true) => SampleType::I8,
        (16, false) => SampleType::U16,
        (16, true) => SampleType::I16,
        (32, false) => SampleType::U32,
        (32, true) => SampleType::I32,
        (b, _) => {
            return Err(StorageError::unsupported(
                &h.path,
                format!("DICOM BitsAllocated {b} (only 8, 16, 32)"),
            ))
        }
    })
}

fn assemble(
    display: &Path,
    headers: Vec<ImageHeader>,
    options: &ReadOptions,
) -> Result<OpenedSource> {
    let first = &headers[0];
    let sample_type = sample_type_of(first)?;
    for h in &headers[1..] {
        if (
            h.rows,
            h.cols,
            h.bits_allocated,
            h.signed,
            h.samples_per_pixel,
        ) != (
            first.rows,
            first.cols,
            first.bits_allocated,
            first.signed,
            first.samples_per_pixel,
        ) {
            return Err(StorageError::invalid(
                &h.path,
                format!(
                    "slice differs from the rest of its series: {}x{} {}-bit{} vs {}x{} {}-bit{} in {}",
                    h.cols,
                    h.rows,
                    h.bits_allocated,
                    if h.signed { " signed" } else { "" },
                    first.cols,
                    first.rows,
                    first.bits_allocated,
                    if first.signed { " signed" } else { "" },
                    first.path.display()
                ),
            ));
        }
    }
    let mut frames: Vec<FrameInfo> = Vec::new();
    for (i, h) in headers.iter().enumerate() {
        for f in &h.frames {
            frames.push(FrameInfo {
                file: i,
                ..f.clone()
            });
        }
    }
    let where_ = |f: &FrameInfo| -> String {
        let p = headers[f.file].path.display();
        if headers[f.file].frames.len() > 1 {
            format!("{p} frame {}", f.frame + 1)
        } else {
            p.to_string()
        }
    };

    let mut notes: Vec<String> = Vec::new();
    if first.photometric.eq_ignore_ascii_case("MONOCHROME1") {
        // Values are kept as stored; only the display convention (high = dark) differs.
        notes.push("MONOCHROME1: low values are meant to display bright".to_string());
    }
    for n in &first.notes {
        notes.push(n.clone());
    }
    if let Some((scaling, units)) = &first.dose {
        notes.push(format!(
            "dose in {units} (DoseGridScaling {scaling} applied)"
        ));
    }
    if let Some(name) = lossy_transfer_syntax(&first.transfer_syntax) {
        notes.push(format!("lossy {name} source"));
    } else if first.lossy_history {
        notes.push(
            "lossy-compressed at some point (LossyImageCompression 01), stored uncompressed now"
                .to_string(),
        );
    }
    let pixel_spacing = frames[0].pixel_spacing.unwrap_or_else(|| {
        notes.push("no PixelSpacing: 1 mm assumed".to_string());
        [1.0, 1.0]
    });
    let positioned = frames.iter().all(|f| f.ipp.is_some() && f.iop.is_some());
    // A multi-phase series (cardiac phases, perfusion time points): phase 0 stays in `frames`
    // and makes the geometry; the other phases, each at the same positions, become frames of
    // the store (written after phase 0, one phase after the other).
    let mut later_phases: Vec<Vec<FrameInfo>> = Vec::new();
    let (direction, origin, slice_gap) = if positioned {
        let iop0 = frames[0].iop.unwrap_or([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        for f in &frames {
            let iop = f.iop.unwrap_or(iop0);
            if iop
                .iter()
                .zip(iop0.iter())
                .any(|(a, b)| (a - b).abs() > 1e-3)
            {
                return Err(StorageError::invalid(
                    display,
                    format!(
                        "slices have different orientations ({} has {:?}, {} has {:?}); a localizer or several stacks in one series?",
                        where_(&frames[0]),
                        iop0,
                        where_(f),
                        iop
                    ),
                ));
            }
        }
        let (row, _) = split_axis(
            display,
            "ImageOrientationPatient row",
            [iop0[0], iop0[1], iop0[2]],
        )?;
        let (col, _) = split_axis(
            display,
            "ImageOrientationPatient column",
            [iop0[3], iop0[4], iop0[5]],
        )?;
        let (normal, _) = split_axis(display, "slice normal", cross(row, col))?;
        let pos = |f: &FrameInfo| f.ipp.map_or(0.0, |p| dot(p, normal));
        later_phases = split_phases(&mut frames, &pos);
        frames.sort_by(|a, b| pos(a).total_cmp(&pos(b)));
        let n = frames.len();
        let p0 = frames[0].ipp.unwrap_or([0.0; 3]);
        if n == 1 {
            let gap = match first.gap_hint {
                Some((g, _)) => g,
                None => {
                    notes.push(
                        "single slice without SliceThickness: 1 mm thickness assumed".to_string(),
                    );
                    1.0
                }
            };
            ([row, col, normal], p0, gap)
        } else {
            for w in frames.windows(2) {
                if (pos(&w[1]) - pos(&w[0])).abs() < 1e-4 {
                    return Err(StorageError::invalid(
                        display,
                        format!(
                            "two slices at the same position {:.3} mm along the normal ({} and {}); the series holds several stacks (echoes, phases, time points), which is not a single volume",
                            pos(&w[0]),
                            where_(&w[0]),
                            where_(&w[1])
                        ),
                    ));
                }
            }
            // Judge gaps against the median: a missing slice is then the odd one out and gets named.
            let mut gaps: Vec<f64> = frames.windows(2).map(|w| pos(&w[1]) - pos(&w[0])).collect();
            gaps.sort_by(f64::total_cmp);
            let median = gaps[gaps.len() / 2];
            let tol = GAP_REL_TOL * median + GAP_ABS_TOL_MM;
            for w in frames.windows(2) {
                let gap = pos(&w[1]) - pos(&w[0]);
                if (gap - median).abs() > tol {
                    return Err(StorageError::invalid(
                        display,
                        format!(
                            "non-uniform slice spacing: gap of {gap:.4} mm between {} and {} while the other slices are {median:.4} mm apart (missing slice?)",
                            where_(&w[0]),
                            where_(&w[1])
                        ),
                    ));
                }
            }
            // The stack axis runs from the first to the last position, which is the normal for
            // ordinary series but tilted for gantry-tilt CT; using it keeps voxel centres exact.
            let pl = frames[n - 1].ipp.unwrap_or(p0);
            let stack = [pl[0] - p0[0], pl[1] - p0[1], pl[2] - p0[2]];
            let (axis, len) = split_axis(display, "slice stack direction", stack)?;
            // Evenly spaced along the normal is not enough: slices shifted in-plane (two stacks
            // interleaved, a moved table) would still be rendered as one block, misplaced.
            let step = len / (n - 1) as f64;
            let tol = GAP_REL_TOL * step + 10.0 * GAP_ABS_TOL_MM;
            for (k, f) in frames.iter().enumerate() {
                let p = f.ipp.unwrap_or(p0);
                let expected = [0, 1, 2].map(|c| p0[c] + axis[c] * step * k as f64);
                let off = norm([p[0] - expected[0], p[1] - expected[1], p[2] - expected[2]]);
                if off > tol {
                    return Err(StorageError::invalid(
                        display,
                        format!(
                            "slice {} ({}) lies {off:.3} mm off the line through the first and last slices; not one regular volume",
                            k + 1,
                            where_(f)
                        ),
                    ));
                }
            }
            ([row, col, axis], p0, step)
        }
    } else {
        // Without positions only the instance order and the stated thickness are left.
        if frames.len() > 1 {
            notes.push(
                "no patient positions: slices ordered by InstanceNumber, orientation unknown"
                    .to_string(),
            );
        }
        frames.sort_by_key(|f| (f.instance, f.file, f.frame));
        let gap = match first.gap_hint {
            Some((g, from)) => {
                if frames.len() > 1 {
                    notes.push(format!("slice spacing {g} mm from {from}"));
                }
                g
            }
            None => {
                notes.push(
                    "1 mm slice spacing assumed (no positions, SpacingBetweenSlices or SliceThickness)"
                        .to_string(),
                );
                1.0
            }
        };
        (
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            frames[0].ipp.unwrap_or([0.0; 3]),
            gap,
        )
    };
    if norm(cross(direction[0], direction[1])) < 1e-3 {
        return Err(StorageError::invalid(
            display,
            "ImageOrientationPatient row and column are parallel",
        ));
    }

    let dims = [first.cols as u64, first.rows as u64, frames.len() as u64];
    let phase_count = later_phases.len() as u64 + 1;
    if !later_phases.is_empty() {
        let along = |f: &FrameInfo| {
            f.ipp.map_or(0.0, |p| {
                dot(
                    [p[0] - origin[0], p[1] - origin[1], p[2] - origin[2]],
                    direction[2],
                )
            })
        };
        for (n, phase) in later_phases.iter_mut().enumerate() {
            phase.sort_by(|a, b| along(a).total_cmp(&along(b)));
            for (k, (f, f0)) in phase.iter().zip(frames.iter()).enumerate() {
                let off = norm(
                    [0, 1, 2].map(|c| f.ipp.unwrap_or([0.0; 3])[c] - f0.ipp.unwrap_or([0.0; 3])[c]),
                );
                if off > GAP_REL_TOL * slice_gap + 10.0 * GAP_ABS_TOL_MM {
                    return Err(StorageError::invalid(
                        display,
                        format!(
                            "phase {} slice {} ({}) lies {off:.3} mm from phase 1's slice {} ({}): the phases are not on one grid",
                            n + 2,
                            k + 1,
                            where_(f),
                            k + 1,
                            where_(f0)
                        ),
                    ));
                }
            }
        }
        notes.push(format!(
            "{phase_count} phases (time points) at the same positions, each a frame of the store"
        ));
    }
    let later_count = later_phases.len();
    frames.extend(later_phases.into_iter().flatten());
    let data_dims = [dims[0], dims[1], dims[2] * phase_count];
    let geometry = VolumeGeometry {
        dims: crate::geometry::checked_dims(dims, display)?,
        // PixelSpacing is (row spacing, column spacing): the step along j, then along i.
        spacing_mm: [pixel_spacing[1], pixel_spacing[0], slice_gap],
        origin_lps_mm: origin,
        direction,
    };
    crate::geometry::validate(&geometry, display)?;

    let uniform = frames.iter().all(|f| {
        (f.slope - frames[0].slope).abs() <= 1e-9 * frames[0].slope.abs()
            && (f.intercept - frames[0].intercept).abs()
                <= 1e-9 * frames[0].intercept.abs().max(1.0)
    });
    let (output, out_type, slope, intercept) = if uniform {
        (
            Output::Stored(sample_type),
            sample_type,
            frames[0].slope,
            frames[0].intercept,
        )
    } else {
        (Output::Physical, SampleType::F32, 1.0, 0.0)
    };

    let staging_bytes = data_dims
        .iter()
        .fold(out_type.size_bytes() as u64, |acc, &d| {
            acc.saturating_mul(d)
        });
    let mut staging = new_staging(display, options.staging_dir.as_deref(), staging_bytes)?;
    {
        let mut out = BufWriter::with_capacity(1 << 20, staging.as_file_mut());
        let mut cur: Option<(usize, Loaded)> = None;
        let mut buf: Vec<u8> = Vec::new();
        let mut raw: Vec<u8> = Vec::new();
        for f in &frames {
            let h = &headers[f.file];
            if cur.as_ref().map(|c| c.0) != Some(f.file) {
                // Release the previous file before loading the next: one slice in memory at a time.
                drop(cur.take());
                let loaded = match h.native_offset {
                    Some(off) => Loaded::Native(crate::regular_file::open(&h.path)?, off),
                    None => {
                        Loaded::Object(Box::new(dicom_object::open_file(&h.path).map_err(|e| {
                            StorageError::invalid(&h.path, format!("unreadable DICOM file: {e}"))
                        })?))
                    }
                };
                cur = Some((f.file, loaded));
            }
            let Some((_, loaded)) = cur.as_mut() else {
                continue;
            };
            buf.clear();
            match loaded {
                Loaded::Native(file, off) => {
                    use std::io::{Read, Seek, SeekFrom};
                    let frame_len =
                        h.rows as usize * h.cols as usize * (h.bits_allocated / 8) as usize;
                    raw.resize(frame_len, 0);
                    file.seek(SeekFrom::Start(*off + f.frame as u64 * frame_len as u64))
                        .and_then(|_| file.read_exact(&mut raw))
                        .map_err(|e| {
                            StorageError::invalid(
                                &h.path,
                                format!("reading frame {}: {e}", f.frame + 1),
                            )
                        })?;
                    convert(
                        h,
                        &raw,
                        ByteOrder::Little,
                        output,
                        f.slope,
                        f.intercept,
                        &mut buf,
                    );
                }
                Loaded::Object(obj) => decode_frame(
                    h,
                    obj,
                    f.frame,
                    output,
                    (f.slope, f.intercept),
                    &mut buf,
                    &mut notes,
                )?,
            }
            out.write_all(&buf)
                .map_err(|e| StorageError::io(display, e))?;
        }
        out.flush().map_err(|e| StorageError::io(display, e))?;
    }
    let data = RawVolume::from_staging(staging, display, out_type, ByteOrder::Little, data_dims)?;

    let mut description = first.series_description.clone();
    for n in notes {
        if !description.is_empty() {
            description.push_str("; ");
        }
        description.push_str(&n);
    }
    Ok(OpenedSource {
        info: SourceInfo {
            path: display.to_path_buf(),
            format: "dicom".into(),
            geometry,
            sample_type: out_type,
            slope,
            intercept,
            modality: first.modality.clone(),
            windows: first.windows.clone(),
            description,
            inputs: vec![display.to_path_buf()],
            labels: Vec::new(),
            frames: later_count as u32 + 1,
        },
        data,
    })
}

/// Byte order of pixel data held by dicom-object (it stores values in host order).
const NATIVE: ByteOrder = if cfg!(target_endian = "big") {
    ByteOrder::Big
} else {
    ByteOrder::Little
};

/// Appends frame `frame` of `obj` to `out` in the staging layout.
fn decode_frame(
    h: &ImageHeader,
    obj: &DefaultDicomObject,
    frame: u32,
    output: Output,
    (slope, intercept): (f64, f64),
    out: &mut Vec<u8>,
    notes: &mut Vec<String>,
) -> Result<()> {
    let bytes_per = (h.bits_allocated / 8) as usize;
    let frame_len = h.rows as usize * h.cols as usize * bytes_per;
    let pixel = obj.get(tags::PIXEL_DATA).ok_or_else(|| {
        StorageError::invalid(
            &h.path,
            "DICOM image has no PixelData (float or double pixel data are not supported)",
        )
    })?;
    // Native (uncompressed) pixel data is used as it is: dicom-object already holds it in native
    // byte order, and decoding it through dicom-pixeldata would only add a copy and stricter checks.
    let decoded;
    let src: &[u8] = match pixel.value() {
        DicomValue::Primitive(p) => {
            // A compressed transfer syntax with plain bytes in PixelData contradicts itself:
            // which one is wrong cannot be told, so neither is trusted.
            if is_encapsulated_transfer_syntax(&h.transfer_syntax) {
                return Err(StorageError::invalid(
                    &h.path,
                    format!(
                        "its transfer syntax {} says compressed (encapsulated) pixel data, but PixelData holds uncompressed bytes",
                        h.transfer_syntax
                    ),
                ));
            }
            let all = p.to_bytes();
            // The whole element must be the frames the header describes (plus one pad byte for
            // an odd length): 16-bit data read with BitsAllocated 8, or frames missing from
            // NumberOfFrames, would otherwise import as plausible garbage.
            let expected = h.frames.len() * frame_len;
            if all.len() != expected && all.len() != expected + (expected & 1) {
                return Err(StorageError::invalid(
                    &h.path,
                    format!(
                        "PixelData holds {} bytes, but {} frame(s) of {}x{} at BitsAllocated {} need {expected}: BitsAllocated, Rows, Columns or NumberOfFrames is wrong",
                        all.len(),
                        h.frames.len(),
                        h.cols,
                        h.rows,
                        h.bits_allocated
                    ),
                ));
            }
            let start = frame as usize * frame_len;
            let Some(slice) = all.get(start..start + frame_len) else {
                return Err(StorageError::invalid(
                    &h.path,
                    format!(
                        "truncated data: PixelData has {} bytes, frame {} of {}x{} {}-bit needs bytes {start}..{}",
                        all.len(),
                        frame + 1,
                        h.cols,
                        h.rows,
                        h.bits_allocated,
                        start + frame_len
                    ),
                ));
            };
            convert(h, slice, NATIVE, output, slope, intercept, out);
            return Ok(());
        }
        value if h.transfer_syntax == uids::JPEG_EXTENDED12_BIT && h.bits_allocated == 16 => {
            let jpeg = frame_fragments(h, value, frame)?;
            let (samples, repaired) = crate::readers::jpeg12::decode_12bit_frame(
                &h.path,
                frame + 1,
                &jpeg,
                h.cols,
                h.rows,
            )?;
            if let Some(note) = repaired {
                if !notes.iter().any(|n| n == note) {
                    notes.push(note.to_string());
                }
            }
            let bytes: Vec<u8> = samples.iter().flat_map(|v| v.to_ne_bytes()).collect();
            convert(h, &bytes, NATIVE, output, slope, intercept, out);
            return Ok(());
        }
        value => {
            if let Some(codec) = codestream_with_end_marker(&h.transfer_syntax) {
                // A cut codestream makes CharLS spin for many seconds and OpenJPEG decode a
                // degraded image without an error: both end in a marker, checked first.
                if let Ok(bytes) = frame_fragments(h, value, frame) {
                    check_end_marker(h, &bytes, frame, codec)?;
                }
            }
            let ts = obj.meta().transfer_syntax().to_string();
            decoded = obj.decode_pixel_data_frame(frame).map_err(|e| {
                StorageError::unsupported(
                    &h.path,
                    format!("cannot decode pixel data (transfer syntax {ts}): {e}"),
                )
            })?;
            decoded.data()
        }
    };
    if src.len() < frame_len {
        return Err(StorageError::invalid(
            &h.path,
            format!(
                "decoded frame {} has {} bytes, {} expected",
                frame + 1,
                src.len(),
                frame_len
            ),
        ));
    }
    convert(h, &src[..frame_len], NATIVE, output, slope, intercept, out);
    Ok(())
}

/// Codecs whose codestream must end in the end-of-image (JPEG-LS EOI) or end-of-codestream
/// (JPEG 2000 EOC) marker, 0xFFD9 in both.
fn codestream_with_end_marker(uid: &str) -> Option<&'static str> {
    Some(match uid {
        uids::JPEGLS_LOSSLESS | uids::JPEGLS_NEAR_LOSSLESS => "JPEG-LS",
        uids::JPEG2000_LOSSLESS | uids::JPEG2000 | uids::JPEG2000MC_LOSSLESS | uids::JPEG2000MC => {
            "JPEG 2000"
        }
        _ => return None,
    })
}

/// Refuses a codestream that does not end in 0xFFD9, after the padding that makes DICOM
/// fragments even (zeros, or one byte of any value: NEMA's MR2_J2KR pads with 0xFF): it was cut
/// short.
fn check_end_marker(h: &ImageHeader, bytes: &[u8], frame: u32, codec: &str) -> Result<()> {
    let end = bytes.iter().rposition(|&b| b != 0).map_or(0, |i| i + 1);
    let ends_at = |e: usize| e >= 2 && bytes[e - 2..e] == [0xFF, 0xD9];
    if ends_at(end) || ends_at(end.saturating_sub(1)) {
        return Ok(());
    }
    Err(StorageError::invalid(
        &h.path,
        format!(
            "truncated data: the {codec} codestream of frame {} ({} bytes) does not end in its end marker (FFD9); the file was cut short or damaged",
            frame + 1,
            bytes.len()
        ),
    ))
}

/// The encoded bytes of frame `frame` of encapsulated pixel data: one fragment per frame, all
/// fragments for a single frame, or the fragments the Basic Offset Table assigns to it.
fn frame_fragments(
    h: &ImageHeader,
    value: &DicomValue<Obj, dicom_core::value::InMemFragment>,
    frame: u32,
) -> Result<Vec<u8>> {
    let (Some(fragments), Some(table)) = (value.fragments(), value.offset_table()) else {
        return Err(StorageError::invalid(
            &h.path,
            "PixelData is not encapsulated although the transfer syntax is compressed",
        ));
    };
    let n_frames = h.frames.len();
    let f = frame as usize;
    if n_frames == 1 {
        return Ok(fragments.concat());
    }
    if fragments.len() == n_frames {
        return Ok(fragments[f].clone());
    }
    if table.len() == n_frames {
        // Offsets count from the first fragment's item header; each item header is 8 bytes.
        let mut out = Vec::new();
        let mut at = 0u64;
        let start = u64::from(table[f]);
        let end = table.get(f + 1).map_or(u64::MAX, |&e| u64::from(e));
        for frag in fragments {
            if at >= start && at < end {
                out.extend_from_slice(frag);
            }
            at += 8 + frag.len() as u64;
        }
        if !out.is_empty() {
            return Ok(out);
        }
    }
    Err(StorageError::invalid(
        &h.path,
        format!(
            "cannot tell which of the {} PixelData fragments hold frame {} of {n_frames} (no usable offset table)",
            fragments.len(),
            frame + 1
        ),
    ))
}

/// Native-endian samples → staging bytes, masking bits above BitsStored (some scanners keep
/// overlays there) and sign-extending signed values.
fn convert(
    h: &ImageHeader,
    src: &[u8],
    order: ByteOrder,
    output: Output,
    slope: f64,
    intercept: f64,
    out: &mut Vec<u8>,
) {
    let bits = h.bits_stored.clamp(1, h.bits_allocated.max(1)) as u32;
    let signed = h.signed;
    let fix = |v: u64, width: u32| -> i64 {
        let bits = bits.min(width);
        let mask = if bits >= 64 {
            u64::MAX
        } else {
            (1u64 << bits) - 1
        };
        let v = v & mask;
        if signed && bits < 64 && v & (1u64 << (bits - 1)) != 0 {
            (v | !mask) as i64
        } else {
            v as i64
        }
    };
    let mut emit = |v: i64| match output {
        Output::Stored(t) => match t {
            SampleType::U8 | SampleType::I8 => out.push(v as u8),
            SampleType::U16 | SampleType::I16 => out.extend_from_slice(&(v as u16).to_le_bytes()),
            _ => out.extend_from_slice(&(v as u32).to_le_bytes()),
        },
        Output::Physical => {
            out.extend_from_slice(&((v as f64 * slope + intercept) as f32).to_le_bytes())
        }
    };
    match h.bits_allocated {
        8 => src.iter().for_each(|&b| emit(fix(b as u64, 8))),
        16 => src.chunks_exact(2).for_each(|c| {
            let a = [c[0], c[1]];
            let v = if order == ByteOrder::Little {
                u16::from_le_bytes(a)
            } else {
                u16::from_be_bytes(a)
            };
            emit(fix(v as u64, 16))
        }),
        _ => src.chunks_exact(4).for_each(|c| {
            let a = [c[0], c[1], c[2], c[3]];
            let v = if order == ByteOrder::Little {
                u32::from_le_bytes(a)
            } else {
                u32::from_be_bytes(a)
            };
            emit(fix(v as u64, 32))
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reading pixel data straight from the file must give exactly what dicom-object decodes.
    #[test]
    fn native_offset_path_matches_object_path() {
        let d = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/niivue");
        if !d.is_dir() {
            eprintln!("SKIP: real test data not found at {}", d.display());
            return;
        }
        for f in ["enh.dcm", "dicom-mr-3slices/1-001.dcm"] {
            let p = d.join(f);
            let h = read_header(&p).unwrap().unwrap();
            assert!(
                h.native_offset.is_some(),
                "{f}: pixel data not located in the file"
            );
            let mut h2 = h.clone();
            h2.native_offset = None;
            let a = assemble(&p, vec![h], &ReadOptions::default()).unwrap();
            let b = assemble(&p, vec![h2], &ReadOptions::default()).unwrap();
            let (mut va, mut vb) = (Vec::new(), Vec::new());
            for k in 0..a.data.dims[2] {
                a.data.read_slice_f64(k, &mut va);
                b.data.read_slice_f64(k, &mut vb);
                assert_eq!(va, vb, "{f} slice {k}");
            }
        }
    }
}
