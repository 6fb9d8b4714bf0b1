//! NIfTI-1 label maps as bytes: the header and the voxels of a layer, to any writer (core: the
//! browser page's Download builds the `.nii.gz` in memory; `io::nifti` writes it to a file).
//!
//! The header follows the NIfTI-1 standard (nifti1.h): `dim` = 3, nx, ny, nz; datatype
//! `NIFTI_TYPE_UINT16` (512); `intent_code` = `NIFTI_INTENT_LABEL` (1002); no scaling
//! (`scl_slope` 1, `scl_inter` 0); units mm. Strata's geometry is LPS and NIfTI's world is RAS,
//! so both the sform (exact, `sform_code` 1 = scanner) and the qform (the rotation part as a
//! quaternion with `qfac` for a left-handed grid, nifti1_io's `nifti_mat44_to_quatern`) carry
//! the first two world axes negated. Values are f32 in the header, so a reader gets the
//! placement to ~1e-7 relative.
//!
//! Voxels stream out one k-slice at a time through [`LabelRead::read_slice_k`] (memory: one
//! slice). `io::write_nifti` replaces a file only once complete. Checked against
//! nibabel (voxels and affine) and Strata's own reader in `segment/tests/peers.rs`.

use std::io::Write;
use std::path::Path;

use flate2::write::GzEncoder;
use flate2::Compression;

use crate::{Label, LabelRead, SegmentError};

const NIFTI_INTENT_LABEL: i16 = 1002;
const NIFTI_TYPE_UINT16: i16 = 512;
const NIFTI_XFORM_SCANNER_ANAT: i16 = 1;
const NIFTI_UNITS_MM: u8 = 2;
const HEADER_BYTES: usize = 348;
/// Header plus the 4-byte extension flag (no extensions).
const VOX_OFFSET: usize = 352;

/// Writes `labels` as a NIfTI-1 label map to `out`, gzip-compressed when `gzip`; `path` names the
/// file in errors.
pub fn write_label_map(
    labels: &dyn LabelRead,
    out: &mut dyn Write,
    gzip: bool,
    path: &Path,
) -> Result<(), SegmentError> {
    let header = nifti_header(labels, path)?;
    if gzip {
        // Level 1: label maps are long runs; higher levels cost seconds and save little.
        let mut z = GzEncoder::new(out, Compression::fast());
        write_body(labels, &header, &mut z, path)?;
        z.finish().map_err(|e| SegmentError::Io {
            path: path.to_path_buf(),
            source: e,
        })?;
        Ok(())
    } else {
        write_body(labels, &header, out, path)
    }
}

/// `labels` as the bytes of a `.nii.gz` label map named `name` (errors name it), in memory:
/// what a browser hands to a download.
pub fn label_map_gz_bytes(labels: &dyn LabelRead, name: &str) -> Result<Vec<u8>, SegmentError> {
    let mut bytes = Vec::new();
    write_label_map(labels, &mut bytes, true, Path::new(name))?;
    Ok(bytes)
}

/// The header, then the voxels one k-slice at a time.
pub fn write_body(
    labels: &dyn LabelRead,
    header: &[u8],
    out: &mut dyn Write,
    path: &Path,
) -> Result<(), SegmentError> {
    let io = |e| SegmentError::Io {
        path: path.to_path_buf(),
        source: e,
    };
    out.write_all(header).map_err(io)?;
    let [nx, ny, nz] = labels.geometry().dims;
    let plane = nx as usize * ny as usize;
    let mut slice: Vec<Label> = vec![0; plane];
    let mut bytes = Vec::with_capacity(plane * 2);
    for k in 0..nz {
        labels.read_slice_k(k, &mut slice)?;
        bytes.clear();
        bytes.extend(slice.iter().flat_map(|v| v.to_le_bytes()));
        out.write_all(&bytes).map_err(io)?;
    }
    Ok(())
}

/// LPS to RAS: negate x and y.
fn ras(v: [f64; 3]) -> [f64; 3] {
    [-v[0], -v[1], v[2]]
}

