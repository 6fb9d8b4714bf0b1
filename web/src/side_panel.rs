//! The page's side panel (wasm32 only): the transfer-function editor on the 3D view's function
//! and the Performance panel, both the desktop viewer's own (strata_viewer_ui). What the browser
//! cannot do (import, local stores, saving a function to a file) is not offered here.
//!
//! The panel owns the function the view draws with: the view's preset until the editor changes
//! it; choosing another preset starts again from that preset. The page's render driver
//! (strata_viewer_ui::render_driver) uploads it to the renderer only when it changed.
//! The address (view_state.rs) keeps the preset and, once edited, the function itself (`tf=`,
//! [`SidePanel::edited_function`]); a link with `tf=` opens with that function, as edited.

use std::collections::VecDeque;

use strata_loader::FrameStats;
use strata_render::testdata::phantom::ct_phantom_hu;
use strata_render::{FrameTiming, RenderMode, TransferFunction, VolumeGeometry};
use strata_storage::histogram::{Histogram, StoredValueCounts};
use strata_viewer_ui::crop_clip;
use strata_viewer_ui::lighting::{self, LightOffer, LitView};
use strata_viewer_ui::performance::{self, FrameClock, PerformanceFigures};
use strata_viewer_ui::presets::{self, ScanValues};
use strata_viewer_ui::target_fps::target_fps_control;
use strata_viewer_ui::tf_editor::{self, TfEditorState};
use web_time::Instant;

use crate::view_state::ViewState;

/// The target frame rate the page starts with: the desktop viewer's default.
const DEFAULT_TARGET_FPS: f64 = 10.0;
/// GPU frame times kept for the plot.
const GPU_TIMES_KEPT: usize = 240;
/// Points per axis at which the sample's histogram samples the phantom (its own formula, not
/// the bricks: 48³ values give the histogram's shape in a few milliseconds).
const SAMPLE_HISTOGRAM_EDGE: u32 = 48;

/// What the page tells the panel about this frame's volume.
pub struct VolumeFigures<'a> {
    /// The loader's figures for a streamed store (`None` for the sample made in the page).
    pub loader: Option<&'a FrameStats>,
    /// The raycaster's step factor the frame on screen was drawn with (samples per voxel =
    /// 1 / it): the controller's while the view moves, the view's own at rest.
    pub step_factor: f64,
    /// The loader's quality factor that frame asked for (1: the full-quality cut).
    pub lod_factor: f64,
    /// Volume frames submitted so far.
    pub frames_submitted: u64,
}

pub struct SidePanel {
    editor: TfEditorState,
    transfer_function: TransferFunction,
    /// The preset `transfer_function` started from.
    preset: String,
    /// Edits since that preset was chosen (0: the preset as it is).
    edits: u64,
    /// The volume's histogram, its physical range and unit (until known: none, no editor).
    histogram: Option<(Histogram, (f64, f64), String)>,
    /// The scan's modality, unit and range once known: presets are fitted to it.
    scan: Option<ScanValues>,
    adapter: String,
    started: Instant,
    clock: FrameClock,
    /// Raycast GPU times (timestamp queries) as `[seconds, ms]` on the clock's axis.
    gpu_ms: VecDeque<[f64; 2]>,
    /// The target-frame-rate control, as the desktop's (on, 10 fps): while the view moves the
    /// time-critical controller holds the rate; at rest the view draws at full quality.
    target_fps_enabled: bool,
    target_fps: f64,
    /// The adaptive sampling slider's ε, kept while the switch is off (the link's
    /// `adaptive=` holds it only while on).
    adaptive_epsilon: f64,
}

impl SidePanel {
    pub fn new(view: &ViewState, adapter: String) -> Self {
        SidePanel {
            editor: TfEditorState::default(),
            transfer_function: view.transfer_function(),
            preset: view.preset.clone(),
            // A link's edited function (`tf=`) shows as edited, with Reset to its preset.
            edits: u64::from(view.tf.is_some()),
            histogram: None,
            scan: None,
            adapter,
            started: Instant::now(),
            clock: FrameClock::default(),
            gpu_ms: VecDeque::new(),
            target_fps_enabled: true,
            target_fps: DEFAULT_TARGET_FPS,
            adaptive_epsilon: view
                .adaptive_epsilon
                .unwrap_or(strata_viewer_ui::adaptive::DEFAULT_EPSILON),
        }
    }

