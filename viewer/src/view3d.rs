//! The 3D view: its camera and mouse handling (orbit: left drag; pan: middle or shift+left;
//! zoom: wheel; TF shift/widen: right drag), the six standard views, the render request it
//! sends, the frame it shows, the slice-plane outlines and the orientation marker.
//!
//! Picking, outlines, measurements, the crop box and the orientation marker are drawn with the
//! shown frame's camera (`View3d::overlay_camera`), not the live orbit's: the frame on screen may
//! be a request or two behind the mouse.

use std::time::{Duration, Instant};

use egui::{Color32, Pos2, Rect, Sense, Stroke, TextureHandle, TextureOptions, Vec2};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use strata_render::{Camera, Projection, RenderMode, RenderSettings, VolumeGeometry};
use strata_viewer_ui::picking;
use strata_viewer_ui::picking::project_to_view;
use strata_viewer_ui::render_driver::{OverlayIn3d, RenderRequest};

use super::oblique::OBLIQUE_COLOUR;
use super::orientation::SliceView;
use super::preferences::Preferences;
use super::scene::{Scene, VolumeData};
use super::segmentation::{SegmentTool, Segmentation};
use super::slice_view::slice_colour;
use super::volume_session::RenderedFrame;
use super::widgets::{view_title, wheel_lines, ViewResponse, NOT_FOR_DIAGNOSIS, WARNING_COLOUR};
use strata_slices::oblique::ObliquePlane;
use strata_viewer_ui::measurements::Tool;

/// Zoom factor per wheel click in the 3D view.
pub const ZOOM_PER_WHEEL_LINE: f64 = 1.1;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OrbitCamera {
    /// Degrees about the patient's superior axis; 0 looks at the patient's face (anterior view).
    pub azimuth_deg: f64,
    /// Degrees towards superior, within ±90.
    pub elevation_deg: f64,
    /// 1 frames the whole volume.
    pub zoom: f64,
    /// Target offset in the view plane, in units of the volume's bounding radius.
    pub pan: [f64; 2],
    pub orthographic: bool,
}

impl Default for OrbitCamera {
    fn default() -> Self {
        OrbitCamera {
            azimuth_deg: 30.0,
            elevation_deg: 15.0,
            zoom: 1.0,
            pan: [0.0, 0.0],
            orthographic: false,
        }
    }
}

use strata_viewer_ui::orbit::StandardView;

impl OrbitCamera {
    pub fn standard(view: StandardView, orthographic: bool) -> Self {
        let (azimuth_deg, elevation_deg) = view.angles_deg();
        OrbitCamera {
            azimuth_deg,
            elevation_deg,
            zoom: 1.0,
            pan: [0.0, 0.0],
            orthographic,
        }
    }

    /// The camera this orbit shows: [`Camera::orbit_panned`], the one definition a shared
    /// link's view (strata_viewer_ui::view_state) also uses.
    pub fn camera(&self, geometry: &VolumeGeometry) -> Camera {
        let projection = if self.orthographic {
            // orbit_panned sizes the height from the zoom.
            Projection::Orthographic { height_mm: 1.0 }
        } else {
            Projection::Perspective { fov_y_deg: 30.0 }
        };
        Camera::orbit_panned(
            geometry,
            self.azimuth_deg,
            self.elevation_deg,
            self.zoom,
            self.pan,
            projection,
        )
    }

    /// Orbit by a drag of `delta` points in a view `size` points tall.
    pub fn orbit_by(&mut self, delta: Vec2, size: Vec2) {
        (self.azimuth_deg, self.elevation_deg) = strata_viewer_ui::orbit::orbit_by_drag(
            self.azimuth_deg,
            self.elevation_deg,
            [delta.x as f64, delta.y as f64],
            size.y as f64,
        );
    }

    pub fn pan_by(&mut self, delta: Vec2, size: Vec2) {
        // A drag across the full view height moves the scene by one bounding diameter at zoom 1.
        let per_point = 2.0 / size.y.max(1.0) as f64 / self.zoom;
        self.pan[0] -= delta.x as f64 * per_point;
        self.pan[1] += delta.y as f64 * per_point;
    }

    /// Wheel: `lines` clicks (positive = away from the user = zoom in), 10 % per click, as
    /// Slicer's 3D view (egui's smoothed scroll in points made 3 clicks zoom ~4×).
    pub fn zoom_by_lines(&mut self, lines: f64) {
        self.zoom = (self.zoom * ZOOM_PER_WHEEL_LINE.powf(lines)).clamp(0.2, 20.0);
    }
}

/// The texture showing the newest volume frame and the frame's serial (re-uploaded only when
/// a newer frame arrives).
struct FrameTexture {
    texture: TextureHandle,
    serial: u64,
    /// The mode the uploaded frame was drawn in: after a switch it is not painted until a
    /// frame of the new mode replaces it.
    mode: RenderMode,
}

/// Whether a frame drawn in `drawn` may stand on screen for a view showing `shown`: only the
/// same mode. After a DVR→MIP switch the DVR frame stayed up (or a stand-in DVR image came
/// under the MIP title) for 1-5 s on lavapipe (issue 36); an empty view that says what it is
/// rendering is the honest picture until the new mode's first frame.
pub fn frame_fits_mode(drawn: RenderMode, shown: RenderMode) -> bool {
    drawn == shown
}

