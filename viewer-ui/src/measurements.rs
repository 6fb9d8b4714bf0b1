//! Measurements, shared by both viewers (issue 47): distance and angle rulers (on slices, or
//! between points picked in the desktop's 3D view) and box or ellipse regions of interest on a
//! slice with mean, SD, min, max, area and voxel count in physical units. Points are level-0
//! continuous indices; lengths, angles and areas are computed in patient millimetres, so
//! anisotropic voxels measure right.
//!
//! Here live the model ([`Measurements`]: the list, the tool, the one being drawn), the
//! statistics ([`roi_stats`], over a slice image of strata-slices' assembler, the one both
//! viewers slice with), a slice view's gestures ([`slice_input`]: drag a ruler or a region,
//! click the three points of an angle) and drawing ([`paint_on_slice`]), the list panel
//! ([`panel`]), and the link's `m=` value ([`to_link_text`], [`from_link_text`]), so a link
//! opens with its measurements in either viewer. Rulers and angles placed by clicks in the 3D
//! view (each click's point is what [`crate::picking`] picks there, fed to
//! [`Measurements::click`]) are drawn over it by [`paint_in_3d`], in both viewers.
//! Tests: the unit tests below; the page's gestures against these functions in
//! web/tests/browser/measure.rs; the desktop's in viewer/tests/ui/measurements.rs.

use egui::{Color32, Pos2, Rect, Stroke, Vec2};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use strata_render::{Camera, ValueMapping, VolumeGeometry};
use strata_slices::{SliceFrame, SliceImage, SliceView};

use crate::picking::project_to_view;
use crate::slice_canvas::{fraction_at, keep_inside, screen_at};

/// The tool the left mouse button uses in the views.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum Tool {
    /// Move the crosshair (slices), orbit (3D).
    #[default]
    Navigate,
    Distance,
    Angle,
    BoxRoi,
    EllipseRoi,
}

impl Tool {
    pub const ALL: [Tool; 5] = [
        Tool::Navigate,
        Tool::Distance,
        Tool::Angle,
        Tool::BoxRoi,
        Tool::EllipseRoi,
    ];

    pub fn label(self) -> &'static str {
        match self {
            Tool::Navigate => "Navigate",
            Tool::Distance => "Ruler",
            Tool::Angle => "Angle",
            Tool::BoxRoi => "Box ROI",
            Tool::EllipseRoi => "Ellipse ROI",
        }
    }

    pub fn hint(self) -> &'static str {
        match self {
            Tool::Navigate => "Left click / drag moves the crosshair",
            Tool::Distance => "Drag on a slice, or click two points in 3D",
            Tool::Angle => "Click three points (the second is the vertex), on a slice or in 3D",
            Tool::BoxRoi | Tool::EllipseRoi => "Drag across the region on a slice",
        }
    }
}

/// Statistics of the voxels whose centres lie inside a region, in physical units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RoiStats {
    pub mean: f64,
    pub sd: f64,
    pub min: f64,
    pub max: f64,
    pub voxels: u64,
    /// The shape's area in mm².
    pub area_mm2: f64,
    /// Octree level the values came from (0 = full resolution).
    pub level: u8,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub enum Shape {
    Distance {
        a: [f64; 3],
        b: [f64; 3],
    },
    Angle {
        a: [f64; 3],
        vertex: [f64; 3],
        b: [f64; 3],
    },
    /// A box or an ellipse inscribed in it, drawn on `view`'s slice between two corners.
    Roi {
        view: SliceView,
        ellipse: bool,
        a: [f64; 3],
        b: [f64; 3],
        stats: Option<RoiStats>,
    },
}

