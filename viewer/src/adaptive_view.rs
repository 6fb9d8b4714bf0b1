//! The still view's final frame by adaptive sampling (render's `strata_render::passes::adaptive`, the
//! adaptive-sampling paper): while the camera moves or the cut refines, the raycaster draws
//! under the time-critical controller as always; once the view is still and the streaming cut
//! has converged, this draws the last frame with the adaptive pass over the same resident cut
//! (same brick cache, page table and transfer function on the GPU).
//!
//! The pass needs the per-block oracle (`block_oracle`), 0.1-1 s of CPU over every resident
//! node's voxels. It is built on its own named thread ([`ORACLE_THREAD`]) from a snapshot of
//! the cut (its page table and the CPU cache's copies of its bricks; what the CPU cache no
//! longer holds is read through the volume source on that thread), never on the render or the
//! UI thread; the raycaster's frame stays on screen meanwhile. An oracle is valid for one
//! `OracleKey` (strata-viewer-ui's `adaptive`, shared with the page: volume, residency
//! generation, transfer function, ε, slice spacing): a build for another key is cancelled, and
//! no oracle is ever applied to a cut or TF it was not built from. Failures (the pass cannot be created or rendered, the oracle thread panics or cannot
//! read a brick) fall back to the raycaster's frame with the reason said.
//!
//! The pass writes the pick depth (the published frame carries it, so picking works on the
//! adaptive frame) and visibility words as the raycaster does. Those words are not handed to
//! the loader: the adaptive frame is drawn only over a cut the raycaster's own feedback has
//! already settled, and letting the final frame's slightly different visibility move that
//! cut would restart refinement under it (raycaster, then adaptive, then perhaps again).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use strata_loader::{CutPayloads, StreamingVolume};
use strata_render::passes::adaptive::{
    block_oracle_with, AdaptiveConfig, AdaptiveFrame, AdaptivePass,
};
use strata_render::{
    Camera, GpuContext, PageTable, RenderMode, RenderSettings, TransferFunction, Traversal,
    ValueMapping,
};
use strata_viewer_ui::adaptive::{self, OracleKey};

use std::future::Future;

/// The thread that builds oracles.
pub const ORACLE_THREAD: &str = "strata-adaptive-oracle";

/// A finished oracle: the distances the pass reads, per cache slot and 2³ block.
pub struct BuiltOracle {
    pub key: OracleKey,
    /// The page table it was built from (tests re-render the same cut from it).
    #[cfg_attr(not(test), allow(dead_code))]
    pub table: Arc<PageTable>,
    pub distances: Vec<f32>,
}

/// What the adaptive pass drew, carried by the published frame.
#[derive(Clone)]
pub struct AdaptiveFacts {
    #[cfg_attr(not(test), allow(dead_code))]
    pub samples_per_level: [u64; 4],
    pub samples: u64,
    /// Samples of the raycaster's converged frame of the same view (its counter), if counted.
    pub raycaster_samples: Option<u64>,
    pub epsilon: f64,
    /// The settings the pass rendered with (the raycaster's final frame's).
    #[cfg_attr(not(test), allow(dead_code))]
    pub settings: RenderSettings,
    #[cfg_attr(not(test), allow(dead_code))]
    pub oracle: Arc<BuiltOracle>,
}

impl AdaptiveFacts {
    /// "adaptive: 0.65 M samples (2.9× fewer than the raycaster), ε 0.001".
    pub fn status_line(&self) -> String {
        adaptive::status_line(self.samples, self.raycaster_samples, self.epsilon)
    }
}

/// The still view the adaptive frame is asked for (the session's render request, in the
/// terms this module needs; it does not reach back into volume_session.rs).
pub struct StillView<'a> {
    /// Some(ε): the user turned adaptive sampling on.
    pub epsilon: Option<f64>,
    pub mode: RenderMode,
    pub camera: &'a Camera,
    pub transfer_function: &'a TransferFunction,
    /// A 3D overlay is drawn (the raycaster's alone).
    pub overlay: bool,
}

impl StillView<'_> {
    /// Why this view is drawn by the raycaster alone although adaptive sampling is on.
    pub fn not_applicable(&self) -> Option<&'static str> {
        self.epsilon?;
        adaptive::not_applicable(self.mode, self.overlay)
    }

    /// Whether the final frame of this view is the adaptive pass's.
    pub fn wanted(&self) -> bool {
        self.epsilon.is_some() && self.not_applicable().is_none()
    }
}

