//! A second volume drawn over the primary in the slice views: a label map (segmentation) with
//! a colour per label, per-label show/hide and an opacity, or a continuous overlay (PET, a
//! statistic map) with its own colour map, range and threshold. The overlay may lie on any
//! grid: every slice pixel of the primary is taken to patient space (LPS mm) through the
//! primary's geometry and back into the overlay's index space through the overlay's, so a
//! segmentation on a coarser or rotated grid lands where it belongs.
//!
//! Labels are categories, never averaged or interpolated: they are read from the overlay
//! store's finest level (level 0) with nearest-voxel sampling, whatever level the primary's
//! slice uses. The store's coarser levels are means of 2×2×2 voxels, which would invent labels
//! at boundaries (the mean of 1 and 3 is 2), so they are not used for labels at all. A
//! continuous overlay is sampled trilinearly from level 0.
//!
//! The oblique view's plane is sampled the same way (nearest label, trilinear continuous), at
//! the centres of the oblique image's pixels: each centre's patient position straight into the
//! overlay's index space in f64, so labels land where a voxel-exact CPU model puts them
//! (`tests::an_oblique_plane_takes_the_nearest_label_of_each_pixel_centre`).
//!
//! Sampling runs on a named thread (`strata-overlay-reader`) per overlay, with its own bounded
//! brick cache; the UI colours the sampled values (cheap) whenever the style changes. The model
//! (kind, style, grids), the pixel mapping, the sampling and the colouring are strata-viewer-ui's
//! `overlay`, which the page's overlay (web/src/overlay_view.rs) runs on fetched bricks; this
//! module is the desktop's half: the thread, its blocking reads and the editable label layer.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};

use glam::DVec3;
use strata_render::{ValueMapping, VolumeGeometry};
use strata_source::VolumeSource;
use strata_types::BrickId;

use super::orientation::SliceView;
use super::segmentation::SharedLayer;
use super::slices::SliceRequest;
use super::sync::{lock_ignoring_poison, wait_ignoring_poison, Repaint};
use strata_slices::oblique::{LevelBricks, ObliquePlane};
// The overlay's model, sampling and colouring, shared with the page (issue 47 item 3).
pub use strata_viewer_ui::overlay::{
    colour_of, label_table_of, oblique_pixels, primary_index_of_pixel, sample_with, slice_pixels,
    LabelEntry, OverlayGrids, OverlayKind, OverlayStyle, Sampled,
};

/// Decompressed overlay bricks kept (bytes).
pub const OVERLAY_CACHE_BYTES: usize = 96 << 20;

