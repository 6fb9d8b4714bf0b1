//! The overlay in the 3D view on the desktop: the overlay volume resampled once, on a named
//! background thread (`strata-overlay-3d`), onto a bounded dense grid over the primary's index
//! box (the primary's own grid at the finest level whose voxel count fits
//! [`OVERLAY_3D_MAX_VOXELS`]), which the render thread uploads for the raycaster
//! (strata-render's overlay.rs states how the grid is sampled and blended). The resampling,
//! the editable layer's grid and the colour table are strata-viewer-ui's `overlay_3d`, which
//! the page runs too (web/src/overlay_view.rs, a few grid slices per animation frame); this
//! module is the desktop's half: the thread, its blocking reads, and following the layer's
//! revisions.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use strata_source::VolumeSource;
use strata_viewer_ui::overlay_3d::{
    grid_dims, lut_for, GridProgress, GridResampler, LayerGrid, Resampled, OVERLAY_3D_MAX_VOXELS,
};
use strata_viewer_ui::render_driver::OverlayIn3d;

use super::overlay::{CachedStore, Overlay, OverlayBrickCache, OverlayGrids, OVERLAY_CACHE_BYTES};
use super::segmentation::SharedLayer;
use super::sync::{lock_ignoring_poison, Repaint};

/// Resamples the overlay onto a `dims` grid over the primary's index box (strata-viewer-ui's
/// `GridResampler`, fed by blocking reads), one grid slice at a time so that `stop` ends it.
pub fn resample(
    store: &dyn VolumeSource,
    cache: &mut OverlayBrickCache,
    grids: &OverlayGrids,
    dims: [u32; 3],
    stop: &AtomicBool,
) -> anyhow::Result<Arc<Resampled>> {
    let mut resampler = GridResampler::new(grids.clone(), dims);
    let mut bricks = CachedStore { store, cache };
    loop {
        if stop.load(Ordering::Acquire) {
            anyhow::bail!("stopped");
        }
        // One slice a step (a budget of one voxel): reads block, nothing is ever missing.
        match resampler.step(&mut bricks, 1, 1)? {
            GridProgress::Complete(resampled) => return Ok(resampled),
            GridProgress::Incomplete { missing, .. } if !missing.is_empty() => {
                anyhow::bail!("blocking reads left bricks missing: {missing:?}")
            }
            GridProgress::Incomplete { .. } => {}
        }
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
        let finish = move |result: anyhow::Result<Arc<Resampled>>| {
            *lock_ignoring_poison(&thread_state) = match result {
                Ok(r) => State::Done(r),
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
                                Ok(true) => {
                                    finish(grid.resampled().map(Arc::new).map_err(Into::into))
                                }
                                Err(e) => {
                                    finish(Err(e.into()));
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
    use crate::overlay::{OverlayKind, OverlayStyle};
    use glam::DVec3;
    use strata_segment::LabelLayer;
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
