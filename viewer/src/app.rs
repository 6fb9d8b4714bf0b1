//! The viewer's shell: options, preferences, the toolbar, the status bar, the layout of the
//! views and the side bar, keyboard shortcuts. The views (view3d.rs, slice_view.rs) and the
//! panels (panels/) own their state and draw themselves; `StrataApp::ui` draws everything
//! into one `Ui`, so the same code runs in the eframe window and in egui_kittest tests.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use egui::{Color32, Key, Rect, RichText, Sense, Vec2};
use strata_render::{CropBox, RenderMode, TransferFunction};

use super::dialogs::{HelpWindow, OpenDialog};
use super::history::History;
use super::jobs::{PrepareJob, VolumeToOpen};
use super::links::{self, DesktopView};
use super::oblique_view::{ObliqueContext, ObliqueViewer};
use super::orientation::{SliceFrame, SliceView};
use super::overlay::Overlay;
use super::overlay_3d::Overlay3d;
use super::panels::{FrameClock, PanelContext, Panels};
pub use super::preferences::{Layout, Preferences, ViewSlot};
use super::scene::{preset_for, start_cursor, Readout, Scene, VolumeData, Window};
use super::screenshots::{ScreenshotJob, ShotTarget};
use super::segmentation::{journal_path, PendingRecovery, Segmentation};
use super::slice_view::SliceViewer;
use super::slices::SliceReader;
use super::view3d::{OrbitCamera, View3d};
use super::volume_session::{ScreenshotRequest, VolumeSession, DEFAULT_GPU_BUDGET_BYTES};
use super::widgets::{elide_middle, NOT_FOR_DIAGNOSIS, WARNING_COLOUR};
use strata_slices::oblique::{default_extent_mm, ObliquePlane};
use strata_viewer_ui::crop_clip::ClipSettings;
use strata_viewer_ui::layouts;
use strata_viewer_ui::measurements::Measurements;
use strata_viewer_ui::orbit::StandardView;
use strata_viewer_ui::shortcuts;
use strata_viewer_ui::tf_editor::TfEditorState;

/// How the viewer was started (command line, tests).
#[derive(Clone, Debug)]
pub struct ViewerOptions {
    pub source: VolumeToOpen,
    pub dicom_series: Option<String>,
    pub window_size: [f32; 2],
    /// Close the window after this many seconds (smoke tests, measurements).
    pub exit_after_seconds: Option<f64>,
    /// Keep orbiting the 3D view at this many degrees per second, as if dragged (measurements).
    pub auto_orbit_deg_per_second: Option<f64>,
    /// Write UI and volume frame times as CSV here on exit.
    pub frame_log: Option<PathBuf>,
    /// Cap on the 3D render's longer edge in pixels (tests keep images small).
    pub max_render_pixels: u32,
    pub gpu_budget_bytes: u64,
    pub persist_settings: bool,
    /// Where scans are imported to (the user's data folder unless a test says otherwise).
    pub import_folder: PathBuf,
    /// Overrides the remembered layout.
    pub initial_layout: Option<Layout>,
    /// Start the 3D view from this side instead of the default oblique view.
    pub initial_view: Option<StandardView>,
    /// Overrides the remembered transfer-function preset.
    pub initial_preset: Option<String>,
    /// A label map opened over the volume once it is shown (`strata view --overlay`).
    pub overlay: Option<PathBuf>,
}

impl ViewerOptions {
    pub fn new(source: VolumeToOpen) -> Self {
        ViewerOptions {
            source,
            dicom_series: None,
            window_size: [1360.0, 860.0],
            exit_after_seconds: None,
            auto_orbit_deg_per_second: None,
            frame_log: None,
            max_render_pixels: 1024,
            gpu_budget_bytes: DEFAULT_GPU_BUDGET_BYTES,
            persist_settings: true,
            import_folder: super::jobs::data_folder(),
            initial_layout: None,
            initial_view: None,
            initial_preset: None,
            overlay: None,
        }
    }
}

/// Where a view was laid out this frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlacedView {
    pub slot: ViewSlot,
    pub rect: Rect,
}

/// Everything about the volume being viewed: its data, the scene and the views' own state.
pub struct OpenVolume {
    pub data: VolumeData,
    pub scene: Scene,
    pub history: History,
    pub view_3d: View3d,
    pub slice_views: [SliceViewer; 3],
    pub oblique_view: ObliqueViewer,
    pub view_rects: Vec<PlacedView>,
    /// A label map or continuous overlay drawn over the slices (overlay.rs).
    pub overlay: Option<Overlay>,
    /// That overlay resampled for the 3D view (overlay_3d.rs), following `overlay`.
    pub overlay_3d: Option<Overlay3d>,
    /// A 4-D volume's frame slider and cine (frames.rs); `None` for one volume.
    pub frames: Option<super::frames::FramePlayer>,
    /// The editable label layer (segmentation.rs), shown through `overlay`.
    pub segmentation: Option<Segmentation>,
    /// An earlier session's journal with edits over this volume, offered for recovery.
    pub recovery: Option<PendingRecovery>,
    /// The last error starting or recovering a segmentation (the Segment section shows it).
    pub segment_error: Option<String>,
    /// The primary's store (a brush limited to a value range reads it).
    pub store: Arc<dyn strata_source::VolumeSource>,
    /// The label overlay's file being loaded as an editable layer (its labels are read once
    /// through, so on its own thread): the file and the loading thread.
    edit_job: Option<(
        PathBuf,
        std::thread::JoinHandle<Result<strata_segment::LabelLayer, strata_segment::SegmentError>>,
    )>,
}

impl OpenVolume {
    /// Makes `layer` the session's segmentation, journaled to `journal` (`fresh`: a new
    /// journal replacing any earlier one), and shows it as the overlay.
    fn begin_segmentation(
        &mut self,
        ctx: &egui::Context,
        layer: strata_segment::LabelLayer,
        base: Option<PathBuf>,
        journal: &std::path::Path,
        fresh: bool,
    ) {
        let name = base.as_ref().map_or_else(
            || "New segmentation".to_string(),
            |p| p.display().to_string(),
        );
        let seg = Segmentation::start(
            layer,
            base,
            (
                self.data.store_path.as_path(),
                &self.data.info.geometry,
                &self.store,
                self.data.info.mapping,
            ),
            Some(journal),
            fresh,
        );
        let repaint_ctx = ctx.clone();
        match Overlay::start_editable(
            seg.layer.clone(),
            name,
            self.data.info.geometry.clone(),
            self.data.info.header.layout.level_dims.clone(),
            Arc::new(move || repaint_ctx.request_repaint()),
        ) {
            Ok(overlay) => {
                self.overlay = Some(overlay);
                self.segmentation = Some(seg);
                self.recovery = None;
                self.segment_error = None;
            }
            Err(e) => self.segment_error = Some(format!("{e:#}")),
        }
    }

    /// The Segment section's request: a new segmentation, the overlay made editable, or done.
    fn segment_request(
        &mut self,
        ctx: &egui::Context,
        request: super::panels::segment::SegmentRequest,
        data_folder: &std::path::Path,
    ) {
        use super::panels::segment::SegmentRequest;
        let journal = journal_path(data_folder);
        match request {
            SegmentRequest::New => {
                let layer = strata_segment::LabelLayer::new_empty(self.data.info.geometry.clone())
                    .and_then(|mut layer| {
                        layer.segments_mut().add("Segment 1")?;
                        Ok(layer)
                    });
                match layer {
                    Ok(layer) => self.begin_segmentation(ctx, layer, None, &journal, true),
                    Err(e) => self.segment_error = Some(e.to_string()),
                }
            }
            SegmentRequest::EditOverlay => {
                let Some(file) = self.overlay.as_ref().map(|o| PathBuf::from(&o.name)) else {
                    return;
                };
                if self.edit_job.is_some() {
                    return;
                }
                // The label file itself, on its own grid (the overlay's store is a copy made
                // for viewing, with mean coarse levels that labels never use), read through
                // once on a named thread.
                let (thread_file, repaint_ctx) = (file.clone(), ctx.clone());
                let spawned = std::thread::Builder::new()
                    .name("strata-segment-load".into())
                    .spawn(move || {
                        let loaded = strata_segment::io::load_label_file(&thread_file);
                        repaint_ctx.request_repaint();
                        loaded
                    });
                match spawned {
                    Ok(thread) => self.edit_job = Some((file, thread)),
                    Err(e) => self.segment_error = Some(format!("could not start loading: {e}")),
                }
            }
            SegmentRequest::Close => {
                if self.overlay.as_ref().is_some_and(|o| o.layer().is_some()) {
                    self.overlay = None;
                }
                self.segmentation = None;
            }
        }
    }

