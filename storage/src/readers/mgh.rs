//! FreeSurfer MGH (.mgh) and its gzip-compressed form (.mgz), as nibabel and niivue read them.
//!
//! A big-endian header (version, width, height, depth, frames, type, dof, goodRASflag, then
//! voxel sizes, the direction cosines Mdc and the RAS position of the volume centre Pxyz_c)
//! in the first 284 bytes, then the voxels (column fastest), then optional scan-parameter tags.
//! The index→RAS map is FreeSurfer's and nibabel's: for index v,
//! `RAS = Mdc·diag(size)·(v − dims/2) + Pxyz_c`; it is turned into LPS here.
//! A .mgh is mapped in place; a .mgz is streamed through the gzip decoder into a staging file
//! (bounded by the header's volume size, checked against the stream's CRC), never held in memory.

use std::io::{BufReader, Read};
use std::path::Path;

use flate2::read::MultiGzDecoder;

use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::readers::common::{flip_xy, geometry_from_axes, volume_bytes};
use crate::readers::ReadOptions;
use crate::source::{ByteOrder, OpenedSource, RawVolume, SampleType, SourceInfo};
use crate::staging::{new_staging, skip_bytes, stream_into};

/// Voxels start here, after the header and its reserved padding.
const DATA_OFFSET: u64 = 284;
/// The header fields this reader uses: 7 ints, a short, 15 floats.
const HEADER_USED: usize = 7 * 4 + 2 + 15 * 4;
/// Scan-parameter tags after the voxels are small (a few kB); more than this after the last
/// frame means the header's sizes do not describe the data.
const MAX_FOOTER_BYTES: u64 = 16 << 20;

/// The parsed header.
#[derive(Debug)]
struct Header {
    dims: [u64; 3],
    frames: u64,
    sample_type: SampleType,
    /// goodRASflag > 0: the voxel sizes, Mdc and Pxyz_c below are the file's own.
    good_ras: bool,
    voxel_size: [f64; 3],
    /// Direction (RAS) of each index axis: rows x, y, z of the file's Mdc.
    mdc: [[f64; 3]; 3],
    centre_ras: [f64; 3],
}

fn be_i32(b: &[u8], at: usize) -> i32 {
    i32::from_be_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

fn be_f32(b: &[u8], at: usize) -> f64 {
    f64::from(f32::from_be_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]]))
}

