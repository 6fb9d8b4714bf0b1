//! The page's three linked slice views (wasm32 only): axial, coronal and sagittal of a
//! streamed store or of the page's built-in sample, oriented as the desktop's (strata-slices' [`SliceFrame`]), sliced by the
//! same [`SliceAssembler`] and coloured by the same window/level step, so a slice looks the
//! same in both viewers.
//!
//! Nothing here waits: the bricks the assembler lists are fetched through the served store's
//! own asynchronous path (a second [`BrickFetcher`] of `served_store.rs`: the same request,
//! checksum verification and decoding as the 3D view's, at most [`DECODES_PER_FRAME`] decoded
//! a frame), with only the [`SLICE_REQUESTS`] most useful bricks asked for at a time, so the
//! slices never crowd the 3D view's requests off the page's few connections. The sample's
//! bricks are in memory already (the render crate's [`BrickedVolume`], bricked as the stores
//! are): at most [`SAMPLE_BRICKS_PER_FRAME`] of them are handed to the same assembler a frame.
//! A view keeps its last image until the new one is complete.
//!
//! Input, as the desktop's slice views: left click or drag moves the linked crosshair (the
//! other two views page to it), the wheel pages, right drag (or Shift + left drag, for
//! touchpads) windows: sideways widens, up raises the level; Ctrl+wheel (or a pinch) zooms
//! about the pointer, middle drag pans, a double-click resets zoom and pan (the desktop's
//! gestures, from strata-viewer-ui's slice_canvas, as is the drawing around the image). The
//! colour-map choice sits at the axial view's top right, the window/level presets (the
//! desktop's, strata-viewer-ui's window_presets) beside it; a scan opens at the window the
//! desktop opens it with (`initial_window`). The line under each view reads
//! W/L, the slice's level when coarser than 0, and the stored value under the pointer in
//! physical units.
//!
//! [`DECODES_PER_FRAME`]: crate::served_store::DECODES_PER_FRAME

use std::rc::Rc;
use std::sync::Arc;

use egui::{Color32, Pos2, Rect, Sense, Stroke, TextureHandle, TextureOptions, Vec2};
use strata_render::{BrickSource, BrickedVolume, ValueMapping, VolumeGeometry};
use strata_slices::{
    drag_window, level_for_pixels, window_level_rgba, ColourMap, SliceAssembler, SliceFrame,
    SliceImage, SliceRequest, SliceView, VoxelLookup, Window,
};
use strata_source::{BrickFetcher, FetchOptions, VolumeSource};
use strata_storage::histogram::Histogram;
use strata_storage::source::WindowPreset as ScanWindow;
use strata_types::{BrickId, OctreeLayout};
use strata_viewer_ui::layouts;
use strata_viewer_ui::measurements::{
    paint_on_slice, slice_input, Measurements, SliceContext, Tool,
};
use strata_viewer_ui::presets::{integer_values, looks_like_ct, readout_value};
use strata_viewer_ui::slice_canvas::{
    colour_map_combo, fraction_at, inner_rect, paint_crosshair, paint_orientation_labels,
    paint_readout_line, screen_at, slice_mesh, ZoomPan,
};
use strata_viewer_ui::view_state::Layout;
use strata_viewer_ui::window_presets::{header_window, initial_window, preset_buttons};

/// Decoded bricks the page keeps for its slices (bytes): a brick row of every view at the
/// level the views need, and more for paging, well inside the page's memory.
pub const SLICE_CACHE_BYTES: usize = 96 << 20;
/// Brick requests the slice views have out at once (the most useful first).
pub const SLICE_REQUESTS: usize = 4;
/// In-memory bricks handed to the assembler a frame (the sample's): a 256³ sample's
/// level-0 slice needs 64, each a copy of about 90 kB, so a slice completes in a frame or
/// two without one frame copying a whole volume's worth.
pub const SAMPLE_BRICKS_PER_FRAME: usize = 64;

/// Where the views' bricks come from.
enum Bricks {
    /// A served store, fetched asynchronously.
    Served(Box<dyn BrickFetcher>),
    /// The page's sample, bricked in memory as the stores are (shared with the 3D view).
    Sample(Rc<BrickedVolume>),
}

