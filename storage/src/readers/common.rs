//! Small helpers shared by the text-header readers and the geometry code.

use std::path::Path;

use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;

/// Checks that the data file a header names (`data`) is a readable regular file; the error
/// names the header too, since that is the file the user gave.
pub(crate) fn check_data_file(header: &Path, data: &Path) -> Result<()> {
    if header == data {
        return Ok(());
    }
    match std::fs::metadata(data) {
        Ok(m) if m.is_file() => Ok(()),
        Ok(_) => Err(StorageError::invalid(
            header,
            format!("its data file {} is not a regular file", data.display()),
        )),
        Err(e) => Err(StorageError::invalid(
            header,
            format!("cannot open its data file {}: {e}", data.display()),
        )),
    }
}

pub(crate) fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Splits a scaled axis vector into (unit direction, length). A zero or non-finite vector is an
/// error because it would make the index→patient map singular.
pub(crate) fn split_axis(path: &Path, what: &str, v: [f64; 3]) -> Result<([f64; 3], f64)> {
    let n = norm(v);
    if !n.is_finite() || n <= 0.0 {
        return Err(StorageError::invalid(
            path,
            format!("{what} {v:?} is zero or not finite"),
        ));
    }
    Ok(([v[0] / n, v[1] / n, v[2] / n], n))
}

/// RAS ↔ LPS: both flip x and y. (`0.0 - x` rather than `-x` keeps zeros from turning into -0.0,
/// which would only clutter printed geometry.)
pub(crate) fn flip_xy(v: [f64; 3]) -> [f64; 3] {
    [0.0 - v[0], 0.0 - v[1], v[2]]
}

/// Builds a geometry from three scaled axis vectors (index axis a → patient offset per voxel).
pub(crate) fn geometry_from_axes(
    path: &Path,
    dims: [u64; 3],
    axes: [[f64; 3]; 3],
    origin: [f64; 3],
) -> Result<VolumeGeometry> {
    let mut direction = [[0.0; 3]; 3];
    let mut spacing = [0.0; 3];
    for a in 0..3 {
        let (d, s) = split_axis(path, &format!("axis {a} vector"), axes[a])?;
        direction[a] = d;
        spacing[a] = s;
    }
    Ok(VolumeGeometry {
        dims: crate::geometry::checked_dims(dims, path)?,
        spacing_mm: spacing,
        origin_lps_mm: origin,
        direction,
    })
}

/// Parses whitespace- (and comma-) separated numbers; `what` names the field for the error.
pub(crate) fn parse_f64s(path: &Path, what: &str, text: &str) -> Result<Vec<f64>> {
    text.split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
        .map(|t| {
            t.parse::<f64>().map_err(|_| {
                StorageError::invalid(path, format!("{what}: '{t}' is not a number (in '{text}')"))
            })
        })
        .collect()
}

pub(crate) fn parse_u64s(path: &Path, what: &str, text: &str) -> Result<Vec<u64>> {
    text.split_whitespace()
        .map(|t| {
            t.parse::<u64>().map_err(|_| {
                StorageError::invalid(
                    path,
                    format!("{what}: '{t}' is not a non-negative integer (in '{text}')"),
                )
            })
        })
        .collect()
}

/// Pads a 1–3 axis size list to three axes; more than three non-trivial axes are not a volume.
pub(crate) fn dims3(path: &Path, what: &str, v: &[u64]) -> Result<[u64; 3]> {
    if v.is_empty() {
        return Err(StorageError::invalid(path, format!("{what} is empty")));
    }
    if v.len() > 3 && v[3..].iter().any(|&d| d > 1) {
        return Err(StorageError::unsupported(
            path,
            format!("{what} {v:?}: only 3-D scalar volumes are supported"),
        ));
    }
    let mut d = [1u64; 3];
    for (o, x) in d.iter_mut().zip(v.iter()) {
        *o = *x;
    }
    Ok(d)
}

/// Total bytes of a volume, or an error when the header's numbers overflow.
pub(crate) fn volume_bytes(path: &Path, dims: [u64; 3], sample_size: usize) -> Result<u64> {
    dims.iter()
        .try_fold(sample_size as u64, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| StorageError::invalid(path, format!("dimensions {dims:?} overflow")))
}