    /// Follows the view's preset: another one replaces the function (and drops the edits).
    fn follow_preset(&mut self, view: &ViewState) {
        if view.preset != self.preset {
            self.transfer_function = self.preset_function(&view.preset);
            self.preset = view.preset.clone();
            self.edits = 0;
            self.editor = TfEditorState::default();
        }
    }

    /// A preset's function fitted to the scan, once known ([`presets::fitted_preset`], the
    /// desktop's); until then as it is.
    fn preset_function(&self, preset: &str) -> TransferFunction {
        match &self.scan {
            Some(scan) => presets::fitted_preset(preset, scan.physical_range),
            None => {
                TransferFunction::preset(preset).unwrap_or_else(|| self.transfer_function.clone())
            }
        }
    }

    /// The scan the view shows (a served store's header, or the sample's): an unedited
    /// function is fitted to it again.
    pub fn set_scan(&mut self, scan: ScanValues) {
        self.scan = Some(scan);
        if self.edits == 0 {
            self.transfer_function = self.preset_function(&self.preset);
        }
    }

    /// An undo or redo put `view` back: its preset and its function (as edited, or the
    /// preset's).
    pub fn restore(&mut self, view: &ViewState) {
        self.preset = view.preset.clone();
        self.transfer_function = match &view.tf {
            Some(tf) => tf.clone(),
            None => self.preset_function(&view.preset),
        };
        self.edits = u64::from(view.tf.is_some());
        self.editor = TfEditorState::default();
        if let Some(epsilon) = view.adaptive_epsilon {
            self.adaptive_epsilon = epsilon;
        }
    }

    /// The scan's values, once known.
    pub fn scan(&self) -> Option<&ScanValues> {
        self.scan.as_ref()
    }

    /// The function the 3D view draws with.
    pub fn transfer_function(&mut self, view: &ViewState) -> TransferFunction {
        self.follow_preset(view);
        self.transfer_function.clone()
    }

    /// The rate the view holds while it moves; None: the control is off (the view's own
    /// sampling step, moving or not).
    pub fn target_fps(&self) -> Option<f64> {
        self.target_fps_enabled.then_some(self.target_fps)
    }

    /// The function for the address: the edited one while it differs from its preset; None
    /// when it is the preset (never edited, or Reset), which `preset=` alone describes.
    pub fn edited_function(&self) -> Option<&TransferFunction> {
        TransferFunction::preset(&self.preset)?;
        let preset = self.preset_function(&self.preset);
        let tf = &self.transfer_function;
        (self.edits > 0 && (tf.opacity != preset.opacity || tf.color != preset.color)).then_some(tf)
    }

    /// The editor's histogram: a served store's own (from its open document).
    pub fn set_histogram(&mut self, histogram: Histogram, unit: &str) {
        let range = (histogram.physical_min, histogram.physical_max);
        self.histogram = Some((histogram, range, unit.to_string()));
    }

    /// The editor's histogram for the sample volume made in the page.
    pub fn set_sample_histogram(&mut self, view: &ViewState) {
        let histogram = sample_histogram(&view.geometry());
        // The sample is the CT phantom, in HU.
        self.set_scan(ScanValues {
            modality: "CT".into(),
            unit: "HU".into(),
            physical_range: (histogram.physical_min, histogram.physical_max),
            integer_values: true,
        });
        self.set_histogram(histogram, "HU");
    }

    /// Raycast GPU times of frames that finished (read without waiting, a frame or two late).
    pub fn gpu_timings(&mut self, timings: Vec<FrameTiming>) {
        let now = self.started.elapsed().as_secs_f64();
        for timing in timings {
            self.gpu_ms.push_back([now, timing.milliseconds]);
        }
        while self.gpu_ms.len() > GPU_TIMES_KEPT {
            self.gpu_ms.pop_front();
        }
    }

