//! A series' thumbnail in "Open from PACS…": the series' middle instance (by InstanceNumber)
//! retrieved into a temporary folder through WADO-RS, as the import retrieves (so every
//! transfer syntax the importer decodes shows, and no server-side rendering is needed), read
//! by the importer's DICOM reader, windowed to the slice's own 1st–99th percentiles (any
//! modality, no preset assumed) and box-averaged to at most [`THUMBNAIL_SIDE`] pixels.

use strata_storage::readers::{open_source, ReadOptions};

/// The longest side of a thumbnail, in pixels (never enlarged).
pub const THUMBNAIL_SIDE: usize = 64;

/// A grey thumbnail, row by row from the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Thumbnail {
    /// Columns, rows.
    pub size: [usize; 2],
    pub gray: Vec<u8>,
    /// The instance it shows.
    pub instance_uid: String,
}

/// Why a series has no thumbnail; the PACS's errors name the server, the reader's the file.
#[derive(Debug, thiserror::Error)]
pub enum ThumbnailError {
    #[error(transparent)]
    Pacs(#[from] strata_pacs::PacsError),
    #[error("the series holds no instance")]
    NoInstance,
    #[error("cannot make a temporary folder for a thumbnail: {0}")]
    TempFolder(std::io::Error),
    #[error(transparent)]
    Read(#[from] strata_storage::StorageError),
}

/// The thumbnail of a series (its middle instance, its middle frame); errors name the server.
pub fn fetch(
    client: &strata_pacs::Client,
    study_uid: &str,
    series_uid: &str,
) -> Result<Thumbnail, ThumbnailError> {
    let uid = client
        .middle_instance(study_uid, series_uid)?
        .ok_or(ThumbnailError::NoInstance)?;
    let dir = tempfile::Builder::new()
        .prefix("strata-thumbnail")
        .tempdir()
        .map_err(ThumbnailError::TempFolder)?;
    let path = client.retrieve_instance(study_uid, series_uid, &uid, dir.path())?;
    let opened = open_source(&path, &ReadOptions::default())?;
    let [columns, rows, frames] = opened.data.dims;
    let mut values = Vec::new();
    opened.data.read_slice_f64(frames / 2, &mut values);
    Ok(thumbnail_from_slice(
        &values,
        [columns as usize, rows as usize],
        THUMBNAIL_SIDE,
        uid,
    ))
}

/// `values` (`dims[0]` columns by `dims[1]` rows) windowed to their 1st–99th percentiles and
/// box-averaged by the smallest whole factor that brings the longest side to `max_side`.
pub fn thumbnail_from_slice(
    values: &[f64],
    dims: [usize; 2],
    max_side: usize,
    instance_uid: String,
) -> Thumbnail {
    let [columns, rows] = dims;
    let mut finite: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
    finite.sort_by(f64::total_cmp);
    let (low, high) = match finite.len() {
        0 => (0.0, 0.0),
        n => (finite[(n - 1) / 100], finite[(n - 1) * 99 / 100]),
    };
    let factor = columns.max(rows).div_ceil(max_side.max(1)).max(1);
    let size = [columns.div_ceil(factor), rows.div_ceil(factor)];
    let mut gray = Vec::with_capacity(size[0] * size[1]);
    for ty in 0..size[1] {
        for tx in 0..size[0] {
            let (mut sum, mut count) = (0.0, 0usize);
            for y in ty * factor..((ty + 1) * factor).min(rows) {
                for x in tx * factor..((tx + 1) * factor).min(columns) {
                    let v = values[y * columns + x];
                    if v.is_finite() {
                        sum += v;
                        count += 1;
                    }
                }
            }
            let level = if count == 0 || high <= low {
                0.0
            } else {
                ((sum / count as f64 - low) / (high - low)).clamp(0.0, 1.0)
            };
            gray.push((level * 255.0).round() as u8);
        }
    }
    Thumbnail {
        size,
        gray,
        instance_uid,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_slice_is_windowed_to_its_percentiles_and_averaged_down_keeping_its_aspect() {
        // 200 × 100 ramp along x from 0 to 199, with one hot outlier the window ignores.
        let (columns, rows) = (200usize, 100usize);
        let mut values: Vec<f64> = (0..rows * columns).map(|i| (i % columns) as f64).collect();
        values[0] = 1e9;
        values[1] = f64::NAN;
        let t = thumbnail_from_slice(&values, [columns, rows], 64, "1.2".into());
        // Factor 4 (200 / 64 rounded up): 50 × 25.
        assert_eq!(t.size, [50, 25]);
        assert_eq!(t.gray.len(), 50 * 25);
        // Percentiles of the ramp: 1 % ≈ 1, 99 % ≈ 197; a block of columns 100..104 averages
        // 101.5.
        let n = values.iter().filter(|v| v.is_finite()).count();
        let mut sorted: Vec<f64> = values.iter().copied().filter(|v| v.is_finite()).collect();
        sorted.sort_by(f64::total_cmp);
        let (low, high) = (sorted[(n - 1) / 100], sorted[(n - 1) * 99 / 100]);
        let want = (((101.5 - low) / (high - low)) * 255.0).round() as u8;
        assert_eq!(t.gray[10 * 50 + 25], want);
        // Rising left to right on every row, dark at the left, bright at the right.
        assert!(
            t.gray[10 * 50] < 5 && t.gray[10 * 50 + 49] > 250,
            "{:?}",
            &t.gray[500..550]
        );
        // A small slice is not enlarged; a constant one is black, not a division by zero.
        let small = thumbnail_from_slice(&[7.0; 12], [4, 3], 64, "1.3".into());
        assert_eq!((small.size, small.gray), ([4, 3], vec![0; 12]));
    }
}
