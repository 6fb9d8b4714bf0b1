//! The page's oblique view (wasm32 only): the desktop's oblique reformat (viewer/src/oblique_view.rs)
//! in the browser, sharing its model with it: the plane, the drag that turns it, the image a
//! view asks for and its trilinear resampling from level bricks are strata-slices'
//! (`strata_slices::oblique`), coloured by the same window/level step (`oblique_rgba`) with the
//! slice views' window and colour map. Shown where the desktop shows it (`show_oblique`): in
//! the sagittal's place in the 2×2, as a fourth slice under the 3D view
//! ([`oblique_layout`]); the link carries it (`oblique=YAW,PITCH[,ROLL]`, degrees off axial).
//!
//! Nothing here waits: the resampling reads only bricks already resident (a bounded LRU of
//! decoded bricks); the ones it lacks are asked for through the served store's asynchronous
//! path, as the slice views ask for theirs (slice_views.rs: a `BrickFetcher` of its own, at
//! most [`OBLIQUE_REQUESTS`] out at once), and the image is resampled again when they arrive.
//! Until the plane's image at the level matching the view is complete, the view shows the
//! plane at the coarsest level once its few bricks are in, then refines; a view that had an
//! image keeps it until the new one is complete (the slice views' rule). The sample's bricks
//! are in memory: copied into the same LRU as the resampling first needs them.
//!
//! Input, as the desktop's oblique view: left drag turns the plane (sideways about the screen's
//! vertical, up/down about its horizontal, `TURN_PER_POINT` a point), a click moves the
//! linked crosshair, right drag (or Shift + left drag) windows, the wheel pages along the
//! plane's normal, one finest voxel spacing a line. With a segment tool chosen the left button
//! is the tool's (brush and eraser a disc in the plane, fill the closed region in it: the
//! page's segmentation, segment_editor.rs), and the labels are drawn over the image.
//!
//! A served overlay (overlay_view.rs, `overlay=`) is drawn over the image as the desktop's
//! oblique view draws its overlay: sampled at the image's own pixel centres by the shared
//! `strata_viewer_ui::overlay` and composited over it.
//!
//! Test hook (`capture=1`): each complete image at the view's level, once the pointer is up,
//! is handed to the page to post (RGBA as drawn, with its level and window, and the overlay
//! over it once sampled), so `web/tests/browser/oblique.rs` compares it with the desktop's
//! resampling of the same plane and `web/tests/browser/overlay.rs` with the desktop's
//! compositing.

use std::rc::Rc;
use std::sync::Arc;

use egui::{Color32, Pos2, Rect, Sense, Stroke, TextureHandle, TextureOptions, Vec2};
use glam::DVec3;
use strata_render::{BrickSource, BrickedVolume, ValueMapping, VolumeGeometry};
use strata_segment::tools::brush::SlicePlane;
use strata_slices::oblique::{
    default_extent_mm, oblique_rgba, resample, LevelBricks, ObliqueImage, ObliquePlane,
    ObliqueRequest, Resampled,
};
use strata_slices::{drag_window, BrickLru, ColourMap, SliceError, Window};
use strata_source::{BrickFetcher, FetchOptions, VolumeSource};
use strata_types::{BrickId, OctreeLayout};
use strata_viewer_ui::layouts;
use strata_viewer_ui::slice_canvas::{fraction_at, paint_orientation_labels, paint_readout_line};
use strata_viewer_ui::view_state::{Layout, ViewState};

use crate::overlay_view::OverlaySlot;
use crate::slice_views::{slice_layout, SliceViews};

/// The plane as the brush's disc lies in it: through the centre, spanned by screen right and
/// down (orthonormal, LPS), so a disc of the brush's size in mm is a circle on screen (the
/// desktop's `oblique::brush_plane`).
pub fn brush_plane(plane: &ObliquePlane) -> SlicePlane {
    SlicePlane::Oblique {
        centre_lps: plane.centre,
        u: plane.right,
        v: plane.down,
    }
}

