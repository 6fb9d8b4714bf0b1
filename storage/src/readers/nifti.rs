//! NIfTI-1 and NIfTI-2 (.nii, .nii.gz, .hdr/.img). The header is parsed here rather than with the
//! `nifti` crate because that crate loads whole volumes; voxels are mapped or staged instead.

use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

use flate2::read::MultiGzDecoder;

use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::readers::common::{dims3, flip_xy, geometry_from_axes, volume_bytes};
use crate::readers::ReadOptions;
use crate::source::{ByteOrder, OpenedSource, RawVolume, SampleType, SourceInfo, WindowPreset};
use crate::staging::{new_staging, skip_bytes, stream_into};

const NIFTI1_SIZE: usize = 348;
const NIFTI2_SIZE: usize = 540;

/// The header fields Strata uses, widened to the NIfTI-2 types.
#[derive(Debug)]
struct Header {
    version: u8,
    order: ByteOrder,
    dim: [i64; 8],
    datatype: i16,
    pixdim: [f64; 8],
    vox_offset: f64,
    scl_slope: f64,
    scl_inter: f64,
    cal_min: f64,
    cal_max: f64,
    descrip: String,
    qform_code: i32,
    sform_code: i32,
    quatern: [f64; 3],
    qoffset: [f64; 3],
    srow: [[f64; 4]; 3],
    /// Single-file (.nii) rather than a .hdr/.img pair.
    single_file: bool,
}

struct Fields<'a> {
    b: &'a [u8],
    order: ByteOrder,
}

impl Fields<'_> {
    fn arr<const N: usize>(&self, at: usize) -> [u8; N] {
        let mut a = [0u8; N];
        a.copy_from_slice(&self.b[at..at + N]);
        a
    }
    fn i16(&self, at: usize) -> i16 {
        match self.order {
            ByteOrder::Little => i16::from_le_bytes(self.arr(at)),
            ByteOrder::Big => i16::from_be_bytes(self.arr(at)),
        }
    }
    fn i32(&self, at: usize) -> i32 {
        match self.order {
            ByteOrder::Little => i32::from_le_bytes(self.arr(at)),
            ByteOrder::Big => i32::from_be_bytes(self.arr(at)),
        }
    }
    fn i64(&self, at: usize) -> i64 {
        match self.order {
            ByteOrder::Little => i64::from_le_bytes(self.arr(at)),
            ByteOrder::Big => i64::from_be_bytes(self.arr(at)),
        }
    }
    fn f32(&self, at: usize) -> f64 {
        (match self.order {
            ByteOrder::Little => f32::from_le_bytes(self.arr(at)),
            ByteOrder::Big => f32::from_be_bytes(self.arr(at)),
        }) as f64
    }
    fn f64(&self, at: usize) -> f64 {
        match self.order {
            ByteOrder::Little => f64::from_le_bytes(self.arr(at)),
            ByteOrder::Big => f64::from_be_bytes(self.arr(at)),
        }
    }
    fn text(&self, at: usize, len: usize) -> String {
        let raw = &self.b[at..at + len];
        let end = raw.iter().position(|&c| c == 0).unwrap_or(len);
        String::from_utf8_lossy(&raw[..end]).trim().to_string()
    }
}

