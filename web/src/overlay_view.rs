//! The page's overlay (issue 47 item 3, wasm32 only): a second store of the same server drawn
//! over the three slice views and the oblique view, as a label map or a continuous overlay, with the desktop's
//! sampling and colouring (strata-viewer-ui's overlay: nearest label or trilinear from level 0,
//! on any grid). The link names it (`overlay=NAME`, its kind, opacity and hidden labels); the
//! side panel's Overlay section lists the server's other stores and edits the link.
//!
//! Nothing waits: the overlay's level-0 bricks come through the served store's asynchronous
//! path (its own [`BrickFetcher`], at most [`OVERLAY_REQUESTS`] asked for at a time, so the
//! slices and the 3D view keep their connections) into a bounded LRU
//! ([`OVERLAY_CACHE_BYTES`]). Each frame a view's overlay that is not complete is sampled again
//! from what is resident, which lists the bricks still missing (at most
//! [`MISSING_PER_SAMPLING`]); once complete it is coloured into a texture, again only when the
//! style changes, and drawn with the slice's own mesh (labels with nearest filtering: a linear
//! filter would blend two labels' colours into a third at every boundary).
//!
//! The 3D view's overlay (issue 47): the desktop's grid (strata-viewer-ui's `overlay_3d`, the
//! nearest level-0 label or trilinear value at each grid voxel's centre over the primary's
//! index box) resampled here without blocking: each frame's pump samples at most
//! [`GRID_VOXELS_PER_FRAME`] voxels (whole grid z-slices) from the resident bricks, a slice
//! that meets a missing brick is tried again once more have arrived, and the missing bricks are
//! asked for after the slice views' own. Complete, the grid goes into the page's render request
//! ([`OverlaySlot::request_3d`]) and the shared render driver uploads it; a style change
//! afterwards is a new colour table only, as on the desktop. The grid is bounded by
//! [`PAGE_OVERLAY_3D_MAX_VOXELS`], an eighth of the desktop's.
//!
//! The oblique view's overlay is sampled as the desktop's (viewer/src/oblique_view.rs): at the
//! centres of the oblique image's own pixels (strata-viewer-ui's `oblique_pixels`), for the
//! image on screen, and drawn over it.
//!
//! For the browser tests (web/tests/browser/overlay.rs) the slice capture (`capture=1`) waits
//! for the axial view's overlay and composites it over the slice ([`OverlaySlot::composite`]),
//! and the oblique capture for the oblique view's ([`OverlaySlot::composite_oblique`]).

use std::cell::RefCell;
use std::collections::BTreeSet;
use std::rc::Rc;
use std::sync::Arc;

use egui::{Rect, TextureHandle, TextureOptions};
use strata_slices::oblique::{LevelBricks, ObliqueRequest};
use strata_slices::{BrickLru, SliceError, SliceImage, SliceRequest, SliceView};
use strata_source::wire::StoreList;
use strata_source::{BrickFetcher, FetchOptions, SourceError, VolumeSource};
use strata_types::{BrickId, OctreeLayout, VolumeGeometry};
use strata_viewer_ui::overlay::{
    colour_image, composite_over, kind_of_store, label_table_of, oblique_pixels, sample,
    slice_pixels, style_controls, OverlayGrids, OverlayKind, OverlayLink, OverlayStyle, Sampled,
};
use strata_viewer_ui::overlay_3d::{
    grid_dims, lut_for, GridProgress, GridResampler, Resampled, PAGE_OVERLAY_3D_MAX_VOXELS,
};
use strata_viewer_ui::render_driver::OverlayIn3d;
use strata_viewer_ui::slice_canvas::slice_mesh;
use strata_viewer_ui::view_state::ViewState;

use crate::served_store::{ListStoresError, ServedStore};
use crate::slice_views::SliceViews;

/// Overlay brick requests out at once (the most useful first).
pub const OVERLAY_REQUESTS: usize = 4;
/// Decoded level-0 overlay bricks kept (bytes): the three views' slices through a 256³ overlay
/// need under 200 bricks (18 MB).
pub const OVERLAY_CACHE_BYTES: usize = 48 << 20;
/// Missing bricks one sampling lists before it stops (bounds a frame's work while bricks come).
pub const MISSING_PER_SAMPLING: usize = 2 * OVERLAY_REQUESTS;
/// Grid voxels the page samples for the 3D grid in one frame: two z-slices of a 128² grid, so
/// a frame's share stays a few milliseconds (one matrix product and one brick lookup a voxel;
/// not measured on a slow device).
pub const GRID_VOXELS_PER_FRAME: u64 = 2 * 128 * 128;