/// Decoded bricks the page keeps for its oblique view (bytes): a tilted plane at the view's
/// level crosses a few bricks per row of its image.
pub const OBLIQUE_CACHE_BYTES: usize = 48 << 20;
/// Brick requests the oblique view has out at once (the slice views' number).
pub const OBLIQUE_REQUESTS: usize = 4;
/// Missing bricks one resampling lists before it stops: the requests and the next few, so a
/// resampling while bricks arrive costs little.
const LISTED_MISSING: usize = 4 * OBLIQUE_REQUESTS;
/// The oblique view's colour, the desktop's (its title and frame).
const OBLIQUE_COLOUR: Color32 = Color32::from_rgb(200, 140, 255);

/// Where the view's bricks come from.
enum Bricks {
    /// A served store, fetched asynchronously.
    Served(Box<dyn BrickFetcher>),
    /// The page's sample, bricked in memory as the stores are (shared with the 3D view).
    Sample(Rc<BrickedVolume>),
}

/// The resident bricks as the shared resampling reads them; the sample's are copied in on
/// first use (always resident), a served store's only once fetched.
struct ResidentBricks<'a> {
    cache: &'a mut BrickLru,
    sample: Option<&'a BrickedVolume>,
}

impl LevelBricks for ResidentBricks<'_> {
    type Error = SliceError;
    fn brick(&mut self, id: BrickId) -> Result<Option<Arc<Vec<u16>>>, SliceError> {
        if let Some(brick) = self.cache.get(id) {
            return Ok(Some(brick));
        }
        let Some(volume) = self.sample else {
            return Ok(None);
        };
        let Some(payload) = volume.brick(id.level, id.coords) else {
            return Ok(None);
        };
        let brick = Arc::new(payload.to_vec());
        self.cache.insert(id, brick.clone());
        Ok(Some(brick))
    }
}

/// The image on screen, its texture, and the window and map it was coloured with.
struct Shown {
    image: ObliqueImage,
    texture: TextureHandle,
    window: Window,
    colour_map: ColourMap,
}

/// The test capture of one oblique image (`capture=1`): what the page posts.
pub struct ObliqueCapture {
    /// RGBA8 as drawn, row 0 at the top.
    pub rgba: Vec<u8>,
    pub width: u32,
    pub height: u32,
    /// Its level, plane angles (degrees) and window, by name.
    pub metrics: Vec<(&'static str, f64)>,
}

/// The oblique view of one volume.
pub struct ObliqueView {
    bricks: Bricks,
    cache: BrickLru,
    geometry: VolumeGeometry,
    layout: OctreeLayout,
    mapping: ValueMapping,
    physical_range: (f64, f64),
    /// The plane's orientation and extent (its centre follows the crosshair every frame).
    plane: ObliquePlane,
    /// The angles the link had when this view last read or wrote them: a change from these
    /// is the link's (the toggle, a notebook), followed.
    linked_angles: [f64; 3],
    /// The image the view asks for now, and whether a brick arrived since it was last tried.
    wanted: Option<ObliqueRequest>,
    retry: bool,
    /// Bricks the wanted image lacks, most needed first.
    missing: Vec<BrickId>,
    shown: Option<Shown>,
    wheel_lines: f64,
    /// The last image handed to the test capture.
    captured: Option<ObliqueRequest>,
    error: Option<String>,
}

/// Why a served store's oblique view could not start.
#[derive(Debug, thiserror::Error)]
pub enum ObliqueViewError {
    #[error(transparent)]
    Fetcher(strata_source::SourceError),
    #[error("the store has no asynchronous brick path")]
    NoAsynchronousPath,
}

/// The 3D view's, the slice views' (axial, coronal, sagittal; None where not shown) and the
/// oblique view's rectangles where the desktop puts them with its oblique view shown: the
/// sagittal's place in the 2×2, a fourth column under the 3D view. `None` for the 3D view
/// alone.
pub fn oblique_layout(layout: Layout, area: Rect) -> Option<(Rect, [Option<Rect>; 3], Rect)> {
    match layout {
        Layout::Single => None,
        Layout::FourUp => {
            let [axial, three_d, oblique, coronal] = layouts::two_by_two_cells(area);
            Some((three_d, [Some(axial), Some(coronal), None], oblique))
        }
        Layout::ThreeDOverSlices => {
            let (three_d, row) = layouts::three_d_over_row(area, 4);
            Some((three_d, [Some(row[0]), Some(row[1]), Some(row[2])], row[3]))
        }
    }
}

impl ObliqueView {
    /// The oblique view of `store`, fetching through its asynchronous path, turned
    /// `angles_deg` off axial.
    pub fn new(store: &dyn VolumeSource, angles_deg: [f64; 3]) -> Result<Self, ObliqueViewError> {
        let fetcher = match store.start_fetching(FetchOptions {
            max_queued: OBLIQUE_REQUESTS + 1,
            max_in_transit: OBLIQUE_REQUESTS + 1,
            threads: 1,
        }) {
            Some(Ok(fetcher)) => fetcher,
            Some(Err(e)) => return Err(ObliqueViewError::Fetcher(e)),
            None => return Err(ObliqueViewError::NoAsynchronousPath),
        };
        let header = store.header();
        Ok(ObliqueView::with_bricks(
            Bricks::Served(fetcher),
            header.geometry.clone(),
            header.layout.clone(),
            header.value_mapping.mapping,
            (header.stored_range[0], header.stored_range[1]),
            angles_deg,
        ))
    }

