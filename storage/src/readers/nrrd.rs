//! NRRD (.nrrd with attached header, .nhdr with detached data), raw and gzip encodings.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use flate2::read::MultiGzDecoder;

use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::readers::common::{dims3, geometry_from_axes, parse_f64s, parse_u64s, volume_bytes};
use crate::readers::ReadOptions;
use crate::source::{ByteOrder, OpenedSource, RawVolume, SampleType, SourceInfo};
use crate::staging::{new_staging, skip_bytes, stream_into};

/// Header lines longer than this mean we are reading binary data, not a header.
const MAX_HEADER_LINE: usize = 64 * 1024;

/// NRRD type names, all spellings the format allows.
pub(crate) fn nrrd_type(name: &str) -> Option<SampleType> {
    let n = name.trim().to_ascii_lowercase();
    Some(match n.as_str() {
        "signed char" | "int8" | "int8_t" => SampleType::I8,
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => SampleType::U8,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => {
            SampleType::I16
        }
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => {
            SampleType::U16
        }
        "int" | "signed int" | "int32" | "int32_t" => SampleType::I32,
        "uint" | "unsigned int" | "uint32" | "uint32_t" => SampleType::U32,
        "float" => SampleType::F32,
        "double" => SampleType::F64,
        _ => return None,
    })
}

/// Reads one '\n'-terminated header line (CR stripped); `None` at end of file.
fn read_line(path: &Path, r: &mut impl BufRead, consumed: &mut u64) -> Result<Option<String>> {
    let mut buf = Vec::new();
    let n = r
        .by_ref()
        .take(MAX_HEADER_LINE as u64)
        .read_until(b'\n', &mut buf)
        .map_err(|e| StorageError::io(path, e))?;
    if n == 0 {
        return Ok(None);
    }
    if n == MAX_HEADER_LINE && buf.last() != Some(&b'\n') {
        return Err(StorageError::invalid(
            path,
            "NRRD header line too long (missing blank line before data?)",
        ));
    }
    *consumed += n as u64;
    while matches!(buf.last(), Some(b'\n') | Some(b'\r')) {
        buf.pop();
    }
    Ok(Some(String::from_utf8_lossy(&buf).into_owned()))
}

/// Parses a vector like "(1.5,0,0)"; "none" gives `None`.
fn parse_vector(path: &Path, what: &str, text: &str) -> Result<Option<Vec<f64>>> {
    let t = text.trim();
    if t.eq_ignore_ascii_case("none") {
        return Ok(None);
    }
    let inner = t
        .strip_prefix('(')
        .and_then(|s| s.strip_suffix(')'))
        .ok_or_else(|| {
            StorageError::invalid(path, format!("{what}: expected '(x,y,z)', got '{t}'"))
        })?;
    parse_f64s(path, what, inner).map(Some)
}

/// Splits "(a,b,c) (d,e,f) none" into its vectors.
fn split_vectors(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut depth = 0;
    for ch in text.chars() {
        match ch {
            '(' => {
                depth += 1;
                cur.push(ch);
            }
            ')' => {
                depth -= 1;
                cur.push(ch);
                if depth == 0 {
                    out.push(std::mem::take(&mut cur));
                }
            }
            c if c.is_whitespace() && depth == 0 => {
                if !cur.trim().is_empty() {
                    out.push(std::mem::take(&mut cur));
                }
                cur.clear();
            }
            c => cur.push(c),
        }
    }
    if !cur.trim().is_empty() {
        out.push(cur);
    }
    out
}

/// Matrix (row a = what LPS becomes) turning vectors of a NRRD `space` into LPS.
fn space_to_lps(path: &Path, space: &str) -> Result<[f64; 3]> {
    let s = space.trim().to_ascii_lowercase();
    Ok(match s.as_str() {
        "left-posterior-superior" | "lps" => [1.0, 1.0, 1.0],
        "right-anterior-superior" | "ras" => [-1.0, -1.0, 1.0],
        "left-anterior-superior" | "las" => [1.0, -1.0, 1.0],
        // Scanner and generic right-handed frames have no anatomical meaning; keep them as they are.
        "scanner-xyz" | "3d-right-handed" | "3d-left-handed" => [1.0, 1.0, 1.0],
        other => {
            return Err(StorageError::unsupported(
                path,
                format!("NRRD space '{other}' (supported: left-posterior-superior, right-anterior-superior, left-anterior-superior, scanner-xyz, 3D-right-handed)"),
            ))
        }
    })
}

