//! The render driver both viewers call (issue 47, item 2): it owns what is applied to the
//! streaming volume now (transfer function, traversal, the overlay in 3D) and which request the
//! last frame answered, and turns a new [`RenderRequest`] into a typed difference, a list of
//! [`RenderChange`]s, each with one action: a new streaming volume for another traversal, the
//! transfer function's tables uploaded again, the overlay's grid or colour table uploaded or
//! cleared, and for the view's own fields (camera, settings, pacing, still passes) a new frame
//! whose pipeline the raycaster picks, or compiles in the background, from the settings' key.
//!
//! Before it the desktop's render thread diffed the request field by field inside one 483-line
//! loop and the browser kept a string key of the preset and its edits; an applied state that
//! drifted from the request (a transfer function not uploaded after a traversal switch, an
//! overlay left on a new volume) was easy to write in either. Here [`RenderDriver::changes`]
//! destructures the request, so a field added to it does not compile until its change and
//! action are written down, and the unit tests below check that each kind of change yields its
//! action and nothing else, and that an unchanged request yields nothing.
//!
//! It lives in strata-viewer-ui because that crate already builds for wasm32 and reaches the
//! render crate and the loader without their default features, and it knows nothing of either
//! app's threads: the desktop (viewer/src/volume_session.rs) calls it on its render thread, the
//! browser (web/src/browser.rs) on the page's frame loop. How a new streaming volume is opened
//! (budgets, background or inline work) is the platform's, passed in as a function. The passes
//! a platform composes after the raycast (the desktop's adaptive pass with its oracle thread,
//! progressive refinement) stay with it; the driver says when they must start again
//! ([`RenderChange::StillPasses`] and every other change), and holds the rules both share:
//! which views refine progressively ([`jitter_refines`]), how many frames by default, and how
//! many refinement frames may be queued ([`frames_in_flight`]).

use std::sync::Arc;
use std::time::Duration;

use strata_loader::{LoaderError, StreamingVolume};
use strata_render::{
    Camera, GpuContext, OverlayLut, OverlayVolume, RenderSettings, ShadowMode, TransferFunction,
    Traversal,
};

/// Progressive frames a still view accumulates by default, in both viewers: the jitter's noise
/// falls as 1/√N, so 64 frames leave 1/8 of one frame's (render/tests/progressive.rs measures
/// the slope).
pub const DEFAULT_PROGRESSIVE_FRAMES: u32 = 64;

/// Whether a still view of `settings` is refined progressively: with shadows, occlusion or
/// scattering (the light's effects, issue 37). The jitter moves the shadow and occlusion rays'
/// sample positions as well as the main ray's, and those secondary rays, sampled more coarsely
/// than the main ray, are where a still frame's wood-grain is most visible. Plain DVR is left
/// to the controller's still refinement of the sampling rate (and the adaptive pass): it was
/// not measured whether its main-ray wood-grain is worth 64 more frames at rest.
pub fn jitter_refines(settings: &RenderSettings) -> bool {
    settings.shadows.mode != ShadowMode::Off
        || settings.occlusion.is_some()
        || settings.scattering.is_some()
}

/// Most refinement frames queued before a viewer waits for the GPU (the desktop's export) or
/// submits no more (the page, whose frame loop never waits).
pub const MOST_FRAMES_IN_FLIGHT: u32 = 8;
/// A frame slower than this is waited for on its own: Cancel must not wait behind a queue of
/// slow frames (lavapipe draws a 2× cinematic frame in seconds), and the live view's next
/// frame waits behind whatever refinement left queued.
pub const SLOW_FRAME: Duration = Duration::from_millis(100);
/// Frames faster than this are queued more deeply (a real GPU's: 1-5 ms).
pub const FAST_FRAME: Duration = Duration::from_millis(20);

/// How many refinement frames may be queued before waiting, from how long the last ones took:
/// one while they are slow, doubling up to [`MOST_FRAMES_IN_FLIGHT`] while they are fast.
pub fn frames_in_flight(current: u32, per_frame: Duration) -> u32 {
    if per_frame > SLOW_FRAME {
        1
    } else if per_frame < FAST_FRAME {
        (current.max(1) * 2).min(MOST_FRAMES_IN_FLIGHT)
    } else {
        current.max(1)
    }
}

