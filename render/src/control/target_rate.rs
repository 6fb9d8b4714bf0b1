//! How a viewer drives the [`TimeCriticalController`] from its "Target frame rate" control
//! (strata-viewer-ui's target_fps): the controller's sampling rate and level of detail while
//! the view moves, full quality once it rests, nothing when the control is off. The desktop
//! viewer's render worker and the browser page use this one type, so both hold the rate the
//! same way.
//!
//! Pure: the caller says whether the view moves and hands over frame times (GPU timestamps,
//! or a measured time where the device has none); no clock is read here, so the policy is
//! tested with synthetic frame times at any cadence.

use crate::control::time_critical::{FrameQuality, TimeCriticalConfig, TimeCriticalController};
use crate::gpu::gpu_timing::FrameTiming;
use crate::model::settings::RenderSettings;

/// What frames look like once the view stops moving.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AtRest {
    /// Still refinement: the rate doubles frame by frame up to the controller's still rate
    /// (the desktop, whose render thread draws those frames while the UI waits for none).
    Refine,
    /// The view's own settings at once: one full-quality frame (the browser page, on one
    /// thread, where a software adapter's frame takes a second: no ramp of frames to draw).
    ViewSettings,
}

#[derive(Clone, Debug)]
pub struct TargetRateDriver {
    controller: TimeCriticalController,
    at_rest: AtRest,
}

impl TargetRateDriver {
    pub fn new(config: TimeCriticalConfig, initial_rate: f64, at_rest: AtRest) -> Self {
        TargetRateDriver {
            controller: TimeCriticalController::new(config, initial_rate),
            at_rest,
        }
    }

    pub fn controller(&self) -> &TimeCriticalController {
        &self.controller
    }

    /// Plans the next frame and sets `settings`' step (and jitter where the rate needs it).
    /// `target_fps` None: the control is off and `settings` stay as they are. `moving`: the
    /// user moves the view. `streaming`: a still view whose cut is still loading, drawn at the
    /// interactive rate so bricks arrive sooner (the desktop's; the page passes false).
    /// None: `settings` are the frame's (control off, or at rest with [`AtRest::ViewSettings`]).
    pub fn plan(
        &mut self,
        target_fps: Option<f64>,
        moving: bool,
        streaming: bool,
        settings: &mut RenderSettings,
    ) -> Option<FrameQuality> {
        let fps = target_fps?;
        if (self.controller.config().controller.target_fps - fps).abs() > 1e-9 {
            self.controller.set_target_fps(fps);
        }
        let interactive = moving || streaming;
        if !interactive && self.at_rest == AtRest::ViewSettings {
            return None;
        }
        let quality = self.controller.plan_frame(interactive);
        quality.apply_to(settings);
        Some(quality)
    }

    /// The loader's quality factor for a frame planned as `quality`: coarser only while the
    /// view moves (lowering it while refining a still view would swap in coarser bricks).
    pub fn lod_factor(quality: Option<FrameQuality>, moving: bool) -> f64 {
        match quality {
            Some(q) if moving => q.lod_factor,
            _ => 1.0,
        }
    }

    /// Remembers what frame `frame_number` was drawn with, for its late GPU timing.
    pub fn submitted(&mut self, frame_number: u64, quality: FrameQuality) {
        self.controller.submitted(frame_number, quality);
    }

    /// Learns from a frame drawn as `quality`: its raycast pass's GPU `timings` (timestamp
    /// queries, a frame or two late) where the device has them, else `measured_ms` (the
    /// frame's measured time, all there is). Still-refinement frames teach nothing.
    pub fn learn(
        &mut self,
        quality: FrameQuality,
        timings: Vec<FrameTiming>,
        timestamps: bool,
        measured_ms: Option<f64>,
    ) {
        if timestamps {
            for timing in timings {
                self.controller.observe(timing);
            }
        } else if let Some(ms) = measured_ms {
            self.controller.observe_ms(ms, quality);
        }
    }

