//! The oblique view: a slice through the crosshair at any orientation (oblique.rs resamples
//! it). Left drag turns the plane (sideways about the screen's vertical, up/down about its
//! horizontal), a click moves the crosshair, right drag windows, the wheel pages along the
//! plane's normal; "Axial" resets the plane, "Align to 3D" takes the 3D camera's orientation.
//! Orientation letters follow the plane.
//!
//! The label overlay (an imported label map or the editable layer) is drawn over the image,
//! sampled by the overlay's thread at the image's own pixel centres (nearest label, on the
//! labels' own grid) and coloured with the slice views' colours, opacity and visibility. With
//! the brush or eraser chosen, the left button paints a disc in the plane instead of turning
//! it (the slice views' gesture, slice_view.rs), and the brush is drawn as its circle; fill and
//! grow take a click as their seed.

use egui::{Color32, Pos2, Rect, Sense, Stroke, TextureHandle, TextureOptions, Vec2};
use glam::DVec3;

use strata_slices::oblique::{
    default_extent_mm, oblique_rgba, ObliqueImage, ObliquePlane, ObliqueRequest,
};

use super::colour_maps::ColourMap;
use super::oblique::{brush_plane, plane_facing};
use super::overlay::{Overlay, OverlayKind, OverlayStyle};
use super::scene::{Scene, VolumeData, Window};
use super::segmentation::Segmentation;
use super::slice_view::{drag_window, segment_pointer_input};
use super::widgets::{view_title, wheel_lines, ViewResponse};

struct ObliqueTexture {
    texture: TextureHandle,
    image: ObliqueImage,
    window: Window,
    colour_map: ColourMap,
}

/// The overlay's texture over the oblique image and what it was coloured from.
struct ObliqueOverlayTexture {
    texture: TextureHandle,
    /// The oblique image's request the overlay was sampled for.
    request: ObliqueRequest,
    values: std::sync::Arc<Vec<f32>>,
    style: OverlayStyle,
}

/// What the shell passes in besides the volume: the 3D view's camera (for "Align to 3D"),
/// the overlay to draw and the segmentation the tools edit.
pub struct ObliqueContext<'a> {
    pub camera: &'a strata_render::Camera,
    pub overlay: Option<&'a Overlay>,
    pub segmentation: Option<&'a mut Segmentation>,
}

pub struct ObliqueViewer {
    /// The plane's orientation (its centre follows the crosshair every frame).
    pub plane: Option<ObliquePlane>,
    texture: Option<ObliqueTexture>,
    overlay_texture: Option<ObliqueOverlayTexture>,
    wheel_lines: f64,
    /// Where the image was drawn last frame (tests).
    pub image_rect: Option<Rect>,
}

impl Default for ObliqueViewer {
    fn default() -> Self {
        ObliqueViewer {
            plane: None,
            texture: None,
            overlay_texture: None,
            wheel_lines: 0.0,
            image_rect: None,
        }
    }
}

impl ObliqueViewer {
    /// Turned to `plane`'s orientation (a restored session's); None: axial.
    pub fn with_plane(plane: Option<ObliquePlane>) -> Self {
        ObliqueViewer {
            plane,
            ..ObliqueViewer::default()
        }
    }

    /// The plane through the crosshair (axial until turned).
    pub fn current_plane(&self, data: &VolumeData, scene: &Scene) -> ObliquePlane {
        let geometry = &data.info.geometry;
        let centre = geometry.patient_from_index(DVec3::from(scene.cursor));
        match self.plane {
            Some(p) => ObliquePlane { centre, ..p },
            None => ObliquePlane::axial(centre, default_extent_mm(geometry)),
        }
    }

    /// The image shown now (tests compare it with the plane asked for).
    #[cfg(test)]
    pub fn shown(&self) -> Option<&ObliqueImage> {
        self.texture.as_ref().map(|t| &t.image)
    }

    /// The overlay values coloured into the texture drawn now, with the oblique image's
    /// request they were sampled for (tests compare them with a CPU model of that plane).
    #[cfg(test)]
    pub fn shown_overlay(&self) -> Option<(ObliqueRequest, std::sync::Arc<Vec<f32>>)> {
        self.overlay_texture
            .as_ref()
            .map(|t| (t.request, t.values.clone()))
    }