    /// Once per frame after the views: completed strokes into the history, the segment
    /// table's changes into the journal once no gesture is in progress, the overlay's colours
    /// after the segment list, and the recovery offer.
    fn segment_frame(&mut self, ctx: &egui::Context, gesture: bool, data_folder: &std::path::Path) {
        if self.edit_job.as_ref().is_some_and(|(_, t)| t.is_finished()) {
            if let Some((file, thread)) = self.edit_job.take() {
                match thread.join() {
                    Ok(Ok(mut layer)) => {
                        let added = if layer.segments().is_empty() {
                            layer.segments_mut().add("Segment 1").map(|_| ())
                        } else {
                            Ok(())
                        };
                        match added {
                            Ok(()) => self.begin_segmentation(
                                ctx,
                                layer,
                                Some(file),
                                &journal_path(data_folder),
                                true,
                            ),
                            Err(e) => self.segment_error = Some(e.to_string()),
                        }
                    }
                    Ok(Err(e)) => self.segment_error = Some(e.to_string()),
                    Err(_) => self.segment_error = Some("the loading thread failed".into()),
                }
            }
        }
        if let Some(seg) = self.segmentation.as_mut() {
            seg.poll_grow();
            seg.poll_save();
            seg.poll_statistics();
            for edit in seg.take_completed() {
                self.history.push_label_edit(seg, edit);
            }
            if !gesture {
                seg.journal_segments_if_changed();
            }
            if let Some(o) = self.overlay.as_mut() {
                if o.layer().is_some_and(|l| Arc::ptr_eq(l, &seg.layer)) {
                    o.follow_segments(seg.layer.read().segments());
                }
            }
        }
        let Some(recovery) = &self.recovery else {
            return;
        };
        let mut choice = None;
        egui::Window::new("Recover segmentation")
            .collapsible(false)
            .resizable(false)
            .anchor(egui::Align2::CENTER_CENTER, Vec2::ZERO)
            .show(ctx, |ui| {
                let what = recovery.note.base.as_ref().map_or_else(
                    || "a new segmentation".to_string(),
                    |p| p.display().to_string(),
                );
                ui.label(format!(
                    "The last session left {} unsaved edits to {what}.",
                    recovery.recovery.edits.len()
                ));
                if let Some(dropped) = &recovery.recovery.dropped {
                    ui.colored_label(WARNING_COLOUR, dropped);
                }
                ui.horizontal(|ui| {
                    if ui.button("Recover").clicked() {
                        choice = Some(true);
                    }
                    if ui.button("Discard").clicked() {
                        choice = Some(false);
                    }
                });
            });
        match choice {
            Some(true) => {
                let Some(recovery) = self.recovery.take() else {
                    return;
                };
                match recovery.layer(&self.data.info.geometry) {
                    Ok(layer) => {
                        let base = recovery.note.base.clone();
                        self.begin_segmentation(ctx, layer, base, &recovery.journal, false)
                    }
                    Err(e) => self.segment_error = Some(format!("recovering: {e}")),
                }
            }
            Some(false) => {
                if let Some(recovery) = self.recovery.take() {
                    if let Err(e) = recovery.discard() {
                        self.segment_error = Some(format!(
                            "{}: could not remove: {e}",
                            recovery.journal.display()
                        ));
                    }
                }
            }
            None => {}
        }
    }
}

/// A short message in the status bar, cleared after a few seconds.
struct Toast {
    text: String,
    shown_at: Instant,
}

pub struct StrataApp {
    ctx: egui::Context,
    options: ViewerOptions,
    pub preferences: Preferences,
    job: Option<PrepareJob>,
    job_error: Option<String>,
    pub volume: Option<OpenVolume>,
    pub panels: Panels,
    open_dialog: OpenDialog,
    /// "Open from PACS…" (pacs_dialog.rs).
    pub pacs_dialog: super::pacs_dialog::PacsDialog,
    /// Whether the running (or just failed) job came from the PACS dialog: its errors show there.
    job_from_pacs: bool,
    help: HelpWindow,
    started_at: Instant,
    clock: FrameClock,
    toast: Option<Toast>,
    /// What the views reported under the pointer last frame.
    hover: Option<[f64; 3]>,
    /// The overlay's value there (a slice view's sampled overlay), if any.
    hover_overlay: Option<f32>,
    /// The readout in the status bar this frame (tests read it).
    pub readout: Option<Readout>,
    screenshot: Option<ScreenshotJob>,
    /// The last screenshot's file (or error), shown until dismissed.
    saved_screenshot: Option<Result<PathBuf, String>>,
    /// The running (or just ended) export: orbit movie, 2×/4× screenshot (exports.rs).
    pub export: Option<Arc<super::exports::ExportProgress>>,
    /// A restarted viewer's saved session, put back when its volume opens (session_restore.rs).
    pub pending_restore: Option<super::session_restore::SavedSession>,
    /// The view of the viewer link being opened (links.rs), applied when its store opens.
    pending_link_view: Option<DesktopView>,
}

/// A viewer link (`http://HOST:PORT/#store=NAME&…`, links.rs) as the store's URL and its view;
/// anything else as it is. The error names the link (without its token).
fn resolve_link(source: VolumeToOpen) -> (VolumeToOpen, Option<DesktopView>, Option<String>) {
    let (text, token_file) = match &source {
        VolumeToOpen::Url {
            url, token_file, ..
        } => (url.clone(), token_file.clone()),
        VolumeToOpen::Path(p) => (p.to_string_lossy().into_owned(), None),
        VolumeToOpen::Demo { .. } | VolumeToOpen::Pacs(_) => return (source, None, None),
    };
    if !links::is_link(&text) {
        return (source, None, None);
    }
    match links::parse_link(&text) {
        Ok(link) => (
            VolumeToOpen::Url {
                url: link.store_url,
                token_file,
                token: link.token,
            },
            Some(links::desktop_view(&link.view)),
            None,
        ),
        Err(e) => (
            source_without_link(),
            None,
            Some(format!("cannot open the link: {e}")),
        ),
    }
}

/// What stands in for a link that could not be read (its text may hold a token).
fn source_without_link() -> VolumeToOpen {
    VolumeToOpen::Path(PathBuf::new())
}

fn lock_free_repaint(ctx: &egui::Context) -> super::volume_session::Repaint {
    let ctx = ctx.clone();
    Arc::new(move || ctx.request_repaint())
}