    /// More frames will differ from the last one: still refinement has not reached full
    /// quality (only with [`AtRest::Refine`] and the control on, at rest).
    pub fn refining(&self, target_fps: Option<f64>, moving: bool) -> bool {
        target_fps.is_some()
            && !moving
            && self.at_rest == AtRest::Refine
            && !self.controller.still_refinement_done()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TARGET_FPS: f64 = 20.0;

    fn driver(at_rest: AtRest) -> TargetRateDriver {
        TargetRateDriver::new(TimeCriticalConfig::default(), 1.0, at_rest)
    }

    /// `frames` moving frames, each taking `ms_per_unit_rate` × its rate (cost grows with the
    /// samples per voxel); returns the rate the last one was drawn with.
    fn drag(driver: &mut TargetRateDriver, frames: usize, ms_per_unit_rate: f64) -> f64 {
        let mut last = 0.0;
        for _ in 0..frames {
            let mut settings = RenderSettings::default();
            let q = driver
                .plan(Some(TARGET_FPS), true, false, &mut settings)
                .expect("planned while moving");
            assert_eq!(settings.quality, q.step_factor());
            // No timestamps (as in many browsers): the measured time teaches.
            driver.learn(
                q,
                Vec::new(),
                false,
                Some(q.sampling_rate * ms_per_unit_rate),
            );
            last = q.sampling_rate;
        }
        last
    }

    #[test]
    fn moving_frames_follow_the_target_and_rest_is_full_quality() {
        for at_rest in [AtRest::Refine, AtRest::ViewSettings] {
            // Slow frames (100 ms at one sample per voxel, twice the 50 ms of 20 fps): the
            // rate falls.
            let mut slow = driver(at_rest);
            let fell = drag(&mut slow, 20, 100.0);
            assert!(fell < 0.7, "{at_rest:?}: rate {fell}");
            // Fast frames (3 ms at rate 1, a GPU's cadence): the rate rises.
            let mut fast = driver(at_rest);
            let rose = drag(&mut fast, 20, 3.0);
            assert!(rose > 2.0, "{at_rest:?}: rate {rose}");
            // Timestamps, when the device has them, teach instead of the measured time.
            let mut timed = driver(at_rest);
            for n in 0..20u64 {
                let mut settings = RenderSettings::default();
                let q = timed
                    .plan(Some(TARGET_FPS), true, false, &mut settings)
                    .expect("planned");
                timed.submitted(n, q);
                let timing = FrameTiming {
                    frame_number: n,
                    milliseconds: q.sampling_rate * 100.0,
                    source: crate::gpu::gpu_timing::FrameTimingSource::GpuTimestamps,
                };
                timed.learn(q, vec![timing], true, Some(1.0));
            }
            assert!(timed.controller().sampling_rate_controller().rate() < 0.7);
        }
        // At rest, the page: the view's own settings at once, whatever was learnt.
        let mut page = driver(AtRest::ViewSettings);
        drag(&mut page, 20, 100.0);
        let mut settings = RenderSettings::default();
        assert_eq!(
            page.plan(Some(TARGET_FPS), false, false, &mut settings),
            None
        );
        assert_eq!(settings, RenderSettings::default(), "full quality at rest");
        assert!(!page.refining(Some(TARGET_FPS), false));
        // At rest, the desktop: refinement frames up to the still rate, then done.
        let mut desktop = driver(AtRest::Refine);
        drag(&mut desktop, 20, 100.0);
        let mut rates = Vec::new();
        while desktop.refining(Some(TARGET_FPS), false) && rates.len() < 32 {
            let mut settings = RenderSettings::default();
            let q = desktop
                .plan(Some(TARGET_FPS), false, false, &mut settings)
                .expect("refining");
            assert!(!q.interactive);
            assert_eq!(TargetRateDriver::lod_factor(Some(q), false), 1.0);
            rates.push(q.sampling_rate);
        }
        assert!(rates.windows(2).all(|w| w[0] <= w[1]), "{rates:?}");
        let still = TimeCriticalConfig::default().lod.still_rate;
        assert_eq!(rates.last().copied(), Some(still), "{rates:?}");
        // The control off: settings untouched, moving or not.
        let mut off = driver(AtRest::Refine);
        let mut settings = RenderSettings::default();
        assert_eq!(off.plan(None, true, false, &mut settings), None);
        assert_eq!(settings, RenderSettings::default());
        assert!(!off.refining(None, false));
    }
}
