use egui::accesskit::Role;
use egui_kittest::kittest::Queryable;
use egui_kittest::Harness;
use strata_segment::tools::morphology::{Islands, LogicalOp};
use strata_segment::{Label, SegmentTable};
use strata_viewer_ui::segment_panel::{
    label_rgba, operations, segment_list, tool_row, OperationSettings, SegmentListChange,
    SegmentOperation, SegmentTool, DEFAULT_BRUSH_DIAMETER_MM,
};

struct Panel {
    tool: SegmentTool,
    diameter_mm: f64,
    table: SegmentTable,
    active: Label,
    changes: Vec<SegmentListChange>,
    tool_buttons: usize,
    offer_grow: bool,
}

fn panel(offer_grow: bool) -> Harness<'static, Panel> {
    let mut table = SegmentTable::new();
    table.add("Liver").expect("first segment");
    table.add("Tumour").expect("second segment");
    let mut harness = Harness::new_ui_state(
        |ui, p: &mut Panel| {
            p.tool_buttons = tool_row(ui, &mut p.tool, &mut p.diameter_mm, p.offer_grow).len();
            if let Some(change) = segment_list(ui, &mut p.table, &mut p.active) {
                p.changes.push(change);
            }
        },
        Panel {
            tool: SegmentTool::None,
            diameter_mm: DEFAULT_BRUSH_DIAMETER_MM,
            table,
            active: 1,
            changes: Vec::new(),
            tool_buttons: 0,
            offer_grow,
        },
    );
    harness.run();
    harness
}

/// A click on a tool's button chooses that tool; the page's row (no grow) offers four tools,
/// the desktop's five.
#[test]
fn a_click_on_a_tool_button_chooses_it_and_grow_is_offered_only_where_asked() {
    let mut h = panel(false);
    assert_eq!(h.state().tool_buttons, 4);
    assert!(h.query_by_label("Grow").is_none());
    h.get_by_label("Brush").click();
    h.run();
    assert_eq!(h.state().tool, SegmentTool::Brush);
    h.get_by_label("Eraser").click();
    h.run();
    assert_eq!(h.state().tool, SegmentTool::Eraser);
    let mut desktop = panel(true);
    assert_eq!(desktop.state().tool_buttons, 5);
    desktop.get_by_label("Grow").click();
    desktop.run();
    assert_eq!(desktop.state().tool, SegmentTool::Grow);
}

/// The list edits the table in place (a segment hidden, another locked) and hands adding and
/// removing to the caller, naming the segment removed.
#[test]
fn the_segment_list_edits_flags_in_place_and_returns_add_and_remove() {
    let mut h = panel(false);
    let shown: Vec<_> = h
        .get_all_by_role_and_label(Role::CheckBox, "Shown")
        .collect();
    assert_eq!(shown.len(), 2);
    shown[1].click();
    h.run();
    let locked: Vec<_> = h
        .get_all_by_role_and_label(Role::CheckBox, "Locked")
        .collect();
    locked[0].click();
    h.run();
    let table = &h.state().table;
    assert!(table.get(1).is_some_and(|s| s.visible && s.locked));
    assert!(table.get(2).is_some_and(|s| !s.visible && !s.locked));
    let removes: Vec<_> = h.get_all_by_label("×").collect();
    removes[1].click();
    h.run();
    h.get_by_label("Add segment").click();
    h.run();
    assert_eq!(
        h.state().changes,
        vec![SegmentListChange::Remove(2), SegmentListChange::Add]
    );
    // The list does not remove by itself: the caller's layer does, as one edit.
    assert_eq!(h.state().table.len(), 2);
}