impl StrataApp {
    pub fn new(ctx: egui::Context, preferences: Preferences, mut options: ViewerOptions) -> Self {
        // A viewer link: the store's URL from here on (a link's token must not show in the
        // Open dialog or a job title), its view applied when the store opens.
        let (source, link_view, link_error) = resolve_link(options.source.clone());
        options.source = source;
        let open_path = match &options.source {
            VolumeToOpen::Path(p) => p.display().to_string(),
            VolumeToOpen::Url { url, .. } => url.clone(),
            VolumeToOpen::Demo { .. } | VolumeToOpen::Pacs(_) => preferences
                .last_opened
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_default(),
        };
        let mut app = StrataApp {
            open_dialog: OpenDialog::new(ctx.clone(), open_path),
            pacs_dialog: super::pacs_dialog::PacsDialog::new(None),
            job_from_pacs: false,
            ctx,
            preferences,
            job: None,
            job_error: None,
            volume: None,
            panels: Panels::default(),
            help: HelpWindow::default(),
            started_at: Instant::now(),
            clock: FrameClock::default(),
            toast: None,
            hover: None,
            hover_overlay: None,
            readout: None,
            screenshot: None,
            saved_screenshot: None,
            export: None,
            pending_restore: None,
            pending_link_view: None,
            options,
        };
        if let Some(layout) = app.options.initial_layout {
            app.preferences.layout = layout;
        }
        if let Some(preset) = app.options.initial_preset.clone() {
            app.preferences.preset = preset;
        }
        let source = app.options.source.clone();
        let series = app.options.dicom_series.clone();
        match link_error {
            Some(e) => app.job_error = Some(e),
            None => app.start_resolved_job(source, series, link_view),
        }
        app
    }

    /// Opens `source`: a store, a scan to import, a served store's URL or a viewer link.
    fn start_job(&mut self, source: VolumeToOpen, dicom_series: Option<String>) {
        let (source, link_view, link_error) = resolve_link(source);
        match link_error {
            Some(e) => self.job_error = Some(e),
            None => self.start_resolved_job(source, dicom_series, link_view),
        }
    }

    /// [`Self::start_job`] once a link is resolved: `link_view` is shown when the store opens.
    fn start_resolved_job(
        &mut self,
        source: VolumeToOpen,
        dicom_series: Option<String>,
        link_view: Option<DesktopView>,
    ) {
        self.job_error = None;
        self.job_from_pacs = matches!(source, VolumeToOpen::Pacs(_));
        if let Some(view) = &link_view {
            self.preferences.preset = view.preset.clone();
            self.preferences.mode = view.mode;
            self.preferences.layout = view.layout;
            // The link's light whole (what it does not carry at the defaults): the picture the
            // link names, as the browser draws it (an effect in it turns shading on there too).
            self.preferences.light = view.light;
            self.preferences.shading = view.shading;
            self.preferences.show_oblique = view.oblique.is_some();
            // The link's adaptive sampling (its ε kept where the link turns it off).
            self.preferences.adaptive_sampling = view.adaptive_epsilon.is_some();
            if let Some(epsilon) = view.adaptive_epsilon {
                self.preferences.adaptive_epsilon = epsilon;
            }
        }
        self.pending_link_view = link_view;
        match PrepareJob::start(
            source,
            dicom_series,
            self.options.import_folder.clone(),
            lock_free_repaint(&self.ctx),
        ) {
            Ok(job) => self.job = Some(job),
            Err(e) => self.job_error = Some(format!("could not start: {e:#}")),
        }
    }

    #[cfg(test)]
    pub fn job_error(&self) -> Option<&str> {
        self.job_error.as_deref()
    }

    /// (done, total, stage) of the running preparation, for tests.
    #[cfg(test)]
    pub fn job_progress(&self) -> Option<(u64, u64, String)> {
        self.job.as_ref().map(|j| j.progress())
    }

    #[cfg(test)]
    pub fn last_screenshot(&self) -> Option<Result<PathBuf, String>> {
        self.saved_screenshot
            .clone()
            .or_else(|| self.volume_status().and_then(|s| s.last_screenshot))
    }

    #[cfg(test)]
    /// The newest 3D frame (tests, measurements).
    pub fn volume_frame(&self) -> Option<super::volume_session::RenderedFrame> {
        self.volume
            .as_ref()
            .and_then(|v| v.data.session.latest_frame())
    }

    #[cfg(test)]
    /// The 3D request the UI sent last (tests wait for the frame that answers it).
    pub fn volume_request(&self) -> Option<strata_viewer_ui::render_driver::RenderRequest> {
        self.volume
            .as_ref()
            .and_then(|v| v.data.session.current_request())
    }

    #[cfg(test)]
    /// The mode of the image the 3D view painted last (None: it was left empty).
    pub fn painted_3d_mode(&self) -> Option<RenderMode> {
        self.volume.as_ref().and_then(|v| v.view_3d.painted_mode())
    }

    pub fn volume_status(&self) -> Option<super::volume_session::SessionStatus> {
        self.volume.as_ref().map(|v| v.data.session.status())
    }

    #[cfg(test)]
    pub fn slice_image(&self, view: SliceView) -> Option<super::slices::SliceImage> {
        self.volume
            .as_ref()
            .and_then(|v| v.data.slices.latest(view))
    }

    #[cfg(test)]
    /// The displayed (window-levelled) slice texture's source values and window, for tests.
    pub fn slice_display(&self, view: SliceView) -> Option<super::slice_view::SliceShown> {
        self.volume.as_ref()?.slice_views[view.index()].shown()
    }

    #[cfg(test)]
    pub fn view_rect(&self, slot: ViewSlot) -> Option<Rect> {
        self.volume
            .as_ref()?
            .view_rects
            .iter()
            .find(|p| p.slot == slot)
            .map(|p| p.rect)
    }

    fn poll_job(&mut self) {
        let Some(job) = &self.job else { return };
        let Some(result) = job.take_result() else {
            return;
        };
        self.job = None;
        let failed = match result {
            Ok(store) => match self.open_store(store) {
                // The dialog has done its job.
                Ok(()) => {
                    self.open_dialog.open = false;
                    self.pacs_dialog.open = false;
                    None
                }
                Err(e) => Some(format!("{e:#}")),
            },
            Err(e) => Some(crate::error_report::describe(&e)),
        };
        if let Some(e) = failed {
            // Also on the terminal: `strata view bad.nii` must not fail silently there.
            eprintln!("strata: {e}");
            self.job_error = Some(e);
            // Shown by the dialog it was started from.
            if self.job_from_pacs {
                self.pacs_dialog.open = true;
            } else {
                self.open_dialog.open = true;
            }
        }
    }

