//! The Segment section's platform-independent part (issue 52 item 7), drawn by the desktop's
//! Segment panel (viewer/src/panels/segment.rs) and the browser page's (web/src/segment_editor.rs):
//! the tool row (off, brush, eraser, slice fill, and 3D grow where the viewer offers it; the
//! brush diameter in mm), the segment list (active segment, colour, name, shown, locked,
//! remove; Add segment), the operations on the active segment (fill between slices, islands,
//! margin, union / subtract / intersect with another segment), the labels' opacity, the
//! colour a label is drawn with, and the rows of the tools that read the primary's values
//! ([`value_rows`]: the value range, region growing's settings; [`progress_row`]: a running
//! grow's progress and Cancel; [`statistics_rows`]: the statistics table and Copy as CSV).
//!
//! It edits plain data: the tool and size, the active label, the operations' settings and a
//! strata-segment [`SegmentTable`] the caller copied out of its layer, and says what the caller
//! must do to the layer itself ([`SegmentListChange`]: adding and removing are edits, undoable
//! on each side; [`SegmentOperation`]: each operation is one edit, run by the caller with
//! strata-segment's `tools::{interpolate, morphology}`, none needing the primary's values).
//!
//! Every row wraps inside the panel's width rather than widening it: a row wider than the
//! panel made the desktop's right-hand panel grow on the frame after the segmentation opened,
//! moving every widget under a pointer that had not moved
//! (`ui_tests::segment_oblique::one_click_on_a_tool_button_chooses_that_tool`).

use egui::Rect;
use strata_segment::stats::Statistics;
use strata_segment::tools::morphology::{Islands, LogicalOp};
use strata_segment::{Label, SegmentTable};

/// The brush diameter both viewers start with (mm).
pub const DEFAULT_BRUSH_DIAMETER_MM: f64 = 10.0;
/// The labels' opacity over the slices both viewers start with (the desktop overlay's).
pub const DEFAULT_LABEL_OPACITY: f32 = 0.5;

/// The tool the left button uses on a slice view.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SegmentTool {
    /// The left button moves the crosshair (or measures).
    None,
    Brush,
    Eraser,
    /// A click fills the closed region around it in the slice.
    Fill,
    /// A click grows the active segment in 3D from that seed (the desktop on a thread, the page
    /// over the bricks it fetches).
    Grow,
}

impl SegmentTool {
    /// Whether the left button is the tool's (not the crosshair's).
    pub fn paints(self) -> bool {
        self != SegmentTool::None
    }

    /// The tool as the 3D view offers it: fill works within a slice, so it has no 3D form.
    pub fn filter_3d(self) -> SegmentTool {
        match self {
            SegmentTool::Fill => SegmentTool::None,
            tool => tool,
        }
    }

    /// Whether the tool is dragged (brush, eraser) rather than clicked.
    pub fn drags(self) -> bool {
        matches!(self, SegmentTool::Brush | SegmentTool::Eraser)
    }
}

/// The tool buttons and the brush diameter, on one wrapping row; `offer_grow` adds the 3D grow
/// (both viewers offer it). Returns each tool button's rectangle (the
/// page publishes them for its browser tests).
pub fn tool_row(
    ui: &mut egui::Ui,
    tool: &mut SegmentTool,
    diameter_mm: &mut f64,
    offer_grow: bool,
) -> Vec<(SegmentTool, Rect)> {
    let mut buttons = Vec::new();
    ui.horizontal_wrapped(|ui| {
        let mut offered = vec![
            (
                SegmentTool::None,
                "Off",
                "The left button moves the crosshair",
            ),
            (
                SegmentTool::Brush,
                "Brush",
                "Paint the active segment: drag on a slice",
            ),
            (
                SegmentTool::Eraser,
                "Eraser",
                "Clear any unlocked segment: drag on a slice",
            ),
            (
                SegmentTool::Fill,
                "Fill",
                "Fill the closed region around a click, in that slice",
            ),
        ];
        if offer_grow {
            offered.push((
                SegmentTool::Grow,
                "Grow",
                "Grow the active segment in 3D from a clicked seed",
            ));
        }
        for (value, label, hover) in offered {
            let response = ui.selectable_value(tool, value, label).on_hover_text(hover);
            buttons.push((value, response.rect));
        }
        ui.add(
            egui::DragValue::new(diameter_mm)
                .range(0.1..=500.0)
                .speed(0.2)
                .suffix(" mm"),
        )
        .on_hover_text("Brush diameter");
    });
    buttons
}

/// What the segment list asks the caller to do to its layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SegmentListChange {
    /// Add a segment (and make it the active one).
    Add,
    /// Remove this segment and clear its voxels (one undoable edit).
    Remove(Label),
}

