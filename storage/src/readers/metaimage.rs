//! MetaImage (.mha with LOCAL data, .mhd with a separate data file), optionally zlib-compressed.
//! Points are in ITK's physical space, which is LPS; TransformMatrix is stored column-wise
//! (its first three values are the direction of the first index axis).

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use flate2::read::{MultiGzDecoder, ZlibDecoder};

use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::readers::common::{dims3, parse_f64s, parse_u64s, split_axis, volume_bytes};
use crate::readers::ReadOptions;
use crate::source::{ByteOrder, OpenedSource, RawVolume, SampleType, SourceInfo};
use crate::staging::{new_staging, stream_into};

const MAX_HEADER_LINE: usize = 64 * 1024;
const MAX_HEADER_LINES: usize = 1000;

fn element_type(name: &str) -> Option<SampleType> {
    Some(match name.trim().to_ascii_uppercase().as_str() {
        "MET_UCHAR" => SampleType::U8,
        "MET_CHAR" => SampleType::I8,
        "MET_USHORT" => SampleType::U16,
        "MET_SHORT" => SampleType::I16,
        "MET_UINT" | "MET_ULONG" => SampleType::U32,
        "MET_INT" | "MET_LONG" => SampleType::I32,
        "MET_FLOAT" => SampleType::F32,
        "MET_DOUBLE" => SampleType::F64,
        _ => return None,
    })
}

fn parse_bool(v: &str) -> bool {
    matches!(v.trim().to_ascii_lowercase().as_str(), "true" | "1" | "yes")
}

/// Direction of an index axis from one AnatomicalOrientation letter, in ITK's convention:
/// the letter names where the axis comes *from* ("RAI" is the identity in LPS).
fn orientation_letter(c: char) -> Option<[f64; 3]> {
    Some(match c.to_ascii_uppercase() {
        'R' => [1.0, 0.0, 0.0],
        'L' => [-1.0, 0.0, 0.0],
        'A' => [0.0, 1.0, 0.0],
        'P' => [0.0, -1.0, 0.0],
        'I' => [0.0, 0.0, 1.0],
        'S' => [0.0, 0.0, -1.0],
        _ => return None,
    })
}