/// A region's statistics are derived (from its corners and its slice, filled in when the slice
/// arrives): two regions with the same corners on the same view are the same measurement, so
/// that filling them in is no change to undo (the desktop's history, the page's snapshots of
/// its view) and a link read back equals what was written.
impl PartialEq for Shape {
    fn eq(&self, other: &Shape) -> bool {
        match (self, other) {
            (Shape::Distance { a, b }, Shape::Distance { a: a2, b: b2 }) => a == a2 && b == b2,
            (
                Shape::Angle { a, vertex, b },
                Shape::Angle {
                    a: a2,
                    vertex: v2,
                    b: b2,
                },
            ) => a == a2 && vertex == v2 && b == b2,
            (
                Shape::Roi {
                    view,
                    ellipse,
                    a,
                    b,
                    ..
                },
                Shape::Roi {
                    view: view2,
                    ellipse: ellipse2,
                    a: a2,
                    b: b2,
                    ..
                },
            ) => view == view2 && ellipse == ellipse2 && a == a2 && b == b2,
            _ => false,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Measurement {
    pub id: u64,
    pub shape: Shape,
}

fn mm(g: &VolumeGeometry, index: [f64; 3]) -> DVec3 {
    g.patient_from_index(DVec3::from(index))
}

/// Patient distance in mm between two level-0 indices.
pub fn distance_mm(g: &VolumeGeometry, a: [f64; 3], b: [f64; 3]) -> f64 {
    (mm(g, b) - mm(g, a)).length()
}

/// The angle at `vertex` in degrees, in patient space.
pub fn angle_deg(g: &VolumeGeometry, a: [f64; 3], vertex: [f64; 3], b: [f64; 3]) -> f64 {
    let (u, v) = (mm(g, a) - mm(g, vertex), mm(g, b) - mm(g, vertex));
    let denominator = u.length() * v.length();
    if denominator <= 0.0 {
        return 0.0;
    }
    (u.dot(v) / denominator)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

impl Measurement {
    /// One line for the list and the label on screen.
    pub fn describe(&self, g: &VolumeGeometry, unit: &str) -> String {
        match &self.shape {
            Shape::Distance { a, b } => format!("Ruler {:.1} mm", distance_mm(g, *a, *b)),
            Shape::Angle { a, vertex, b } => {
                format!("Angle {:.1}°", angle_deg(g, *a, *vertex, *b))
            }
            Shape::Roi { ellipse, stats, .. } => {
                let kind = if *ellipse { "Ellipse" } else { "Box" };
                match stats {
                    Some(s) => format!(
                        "{kind} mean {:.1} SD {:.1} min {:.0} max {:.0} {unit} · {:.1} mm² · {} voxels{}",
                        s.mean,
                        s.sd,
                        s.min,
                        s.max,
                        s.area_mm2,
                        s.voxels,
                        if s.level > 0 {
                            format!(" (level {})", s.level)
                        } else {
                            String::new()
                        }
                    ),
                    None => format!("{kind} (no values yet)"),
                }
            }
        }
    }

    /// The points that define it (for drawing and for "is it on this slice").
    pub fn points(&self) -> Vec<[f64; 3]> {
        match &self.shape {
            Shape::Distance { a, b } => vec![*a, *b],
            Shape::Angle { a, vertex, b } => vec![*a, *vertex, *b],
            Shape::Roi { a, b, .. } => vec![*a, *b],
        }
    }
}

/// Statistics of a box or ellipse ROI from corners `a`, `b` (level-0 indices on the slice
/// `image` shows), over the image's voxels whose centres lie inside the shape.
pub fn roi_stats(
    image: &SliceImage,
    g: &VolumeGeometry,
    mapping: ValueMapping,
    ellipse: bool,
    a: [f64; 3],
    b: [f64; 3],
) -> Option<RoiStats> {
    let frame: SliceFrame = image.request.frame;
    let (ax, dx) = (frame.across_axis, frame.down_axis);
    let level = image.request.level;
    let scale = (1u64 << level) as f64;
    let (a0, a1) = (a[ax].min(b[ax]), a[ax].max(b[ax]));
    let (d0, d1) = (a[dx].min(b[dx]), a[dx].max(b[dx]));
    let (ca, cd) = ((a0 + a1) * 0.5, (d0 + d1) * 0.5);
    let (ra, rd) = ((a1 - a0) * 0.5, (d1 - d0) * 0.5);
    let (mut n, mut sum, mut sum2) = (0u64, 0.0f64, 0.0f64);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for y in 0..image.height {
        // Level-L voxel centre in level-0 index units.
        let d = (y as f64 + 0.5) * scale - 0.5;
        if d < d0 || d > d1 {
            continue;
        }
        for x in 0..image.width {
            let across = (x as f64 + 0.5) * scale - 0.5;
            if across < a0 || across > a1 {
                continue;
            }
            if ellipse {
                let (u, v) = ((across - ca) / ra.max(1e-12), (d - cd) / rd.max(1e-12));
                if u * u + v * v > 1.0 {
                    continue;
                }
            }
            let value = mapping.physical(image.values[y * image.width + x] as f64);
            n += 1;
            sum += value;
            sum2 += value * value;
            lo = lo.min(value);
            hi = hi.max(value);
        }
    }
    if n == 0 {
        return None;
    }
    let mean = sum / n as f64;
    // Population SD of the region's voxels (what Slicer's segment statistics report).
    let sd = (sum2 / n as f64 - mean * mean).max(0.0).sqrt();
    let box_area = (a1 - a0) * g.spacing_mm[ax] * (d1 - d0) * g.spacing_mm[dx];
    Some(RoiStats {
        mean,
        sd,
        min: lo,
        max: hi,
        voxels: n,
        area_mm2: if ellipse {
            box_area * std::f64::consts::FRAC_PI_4
        } else {
            box_area
        },
        level,
    })
}

/// A measurement being drawn.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Draft {
    pub points: Vec<[f64; 3]>,
}

/// The measurement list, the active tool and the one being drawn.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Measurements {
    pub items: Vec<Measurement>,
    pub tool: Tool,
    pub draft: Draft,
    next_id: u64,
}

impl Measurements {
    pub fn with_items(items: Vec<Measurement>) -> Self {
        let next_id = items.iter().map(|m| m.id + 1).max().unwrap_or(0);
        Measurements {
            items,
            next_id,
            ..Default::default()
        }
    }

    pub fn add(&mut self, shape: Shape) {
        self.items.push(Measurement {
            id: self.next_id,
            shape,
        });
        self.next_id += 1;
    }

    pub fn remove(&mut self, id: u64) {
        self.items.retain(|m| m.id != id);
    }

    /// A point clicked with the tool (slices: angle; 3D: distance and angle); adds the
    /// measurement once it has all its points.
    pub fn click(&mut self, point: [f64; 3]) {
        let needed = match self.tool {
            Tool::Distance => 2,
            Tool::Angle => 3,
            _ => return,
        };
        self.draft.points.push(point);
        if self.draft.points.len() >= needed {
            let p = std::mem::take(&mut self.draft.points);
            self.add(match self.tool {
                Tool::Distance => Shape::Distance { a: p[0], b: p[1] },
                _ => Shape::Angle {
                    a: p[0],
                    vertex: p[1],
                    b: p[2],
                },
            });
        }
    }
}

impl Measurements {
    /// Takes `items` when they differ from the list (a link opened, an undo in the page):
    /// the tool stays, a half-drawn measurement is dropped, new ids stay unique.
    pub fn follow(&mut self, items: &[Measurement]) {
        if self.items == items {
            return;
        }
        self.items = items.to_vec();
        self.draft.points.clear();
        let after_items = items.iter().map(|m| m.id + 1).max().unwrap_or(0);
        self.next_id = self.next_id.max(after_items);
    }

    /// Fills in the statistics of `view`'s regions that have none (opened from a link, or
    /// drawn before their slice arrived), or have a coarser level's, from `image` when it shows
    /// their slice; true when one was filled.
    pub fn fill_missing_stats(
        &mut self,
        view: SliceView,
        image: &SliceImage,
        geometry: &VolumeGeometry,
        mapping: ValueMapping,
    ) -> bool {
        let mut filled = false;
        for item in &mut self.items {
            if let Shape::Roi {
                view: shape_view,
                ellipse,
                a,
                b,
                stats,
            } = &mut item.shape
            {
                let wanted = match stats {
                    None => true,
                    Some(s) => s.level > image.request.level,
                };
                if wanted && *shape_view == view && image_shows(image, view, *a) {
                    if let Some(new) = roi_stats(image, geometry, mapping, *ellipse, *a, *b) {
                        *stats = Some(new);
                        filled = true;
                    }
                }
            }
        }
        filled
    }
}

/// Whether `image` is `view`'s slice through `point` (the slice a region drawn there lies on).
pub fn image_shows(image: &SliceImage, view: SliceView, point: [f64; 3]) -> bool {
    let normal = image.request.frame.normal_axis;
    image.request.view == view && image.request.position.round() == point[normal].round()
}

/// What a slice view's gestures and drawing need: which view, its frame, the volume's
/// geometry and value mapping, and the linked crosshair (which slice is shown).
#[derive(Clone, Copy, Debug)]
pub struct SliceContext<'a> {
    pub view: SliceView,
    pub frame: SliceFrame,
    pub geometry: &'a VolumeGeometry,
    pub mapping: ValueMapping,
    /// The crosshair, level-0 continuous index: its component along the view's normal is the
    /// slice shown.
    pub cursor: [f64; 3],
}

impl SliceContext<'_> {
    /// The level-0 continuous index at screen point `pos` of the image drawn in `image_rect`,
    /// on the slice shown (strata-slices' frame mapping, as the crosshair's click).
    pub fn index_at(&self, image_rect: Rect, pos: Pos2) -> [f64; 3] {
        let (u, w) = fraction_at(image_rect, pos);
        let (across, down) = self.frame.index_at(self.geometry.dims, u, w);
        let mut index = self.cursor;
        index[self.frame.across_axis] = across;
        index[self.frame.down_axis] = down;
        index
    }