/// A label is its segment's colour at the opacity; background, a hidden segment and a value no
/// segment has are clear.
#[test]
fn a_label_is_its_segments_colour_at_the_opacity_and_hidden_ones_are_clear() {
    let mut table = SegmentTable::new();
    let liver = table.add("Liver").expect("segment");
    let [r, g, b] = table.get(liver).expect("segment").rgb;
    assert_eq!(label_rgba(&table, liver, 0.5), [r, g, b, 128]);
    assert_eq!(label_rgba(&table, liver, 1.0), [r, g, b, 255]);
    assert_eq!(label_rgba(&table, 0, 0.5), [0; 4]);
    assert_eq!(label_rgba(&table, 7, 0.5), [0; 4]);
    table.get_mut(liver).expect("segment").visible = false;
    assert_eq!(label_rgba(&table, liver, 0.5), [0; 4]);
}

struct Operations {
    settings: OperationSettings,
    table: SegmentTable,
    active: Label,
    enabled: bool,
    chosen: Vec<SegmentOperation>,
    buttons: Vec<&'static str>,
}

fn operations_panel() -> Harness<'static, Operations> {
    let mut table = SegmentTable::new();
    table.add("Liver").expect("first segment");
    table.add("Tumour").expect("second segment");
    let mut harness = Harness::new_ui_state(
        |ui, p: &mut Operations| {
            let response = operations(ui, &mut p.settings, &p.table, p.active, p.enabled);
            p.chosen.extend(response.chosen);
            p.buttons = response.buttons.iter().map(|(name, _)| *name).collect();
        },
        Operations {
            settings: OperationSettings::default(),
            table,
            active: 1,
            enabled: true,
            chosen: Vec::new(),
            buttons: Vec::new(),
        },
    );
    harness.run();
    harness
}

/// Each button asks for its operation with the settings' N and margin; the logical operations
/// wait for another segment that still exists and is not the active one; a disabled section
/// asks for nothing.
#[test]
fn the_operations_return_their_choice_and_combine_only_with_another_live_segment() {
    let mut h = operations_panel();
    assert_eq!(
        h.state().buttons,
        [
            "between",
            "largest",
            "islands",
            "margin",
            "union",
            "subtract",
            "intersect"
        ]
    );
    for label in [
        "Between slices",
        "Keep largest",
        "Remove islands <",
        "Margin",
    ] {
        h.get_by_label(label).click();
        h.run();
    }
    // No other segment chosen yet: Union is disabled.
    h.get_by_label("Union").click();
    h.run();
    assert_eq!(
        h.state().chosen,
        [
            SegmentOperation::FillBetween,
            SegmentOperation::Islands(Islands::KeepLargest),
            SegmentOperation::Islands(Islands::RemoveSmallerThan(100)),
            SegmentOperation::Margin(2.0),
        ]
    );
    h.state_mut().chosen.clear();
    h.state_mut().settings.other = 2;
    h.run();
    h.get_by_label("Subtract").click();
    h.run();
    assert_eq!(
        h.state().chosen,
        [SegmentOperation::Combine(LogicalOp::Subtract, 2)]
    );
    // The chosen segment became the active one: combining it with itself is not offered.
    h.state_mut().chosen.clear();
    h.state_mut().active = 2;
    h.run();
    h.get_by_label("Union").click();
    h.run();
    assert!(h.state().chosen.is_empty(), "{:?}", h.state().chosen);
    // Disabled (a grow or a stroke running): nothing is asked for.
    h.state_mut().enabled = false;
    h.run();
    h.get_by_label("Keep largest").click();
    h.run();
    assert!(h.state().chosen.is_empty(), "{:?}", h.state().chosen);
}

/// The other segment counts only while it is in the table and is not the active one.
#[test]
fn a_removed_or_active_operand_is_no_operand() {
    let mut table = SegmentTable::new();
    let liver = table.add("Liver").expect("segment");
    let tumour = table.add("Tumour").expect("segment");
    let settings = OperationSettings {
        other: tumour,
        ..OperationSettings::default()
    };
    assert_eq!(settings.operand(&table, liver), Some(tumour));
    assert_eq!(settings.operand(&table, tumour), None);
    assert!(table.remove(tumour).is_some());
    assert_eq!(settings.operand(&table, liver), None);
    assert_eq!(OperationSettings::default().operand(&table, liver), None);
}