    /// The oblique view of the page's sample, read from its in-memory bricks.
    pub fn for_sample(volume: Rc<BrickedVolume>, angles_deg: [f64; 3]) -> Self {
        let geometry = volume.geometry.clone();
        let layout = OctreeLayout::new(geometry.dims);
        let (mapping, stored) = (volume.mapping, volume.stored_range);
        ObliqueView::with_bricks(
            Bricks::Sample(volume),
            geometry,
            layout,
            mapping,
            stored,
            angles_deg,
        )
    }

    fn with_bricks(
        bricks: Bricks,
        geometry: VolumeGeometry,
        layout: OctreeLayout,
        mapping: ValueMapping,
        stored_range: (u16, u16),
        angles_deg: [f64; 3],
    ) -> Self {
        let a = mapping.physical(stored_range.0 as f64);
        let b = mapping.physical(stored_range.1 as f64);
        let plane = ObliquePlane::from_orientation_deg(
            DVec3::ZERO,
            default_extent_mm(&geometry),
            angles_deg,
        );
        ObliqueView {
            bricks,
            cache: BrickLru::new(OBLIQUE_CACHE_BYTES),
            geometry,
            layout,
            mapping,
            physical_range: (a.min(b), a.max(b)),
            plane,
            linked_angles: angles_deg,
            wanted: None,
            retry: false,
            missing: Vec::new(),
            shown: None,
            wheel_lines: 0.0,
            captured: None,
            error: None,
        }
    }

    /// Another frame of the 4-D store (frames.rs): its bricks from now on (the cached ones are
    /// the old frame's); the image on screen stays until the new frame's arrives.
    pub fn show_frame(&mut self, store: &dyn VolumeSource) -> Result<(), ObliqueViewError> {
        let fetcher = match store.start_fetching(FetchOptions {
            max_queued: OBLIQUE_REQUESTS + 1,
            max_in_transit: OBLIQUE_REQUESTS + 1,
            threads: 1,
        }) {
            Some(Ok(fetcher)) => fetcher,
            Some(Err(e)) => return Err(ObliqueViewError::Fetcher(e)),
            None => return Err(ObliqueViewError::NoAsynchronousPath),
        };
        self.bricks = Bricks::Served(fetcher);
        self.cache = BrickLru::new(OBLIQUE_CACHE_BYTES);
        self.wanted = None;
        self.retry = false;
        self.missing.clear();
        Ok(())
    }

    /// Takes the bricks that arrived; a brick in makes the wanted image worth another try.
    fn take_arrivals(&mut self) {
        let Bricks::Served(fetcher) = &mut self.bricks else {
            return;
        };
        for result in fetcher.try_results() {
            match result.outcome {
                Ok(voxels) => {
                    self.cache.insert(result.id, voxels);
                    self.retry = true;
                }
                Err(e) => self.error = Some(e.to_string()),
            }
            fetcher.complete(result.id);
        }
    }

    fn resample_resident(&mut self, request: &ObliqueRequest) -> Result<Resampled, SliceError> {
        let sample = match &self.bricks {
            Bricks::Sample(volume) => Some(volume.as_ref()),
            Bricks::Served(_) => None,
        };
        let mut resident = ResidentBricks {
            cache: &mut self.cache,
            sample,
        };
        resample(
            &self.geometry,
            &self.layout,
            &mut resident,
            request,
            LISTED_MISSING,
        )
    }