/// One step towards the adaptive frame.
pub enum Step {
    /// The oracle is building on its thread; the raycaster's frame stays.
    Building,
    /// Drawn: the frame and what drew it.
    Drawn(Box<(AdaptiveFrame, AdaptiveFacts)>),
    /// The raycaster's frame is final; the reason for the status line.
    Failed(String),
    /// A render call failed: the caller classifies it (a lost device is the recovery's, any
    /// other error a fallback, [`AdaptiveView::note_failure`]).
    RenderError(anyhow::Error),
}

/// Why the adaptive refinement of a still view cannot go on; the status line shows it.
#[derive(Debug, thiserror::Error)]
enum AdaptiveError {
    #[error("the adaptive oracle could not read a brick: {0}")]
    ReadBrick(strata_loader::LoaderError),
    /// The oracle's thread ended without a result; its panic message.
    #[error("the adaptive oracle thread failed: {0}")]
    ThreadPanicked(String),
    #[error("the adaptive oracle thread could not start: {0}")]
    ThreadStart(std::io::Error),
    /// The validation error or panic message of the pass's creation.
    #[error("the adaptive pass could not be created: {0}")]
    PassCreation(String),
}

struct Pending {
    key: OracleKey,
    cancel: Arc<AtomicBool>,
    result: crossbeam_channel::Receiver<Result<Option<BuiltOracle>, AdaptiveError>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Pending {
    /// Flags the build to stop and hands back its thread. Not joined here: that would hold
    /// the render thread until block_oracle returns; the thread sees the flag between reads
    /// and its result goes nowhere.
    fn cancel(mut self) -> Option<std::thread::JoinHandle<()>> {
        self.cancel.store(true, Ordering::Release);
        self.thread.take()
    }
}

/// The adaptive pass of one device and the oracle for its current cut.
#[derive(Default)]
pub struct AdaptiveView {
    pass: Option<AdaptivePass>,
    /// The pass could not be created on this device: never retried on it.
    pass_error: Option<String>,
    /// The oracle set on the pass.
    applied: Option<Arc<BuiltOracle>>,
    pending: Option<Pending>,
    /// The key whose build or render failed, and why (no retry loop for the same key).
    failed: Option<(OracleKey, String)>,
    volume: u64,
    /// Cancelled builds still finishing (joined once done, all of them on drop: no oracle
    /// thread outlives the session).
    abandoned: Vec<std::thread::JoinHandle<()>>,
}

impl Drop for AdaptiveView {
    fn drop(&mut self) {
        self.cancel_pending();
        for thread in self.abandoned.drain(..) {
            let _ = thread.join();
        }
    }
}

impl AdaptiveView {
    pub fn new() -> Self {
        Self::default()
    }

    /// A new streaming volume on the same device: its slots and generations are new, so
    /// nothing built for the old one may be applied (the pass itself only needs the device).
    pub fn new_volume(&mut self) {
        self.volume += 1;
        self.applied = None;
        self.failed = None;
        self.cancel_pending();
    }

    /// The pending build delivered: its thread is returning; joined with the abandoned ones.
    fn finish_pending(&mut self) {
        if let Some(thread) = self.pending.take().and_then(|mut p| p.thread.take()) {
            self.abandoned.push(thread);
        }
        self.join_finished();
    }

    fn cancel_pending(&mut self) {
        if let Some(thread) = self.pending.take().and_then(Pending::cancel) {
            self.abandoned.push(thread);
        }
        self.join_finished();
    }

    /// Joins the builds that are done, without waiting for the others.
    fn join_finished(&mut self) {
        let (done, running): (Vec<_>, Vec<_>) = std::mem::take(&mut self.abandoned)
            .into_iter()
            .partition(|t| t.is_finished());
        self.abandoned = running;
        for thread in done {
            let _ = thread.join();
        }
    }

    pub fn key(
        &self,
        volume: &StreamingVolume,
        view: &StillView,
        settings: &RenderSettings,
    ) -> Option<OracleKey> {
        Some(OracleKey::new(
            self.volume,
            volume.residency_generation(),
            view.transfer_function,
            view.epsilon?,
            settings,
        ))
    }

