//! The overlay in the 3D view: the overlay volume resampled once, on a named background thread
//! (`strata-overlay-3d`), onto a bounded dense grid over the primary's index box (the primary's
//! own grid at the finest level whose voxel count fits [`OVERLAY_3D_MAX_VOXELS`]), which the
//! render thread uploads for the raycaster (strata-render's overlay.rs states how the grid is
//! sampled and blended). Labels are read nearest from the overlay store's level 0 as on the
//! slices and stored as indices into a colour table, so a style change (opacity, hidden labels,
//! colour map, range, threshold) is a new table only ([`lut_for`]): nothing is read again and
//! no grid is uploaded again.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use glam::DVec3;
use strata_render::model::overlay::OVERLAY_OUTSIDE;
use strata_render::{OverlayKind as GridKind, OverlayLut, OverlayVolume};
use strata_segment::{label_colour, BrickKey, LabelLayer, LABEL_BRICK};
use strata_source::VolumeSource;
use strata_viewer_ui::render_driver::OverlayIn3d;

use super::overlay::{
    trilinear, Overlay, OverlayBrickCache, OverlayGrids, OverlayKind, OverlayStyle,
    OVERLAY_CACHE_BYTES,
};
use super::segmentation::SharedLayer;
use super::sync::{lock_ignoring_poison, Repaint};

/// At most this many grid voxels (256³: 64 MiB of f32 on the GPU).
pub const OVERLAY_3D_MAX_VOXELS: u64 = 256 * 256 * 256;

/// Colour-map entries of a continuous overlay's table.
pub const CONTINUOUS_LUT_ENTRIES: usize = 256;

/// The overlay on the 3D grid, with the label each colour-table index stands for.
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

/// Resamples the overlay onto a `dims` grid over the primary's index box: grid voxel `i`'s
/// centre is primary index `(i + ½)·primary/dims − ½` per axis (strata-render overlay.rs),
/// taken to patient space and into the overlay's index space. Labels: nearest level-0 voxel;
/// continuous: trilinear (as the slices). Outside the overlay: background / OVERLAY_OUTSIDE.
pub fn resample(
    store: &dyn VolumeSource,
    cache: &mut OverlayBrickCache,
    grids: &OverlayGrids,
    dims: [u32; 3],
    stop: &AtomicBool,
) -> anyhow::Result<Resampled> {
    let overlay_from_primary =
        grids.overlay.index_from_patient_linear() * grids.primary.patient_from_index_linear();
    let offset = grids.overlay.index_from_patient(grids.primary.origin());
    let odims = grids.overlay.dims;
    let scale = DVec3::from([0, 1, 2].map(|a| grids.primary.dims[a] as f64 / dims[a] as f64));
    let inside =
        |p: DVec3| (0..3).all(|a| p[a] >= -0.5 && p[a] < odims[a] as f64 - 0.5 && p[a].is_finite());
    let mut values = Vec::with_capacity(dims.iter().map(|&d| d as usize).product());
    let mut labels: Vec<i64> = Vec::new();
    for z in 0..dims[2] {
        if stop.load(Ordering::Acquire) {
            anyhow::bail!("stopped");
        }
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let centre = (DVec3::new(x as f64, y as f64, z as f64) + 0.5) * scale - 0.5;
                let p = offset + overlay_from_primary * centre;
                let value = match grids.kind {
                    OverlayKind::Labels if inside(p) => {
                        let index = [0, 1, 2].map(|a| {
                            (p[a].round().max(0.0) as u32).min(odims[a].saturating_sub(1))
                        });
                        let stored = cache.voxel(store, index)?;
                        let label = grids.overlay_mapping.physical(stored as f64).round() as i64;
                        if label == 0 {
                            0.0
                        } else {
                            let slot = match labels.iter().position(|&l| l == label) {
                                Some(i) => i,
                                None => {
                                    labels.push(label);
                                    labels.len() - 1
                                }
                            };
                            (slot + 1) as f32
                        }
                    }
                    OverlayKind::Labels => 0.0,
                    OverlayKind::Continuous if inside(p) => {
                        trilinear(store, cache, odims, p, |s| {
                            grids.overlay_mapping.physical(s as f64)
                        })? as f32
                    }
                    OverlayKind::Continuous => OVERLAY_OUTSIDE,
                };
                values.push(value);
            }
        }
    }
    let kind = match grids.kind {
        OverlayKind::Labels => GridKind::Labels,
        OverlayKind::Continuous => GridKind::Continuous,
    };
    Ok(Resampled {
        volume: Arc::new(OverlayVolume::new(dims, kind, values)?),
        labels,
    })
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

