//! The label pyramid: coarser levels of a label layer for the 3D view, kept up to date edit by
//! edit by recomputing only the ancestors of the bricks an edit changed.
//!
//! Labels are categories, so a coarse voxel is never a mean of its eight children. It takes the
//! most frequent segment among the children that are not background (ties to the lowest label
//! value), and is background only when all eight are: a mode that counted background would
//! erase a vessel or a thin cortex one voxel wide at the first coarser level, which is exactly
//! what a 3D overview must still show. Level `l` voxel `v` covers level `l − 1` voxels
//! `2v .. 2v + 1` per axis; level dims are `ceil(d / 2)` of the level below, down to one brick.
//!
//! Only non-background bricks are held (`Arc`-shared images of 32³ labels), so the pyramid of a
//! sparse segmentation costs memory in proportion to what is labelled, as the layer does.

use std::sync::Arc;

use rustc_hash::{FxHashMap, FxHashSet};

use crate::grid::{BrickKey, LABEL_BRICK, LABEL_BRICK_VOXELS};
use crate::layer::LabelLayer;
use crate::{Label, SegmentError};

/// One coarser level: its dims and its non-background bricks.
#[derive(Clone, Debug, Default)]
struct Level {
    dims: [u32; 3],
    bricks: FxHashMap<BrickKey, Arc<[Label]>>,
}

/// Levels 1.. of a label layer (level 0 is the layer itself).
#[derive(Clone, Debug)]
pub struct LabelPyramid {
    level0_dims: [u32; 3],
    levels: Vec<Level>,
}

/// What an update recomputed, per coarser level (index 0 is level 1).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PyramidUpdate {
    pub bricks_recomputed: Vec<usize>,
}

impl LabelPyramid {
    /// The pyramid of a layer, from every brick of it that holds labels.
    pub fn build(layer: &LabelLayer) -> Result<Self, SegmentError> {
        let mut pyramid = Self::empty(layer.grid().dims());
        let [bx, by, bz] = layer.grid().bricks();
        let mut keys = Vec::new();
        for k in 0..bz {
            for j in 0..by {
                for i in 0..bx {
                    let key = BrickKey([i, j, k]);
                    if !layer.brick_is_empty(key) {
                        keys.push(key);
                    }
                }
            }
        }
        pyramid.update(layer, keys)?;
        Ok(pyramid)
    }

    /// A pyramid with no labels over a level-0 grid of `dims`.
    pub fn empty(dims: [u32; 3]) -> Self {
        let mut levels = Vec::new();
        let mut d = dims;
        while d.iter().any(|&n| n > LABEL_BRICK) {
            d = d.map(|n| n.div_ceil(2));
            levels.push(Level {
                dims: d,
                bricks: FxHashMap::default(),
            });
        }
        LabelPyramid {
            level0_dims: dims,
            levels,
        }
    }

    /// Coarser levels held (the level-0 grid of one brick has none).
    pub fn levels(&self) -> usize {
        self.levels.len()
    }

    /// Dims of `level` (0 is the layer's).
    pub fn level_dims(&self, level: usize) -> Option<[u32; 3]> {
        if level == 0 {
            Some(self.level0_dims)
        } else {
            self.levels.get(level - 1).map(|l| l.dims)
        }
    }

    /// A brick of coarser `level` ≥ 1 (`None`: all background, or no such level).
    pub fn brick(&self, level: usize, key: BrickKey) -> Option<&Arc<[Label]>> {
        level
            .checked_sub(1)
            .and_then(|l| self.levels.get(l))
            .and_then(|l| l.bricks.get(&key))
    }

    /// The label of voxel `v` of coarser `level` ≥ 1 (0 outside or in background).
    pub fn get(&self, level: usize, v: [u32; 3]) -> Label {
        let key = BrickKey(v.map(|c| c / LABEL_BRICK));
        let b = LABEL_BRICK as usize;
        let [li, lj, lk] = v.map(|c| (c % LABEL_BRICK) as usize);
        self.brick(level, key)
            .map_or(0, |brick| brick[li + b * (lj + b * lk)])
    }

