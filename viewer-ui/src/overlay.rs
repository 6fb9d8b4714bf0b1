//! The overlay both viewers draw over the primary's slices (issue 47 item 3): a second volume,
//! a label map (a colour per label, per-label show/hide, an opacity) or a continuous overlay (a
//! colour map, range and threshold), on any grid. Everything here is platform-independent:
//! the desktop's reader thread (viewer/src/overlay.rs, blocking reads) and the page's fetches
//! (web/src/overlay_view.rs, bricks that may not be resident yet) feed the same sampling, the
//! same colouring and the same link keys.
//!
//! - The mapping: every slice pixel of the primary goes to patient space (LPS mm) through the
//!   primary's geometry and back into the overlay's index space through the overlay's
//!   ([`slice_pixels`], [`oblique_pixels`]).
//! - The sampling ([`sample`]): labels are categories, never averaged or interpolated, so they
//!   are read from the overlay's finest level (level 0) by nearest voxel whatever level the
//!   primary's slice uses (the coarser levels are means of 2×2×2 voxels, which would invent
//!   labels at boundaries: the mean of 1 and 3 is 2); a continuous overlay is trilinear
//!   between level-0 voxel centres. Bricks come through strata-slices' [`LevelBricks`], which
//!   may answer "not resident yet": the sampling then lists the bricks it misses.
//! - The colouring ([`colour_of`]) and the compositing of the premultiplied overlay over a
//!   slice ([`composite_over`], what the viewers' painters do when they draw one over the other).
//! - The link ([`OverlayLink`]): `overlay=NAME` (a store of the same server, the page),
//!   `overlay_kind=labels|continuous` (absent: the store decides, [`kind_of_store`]),
//!   `overlay_opacity=F` and `overlay_hidden=L1,L2` (the hidden labels), and a continuous
//!   overlay's `overlay_cmap=NAME` (as `cmap=` names maps), `overlay_range=LO,HI` and
//!   `overlay_threshold=T` (physical values, written so they read back exactly; absent: the
//!   opening style's, [`OverlayStyle::opening`]); defaults not written.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use glam::DVec3;
use strata_segment::label_colour;
use strata_slices::oblique::{LevelBricks, ObliquePlane};
use strata_slices::{ColourMap, SliceRequest};
use strata_storage::LabelInfo;
use strata_types::{
    BrickId, ValueMapping, VolumeGeometry, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD,
    BRICK_PAYLOAD_VOXELS,
};

/// The opacity an overlay opens with.
pub const DEFAULT_OPACITY: f32 = 0.5;
/// The largest label value a store without named labels may hold and still open as a label
/// map by itself: a segmentation's labels are small whole numbers, a CT's or MR's values run
/// into the thousands (or below zero).
pub const MAX_IMPLIED_LABEL: f64 = 255.0;
/// The most hidden labels a link may name (a link stays a line).
pub const MAX_LINK_HIDDEN_LABELS: usize = 256;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OverlayKind {
    /// Integer labels, 0 = background.
    Labels,
    /// Physical values with a colour map.
    Continuous,
}

impl OverlayKind {
    /// The link's and the panels' name.
    pub fn name(self) -> &'static str {
        match self {
            OverlayKind::Labels => "labels",
            OverlayKind::Continuous => "continuous",
        }
    }
}

/// How a store opens as an overlay when nobody said: a label map when its header names labels
/// (a DICOM SEG), or when its physical values are whole numbers from 0 to
/// [`MAX_IMPLIED_LABEL`] (a label map imported from NIfTI or NRRD); otherwise continuous.
/// Whole numbers are read from the value mapping, as the readouts decide that a scan's values
/// are integers (crate::presets::integer_values).
pub fn kind_of_store(
    named_labels: bool,
    mapping: &ValueMapping,
    physical_range: (f64, f64),
) -> OverlayKind {
    let integral = crate::presets::integer_values(mapping);
    if named_labels || integral && physical_range.0 >= 0.0 && physical_range.1 <= MAX_IMPLIED_LABEL
    {
        OverlayKind::Labels
    } else {
        OverlayKind::Continuous
    }
}

/// How the overlay is drawn (the overlay panels edit it).
#[derive(Clone, Debug, PartialEq)]
pub struct OverlayStyle {
    pub visible: bool,
    /// Drawn in the 3D view too, not only on the slices.
    pub show_in_3d: bool,
    /// 0..1, multiplied into every overlay pixel.
    pub opacity: f32,
    /// Labels hidden by the user.
    pub hidden_labels: BTreeSet<i64>,
    /// Names and colours the label store's header gives (a DICOM SEG's segments); labels not
    /// in it take [`label_colour`].
    pub label_table: BTreeMap<i64, LabelEntry>,
    pub colour_map: ColourMap,
    /// Continuous: values in `range` run through the colour map; below `threshold` nothing is
    /// drawn (the base shows through).
    pub range: (f64, f64),
    pub threshold: f64,
}