/// Reads up to `buf.len()` bytes; fewer only at end of stream.
fn read_full(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut done = 0;
    while done < buf.len() {
        match r.read(&mut buf[done..]) {
            Ok(0) => break,
            Ok(n) => done += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(done)
}

/// Parses the header from the start of `r`, leaving `r` just past the bytes consumed
/// (returned as the second value).
fn parse_header(path: &Path, r: &mut impl Read) -> Result<(Header, u64)> {
    let mut buf = vec![0u8; NIFTI2_SIZE];
    let got = read_full(r, &mut buf[..NIFTI1_SIZE]).map_err(|e| {
        StorageError::invalid(
            path,
            format!("reading NIfTI header (truncated or corrupt file?): {e}"),
        )
    })?;
    if got < NIFTI1_SIZE {
        return Err(StorageError::invalid(
            path,
            format!("truncated NIfTI header: {got} bytes, at least {NIFTI1_SIZE} needed"),
        ));
    }
    let le = i32::from_le_bytes([buf[0], buf[1], buf[2], buf[3]]);
    let be = i32::from_be_bytes([buf[0], buf[1], buf[2], buf[3]]);
    let (version, order) = match (le, be) {
        (348, _) => (1, ByteOrder::Little),
        (_, 348) => (1, ByteOrder::Big),
        (540, _) => (2, ByteOrder::Little),
        (_, 540) => (2, ByteOrder::Big),
        _ => {
            return Err(StorageError::invalid(
                path,
                format!("not a NIfTI file: sizeof_hdr is {le} (expected 348 or 540)"),
            ))
        }
    };
    let mut consumed = NIFTI1_SIZE as u64;
    if version == 2 {
        let more = read_full(r, &mut buf[NIFTI1_SIZE..]).map_err(|e| {
            StorageError::invalid(
                path,
                format!("reading NIfTI-2 header (truncated or corrupt file?): {e}"),
            )
        })?;
        if more < NIFTI2_SIZE - NIFTI1_SIZE {
            return Err(StorageError::invalid(path, "truncated NIfTI-2 header"));
        }
        consumed = NIFTI2_SIZE as u64;
    }
    let f = Fields { b: &buf, order };
    let h = if version == 1 {
        let magic = &buf[344..348];
        let single_file = match magic {
            b"n+1\0" => true,
            b"ni1\0" => false,
            // Pre-NIfTI ANALYZE 7.5 headers have no magic; read them like a .hdr/.img pair.
            _ => false,
        };
        let mut dim = [0i64; 8];
        let mut pixdim = [0f64; 8];
        for i in 0..8 {
            dim[i] = f.i16(40 + 2 * i) as i64;
            pixdim[i] = f.f32(76 + 4 * i);
        }
        let mut srow = [[0f64; 4]; 3];
        for (r, row) in srow.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = f.f32(280 + 16 * r + 4 * c);
            }
        }
        Header {
            version,
            order,
            dim,
            datatype: f.i16(70),
            pixdim,
            vox_offset: f.f32(108),
            scl_slope: f.f32(112),
            scl_inter: f.f32(116),
            cal_max: f.f32(124),
            cal_min: f.f32(128),
            descrip: f.text(148, 80),
            qform_code: f.i16(252) as i32,
            sform_code: f.i16(254) as i32,
            quatern: [f.f32(256), f.f32(260), f.f32(264)],
            qoffset: [f.f32(268), f.f32(272), f.f32(276)],
            srow,
            single_file,
        }
    } else {
        let magic = &buf[4..12];
        if &magic[..3] != b"n+2" && &magic[..3] != b"ni2" {
            return Err(StorageError::invalid(
                path,
                format!("bad NIfTI-2 magic {magic:?}"),
            ));
        }
        let mut dim = [0i64; 8];
        let mut pixdim = [0f64; 8];
        for i in 0..8 {
            dim[i] = f.i64(16 + 8 * i);
            pixdim[i] = f.f64(104 + 8 * i);
        }
        let mut srow = [[0f64; 4]; 3];
        for (r, row) in srow.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = f.f64(400 + 32 * r + 8 * c);
            }
        }
        Header {
            version,
            order,
            dim,
            datatype: f.i16(12),
            pixdim,
            vox_offset: f.i64(168) as f64,
            scl_slope: f.f64(176),
            scl_inter: f.f64(184),
            cal_max: f.f64(192),
            cal_min: f.f64(200),
            descrip: f.text(240, 80),
            qform_code: f.i32(344),
            sform_code: f.i32(348),
            quatern: [f.f64(352), f.f64(360), f.f64(368)],
            qoffset: [f.f64(376), f.f64(384), f.f64(392)],
            srow,
            single_file: &magic[..3] == b"n+2",
        }
    };
    Ok((h, consumed))
}

fn sample_type(path: &Path, datatype: i16) -> Result<SampleType> {
    Ok(match datatype {
        2 => SampleType::U8,
        4 => SampleType::I16,
        8 => SampleType::I32,
        16 => SampleType::F32,
        64 => SampleType::F64,
        256 => SampleType::I8,
        512 => SampleType::U16,
        768 => SampleType::U32,
        other => {
            let name = match other {
                1 => "binary",
                32 => "complex64",
                128 => "RGB24",
                1024 => "int64",
                1280 => "uint64",
                1536 => "float128",
                1792 => "complex128",
                2048 => "complex256",
                2304 => "RGBA32",
                _ => "unknown",
            };
            return Err(StorageError::unsupported(
                path,
                format!("NIfTI datatype {other} ({name}); supported: uint8, int8, uint16, int16, uint32, int32, float32, float64"),
            ));
        }
    })
}