    /// Recomputes the ancestors of the level-0 bricks in `changed` (an edit's keys) from the
    /// layer as it is now, level by level; nothing else is read or recomputed.
    pub fn update(
        &mut self,
        layer: &LabelLayer,
        changed: impl IntoIterator<Item = BrickKey>,
    ) -> Result<PyramidUpdate, SegmentError> {
        if layer.grid().dims() != self.level0_dims {
            return Err(SegmentError::Grid(format!(
                "the pyramid is of a {:?} grid, the layer {:?}",
                self.level0_dims,
                layer.grid().dims()
            )));
        }
        let mut report = PyramidUpdate::default();
        let mut dirty: FxHashSet<BrickKey> = changed
            .into_iter()
            .map(|k| BrickKey(k.0.map(|c| c / 2)))
            .collect();
        let mut children = vec![0 as Label; LABEL_BRICK_VOXELS];
        for level in 0..self.levels.len() {
            let mut parents = FxHashSet::default();
            let mut sorted: Vec<BrickKey> = dirty.iter().copied().collect();
            sorted.sort_unstable();
            for key in &sorted {
                let image = self.coarsen(layer, level, *key, &mut children)?;
                let bricks = &mut self.levels[level].bricks;
                match image {
                    Some(image) => {
                        bricks.insert(*key, image.into());
                    }
                    None => {
                        bricks.remove(key);
                    }
                }
                parents.insert(BrickKey(key.0.map(|c| c / 2)));
            }
            report.bricks_recomputed.push(sorted.len());
            dirty = parents;
        }
        Ok(report)
    }