/// What the 3D view draws of the overlay (part of the render request). Equal when the same
/// grid (by identity: it is large) has the same colour table.
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

/// What the UI wants to see; the render loop always works on the newest one.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderRequest {
    pub camera: Camera,
    pub settings: RenderSettings,
    pub transfer_function: TransferFunction,
    /// Some(fps): the time-critical controller sets the sampling rate; None: `settings.quality`.
    pub target_fps: Option<f64>,
    /// The user is dragging: interactive quality; when it stops, still frames refine.
    pub interacting: bool,
    /// The overlay drawn in 3D, if any.
    pub overlay: Option<OverlayIn3d>,
    /// The raycaster's traversal; None: the loader's choice (flat where it fits). A change
    /// restarts the streaming volume on the same device.
    pub traversal: Option<Traversal>,
    /// Some(ε): once the view is still and the cut converged, the final frame is drawn by the
    /// adaptive pass with the block oracle's ε (the desktop's adaptive_view.rs); DVR and MIP only.
    pub adaptive_epsilon: Option<f64>,
    /// How many jittered frames a still, converged view with shadows, occlusion or
    /// scattering accumulates into its running mean (progressive refinement); 0: off.
    pub progressive_frames: u32,
}

/// One difference between a request and what is applied or drawn, named by its action.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RenderChange {
    /// Another traversal: it is the index's layout, so a new streaming volume (the bricks are
    /// read again), opened with the request's transfer function and without an overlay.
    Traversal,
    /// Another transfer function: its tables are uploaded again (the cut's emptiness follows).
    TransferFunction,
    /// The same overlay grid with another colour table: the table only is uploaded.
    OverlayColours,
    /// Another overlay grid, or one where there was none: grid and table are uploaded.
    OverlayGrid,
    /// The overlay is gone: frames are drawn without it.
    OverlayCleared,
    /// No frame answers a request on this volume yet (a new device or volume, or an export
    /// drew over the last one): draw.
    NotDrawn,
    /// Another camera: draw.
    Camera,
    /// Other settings (mode, size, shading, effects, sampling): draw; the raycaster picks the
    /// pipeline for the settings' key, compiling a new one in the background.
    Settings,
    /// Another target rate or the drag started or stopped: the controller plans again.
    Pacing,
    /// Another adaptive ε or progressive frame count: the still passes start again.
    StillPasses,
}

/// What is on the streaming volume now.
#[derive(Clone, Debug)]
struct Applied {
    transfer_function: TransferFunction,
    traversal: Option<Traversal>,
    overlay: Option<OverlayIn3d>,
}

/// The applied state of one streaming volume and the request its last frame answered.
#[derive(Debug)]
pub struct RenderDriver {
    applied: Applied,
    drawn: Option<RenderRequest>,
}

impl RenderDriver {
    /// The driver of a volume just opened with `transfer_function` and `traversal` (no overlay,
    /// nothing drawn).
    pub fn new(transfer_function: TransferFunction, traversal: Option<Traversal>) -> Self {
        RenderDriver {
            applied: Applied {
                transfer_function,
                traversal,
                overlay: None,
            },
            drawn: None,
        }
    }

    /// What `request` changes, in the order [`RenderDriver::apply`] acts on it; empty when its
    /// frame is drawn and nothing differs.
    pub fn changes(&self, request: &RenderRequest) -> Vec<RenderChange> {
        // Destructured so that a field added to the request fails to compile here until its
        // change is written down.
        let RenderRequest {
            camera,
            settings,
            transfer_function,
            target_fps,
            interacting,
            overlay,
            traversal,
            adaptive_epsilon,
            progressive_frames,
        } = request;
        let mut changes = Vec::new();
        let applied = &self.applied;
        let reopened = *traversal != applied.traversal;
        if reopened {
            // The new volume is opened with the request's function and no overlay.
            changes.push(RenderChange::Traversal);
        } else if *transfer_function != applied.transfer_function {
            changes.push(RenderChange::TransferFunction);
        }
        let overlay_now = if reopened { &None } else { &applied.overlay };
        match (overlay, overlay_now) {
            (new, old) if new == old => {}
            (Some(new), Some(old)) if Arc::ptr_eq(&new.volume, &old.volume) => {
                changes.push(RenderChange::OverlayColours)
            }
            (Some(_), _) => changes.push(RenderChange::OverlayGrid),
            (None, _) => changes.push(RenderChange::OverlayCleared),
        }
        let Some(drawn) = &self.drawn else {
            changes.push(RenderChange::NotDrawn);
            return changes;
        };
        if *camera != drawn.camera {
            changes.push(RenderChange::Camera);
        }
        if *settings != drawn.settings {
            changes.push(RenderChange::Settings);
        }
        if (*target_fps, *interacting) != (drawn.target_fps, drawn.interacting) {
            changes.push(RenderChange::Pacing);
        }
        if (*adaptive_epsilon, *progressive_frames)
            != (drawn.adaptive_epsilon, drawn.progressive_frames)
        {
            changes.push(RenderChange::StillPasses);
        }
        changes
    }