/// The segments, one wrapping row each: active (radio), colour, name, shown, locked, remove;
/// then Add segment. Names, colours and the two flags are edited in `table` in place; adding
/// and removing are returned for the caller's layer to do.
pub fn segment_list(
    ui: &mut egui::Ui,
    table: &mut SegmentTable,
    active: &mut Label,
) -> Option<SegmentListChange> {
    let mut change = None;
    let values: Vec<Label> = table.iter().map(|s| s.value).collect();
    for value in values {
        let Some(s) = table.get_mut(value) else {
            continue;
        };
        ui.horizontal_wrapped(|ui| {
            ui.radio_value(active, s.value, "")
                .on_hover_text("The segment the tools paint");
            ui.color_edit_button_srgb(&mut s.rgb);
            // The hover text names the field for screen readers and tests too.
            ui.add(egui::TextEdit::singleline(&mut s.name).desired_width(110.0))
                .on_hover_text("The segment's name");
            ui.checkbox(&mut s.visible, "Shown");
            ui.checkbox(&mut s.locked, "Locked")
                .on_hover_text("No tool paints over or erases a locked segment");
            if ui
                .small_button("×")
                .on_hover_text("Remove the segment and clear its voxels (undoable)")
                .clicked()
            {
                change = Some(SegmentListChange::Remove(s.value));
            }
        });
    }
    if ui.button("Add segment").clicked() {
        change = Some(SegmentListChange::Add);
    }
    change
}

/// An operation on the active segment, chosen in [`operations`]; the caller runs it on its
/// layer as one undo step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SegmentOperation {
    /// Interpolate the slices between the drawn ones, along the caller's last stroke's plane
    /// (the caller knows it; the panel does not).
    FillBetween,
    Islands(Islands),
    /// Grow (> 0) or shrink (< 0) by this many mm.
    Margin(f64),
    /// The active segment combined with this other one.
    Combine(LogicalOp, Label),
}

/// The operations' own inputs, kept by the caller between frames.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OperationSettings {
    /// Remove islands smaller than this many voxels.
    pub min_island_voxels: u64,
    pub margin_mm: f64,
    /// The other segment of union / subtract / intersect as chosen (0: none yet).
    pub other: Label,
}

impl Default for OperationSettings {
    fn default() -> Self {
        OperationSettings {
            min_island_voxels: 100,
            margin_mm: 2.0,
            other: 0,
        }
    }
}

impl OperationSettings {
    /// The other segment a logical operation may use now: the one chosen, while it is still a
    /// segment of `table` and not the `active` one. A choice goes stale when that segment is
    /// removed or made active, and combining a segment with itself or a missing one is refused
    /// by strata-segment, so the buttons are disabled instead.
    pub fn operand(&self, table: &SegmentTable, active: Label) -> Option<Label> {
        (self.other != 0 && self.other != active && table.get(self.other).is_some())
            .then_some(self.other)
    }
}