    fn open_store(&mut self, store: Arc<dyn strata_source::VolumeSource>) -> anyhow::Result<()> {
        // A local store's folder, or a served store's URL: what "open last" and the
        // remembered measurements are keyed by.
        let location = PathBuf::from(store.location());
        // Drop the old volume first: its threads and GPU memory go before the new ones start.
        self.volume = None;
        let repaint = lock_free_repaint(&self.ctx);
        let session = VolumeSession::start(
            store.clone(),
            self.options.gpu_budget_bytes,
            repaint.clone(),
        )?;
        let slices = SliceReader::start(store.clone(), repaint.clone())?;
        let oblique = super::oblique::ObliqueReader::start(store.clone(), repaint.clone())?;
        let mut frame_player = super::frames::FramePlayer::for_source(
            store.clone(),
            self.options.gpu_budget_bytes,
            repaint,
        );
        let info = session.info().clone();
        let header = &info.header;
        let scan = strata_viewer_ui::presets::ScanValues::of(header);
        let is_ct = scan.is_ct();
        let asked = self.options.initial_preset.is_some() || self.pending_link_view.is_some();
        // A preset that does not fit this scan (a CT preset on an MR, issue 47) is replaced by
        // the one it opens with, unless a link or the command line asked for it.
        if !TransferFunction::PRESETS.contains(&self.preferences.preset.as_str())
            || (!asked && !strata_viewer_ui::presets::keeps_preset(&self.preferences.preset, &scan))
        {
            self.preferences.preset = strata_viewer_ui::presets::initial_preset(&scan).into();
        }
        let transfer_function = preset_for(&self.preferences.preset, &info);
        let window = strata_viewer_ui::window_presets::initial_window(
            strata_viewer_ui::window_presets::header_window(&header.windows),
            is_ct,
            store.histogram(),
        );
        let dims = info.geometry.dims;
        let frames = SliceView::ALL.map(|v| SliceFrame::for_view(v, &info.geometry));
        let (lo, hi) = info.physical_range;
        self.preferences.last_opened = Some(location.clone());
        self.panels.transfer_function.editor = TfEditorState::default();
        let orbit = match self.options.initial_view {
            Some(view) => OrbitCamera::standard(view, self.preferences.orthographic),
            None => OrbitCamera {
                orthographic: self.preferences.orthographic,
                ..OrbitCamera::default()
            },
        };
        let scene = Scene {
            cursor: start_cursor(dims),
            window,
            colour_map: Default::default(),
            tf_source: transfer_function.clone(),
            transfer_function,
            iso_value: if is_ct {
                300.0f64.clamp(lo, hi)
            } else {
                lo + 0.35 * (hi - lo)
            },
            crop: CropBox::default(),
            clip: ClipSettings::default(),
            measurements: Measurements::with_items(
                self.preferences
                    .measurements
                    .get(&location.display().to_string())
                    .cloned()
                    .unwrap_or_default(),
            ),
        };
        let mut scene = scene;
        let mut orbit = orbit;
        let mut oblique_plane = None;
        if let Some(view) = self.pending_link_view.take() {
            orbit = view.orbit;
            // The link's oblique angles (its centre follows the crosshair).
            oblique_plane = view.oblique.map(|angles| {
                ObliquePlane::from_orientation_deg(
                    glam::DVec3::ZERO,
                    default_extent_mm(&info.geometry),
                    angles,
                )
            });
            scene.iso_value = view.iso_value;
            scene.colour_map = view.colour_map;
            // The link's frame is shown from the first UI frame (the player swaps readers).
            if let Some(player) = frame_player.as_mut().filter(|_| view.frame > 0) {
                player.playback.requested = Some(view.frame);
            }
            scene.crop = view.crop;
            scene.clip = view.clip;
            if let Some(tf) = view.tf {
                // Edited from the link's preset (tf_source): the panel shows it as edited.
                scene.transfer_function = tf;
                scene.name_tf_edits();
            }
            if let Some(cursor) = view.cursor {
                scene.cursor = std::array::from_fn(|axis| {
                    cursor[axis].clamp(0.0, (dims[axis] as f64 - 1.0).max(0.0))
                });
            }
            if let Some([centre, width]) = view.window {
                scene.window = Window::new(centre, width);
            }
            // A link's measurements replace the ones remembered for the store: the link shows
            // what its sender measured.
            if !view.measurements.is_empty() {
                scene.measurements = Measurements::with_items(view.measurements);
            }
        }
        if let Some(saved) = self.pending_restore.take() {
            if saved.apply(&location, &mut scene, &mut orbit) {
                saved.apply_view(&mut self.preferences.preset, &mut oblique_plane);
                self.toast = Some(Toast {
                    text: "the session was restored after the viewer restarted".into(),
                    shown_at: Instant::now(),
                });
            }
        }
        let history = History::new(&scene);
        let oblique_view = ObliqueViewer::with_plane(oblique_plane);
        let (recovery, segment_error) =
            match PendingRecovery::find(&self.options.import_folder, &location) {
                Ok(found) => (found, None),
                Err(e) => (None, Some(format!("segmentation journal: {e}"))),
            };
        self.volume = Some(OpenVolume {
            history,
            data: VolumeData {
                histogram: store.histogram().clone(),
                session,
                slices,
                oblique,
                info,
                frames,
                store_path: location,
            },
            scene,
            view_3d: View3d::new(orbit),
            slice_views: SliceView::ALL.map(SliceViewer::new),
            oblique_view,
            view_rects: Vec::new(),
            overlay: None,
            overlay_3d: None,
            frames: frame_player,
            segmentation: None,
            recovery,
            segment_error,
            store,
            edit_job: None,
        });
        Ok(())
    }

    /// The link to the 3D view of the served store on screen (links.rs); None without a volume
    /// or for a volume that is not a served store.
    pub fn share_link(&self) -> Option<String> {
        let v = self.volume.as_ref()?;
        links::link_for(
            &v.data.store_path.to_string_lossy(),
            &DesktopView {
                orbit: v.view_3d.orbit,
                mode: self.preferences.mode,
                preset: self.preferences.preset.clone(),
                tf: self.tf_for_link(),
                iso_value: v.scene.iso_value,
                layout: self.preferences.layout,
                cursor: Some(v.scene.cursor),
                window: Some([v.scene.window.centre, v.scene.window.width]),
                colour_map: v.scene.colour_map,
                crop: v.scene.crop,
                clip: v.scene.clip,
                shading: self.preferences.shading,
                light: self.preferences.light,
                measurements: v.scene.measurements.items.clone(),
                oblique: self.preferences.show_oblique.then(|| {
                    v.oblique_view
                        .current_plane(&v.data, &v.scene)
                        .orientation_deg()
                }),
                frame: v.frames.as_ref().map_or(0, |p| p.playback.current),
                adaptive_epsilon: self
                    .preferences
                    .adaptive_sampling
                    .then_some(self.preferences.adaptive_epsilon),
            },
        )
    }

    /// The 3D view's transfer function for a link when the preset alone would not give it
    /// (edited, or loaded from a file): the link's `tf=`.
    fn tf_for_link(&self) -> Option<TransferFunction> {
        let v = self.volume.as_ref()?;
        let preset = preset_for(&self.preferences.preset, &v.data.info);
        let tf = &v.scene.transfer_function;
        (tf.opacity != preset.opacity || tf.color != preset.color).then(|| tf.clone())
    }

    /// The session as a restarted viewer would put it back; None without a volume.
    pub fn saved_session(&self) -> Option<super::session_restore::SavedSession> {
        let v = self.volume.as_ref()?;
        Some(
            super::session_restore::SavedSession::capture(
                &v.data.store_path,
                &self.preferences,
                &v.scene,
                &v.view_3d.orbit,
            )
            .with_oblique(v.oblique_view.plane.as_ref()),
        )
    }