    /// The index at `pos` when it lies on the image.
    pub fn point_at(&self, image_rect: Rect, pos: Pos2) -> Option<[f64; 3]> {
        image_rect
            .contains(pos)
            .then(|| self.index_at(image_rect, pos))
    }

    /// The screen point of a level-0 index's across and down components.
    pub fn screen_of(&self, image_rect: Rect, index: [f64; 3]) -> Pos2 {
        screen_at(
            image_rect,
            self.frame.fraction_of(
                self.geometry.dims,
                index[self.frame.across_axis],
                index[self.frame.down_axis],
            ),
        )
    }

    /// Whether `point` lies on the slice shown (same voxel slice along the normal).
    pub fn on_slice(&self, point: [f64; 3]) -> bool {
        let normal = self.frame.normal_axis;
        point[normal].round() == self.cursor[normal].round()
    }
}

/// The left button with a measuring tool on a slice view: a drag draws a ruler or a region
/// (from where the button went down, which must be on the image), clicks place an angle's
/// three points (the second is the vertex). A region's statistics come from `shown`, the
/// view's slice image, when it is the region's slice (else [`Measurements::fill_missing_stats`]
/// fills them when it arrives). Navigate does nothing here.
pub fn slice_input(
    ui: &egui::Ui,
    response: &egui::Response,
    image_rect: Rect,
    slice: &SliceContext<'_>,
    measurements: &mut Measurements,
    shown: Option<&SliceImage>,
) {
    let tool = measurements.tool;
    match tool {
        Tool::Angle => {
            if response.clicked() {
                if let Some(p) = response
                    .interact_pointer_pos()
                    .and_then(|p| slice.point_at(image_rect, p))
                {
                    measurements.click(p);
                }
            }
        }
        Tool::Distance | Tool::BoxRoi | Tool::EllipseRoi => {
            if response.dragged_by(egui::PointerButton::Primary) {
                let start = ui.input(|i| i.pointer.press_origin());
                let now = response.interact_pointer_pos();
                if let (Some(a), Some(b)) = (
                    start.and_then(|p| slice.point_at(image_rect, p)),
                    now.map(|p| slice.index_at(image_rect, p)),
                ) {
                    measurements.draft.points = vec![a, b];
                }
            }
            if response.drag_stopped() {
                let points = std::mem::take(&mut measurements.draft.points);
                if let [a, b] = points[..] {
                    let shape = match tool {
                        Tool::Distance => Shape::Distance { a, b },
                        _ => {
                            let ellipse = tool == Tool::EllipseRoi;
                            let stats = shown
                                .filter(|image| image_shows(image, slice.view, a))
                                .and_then(|image| {
                                    roi_stats(image, slice.geometry, slice.mapping, ellipse, a, b)
                                });
                            Shape::Roi {
                                view: slice.view,
                                ellipse,
                                a,
                                b,
                                stats,
                            }
                        }
                    };
                    if distance_mm(slice.geometry, a, b) > 0.0 {
                        measurements.add(shape);
                    }
                }
            }
        }
        Tool::Navigate => {}
    }
}