    /// Cancels a build for another key than `current` (the camera, TF, ε or cut changed).
    pub fn supersede(&mut self, current: Option<&OracleKey>) {
        if self
            .pending
            .as_ref()
            .is_some_and(|p| Some(&p.key) != current)
        {
            self.cancel_pending();
        }
    }

    /// Records a render failure for `key`: its frames stay the raycaster's.
    pub fn note_failure(&mut self, key: OracleKey, reason: String) {
        self.failed = Some((key, reason));
    }

    /// Advances towards the adaptive frame of `view` drawn with the raycaster's final
    /// `settings` over `volume`'s current cut: starts or polls the oracle's build, renders once
    /// it is there. Never waits for the build.
    pub fn step(
        &mut self,
        ctx: &GpuContext,
        volume: &StreamingVolume,
        view: &StillView,
        settings: &RenderSettings,
        raycaster_samples: Option<u64>,
    ) -> Step {
        let Some(key) = self.key(volume, view, settings) else {
            return Step::Failed("adaptive sampling is off".into());
        };
        if let Some((failed, reason)) = &self.failed {
            if *failed == key {
                return Step::Failed(reason.clone());
            }
        }
        if volume.traversal() != Traversal::Flat {
            // The pass reads the flat page table; the octree traversal keeps only its node
            // buffer on the GPU.
            return Step::Failed(
                "adaptive sampling needs the flat page table (the octree traversal is on)".into(),
            );
        }
        if let Err(reason) = self.ensure_pass(ctx, volume) {
            return Step::Failed(reason.to_string());
        }
        if self.applied.as_ref().is_none_or(|a| a.key != key) {
            match self.poll_or_start(volume, &key) {
                Ok(Some(built)) => {
                    if let Some(pass) = self.pass.as_mut() {
                        pass.set_oracle(ctx, &built.distances);
                    }
                    self.applied = Some(built);
                }
                Ok(None) => return Step::Building,
                Err(reason) => {
                    let reason = reason.to_string();
                    self.failed = Some((key, reason.clone()));
                    return Step::Failed(reason);
                }
            }
        }
        let (Some(pass), Some(oracle)) = (self.pass.as_mut(), self.applied.clone()) else {
            return Step::Failed("the adaptive pass is missing".into());
        };
        let scene = volume.scene(view.camera, settings);
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let rendered = pass.render_blocking(ctx, &scene, &AdaptiveConfig::default());
        let validation = resolved_scope(scope);
        match (rendered, validation) {
            (Ok(frame), None) => {
                let facts = AdaptiveFacts {
                    samples_per_level: frame.samples_per_level,
                    samples: frame.total_samples(),
                    raycaster_samples,
                    epsilon: key.epsilon,
                    settings: settings.clone(),
                    oracle,
                };
                Step::Drawn(Box::new((frame, facts)))
            }
            (Err(e), _) => Step::RenderError(
                anyhow::Error::from(e).context("the adaptive pass failed to render"),
            ),
            (Ok(_), Some(error)) => Step::RenderError(anyhow::anyhow!(
                "the adaptive pass failed to render: {error}"
            )),
        }
    }

    /// The oracle for `key`: Ok(Some) when its build finished, Ok(None) while it runs (started
    /// now if none was running for it), Err when it failed.
    fn poll_or_start(
        &mut self,
        volume: &StreamingVolume,
        key: &OracleKey,
    ) -> Result<Option<Arc<BuiltOracle>>, AdaptiveError> {
        self.supersede(Some(key));
        let Some(pending) = self.pending.as_mut() else {
            self.pending = Some(start_build(
                volume.cut_payloads(),
                volume.mapping(),
                key.clone(),
            )?);
            return Ok(None);
        };
        match pending.result.try_recv() {
            Ok(Ok(Some(built))) => {
                self.finish_pending();
                Ok(Some(Arc::new(built)))
            }
            Ok(Ok(None)) => {
                // Cancelled, yet asked for again: build anew.
                self.finish_pending();
                Ok(None)
            }
            Ok(Err(reason)) => {
                self.finish_pending();
                Err(reason)
            }
            Err(crossbeam_channel::TryRecvError::Empty) => Ok(None),
            Err(crossbeam_channel::TryRecvError::Disconnected) => {
                // The thread ended without a result: it panicked. It has finished, so joining
                // does not wait; its message goes to the status line.
                let message = pending
                    .thread
                    .take()
                    .map(|t| match t.join() {
                        Err(panic) => panic_message(panic.as_ref()),
                        Ok(()) => "no result".into(),
                    })
                    .unwrap_or_else(|| "no result".into());
                self.pending = None;
                Err(AdaptiveError::ThreadPanicked(message))
            }
        }
    }