    /// Everything, into `ui` (eframe's root Ui, or a test harness's).
    pub fn ui(&mut self, ui: &mut egui::Ui) {
        let ui_started = Instant::now();
        self.poll_job();
        if self.volume.is_some() {
            if let Some(path) = self.options.overlay.take() {
                // As the panel's "Open overlay" would: imported first if it is a scan.
                self.panels.overlay.path = path.display().to_string();
                self.panels.overlay.open(
                    ui.ctx(),
                    path,
                    super::overlay::OverlayKind::Labels,
                    &self.options.import_folder,
                );
            }
        }
        if let Some(v) = self.volume.as_mut() {
            // Here, not in the panel: an overlay opens even with the side bar hidden.
            self.panels.overlay.poll(ui.ctx(), &v.data, &mut v.overlay);
            // The 3D grid follows the overlay: started for a new one, dropped with it.
            match &v.overlay {
                Some(o) if !v.overlay_3d.as_ref().is_some_and(|g| g.is_for(o)) => {
                    let ctx = ui.ctx().clone();
                    v.overlay_3d = Overlay3d::start(o, Arc::new(move || ctx.request_repaint()))
                        .map_err(|e| eprintln!("strata: overlay in 3D: {e:#}"))
                        .ok();
                }
                Some(_) => {}
                None => v.overlay_3d = None,
            }
            if let Some(player) = v.frames.as_mut() {
                if player.tick(ui.ctx(), &mut v.data) {
                    // New readers: the views ask them again and take their next images.
                    for view in &mut v.slice_views {
                        view.forget_requests();
                    }
                    v.view_3d.forget_frame();
                }
            }
        }
        self.handle_shortcuts(ui.ctx());
        if let (Some(deg), Some(v)) = (self.options.auto_orbit_deg_per_second, self.volume.as_mut())
        {
            let dt = ui.ctx().input(|i| i.stable_dt).min(0.1) as f64;
            let orbit = &mut v.view_3d.orbit;
            orbit.azimuth_deg = (orbit.azimuth_deg + deg * dt).rem_euclid(360.0);
            v.view_3d.interacting_until = Some(Instant::now() + Duration::from_millis(200));
            ui.ctx().request_repaint();
        }

        egui::Panel::top("toolbar").show(ui, |ui| self.toolbar(ui));
        egui::Panel::bottom("status").show(ui, |ui| self.status_bar(ui));
        if self.preferences.show_side_panel && self.volume.is_some() {
            egui::Panel::right("side")
                .resizable(true)
                .default_size(340.0)
                .min_size(260.0)
                .show(ui, |ui| {
                    // The width is the user's (the resize handle) or the default: text wraps
                    // (or elides, with the full text on hover) inside it rather than widening
                    // the panel, which shrank the views and moved the buttons (issue 36).
                    ui.style_mut().wrap_mode = Some(egui::TextWrapMode::Wrap);
                    egui::ScrollArea::vertical()
                        .auto_shrink([false, true])
                        .show(ui, |ui| self.side_panel(ui));
                });
        }
        egui::CentralPanel::default()
            .frame(egui::Frame::NONE.fill(Color32::BLACK))
            .show(ui, |ui| {
                if self.volume.is_some() {
                    self.views(ui);
                } else {
                    self.waiting_screen(ui);
                }
            });
        if let Some((source, series)) =
            self.open_dialog
                .ui(ui.ctx(), self.job.as_ref(), &mut self.job_error)
        {
            self.start_job(source, series);
        }
        if let Some(source) = self
            .pacs_dialog
            .ui(ui.ctx(), self.job.as_ref(), &mut self.job_error)
        {
            self.start_job(source, None);
        }
        self.help.ui(ui.ctx());

        if let Some(toast) = &self.toast {
            let left = Duration::from_secs(6).saturating_sub(toast.shown_at.elapsed());
            if left.is_zero() {
                self.toast = None;
            } else {
                // One wake when it expires: without it the toast stayed until the next input.
                ui.ctx().request_repaint_after(left);
            }
        }
        self.step_screenshot(ui.ctx());
        if let Some(job) = &self.export {
            if super::exports::progress_window(ui.ctx(), job) {
                self.export = None;
            }
        }
        if let Some((frames, folder)) = self.panels.screenshot.take_orbit_request() {
            self.take_orbit_movie_into(frames, Some(folder));
        }
        if let Some(request) = self.panels.segment_request.take() {
            if let Some(v) = self.volume.as_mut() {
                v.segment_request(ui.ctx(), request, &self.options.import_folder);
            }
        }
        if let Some(v) = self.volume.as_mut() {
            let gesture = ui.ctx().input(|i| i.pointer.any_down());
            v.segment_frame(ui.ctx(), gesture, &self.options.import_folder);
            v.history.observe(&v.scene, gesture);
        }
        self.remember_measurements();
        self.record_frame(ui_started);
        if let Some(limit) = self.options.exit_after_seconds {
            let elapsed = self.started_at.elapsed().as_secs_f64();
            if elapsed >= limit {
                self.write_frame_log();
                ui.ctx().send_viewport_cmd(egui::ViewportCommand::Close);
            } else {
                // One wake at the deadline, not a 10 Hz repaint for the whole run: the run
                // is how the idle CPU is measured (issue 36).
                ui.ctx()
                    .request_repaint_after(Duration::from_secs_f64(limit - elapsed));
            }
        }
    }

    /// Keeps the preferences' copy of this store's measurements current (eframe saves them).
    fn remember_measurements(&mut self) {
        let Some(v) = &self.volume else { return };
        let key = v.data.store_path.display().to_string();
        let items = &v.scene.measurements.items;
        let remembered = self.preferences.measurements.get(&key);
        if remembered.map_or(!items.is_empty(), |r| r != items) {
            if items.is_empty() {
                self.preferences.measurements.remove(&key);
            } else {
                self.preferences.measurements.insert(key, items.clone());
            }
        }
    }

    fn record_frame(&mut self, ui_started: Instant) {
        let volume_frames = self.volume_status().map_or(0, |s| s.frames_rendered);
        self.clock.record(
            self.started_at.elapsed().as_secs_f64(),
            ui_started,
            volume_frames,
            self.options.frame_log.is_some(),
        );
    }

    pub fn write_frame_log(&mut self) {
        let Some(path) = self.options.frame_log.clone() else {
            return;
        };
        if let Err(e) = std::fs::write(&path, self.clock.log_csv()) {
            eprintln!("cannot write the frame log {}: {e}", path.display());
        }
    }

    fn handle_shortcuts(&mut self, ctx: &egui::Context) {
        if ctx.egui_wants_keyboard_input() {
            return;
        }
        // The keys both viewers share (strata_viewer_ui::shortcuts: the help's table).
        let pressed = |k: Key| ctx.input(|i| shortcuts::plain_key(i, k));
        if ctx.input(shortcuts::help_pressed) {
            self.help.open = !self.help.open;
        }
        if ctx.input(|i| i.key_pressed(Key::O) && i.modifiers.command) {
            self.open_dialog.open = true;
        }
        if let Some(layout) = ctx.input(shortcuts::layout_pressed) {
            self.preferences.layout =
                [Layout::Single, Layout::ThreeDOverSlices, Layout::TwoByTwo][layout];
        }
        if pressed(Key::T) {
            self.preferences.target_fps_enabled = !self.preferences.target_fps_enabled;
        }
        if ctx.input(shortcuts::mode_cycle_pressed) {
            self.preferences.mode = shortcuts::next_mode(self.preferences.mode);
        }
        if ctx.input(shortcuts::screenshot_pressed) {
            self.take_screenshot(ShotTarget::View(self.preferences.focused));
        }
        let (undo, redo) = ctx.input(shortcuts::undo_redo_pressed);
        if let Some(v) = self.volume.as_mut() {
            if undo {
                v.history.undo(&mut v.scene, v.segmentation.as_mut());
            }
            if redo {
                v.history.redo(&mut v.scene, v.segmentation.as_mut());
            }
        }
        let orthographic = self.preferences.orthographic;
        if let Some(v) = self.volume.as_mut() {
            for view in StandardView::ALL {
                if pressed(view.key()) {
                    v.view_3d.orbit = OrbitCamera::standard(view, orthographic);
                }
            }
            if ctx.input(shortcuts::reset_view_pressed) {
                v.view_3d.reset(orthographic);
            }
            // Arrow keys / page keys page the focused (or axial) slice.
            let step = ctx.input(|i| {
                (i.key_pressed(Key::ArrowUp) as i32 + i.key_pressed(Key::PageUp) as i32)
                    - (i.key_pressed(Key::ArrowDown) as i32 + i.key_pressed(Key::PageDown) as i32)
            });
            if step != 0 {
                let view = match self.preferences.focused {
                    ViewSlot::Slice(s) => s,
                    ViewSlot::ThreeD | ViewSlot::Oblique => SliceView::Axial,
                };
                v.data.page_slice(&mut v.scene, view, step as f64);
            }
        }
    }

