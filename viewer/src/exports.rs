//! Long exports (the orbit movie, 2×/4× screenshots) as jobs: frames done of the total, an
//! estimate of the time left and Cancel, drawn as the import's progress dialog is. The render
//! thread writes the frames (volume_session.rs) and reports here; the UI reads and cancels.
//!
//! Issue 36: a 36-frame movie took about 18 minutes on lavapipe with no progress and no way to
//! stop it. A cancelled movie removes the frames it wrote and is never encoded, so nothing it
//! leaves looks like a finished movie.
//!
//! Issue 47: a single 2× screenshot with cinematic effects sat at "0 of 1 frames" for over
//! 8 minutes and Cancel waited for the frame. A frame now reports its own stages (bricks for
//! the shot's size, a pipeline compile, each refinement pass) and the render thread checks
//! Cancel between them, so the bar moves within a frame and Cancel ends it after at most one
//! pass or poll.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::sync::lock_ignoring_poison;

/// How an export ended.
#[derive(Clone, Debug, PartialEq)]
pub enum ExportOutcome {
    /// The file (a PNG, the MP4) or the folder of frames written.
    Written(PathBuf),
    /// Stopped by Cancel after `done` of `total` frames; what it had written was removed.
    Cancelled {
        done: u32,
        total: u32,
    },
    Failed(String),
}

/// One export's progress, shared by the UI and the render thread.
#[derive(Debug)]
pub struct ExportProgress {
    pub title: String,
    total: u32,
    done: AtomicU32,
    cancelled: AtomicBool,
    started: Instant,
    /// Files written so far (removed on cancel).
    written: Mutex<Vec<PathBuf>>,
    /// A folder the export created for its frames (removed on cancel when left empty).
    folder: Option<PathBuf>,
    outcome: Mutex<Option<ExportOutcome>>,
    /// How far the frame in progress is, in millionths, and what it is doing.
    within_frame: AtomicU32,
    stage: Mutex<Option<String>>,
}

impl ExportProgress {
    pub fn new(title: impl Into<String>, total: u32, folder: Option<PathBuf>) -> Self {
        ExportProgress {
            title: title.into(),
            total: total.max(1),
            done: AtomicU32::new(0),
            cancelled: AtomicBool::new(false),
            started: Instant::now(),
            written: Mutex::new(Vec::new()),
            folder,
            outcome: Mutex::new(None),
            within_frame: AtomicU32::new(0),
            stage: Mutex::new(None),
        }
    }

    /// The frame in progress is `fraction` done (0..=1), doing `stage` ("refining: pass 3 of
    /// 64"). The bar moves within a frame: one frame can take minutes on a CPU adapter.
    pub fn frame_stage(&self, fraction: f64, stage: impl Into<String>) {
        let millionths = (fraction.clamp(0.0, 1.0) * 1e6).round() as u32;
        self.within_frame.store(millionths, Ordering::Release);
        *lock_ignoring_poison(&self.stage) = Some(stage.into());
    }

    /// What the frame in progress is doing, if it said.
    pub fn stage(&self) -> Option<String> {
        lock_ignoring_poison(&self.stage).clone()
    }

    pub fn cancel(&self) {
        self.cancelled.store(true, Ordering::Release);
    }

    pub fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::Acquire)
    }

    pub fn total(&self) -> u32 {
        self.total
    }

    pub fn done(&self) -> u32 {
        self.done.load(Ordering::Acquire)
    }

    /// A frame (file) is written.
    pub fn frame_written(&self, path: PathBuf) {
        lock_ignoring_poison(&self.written).push(path);
        self.within_frame.store(0, Ordering::Release);
        *lock_ignoring_poison(&self.stage) = None;
        self.done.fetch_add(1, Ordering::AcqRel);
    }

    pub fn finish(&self, outcome: ExportOutcome) {
        let mut slot = lock_ignoring_poison(&self.outcome);
        // The first outcome stands (a cancel is not overwritten by a later failure).
        if slot.is_none() {
            *slot = Some(outcome);
        }
    }

    pub fn outcome(&self) -> Option<ExportOutcome> {
        lock_ignoring_poison(&self.outcome).clone()
    }

    /// Removes what the export wrote (its frames, then its folder if that is left empty) and
    /// records the cancel. Only the export's own files go: the folder is removed with
    /// `remove_dir`, which leaves anything else there alone.
    pub fn finish_cancelled(&self) {
        for path in lock_ignoring_poison(&self.written).drain(..) {
            let _ = std::fs::remove_file(path);
        }
        if let Some(folder) = &self.folder {
            let _ = std::fs::remove_dir(folder);
        }
        self.finish(ExportOutcome::Cancelled {
            done: self.done(),
            total: self.total,
        });
    }

    /// "12 of 36 frames · about 3 min left", with the frame's stage when it said one
    /// ("0 of 1 frames · refining: pass 3 of 64"); no estimate before the first frame.
    pub fn line(&self) -> String {
        let done = self.done();
        let left = estimate_left(self.started.elapsed(), done, self.total);
        let mut line = match left {
            Some(left) => format!(
                "{done} of {} frames · about {} left",
                self.total,
                format_duration(left)
            ),
            None if self.stage().is_some() => format!("{done} of {} frames", self.total),
            None => format!(
                "{done} of {} frames · estimating the time left…",
                self.total
            ),
        };
        if let Some(stage) = self.stage() {
            line.push_str(" · ");
            line.push_str(&stage);
        }
        line
    }

    /// Frames done plus the share of the frame in progress, of the total.
    pub fn fraction(&self) -> f32 {
        let within = f64::from(self.within_frame.load(Ordering::Acquire)) / 1e6;
        ((f64::from(self.done()) + within) / f64::from(self.total)).min(1.0) as f32
    }
}