    pub fn ui(
        &mut self,
        ui: &mut egui::Ui,
        rect: Rect,
        data: &VolumeData,
        scene: &mut Scene,
        context: ObliqueContext<'_>,
    ) -> ViewResponse {
        let ObliqueContext {
            camera,
            overlay,
            mut segmentation,
        } = context;
        let geometry = &data.info.geometry;
        let painter = ui.painter_at(rect);
        painter.rect_filled(rect, 0.0, Color32::BLACK);
        let colour = super::oblique::OBLIQUE_COLOUR;
        painter.rect_stroke(
            rect.shrink(0.5),
            0.0,
            Stroke::new(1.0, colour.gamma_multiply(0.6)),
            egui::StrokeKind::Inside,
        );
        let inner = Rect::from_min_max(
            rect.min + Vec2::new(18.0, 38.0),
            rect.max - Vec2::new(18.0, 36.0),
        );
        let side = inner.width().min(inner.height()).max(1.0);
        let image_rect = Rect::from_center_size(inner.center(), Vec2::splat(side));
        let response = ui.interact(rect, ui.scope_id().with("oblique"), Sense::click_and_drag());
        let mut plane = self.current_plane(data, scene);
        let painting = segmentation.as_ref().is_some_and(|s| s.tool.paints());
        if let Some(seg) = segmentation.as_deref_mut().filter(|_| painting) {
            let brush_plane = brush_plane(&plane);
            let to_lps = |pos: Pos2| pixel_patient(&plane, image_rect, pos);
            segment_pointer_input(ui, &response, image_rect, seg, &to_lps, &|_| brush_plane);
        } else if response.dragged_by(egui::PointerButton::Primary) {
            let delta = ui.input(|i| i.pointer.delta());
            if delta != Vec2::ZERO {
                // The page turns its plane by the same mapping (strata_slices::oblique).
                plane = plane.turned_by_drag(delta.x as f64, delta.y as f64);
                self.plane = Some(plane);
            }
        } else if response.clicked() {
            if let Some(pos) = response.interact_pointer_pos() {
                if image_rect.contains(pos) {
                    let index = index_at(&plane, image_rect, pos, data);
                    let dims = geometry.dims;
                    for a in 0..3 {
                        scene.cursor[a] = index[a].clamp(0.0, dims[a] as f64 - 1.0);
                    }
                    plane = self.current_plane(data, scene);
                }
            }
        }
        if response.dragged_by(egui::PointerButton::Secondary) {
            let delta = ui.input(|i| i.pointer.delta());
            scene.window = drag_window(scene.window, delta, data.info.physical_range);
        }
        if response.hovered() {
            self.wheel_lines += wheel_lines(ui);
            let step = self.wheel_lines.trunc();
            if step != 0.0 {
                self.wheel_lines -= step;
                // One finest voxel spacing per click along the normal.
                let along = plane.normal() * (step * geometry.finest_spacing_mm());
                let moved = geometry.index_from_patient(plane.centre + along);
                let dims = geometry.dims;
                for a in 0..3 {
                    scene.cursor[a] = moved[a].clamp(0.0, dims[a] as f64 - 1.0);
                }
                plane = self.current_plane(data, scene);
            }
        } else {
            self.wheel_lines = 0.0;
        }

        let ppp = ui.ctx().pixels_per_point();
        let request = ObliqueRequest::for_view(
            plane,
            (side * ppp) as f64,
            geometry,
            data.info.header.layout.level_count(),
        );
        data.oblique.request(request);
        if let Some(image) = data.oblique.latest() {
            let stale = self.texture.as_ref().is_none_or(|t| {
                !std::sync::Arc::ptr_eq(&t.image.values, &image.values)
                    || t.window != scene.window
                    || t.colour_map != scene.colour_map
            });
            if stale {
                let pixels = window_level(&image, scene.window, scene.colour_map, data);
                match &mut self.texture {
                    Some(t) => {
                        t.texture.set(pixels, TextureOptions::LINEAR);
                        t.image = image;
                        t.window = scene.window;
                        t.colour_map = scene.colour_map;
                    }
                    None => {
                        self.texture = Some(ObliqueTexture {
                            texture: ui.ctx().load_texture(
                                "oblique",
                                pixels,
                                TextureOptions::LINEAR,
                            ),
                            image,
                            window: scene.window,
                            colour_map: scene.colour_map,
                        })
                    }
                }
            }
        }
        if let Some(t) = &self.texture {
            painter.image(
                t.texture.id(),
                image_rect,
                Rect::from_min_max(Pos2::ZERO, Pos2::new(1.0, 1.0)),
                Color32::WHITE,
            );
            let request = t.image.request;
            if let Some(o) = overlay {
                self.paint_overlay(ui, &painter, o, request, image_rect);
            }
        }
        if let Some(seg) = segmentation.as_deref().filter(|s| s.tool.drags()) {
            if let Some(pos) = response.hover_pos().filter(|p| image_rect.contains(*p)) {
                // The square image spans the plane's extent across and down.
                let radius = (seg.diameter_mm / 2.0 / plane.extent_mm) as f32 * image_rect.width();
                painter.circle_stroke(pos, radius, Stroke::new(1.0, Color32::WHITE));
            }
        }
        // The crosshair is the plane's centre.
        let c = image_rect.center();
        let hair = Stroke::new(1.0, Color32::from_rgba_unmultiplied(120, 220, 255, 150));
        painter.line_segment([c - Vec2::new(12.0, 0.0), c + Vec2::new(12.0, 0.0)], hair);
        painter.line_segment([c - Vec2::new(0.0, 12.0), c + Vec2::new(0.0, 12.0)], hair);
        strata_viewer_ui::slice_canvas::paint_orientation_labels(&painter, rect, plane.labels());
        let toggled = view_title(ui, rect, "Oblique", "Oblique", colour);
        // Buttons in the top-right corner.
        let buttons = Rect::from_min_max(
            Pos2::new(rect.right() - 160.0, rect.top() + 2.0),
            Pos2::new(rect.right() - 4.0, rect.top() + 22.0),
        );
        ui.scope_builder(egui::UiBuilder::new().max_rect(buttons), |ui| {
            ui.with_layout(egui::Layout::right_to_left(egui::Align::Center), |ui| {
                if ui
                    .small_button("Align to 3D")
                    .on_hover_text("Turn the plane to face the 3D view's camera")
                    .clicked()
                {
                    self.plane = Some(plane_facing(camera, plane.centre, plane.extent_mm));
                }
                if ui
                    .small_button("Axial")
                    .on_hover_text("Reset the plane to axial")
                    .clicked()
                {
                    self.plane = None;
                }
            });
        });
        if let Some(e) = data.oblique.error() {
            painter.text(
                rect.left_bottom() + Vec2::new(8.0, -4.0),
                egui::Align2::LEFT_BOTTOM,
                e,
                egui::FontId::proportional(11.0),
                Color32::LIGHT_RED,
            );
        }
        let hover = response
            .hover_pos()
            .filter(|p| image_rect.contains(*p))
            .map(|p| {
                let i = index_at(&plane, image_rect, p, data);
                [i.x, i.y, i.z]
            });
        self.image_rect = Some(image_rect);
        ViewResponse {
            toggle_focus: toggled,
            focused: response.clicked()
                || response.drag_started()
                || response.hovered() && ui.input(|i| i.pointer.any_pressed()),
            hover,
        }
    }
}