fn parse_header(path: &Path, b: &[u8; HEADER_USED]) -> Result<Header> {
    let version = be_i32(b, 0);
    if version != 1 {
        return Err(StorageError::invalid(
            path,
            format!(
                "MGH version {version} (only version 1 exists; not an MGH file, or a damaged one)"
            ),
        ));
    }
    let mut sizes = [0u64; 4];
    for (a, s) in sizes.iter_mut().enumerate() {
        let v = be_i32(b, 4 + 4 * a);
        if v <= 0 {
            let names = ["width", "height", "depth", "frames"];
            return Err(StorageError::invalid(
                path,
                format!("MGH {} is {v} (must be at least 1)", names[a]),
            ));
        }
        *s = v as u64;
    }
    let sample_type = match be_i32(b, 20) {
        0 => SampleType::U8,
        1 => SampleType::I32,
        3 => SampleType::F32,
        4 => SampleType::I16,
        t => {
            return Err(StorageError::unsupported(
                path,
                format!("MGH data type {t} (supported: 0 uchar, 1 int, 3 float, 4 short)"),
            ))
        }
    };
    let good_ras = i16::from_be_bytes([b[28], b[29]]) > 0;
    let f = |i: usize| be_f32(b, 30 + 4 * i);
    let (voxel_size, mdc, centre_ras) = if good_ras {
        let voxel_size = [f(0), f(1), f(2)];
        let mdc = [[f(3), f(4), f(5)], [f(6), f(7), f(8)], [f(9), f(10), f(11)]];
        let centre = [f(12), f(13), f(14)];
        if voxel_size.iter().any(|s| !s.is_finite() || *s <= 0.0) {
            return Err(StorageError::invalid(
                path,
                format!("MGH voxel sizes {voxel_size:?} must be positive"),
            ));
        }
        if mdc
            .iter()
            .flatten()
            .chain(centre.iter())
            .any(|v| !v.is_finite())
        {
            return Err(StorageError::invalid(
                path,
                format!("MGH direction cosines {mdc:?} or centre {centre:?} not finite"),
            ));
        }
        (voxel_size, mdc, centre)
    } else {
        // FreeSurfer's defaults (MRIallocHeader) when the file carries no RAS information:
        // coronal slices, 1 mm, centred on the origin; x → left, y → inferior, z → anterior.
        (
            [1.0; 3],
            [[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],
            [0.0; 3],
        )
    };
    Ok(Header {
        dims: [sizes[0], sizes[1], sizes[2]],
        frames: sizes[3],
        sample_type,
        good_ras,
        voxel_size,
        mdc,
        centre_ras,
    })
}

/// Index → LPS geometry: RAS axis vectors Mdc·size, RAS origin Pxyz_c − Σ axis·dims/2, both
/// with x and y negated.
fn geometry(path: &Path, h: &Header) -> Result<VolumeGeometry> {
    let axes_ras: [[f64; 3]; 3] = std::array::from_fn(|a| h.mdc[a].map(|c| c * h.voxel_size[a]));
    let mut origin_ras = h.centre_ras;
    for (a, axis) in axes_ras.iter().enumerate() {
        let half = h.dims[a] as f64 / 2.0;
        for c in 0..3 {
            origin_ras[c] -= axis[c] * half;
        }
    }
    geometry_from_axes(path, h.dims, axes_ras.map(flip_xy), flip_xy(origin_ras))
}

fn is_gz(path: &Path) -> Result<bool> {
    let mut magic = [0u8; 2];
    let mut f = crate::regular_file::open(path)?;
    let n = f.read(&mut magic).map_err(|e| StorageError::io(path, e))?;
    Ok(n == 2 && magic == [0x1f, 0x8b])
}

/// Reads `buf.len()` bytes or says how many the stream held.
fn read_exactly(path: &Path, r: &mut impl Read, buf: &mut [u8], what: &str) -> Result<()> {
    let mut done = 0;
    while done < buf.len() {
        match r.read(&mut buf[done..]) {
            Ok(0) => {
                return Err(StorageError::invalid(
                    path,
                    format!("truncated {what}: {done} of {} bytes", buf.len()),
                ))
            }
            Ok(n) => done += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(StorageError::invalid(path, format!("reading {what}: {e}"))),
        }
    }
    Ok(())
}

pub(crate) fn open_mgh(path: &Path, options: &ReadOptions) -> Result<OpenedSource> {
    // The content decides, not the name: .mgz files are sometimes left uncompressed and the
    // other way round.
    let gz = is_gz(path)?;
    let file = crate::regular_file::open(path)?;
    let mut reader: Box<dyn Read> = if gz {
        Box::new(MultiGzDecoder::new(BufReader::new(file)))
    } else {
        Box::new(BufReader::new(file))
    };
    let mut raw = [0u8; HEADER_USED];
    read_exactly(path, &mut reader, &mut raw, "MGH header")?;
    let h = parse_header(path, &raw)?;
    let geometry = geometry(path, &h)?;
    crate::geometry::validate(&geometry, path)?;
    let frame_bytes = volume_bytes(path, h.dims, h.sample_type.size_bytes())?;
    let all_frames = frame_bytes
        .checked_mul(h.frames)
        .ok_or_else(|| StorageError::invalid(path, "MGH frame count overflows"))?;

    let data = if gz {
        skip_bytes(
            path,
            &mut reader,
            DATA_OFFSET - HEADER_USED as u64,
            "MGH header padding",
        )?;
        let mut staging = new_staging(path, options.staging_dir.as_deref(), frame_bytes)?;
        if h.frames == 1 {
            stream_into(path, &mut reader, &mut staging, frame_bytes)?;
        } else {
            // Only the first frame is kept; the others are decompressed and dropped so the
            // stream still reaches its CRC.
            stream_into(
                path,
                &mut (&mut reader).take(frame_bytes),
                &mut staging,
                frame_bytes,
            )?;
            skip_bytes(path, &mut reader, all_frames - frame_bytes, "MGH frames")?;
            let footer = std::io::copy(
                &mut (&mut reader).take(MAX_FOOTER_BYTES + 1),
                &mut std::io::sink(),
            )
            .map_err(|e| {
                StorageError::invalid(
                    path,
                    format!("compressed data is corrupt after the voxels (checksum or length trailer): {e}"),
                )
            })?;
            if footer > MAX_FOOTER_BYTES {
                return Err(StorageError::invalid(
                    path,
                    format!("more than {} MB after the last frame: the header's sizes do not match the data", MAX_FOOTER_BYTES >> 20),
                ));
            }
        }
        RawVolume::from_staging(staging, path, h.sample_type, ByteOrder::Big, h.dims)?
    } else {
        drop(reader);
        let len = std::fs::metadata(path)
            .map_err(|e| StorageError::io(path, e))?
            .len();
        let need = DATA_OFFSET.saturating_add(all_frames);
        if len < need {
            return Err(StorageError::invalid(
                path,
                format!(
                    "truncated data: the header describes {} frame(s) of {:?} {:?} ({need} bytes with the header), the file has {len}",
                    h.frames, h.dims, h.sample_type
                ),
            ));
        }
        RawVolume::map_file(path, DATA_OFFSET, h.sample_type, ByteOrder::Big, h.dims)?
    };

    let mut notes = Vec::new();
    if !h.good_ras {
        notes.push(
            "goodRASflag 0: FreeSurfer's default orientation assumed (coronal LIA, 1 mm, centred)"
                .to_string(),
        );
    }
    if h.frames > 1 {
        notes.push(format!("first of {} frames", h.frames));
    }
    Ok(OpenedSource {
        info: SourceInfo {
            path: path.to_path_buf(),
            format: if gz { "mgz" } else { "mgh" }.into(),
            geometry,
            sample_type: h.sample_type,
            slope: 1.0,
            intercept: 0.0,
            modality: String::new(),
            windows: Vec::new(),
            description: notes.join("; "),
            inputs: vec![path.to_path_buf()],
            labels: Vec::new(),
            frames: 1,
        },
        data,
    })
}
