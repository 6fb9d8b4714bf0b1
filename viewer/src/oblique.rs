//! Oblique reformat, the desktop's side: the plane, the image a view asks for and its trilinear
//! resampling are strata-slices' (`strata_slices::oblique`, shared with the page and tested
//! there against an f64 model); here the resampling runs on a named thread
//! (`strata-oblique-reader`) with blocking reads through a bounded brick cache, the newest
//! request winning. "Align to 3D" takes the 3D camera's axes ([`plane_facing`]); the brush
//! paints a disc in the same plane ([`brush_plane`]), and the label overlay is sampled at the
//! same pixel centres (overlay.rs).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};

use glam::DVec3;
use strata_render::Camera;
use strata_segment::tools::brush::SlicePlane;
use strata_slices::oblique::{LevelBricks, ObliqueImage, ObliquePlane, ObliqueRequest, Resampled};
use strata_source::VolumeSource;
use strata_types::BrickId;

use super::sync::{lock_ignoring_poison, wait_ignoring_poison, Repaint};

/// Decompressed bricks kept for oblique slices (bytes).
pub const OBLIQUE_CACHE_BYTES: usize = 96 << 20;

/// The oblique view's colour: its title, and its plane's outline in the 3D view.
pub const OBLIQUE_COLOUR: egui::Color32 = egui::Color32::from_rgb(200, 140, 255);

/// Through `centre`, facing like `camera`: screen right and up as the 3D view has them
/// ("Align to 3D").
pub fn plane_facing(camera: &Camera, centre: DVec3, extent_mm: f64) -> ObliquePlane {
    let basis = camera.basis();
    ObliquePlane::facing_axes(centre, basis.right, basis.up, extent_mm)
}

/// The plane as the brush's disc lies in it: through the centre, spanned by screen right
/// and down (LPS, orthonormal), so a disc of the brush's size in mm is a circle on screen
/// whatever the label grid's spacing or orientation. (Here, not in strata-slices: that
/// crate knows nothing of strata-segment.)
pub fn brush_plane(plane: &ObliquePlane) -> SlicePlane {
    SlicePlane::Oblique {
        centre_lps: plane.centre,
        u: plane.right,
        v: plane.down,
    }
}

/// Bricks of any level read from the store, bounded (cleared when full: a plane's bricks
/// are read again at once, in the order it needs them).
pub struct LevelBrickCache {
    budget_bricks: usize,
    bricks: HashMap<BrickId, Arc<Vec<u16>>>,
}

impl LevelBrickCache {
    pub fn new(budget_bytes: usize) -> Self {
        LevelBrickCache {
            budget_bricks: (budget_bytes / (strata_types::BRICK_PAYLOAD_VOXELS * 2)).max(16),
            bricks: HashMap::new(),
        }
    }

    /// Brick `id`, read from `store` (blocking) unless cached.
    pub fn brick(
        &mut self,
        store: &dyn VolumeSource,
        id: BrickId,
    ) -> anyhow::Result<Arc<Vec<u16>>> {
        if let Some(brick) = self.bricks.get(&id) {
            return Ok(brick.clone());
        }
        if self.bricks.len() >= self.budget_bricks {
            self.bricks.clear();
        }
        let brick = Arc::new(store.read_brick(id)?);
        self.bricks.insert(id, brick.clone());
        Ok(brick)
    }
}

/// The store's bricks as the shared resampling asks for them: always resident, read now.
struct StoreBricks<'a> {
    store: &'a dyn VolumeSource,
    cache: &'a mut LevelBrickCache,
}

impl LevelBricks for StoreBricks<'_> {
    type Error = anyhow::Error;
    fn brick(&mut self, id: BrickId) -> anyhow::Result<Option<Arc<Vec<u16>>>> {
        self.cache.brick(self.store, id).map(Some)
    }
}

/// Resamples one oblique image from `store` (strata-slices' resampling, with blocking reads).
pub fn resample(
    store: &dyn VolumeSource,
    cache: &mut LevelBrickCache,
    request: &ObliqueRequest,
) -> anyhow::Result<ObliqueImage> {
    let mut bricks = StoreBricks { store, cache };
    match strata_slices::oblique::resample(
        &store.header().geometry,
        store.layout(),
        &mut bricks,
        request,
        usize::MAX,
    )? {
        Resampled::Complete(image) => Ok(image),
        Resampled::Incomplete { missing } => Err(anyhow::anyhow!(
            "the oblique image lacks bricks {missing:?}, which blocking reads always give"
        )),
    }
}

struct Shared {
    pending: Mutex<Option<ObliqueRequest>>,
    result: Mutex<Option<ObliqueImage>>,
    error: Mutex<Option<String>>,
    wake: Condvar,
    stop: AtomicBool,
}

/// The oblique view's reader thread: the newest request wins.
pub struct ObliqueReader {
    shared: Arc<Shared>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl ObliqueReader {
    pub fn start(store: Arc<dyn VolumeSource>, repaint: Repaint) -> anyhow::Result<Self> {
        let shared = Arc::new(Shared {
            pending: Mutex::new(None),
            result: Mutex::new(None),
            error: Mutex::new(None),
            wake: Condvar::new(),
            stop: AtomicBool::new(false),
        });
        let thread_shared = shared.clone();
        let thread = std::thread::Builder::new()
            .name("strata-oblique-reader".into())
            .spawn(move || {
                let mut cache = LevelBrickCache::new(OBLIQUE_CACHE_BYTES);
                loop {
                    let next = {
                        let mut pending = lock_ignoring_poison(&thread_shared.pending);
                        loop {
                            if thread_shared.stop.load(Ordering::Acquire) {
                                return;
                            }
                            if let Some(r) = pending.take() {
                                break r;
                            }
                            pending = wait_ignoring_poison(&thread_shared.wake, pending);
                        }
                    };
                    match resample(store.as_ref(), &mut cache, &next) {
                        Ok(image) => {
                            *lock_ignoring_poison(&thread_shared.result) = Some(image);
                            *lock_ignoring_poison(&thread_shared.error) = None;
                        }
                        Err(e) => {
                            *lock_ignoring_poison(&thread_shared.error) = Some(format!("{e:#}"))
                        }
                    }
                    repaint();
                }
            })?;
        Ok(ObliqueReader {
            shared,
            thread: Some(thread),
        })
    }

    pub fn request(&self, request: ObliqueRequest) {
        if self.latest().is_some_and(|l| l.request == request) {
            return;
        }
        let mut pending = lock_ignoring_poison(&self.shared.pending);
        if *pending != Some(request) {
            *pending = Some(request);
            self.shared.wake.notify_all();
        }
    }

    pub fn latest(&self) -> Option<ObliqueImage> {
        lock_ignoring_poison(&self.shared.result).clone()
    }

    pub fn error(&self) -> Option<String> {
        lock_ignoring_poison(&self.shared.error).clone()
    }
}

impl Drop for ObliqueReader {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        self.shared.wake.notify_all();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