    /// Screenshot of the focused view (F12, the toolbar) or the layout: at 1× the view as seen,
    /// annotations included; at 2×/4× the 3D image alone from the render thread.
    fn take_screenshot(&mut self, target: ShotTarget) {
        let Some(v) = &self.volume else { return };
        let folder = self.preferences.screenshot_folder.clone();
        self.saved_screenshot = None;
        let scale = self.preferences.screenshot_scale.clamp(1, 4);
        if scale == 1 {
            let job = ScreenshotJob::new(target, &folder);
            self.toast = Some(Toast {
                text: format!("Saving screenshot to {}…", job.path.display()),
                shown_at: Instant::now(),
            });
            self.screenshot = Some(job);
            return;
        }
        let Some(rect) = v
            .view_rects
            .iter()
            .find(|p| p.slot == ViewSlot::ThreeD)
            .map(|p| p.rect)
        else {
            self.saved_screenshot = Some(Err("no 3D view is shown to capture at 2×/4×".into()));
            return;
        };
        let size =
            View3d::full_resolution_size(rect, self.ctx.pixels_per_point()).map(|s| s * scale);
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis());
        let path = folder.join(format!("strata-3d-{scale}x-{stamp}.png"));
        if let Err(e) = std::fs::create_dir_all(&folder) {
            self.saved_screenshot = Some(Err(format!(
                "cannot create the folder {}: {e}",
                folder.display()
            )));
            return;
        }
        let job = Arc::new(super::exports::ExportProgress::new(
            format!("{scale}× screenshot of the 3D view to {}", path.display()),
            1,
            None,
        ));
        v.data.session.request_screenshot(ScreenshotRequest {
            path: path.clone(),
            size,
            camera: None,
            then_encode: None,
            job: Some(job.clone()),
        });
        self.export = Some(job);
        self.toast = Some(Toast {
            text: format!("Saving screenshot to {}…", path.display()),
            shown_at: Instant::now(),
        });
    }

    /// An orbit movie of the 3D view: `frames` frames at the view's full resolution, turning
    /// the camera about the superior axis from where it is now, into a new folder beside the
    /// screenshots; orbit.mp4 when ffmpeg is there. The render thread writes them in order.
    #[cfg(test)]
    pub fn take_orbit_movie(&mut self, frames: u32) {
        self.take_orbit_movie_into(frames, None);
    }

    /// The orbit movie into `folder` (the one the panel's save dialog chose), or a new
    /// strata-orbit-<time> folder beside the screenshots.
    pub fn take_orbit_movie_into(&mut self, frames: u32, folder: Option<PathBuf>) {
        let Some(v) = &self.volume else { return };
        let frames = strata_viewer_ui::orbit_movie::orbit_frame_count(frames);
        let Some(rect) = v
            .view_rects
            .iter()
            .find(|p| p.slot == ViewSlot::ThreeD)
            .map(|p| p.rect)
        else {
            self.saved_screenshot = Some(Err("no 3D view is shown to make a movie of".into()));
            return;
        };
        let size = View3d::full_resolution_size(rect, self.ctx.pixels_per_point());
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis());
        let folder = folder.unwrap_or_else(|| {
            self.preferences
                .screenshot_folder
                .join(format!("strata-orbit-{stamp}"))
        });
        if let Err(e) = std::fs::create_dir_all(&folder) {
            self.saved_screenshot = Some(Err(format!(
                "cannot create the folder {}: {e}",
                folder.display()
            )));
            return;
        }
        let geometry = &v.data.info.geometry;
        let start = v.view_3d.orbit;
        let job = Arc::new(super::exports::ExportProgress::new(
            format!("{frames}-frame orbit movie to {}", folder.display()),
            frames,
            Some(folder.clone()),
        ));
        for i in 0..frames {
            let orbit = OrbitCamera {
                azimuth_deg: crate::export::orbit_azimuth(start.azimuth_deg, i, frames),
                ..start
            };
            v.data.session.request_screenshot(ScreenshotRequest {
                path: folder.join(crate::export::orbit_frame_name(i)),
                size,
                camera: Some(orbit.camera(geometry)),
                then_encode: (i + 1 == frames).then(|| folder.clone()),
                job: Some(job.clone()),
            });
        }
        self.export = Some(job);
        self.saved_screenshot = None;
        self.toast = Some(Toast {
            text: format!(
                "Writing a {frames}-frame orbit movie to {}…",
                folder.display()
            ),
            shown_at: Instant::now(),
        });
    }

    /// Moves a running screenshot on: full-resolution 3D frame, window capture, PNG.
    fn step_screenshot(&mut self, ctx: &egui::Context) {
        let (Some(job), Some(v)) = (self.screenshot.as_mut(), self.volume.as_mut()) else {
            return;
        };
        let rect_of = |slot: ViewSlot| v.view_rects.iter().find(|p| p.slot == slot).map(|p| p.rect);
        let (rect, has_3d) = match job.target {
            ShotTarget::View(slot) => (rect_of(slot), slot == ViewSlot::ThreeD),
            ShotTarget::Layout => (
                v.view_rects
                    .iter()
                    .map(|p| p.rect)
                    .reduce(|a, b| a.union(b)),
                v.view_rects.iter().any(|p| p.slot == ViewSlot::ThreeD),
            ),
        };
        let ready = !has_3d || v.view_3d.shows_converged_frame();
        if let Some(outcome) = job.step(ctx, ready, rect) {
            if let Err(e) = &outcome {
                eprintln!("strata: screenshot failed: {e}");
            }
            self.saved_screenshot = Some(outcome.map_err(|e| e.to_string()));
            self.screenshot = None;
            self.toast = None;
        }
        if let Some(v) = self.volume.as_mut() {
            v.view_3d.full_resolution = self
                .screenshot
                .as_ref()
                .is_some_and(|j| j.wants_full_resolution());
        }
    }

    fn toolbar(&mut self, ui: &mut egui::Ui) {
        // The warning takes its place at the right first and the buttons wrap in what is left,
        // so no button can slide under it at any window width (issue 36: "Panels" overlapped
        // it when the row wrapped).
        let warning = egui::WidgetText::from(
            RichText::new(NOT_FOR_DIAGNOSIS)
                .strong()
                .color(WARNING_COLOUR),
        );
        let galley = warning.clone().into_galley(
            ui,
            Some(egui::TextWrapMode::Extend),
            f32::INFINITY,
            egui::TextStyle::Body,
        );
        let warning_width = galley.size().x + 2.0 * ui.spacing().item_spacing.x;
        ui.horizontal_top(|ui| {
            let buttons_width = (ui.available_width() - warning_width).max(0.0);
            ui.allocate_ui_with_layout(
                Vec2::new(buttons_width, 0.0),
                egui::Layout::left_to_right(egui::Align::Center).with_main_wrap(true),
                |ui| {
                    ui.set_max_width(buttons_width);
                    self.toolbar_buttons(ui)
                },
            );
            ui.with_layout(egui::Layout::right_to_left(egui::Align::Min), |ui| {
                ui.label(warning);
            });
        });
    }

    fn toolbar_buttons(&mut self, ui: &mut egui::Ui) {
        {
            ui.strong("Strata");
            if ui
                .button("Open…")
                .on_hover_text("Open a store, or import a scan (Ctrl+O)")
                .clicked()
            {
                self.open_dialog.open = true;
            }
            if ui
                .button("Open from PACS…")
                .on_hover_text("Search a DICOMweb server (PACS) and open a series")
                .clicked()
            {
                self.pacs_dialog.open = true;
            }
            ui.separator();
            ui.label("Layout");
            ui.selectable_value(&mut self.preferences.layout, Layout::Single, "1×1")
                .on_hover_text("One view (1); double-click a view title to focus it");
            ui.selectable_value(
                &mut self.preferences.layout,
                Layout::ThreeDOverSlices,
                "3D + 1×3",
            )
            .on_hover_text("3D over axial, coronal, sagittal (2)");
            ui.selectable_value(&mut self.preferences.layout, Layout::TwoByTwo, "2×2")
                .on_hover_text("Four-up (3)");
            ui.separator();
            for (mode, label) in super::panels::rendering::RENDER_MODES {
                let label = if mode == RenderMode::Isosurface {
                    "Iso"
                } else {
                    label
                };
                ui.selectable_value(&mut self.preferences.mode, mode, label);
            }
            if ui
                .checkbox(&mut self.preferences.shading, "Shading")
                .changed()
                && !self.preferences.shading
            {
                // As in the Rendering panel: the lighting effects would keep the view shaded
                // otherwise.
                self.preferences.light.effects_off();
            }
            ui.separator();
            let orthographic = self.preferences.orthographic;
            if let Some(v) = self.volume.as_mut() {
                for view in StandardView::ALL {
                    if ui
                        .button(view.letter())
                        .on_hover_text(format!("View {} ({})", view.description(), view.letter()))
                        .clicked()
                    {
                        v.view_3d.orbit = OrbitCamera::standard(view, orthographic);
                    }
                }
                if ui
                    .button("Reset")
                    .on_hover_text("Reset the 3D view (Home)")
                    .clicked()
                {
                    v.view_3d.reset(orthographic);
                }
            }
            if let Some(link) = self.share_link() {
                if ui
                    .button("Copy link")
                    .on_hover_text(
                        "Copy a link to this view of the served store: it opens in a browser \
                         (strata serve's web viewer) or in Strata (strata view LINK). The \
                         server's token is not in it.",
                    )
                    .clicked()
                {
                    ui.ctx().copy_text(link);
                    let left_out = self
                        .tf_for_link()
                        .as_ref()
                        .and_then(strata_viewer_ui::compact_tf::unwritable);
                    self.toast = Some(Toast {
                        text: match left_out {
                            // The link then opens the preset (view_state::to_fragment).
                            Some(why) => format!(
                                "link copied with the preset, not the edited transfer \
                                 function ({why})"
                            ),
                            None => "link to this view copied".into(),
                        },
                        shown_at: Instant::now(),
                    });
                }
            }
            ui.separator();
            let busy = self.screenshot.is_some();
            if ui
                .add_enabled(!busy, egui::Button::new("Screenshot"))
                .on_hover_text(
                    "Save the focused view as PNG at full resolution, with its annotations (F12)",
                )
                .clicked()
            {
                self.take_screenshot(ShotTarget::View(self.preferences.focused));
            }
            if ui
                .add_enabled(!busy, egui::Button::new("Layout"))
                .on_hover_text("Save all views as laid out, as PNG")
                .clicked()
            {
                self.take_screenshot(ShotTarget::Layout);
            }
            if let Some(v) = self.volume.as_mut() {
                let (can_undo, can_redo) = (v.history.can_undo(), v.history.can_redo());
                if ui
                    .add_enabled(can_undo, egui::Button::new("Undo"))
                    .on_hover_text("Undo the last TF, window, crop or measurement change (Ctrl+Z)")
                    .clicked()
                {
                    v.history.undo(&mut v.scene, v.segmentation.as_mut());
                }
                if ui
                    .add_enabled(can_redo, egui::Button::new("Redo"))
                    .on_hover_text("Redo (Ctrl+Shift+Z, Ctrl+Y)")
                    .clicked()
                {
                    v.history.redo(&mut v.scene, v.segmentation.as_mut());
                }
            }
            ui.toggle_value(&mut self.preferences.show_oblique, "Oblique")
                .on_hover_text("Show the oblique view: a slice through the crosshair at any angle");
            ui.toggle_value(&mut self.preferences.show_side_panel, "Panels");
            if ui
                .button("?")
                .on_hover_text("Keyboard and mouse (F1)")
                .clicked()
            {
                self.help.open = !self.help.open;
            }
        }
    }

    fn status_bar(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            if let Some(v) = &self.volume {
                let status = v.data.session.status();
                // Under the pointer when it is over a view, else at the crosshair.
                let readout = match self.hover {
                    Some(at) => v.data.readout(at, true),
                    None => v.data.readout(v.scene.cursor, false),
                };
                let overlay_text = match (&v.overlay, self.hover_overlay) {
                    (Some(o), Some(value)) => match o.kind {
                        super::overlay::OverlayKind::Labels => {
                            match o.label_name(value.round() as i64) {
                                Some(name) => format!(" · label {value:.0} {name}"),
                                None => format!(" · label {value:.0}"),
                            }
                        }
                        super::overlay::OverlayKind::Continuous => {
                            format!(" · overlay {value:.4}")
                        }
                    },
                    _ => String::new(),
                };
                ui.label(format!("{}{overlay_text}", readout.text()))
                    .on_hover_text(
                        "Value, voxel index and patient position (mm) under the pointer, or at \
                     the crosshair when the pointer is off the views; the overlay's value",
                    );
                self.readout = Some(readout);
                ui.separator();
                ui.label(format!(
                    "W {:.0} / L {:.0}",
                    v.scene.window.width, v.scene.window.centre
                ));
                ui.separator();
                if let Some(loading) = &status.loading {
                    strata_viewer_ui::widgets::slow_spinner(ui);
                    ui.label(loading);
                } else if status.refining {
                    strata_viewer_ui::widgets::slow_spinner(ui);
                    ui.label(status.refining_line());
                } else if let Some(stats) = status.loader.as_ref().filter(|s| s.converged_at_budget)
                {
                    ui.label(stats.convergence_status());
                } else if status.settled_unconverged {
                    ui.label(status.refining_line()).on_hover_text(
                        "Nothing changed for several frames with no read pending: the view \
                         rests on this image until it moves",
                    );
                }
                if let Some(line) = &status.adaptive {
                    ui.label(line);
                }
                if let Some(line) = status.source_line() {
                    // A remote store that cannot be reached: the view keeps what it has.
                    ui.colored_label(Color32::YELLOW, line);
                }
                if let Some(line) = &status.gpu_recovery {
                    // The GPU failed and the renderer was rebuilt: the session carried on.
                    ui.colored_label(Color32::YELLOW, line);
                }
                if let Some(e) = &status.error {
                    ui.colored_label(Color32::LIGHT_RED, e);
                }
                if let Some(e) = v.data.slices.error() {
                    ui.colored_label(Color32::LIGHT_RED, format!("slices: {e}"));
                }
                if let Some(Err(e)) = &status.last_screenshot {
                    ui.colored_label(Color32::LIGHT_RED, format!("screenshot failed: {e}"));
                }
            }
            if let Some(toast) = &self.toast {
                ui.separator();
                ui.label(&toast.text);
            }
            let mut dismiss = false;
            match &self.saved_screenshot {
                Some(Ok(path)) => {
                    ui.separator();
                    // Elided to leave room for Dismiss and the warning on the right.
                    let warning = ui
                        .painter()
                        .layout_no_wrap(
                            NOT_FOR_DIAGNOSIS.into(),
                            egui::TextStyle::Body.resolve(ui.style()),
                            WARNING_COLOUR,
                        )
                        .size()
                        .x;
                    let char_width = egui::TextStyle::Body.resolve(ui.style()).size * 0.6;
                    let room = ui.available_width() - warning - 90.0;
                    let max_chars = (room / char_width).max(8.0) as usize;
                    let shown = elide_middle(&format!("Saved {}", path.display()), max_chars);
                    ui.label(shown)
                        .on_hover_text(format!("Saved {}", path.display()));
                    dismiss = ui.small_button("Dismiss").clicked();
                }
                Some(Err(e)) => {
                    ui.separator();
                    ui.colored_label(Color32::LIGHT_RED, format!("screenshot failed: {e}"));
                    dismiss = ui.small_button("Dismiss").clicked();
                }
                None => {}
            }
            if dismiss {
                self.saved_screenshot = None;
            }
            ui.with_layout(egui::Layout::right_to_left(egui::Align::Center), |ui| {
                ui.label(RichText::new(NOT_FOR_DIAGNOSIS).color(WARNING_COLOUR));
            });
        });
        if let (Some(v), Some(toast)) = (&self.volume, &mut self.toast) {
            if let Some(Ok(path)) = v.data.session.status().last_screenshot {
                let done = format!("Saved {}", path.display());
                if toast.text != done && toast.text.contains(&*path.display().to_string()) {
                    toast.text = done;
                }
            }
        }
    }

    fn waiting_screen(&mut self, ui: &mut egui::Ui) {
        ui.vertical_centered(|ui| {
            ui.add_space(ui.available_height() * 0.35);
            if let Some(job) = &self.job {
                let (done, total, stage) = job.progress();
                ui.heading(RichText::new(&job.title).color(Color32::WHITE));
                ui.label(RichText::new(stage).color(Color32::LIGHT_GRAY));
                let fraction = if total > 0 {
                    done as f32 / total as f32
                } else {
                    0.0
                };
                ui.add(
                    egui::ProgressBar::new(fraction)
                        .show_percentage()
                        .desired_width(360.0),
                );
                if ui.button("Cancel").clicked() {
                    job.cancel();
                }
            } else if let Some(e) = &self.job_error {
                // The open dialog shows the error when it is open; once is enough.
                if self.open_dialog.open || self.pacs_dialog.open {
                    ui.label(
                        RichText::new("Could not open (see the dialog).").color(Color32::LIGHT_RED),
                    );
                } else {
                    ui.colored_label(Color32::LIGHT_RED, e);
                }
            } else {
                ui.label("Open a store or a scan to begin.");
            }
            ui.add_space(12.0);
            ui.label(RichText::new(NOT_FOR_DIAGNOSIS).color(WARNING_COLOUR));
        });
    }

    fn side_panel(&mut self, ui: &mut egui::Ui) {
        let Some(v) = self.volume.as_mut() else {
            return;
        };
        self.panels.ui(
            ui,
            PanelContext {
                prefs: &mut self.preferences,
                data: &v.data,
                scene: &mut v.scene,
                view_3d: &mut v.view_3d,
                clock: &self.clock,
                overlay: &mut v.overlay,
                frames: &mut v.frames,
                import_folder: &self.options.import_folder,
                segmentation: &mut v.segmentation,
                segment_error: v.segment_error.as_deref(),
            },
        );
    }

    fn views(&mut self, ui: &mut egui::Ui) {
        let area = ui.available_rect_before_wrap();
        let focused = self.preferences.focused;
        let show_oblique = self.preferences.show_oblique;
        let slots: Vec<(ViewSlot, Rect)> = match self.preferences.layout {
            Layout::Single => vec![(focused, area)],
            Layout::ThreeDOverSlices => {
                let mut row: Vec<ViewSlot> = SliceView::ALL.map(ViewSlot::Slice).to_vec();
                if show_oblique {
                    row.push(ViewSlot::Oblique);
                }
                let (top, cells) = layouts::three_d_over_row(area, row.len());
                let mut slots = vec![(ViewSlot::ThreeD, top)];
                slots.extend(row.into_iter().zip(cells));
                slots
            }
            Layout::TwoByTwo => {
                let [top_left, top_right, bottom_left, bottom_right] =
                    layouts::two_by_two_cells(area);
                vec![
                    (ViewSlot::Slice(SliceView::Axial), top_left),
                    (ViewSlot::ThreeD, top_right),
                    (
                        if show_oblique {
                            ViewSlot::Oblique
                        } else {
                            ViewSlot::Slice(SliceView::Sagittal)
                        },
                        bottom_left,
                    ),
                    (ViewSlot::Slice(SliceView::Coronal), bottom_right),
                ]
            }
        };
        ui.allocate_rect(area, Sense::hover());
        let mut focus_request = None;
        let max_pixels = self.options.max_render_pixels;
        let Some(v) = self.volume.as_mut() else {
            return;
        };
        self.hover = None;
        self.hover_overlay = None;
        let overlay_3d = match (&v.overlay, &v.overlay_3d) {
            (Some(o), Some(g)) => g.request(o),
            _ => None,
        };
        // Drawn in 3D only while the oblique view is shown, as the slice views are.
        let oblique_plane = (show_oblique && slots.iter().any(|(s, _)| *s == ViewSlot::Oblique))
            .then(|| v.oblique_view.current_plane(&v.data, &v.scene));
        for (slot, rect) in &slots {
            let response = match slot {
                ViewSlot::ThreeD => v.view_3d.ui(
                    ui,
                    *rect,
                    &v.data,
                    &mut v.scene,
                    &self.preferences,
                    max_pixels,
                    overlay_3d.clone(),
                    oblique_plane,
                    v.segmentation.as_mut(),
                ),
                ViewSlot::Oblique => {
                    let camera = v.view_3d.orbit.camera(&v.data.info.geometry);
                    v.oblique_view.ui(
                        ui,
                        *rect,
                        &v.data,
                        &mut v.scene,
                        ObliqueContext {
                            camera: &camera,
                            overlay: v.overlay.as_ref(),
                            segmentation: v.segmentation.as_mut(),
                        },
                    )
                }
                ViewSlot::Slice(view) => v.slice_views[view.index()].ui(
                    ui,
                    *rect,
                    &v.data,
                    &mut v.scene,
                    v.overlay.as_ref(),
                    v.segmentation.as_mut(),
                ),
            };
            if response.focused {
                self.preferences.focused = *slot;
            }
            if response.toggle_focus {
                focus_request = Some(*slot);
            }
            if let Some(at) = response.hover {
                self.hover = Some(at);
                self.hover_overlay = match (slot, &v.overlay) {
                    (ViewSlot::Slice(view), Some(o)) => {
                        v.data.slices.latest(*view).and_then(|image| {
                            v.slice_views[view.index()].overlay_value_at(o, at, &image)
                        })
                    }
                    _ => None,
                };
            }
        }
        v.view_rects = slots
            .iter()
            .map(|&(slot, rect)| PlacedView { slot, rect })
            .collect();
        if let Some(slot) = focus_request {
            if self.preferences.layout == Layout::Single {
                self.preferences.layout = Layout::ThreeDOverSlices;
            } else {
                self.preferences.layout = Layout::Single;
            }
            self.preferences.focused = slot;
        }
    }
}

