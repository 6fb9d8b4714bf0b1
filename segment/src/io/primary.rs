//! The primary scan as the tools and statistics read it ([`Intensity`]): an opened source file
//! (any reader of strata-storage) sampled at the label grid's voxel centres.
//!
//! On the labels' own grid the values are the source's voxels. On another grid (a label map
//! drawn on a resampled copy, a SEG of a sub-volume) each label voxel takes the value of the
//! source voxel nearest its centre in patient space (LPS mm), and NaN outside the source, so
//! statistics never count voxels the scan does not cover. Callers say so to the user:
//! [`SourceIntensity::resampled`].

use glam::DVec3;
use strata_storage::source::decode_samples;
use strata_storage::OpenedSource;

use crate::grid::{BrickKey, LabelGrid, LABEL_BRICK, LABEL_BRICK_VOXELS};
use crate::intensity::Intensity;
use crate::SegmentError;

/// An opened source's physical values (slope · sample + intercept) on a label grid.
pub struct SourceIntensity {
    source: OpenedSource,
    unit: String,
    /// The label grid it was made for.
    grid: LabelGrid,
    /// The source's continuous index from the label grid's: `None` when both are one grid.
    source_from_label: Option<(glam::DMat3, DVec3)>,
}

impl SourceIntensity {
    /// Samples `source` (its first frame) on `grid`. The unit is HU for CT, otherwise none.
    pub fn new(source: OpenedSource, grid: &LabelGrid) -> Result<Self, SegmentError> {
        let own = &source.info.geometry;
        let label = grid.geometry();
        let same = own.dims == label.dims
            && own.spacing_mm == label.spacing_mm
            && own.origin_lps_mm == label.origin_lps_mm
            && own.direction == label.direction;
        let source_from_label = (!same).then(|| {
            // index_source = A⁻¹ (origin_label + L · index_label − origin_source)
            let source_from_patient = own.patient_from_index_linear().inverse();
            let linear = source_from_patient * label.patient_from_index_linear();
            let offset = source_from_patient * (label.origin() - own.origin());
            (linear, offset)
        });
        if let Some((linear, offset)) = source_from_label {
            if !linear.is_finite() || !offset.is_finite() {
                return Err(SegmentError::Format {
                    path: source.info.path.clone(),
                    message: "its orientation cannot be mapped onto the label grid".into(),
                });
            }
        }
        let unit = if source.info.modality.eq_ignore_ascii_case("CT") {
            "HU"
        } else {
            ""
        };
        Ok(SourceIntensity {
            unit: unit.to_owned(),
            grid: grid.clone(),
            source_from_label,
            source,
        })
    }

    /// Whether the values are resampled (the source is on another grid than the labels).
    pub fn resampled(&self) -> bool {
        self.source_from_label.is_some()
    }

    /// The source's header (path, grid, modality).
    pub fn info(&self) -> &strata_storage::SourceInfo {
        &self.source.info
    }

    fn check_grid(&self, grid: &LabelGrid) -> Result<(), SegmentError> {
        if grid == &self.grid {
            Ok(())
        } else {
            Err(SegmentError::Grid(format!(
                "{} was sampled for a {:?} label grid, asked for {:?}",
                self.source.info.path.display(),
                self.grid.dims(),
                grid.dims()
            )))
        }
    }

    /// The physical value of source voxel `[i, j, k]` (first frame; NaN outside).
    fn sample(&self, at: [i64; 3]) -> f32 {
        let dims = self.source.info.geometry.dims;
        if (0..3).any(|a| at[a] < 0 || at[a] >= i64::from(dims[a])) {
            return f32::NAN;
        }
        let size = self.source.info.sample_type.size_bytes();
        let row = self.source.data.slice_bytes(at[2] as u64);
        let start = (at[0] as usize + dims[0] as usize * at[1] as usize) * size;
        let mut value = f64::NAN;
        decode_samples(
            &row[start..start + size],
            self.source.info.sample_type,
            self.source.data.byte_order,
            |v| value = v,
        );
        (value * self.source.info.slope + self.source.info.intercept) as f32
    }

    /// The source voxel nearest a label voxel's centre.
    fn source_voxel(&self, voxel: [u32; 3]) -> [i64; 3] {
        match self.source_from_label {
            None => voxel.map(i64::from),
            Some((linear, offset)) => {
                let at = linear * DVec3::from(voxel.map(f64::from)) + offset;
                // Half-way rounds up, as everywhere a centre picks its voxel here.
                [at.x, at.y, at.z].map(|c| (c + 0.5).floor() as i64)
            }
        }
    }
}

impl Intensity for SourceIntensity {
    fn value(&self, grid: &LabelGrid, voxel: [u32; 3]) -> Result<f32, SegmentError> {
        self.check_grid(grid)?;
        if !grid.contains(voxel.map(i64::from)) {
            return Err(SegmentError::OutOfBounds {
                voxel: voxel.map(i64::from),
                dims: grid.dims(),
            });
        }
        Ok(self.sample(self.source_voxel(voxel)))
    }

    fn read_brick(
        &self,
        grid: &LabelGrid,
        key: BrickKey,
        out: &mut [f32],
    ) -> Result<(), SegmentError> {
        self.check_grid(grid)?;
        if out.len() != LABEL_BRICK_VOXELS {
            return Err(SegmentError::Grid(format!(
                "a brick read needs {LABEL_BRICK_VOXELS} values, got {}",
                out.len()
            )));
        }
        out.fill(f32::NAN);
        let b = LABEL_BRICK as usize;
        let origin = grid.brick_origin(key);
        let dims = grid.dims();
        let extent = [0, 1, 2].map(|a| dims[a].saturating_sub(origin[a]).min(LABEL_BRICK));
        for lk in 0..extent[2] {
            for lj in 0..extent[1] {
                for li in 0..extent[0] {
                    let voxel = [origin[0] + li, origin[1] + lj, origin[2] + lk];
                    out[li as usize + b * (lj as usize + b * lk as usize)] =
                        self.sample(self.source_voxel(voxel));
                }
            }
        }
        Ok(())
    }

    fn unit(&self) -> &str {
        &self.unit
    }
}
