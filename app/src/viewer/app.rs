//! The viewer's state and its egui UI. `StrataApp::ui` draws everything into one `Ui`, so the
//! same code runs in the eframe window and in egui_kittest tests.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use egui::{
    Color32, Key, Pos2, Rect, RichText, Sense, Stroke, TextureHandle, TextureOptions, Vec2,
};
use serde::{Deserialize, Serialize};
use strata_render::{ClipPlane, CropBox, RenderMode, RenderSettings, Shading, TransferFunction};
use strata_storage::histogram::Histogram;
use strata_storage::Store;

use super::jobs::{PrepareJob, VolumeSource};
use super::orientation::{SliceFrame, SliceView};
use super::slices::{level_for_pixels, SliceImage, SliceReader, SliceRequest};
use super::sync::lock_ignoring_poison;
use super::tf_editor::{self, TfEditorState};
use super::view3d::{paint_orientation_marker, OrbitCamera, StandardView};
use super::volume_session::{
    RenderRequest, ScreenshotRequest, VolumeInfo, VolumeSession, DEFAULT_GPU_BUDGET_BYTES,
};

const NOT_FOR_DIAGNOSIS: &str = "NOT FOR DIAGNOSTIC USE";
const WARNING_COLOUR: Color32 = Color32::from_rgb(255, 170, 40);

/// How the viewer was started (command line, tests).
#[derive(Clone, Debug)]
pub struct ViewerOptions {
    pub source: VolumeSource,
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
}