    /// Resamples the wanted image if it changed or a brick arrived: shown when complete; until
    /// then the plane at the coarsest level where nothing of this plane is shown yet.
    fn refine(&mut self, ctx: &egui::Context, window: Window, colour_map: ColourMap) {
        let Some(wanted) = self.wanted.filter(|_| self.retry) else {
            return;
        };
        self.retry = false;
        match self.resample_resident(&wanted) {
            Ok(Resampled::Complete(image)) => {
                self.missing.clear();
                self.show(ctx, image, window, colour_map);
            }
            Ok(Resampled::Incomplete { missing }) => {
                let coarsest = self.layout.level_count().saturating_sub(1) as u8;
                let plane_shown = self
                    .shown
                    .as_ref()
                    .is_some_and(|s| s.image.request.plane == wanted.plane);
                let mut wanted_first = Vec::new();
                if !plane_shown && wanted.level < coarsest {
                    let preview = ObliqueRequest {
                        level: coarsest,
                        ..wanted
                    };
                    match self.resample_resident(&preview) {
                        Ok(Resampled::Complete(image)) => self.show(ctx, image, window, colour_map),
                        // The preview's few bricks first: something shows soon.
                        Ok(Resampled::Incomplete { missing }) => wanted_first = missing,
                        Err(e) => self.error = Some(e.to_string()),
                    }
                }
                for id in missing {
                    if !wanted_first.contains(&id) {
                        wanted_first.push(id);
                    }
                }
                self.missing = wanted_first;
            }
            Err(e) => self.error = Some(e.to_string()),
        }
    }

    /// Asks for the bricks the wanted image lacks (the most needed first).
    fn request_missing(&mut self, ctx: &egui::Context) {
        let Bricks::Served(fetcher) = &mut self.bricks else {
            return;
        };
        let demand: Vec<(BrickId, f64)> = self
            .missing
            .iter()
            .take(OBLIQUE_REQUESTS)
            .enumerate()
            .map(|(rank, id)| (*id, (OBLIQUE_REQUESTS - rank) as f64))
            .collect();
        fetcher.set_requests(&demand, &[]);
        if !demand.is_empty() {
            // Answers arrive between frames and wake nothing: poll until they are in.
            ctx.request_repaint();
        }
    }

    fn show(
        &mut self,
        ctx: &egui::Context,
        image: ObliqueImage,
        window: Window,
        colour_map: ColourMap,
    ) {
        let colours = self.coloured(&image, window, colour_map);
        match self.shown.as_mut() {
            Some(shown) => {
                shown.texture.set(colours, TextureOptions::LINEAR);
                shown.image = image;
                shown.window = window;
                shown.colour_map = colour_map;
            }
            None => {
                let texture = ctx.load_texture("oblique", colours, TextureOptions::LINEAR);
                self.shown = Some(Shown {
                    image,
                    texture,
                    window,
                    colour_map,
                });
            }
        }
    }

    fn coloured(
        &self,
        image: &ObliqueImage,
        window: Window,
        colour_map: ColourMap,
    ) -> egui::ColorImage {
        let rgba = oblique_rgba(&image.values, window, colour_map, self.mapping);
        egui::ColorImage::from_rgba_unmultiplied([image.request.width, image.request.height], &rgba)
    }

    /// Test hook (`capture=1`): the image on screen once it is the wanted one (complete at the
    /// view's level) and the pointer is up, each such image once: its RGBA as coloured with
    /// `overlay` over it (once sampled: until then nothing is taken), width, height, and its
    /// level, plane angles and window as the capture's metrics.
    pub fn take_capture(
        &mut self,
        pointer_down: bool,
        overlay: &OverlaySlot,
    ) -> Option<ObliqueCapture> {
        let shown = self.shown.as_ref()?;
        let request = shown.image.request;
        if pointer_down || Some(request) != self.wanted || self.captured == Some(request) {
            return None;
        }
        let mut rgba = oblique_rgba(
            &shown.image.values,
            shown.window,
            shown.colour_map,
            self.mapping,
        );
        if !overlay.composite_oblique(&request, &mut rgba) {
            return None;
        }
        self.captured = Some(request);
        let [yaw, pitch, roll] = request.plane.orientation_deg();
        let metrics = vec![
            ("oblique_level", f64::from(request.level)),
            ("oblique_yaw", yaw),
            ("oblique_pitch", pitch),
            ("oblique_roll", roll),
            ("oblique_window_centre", shown.window.centre),
            ("oblique_window_width", shown.window.width),
        ];
        Some(ObliqueCapture {
            rgba,
            width: request.width as u32,
            height: request.height as u32,
            metrics,
        })
    }

