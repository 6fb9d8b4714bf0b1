//! The overlay in the 3D view, for both viewers (issues 47 and 52): the overlay volume (a label
//! map or a continuous overlay, on any grid) or the segmentation's editable label layer,
//! resampled onto a bounded dense grid over the primary's index box (the primary's own grid at
//! the finest level whose voxel count fits a bound, [`grid_dims`]) that the raycaster samples
//! and blends (strata-render's overlay.rs states how). Labels are stored as indices into a
//! colour table, so a style change (opacity, hidden labels, colour map, range, threshold) is a
//! new table only ([`lut_for`]): nothing is read again and no grid is uploaded again.
//!
//! - A store ([`GridResampler`]): grid voxel `i`'s centre is primary index
//!   `(i + ½)·primary/dims − ½` per axis, taken to patient space and into the overlay's index
//!   space; labels are the nearest level-0 voxel's, continuous values trilinear from level 0,
//!   both by the slices' own sampler (crate::overlay's [`sample`]), one grid z-slice at a time.
//!   The bricks come through strata-slices' [`LevelBricks`], which may answer "not resident
//!   yet": a slice that meets a missing brick is tried again later and the brick is listed.
//!   So the desktop runs it to the end on its `strata-overlay-3d` thread over blocking reads
//!   (viewer/src/overlay_3d.rs), and the page, which has one thread, a few slices per animation
//!   frame over the bricks it has fetched (web/src/overlay_view.rs), resuming as they arrive.
//!   Labels take their table slots in the order first met along the grid (x fastest), however
//!   the slices were visited, so both viewers' grids are equal value for value.
//! - An editable layer ([`LayerGrid`]): sampled whole once, then after an edit only where the
//!   changed label bricks reach.
//!
//! Tests: `viewer/src/overlay_3d.rs`'s (the nearest label at each voxel centre, computed in
//! f64; the edited layer's grid edit by edit against a whole resample), the unit tests below
//! (a grid resumed over missing bricks equals one sampled at once), and the page's 3D frame
//! against the native raycaster's (`web/tests/browser/overlay_3d.rs`).

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

use glam::DVec3;
use strata_render::model::overlay::OVERLAY_OUTSIDE;
use strata_render::{OverlayKind as GridKind, OverlayLut, OverlayVolume, RenderError};
use strata_segment::{label_colour, BrickKey, LabelLayer, SegmentError, LABEL_BRICK};
use strata_slices::oblique::LevelBricks;
use strata_types::BrickId;

use crate::overlay::{sample, OverlayGrids, OverlayKind, OverlayStyle, Sampled};

/// The desktop's bound: at most this many grid voxels (256³: 64 MiB of f32 on the GPU).
pub const OVERLAY_3D_MAX_VOXELS: u64 = 256 * 256 * 256;

/// The page's bound (web/src/overlay_view.rs): 128³ (8 MiB of R32Float on the GPU), an eighth
/// of the desktop's. The page resamples on its only thread, between frames: at 128³ the grid
/// is 2 M voxels, filled in 64 frames at the page's two 128² slices a frame once its bricks are
/// in, where 256³ would take 512 frames and 64 MiB of the tab's GPU memory. A primary up to
/// 128³ gets the same grid as on the desktop (its level 0); one up to 256³ gets its level 1.
pub const PAGE_OVERLAY_3D_MAX_VOXELS: u64 = 128 * 128 * 128;

/// Colour-map entries of a continuous overlay's table.
pub const CONTINUOUS_LUT_ENTRIES: usize = 256;

/// The overlay on the 3D grid, with the label each colour-table index stands for.
#[derive(Debug)]
pub struct Resampled {
    pub volume: Arc<OverlayVolume>,
    /// Labels: table index `i ≥ 1` is label `labels[i - 1]` (0 is background).
    pub labels: Vec<i64>,
}