impl ViewerOptions {
    pub fn new(source: VolumeSource) -> Self {
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
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Layout {
    /// One view filling the area (the focused one).
    Single,
    /// 3D on top, the three slices in a row below (Slicer's "conventional").
    ThreeDOverSlices,
    /// Axial, 3D / sagittal, coronal (Slicer's "four-up").
    TwoByTwo,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ViewSlot {
    ThreeD,
    Slice(SliceView),
}

/// Remembered between runs (eframe persistence).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Preferences {
    pub layout: Layout,
    pub focused: ViewSlot,
    pub last_opened: Option<PathBuf>,
    pub preset: String,
    pub mode: RenderMode,
    pub shading: bool,
    /// Continuous field where bricks of different resolution meet (off: visible seams).
    pub smooth_transitions: bool,
    pub orthographic: bool,
    pub target_fps_enabled: bool,
    pub target_fps: f64,
    /// Step in finest voxels when the target frame rate is off.
    pub step_voxels: f64,
    /// Fraction of the view's pixels the volume is rendered at.
    pub render_scale: f32,
    pub show_identifiers: bool,
    pub show_side_panel: bool,
    /// Outline the three slice planes in the 3D view.
    pub show_planes_in_3d: bool,
    pub screenshot_folder: PathBuf,
    pub screenshot_scale: u32,
}

impl Default for Preferences {
    fn default() -> Self {
        Preferences {
            layout: Layout::ThreeDOverSlices,
            focused: ViewSlot::ThreeD,
            last_opened: None,
            preset: "ct-bone".into(),
            mode: RenderMode::Dvr,
            shading: true,
            smooth_transitions: true,
            orthographic: false,
            target_fps_enabled: true,
            target_fps: 10.0,
            step_voxels: 0.5,
            render_scale: 0.6,
            show_identifiers: false,
            show_side_panel: true,
            show_planes_in_3d: true,
            screenshot_folder: PathBuf::from("."),
            screenshot_scale: 1,
        }
    }
}

const PRESETS: [(&str, &str); 5] = [
    ("ct-bone", "Bone"),
    ("ct-soft-tissue", "Soft tissue"),
    ("ct-lung", "Lung"),
    ("ct-vessels", "Vessels"),
    ("mr-default", "MR"),
];

/// The stored values behind a slice texture and the window they were shown with.
#[cfg(test)]
pub type SliceShown = (Arc<Vec<u16>>, (f64, f64));

/// A slice texture and what it was made from (so it is rebuilt only when one of them changes).
struct SliceTexture {
    texture: TextureHandle,
    values: Arc<Vec<u16>>,
    window: (f64, f64),
}

/// Everything about the volume being viewed.
pub struct OpenVolume {
    session: VolumeSession,
    slices: SliceReader,
    pub info: VolumeInfo,
    histogram: Histogram,
    pub transfer_function: TransferFunction,
    pub tf_state: TfEditorState,
    pub orbit: OrbitCamera,
    /// Linked crosshair, level-0 continuous index.
    pub cursor: [f64; 3],
    /// Slice window: (centre, width) in physical units.
    pub window: (f64, f64),
    pub iso_value: f64,
    pub crop: CropBox,
    clip_enabled: bool,
    clip_axis: usize,
    clip_flip: bool,
    clip_fraction: f64,
    frames: [SliceFrame; 3],
    volume_texture: Option<(TextureHandle, u64)>,
    slice_textures: [Option<SliceTexture>; 3],
    last_slice_requests: [Option<SliceRequest>; 3],
    interacting_until: Option<Instant>,
    pub view_rects: Vec<(ViewSlot, Rect)>,
    /// Per slice view: magnification over fit-to-view, and pan in points.
    slice_zoom: [f32; 3],
    slice_pan: [Vec2; 3],
}

/// Frame-time history for the performance panel and the frame log.
#[derive(Default)]
struct FrameClock {
    last_frame_at: Option<Instant>,
    /// (seconds since start, interval ms, ui cpu ms, volume frames so far)
    samples: VecDeque<(f64, f64, f64, u64)>,
    log: Vec<(f64, f64, f64, u64)>,
}

pub struct StrataApp {
    ctx: egui::Context,
    options: ViewerOptions,
    pub preferences: Preferences,
    job: Option<PrepareJob>,
    job_error: Option<String>,
    pub volume: Option<OpenVolume>,
    open_dialog: bool,
    open_path: String,
    open_series: String,
    /// A native file dialog running on its own thread: None while open, then what it chose.
    /// Filled by the dialog's thread when it closes; `None` while it is open.
    file_dialog: Option<Arc<std::sync::Mutex<Option<DialogOutcome>>>>,
    file_dialog_note: Option<String>,
    tf_path: String,
    tf_message: Option<String>,
    show_help: bool,
    started_at: Instant,
    clock: FrameClock,
    toast: Option<(String, Instant)>,
}

/// How a closed file dialog ended.
enum DialogOutcome {
    Chosen(PathBuf),
    /// Cancelled, or no desktop portal answered.
    NothingChosen,
}

fn lock_free_repaint(ctx: &egui::Context) -> super::volume_session::Repaint {
    let ctx = ctx.clone();
    Arc::new(move || ctx.request_repaint())
}

impl StrataApp {
    pub fn new(ctx: egui::Context, preferences: Preferences, options: ViewerOptions) -> Self {
        let mut app = StrataApp {
            ctx,
            preferences,
            job: None,
            job_error: None,
            volume: None,
            open_dialog: false,
            open_path: String::new(),
            open_series: String::new(),
            file_dialog: None,
            file_dialog_note: None,
            tf_path: "transfer-function.json".into(),
            tf_message: None,
            show_help: false,
            started_at: Instant::now(),
            clock: FrameClock::default(),
            toast: None,
            options,
        };
        app.open_path = match &app.options.source {
            VolumeSource::Path(p) => p.display().to_string(),
            VolumeSource::Demo { .. } => app
                .preferences
                .last_opened
                .as_ref()
                .map(|p| p.display().to_string())
                .unwrap_or_default(),
        };
        if let Some(layout) = app.options.initial_layout {
            app.preferences.layout = layout;
        }
        if let Some(preset) = app.options.initial_preset.clone() {
            app.preferences.preset = preset;
        }
        let source = app.options.source.clone();
        let series = app.options.dicom_series.clone();
        app.start_job(source, series);
        app
    }

    fn start_job(&mut self, source: VolumeSource, dicom_series: Option<String>) {
        self.job_error = None;
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
        self.volume_status().and_then(|s| s.last_screenshot)
    }

    #[cfg(test)]
    /// The newest 3D frame (tests, measurements).
    pub fn volume_frame(&self) -> Option<super::volume_session::RenderedFrame> {
        self.volume.as_ref().and_then(|v| v.session.latest_frame())
    }

    #[cfg(test)]
    /// The 3D request the UI sent last (tests wait for the frame that answers it).
    pub fn volume_request(&self) -> Option<RenderRequest> {
        self.volume
            .as_ref()
            .and_then(|v| v.session.current_request())
    }

    pub fn volume_status(&self) -> Option<super::volume_session::SessionStatus> {
        self.volume.as_ref().map(|v| v.session.status())
    }

    #[cfg(test)]
    pub fn slice_image(&self, view: SliceView) -> Option<SliceImage> {
        self.volume.as_ref().and_then(|v| v.slices.latest(view))
    }

    #[cfg(test)]
    /// The displayed (window-levelled) slice texture's source values and window, for tests.
    pub fn slice_display(&self, view: SliceView) -> Option<SliceShown> {
        let v = self.volume.as_ref()?;
        v.slice_textures[view.index()]
            .as_ref()
            .map(|t| (t.values.clone(), t.window))
    }

    #[cfg(test)]
    pub fn view_rect(&self, slot: ViewSlot) -> Option<Rect> {
        self.volume
            .as_ref()?
            .view_rects
            .iter()
            .find(|(s, _)| *s == slot)
            .map(|(_, r)| *r)
    }

    fn poll_job(&mut self) {
        let Some(job) = &self.job else { return };
        let Some(result) = job.take_result() else {
            return;
        };
        self.job = None;
        match result {
            Ok(store) => match self.open_store(store) {
                // The dialog has done its job.
                Ok(()) => self.open_dialog = false,
                Err(e) => {
                    self.job_error = Some(format!("{e:#}"));
                    self.open_dialog = true;
                }
            },
            Err(e) => {
                self.job_error = Some(e);
                self.open_dialog = true;
            }
        }
    }

    fn open_store(&mut self, store: Arc<Store>) -> anyhow::Result<()> {
        // Drop the old volume first: its threads and GPU memory go before the new ones start.
        self.volume = None;
        let repaint = lock_free_repaint(&self.ctx);
        let session = VolumeSession::start(
            store.clone(),
            self.options.gpu_budget_bytes,
            repaint.clone(),
        )?;
        let slices = SliceReader::start(store.clone(), repaint)?;
        let info = session.info().clone();
        let header = &info.header;
        let is_ct = header.modality.eq_ignore_ascii_case("CT")
            || header.value_mapping.unit.eq_ignore_ascii_case("HU");
        let asked = self.options.initial_preset.is_some();
        if !PRESETS.iter().any(|(p, _)| *p == self.preferences.preset)
            || (!asked
                && ((!is_ct && self.preferences.preset.starts_with("ct-"))
                    || (is_ct && self.preferences.preset.starts_with("mr"))))
        {
            self.preferences.preset = if is_ct { "ct-bone" } else { "mr-default" }.into();
        }
        let transfer_function = preset_for(&self.preferences.preset, &info);
        let window = header
            .windows
            .first()
            .map(|w| (w.center, w.width.max(1e-6)))
            .unwrap_or_else(|| percentile_window(store.histogram()));
        let dims = info.geometry.dims;
        let frames = SliceView::ALL.map(|v| SliceFrame::for_view(v, &info.geometry));
        let (lo, hi) = info.physical_range;
        self.preferences.last_opened = Some(store.path().to_path_buf());
        self.volume = Some(OpenVolume {
            histogram: store.histogram().clone(),
            session,
            slices,
            transfer_function,
            tf_state: TfEditorState::default(),
            orbit: match self.options.initial_view {
                Some(view) => OrbitCamera::standard(view, self.preferences.orthographic),
                None => OrbitCamera {
                    orthographic: self.preferences.orthographic,
                    ..OrbitCamera::default()
                },
            },
            cursor: dims.map(|d| (d as f64 - 1.0) * 0.5),
            window,
            iso_value: if is_ct {
                300.0f64.clamp(lo, hi)
            } else {
                lo + 0.35 * (hi - lo)
            },
            crop: CropBox::default(),
            clip_enabled: false,
            clip_axis: 1,
            clip_flip: false,
            clip_fraction: 0.5,
            frames,
            volume_texture: None,
            slice_textures: [None, None, None],
            last_slice_requests: [None; 3],
            interacting_until: None,
            view_rects: Vec::new(),
            slice_zoom: [1.0; 3],
            slice_pan: [Vec2::ZERO; 3],
            info,
        });
        Ok(())
    }

    /// Everything, into `ui` (eframe's root Ui, or a test harness's).
    pub fn ui(&mut self, ui: &mut egui::Ui) {
        let ui_started = Instant::now();
        self.poll_job();
        self.handle_shortcuts(ui.ctx());
        if let (Some(deg), Some(v)) = (self.options.auto_orbit_deg_per_second, self.volume.as_mut())
        {
            let dt = ui.ctx().input(|i| i.stable_dt).min(0.1) as f64;
            v.orbit.azimuth_deg = (v.orbit.azimuth_deg + deg * dt).rem_euclid(360.0);
            v.interacting_until = Some(Instant::now() + Duration::from_millis(200));
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
                    egui::ScrollArea::vertical().show(ui, |ui| self.side_panel(ui));
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
        self.open_window(ui.ctx());
        self.help_window(ui.ctx());

        if let Some((_, at)) = &self.toast {
            if at.elapsed() > Duration::from_secs(6) {
                self.toast = None;
            }
        }
        self.record_frame(ui_started);
        if let Some(limit) = self.options.exit_after_seconds {
            if self.started_at.elapsed().as_secs_f64() >= limit {
                self.write_frame_log();
                ui.ctx().send_viewport_cmd(egui::ViewportCommand::Close);
            } else {
                ui.ctx().request_repaint_after(Duration::from_millis(100));
            }
        }
    }

    fn record_frame(&mut self, ui_started: Instant) {
        let now = Instant::now();
        let interval = self
            .clock
            .last_frame_at
            .map_or(0.0, |t| (now - t).as_secs_f64() * 1e3);
        self.clock.last_frame_at = Some(now);
        let cpu = (now - ui_started).as_secs_f64() * 1e3;
        let volume_frames = self.volume_status().map_or(0, |s| s.frames_rendered);
        let sample = (
            self.started_at.elapsed().as_secs_f64(),
            interval,
            cpu,
            volume_frames,
        );
        self.clock.samples.push_back(sample);
        while self.clock.samples.len() > 300 {
            self.clock.samples.pop_front();
        }
        if self.options.frame_log.is_some() {
            self.clock.log.push(sample);
        }
    }

    pub fn write_frame_log(&mut self) {
        let Some(path) = self.options.frame_log.clone() else {
            return;
        };
        let mut text = String::from("seconds,ui_interval_ms,ui_cpu_ms,volume_frames\n");
        for (t, interval, cpu, frames) in &self.clock.log {
            text.push_str(&format!("{t:.4},{interval:.3},{cpu:.3},{frames}\n"));
        }
        if let Err(e) = std::fs::write(&path, text) {
            eprintln!("cannot write the frame log {}: {e}", path.display());
        }
    }

    fn handle_shortcuts(&mut self, ctx: &egui::Context) {
        if ctx.egui_wants_keyboard_input() {
            return;
        }
        let pressed =
            |k: Key| ctx.input(|i| i.key_pressed(k) && !i.modifiers.ctrl && !i.modifiers.command);
        if pressed(Key::F1) || pressed(Key::H) || ctx.input(|i| i.key_pressed(Key::Questionmark)) {
            self.show_help = !self.show_help;
        }
        if ctx.input(|i| i.key_pressed(Key::O) && i.modifiers.command) {
            self.open_dialog = true;
        }
        if pressed(Key::Num1) {
            self.preferences.layout = Layout::Single;
        }
        if pressed(Key::Num2) {
            self.preferences.layout = Layout::ThreeDOverSlices;
        }
        if pressed(Key::Num3) {
            self.preferences.layout = Layout::TwoByTwo;
        }
        if pressed(Key::T) {
            self.preferences.target_fps_enabled = !self.preferences.target_fps_enabled;
        }
        if pressed(Key::M) {
            self.preferences.mode = match self.preferences.mode {
                RenderMode::Dvr => RenderMode::Mip,
                RenderMode::Mip => RenderMode::Isosurface,
                RenderMode::Isosurface => RenderMode::Dvr,
            };
        }
        if pressed(Key::F12) {
            self.take_screenshot();
        }
        let orthographic = self.preferences.orthographic;
        if let Some(v) = self.volume.as_mut() {
            for view in StandardView::ALL {
                if pressed(view.key()) {
                    v.orbit = OrbitCamera::standard(view, orthographic);
                }
            }
            if pressed(Key::Home) || pressed(Key::Num0) {
                v.orbit = OrbitCamera {
                    orthographic,
                    ..OrbitCamera::default()
                };
            }
            // Arrow keys / page keys page the focused (or axial) slice.
            let step = ctx.input(|i| {
                (i.key_pressed(Key::ArrowUp) as i32 + i.key_pressed(Key::PageUp) as i32)
                    - (i.key_pressed(Key::ArrowDown) as i32 + i.key_pressed(Key::PageDown) as i32)
            });
            if step != 0 {
                let view = match self.preferences.focused {
                    ViewSlot::Slice(s) => s,
                    ViewSlot::ThreeD => SliceView::Axial,
                };
                page_slice(v, view, step as f64);
            }
        }
    }

    fn take_screenshot(&mut self) {
        let Some(v) = &self.volume else { return };
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let path = self
            .preferences
            .screenshot_folder
            .join(format!("strata-{stamp}.png"));
        v.session.request_screenshot(ScreenshotRequest {
            path: path.clone(),
            scale: self.preferences.screenshot_scale,
        });
        self.toast = Some((
            format!("Saving screenshot to {}…", path.display()),
            Instant::now(),
        ));
    }

    fn toolbar(&mut self, ui: &mut egui::Ui) {
        ui.horizontal_wrapped(|ui| {
            ui.strong("Strata");
            if ui
                .button("Open…")
                .on_hover_text("Open a store, or import a scan (Ctrl+O)")
                .clicked()
            {
                self.open_dialog = true;
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
            ui.selectable_value(&mut self.preferences.mode, RenderMode::Dvr, "DVR");
            ui.selectable_value(&mut self.preferences.mode, RenderMode::Mip, "MIP");
            ui.selectable_value(&mut self.preferences.mode, RenderMode::Isosurface, "Iso");
            ui.checkbox(&mut self.preferences.shading, "Shading");
            ui.separator();
            let orthographic = self.preferences.orthographic;
            if let Some(v) = self.volume.as_mut() {
                for view in StandardView::ALL {
                    if ui
                        .button(view.letter())
                        .on_hover_text(format!("View {} ({})", view.description(), view.letter()))
                        .clicked()
                    {
                        v.orbit = OrbitCamera::standard(view, orthographic);
                    }
                }
                if ui
                    .button("Reset")
                    .on_hover_text("Reset the 3D view (Home)")
                    .clicked()
                {
                    v.orbit = OrbitCamera {
                        orthographic,
                        ..OrbitCamera::default()
                    };
                }
            }
            ui.separator();
            if ui
                .button("Screenshot")
                .on_hover_text("Save the 3D view as PNG (F12)")
                .clicked()
            {
                self.take_screenshot();
            }
            ui.toggle_value(&mut self.preferences.show_side_panel, "Panels");
            if ui
                .button("?")
                .on_hover_text("Keyboard and mouse (F1)")
                .clicked()
            {
                self.show_help = !self.show_help;
            }
            ui.with_layout(egui::Layout::right_to_left(egui::Align::Center), |ui| {
                ui.label(
                    RichText::new(NOT_FOR_DIAGNOSIS)
                        .strong()
                        .color(WARNING_COLOUR),
                );
            });
        });
    }

    fn status_bar(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            if let Some(v) = &self.volume {
                let status = v.session.status();
                let p = v
                    .info
                    .geometry
                    .patient_from_index(glam::DVec3::from(v.cursor));
                // LPS → the signed R/L, A/P, S/I a radiologist reads.
                let side = |value: f64, pos: &str, neg: &str| {
                    format!("{}{:.1}", if value >= 0.0 { pos } else { neg }, value.abs())
                };
                ui.label(format!(
                    "Cursor {} {} {} mm  ·  voxel ({:.0}, {:.0}, {:.0})",
                    side(p.x, "L", "R"),
                    side(p.y, "P", "A"),
                    side(p.z, "S", "I"),
                    v.cursor[0],
                    v.cursor[1],
                    v.cursor[2]
                ));
                ui.separator();
                ui.label(format!("W {:.0} / L {:.0}", v.window.1, v.window.0));
                ui.separator();
                if let Some(loading) = &status.loading {
                    ui.spinner();
                    ui.label(loading);
                } else if status.refining {
                    ui.spinner();
                    ui.label("refining…");
                }
                if let Some(e) = &status.error {
                    ui.colored_label(Color32::LIGHT_RED, e);
                }
                if let Some(e) = v.slices.error() {
                    ui.colored_label(Color32::LIGHT_RED, format!("slices: {e}"));
                }
                if let Some(Err(e)) = &status.last_screenshot {
                    ui.colored_label(Color32::LIGHT_RED, format!("screenshot failed: {e}"));
                }
            }
            if let Some((text, _)) = &self.toast {
                ui.separator();
                ui.label(text);
            }
            ui.with_layout(egui::Layout::right_to_left(egui::Align::Center), |ui| {
                ui.label(RichText::new(NOT_FOR_DIAGNOSIS).color(WARNING_COLOUR));
            });
        });
        if let (Some(v), Some((text, _))) = (&self.volume, &mut self.toast) {
            if let Some(Ok(path)) = v.session.status().last_screenshot {
                let done = format!("Saved {}", path.display());
                if *text != done && text.contains(&*path.display().to_string()) {
                    *text = done;
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
                ui.colored_label(Color32::LIGHT_RED, e);
            } else {
                ui.label("Open a store or a scan to begin.");
            }
            ui.add_space(12.0);
            ui.label(RichText::new(NOT_FOR_DIAGNOSIS).color(WARNING_COLOUR));
        });
    }

    fn open_window(&mut self, ctx: &egui::Context) {
        if !self.open_dialog {
            return;
        }
        let mut open = true;
        let mut start: Option<VolumeSource> = None;
        egui::Window::new("Open or import").open(&mut open).resizable(false).default_width(460.0).show(ctx, |ui| {
            ui.label("A Strata store, or a scan to import: DICOM folder or file, NIfTI (.nii, .nii.gz), NRRD, MetaImage (.mha/.mhd).");
            ui.label("Scans are imported once into your data folder; the next open is instant.");
            ui.horizontal(|ui| {
                ui.label("Path");
                ui.add(egui::TextEdit::singleline(&mut self.open_path).desired_width(340.0).hint_text("/path/to/scan.nii.gz"));
            });
            ui.horizontal(|ui| {
                let idle = self.file_dialog.is_none();
                if ui.add_enabled(idle, egui::Button::new("Choose file…")).clicked() {
                    self.start_file_dialog(false);
                }
                if ui.add_enabled(idle, egui::Button::new("Choose folder…")).on_hover_text("A DICOM series folder, or a store").clicked() {
                    self.start_file_dialog(true);
                }
                if !idle {
                    ui.spinner();
                }
            });
            self.poll_file_dialog();
            if let Some(note) = &self.file_dialog_note {
                ui.weak(note);
            }
            ui.horizontal(|ui| {
                ui.label("DICOM series (optional)");
                ui.add(egui::TextEdit::singleline(&mut self.open_series).desired_width(200.0).hint_text("index or UID"));
            });
            ui.horizontal(|ui| {
                let busy = self.job.is_some();
                if ui.add_enabled(!busy && !self.open_path.trim().is_empty(), egui::Button::new("Open / import")).clicked() {
                    start = Some(VolumeSource::Path(PathBuf::from(self.open_path.trim())));
                }
                if ui.add_enabled(!busy, egui::Button::new("Demo phantom")).clicked() {
                    start = Some(super::demo_source());
                }
            });
            if let Some(job) = &self.job {
                ui.separator();
                let (done, total, stage) = job.progress();
                ui.label(&job.title);
                ui.label(stage);
                let fraction = if total > 0 { done as f32 / total as f32 } else { 0.0 };
                ui.add(egui::ProgressBar::new(fraction).show_percentage());
                if ui.button("Cancel").clicked() {
                    job.cancel();
                }
            }
            if let Some(e) = self.job_error.clone() {
                ui.separator();
                egui::Frame::NONE.fill(Color32::from_rgb(70, 20, 20)).inner_margin(8.0).corner_radius(4.0).show(ui, |ui| {
                    ui.colored_label(Color32::from_rgb(255, 190, 190), RichText::new("Could not open").strong());
                    ui.label(RichText::new(&e).color(Color32::from_rgb(255, 220, 220)));
                    if ui.button("Dismiss").clicked() {
                        self.job_error = None;
                    }
                });
            }
        });
        if let Some(source) = start {
            let series = Some(self.open_series.trim().to_string()).filter(|s| !s.is_empty());
            self.start_job(source, series);
        }
        if !open {
            self.open_dialog = false;
        }
    }

    /// The system dialog blocks whoever calls it, so it runs on its own thread; without a
    /// desktop portal it returns nothing and the typed path still works.
    fn start_file_dialog(&mut self, folder: bool) {
        let slot = Arc::new(std::sync::Mutex::new(None));
        let thread_slot = slot.clone();
        let ctx = self.ctx.clone();
        let start = PathBuf::from(self.open_path.trim());
        let spawned = std::thread::Builder::new()
            .name("strata-file-dialog".into())
            .spawn(move || {
                let mut dialog = rfd::FileDialog::new().set_title(if folder {
                    "Open a DICOM folder or store"
                } else {
                    "Open a scan"
                });
                if let Some(dir) = start.parent().filter(|d| d.is_dir()) {
                    dialog = dialog.set_directory(dir);
                }
                let chosen = if folder {
                    dialog.pick_folder()
                } else {
                    dialog.pick_file()
                };
                let outcome = chosen.map_or(DialogOutcome::NothingChosen, DialogOutcome::Chosen);
                *lock_ignoring_poison(&thread_slot) = Some(outcome);
                ctx.request_repaint();
            });
        match spawned {
            Ok(_) => {
                self.file_dialog = Some(slot);
                self.file_dialog_note = None;
            }
            Err(e) => self.file_dialog_note = Some(format!("no file dialog: {e}; type the path")),
        }
    }

    fn poll_file_dialog(&mut self) {
        let Some(slot) = &self.file_dialog else {
            return;
        };
        let Some(chosen) = lock_ignoring_poison(slot).take() else {
            return;
        };
        self.file_dialog = None;
        match chosen {
            DialogOutcome::Chosen(path) => {
                self.open_path = path.display().to_string();
                self.file_dialog_note = None;
            }
            DialogOutcome::NothingChosen => {
                self.file_dialog_note = Some(
                    "Nothing chosen (the dialog needs a desktop portal); you can type the path."
                        .into(),
                )
            }
        }
    }

    fn help_window(&mut self, ctx: &egui::Context) {
        let mut open = self.show_help;
        egui::Window::new("Keyboard and mouse").open(&mut open).resizable(false).show(ctx, |ui| {
            egui::Grid::new("help").num_columns(2).striped(true).show(ui, |ui| {
                for (keys, what) in [
                    ("Left drag (3D)", "orbit"),
                    ("Middle / Shift+left drag (3D)", "pan"),
                    ("Wheel (3D)", "zoom"),
                    ("Right drag (3D)", "shift (sideways) / widen (up-down) the transfer function"),
                    ("Double-click (3D)", "reset view"),
                    ("A P L R S I", "standard views: anterior, posterior, left, right, superior, inferior"),
                    ("Home, 0", "reset view"),
                    ("Left click / drag (slice)", "move the linked crosshair"),
                    ("Wheel, Up/Down, PgUp/PgDn (slice)", "page slices"),
                    ("Right drag (slice)", "window (sideways) / level (up-down)"),
                    ("Ctrl+wheel, middle drag (slice)", "zoom, pan; double-click resets"),
                    ("Double-click view title", "focus the view (1×1)"),
                    ("1 2 3", "layouts 1×1, 3D + 1×3, 2×2"),
                    ("M", "cycle DVR / MIP / isosurface"),
                    ("T", "target frame rate on/off"),
                    ("F12", "screenshot of the 3D view"),
                    ("Ctrl+O", "open or import"),
                    ("F1, H", "this help"),
                ] {
                    ui.strong(keys);
                    ui.label(what);
                    ui.end_row();
                }
            });
            ui.add_space(6.0);
            ui.label(RichText::new(format!("{NOT_FOR_DIAGNOSIS}: research and education only.")).color(WARNING_COLOUR));
        });
        self.show_help = open;
    }

    fn side_panel(&mut self, ui: &mut egui::Ui) {
        let prefs = &mut self.preferences;
        let Some(v) = self.volume.as_mut() else {
            return;
        };
        let unit = v.info.header.value_mapping.unit.clone();
        egui::CollapsingHeader::new("Transfer function")
            .default_open(true)
            .show(ui, |ui| {
                ui.horizontal_wrapped(|ui| {
                    for (name, label) in PRESETS {
                        if ui.selectable_label(prefs.preset == name, label).clicked() {
                            prefs.preset = name.into();
                            v.transfer_function = preset_for(name, &v.info);
                            v.tf_state = TfEditorState::default();
                        }
                    }
                });
                tf_editor::show(
                    ui,
                    &mut v.tf_state,
                    &mut v.transfer_function,
                    &v.histogram,
                    v.info.physical_range,
                    &unit,
                );
                ui.horizontal(|ui| {
                    ui.add(egui::TextEdit::singleline(&mut self.tf_path).desired_width(150.0))
                        .accessible_name("Transfer function file");
                    if ui.button("Save").clicked() {
                        self.tf_message = Some(
                            match v
                                .transfer_function
                                .save(std::path::Path::new(&self.tf_path))
                            {
                                Ok(()) => format!("saved {}", self.tf_path),
                                Err(e) => format!("could not save: {e}"),
                            },
                        );
                    }
                    if ui.button("Load").clicked() {
                        self.tf_message = Some(
                            match TransferFunction::load(std::path::Path::new(&self.tf_path)) {
                                Ok(tf) => {
                                    v.transfer_function = tf;
                                    v.tf_state = TfEditorState::default();
                                    format!("loaded {}", self.tf_path)
                                }
                                Err(e) => format!("could not load: {e}"),
                            },
                        );
                    }
                });
                if let Some(m) = &self.tf_message {
                    ui.weak(m);
                }
            });
        egui::CollapsingHeader::new("Rendering")
            .default_open(true)
            .show(ui, |ui| {
                ui.horizontal(|ui| {
                    ui.radio_value(&mut prefs.mode, RenderMode::Dvr, "DVR");
                    ui.radio_value(&mut prefs.mode, RenderMode::Mip, "MIP");
                    ui.radio_value(&mut prefs.mode, RenderMode::Isosurface, "Isosurface");
                });
                if prefs.mode == RenderMode::Isosurface {
                    let (lo, hi) = v.info.physical_range;
                    ui.add(
                        egui::Slider::new(&mut v.iso_value, lo..=hi)
                            .text(format!("iso value {unit}")),
                    );
                }
                ui.checkbox(&mut prefs.shading, "Shading (DVR)");
                ui.checkbox(&mut prefs.smooth_transitions, "Smooth level transitions")
                    .on_hover_text(
                        "Blend across the half voxel where bricks of different resolution meet, \
                         so coarse and fine bricks join without seams. Off shows the seams.",
                    );
                ui.checkbox(&mut prefs.show_planes_in_3d, "Slice planes in the 3D view");
                if ui
                    .checkbox(&mut prefs.orthographic, "Orthographic projection")
                    .changed()
                {
                    v.orbit.orthographic = prefs.orthographic;
                }
                ui.label("Crop box (fraction of each index axis)");
                for (axis, name) in ["i", "j", "k"].iter().enumerate() {
                    ui.horizontal(|ui| {
                        ui.label(*name);
                        let mut min = v.crop.min[axis];
                        let mut max = v.crop.max[axis];
                        ui.add(egui::DragValue::new(&mut min).speed(0.005).range(0.0..=1.0))
                            .accessible_name(format!("Crop {name} from"));
                        ui.add(egui::DragValue::new(&mut max).speed(0.005).range(0.0..=1.0))
                            .accessible_name(format!("Crop {name} to"));
                        v.crop.min[axis] = min.min(max - 0.01).max(0.0);
                        v.crop.max[axis] = max.max(min + 0.01).min(1.0);
                    });
                }
                ui.horizontal(|ui| {
                    ui.checkbox(&mut v.clip_enabled, "Clip plane");
                    egui::ComboBox::from_id_salt("clip axis")
                        .selected_text(["L–R", "A–P", "S–I"][v.clip_axis])
                        .show_ui(ui, |ui| {
                            ui.selectable_value(&mut v.clip_axis, 0, "L–R (sagittal)");
                            ui.selectable_value(&mut v.clip_axis, 1, "A–P (coronal)");
                            ui.selectable_value(&mut v.clip_axis, 2, "S–I (axial)");
                        })
                        .response
                        .accessible_name("Clip plane axis");
                    ui.checkbox(&mut v.clip_flip, "flip");
                });
                if v.clip_enabled {
                    ui.add(egui::Slider::new(&mut v.clip_fraction, 0.0..=1.0).text("position"));
                }
                if ui.button("Reset crop and clip").clicked() {
                    v.crop = CropBox::default();
                    v.clip_enabled = false;
                }
            });
        egui::CollapsingHeader::new("Performance")
            .default_open(true)
            .show(ui, |ui| {
                performance_panel(ui, prefs, v, &self.clock);
            });
        egui::CollapsingHeader::new("Screenshot")
            .default_open(false)
            .show(ui, |ui| {
                ui.horizontal(|ui| {
                    ui.label("Folder");
                    let mut folder = prefs.screenshot_folder.display().to_string();
                    if ui
                        .text_edit_singleline(&mut folder)
                        .accessible_name("Screenshot folder")
                        .changed()
                    {
                        prefs.screenshot_folder = PathBuf::from(folder);
                    }
                });
                ui.horizontal(|ui| {
                    ui.label("Resolution");
                    for s in [1, 2, 4] {
                        ui.selectable_value(&mut prefs.screenshot_scale, s, format!("{s}×"));
                    }
                });
            });
        egui::CollapsingHeader::new("Volume information")
            .default_open(false)
            .show(ui, |ui| {
                info_panel(ui, prefs, v);
            });
    }

    fn views(&mut self, ui: &mut egui::Ui) {
        let area = ui.available_rect_before_wrap();
        let gap = 2.0;
        let focused = self.preferences.focused;
        let slots: Vec<(ViewSlot, Rect)> = match self.preferences.layout {
            Layout::Single => vec![(focused, area)],
            Layout::ThreeDOverSlices => {
                let split = area.top() + area.height() * 0.62;
                let top = Rect::from_min_max(area.min, Pos2::new(area.right(), split - gap));
                let w = (area.width() - 2.0 * gap) / 3.0;
                let mut slots = vec![(ViewSlot::ThreeD, top)];
                for (i, view) in SliceView::ALL.iter().enumerate() {
                    let left = area.left() + i as f32 * (w + gap);
                    slots.push((
                        ViewSlot::Slice(*view),
                        Rect::from_min_max(
                            Pos2::new(left, split),
                            Pos2::new(left + w, area.bottom()),
                        ),
                    ));
                }
                slots
            }
            Layout::TwoByTwo => {
                let (w, h) = ((area.width() - gap) / 2.0, (area.height() - gap) / 2.0);
                let cell = |c: f32, r: f32| {
                    Rect::from_min_size(
                        Pos2::new(area.left() + c * (w + gap), area.top() + r * (h + gap)),
                        Vec2::new(w, h),
                    )
                };
                vec![
                    (ViewSlot::Slice(SliceView::Axial), cell(0.0, 0.0)),
                    (ViewSlot::ThreeD, cell(1.0, 0.0)),
                    (ViewSlot::Slice(SliceView::Sagittal), cell(0.0, 1.0)),
                    (ViewSlot::Slice(SliceView::Coronal), cell(1.0, 1.0)),
                ]
            }
        };
        ui.allocate_rect(area, Sense::hover());
        let mut focus_request = None;
        for (slot, rect) in &slots {
            let toggled = match slot {
                ViewSlot::ThreeD => self.view_3d(ui, *rect),
                ViewSlot::Slice(view) => self.slice_view(ui, *view, *rect),
            };
            if toggled {
                focus_request = Some(*slot);
            }
        }
        if let Some(slot) = focus_request {
            if self.preferences.layout == Layout::Single {
                self.preferences.layout = Layout::ThreeDOverSlices;
            } else {
                self.preferences.layout = Layout::Single;
            }
            self.preferences.focused = slot;
        }
        if let Some(v) = self.volume.as_mut() {
            v.view_rects = slots;
        }
    }

    /// Paints a view's title; returns true when it was double-clicked (focus toggle).
    fn view_title(ui: &mut egui::Ui, rect: Rect, id: &str, title: &str, colour: Color32) -> bool {
        let galley_rect = Rect::from_min_size(
            rect.min + Vec2::new(6.0, 4.0),
            Vec2::new(title.len() as f32 * 7.5 + 8.0, 16.0),
        );
        let response = ui.interact(
            galley_rect,
            ui.scope_id().with(("title", id)),
            Sense::click(),
        );
        ui.painter_at(rect).text(
            rect.min + Vec2::new(8.0, 4.0),
            egui::Align2::LEFT_TOP,
            title,
            egui::FontId::proportional(13.0),
            colour,
        );
        response
            .on_hover_text("Double-click to focus / unfocus this view")
            .double_clicked()
    }

    fn view_3d(&mut self, ui: &mut egui::Ui, rect: Rect) -> bool {
        let prefs = &self.preferences;
        let max_pixels = self.options.max_render_pixels;
        let Some(v) = self.volume.as_mut() else {
            return false;
        };
        let painter = ui.painter_at(rect);
        painter.rect_filled(rect, 0.0, Color32::BLACK);
        let response = ui.interact(rect, ui.scope_id().with("3d view"), Sense::click_and_drag());
        let (shift, pointer_delta) = ui.input(|i| (i.modifiers.shift, i.pointer.delta()));
        let mut moved = false;
        if response.dragged_by(egui::PointerButton::Primary) && !shift {
            v.orbit.orbit_by(pointer_delta, rect.size());
            moved = true;
        }
        if response.dragged_by(egui::PointerButton::Middle)
            || (response.dragged_by(egui::PointerButton::Primary) && shift)
        {
            v.orbit.pan_by(pointer_delta, rect.size());
            moved = true;
        }
        if response.dragged_by(egui::PointerButton::Secondary) {
            let (lo, hi) = v.info.physical_range;
            let shift_value = pointer_delta.x as f64 / rect.width().max(1.0) as f64 * (hi - lo);
            let scale = (-pointer_delta.y as f64 / rect.height().max(1.0) as f64 * 2.0).exp();
            tf_editor::shift_and_scale(&mut v.transfer_function, shift_value, scale);
            moved = true;
        }
        if response.hovered() {
            let scroll = ui.input(|i| i.smooth_scroll_delta.y);
            if scroll != 0.0 {
                v.orbit.zoom_by(scroll);
                moved = true;
            }
        }
        if response.double_clicked() {
            v.orbit = OrbitCamera {
                orthographic: prefs.orthographic,
                ..OrbitCamera::default()
            };
        }
        if moved {
            v.interacting_until = Some(Instant::now() + Duration::from_millis(150));
        }
        let interacting = v.interacting_until.is_some_and(|t| t > Instant::now());
        if interacting {
            ui.ctx().request_repaint_after(Duration::from_millis(160));
        }

        // Request a frame at the view's aspect.
        let ppp = ui.ctx().pixels_per_point();
        let mut scale = prefs.render_scale.clamp(0.2, 1.0) * ppp;
        if interacting && prefs.target_fps_enabled {
            // While dragging, fewer pixels: the controller then keeps a higher sampling rate.
            scale *= 0.5;
        }
        let longest = rect.width().max(rect.height()) * scale;
        if longest > max_pixels as f32 {
            scale *= max_pixels as f32 / longest;
        }
        let width = ((rect.width() * scale).round() as u32).max(16);
        let height = ((rect.height() * scale).round() as u32).max(16);
        let camera = v.orbit.camera(&v.info.geometry);
        let clip_plane = v.clip_enabled.then(|| clip_plane_for(v));
        let settings = RenderSettings {
            width,
            height,
            mode: prefs.mode,
            quality: prefs.step_voxels,
            shading: prefs.shading.then(Shading::default),
            smooth_transitions: prefs.smooth_transitions,
            iso_value: v.iso_value,
            crop: v.crop,
            clip_plane,
            ..RenderSettings::default()
        };
        v.session.request(RenderRequest {
            camera,
            settings,
            transfer_function: v.transfer_function.clone(),
            target_fps: prefs.target_fps_enabled.then_some(prefs.target_fps),
            interacting,
        });

        if let Some(frame) = v.session.latest_frame() {
            let fresh = v
                .volume_texture
                .as_ref()
                .is_none_or(|(_, serial)| *serial != frame.serial);
            if fresh {
                let image = egui::ColorImage::from_rgba_premultiplied(
                    [frame.width as usize, frame.height as usize],
                    &frame.rgba,
                );
                match &mut v.volume_texture {
                    Some((texture, serial)) => {
                        texture.set(image, TextureOptions::LINEAR);
                        *serial = frame.serial;
                    }
                    None => {
                        v.volume_texture = Some((
                            ui.ctx()
                                .load_texture("volume", image, TextureOptions::LINEAR),
                            frame.serial,
                        ))
                    }
                }
            }
            if let Some((texture, _)) = &v.volume_texture {
                painter.image(
                    texture.id(),
                    rect,
                    Rect::from_min_max(Pos2::ZERO, Pos2::new(1.0, 1.0)),
                    Color32::WHITE,
                );
            }
        }
        if prefs.show_planes_in_3d {
            paint_slice_planes(&painter, rect, &camera, v);
        }
        paint_orientation_marker(&painter, rect, &camera);
        let status = v.session.status();
        let mode = match prefs.mode {
            RenderMode::Dvr => "DVR",
            RenderMode::Mip => "MIP",
            RenderMode::Isosurface => "Isosurface",
        };
        let toggled = Self::view_title(
            ui,
            rect,
            "3d",
            &format!("3D · {mode} · {}", v.transfer_function.name),
            Color32::from_rgb(200, 200, 255),
        );
        let mut right_lines = Vec::new();
        if let Some(loading) = &status.loading {
            right_lines.push(loading.clone());
        } else if status.refining {
            right_lines.push("refining…".to_string());
        }
        if let Some(level) = status.finest_resident_level {
            right_lines.push(format!("finest level {level}"));
        }
        for (i, line) in right_lines.iter().enumerate() {
            painter.text(
                Pos2::new(rect.right() - 8.0, rect.top() + 4.0 + 15.0 * i as f32),
                egui::Align2::RIGHT_TOP,
                line,
                egui::FontId::proportional(12.0),
                Color32::LIGHT_GRAY,
            );
        }
        if let Some(error) = &status.error {
            painter.text(
                rect.center(),
                egui::Align2::CENTER_CENTER,
                error,
                egui::FontId::proportional(13.0),
                Color32::LIGHT_RED,
            );
        }
        painter.text(
            rect.right_bottom() + Vec2::new(-8.0, -6.0),
            egui::Align2::RIGHT_BOTTOM,
            NOT_FOR_DIAGNOSIS,
            egui::FontId::proportional(11.0),
            WARNING_COLOUR,
        );
        if response.clicked() || response.drag_started() {
            self.preferences.focused = ViewSlot::ThreeD;
        }
        toggled
    }

    fn slice_view(&mut self, ui: &mut egui::Ui, view: SliceView, rect: Rect) -> bool {
        let Some(v) = self.volume.as_mut() else {
            return false;
        };
        let frame = v.frames[view.index()];
        let geometry = &v.info.geometry;
        let dims = geometry.dims;
        let painter = ui.painter_at(rect);
        painter.rect_filled(rect, 0.0, Color32::BLACK);
        let colour = slice_colour(view);
        painter.rect_stroke(
            rect.shrink(0.5),
            0.0,
            Stroke::new(1.0, colour.gamma_multiply(0.6)),
            egui::StrokeKind::Inside,
        );
        // The image keeps the patient's proportions, centred with room for labels.
        let (w_mm, h_mm) = frame.extent_mm(geometry);
        // Room for the title line above, the W/L line below and the side labels.
        let inner = Rect::from_min_max(
            rect.min + Vec2::new(18.0, 38.0),
            rect.max - Vec2::new(18.0, 36.0),
        );
        let fit = (inner.width() as f64 / w_mm)
            .min(inner.height() as f64 / h_mm)
            .max(1e-6);
        let k = view.index();
        let response = ui.interact(
            rect,
            ui.scope_id().with(("slice", k)),
            Sense::click_and_drag(),
        );
        if response.hovered() {
            // Ctrl+wheel (or pinch) zooms about the pointer; plain wheel pages (below).
            let zoom = ui.input(|i| i.zoom_delta());
            if zoom != 1.0 {
                let old = v.slice_zoom[k];
                v.slice_zoom[k] = (old * zoom).clamp(1.0, 32.0);
                if let Some(pointer) = response.hover_pos() {
                    let from_centre = pointer - inner.center() - v.slice_pan[k];
                    v.slice_pan[k] -= from_centre * (v.slice_zoom[k] / old - 1.0);
                }
            }
        }
        if response.dragged_by(egui::PointerButton::Middle) {
            v.slice_pan[k] += ui.input(|i| i.pointer.delta());
        }
        if response.double_clicked() {
            v.slice_zoom[k] = 1.0;
            v.slice_pan[k] = Vec2::ZERO;
        }
        if v.slice_zoom[k] <= 1.0 {
            v.slice_pan[k] = Vec2::ZERO;
        }
        let scale = v.slice_zoom[k];
        let image_rect = Rect::from_center_size(
            inner.center() + v.slice_pan[k],
            Vec2::new((w_mm * fit) as f32 * scale, (h_mm * fit) as f32 * scale),
        );

        if let Some(pos) = response.interact_pointer_pos() {
            if (response.clicked() || response.dragged_by(egui::PointerButton::Primary))
                && image_rect.contains(pos)
            {
                let u = ((pos.x - image_rect.left()) / image_rect.width()) as f64;
                let w = ((pos.y - image_rect.top()) / image_rect.height()) as f64;
                let (a, d) = frame.index_at(dims, u, w);
                v.cursor[frame.across_axis] = a.clamp(0.0, dims[frame.across_axis] as f64 - 1.0);
                v.cursor[frame.down_axis] = d.clamp(0.0, dims[frame.down_axis] as f64 - 1.0);
            }
        }
        if response.dragged_by(egui::PointerButton::Secondary) {
            let delta = ui.input(|i| i.pointer.delta());
            let (lo, hi) = v.info.physical_range;
            let per_point = (hi - lo).max(1e-6) / rect.width().max(100.0) as f64;
            let (centre, width) = v.window;
            v.window = (
                centre - delta.y as f64 * per_point,
                (width + delta.x as f64 * per_point * 2.0).max(per_point),
            );
        }
        if response.hovered() && !ui.input(|i| i.modifiers.command || i.modifiers.ctrl) {
            let lines = ui.input(|i| {
                i.events
                    .iter()
                    .map(|e| match e {
                        egui::Event::MouseWheel { unit, delta, .. } => match unit {
                            egui::MouseWheelUnit::Point => delta.y as f64 / 40.0,
                            egui::MouseWheelUnit::Line => delta.y as f64,
                            egui::MouseWheelUnit::Page => delta.y as f64 * 10.0,
                        },
                        _ => 0.0,
                    })
                    .sum::<f64>()
            });
            if lines != 0.0 {
                // Wheel up (content moves down) goes towards higher slice numbers, as in Slicer.
                page_slice(v, view, lines.signum() * lines.abs().round().max(1.0));
            }
        }
        if response.clicked()
            || response.drag_started()
            || response.hovered() && ui.input(|i| i.pointer.any_pressed())
        {
            self.preferences.focused = ViewSlot::Slice(view);
        }
        let Some(v) = self.volume.as_mut() else {
            return false;
        };

        // Ask for the slice at the level matching this view's pixels.
        let ppp = ui.ctx().pixels_per_point();
        let voxels_across = dims[frame.across_axis] as f64;
        let level_count = v.info.header.layout.level_count();
        let level = level_for_pixels(
            voxels_across,
            (image_rect.width() * ppp) as f64,
            level_count,
        );
        let request = SliceRequest {
            view,
            frame,
            position: v.cursor[frame.normal_axis],
            level,
        };
        if v.last_slice_requests[view.index()] != Some(request) {
            v.slices.request(request);
            v.last_slice_requests[view.index()] = Some(request);
        }
        if let Some(image) = v.slices.latest(view) {
            let slot = &mut v.slice_textures[view.index()];
            let stale = slot
                .as_ref()
                .is_none_or(|t| !Arc::ptr_eq(&t.values, &image.values) || t.window != v.window);
            if stale {
                let grey = window_level_image(&image, v.window, v.info.mapping);
                match slot {
                    Some(t) => {
                        t.texture.set(grey, TextureOptions::LINEAR);
                        t.values = image.values.clone();
                        t.window = v.window;
                    }
                    None => {
                        *slot = Some(SliceTexture {
                            texture: ui.ctx().load_texture(
                                format!("slice {}", view.name()),
                                grey,
                                TextureOptions::LINEAR,
                            ),
                            values: image.values.clone(),
                            window: v.window,
                        })
                    }
                }
            }
            if let Some(t) = slot {
                let (fu, fv) = image.inside_fraction;
                let (u0, u1) = if frame.across_flipped {
                    (fu as f32, 0.0)
                } else {
                    (0.0, fu as f32)
                };
                let (v0, v1) = if frame.down_flipped {
                    (fv as f32, 0.0)
                } else {
                    (0.0, fv as f32)
                };
                let mut mesh = egui::Mesh::with_texture(t.texture.id());
                mesh.add_rect_with_uv(
                    image_rect,
                    Rect::from_min_max(Pos2::new(u0, v0), Pos2::new(u1, v1)),
                    Color32::WHITE,
                );
                // add_rect_with_uv orders uv corners by min/max; flip by swapping vertex uvs.
                if u0 > u1 || v0 > v1 {
                    for vertex in &mut mesh.vertices {
                        let fx = (vertex.pos.x - image_rect.left()) / image_rect.width();
                        let fy = (vertex.pos.y - image_rect.top()) / image_rect.height();
                        vertex.uv = Pos2::new(u0 + (u1 - u0) * fx, v0 + (v1 - v0) * fy);
                    }
                }
                painter.add(egui::Shape::mesh(mesh));
            }
        }
        // Crosshair.
        let (cu, cv) =
            frame.fraction_of(dims, v.cursor[frame.across_axis], v.cursor[frame.down_axis]);
        let cx = image_rect.left() + cu as f32 * image_rect.width();
        let cy = image_rect.top() + cv as f32 * image_rect.height();
        let hair = Stroke::new(1.0, Color32::from_rgba_unmultiplied(120, 220, 255, 150));
        painter.line_segment(
            [Pos2::new(image_rect.left(), cy), Pos2::new(cx - 8.0, cy)],
            hair,
        );
        painter.line_segment(
            [Pos2::new(cx + 8.0, cy), Pos2::new(image_rect.right(), cy)],
            hair,
        );
        painter.line_segment(
            [Pos2::new(cx, image_rect.top()), Pos2::new(cx, cy - 8.0)],
            hair,
        );
        painter.line_segment(
            [Pos2::new(cx, cy + 8.0), Pos2::new(cx, image_rect.bottom())],
            hair,
        );
        // Orientation labels.
        let font = egui::FontId::proportional(14.0);
        let label_colour = Color32::from_rgb(255, 220, 120);
        let [left, right, top, bottom] = frame.labels;
        painter.text(
            Pos2::new(rect.left() + 5.0, rect.center().y),
            egui::Align2::LEFT_CENTER,
            left,
            font.clone(),
            label_colour,
        );
        painter.text(
            Pos2::new(rect.right() - 5.0, rect.center().y),
            egui::Align2::RIGHT_CENTER,
            right,
            font.clone(),
            label_colour,
        );
        painter.text(
            Pos2::new(rect.center().x, rect.top() + 21.0),
            egui::Align2::CENTER_TOP,
            top,
            font.clone(),
            label_colour,
        );
        painter.text(
            Pos2::new(rect.center().x, rect.bottom() - 19.0),
            egui::Align2::CENTER_BOTTOM,
            bottom,
            font,
            label_colour,
        );
        let n = frame.normal_axis;
        let slice_number = v.cursor[n].round() as i64 + 1;
        let title = format!("{} {}/{}", view.name(), slice_number, dims[n]);
        let toggled = Self::view_title(ui, rect, view.name(), &title, colour);
        let shown_level = v.slices.latest(view).map(|i| i.request.level);
        let info = format!(
            "W {:.0} L {:.0}{}",
            v.window.1,
            v.window.0,
            shown_level
                .filter(|l| *l > 0)
                .map(|l| format!(" · level {l}"))
                .unwrap_or_default()
        );
        painter.text(
            rect.left_bottom() + Vec2::new(8.0, -4.0),
            egui::Align2::LEFT_BOTTOM,
            info,
            egui::FontId::proportional(11.0),
            Color32::LIGHT_GRAY,
        );
        toggled
    }
}

fn slice_colour(view: SliceView) -> Color32 {
    match view {
        SliceView::Axial => Color32::from_rgb(240, 90, 90),
        SliceView::Coronal => Color32::from_rgb(110, 200, 110),
        SliceView::Sagittal => Color32::from_rgb(230, 210, 90),
    }
}

/// Outlines where the three slice views cut the volume, projected with the 3D view's camera
/// (the frame fills `rect`, rendered at its aspect).
fn paint_slice_planes(
    painter: &egui::Painter,
    rect: Rect,
    camera: &strata_render::Camera,
    v: &OpenVolume,
) {
    let basis = camera.basis();
    let aspect = (rect.width() / rect.height().max(1.0)) as f64;
    let g = &v.info.geometry;
    let project = |index: glam::DVec3| -> Option<Pos2> {
        let d = g.patient_from_index(index) - basis.eye;
        let depth = d.dot(basis.forward);
        let (sx, sy) = if basis.orthographic {
            (d.dot(basis.right), d.dot(basis.up))
        } else if depth > 1e-6 {
            (d.dot(basis.right) / depth, d.dot(basis.up) / depth)
        } else {
            return None;
        };
        let u = (sx / (aspect * basis.half_extent) + 1.0) * 0.5;
        let w = (1.0 - sy / basis.half_extent) * 0.5;
        Some(Pos2::new(
            rect.left() + u as f32 * rect.width(),
            rect.top() + w as f32 * rect.height(),
        ))
    };
    for view in SliceView::ALL {
        let frame = v.frames[view.index()];
        let (n, a, b) = (frame.normal_axis, frame.across_axis, frame.down_axis);
        let (lo_a, hi_a) = (-0.5, g.dims[a] as f64 - 0.5);
        let (lo_b, hi_b) = (-0.5, g.dims[b] as f64 - 0.5);
        let corner = |ca: f64, cb: f64| {
            let mut i = [0.0; 3];
            i[n] = v.cursor[n];
            i[a] = ca;
            i[b] = cb;
            project(glam::DVec3::from(i))
        };
        let corners = [
            corner(lo_a, lo_b),
            corner(hi_a, lo_b),
            corner(hi_a, hi_b),
            corner(lo_a, hi_b),
        ];
        if let [Some(p0), Some(p1), Some(p2), Some(p3)] = corners {
            let stroke = Stroke::new(1.5, slice_colour(view).gamma_multiply(0.8));
            painter.add(egui::Shape::closed_line(vec![p0, p1, p2, p3], stroke));
        }
    }
}

fn page_slice(v: &mut OpenVolume, view: SliceView, step: f64) {
    let frame = v.frames[view.index()];
    let n = frame.normal_axis;
    let max = v.info.geometry.dims[n] as f64 - 1.0;
    // One displayed slice: a voxel of the level shown.
    let level = v.slices.latest(view).map_or(0, |i| i.request.level);
    let voxel = (1u64 << level) as f64;
    v.cursor[n] = (v.cursor[n].round() + step * voxel).clamp(0.0, max);
}

fn clip_plane_for(v: &OpenVolume) -> ClipPlane {
    let g = &v.info.geometry;
    let mut normal = [0.0; 3];
    normal[v.clip_axis] = if v.clip_flip { -1.0 } else { 1.0 };
    let n = glam::DVec3::from(normal);
    // Offset from the fraction of the volume's extent along the plane's normal.
    let corners = (0..8).map(|c| {
        let idx = glam::DVec3::new(
            if c & 1 == 0 {
                -0.5
            } else {
                g.dims[0] as f64 - 0.5
            },
            if c & 2 == 0 {
                -0.5
            } else {
                g.dims[1] as f64 - 0.5
            },
            if c & 4 == 0 {
                -0.5
            } else {
                g.dims[2] as f64 - 0.5
            },
        );
        g.patient_from_index(idx).dot(n)
    });
    let (lo, hi) = corners.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
        (a.min(x), b.max(x))
    });
    ClipPlane {
        normal,
        offset_mm: lo + (hi - lo) * v.clip_fraction,
    }
}

