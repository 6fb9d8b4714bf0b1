//! One slice view (axial, coronal or sagittal): the slice read at the level matching its
//! pixels, window-levelled into a texture, the crosshair, orientation labels and the W/L line.
//! Left click/drag moves the linked crosshair, right drag windows, the wheel pages, Ctrl+wheel
//! zooms about the pointer, middle drag pans, a double-click resets zoom and pan. With the
//! segment brush or eraser chosen (segmentation.rs), the left button paints instead, and the
//! brush is drawn as a circle of its size under the pointer.

use std::sync::Arc;

use egui::{Color32, Pos2, Rect, Sense, Stroke, TextureHandle, TextureOptions, Vec2};
use glam::DVec3;
use strata_segment::tools::brush::SlicePlane;
use strata_viewer_ui::slice_canvas::{
    fraction_at, inner_rect, paint_crosshair, paint_orientation_labels, paint_readout_line,
    screen_at, slice_mesh, ZoomPan,
};

use super::colour_maps::ColourMap;
use super::orientation::SliceView;
use super::overlay::{Overlay, OverlayKind, OverlayStyle};
use super::scene::{voxel_index, Scene, VolumeData, Window};
use super::segmentation::{plane_for_view, Segmentation};
use super::slices::{level_for_pixels, SliceImage, SliceRequest};
use super::widgets::{view_title, wheel_lines, ViewResponse};
use strata_viewer_ui::measurements::{paint_on_slice, slice_input, SliceContext, Tool};

/// A slice texture and what it was made from (so it is rebuilt only when one of them changes).
struct SliceTexture {
    texture: TextureHandle,
    values: Arc<Vec<u16>>,
    window: Window,
    colour_map: ColourMap,
}

/// The overlay's texture over a slice and what it was coloured from.
struct OverlayTexture {
    texture: TextureHandle,
    values: Arc<Vec<f32>>,
    style: OverlayStyle,
}

/// The stored values behind a slice texture and the window they were shown with (tests).
#[cfg(test)]
pub struct SliceShown {
    pub values: Arc<Vec<u16>>,
    pub window: Window,
    pub colour_map: ColourMap,
}

/// One slice view's own state.
pub struct SliceViewer {
    pub view: SliceView,
    /// Magnification over fit-to-view, and pan in points (strata-viewer-ui's slice_canvas).
    zoom_pan: ZoomPan,
    texture: Option<SliceTexture>,
    overlay_texture: Option<OverlayTexture>,
    last_request: Option<SliceRequest>,
    /// Wheel movement not yet paged (fractions of a line).
    wheel_lines: f64,
    /// Where the slice image was drawn last frame (tests point at voxels through it).
    pub image_rect: Option<Rect>,
    /// The crosshair before the last single click moved it: a double-click (whose first click
    /// is such a click) puts it back, so it resets the zoom only (issue 36).
    cursor_before_click: Option<[f64; 3]>,
}

pub fn slice_colour(view: SliceView) -> Color32 {
    match view {
        SliceView::Axial => Color32::from_rgb(240, 90, 90),
        SliceView::Coronal => Color32::from_rgb(110, 200, 110),
        SliceView::Sagittal => Color32::from_rgb(230, 210, 90),
    }
}

impl SliceViewer {
    /// The slice reader changed (another frame of a 4-D volume): ask it again.
    pub fn forget_requests(&mut self) {
        self.last_request = None;
    }

    pub fn new(view: SliceView) -> Self {
        SliceViewer {
            view,
            zoom_pan: ZoomPan::default(),
            texture: None,
            overlay_texture: None,
            last_request: None,
            wheel_lines: 0.0,
            image_rect: None,
            cursor_before_click: None,
        }
    }

    #[cfg(test)]
    pub fn shown(&self) -> Option<SliceShown> {
        self.texture.as_ref().map(|t| SliceShown {
            values: t.values.clone(),
            window: t.window,
            colour_map: t.colour_map,
        })
    }