/// What a scan tells the window presets (strata-viewer-ui's window_presets, the desktop's).
struct ScanWindows {
    modality: String,
    /// The scan's own windows (DICOM's), first the one it opens with.
    own: Vec<ScanWindow>,
    /// Its histogram, for Auto (1st to 99th percentile) and MR's opening window.
    histogram: Histogram,
}

/// A slice on screen: the image, its texture, and the window and map it was coloured with.
struct Shown {
    image: SliceImage,
    texture: TextureHandle,
    window: Window,
    colour_map: ColourMap,
}

/// The three slice views of one volume.
pub struct SliceViews {
    bricks: Bricks,
    assembler: SliceAssembler,
    geometry: VolumeGeometry,
    frames: [SliceFrame; 3],
    mapping: ValueMapping,
    unit: String,
    physical_range: (f64, f64),
    /// The linked crosshair, level-0 continuous index.
    pub cursor: [f64; 3],
    pub window: Window,
    /// Whether the scan is a CT (CT's named windows are offered).
    is_ct: bool,
    /// What the window presets offer besides CT's: the scan's own windows, Auto's histogram.
    windows: ScanWindows,
    pub colour_map: ColourMap,
    /// Each view's zoom and pan.
    zoom_pan: [ZoomPan; 3],
    /// The crosshair before the last single click moved it: a double-click (whose first
    /// click is such a click) puts it back, so it resets the zoom only (as on the desktop).
    cursor_before_click: Option<[f64; 3]>,
    shown: [Option<Shown>; 3],
    /// The views drawn this frame (the oblique view may take the sagittal's place).
    drawn: [bool; 3],
    requested: [Option<SliceRequest>; 3],
    /// Wheel movement not yet paged, per view (fractions of a line).
    wheel_lines: [f64; 3],
    /// The level-0 voxel under the pointer this frame, if any.
    hovered: Option<[u32; 3]>,
    error: Option<String>,
    /// The test capture of the axial view was handed out (`capture=1`).
    captured: bool,
    /// Each view's image is of the 4-D store's frame shown before (frames.rs): it stays on
    /// screen until the new frame's arrives, and is not captured.
    stale_frame: [bool; 3],
    /// The rulers, angles and regions, the tool and the one being drawn (measure.rs).
    measurements: Measurements,
    /// The label layer being edited on this volume (segment_editor.rs), if one was started.
    pub segmentation: Option<crate::segment_editor::PageSegmentation>,
    /// A second served store drawn over the slices (overlay_view.rs), as the link names it.
    pub overlay: crate::overlay_view::OverlaySlot,
    /// The volume's level-0 values for the segmentation tools that read them
    /// (primary_values_page.rs), or why the page has none.
    pub primary_values: Result<crate::primary_values_page::PagePrimaryValues, String>,
}

pub fn slice_colour(view: SliceView) -> Color32 {
    match view {
        SliceView::Axial => Color32::from_rgb(240, 90, 90),
        SliceView::Coronal => Color32::from_rgb(110, 200, 110),
        SliceView::Sagittal => Color32::from_rgb(230, 210, 90),
    }
}

/// The 3D view's rectangle and the slice views' (axial, coronal, sagittal) in a layout that
/// shows slices, placed as the desktop places them (strata-viewer-ui's layouts): the 2×2
/// (axial | 3D over sagittal | coronal), or the 3D view over axial, coronal, sagittal.
/// `None` for the 3D view alone.
pub fn slice_layout(layout: Layout, area: Rect) -> Option<(Rect, [Rect; 3])> {
    match layout {
        Layout::Single => None,
        Layout::FourUp => {
            let [axial, three_d, sagittal, coronal] = layouts::two_by_two_cells(area);
            Some((three_d, [axial, coronal, sagittal]))
        }
        Layout::ThreeDOverSlices => {
            let (three_d, row) = layouts::three_d_over_row(area, SliceView::ALL.len());
            Some((three_d, [row[0], row[1], row[2]]))
        }
    }
}

/// Wheel movement this frame in lines (up positive), whatever unit the browser reports.
pub(crate) fn wheel_lines(ui: &egui::Ui) -> f64 {
    ui.input(|i| {
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
    })
}

/// Why a served store's slice views could not start.
#[derive(Debug, thiserror::Error)]
pub enum SliceViewsError {
    #[error(transparent)]
    Fetcher(strata_source::SourceError),
    #[error("the store has no asynchronous brick path")]
    NoAsynchronousPath,
}