fn preset_for(name: &str, info: &VolumeInfo) -> TransferFunction {
    let mut tf = TransferFunction::preset(name).unwrap_or_else(|| {
        TransferFunction::new(name, &[(0.0, 0.0), (1.0, 1.0)], &[(0.0, [1.0; 3])])
    });
    // The MR preset assumes intensities near 0..1000; stretch it onto this scan's range.
    if name.starts_with("mr") {
        let (lo, hi) = info.physical_range;
        let scale = (hi - lo).max(1e-6) / 1000.0;
        for p in &mut tf.opacity {
            p.value = lo + p.value * scale;
        }
        for c in &mut tf.color {
            c.value = lo + c.value * scale;
        }
    }
    tf
}

/// A window from the histogram's 1st to 99th percentile, for scans without presets.
fn percentile_window(h: &Histogram) -> (f64, f64) {
    let total = h.total().max(1) as f64;
    let bin = (h.physical_max - h.physical_min) / h.counts.len().max(1) as f64;
    let mut seen = 0.0;
    let (mut lo, mut hi) = (h.physical_min, h.physical_max);
    let mut lo_set = false;
    for (i, &c) in h.counts.iter().enumerate() {
        seen += c as f64;
        if !lo_set && seen >= 0.01 * total {
            lo = h.physical_min + i as f64 * bin;
            lo_set = true;
        }
        if seen >= 0.99 * total {
            hi = h.physical_min + (i + 1) as f64 * bin;
            break;
        }
    }
    ((lo + hi) * 0.5, (hi - lo).max(1e-6))
}