/// The 3D view's own state.
pub struct View3d {
    pub orbit: OrbitCamera,
    texture: Option<FrameTexture>,
    /// The frame on screen (its depth and camera turn a pixel into a picked point).
    shown: Option<RenderedFrame>,
    /// Until when input counts as interaction (lower resolution, target frame rate held).
    pub interacting_until: Option<Instant>,
    /// Render at the screen's full pixel density (a screenshot is being taken).
    pub full_resolution: bool,
    /// The frame size asked for last.
    requested_size: [u32; 2],
    /// The mode of the image painted in the last pass; None: the view was left empty (no
    /// frame yet, or only frames of another mode).
    #[cfg_attr(not(test), allow(dead_code))]
    painted: Option<RenderMode>,
    /// The camera of the frame painted in the last pass and the one its overlays (outlines,
    /// measurements, crop box, marker) were projected with: the motion rule's test compares them.
    #[cfg_attr(not(test), allow(dead_code))]
    painted_camera: Option<Camera>,
    #[cfg_attr(not(test), allow(dead_code))]
    overlays_camera: Option<Camera>,
}

impl View3d {
    /// The readers changed (another frame of a 4-D volume): the next frame they publish is
    /// uploaded whatever its serial (serials count per render session).
    pub fn forget_frame(&mut self) {
        if let Some(t) = &mut self.texture {
            t.serial = u64::MAX;
        }
    }
}

/// A short name of the render mode for titles (new modes add a line here).
pub fn mode_name(mode: RenderMode) -> &'static str {
    match mode {
        RenderMode::Dvr => "DVR",
        RenderMode::Mip => "MIP",
        RenderMode::Isosurface => "Isosurface",
    }
}

impl View3d {
    pub fn new(orbit: OrbitCamera) -> Self {
        View3d {
            orbit,
            texture: None,
            shown: None,
            interacting_until: None,
            full_resolution: false,
            requested_size: [0, 0],
            painted: None,
            painted_camera: None,
            overlays_camera: None,
        }
    }

    pub fn reset(&mut self, orthographic: bool) {
        self.orbit = OrbitCamera {
            orthographic,
            ..OrbitCamera::default()
        };
    }

    /// The view shows the converged frame of the size it asks for now (a screenshot may go).
    pub fn shows_converged_frame(&self) -> bool {
        self.shown.as_ref().is_some_and(|f| {
            f.converged
                && [f.width, f.height] == self.requested_size
                && [f.request.settings.width, f.request.settings.height] == self.requested_size
        })
    }

    /// The mode of the image the last pass painted (None: none painted).
    #[cfg(test)]
    pub fn painted_mode(&self) -> Option<RenderMode> {
        self.painted
    }

    /// The camera of the image the last pass painted, and the one it drew the overlays with.
    #[cfg(test)]
    pub fn painted_and_overlay_cameras(&self) -> (Option<Camera>, Option<Camera>) {
        (self.painted_camera, self.overlays_camera)
    }

    /// The pixel size of the frames this view asks for at full resolution.
    pub fn full_resolution_size(rect: Rect, pixels_per_point: f32) -> [u32; 2] {
        [
            ((rect.width() * pixels_per_point).round() as u32).max(16),
            ((rect.height() * pixels_per_point).round() as u32).max(16),
        ]
    }

    /// What the user sees at screen point `pos` of the view drawn in `rect`: the level-0
    /// continuous index at the frame's pick depth (DVR: where the accumulated opacity reaches
    /// render's `DEPTH_OPACITY`; MIP: the maximum; iso: the surface), or None where the ray
    /// meets nothing. Uses the frame on screen and the camera it was rendered with, so a
    /// click picks what is shown even while a newer frame renders.
    pub fn pick(&self, pos: Pos2, rect: Rect, data: &VolumeData) -> Option<[f64; 3]> {
        let frame = self.shown.as_ref()?;
        let size = [frame.width, frame.height];
        let pixel = picking::frame_pixel(
            (pos.x - rect.left()) / rect.width().max(1.0),
            (pos.y - rect.top()) / rect.height().max(1.0),
            size,
        )?;
        let depth_mm = *frame
            .depth
            .get((pixel[1] * frame.width + pixel[0]) as usize)?;
        picking::picked_index(
            &frame.request.camera,
            &data.info.geometry,
            pixel,
            size,
            depth_mm,
        )
    }