pub(crate) fn open_nrrd(path: &Path, options: &ReadOptions) -> Result<OpenedSource> {
    let file = crate::regular_file::open(path)?;
    let mut r = BufReader::new(file);
    let mut consumed = 0u64;
    let magic = read_line(path, &mut r, &mut consumed)?.unwrap_or_default();
    if !magic.starts_with("NRRD000") {
        return Err(StorageError::invalid(
            path,
            format!(
                "not a NRRD file (first line '{}')",
                magic.chars().take(40).collect::<String>()
            ),
        ));
    }
    let mut fields: HashMap<String, String> = HashMap::new();
    loop {
        match read_line(path, &mut r, &mut consumed)? {
            None => break,
            Some(line) if line.is_empty() => break,
            Some(line) if line.starts_with('#') => {}
            Some(line) => {
                // Key/value pairs ("key:=value") are free-form metadata; only fields ("key: value") matter.
                if line.contains(":=") {
                    continue;
                }
                if let Some((k, v)) = line.split_once(": ") {
                    fields.insert(k.trim().to_ascii_lowercase(), v.trim().to_string());
                } else if let Some((k, v)) = line.split_once(':') {
                    fields.insert(k.trim().to_ascii_lowercase(), v.trim().to_string());
                }
            }
        }
    }
    let get = |k: &str| fields.get(k).map(String::as_str);
    let need = |k: &str| {
        get(k).ok_or_else(|| {
            StorageError::invalid(path, format!("NRRD header lacks the required '{k}' field"))
        })
    };

    let type_name = need("type")?;
    let sample_type = nrrd_type(type_name).ok_or_else(|| {
        StorageError::unsupported(
            path,
            format!("NRRD type '{type_name}' (supported: 8/16/32-bit integers, float, double)"),
        )
    })?;
    let dimension: usize = need("dimension")?.parse().map_err(|_| {
        StorageError::invalid(
            path,
            format!(
                "NRRD dimension '{}' is not a number",
                get("dimension").unwrap_or("")
            ),
        )
    })?;
    let sizes = parse_u64s(path, "sizes", need("sizes")?)?;
    if sizes.len() != dimension {
        return Err(StorageError::invalid(
            path,
            format!("NRRD sizes {sizes:?} do not match dimension {dimension}"),
        ));
    }
    if dimension > 3 {
        return Err(StorageError::unsupported(
            path,
            format!("{dimension}-D NRRD (only 3-D scalar volumes; sizes {sizes:?})"),
        ));
    }
    let dims = dims3(path, "sizes", &sizes)?;
    if let Some(kinds) = get("kinds") {
        // Colour, vector or list axes would otherwise be read as a spatial axis of a few voxels.
        for (a, kind) in kinds.split_whitespace().enumerate() {
            let k = kind.to_ascii_lowercase();
            let spatial = matches!(k.as_str(), "domain" | "space" | "???" | "none")
                || (matches!(k.as_str(), "stub" | "scalar") && sizes.get(a) == Some(&1));
            if !spatial {
                return Err(StorageError::unsupported(
                    path,
                    format!("NRRD axis {a} has kind '{kind}'; only scalar volumes with spatial axes are supported"),
                ));
            }
        }
    }
    let byte_order = match get("endian").map(|s| s.to_ascii_lowercase()) {
        Some(e) if e == "big" => ByteOrder::Big,
        Some(e) if e == "little" => ByteOrder::Little,
        Some(e) => {
            return Err(StorageError::invalid(
                path,
                format!("NRRD endian '{e}' (expected little or big)"),
            ))
        }
        // Only single-byte types may omit it; little is what every writer in practice uses.
        None => ByteOrder::Little,
    };
    let encoding = need("encoding")?.to_ascii_lowercase();
    #[derive(PartialEq)]
    enum Encoding {
        Raw,
        Gzip,
        Ascii,
    }
    let enc = match encoding.as_str() {
        "raw" => Encoding::Raw,
        "gzip" | "gz" => Encoding::Gzip,
        "ascii" | "text" | "txt" => Encoding::Ascii,
        other => {
            return Err(StorageError::unsupported(
                path,
                format!("NRRD encoding '{other}' (supported: raw, gzip, ascii)"),
            ))
        }
    };

    let geometry = nrrd_geometry(path, &fields, dimension, dims)?;
    crate::geometry::validate(&geometry, path)?;
    let needed = volume_bytes(path, dims, sample_type.size_bytes())?;

    let line_skip: u64 = match get("line skip").or(get("lineskip")) {
        Some(v) => v.parse().map_err(|_| {
            StorageError::invalid(path, format!("NRRD line skip '{v}' is not a count"))
        })?,
        None => 0,
    };
    let byte_skip: i64 = match get("byte skip").or(get("byteskip")) {
        Some(v) => v.parse().map_err(|_| {
            StorageError::invalid(path, format!("NRRD byte skip '{v}' is not a number"))
        })?,
        None => 0,
    };
    if byte_skip < -1 {
        return Err(StorageError::invalid(
            path,
            format!("NRRD byte skip {byte_skip} (only -1 or a count is valid)"),
        ));
    }

    let (data_path, base_offset) = match get("data file").or(get("datafile")) {
        None => (path.to_path_buf(), consumed),
        Some(spec) => {
            // "LIST" and "pattern min max step" forms spread slices over many files; a plain
            // name (even one with spaces) is a single file.
            let tokens: Vec<&str> = spec.split_whitespace().collect();
            if spec.starts_with("LIST") || (tokens.len() > 1 && tokens[0].contains('%')) {
                return Err(StorageError::unsupported(
                    path,
                    format!("NRRD multi-file 'data file: {spec}'"),
                ));
            }
            let p = PathBuf::from(spec);
            let full = if p.is_absolute() {
                p
            } else {
                path.parent().unwrap_or(Path::new(".")).join(p)
            };
            (full, 0)
        }
    };
    drop(r);

    crate::readers::common::check_data_file(path, &data_path)?;
    let data_file = crate::regular_file::open(&data_path)?;
    let mut dr = BufReader::new(data_file);
    dr.seek(SeekFrom::Start(base_offset))
        .map_err(|e| StorageError::io(&data_path, e))?;
    let mut offset = base_offset;
    for _ in 0..line_skip {
        if read_line(&data_path, &mut dr, &mut offset)?.is_none() {
            return Err(StorageError::invalid(
                &data_path,
                format!("truncated data: fewer than {line_skip} lines to skip"),
            ));
        }
    }

    let data = if enc == Encoding::Ascii {
        let mut staging = new_staging(path, options.staging_dir.as_deref(), needed)?;
        stage_ascii(&data_path, &mut dr, &mut staging, sample_type, dims)?;
        RawVolume::from_staging(staging, &data_path, sample_type, ByteOrder::Little, dims)?
    } else if enc == Encoding::Gzip {
        if byte_skip == -1 {
            return Err(StorageError::unsupported(
                path,
                "NRRD byte skip -1 with gzip encoding",
            ));
        }
        let mut z = MultiGzDecoder::new(dr);
        // For compressed encodings the byte skip counts decompressed bytes (NRRD spec).
        skip_bytes(&data_path, &mut z, byte_skip as u64, "byte skip")?;
        let mut staging = new_staging(path, options.staging_dir.as_deref(), needed)?;
        stream_into(&data_path, &mut z, &mut staging, needed)?;
        RawVolume::from_staging(staging, &data_path, sample_type, byte_order, dims)?
    } else {
        let len = std::fs::metadata(&data_path)
            .map_err(|e| StorageError::io(&data_path, e))?
            .len();
        let start = if byte_skip == -1 {
            len.checked_sub(needed).ok_or_else(|| {
                StorageError::invalid(
                    &data_path,
                    format!("truncated data: {needed} bytes of voxels expected, file has {len}"),
                )
            })?
        } else {
            offset + byte_skip as u64
        };
        RawVolume::map_file(&data_path, start, sample_type, byte_order, dims)?
    };

    let mut inputs = vec![path.to_path_buf()];
    if data_path != path {
        inputs.push(data_path);
    }
    Ok(OpenedSource {
        info: SourceInfo {
            path: path.to_path_buf(),
            format: "nrrd".into(),
            geometry,
            sample_type,
            slope: 1.0,
            intercept: 0.0,
            modality: String::new(),
            windows: Vec::new(),
            description: get("content").unwrap_or("").to_string(),
            inputs,
            labels: Vec::new(),
            frames: 1,
        },
        data,
    })
}