/// Stored values → grey through the window (physical units), as a texture image.
pub fn window_level_image(
    image: &SliceImage,
    window: (f64, f64),
    mapping: strata_render::ValueMapping,
) -> egui::ColorImage {
    let (centre, width) = window;
    let lo = centre - width * 0.5;
    let scale = 255.0 / width.max(1e-9);
    let pixels = image
        .values
        .iter()
        .map(|&s| {
            let g = ((mapping.physical(s as f64) - lo) * scale).clamp(0.0, 255.0) as u8;
            Color32::from_gray(g)
        })
        .collect();
    egui::ColorImage::new([image.width, image.height], pixels)
}

const MIB: f64 = (1u64 << 20) as f64;

fn performance_panel(
    ui: &mut egui::Ui,
    prefs: &mut Preferences,
    v: &mut OpenVolume,
    clock: &FrameClock,
) {
    let status = v.session.status();
    ui.horizontal(|ui| {
        let enabled = ui.checkbox(&mut prefs.target_fps_enabled, "Target frame rate");
        ui.add_enabled(
            prefs.target_fps_enabled,
            egui::Slider::new(&mut prefs.target_fps, 2.0..=60.0)
                .suffix(" fps")
                .logarithmic(true),
        )
        .labelled_by(enabled.id);
    });
    if !prefs.target_fps_enabled {
        ui.add(
            egui::Slider::new(&mut prefs.step_voxels, 0.125..=4.0)
                .logarithmic(true)
                .text("step (voxels)"),
        );
    }
    ui.add(egui::Slider::new(&mut prefs.render_scale, 0.25..=1.0).text("resolution"));
    let now = Instant::now();
    let ui_ms: Vec<[f64; 2]> = clock
        .samples
        .iter()
        .filter(|s| s.1 > 0.0)
        .map(|s| [s.0, s.1])
        .collect();
    let t_now = clock.samples.back().map_or(0.0, |s| s.0);
    let volume_ms: Vec<[f64; 2]> = status
        .volume_frame_ms
        .iter()
        .map(|(at, ms)| {
            [
                t_now - now.saturating_duration_since(*at).as_secs_f64(),
                *ms,
            ]
        })
        .collect();
    let mean = |xs: &[[f64; 2]]| {
        if xs.is_empty() {
            f64::NAN
        } else {
            xs.iter().map(|p| p[1]).sum::<f64>() / xs.len() as f64
        }
    };
    ui.label(format!(
        "UI frame {:.1} ms · volume frame {:.1} ms",
        mean(&ui_ms[ui_ms.len().saturating_sub(30)..]),
        mean(&volume_ms[volume_ms.len().saturating_sub(10)..]),
    ));
    ui.weak(format!("volume on {}", status.adapter));
    egui_plot::Plot::new("frame times")
        .height(110.0)
        .allow_drag(false)
        .allow_zoom(false)
        .allow_scroll(false)
        .include_y(0.0)
        .legend(egui_plot::Legend::default())
        .x_axis_label("s")
        .y_axis_label("ms")
        .show(ui, |plot| {
            plot.line(egui_plot::Line::new(
                "UI frame",
                egui_plot::PlotPoints::from(ui_ms),
            ));
            plot.line(egui_plot::Line::new(
                "volume frame",
                egui_plot::PlotPoints::from(volume_ms),
            ));
        });
    egui::Grid::new("perf figures")
        .num_columns(2)
        .show(ui, |ui| {
            ui.label("Sampling rate");
            ui.label(format!("{:.2} samples/voxel", status.sampling_rate));
            ui.end_row();
            ui.label("Quality (lod) factor");
            ui.label(format!("{:.1}", status.lod_factor));
            ui.end_row();
            if let Some(l) = &status.loader {
                ui.label("GPU bricks per level");
                let per_level: Vec<String> = l
                    .gpu_resident_per_level
                    .iter()
                    .enumerate()
                    .filter(|(_, n)| **n > 0)
                    .map(|(level, n)| format!("L{level}: {n}"))
                    .collect();
                ui.label(per_level.join("  "));
                ui.end_row();
                ui.label("GPU cache");
                ui.label(format!(
                    "{} / {} slots · {:.0} / {:.0} MiB",
                    l.gpu_slots_used,
                    l.gpu_slots_capacity,
                    l.gpu_bytes as f64 / MIB,
                    l.gpu_budget_bytes as f64 / MIB
                ));
                ui.end_row();
                ui.label("CPU cache");
                ui.label(format!(
                    "{:.0} / {:.0} MiB · hit {:.0}%",
                    l.cpu_bytes as f64 / MIB,
                    l.cpu_budget_bytes as f64 / MIB,
                    l.cpu_hit_rate * 100.0
                ));
                ui.end_row();
                ui.label("Pending loads");
                ui.label(format!("{} ({} reading)", l.pending, l.in_flight));
                ui.end_row();
                ui.label("I/O");
                ui.label(format!(
                    "{:.1} MB/s · {} bricks read",
                    l.bytes_read_per_second / 1e6,
                    l.bricks_read_total
                ));
                ui.end_row();
            }
            ui.label("Finest level on GPU");
            ui.label(status.finest_resident_level.map_or("—".into(), |l| {
                format!(
                    "{l} (0 = full resolution; root {})",
                    status.level_count.saturating_sub(1)
                )
            }));
            ui.end_row();
            ui.label("Volume frames");
            ui.label(status.frames_rendered.to_string());
            ui.end_row();
        });
    if status.loading.is_some() || status.refining {
        ui.horizontal(|ui| {
            ui.spinner();
            ui.label(status.loading.clone().unwrap_or_else(|| "refining…".into()));
        });
    } else {
        ui.weak("converged");
    }
}