/// Draws the measurements lying on the slice shown, each with its described line (kept
/// inside the view), and the one being drawn.
pub fn paint_on_slice(
    painter: &egui::Painter,
    image_rect: Rect,
    slice: &SliceContext<'_>,
    measurements: &Measurements,
    unit: &str,
) {
    let screen = |p: [f64; 3]| slice.screen_of(image_rect, p);
    let colour = Color32::from_rgb(255, 230, 80);
    let stroke = Stroke::new(1.5, colour);
    let font = egui::FontId::proportional(12.0);
    let draw = |shape: &Shape, label: Option<String>| {
        let anchor = match shape {
            Shape::Distance { a, b } => {
                painter.line_segment([screen(*a), screen(*b)], stroke);
                screen(*b)
            }
            Shape::Angle { a, vertex, b } => {
                painter.line_segment([screen(*a), screen(*vertex)], stroke);
                painter.line_segment([screen(*vertex), screen(*b)], stroke);
                screen(*vertex)
            }
            Shape::Roi { ellipse, a, b, .. } => {
                let r = Rect::from_two_pos(screen(*a), screen(*b));
                if *ellipse {
                    let points: Vec<Pos2> = (0..48)
                        .map(|i| {
                            let t = i as f32 / 48.0 * std::f32::consts::TAU;
                            r.center()
                                + Vec2::new(t.cos() * r.width() * 0.5, t.sin() * r.height() * 0.5)
                        })
                        .collect();
                    painter.add(egui::Shape::closed_line(points, stroke));
                } else {
                    painter.rect_stroke(r, 0.0, stroke, egui::StrokeKind::Middle);
                }
                r.right_top()
            }
        };
        if let Some(label) = label {
            // Kept inside the view (issue 47: labels were cut at its edge).
            let galley = painter.layout_no_wrap(label, font.clone(), colour);
            let wanted =
                egui::Align2::LEFT_BOTTOM.anchor_size(anchor + Vec2::new(4.0, -4.0), galley.size());
            let placed = keep_inside(wanted, painter.clip_rect().shrink(2.0));
            painter.galley(placed.min, galley, colour);
        }
    };
    for m in &measurements.items {
        let visible = match &m.shape {
            Shape::Roi { view, a, .. } => *view == slice.view && slice.on_slice(*a),
            _ => m.points().iter().all(|p| slice.on_slice(*p)),
        };
        if visible {
            draw(&m.shape, Some(m.describe(slice.geometry, unit)));
        }
    }
    let draft = &measurements.draft.points;
    if draft.iter().all(|p| slice.on_slice(*p)) {
        match (measurements.tool, &draft[..]) {
            (Tool::Distance, [a, b]) => draw(
                &Shape::Distance { a: *a, b: *b },
                Some(format!("{:.1} mm", distance_mm(slice.geometry, *a, *b))),
            ),
            (Tool::BoxRoi | Tool::EllipseRoi, [a, b]) => draw(
                &Shape::Roi {
                    view: slice.view,
                    ellipse: measurements.tool == Tool::EllipseRoi,
                    a: *a,
                    b: *b,
                    stats: None,
                },
                None,
            ),
            (Tool::Angle, [a, vertex]) => draw(&Shape::Distance { a: *a, b: *vertex }, None),
            _ => {
                for p in draft {
                    painter.circle_filled(screen(*p), 3.0, colour);
                }
            }
        }
    }
}