/// Overlay values for one primary slice image: one per pixel of that image, in its order
/// (`across` fastest). Labels as whole numbers, continuous values in physical units; NaN where
/// the pixel lies outside the overlay's grid.
#[derive(Clone, Debug)]
pub struct OverlaySlice {
    pub request: SliceRequest,
    /// The source's revision it was sampled at (an edited layer's changes count up).
    pub revision: u64,
    pub width: usize,
    pub height: usize,
    pub values: Arc<Vec<f32>>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct OverlayRequest {
    slice: SliceRequest,
    width: usize,
    height: usize,
    revision: u64,
}

/// The overlay over the oblique view's image: one value per pixel of the `width`×`height`
/// image of `plane` (row 0 at the top), as [`OverlaySlice`] holds them.
#[derive(Clone, Debug)]
pub struct ObliqueOverlay {
    pub plane: ObliquePlane,
    pub width: usize,
    pub height: usize,
    /// The source's revision it was sampled at.
    pub revision: u64,
    pub values: Arc<Vec<f32>>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct ObliqueOverlayRequest {
    plane: ObliquePlane,
    width: usize,
    height: usize,
    revision: u64,
}

/// What the reader thread has still to sample: the newest request of each slice view and of
/// the oblique view.
#[derive(Default)]
struct Pending {
    slices: [Option<OverlayRequest>; 3],
    oblique: Option<ObliqueOverlayRequest>,
}

/// One sampling job taken from [`Pending`].
enum Job {
    Slice(OverlayRequest),
    Oblique(ObliqueOverlayRequest),
}

impl Pending {
    fn take(&mut self) -> Option<Job> {
        self.slices
            .iter_mut()
            .find_map(|p| p.take())
            .map(Job::Slice)
            .or_else(|| self.oblique.take().map(Job::Oblique))
    }
}

struct Shared {
    pending: Mutex<Pending>,
    results: Mutex<[Option<OverlaySlice>; 3]>,
    oblique: Mutex<Option<ObliqueOverlay>>,
    labels_seen: Mutex<BTreeSet<i64>>,
    error: Mutex<Option<String>>,
    wake: Condvar,
    stop: AtomicBool,
}

/// What an overlay shows: an opened store, or the session's editable label layer, which the
/// sampler reads directly (an edit shows on the next slice sampled, nothing to re-upload but
/// that slice's texture).
#[derive(Clone)]
pub enum OverlaySource {
    Store(Arc<dyn VolumeSource>),
    Layer(Arc<SharedLayer>),
}

impl OverlaySource {
    fn revision(&self) -> u64 {
        match self {
            OverlaySource::Store(_) => 0,
            OverlaySource::Layer(layer) => layer.revision(),
        }
    }
}

/// An opened overlay: its store's facts, its style and its sampling thread.
pub struct Overlay {
    pub name: String,
    pub kind: OverlayKind,
    pub style: OverlayStyle,
    /// The overlay's physical value range.
    pub physical_range: (f64, f64),
    /// The overlay's store (or label layer) and both grids (the 3D view resamples from them,
    /// overlay_3d.rs).
    source: OverlaySource,
    grids: OverlayGrids,
    shared: Arc<Shared>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Overlay {
    pub fn start(
        store: Arc<dyn VolumeSource>,
        kind: OverlayKind,
        primary: VolumeGeometry,
        primary_level_dims: Vec<[u32; 3]>,
        repaint: Repaint,
    ) -> anyhow::Result<Self> {
        let header = store.header().clone();
        // A store that names its labels (a DICOM SEG) is a label map whatever was asked.
        let kind = if header.labels.is_empty() {
            kind
        } else {
            OverlayKind::Labels
        };
        let label_table = label_table_of(&header.labels);
        let mapping = header.value_mapping.mapping;
        let (a, b) = (
            mapping.physical(header.stored_range[0] as f64),
            mapping.physical(header.stored_range[1] as f64),
        );
        let physical_range = (a.min(b), a.max(b));
        let grids = OverlayGrids {
            primary,
            primary_level_dims,
            overlay: header.geometry.clone(),
            overlay_mapping: mapping,
            kind,
        };
        let name = store.location();
        Self::start_sampling(
            OverlaySource::Store(store),
            name,
            grids,
            label_table,
            physical_range,
            repaint,
        )
    }

    /// The session's editable label layer as a label overlay (segmentation.rs).
    pub fn start_editable(
        layer: Arc<SharedLayer>,
        name: String,
        primary: VolumeGeometry,
        primary_level_dims: Vec<[u32; 3]>,
        repaint: Repaint,
    ) -> anyhow::Result<Self> {
        let grids = OverlayGrids {
            primary,
            primary_level_dims,
            overlay: layer.geometry(),
            overlay_mapping: ValueMapping::default(),
            kind: OverlayKind::Labels,
        };
        let mut overlay = Self::start_sampling(
            OverlaySource::Layer(layer.clone()),
            name,
            grids,
            BTreeMap::new(),
            (0.0, f64::from(u16::MAX)),
            repaint,
        )?;
        overlay.follow_segments(layer.read().segments());
        Ok(overlay)
    }

    fn start_sampling(
        source: OverlaySource,
        name: String,
        grids: OverlayGrids,
        label_table: BTreeMap<i64, LabelEntry>,
        physical_range: (f64, f64),
        repaint: Repaint,
    ) -> anyhow::Result<Self> {
        let kind = grids.kind;
        let shared = Arc::new(Shared {
            pending: Mutex::new(Pending::default()),
            results: Mutex::new([None, None, None]),
            oblique: Mutex::new(None),
            labels_seen: Mutex::new(BTreeSet::new()),
            error: Mutex::new(None),
            wake: Condvar::new(),
            stop: AtomicBool::new(false),
        });
        let thread_source = source.clone();
        let thread_shared = shared.clone();
        let thread_grids = grids.clone();
        let thread = std::thread::Builder::new()
            .name("strata-overlay-reader".into())
            .spawn(move || {
                let mut cache = OverlayBrickCache::new(OVERLAY_CACHE_BYTES);
                loop {
                    let next = {
                        let mut pending = lock_ignoring_poison(&thread_shared.pending);
                        loop {
                            if thread_shared.stop.load(Ordering::Acquire) {
                                return;
                            }
                            if let Some(job) = pending.take() {
                                break job;
                            }
                            pending = wait_ignoring_poison(&thread_shared.wake, pending);
                        }
                    };
                    // Read before the layer: an edit after this makes the sample stale.
                    let revision = thread_source.revision();
                    let sampled = match next {
                        Job::Slice(next) => sample_source(
                            &thread_source,
                            &mut cache,
                            &thread_grids,
                            &slice_pixels(&thread_grids, next.slice),
                            next.width,
                            next.height,
                        )
                        .map(|values| {
                            let values = Arc::new(values);
                            let slice = OverlaySlice {
                                request: next.slice,
                                revision,
                                width: next.width,
                                height: next.height,
                                values: values.clone(),
                            };
                            lock_ignoring_poison(&thread_shared.results)[next.slice.view.index()] =
                                Some(slice);
                            values
                        }),
                        Job::Oblique(next) => sample_source(
                            &thread_source,
                            &mut cache,
                            &thread_grids,
                            &oblique_pixels(&thread_grids, &next.plane, next.width, next.height),
                            next.width,
                            next.height,
                        )
                        .map(|values| {
                            let values = Arc::new(values);
                            *lock_ignoring_poison(&thread_shared.oblique) = Some(ObliqueOverlay {
                                plane: next.plane,
                                width: next.width,
                                height: next.height,
                                revision,
                                values: values.clone(),
                            });
                            values
                        }),
                    };
                    match sampled {
                        Ok(values) => {
                            if kind == OverlayKind::Labels {
                                let mut seen = lock_ignoring_poison(&thread_shared.labels_seen);
                                for &v in values.iter() {
                                    if v.is_finite() && v != 0.0 {
                                        seen.insert(v as i64);
                                    }
                                }
                            }
                            *lock_ignoring_poison(&thread_shared.error) = None;
                        }
                        Err(e) => {
                            *lock_ignoring_poison(&thread_shared.error) = Some(format!("{e:#}"))
                        }
                    }
                    repaint();
                }
            })?;
        let style = OverlayStyle::opening(label_table, physical_range);
        Ok(Overlay {
            name,
            kind,
            style,
            physical_range,
            source,
            grids,
            shared,
            thread: Some(thread),
        })
    }

    /// The overlay's store (`None` for the editable label layer).
    pub fn source(&self) -> Option<&Arc<dyn VolumeSource>> {
        match &self.source {
            OverlaySource::Store(store) => Some(store),
            OverlaySource::Layer(_) => None,
        }
    }

    /// The editable label layer this overlay shows, if it shows one.
    pub fn layer(&self) -> Option<&Arc<SharedLayer>> {
        match &self.source {
            OverlaySource::Layer(layer) => Some(layer),
            OverlaySource::Store(_) => None,
        }
    }

    /// Takes the segments' names, colours and visibility into the style (the segment list
    /// edits them).
    pub fn follow_segments(&mut self, segments: &strata_segment::SegmentTable) {
        let (table, hidden) = strata_viewer_ui::overlay::segment_labels(segments);
        if table != self.style.label_table {
            self.style.label_table = table;
        }
        if hidden != self.style.hidden_labels {
            self.style.hidden_labels = hidden;
        }
    }

    /// The primary's and the overlay's grids.
    pub fn grids(&self) -> &OverlayGrids {
        &self.grids
    }

    /// Asks for the overlay over the primary slice image `slice` (`width`×`height` pixels).
    pub fn request(&self, slice: SliceRequest, width: usize, height: usize) {
        let revision = self.source.revision();
        let request = OverlayRequest {
            slice,
            width,
            height,
            revision,
        };
        let latest = self.latest(slice.view);
        if latest.is_some_and(|l| {
            l.request == slice && l.width == width && l.height == height && l.revision == revision
        }) {
            return;
        }
        let mut pending = lock_ignoring_poison(&self.shared.pending);
        if pending.slices[slice.view.index()] != Some(request) {
            pending.slices[slice.view.index()] = Some(request);
            self.shared.wake.notify_all();
        }
    }

    pub fn latest(&self, view: SliceView) -> Option<OverlaySlice> {
        lock_ignoring_poison(&self.shared.results)[view.index()].clone()
    }

    /// Asks for the overlay over the oblique view's `width`×`height` image of `plane`.
    pub fn request_oblique(&self, plane: ObliquePlane, width: usize, height: usize) {
        let request = ObliqueOverlayRequest {
            plane,
            width,
            height,
            revision: self.source.revision(),
        };
        let latest = self.latest_oblique();
        if latest.is_some_and(|l| {
            l.plane == plane
                && l.width == width
                && l.height == height
                && l.revision == request.revision
        }) {
            return;
        }
        let mut pending = lock_ignoring_poison(&self.shared.pending);
        if pending.oblique != Some(request) {
            pending.oblique = Some(request);
            self.shared.wake.notify_all();
        }
    }

    /// The newest overlay sampled over the oblique view's image.
    pub fn latest_oblique(&self) -> Option<ObliqueOverlay> {
        lock_ignoring_poison(&self.shared.oblique).clone()
    }

    /// A label's name from the store header ("kidney"), if it has one.
    pub fn label_name(&self, label: i64) -> Option<&str> {
        self.style.label_table.get(&label).map(|e| e.name.as_str())
    }

    /// Labels met so far in the sampled slices (the panel lists them).
    pub fn labels_seen(&self) -> BTreeSet<i64> {
        lock_ignoring_poison(&self.shared.labels_seen).clone()
    }

    pub fn error(&self) -> Option<String> {
        lock_ignoring_poison(&self.shared.error).clone()
    }

    /// What the overlay draws at one sampled value: premultiplied RGBA.
    pub fn colour_of(&self, value: f32) -> [u8; 4] {
        colour_of(self.kind, &self.style, value)
    }

    /// The overlay image for `slice`, premultiplied RGBA in its pixel order.
    pub fn colourise(&self, slice: &OverlaySlice) -> egui::ColorImage {
        self.colourise_values(&slice.values, slice.width, slice.height)
    }

    /// The overlay image of `width`×`height` sampled `values` (row by row), premultiplied RGBA.
    pub fn colourise_values(
        &self,
        values: &[f32],
        width: usize,
        height: usize,
    ) -> egui::ColorImage {
        strata_viewer_ui::overlay::colour_image(self.kind, &self.style, values, width, height)
    }
}

impl Drop for Overlay {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        self.shared.wake.notify_all();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Level-0 bricks of the overlay, bounded (the shared sampler keeps the last brick used at
/// hand itself).
pub struct OverlayBrickCache {
    budget_bricks: usize,
    bricks: HashMap<BrickId, Arc<Vec<u16>>>,
}

impl OverlayBrickCache {
    pub fn new(budget_bytes: usize) -> Self {
        OverlayBrickCache {
            budget_bricks: (budget_bytes / (strata_types::BRICK_PAYLOAD_VOXELS * 2)).max(16),
            bricks: HashMap::new(),
        }
    }

    /// Level-0 brick `id`, read when not cached.
    pub fn brick(
        &mut self,
        store: &dyn VolumeSource,
        id: BrickId,
    ) -> anyhow::Result<Arc<Vec<u16>>> {
        Ok(match self.bricks.get(&id) {
            Some(b) => b.clone(),
            None => {
                if self.bricks.len() >= self.budget_bricks {
                    // Whole-cache reset: simple, bounded, and a slice refills it.
                    self.bricks.clear();
                }
                let b = Arc::new(store.read_brick(id)?);
                self.bricks.insert(id, b.clone());
                b
            }
        })
    }
}

/// Samples the overlay over one primary slice image. Labels: nearest level-0 voxel, rounded to
/// a whole label. Continuous: trilinear between level-0 voxel centres (clamped at the edges).
pub fn sample_slice(
    store: &dyn VolumeSource,
    cache: &mut OverlayBrickCache,
    grids: &OverlayGrids,
    request: SliceRequest,
    width: usize,
    height: usize,
) -> anyhow::Result<OverlaySlice> {
    let values = sample_store(
        store,
        cache,
        grids,
        &slice_pixels(grids, request),
        width,
        height,
    )?;
    Ok(OverlaySlice {
        request,
        revision: 0,
        width,
        height,
        values: Arc::new(values),
    })
}

/// Samples the overlay's store or layer at the pixels `index_of_pixel` places in its grid.
fn sample_source(
    source: &OverlaySource,
    cache: &mut OverlayBrickCache,
    grids: &OverlayGrids,
    index_of_pixel: &dyn Fn(usize, usize) -> DVec3,
    width: usize,
    height: usize,
) -> anyhow::Result<Vec<f32>> {
    match source {
        OverlaySource::Store(store) => {
            sample_store(store.as_ref(), cache, grids, index_of_pixel, width, height)
        }
        OverlaySource::Layer(layer) => {
            sample_layer(&layer.read(), grids, index_of_pixel, width, height)
        }
    }
}

/// The overlay at every pixel through the shared sampler (strata-viewer-ui's overlay: labels
/// the nearest level-0 voxel's, continuous trilinear), every brick read here when missing.
fn sample_store(
    store: &dyn VolumeSource,
    cache: &mut OverlayBrickCache,
    grids: &OverlayGrids,
    index_of_pixel: &dyn Fn(usize, usize) -> DVec3,
    width: usize,
    height: usize,
) -> anyhow::Result<Vec<f32>> {
    let mut bricks = CachedStore { store, cache };
    match strata_viewer_ui::overlay::sample(&mut bricks, grids, index_of_pixel, (width, height), 1)?
    {
        Sampled::Complete(values) => Ok(values),
        // A blocking read answers every brick: nothing is ever missing here.
        Sampled::Incomplete { missing } => {
            anyhow::bail!("overlay bricks not read: {missing:?}")
        }
    }
}

/// The store's level-0 bricks through the bounded cache, read (blocking) when missing.
pub(crate) struct CachedStore<'a> {
    pub(crate) store: &'a dyn VolumeSource,
    pub(crate) cache: &'a mut OverlayBrickCache,
}

impl LevelBricks for CachedStore<'_> {
    type Error = anyhow::Error;
    fn brick(&mut self, id: BrickId) -> anyhow::Result<Option<Arc<Vec<u16>>>> {
        self.cache.brick(self.store, id).map(Some)
    }
}

/// Samples an editable label layer over one primary slice image: the nearest voxel's label,
/// each label brick read once per slice.
pub fn sample_layer_slice(
    layer: &strata_segment::LabelLayer,
    grids: &OverlayGrids,
    request: SliceRequest,
    width: usize,
    height: usize,
) -> anyhow::Result<OverlaySlice> {
    let values = sample_layer(layer, grids, &slice_pixels(grids, request), width, height)?;
    Ok(OverlaySlice {
        request,
        revision: 0,
        width,
        height,
        values: Arc::new(values),
    })
}

/// An editable label layer's nearest label at every pixel, each label brick read once per run
/// of pixels in it.
fn sample_layer(
    layer: &strata_segment::LabelLayer,
    grids: &OverlayGrids,
    index_of_pixel: &dyn Fn(usize, usize) -> DVec3,
    width: usize,
    height: usize,
) -> anyhow::Result<Vec<f32>> {
    let dims = grids.overlay.dims;
    let mut last: Option<(strata_segment::BrickKey, Option<Arc<[u16]>>)> = None;
    sample_with(dims, index_of_pixel, width, height, |p| {
        let index =
            [0, 1, 2].map(|a| (p[a].round().max(0.0) as u32).min(dims[a].saturating_sub(1)));
        let (key, at) = layer.grid().brick_of(index);
        if last.as_ref().is_none_or(|(k, _)| *k != key) {
            let brick = if layer.brick_is_empty(key) {
                None
            } else {
                Some(layer.brick(key)?)
            };
            last = Some((key, brick));
        }
        Ok::<_, anyhow::Error>(Some(
            last.as_ref()
                .and_then(|(_, b)| b.as_ref())
                .map_or(0.0, |b| f64::from(b[at])),
        ))
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    use crate::orientation::SliceFrame;
    use std::path::Path;
    use strata_storage::phantom::Phantom;

    /// Writes a NRRD of `kind` ("uint8" or "float") with `value(i, j, k)` at each voxel.
    pub(crate) fn write_nrrd(
        path: &Path,
        dims: [u32; 3],
        spacing: f64,
        origin: [f64; 3],
        float: bool,
        value: impl Fn(u32, u32, u32) -> f64,
    ) {
        let mut bytes = format!(
            "NRRD0004\ntype: {}\ndimension: 3\nsizes: {} {} {}\n\
             space: left-posterior-superior\n\
             space directions: ({spacing},0,0) (0,{spacing},0) (0,0,{spacing})\n\
             space origin: ({},{},{})\nencoding: raw\nendian: little\n\n",
            if float { "float" } else { "uint8" },
            dims[0],
            dims[1],
            dims[2],
            origin[0],
            origin[1],
            origin[2]
        )
        .into_bytes();
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    let v = value(i, j, k);
                    if float {
                        bytes.extend_from_slice(&(v as f32).to_le_bytes());
                    } else {
                        bytes.push(v as u8);
                    }
                }
            }
        }
        std::fs::write(path, bytes).expect("writing the test NRRD");
    }