/// The 3D grid of an editable label layer, kept up to date edit by edit: each grid voxel takes
/// the label of the layer voxel nearest its centre (as [`resample`] does for a store), and after
/// a change only the grid voxels whose nearest layer voxel lies in a changed brick are sampled
/// again. Changed bricks are found by identity: every edit, undo and redo puts a new `Arc`
/// image in the layer's edited bricks.
struct LayerGrid {
    dims: [u32; 3],
    values: Vec<f32>,
    /// Colour-table slot `i` (from 1) is label `labels[i - 1]`.
    labels: Vec<i64>,
    /// The edited bricks' images at the last update, by address.
    seen: HashMap<BrickKey, usize>,
    sampled_once: bool,
}

impl LayerGrid {
    fn new(dims: [u32; 3]) -> Self {
        LayerGrid {
            dims,
            values: vec![0.0; dims.iter().map(|&d| d as usize).product()],
            labels: Vec::new(),
            seen: HashMap::new(),
            sampled_once: false,
        }
    }

    /// Samples what changed since the last call (everything the first time); whether anything
    /// was sampled.
    fn update(&mut self, layer: &LabelLayer, grids: &OverlayGrids) -> anyhow::Result<bool> {
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
    ) -> anyhow::Result<()> {
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

    fn resampled(&self) -> anyhow::Result<Resampled> {
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

/// Grid voxel centres to overlay (layer) indices and back, as [`resample`] maps them.
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

    /// The overlay voxel nearest grid voxel `g`'s centre, or `None` outside the overlay (the
    /// same rounding as [`resample`]).
    fn nearest_overlay_voxel(&self, g: [u32; 3]) -> Option<[u32; 3]> {
        let centre = (DVec3::from(g.map(f64::from)) + 0.5) * self.scale - 0.5;
        let p = self.offset + self.overlay_from_primary * centre;
        let odims = self.overlay_dims;
        let inside =
            (0..3).all(|a| p[a] >= -0.5 && p[a] < odims[a] as f64 - 0.5 && p[a].is_finite());
        inside.then(|| {
            [0, 1, 2].map(|a| (p[a].round().max(0.0) as u32).min(odims[a].saturating_sub(1)))
        })
    }

    /// The grid voxels that can have their nearest overlay voxel in brick `key` (its box grown
    /// by a voxel, mapped into the grid), or `None` when none can.
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

enum State {
    Resampling,
    Done(Arc<Resampled>),
    /// Not drawn in 3D (the reason went to the log); the slices are unaffected.
    Failed,
}

/// What a 3D grid is resampled from.
enum Source3d {
    /// An imported overlay's store: resampled once.
    Store(Arc<dyn VolumeSource>),
    /// The session's editable label layer: resampled whole once, then after each change only
    /// where the changed label bricks reach ([`LayerGrid`]).
    Layer(Arc<SharedLayer>),
}

/// One overlay's 3D grid, resampled on its own thread; dropped with the overlay.
pub struct Overlay3d {
    source: Source3d,
    state: Arc<Mutex<State>>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// How often the layer's grid thread looks for a new revision: well under a frame at 60 Hz, so
/// a stroke reaches the 3D view within a frame or two of the slices, for a few atomic loads.
const LAYER_POLL: std::time::Duration = std::time::Duration::from_millis(4);

impl Overlay3d {
    /// Starts resampling `overlay` for the 3D view.
    pub fn start(overlay: &Overlay, repaint: Repaint) -> anyhow::Result<Self> {
        let grids = overlay.grids().clone();
        let dims = grid_dims(&grids.primary_level_dims, OVERLAY_3D_MAX_VOXELS);
        let state = Arc::new(Mutex::new(State::Resampling));
        let stop = Arc::new(AtomicBool::new(false));
        let (thread_state, thread_stop) = (state.clone(), stop.clone());
        let finish = move |result: anyhow::Result<Resampled>| {
            *lock_ignoring_poison(&thread_state) = match result {
                Ok(r) => State::Done(Arc::new(r)),
                Err(e) => {
                    eprintln!("strata: overlay in 3D: {e:#}");
                    State::Failed
                }
            };
            repaint();
        };
        let (source, thread) = if let Some(layer) = overlay.layer() {
            let layer = layer.clone();
            let thread_layer = layer.clone();
            let thread = std::thread::Builder::new()
                .name("strata-overlay-3d".into())
                .spawn(move || {
                    let mut grid = LayerGrid::new(dims);
                    let mut seen_revision = None;
                    while !thread_stop.load(Ordering::Acquire) {
                        // Read before sampling: a change during it makes the next pass run.
                        let revision = thread_layer.revision();
                        if seen_revision != Some(revision) {
                            seen_revision = Some(revision);
                            let updated = grid.update(&thread_layer.read(), &grids);
                            match updated {
                                Ok(false) => {}
                                Ok(true) => finish(grid.resampled()),
                                Err(e) => {
                                    finish(Err(e));
                                    return;
                                }
                            }
                        }
                        std::thread::sleep(LAYER_POLL);
                    }
                })?;
            (Source3d::Layer(layer), thread)
        } else {
            let store = overlay
                .source()
                .ok_or_else(|| anyhow::anyhow!("the overlay has neither a store nor a layer"))?
                .clone();
            let thread_store = store.clone();
            let thread = std::thread::Builder::new()
                .name("strata-overlay-3d".into())
                .spawn(move || {
                    let mut cache = OverlayBrickCache::new(OVERLAY_CACHE_BYTES);
                    finish(resample(
                        thread_store.as_ref(),
                        &mut cache,
                        &grids,
                        dims,
                        &thread_stop,
                    ));
                })?;
            (Source3d::Store(store), thread)
        };
        Ok(Overlay3d {
            source,
            state,
            stop,
            thread: Some(thread),
        })
    }

    /// Whether this grid is `overlay`'s (the same store or layer).
    pub fn is_for(&self, overlay: &Overlay) -> bool {
        match &self.source {
            Source3d::Store(store) => overlay.source().is_some_and(|s| Arc::ptr_eq(store, s)),
            Source3d::Layer(layer) => overlay.layer().is_some_and(|l| Arc::ptr_eq(layer, l)),
        }
    }

    pub fn resampled(&self) -> Option<Arc<Resampled>> {
        match &*lock_ignoring_poison(&self.state) {
            State::Done(r) => Some(r.clone()),
            _ => None,
        }
    }

    /// What the 3D view draws of `overlay` now: None while resampling, or when the overlay is
    /// hidden or not shown in 3D (then the raycaster's pipelines have no overlay code).
    pub fn request(&self, overlay: &Overlay) -> Option<OverlayIn3d> {
        if !overlay.style.visible || !overlay.style.show_in_3d {
            return None;
        }
        let resampled = self.resampled()?;
        Some(OverlayIn3d {
            volume: resampled.volume.clone(),
            lut: lut_for(overlay.kind, &overlay.style, &resampled.labels),
        })
    }
}

impl Drop for Overlay3d {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::overlay::tests::{
        import, label_of, write_nrrd, LABEL_DIMS, LABEL_ORIGIN, LABEL_SPACING,
    };
    use strata_storage::phantom::Phantom;

    /// Every grid voxel carries the label of the overlay voxel nearest to its centre's patient
    /// position (computed here in f64 from the label function), through the colour-table
    /// indices; a style change alters the table only.
    #[test]
    fn the_3d_grid_holds_the_nearest_label_at_each_voxel_centre() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("primary.strata");
        Phantom::cube(48)
            .write_store(&path, &Default::default())
            .expect("phantom store");
        let primary: Arc<dyn VolumeSource> =
            Arc::new(strata_storage::Store::open(&path).expect("open"));
        let nrrd = dir.path().join("labels.nrrd");
        write_nrrd(
            &nrrd,
            LABEL_DIMS,
            LABEL_SPACING,
            LABEL_ORIGIN,
            false,
            label_of,
        );
        let overlay = import(&nrrd, &dir.path().join("labels.strata"));
        let grids = OverlayGrids {
            primary: primary.header().geometry.clone(),
            primary_level_dims: primary.layout().level_dims.clone(),
            overlay: overlay.header().geometry.clone(),
            overlay_mapping: overlay.header().value_mapping.mapping,
            kind: OverlayKind::Labels,
        };
        // A budget below level 0: the grid is the primary's level 1.
        let level0 = grids.primary_level_dims[0];
        let dims = grid_dims(&grids.primary_level_dims, 30 * 30 * 30);
        assert_eq!(dims, grids.primary_level_dims[1]);
        assert_ne!(dims, level0);
        let mut cache = OverlayBrickCache::new(8 << 20);
        let r = resample(
            overlay.as_ref(),
            &mut cache,
            &grids,
            dims,
            &AtomicBool::new(false),
        )
        .expect("resampling");
        let scale = DVec3::from([0, 1, 2].map(|a| level0[a] as f64 / dims[a] as f64));
        let mut compared = 0;
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let centre = (DVec3::new(x as f64, y as f64, z as f64) + 0.5) * scale - 0.5;
                    let o = grids
                        .overlay
                        .index_from_patient(grids.primary.patient_from_index(centre));
                    let tie = (0..3).any(|a| ((o[a] - o[a].floor()) - 0.5).abs() < 1e-6);
                    let outside = (0..3).any(|a| o[a] < -0.5 || o[a] >= LABEL_DIMS[a] as f64 - 0.5);
                    if tie || outside {
                        continue;
                    }
                    let n = o.round();
                    let expected = label_of(n.x as u32, n.y as u32, n.z as u32) as i64;
                    let i = (x + dims[0] * (y + dims[1] * z)) as usize;
                    let index = r.volume.values[i] as usize;
                    let got = if index == 0 { 0 } else { r.labels[index - 1] };
                    assert_eq!(got, expected, "grid voxel ({x},{y},{z})");
                    compared += 1;
                }
            }
        }
        assert!(compared > 1000, "only {compared} voxels compared");
        let style = OverlayStyle {
            visible: true,
            show_in_3d: true,
            opacity: 0.5,
            hidden_labels: [2].into_iter().collect(),
            label_table: Default::default(),
            colour_map: crate::colour_maps::ColourMap::Hot,
            range: (0.0, 1.0),
            threshold: 0.0,
        };
        let lut = lut_for(OverlayKind::Labels, &style, &r.labels);
        assert_eq!(lut.entries.len(), r.labels.len() + 1);
        for (i, &label) in r.labels.iter().enumerate() {
            let alpha = lut.entries[i + 1][3];
            assert_eq!(alpha, if label == 2 { 0.0 } else { 0.5 }, "label {label}");
        }
    }