/// Parses whitespace/comma separated numbers into little-endian samples, one token at a time.
fn stage_ascii(
    path: &Path,
    r: &mut impl BufRead,
    staging: &mut crate::staging::StagingFile,
    sample_type: SampleType,
    dims: [u64; 3],
) -> Result<()> {
    use std::io::Write;
    let total = dims[0] * dims[1] * dims[2];
    let mut out = std::io::BufWriter::with_capacity(1 << 20, staging.as_file_mut());
    let mut token = Vec::with_capacity(32);
    let mut count = 0u64;
    let mut emit = |tok: &[u8], count: &mut u64| -> Result<()> {
        let text = std::str::from_utf8(tok).unwrap_or("?");
        let v: f64 = text.parse().map_err(|_| {
            StorageError::invalid(
                path,
                format!("ascii NRRD value {} is '{text}', not a number", *count + 1),
            )
        })?;
        let bytes: Vec<u8> = match sample_type {
            SampleType::U8 => vec![v as u8],
            SampleType::I8 => vec![v as i8 as u8],
            SampleType::U16 => (v as u16).to_le_bytes().to_vec(),
            SampleType::I16 => (v as i16).to_le_bytes().to_vec(),
            SampleType::U32 => (v as u32).to_le_bytes().to_vec(),
            SampleType::I32 => (v as i32).to_le_bytes().to_vec(),
            SampleType::F32 => (v as f32).to_le_bytes().to_vec(),
            SampleType::F64 => v.to_le_bytes().to_vec(),
        };
        out.write_all(&bytes)
            .map_err(|e| StorageError::io(path, e))?;
        *count += 1;
        Ok(())
    };
    let mut bytes = r.bytes();
    while count < total {
        match bytes.next() {
            Some(Ok(b)) if b.is_ascii_whitespace() || b == b',' => {
                if !token.is_empty() {
                    emit(&token, &mut count)?;
                    token.clear();
                }
            }
            Some(Ok(b)) => {
                if token.len() > 64 {
                    return Err(StorageError::invalid(
                        path,
                        "ascii NRRD data holds a token too long to be a number",
                    ));
                }
                token.push(b)
            }
            Some(Err(e)) => return Err(StorageError::io(path, e)),
            None => {
                if !token.is_empty() {
                    emit(&token, &mut count)?;
                    token.clear();
                }
                break;
            }
        }
    }
    out.flush().map_err(|e| StorageError::io(path, e))?;
    if count < total {
        return Err(StorageError::invalid(
            path,
            format!("truncated data: ascii NRRD holds {count} values, {dims:?} needs {total}"),
        ));
    }
    Ok(())
}

