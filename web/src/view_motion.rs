//! The page's 3D view in motion (issue 39, "the target-fps control"): while the user orbits or
//! zooms, the time-critical controller (strata_render::control::target_rate, the desktop's driver)
//! holds the side panel's target rate; once the view rests, one frame at the view's own full
//! quality replaces the last reduced one.
//!
//! Platform independent and clock-free (the page passes its seconds), so the policy is tested
//! natively at a GPU's cadence with synthetic frame times.

use strata_render::control::target_rate::{AtRest, TargetRateDriver};
use strata_render::control::time_critical::{FrameQuality, TimeCriticalConfig};
use strata_render::{FrameTiming, RenderSettings};

/// How long after the last drag or wheel event the view still counts as moving (seconds):
/// the desktop's 150 ms, so that a pause between two pointer events is not a rest.
pub const MOTION_HOLD_S: f64 = 0.15;

pub struct ViewMotion {
    rate: TargetRateDriver,
    /// The device answers timestamp queries (then they, not frame intervals, teach).
    timestamps: bool,
    moving_until_s: f64,
    /// The frame on screen was drawn at the controller's quality (a full one is due at rest).
    drawn_reduced: bool,
    /// When the previous moving frame was submitted: the interval is its measured time on a
    /// device without timestamp queries.
    last_moving_frame_s: Option<f64>,
    /// Step factor and loader quality factor of the frame on screen (the Performance panel).
    shown: (f64, f64),
}

impl ViewMotion {
    pub fn new(timestamps: bool) -> Self {
        ViewMotion {
            rate: TargetRateDriver::new(TimeCriticalConfig::default(), 1.0, AtRest::ViewSettings),
            timestamps,
            moving_until_s: f64::NEG_INFINITY,
            drawn_reduced: false,
            last_moving_frame_s: None,
            shown: (RenderSettings::default().quality, 1.0),
        }
    }

    /// The user dragged or zoomed the view at `now_s`.
    pub fn moved(&mut self, now_s: f64) {
        self.moving_until_s = now_s + MOTION_HOLD_S;
    }

    pub fn moving(&self, now_s: f64) -> bool {
        now_s < self.moving_until_s
    }

    /// The frame on screen must be drawn again though the view did not change: it was drawn
    /// at the controller's reduced quality and the view now rests (or the control went off).
    pub fn full_quality_due(&self, now_s: f64, target_fps: Option<f64>) -> bool {
        self.drawn_reduced && !(self.moving(now_s) && target_fps.is_some())
    }

    /// Plans the frame about to be drawn: `settings` (the view's own) get the controller's
    /// step while the view moves with the control on. Returns the quality for [`Self::drawn`]
    /// and the loader's quality factor for the frame.
    pub fn plan(
        &mut self,
        now_s: f64,
        target_fps: Option<f64>,
        settings: &mut RenderSettings,
    ) -> (Option<FrameQuality>, f64) {
        let moving = self.moving(now_s);
        let quality = self.rate.plan(target_fps, moving, false, settings);
        let lod_factor = TargetRateDriver::lod_factor(quality, moving);
        self.shown = (settings.quality, lod_factor);
        (quality, lod_factor)
    }

    /// Frame `frame_number`, planned as `quality`, was submitted at `now_s`; `timings` are the
    /// GPU times that arrived with it (of earlier frames).
    pub fn drawn(
        &mut self,
        now_s: f64,
        frame_number: u64,
        quality: Option<FrameQuality>,
        timings: Vec<FrameTiming>,
    ) {
        self.drawn_reduced = quality.is_some();
        let Some(q) = quality else {
            self.last_moving_frame_s = None;
            return;
        };
        self.rate.submitted(frame_number, q);
        let measured_ms = self
            .last_moving_frame_s
            .map(|previous| (now_s - previous) * 1e3);
        self.rate.learn(q, timings, self.timestamps, measured_ms);
        self.last_moving_frame_s = Some(now_s);
    }