/// The time left at the mean time per frame so far; None before the first frame is done.
pub fn estimate_left(elapsed: Duration, done: u32, total: u32) -> Option<Duration> {
    if done == 0 {
        return None;
    }
    let per_frame = elapsed.as_secs_f64() / done as f64;
    Some(Duration::from_secs_f64(
        per_frame * total.saturating_sub(done) as f64,
    ))
}

/// "45 s", "3 min", "1 h 05 min".
pub fn format_duration(d: Duration) -> String {
    let s = d.as_secs();
    if s < 90 {
        format!("{s} s")
    } else if s < 3600 {
        format!("{} min", (s + 30) / 60)
    } else {
        format!("{} h {:02} min", s / 3600, (s % 3600) / 60)
    }
}

/// Draws the export's progress window (as the import's progress dialog): what it is, frames
/// done of the total with the time left, and Cancel. Returns true once the user closes it
/// after the export ended.
pub fn progress_window(ctx: &egui::Context, job: &ExportProgress) -> bool {
    let mut dismissed = false;
    egui::Window::new("Export")
        .id(egui::Id::unique("strata export progress"))
        .resizable(false)
        .collapsible(false)
        .default_width(360.0)
        .show(ctx, |ui| {
            ui.label(&job.title);
            match job.outcome() {
                None => {
                    ui.label(job.line());
                    ui.add(egui::ProgressBar::new(job.fraction()).show_percentage());
                    if job.is_cancelled() {
                        ui.label("cancelling…");
                    } else if ui.button("Cancel").clicked() {
                        job.cancel();
                    }
                    // The line's estimate moves with time: one wake a second while it runs.
                    ctx.request_repaint_after(Duration::from_secs(1));
                }
                Some(outcome) => {
                    ui.label(match outcome {
                        ExportOutcome::Written(path) => format!("written to {}", path.display()),
                        ExportOutcome::Cancelled { done, total } => format!(
                            "cancelled after {done} of {total} frames; the frames written were removed"
                        ),
                        ExportOutcome::Failed(e) => format!("failed: {e}"),
                    });
                    dismissed = ui.button("Close").clicked();
                }
            }
        });
    dismissed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_estimate_is_the_mean_frame_time_times_the_frames_left() {
        assert_eq!(estimate_left(Duration::from_secs(10), 0, 36), None);
        // 4 frames in 120 s: 30 s each, 32 left.
        assert_eq!(
            estimate_left(Duration::from_secs(120), 4, 36),
            Some(Duration::from_secs(960))
        );
        assert_eq!(
            estimate_left(Duration::from_secs(5), 36, 36),
            Some(Duration::ZERO)
        );
        assert_eq!(format_duration(Duration::from_secs(960)), "16 min");
        assert_eq!(format_duration(Duration::from_secs(45)), "45 s");
        assert_eq!(format_duration(Duration::from_secs(3900)), "1 h 05 min");
    }

    #[test]
    fn the_bar_moves_within_a_frame_and_a_written_frame_clears_the_stage() {
        let job = ExportProgress::new("2× screenshot", 1, None);
        assert_eq!(job.fraction(), 0.0);
        job.frame_stage(0.25, "refining: pass 16 of 64");
        assert!((job.fraction() - 0.25).abs() < 1e-6, "{}", job.fraction());
        assert_eq!(job.line(), "0 of 1 frames · refining: pass 16 of 64");
        let job = ExportProgress::new("movie", 4, None);
        job.frame_written(PathBuf::from("frame-0000.png"));
        job.frame_stage(0.5, "loading bricks");
        assert!((job.fraction() - 0.375).abs() < 1e-6, "{}", job.fraction());
        job.frame_written(PathBuf::from("frame-0001.png"));
        assert_eq!(job.stage(), None);
        assert!((job.fraction() - 0.5).abs() < 1e-6, "{}", job.fraction());
    }

    #[test]
    fn a_cancelled_export_removes_its_frames_and_folder_and_says_so() {
        let dir = tempfile::tempdir().expect("temp dir");
        let folder = dir.path().join("orbit");
        std::fs::create_dir_all(&folder).expect("folder");
        let job = ExportProgress::new("movie", 4, Some(folder.clone()));
        for i in 0..2 {
            let path = folder.join(format!("frame-{i:04}.png"));
            std::fs::write(&path, b"png").expect("frame");
            job.frame_written(path);
        }
        assert!(
            job.line().starts_with("2 of 4 frames · about"),
            "{}",
            job.line()
        );
        job.cancel();
        job.finish_cancelled();
        assert!(!folder.exists(), "the partial movie's folder stayed");
        assert_eq!(
            job.outcome(),
            Some(ExportOutcome::Cancelled { done: 2, total: 4 })
        );
        // A later failure does not replace the cancel.
        job.finish(ExportOutcome::Failed("late".into()));
        assert_eq!(
            job.outcome(),
            Some(ExportOutcome::Cancelled { done: 2, total: 4 })
        );
    }
}