    /// The view in `rect` with the link's angles `oblique` (followed when the link changed
    /// them, written back as turned), linked to the slice views' crosshair, window and colour
    /// map.
    pub fn ui(
        &mut self,
        ui: &mut egui::Ui,
        rect: Rect,
        slices: &mut SliceViews,
        oblique: &mut [f64; 3],
    ) {
        if *oblique != self.linked_angles {
            self.plane = ObliquePlane::from_orientation_deg(
                self.plane.centre,
                self.plane.extent_mm,
                *oblique,
            );
        }
        let colour_map = slices.colour_map;
        let (cursor, window) = (&mut slices.cursor, &mut slices.window);
        let ctx = ui.ctx().clone();
        self.take_arrivals();
        let dims = self.geometry.dims;
        let painter = ui.painter_at(rect);
        painter.rect_filled(rect, 0.0, Color32::BLACK);
        painter.rect_stroke(
            rect.shrink(0.5),
            0.0,
            Stroke::new(1.0, OBLIQUE_COLOUR.gamma_multiply(0.6)),
            egui::StrokeKind::Inside,
        );
        // The desktop's square image, with room for the title, labels and readout.
        let inner = Rect::from_min_max(
            rect.min + Vec2::new(18.0, 38.0),
            rect.max - Vec2::new(18.0, 36.0),
        );
        let side = inner.width().min(inner.height()).max(1.0);
        let image_rect = Rect::from_center_size(inner.center(), Vec2::splat(side));
        let response = ui.interact(rect, ui.scope_id().with("oblique"), Sense::click_and_drag());
        let centre_of = |cursor: &[f64; 3]| self.geometry.patient_from_index(DVec3::from(*cursor));
        self.plane.centre = centre_of(cursor);
        let windowing = response.dragged_by(egui::PointerButton::Secondary)
            || response.dragged_by(egui::PointerButton::Primary) && ui.input(|i| i.modifiers.shift);
        if windowing {
            let delta = ui.input(|i| i.pointer.delta());
            *window = drag_window(*window, delta.x as f64, delta.y as f64, self.physical_range);
        } else if slices.segmentation.as_ref().is_some_and(|s| s.paints()) {
            // A segment tool has the left button, as on the desktop's oblique view: the brush
            // and eraser a disc in the plane, fill the region in it (segment_editor.rs).
            let plane = self.plane;
            let to_lps = |p: Pos2| {
                let (u, w) = fraction_at(image_rect, p);
                plane.patient_at(u, w)
            };
            if let Some(seg) = slices.segmentation.as_mut() {
                seg.pointer(ui, &response, image_rect, &to_lps, brush_plane(&plane));
            }
        } else if response.dragged_by(egui::PointerButton::Primary) {
            let delta = ui.input(|i| i.pointer.delta());
            if delta != Vec2::ZERO {
                // The desktop's drag mapping (strata_slices::oblique).
                self.plane = self.plane.turned_by_drag(delta.x as f64, delta.y as f64);
            }
        } else if response.clicked() {
            if let Some(pos) = response
                .interact_pointer_pos()
                .filter(|p| image_rect.contains(*p))
            {
                let (u, w) = fraction_at(image_rect, pos);
                let index = self
                    .geometry
                    .index_from_patient(self.plane.patient_at(u, w));
                for a in 0..3 {
                    cursor[a] = index[a].clamp(0.0, dims[a] as f64 - 1.0);
                }
            }
        }
        if response.hovered() {
            self.wheel_lines += crate::slice_views::wheel_lines(ui);
            let step = self.wheel_lines.trunc();
            if step != 0.0 {
                self.wheel_lines -= step;
                // One finest voxel spacing a line along the normal, as on the desktop.
                let along = self.plane.normal() * (step * self.geometry.finest_spacing_mm());
                let moved = self.geometry.index_from_patient(self.plane.centre + along);
                for a in 0..3 {
                    cursor[a] = moved[a].clamp(0.0, dims[a] as f64 - 1.0);
                }
            }
        } else {
            self.wheel_lines = 0.0;
        }
        self.plane.centre = centre_of(cursor);

        let ppp = ui.ctx().pixels_per_point();
        let request = ObliqueRequest::for_view(
            self.plane,
            (side * ppp) as f64,
            &self.geometry,
            self.layout.level_count(),
        );
        if self.wanted != Some(request) {
            self.wanted = Some(request);
            self.retry = true;
        }
        self.refine(&ctx, *window, colour_map);
        self.request_missing(&ctx);
        if let Some(shown) = self.shown.as_mut() {
            if shown.window != *window || shown.colour_map != colour_map {
                let rgba = oblique_rgba(&shown.image.values, *window, colour_map, self.mapping);
                shown.texture.set(
                    egui::ColorImage::from_rgba_unmultiplied(
                        [shown.image.request.width, shown.image.request.height],
                        &rgba,
                    ),
                    TextureOptions::LINEAR,
                );
                shown.window = *window;
                shown.colour_map = colour_map;
            }
            painter.image(
                shown.texture.id(),
                image_rect,
                Rect::from_min_max(Pos2::ZERO, Pos2::new(1.0, 1.0)),
                Color32::WHITE,
            );
            // The served overlay over the image on screen, sampled at its own pixel centres
            // (overlay_view.rs), as the desktop's oblique view draws its overlay.
            let shown_request = shown.image.request;
            slices
                .overlay
                .paint_oblique(&ctx, &painter, &shown_request, image_rect);
        }
        if let Some(seg) = slices.segmentation.as_mut() {
            // The labels at the oblique image's own pixels (its request's, before one shows).
            let pixels = self
                .shown
                .as_ref()
                .map_or(request.width, |s| s.image.request.width);
            seg.paint_oblique_labels(&ctx, &painter, &self.plane, image_rect, pixels);
        }
        // The crosshair is the plane's centre.
        let c = image_rect.center();
        let hair = Stroke::new(1.0, Color32::from_rgba_unmultiplied(120, 220, 255, 150));
        painter.line_segment([c - Vec2::new(12.0, 0.0), c + Vec2::new(12.0, 0.0)], hair);
        painter.line_segment([c - Vec2::new(0.0, 12.0), c + Vec2::new(0.0, 12.0)], hair);
        paint_orientation_labels(&painter, rect, self.plane.labels());
        painter.text(
            rect.left_top() + Vec2::new(8.0, 4.0),
            egui::Align2::LEFT_TOP,
            "Oblique",
            egui::FontId::proportional(13.0),
            OBLIQUE_COLOUR,
        );
        let mut info = format!("W {:.0} L {:.0}", window.width, window.centre);
        if let Some(level) = self
            .shown
            .as_ref()
            .map(|s| s.image.request.level)
            .filter(|l| *l > 0)
        {
            info.push_str(&format!(" · level {level}"));
        }
        if !self.missing.is_empty() {
            info.push_str(" · loading");
        }
        if let Some(error) = &self.error {
            info.push_str(&format!(" · {error}"));
        }
        paint_readout_line(&painter, rect, info);
        let angles = self.plane.orientation_deg();
        if angles != *oblique {
            *oblique = angles;
        }
        self.linked_angles = *oblique;
    }
}

/// The toolbar's switch: the oblique view shown (axial when switched on) or not.
pub fn oblique_toggle(ui: &mut egui::Ui, view: &mut ViewState) {
    let mut shown = view.oblique.is_some();
    if ui
        .toggle_value(&mut shown, "Oblique")
        .on_hover_text("Show the oblique view: a slice through the crosshair at any angle")
        .changed()
    {
        view.oblique = shown.then_some([0.0; 3]);
    }
}

/// Where the views go: the 3D view, the slice views (None where the oblique view takes a
/// slice's place) and the oblique view when `show_oblique`; as slice_views.rs's
/// `slice_layout` without it. `None` for the 3D view alone.
pub fn place_views(
    layout: Layout,
    show_oblique: bool,
    area: Rect,
) -> Option<(Rect, [Option<Rect>; 3], Option<Rect>)> {
    if show_oblique {
        return oblique_layout(layout, area)
            .map(|(three_d, slices, oblique)| (three_d, slices, Some(oblique)));
    }
    slice_layout(layout, area).map(|(three_d, slices)| (three_d, slices.map(Some), None))
}