    /// The level-0 continuous index at screen point `pos` of an image drawn in `image_rect`:
    /// on this view's slice (the crosshair's position along its normal).
    pub fn index_at(
        &self,
        pos: Pos2,
        image_rect: Rect,
        data: &VolumeData,
        scene: &Scene,
    ) -> [f64; 3] {
        let frame = data.frame(self.view);
        let (u, w) = fraction_at(image_rect, pos);
        let (a, d) = frame.index_at(data.info.geometry.dims, u, w);
        let mut index = scene.cursor;
        index[frame.across_axis] = a;
        index[frame.down_axis] = d;
        index
    }

    /// The screen point of level-0 index `index` (its across and down components) in the
    /// image as drawn last frame.
    #[cfg_attr(not(test), allow(dead_code))]
    pub fn screen_of(&self, index: [f64; 3], data: &VolumeData) -> Option<Pos2> {
        let rect = self.image_rect?;
        let frame = data.frame(self.view);
        Some(screen_at(
            rect,
            frame.fraction_of(
                data.info.geometry.dims,
                index[frame.across_axis],
                index[frame.down_axis],
            ),
        ))
    }

    /// What strata-viewer-ui's measurement gestures and drawing need of this view.
    fn measure_context<'a>(&self, data: &'a VolumeData, scene: &Scene) -> SliceContext<'a> {
        SliceContext {
            view: self.view,
            frame: data.frame(self.view),
            geometry: &data.info.geometry,
            mapping: data.info.mapping,
            cursor: scene.cursor,
        }
    }

    /// Left button with a segment tool ([`segment_pointer_input`]) on this slice.
    fn brush_input(
        &self,
        ui: &egui::Ui,
        response: &egui::Response,
        image_rect: Rect,
        data: &VolumeData,
        scene: &Scene,
        seg: &mut Segmentation,
    ) {
        let frame = data.frame(self.view);
        let geometry = &data.info.geometry;
        let to_lps = |p: Pos2| {
            let index = self.index_at(p, image_rect, data, scene);
            geometry.patient_from_index(DVec3::from(index))
        };
        let labels = seg.layer.geometry();
        let plane = |centre| {
            plane_for_view(
                frame.normal_axis,
                frame.across_axis,
                frame.down_axis,
                geometry,
                &labels,
                centre,
            )
        };
        segment_pointer_input(ui, response, image_rect, seg, &to_lps, &plane);
    }

    /// The overlay over the slice `image`: asked for on the overlay's thread for exactly this
    /// image's grid, coloured here (again only when the values or the style change), drawn
    /// with the slice's own mesh. Labels are drawn with nearest filtering: a linear filter
    /// would blend two labels' colours into a third at every boundary.
    fn paint_overlay(
        &mut self,
        ui: &egui::Ui,
        painter: &egui::Painter,
        overlay: &Overlay,
        image: &SliceImage,
        image_rect: Rect,
    ) {
        overlay.request(image.request, image.width, image.height);
        let Some(slice) = overlay
            .latest(self.view)
            .filter(|s| s.request == image.request && s.width == image.width)
        else {
            return;
        };
        let filter = match overlay.kind {
            OverlayKind::Labels => TextureOptions::NEAREST,
            OverlayKind::Continuous => TextureOptions::LINEAR,
        };
        let stale = self
            .overlay_texture
            .as_ref()
            .is_none_or(|t| !Arc::ptr_eq(&t.values, &slice.values) || t.style != overlay.style);
        if stale {
            let colours = overlay.colourise(&slice);
            match &mut self.overlay_texture {
                Some(t) => {
                    t.texture.set(colours, filter);
                    t.values = slice.values.clone();
                    t.style = overlay.style.clone();
                }
                None => {
                    self.overlay_texture = Some(OverlayTexture {
                        texture: ui.ctx().load_texture(
                            format!("overlay {}", self.view.name()),
                            colours,
                            filter,
                        ),
                        values: slice.values.clone(),
                        style: overlay.style.clone(),
                    })
                }
            }
        }
        if let Some(t) = &self.overlay_texture {
            painter.add(egui::Shape::mesh(slice_mesh(
                t.texture.id(),
                image_rect,
                image.inside_fraction,
                image.request.frame,
            )));
        }
    }

    /// The overlay's value at the slice pixel under `index` (level-0 continuous), if sampled.
    pub fn overlay_value_at(
        &self,
        overlay: &Overlay,
        index: [f64; 3],
        image: &SliceImage,
    ) -> Option<f32> {
        let slice = overlay
            .latest(self.view)
            .filter(|s| s.request == image.request && s.width == image.width)?;
        let frame = image.request.frame;
        let scale = (1u64 << image.request.level) as f64;
        let pixel = |axis: usize| ((index[axis] + 0.5) / scale - 0.5).round();
        let (x, y) = (pixel(frame.across_axis), pixel(frame.down_axis));
        if x < 0.0 || y < 0.0 || x as usize >= slice.width || y as usize >= slice.height {
            return None;
        }
        slice
            .values
            .get(y as usize * slice.width + x as usize)
            .copied()
            .filter(|v| v.is_finite())
    }

    pub fn ui(
        &mut self,
        ui: &mut egui::Ui,
        rect: Rect,
        data: &VolumeData,
        scene: &mut Scene,
        overlay: Option<&Overlay>,
        mut segmentation: Option<&mut Segmentation>,
    ) -> ViewResponse {
        let view = self.view;
        let frame = data.frame(view);
        let geometry = &data.info.geometry;
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
        // The image keeps the patient's proportions, centred with room for the title line
        // above, the W/L line below and the side labels; zoomed and panned.
        let inner = inner_rect(rect);
        let response = ui.interact(
            rect,
            ui.scope_id().with(("slice", view.index())),
            Sense::click_and_drag(),
        );
        // Ctrl+wheel (or pinch) zooms about the pointer (plain wheel pages, below), middle
        // drag pans, a double-click resets.
        let double_clicked = self.zoom_pan.input(ui, &response, inner);
        if double_clicked {
            if let Some(cursor) = self.cursor_before_click.take() {
                scene.cursor = cursor;
            }
        }
        let image_rect = self.zoom_pan.image_rect(inner, frame.extent_mm(geometry));

        let tool = scene.measurements.tool;
        let painting = segmentation.as_ref().is_some_and(|s| s.tool.paints());
        if let Some(seg) = segmentation.as_deref_mut().filter(|_| painting) {
            self.brush_input(ui, &response, image_rect, data, scene, seg);
        } else if tool != Tool::Navigate {
            let context = self.measure_context(data, scene);
            let shown = data.slices.latest(self.view);
            slice_input(
                ui,
                &response,
                image_rect,
                &context,
                &mut scene.measurements,
                shown.as_ref(),
            );
        } else if let Some(pos) = response.interact_pointer_pos().filter(|_| !double_clicked) {
            if (response.clicked() || response.dragged_by(egui::PointerButton::Primary))
                && image_rect.contains(pos)
            {
                self.cursor_before_click = response.clicked().then_some(scene.cursor);
                let (u, w) = fraction_at(image_rect, pos);
                let (a, d) = frame.index_at(dims, u, w);
                scene.cursor[frame.across_axis] =
                    a.clamp(0.0, dims[frame.across_axis] as f64 - 1.0);
                scene.cursor[frame.down_axis] = d.clamp(0.0, dims[frame.down_axis] as f64 - 1.0);
            }
        }
        if response.dragged_by(egui::PointerButton::Secondary) {
            let delta = ui.input(|i| i.pointer.delta());
            scene.window = drag_window(scene.window, delta, data.info.physical_range);
        }
        if response.hovered() && !ui.input(|i| i.modifiers.command || i.modifiers.ctrl) {
            // Whole lines page; fractions (touchpads, pixel-precise wheels) add up, so every
            // wheel click pages the same one slice however the events are split.
            self.wheel_lines += wheel_lines(ui);
            let step = self.wheel_lines.trunc();
            if step != 0.0 {
                self.wheel_lines -= step;
                // Wheel up (content moves down) goes towards higher slice numbers, as in Slicer.
                data.page_slice(scene, view, step);
            }
        } else {
            self.wheel_lines = 0.0;
        }
        let focused = response.clicked()
            || response.drag_started()
            || response.hovered() && ui.input(|i| i.pointer.any_pressed());

        // Ask for the slice at the level matching this view's pixels.
        let ppp = ui.ctx().pixels_per_point();
        let voxels_across = dims[frame.across_axis] as f64;
        let level_count = data.info.header.layout.level_count();
        let level = level_for_pixels(
            voxels_across,
            (image_rect.width() * ppp) as f64,
            level_count,
        );
        let request = SliceRequest {
            view,
            frame,
            position: scene.cursor[frame.normal_axis],
            level,
        };
        if self.last_request != Some(request) {
            data.slices.request(request);
            self.last_request = Some(request);
        }
        if let Some(image) = data.slices.latest(view) {
            let stale = self.texture.as_ref().is_none_or(|t| {
                !Arc::ptr_eq(&t.values, &image.values)
                    || t.window != scene.window
                    || t.colour_map != scene.colour_map
            });
            if stale {
                let grey =
                    window_level_image(&image, scene.window, scene.colour_map, data.info.mapping);
                match &mut self.texture {
                    Some(t) => {
                        t.texture.set(grey, TextureOptions::LINEAR);
                        t.values = image.values.clone();
                        t.window = scene.window;
                        t.colour_map = scene.colour_map;
                    }
                    None => {
                        self.texture = Some(SliceTexture {
                            texture: ui.ctx().load_texture(
                                format!("slice {}", view.name()),
                                grey,
                                TextureOptions::LINEAR,
                            ),
                            values: image.values.clone(),
                            window: scene.window,
                            colour_map: scene.colour_map,
                        })
                    }
                }
            }
            if let Some(t) = &self.texture {
                painter.add(egui::Shape::mesh(slice_mesh(
                    t.texture.id(),
                    image_rect,
                    image.inside_fraction,
                    frame,
                )));
            }
            if let Some(o) = overlay {
                self.paint_overlay(ui, &painter, o, &image, image_rect);
            }
        }
        // Crosshair, measurements, orientation labels.
        let centre = screen_at(
            image_rect,
            frame.fraction_of(
                dims,
                scene.cursor[frame.across_axis],
                scene.cursor[frame.down_axis],
            ),
        );
        paint_crosshair(&painter, image_rect, centre);
        if let Some(seg) = segmentation.as_deref().filter(|s| s.tool.drags()) {
            if let Some(pos) = response.hover_pos().filter(|p| image_rect.contains(*p)) {
                // The image keeps the patient's proportions: one scale for both directions.
                let (across_mm, _) = frame.extent_mm(geometry);
                let radius = (seg.diameter_mm / 2.0 / across_mm) as f32 * image_rect.width();
                painter.circle_stroke(pos, radius, Stroke::new(1.0, Color32::WHITE));
            }
        }
        // Regions opened from a link (or drawn before their slice came) get their statistics
        // from the slice once it is shown.
        if let Some(image) = data.slices.latest(view) {
            scene.measurements.fill_missing_stats(
                view,
                &image,
                &data.info.geometry,
                data.info.mapping,
            );
        }
        let context = self.measure_context(data, scene);
        paint_on_slice(
            &painter,
            image_rect,
            &context,
            &scene.measurements,
            &data.unit(),
        );
        paint_orientation_labels(&painter, rect, frame.labels);
        let n = frame.normal_axis;
        let slice_number = voxel_index(scene.cursor)[n] + 1;
        let title = format!("{} {}/{}", view.name(), slice_number, dims[n]);
        let toggled = view_title(ui, rect, view.name(), &title, colour);
        let shown_level = data.slices.latest(view).map(|i| i.request.level);
        let info = format!(
            "W {:.0} L {:.0}{}",
            scene.window.width,
            scene.window.centre,
            shown_level
                .filter(|l| *l > 0)
                .map(|l| format!(" · level {l}"))
                .unwrap_or_default()
        );
        paint_readout_line(&painter, rect, info);
        let hover = response
            .hover_pos()
            .filter(|p| image_rect.contains(*p))
            .map(|p| self.index_at(p, image_rect, data, scene));
        self.image_rect = Some(image_rect);
        ViewResponse {
            toggle_focus: toggled,
            focused,
            hover,
        }
    }
}