impl OverlayStyle {
    /// The style an overlay opens with: visible, half opaque, Hot over its whole range with the
    /// lower fifth transparent.
    pub fn opening(label_table: BTreeMap<i64, LabelEntry>, physical_range: (f64, f64)) -> Self {
        OverlayStyle {
            visible: true,
            show_in_3d: true,
            opacity: DEFAULT_OPACITY,
            hidden_labels: BTreeSet::new(),
            label_table,
            colour_map: ColourMap::Hot,
            range: physical_range,
            // Continuous: the lower fifth of the range stays transparent at first.
            threshold: physical_range.0 + 0.2 * (physical_range.1 - physical_range.0),
        }
    }
}

/// A named label with its colour (from the store header's labels).
#[derive(Clone, Debug, PartialEq)]
pub struct LabelEntry {
    pub name: String,
    pub colour: [u8; 3],
}

/// The label table of a store header: each label's name and its recommended colour, or the
/// default table's where the source recommends none.
pub fn label_table_of(labels: &[LabelInfo]) -> BTreeMap<i64, LabelEntry> {
    labels
        .iter()
        .map(|l| {
            let value = i64::from(l.value);
            let colour = l.rgb.unwrap_or_else(|| label_colour(value));
            (
                value,
                LabelEntry {
                    name: l.name.clone(),
                    colour,
                },
            )
        })
        .collect()
}

/// An editable layer's segments as an overlay's label table (each segment's name and colour)
/// and its hidden labels (the segments not shown): both viewers draw the segmentation's labels
/// as a label overlay with these, on the slices and in 3D.
pub fn segment_labels(
    segments: &strata_segment::SegmentTable,
) -> (BTreeMap<i64, LabelEntry>, BTreeSet<i64>) {
    let table = segments
        .iter()
        .map(|s| {
            let entry = LabelEntry {
                name: s.name.clone(),
                colour: s.rgb,
            };
            (i64::from(s.value), entry)
        })
        .collect();
    let hidden = segments
        .iter()
        .filter(|s| !s.visible)
        .map(|s| i64::from(s.value))
        .collect();
    (table, hidden)
}

/// Premultiplied RGBA for one sampled value under `style`.
pub fn colour_of(kind: OverlayKind, style: &OverlayStyle, value: f32) -> [u8; 4] {
    if !style.visible || !value.is_finite() {
        return [0; 4];
    }
    let (rgb, alpha) = match kind {
        OverlayKind::Labels => {
            let label = value as i64;
            if label == 0 || style.hidden_labels.contains(&label) {
                return [0; 4];
            }
            let colour = style
                .label_table
                .get(&label)
                .map_or_else(|| label_colour(label), |e| e.colour);
            (colour, style.opacity)
        }
        OverlayKind::Continuous => {
            let v = value as f64;
            if v < style.threshold {
                return [0; 4];
            }
            let (lo, hi) = style.range;
            let t = if hi > lo { (v - lo) / (hi - lo) } else { 1.0 };
            (style.colour_map.rgb(t), style.opacity)
        }
    };
    let a = alpha.clamp(0.0, 1.0);
    let premultiply = |c: u8| (c as f32 * a).round() as u8;
    [
        premultiply(rgb[0]),
        premultiply(rgb[1]),
        premultiply(rgb[2]),
        (255.0 * a).round() as u8,
    ]
}

/// The overlay image of `width`×`height` sampled `values` (row by row), premultiplied RGBA.
pub fn colour_image(
    kind: OverlayKind,
    style: &OverlayStyle,
    values: &[f32],
    width: usize,
    height: usize,
) -> egui::ColorImage {
    let pixels = values
        .iter()
        .map(|&v| {
            let [r, g, b, a] = colour_of(kind, style, v);
            egui::Color32::from_rgba_premultiplied(r, g, b, a)
        })
        .collect();
    egui::ColorImage::new([width, height], pixels)
}

/// Draws the overlay's `values` (coloured under `style`) over an opaque slice image `base`
/// (RGBA8, the same pixel order): premultiplied "over", `out = overlay + base × (1 − α)`,
/// which is what the viewers' painters do with the overlay's texture over the slice's.
pub fn composite_over(base: &mut [u8], kind: OverlayKind, style: &OverlayStyle, values: &[f32]) {
    for (pixel, &value) in base.chunks_exact_mut(4).zip(values) {
        let [r, g, b, a] = colour_of(kind, style, value);
        let keep = 255 - u16::from(a);
        for (channel, over) in pixel.iter_mut().zip([r, g, b]) {
            let below = (u16::from(*channel) * keep + 127) / 255;
            *channel = (u16::from(over) + below).min(255) as u8;
        }
    }
}