    /// Whether `request` differs from the one the last frame answered (or none was drawn).
    pub fn is_new(&self, request: &RenderRequest) -> bool {
        self.drawn.as_ref() != Some(request)
    }

    /// Applies `request`'s changes to `volume`: a traversal change replaces it by `reopen`'s
    /// (called with the request's transfer function and traversal), the transfer function and
    /// the overlay are uploaded; the view's changes are left to the frame that follows. Returns
    /// the changes. On an error the applied state is what reached the volume.
    pub fn apply<E: From<LoaderError>>(
        &mut self,
        ctx: &GpuContext,
        volume: &mut StreamingVolume,
        request: &RenderRequest,
        reopen: impl FnOnce(&TransferFunction, Option<Traversal>) -> Result<StreamingVolume, E>,
    ) -> Result<Vec<RenderChange>, E> {
        let changes = self.changes(request);
        // Called at most once: a request has one traversal.
        let mut reopen = Some(reopen);
        for change in &changes {
            match change {
                RenderChange::Traversal => {
                    let Some(reopen) = reopen.take() else {
                        continue;
                    };
                    *volume = reopen(&request.transfer_function, request.traversal)?;
                    self.applied = Applied {
                        transfer_function: request.transfer_function.clone(),
                        traversal: request.traversal,
                        overlay: None,
                    };
                    self.drawn = None;
                }
                RenderChange::TransferFunction => {
                    volume.set_transfer_function(ctx, &request.transfer_function)?;
                    self.applied.transfer_function = request.transfer_function.clone();
                }
                RenderChange::OverlayColours | RenderChange::OverlayGrid => {
                    let Some(overlay) = &request.overlay else {
                        continue;
                    };
                    let dims = volume.geometry().dims;
                    let raycaster = volume.raycaster_mut();
                    if *change == RenderChange::OverlayColours {
                        raycaster.set_overlay_lut(ctx, &overlay.lut)
                    } else {
                        raycaster.set_overlay(ctx, &overlay.volume, &overlay.lut, dims)
                    }
                    .map_err(LoaderError::from)?;
                    self.applied.overlay = Some(overlay.clone());
                }
                RenderChange::OverlayCleared => {
                    volume.raycaster_mut().clear_overlay();
                    self.applied.overlay = None;
                }
                RenderChange::NotDrawn
                | RenderChange::Camera
                | RenderChange::Settings
                | RenderChange::Pacing
                | RenderChange::StillPasses => {}
            }
        }
        Ok(changes)
    }

    /// The request the last frame answered, if it still stands for the volume's view.
    pub fn drawn_request(&self) -> Option<&RenderRequest> {
        self.drawn.as_ref()
    }

    /// The transfer function on the volume now.
    pub fn transfer_function(&self) -> &TransferFunction {
        &self.applied.transfer_function
    }

    /// Records that a frame answering `request` was drawn (after [`RenderDriver::apply`]).
    pub fn drawn(&mut self, request: &RenderRequest) {
        self.drawn = Some(request.clone());
    }

    /// The last frame no longer answers its request (an export drew over the volume's cut and
    /// size): the next request is drawn again, with nothing uploaded again.
    pub fn forget_drawn(&mut self) {
        self.drawn = None;
    }