/// Index→patient geometry in LPS: sform if set, else qform, else pixdim only (NIfTI "method 1").
fn geometry(path: &Path, h: &Header, dims: [u64; 3]) -> Result<VolumeGeometry> {
    if h.sform_code > 0 {
        let mut axes = [[0.0; 3]; 3];
        for (a, axis) in axes.iter_mut().enumerate() {
            *axis = flip_xy([h.srow[0][a], h.srow[1][a], h.srow[2][a]]);
        }
        let origin = flip_xy([h.srow[0][3], h.srow[1][3], h.srow[2][3]]);
        let g = geometry_from_axes(path, dims, axes, origin);
        // A writer that set sform_code but left the rows empty still usually has a good qform.
        match g {
            Ok(g) => return Ok(g),
            Err(e) if h.qform_code <= 0 => return Err(e),
            Err(_) => {}
        }
    }
    let spacing = [h.pixdim[1].abs(), h.pixdim[2].abs(), h.pixdim[3].abs()];
    if h.qform_code > 0 {
        let [b, c, d] = h.quatern;
        let sum = b * b + c * c + d * d;
        // nifti1_io: a rounding error can push b²+c²+d² past 1; then a = 0 and (b,c,d) renormalised.
        let (a, b, c, d) = if 1.0 - sum > 1e-7 {
            ((1.0 - sum).sqrt(), b, c, d)
        } else {
            let n = sum.sqrt();
            if n.is_nan() || n <= 0.0 {
                return Err(StorageError::invalid(
                    path,
                    format!("degenerate qform quaternion {:?}", h.quatern),
                ));
            }
            (0.0, b / n, c / n, d / n)
        };
        let r = [
            [
                a * a + b * b - c * c - d * d,
                2.0 * (b * c - a * d),
                2.0 * (b * d + a * c),
            ],
            [
                2.0 * (b * c + a * d),
                a * a + c * c - b * b - d * d,
                2.0 * (c * d - a * b),
            ],
            [
                2.0 * (b * d - a * c),
                2.0 * (c * d + a * b),
                a * a + d * d - c * c - b * b,
            ],
        ];
        // qfac lives in pixdim[0]; anything but a negative value means +1 (the spec's rule).
        let qfac = if h.pixdim[0] < 0.0 { -1.0 } else { 1.0 };
        let mut direction = [[0.0; 3]; 3];
        for (a_idx, dir) in direction.iter_mut().enumerate() {
            let s = if a_idx == 2 { qfac } else { 1.0 };
            *dir = flip_xy([r[0][a_idx] * s, r[1][a_idx] * s, r[2][a_idx] * s]);
        }
        return Ok(VolumeGeometry {
            dims: crate::geometry::checked_dims(dims, path)?,
            spacing_mm: spacing,
            origin_lps_mm: flip_xy(h.qoffset),
            direction,
        });
    }
    Ok(VolumeGeometry {
        dims: crate::geometry::checked_dims(dims, path)?,
        spacing_mm: spacing,
        origin_lps_mm: [0.0; 3],
        // Method 1 puts index axes along RAS x, y, z; in LPS that flips the first two.
        direction: [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]],
    })
}

/// Gzip is recognised by its magic bytes, not the name: tools save gzipped data as ".nii" and
/// the reverse often enough.
fn is_gz(path: &Path) -> bool {
    let mut magic = [0u8; 2];
    crate::regular_file::open(path).is_ok_and(|mut f| f.read_exact(&mut magic).is_ok())
        && magic == [0x1f, 0x8b]
}

/// The .img that goes with a .hdr (or .hdr.gz): same stem, compressed if one exists that way.
fn image_file_for(path: &Path) -> Result<PathBuf> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_default();
    let lower = name.to_ascii_lowercase();
    let stem_len = if lower.ends_with(".hdr.gz") {
        name.len() - 7
    } else {
        name.len() - 4
    };
    let stem = &name[..stem_len];
    for ext in [".img", ".IMG", ".img.gz", ".IMG.GZ"] {
        let candidate = path.with_file_name(format!("{stem}{ext}"));
        if candidate.exists() {
            return Ok(candidate);
        }
    }
    Err(StorageError::invalid(
        path,
        format!("NIfTI/ANALYZE header without its image file {stem}.img"),
    ))
}