/// What the sampler needs to know about both volumes.
#[derive(Clone, Debug)]
pub struct OverlayGrids {
    pub primary: VolumeGeometry,
    /// The primary's level dims (the slice image's grid at each level).
    pub primary_level_dims: Vec<[u32; 3]>,
    pub overlay: VolumeGeometry,
    pub overlay_mapping: ValueMapping,
    pub kind: OverlayKind,
}

/// The level-0 continuous index (of the primary) at the centre of pixel (`x`, `y`) of the
/// primary's slice image for `request`: the same grid strata-slices' assembler fills.
pub fn primary_index_of_pixel(
    request: &SliceRequest,
    level_dims: &[[u32; 3]],
    x: usize,
    y: usize,
) -> DVec3 {
    let level = (request.level as usize).min(level_dims.len().saturating_sub(1));
    let dims = level_dims[level];
    let scale = (1u64 << level) as f64;
    let frame = request.frame;
    let slice = ((request.position + 0.5) / scale - 0.5)
        .round()
        .clamp(0.0, dims[frame.normal_axis] as f64 - 1.0);
    let centre = |i: f64| (i + 0.5) * scale - 0.5;
    let mut index = [0.0; 3];
    index[frame.normal_axis] = centre(slice);
    index[frame.across_axis] = centre(x as f64);
    index[frame.down_axis] = centre(y as f64);
    DVec3::from(index)
}

/// The overlay's continuous index at the centre of pixel (`x`, `y`) of the primary's slice
/// image for `request`.
pub fn slice_pixels(grids: &OverlayGrids, request: SliceRequest) -> impl Fn(usize, usize) -> DVec3 {
    let overlay_from_primary =
        grids.overlay.index_from_patient_linear() * grids.primary.patient_from_index_linear();
    let offset = grids.overlay.index_from_patient(grids.primary.origin());
    let level_dims = grids.primary_level_dims.clone();
    move |x, y| offset + overlay_from_primary * primary_index_of_pixel(&request, &level_dims, x, y)
}

/// The overlay's continuous index at the centre of pixel (`x`, `y`) of the oblique view's
/// `width`×`height` image of `plane` (strata-slices' oblique pixel centres).
pub fn oblique_pixels(
    grids: &OverlayGrids,
    plane: &ObliquePlane,
    width: usize,
    height: usize,
) -> impl Fn(usize, usize) -> DVec3 {
    let (plane, overlay) = (*plane, grids.overlay.clone());
    move |x, y| {
        overlay.index_from_patient(plane.patient_at(
            (x as f64 + 0.5) / width as f64,
            (y as f64 + 0.5) / height as f64,
        ))
    }
}

/// Calls `value_at` with the overlay's continuous index at every pixel that lies inside the
/// overlay's grid (of `dims` voxels); NaN elsewhere. `value_at` answering `None` (a brick not
/// resident) leaves that pixel NaN and goes on; an error stops.
pub fn sample_with<E>(
    dims: [u32; 3],
    index_of_pixel: &dyn Fn(usize, usize) -> DVec3,
    width: usize,
    height: usize,
    mut value_at: impl FnMut(DVec3) -> Result<Option<f64>, E>,
) -> Result<Vec<f32>, E> {
    let inside =
        |p: DVec3| (0..3).all(|a| p[a] >= -0.5 && p[a] < dims[a] as f64 - 0.5 && p[a].is_finite());
    let mut values = vec![f32::NAN; width * height];
    for y in 0..height {
        for x in 0..width {
            let p = index_of_pixel(x, y);
            if !inside(p) {
                continue;
            }
            if let Some(value) = value_at(p)? {
                values[y * width + x] = value as f32;
            }
        }
    }
    Ok(values)
}

/// What one sampling gave.
#[derive(Clone, Debug, PartialEq)]
pub enum Sampled {
    /// One value per pixel: labels as whole numbers, continuous values in physical units, NaN
    /// outside the overlay's grid.
    Complete(Vec<f32>),
    /// Level-0 bricks not resident yet, each once, in the order the image first needed them
    /// (at most the `max_missing` asked for).
    Incomplete { missing: Vec<BrickId> },
}

/// The stored value of one level-0 voxel through `bricks`, keeping the last brick at hand
/// (neighbouring pixels almost always fall into it).
struct Level0<'a, B: ?Sized> {
    bricks: &'a mut B,
    last: Option<(BrickId, Arc<Vec<u16>>)>,
    missing: Vec<BrickId>,
}