/// The store being opened as the overlay: filled by the open's future.
type Opening = Rc<RefCell<Option<Result<ServedStore, SourceError>>>>;

/// The overlay of the slice views, following the link.
#[derive(Default)]
pub enum OverlaySlot {
    #[default]
    Closed,
    Opening {
        name: String,
        kind: Option<OverlayKind>,
        store: Opening,
    },
    Open(Box<PageOverlay>),
    Failed {
        name: String,
        kind: Option<OverlayKind>,
        error: String,
    },
}

impl OverlaySlot {
    /// The store and kind the slot holds (or is opening, or failed to open).
    fn identity(&self) -> Option<(&str, Option<OverlayKind>)> {
        match self {
            OverlaySlot::Closed => None,
            OverlaySlot::Opening { name, kind, .. } | OverlaySlot::Failed { name, kind, .. } => {
                Some((name, *kind))
            }
            OverlaySlot::Open(overlay) => Some((&overlay.name, overlay.kind_asked)),
        }
    }

    /// Takes the bricks that arrived and asks for the next. Once a frame, before the views.
    pub fn pump(&mut self, ctx: &egui::Context) {
        if let OverlaySlot::Open(overlay) = self {
            overlay.pump(ctx);
        }
    }

    /// The overlay over the slice `image`, drawn in `image_rect` (nothing until it is sampled).
    pub fn paint(
        &mut self,
        ctx: &egui::Context,
        painter: &egui::Painter,
        image: &SliceImage,
        image_rect: Rect,
    ) {
        if let OverlaySlot::Open(overlay) = self {
            overlay.paint(ctx, painter, image, image_rect);
        }
    }

    /// What the 3D view draws of the overlay now (the render request's): None while its grid
    /// is being resampled, without an overlay, or when it is hidden or not shown in 3D.
    pub fn request_3d(&self) -> Option<OverlayIn3d> {
        let OverlaySlot::Open(overlay) = self else {
            return None;
        };
        let style = &overlay.style;
        if !style.visible || !style.show_in_3d {
            return None;
        }
        let grid = overlay.grid_done.as_ref()?;
        Some(OverlayIn3d {
            volume: grid.volume.clone(),
            lut: lut_for(overlay.kind, style, &grid.labels),
        })
    }

    /// Whether the 3D view is still to show the overlay the link names: it is opening, or its
    /// 3D grid is being resampled (the test capture waits for it).
    pub fn pending_3d(&self) -> bool {
        match self {
            OverlaySlot::Closed | OverlaySlot::Failed { .. } => false,
            OverlaySlot::Opening { .. } => true,
            OverlaySlot::Open(overlay) => {
                overlay.grid_done.is_none() && overlay.error.is_none() && overlay.style.visible
            }
        }
    }

    /// The overlay over the oblique view's image of `request`, drawn in `image_rect` (nothing
    /// until it is sampled).
    pub fn paint_oblique(
        &mut self,
        ctx: &egui::Context,
        painter: &egui::Painter,
        request: &ObliqueRequest,
        image_rect: Rect,
    ) {
        if let OverlaySlot::Open(overlay) = self {
            overlay.paint_oblique(ctx, painter, request, image_rect);
        }
    }

    /// Test hook (`capture=1`): the overlay over the captured oblique image of `request` (its
    /// `rgba`), as [`OverlaySlot::composite`] does for a slice.
    pub fn composite_oblique(&self, request: &ObliqueRequest, rgba: &mut [u8]) -> bool {
        match self {
            OverlaySlot::Closed | OverlaySlot::Failed { .. } => true,
            OverlaySlot::Opening { .. } => false,
            OverlaySlot::Open(overlay) => {
                let Some(values) = overlay.oblique_values_for(request) else {
                    return false;
                };
                composite_over(rgba, overlay.kind, &overlay.style, values);
                true
            }
        }
    }