/// What [`operations`] drew: the operation asked for this frame, and each button's name and
/// rectangle (`between`, `largest`, `islands`, `margin`, `union`, `subtract`, `intersect`; the
/// page publishes them for its browser tests).
pub struct OperationsResponse {
    pub chosen: Option<SegmentOperation>,
    pub buttons: Vec<(&'static str, Rect)>,
}

/// The operations on the active segment, in three wrapping rows: Between slices, Keep largest,
/// Remove islands < N; Margin with its mm; the other segment's choice and union / subtract /
/// intersect. `enabled` is false while the caller cannot edit (no active segment, a grow
/// running).
pub fn operations(
    ui: &mut egui::Ui,
    settings: &mut OperationSettings,
    table: &SegmentTable,
    active: Label,
    enabled: bool,
) -> OperationsResponse {
    let mut chosen = None;
    let mut buttons = Vec::new();
    ui.add_enabled_ui(enabled && active != 0, |ui| {
        ui.horizontal_wrapped(|ui| {
            let between = ui.button("Between slices").on_hover_text(
                "Interpolate the active segment into the slices between the ones drawn, along \
                 the last stroke's view",
            );
            if between.clicked() {
                chosen = Some(SegmentOperation::FillBetween);
            }
            let largest = ui
                .button("Keep largest")
                .on_hover_text("Keep only the largest connected island");
            if largest.clicked() {
                chosen = Some(SegmentOperation::Islands(Islands::KeepLargest));
            }
            let islands = ui
                .button("Remove islands <")
                .on_hover_text("Remove the islands with fewer voxels than this");
            if islands.clicked() {
                chosen = Some(SegmentOperation::Islands(Islands::RemoveSmallerThan(
                    settings.min_island_voxels,
                )));
            }
            ui.add(
                egui::DragValue::new(&mut settings.min_island_voxels)
                    .range(1..=u64::MAX)
                    .suffix(" vx"),
            );
            buttons.extend([
                ("between", between.rect),
                ("largest", largest.rect),
                ("islands", islands.rect),
            ]);
        });
        ui.horizontal_wrapped(|ui| {
            let margin = ui
                .button("Margin")
                .on_hover_text("Grow (> 0) or shrink (< 0) the active segment by this many mm");
            if margin.clicked() {
                chosen = Some(SegmentOperation::Margin(settings.margin_mm));
            }
            ui.add(
                egui::DragValue::new(&mut settings.margin_mm)
                    .range(-200.0..=200.0)
                    .speed(0.1)
                    .suffix(" mm"),
            );
            buttons.push(("margin", margin.rect));
        });
        ui.horizontal_wrapped(|ui| {
            let operand = settings.operand(table, active);
            let name = operand
                .and_then(|v| table.get(v))
                .map_or_else(|| "—".to_string(), |s| s.name.clone());
            // Labelled: the label is its accessible name too (screen readers, kittest).
            egui::ComboBox::new("segment operand", "other segment")
                .selected_text(name)
                .width(90.0)
                .show_ui(ui, |ui| {
                    for s in table.iter().filter(|s| s.value != active) {
                        ui.selectable_value(&mut settings.other, s.value, &s.name);
                    }
                });
            for (op, label, name) in [
                (LogicalOp::Union, "Union", "union"),
                (LogicalOp::Subtract, "Subtract", "subtract"),
                (LogicalOp::Intersect, "Intersect", "intersect"),
            ] {
                let button = ui
                    .add_enabled(operand.is_some(), egui::Button::new(label))
                    .on_hover_text("The active segment with the chosen one");
                if let (true, Some(other)) = (button.clicked(), operand) {
                    chosen = Some(SegmentOperation::Combine(op, other));
                }
                buttons.push((name, button.rect));
            }
        });
    });
    OperationsResponse { chosen, buttons }
}

/// The value settings of the tools that read the primary, kept by the caller between frames:
/// the brush's, eraser's and fill's optional value range, and region growing's range or
/// mean ± k·σ and voxel cap.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ValueSettings {
    /// Paint, erase or fill only where the primary's value lies in `range`.
    pub limit_to_range: bool,
    /// Inclusive, in the primary's physical unit; also the grow's range unless by σ.
    pub range: (f64, f64),
    /// The grow takes mean ± k·σ of the seed's 3×3×3 neighbourhood instead of `range`.
    pub grow_by_sigma: bool,
    pub k: f64,
    /// The grow stops at this many voxels, keeping what it took (one undoable step).
    pub max_voxels: u64,
}

impl Default for ValueSettings {
    /// Bone (HU ≥ 300), off; the grow by range, k = 2, capped at 50 M voxels: the desktop's
    /// defaults.
    fn default() -> Self {
        ValueSettings {
            limit_to_range: false,
            range: (300.0, 3000.0),
            grow_by_sigma: false,
            k: 2.0,
            max_voxels: 50_000_000,
        }
    }
}

/// The value range row (Only values, lo to hi) and, with the grow tool, its row (mean ± k·σ,
/// k, cap). Returns the rectangles of the checkboxes (`only-values`, `sigma`; the page
/// publishes them for its browser tests).
pub fn value_rows(
    ui: &mut egui::Ui,
    tool: SegmentTool,
    settings: &mut ValueSettings,
) -> Vec<(&'static str, Rect)> {
    let mut rects = Vec::new();
    ui.horizontal_wrapped(|ui| {
        let growing_by_sigma = tool == SegmentTool::Grow && settings.grow_by_sigma;
        if tool == SegmentTool::Grow {
            ui.label("Values");
        } else {
            let only = ui
                .checkbox(&mut settings.limit_to_range, "Only values")
                .on_hover_text(
                    "Paint, erase or fill only where the volume's value lies in the range",
                );
            rects.push(("only-values", only.rect));
        }
        let enabled = (settings.limit_to_range || tool == SegmentTool::Grow) && !growing_by_sigma;
        ui.add_enabled(
            enabled,
            egui::DragValue::new(&mut settings.range.0).speed(1.0),
        );
        ui.label("to");
        ui.add_enabled(
            enabled,
            egui::DragValue::new(&mut settings.range.1).speed(1.0),
        );
    });
    if tool == SegmentTool::Grow {
        ui.horizontal_wrapped(|ui| {
            let sigma = ui
                .checkbox(&mut settings.grow_by_sigma, "mean ± k·σ")
                .on_hover_text("The range from the 3×3×3 voxels around the seed");
            rects.push(("sigma", sigma.rect));
            ui.add_enabled(
                settings.grow_by_sigma,
                egui::DragValue::new(&mut settings.k)
                    .range(0.0..=10.0)
                    .speed(0.05),
            );
            ui.label("cap");
            ui.add(
                egui::DragValue::new(&mut settings.max_voxels)
                    .range(1..=u64::MAX)
                    .speed(10_000.0)
                    .suffix(" vx"),
            )
            .on_hover_text("The grow stops here, keeping what it took");
        });
    }
    rects
}