/// Rulers and angles (and the points of one being drawn) over a 3D view whose frame, drawn
/// with `camera`, fills `rect`; regions belong to their slice and are not drawn here.
pub fn paint_in_3d(
    painter: &egui::Painter,
    rect: Rect,
    camera: &Camera,
    geometry: &VolumeGeometry,
    unit: &str,
    measurements: &Measurements,
) {
    let project = |p: [f64; 3]| project_to_view(camera, rect, geometry, DVec3::from(p));
    let colour = Color32::from_rgb(255, 230, 80);
    let stroke = Stroke::new(1.5, colour);
    for m in &measurements.items {
        let points: Option<Vec<Pos2>> = match &m.shape {
            Shape::Roi { .. } => None,
            _ => m.points().into_iter().map(project).collect(),
        };
        let Some(points) = points else { continue };
        painter.add(egui::Shape::line(points.clone(), stroke));
        if let Some(last) = points.last() {
            painter.text(
                *last + Vec2::new(4.0, -4.0),
                egui::Align2::LEFT_BOTTOM,
                m.describe(geometry, unit),
                egui::FontId::proportional(12.0),
                colour,
            );
        }
    }
    for p in measurements.draft.points.iter().filter_map(|p| project(*p)) {
        painter.circle_filled(p, 3.0, colour);
    }
}

/// The measurements panel: the tool row (the left button's tool), its hint, the list (each
/// line elided, deletable) and "Delete all". Returns where each tool's button was drawn (the
/// page publishes them for its tests).
pub fn panel(
    ui: &mut egui::Ui,
    measurements: &mut Measurements,
    geometry: &VolumeGeometry,
    unit: &str,
) -> Vec<(Tool, Rect)> {
    let mut tool_rects = Vec::with_capacity(Tool::ALL.len());
    ui.horizontal_wrapped(|ui| {
        for tool in Tool::ALL {
            let response = ui
                .selectable_label(measurements.tool == tool, tool.label())
                .on_hover_text(tool.hint());
            if response.clicked() {
                measurements.tool = tool;
                measurements.draft.points.clear();
            }
            tool_rects.push((tool, response.rect));
        }
    });
    ui.weak(measurements.tool.hint());
    if measurements.items.is_empty() {
        ui.weak("No measurements.");
        return tool_rects;
    }
    let mut delete = None;
    for item in &measurements.items {
        // The button first and the line elided in what is left, the full line on hover: a long
        // ROI statistics line in a grid widened the side panel and moved every view and button
        // under the cursor (issue 36).
        ui.horizontal(|ui| {
            if ui
                .small_button("Delete")
                .on_hover_text("Delete this measurement (Ctrl+Z brings it back)")
                .clicked()
            {
                delete = Some(item.id);
            }
            ui.add(egui::Label::new(item.describe(geometry, unit)).truncate());
        });
    }
    if let Some(id) = delete {
        measurements.remove(id);
    }
    if ui.button("Delete all").clicked() {
        measurements.items.clear();
    }
    tool_rects
}

