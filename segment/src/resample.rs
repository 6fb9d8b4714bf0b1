//! Labels moved onto another grid by nearest neighbour (labels are categories: never blended).
//!
//! Each voxel of the target grid takes the label of the source voxel nearest its centre in
//! patient space (LPS mm); outside the source, background. The work goes by source brick: only
//! bricks holding labels are visited, and each maps to the box of target voxels it can reach,
//! so resampling a sparse segmentation costs time and memory in proportion to its labelled
//! bricks, not to either grid.

use glam::{DMat3, DVec3};
use strata_types::VolumeGeometry;

use crate::grid::{BrickKey, LABEL_BRICK};
use crate::layer::LabelLayer;
use crate::SegmentError;

/// What a resampling did, for the message that says so.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Resampled {
    pub from_dims: [u32; 3],
    pub to_dims: [u32; 3],
    /// Labelled voxels of the target grid.
    pub labelled_voxels: u64,
}

/// A new layer on `target` holding `source`'s labels (nearest neighbour) and segment table.
pub fn resample_nearest(
    source: &LabelLayer,
    target: VolumeGeometry,
) -> Result<(LabelLayer, Resampled), SegmentError> {
    let mut out = LabelLayer::new_empty(target)?;
    *out.segments_mut() = source.segments().clone();
    let from = source.grid().geometry().clone();
    let to = out.grid().geometry().clone();
    // source index = source_from_target · target index + offset, and its inverse for boxes.
    let source_from_patient = from.patient_from_index_linear().inverse();
    let linear: DMat3 = source_from_patient * to.patient_from_index_linear();
    let offset = source_from_patient * (to.origin() - from.origin());
    let target_from_source = linear.inverse();
    if !linear.is_finite() || !offset.is_finite() || !target_from_source.is_finite() {
        return Err(SegmentError::Grid(
            "the two grids' orientations cannot be mapped onto each other".into(),
        ));
    }
    let to_dims = to.dims;
    let from_dims = from.dims;
    let [bx, by, bz] = source.grid().bricks();
    let mut labelled = 0u64;
    out.edit("Resample", |w| {
        for k in 0..bz {
            for j in 0..by {
                for i in 0..bx {
                    let key = BrickKey([i, j, k]);
                    if source.brick_is_empty(key) {
                        continue;
                    }
                    let brick = source.brick(key)?;
                    if brick.iter().all(|&l| l == 0) {
                        continue;
                    }
                    let lo = source.grid().brick_origin(key);
                    let hi = [0, 1, 2].map(|a| (lo[a] + LABEL_BRICK).min(from_dims[a]));
                    // The target voxels whose nearest source voxel can lie in this brick: the
                    // brick's box grown by half a voxel, mapped to target indices.
                    let mut t_lo = DVec3::splat(f64::INFINITY);
                    let mut t_hi = DVec3::splat(f64::NEG_INFINITY);
                    for corner in 0..8 {
                        let c = DVec3::new(
                            if corner & 1 == 0 {
                                f64::from(lo[0]) - 0.5
                            } else {
                                f64::from(hi[0]) - 0.5
                            },
                            if corner & 2 == 0 {
                                f64::from(lo[1]) - 0.5
                            } else {
                                f64::from(hi[1]) - 0.5
                            },
                            if corner & 4 == 0 {
                                f64::from(lo[2]) - 0.5
                            } else {
                                f64::from(hi[2]) - 0.5
                            },
                        );
                        let t = target_from_source * (c - offset);
                        t_lo = t_lo.min(t);
                        t_hi = t_hi.max(t);
                    }
                    let first = [t_lo.x, t_lo.y, t_lo.z].map(|v| v.floor().max(0.0));
                    let last = [0, 1, 2].map(|a| {
                        [t_hi.x, t_hi.y, t_hi.z][a]
                            .ceil()
                            .min(f64::from(to_dims[a]) - 1.0)
                    });
                    if (0..3).any(|a| last[a] < first[a]) {
                        continue;
                    }
                    let b = LABEL_BRICK as i64;
                    for tk in first[2] as u32..=last[2] as u32 {
                        for tj in first[1] as u32..=last[1] as u32 {
                            for ti in first[0] as u32..=last[0] as u32 {
                                let s = linear
                                    * DVec3::new(f64::from(ti), f64::from(tj), f64::from(tk))
                                    + offset;
                                let s = [s.x, s.y, s.z].map(|c| (c + 0.5).floor() as i64);
                                // Only the brick that holds the nearest source voxel writes it,
                                // so every target voxel is decided once.
                                if (0..3)
                                    .any(|a| s[a] < i64::from(lo[a]) || s[a] >= i64::from(hi[a]))
                                {
                                    continue;
                                }
                                let at = (s[0] - i64::from(lo[0]))
                                    + b * ((s[1] - i64::from(lo[1]))
                                        + b * (s[2] - i64::from(lo[2])));
                                let label = brick[at as usize];
                                if label != 0 {
                                    w.set([ti, tj, tk], label)?;
                                    labelled += 1;
                                }
                            }
                        }
                    }
                }
            }
        }
        Ok(())
    })?;
    Ok((
        out,
        Resampled {
            from_dims,
            to_dims,
            labelled_voxels: labelled,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat3;

    fn rotated(dims: [u32; 3], spacing: [f64; 3], origin: [f64; 3], angle: f64) -> VolumeGeometry {
        let r = DMat3::from_axis_angle(DVec3::new(1.0, -2.0, 0.5).normalize_or_zero(), angle);
        VolumeGeometry {
            dims,
            spacing_mm: spacing,
            origin_lps_mm: origin,
            direction: [
                r.x_axis.to_array(),
                r.y_axis.to_array(),
                r.z_axis.to_array(),
            ],
        }
    }

    /// A ball of label 3 and a slab of label 9 on a 40×36×30 grid.
    fn source_layer(g: VolumeGeometry) -> LabelLayer {
        let mut layer = LabelLayer::new_empty(g).unwrap();
        layer.segments_mut().add("one").unwrap();
        layer
            .edit("draw", |w| {
                let [nx, ny, nz] = w.grid().dims();
                for k in 0..nz {
                    for j in 0..ny {
                        for i in 0..nx {
                            let d = (f64::from(i) - 18.0).powi(2)
                                + (f64::from(j) - 15.0).powi(2)
                                + (f64::from(k) - 14.0).powi(2);
                            if d < 100.0 {
                                w.set([i, j, k], 3)?;
                            } else if (33..36).contains(&i) {
                                w.set([i, j, k], 9)?;
                            }
                        }
                    }
                }
                Ok(())
            })
            .unwrap();
        layer
    }

    /// Brute force: every target voxel's nearest source voxel through patient space.
    fn expected(source: &LabelLayer, target: &VolumeGeometry) -> Vec<u16> {
        let from = source.grid().geometry();
        let mut out = Vec::new();
        for k in 0..target.dims[2] {
            for j in 0..target.dims[1] {
                for i in 0..target.dims[0] {
                    let p = target.patient_from_index(DVec3::new(
                        f64::from(i),
                        f64::from(j),
                        f64::from(k),
                    ));
                    let s = from.index_from_patient(p);
                    let s = [s.x, s.y, s.z].map(|c| (c + 0.5).floor() as i64);
                    let inside = (0..3).all(|a| s[a] >= 0 && s[a] < i64::from(from.dims[a]));
                    out.push(if inside {
                        source.get(s.map(|c| c as u32)).unwrap()
                    } else {
                        0
                    });
                }
            }
        }
        out
    }

    fn all(layer: &LabelLayer) -> Vec<u16> {
        let [nx, ny, nz] = layer.grid().dims();
        let mut out = Vec::new();
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    out.push(layer.get([i, j, k]).unwrap());
                }
            }
        }
        out
    }

    #[test]
    fn the_same_grid_gives_the_same_labels() {
        let g = rotated([40, 36, 30], [0.8, 0.9, 1.5], [3.0, -7.0, 11.0], 0.4);
        let source = source_layer(g.clone());
        let (out, report) = resample_nearest(&source, g).unwrap();
        assert_eq!(all(&out), all(&source));
        assert_eq!(out.segments(), source.segments());
        assert_eq!(
            report.labelled_voxels,
            all(&source).iter().filter(|&&l| l != 0).count() as u64
        );
    }

    #[test]
    fn another_grid_takes_the_nearest_source_voxel_everywhere() {
        let source = source_layer(rotated(
            [40, 36, 30],
            [0.8, 0.9, 1.5],
            [3.0, -7.0, 11.0],
            0.4,
        ));
        // Finer, rotated otherwise, shifted, and larger than the source (voxels outside it).
        let target = rotated([70, 64, 48], [0.55, 0.6, 0.95], [-4.0, -12.0, 5.0], -0.3);
        let (out, report) = resample_nearest(&source, target.clone()).unwrap();
        let want = expected(&source, &target);
        let got = all(&out);
        let differing = want.iter().zip(&got).filter(|(a, b)| a != b).count();
        assert_eq!(
            differing, 0,
            "voxels differing from the brute-force nearest neighbour"
        );
        assert!(want.contains(&3) && want.contains(&9));
        assert_eq!(
            report.labelled_voxels,
            want.iter().filter(|&&l| l != 0).count() as u64
        );
        // Only bricks that hold labels were written.
        assert!(out.edited_brick_count() < out.grid().bricks().iter().product::<u32>() as usize);
    }
}