/// The 352 bytes before the voxels; `path` names the file in an error (header and an empty extension flag).
pub fn nifti_header(labels: &dyn LabelRead, path: &Path) -> Result<Vec<u8>, SegmentError> {
    let g = labels.geometry();
    if g.dims.iter().any(|&d| d > i16::MAX as u32) {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: format!(
                "NIfTI-1 holds at most {} voxels along an axis; this grid is {:?} (save as OME-Zarr or DICOM SEG instead)",
                i16::MAX,
                g.dims
            ),
        });
    }
    let mut h = vec![0u8; VOX_OFFSET];
    let put_i16 = |h: &mut [u8], at: usize, v: i16| h[at..at + 2].copy_from_slice(&v.to_le_bytes());
    let put_f32 =
        |h: &mut [u8], at: usize, v: f64| h[at..at + 4].copy_from_slice(&(v as f32).to_le_bytes());
    h[0..4].copy_from_slice(&(HEADER_BYTES as i32).to_le_bytes());
    let dims = [
        3,
        g.dims[0] as i16,
        g.dims[1] as i16,
        g.dims[2] as i16,
        1,
        1,
        1,
        1,
    ];
    for (n, d) in dims.iter().enumerate() {
        put_i16(&mut h, 40 + 2 * n, *d);
    }
    put_i16(&mut h, 68, NIFTI_INTENT_LABEL);
    put_i16(&mut h, 70, NIFTI_TYPE_UINT16);
    put_i16(&mut h, 72, 16);

    // RAS columns: axis a's direction times its spacing.
    let axes = [0, 1, 2].map(|a| ras(g.direction[a]));
    let origin = ras(g.origin_lps_mm);
    let (quatern, qfac) = quaternion_of(axes);
    put_f32(&mut h, 76, qfac);
    for a in 0..3 {
        put_f32(&mut h, 80 + 4 * a, g.spacing_mm[a]);
    }
    put_f32(&mut h, 108, VOX_OFFSET as f64);
    put_f32(&mut h, 112, 1.0);
    put_f32(&mut h, 116, 0.0);
    h[123] = NIFTI_UNITS_MM;
    let descrip = b"Strata label map";
    h[148..148 + descrip.len()].copy_from_slice(descrip);
    put_i16(&mut h, 252, NIFTI_XFORM_SCANNER_ANAT);
    put_i16(&mut h, 254, NIFTI_XFORM_SCANNER_ANAT);
    for (n, q) in quatern.iter().enumerate() {
        put_f32(&mut h, 256 + 4 * n, *q);
    }
    for (n, o) in origin.iter().enumerate() {
        put_f32(&mut h, 268 + 4 * n, *o);
    }
    for row in 0..3 {
        for (a, (axis, spacing)) in axes.iter().zip(g.spacing_mm).enumerate() {
            put_f32(&mut h, 280 + 16 * row + 4 * a, axis[row] * spacing);
        }
        put_f32(&mut h, 280 + 16 * row + 12, origin[row]);
    }
    let intent = b"labels";
    h[328..328 + intent.len()].copy_from_slice(intent);
    h[344..348].copy_from_slice(b"n+1\0");
    Ok(h)
}

/// The qform quaternion (b, c, d) and qfac of the rotation whose columns are `axes` (RAS unit
/// vectors), after nifti1_io's `nifti_mat44_to_quatern`.
fn quaternion_of(axes: [[f64; 3]; 3]) -> ([f64; 3], f64) {
    // r[i][j]: row i (world x, y, z), column j (index axis).
    let mut r = [[0.0; 3]; 3];
    for (j, axis) in axes.iter().enumerate() {
        for i in 0..3 {
            r[i][j] = axis[i];
        }
    }
    let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
    let qfac = if det < 0.0 {
        for row in &mut r {
            row[2] = -row[2];
        }
        -1.0
    } else {
        1.0
    };
    let trace = r[0][0] + r[1][1] + r[2][2] + 1.0;
    let (mut a, mut b, mut c, mut d);
    if trace > 0.5 {
        a = 0.5 * trace.sqrt();
        b = 0.25 * (r[2][1] - r[1][2]) / a;
        c = 0.25 * (r[0][2] - r[2][0]) / a;
        d = 0.25 * (r[1][0] - r[0][1]) / a;
    } else {
        let xd = 1.0 + r[0][0] - (r[1][1] + r[2][2]);
        let yd = 1.0 + r[1][1] - (r[0][0] + r[2][2]);
        let zd = 1.0 + r[2][2] - (r[0][0] + r[1][1]);
        if xd > 1.0 {
            b = 0.5 * xd.sqrt();
            c = 0.25 * (r[0][1] + r[1][0]) / b;
            d = 0.25 * (r[0][2] + r[2][0]) / b;
            a = 0.25 * (r[2][1] - r[1][2]) / b;
        } else if yd > 1.0 {
            c = 0.5 * yd.sqrt();
            b = 0.25 * (r[0][1] + r[1][0]) / c;
            d = 0.25 * (r[1][2] + r[2][1]) / c;
            a = 0.25 * (r[0][2] - r[2][0]) / c;
        } else {
            d = 0.5 * zd.sqrt();
            b = 0.25 * (r[0][2] + r[2][0]) / d;
            c = 0.25 * (r[1][2] + r[2][1]) / d;
            a = 0.25 * (r[1][0] - r[0][1]) / d;
        }
        if a < 0.0 {
            (a, b, c, d) = (-a, -b, -c, -d);
        }
    }
    let _ = a;
    ([b, c, d], qfac)
}