    /// Records a transfer function applied outside [`RenderDriver::apply`] (the browser's
    /// sample, drawn by an `OffscreenRenderer` rather than a streaming volume).
    pub fn transfer_function_applied(&mut self, transfer_function: &TransferFunction) {
        self.applied.transfer_function = transfer_function.clone();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_render::{OverlayKind, Projection, RenderMode};

    fn request() -> RenderRequest {
        RenderRequest {
            camera: Camera::look_at(
                [0.0, -300.0, 0.0],
                [0.0, 0.0, 0.0],
                [0.0, 0.0, 1.0],
                Projection::Perspective { fov_y_deg: 30.0 },
            ),
            settings: RenderSettings::default(),
            transfer_function: TransferFunction::preset("ct-bone").expect("a built-in preset"),
            target_fps: None,
            interacting: false,
            overlay: None,
            traversal: None,
            adaptive_epsilon: None,
            progressive_frames: 0,
        }
    }

    fn overlay(values: f32) -> OverlayIn3d {
        OverlayIn3d {
            volume: Arc::new(
                OverlayVolume::new([2, 2, 2], OverlayKind::Labels, vec![values; 8])
                    .expect("eight values for 2³"),
            ),
            lut: OverlayLut {
                entries: vec![[0.0; 4], [1.0, 0.0, 0.0, 0.5]],
                lo: 0.0,
                hi: 1.0,
                threshold: 0.0,
            },
        }
    }

    /// A driver that has applied and drawn `request`.
    fn drawn(request: &RenderRequest) -> RenderDriver {
        let mut driver = RenderDriver::new(request.transfer_function.clone(), request.traversal);
        driver.applied.overlay = request.overlay.clone();
        driver.drawn(request);
        driver
    }

    #[test]
    fn an_unchanged_request_changes_nothing() {
        let request = request();
        let driver = drawn(&request);
        assert_eq!(driver.changes(&request), vec![]);
        assert!(!driver.is_new(&request));
        let with_overlay = RenderRequest {
            overlay: Some(overlay(1.0)),
            ..request
        };
        assert_eq!(drawn(&with_overlay).changes(&with_overlay), vec![]);
    }

    #[test]
    fn each_view_change_yields_its_own_change_and_nothing_else() {
        let base = request();
        let driver = drawn(&base);
        let mut moved = base.clone();
        moved.camera.eye[0] = 10.0;
        assert_eq!(driver.changes(&moved), vec![RenderChange::Camera]);
        let mut mip = base.clone();
        mip.settings.mode = RenderMode::Mip;
        assert_eq!(driver.changes(&mip), vec![RenderChange::Settings]);
        let dragging = RenderRequest {
            interacting: true,
            ..base.clone()
        };
        assert_eq!(driver.changes(&dragging), vec![RenderChange::Pacing]);
        let paced = RenderRequest {
            target_fps: Some(30.0),
            ..base.clone()
        };
        assert_eq!(driver.changes(&paced), vec![RenderChange::Pacing]);
        let adaptive = RenderRequest {
            adaptive_epsilon: Some(0.01),
            ..base.clone()
        };
        assert_eq!(driver.changes(&adaptive), vec![RenderChange::StillPasses]);
        let progressive = RenderRequest {
            progressive_frames: 16,
            ..base.clone()
        };
        assert_eq!(
            driver.changes(&progressive),
            vec![RenderChange::StillPasses]
        );
        for changed in [moved, mip, dragging, paced, adaptive, progressive] {
            assert!(driver.is_new(&changed), "{changed:?}");
        }
    }

    #[test]
    fn a_transfer_function_change_uploads_it_and_nothing_else() {
        let base = request();
        let soft = RenderRequest {
            transfer_function: TransferFunction::preset("ct-soft-tissue")
                .expect("a built-in preset"),
            ..base.clone()
        };
        assert_ne!(soft.transfer_function, base.transfer_function);
        // Drawn with the new function already: only the upload is missing.
        let mut driver = drawn(&soft);
        driver.applied.transfer_function = base.transfer_function.clone();
        assert_eq!(driver.changes(&soft), vec![RenderChange::TransferFunction]);
        driver.transfer_function_applied(&soft.transfer_function);
        assert_eq!(driver.changes(&soft), vec![]);
    }

    #[test]
    fn a_traversal_change_restarts_streaming_with_the_request_s_function_and_overlay() {
        let base = request();
        let driver = drawn(&base);
        let octree = RenderRequest {
            traversal: Some(Traversal::Octree),
            ..base.clone()
        };
        assert_eq!(driver.changes(&octree), vec![RenderChange::Traversal]);
        // The new volume is opened with the request's function: no upload of its own.
        let octree_soft = RenderRequest {
            transfer_function: TransferFunction::preset("ct-soft-tissue")
                .expect("a built-in preset"),
            ..octree.clone()
        };
        assert_eq!(driver.changes(&octree_soft), vec![RenderChange::Traversal]);
        // The new volume has no overlay: the request's is uploaded whole, even if unchanged.
        let with_overlay = RenderRequest {
            overlay: Some(overlay(1.0)),
            ..base
        };
        let driver = drawn(&with_overlay);
        let octree_overlay = RenderRequest {
            traversal: Some(Traversal::Octree),
            ..with_overlay
        };
        assert_eq!(
            driver.changes(&octree_overlay),
            vec![RenderChange::Traversal, RenderChange::OverlayGrid]
        );
    }

    #[test]
    fn overlay_changes_upload_the_grid_the_colours_or_clear_it() {
        let base = request();
        let labels = overlay(1.0);
        let with_overlay = RenderRequest {
            overlay: Some(labels.clone()),
            ..base.clone()
        };
        // Drawn already with the request's overlay, so only the overlay's own change shows.
        let mut driver = drawn(&with_overlay);
        driver.applied.overlay = None;
        assert_eq!(
            driver.changes(&with_overlay),
            vec![RenderChange::OverlayGrid]
        );
        let mut driver = drawn(&with_overlay);
        let mut dimmer = labels.clone();
        dimmer.lut.entries[1][3] = 0.25;
        let restyled = RenderRequest {
            overlay: Some(dimmer),
            ..base.clone()
        };
        driver.drawn(&restyled);
        assert_eq!(
            driver.changes(&restyled),
            vec![RenderChange::OverlayColours]
        );
        // Equal values in another grid are another grid (identity: grids are large).
        let regridded = RenderRequest {
            overlay: Some(OverlayIn3d {
                volume: Arc::new((*labels.volume).clone()),
                lut: labels.lut.clone(),
            }),
            ..base.clone()
        };
        driver.drawn(&regridded);
        assert_eq!(driver.changes(&regridded), vec![RenderChange::OverlayGrid]);
        driver.drawn(&base);
        assert_eq!(driver.changes(&base), vec![RenderChange::OverlayCleared]);
    }

    #[test]
    fn slow_refinement_frames_are_sent_one_at_a_time_and_fast_ones_queue_deeper() {
        let slow = SLOW_FRAME + Duration::from_millis(1);
        let fast = FAST_FRAME / 2;
        let between = (SLOW_FRAME + FAST_FRAME) / 2;
        assert_eq!(frames_in_flight(MOST_FRAMES_IN_FLIGHT, slow), 1);
        assert_eq!(frames_in_flight(1, fast), 2);
        assert_eq!(frames_in_flight(4, between), 4);
        let mut depth = 1;
        for _ in 0..10 {
            depth = frames_in_flight(depth, fast);
        }
        assert_eq!(depth, MOST_FRAMES_IN_FLIGHT, "bounded however fast");
        // None in flight is never the answer: the run would stop.
        assert_eq!(frames_in_flight(0, between), 1);
    }

    #[test]
    fn only_the_lights_effects_are_refined_by_jitter() {
        let mut settings = RenderSettings::default();
        assert!(!jitter_refines(&settings), "plain DVR");
        settings.shadows.mode = ShadowMode::Cache;
        assert!(jitter_refines(&settings));
        settings.shadows.mode = ShadowMode::Off;
        settings.occlusion = Some(strata_render::Occlusion { radius_mm: 4.0 });
        assert!(jitter_refines(&settings));
        settings.occlusion = None;
        settings.scattering = Some(strata_render::Scattering { g: 0.3, blend: 0.5 });
        assert!(jitter_refines(&settings));
    }

    #[test]
    fn nothing_drawn_yet_or_after_an_export_draws_without_uploading_again() {
        let base = request();
        let mut driver = drawn(&base);
        driver.forget_drawn();
        assert_eq!(driver.changes(&base), vec![RenderChange::NotDrawn]);
        assert!(driver.is_new(&base));
        let fresh = RenderDriver::new(base.transfer_function.clone(), None);
        assert_eq!(fresh.changes(&base), vec![RenderChange::NotDrawn]);
    }
}