/// The grid's dims: the primary's level dims at the finest level that fits `max_voxels` (the
/// coarsest level if none does).
pub fn grid_dims(level_dims: &[[u32; 3]], max_voxels: u64) -> [u32; 3] {
    let voxels = |d: &[u32; 3]| d.iter().map(|&v| v as u64).product::<u64>();
    level_dims
        .iter()
        .find(|&d| voxels(d) <= max_voxels)
        .or(level_dims.last())
        .copied()
        .unwrap_or([1; 3])
}

/// The colour table for `style`: per label its colour at the overlay's opacity (0 when hidden),
/// or the colour map over the range; the same colours the slices draw (overlay.rs colour_of).
pub fn lut_for(kind: OverlayKind, style: &OverlayStyle, labels: &[i64]) -> OverlayLut {
    let opacity = if style.visible {
        style.opacity.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let straight = |rgb: [u8; 3]| rgb.map(|c| c as f32 / 255.0);
    let with_alpha = |c: [f32; 3], a: f32| [c[0], c[1], c[2], a];
    let entries = match kind {
        OverlayKind::Labels => std::iter::once([0.0; 4])
            .chain(labels.iter().map(|&label| {
                let colour = style
                    .label_table
                    .get(&label)
                    .map_or_else(|| label_colour(label), |e| e.colour);
                let a = if style.hidden_labels.contains(&label) {
                    0.0
                } else {
                    opacity
                };
                with_alpha(straight(colour), a)
            }))
            .collect(),
        OverlayKind::Continuous => (0..CONTINUOUS_LUT_ENTRIES)
            .map(|i| {
                let t = i as f64 / (CONTINUOUS_LUT_ENTRIES - 1) as f64;
                with_alpha(straight(style.colour_map.rgb(t)), opacity)
            })
            .collect(),
    };
    OverlayLut {
        entries,
        lo: style.range.0,
        hi: style.range.1,
        threshold: style.threshold,
    }
}

/// Grid voxel centres to overlay indices and back.
struct GridMapping {
    overlay_from_primary: glam::DMat3,
    offset: DVec3,
    scale: DVec3,
    overlay_dims: [u32; 3],
    grid_dims: [u32; 3],
}

impl GridMapping {
    fn new(grids: &OverlayGrids, grid_dims: [u32; 3]) -> Self {
        GridMapping {
            overlay_from_primary: grids.overlay.index_from_patient_linear()
                * grids.primary.patient_from_index_linear(),
            offset: grids.overlay.index_from_patient(grids.primary.origin()),
            scale: DVec3::from(
                [0, 1, 2].map(|a| grids.primary.dims[a] as f64 / grid_dims[a] as f64),
            ),
            overlay_dims: grids.overlay.dims,
            grid_dims,
        }
    }

    /// The overlay's continuous index at grid voxel `g`'s centre.
    fn overlay_index(&self, g: [u32; 3]) -> DVec3 {
        let centre = (DVec3::from(g.map(f64::from)) + 0.5) * self.scale - 0.5;
        self.offset + self.overlay_from_primary * centre
    }

    /// The overlay voxel nearest grid voxel `g`'s centre, or `None` outside the overlay (the
    /// slices' rounding).
    fn nearest_overlay_voxel(&self, g: [u32; 3]) -> Option<[u32; 3]> {
        let p = self.overlay_index(g);
        let odims = self.overlay_dims;
        let inside =
            (0..3).all(|a| p[a] >= -0.5 && p[a] < odims[a] as f64 - 0.5 && p[a].is_finite());
        inside.then(|| {
            [0, 1, 2].map(|a| (p[a].round().max(0.0) as u32).min(odims[a].saturating_sub(1)))
        })
    }

    /// The grid voxels that can have their nearest overlay voxel in label brick `key` (its box
    /// grown by a voxel, mapped into the grid), or `None` when none can.
    fn grid_box_of_brick(&self, key: BrickKey) -> Option<([u32; 3], [u32; 3])> {
        let primary_from_overlay = self.overlay_from_primary.inverse();
        if !primary_from_overlay.is_finite() {
            return None;
        }
        let lo = key.0.map(|b| f64::from(b * LABEL_BRICK) - 1.0);
        let hi = key.0.map(|b| f64::from((b + 1) * LABEL_BRICK) + 1.0);
        let mut g_lo = DVec3::splat(f64::INFINITY);
        let mut g_hi = DVec3::splat(f64::NEG_INFINITY);
        for corner in 0..8 {
            let p = DVec3::new(
                if corner & 1 == 0 { lo[0] } else { hi[0] },
                if corner & 2 == 0 { lo[1] } else { hi[1] },
                if corner & 4 == 0 { lo[2] } else { hi[2] },
            );
            let centre = primary_from_overlay * (p - self.offset);
            let g = (centre + 0.5) / self.scale - 0.5;
            g_lo = g_lo.min(g);
            g_hi = g_hi.max(g);
        }
        let first = [g_lo.x, g_lo.y, g_lo.z].map(|v| v.floor().max(0.0));
        let last = [0, 1, 2].map(|a| {
            [g_hi.x, g_hi.y, g_hi.z][a]
                .ceil()
                .min(f64::from(self.grid_dims[a]) - 1.0)
        });
        if (0..3).any(|a| last[a] < first[a] || !first[a].is_finite()) {
            return None;
        }
        Some((first.map(|v| v as u32), last.map(|v| v as u32)))
    }
}

/// What one [`GridResampler::step`] left.
#[derive(Debug)]
pub enum GridProgress {
    /// Every grid slice is sampled: the grid to upload.
    Complete(Arc<Resampled>),
    /// Slices are left: `missing` lists level-0 bricks they met not resident (each once, at
    /// most the number asked for), none when only the voxel budget stopped the step.
    Incomplete {
        missing: Vec<BrickId>,
        slices_left: usize,
    },
}

/// A store's overlay resampled onto the 3D grid one z-slice at a time, over bricks that may not
/// be resident yet (the module doc).
pub struct GridResampler {
    grids: OverlayGrids,
    mapping: GridMapping,
    /// Per grid voxel (x fastest): a label (whole number) or a physical value, NaN outside the
    /// overlay, as the slices' sampler gives them.
    values: Vec<f32>,
    /// The grid's z-slices still to sample, in the order they are tried.
    todo: VecDeque<u32>,
    done: Option<Arc<Resampled>>,
}

impl GridResampler {
    /// A resampler of `grids`' overlay onto a grid of `dims` over the primary's index box.
    pub fn new(grids: OverlayGrids, dims: [u32; 3]) -> Self {
        let dims = dims.map(|d| d.max(1));
        let voxels = dims.iter().map(|&d| d as usize).product();
        GridResampler {
            mapping: GridMapping::new(&grids, dims),
            grids,
            values: vec![f32::NAN; voxels],
            todo: (0..dims[2]).collect(),
            done: None,
        }
    }

    /// The grid's dims.
    pub fn dims(&self) -> [u32; 3] {
        self.mapping.grid_dims
    }

    /// Samples grid z-slices from `bricks` until `voxel_budget` voxels were tried (at least
    /// one slice), `max_missing` missing bricks were listed (at least one), or none is left. A
    /// slice that meets a missing brick goes to the back of the queue, to be tried once the
    /// brick may be in. Complete once every slice is sampled (then every later call answers
    /// the same grid).
    pub fn step<B: LevelBricks + ?Sized>(
        &mut self,
        bricks: &mut B,
        voxel_budget: u64,
        max_missing: usize,
    ) -> Result<GridProgress, B::Error> {
        if let Some(done) = &self.done {
            return Ok(GridProgress::Complete(done.clone()));
        }
        let [nx, ny, _] = self.mapping.grid_dims;
        let slice_voxels = u64::from(nx) * u64::from(ny);
        let max_missing = max_missing.max(1);
        let mut missing: Vec<BrickId> = Vec::new();
        let mut tried = 0u64;
        // Each slice at most once a step: a slice sent to the back is not tried again now.
        for _ in 0..self.todo.len() {
            if (tried > 0 && tried >= voxel_budget) || missing.len() >= max_missing {
                break;
            }
            let Some(z) = self.todo.pop_front() else {
                break;
            };
            tried += slice_voxels;
            let mapping = &self.mapping;
            let pixels = |x: usize, y: usize| mapping.overlay_index([x as u32, y as u32, z]);
            let sampled = sample(
                bricks,
                &self.grids,
                &pixels,
                (nx as usize, ny as usize),
                max_missing - missing.len(),
            )?;
            match sampled {
                Sampled::Complete(values) => {
                    let start = z as usize * values.len();
                    self.values[start..start + values.len()].copy_from_slice(&values);
                }
                Sampled::Incomplete { missing: lacking } => {
                    for id in lacking {
                        if !missing.contains(&id) {
                            missing.push(id);
                        }
                    }
                    self.todo.push_back(z);
                }
            }
        }
        if !self.todo.is_empty() {
            return Ok(GridProgress::Incomplete {
                missing,
                slices_left: self.todo.len(),
            });
        }
        let done = Arc::new(self.finish());
        self.done = Some(done.clone());
        Ok(GridProgress::Complete(done))
    }

    /// The sampled values as the raycaster's grid: labels as colour-table slots in the order
    /// first met along the grid, continuous values with [`OVERLAY_OUTSIDE`] outside.
    fn finish(&mut self) -> Resampled {
        let values = std::mem::take(&mut self.values);
        let mut labels: Vec<i64> = Vec::new();
        let (kind, grid) = match self.grids.kind {
            OverlayKind::Labels => {
                let mut slot_of: HashMap<i64, usize> = HashMap::new();
                let slots: Vec<f32> = values
                    .into_iter()
                    .map(|v| {
                        let label = if v.is_finite() { v as i64 } else { 0 };
                        if label == 0 {
                            return 0.0;
                        }
                        let slot = *slot_of.entry(label).or_insert_with(|| {
                            labels.push(label);
                            labels.len()
                        });
                        slot as f32
                    })
                    .collect();
                (GridKind::Labels, slots)
            }
            OverlayKind::Continuous => {
                let outside = |v: f32| if v.is_finite() { v } else { OVERLAY_OUTSIDE };
                (
                    GridKind::Continuous,
                    values.into_iter().map(outside).collect(),
                )
            }
        };
        let volume = OverlayVolume {
            dims: self.mapping.grid_dims,
            kind,
            values: grid,
        };
        Resampled {
            volume: Arc::new(volume),
            labels,
        }
    }
}

/// Why an editable layer's grid could not be sampled.
#[derive(Debug, thiserror::Error)]
pub enum LayerGridError {
    #[error("reading the label layer: {0}")]
    Layer(#[from] SegmentError),
    #[error("making the 3D grid: {0}")]
    Grid(#[from] RenderError),
}

/// The 3D grid of an editable label layer, kept up to date edit by edit: each grid voxel takes
/// the label of the layer voxel nearest its centre (as [`GridResampler`] does for a store), and
/// after a change only the grid voxels whose nearest layer voxel lies in a changed brick are
/// sampled again. Changed bricks are found by identity: every edit, undo and redo puts a new
/// `Arc` image in the layer's edited bricks.
pub struct LayerGrid {
    dims: [u32; 3],
    values: Vec<f32>,
    /// Colour-table slot `i` (from 1) is label `labels[i - 1]`.
    labels: Vec<i64>,
    /// The edited bricks' images at the last update, by address.
    seen: HashMap<BrickKey, usize>,
    sampled_once: bool,
}

impl LayerGrid {
    pub fn new(dims: [u32; 3]) -> Self {
        LayerGrid {
            dims,
            values: vec![0.0; dims.iter().map(|&d| d as usize).product()],
            labels: Vec::new(),
            seen: HashMap::new(),
            sampled_once: false,
        }
    }

    /// The grid of a layer that has no edited brick yet (a new segmentation): all background
    /// already, so the first update samples only where edits reach, never the whole grid (the
    /// page, on its one thread, then never samples 2 M voxels in one frame).
    pub fn for_empty_layer(dims: [u32; 3]) -> Self {
        LayerGrid {
            sampled_once: true,
            ..LayerGrid::new(dims)
        }
    }

    /// Samples what changed since the last call (everything the first time); whether anything
    /// was sampled.
    pub fn update(
        &mut self,
        layer: &LabelLayer,
        grids: &OverlayGrids,
    ) -> Result<bool, LayerGridError> {
        let now: HashMap<BrickKey, usize> = layer
            .edited_bricks()
            .map(|(key, image)| (key, Arc::as_ptr(image) as *const u16 as usize))
            .collect();
        let mapping = GridMapping::new(grids, self.dims);
        if !self.sampled_once {
            self.sampled_once = true;
            self.seen = now;
            let all = ([0; 3], self.dims.map(|d| d.saturating_sub(1)));
            self.sample_box(layer, &mapping, all, None)?;
            return Ok(true);
        }
        let mut changed: Vec<BrickKey> = now
            .iter()
            .filter(|(key, address)| self.seen.get(key) != Some(address))
            .map(|(key, _)| *key)
            .collect();
        changed.extend(self.seen.keys().filter(|k| !now.contains_key(k)).copied());
        self.seen = now;
        if changed.is_empty() {
            return Ok(false);
        }
        for key in changed {
            if let Some(grid_box) = mapping.grid_box_of_brick(key) {
                self.sample_box(layer, &mapping, grid_box, Some(key))?;
            }
        }
        Ok(true)
    }

    /// Samples the grid voxels of `grid_box` (first and last, inclusive); with `only`, just
    /// those whose nearest layer voxel is in that brick (the others belong to its neighbours).
    fn sample_box(
        &mut self,
        layer: &LabelLayer,
        mapping: &GridMapping,
        (lo, hi): ([u32; 3], [u32; 3]),
        only: Option<BrickKey>,
    ) -> Result<(), SegmentError> {
        let mut last: Option<(BrickKey, Option<Arc<[u16]>>)> = None;
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    let Some(index) = mapping.nearest_overlay_voxel([x, y, z]) else {
                        if only.is_none() {
                            self.set([x, y, z], 0);
                        }
                        continue;
                    };
                    let (key, at) = layer.grid().brick_of(index);
                    if only.is_some_and(|o| o != key) {
                        continue;
                    }
                    if last.as_ref().is_none_or(|(k, _)| *k != key) {
                        let image = if layer.brick_is_empty(key) {
                            None
                        } else {
                            Some(layer.brick(key)?)
                        };
                        last = Some((key, image));
                    }
                    let label = last
                        .as_ref()
                        .and_then(|(_, b)| b.as_ref())
                        .map_or(0, |b| b[at]);
                    self.set([x, y, z], i64::from(label));
                }
            }
        }
        Ok(())
    }

    fn set(&mut self, voxel: [u32; 3], label: i64) {
        let slot = if label == 0 {
            0
        } else {
            match self.labels.iter().position(|&l| l == label) {
                Some(i) => i + 1,
                None => {
                    self.labels.push(label);
                    self.labels.len()
                }
            }
        };
        let [nx, ny, _] = self.dims.map(|d| d as usize);
        let [x, y, z] = voxel.map(|v| v as usize);
        self.values[x + nx * (y + ny * z)] = slot as f32;
    }

    /// The grid as it is now, for the raycaster.
    pub fn resampled(&self) -> Result<Resampled, LayerGridError> {
        Ok(Resampled {
            volume: Arc::new(OverlayVolume::new(
                self.dims,
                GridKind::Labels,
                self.values.clone(),
            )?),
            labels: self.labels.clone(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;
    use strata_render::{ValueMapping, VolumeGeometry};
    use strata_slices::SliceError;
    use strata_types::{BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS};

    /// A label volume's level-0 bricks made in memory, resident only once asked for twice.
    struct ArrivingBricks {
        dims: [u32; 3],
        asked: BTreeSet<[u32; 3]>,
        resident: BTreeSet<[u32; 3]>,
        always: bool,
    }

    fn label(i: [u32; 3]) -> u16 {
        ((i[0] / 5 + 3 * (i[1] / 7) + i[2] / 9) % 6) as u16
    }

    impl LevelBricks for ArrivingBricks {
        type Error = SliceError;
        fn brick(&mut self, id: BrickId) -> Result<Option<Arc<Vec<u16>>>, SliceError> {
            if !self.always && !self.resident.contains(&id.coords) {
                self.asked.insert(id.coords);
                return Ok(None);
            }
            let edge = BRICK_PAYLOAD as usize;
            let mut voxels = vec![0u16; BRICK_PAYLOAD_VOXELS];
            for z in 0..edge {
                for y in 0..edge {
                    for x in 0..edge {
                        let index = [x, y, z].map(|v| v as i64 - BRICK_APRON as i64);
                        let global: [i64; 3] = std::array::from_fn(|a| {
                            (index[a] + (id.coords[a] * BRICK_CORE) as i64)
                                .clamp(0, self.dims[a] as i64 - 1)
                        });
                        voxels[(z * edge + y) * edge + x] = label(global.map(|g| g as u32));
                    }
                }
            }
            Ok(Some(Arc::new(voxels)))
        }
    }

    /// A 50³ primary under a 70³ label map shifted and on a finer grid: resampled in small
    /// steps over bricks that arrive only after they are listed missing, the grid ends equal,
    /// value for value and slot for slot, to one sampled in one step with every brick
    /// resident; and each grid voxel holds the label of the overlay voxel nearest its centre.
    #[test]
    fn a_grid_resumed_as_bricks_arrive_equals_one_sampled_at_once() {
        let mut primary = VolumeGeometry::axis_aligned([50, 50, 50], [1.4; 3]);
        primary.origin_lps_mm = [0.0; 3];
        let mut overlay = VolumeGeometry::axis_aligned([70, 70, 70], [1.0; 3]);
        overlay.origin_lps_mm = [-2.3, 1.7, -0.6];
        let grids = OverlayGrids {
            primary: primary.clone(),
            primary_level_dims: vec![[50, 50, 50], [25, 25, 25], [13, 13, 13]],
            overlay: overlay.clone(),
            overlay_mapping: ValueMapping::default(),
            kind: OverlayKind::Labels,
        };
        let dims = grid_dims(&grids.primary_level_dims, 30 * 30 * 30);
        assert_eq!(dims, [25, 25, 25]);
        let mut whole_bricks = ArrivingBricks {
            dims: overlay.dims,
            asked: BTreeSet::new(),
            resident: BTreeSet::new(),
            always: true,
        };
        let GridProgress::Complete(whole) = GridResampler::new(grids.clone(), dims)
            .step(&mut whole_bricks, u64::MAX, usize::MAX)
            .expect("sampling")
        else {
            panic!("every brick is resident");
        };
        let mut bricks = ArrivingBricks {
            always: false,
            ..whole_bricks
        };
        let mut resampler = GridResampler::new(grids.clone(), dims);
        let mut steps = 0;
        let resumed = loop {
            steps += 1;
            assert!(steps < 10_000, "the resampling never completes");
            match resampler
                .step(&mut bricks, 2 * 25 * 25, 3)
                .expect("sampling")
            {
                GridProgress::Complete(grid) => break grid,
                GridProgress::Incomplete { missing, .. } => {
                    assert!(missing.len() <= 3, "listed {missing:?}");
                    // The bricks listed arrive before the next step.
                    bricks.resident.extend(missing.iter().map(|id| id.coords));
                }
            }
        };
        assert!(steps > 2, "resumed in {steps} steps");
        assert_eq!(resumed.volume.values, whole.volume.values);
        assert_eq!(resumed.labels, whole.labels);
        let mut compared = 0;
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let scale = 50.0 / 25.0;
                    let centre = (DVec3::new(x as f64, y as f64, z as f64) + 0.5) * scale - 0.5;
                    let o = overlay.index_from_patient(primary.patient_from_index(centre));
                    let tie = (0..3).any(|a| ((o[a] - o[a].floor()) - 0.5).abs() < 1e-6);
                    let outside = (0..3).any(|a| o[a] < -0.5 || o[a] >= 69.5);
                    let index = resumed.volume.values[(x + 25 * (y + 25 * z)) as usize] as usize;
                    let got = if index == 0 {
                        0
                    } else {
                        resumed.labels[index - 1]
                    };
                    if tie {
                        continue;
                    }
                    if outside {
                        assert_eq!(got, 0, "grid voxel ({x},{y},{z}) outside");
                        continue;
                    }
                    let n = o.round();
                    let expected = label([n.x as u32, n.y as u32, n.z as u32]);
                    assert_eq!(got, i64::from(expected), "grid voxel ({x},{y},{z})");
                    compared += 1;
                }
            }
        }
        assert!(compared > 5000, "only {compared} voxels compared");
    }

    /// The page's grid of a new segmentation: started as all background, it samples only where
    /// each edit reaches, yet after two edits and an undo it equals a grid sampled whole from
    /// the layer as it is (the layer on its own grid, shifted against the primary).
    #[test]
    fn an_empty_layers_grid_updated_edit_by_edit_equals_a_whole_sample() {
        let mut primary = VolumeGeometry::axis_aligned([50, 50, 50], [1.4; 3]);
        primary.origin_lps_mm = [0.0; 3];
        let mut geometry = VolumeGeometry::axis_aligned([70, 70, 70], [1.0; 3]);
        geometry.origin_lps_mm = [-2.3, 1.7, -0.6];
        let mut layer = LabelLayer::new_empty(geometry.clone()).expect("layer");
        layer.segments_mut().add("a").expect("segment");
        let grids = OverlayGrids {
            primary,
            primary_level_dims: vec![[50, 50, 50], [25, 25, 25], [13, 13, 13]],
            overlay: geometry,
            overlay_mapping: ValueMapping::default(),
            kind: OverlayKind::Labels,
        };
        let dims = [25, 25, 25];
        let mut grid = LayerGrid::for_empty_layer(dims);
        assert!(
            !grid.update(&layer, &grids).expect("update"),
            "nothing to sample"
        );
        let whole = |layer: &LabelLayer| {
            let mut whole = LayerGrid::new(dims);
            whole.update(layer, &grids).expect("whole");
            let r = whole.resampled().expect("grid");
            r.volume
                .values
                .iter()
                .map(|&v| {
                    if v == 0.0 {
                        0
                    } else {
                        r.labels[v as usize - 1]
                    }
                })
                .collect::<Vec<i64>>()
        };
        let labels_of = |grid: &LayerGrid| {
            let r = grid.resampled().expect("grid");
            r.volume
                .values
                .iter()
                .map(|&v| {
                    if v == 0.0 {
                        0
                    } else {
                        r.labels[v as usize - 1]
                    }
                })
                .collect::<Vec<i64>>()
        };
        let first = layer
            .edit("box", |w| {
                for k in 20..40 {
                    for j in 28..36 {
                        for i in 10..45 {
                            w.set([i, j, k], 1)?;
                        }
                    }
                }
                Ok(())
            })
            .expect("edit")
            .expect("changed");
        assert!(grid.update(&layer, &grids).expect("update"));
        layer
            .edit("block", |w| {
                // 3 voxels an axis: wider than the grid's 2.8-voxel spacing, so some grid
                // voxel centre's nearest voxel is in it.
                for k in 49..52 {
                    for j in 2..5 {
                        for i in 58..61 {
                            w.set([i, j, k], 7)?;
                        }
                    }
                }
                Ok(())
            })
            .expect("edit");
        assert!(grid.update(&layer, &grids).expect("update"));
        let now = whole(&layer);
        assert!(
            now.contains(&1) && now.contains(&7),
            "the edits reach the grid"
        );
        assert_eq!(labels_of(&grid), now);
        layer.revert(&first);
        assert!(grid.update(&layer, &grids).expect("update"));
        let now = whole(&layer);
        assert!(!now.contains(&1), "the undone box is gone");
        assert_eq!(labels_of(&grid), now);
    }
}