impl ObliqueViewer {
    /// The overlay over the image of `request`: asked for on the overlay's thread at exactly
    /// that image's pixels, coloured here (again only when the values or the style change)
    /// and drawn over the image. Labels use nearest filtering: a linear filter would blend two
    /// labels' colours into a third at every boundary.
    fn paint_overlay(
        &mut self,
        ui: &egui::Ui,
        painter: &egui::Painter,
        overlay: &Overlay,
        request: ObliqueRequest,
        image_rect: Rect,
    ) {
        overlay.request_oblique(request.plane, request.width, request.height);
        let Some(sampled) = overlay.latest_oblique().filter(|s| {
            s.plane == request.plane && s.width == request.width && s.height == request.height
        }) else {
            return;
        };
        let filter = match overlay.kind {
            OverlayKind::Labels => TextureOptions::NEAREST,
            OverlayKind::Continuous => TextureOptions::LINEAR,
        };
        let stale = self.overlay_texture.as_ref().is_none_or(|t| {
            !std::sync::Arc::ptr_eq(&t.values, &sampled.values) || t.style != overlay.style
        });
        if stale {
            let colours = overlay.colourise_values(&sampled.values, sampled.width, sampled.height);
            match &mut self.overlay_texture {
                Some(t) => {
                    t.texture.set(colours, filter);
                    t.request = request;
                    t.values = sampled.values.clone();
                    t.style = overlay.style.clone();
                }
                None => {
                    self.overlay_texture = Some(ObliqueOverlayTexture {
                        texture: ui.ctx().load_texture("oblique overlay", colours, filter),
                        request,
                        values: sampled.values.clone(),
                        style: overlay.style.clone(),
                    })
                }
            }
        }
        if let Some(t) = &self.overlay_texture {
            painter.image(
                t.texture.id(),
                image_rect,
                Rect::from_min_max(Pos2::ZERO, Pos2::new(1.0, 1.0)),
                Color32::WHITE,
            );
        }
    }
}

/// The patient position (LPS mm) under screen position `pos` of the image of `plane`.
pub fn pixel_patient(plane: &ObliquePlane, image_rect: Rect, pos: Pos2) -> DVec3 {
    let u = ((pos.x - image_rect.left()) / image_rect.width()) as f64;
    let w = ((pos.y - image_rect.top()) / image_rect.height()) as f64;
    plane.patient_at(u, w)
}

/// The level-0 continuous index under screen position `pos`.
fn index_at(plane: &ObliquePlane, image_rect: Rect, pos: Pos2, data: &VolumeData) -> DVec3 {
    data.info
        .geometry
        .index_from_patient(pixel_patient(plane, image_rect, pos))
}

fn window_level(
    image: &ObliqueImage,
    window: Window,
    colour_map: ColourMap,
    data: &VolumeData,
) -> egui::ColorImage {
    // The page colours its oblique image with the same step.
    let rgba = oblique_rgba(&image.values, window, colour_map, data.info.mapping);
    egui::ColorImage::from_rgba_unmultiplied([image.request.width, image.request.height], &rgba)
}
