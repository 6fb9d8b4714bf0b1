//! A served 4-D store's frames in the page (wasm32 only): which frame the views show, the
//! shared Frames panel and cine clock (strata-viewer-ui's frames, the desktop's), and the
//! frames' stores, opened without waiting.
//!
//! Each frame is a store of its own (`ServedStore::open_frame`: that frame's skeleton and root
//! brick, then its bricks from the frame's routes). The slider, cine or the link (`frame=N`)
//! name a frame; once its store is open, [`PageFrames::tick`] hands it to the page, which
//! swaps the 3D view's streaming volume and the slice and oblique views' bricks for that
//! frame's (their images stay on screen until the new frame's arrive), then reports it shown.
//! A frame not yet open holds cine back rather than being skipped, as on the desktop. The next
//! frame's store is opened ahead (two small requests), and once the shown frame's 3D view has
//! converged, the bricks of its working set are fetched for the next frame too
//! ([`PageFrames::stream_ahead`], web/src/frame_ahead.rs: two requests at once, at most 32 MiB
//! of records, kept for the next frame only), so that frame's views start from them when
//! cine (or the slider) shows it, as the desktop's frame ahead streams the shown frame's
//! requests.
//!
//! The shown frame and the count are published on the canvas (`data-frame="2/3 paused"`), the
//! panel's controls (`data-frame-controls`) and what was fetched ahead
//! (`data-frame-ahead="next=1 asked=5 kept=5 bytes=…; used=12"`, used: records the frames'
//! fetchers took, over the page's life) for the browser test (web/tests/browser/frames.rs).

use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;
use std::sync::Arc;
use std::time::Duration;

use strata_source::{SourceError, VolumeSource};
use strata_types::BrickId;
use strata_viewer_ui::frames::{FramePlayback, FramesPanelRects};

use crate::served_store::ServedStore;

/// Frame stores kept open at once (each holds its skeleton and root brick): the one shown,
/// the one asked for and the one ahead, and frame 0 (which opens the others).
const KEPT_FRAME_STORES: usize = 4;

/// A frame's store being opened: filled by the open's future, taken by the next page frame.
type FrameSlot = Rc<RefCell<Option<Result<ServedStore, SourceError>>>>;

/// The frames of the served store the page streams.
pub struct PageFrames {
    pub playback: FramePlayback,
    /// Frame stores opened, by frame (frame 0 always: the store the page opened).
    opened: HashMap<u32, Arc<ServedStore>>,
    /// The one being opened (one at a time: the page has few connections).
    opening: Option<(u32, FrameSlot)>,
    /// The frame the views are to show, once its store is open.
    target: u32,
    /// The link's frame as last read or written: a change there (undo, the notebook) is
    /// followed.
    linked: u32,
    /// A frame ahead that could not be opened is not asked for again every page frame.
    ahead_failed: Option<u32>,
    /// Records fetched ahead that the fetchers of frames no longer kept open took.
    used_by_closed_frames: u64,
}

impl PageFrames {
    /// The frames of `store` (the store as the page opened it: frame 0), when it has several.
    pub fn for_store(store: &Arc<ServedStore>, now_s: f64) -> Option<Self> {
        let count = store.frame_count();
        if count < 2 {
            return None;
        }
        Some(PageFrames {
            playback: FramePlayback::new(count, now_s),
            opened: HashMap::from([(0, store.clone())]),
            opening: None,
            target: 0,
            linked: 0,
            ahead_failed: None,
            used_by_closed_frames: 0,
        })
    }

    /// Once a page frame: follows the link's frame (`view_frame`) and the panel's or cine's
    /// choice, opens what is needed, and returns the frame to show now with its store, once
    /// that store is open. The caller swaps its views and calls [`PageFrames::shown`].
    pub fn tick(
        &mut self,
        ctx: &egui::Context,
        view_frame: &mut u32,
        now_s: f64,
    ) -> Option<(u32, Arc<ServedStore>)> {
        let count = self.playback.count;
        if *view_frame != self.linked {
            if *view_frame < count {
                self.target = *view_frame;
            } else {
                self.playback.failed(
                    *view_frame,
                    &format!("the link names a frame past the last: the store has {count} frames (numbered from 0)"),
                );
                *view_frame = self.playback.current;
            }
            self.linked = *view_frame;
        }
        let (wanted, repaint_in_s) = self.playback.wanted(now_s);
        if let Some(frame) = wanted {
            self.target = frame;
        }
        if let Some(seconds) = repaint_in_s {
            ctx.request_repaint_after(Duration::from_secs_f64(seconds));
        }
        self.take_opened();
        publish(&self.playback);
        self.publish_ahead();
        if self.target != self.playback.current {
            if let Some(store) = self.opened.get(&self.target) {
                return Some((self.target, store.clone()));
            }
            self.open(self.target, ctx);
        } else {
            let next = self.playback.next_frame();
            if !self.opened.contains_key(&next) && self.ahead_failed != Some(next) {
                self.open(next, ctx);
            }
        }
        None
    }

