//! 4-D stores in the viewer: which frame is shown, cine playback, and the next frame's readers
//! opened ahead.
//!
//! Each frame is a volume source of its own (`VolumeSource::frame_source`), so a frame is shown
//! by swapping the readers every view reads through (the render session, the slice and oblique
//! readers) for that frame's. The next frame's readers are started as soon as a frame is shown
//! and are sent the same render and slice requests as the shown ones, so its bricks stream in
//! and its images are ready before cine reaches it: a second streaming volume, on its own
//! render thread and GPU budget, that is dropped or swapped in when the frame changes.

use std::sync::Arc;
use std::time::{Duration, Instant};

use strata_source::VolumeSource;

use super::oblique::ObliqueReader;
use super::orientation::SliceView;
use super::scene::VolumeData;
use super::slices::SliceReader;
use super::sync::Repaint;
use super::volume_session::VolumeSession;

/// Cine frame rates offered (frames per second).
pub const FPS_RANGE: std::ops::RangeInclusive<f64> = 1.0..=30.0;

/// The readers of one frame.
pub struct FrameReaders {
    pub frame: u32,
    pub session: VolumeSession,
    pub slices: SliceReader,
    pub oblique: ObliqueReader,
}

impl FrameReaders {
    fn start(
        source: &Arc<dyn VolumeSource>,
        frame: u32,
        gpu_budget_bytes: u64,
        repaint: &Repaint,
    ) -> anyhow::Result<Self> {
        let frame_source = source
            .clone()
            .frame_source(frame)
            .ok_or_else(|| anyhow::anyhow!("{} has no frame {frame}", source.location()))?;
        Ok(FrameReaders {
            frame,
            session: VolumeSession::start(frame_source.clone(), gpu_budget_bytes, repaint.clone())?,
            slices: SliceReader::start(frame_source.clone(), repaint.clone())?,
            oblique: ObliqueReader::start(frame_source, repaint.clone())?,
        })
    }
}

/// The frame state of an open 4-D volume (the Frames panel edits it).
pub struct FramePlayer {
    source: Arc<dyn VolumeSource>,
    pub count: u32,
    /// The frame every view shows.
    pub current: u32,
    /// What the slider or a test asked for; applied at the start of the next UI frame.
    pub requested: Option<u32>,
    pub playing: bool,
    pub fps: f64,
    shown_at: Instant,
    ahead: Option<FrameReaders>,
    gpu_budget_bytes: u64,
    repaint: Repaint,
    pub error: Option<String>,
    /// The slice requests last passed to the frame ahead (each is passed once).
    mirrored: [Option<super::slices::SliceRequest>; 3],
    /// Seconds between the last cine steps shown (newest last, at most 8), for the rate line.
    step_seconds: Vec<f64>,
}

/// What the Frames panel says about the cine rate: None while it holds the asked rate (within
/// 20 %) or before 3 steps are timed; otherwise the rate it reaches, so a slow cine says so
/// (issue 36: 5 frames/s asked, about 1 shown, nothing said).
pub fn cine_rate_line(asked_fps: f64, step_seconds: &[f64]) -> Option<String> {
    if step_seconds.len() < 3 {
        return None;
    }
    let mean = step_seconds.iter().sum::<f64>() / step_seconds.len() as f64;
    let reached = 1.0 / mean.max(1e-6);
    (reached < 0.8 * asked_fps).then(|| {
        format!(
            "playing at {reached:.1} frames/s: cannot hold {asked_fps:.0} (each frame is read as it plays)"
        )
    })
}

impl FramePlayer {
    /// The Frames panel's line when the cine cannot hold its rate ([`cine_rate_line`]).
    pub fn rate_line(&self) -> Option<String> {
        if !self.playing {
            return None;
        }
        cine_rate_line(self.fps, &self.step_seconds)
    }

    /// A player for `source` when it has more than one frame; frame 0 is shown (by the readers
    /// the viewer opened on the source itself) and frame 1 is opened ahead.
    pub fn for_source(
        source: Arc<dyn VolumeSource>,
        gpu_budget_bytes: u64,
        repaint: Repaint,
    ) -> Option<Self> {
        let count = source.frame_count();
        if count < 2 {
            return None;
        }
        let mut player = FramePlayer {
            source,
            count,
            current: 0,
            requested: None,
            playing: false,
            fps: 5.0,
            shown_at: Instant::now(),
            ahead: None,
            gpu_budget_bytes,
            repaint,
            error: None,
            mirrored: [None; 3],
            step_seconds: Vec::new(),
        };
        player.open_ahead();
        Some(player)
    }