pub(crate) fn open_metaimage(path: &Path, options: &ReadOptions) -> Result<OpenedSource> {
    let file = crate::regular_file::open(path)?;
    let mut r = BufReader::new(file);
    let mut consumed = 0u64;
    let mut fields: HashMap<String, String> = HashMap::new();
    let mut lines = 0;
    // The header ends with ElementDataFile; for LOCAL data the voxels start right after that line.
    loop {
        let mut buf = Vec::new();
        let n = r
            .by_ref()
            .take(MAX_HEADER_LINE as u64)
            .read_until(b'\n', &mut buf)
            .map_err(|e| StorageError::io(path, e))?;
        if n == 0 {
            return Err(StorageError::invalid(
                path,
                "MetaImage header ends without an ElementDataFile line",
            ));
        }
        consumed += n as u64;
        lines += 1;
        if lines > MAX_HEADER_LINES || (n == MAX_HEADER_LINE && buf.last() != Some(&b'\n')) {
            return Err(StorageError::invalid(
                path,
                "not a MetaImage header (no ElementDataFile in the first lines)",
            ));
        }
        let line = String::from_utf8_lossy(&buf);
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let Some((k, v)) = line.split_once('=') else {
            return Err(StorageError::invalid(
                path,
                format!(
                    "MetaImage header line without '=': '{}'",
                    line.chars().take(60).collect::<String>()
                ),
            ));
        };
        let key = k.trim().to_ascii_lowercase();
        let done = key == "elementdatafile";
        fields.insert(key, v.trim().to_string());
        if done {
            break;
        }
    }
    let get = |k: &str| fields.get(&k.to_ascii_lowercase()).map(String::as_str);
    let need = |k: &str| {
        get(k).ok_or_else(|| StorageError::invalid(path, format!("MetaImage header lacks {k}")))
    };

    let ndims: usize = need("NDims")?.parse().map_err(|_| {
        StorageError::invalid(
            path,
            format!(
                "MetaImage NDims '{}' is not a number",
                get("NDims").unwrap_or("")
            ),
        )
    })?;
    if !(2..=3).contains(&ndims) {
        return Err(StorageError::unsupported(
            path,
            format!("MetaImage NDims = {ndims} (only 2-D and 3-D images)"),
        ));
    }
    let sizes = parse_u64s(path, "DimSize", need("DimSize")?)?;
    if sizes.len() != ndims {
        return Err(StorageError::invalid(
            path,
            format!("MetaImage DimSize {sizes:?} does not match NDims {ndims}"),
        ));
    }
    let dims = dims3(path, "DimSize", &sizes)?;
    let et = need("ElementType")?;
    let sample_type = element_type(et).ok_or_else(|| {
        StorageError::unsupported(path, format!("MetaImage ElementType '{et}' (supported: MET_UCHAR, MET_CHAR, MET_USHORT, MET_SHORT, MET_UINT, MET_INT, MET_FLOAT, MET_DOUBLE)"))
    })?;
    if let Some(ch) = get("ElementNumberOfChannels") {
        if ch.trim() != "1" {
            return Err(StorageError::unsupported(
                path,
                format!("MetaImage with {ch} channels (only scalar images)"),
            ));
        }
    }
    let msb = get("BinaryDataByteOrderMSB")
        .or(get("ElementByteOrderMSB"))
        .is_some_and(parse_bool);
    let byte_order = if msb {
        ByteOrder::Big
    } else {
        ByteOrder::Little
    };
    let compressed = get("CompressedData").is_some_and(parse_bool);

    let geometry = meta_geometry(path, &get, ndims, dims)?;
    crate::geometry::validate(&geometry, path)?;
    let needed = volume_bytes(path, dims, sample_type.size_bytes())?;

    let data_spec = need("ElementDataFile")?.to_string();
    let (data_path, base) = if data_spec.eq_ignore_ascii_case("LOCAL") {
        (path.to_path_buf(), consumed)
    } else if data_spec.to_ascii_uppercase().starts_with("LIST")
        || (data_spec.split_whitespace().count() > 1 && data_spec.contains('%'))
    {
        return Err(StorageError::unsupported(
            path,
            format!("MetaImage multi-file ElementDataFile '{data_spec}'"),
        ));
    } else {
        let p = PathBuf::from(&data_spec);
        let full = if p.is_absolute() {
            p
        } else {
            path.parent().unwrap_or(Path::new(".")).join(p)
        };
        (full, 0)
    };
    drop(r);
    let header_size: i64 = match get("HeaderSize") {
        Some(v) => v.trim().parse().map_err(|_| {
            StorageError::invalid(path, format!("MetaImage HeaderSize '{v}' is not a number"))
        })?,
        None => 0,
    };

    crate::readers::common::check_data_file(path, &data_path)?;
    let data = if compressed {
        let f = crate::regular_file::open(&data_path)?;
        let mut br = BufReader::new(f);
        br.seek(SeekFrom::Start(base))
            .map_err(|e| StorageError::io(&data_path, e))?;
        // ITK writes zlib streams; some tools write gzip. The first two bytes tell them apart.
        let head = br.fill_buf().map_err(|e| StorageError::io(&data_path, e))?;
        let is_gzip = head.len() >= 2 && head[0] == 0x1f && head[1] == 0x8b;
        let mut staging = new_staging(path, options.staging_dir.as_deref(), needed)?;
        if is_gzip {
            stream_into(
                &data_path,
                &mut MultiGzDecoder::new(br),
                &mut staging,
                needed,
            )?;
        } else {
            stream_into(&data_path, &mut ZlibDecoder::new(br), &mut staging, needed)?;
        }
        RawVolume::from_staging(staging, &data_path, sample_type, byte_order, dims)?
    } else {
        let start = if header_size == -1 {
            // -1: the data sits at the end of the file, after a header of unknown size.
            let len = std::fs::metadata(&data_path)
                .map_err(|e| StorageError::io(&data_path, e))?
                .len();
            len.checked_sub(needed).ok_or_else(|| {
                StorageError::invalid(
                    &data_path,
                    format!("truncated data: {needed} bytes of voxels expected, file has {len}"),
                )
            })?
        } else if header_size >= 0 {
            base + header_size as u64
        } else {
            return Err(StorageError::invalid(
                path,
                format!("MetaImage HeaderSize {header_size}"),
            ));
        };
        RawVolume::map_file(&data_path, start, sample_type, byte_order, dims)?
    };

    let mut inputs = vec![path.to_path_buf()];
    if data_path != path {
        inputs.push(data_path);
    }
    let modality = match get("Modality").map(|m| m.trim().to_ascii_uppercase()) {
        Some(m) if m.starts_with("MET_MOD_") => m.trim_start_matches("MET_MOD_").to_string(),
        _ => String::new(),
    };
    Ok(OpenedSource {
        info: SourceInfo {
            path: path.to_path_buf(),
            format: "metaimage".into(),
            geometry,
            sample_type,
            slope: 1.0,
            intercept: 0.0,
            modality,
            windows: Vec::new(),
            description: get("Comment").unwrap_or("").to_string(),
            inputs,
            labels: Vec::new(),
            frames: 1,
        },
        data,
    })
}

