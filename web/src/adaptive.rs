//! Adaptive sampling of the page's still 3D view (issue 47), as the desktop draws it
//! (viewer/src/adaptive_view.rs): once a served store's view is still and its cut converged,
//! and the link asks for it (`adaptive=EPS`, strata-viewer-ui's `adaptive`), the final frame is
//! drawn by render's adaptive pass over the same resident cut, with the block oracle built from
//! the CPU copies of the cut's bricks.
//!
//! The page has one thread, so the oracle is built a bounded number of slots per animation
//! frame ([`SLOTS_PER_FRAME`], render's `BlockOracleBuild`, whose table equals the one-shot
//! `block_oracle_with` the desktop's thread builds), never waiting on a fetch: a brick the CPU
//! cache no longer holds is not fetched, the raycaster's frame stays with the reason said. The
//! build belongs to one `OracleKey` (volume, residency generation, transfer function, ε, slice
//! spacing, target); a cut or TF change drops it, so no oracle is applied to a cut or TF it was
//! not built from. The frame is shown from the pass's colour target (no readback); its sample
//! counters come back through an asynchronous map. Any failure leaves the raycaster's frame on
//! screen, with the reason in the status line and in `data-adaptive`.
//!
//! What it publishes for the browser tests: the canvas's `data-adaptive`,
//! `state=off|building|drawn|failed;slots=D/T;samples=N;reason=…`
//! (`web/tests/browser/adaptive.rs`).

use strata_loader::{CutPayloads, StreamingVolume};
use strata_render::passes::adaptive::{
    AdaptiveConfig, AdaptivePass, BlockOracleBuild, CountsReadback,
};
use strata_render::{Camera, GpuContext, RenderSettings, TransferFunction, Traversal};
use strata_viewer_ui::adaptive::{self, OracleKey};
use strata_viewer_ui::render_driver::jitter_refines;

/// Oracle slots built per animation frame. A slot is a node's 16³ blocks: its own distances
/// read 64 voxels per block, its dilation up to 9³ neighbours per block at a slice per voxel,
/// a few milliseconds in wasm; four keep a frame of the page responsive.
pub(crate) const SLOTS_PER_FRAME: usize = 4;

/// The page's adaptive pass and the oracle of its current cut.
#[derive(Default)]
pub(crate) struct StillAdaptive {
    pass: Option<AdaptivePass>,
    /// Counts the streaming volumes this page opened (a 4-D frame is a new one): its slots
    /// and residency generations start again.
    volume: u64,
    /// The oracle being built, with what it is built from.
    build: Option<Build>,
    /// The key of the oracle set on the pass.
    applied: Option<OracleKey>,
    /// The still view whose adaptive frame is wanted: its camera and the raycaster's final
    /// settings.
    wanted: Option<(Camera, RenderSettings)>,
    /// The adaptive frame of the wanted view is on screen.
    shown: bool,
    /// The key whose build or frame failed (no retry loop for it) and why.
    failed: Option<(OracleKey, String)>,
    counts: Option<CountsReadback>,
    state: State,
}

struct Build {
    key: OracleKey,
    oracle: BlockOracleBuild,
    payloads: CutPayloads,
}

#[derive(Default)]
enum State {
    #[default]
    Off,
    Building {
        done: usize,
        total: usize,
    },
    Drawn {
        samples: Option<u64>,
        epsilon: f64,
    },
    Failed(String),
}

/// Why an adaptive frame could not be drawn; the status line shows it.
#[derive(Debug, thiserror::Error)]
enum AdaptiveError {
    #[error("adaptive sampling needs the flat page table (the loader chose the octree traversal)")]
    OctreeTraversal,
    #[error(
        "adaptive sampling off: {0} of the cut's bricks are no longer in the page's memory \
         (the page never waits for a fetch)"
    )]
    BricksEvicted(usize),
    #[error("the adaptive pass failed to render: {0}")]
    Render(strata_render::RenderError),
    #[error("the adaptive pass drew no image")]
    NoImage,
}

