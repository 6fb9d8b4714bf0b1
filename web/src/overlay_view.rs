//! The page's overlay (issue 47 item 3, wasm32 only): a second store of the same server drawn
//! over the three slice views, as a label map or a continuous overlay, with the desktop's
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
//! For the browser tests (web/tests/browser/overlay.rs) the slice capture (`capture=1`) waits
//! for the axial view's overlay and composites it over the slice ([`OverlaySlot::composite`]).

use std::cell::RefCell;
use std::collections::BTreeSet;
use std::rc::Rc;
use std::sync::Arc;

use egui::{Rect, TextureHandle, TextureOptions};
use strata_slices::oblique::LevelBricks;
use strata_slices::{BrickLru, SliceError, SliceImage, SliceRequest, SliceView};
use strata_source::wire::StoreList;
use strata_source::{BrickFetcher, FetchOptions, SourceError, VolumeSource};
use strata_types::{BrickId, OctreeLayout, VolumeGeometry};
use strata_viewer_ui::overlay::{
    colour_image, composite_over, kind_of_store, label_table_of, sample, slice_pixels,
    style_controls, OverlayGrids, OverlayKind, OverlayLink, OverlayStyle, Sampled,
};
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

/// One view's overlay: the slice it is sampled for, its values once complete, its texture.
struct ViewOverlay {
    request: SliceRequest,
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
    /// Labels met in the sampled slices (the section lists them).
    labels_seen: BTreeSet<i64>,
    error: Option<String>,
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
        Ok(PageOverlay {
            name,
            kind_asked,
            kind,
            style: OverlayStyle::opening(label_table_of(&header.labels), physical_range),
            physical_range,
            grids: OverlayGrids {
                primary,
                primary_level_dims,
                overlay: header.geometry.clone(),
                overlay_mapping: mapping,
                kind,
            },
            fetcher,
            bricks: BrickLru::new(OVERLAY_CACHE_BYTES),
            wanted: Vec::new(),
            views: [None, None, None],
            labels_seen: BTreeSet::new(),
            error: None,
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

    /// The sampled values over `image`, once complete.
    fn values_for(&self, image: &SliceImage) -> Option<&[f32]> {
        let shown = self.views[image.request.view.index()].as_ref()?;
        (shown.request == image.request && shown.size == (image.width, image.height))
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
        let size = (image.width, image.height);
        let slot = &mut self.views[view.index()];
        let current = slot
            .as_ref()
            .is_some_and(|s| s.request == image.request && s.size == size);
        if !current {
            let texture = slot.take().and_then(|s| s.texture);
            *slot = Some(ViewOverlay {
                request: image.request,
                size,
                values: None,
                texture,
            });
        }
        let Some(shown) = slot.as_mut() else {
            return;
        };
        if shown.values.is_none() {
            let pixels = slice_pixels(&self.grids, image.request);
            let sampled = sample(
                &mut Resident(&mut self.bricks),
                &self.grids,
                &pixels,
                size,
                MISSING_PER_SAMPLING,
            );
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
        let Some(values) = shown.values.clone() else {
            return;
        };
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
                    let texture =
                        ctx.load_texture(format!("overlay {}", view.name()), colours, filter);
                    shown.texture = Some((texture, values.clone(), self.style.clone()));
                }
            }
        }
        if let Some((texture, _, _)) = &shown.texture {
            painter.add(egui::Shape::mesh(slice_mesh(
                texture.id(),
                image_rect,
                image.inside_fraction,
                image.request.frame,
            )));
        }
    }
}
