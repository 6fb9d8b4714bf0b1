//! Progressive refinement of the page's still 3D view (issue 47 item 3), as the desktop's
//! render thread refines it (viewer/src/volume_session.rs): once a view's frame is final (its
//! cut converged, drawn at full quality) and its settings have an effect that jitter refines
//! (shadows, occlusion, scattering: strata-viewer-ui's `render_driver::jitter_refines`), the
//! page draws jittered frames of the same view, frame n with jitter seed n, and shows their
//! running mean (render's `passes::progressive::Accumulator`, on the GPU, shown without a
//! copy), up to the driver's `DEFAULT_PROGRESSIVE_FRAMES`, then rests. Any change draws a live
//! frame, which drops the run; a cut that changes under it bumps the mean's generation, which
//! restarts it at 1.
//!
//! The page's frame loop never waits: at most one pass per animation frame, and none while as
//! many passes are on the GPU as the driver's frames-in-flight rule allows for their measured
//! time (`render_driver::frames_in_flight`: one at a time while they are slow, as on a software
//! adapter, so a drag is never queued behind refinement). A pass's time is from its submission
//! to the queue's work-done callback.
//!
//! What it publishes for the browser tests: the canvas's `data-refine`,
//! `run=R;passes=N/T;state=refining|converged|stopped|off` (R counts the runs started, so a
//! test sees a restart).

use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use strata_render::passes::progressive::{jittered_frame, Accumulator, ViewKey};
use strata_render::{Camera, GpuContext, Raycaster, RenderError, RenderSettings};
use strata_viewer_ui::render_driver::{frames_in_flight, jitter_refines};

/// A run whose cut keeps changing restarts its mean at every change; after this many times its
/// frame count in passes it stops where it is (as the desktop's export bounds its mean).
const MOST_PASSES_PER_FRAME_COUNTED: u32 = 4;

/// The refinement of the view on screen (a served store's or the sample's).
pub(crate) struct Refinement {
    /// The running mean, made on first use (its pipeline compiles once).
    accumulator: Option<Accumulator>,
    run: Option<Run>,
    /// Runs started on this page: a test tells a restart by it.
    runs_started: u64,
    /// Passes submitted whose GPU work the queue has not reported done.
    in_flight: Arc<AtomicU32>,
    /// The last finished pass's time from submission to done (µs), and how many have finished.
    last_pass_us: Arc<AtomicU64>,
    passes_done: Arc<AtomicU64>,
    /// How many passes may be in flight now, and the finished count it was last set at.
    allowed_in_flight: u32,
    allowed_at: u64,
}

/// The jittered frames of one still view.
struct Run {
    camera: Camera,
    /// The final live frame's settings, which every pass jitters.
    settings: RenderSettings,
    generation: u64,
    seed: u32,
    accumulated: u32,
    total: u32,
}

impl Run {
    fn stopped(&self) -> bool {
        self.seed >= self.total.saturating_mul(MOST_PASSES_PER_FRAME_COUNTED)
    }
}

impl Refinement {
    pub(crate) fn new() -> Self {
        Refinement {
            accumulator: None,
            run: None,
            runs_started: 0,
            in_flight: Arc::default(),
            last_pass_us: Arc::default(),
            passes_done: Arc::default(),
            allowed_in_flight: 1,
            allowed_at: 0,
        }
    }

    /// A live frame is drawn: the mean so far shows another view (or is superseded by it).
    pub(crate) fn restart(&mut self) {
        self.run = None;
    }

    /// After a live frame of `camera` and `settings`: where it is `final_frame` (converged, at
    /// full quality) and its effects refine with jitter, a run of `total` passes starts. True
    /// when one did (the caller asks for the next animation frame).
    pub(crate) fn start_if_final(
        &mut self,
        camera: &Camera,
        settings: &RenderSettings,
        final_frame: bool,
        total: u32,
    ) -> bool {
        if !final_frame || total == 0 || !jitter_refines(settings) {
            return false;
        }
        self.run = Some(Run {
            camera: *camera,
            settings: RenderSettings {
                count_samples: false,
                ..settings.clone()
            },
            generation: 0,
            seed: 0,
            accumulated: 0,
            total,
        });
        self.runs_started += 1;
        true
    }

    /// A run is under way and its mean is not complete.
    pub(crate) fn wants_pass(&self) -> bool {
        self.run
            .as_ref()
            .is_some_and(|r| r.accumulated < r.total && !r.stopped())
    }