    /// No frame was drawn this UI frame (the view did not change): the next interval would
    /// measure the user's pause, not a frame.
    pub fn skipped(&mut self) {
        self.last_moving_frame_s = None;
    }

    /// Step factor and loader quality factor of the frame on screen.
    pub fn shown(&self) -> (f64, f64) {
        self.shown
    }

    /// The controller's current sampling rate (samples per voxel while moving).
    pub fn sampling_rate(&self) -> f64 {
        self.rate.controller().sampling_rate_controller().rate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TARGET: Option<f64> = Some(10.0);

    /// A drag of `frames` frames, each taking `ms_at_rate_one` × its rate (cost grows with the
    /// samples per voxel), drawn back to back from `start_s`; returns the end time.
    fn drag(motion: &mut ViewMotion, start_s: f64, frames: u32, ms_at_rate_one: f64) -> f64 {
        let mut now = start_s;
        for n in 0..frames {
            motion.moved(now);
            let mut settings = RenderSettings::default();
            let (quality, _) = motion.plan(now, TARGET, &mut settings);
            let q = quality.expect("the controller plans moving frames");
            assert_eq!(settings.quality, q.step_factor());
            motion.drawn(now, u64::from(n), quality, Vec::new());
            now += q.sampling_rate * ms_at_rate_one / 1e3;
        }
        now
    }

    #[test]
    fn moving_frames_hold_the_target_and_the_resting_view_is_drawn_at_full_quality() {
        // A GPU's cadence: 3 ms a frame at one sample per voxel, far under 100 ms (10 fps).
        let mut fast = ViewMotion::new(false);
        let end = drag(&mut fast, 0.0, 30, 3.0);
        assert!(fast.sampling_rate() > 2.0, "rate {}", fast.sampling_rate());
        // Slow frames: 250 ms at one sample per voxel; the rate falls under one.
        let mut slow = ViewMotion::new(false);
        drag(&mut slow, 0.0, 30, 250.0);
        assert!(slow.sampling_rate() < 0.6, "rate {}", slow.sampling_rate());
        let (step, _) = slow.shown();
        assert!(step > 1.5, "the frame on screen is coarse: step {step}");

        // At rest (past the hold), the reduced frame is replaced by one at the view's own
        // settings, whatever rate was learnt, and then nothing more is due.
        let rest = end + MOTION_HOLD_S + 0.01;
        assert!(fast.moving(end) && !fast.moving(rest));
        assert!(fast.full_quality_due(rest, TARGET));
        let mut settings = RenderSettings::default();
        let (quality, lod) = fast.plan(rest, TARGET, &mut settings);
        assert_eq!(quality, None);
        assert_eq!(lod, 1.0);
        assert_eq!(settings, RenderSettings::default(), "full quality at rest");
        fast.drawn(rest, 99, quality, Vec::new());
        assert!(!fast.full_quality_due(rest, TARGET));
        assert_eq!(fast.shown(), (RenderSettings::default().quality, 1.0));

        // The control off: moving frames keep the view's settings too.
        let mut off = ViewMotion::new(false);
        off.moved(0.0);
        let mut settings = RenderSettings::default();
        assert_eq!(off.plan(0.01, None, &mut settings).0, None);
        assert_eq!(settings, RenderSettings::default());
        // Turning it off mid-drag draws the view at full quality at once.
        drag(&mut off, 1.0, 3, 3.0);
        assert!(off.full_quality_due(1.0, None));
    }

    #[test]
    fn a_pause_in_the_drag_is_not_measured_as_a_frame() {
        let mut motion = ViewMotion::new(false);
        let end = drag(&mut motion, 0.0, 20, 3.0);
        let rate = motion.sampling_rate();
        // The pointer rests (no frame drawn), then moves again 2 s later.
        motion.skipped();
        let later = end + 2.0;
        motion.moved(later);
        let mut settings = RenderSettings::default();
        let (quality, _) = motion.plan(later, TARGET, &mut settings);
        motion.drawn(later, 100, quality, Vec::new());
        assert_eq!(motion.sampling_rate(), rate, "the 2 s pause taught nothing");
    }
}