    /// Records the UI frame that started at `ui_started` (the panel plots the intervals).
    pub fn record_frame(&mut self, ui_started: Instant, frames_submitted: u64) {
        let seconds = self.started.elapsed().as_secs_f64();
        self.clock
            .record(seconds, ui_started, frames_submitted, false);
    }

    /// The panel; its cut and shading controls change `view` (the address follows it).
    pub fn ui(&mut self, ui: &mut egui::Ui, view: &mut ViewState, figures: VolumeFigures<'_>) {
        self.follow_preset(view);
        egui::ScrollArea::vertical().show(ui, |ui| {
            egui::CollapsingHeader::new("Transfer function")
                .default_open(true)
                .show(ui, |ui| self.transfer_function_ui(ui));
            egui::CollapsingHeader::new("Crop, clip, shading and projection")
                .default_open(false)
                .show(ui, |ui| {
                    // The desktop's rendering panel draws the same controls (crop_clip.rs).
                    let shading = ui.add_enabled(
                        view.mode != RenderMode::Mip,
                        egui::Checkbox::new(&mut view.shading, "Shading (DVR, isosurface)"),
                    );
                    if shading.changed() && !view.shading {
                        // As the desktop's: each effect would keep the view shaded otherwise.
                        view.light.effects_off();
                    }
                    ui.checkbox(&mut view.orthographic, "Orthographic projection");
                    crop_clip::controls(ui, &mut view.crop, &mut view.clip);
                });
            let light = egui::CollapsingHeader::new("Light and shadows")
                .default_open(false)
                .show(ui, |ui| self.light_ui(ui, view));
            // For the browser tests: where to click to open the section, and (light_ui) the
            // cinematic buttons' places while it is open.
            crate::canvas_attributes::set(
                "data-light-header",
                &rect_text(light.header_response.rect),
            );
            if light.body_returned.is_none() {
                crate::canvas_attributes::set("data-cinematic-buttons", "");
            }
            egui::CollapsingHeader::new("Performance")
                .default_open(true)
                .show(ui, |ui| {
                    // The desktop's Rendering-panel switch and ε slider; the still view of a
                    // served store is then drawn by the adaptive pass (adaptive.rs).
                    let mut on = view.adaptive_epsilon.is_some();
                    strata_viewer_ui::adaptive::controls(
                        ui,
                        view.mode,
                        &mut on,
                        &mut self.adaptive_epsilon,
                    );
                    view.adaptive_epsilon = on.then_some(self.adaptive_epsilon);
                    self.performance_ui(ui, figures);
                });
        });
    }

    /// The desktop's cinematic presets and light controls (viewer-ui's lighting.rs) on the
    /// view the address carries; the page refines their effects while the view is still
    /// (refine.rs), as the desktop does.
    fn light_ui(&mut self, ui: &mut egui::Ui, view: &mut ViewState) {
        let unedited = self.edits == 0;
        let (clicked, rects) = match self.scan.as_ref() {
            Some(scan) => lighting::cinematic_buttons(ui, scan, |preset| {
                unedited && view.preset == preset.tf_preset && view.light == preset.light()
            }),
            None => (None, Vec::new()),
        };
        let places: Vec<String> = rects
            .iter()
            .map(|(preset, rect)| format!("{}:{}", preset.label, rect_text(*rect)))
            .collect();
        crate::canvas_attributes::set("data-cinematic-buttons", &places.join(";"));
        if let Some(preset) = clicked {
            preset.light_view(&mut view.light, &mut view.shading, &mut view.mode);
            view.preset = preset.tf_preset.into();
            view.tf = None;
            // The preset's function as it is, fitted to the scan, not an edit of the last one.
            self.restore(view);
        }
        let lit = LitView {
            mode: view.mode,
            shading: view.shading,
            // The page runs no adaptive pass.
            adaptive_sampling: false,
        };
        let offer = LightOffer {
            effects_refused: lighting::effects_refused(lit),
        };
        lighting::light_controls(ui, &mut view.light, &mut view.shading, offer);
    }