impl<B: LevelBricks + ?Sized> Level0<'_, B> {
    fn voxel(&mut self, index: [u32; 3]) -> Result<Option<u16>, B::Error> {
        let id = BrickId::new(0, index.map(|i| i / BRICK_CORE));
        let brick = match &self.last {
            Some((last_id, brick)) if *last_id == id => brick.clone(),
            _ => {
                if self.missing.contains(&id) {
                    return Ok(None);
                }
                match self.bricks.brick(id)? {
                    Some(brick) if brick.len() == BRICK_PAYLOAD_VOXELS => {
                        self.last = Some((id, brick.clone()));
                        brick
                    }
                    Some(brick) => {
                        return Err(strata_slices::SliceError::WrongBrickSize {
                            id,
                            voxels: brick.len(),
                        }
                        .into())
                    }
                    None => {
                        self.missing.push(id);
                        return Ok(None);
                    }
                }
            }
        };
        let local = index.map(|i| (i % BRICK_CORE + BRICK_APRON) as usize);
        let edge = BRICK_PAYLOAD as usize;
        Ok(Some(brick[(local[2] * edge + local[1]) * edge + local[0]]))
    }
}

/// Samples the overlay at the pixels `index_of_pixel` places in its grid, from its level-0
/// bricks. Labels: the nearest voxel's, rounded to a whole label. Continuous: trilinear between
/// level-0 voxel centres (clamped at the edges). Stops once `max_missing` bricks (at least one)
/// were found not resident.
pub fn sample<B: LevelBricks + ?Sized>(
    bricks: &mut B,
    grids: &OverlayGrids,
    index_of_pixel: &dyn Fn(usize, usize) -> DVec3,
    (width, height): (usize, usize),
    max_missing: usize,
) -> Result<Sampled, B::Error> {
    let dims = grids.overlay.dims;
    let mapping = grids.overlay_mapping;
    let max_missing = max_missing.max(1);
    let mut level0 = Level0 {
        bricks,
        last: None,
        missing: Vec::new(),
    };
    let values = sample_with(dims, index_of_pixel, width, height, |p| {
        if level0.missing.len() >= max_missing {
            return Ok::<_, B::Error>(None);
        }
        Ok(match grids.kind {
            OverlayKind::Labels => {
                let index = [0, 1, 2]
                    .map(|a| (p[a].round().max(0.0) as u32).min(dims[a].saturating_sub(1)));
                level0
                    .voxel(index)?
                    .map(|stored| mapping.physical(stored as f64).round())
            }
            OverlayKind::Continuous => {
                let mut sum = 0.0;
                let mut complete = true;
                for (index, weight) in strata_types::trilinear_corners(p.to_array(), dims) {
                    if weight > 0.0 {
                        match level0.voxel(index)? {
                            Some(stored) => sum += weight * mapping.physical(stored as f64),
                            None => complete = false,
                        }
                    }
                }
                complete.then_some(sum)
            }
        })
    })?;
    Ok(if level0.missing.is_empty() {
        Sampled::Complete(values)
    } else {
        Sampled::Incomplete {
            missing: level0.missing,
        }
    })
}

/// What a link's overlay key must hold (view_state names the key and the value around it).
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("{expected}")]
pub struct OverlayLinkError {
    pub expected: String,
}

/// The overlay a link names and how it is drawn (`overlay=`, `overlay_kind=`,
/// `overlay_opacity=`, `overlay_hidden=`, `overlay_cmap=`, `overlay_range=`,
/// `overlay_threshold=`).
#[derive(Clone, Debug, PartialEq)]
pub struct OverlayLink {
    /// A store of the server that served the page; None: no overlay.
    pub name: Option<String>,
    /// None: the store decides ([`kind_of_store`]).
    pub kind: Option<OverlayKind>,
    pub opacity: f32,
    pub hidden_labels: BTreeSet<i64>,
    /// A continuous overlay's colour map, range and threshold; None: the opening style's
    /// (which depends on the store's range, so the link cannot say it by itself).
    pub colour_map: Option<ColourMap>,
    pub range: Option<(f64, f64)>,
    pub threshold: Option<f64>,
}

impl Default for OverlayLink {
    fn default() -> Self {
        OverlayLink {
            name: None,
            kind: None,
            opacity: DEFAULT_OPACITY,
            hidden_labels: BTreeSet::new(),
            colour_map: None,
            range: None,
            threshold: None,
        }
    }
}

/// A colour map's name in a link: its label in lower case, as view_state's `cmap=` writes it
/// (view_state reads these keys through this module, so this module cannot call it).
fn colour_map_link_name(map: ColourMap) -> String {
    map.label().to_lowercase()
}

/// Largest magnitude of a link's overlay value: physical values (HU, SUV, a statistic) are far
/// inside it; bounds what a hostile link can make the sliders span.
pub const MAX_LINK_OVERLAY_VALUE: f64 = 1.0e9;

impl OverlayLink {
    /// The link's keys this reads (view_state hands them here).
    pub const KEYS: [&'static str; 7] = [
        "overlay",
        "overlay_kind",
        "overlay_opacity",
        "overlay_hidden",
        "overlay_cmap",
        "overlay_range",
        "overlay_threshold",
    ];

