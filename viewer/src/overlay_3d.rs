//! The overlay in the 3D view: the overlay volume resampled once, on a named background thread
//! (`strata-overlay-3d`), onto a bounded dense grid over the primary's index box (the primary's
//! own grid at the finest level whose voxel count fits [`OVERLAY_3D_MAX_VOXELS`]), which the
//! render thread uploads for the raycaster (strata-render's overlay.rs states how the grid is
//! sampled and blended). Labels are read nearest from the overlay store's level 0 as on the
//! slices and stored as indices into a colour table, so a style change (opacity, hidden labels,
//! colour map, range, threshold) is a new table only ([`lut_for`]): nothing is read again and
//! no grid is uploaded again.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use glam::DVec3;
use strata_render::overlay::OVERLAY_OUTSIDE;
use strata_render::{OverlayKind as GridKind, OverlayLut, OverlayVolume};
use strata_source::VolumeSource;

use super::overlay::{
    label_colour, trilinear, Overlay, OverlayBrickCache, OverlayGrids, OverlayKind, OverlayStyle,
    OVERLAY_CACHE_BYTES,
};
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

/// What the 3D view draws of the overlay this frame (part of the render request). Equal when
/// the same grid (by identity: it is large) has the same colour table.
#[derive(Clone)]
pub struct OverlayIn3d {
    pub volume: Arc<OverlayVolume>,
    pub lut: OverlayLut,
}

/// Not the grid's values (millions): requests are debug-printed in logs and test failures.
impl std::fmt::Debug for OverlayIn3d {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OverlayIn3d")
            .field("dims", &self.volume.dims)
            .field("kind", &self.volume.kind)
            .field("lut_entries", &self.lut.entries.len())
            .finish()
    }
}

impl PartialEq for OverlayIn3d {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.volume, &other.volume) && self.lut == other.lut
    }
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

enum State {
    Resampling,
    Done(Arc<Resampled>),
    /// Not drawn in 3D (the reason went to the log); the slices are unaffected.
    Failed,
}

/// One overlay's 3D grid, resampled on its own thread; dropped with the overlay.
pub struct Overlay3d {
    source: Arc<dyn VolumeSource>,
    state: Arc<Mutex<State>>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Overlay3d {
    /// Starts resampling `overlay` for the 3D view.
    pub fn start(overlay: &Overlay, repaint: Repaint) -> anyhow::Result<Self> {
        let source = overlay
            .source()
            .ok_or_else(|| anyhow::anyhow!("an edited label layer is drawn on the slices only"))?
            .clone();
        let grids = overlay.grids().clone();
        let dims = grid_dims(&grids.primary_level_dims, OVERLAY_3D_MAX_VOXELS);
        let state = Arc::new(Mutex::new(State::Resampling));
        let stop = Arc::new(AtomicBool::new(false));
        let (thread_state, thread_stop, store) = (state.clone(), stop.clone(), source.clone());
        let thread = std::thread::Builder::new()
            .name("strata-overlay-3d".into())
            .spawn(move || {
                let mut cache = OverlayBrickCache::new(OVERLAY_CACHE_BYTES);
                let result = resample(store.as_ref(), &mut cache, &grids, dims, &thread_stop);
                *lock_ignoring_poison(&thread_state) = match result {
                    Ok(r) => State::Done(Arc::new(r)),
                    Err(e) => {
                        eprintln!("strata: overlay in 3D: {e:#}");
                        State::Failed
                    }
                };
                repaint();
            })?;
        Ok(Overlay3d {
            source,
            state,
            stop,
            thread: Some(thread),
        })
    }

    /// Whether this grid is `overlay`'s (the same store).
    pub fn is_for(&self, overlay: &Overlay) -> bool {
        overlay
            .source()
            .is_some_and(|s| Arc::ptr_eq(&self.source, s))
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
}
