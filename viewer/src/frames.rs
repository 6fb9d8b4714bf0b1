//! 4-D stores in the viewer: which frame is shown, cine playback, and the next frame's readers
//! opened ahead.
//!
//! Each frame is a volume source of its own (`VolumeSource::frame_source`), so a frame is shown
//! by swapping the readers every view reads through (the render session, the slice and oblique
//! readers) for that frame's. The next frame's readers are started as soon as a frame is shown
//! and are sent the same render and slice requests as the shown ones, so its bricks stream in
//! and its images are ready before cine reaches it: a second streaming volume, on its own
//! render thread and GPU budget, that is dropped or swapped in when the frame changes.
//! Which frame is wanted (the slider, a link, the cine clock) is strata-viewer-ui's
//! [`FramePlayback`], which the page shares.

use std::sync::Arc;
use std::time::{Duration, Instant};

use strata_source::VolumeSource;
use strata_viewer_ui::frames::FramePlayback;

use super::oblique::ObliqueReader;
use super::orientation::SliceView;
use super::scene::VolumeData;
use super::slices::SliceReader;
use super::sync::Repaint;
use super::volume_session::VolumeSession;

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

/// The frame state of an open 4-D volume: the shared playback (the Frames panel edits it)
/// and the readers of the frame ahead.
pub struct FramePlayer {
    source: Arc<dyn VolumeSource>,
    pub playback: FramePlayback,
    /// The playback clock's zero (it counts seconds from here).
    clock_zero: Instant,
    ahead: Option<FrameReaders>,
    gpu_budget_bytes: u64,
    repaint: Repaint,
    /// The slice requests last passed to the frame ahead (each is passed once).
    mirrored: [Option<super::slices::SliceRequest>; 3],
}

impl FramePlayer {
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
        let clock_zero = Instant::now();
        let mut player = FramePlayer {
            source,
            playback: FramePlayback::new(count, 0.0),
            clock_zero,
            ahead: None,
            gpu_budget_bytes,
            repaint,
            mirrored: [None; 3],
        };
        player.open_ahead();
        Some(player)
    }

    fn now_s(&self) -> f64 {
        self.clock_zero.elapsed().as_secs_f64()
    }

    fn open_ahead(&mut self) {
        let next = self.playback.next_frame();
        if self.ahead.as_ref().is_some_and(|a| a.frame == next) {
            return;
        }
        self.ahead = None;
        self.mirrored = [None; 3];
        match FrameReaders::start(&self.source, next, self.gpu_budget_bytes, &self.repaint) {
            Ok(readers) => self.ahead = Some(readers),
            Err(e) => self.playback.error = Some(format!("frame {next}: {e:#}")),
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
        let (wanted, repaint_in_s) = self.playback.wanted(self.now_s());
        if let Some(seconds) = repaint_in_s {
            ctx.request_repaint_after(Duration::from_secs_f64(seconds));
        }
        let changed = match wanted {
            Some(frame) => self.show(frame, data),
            None => false,
        };
        self.mirror_requests(data);
        changed
    }

    /// Swaps `data`'s readers for frame `frame`'s (the ahead ones when they are that frame's);
    /// true when it is shown.
    fn show(&mut self, frame: u32, data: &mut VolumeData) -> bool {
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
                let now_s = self.now_s();
                self.playback.shown(frame, now_s);
                self.open_ahead();
                true
            }
            Err(e) => {
                self.playback.failed(frame, &format!("{e:#}"));
                false
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