/// eframe's side: the app plus persistence.
pub struct EframeApp {
    pub app: StrataApp,
    pub persist: bool,
    /// Writes the session for a restart (None: --fresh without a supervisor).
    pub autosave: Option<super::session_restore::Autosave>,
    /// eframe's own device (the UI's), watched for loss.
    pub ui_device: Option<super::session_restore::UiDeviceWatch>,
}

impl eframe::App for EframeApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        self.app.ui(ui);
        let lost = self.ui_device.as_ref().and_then(|w| w.lost());
        if let Some(autosave) = &mut self.autosave {
            autosave.tick(self.app.saved_session().as_ref(), lost.is_some());
        }
        if let Some(detail) = lost {
            // eframe cannot recreate its device: end this process with the session saved, and
            // the supervising parent starts a new window that restores it (session_restore.rs).
            eprintln!("strata: the window's GPU device was lost ({detail}); the session was saved");
            self.app.write_frame_log();
            std::process::exit(super::session_restore::UI_DEVICE_LOST_EXIT);
        }
    }

    fn save(&mut self, storage: &mut dyn eframe::Storage) {
        if self.persist {
            eframe::set_value(storage, eframe::APP_KEY, &self.app.preferences);
        }
    }

    fn on_exit(&mut self) {
        self.app.write_frame_log();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn preferences_survive_a_round_trip_and_old_files_fill_in_defaults() {
        let mut p = Preferences {
            layout: Layout::TwoByTwo,
            preset: "ct-lung".into(),
            target_fps: 24.0,
            show_identifiers: true,
            adaptive_sampling: true,
            adaptive_epsilon: 0.004,
            progressive_frames: 16,
            ..Preferences::default()
        };
        p.focused = ViewSlot::Slice(SliceView::Sagittal);
        let text = serde_json::to_string(&p).expect("serialise");
        assert_eq!(
            serde_json::from_str::<Preferences>(&text).expect("parse"),
            p
        );
        // A file written by an older version lacks newer fields: they take their defaults.
        let old: Preferences = serde_json::from_str(r#"{"layout":"Single","preset":"mr-default"}"#)
            .expect("parse old");
        assert_eq!(old.layout, Layout::Single);
        assert_eq!(old.preset, "mr-default");
        assert_eq!(old.target_fps, Preferences::default().target_fps);
        assert!(!old.adaptive_sampling, "adaptive sampling is opt-in");
        assert_eq!(
            old.progressive_frames,
            crate::preferences::DEFAULT_PROGRESSIVE_FRAMES
        );
        assert_eq!(
            old.adaptive_epsilon,
            strata_viewer_ui::adaptive::DEFAULT_EPSILON
        );
        assert!(
            !old.show_identifiers,
            "identifiers stay hidden unless the user showed them"
        );
    }
}