    /// `frame` is on screen from `now_s`: the link names it, cine counts from here.
    pub fn shown(&mut self, frame: u32, now_s: f64, view_frame: &mut u32) {
        self.playback.shown(frame, now_s);
        *view_frame = frame;
        self.linked = frame;
        self.target = frame;
        self.ahead_failed = None;
        let keep = [0, frame, self.playback.next_frame()];
        if self.opened.len() > KEPT_FRAME_STORES {
            let mut used = 0;
            self.opened.retain(|f, store| {
                let kept = keep.contains(f);
                if !kept {
                    used += store.ahead().counts().used;
                }
                kept
            });
            self.used_by_closed_frames += used;
        }
        publish(&self.playback);
    }

    /// Once a page frame after the shown frame's 3D view has converged on `working_set`: the
    /// next frame's store (when open) fetches those bricks ahead, and every other frame's
    /// records are dropped (the shown frame's loader has taken what it needed of them).
    pub fn stream_ahead(&self, working_set: &[BrickId], ctx: &egui::Context) {
        let next = self.playback.next_frame();
        for (frame, store) in &self.opened {
            if *frame != next {
                store.ahead().clear();
            }
        }
        if next != self.playback.current {
            if let Some(store) = self.opened.get(&next) {
                store.fetch_ahead(working_set, ctx);
            }
        }
        self.publish_ahead();
    }

    /// `data-frame-ahead`, every page frame: the records a shown frame's fetchers take land
    /// while its view loads, long before that view converges (when [`Self::stream_ahead`]
    /// runs again).
    fn publish_ahead(&self) {
        let next = self.playback.next_frame();
        let ahead = self
            .opened
            .get(&next)
            .map(|store| store.ahead().counts())
            .unwrap_or_default();
        let used = self.used_by_closed_frames
            + self
                .opened
                .values()
                .map(|store| store.ahead().counts().used)
                .sum::<u64>();
        crate::canvas_attributes::set(
            "data-frame-ahead",
            &format!(
                "next={next} asked={} kept={} bytes={}; used={used}",
                ahead.asked, ahead.kept, ahead.bytes
            ),
        );
    }

    /// The Frames section of the side panel (the desktop's panel, shared).
    pub fn panel(&mut self, ui: &mut egui::Ui) {
        egui::CollapsingHeader::new("Frames")
            .default_open(true)
            .show(ui, |ui| {
                let rects = strata_viewer_ui::frames::ui(ui, &mut self.playback);
                publish_controls(rects);
            });
    }

    /// Starts opening `frame`'s store unless one is being opened already (it lands first).
    fn open(&mut self, frame: u32, ctx: &egui::Context) {
        if self.opening.is_some() {
            return;
        }
        let Some(first) = self.opened.get(&0).cloned() else {
            return;
        };
        let slot: FrameSlot = Rc::default();
        let (filled, repaint) = (slot.clone(), ctx.clone());
        wasm_bindgen_futures::spawn_local(async move {
            let opened = first.open_frame(frame).await;
            *filled.borrow_mut() = Some(opened);
            repaint.request_repaint();
        });
        self.opening = Some((frame, slot));
    }

    /// Keeps a frame store that arrived; a frame asked for that failed stops cine and says why.
    fn take_opened(&mut self) {
        let Some((frame, slot)) = self.opening.take() else {
            return;
        };
        let Some(result) = slot.borrow_mut().take() else {
            self.opening = Some((frame, slot));
            return;
        };
        match result {
            Ok(store) => {
                self.opened.insert(frame, Arc::new(store));
            }
            Err(e) if frame == self.target => {
                self.playback.failed(frame, &e.to_string());
                self.target = self.playback.current;
            }
            Err(e) => {
                self.playback.error = Some(format!("frame {frame}: {e}"));
                self.ahead_failed = Some(frame);
            }
        }
    }
}

/// `data-frame`: the frame shown, the count, whether cine plays (`2/3 paused`), and why a
/// frame failed, if one did.
fn publish(playback: &FramePlayback) {
    let state = if playback.playing {
        "playing"
    } else {
        "paused"
    };
    let mut text = format!("{}/{} {state}", playback.current, playback.count);
    if let Some(error) = &playback.error {
        text.push_str(&format!("; {error}"));
    }
    crate::canvas_attributes::set("data-frame", &text);
}

/// `data-frame-controls`: the Play button's and the frame slider's rectangles (CSS pixels,
/// `x,y,w,h`), for the browser test to click.
fn publish_controls(rects: FramesPanelRects) {
    let rect_text = |r: egui::Rect| format!("{},{},{},{}", r.min.x, r.min.y, r.width(), r.height());
    let text = format!(
        "play:{};slider:{}",
        rect_text(rects.play),
        rect_text(rects.slider)
    );
    crate::canvas_attributes::set("data-frame-controls", &text);
}