pub(crate) fn open_nifti(path: &Path, options: &ReadOptions) -> Result<OpenedSource> {
    let file = crate::regular_file::open(path)?;
    let gz = is_gz(path);
    let mut reader: Box<dyn Read> = if gz {
        Box::new(MultiGzDecoder::new(BufReader::new(file)))
    } else {
        Box::new(BufReader::new(file))
    };
    let (h, consumed) = parse_header(path, &mut reader)?;

    let ndim = h.dim[0];
    if !(1..=7).contains(&ndim) {
        return Err(StorageError::invalid(
            path,
            format!("dim[0] = {ndim} (must be 1..7)"),
        ));
    }
    let raw_dims: Vec<i64> = h.dim[1..=ndim as usize].to_vec();
    if let Some(bad) = raw_dims.iter().find(|&&d| d <= 0) {
        return Err(StorageError::invalid(
            path,
            format!("zero dimension: dim {raw_dims:?} contains {bad}"),
        ));
    }
    // A 4-D series (dim[4] > 1: time points) imports every volume as a frame; they lie one
    // after the other in the data. Of dimensions 5..7 (vector components and the like) only the
    // first volume is read.
    let frames = raw_dims.get(3).copied().unwrap_or(1);
    if frames as u64 > crate::geometry::MAX_AXIS_VOXELS {
        return Err(StorageError::invalid(
            path,
            format!("absurd dim[4] = {frames} (time points)"),
        ));
    }
    let frames = frames as u64;
    let extra_volumes: i64 = raw_dims
        .iter()
        .skip(4)
        .fold(1i64, |acc, &d| acc.saturating_mul(d));
    let spatial: Vec<u64> = raw_dims.iter().take(3).map(|&d| d as u64).collect();
    let dims = dims3(path, "dim", &spatial)?;
    let sample_type = sample_type(path, h.datatype)?;
    let geometry = geometry(path, &h, dims)?;
    crate::geometry::validate(&geometry, path)?;
    // Every frame: the voxels are read as one stack of dims[2] · frames slices.
    let data_dims = [dims[0], dims[1], dims[2].saturating_mul(frames)];
    let needed = volume_bytes(path, data_dims, sample_type.size_bytes())?;

    let slope = if h.scl_slope == 0.0 || !h.scl_slope.is_finite() {
        1.0
    } else {
        h.scl_slope
    };
    let intercept = if h.scl_inter.is_finite() {
        h.scl_inter
    } else {
        0.0
    };
    let mut windows = Vec::new();
    if h.cal_max.is_finite() && h.cal_min.is_finite() && h.cal_max > h.cal_min {
        windows.push(WindowPreset {
            name: "cal_min/cal_max".into(),
            center: 0.5 * (h.cal_min + h.cal_max),
            width: h.cal_max - h.cal_min,
        });
    }
    let mut description = h.descrip.clone();
    if extra_volumes > 1 {
        if !description.is_empty() {
            description.push_str("; ");
        }
        description.push_str(&format!(
            "first of {extra_volumes} volumes per time point (dimensions 5-7)"
        ));
    }

    let lower = path.to_string_lossy().to_ascii_lowercase();
    if !h.single_file && (lower.ends_with(".nii") || lower.ends_with(".nii.gz")) {
        return Err(StorageError::invalid(
            path,
            "NIfTI magic is not \"n+1\"/\"n+2\" (a .nii file must hold its own data; corrupt header?)",
        ));
    }
    let (data_path, data_offset, data_gz) = if h.single_file {
        // A single file holds the header, then 4 extension-flag bytes, then any extensions:
        // voxels start at 352 (NIfTI-1) or 544 (NIfTI-2) at the earliest. An offset inside
        // that, or a fractional one, would read the voxels shifted.
        let earliest = consumed as f64 + 4.0;
        if !(h.vox_offset.is_finite() && h.vox_offset >= earliest && h.vox_offset.fract() == 0.0) {
            return Err(StorageError::invalid(
                path,
                format!(
                    "vox_offset {} must be a whole number of bytes at or after {earliest} (the header and its extension flag)",
                    h.vox_offset
                ),
            ));
        }
        (path.to_path_buf(), h.vox_offset as u64, gz)
    } else {
        let img = image_file_for(path)?;
        let off = if h.vox_offset.is_finite() && h.vox_offset > 0.0 {
            h.vox_offset as u64
        } else {
            0
        };
        let img_gz = is_gz(&img);
        (img, off, img_gz)
    };

    crate::readers::common::check_data_file(path, &data_path)?;
    let data = if data_gz {
        let mut reader: Box<dyn Read> = if data_path == path {
            skip_bytes(
                path,
                &mut reader,
                data_offset - consumed,
                "NIfTI extensions",
            )?;
            reader
        } else {
            let f = crate::regular_file::open(&data_path)?;
            let mut r: Box<dyn Read> = Box::new(MultiGzDecoder::new(BufReader::new(f)));
            skip_bytes(&data_path, &mut r, data_offset, "image header bytes")?;
            r
        };
        let mut staging = new_staging(path, options.staging_dir.as_deref(), needed)?;
        stream_into(&data_path, &mut reader, &mut staging, needed)?;
        RawVolume::from_staging(staging, &data_path, sample_type, h.order, data_dims)?
    } else {
        drop(reader);
        RawVolume::map_file(&data_path, data_offset, sample_type, h.order, data_dims)?
    };

    let mut inputs = vec![path.to_path_buf()];
    if data_path != path {
        inputs.push(data_path);
    }
    Ok(OpenedSource {
        info: SourceInfo {
            path: path.to_path_buf(),
            format: if h.version == 1 { "nifti-1" } else { "nifti-2" }.into(),
            geometry,
            sample_type,
            slope,
            intercept,
            modality: String::new(),
            windows,
            description,
            inputs,
            labels: Vec::new(),
            frames: frames as u32,
        },
        data,
    })
}