    fn transfer_function_ui(&mut self, ui: &mut egui::Ui) {
        let source = if self.edits > 0 {
            format!("{} — edited", self.preset)
        } else {
            self.preset.clone()
        };
        ui.horizontal(|ui| {
            ui.add(egui::Label::new(egui::RichText::new(source).weak()).truncate());
            if self.edits > 0 && ui.button("Reset").clicked() {
                self.transfer_function = self.preset_function(&self.preset);
                // A new key: the view draws the preset again.
                self.edits += 1;
                self.editor = TfEditorState::default();
            }
        });
        let Some((histogram, range, unit)) = &self.histogram else {
            ui.weak("the volume's histogram arrives with the volume");
            return;
        };
        if tf_editor::show(
            ui,
            &mut self.editor,
            &mut self.transfer_function,
            histogram,
            *range,
            unit,
        ) {
            self.edits += 1;
        }
    }

    fn performance_ui(&mut self, ui: &mut egui::Ui, figures: VolumeFigures<'_>) {
        let loader = figures.loader;
        // The finest level with a brick on the GPU and the pyramid's depth, from the loader's
        // residency per level.
        let per_level = loader.map_or(&[][..], |l| &l.gpu_resident_per_level[..]);
        let working = match loader {
            Some(l) if l.source_status.is_retrying() => Some(format!(
                "server unreachable, retrying ({:?})",
                l.source_status
            )),
            Some(l) if !l.converged => Some(format!(
                "loading: {} requested, {} in flight",
                l.queued, l.in_flight
            )),
            _ => None,
        };
        target_fps_control(ui, &mut self.target_fps_enabled, &mut self.target_fps);
        let volume_frame_ms: Vec<[f64; 2]> = self.gpu_ms.iter().copied().collect();
        let shown = PerformanceFigures {
            adapter: &self.adapter,
            gpu_frame_ms: volume_frame_ms.last().map(|p| p[1]),
            volume_frame_ms,
            sampling_rate: 1.0 / figures.step_factor.max(1e-9),
            lod_factor: figures.lod_factor,
            loader,
            traversal: None,
            finest_resident_level: per_level.iter().position(|&n| n > 0).map(|l| l as u8),
            level_count: per_level.len(),
            frames_rendered: figures.frames_submitted,
            working,
        };
        performance::show(ui, &self.clock, &shown);
        if self.gpu_ms.is_empty() {
            ui.weak("volume frame times: this browser's WebGPU offers no timestamp queries");
        } else {
            ui.weak("volume frame: the raycast pass's GPU time (timestamp queries)");
        }
    }
}

/// The sample volume's histogram: the CT phantom's formula (render::phantom) sampled on a
/// coarser grid over the same box, in the sample's stored values (HU + 1024).
pub fn sample_histogram(geometry: &VolumeGeometry) -> Histogram {
    let centre = geometry.centre_patient();
    let extent = [0, 1, 2].map(|a| geometry.dims[a] as f64 * geometry.spacing_mm[a]);
    let radius = 0.5 * extent.iter().cloned().fold(f64::INFINITY, f64::min);
    let edge_mm = geometry.spacing_mm.iter().cloned().fold(0.0, f64::max);
    let n = SAMPLE_HISTOGRAM_EDGE;
    let mut counts = StoredValueCounts::default();
    let mut row = Vec::with_capacity(n as usize);
    for z in 0..n {
        for y in 0..n {
            row.clear();
            for x in 0..n {
                let at = [x, y, z];
                let index: [f64; 3] = std::array::from_fn(|axis| {
                    (at[axis] as f64 + 0.5) / n as f64 * geometry.dims[axis] as f64
                });
                let hu = ct_phantom_hu(geometry.patient_from_index(index), centre, radius, edge_mm);
                row.push((hu + 1024.0).round().clamp(0.0, 4095.0) as u16);
            }
            counts.add_slice(&row);
        }
    }
    Histogram::from_stored(&counts, 1.0, -1024.0)
}

/// A rectangle as the page publishes it for its tests: `x,y,w,h` in CSS pixels of the canvas.
fn rect_text(rect: egui::Rect) -> String {
    format!(
        "{},{},{},{}",
        rect.min.x,
        rect.min.y,
        rect.width(),
        rect.height()
    )
}