    /// Test hook (`capture=1`): the overlay over the captured slice `image`'s `rgba`. False
    /// while an overlay is opening or the image's overlay is not sampled yet (the capture
    /// waits); true with nothing to add when there is no overlay.
    pub fn composite(&self, image: &SliceImage, rgba: &mut [u8]) -> bool {
        match self {
            OverlaySlot::Closed | OverlaySlot::Failed { .. } => true,
            OverlaySlot::Opening { .. } => false,
            OverlaySlot::Open(overlay) => {
                let Some(values) = overlay.values_for(image) else {
                    return false;
                };
                composite_over(rgba, overlay.kind, &overlay.style, values);
                true
            }
        }
    }
}

/// Opens, replaces or closes the slice views' overlay as `link` names it, and applies the
/// link's style. Once a frame, before the views are drawn.
pub fn follow_link(
    link: &OverlayLink,
    slices: &mut SliceViews,
    token: Option<&str>,
    ctx: &egui::Context,
) {
    let wanted = link.name.as_deref().map(|name| (name, link.kind));
    if slices.overlay.identity() != wanted {
        slices.overlay = match wanted {
            None => OverlaySlot::Closed,
            Some((name, kind)) => {
                let store: Opening = Rc::default();
                let filled = store.clone();
                let (opened_name, token, repaint) =
                    (name.to_string(), token.map(str::to_string), ctx.clone());
                wasm_bindgen_futures::spawn_local(async move {
                    let opened = ServedStore::open(&opened_name, token).await;
                    *filled.borrow_mut() = Some(opened);
                    repaint.request_repaint();
                });
                OverlaySlot::Opening {
                    name: name.to_string(),
                    kind,
                    store,
                }
            }
        };
    }
    if let OverlaySlot::Opening { name, kind, store } = &slices.overlay {
        let opened = store.borrow_mut().take();
        if let Some(opened) = opened {
            let (name, kind) = (name.clone(), *kind);
            let geometry = slices.geometry().clone();
            slices.overlay =
                match opened.and_then(|s| PageOverlay::new(name.clone(), kind, &s, geometry)) {
                    Ok(overlay) => OverlaySlot::Open(Box::new(overlay)),
                    Err(e) => {
                        let error = format!("the overlay {name}: {e}");
                        web_sys::console::warn_1(&wasm_bindgen::JsValue::from_str(&error));
                        OverlaySlot::Failed { name, kind, error }
                    }
                };
        }
    }
    if let OverlaySlot::Open(overlay) = &mut slices.overlay {
        link.apply_to(&mut overlay.style);
    }
}

/// The side panel's Overlay section: which of the server's other stores is drawn over the
/// slices, as labels or continuous, and its style (strata-viewer-ui's controls, the desktop's).
/// What the link carries (store, kind, opacity, hidden labels, an edited colour map, range or
/// threshold) is written into `view`.
pub fn section(
    ui: &mut egui::Ui,
    view: &mut ViewState,
    slices: &mut SliceViews,
    stores: &RefCell<Option<Result<StoreList, ListStoresError>>>,
) {
    let mut chosen = view.overlay.name.clone();
    egui::ComboBox::from_id_salt("overlay store")
        .selected_text(chosen.as_deref().unwrap_or("none"))
        .show_ui(ui, |ui| {
            ui.selectable_value(&mut chosen, None, "none");
            match &*stores.borrow() {
                Some(Ok(list)) => {
                    for store in &list.stores {
                        if Some(&store.name) != view.store.as_ref() {
                            let [x, y, z] = store.dims;
                            let label = format!("{} ({x}×{y}×{z})", store.name);
                            ui.selectable_value(&mut chosen, Some(store.name.clone()), label);
                        }
                    }
                }
                Some(Err(e)) => {
                    ui.label(format!("the server's stores: {e}"));
                }
                None => {
                    ui.label("asking the server for its stores…");
                }
            }
        })
        .response
        .on_hover_text("Another store of this server, drawn over the slices");
    if chosen != view.overlay.name {
        view.overlay.name = chosen;
        view.overlay.hidden_labels.clear();
    }
    if view.overlay.name.is_none() {
        return;
    }
    ui.horizontal(|ui| {
        ui.selectable_value(&mut view.overlay.kind, None, "auto");
        ui.selectable_value(&mut view.overlay.kind, Some(OverlayKind::Labels), "labels");
        ui.selectable_value(
            &mut view.overlay.kind,
            Some(OverlayKind::Continuous),
            "continuous",
        );
    });
    match &mut slices.overlay {
        OverlaySlot::Closed => {}
        OverlaySlot::Opening { name, .. } => {
            ui.weak(format!("opening {name}…"));
        }
        OverlaySlot::Failed { error, .. } => {
            ui.colored_label(egui::Color32::LIGHT_RED, error.as_str());
        }
        OverlaySlot::Open(overlay) => {
            ui.weak(format!("{} as {}", overlay.name, overlay.kind.name()));
            ui.checkbox(&mut overlay.style.visible, "Show");
            let seen = overlay.labels_seen.clone();
            let before = overlay.style.clone();
            style_controls(
                ui,
                overlay.kind,
                &mut overlay.style,
                overlay.physical_range,
                &seen,
            );
            view.overlay.opacity = overlay.style.opacity;
            view.overlay.follow_style_edit(&before, &overlay.style);
            if view.overlay.hidden_labels != overlay.style.hidden_labels {
                view.overlay.hidden_labels = overlay.style.hidden_labels.clone();
            }
            if let Some(error) = &overlay.error {
                ui.colored_label(egui::Color32::LIGHT_RED, error.as_str());
            }
        }
    }
}