    pub(crate) fn import(input: &Path, store: &Path) -> Arc<dyn VolumeSource> {
        let opened = strata_storage::readers::open_source(input, &Default::default())
            .expect("reading the test NRRD");
        strata_storage::import::import_source(opened, store, &Default::default())
            .expect("importing the test NRRD");
        Arc::new(strata_storage::Store::open(store).expect("opening the overlay store"))
    }

    /// The label test volume: stripes of labels 0..=4 whose boundaries cross at odd places,
    /// on a 40³ grid of 10 mm voxels (two octree levels) shifted against the primary's.
    pub(crate) fn label_of(i: u32, j: u32, k: u32) -> f64 {
        ((i / 5 + 2 * (j / 7) + k / 9) % 5) as f64
    }
    pub(crate) const LABEL_DIMS: [u32; 3] = [40, 40, 40];
    pub(crate) const LABEL_SPACING: f64 = 10.0;
    pub(crate) const LABEL_ORIGIN: [f64; 3] = [-187.0, -203.0, -195.0];

    fn grids(
        primary_store: &dyn VolumeSource,
        overlay: &dyn VolumeSource,
        kind: OverlayKind,
    ) -> OverlayGrids {
        OverlayGrids {
            primary: primary_store.header().geometry.clone(),
            primary_level_dims: primary_store.layout().level_dims.clone(),
            overlay: overlay.header().geometry.clone(),
            overlay_mapping: overlay.header().value_mapping.mapping,
            kind,
        }
    }