impl SliceViews {
    /// Slice views of `store`, fetching through its asynchronous path.
    pub fn new(store: &dyn VolumeSource) -> Result<SliceViews, SliceViewsError> {
        let fetcher = match store.start_fetching(FetchOptions {
            max_queued: SLICE_REQUESTS + 1,
            max_in_transit: SLICE_REQUESTS + 1,
            threads: 1,
        }) {
            Some(Ok(fetcher)) => fetcher,
            Some(Err(e)) => return Err(SliceViewsError::Fetcher(e)),
            None => return Err(SliceViewsError::NoAsynchronousPath),
        };
        let header = store.header();
        let stored = (header.stored_range[0], header.stored_range[1]);
        let primary_values =
            crate::primary_values_page::PagePrimaryValues::served(store).map_err(|e| e.to_string());
        Ok(SliceViews::with_bricks(
            Bricks::Served(fetcher),
            header.geometry.clone(),
            header.layout.clone(),
            (header.value_mapping.mapping, stored),
            header.value_mapping.unit.clone(),
            ScanWindows {
                modality: header.modality.clone(),
                own: header.windows.clone(),
                histogram: store.histogram().clone(),
            },
            primary_values,
        ))
    }

    /// Slice views of the page's sample (a CT phantom in HU), read from its in-memory bricks.
    pub fn for_sample(volume: Rc<BrickedVolume>) -> SliceViews {
        let geometry = volume.geometry.clone();
        let layout = OctreeLayout::new(geometry.dims);
        let (mapping, stored) = (volume.mapping, volume.stored_range);
        // The sample is the CT phantom: CT's windows, none of its own.
        let windows = ScanWindows {
            modality: "CT".into(),
            own: Vec::new(),
            histogram: crate::side_panel::sample_histogram(&geometry),
        };
        let primary_values = Ok(crate::primary_values_page::PagePrimaryValues::sample(
            volume.clone(),
        ));
        SliceViews::with_bricks(
            Bricks::Sample(volume),
            geometry,
            layout,
            (mapping, stored),
            "HU".into(),
            windows,
            primary_values,
        )
    }

    fn with_bricks(
        bricks: Bricks,
        geometry: VolumeGeometry,
        layout: OctreeLayout,
        (mapping, stored_range): (ValueMapping, (u16, u16)),
        unit: String,
        windows: ScanWindows,
        primary_values: Result<crate::primary_values_page::PagePrimaryValues, String>,
    ) -> SliceViews {
        let a = mapping.physical(stored_range.0 as f64);
        let b = mapping.physical(stored_range.1 as f64);
        let physical_range = (a.min(b), a.max(b));
        // The window the desktop opens the same scan with (one rule, shared).
        let is_ct = looks_like_ct(&windows.modality, &unit, physical_range);
        let window = initial_window(header_window(&windows.own), is_ct, &windows.histogram);
        let frames = SliceView::ALL.map(|v| SliceFrame::for_view(v, &geometry));
        let cursor = geometry
            .dims
            .map(|d| ((d as f64 - 1.0) * 0.5).floor().max(0.0));
        SliceViews {
            bricks,
            assembler: SliceAssembler::new(layout, SLICE_CACHE_BYTES),
            geometry,
            frames,
            mapping,
            unit,
            physical_range,
            cursor,
            window,
            is_ct,
            windows,
            colour_map: ColourMap::Grey,
            zoom_pan: [ZoomPan::default(); 3],
            cursor_before_click: None,
            shown: [None, None, None],
            drawn: [true; 3],
            requested: [None, None, None],
            wheel_lines: [0.0; 3],
            hovered: None,
            error: None,
            captured: false,
            stale_frame: [false; 3],
            measurements: Measurements::default(),
            segmentation: None,
            overlay: Default::default(),
            primary_values,
        }
    }

    /// The measurements with what their list describes them by (measure.rs).
    pub fn measurement_parts(&mut self) -> (&mut Measurements, &VolumeGeometry, &str) {
        (&mut self.measurements, &self.geometry, &self.unit)
    }