    /// Reads one of [`OverlayLink::KEYS`]; a bad value says what the key must hold.
    pub fn parse_key(&mut self, key: &str, value: &str) -> Result<(), OverlayLinkError> {
        let bad = |expected: &str| OverlayLinkError {
            expected: expected.into(),
        };
        match key {
            "overlay" => {
                if !strata_source::wire::is_valid_store_name(value) {
                    return Err(bad(
                        "a store name of letters, digits, '-', '_' and '.' (as `strata serve` \
                         lists them)",
                    ));
                }
                self.name = Some(value.to_string());
            }
            "overlay_kind" => {
                self.kind = Some(match value {
                    "labels" => OverlayKind::Labels,
                    "continuous" => OverlayKind::Continuous,
                    _ => return Err(bad("labels or continuous")),
                })
            }
            "overlay_opacity" => {
                self.opacity = match value.parse::<f32>() {
                    Ok(o) if (0.0..=1.0).contains(&o) => o,
                    _ => return Err(bad("a number from 0 to 1")),
                }
            }
            "overlay_hidden" => {
                let labels: Result<BTreeSet<i64>, _> =
                    value.split(',').map(|l| l.trim().parse::<i64>()).collect();
                self.hidden_labels = match labels {
                    Ok(labels) if labels.len() <= MAX_LINK_HIDDEN_LABELS => labels,
                    _ => {
                        return Err(bad(&format!(
                            "up to {MAX_LINK_HIDDEN_LABELS} whole label values L1,L2,…"
                        )))
                    }
                }
            }
            "overlay_cmap" => {
                let map = ColourMap::ALL
                    .into_iter()
                    .find(|map| colour_map_link_name(*map) == value);
                let names: Vec<String> = ColourMap::ALL
                    .into_iter()
                    .map(colour_map_link_name)
                    .collect();
                self.colour_map =
                    Some(map.ok_or_else(|| bad(&format!("one of {}", names.join(", "))))?);
            }
            "overlay_range" => {
                let expected =
                    format!("two numbers LO,HI within ±{MAX_LINK_OVERLAY_VALUE}, LO below HI");
                let range = value
                    .split_once(',')
                    .and_then(|(lo, hi)| Some((link_value(lo)?, link_value(hi)?)))
                    .filter(|(lo, hi)| lo < hi);
                self.range = Some(range.ok_or_else(|| bad(&expected))?);
            }
            "overlay_threshold" => {
                self.threshold =
                    Some(link_value(value).ok_or_else(|| {
                        bad(&format!("a number within ±{MAX_LINK_OVERLAY_VALUE}"))
                    })?);
            }
            _ => {}
        }
        Ok(())
    }

    /// The link's parts for this overlay (nothing without one; defaults not written).
    pub fn link_parts(&self) -> Vec<String> {
        let Some(name) = &self.name else {
            return Vec::new();
        };
        let mut parts = vec![format!("overlay={name}")];
        if let Some(kind) = self.kind {
            parts.push(format!("overlay_kind={}", kind.name()));
        }
        if self.opacity != DEFAULT_OPACITY {
            parts.push(format!("overlay_opacity={:.2}", self.opacity));
        }
        if !self.hidden_labels.is_empty() {
            let hidden: Vec<String> = self.hidden_labels.iter().map(i64::to_string).collect();
            parts.push(format!("overlay_hidden={}", hidden.join(",")));
        }
        // `{}` writes the shortest text that reads back as the same f64.
        if let Some(map) = self.colour_map {
            parts.push(format!("overlay_cmap={}", colour_map_link_name(map)));
        }
        if let Some((lo, hi)) = self.range {
            parts.push(format!("overlay_range={lo},{hi}"));
        }
        if let Some(threshold) = self.threshold {
            parts.push(format!("overlay_threshold={threshold}"));
        }
        parts
    }

    /// The link's opacity, hidden labels, colour map, range and threshold in `style` (those
    /// the link leaves out stay as they are).
    pub fn apply_to(&self, style: &mut OverlayStyle) {
        style.opacity = self.opacity;
        if style.hidden_labels != self.hidden_labels {
            style.hidden_labels = self.hidden_labels.clone();
        }
        if let Some(map) = self.colour_map {
            style.colour_map = map;
        }
        if let Some(range) = self.range {
            style.range = range;
        }
        if let Some(threshold) = self.threshold {
            style.threshold = threshold;
        }
    }

    /// Takes a continuous overlay's colour map, range and threshold from `style` into the link
    /// where `before` (the style before the panel's controls ran) differs from it: an edit.
    pub fn follow_style_edit(&mut self, before: &OverlayStyle, style: &OverlayStyle) {
        if before.colour_map != style.colour_map {
            self.colour_map = Some(style.colour_map);
        }
        if before.range != style.range {
            self.range = Some(style.range);
        }
        if before.threshold != style.threshold {
            self.threshold = Some(style.threshold);
        }
    }
}