    fn next_frame(&self) -> u32 {
        (self.current + 1) % self.count
    }

    fn open_ahead(&mut self) {
        let next = self.next_frame();
        if self.ahead.as_ref().is_some_and(|a| a.frame == next) {
            return;
        }
        self.ahead = None;
        self.mirrored = [None; 3];
        match FrameReaders::start(&self.source, next, self.gpu_budget_bytes, &self.repaint) {
            Ok(readers) => self.ahead = Some(readers),
            Err(e) => self.error = Some(format!("frame {next}: {e:#}")),
        }
    }

    /// The frame ahead (tests).
    #[cfg(test)]
    pub fn ahead_frame(&self) -> Option<u32> {
        self.ahead.as_ref().map(|a| a.frame)
    }

    /// Called once per UI frame: applies a requested frame or the next cine step (swapping the
    /// readers in `data`), then passes the shown frame's requests on to the frame ahead.
    /// Returns true when the shown frame changed (the views then drop their cached requests).
    pub fn tick(&mut self, ctx: &egui::Context, data: &mut VolumeData) -> bool {
        let mut wanted = self.requested.take();
        if self.playing {
            let step =
                Duration::from_secs_f64(1.0 / self.fps.clamp(*FPS_RANGE.start(), *FPS_RANGE.end()));
            let elapsed = self.shown_at.elapsed();
            if wanted.is_none() && elapsed >= step {
                wanted = Some(self.next_frame());
            }
            ctx.request_repaint_after(step.saturating_sub(elapsed));
        }
        let changed = match wanted {
            Some(frame) if frame != self.current && frame < self.count => {
                self.show(frame, data);
                true
            }
            _ => false,
        };
        self.mirror_requests(data);
        changed
    }

    fn show(&mut self, frame: u32, data: &mut VolumeData) {
        let readers = match self.ahead.take() {
            Some(a) if a.frame == frame => Ok(a),
            other => {
                drop(other);
                FrameReaders::start(&self.source, frame, self.gpu_budget_bytes, &self.repaint)
            }
        };
        match readers {
            Ok(r) => {
                // The old frame's readers go (their threads stop) when these are replaced.
                data.session = r.session;
                data.slices = r.slices;
                data.oblique = r.oblique;
                self.current = frame;
                if self.playing {
                    self.step_seconds
                        .push(self.shown_at.elapsed().as_secs_f64());
                    let excess = self.step_seconds.len().saturating_sub(8);
                    self.step_seconds.drain(..excess);
                } else {
                    self.step_seconds.clear();
                }
                self.shown_at = Instant::now();
                self.error = None;
                self.open_ahead();
            }
            Err(e) => {
                self.playing = false;
                self.error = Some(format!("frame {frame}: {e:#}"));
            }
        }
    }

    /// The frame ahead streams what the shown frame shows: the same render request and slices.
    fn mirror_requests(&mut self, data: &VolumeData) {
        let Some(ahead) = &self.ahead else { return };
        if let Some(request) = data.session.current_request() {
            if ahead.session.current_request().as_ref() != Some(&request) {
                ahead.session.request(request);
            }
        }
        for view in SliceView::ALL {
            if let Some(image) = data.slices.latest(view) {
                if self.mirrored[view.index()] != Some(image.request) {
                    ahead.slices.request(image.request);
                    self.mirrored[view.index()] = Some(image.request);
                }
            }
        }
    }
}

#[cfg(test)]
mod rate_tests {
    use super::cine_rate_line;

    #[test]
    fn a_cine_that_cannot_hold_its_rate_says_what_it_reaches() {
        // 5 frames/s asked, a step every second: said, with the rate reached.
        let line = cine_rate_line(5.0, &[1.0, 1.0, 1.0]).expect("a slow cine says so");
        assert!(
            line.contains("1.0 frames/s") && line.contains("cannot hold 5"),
            "{line}"
        );
        // Within 20 % of the rate, or too few steps to tell: nothing.
        assert_eq!(cine_rate_line(5.0, &[0.22, 0.21, 0.2]), None);
        assert_eq!(cine_rate_line(5.0, &[1.0, 1.0]), None);
    }
}
