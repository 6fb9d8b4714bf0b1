//! Loading a label file (NIfTI, DICOM SEG, NRRD, MetaImage, MGH: whatever
//! `strata_storage::readers` opens) as the base of an editable [`LabelLayer`].
//!
//! The reader maps the file's voxels (or stages a decompressed copy and maps that), so the layer's
//! base is read a brick at a time from the mapping ([`MappedLabels`]): no size bound beyond the
//! storage readers' own, and memory grows with the bricks edited, not the file. One streamed
//! pre-pass checks that every value is a label (an integer in 0..=65 535; floats only where
//! integral) and finds which labels occur, so a bad file fails at load with the value and its
//! voxel, never later during an edit. Segments take their names and colours from the file where it
//! has them (DICOM SEG), else "segment N" and a generated colour.

use std::path::Path;
use std::sync::Arc;

use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::{ByteOrder, OpenedSource, SampleType};

use crate::grid::{BrickKey, LabelGrid, LABEL_BRICK};
use crate::{Label, LabelBase, LabelLayer, Segment, SegmentError, SegmentTable};

/// A label file's voxels, mapped, read a brick at a time.
pub struct MappedLabels {
    source: OpenedSource,
}

impl MappedLabels {
    fn row(&self, k: u32, j: u32, i0: u32, out: &mut [Label]) -> Result<(), NotALabel> {
        let data = &self.source.data;
        let size = data.sample_type.size_bytes();
        let nx = data.dims[0] as usize;
        let slice = data.slice_bytes(u64::from(k));
        let start = (j as usize * nx + i0 as usize) * size;
        let bytes = &slice[start..start + out.len() * size];
        for (n, (o, b)) in out.iter_mut().zip(bytes.chunks_exact(size)).enumerate() {
            *o = label_of(b, data.sample_type, data.byte_order).ok_or_else(|| NotALabel {
                voxel: [i0 as usize + n, j as usize, k as usize],
                value: value_text(b, data.sample_type, data.byte_order),
            })?;
        }
        Ok(())
    }
}

/// A voxel of a label file whose value is no label; `value` is the sample as the file holds it.
#[derive(Debug, thiserror::Error)]
#[error("voxel ({}, {}, {}) holds {value}, not a label (0..=65535)", .voxel[0], .voxel[1], .voxel[2])]
struct NotALabel {
    voxel: [usize; 3],
    value: String,
}

impl LabelBase for MappedLabels {
    fn read_brick(
        &self,
        grid: &LabelGrid,
        key: BrickKey,
        out: &mut [Label],
    ) -> Result<(), SegmentError> {
        out.fill(0);
        let [nx, ny, nz] = grid.dims();
        let b = LABEL_BRICK as usize;
        let o = grid.brick_origin(key);
        let w = LABEL_BRICK.min(nx.saturating_sub(o[0])) as usize;
        for lk in 0..LABEL_BRICK.min(nz.saturating_sub(o[2])) {
            for lj in 0..LABEL_BRICK.min(ny.saturating_sub(o[1])) {
                let at = b * (lj as usize + b * lk as usize);
                self.row(o[2] + lk, o[1] + lj, o[0], &mut out[at..at + w])
                    .map_err(|message| SegmentError::BaseRead {
                        brick: key.0,
                        message: format!("{}: {message}", self.source.info.path.display()),
                    })?;
            }
        }
        Ok(())
    }
}

/// One sample as a label: integers 0..=65 535 (floats only when integral); else `None`.
fn label_of(b: &[u8], t: SampleType, order: ByteOrder) -> Option<Label> {
    let mut v = None;
    strata_storage::source::decode_samples(b, t, order, |x| v = Some(x));
    let x = v?;
    (x.fract() == 0.0 && (0.0..=f64::from(Label::MAX)).contains(&x)).then_some(x as Label)
}

fn value_text(b: &[u8], t: SampleType, order: ByteOrder) -> String {
    let mut v = f64::NAN;
    strata_storage::source::decode_samples(b, t, order, |x| v = x);
    format!("{v}")
}

/// Opens a label file (or a Strata label store) as an editable layer on its own grid.
pub fn load_label_file(path: &Path) -> Result<LabelLayer, SegmentError> {
    if super::label_store::is_strata_store(path) {
        return super::label_store::load_label_store(path);
    }
    let source = open_source(path, &ReadOptions::default()).map_err(|e| SegmentError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let info = &source.info;
    if info.frames != 1 {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: format!(
                "{} frames (a time series): a label map has one",
                info.frames
            ),
        });
    }
    let scaled = !(info.slope == 1.0 || info.slope == 0.0) || info.intercept != 0.0;
    if scaled {
        return Err(SegmentError::Format {
            path: path.to_path_buf(),
            message: format!(
                "values are scaled (slope {}, intercept {}): not a label map",
                info.slope, info.intercept
            ),
        });
    }
    let geometry = info.geometry.clone();
    let mapped = MappedLabels { source };
    // The pre-pass: every voxel a label, and which labels occur.
    let [nx, ny, nz] = geometry.dims;
    let mut present = vec![false; usize::from(Label::MAX) + 1];
    let mut row = vec![0; nx as usize];
    for k in 0..nz {
        for j in 0..ny {
            mapped
                .row(k, j, 0, &mut row)
                .map_err(|problem| SegmentError::Format {
                    path: path.to_path_buf(),
                    message: problem.to_string(),
                })?;
            for &v in &row {
                present[usize::from(v)] = true;
            }
        }
        mapped.source.data.release_slice(u64::from(k));
    }
    let mut segments = SegmentTable::new();
    for value in 1..=Label::MAX {
        let named = mapped
            .source
            .info
            .labels
            .iter()
            .find(|l| l.value == u32::from(value));
        if !present[usize::from(value)] && named.is_none() {
            continue;
        }
        segments.insert(Segment {
            value,
            name: named.map_or_else(|| format!("segment {value}"), |l| l.name.clone()),
            rgb: named
                .and_then(|l| l.rgb)
                .unwrap_or_else(|| crate::segments::label_colour(i64::from(value))),
            visible: true,
            locked: false,
            category: named.and_then(|l| l.category.clone()),
        })?;
    }
    LabelLayer::with_base(geometry, Arc::new(mapped), segments)
}