/// A running job's progress bar (`fraction` of the way, `text` on it) and its Cancel button.
/// Returns whether Cancel was clicked, and the button's rectangle.
pub fn progress_row(ui: &mut egui::Ui, fraction: f32, text: &str) -> (bool, Rect) {
    ui.horizontal(|ui| {
        ui.add(
            egui::ProgressBar::new(fraction.clamp(0.0, 1.0))
                .text(text)
                .desired_width(160.0),
        );
        let cancel = ui.button("Cancel");
        (cancel.clicked(), cancel.rect)
    })
    .inner
}

/// What [`statistics_rows`] asks of the caller, and its buttons' rectangles (`statistics`,
/// `copy-csv`).
pub struct StatisticsResponse {
    /// Compute the statistics now.
    pub compute: bool,
    /// Copy the table as CSV.
    pub copy_csv: bool,
    pub buttons: Vec<(&'static str, Rect)>,
}

/// The Statistics button (disabled while `running`), Copy as CSV once there is a table, and the
/// table: per segment its voxels, mL, mean, SD, min, max and median in the primary's unit, and
/// its bounding box in LPS mm; or why there is none.
pub fn statistics_rows(
    ui: &mut egui::Ui,
    running: bool,
    stats: Option<&Result<Statistics, String>>,
) -> StatisticsResponse {
    let mut response = StatisticsResponse {
        compute: false,
        copy_csv: false,
        buttons: Vec::new(),
    };
    ui.horizontal_wrapped(|ui| {
        let compute = ui
            .add_enabled(!running, egui::Button::new("Statistics"))
            .on_hover_text("Voxels, volume and the volume's values in each segment");
        response.compute = compute.clicked();
        response.buttons.push(("statistics", compute.rect));
        if running {
            ui.spinner();
        }
        if let Some(Ok(_)) = stats {
            let copy = ui.button("Copy as CSV");
            response.copy_csv = copy.clicked();
            response.buttons.push(("copy-csv", copy.rect));
        }
    });
    match stats {
        Some(Ok(stats)) => {
            let unit = if stats.unit.is_empty() {
                String::new()
            } else {
                format!(" ({})", stats.unit)
            };
            let value = |v: Option<f64>| v.map_or_else(|| "–".to_string(), |v| format!("{v:.1}"));
            let mm = |v: Option<([f64; 3], [f64; 3])>| {
                v.map_or_else(
                    || "–".to_string(),
                    |(lo, hi)| {
                        format!(
                            "{:.1}…{:.1}, {:.1}…{:.1}, {:.1}…{:.1}",
                            lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]
                        )
                    },
                )
            };
            // Scrolled sideways rather than widening the panel (see the module's note).
            egui::ScrollArea::horizontal().show(ui, |ui| {
                egui::Grid::new("segment statistics")
                    .striped(true)
                    .show(ui, |ui| {
                        for heading in [
                            "Segment".to_string(),
                            "Voxels".to_string(),
                            "mL".to_string(),
                            format!("Mean{unit}"),
                            "SD".to_string(),
                            "Min".to_string(),
                            "Max".to_string(),
                            "Median".to_string(),
                            "L, P, S (mm)".to_string(),
                        ] {
                            ui.label(heading);
                        }
                        ui.end_row();
                        for s in &stats.segments {
                            ui.label(&s.name);
                            ui.label(s.voxels.to_string());
                            ui.label(format!("{:.2}", s.volume_ml));
                            for v in [s.mean, s.sd, s.min, s.max, s.median] {
                                ui.label(value(v));
                            }
                            ui.label(mm(s.lps_box_mm));
                            ui.end_row();
                        }
                    });
            });
        }
        Some(Err(e)) => {
            ui.colored_label(egui::Color32::LIGHT_RED, e);
        }
        None => {}
    }
    response
}

/// The labels' opacity over the slices.
pub fn opacity_row(ui: &mut egui::Ui, opacity: &mut f32) -> egui::Response {
    ui.add(egui::Slider::new(opacity, 0.0..=1.0).text("Opacity"))
}

/// The colour `label` is drawn with over a slice, unmultiplied RGBA: its segment's colour at
/// `opacity`; clear for background, a hidden segment, or a value no segment has.
pub fn label_rgba(table: &SegmentTable, label: Label, opacity: f32) -> [u8; 4] {
    match table.get(label) {
        Some(s) if label != 0 && s.visible => {
            let [r, g, b] = s.rgb;
            [r, g, b, (opacity.clamp(0.0, 1.0) * 255.0).round() as u8]
        }
        _ => [0; 4],
    }
}