    /// A link's crosshair (clamped into the volume) and window (None: keep the store's).
    pub fn set_from_link(&mut self, cursor: Option<[f64; 3]>, window: Option<[f64; 2]>) {
        if let Some(cursor) = cursor {
            let dims = self.geometry.dims;
            self.cursor = std::array::from_fn(|axis| {
                cursor[axis].clamp(0.0, (dims[axis] as f64 - 1.0).max(0.0))
            });
        }
        if let Some([centre, width]) = window {
            self.window = Window::new(centre, width);
        }
    }

    /// Test hook (`capture=1`): once every view shows the slice it asked for, the axial view's
    /// image as the page coloured it (RGBA8 in index order, flips not applied), with its
    /// width and height; given once. The browser test compares it with the desktop's
    /// assembler and window/level on the same store.
    pub fn take_capture(&mut self) -> Option<(Vec<u8>, u32, u32)> {
        let complete = SliceView::ALL
            .iter()
            .filter(|v| self.drawn[v.index()])
            .all(|v| {
                self.assembler.pending(*v).is_none()
                    && !self.stale_frame[v.index()]
                    && self.shown[v.index()]
                        .as_ref()
                        .is_some_and(|s| Some(s.image.request) == self.requested[v.index()])
            });
        if self.captured || !complete {
            return None;
        }
        let shown = self.shown[SliceView::Axial.index()].as_ref()?;
        let image = &shown.image;
        let mut rgba =
            window_level_rgba(&image.values, shown.window, self.colour_map, self.mapping);
        // With the overlay over it, once sampled (overlay_view.rs).
        if !self.overlay.composite(image, &mut rgba) {
            return None;
        }
        self.captured = true;
        Some((rgba, image.width as u32, image.height as u32))
    }

    /// The volume's grid (a new segmentation's).
    pub fn geometry(&self) -> &VolumeGeometry {
        &self.geometry
    }

    pub fn captured(&self) -> bool {
        self.captured
    }

    /// Takes the bricks that arrived, hands finished slices to their views and asks for the
    /// next bricks. Call once a frame, before [`SliceViews::ui`].
    fn pump(&mut self, ctx: &egui::Context) {
        if let Bricks::Served(fetcher) = &mut self.bricks {
            for result in fetcher.try_results() {
                match result.outcome {
                    Ok(voxels) => {
                        if let Err(e) = self.assembler.offer(result.id, voxels) {
                            self.error = Some(e.to_string());
                        }
                    }
                    Err(e) => self.error = Some(e.to_string()),
                }
                fetcher.complete(result.id);
            }
        }
        let limit = match self.bricks {
            Bricks::Served(_) => SLICE_REQUESTS,
            Bricks::Sample(_) => SAMPLE_BRICKS_PER_FRAME,
        };
        // The voxel under the pointer first (one brick), then the slices' most useful bricks.
        let mut wanted: Vec<BrickId> = Vec::with_capacity(limit);
        if let Some(index) = self.hovered {
            if let Ok(VoxelLookup::Needs(id)) = self.assembler.voxel(index) {
                wanted.push(id);
            }
        }
        for id in self.assembler.most_useful_missing(limit) {
            if wanted.len() >= limit {
                break;
            }
            if !wanted.contains(&id) {
                wanted.push(id);
            }
        }
        match &mut self.bricks {
            Bricks::Served(fetcher) => {
                let demand: Vec<(BrickId, f64)> = wanted
                    .iter()
                    .enumerate()
                    .map(|(rank, id)| (*id, (limit - rank) as f64))
                    .collect();
                fetcher.set_requests(&demand, &[]);
                if !demand.is_empty() {
                    // Answers arrive between frames and wake nothing: poll until they are in.
                    ctx.request_repaint();
                }
            }
            Bricks::Sample(volume) => {
                for id in wanted {
                    match volume.brick(id.level, id.coords) {
                        Some(payload) => {
                            if let Err(e) = self.assembler.offer(id, Arc::new(payload.to_vec())) {
                                self.error = Some(e.to_string());
                            }
                        }
                        None => {
                            self.error = Some(format!(
                                "the sample has no brick at level {} {:?}",
                                id.level, id.coords
                            ))
                        }
                    }
                }
            }
        }
    }