/// A link's overlay value: a finite number within ±[`MAX_LINK_OVERLAY_VALUE`].
fn link_value(text: &str) -> Option<f64> {
    text.trim()
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite() && v.abs() <= MAX_LINK_OVERLAY_VALUE)
}

/// The overlay's style controls both viewers' panels draw (the desktop's Overlay panel and the
/// page's Overlay section): the opacity, then the labels (the store's named labels and those
/// met in the slices shown, a swatch and a show/hide checkbox each) or the colour map,
/// threshold and range of a continuous overlay over its `physical_range`.
pub fn style_controls(
    ui: &mut egui::Ui,
    kind: OverlayKind,
    style: &mut OverlayStyle,
    physical_range: (f64, f64),
    labels_seen: &BTreeSet<i64>,
) {
    ui.add(egui::Slider::new(&mut style.opacity, 0.0..=1.0).text("Opacity"));
    match kind {
        OverlayKind::Labels => {
            ui.label(
                egui::RichText::new("Labels from the finest level, nearest voxel (never averaged)")
                    .small(),
            );
            // The store's named labels (a DICOM SEG's segments) and any other label met in
            // the slices shown.
            let mut labels = labels_seen.clone();
            labels.extend(style.label_table.keys().copied());
            if labels.is_empty() {
                ui.label("No label in the slices shown yet.");
            }
            ui.horizontal_wrapped(|ui| {
                for label in labels {
                    let entry = style.label_table.get(&label);
                    let [r, g, b] = entry.map_or_else(|| label_colour(label), |e| e.colour);
                    let text = match entry {
                        Some(e) => format!("{label} {}", e.name),
                        None => format!("{label}"),
                    };
                    let mut shown = !style.hidden_labels.contains(&label);
                    let (swatch, _) =
                        ui.allocate_exact_size(egui::vec2(12.0, 12.0), egui::Sense::hover());
                    ui.painter()
                        .rect_filled(swatch, 2.0, egui::Color32::from_rgb(r, g, b));
                    if ui.checkbox(&mut shown, text).changed() {
                        if shown {
                            style.hidden_labels.remove(&label);
                        } else {
                            style.hidden_labels.insert(label);
                        }
                    }
                }
            });
        }
        OverlayKind::Continuous => {
            egui::ComboBox::from_label("Colour map")
                .selected_text(style.colour_map.label())
                .show_ui(ui, |ui| {
                    for map in ColourMap::ALL {
                        ui.selectable_value(&mut style.colour_map, map, map.label());
                    }
                });
            let (lo, hi) = physical_range;
            let span = lo..=hi.max(lo + 1e-9);
            ui.add(egui::Slider::new(&mut style.threshold, span.clone()).text("Threshold"));
            ui.add(egui::Slider::new(&mut style.range.0, span.clone()).text("Range from"));
            ui.add(egui::Slider::new(&mut style.range.1, span).text("Range to"));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_slices::{SliceFrame, SliceView};

    #[test]
    fn label_colours_are_distinct_for_the_first_labels_and_background_is_clear() {
        let colours: BTreeSet<[u8; 3]> = (1..=40).map(label_colour).collect();
        assert_eq!(colours.len(), 40, "40 labels, 40 colours");
        let style = OverlayStyle {
            visible: true,
            show_in_3d: true,
            opacity: 0.5,
            hidden_labels: [2].into_iter().collect(),
            label_table: BTreeMap::new(),
            colour_map: ColourMap::Hot,
            range: (0.0, 1.0),
            threshold: 0.5,
        };
        assert_eq!(colour_of(OverlayKind::Labels, &style, 0.0), [0; 4]);
        assert_eq!(colour_of(OverlayKind::Labels, &style, f32::NAN), [0; 4]);
        assert_eq!(
            colour_of(OverlayKind::Labels, &style, 2.0),
            [0; 4],
            "hidden"
        );
        let [r, g, b] = label_colour(1);
        let half = |c: u8| (c as f32 * 0.5).round() as u8;
        assert_eq!(
            colour_of(OverlayKind::Labels, &style, 1.0),
            [half(r), half(g), half(b), 128]
        );
        // Continuous: below the threshold clear, above it the colour map at its place in the
        // range; hiding the overlay clears everything.
        assert_eq!(colour_of(OverlayKind::Continuous, &style, 0.4), [0; 4]);
        let [r, g, b] = ColourMap::Hot.rgb(0.75);
        assert_eq!(
            colour_of(OverlayKind::Continuous, &style, 0.75),
            [half(r), half(g), half(b), 128]
        );
        // A header's label table (a DICOM SEG's recommended colours) wins over the default.
        let named = OverlayStyle {
            label_table: label_table_of(&[LabelInfo {
                value: 1,
                name: "liver".into(),
                rgb: Some([200, 100, 50]),
                category: None,
            }]),
            ..style.clone()
        };
        assert_eq!(
            colour_of(OverlayKind::Labels, &named, 1.0),
            [100, 50, 25, 128]
        );
        let hidden = OverlayStyle {
            visible: false,
            ..style
        };
        assert_eq!(colour_of(OverlayKind::Labels, &hidden, 1.0), [0; 4]);
    }

    /// Compositing is premultiplied "over": a clear overlay pixel leaves the slice, a half
    /// opaque one is its colour plus half the slice's.
    #[test]
    fn compositing_keeps_the_slice_under_clear_pixels_and_mixes_under_coloured_ones() {
        let style = OverlayStyle::opening(BTreeMap::new(), (0.0, 4.0));
        let mut base = vec![200, 100, 40, 255, 200, 100, 40, 255];
        composite_over(&mut base, OverlayKind::Labels, &style, &[0.0, 3.0]);
        assert_eq!(&base[..4], &[200, 100, 40, 255]);
        let [r, g, b, a] = colour_of(OverlayKind::Labels, &style, 3.0);
        assert_eq!(a, 128);
        let under = |c: u16| ((c * 127 + 127) / 255) as u8;
        assert_eq!(
            &base[4..],
            &[r + under(200), g + under(100), b + under(40), 255]
        );
    }

    /// Bricks of a label volume made in memory, resident or not as the test says.
    struct MemoryBricks {
        dims: [u32; 3],
        label: fn([u32; 3]) -> u16,
        resident: BTreeSet<[u32; 3]>,
    }

    impl LevelBricks for MemoryBricks {
        type Error = strata_slices::SliceError;
        fn brick(&mut self, id: BrickId) -> Result<Option<Arc<Vec<u16>>>, Self::Error> {
            if !self.resident.contains(&id.coords) {
                return Ok(None);
            }
            let edge = BRICK_PAYLOAD as usize;
            let mut voxels = vec![0u16; BRICK_PAYLOAD_VOXELS];
            for z in 0..edge {
                for y in 0..edge {
                    for x in 0..edge {
                        let index = [x, y, z].map(|v| v as i64 - BRICK_APRON as i64);
                        let global: [i64; 3] = std::array::from_fn(|a| {
                            (index[a] + (id.coords[a] * BRICK_CORE) as i64)
                                .clamp(0, self.dims[a] as i64 - 1)
                        });
                        voxels[(z * edge + y) * edge + x] = (self.label)(global.map(|g| g as u32));
                    }
                }
            }
            Ok(Some(Arc::new(voxels)))
        }
    }

    /// An axial slice of a 40³ primary over a 48³ label map on a grid shifted by 3.25 voxels:
    /// with no brick resident the sampling lists the bricks it needs (each once, at most as
    /// many as asked); with them resident every pixel has the nearest voxel's label.
    #[test]
    fn sampling_lists_missing_bricks_then_takes_the_nearest_label() {
        let mut primary = VolumeGeometry::axis_aligned([40, 40, 40], [1.0; 3]);
        primary.origin_lps_mm = [0.0; 3];
        let mut overlay = VolumeGeometry::axis_aligned([48, 48, 48], [1.0; 3]);
        overlay.origin_lps_mm = [-3.25; 3];
        let label = |i: [u32; 3]| ((i[0] / 5 + i[1] / 7 + i[2] / 9) % 4) as u16;
        let grids = OverlayGrids {
            primary: primary.clone(),
            primary_level_dims: vec![[40, 40, 40], [20, 20, 20]],
            overlay: overlay.clone(),
            overlay_mapping: ValueMapping::default(),
            kind: OverlayKind::Labels,
        };
        let frame = SliceFrame::for_view(SliceView::Axial, &primary);
        let request = SliceRequest {
            view: SliceView::Axial,
            frame,
            position: 20.0,
            level: 0,
        };
        let pixels = slice_pixels(&grids, request);
        let mut bricks = MemoryBricks {
            dims: [48, 48, 48],
            label,
            resident: BTreeSet::new(),
        };
        let Sampled::Incomplete { missing } =
            sample(&mut bricks, &grids, &pixels, (40, 40), 2).expect("sampling")
        else {
            panic!("nothing is resident");
        };
        assert_eq!(missing.len(), 2, "stops at the bound: {missing:?}");
        let Sampled::Incomplete { missing } =
            sample(&mut bricks, &grids, &pixels, (40, 40), 64).expect("sampling")
        else {
            panic!("nothing is resident");
        };
        // Overlay z = 20 + 3.25 rounds into brick row 0; x, y 3.25..42.25 span two bricks each.
        let listed: BTreeSet<[u32; 3]> = missing.iter().map(|id| id.coords).collect();
        assert_eq!(listed.len(), missing.len(), "each brick once");
        assert_eq!(
            listed,
            [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]
                .into_iter()
                .collect()
        );
        bricks.resident = listed;
        let Sampled::Complete(values) =
            sample(&mut bricks, &grids, &pixels, (40, 40), 64).expect("sampling")
        else {
            panic!("every brick is resident");
        };
        let mut compared = 0;
        for y in 0..40 {
            for x in 0..40 {
                let p = primary_index_of_pixel(&request, &grids.primary_level_dims, x, y);
                // Primary index i sits at overlay index i + 3.25 (no ties between voxels).
                let o = (p + DVec3::splat(3.25)).round();
                let expected = label([o.x as u32, o.y as u32, o.z as u32]);
                assert_eq!(values[y * 40 + x], f32::from(expected), "pixel ({x},{y})");
                compared += 1;
            }
        }
        assert_eq!(compared, 1600);
    }

    #[test]
    fn the_link_writes_only_what_differs_from_the_defaults_and_reads_it_back() {
        let mut link = OverlayLink::default();
        assert!(link.link_parts().is_empty(), "no overlay, no keys");
        link.parse_key("overlay", "labels.v1")
            .expect("a store name");
        assert_eq!(link.link_parts(), ["overlay=labels.v1"]);
        link.parse_key("overlay_opacity", "0.75").expect("opacity");
        link.parse_key("overlay_hidden", "3,1").expect("hidden");
        link.parse_key("overlay_kind", "continuous").expect("kind");
        link.parse_key("overlay_cmap", "viridis")
            .expect("colour map");
        link.parse_key("overlay_range", "-12.5,0.1").expect("range");
        link.parse_key("overlay_threshold", "-3.0000000001")
            .expect("threshold");
        let parts = link.link_parts();
        assert_eq!(
            parts,
            [
                "overlay=labels.v1",
                "overlay_kind=continuous",
                "overlay_opacity=0.75",
                "overlay_hidden=1,3",
                "overlay_cmap=viridis",
                "overlay_range=-12.5,0.1",
                "overlay_threshold=-3.0000000001"
            ]
        );
        // The style follows the link, and an edit of the style goes back into it.
        let mut style = OverlayStyle::opening(BTreeMap::new(), (0.0, 100.0));
        link.apply_to(&mut style);
        assert_eq!(
            (style.colour_map, style.range, style.threshold),
            (ColourMap::Viridis, (-12.5, 0.1), -3.0000000001)
        );
        let before = style.clone();
        style.threshold = 0.05;
        let mut edited = link.clone();
        edited.follow_style_edit(&before, &style);
        assert_eq!(
            (edited.colour_map, edited.range, edited.threshold),
            (Some(ColourMap::Viridis), Some((-12.5, 0.1)), Some(0.05))
        );
        let mut untouched = OverlayLink::default();
        untouched.follow_style_edit(&before, &before);
        assert_eq!(untouched, OverlayLink::default(), "no edit, no keys");
        let mut again = OverlayLink::default();
        for part in &parts {
            let (key, value) = part.split_once('=').expect("key=value");
            again.parse_key(key, value).expect("its own link");
        }
        assert_eq!(again, link);
        for (key, value, expected) in [
            ("overlay", "../etc", "a store name"),
            ("overlay_kind", "pet", "labels or continuous"),
            ("overlay_opacity", "2", "from 0 to 1"),
            ("overlay_hidden", "1,x", "whole label values"),
            (
                "overlay_cmap",
                "rainbow",
                "one of grey, inverted, hot, turbo, viridis",
            ),
            ("overlay_range", "5,1", "LO below HI"),
            ("overlay_range", "1,inf", "two numbers"),
            ("overlay_threshold", "NaN", "a number within"),
        ] {
            let e = OverlayLink::default()
                .parse_key(key, value)
                .expect_err("a bad value");
            assert!(e.to_string().contains(expected), "{key}: {e}");
        }
    }

    #[test]
    fn a_store_opens_as_labels_when_its_values_are_small_whole_numbers_or_named() {
        let whole = ValueMapping::default();
        assert_eq!(
            kind_of_store(false, &whole, (0.0, 4.0)),
            OverlayKind::Labels
        );
        assert_eq!(
            kind_of_store(false, &whole, (-1024.0, 3000.0)),
            OverlayKind::Continuous,
            "a CT's range"
        );
        let fractional = ValueMapping {
            slope: 0.01,
            intercept: 0.0,
        };
        assert_eq!(
            kind_of_store(false, &fractional, (0.0, 4.0)),
            OverlayKind::Continuous
        );
        assert_eq!(
            kind_of_store(true, &fractional, (0.0, 4.0)),
            OverlayKind::Labels
        );
    }
}