    /// The editable layer's 3D grid: sampled whole at first, then after each edit (and undo)
    /// only where the changed bricks reach, ending equal to a whole resample of the layer as it
    /// is and to the nearest label at each voxel centre computed here in f64 (a layer on its own
    /// 10 mm grid shifted against the 48³ primary, so the brick boxes map across voxels).
    #[test]
    fn the_edited_layer_grid_follows_each_edit_where_it_reaches() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("primary.strata");
        Phantom::cube(48)
            .write_store(&path, &Default::default())
            .expect("phantom store");
        let primary = strata_storage::Store::open(&path).expect("open");
        let mut geometry =
            strata_render::VolumeGeometry::axis_aligned(LABEL_DIMS, [LABEL_SPACING; 3]);
        geometry.origin_lps_mm = LABEL_ORIGIN;
        let mut layer = LabelLayer::new_empty(geometry).expect("layer");
        layer.segments_mut().add("a").expect("segment");
        let shared = Arc::new(SharedLayer::new(layer));
        let overlay = Overlay::start_editable(
            shared.clone(),
            "segmentation".into(),
            primary.header().geometry.clone(),
            primary.layout().level_dims.clone(),
            Arc::new(|| {}),
        )
        .expect("overlay");
        let grid = Overlay3d::start(&overlay, Arc::new(|| {})).expect("3D grid");
        assert!(grid.is_for(&overlay));
        let grids = overlay.grids().clone();
        let dims = grid_dims(&grids.primary_level_dims, OVERLAY_3D_MAX_VOXELS);
        // Waits for the grid thread to publish a grid other than `previous` (not a timing
        // assertion: a bound on waiting, far above the milliseconds it takes).
        let next = |previous: Option<&Arc<Resampled>>| -> Arc<Resampled> {
            let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
            loop {
                if let Some(r) = grid.resampled() {
                    if previous.is_none_or(|p| !Arc::ptr_eq(p, &r)) {
                        return r;
                    }
                }
                assert!(std::time::Instant::now() < deadline, "no new 3D grid");
                std::thread::sleep(std::time::Duration::from_millis(5));
            }
        };
        let labels_of = |r: &Resampled| -> Vec<i64> {
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
                .collect()
        };
        let first = next(None);
        assert!(labels_of(&first).iter().all(|&l| l == 0));