/// What one view's overlay is sampled for: a slice view's image or the oblique view's.
#[derive(Clone, Copy, Debug, PartialEq)]
enum SampledFor {
    Slice(SliceRequest),
    Oblique(ObliqueRequest),
}

/// One view's overlay: the image it is sampled for, its values once complete, its texture.
struct ViewOverlay {
    target: SampledFor,
    size: (usize, usize),
    values: Option<Arc<Vec<f32>>>,
    /// The texture and the values and style it was coloured from.
    texture: Option<(TextureHandle, Arc<Vec<f32>>, OverlayStyle)>,
}

/// An open overlay: its grids, style, fetcher and resident bricks.
pub struct PageOverlay {
    name: String,
    /// The kind the link asked for (None: the store decided).
    kind_asked: Option<OverlayKind>,
    kind: OverlayKind,
    style: OverlayStyle,
    physical_range: (f64, f64),
    grids: OverlayGrids,
    fetcher: Box<dyn BrickFetcher>,
    bricks: BrickLru,
    /// Bricks the views found missing this frame (asked for at the next pump).
    wanted: Vec<BrickId>,
    views: [Option<ViewOverlay>; 3],
    /// The oblique view's.
    oblique: Option<ViewOverlay>,
    /// Labels met in the sampled slices (the section lists them).
    labels_seen: BTreeSet<i64>,
    error: Option<String>,
    /// The 3D view's grid being resampled, a few slices a frame; then the grid.
    grid_3d: GridResampler,
    grid_done: Option<Arc<Resampled>>,
}

/// The resident bricks as strata-slices' level bricks: `None` while a brick is not fetched.
struct Resident<'a>(&'a mut BrickLru);

impl LevelBricks for Resident<'_> {
    type Error = SliceError;
    fn brick(&mut self, id: BrickId) -> Result<Option<Arc<Vec<u16>>>, SliceError> {
        Ok(self.0.get(id))
    }
}