impl StillAdaptive {
    /// A new streaming volume: nothing built for the old one may be applied.
    pub(crate) fn new_volume(&mut self) {
        self.volume += 1;
        self.build = None;
        self.applied = None;
        self.failed = None;
        self.restart();
    }

    /// A live frame is drawn: the adaptive frame, if any, no longer shows. The build goes on
    /// only if the next still view has its key.
    pub(crate) fn restart(&mut self) {
        self.wanted = None;
        self.shown = false;
        self.counts = None;
        self.state = State::Off;
    }

    /// After a live frame of `camera` drawn with `settings` (`overlay`: with a 3D overlay):
    /// where it is `final_frame` and the link asks for adaptive sampling of this view, its
    /// adaptive frame is wanted. True when it is (the caller asks for the next animation frame).
    pub(crate) fn start_if_final(
        &mut self,
        camera: &Camera,
        settings: &RenderSettings,
        final_frame: bool,
        epsilon: Option<f64>,
        overlay: bool,
    ) -> bool {
        if !final_frame || epsilon.is_none() {
            return false;
        }
        if let Some(reason) = adaptive::not_applicable(settings.mode, overlay) {
            self.state = State::Failed(reason.into());
            return false;
        }
        if jitter_refines(settings) || settings.effective_light_cache() {
            // The link's light effects are refused with adaptive sampling on (view_state's
            // settings); a frame that still has them is refinement's (refine.rs).
            return false;
        }
        self.wanted = Some((
            *camera,
            RenderSettings {
                count_samples: false,
                ..settings.clone()
            },
        ));
        true
    }

    /// More animation frames are needed: the oracle builds, the frame is to be drawn, or its
    /// counters are on their way.
    pub(crate) fn wants_frames(&self) -> bool {
        (self.wanted.is_some() && !self.shown && !matches!(self.state, State::Failed(_)))
            || self.counts.is_some()
    }

    /// Whether the picture on screen is final: no adaptive frame wanted, it is shown, or it
    /// failed (the raycaster's frame is final).
    pub(crate) fn settled(&self) -> bool {
        self.wanted.is_none() || self.shown || matches!(self.state, State::Failed(_))
    }

    /// One animation frame's work towards the wanted adaptive frame over `volume`'s current
    /// cut: builds a few oracle slots, or draws the frame once the oracle is there. Returns the
    /// frame to show when one was drawn now.
    pub(crate) fn step(
        &mut self,
        gpu: &GpuContext,
        volume: &StreamingVolume,
        transfer_function: &TransferFunction,
        epsilon: f64,
        repaint: &egui::Context,
    ) -> Option<&wgpu::TextureView> {
        self.take_counts();
        let (_, settings) = self.wanted.as_ref()?;
        if self.shown {
            return None;
        }
        let key = OracleKey::new(
            self.volume,
            volume.residency_generation(),
            transfer_function,
            epsilon,
            settings,
        );
        if let Some((failed, reason)) = &self.failed {
            if *failed == key {
                self.state = State::Failed(reason.clone());
                return None;
            }
        }
        match self.advance(gpu, volume, key.clone(), repaint) {
            Ok(true) => self.pass.as_ref()?.output_view(),
            Ok(false) => None,
            Err(error) => {
                let reason = error.to_string();
                self.failed = Some((key, reason.clone()));
                self.state = State::Failed(reason);
                None
            }
        }
    }