fn info_panel(ui: &mut egui::Ui, prefs: &mut Preferences, v: &OpenVolume) {
    let h = &v.info.header;
    let g = &h.geometry;
    egui::Grid::new("info")
        .num_columns(2)
        .striped(true)
        .show(ui, |ui| {
            let mut row = |k: &str, val: String| {
                ui.label(k);
                ui.label(val);
                ui.end_row();
            };
            row(
                "Modality",
                if h.modality.is_empty() {
                    "(unknown)".into()
                } else {
                    h.modality.clone()
                },
            );
            row(
                "Dimensions",
                format!("{} × {} × {}", g.dims[0], g.dims[1], g.dims[2]),
            );
            row(
                "Spacing",
                format!(
                    "{:.3} × {:.3} × {:.3} mm",
                    g.spacing_mm[0], g.spacing_mm[1], g.spacing_mm[2]
                ),
            );
            row(
                "Extent",
                format!(
                    "{:.0} × {:.0} × {:.0} mm",
                    g.dims[0] as f64 * g.spacing_mm[0],
                    g.dims[1] as f64 * g.spacing_mm[1],
                    g.dims[2] as f64 * g.spacing_mm[2]
                ),
            );
            row(
                "Origin (LPS)",
                format!(
                    "{:.1}, {:.1}, {:.1} mm",
                    g.origin_lps_mm[0], g.origin_lps_mm[1], g.origin_lps_mm[2]
                ),
            );
            let code: String = g.direction.iter().map(|d| orientation_letter(*d)).collect();
            row("Orientation", format!("{code} (index axes point towards)"));
            row(
                "Values",
                format!(
                    "{:.1} … {:.1} {}",
                    v.info.physical_range.0, v.info.physical_range.1, h.value_mapping.unit
                ),
            );
            row(
                "Stored as",
                format!(
                    "{:?}, physical = {} × stored + {}",
                    h.stored, h.value_mapping.mapping.slope, h.value_mapping.mapping.intercept
                ),
            );
            row("Levels", h.layout.level_count().to_string());
            for w in &h.windows {
                row(
                    "Window",
                    format!("{}: W {:.0} / L {:.0}", w.name, w.width, w.center),
                );
            }
        });
    ui.checkbox(
        &mut prefs.show_identifiers,
        "Show identifiers (description, source file names)",
    );
    if prefs.show_identifiers {
        ui.label(format!("Description: {}", h.description));
        for input in &h.provenance.inputs {
            ui.label(format!("Source: {input}"));
        }
    } else {
        ui.weak("Patient identifiers hidden.");
    }
}