    /// The segment tools in 3D: the brush and eraser sweep a ball of the brush's diameter
    /// through the surface points picked along a drag (a click: one ball), one undo step per
    /// stroke; the grow tool seeds at the picked point. A ray that meets nothing edits nothing.
    fn segment_input(
        &self,
        ui: &egui::Ui,
        response: &egui::Response,
        rect: Rect,
        data: &VolumeData,
        seg: &mut Segmentation,
    ) {
        let g = &data.info.geometry;
        let picked = |pos: Pos2| {
            self.pick(pos, rect, data)
                .map(|index| g.patient_from_index(DVec3::from(index)))
        };
        let primary = egui::PointerButton::Primary;
        if seg.tool == SegmentTool::Grow {
            if response.clicked_by(primary) {
                if let Some(p) = response.interact_pointer_pos().and_then(picked) {
                    let ctx = ui.ctx().clone();
                    // The grow is 3D: the plane is not used.
                    seg.click_at(
                        strata_segment::tools::brush::SlicePlane::Axial,
                        p,
                        std::sync::Arc::new(move || ctx.request_repaint()),
                    );
                }
            }
            return;
        }
        if response.drag_started_by(primary) {
            if let Some(p) = ui.input(|i| i.pointer.press_origin()).and_then(picked) {
                seg.sphere_stroke_to(p);
            }
        }
        if response.dragged_by(primary) {
            if let Some(p) = response.interact_pointer_pos().and_then(picked) {
                seg.sphere_stroke_to(p);
            }
        }
        if response.drag_stopped_by(primary) {
            seg.end_stroke();
        }
        if response.clicked_by(primary) {
            if let Some(p) = response.interact_pointer_pos().and_then(picked) {
                seg.sphere_stroke_to(p);
                seg.end_stroke();
            }
        }
    }

    /// The brush's ball as the cursor: a circle of its projected size around the pointer where
    /// the pointer picks a surface point.
    fn paint_ball_cursor(
        &self,
        painter: &egui::Painter,
        pos: Pos2,
        rect: Rect,
        data: &VolumeData,
        diameter_mm: f64,
    ) {
        let (Some(index), Some(frame)) = (self.pick(pos, rect, data), self.shown.as_ref()) else {
            return;
        };
        let g = &data.info.geometry;
        let camera = frame.request.camera;
        let centre = DVec3::from(index);
        let edge_lps = g.patient_from_index(centre) + camera.basis().right * (diameter_mm / 2.0);
        let (Some(a), Some(b)) = (
            project_to_view(&camera, rect, g, centre),
            project_to_view(&camera, rect, g, g.index_from_patient(edge_lps)),
        ) else {
            return;
        };
        painter.circle_stroke(pos, a.distance(b), Stroke::new(1.5, Color32::YELLOW));
    }

    /// The camera to draw the overlays (slice outlines, measurements, crop box, orientation
    /// marker) with: the shown frame's, which may lag `live` (the orbit's now) while the render
    /// thread catches up; `live` before any frame.
    pub fn overlay_camera(&self, live: Camera) -> Camera {
        self.shown
            .as_ref()
            .map_or(live, |frame| frame.request.camera)
    }