    /// Builds towards `key`'s oracle, or draws with it: Ok(true) once a frame was drawn.
    fn advance(
        &mut self,
        gpu: &GpuContext,
        volume: &StreamingVolume,
        key: OracleKey,
        repaint: &egui::Context,
    ) -> Result<bool, AdaptiveError> {
        if volume.traversal() != Traversal::Flat {
            return Err(AdaptiveError::OctreeTraversal);
        }
        if self.applied.as_ref() != Some(&key) {
            // A build for another cut or TF is dropped: its table would not fit this one.
            if self.build.as_ref().is_some_and(|b| b.key != key) {
                self.build = None;
            }
            if self.build.is_none() {
                self.build = Some(start_build(volume, key.clone())?);
            }
            let Some(build) = self.build.as_mut() else {
                return Ok(false);
            };
            let finished = build.oracle.step(&build.payloads, SLOTS_PER_FRAME);
            let (done, total) = build.oracle.progress();
            self.state = State::Building { done, total };
            if !finished {
                return Ok(false);
            }
            let missing = build.oracle.missing_bricks();
            let distances = build.oracle.finished();
            self.build = None;
            if missing > 0 {
                return Err(AdaptiveError::BricksEvicted(missing));
            }
            let pass = self
                .pass
                .get_or_insert_with(|| AdaptivePass::new(gpu, volume.brick_cache()));
            pass.set_oracle(gpu, &distances.unwrap_or_default());
            self.applied = Some(key.clone());
        }
        let (Some(pass), Some((camera, settings))) = (self.pass.as_mut(), self.wanted.as_ref())
        else {
            return Ok(false);
        };
        let scene = volume.scene(camera, settings);
        pass.render(gpu, &scene, &AdaptiveConfig::default())
            .map_err(AdaptiveError::Render)?;
        if pass.output_view().is_none() {
            return Err(AdaptiveError::NoImage);
        }
        let repaint = repaint.clone();
        self.counts = Some(pass.read_counts_async(gpu, move || repaint.request_repaint()));
        self.shown = true;
        self.state = State::Drawn {
            samples: None,
            epsilon: key.epsilon,
        };
        Ok(true)
    }

    /// Takes the drawn frame's sample count once its buffer is mapped.
    pub(crate) fn take_counts(&mut self) {
        let Some(taken) = self.counts.as_ref().and_then(CountsReadback::take) else {
            return;
        };
        self.counts = None;
        match taken {
            Ok(counts) => {
                if let State::Drawn { samples, .. } = &mut self.state {
                    *samples = Some(counts.total_samples());
                }
            }
            // The frame is drawn; its figure could not be read.
            Err(e) => {
                if matches!(self.state, State::Drawn { .. }) {
                    self.state = State::Failed(e.to_string());
                }
            }
        }
    }

    /// The adaptive frame on screen, for a capture or a screenshot (what is seen).
    pub(crate) fn shown_texture(&self) -> Option<&wgpu::Texture> {
        if !self.shown {
            return None;
        }
        self.pass.as_ref()?.output_texture()
    }

    /// The status bar's line: building, drawn (samples and ε) or why not.
    pub(crate) fn status_line(&self) -> Option<String> {
        match &self.state {
            State::Off => None,
            State::Building { done, total } => {
                Some(format!("adaptive: building oracle… ({done}/{total} slots)"))
            }
            State::Drawn { samples, epsilon } => Some(match samples {
                Some(samples) => adaptive::status_line(*samples, None, *epsilon),
                None => format!("adaptive: ε {}", adaptive::format_epsilon(*epsilon)),
            }),
            State::Failed(reason) => Some(reason.clone()),
        }
    }

    /// What the browser tests read of it: the canvas's `data-adaptive`.
    pub(crate) fn publish(&self) {
        let text = match &self.state {
            State::Off => "state=off".to_string(),
            State::Building { done, total } => format!("state=building;slots={done}/{total}"),
            State::Drawn { samples, .. } => match samples {
                Some(samples) => format!("state=drawn;samples={samples}"),
                None => "state=drawn".to_string(),
            },
            State::Failed(reason) => format!("state=failed;reason={reason}"),
        };
        crate::canvas_attributes::set("data-adaptive", &text);
    }
}

/// A build of `key`'s oracle from the CPU copies of `volume`'s resident cut; refused where
/// the CPU cache no longer holds some of them (reading them would wait on the network).
fn start_build(volume: &StreamingVolume, key: OracleKey) -> Result<Build, AdaptiveError> {
    let payloads = volume.cut_payloads();
    if payloads.missing() > 0 {
        return Err(AdaptiveError::BricksEvicted(payloads.missing()));
    }
    let oracle = BlockOracleBuild::new(
        payloads.table().clone(),
        volume.mapping(),
        &key.transfer_function,
        key.epsilon,
        AdaptiveConfig::default().l_max,
        key.quality,
        key.target,
    );
    Ok(Build {
        key,
        oracle,
        payloads,
    })
}