/// Most measurements a link may carry: a reading's handful, with room; bounds what a link
/// makes the viewer allocate.
pub const MAX_LINK_MEASUREMENTS: usize = 200;
/// Largest magnitude of a link's voxel index (a point may lie off the volume, not absurdly).
pub const MAX_LINK_INDEX: f64 = 1.0e7;

/// Why a link's `m=` value could not be read.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MeasurementTextError {
    #[error("measurement {item} is `{kind}`: not r, a, ba, bc, bs, ea, ec or es")]
    UnknownKind { item: usize, kind: String },
    #[error("measurement {item} ({kind}) has {found} numbers, not {expected}")]
    WrongCount {
        item: usize,
        kind: String,
        expected: usize,
        found: usize,
    },
    #[error(
        "measurement {item}'s `{number}` is not a voxel index (a number within ±{MAX_LINK_INDEX})"
    )]
    BadNumber { item: usize, number: String },
    #[error("measurement {item} has no `KIND:` before its numbers")]
    NoKind { item: usize },
    #[error("{count} measurements, more than the {MAX_LINK_MEASUREMENTS} a link carries")]
    TooMany { count: usize },
}

/// Two decimals of a voxel index: a hundredth of a voxel, finer than a pointer places a point.
fn round2(v: f64) -> f64 {
    (v * 100.0).round() / 100.0
}

fn view_letter(view: SliceView) -> char {
    match view {
        SliceView::Axial => 'a',
        SliceView::Coronal => 'c',
        SliceView::Sagittal => 's',
    }
}

/// The link's `m=` value of `items`: `;`-separated `KIND:I,J,K,…` with the points' level-0
/// indices at two decimals; KIND `r` a ruler (two points), `a` an angle (three, the vertex
/// second), `b`/`e` a box/ellipse region followed by its view's letter (`a`xial, `c`oronal,
/// `s`agittal) and its two corners. Statistics are not written: the viewer that opens the
/// link computes them from its slice. None for no measurements (the link leaves `m=` out).
pub fn to_link_text(items: &[Measurement]) -> Option<String> {
    if items.is_empty() {
        return None;
    }
    let text: Vec<String> = items
        .iter()
        .map(|m| {
            let kind = match &m.shape {
                Shape::Distance { .. } => "r".to_string(),
                Shape::Angle { .. } => "a".to_string(),
                Shape::Roi { view, ellipse, .. } => {
                    format!("{}{}", if *ellipse { 'e' } else { 'b' }, view_letter(*view))
                }
            };
            let numbers: Vec<String> = m
                .points()
                .iter()
                .flatten()
                .map(|v| format!("{}", round2(*v)))
                .collect();
            format!("{kind}:{}", numbers.join(","))
        })
        .collect();
    Some(text.join(";"))
}