    fn primary(dir: &Path) -> Arc<dyn VolumeSource> {
        let path = dir.join("primary.strata");
        Phantom::cube(48)
            .write_store(&path, &Default::default())
            .expect("phantom store");
        Arc::new(strata_storage::Store::open(&path).expect("open"))
    }

    /// Every pixel of an axial slice of the primary, at level 0 and at the coarser level 1,
    /// carries exactly the label of the overlay voxel nearest to its patient position
    /// (computed here in f64 from the label function, not from the store), and only labels
    /// that exist: the store's mean coarse levels never leak in.
    #[test]
    fn labels_are_the_nearest_level_zero_label_at_each_pixels_patient_position() {
        let dir = tempfile::tempdir().expect("temp dir");
        let primary = primary(dir.path());
        let nrrd = dir.path().join("labels.nrrd");
        write_nrrd(
            &nrrd,
            LABEL_DIMS,
            LABEL_SPACING,
            LABEL_ORIGIN,
            false,
            label_of,
        );
        let overlay = import(&nrrd, &dir.path().join("labels.strata"));
        assert!(
            overlay.layout().level_count() > 1,
            "the overlay has coarse levels to avoid"
        );
        let grids = grids(primary.as_ref(), overlay.as_ref(), OverlayKind::Labels);
        let frame = SliceFrame::for_view(SliceView::Axial, &grids.primary);
        let mut cache = OverlayBrickCache::new(8 << 20);
        let mut compared = 0;
        for (level, position) in [(0u8, 20.0), (1, 31.0)] {
            let request = SliceRequest {
                view: SliceView::Axial,
                frame,
                position,
                level,
            };
            let dims = grids.primary_level_dims[level as usize];
            let (w, h) = (
                dims[frame.across_axis] as usize,
                dims[frame.down_axis] as usize,
            );
            let slice = sample_slice(overlay.as_ref(), &mut cache, &grids, request, w, h)
                .expect("sampling");
            for y in 0..h {
                for x in 0..w {
                    let index = primary_index_of_pixel(&request, &grids.primary_level_dims, x, y);
                    let patient = grids.primary.patient_from_index(index);
                    let o = grids.overlay.index_from_patient(patient);
                    let got = slice.values[y * w + x];
                    let outside = (0..3).any(|a| o[a] < -0.5 || o[a] >= LABEL_DIMS[a] as f64 - 0.5);
                    // A centre exactly between two overlay voxels may round either way.
                    let tie = (0..3).any(|a| ((o[a] - o[a].floor()) - 0.5).abs() < 1e-6);
                    if tie {
                        continue;
                    }
                    if outside {
                        assert!(
                            got.is_nan(),
                            "pixel ({x},{y}) outside the overlay has {got}"
                        );
                        continue;
                    }
                    let n = o.round();
                    let expected = label_of(n.x as u32, n.y as u32, n.z as u32);
                    assert_eq!(
                        got as f64, expected,
                        "level {level} pixel ({x},{y}) at {o:?}"
                    );
                    compared += 1;
                }
            }
        }
        assert!(compared > 1000, "only {compared} pixels compared");
    }