    /// The views in their rectangles (axial, coronal, sagittal; None: not shown, its place
    /// the oblique view's).
    pub fn ui(&mut self, ui: &mut egui::Ui, rects: [Option<Rect>; 3]) {
        let ctx = ui.ctx().clone();
        self.pump(&ctx);
        self.overlay.pump(&ctx);
        self.hovered = None;
        for view in SliceView::ALL {
            if let Some(image) = self.assembler.take_finished(view) {
                self.show(&ctx, image);
            }
            self.drawn[view.index()] = rects[view.index()].is_some();
            match rects[view.index()] {
                Some(rect) => self.view_ui(ui, view, rect),
                None => {
                    self.assembler.cancel(view);
                    self.requested[view.index()] = None;
                }
            }
        }
        // A slice started this frame, or a readout waiting for its brick: the next frame must
        // come (fetch answers wake nothing) to ask for and take the bricks.
        let waiting_for_voxel = self
            .hovered
            .is_some_and(|i| matches!(self.assembler.voxel(i), Ok(VoxelLookup::Needs(_))));
        if waiting_for_voxel
            || SliceView::ALL
                .iter()
                .any(|v| self.assembler.pending(*v).is_some())
        {
            ctx.request_repaint();
        }
        // The colour map, at the axial view's top right.
        let Some(axial) = rects[SliceView::Axial.index()] else {
            return;
        };
        let picker = Rect::from_min_size(
            Pos2::new(axial.right() - 104.0, axial.top() + 2.0),
            Vec2::new(100.0, 20.0),
        );
        ui.scope_builder(egui::UiBuilder::new().max_rect(picker), |ui| {
            colour_map_combo(ui, &mut self.colour_map)
        });
        // The window/level presets beside it: the desktop's Slices panel's buttons.
        let presets = picker.translate(Vec2::new(-picker.width() - 4.0, 0.0));
        ui.scope_builder(egui::UiBuilder::new().max_rect(presets), |ui| {
            egui::ComboBox::from_id_salt("slice window presets")
                .selected_text("W/L")
                .width(presets.width())
                .show_ui(ui, |ui| {
                    ui.set_min_width(240.0);
                    preset_buttons(
                        ui,
                        self.is_ct,
                        &self.windows.own,
                        &self.windows.histogram,
                        &mut self.window,
                    );
                })
                .response
                .on_hover_text("Window/level presets")
        });
        // Textures follow the window (dragged this frame) and the colour map, every view.
        for view in SliceView::ALL {
            if let Some(shown) = self.shown[view.index()].as_mut() {
                if shown.window != self.window || shown.colour_map != self.colour_map {
                    let rgba = window_level_rgba(
                        &shown.image.values,
                        self.window,
                        self.colour_map,
                        self.mapping,
                    );
                    shown.texture.set(
                        egui::ColorImage::from_rgba_unmultiplied(
                            [shown.image.width, shown.image.height],
                            &rgba,
                        ),
                        TextureOptions::LINEAR,
                    );
                    shown.window = self.window;
                    shown.colour_map = self.colour_map;
                }
            }
        }
    }

    /// Another frame of the 4-D store (frames.rs): its bricks from now on (a new fetcher and
    /// assembler: the cached bricks are the old frame's), the same crosshair, window and zoom;
    /// the images on screen stay until the new frame's arrive, and the test capture is taken
    /// again of the new frame.
    pub fn show_frame(&mut self, store: &dyn VolumeSource) -> Result<(), SliceViewsError> {
        let fetcher = match store.start_fetching(FetchOptions {
            max_queued: SLICE_REQUESTS + 1,
            max_in_transit: SLICE_REQUESTS + 1,
            threads: 1,
        }) {
            Some(Ok(fetcher)) => fetcher,
            Some(Err(e)) => return Err(SliceViewsError::Fetcher(e)),
            None => return Err(SliceViewsError::NoAsynchronousPath),
        };
        self.bricks = Bricks::Served(fetcher);
        self.assembler = SliceAssembler::new(store.header().layout.clone(), SLICE_CACHE_BYTES);
        self.requested = [None, None, None];
        self.stale_frame = [true; 3];
        self.captured = false;
        Ok(())
    }

    fn show(&mut self, ctx: &egui::Context, image: SliceImage) {
        let rgba = window_level_rgba(&image.values, self.window, self.colour_map, self.mapping);
        let colours = egui::ColorImage::from_rgba_unmultiplied([image.width, image.height], &rgba);
        let view = image.request.view;
        self.stale_frame[view.index()] = false;
        match self.shown[view.index()].as_mut() {
            Some(shown) => {
                shown.texture.set(colours, TextureOptions::LINEAR);
                shown.image = image;
                shown.window = self.window;
                shown.colour_map = self.colour_map;
            }
            None => {
                let texture = ctx.load_texture(
                    format!("slice {}", view.name()),
                    colours,
                    TextureOptions::LINEAR,
                );
                self.shown[view.index()] = Some(Shown {
                    image,
                    texture,
                    window: self.window,
                    colour_map: self.colour_map,
                });
            }
        }
    }