    /// Draws the view into `rect`, turns input into camera and TF changes and sends the render
    /// request for this frame, with the overlay to draw in 3D (`overlay`, overlay_3d.rs).
    #[allow(clippy::too_many_arguments)]
    pub fn ui(
        &mut self,
        ui: &mut egui::Ui,
        rect: Rect,
        data: &VolumeData,
        scene: &mut Scene,
        prefs: &Preferences,
        max_pixels: u32,
        overlay: Option<OverlayIn3d>,
        oblique: Option<ObliquePlane>,
        segmentation: Option<&mut Segmentation>,
    ) -> ViewResponse {
        let painter = ui.painter_at(rect);
        painter.rect_filled(rect, 0.0, Color32::BLACK);
        let response = ui.interact(rect, ui.scope_id().with("3d view"), Sense::click_and_drag());
        let (shift, pointer_delta) = ui.input(|i| (i.modifiers.shift, i.pointer.delta()));
        // With the brush, eraser or grow chosen the left button edits labels here (shift-drag
        // still pans, the other buttons and the wheel still orbit, window and zoom).
        let segment_tool = segmentation
            .as_ref()
            .map_or(SegmentTool::None, |s| s.tool)
            .filter_3d();
        let mut moved = false;
        if response.dragged_by(egui::PointerButton::Primary)
            && !shift
            && segment_tool == SegmentTool::None
        {
            self.orbit.orbit_by(pointer_delta, rect.size());
            moved = true;
        }
        if response.dragged_by(egui::PointerButton::Middle)
            || (response.dragged_by(egui::PointerButton::Primary) && shift)
        {
            self.orbit.pan_by(pointer_delta, rect.size());
            moved = true;
        }
        if response.dragged_by(egui::PointerButton::Secondary) {
            let (lo, hi) = data.info.physical_range;
            let shift_value = pointer_delta.x as f64 / rect.width().max(1.0) as f64 * (hi - lo);
            let scale = (-pointer_delta.y as f64 / rect.height().max(1.0) as f64 * 2.0).exp();
            strata_viewer_ui::tf_editor::shift_and_scale(
                &mut scene.transfer_function,
                shift_value,
                scale,
            );
            moved = true;
        }
        if response.hovered() {
            let lines = wheel_lines(ui);
            if lines != 0.0 {
                self.orbit.zoom_by_lines(lines);
                moved = true;
            }
        }
        if response.double_clicked() {
            self.reset(prefs.orthographic);
        }
        if moved {
            self.interacting_until = Some(Instant::now() + Duration::from_millis(150));
        }
        let interacting = self.interacting_until.is_some_and(|t| t > Instant::now());
        if interacting {
            ui.ctx().request_repaint_after(Duration::from_millis(160));
        }

        scene.name_tf_edits();
        // Request a frame at the view's aspect.
        let ppp = ui.ctx().pixels_per_point();
        let mut scale = prefs.render_scale.clamp(0.2, 1.0) * ppp;
        if self.full_resolution {
            // A screenshot: one ray per screen pixel, whatever the interactive settings.
            scale = ppp;
        } else {
            if interacting && prefs.target_fps_enabled {
                // While dragging, fewer pixels: the controller then keeps a higher sampling rate.
                scale *= 0.5;
            }
            let longest = rect.width().max(rect.height()) * scale;
            if longest > max_pixels as f32 {
                scale *= max_pixels as f32 / longest;
            }
        }
        let width = ((rect.width() * scale).round() as u32).max(16);
        let height = ((rect.height() * scale).round() as u32).max(16);
        self.requested_size = [width, height];
        let camera = self.orbit.camera(&data.info.geometry);
        let clip_plane = scene.clip.plane_if_enabled(&data.info.geometry);
        let mut settings = RenderSettings {
            width,
            height,
            mode: prefs.mode,
            quality: prefs.step_voxels,
            smooth_transitions: prefs.smooth_transitions,
            iso_value: scene.iso_value,
            crop: scene.crop,
            clip_plane,
            ..RenderSettings::default()
        };
        super::preferences::render_lighting(prefs).apply_to(&mut settings);
        data.session.request(RenderRequest {
            camera,
            settings,
            transfer_function: scene.transfer_function.clone(),
            target_fps: prefs.target_fps_enabled.then_some(prefs.target_fps),
            interacting,
            overlay,
            traversal: prefs.traversal.traversal(),
            adaptive_epsilon: prefs.adaptive_sampling.then_some(prefs.adaptive_epsilon),
            progressive_frames: prefs.progressive_frames,
        });

        if self
            .shown
            .as_ref()
            .is_some_and(|f| !frame_fits_mode(f.drawn_mode, prefs.mode))
        {
            // Picks and the overlay camera must not use the previous mode's frame either.
            self.shown = None;
        }
        let mut waiting_for_mode = true;
        self.painted = None;
        self.painted_camera = None;
        if let Some(frame) = data
            .session
            .latest_frame()
            .filter(|f| frame_fits_mode(f.drawn_mode, prefs.mode))
        {
            let fresh = self
                .texture
                .as_ref()
                .is_none_or(|t| t.serial != frame.serial);
            if fresh {
                self.shown = Some(frame.clone());
            }
            if fresh {
                let image = egui::ColorImage::from_rgba_premultiplied(
                    [frame.width as usize, frame.height as usize],
                    &frame.rgba,
                );
                match &mut self.texture {
                    Some(t) => {
                        t.texture.set(image, TextureOptions::LINEAR);
                        t.serial = frame.serial;
                        t.mode = frame.drawn_mode;
                    }
                    None => {
                        self.texture = Some(FrameTexture {
                            texture: ui
                                .ctx()
                                .load_texture("volume", image, TextureOptions::LINEAR),
                            serial: frame.serial,
                            mode: frame.drawn_mode,
                        })
                    }
                }
            }
            if let Some(t) = self
                .texture
                .as_ref()
                .filter(|t| frame_fits_mode(t.mode, prefs.mode))
            {
                waiting_for_mode = false;
                self.painted = Some(t.mode);
                self.painted_camera = self.shown.as_ref().map(|f| f.request.camera);
                painter.image(
                    t.texture.id(),
                    rect,
                    Rect::from_min_max(Pos2::ZERO, Pos2::new(1.0, 1.0)),
                    Color32::WHITE,
                );
            }
        }
        // Everything drawn over the image uses the camera the image was rendered with, so
        // outlines, crosshair and measurements stay on the structures while the image lags the
        // orbit (issue 36: outlines had already rotated over the old image).
        let camera = self.overlay_camera(camera);
        self.overlays_camera = Some(camera);
        if prefs.show_planes_in_3d {
            paint_slice_planes(&painter, rect, &camera, data, scene, oblique.as_ref());
        }
        // The rulers and angles both viewers draw (strata_viewer_ui::measurements).
        strata_viewer_ui::measurements::paint_in_3d(
            &painter,
            rect,
            &camera,
            &data.info.geometry,
            &data.unit(),
            &scene.measurements,
        );
        if prefs.show_crop_box && crop_box_ui(ui, &painter, rect, &camera, data, scene) {
            self.interacting_until = Some(Instant::now() + Duration::from_millis(150));
        }
        // The triad both viewers draw (strata_viewer_ui::triad).
        strata_viewer_ui::triad::paint_triad(&painter, rect, &camera);
        let status = data.session.status();
        let toggled = view_title(
            ui,
            rect,
            "3d",
            &format!(
                "3D · {} · {}",
                mode_name(prefs.mode),
                scene.transfer_function.name
            ),
            Color32::from_rgb(200, 200, 255),
        );
        let mut right_lines = Vec::new();
        if waiting_for_mode && status.loading.is_none() && status.error.is_none() {
            // The view is empty until the mode's first frame (see `frame_fits_mode`): say why.
            right_lines.push(format!("rendering {}…", mode_name(prefs.mode)));
        }
        if let Some(loading) = &status.loading {
            right_lines.push(loading.clone());
        } else if status.refining {
            right_lines.push(status.refining_line());
        }
        if let Some(level) = status.finest_resident_level {
            right_lines.push(format!("finest level {level}"));
        }
        if let Some(exporting) = &status.exporting {
            // Why the view is not redrawn for seconds at a time while a movie renders.
            right_lines.push(exporting.clone());
        }
        let font = egui::FontId::proportional(12.0);
        for (i, line) in right_lines.iter().enumerate() {
            // The first line shares its row with the view's title; the others have the width.
            let room = if i == 0 {
                rect.width() * 0.5
            } else {
                rect.width() - 16.0
            };
            painter.text(
                Pos2::new(rect.right() - 8.0, rect.top() + 4.0 + 15.0 * i as f32),
                egui::Align2::RIGHT_TOP,
                super::widgets::fit_line(&painter, line, &font, room),
                font.clone(),
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
        if let Some(seg) = segmentation.filter(|_| segment_tool != SegmentTool::None) {
            if !shift {
                self.segment_input(ui, &response, rect, data, seg);
            }
            if let Some(pos) = response.hover_pos() {
                self.paint_ball_cursor(&painter, pos, rect, data, seg.diameter_mm);
            }
        }
        // A click (no drag) moves the linked crosshair to what is seen there, or adds a ruler
        // or angle point there with a measuring tool.
        if response.clicked() && segment_tool == SegmentTool::None {
            if let Some(index) = response
                .interact_pointer_pos()
                .and_then(|p| self.pick(p, rect, data))
            {
                match scene.measurements.tool {
                    Tool::Distance | Tool::Angle => scene.measurements.click(index),
                    _ => scene.cursor = index,
                }
            }
        }
        let hover = response.hover_pos().and_then(|p| self.pick(p, rect, data));
        ViewResponse {
            toggle_focus: toggled,
            focused: response.clicked() || response.drag_started(),
            hover,
        }
    }
}

/// A crop-box face handle: the index axis it moves, which end, and where it is drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CropHandle {
    pub axis: usize,
    pub max_side: bool,
    /// The face's anatomical direction (R/L, A/P, S/I).
    pub label: &'static str,
    pub at: Pos2,
}

/// The crop box's corners in level-0 index space (voxel faces, not centres).
fn crop_bounds(data: &VolumeData, scene: &Scene) -> ([f64; 3], [f64; 3]) {
    let dims = data.info.geometry.dims;
    let lo = [0, 1, 2].map(|a| scene.crop.min[a] as f64 * dims[a] as f64 - 0.5);
    let hi = [0, 1, 2].map(|a| scene.crop.max[a] as f64 * dims[a] as f64 - 0.5);
    (lo, hi)
}

/// The six face handles of the crop box on screen (None behind the eye).
pub fn crop_handles(
    rect: Rect,
    camera: &Camera,
    data: &VolumeData,
    scene: &Scene,
) -> Vec<CropHandle> {
    let g = &data.info.geometry;
    let (lo, hi) = crop_bounds(data, scene);
    let mut handles = Vec::new();
    for axis in 0..3 {
        for max_side in [false, true] {
            let mut centre = [0.0; 3];
            for a in 0..3 {
                centre[a] = (lo[a] + hi[a]) * 0.5;
            }
            centre[axis] = if max_side { hi[axis] } else { lo[axis] };
            let outward = DVec3::from(g.direction[axis]) * if max_side { 1.0 } else { -1.0 };
            if let Some(at) = project_to_view(camera, rect, g, DVec3::from(centre)) {
                handles.push(CropHandle {
                    axis,
                    max_side,
                    label: super::orientation::label_of(outward),
                    at,
                });
            }
        }
    }
    handles
}

/// Draws the crop box (12 edges) and its face handles; dragging a handle moves that face
/// along its axis by the pointer's motion along the axis's screen direction. True while a
/// handle is dragged.
fn crop_box_ui(
    ui: &mut egui::Ui,
    painter: &egui::Painter,
    rect: Rect,
    camera: &Camera,
    data: &VolumeData,
    scene: &mut Scene,
) -> bool {
    let g = &data.info.geometry;
    let (lo, hi) = crop_bounds(data, scene);
    let corner = |c: usize| {
        DVec3::new(
            if c & 1 == 0 { lo[0] } else { hi[0] },
            if c & 2 == 0 { lo[1] } else { hi[1] },
            if c & 4 == 0 { lo[2] } else { hi[2] },
        )
    };
    let colour = Color32::from_rgb(120, 220, 255);
    let stroke = Stroke::new(1.2, colour.gamma_multiply(0.8));
    for c in 0..8usize {
        for bit in [1usize, 2, 4] {
            if c & bit == 0 {
                if let (Some(a), Some(b)) = (
                    project_to_view(camera, rect, g, corner(c)),
                    project_to_view(camera, rect, g, corner(c | bit)),
                ) {
                    painter.line_segment([a, b], stroke);
                }
            }
        }
    }
    let mut dragging = false;
    let dims = g.dims;
    for handle in crop_handles(rect, camera, data, scene) {
        let id = ui
            .scope_id()
            .with(("crop handle", handle.axis, handle.max_side));
        let response = ui.interact(
            Rect::from_center_size(handle.at, Vec2::splat(14.0)),
            id,
            Sense::drag(),
        );
        let radius = if response.hovered() || response.dragged() {
            7.0
        } else {
            5.0
        };
        painter.circle_filled(handle.at, radius, colour);
        painter.text(
            handle.at + Vec2::new(8.0, -8.0),
            egui::Align2::LEFT_BOTTOM,
            handle.label,
            egui::FontId::proportional(12.0),
            colour,
        );
        if response.dragged() {
            dragging = true;
            // The screen motion of one voxel along the axis, from this face's centre.
            let mut centre = [0.0; 3];
            for a in 0..3 {
                centre[a] = (lo[a] + hi[a]) * 0.5;
            }
            centre[handle.axis] = if handle.max_side {
                hi[handle.axis]
            } else {
                lo[handle.axis]
            };
            let mut next = centre;
            next[handle.axis] += 1.0;
            let (Some(p0), Some(p1)) = (
                project_to_view(camera, rect, g, DVec3::from(centre)),
                project_to_view(camera, rect, g, DVec3::from(next)),
            ) else {
                continue;
            };
            let per_voxel = p1 - p0;
            if per_voxel.length_sq() < 1e-6 {
                continue; // looking straight along the axis: no sensible motion
            }
            let voxels = response.drag_delta().dot(per_voxel) / per_voxel.length_sq();
            let fraction = voxels as f64 / dims[handle.axis] as f64;
            let (min, max) = (
                &mut scene.crop.min[handle.axis],
                &mut scene.crop.max[handle.axis],
            );
            if handle.max_side {
                *max = (*max as f64 + fraction).clamp(*min as f64 + 0.01, 1.0) as f32;
            } else {
                *min = (*min as f64 + fraction).clamp(0.0, *max as f64 - 0.01) as f32;
            }
        }
    }
    dragging
}

/// Outlines where the three slice views cut the volume, projected with the 3D view's camera
/// (the frame fills `rect`, rendered at its aspect).
fn paint_slice_planes(
    painter: &egui::Painter,
    rect: Rect,
    camera: &Camera,
    data: &VolumeData,
    scene: &Scene,
    oblique: Option<&ObliquePlane>,
) {
    let g = &data.info.geometry;
    let project = |index: DVec3| project_to_view(camera, rect, g, index);
    let (lo, hi) = crop_bounds(data, scene);
    if let Some(plane) = oblique {
        // The oblique view's plane as the orthogonal ones are drawn: the part of it inside the
        // crop box and the oblique image's square (issue 36: it was not drawn at all).
        let outline = oblique_outline(plane, g, lo, hi);
        let points: Option<Vec<Pos2>> = outline.into_iter().map(project).collect();
        if let Some(points) = points.filter(|p| p.len() >= 3) {
            let stroke = Stroke::new(1.5, OBLIQUE_COLOUR.gamma_multiply(0.8));
            painter.add(egui::Shape::closed_line(points, stroke));
        }
    }
    for view in SliceView::ALL {
        let frame = data.frame(view);
        let Some(outline) = slice_outline(frame, scene.cursor, lo, hi) else {
            continue;
        };
        if let [Some(p0), Some(p1), Some(p2), Some(p3)] = outline.map(project) {
            let stroke = Stroke::new(1.5, slice_colour(view).gamma_multiply(0.8));
            painter.add(egui::Shape::closed_line(vec![p0, p1, p2, p3], stroke));
        }
    }
}

/// The outline (level-0 index space, in order around it) of the oblique plane's part inside
/// the crop box `lo`..`hi` (voxel faces) and inside the oblique image's square: the plane cut
/// by the box's 12 edges, then clipped to the square in the plane's own coordinates. Empty
/// when the plane misses the box.
pub fn oblique_outline(
    plane: &ObliquePlane,
    g: &VolumeGeometry,
    lo: [f64; 3],
    hi: [f64; 3],
) -> Vec<DVec3> {
    if (0..3).any(|a| lo[a] >= hi[a]) {
        return Vec::new();
    }
    let normal = plane.normal();
    let corner = |c: usize| {
        DVec3::new(
            if c & 1 == 0 { lo[0] } else { hi[0] },
            if c & 2 == 0 { lo[1] } else { hi[1] },
            if c & 4 == 0 { lo[2] } else { hi[2] },
        )
    };
    let distance = |index: DVec3| (g.patient_from_index(index) - plane.centre).dot(normal);
    // Plane coordinates (mm along right and down from the centre) of each crossing.
    let to_plane = |index: DVec3| {
        let d = g.patient_from_index(index) - plane.centre;
        (d.dot(plane.right), d.dot(plane.down))
    };
    // Corners on the plane, then the edges whose ends lie strictly on either side.
    let mut points: Vec<(f64, f64)> = (0..8usize)
        .map(corner)
        .filter(|c| distance(*c) == 0.0)
        .map(to_plane)
        .collect();
    for c in 0..8usize {
        for bit in [1usize, 2, 4] {
            if c & bit != 0 {
                continue;
            }
            let (a, b) = (corner(c), corner(c | bit));
            let (da, db) = (distance(a), distance(b));
            if (da < 0.0 && db > 0.0) || (da > 0.0 && db < 0.0) {
                points.push(to_plane(a + (b - a) * (da / (da - db))));
            }
        }
    }
    if points.len() < 3 {
        return Vec::new();
    }
    // Convex: ordered by angle about the centroid.
    let n = points.len() as f64;
    let mid = points
        .iter()
        .fold((0.0, 0.0), |m, p| (m.0 + p.0 / n, m.1 + p.1 / n));
    points.sort_by(|p, q| {
        (p.1 - mid.1)
            .atan2(p.0 - mid.0)
            .total_cmp(&(q.1 - mid.1).atan2(q.0 - mid.0))
    });
    // Clipped to the oblique image's square (Sutherland-Hodgman, four half-planes).
    let half = plane.extent_mm * 0.5;
    for (axis, sign) in [(0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)] {
        let inside = |p: &(f64, f64)| sign * if axis == 0 { p.0 } else { p.1 } <= half;
        let value = |p: &(f64, f64)| sign * if axis == 0 { p.0 } else { p.1 } - half;
        let mut clipped = Vec::with_capacity(points.len() + 1);
        for i in 0..points.len() {
            let (p, q) = (points[i], points[(i + 1) % points.len()]);
            if inside(&p) {
                clipped.push(p);
            }
            if inside(&p) != inside(&q) {
                let t = value(&p) / (value(&p) - value(&q));
                clipped.push((p.0 + (q.0 - p.0) * t, p.1 + (q.1 - p.1) * t));
            }
        }
        points = clipped;
        if points.len() < 3 {
            return Vec::new();
        }
    }
    points
        .into_iter()
        .map(|(u, w)| g.index_from_patient(plane.centre + plane.right * u + plane.down * w))
        .collect()
}

/// The four corners (level-0 index space) of a slice plane's outline, clipped to the crop box
/// `lo`..`hi` (voxel faces), as the raycaster clips the volume: the part of the slice that is
/// still drawn in 3D. None when the slice lies outside the box (nothing of it is shown).
pub fn slice_outline(
    frame: crate::orientation::SliceFrame,
    cursor: [f64; 3],
    lo: [f64; 3],
    hi: [f64; 3],
) -> Option<[DVec3; 4]> {
    let (n, a, b) = (frame.normal_axis, frame.across_axis, frame.down_axis);
    if cursor[n] < lo[n] || cursor[n] > hi[n] || lo[a] >= hi[a] || lo[b] >= hi[b] {
        return None;
    }
    let corner = |ca: f64, cb: f64| {
        let mut i = [0.0; 3];
        i[n] = cursor[n];
        i[a] = ca;
        i[b] = cb;
        DVec3::from(i)
    };
    Some([
        corner(lo[a], lo[b]),
        corner(hi[a], lo[b]),
        corner(hi[a], hi[b]),
        corner(lo[a], hi[b]),
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_frame_of_the_shown_mode_stands_on_screen() {
        use RenderMode::*;
        for drawn in [Dvr, Mip, Isosurface] {
            for shown in [Dvr, Mip, Isosurface] {
                assert_eq!(
                    frame_fits_mode(drawn, shown),
                    drawn == shown,
                    "{drawn:?} {shown:?}"
                );
            }
        }
    }

    #[test]
    fn slice_outlines_are_clipped_to_the_crop_box_and_vanish_outside_it() {
        let g = VolumeGeometry::axis_aligned([40, 30, 20], [1.0, 1.0, 1.0]);
        let axial = crate::orientation::SliceFrame::for_view(SliceView::Axial, &g);
        let full = ([-0.5; 3], [39.5, 29.5, 19.5]);
        let cursor = [10.0, 12.0, 7.0];
        let outline = slice_outline(axial, cursor, full.0, full.1).expect("inside");
        // Uncropped: the whole slice, at the cursor's k.
        for corner in outline {
            assert_eq!(corner.z, 7.0);
            assert!(corner.x == -0.5 || corner.x == 39.5);
            assert!(corner.y == -0.5 || corner.y == 29.5);
        }
        // Cropped to i 4.5..20.5, j 2.5..25.5, k 5.5..15.5: the outline follows the box.
        let (lo, hi) = ([4.5, 2.5, 5.5], [20.5, 25.5, 15.5]);
        let clipped = slice_outline(axial, cursor, lo, hi).expect("inside the box");
        let xs: Vec<f64> = clipped.iter().map(|c| c.x).collect();
        let ys: Vec<f64> = clipped.iter().map(|c| c.y).collect();
        assert_eq!(xs.iter().cloned().fold(f64::INFINITY, f64::min), 4.5);
        assert_eq!(xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max), 20.5);
        assert_eq!(ys.iter().cloned().fold(f64::INFINITY, f64::min), 2.5);
        assert_eq!(ys.iter().cloned().fold(f64::NEG_INFINITY, f64::max), 25.5);
        // The axial slice at k = 3 is cropped away: no outline.
        assert!(slice_outline(axial, [10.0, 12.0, 3.0], lo, hi).is_none());
    }

    #[test]
    fn the_oblique_outline_is_the_planes_part_inside_the_box_and_its_square() {
        let g = VolumeGeometry::axis_aligned([40, 30, 20], [1.0, 1.0, 1.0]);
        let (lo, hi) = ([-0.5; 3], [39.5, 29.5, 19.5]);
        // Axial, through k = 7, square large enough: the axial slice's outline.
        let centre = g.patient_from_index(DVec3::new(10.0, 12.0, 7.0));
        let axial = ObliquePlane::axial(centre, 200.0);
        let outline = oblique_outline(&axial, &g, lo, hi);
        assert_eq!(outline.len(), 4, "{outline:?}");
        let frame = crate::orientation::SliceFrame::for_view(SliceView::Axial, &g);
        let slice = slice_outline(frame, [10.0, 12.0, 7.0], lo, hi).expect("inside");
        for corner in slice {
            assert!(
                outline.iter().any(|p| (*p - corner).length() < 1e-6),
                "{corner} not in {outline:?}"
            );
        }
        // Tilted 30° about screen right: every point on the plane and on the box's surface.
        let tilted = axial.rotated(0.0, 30f64.to_radians());
        let outline = oblique_outline(&tilted, &g, lo, hi);
        assert!(outline.len() >= 4, "{outline:?}");
        for p in &outline {
            let off = (g.patient_from_index(*p) - tilted.centre).dot(tilted.normal());
            assert!(off.abs() < 1e-6, "{p} is {off} mm off the plane");
            let on_face =
                (0..3).any(|a| (p[a] - lo[a]).abs() < 1e-6 || (p[a] - hi[a]).abs() < 1e-6);
            assert!(on_face, "{p} is not on the box");
        }
        // A 10 mm square: the outline is the square itself, 10 mm across.
        let small = ObliquePlane {
            extent_mm: 10.0,
            ..tilted
        };
        let outline = oblique_outline(&small, &g, lo, hi);
        assert_eq!(outline.len(), 4, "{outline:?}");
        let widest = outline
            .iter()
            .flat_map(|a| outline.iter().map(move |b| (*a - *b).length()))
            .fold(0.0, f64::max);
        assert!((widest - 200f64.sqrt()).abs() < 1e-6, "diagonal {widest}");
        // Outside the box: nothing.
        let outside =
            ObliquePlane::axial(g.patient_from_index(DVec3::new(10.0, 12.0, 40.0)), 200.0);
        assert!(oblique_outline(&outside, &g, lo, hi).is_empty());
    }

    fn geometry() -> VolumeGeometry {
        VolumeGeometry::axis_aligned([64, 64, 64], [1.0, 1.0, 1.0])
    }

    #[test]
    fn standard_views_look_from_the_named_side() {
        let g = geometry();
        let centre = g.centre_patient();
        let from = |v: StandardView| {
            (DVec3::from(OrbitCamera::standard(v, false).camera(&g).eye) - centre)
                .try_normalize()
                .expect("the eye is away from the centre")
        };
        assert!(
            from(StandardView::Anterior).dot(-DVec3::Y) > 0.99,
            "anterior is -y in LPS"
        );
        assert!(from(StandardView::Posterior).dot(DVec3::Y) > 0.99);
        assert!(
            from(StandardView::Left).dot(DVec3::X) > 0.99,
            "patient left is +x in LPS"
        );
        assert!(from(StandardView::Right).dot(-DVec3::X) > 0.99);
        assert!(
            from(StandardView::Superior).dot(DVec3::Z) > 0.99,
            "superior is +z in LPS"
        );
        assert!(from(StandardView::Inferior).dot(-DVec3::Z) > 0.99);
    }

    #[test]
    fn superior_is_up_on_screen_and_the_patients_left_on_the_right_in_an_anterior_view() {
        let g = geometry();
        let basis = OrbitCamera::standard(StandardView::Anterior, false)
            .camera(&g)
            .basis();
        assert!(basis.up.dot(DVec3::Z) > 0.99, "superior at the top");
        // Facing the patient, their left (+x) is on the viewer's right.
        assert!(basis.right.dot(DVec3::X) > 0.99);
        let basis = OrbitCamera::standard(StandardView::Superior, false)
            .camera(&g)
            .basis();
        assert!(
            basis.up.dot(-DVec3::Y) > 0.99,
            "anterior at the top when looking down"
        );
    }

    #[test]
    fn three_wheel_clicks_zoom_a_third_not_four_times() {
        let mut orbit = OrbitCamera::default();
        for _ in 0..3 {
            orbit.zoom_by_lines(1.0);
        }
        assert!((orbit.zoom - 1.331).abs() < 1e-9, "zoom {}", orbit.zoom);
        orbit.zoom_by_lines(-3.0);
        assert!((orbit.zoom - 1.0).abs() < 1e-9);
    }

    #[test]
    fn pan_moves_eye_and_target_together() {
        let g = geometry();
        let mut orbit = OrbitCamera::default();
        let before = orbit.camera(&g);
        orbit.pan_by(Vec2::new(30.0, 0.0), Vec2::new(300.0, 300.0));
        let after = orbit.camera(&g);
        let eye_shift = DVec3::from(after.eye) - DVec3::from(before.eye);
        let target_shift = DVec3::from(after.target) - DVec3::from(before.target);
        assert!((eye_shift - target_shift).length() < 1e-9 && eye_shift.length() > 1.0);
    }
}
