//! A 4-D volume's frames in either viewer: which frame is shown, which one the slider or a link
//! asked for, the cine clock (play/pause, 1-30 frames/s, looping) and the Frames panel.
//!
//! The clock is driven by the caller's time in seconds (the desktop's `Instant`, the page's
//! `web_time` clock; a test's own numbers), so it holds no clock of its own and runs the same
//! on wasm32. It only says which frame is wanted; each viewer swaps its readers for that
//! frame's (the desktop: `viewer/src/frames.rs`, the page: `web/src/frames.rs`) and reports
//! back with [`FramePlayback::shown`] once the frame is on screen, so a slow frame holds cine
//! back instead of being skipped. Tested below (`cine_steps_…`) and by both viewers' frame
//! tests (`the_frame_slider_moves_the_readout_to_the_next_frames_value`,
//! `the_page_shows_a_served_4d_stores_frames_and_plays_them`).

use egui::Color32;

/// Cine frame rates offered (frames per second).
pub const FPS_RANGE: std::ops::RangeInclusive<f64> = 1.0..=30.0;
/// The cine rate a volume opens with.
pub const DEFAULT_FPS: f64 = 5.0;
/// The slow-cine line's colour: the desktop's warning amber.
const SLOW_CINE_COLOUR: Color32 = Color32::from_rgb(255, 170, 40);
/// Cine steps whose intervals the rate line averages.
const TIMED_STEPS: usize = 8;

/// The frame state of an open 4-D volume (the Frames panel edits it).
#[derive(Clone, Debug, PartialEq)]
pub struct FramePlayback {
    pub count: u32,
    /// The frame every view shows.
    pub current: u32,
    /// What the slider, a link or a test asked for; taken by [`FramePlayback::wanted`].
    pub requested: Option<u32>,
    pub playing: bool,
    pub fps: f64,
    /// When the current frame was shown (the caller's seconds).
    shown_at_s: f64,
    /// Seconds between the last cine steps shown (newest last), for the rate line.
    step_seconds: Vec<f64>,
    /// Why the last frame asked for is not shown, for the panel.
    pub error: Option<String>,
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

impl FramePlayback {
    /// Frame 0 of `count` shown at `now_s`, paused at the default rate.
    pub fn new(count: u32, now_s: f64) -> Self {
        FramePlayback {
            count: count.max(1),
            current: 0,
            requested: None,
            playing: false,
            fps: DEFAULT_FPS,
            shown_at_s: now_s,
            step_seconds: Vec::new(),
            error: None,
        }
    }

    /// The frame after the current one, looping.
    pub fn next_frame(&self) -> u32 {
        (self.current + 1) % self.count
    }

    /// Seconds between cine steps at the chosen rate (clamped to [`FPS_RANGE`]).
    pub fn step_s(&self) -> f64 {
        1.0 / self.fps.clamp(*FPS_RANGE.start(), *FPS_RANGE.end())
    }

    /// The frame to show now, if it is not the current one: the one asked for, else the next
    /// cine step once its time has come. Also how long until the next cine step (None while
    /// paused), for the caller's repaint.
    pub fn wanted(&mut self, now_s: f64) -> (Option<u32>, Option<f64>) {
        let mut wanted = self.requested.take();
        let mut repaint_in_s = None;
        if self.playing {
            let elapsed = (now_s - self.shown_at_s).max(0.0);
            if wanted.is_none() && elapsed >= self.step_s() {
                wanted = Some(self.next_frame());
            }
            repaint_in_s = Some((self.step_s() - elapsed).max(0.0));
        }
        let wanted = wanted.filter(|&frame| frame != self.current && frame < self.count);
        (wanted, repaint_in_s)
    }

    /// `frame` is on screen from `now_s`: the next cine step counts from here, and a cine step's
    /// interval is timed for the rate line.
    pub fn shown(&mut self, frame: u32, now_s: f64) {
        if self.playing {
            self.step_seconds.push((now_s - self.shown_at_s).max(0.0));
            let excess = self.step_seconds.len().saturating_sub(TIMED_STEPS);
            self.step_seconds.drain(..excess);
        } else {
            self.step_seconds.clear();
        }
        self.current = frame;
        self.shown_at_s = now_s;
        self.error = None;
    }

    /// `frame` could not be shown: cine stops and the panel says why.
    pub fn failed(&mut self, frame: u32, message: &str) {
        self.playing = false;
        self.error = Some(format!("frame {frame}: {message}"));
    }