        // Two edits in different bricks, one of them across a brick edge.
        let edit = shared
            .write()
            .edit("boxes", |w| {
                for k in 3..12 {
                    for j in 28..36 {
                        for i in 10..17 {
                            w.set([i, j, k], 1)?;
                        }
                    }
                }
                for v in [[33u32, 2, 30], [34, 2, 30], [33, 3, 30]] {
                    w.set(v, 7)?;
                }
                Ok(())
            })
            .expect("edit")
            .expect("changed");
        let mut after = next(Some(&first));
        // The thread may publish once per revision it saw; wait until it shows the edit.
        let expected_of = |layer: &LabelLayer| -> Vec<i64> {
            let level0 = grids.primary_level_dims[0];
            let scale = DVec3::from([0, 1, 2].map(|a| level0[a] as f64 / dims[a] as f64));
            let mut out = Vec::new();
            for z in 0..dims[2] {
                for y in 0..dims[1] {
                    for x in 0..dims[0] {
                        let centre = (DVec3::new(x as f64, y as f64, z as f64) + 0.5) * scale - 0.5;
                        let o = grids
                            .overlay
                            .index_from_patient(grids.primary.patient_from_index(centre));
                        let inside =
                            (0..3).all(|a| o[a] >= -0.5 && o[a] < LABEL_DIMS[a] as f64 - 0.5);
                        out.push(if inside {
                            let n = o.round();
                            i64::from(
                                layer
                                    .get([n.x as u32, n.y as u32, n.z as u32])
                                    .expect("voxel"),
                            )
                        } else {
                            0
                        });
                    }
                }
            }
            out
        };
        let want = expected_of(&shared.read());
        while labels_of(&after) != want {
            after = next(Some(&after));
        }
        assert!(
            want.contains(&1) && want.contains(&7),
            "the edits reach the grid"
        );
        // Incremental equals whole: a fresh grid sampled whole from the layer as it is now.
        let mut whole = LayerGrid::new(dims);
        assert!(whole.update(&shared.read(), &grids).expect("whole"));
        assert_eq!(labels_of(&whole.resampled().expect("grid")), want);

        // Undo: the bricks' before images go back, and so does the grid.
        shared.write().revert(&edit);
        let zeros = vec![0i64; want.len()];
        while labels_of(&after) != zeros {
            after = next(Some(&after));
        }
    }
}