    fn ensure_pass(
        &mut self,
        ctx: &GpuContext,
        volume: &StreamingVolume,
    ) -> Result<(), AdaptiveError> {
        if let Some(reason) = &self.pass_error {
            return Err(AdaptiveError::PassCreation(reason.clone()));
        }
        if self.pass.is_some() {
            return Ok(());
        }
        // Validation errors go to this scope, not to the device watch (which would stop the
        // whole renderer for a pass that is an optional refinement).
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let created = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            AdaptivePass::new(ctx, volume.brick_cache())
        }));
        let validation = resolved_scope(scope);
        match (created, validation) {
            (Ok(pass), None) => {
                self.pass = Some(pass);
                Ok(())
            }
            (Ok(_), Some(error)) => {
                let reason = error.to_string();
                self.pass_error = Some(reason.clone());
                Err(AdaptiveError::PassCreation(reason))
            }
            (Err(panic), _) => {
                let reason = panic_message(panic.as_ref());
                self.pass_error = Some(reason.clone());
                Err(AdaptiveError::PassCreation(reason))
            }
        }
    }
}

/// Starts the oracle's build on [`ORACLE_THREAD`].
fn start_build(
    mut payloads: CutPayloads,
    mapping: ValueMapping,
    key: OracleKey,
) -> Result<Pending, AdaptiveError> {
    let cancel = Arc::new(AtomicBool::new(false));
    let (send, result) = crossbeam_channel::bounded(1);
    let thread_cancel = cancel.clone();
    let thread_key = key.clone();
    let thread = std::thread::Builder::new()
        .name(ORACLE_THREAD.into())
        .spawn(move || {
            let cancelled = || thread_cancel.load(Ordering::Acquire);
            let outcome = match payloads.read_missing(cancelled) {
                Err(e) => Err(AdaptiveError::ReadBrick(e)),
                Ok(false) => Ok(None),
                Ok(true) => {
                    inject_test_fault(thread_key.epsilon);
                    let distances = block_oracle_with(
                        payloads.table(),
                        &payloads,
                        mapping,
                        &thread_key.transfer_function,
                        thread_key.epsilon,
                        AdaptiveConfig::default().l_max,
                        thread_key.quality,
                        thread_key.target,
                    );
                    Ok((!cancelled()).then(|| BuiltOracle {
                        key: thread_key,
                        table: payloads.table().clone(),
                        distances,
                    }))
                }
            };
            // The receiver is gone when the build was superseded: nothing to tell.
            let _ = send.send(outcome);
        })
        .map_err(AdaptiveError::ThreadStart)?;
    Ok(Pending {
        key,
        cancel,
        result,
        thread: Some(thread),
    })
}

/// Test hook: the oracle for [`tests::PANICKING_EPSILON`] panics on its thread.
#[cfg(test)]
fn inject_test_fault(epsilon: f64) {
    if epsilon == tests::PANICKING_EPSILON {
        panic!("injected oracle panic");
    }
}

#[cfg(not(test))]
fn inject_test_fault(_epsilon: f64) {}

/// The error an error scope caught. On native wgpu the scope's future is ready when popped;
/// should one ever be pending, no error is assumed (the device watch still sees real ones).
fn resolved_scope(scope: wgpu::ErrorScopeGuard) -> Option<wgpu::Error> {
    let mut future = std::pin::pin!(scope.pop());
    let mut cx = std::task::Context::from_waker(std::task::Waker::noop());
    match future.as_mut().poll(&mut cx) {
        std::task::Poll::Ready(error) => error,
        std::task::Poll::Pending => None,
    }
}

/// A caught panic's message (a `String` or `&str` payload), for status lines.
pub(crate) fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<String>()
        .cloned()
        .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_else(|| "panic".into())
}

#[cfg(test)]
pub(crate) mod tests {
    /// Test hook: an oracle built for this ε panics on its thread (the fallback is tested
    /// for real, not by faking a result).
    pub const PANICKING_EPSILON: f64 = 0.0123;
}