/// Reads a link's `m=` value ([`to_link_text`]'s format); ids are given in order from 0 and
/// regions have no statistics until a slice gives them.
pub fn from_link_text(text: &str) -> Result<Vec<Measurement>, MeasurementTextError> {
    let entries: Vec<&str> = text.split(';').filter(|e| !e.is_empty()).collect();
    if entries.len() > MAX_LINK_MEASUREMENTS {
        return Err(MeasurementTextError::TooMany {
            count: entries.len(),
        });
    }
    let mut items = Vec::with_capacity(entries.len());
    for (item, entry) in entries.into_iter().enumerate() {
        let (kind, numbers) = entry
            .split_once(':')
            .ok_or(MeasurementTextError::NoKind { item })?;
        let roi = |ellipse: bool, view: SliceView| (ellipse, view);
        let (expected, region) = match kind {
            "r" => (6, None),
            "a" => (9, None),
            "ba" => (6, Some(roi(false, SliceView::Axial))),
            "bc" => (6, Some(roi(false, SliceView::Coronal))),
            "bs" => (6, Some(roi(false, SliceView::Sagittal))),
            "ea" => (6, Some(roi(true, SliceView::Axial))),
            "ec" => (6, Some(roi(true, SliceView::Coronal))),
            "es" => (6, Some(roi(true, SliceView::Sagittal))),
            _ => {
                return Err(MeasurementTextError::UnknownKind {
                    item,
                    kind: kind.chars().take(20).collect(),
                })
            }
        };
        let parts: Vec<&str> = numbers.split(',').collect();
        if parts.len() != expected {
            return Err(MeasurementTextError::WrongCount {
                item,
                kind: kind.into(),
                expected,
                found: parts.len(),
            });
        }
        let mut values = [0.0f64; 9];
        for (slot, part) in values.iter_mut().zip(&parts) {
            *slot = match part.parse::<f64>() {
                Ok(v) if v.is_finite() && v.abs() <= MAX_LINK_INDEX => v,
                _ => {
                    return Err(MeasurementTextError::BadNumber {
                        item,
                        number: part.chars().take(20).collect(),
                    })
                }
            };
        }
        let point = |i: usize| [values[3 * i], values[3 * i + 1], values[3 * i + 2]];
        let shape = match (kind, region) {
            (_, Some((ellipse, view))) => Shape::Roi {
                view,
                ellipse,
                a: point(0),
                b: point(1),
                stats: None,
            },
            ("a", None) => Shape::Angle {
                a: point(0),
                vertex: point(1),
                b: point(2),
            },
            _ => Shape::Distance {
                a: point(0),
                b: point(1),
            },
        };
        items.push(Measurement {
            id: item as u64,
            shape,
        });
    }
    Ok(items)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lengths_and_angles_are_in_patient_millimetres() {
        // Anisotropic: 0.5 mm across, 2 mm slices.
        let g = VolumeGeometry::axis_aligned([10, 10, 10], [0.5, 0.5, 2.0]);
        assert!((distance_mm(&g, [0.0, 0.0, 0.0], [6.0, 8.0, 0.0]) - 5.0).abs() < 1e-12);
        assert!((distance_mm(&g, [0.0, 0.0, 0.0], [0.0, 0.0, 3.0]) - 6.0).abs() < 1e-12);
        // 4 voxels across (2 mm) and 1 slice (2 mm): 45° in patient space, not 14° in index.
        let a = angle_deg(&g, [4.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
        assert!((a - 90.0).abs() < 1e-9, "{a}");
        let a = angle_deg(&g, [4.0, 0.0, 0.0], [0.0, 0.0, 0.0], [4.0, 0.0, 1.0]);
        assert!((a - 45.0).abs() < 1e-9, "{a}");
    }

    #[test]
    fn clicks_complete_rulers_and_angles_and_ids_stay_unique() {
        let mut m = Measurements {
            tool: Tool::Angle,
            ..Default::default()
        };
        m.click([1.0, 0.0, 0.0]);
        m.click([0.0, 0.0, 0.0]);
        assert!(m.items.is_empty());
        m.click([0.0, 1.0, 0.0]);
        assert_eq!(m.items.len(), 1);
        m.tool = Tool::Distance;
        m.click([0.0; 3]);
        m.click([1.0; 3]);
        assert_eq!(m.items.len(), 2);
        m.remove(0);
        let restored = Measurements::with_items(m.items.clone());
        let mut restored = restored;
        restored.add(Shape::Distance {
            a: [0.0; 3],
            b: [0.0; 3],
        });
        let ids: Vec<u64> = restored.items.iter().map(|i| i.id).collect();
        assert_eq!(ids, vec![1, 2]);
    }

    fn axial_image(geometry: &VolumeGeometry, position: f64, values: Vec<u16>) -> SliceImage {
        let frame = SliceFrame::for_view(SliceView::Axial, geometry);
        SliceImage {
            request: strata_slices::SliceRequest {
                view: SliceView::Axial,
                frame,
                position,
                level: 0,
            },
            width: geometry.dims[frame.across_axis] as usize,
            height: geometry.dims[frame.down_axis] as usize,
            values: std::sync::Arc::new(values),
            inside_fraction: (1.0, 1.0),
        }
    }

    #[test]
    fn a_links_measurements_round_trip_at_two_decimals_and_regions_get_their_slices_stats() {
        let items = vec![
            Measurement {
                id: 4,
                shape: Shape::Distance {
                    a: [1.004, 2.5, 3.0],
                    b: [-0.5, 7.126, 3.0],
                },
            },
            Measurement {
                id: 9,
                shape: Shape::Angle {
                    a: [1.0, 0.0, 2.0],
                    vertex: [0.0, 0.0, 2.0],
                    b: [0.0, 1.0, 2.0],
                },
            },
            Measurement {
                id: 11,
                shape: Shape::Roi {
                    view: SliceView::Axial,
                    ellipse: false,
                    a: [0.0, 0.0, 1.0],
                    b: [1.0, 1.0, 1.0],
                    stats: None,
                },
            },
            Measurement {
                id: 12,
                shape: Shape::Roi {
                    view: SliceView::Coronal,
                    ellipse: true,
                    a: [0.0, 1.0, 0.0],
                    b: [3.0, 1.0, 3.0],
                    stats: None,
                },
            },
        ];
        let text = to_link_text(&items).expect("some measurements");
        assert_eq!(
            text,
            "r:1,2.5,3,-0.5,7.13,3;a:1,0,2,0,0,2,0,1,2;ba:0,0,1,1,1,1;ec:0,1,0,3,1,3"
        );
        let read = from_link_text(&text).expect("its own text");
        assert_eq!(read.len(), 4);
        assert_eq!(read.iter().map(|m| m.id).collect::<Vec<_>>(), [0, 1, 2, 3]);
        // Exact at the precision written: the text read back writes the same text.
        assert_eq!(to_link_text(&read).as_deref(), Some(text.as_str()));
        assert_eq!(read[3].shape, items[3].shape);
        assert_eq!(to_link_text(&[]), None);

        // The box on axial slice 1 gets its statistics from that slice only.
        let geometry = VolumeGeometry::axis_aligned([2, 2, 3], [0.5, 0.5, 2.0]);
        let mut m = Measurements::with_items(read);
        let other_slice = axial_image(&geometry, 2.0, vec![7; 4]);
        assert!(!m.fill_missing_stats(
            SliceView::Axial,
            &other_slice,
            &geometry,
            ValueMapping::default()
        ));
        let slice = axial_image(&geometry, 1.0, vec![10, 20, 30, 40]);
        assert!(m.fill_missing_stats(SliceView::Axial, &slice, &geometry, ValueMapping::default()));
        let Shape::Roi {
            stats: Some(stats), ..
        } = m.items[2].shape
        else {
            panic!("no statistics: {:?}", m.items[2]);
        };
        assert_eq!(stats.voxels, 4);
        assert_eq!((stats.mean, stats.min, stats.max), (25.0, 10.0, 40.0));
        assert!((stats.sd - 125.0f64.sqrt()).abs() < 1e-12, "{stats:?}");
        assert!((stats.area_mm2 - 0.25).abs() < 1e-12, "{stats:?}");
        // Statistics are derived: filling them in changes no measurement (nothing to undo).
        assert_eq!(m.items, from_link_text(&text).expect("its own text"));
        // The coronal ellipse is not the axial view's.
        assert!(matches!(m.items[3].shape, Shape::Roi { stats: None, .. }));
        // A list that differs replaces this one; ids stay unique.
        let mut page = Measurements::default();
        page.follow(&m.items);
        page.add(Shape::Distance {
            a: [0.0; 3],
            b: [1.0; 3],
        });
        assert_eq!(page.items.last().map(|i| i.id), Some(4));
    }

    #[test]
    fn a_bad_link_text_says_which_measurement_and_why() {
        for (text, wanted) in [
            ("r:0,0,0,1,1,1;x:1,2", "measurement 1 is `x`"),
            ("a:0,0,0,1,1,1", "measurement 0 (a) has 6 numbers, not 9"),
            (
                "r:0,0,0,1,1,nan",
                "measurement 0's `nan` is not a voxel index",
            ),
            (
                "r:0,0,0,1,1,1e9",
                "measurement 0's `1e9` is not a voxel index",
            ),
            ("0,0,0,1,1,1", "measurement 0 has no `KIND:`"),
        ] {
            let message = from_link_text(text).expect_err(text).to_string();
            assert!(message.contains(wanted), "{text}: {message}");
        }
        let many = vec!["r:0,0,0,1,1,1"; MAX_LINK_MEASUREMENTS + 1].join(";");
        assert_eq!(
            from_link_text(&many),
            Err(MeasurementTextError::TooMany {
                count: MAX_LINK_MEASUREMENTS + 1
            })
        );
    }
}