    /// Brick `key` of coarser level `level + 1` from its (up to) eight children one level down
    /// (`None` when all background).
    fn coarsen(
        &self,
        layer: &LabelLayer,
        level: usize,
        key: BrickKey,
        scratch: &mut [Label],
    ) -> Result<Option<Vec<Label>>, SegmentError> {
        let b = LABEL_BRICK as usize;
        let half = b / 2;
        let mut out = vec![0 as Label; LABEL_BRICK_VOXELS];
        let mut any = false;
        for octant in 0..8u32 {
            let offset = [octant & 1, (octant >> 1) & 1, (octant >> 2) & 1];
            let child = BrickKey([0, 1, 2].map(|a| key.0[a] * 2 + offset[a]));
            // The child's image: the layer's brick at level 0, a held coarse brick above.
            let image: Option<Arc<[Label]>> = if level == 0 {
                let inside = (0..3).all(|a| child.0[a] < self.level0_dims[a].div_ceil(LABEL_BRICK));
                if !inside || layer.brick_is_empty(child) {
                    None
                } else {
                    Some(layer.brick(child)?)
                }
            } else {
                self.levels[level - 1].bricks.get(&child).cloned()
            };
            let Some(image) = image else {
                continue;
            };
            scratch.copy_from_slice(&image);
            // The child brick's 32³ voxels fill one 16³ octant of the parent.
            for pk in 0..half {
                for pj in 0..half {
                    for pi in 0..half {
                        let mut votes: [(Label, u8); 8] = [(0, 0); 8];
                        let mut n_votes = 0;
                        for c in 0..8 {
                            let (ci, cj, ck) =
                                (2 * pi + (c & 1), 2 * pj + ((c >> 1) & 1), 2 * pk + (c >> 2));
                            let label = scratch[ci + b * (cj + b * ck)];
                            if label == 0 {
                                continue;
                            }
                            match votes[..n_votes].iter_mut().find(|(l, _)| *l == label) {
                                Some((_, count)) => *count += 1,
                                None => {
                                    votes[n_votes] = (label, 1);
                                    n_votes += 1;
                                }
                            }
                        }
                        let winner = votes[..n_votes]
                            .iter()
                            .max_by(|x, y| x.1.cmp(&y.1).then(y.0.cmp(&x.0)))
                            .map_or(0, |(l, _)| *l);
                        if winner != 0 {
                            any = true;
                            let at = [0, 1, 2].map(|a| offset[a] as usize * half);
                            out[(at[0] + pi) + b * ((at[1] + pj) + b * (at[2] + pk))] = winner;
                        }
                    }
                }
            }
        }
        Ok(any.then_some(out))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_types::VolumeGeometry;

    /// The coarse label of a voxel by brute force from the dense level below.
    fn coarsen_dense(dims: [u32; 3], fine: &[Label]) -> ([u32; 3], Vec<Label>) {
        let out_dims = dims.map(|d| d.div_ceil(2));
        let mut out = Vec::new();
        for k in 0..out_dims[2] {
            for j in 0..out_dims[1] {
                for i in 0..out_dims[0] {
                    let mut counts: std::collections::BTreeMap<Label, u32> = Default::default();
                    for c in 0..8u32 {
                        let v = [2 * i + (c & 1), 2 * j + ((c >> 1) & 1), 2 * k + (c >> 2)];
                        if (0..3).any(|a| v[a] >= dims[a]) {
                            continue;
                        }
                        let l = fine[(v[0] + dims[0] * (v[1] + dims[1] * v[2])) as usize];
                        if l != 0 {
                            *counts.entry(l).or_default() += 1;
                        }
                    }
                    // Highest count; among equals the lowest label (BTreeMap iterates ascending).
                    let mut best = (0, 0);
                    for (l, n) in counts {
                        if n > best.1 {
                            best = (l, n);
                        }
                    }
                    out.push(best.0);
                }
            }
        }
        (out_dims, out)
    }

    fn dense_level(p: &LabelPyramid, level: usize) -> Vec<Label> {
        let [nx, ny, nz] = p.level_dims(level).unwrap();
        let mut out = Vec::new();
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    out.push(p.get(level, [i, j, k]));
                }
            }
        }
        out
    }

    fn dense_layer(layer: &LabelLayer) -> Vec<Label> {
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

    fn check_against_brute_force(layer: &LabelLayer, p: &LabelPyramid) {
        let mut dims = layer.grid().dims();
        let mut fine = dense_layer(layer);
        for level in 1..=p.levels() {
            let (d, coarse) = coarsen_dense(dims, &fine);
            assert_eq!(p.level_dims(level), Some(d));
            let got = dense_level(p, level);
            let differing = got.iter().zip(&coarse).filter(|(a, b)| a != b).count();
            assert_eq!(
                differing, 0,
                "level {level}: voxels differing from the brute-force mode"
            );
            dims = d;
            fine = coarse;
        }
    }

    #[test]
    fn levels_are_the_mode_of_labelled_children_and_updates_touch_ancestors_only() {
        // 150×97×70: odd dims at every level, three coarser levels.
        let g = VolumeGeometry::axis_aligned([150, 97, 70], [1.0; 3]);
        let mut layer = LabelLayer::new_empty(g).unwrap();
        for name in ["a", "b", "c"] {
            layer.segments_mut().add(name).unwrap();
        }
        layer
            .edit("draw", |w| {
                let [nx, ny, nz] = w.grid().dims();
                for k in 0..nz {
                    for j in 0..ny {
                        for i in 0..nx {
                            // A one-voxel-thin sheet (kept by the rule), a ball, and a
                            // checkerboard of two labels (ties).
                            let ball = (i as i64 - 40).pow(2)
                                + (j as i64 - 50).pow(2)
                                + (k as i64 - 30).pow(2);
                            let label = if i == 101 {
                                1
                            } else if ball < 400 {
                                2
                            } else if (110..140).contains(&i) && (10..40).contains(&j) && k < 20 {
                                if (i + j + k) % 2 == 0 {
                                    3
                                } else {
                                    1
                                }
                            } else {
                                0
                            };
                            if label != 0 {
                                w.set([i, j, k], label)?;
                            }
                        }
                    }
                }
                Ok(())
            })
            .unwrap();
        let mut p = LabelPyramid::build(&layer).unwrap();
        assert_eq!(p.levels(), 3);
        check_against_brute_force(&layer, &p);
        // The thin sheet survives at every level.
        assert_eq!(p.get(3, [101 / 8, 5, 5]), 1);

        // One small edit: only the ancestors of its bricks are recomputed, one per level here,
        // and the result equals a pyramid built from scratch.
        let edit = layer
            .edit("dot", |w| {
                for v in [[5u32, 5, 5], [6, 5, 5], [5, 6, 5]] {
                    w.set(v, 3)?;
                }
                Ok(())
            })
            .unwrap()
            .unwrap();
        let report = p
            .update(&layer, edit.changes.iter().map(|c| c.key))
            .unwrap();
        assert_eq!(report.bricks_recomputed, vec![1, 1, 1]);
        check_against_brute_force(&layer, &p);
        // Undo: the edit's bricks go back; so does the pyramid.
        layer.revert(&edit);
        p.update(&layer, edit.changes.iter().map(|c| c.key))
            .unwrap();
        check_against_brute_force(&layer, &p);
        assert_eq!(p.get(1, [2, 2, 2]), 0);
    }

    #[test]
    fn a_sparse_pyramid_holds_labelled_bricks_only() {
        let g = VolumeGeometry::axis_aligned([4096, 4096, 4096], [1.0; 3]);
        let mut layer = LabelLayer::new_empty(g).unwrap();
        layer.segments_mut().add("a").unwrap();
        let mut p = LabelPyramid::empty(layer.grid().dims());
        assert_eq!(p.levels(), 7);
        let edit = layer
            .edit("dot", |w| w.set([3000, 17, 2222], 1))
            .unwrap()
            .unwrap();
        let report = p
            .update(&layer, edit.changes.iter().map(|c| c.key))
            .unwrap();
        assert_eq!(report.bricks_recomputed, vec![1; 7]);
        for level in 1..=7 {
            let held = p.levels[level - 1].bricks.len();
            assert_eq!(held, 1, "level {level} holds the one labelled brick");
            let v = [3000u32, 17, 2222].map(|c| c >> level);
            assert_eq!(p.get(level, v), 1, "level {level}");
        }
    }
}