    /// A continuous overlay samples trilinearly: for a linear field, trilinear interpolation
    /// is exact, so inside the grid every pixel must equal the field at its overlay index up to
    /// the import's u16 quantisation (the store reports its bound).
    #[test]
    fn a_continuous_overlay_matches_the_trilinear_reference() {
        let dir = tempfile::tempdir().expect("temp dir");
        let primary = primary(dir.path());
        let field = |i: f64, j: f64, k: f64| 3.0 * i + 5.0 * j - 2.0 * k + 40.25;
        let nrrd = dir.path().join("pet.nrrd");
        write_nrrd(
            &nrrd,
            LABEL_DIMS,
            LABEL_SPACING,
            LABEL_ORIGIN,
            true,
            |i, j, k| field(i as f64, j as f64, k as f64),
        );
        let overlay = import(&nrrd, &dir.path().join("pet.strata"));
        let bound = overlay.header().quantization_error;
        let grids = grids(primary.as_ref(), overlay.as_ref(), OverlayKind::Continuous);
        let frame = SliceFrame::for_view(SliceView::Coronal, &grids.primary);
        let request = SliceRequest {
            view: SliceView::Coronal,
            frame,
            position: 22.0,
            level: 0,
        };
        let dims = grids.primary_level_dims[0];
        let (w, h) = (
            dims[frame.across_axis] as usize,
            dims[frame.down_axis] as usize,
        );
        let mut cache = OverlayBrickCache::new(8 << 20);
        let slice =
            sample_slice(overlay.as_ref(), &mut cache, &grids, request, w, h).expect("sampling");
        let mut compared = 0;
        for y in 0..h {
            for x in 0..w {
                let index = primary_index_of_pixel(&request, &grids.primary_level_dims, x, y);
                let o = grids
                    .overlay
                    .index_from_patient(grids.primary.patient_from_index(index));
                // Interior only: at the edges the sampler clamps (no extrapolation).
                if (0..3).any(|a| o[a] < 0.0 || o[a] > LABEL_DIMS[a] as f64 - 1.0) {
                    continue;
                }
                let expected = field(o.x, o.y, o.z);
                let got = slice.values[y * w + x] as f64;
                // Quantisation of each corner (bound) plus f32 storage of the result.
                let tolerance = bound + 1e-6 * expected.abs() + 1e-4;
                assert!(
                    (got - expected).abs() <= tolerance,
                    "pixel ({x},{y}): {got} vs {expected} (±{tolerance})"
                );
                compared += 1;
            }
        }
        assert!(compared > 500, "only {compared} pixels compared");
    }