    /// The picture on screen is final: no run, or its mean complete (or stopped).
    pub(crate) fn settled(&self) -> bool {
        !self.wants_pass()
    }

    /// The camera and jittered settings of the next pass; None where no run wants one, or
    /// while as many passes are on the GPU as the frames-in-flight rule allows.
    pub(crate) fn next_pass(&mut self) -> Option<(Camera, RenderSettings)> {
        if !self.wants_pass() {
            return None;
        }
        let done = self.passes_done.load(Ordering::Acquire);
        if done != self.allowed_at {
            let per_pass = Duration::from_micros(self.last_pass_us.load(Ordering::Acquire));
            self.allowed_in_flight = frames_in_flight(self.allowed_in_flight, per_pass);
            self.allowed_at = done;
        }
        if self.in_flight.load(Ordering::Acquire) >= self.allowed_in_flight {
            return None;
        }
        let run = self.run.as_mut()?;
        let settings = jittered_frame(&run.settings, run.seed);
        run.seed += 1;
        Some((run.camera, settings))
    }

    /// Folds the frame `raycaster` just drew for [`Refinement::next_pass`] into the mean
    /// (`cut_changed`: that frame uploaded bricks or rewrote the page table, so the mean starts
    /// again). Returns the mean's view to show, or None where the frame was a stand-in drawn
    /// while the jittered pipeline compiles (not counted: averaging stand-ins gives back the
    /// single frame).
    pub(crate) fn accumulate(
        &mut self,
        gpu: &GpuContext,
        raycaster: &Raycaster,
        cut_changed: bool,
    ) -> Result<Option<&wgpu::TextureView>, RenderError> {
        let Some(run) = self.run.as_mut() else {
            return Ok(None);
        };
        if cut_changed {
            run.generation += 1;
        }
        if !raycaster.last_pipeline_key().is_some_and(|key| key.jitter) {
            return Ok(None);
        }
        let output = raycaster.output_texture().ok_or_else(|| {
            RenderError::Readback("the raycaster has no output to accumulate".into())
        })?;
        let key = ViewKey::new(&run.camera, &run.settings).with_generation(run.generation);
        let accumulator = self
            .accumulator
            .get_or_insert_with(|| Accumulator::new(gpu));
        let submitted = web_time::Instant::now();
        run.accumulated = accumulator.accumulate(gpu, &key, output)?;
        self.in_flight.fetch_add(1, Ordering::AcqRel);
        let (in_flight, last, done) = (
            self.in_flight.clone(),
            self.last_pass_us.clone(),
            self.passes_done.clone(),
        );
        gpu.queue.on_submitted_work_done(move || {
            let micros = u64::try_from(submitted.elapsed().as_micros()).unwrap_or(u64::MAX);
            last.store(micros, Ordering::Release);
            done.fetch_add(1, Ordering::AcqRel);
            in_flight.fetch_sub(1, Ordering::AcqRel);
        });
        Ok(accumulator.mean_view())
    }

    /// The complete mean (the still view's final picture), once a run finished it.
    pub(crate) fn refined_texture(&self) -> Option<&wgpu::Texture> {
        let run = self.run.as_ref()?;
        if run.accumulated < run.total {
            return None;
        }
        self.accumulator.as_ref()?.mean_texture()
    }

    /// The mean on screen (a screenshot is what is seen), once a pass of the run is in it.
    pub(crate) fn shown_texture(&self) -> Option<&wgpu::Texture> {
        self.run.as_ref().filter(|run| run.accumulated > 0)?;
        self.accumulator.as_ref()?.mean_texture()
    }

    /// What the browser tests read of it: the canvas's `data-refine`.
    pub(crate) fn publish(&self) {
        crate::canvas_attributes::set("data-refine", &self.state_text());
    }

    fn state_text(&self) -> String {
        let (passes, total, state) = match &self.run {
            None => (0, 0, "off"),
            Some(run) if run.accumulated >= run.total => (run.accumulated, run.total, "converged"),
            Some(run) if run.stopped() => (run.accumulated, run.total, "stopped"),
            Some(run) => (run.accumulated, run.total, "refining"),
        };
        format!(
            "run={};passes={passes}/{total};state={state}",
            self.runs_started
        )
    }
}