fn orientation_letter(direction: [f64; 3]) -> char {
    let a = direction.map(f64::abs);
    if a[0] >= a[1] && a[0] >= a[2] {
        if direction[0] > 0.0 {
            'L'
        } else {
            'R'
        }
    } else if a[1] >= a[2] {
        if direction[1] > 0.0 {
            'P'
        } else {
            'A'
        }
    } else if direction[2] > 0.0 {
        'S'
    } else {
        'I'
    }
}

/// eframe's side: the app plus persistence.
pub struct EframeApp {
    pub app: StrataApp,
    pub persist: bool,
}

impl eframe::App for EframeApp {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        self.app.ui(ui);
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
        assert!(
            !old.show_identifiers,
            "identifiers stay hidden unless the user showed them"
        );
    }

    #[test]
    fn percentile_window_spans_the_bulk_of_the_histogram() {
        let mut counts = vec![0u64; 100];
        counts[10] = 1; // an outlier below
        for c in counts.iter_mut().take(80).skip(20) {
            *c = 100;
        }
        counts[99] = 1; // an outlier above
        let h = Histogram {
            physical_min: 0.0,
            physical_max: 100.0,
            counts,
        };
        let (centre, width) = percentile_window(&h);
        assert!(
            (centre - 50.0).abs() < 2.0 && (width - 60.0).abs() < 3.0,
            "window {centre} / {width}"
        );
    }
}