    /// Over a plane tilted 0.5 and 0.3 rad off axial, the oblique sampling of a label map
    /// gives each pixel the label of the label voxel nearest to its centre, computed here in
    /// f64 from the NRRD header and the label function (exact; only pixels whose centre lies
    /// within 1e-6 voxels of a boundary between two voxels are left out, where rounding may
    /// pick either), NaN outside the label grid: from the imported store and from the same
    /// file loaded as an editable layer alike.
    #[test]
    fn an_oblique_plane_takes_the_nearest_label_of_each_pixel_centre() {
        let dir = tempfile::tempdir().expect("temp dir");
        let primary = primary(dir.path());
        let nrrd = dir.path().join("labels.nrrd");
        write_nrrd(
            &nrrd,
            LABEL_DIMS,
            LABEL_SPACING,
            LABEL_ORIGIN,
            false,
            label_of,
        );
        let store = import(&nrrd, &dir.path().join("labels.strata"));
        let grids = grids(primary.as_ref(), store.as_ref(), OverlayKind::Labels);
        let layer = strata_segment::io::load_label_file(&nrrd).expect("the NRRD as a layer");
        assert_eq!(layer.grid().geometry(), &grids.overlay, "one grid for both");
        let origin = DVec3::from(LABEL_ORIGIN);
        let centre = origin + DVec3::new(17.3, 21.6, 19.2) * LABEL_SPACING;
        let plane = ObliquePlane::axial(centre, 520.0).rotated(0.5, 0.3);
        let (w, h) = (96, 80);
        let model = |x: usize, y: usize| {
            let across = (x as f64 + 0.5) / w as f64 - 0.5;
            let down = (y as f64 + 0.5) / h as f64 - 0.5;
            let p = plane.centre + plane.right * (across * 520.0) + plane.down * (down * 520.0);
            let o = (p - origin) / LABEL_SPACING;
            if (0..3).any(|a| o[a] < -0.5 || o[a] >= LABEL_DIMS[a] as f64 - 0.5) {
                return Some(f64::NAN);
            }
            if (0..3).any(|a| ((o[a] - o[a].floor()) - 0.5).abs() < 1e-6) {
                return None;
            }
            let n = o.round();
            Some(label_of(n.x as u32, n.y as u32, n.z as u32))
        };
        let sources = [
            ("store", OverlaySource::Store(store.clone())),
            (
                "layer",
                OverlaySource::Layer(Arc::new(SharedLayer::new(layer))),
            ),
        ];
        for (name, source) in sources {
            let mut cache = OverlayBrickCache::new(8 << 20);
            let pixels = oblique_pixels(&grids, &plane, w, h);
            let values =
                sample_source(&source, &mut cache, &grids, &pixels, w, h).expect("sampling");
            let (mut compared, mut outside, mut labels) = (0, 0, BTreeSet::new());
            for y in 0..h {
                for x in 0..w {
                    let Some(expected) = model(x, y) else {
                        continue;
                    };
                    let got = values[y * w + x];
                    if expected.is_nan() {
                        assert!(got.is_nan(), "{name}: pixel ({x},{y}) outside has {got}");
                        outside += 1;
                        continue;
                    }
                    assert_eq!(got as f64, expected, "{name}: pixel ({x},{y})");
                    labels.insert(expected as i64);
                    compared += 1;
                }
            }
            assert!(compared > 3000, "{name}: only {compared} pixels compared");
            assert!(outside > 100, "{name}: the plane leaves the grid");
            assert_eq!(labels.len(), 5, "{name}: every label is crossed");
        }
    }
}