#[cfg(test)]
mod tests {
    use std::io::Read;

    use super::*;
    use crate::LabelLayer;
    use strata_types::VolumeGeometry;

    fn i16_at(bytes: &[u8], at: usize) -> i16 {
        i16::from_le_bytes([bytes[at], bytes[at + 1]])
    }

    /// The in-memory `.nii.gz` is a NIfTI-1 label map of the layer: dims, u16 datatype, label
    /// intent, and every voxel at its place (i fastest) after the 352-byte header.
    #[test]
    fn the_gz_bytes_hold_the_header_and_every_voxel_in_place() {
        let dims = [5, 4, 3];
        let mut layer =
            LabelLayer::new_empty(VolumeGeometry::axis_aligned(dims, [1.0, 2.0, 3.0])).unwrap();
        let label = layer.segments_mut().add("Liver").unwrap();
        let painted = [[0, 0, 0], [4, 3, 2], [2, 1, 1]];
        layer
            .edit("test", |w: &mut crate::EditWriter<'_>| {
                for v in painted {
                    w.paint(v, label)?;
                }
                Ok(())
            })
            .unwrap();
        let gz = label_map_gz_bytes(&layer, "segmentation.nii.gz").unwrap();
        let mut bytes = Vec::new();
        flate2::read::GzDecoder::new(&gz[..])
            .read_to_end(&mut bytes)
            .unwrap();
        assert_eq!(bytes.len(), VOX_OFFSET + 2 * 5 * 4 * 3);
        assert_eq!(&bytes[344..348], b"n+1\0");
        assert_eq!(
            (1..4)
                .map(|n| i16_at(&bytes, 40 + 2 * n))
                .collect::<Vec<_>>(),
            vec![5, 4, 3]
        );
        assert_eq!(i16_at(&bytes, 70), NIFTI_TYPE_UINT16);
        assert_eq!(i16_at(&bytes, 68), NIFTI_INTENT_LABEL);
        let mut labelled = Vec::new();
        for (n, v) in bytes[VOX_OFFSET..].chunks(2).enumerate() {
            if u16::from_le_bytes([v[0], v[1]]) != 0 {
                assert_eq!(u16::from_le_bytes([v[0], v[1]]), label);
                labelled.push([n % 5, n / 5 % 4, n / 20].map(|c| c as u32));
            }
        }
        let mut expected = painted.to_vec();
        expected.sort_by_key(|v| [v[2], v[1], v[0]]);
        assert_eq!(labelled, expected);
    }

    /// A grid wider than NIfTI-1's i16 dims is refused naming the file, before any byte.
    #[test]
    fn a_grid_nifti_cannot_hold_is_refused_naming_the_download() {
        let layer =
            LabelLayer::new_empty(VolumeGeometry::axis_aligned([40_000, 1, 1], [1.0; 3])).unwrap();
        let e = label_map_gz_bytes(&layer, "big.nii.gz").unwrap_err();
        assert!(
            e.to_string()
                .starts_with("big.nii.gz: NIfTI-1 holds at most"),
            "{e}"
        );
    }
}