    fn view_ui(&mut self, ui: &mut egui::Ui, view: SliceView, rect: Rect) {
        let frame = self.frames[view.index()];
        let dims = self.geometry.dims;
        let painter = ui.painter_at(rect);
        painter.rect_filled(rect, 0.0, Color32::BLACK);
        let colour = slice_colour(view);
        painter.rect_stroke(
            rect.shrink(0.5),
            0.0,
            Stroke::new(1.0, colour.gamma_multiply(0.6)),
            egui::StrokeKind::Inside,
        );
        // The image keeps the patient's proportions, centred with room for the labels;
        // zoomed and panned as on the desktop.
        let inner = inner_rect(rect);
        let response = ui.interact(
            rect,
            ui.scope_id().with(("slice", view.index())),
            Sense::click_and_drag(),
        );
        let double_clicked = self.zoom_pan[view.index()].input(ui, &response, inner);
        if double_clicked {
            if let Some(cursor) = self.cursor_before_click.take() {
                self.cursor = cursor;
            }
        }
        let image_rect =
            self.zoom_pan[view.index()].image_rect(inner, frame.extent_mm(&self.geometry));
        let windowing = response.dragged_by(egui::PointerButton::Secondary)
            || response.dragged_by(egui::PointerButton::Primary) && ui.input(|i| i.modifiers.shift);
        let measuring = SliceContext {
            view,
            frame,
            geometry: &self.geometry,
            mapping: self.mapping,
            cursor: self.cursor,
        };
        if windowing {
            let delta = ui.input(|i| i.pointer.delta());
            self.window = drag_window(
                self.window,
                delta.x as f64,
                delta.y as f64,
                self.physical_range,
            );
        } else if self.measurements.tool != Tool::Navigate {
            // A measuring tool takes the left button, as on the desktop (measure.rs).
            let shown = self.shown[view.index()].as_ref().map(|s| &s.image);
            slice_input(
                ui,
                &response,
                image_rect,
                &measuring,
                &mut self.measurements,
                shown,
            );
        } else if self.segmentation.as_ref().is_some_and(|s| s.paints()) {
            // A segment tool has the left button (segment_editor.rs); the crosshair stays.
            let (geometry, cursor) = (&self.geometry, self.cursor);
            let to_lps = |p: Pos2| {
                let (u, v) = fraction_at(image_rect, p);
                let (a, d) = frame.index_at(dims, u, v);
                let mut index = cursor;
                index[frame.across_axis] = a;
                index[frame.down_axis] = d;
                geometry.patient_from_index(glam::DVec3::from(index))
            };
            if let Some(seg) = self.segmentation.as_mut() {
                let plane = crate::segment_editor::plane_of(frame);
                seg.pointer(ui, &response, image_rect, &to_lps, plane);
            }
        } else if let Some(pos) = response.interact_pointer_pos().filter(|_| !double_clicked) {
            if (response.clicked() || response.dragged_by(egui::PointerButton::Primary))
                && image_rect.contains(pos)
            {
                self.cursor_before_click = response.clicked().then_some(self.cursor);
                let (u, v) = fraction_at(image_rect, pos);
                let (a, d) = frame.index_at(dims, u, v);
                self.cursor[frame.across_axis] = a.clamp(0.0, dims[frame.across_axis] as f64 - 1.0);
                self.cursor[frame.down_axis] = d.clamp(0.0, dims[frame.down_axis] as f64 - 1.0);
            }
        }
        let n = frame.normal_axis;
        if response.hovered() && !ui.input(|i| i.modifiers.command || i.modifiers.ctrl) {
            // Whole lines page; fractions (touchpads) add up to the same one slice a click.
            // (Ctrl+wheel zooms.)
            self.wheel_lines[view.index()] += wheel_lines(ui);
            let step = self.wheel_lines[view.index()].trunc();
            if step != 0.0 {
                self.wheel_lines[view.index()] -= step;
                self.cursor[n] = (self.cursor[n].round() + step).clamp(0.0, dims[n] as f64 - 1.0);
            }
        } else {
            self.wheel_lines[view.index()] = 0.0;
        }

        // Ask for the slice at the level matching this view's pixels.
        let ppp = ui.ctx().pixels_per_point();
        let level = level_for_pixels(
            dims[frame.across_axis] as f64,
            (image_rect.width() * ppp) as f64,
            self.assembler.layout().level_count(),
        );
        let request = SliceRequest {
            view,
            frame,
            position: self.cursor[n],
            level,
        };
        if self.requested[view.index()] != Some(request) {
            match self.assembler.start(request) {
                Ok(()) => self.requested[view.index()] = Some(request),
                Err(e) => self.error = Some(e.to_string()),
            }
        }
        if let Some(shown) = &self.shown[view.index()] {
            painter.add(egui::Shape::mesh(slice_mesh(
                shown.texture.id(),
                image_rect,
                shown.image.inside_fraction,
                frame,
            )));
        }
        if let Some(shown) = &self.shown[view.index()] {
            self.overlay
                .paint(ui.ctx(), &painter, &shown.image, image_rect);
        }
        if let Some(seg) = self.segmentation.as_mut() {
            seg.paint_labels(ui.ctx(), &painter, view, frame, image_rect, self.cursor[n]);
        }

        // The crosshair and the orientation labels.
        let centre = screen_at(
            image_rect,
            frame.fraction_of(
                dims,
                self.cursor[frame.across_axis],
                self.cursor[frame.down_axis],
            ),
        );
        paint_crosshair(&painter, image_rect, centre);
        if let Some(shown) = &self.shown[view.index()] {
            // Regions opened from a link get their statistics once their slice is shown.
            self.measurements
                .fill_missing_stats(view, &shown.image, &self.geometry, self.mapping);
        }
        let on_screen = SliceContext {
            cursor: self.cursor,
            ..measuring
        };
        paint_on_slice(
            &painter,
            image_rect,
            &on_screen,
            &self.measurements,
            &self.unit,
        );
        paint_orientation_labels(&painter, rect, frame.labels);
        let slice_number = self.cursor[n].round() as i64 + 1;
        painter.text(
            rect.left_top() + Vec2::new(8.0, 4.0),
            egui::Align2::LEFT_TOP,
            format!("{} {}/{}", view.name(), slice_number, dims[n]),
            egui::FontId::proportional(13.0),
            colour,
        );
        let mut info = format!("W {:.0} L {:.0}", self.window.width, self.window.centre);
        if let Some(level) = self.shown[view.index()]
            .as_ref()
            .map(|s| s.image.request.level)
            .filter(|l| *l > 0)
        {
            info.push_str(&format!(" · level {level}"));
        }
        if self.assembler.pending(view).is_some() {
            info.push_str(" · loading");
        }
        if let Some(pos) = response.hover_pos().filter(|p| image_rect.contains(*p)) {
            let (u, v) = fraction_at(image_rect, pos);
            let (a, d) = frame.index_at(dims, u, v);
            let mut index = self.cursor.map(|c| c.round().max(0.0) as u32);
            index[frame.across_axis] = (a.round().max(0.0) as u32).min(dims[frame.across_axis] - 1);
            index[frame.down_axis] = (d.round().max(0.0) as u32).min(dims[frame.down_axis] - 1);
            self.hovered = Some(index);
            let value = match self.assembler.voxel(index) {
                // The desktop's readout of a value (strata_viewer_ui::presets).
                Ok(VoxelLookup::Value(stored)) => readout_value(
                    self.mapping.physical(stored as f64),
                    &self.unit,
                    integer_values(&self.mapping),
                ),
                Ok(VoxelLookup::Needs(_)) => "…".to_string(),
                Err(e) => e.to_string(),
            };
            crate::page_tools::publish_readout(
                &view.name().to_lowercase(),
                index,
                value.trim_end(),
            );
            info.push_str(&format!(
                " · ({}, {}, {}) {}",
                index[0],
                index[1],
                index[2],
                value.trim_end()
            ));
        }
        if let Some(error) = &self.error {
            info.push_str(&format!(" · {error}"));
        }
        paint_readout_line(&painter, rect, info);
    }
}