fn meta_geometry<'a>(
    path: &Path,
    get: &impl Fn(&str) -> Option<&'a str>,
    ndims: usize,
    dims: [u64; 3],
) -> Result<VolumeGeometry> {
    let mut spacing = [1.0; 3];
    if let Some(s) = get("ElementSpacing").or(get("ElementSize")) {
        let v = parse_f64s(path, "ElementSpacing", s)?;
        if v.len() != ndims {
            return Err(StorageError::invalid(
                path,
                format!("MetaImage ElementSpacing {v:?} does not match NDims {ndims}"),
            ));
        }
        // Spacing is a length: zero, negative or not finite is nothing a scanner writes (a
        // flip belongs in TransformMatrix), and guessing which axis was meant would be silent.
        if let Some(bad) = v.iter().find(|s| !s.is_finite() || **s <= 0.0) {
            return Err(StorageError::invalid(
                path,
                format!("MetaImage ElementSpacing {v:?}: {bad} is not a positive, finite spacing"),
            ));
        }
        spacing[..ndims].copy_from_slice(&v);
    }
    let mut origin = [0.0; 3];
    if let Some(s) = get("Offset").or(get("Position")).or(get("Origin")) {
        let v = parse_f64s(path, "Offset", s)?;
        if v.len() != ndims {
            return Err(StorageError::invalid(
                path,
                format!("MetaImage Offset {v:?} does not match NDims {ndims}"),
            ));
        }
        origin[..ndims].copy_from_slice(&v);
    }
    let mut direction = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    if let Some(s) = get("TransformMatrix")
        .or(get("Rotation"))
        .or(get("Orientation"))
    {
        let v = parse_f64s(path, "TransformMatrix", s)?;
        if v.len() != ndims * ndims {
            return Err(StorageError::invalid(
                path,
                format!(
                    "MetaImage TransformMatrix has {} values, NDims {ndims} needs {}",
                    v.len(),
                    ndims * ndims
                ),
            ));
        }
        for a in 0..ndims {
            let mut col = [0.0; 3];
            col[..ndims].copy_from_slice(&v[a * ndims..(a + 1) * ndims]);
            direction[a] = col;
        }
    } else if let Some(o) = get("AnatomicalOrientation") {
        let letters: Vec<char> = o.trim().chars().collect();
        if letters.len() == 3 {
            if let (Some(a), Some(b), Some(c)) = (
                orientation_letter(letters[0]),
                orientation_letter(letters[1]),
                orientation_letter(letters[2]),
            ) {
                direction = [a, b, c];
            }
        }
    }
    if ndims == 2 {
        let n = crate::readers::common::cross(direction[0], direction[1]);
        direction[2] = split_axis(path, "slice normal", n)?.0;
    }
    Ok(VolumeGeometry {
        dims: crate::geometry::checked_dims(dims, path)?,
        spacing_mm: spacing,
        origin_lps_mm: origin,
        direction,
    })
}