impl PageOverlay {
    fn new(
        name: String,
        kind_asked: Option<OverlayKind>,
        store: &ServedStore,
        primary: VolumeGeometry,
    ) -> Result<PageOverlay, SourceError> {
        let fetcher = match store.start_fetching(FetchOptions {
            max_queued: OVERLAY_REQUESTS + 1,
            max_in_transit: OVERLAY_REQUESTS + 1,
            threads: 1,
        }) {
            Some(fetcher) => fetcher?,
            None => {
                return Err(SourceError::Refused {
                    location: store.location(),
                    message: "the store has no asynchronous brick path".into(),
                })
            }
        };
        let header = store.header();
        let mapping = header.value_mapping.mapping;
        let (a, b) = (
            mapping.physical(header.stored_range[0] as f64),
            mapping.physical(header.stored_range[1] as f64),
        );
        let physical_range = (a.min(b), a.max(b));
        let named_labels = !header.labels.is_empty();
        // A store that names its labels (a DICOM SEG) is a label map whatever was asked, as on
        // the desktop.
        let kind = match kind_asked {
            Some(_) if named_labels => OverlayKind::Labels,
            Some(kind) => kind,
            None => kind_of_store(named_labels, &mapping, physical_range),
        };
        let primary_level_dims = OctreeLayout::new(primary.dims).level_dims;
        let grids = OverlayGrids {
            primary,
            primary_level_dims,
            overlay: header.geometry.clone(),
            overlay_mapping: mapping,
            kind,
        };
        let grid_3d = GridResampler::new(
            grids.clone(),
            grid_dims(&grids.primary_level_dims, PAGE_OVERLAY_3D_MAX_VOXELS),
        );
        Ok(PageOverlay {
            name,
            kind_asked,
            kind,
            style: OverlayStyle::opening(label_table_of(&header.labels), physical_range),
            physical_range,
            grids,
            fetcher,
            bricks: BrickLru::new(OVERLAY_CACHE_BYTES),
            wanted: Vec::new(),
            views: [None, None, None],
            oblique: None,
            labels_seen: BTreeSet::new(),
            error: None,
            grid_3d,
            grid_done: None,
        })
    }

    fn pump(&mut self, ctx: &egui::Context) {
        for result in self.fetcher.try_results() {
            match result.outcome {
                Ok(voxels) => self.bricks.insert(result.id, voxels),
                Err(e) => self.error = Some(e.to_string()),
            }
            self.fetcher.complete(result.id);
        }
        self.step_grid_3d(ctx);
        let demand: Vec<(BrickId, f64)> = self
            .wanted
            .iter()
            .take(OVERLAY_REQUESTS)
            .enumerate()
            .map(|(rank, id)| (*id, (OVERLAY_REQUESTS - rank) as f64))
            .collect();
        self.fetcher.set_requests(&demand, &[]);
        if !demand.is_empty() {
            // Answers arrive between frames and wake nothing: poll until they are in.
            ctx.request_repaint();
        }
        self.wanted.clear();
    }

    /// A frame's share of the 3D grid ([`GRID_VOXELS_PER_FRAME`]) from the resident bricks; the
    /// bricks it lacks are asked for after the slice views' (they are what is being looked at).
    fn step_grid_3d(&mut self, ctx: &egui::Context) {
        if self.grid_done.is_some() || self.error.is_some() || !self.style.visible {
            return;
        }
        let stepped = self.grid_3d.step(
            &mut Resident(&mut self.bricks),
            GRID_VOXELS_PER_FRAME,
            MISSING_PER_SAMPLING,
        );
        match stepped {
            Ok(GridProgress::Complete(grid)) => {
                if self.kind == OverlayKind::Labels {
                    self.labels_seen.extend(grid.labels.iter().copied());
                }
                self.grid_done = Some(grid);
                ctx.request_repaint();
            }
            Ok(GridProgress::Incomplete { missing, .. }) => {
                for id in missing {
                    if !self.wanted.contains(&id) {
                        self.wanted.push(id);
                    }
                }
                ctx.request_repaint();
            }
            Err(e) => self.error = Some(format!("the overlay in 3D: {e}")),
        }
    }

    /// The sampled values over `image`, once complete.
    fn values_for(&self, image: &SliceImage) -> Option<&[f32]> {
        let shown = self.views[image.request.view.index()].as_ref()?;
        (shown.target == SampledFor::Slice(image.request)
            && shown.size == (image.width, image.height))
            .then_some(shown.values.as_deref()?.as_slice())
    }

    /// The sampled values over the oblique image of `request`, once complete.
    fn oblique_values_for(&self, request: &ObliqueRequest) -> Option<&[f32]> {
        let shown = self.oblique.as_ref()?;
        (shown.target == SampledFor::Oblique(*request))
            .then_some(shown.values.as_deref()?.as_slice())
    }