/// Left button with the brush or eraser over an image drawn in `image_rect`: a press starts a
/// stroke at the press position, a drag sweeps it on to each new pointer position, the release
/// ends it (one edit); a click paints one disc. With fill or grow, a click is the seed.
/// `to_lps` takes a screen point to patient space, `plane` gives the brush's plane through a
/// patient point; the slice views and the oblique view share this, so a stroke is the same
/// gesture in every view.
pub(crate) fn segment_pointer_input(
    ui: &egui::Ui,
    response: &egui::Response,
    image_rect: Rect,
    seg: &mut Segmentation,
    to_lps: &dyn Fn(Pos2) -> DVec3,
    plane: &dyn Fn(DVec3) -> SlicePlane,
) {
    if !seg.tool.drags() {
        // Fill and grow: a click is the seed.
        if response.clicked_by(egui::PointerButton::Primary) {
            if let Some(pos) = response
                .interact_pointer_pos()
                .filter(|p| image_rect.contains(*p))
            {
                let p = to_lps(pos);
                let ctx = ui.ctx().clone();
                seg.click_at(plane(p), p, Arc::new(move || ctx.request_repaint()));
            }
        }
        return;
    }
    let stroke_to = |seg: &mut Segmentation, pos: Pos2| {
        let p = to_lps(pos);
        seg.stroke_to(plane(p), p);
    };
    if response.drag_started_by(egui::PointerButton::Primary) {
        if let Some(origin) = ui
            .input(|i| i.pointer.press_origin())
            .filter(|p| image_rect.contains(*p))
        {
            stroke_to(seg, origin);
        }
    }
    if response.dragged_by(egui::PointerButton::Primary) && seg.stroke_in_progress() {
        if let Some(pos) = response.interact_pointer_pos() {
            stroke_to(seg, pos);
        }
    }
    if response.drag_stopped_by(egui::PointerButton::Primary) {
        seg.end_stroke();
    }
    if response.clicked_by(egui::PointerButton::Primary) {
        if let Some(pos) = response
            .interact_pointer_pos()
            .filter(|p| image_rect.contains(*p))
        {
            stroke_to(seg, pos);
            seg.end_stroke();
        }
    }
}

/// Right drag: strata-slices' window gesture (shared with the browser viewer), from egui's
/// pointer delta.
pub fn drag_window(window: Window, delta: Vec2, physical_range: (f64, f64)) -> Window {
    strata_slices::drag_window(window, delta.x as f64, delta.y as f64, physical_range)
}

/// Stored values → colours through the window (physical units) and the colour map, as a
/// texture image: strata-slices' image step, which the browser viewer uses too. (The drag
/// gesture's test lives with it in strata-slices.)
pub fn window_level_image(
    image: &SliceImage,
    window: Window,
    colour_map: ColourMap,
    mapping: strata_render::ValueMapping,
) -> egui::ColorImage {
    let rgba = strata_slices::window_level_rgba(&image.values, window, colour_map, mapping);
    egui::ColorImage::from_rgba_unmultiplied([image.width, image.height], &rgba)
}