fn nrrd_geometry(
    path: &Path,
    fields: &HashMap<String, String>,
    dimension: usize,
    dims: [u64; 3],
) -> Result<VolumeGeometry> {
    let get = |k: &str| fields.get(k).map(String::as_str);
    let space_sign = match get("space") {
        Some(s) => space_to_lps(path, s)?,
        // "space dimension" without a named space: a generic frame, kept as is.
        None => [1.0, 1.0, 1.0],
    };
    let to_lps = |v: &[f64]| -> Result<[f64; 3]> {
        if v.len() != 3 {
            return Err(StorageError::unsupported(
                path,
                format!("NRRD space vector {v:?} is not 3-D"),
            ));
        }
        Ok([
            v[0] * space_sign[0],
            v[1] * space_sign[1],
            v[2] * space_sign[2],
        ])
    };
    let origin = match get("space origin") {
        Some(o) => match parse_vector(path, "space origin", o)? {
            Some(v) => to_lps(&v)?,
            None => [0.0; 3],
        },
        None => [0.0; 3],
    };
    if let Some(sd) = get("space directions") {
        let parts = split_vectors(sd);
        if parts.len() != dimension {
            return Err(StorageError::invalid(
                path,
                format!(
                    "NRRD space directions has {} entries for dimension {dimension}: '{sd}'",
                    parts.len()
                ),
            ));
        }
        let mut axes = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        for (a, part) in parts.iter().enumerate() {
            match parse_vector(path, "space directions", part)? {
                Some(v) => axes[a] = to_lps(&v)?,
                None => {
                    return Err(StorageError::unsupported(
                        path,
                        format!("NRRD axis {a} is not spatial ('none' in space directions)"),
                    ))
                }
            }
        }
        if dimension == 2 {
            // A single slice: the missing axis is the slice normal, 1 mm thick.
            let n = crate::readers::common::cross(axes[0], axes[1]);
            let (d, _) = crate::readers::common::split_axis(path, "slice normal", n)?;
            axes[2] = d;
        }
        return geometry_from_axes(path, dims, axes, origin);
    }
    let mut spacing = [1.0; 3];
    let mut g_dirs = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    if let Some(s) = get("spacings") {
        let v = parse_f64s(path, "spacings", s)?;
        if v.len() != dimension {
            return Err(StorageError::invalid(
                path,
                format!("NRRD spacings {v:?} do not match dimension {dimension}"),
            ));
        }
        for (a, x) in v.into_iter().enumerate() {
            if x.is_nan() {
                return Err(StorageError::invalid(
                    path,
                    format!("NRRD spacings '{s}' contain NaN"),
                ));
            }
            // A negative spacing is a flip: it belongs in the direction, spacing stays positive.
            spacing[a] = x.abs();
            if x < 0.0 {
                g_dirs[a][a] = -1.0;
            }
        }
    }
    let mut g = VolumeGeometry::axis_aligned(crate::geometry::checked_dims(dims, path)?, spacing);
    g.direction = g_dirs;
    g.origin_lps_mm = origin;
    Ok(g)
}