    /// The Frames panel's line when the cine cannot hold its rate ([`cine_rate_line`]).
    pub fn rate_line(&self) -> Option<String> {
        if !self.playing {
            return None;
        }
        cine_rate_line(self.fps, &self.step_seconds)
    }
}

/// Where the Frames panel put its Play/Pause button and frame slider (the page publishes
/// them for its browser test to click).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FramesPanelRects {
    pub play: egui::Rect,
    pub slider: egui::Rect,
}

/// The Frames panel: Play/Pause, the frame slider, the rate, which frame is shown, and why a
/// frame failed. Both viewers show it for a volume with more than one frame.
pub fn ui(ui: &mut egui::Ui, playback: &mut FramePlayback) -> FramesPanelRects {
    let mut frame = playback.requested.unwrap_or(playback.current);
    let last = playback.count.saturating_sub(1);
    let rects = ui
        .horizontal(|ui| {
            let play = ui
                .button(if playback.playing { "Pause" } else { "Play" })
                .on_hover_text("Cine: step through the frames at the frame rate, looping");
            if play.clicked() {
                playback.playing = !playback.playing;
            }
            let slider = ui
                .add(egui::Slider::new(&mut frame, 0..=last).text("Frame"))
                .on_hover_text("Every view and the readout show this frame");
            if slider.changed() {
                playback.requested = Some(frame);
            }
            FramesPanelRects {
                play: play.rect,
                slider: slider.rect,
            }
        })
        .inner;
    ui.add(
        egui::Slider::new(&mut playback.fps, FPS_RANGE)
            .text("frames/s")
            .logarithmic(true),
    );
    ui.label(format!(
        "frame {} of {} (frames numbered from 0)",
        playback.current, playback.count
    ));
    if let Some(line) = playback.rate_line() {
        ui.colored_label(SLOW_CINE_COLOUR, line);
    }
    if let Some(e) = &playback.error {
        ui.colored_label(Color32::LIGHT_RED, e);
    }
    rects
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn cine_steps_at_its_rate_loops_and_waits_for_the_frame_to_be_shown() {
        let mut playback = FramePlayback::new(3, 10.0);
        // Paused: no step however long it waits, and no repaint asked.
        assert_eq!(playback.wanted(100.0), (None, None));
        playback.playing = true;
        playback.fps = 4.0;
        playback.shown(0, 100.0);
        // Before a quarter second: nothing yet, the repaint due at the step.
        let (wanted, repaint) = playback.wanted(100.1);
        assert_eq!(wanted, None);
        assert!((repaint.expect("playing repaints") - 0.15).abs() < 1e-9);
        // At the step: the next frame; until it is shown, current stays (the caller is slow).
        assert_eq!(playback.wanted(100.25).0, Some(1));
        assert_eq!(playback.current, 0);
        playback.shown(1, 100.3);
        assert_eq!(
            playback.wanted(100.5).0,
            None,
            "the step counts from the showing"
        );
        assert_eq!(playback.wanted(100.56).0, Some(2));
        playback.shown(2, 100.56);
        assert_eq!(playback.wanted(100.9).0, Some(0), "it loops");
        // A request wins over the cine step; the current frame or one past the end is no change.
        playback.requested = Some(1);
        assert_eq!(playback.wanted(100.9).0, Some(1));
        playback.requested = Some(2);
        assert_eq!(playback.wanted(100.6).0, None);
        playback.playing = false;
        playback.requested = Some(3);
        assert_eq!(playback.wanted(200.0).0, None);
        // A failure stops cine and is said.
        playback.playing = true;
        playback.failed(1, "the server answered 404");
        assert!(!playback.playing);
        assert_eq!(
            playback.error.as_deref(),
            Some("frame 1: the server answered 404")
        );
    }

    #[test]
    fn a_slow_cine_is_timed_from_the_frames_shown() {
        let mut playback = FramePlayback::new(4, 0.0);
        playback.playing = true;
        for (n, frame) in [1, 2, 3, 0].into_iter().enumerate() {
            playback.shown(frame, (n + 1) as f64);
        }
        let line = playback
            .rate_line()
            .expect("one frame a second of five asked");
        assert!(line.contains("1.0 frames/s"), "{line}");
        playback.playing = false;
        assert_eq!(playback.rate_line(), None, "paused: nothing said");
    }
}