    fn paint(
        &mut self,
        ctx: &egui::Context,
        painter: &egui::Painter,
        image: &SliceImage,
        image_rect: Rect,
    ) {
        let view: SliceView = image.request.view;
        let target = SampledFor::Slice(image.request);
        let mut slot = self.views[view.index()].take();
        let texture = self.sampled_texture(ctx, &mut slot, target, (image.width, image.height));
        if let Some(texture) = texture {
            painter.add(egui::Shape::mesh(slice_mesh(
                texture,
                image_rect,
                image.inside_fraction,
                image.request.frame,
            )));
        }
        self.views[view.index()] = slot;
    }

    /// The oblique view's overlay over its image of `request` in `image_rect`, sampled at that
    /// image's pixel centres as the desktop's oblique view has it sampled.
    fn paint_oblique(
        &mut self,
        ctx: &egui::Context,
        painter: &egui::Painter,
        request: &ObliqueRequest,
        image_rect: Rect,
    ) {
        let target = SampledFor::Oblique(*request);
        let mut slot = self.oblique.take();
        let size = (request.width, request.height);
        if let Some(texture) = self.sampled_texture(ctx, &mut slot, target, size) {
            painter.image(
                texture,
                image_rect,
                Rect::from_min_max(egui::Pos2::ZERO, egui::Pos2::new(1.0, 1.0)),
                egui::Color32::WHITE,
            );
        }
        self.oblique = slot;
    }

    /// Samples `slot` for `target` (`size` pixels) from the resident bricks until complete
    /// (listing the missing ones for the next pump), and colours it into its texture, again
    /// only when the values or the style change. The texture to draw, once there is one.
    fn sampled_texture(
        &mut self,
        ctx: &egui::Context,
        slot: &mut Option<ViewOverlay>,
        target: SampledFor,
        size: (usize, usize),
    ) -> Option<egui::TextureId> {
        let current = slot
            .as_ref()
            .is_some_and(|s| s.target == target && s.size == size);
        if !current {
            let texture = slot.take().and_then(|s| s.texture);
            *slot = Some(ViewOverlay {
                target,
                size,
                values: None,
                texture,
            });
        }
        let shown = slot.as_mut()?;
        if shown.values.is_none() {
            let sampled = match target {
                SampledFor::Slice(request) => sample(
                    &mut Resident(&mut self.bricks),
                    &self.grids,
                    &slice_pixels(&self.grids, request),
                    size,
                    MISSING_PER_SAMPLING,
                ),
                SampledFor::Oblique(request) => sample(
                    &mut Resident(&mut self.bricks),
                    &self.grids,
                    &oblique_pixels(&self.grids, &request.plane, size.0, size.1),
                    size,
                    MISSING_PER_SAMPLING,
                ),
            };
            match sampled {
                Ok(Sampled::Complete(values)) => {
                    if self.kind == OverlayKind::Labels {
                        let labels = values.iter().filter(|v| v.is_finite() && **v != 0.0);
                        self.labels_seen.extend(labels.map(|v| *v as i64));
                    }
                    shown.values = Some(Arc::new(values));
                }
                Ok(Sampled::Incomplete { missing }) => {
                    for id in missing {
                        if !self.wanted.contains(&id) {
                            self.wanted.push(id);
                        }
                    }
                    ctx.request_repaint();
                }
                Err(e) => self.error = Some(e.to_string()),
            }
        }
        let values = shown.values.clone()?;
        let filter = match self.kind {
            OverlayKind::Labels => TextureOptions::NEAREST,
            OverlayKind::Continuous => TextureOptions::LINEAR,
        };
        let stale = shown
            .texture
            .as_ref()
            .is_none_or(|(_, from, style)| !Arc::ptr_eq(from, &values) || *style != self.style);
        if stale {
            let colours = colour_image(self.kind, &self.style, &values, size.0, size.1);
            match shown.texture.as_mut() {
                Some((texture, from, style)) => {
                    texture.set(colours, filter);
                    *from = values.clone();
                    *style = self.style.clone();
                }
                None => {
                    let name = match target {
                        SampledFor::Slice(request) => format!("overlay {}", request.view.name()),
                        SampledFor::Oblique(_) => "overlay oblique".to_string(),
                    };
                    let texture = ctx.load_texture(name, colours, filter);
                    shown.texture = Some((texture, values.clone(), self.style.clone()));
                }
            }
        }
        shown.texture.as_ref().map(|(texture, _, _)| texture.id())
    }
}
