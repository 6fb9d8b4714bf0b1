//! What every UI test goes through: a phantom store, a kittest harness around the app, the
//! steps until a state or a settled frame, and the pointer and pixel helpers. Feature files
//! import it whole (`use super::harness::*`), the imports below included.

pub(crate) use crate::app::{Layout, Preferences, StrataApp, ViewSlot, ViewerOptions};
pub(crate) use crate::jobs::VolumeToOpen;
pub(crate) use crate::orientation::SliceView;
pub(crate) use crate::volume_session::RenderedFrame;
pub(crate) use egui::{Event, Modifiers, PointerButton, Vec2};
pub(crate) use egui_kittest::kittest::Queryable;
pub(crate) use egui_kittest::Harness;
pub(crate) use std::path::Path;
pub(crate) use std::time::{Duration, Instant};
pub(crate) use strata_storage::phantom::Phantom;

/// Generous: lavapipe on two shared cores compiles the raycast pipeline in seconds.
pub(crate) const WAIT: Duration = Duration::from_secs(180);

pub(crate) fn phantom_store(dir: &Path) -> std::path::PathBuf {
    let path = dir.join("phantom.strata");
    Phantom::cube(48)
        .write_store(&path, &Default::default())
        .expect("writing the test phantom");
    path
}

/// The viewer opened on `store` in the usual 2×2 layout (most tests' whole setup).
pub(crate) fn harness(store: &Path, side_panel: bool) -> Harness<'static, Option<StrataApp>> {
    let folder = store.parent().unwrap_or(Path::new("."));
    harness_with(options_for(store, folder), two_by_two(side_panel))
}

/// The commonest start in one call: the phantom's store in a temp folder, the viewer on it in
/// the 2×2 layout, stepped until its first settled 3D frame (`what` names it in a timeout).
/// The caller keeps the folder alive for the test's length.
pub(crate) fn open_phantom_settled(
    side_panel: bool,
    what: &str,
) -> (
    tempfile::TempDir,
    Harness<'static, Option<StrataApp>>,
    RenderedFrame,
) {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, side_panel);
    let first = wait_for_settled_frame(&mut h, what, 0);
    (dir, h, first)
}

/// Options that open `volume` and import into `folder`/imported (the test's temp folder, never
/// the user's), for a test that changes some before [`harness_with`] or [`harness_sized`].
pub(crate) fn options_for(volume: &Path, folder: &Path) -> ViewerOptions {
    let mut options = ViewerOptions::new(VolumeToOpen::Path(volume.to_path_buf()));
    options.import_folder = folder.join("imported");
    options
}

/// The 2×2 layout with or without the side panel, everything else as a new user has it.
pub(crate) fn two_by_two(side_panel: bool) -> Preferences {
    Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: side_panel,
        ..Preferences::default()
    }
}

pub(crate) fn harness_with(
    options: ViewerOptions,
    preferences: Preferences,
) -> Harness<'static, Option<StrataApp>> {
    harness_sized(options, preferences, Vec2::new(560.0, 380.0))
}

/// A harness with a window of `size` points (taller where a test needs lower side panels).
pub(crate) fn harness_sized(
    mut options: ViewerOptions,
    preferences: Preferences,
    size: Vec2,
) -> Harness<'static, Option<StrataApp>> {
    options.max_render_pixels = 96;
    options.persist_settings = false;
    // Fixed sampling: frames differ only by what the test changes.
    let preferences = Preferences {
        target_fps_enabled: false,
        step_voxels: 1.0,
        ..preferences
    };
    Harness::builder().with_size(size).wgpu().build_ui_state(
        move |ui, state: &mut Option<StrataApp>| {
            state
                .get_or_insert_with(|| {
                    StrataApp::new(ui.ctx().clone(), preferences.clone(), options.clone())
                })
                .ui(ui);
        },
        None,
    )
}

pub(crate) fn app<'h>(h: &'h Harness<'static, Option<StrataApp>>) -> &'h StrataApp {
    h.state()
        .as_ref()
        .expect("the app is created on the first step")
}

/// Steps the UI until `found` gives a value and returns it, failing with `what` after [`WAIT`].
pub(crate) fn step_until_some<T>(
    h: &mut Harness<'static, Option<StrataApp>>,
    what: &str,
    found: impl Fn(&StrataApp) -> Option<T>,
) -> T {
    let start = Instant::now();
    loop {
        h.step();
        if let Some(e) = app(h).job_error() {
            panic!("opening the phantom failed: {e}");
        }
        if let Some(e) = app(h).volume_status().and_then(|s| s.error) {
            panic!("the renderer failed: {e} (needs a Vulkan driver: apt-get install mesa-vulkan-drivers libvulkan1)");
        }
        if let Some(value) = found(app(h)) {
            return value;
        }
        assert!(start.elapsed() < WAIT, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Steps the UI until `done` holds, failing with `what` after [`WAIT`].
pub(crate) fn step_until(
    h: &mut Harness<'static, Option<StrataApp>>,
    what: &str,
    done: impl Fn(&StrataApp) -> bool,
) {
    step_until_some(h, what, |a| done(a).then_some(()));
}

/// The newest 3D frame if it is the final one for the request the UI sends now: rendered for
/// exactly that request (view size, camera, transfer function, settings) and converged. A frame
/// of an earlier request, or one of this request drawn while bricks were still streaming in,
/// is not. The frame carries its own convergence: the session status is published separately
/// and after the frame, so pairing the two can match a frame with another frame's status.
/// Requests only change in `h.step()`, on this thread, so the comparison cannot race the UI.
pub(crate) fn settled_frame(app: &StrataApp) -> Option<RenderedFrame> {
    let frame = app.volume_frame()?;
    (frame.converged && app.volume_request().as_ref() == Some(&frame.request)).then_some(frame)
}

/// Steps until [`settled_frame`] gives a frame newer than serial `after`, and returns that
/// frame (not whatever is newest by the time the caller looks again).
pub(crate) fn wait_for_settled_frame(
    h: &mut Harness<'static, Option<StrataApp>>,
    what: &str,
    after: u64,
) -> RenderedFrame {
    step_until_some(h, what, |a| settled_frame(a).filter(|f| f.serial > after))
}

pub(crate) fn lit_fraction(rgba: &[u8]) -> f64 {
    let lit = rgba
        .chunks_exact(4)
        .filter(|p| p[0].max(p[1]).max(p[2]) > 16)
        .count();
    lit as f64 / (rgba.len() / 4).max(1) as f64
}

pub(crate) fn mean_abs_difference(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (*x as f64 - *y as f64).abs())
        .sum::<f64>()
        / a.len().max(1) as f64
}

pub(crate) fn region_pixels(image: &image::RgbaImage, rect: egui::Rect) -> Vec<u8> {
    let mut out = Vec::new();
    for y in rect.top().max(0.0) as u32..(rect.bottom() as u32).min(image.height()) {
        for x in rect.left().max(0.0) as u32..(rect.right() as u32).min(image.width()) {
            out.extend_from_slice(&image.get_pixel(x, y).0);
        }
    }
    out
}

pub(crate) fn click(
    h: &mut Harness<'static, Option<StrataApp>>,
    at: egui::Pos2,
    button: PointerButton,
) {
    h.event(Event::PointerMoved(at));
    h.event(Event::PointerButton {
        pos: at,
        button,
        pressed: true,
        modifiers: Modifiers::NONE,
    });
    h.event(Event::PointerButton {
        pos: at,
        button,
        pressed: false,
        modifiers: Modifiers::NONE,
    });
    h.step();
}

/// Left-drags from `from` to `to` in steps, as a user would.
pub(crate) fn drag(h: &mut Harness<'static, Option<StrataApp>>, from: egui::Pos2, to: egui::Pos2) {
    h.event(Event::PointerMoved(from));
    h.event(Event::PointerButton {
        pos: from,
        button: PointerButton::Primary,
        pressed: true,
        modifiers: Modifiers::NONE,
    });
    h.step();
    for i in 1..=8 {
        h.event(Event::PointerMoved(from + (to - from) * (i as f32 / 8.0)));
        h.step();
    }
    h.event(Event::PointerButton {
        pos: to,
        button: PointerButton::Primary,
        pressed: false,
        modifiers: Modifiers::NONE,
    });
    h.step();
}

pub(crate) fn set_tool(
    h: &mut Harness<'static, Option<StrataApp>>,
    tool: strata_viewer_ui::measurements::Tool,
) {
    h.state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .expect("volume")
        .scene
        .measurements
        .tool = tool;
}

pub(crate) fn axial_point(h: &Harness<'static, Option<StrataApp>>, i: f64, j: f64) -> egui::Pos2 {
    let v = app(h).volume.as_ref().expect("volume");
    let k = v.scene.cursor[2];
    v.slice_views[SliceView::Axial.index()]
        .screen_of([i, j, k], &v.data)
        .expect("axial image on screen")
}

// ---- Segmentation (issue 52): brush and eraser through real pointer events ----

/// Every labelled voxel of the session's segmentation with its label, sorted by k, j, i (the
/// order the segment crate's `stroke_voxels` gives).
pub(crate) fn labelled_voxels(app: &StrataApp) -> Vec<([u32; 3], u16)> {
    let seg = app
        .volume
        .as_ref()
        .and_then(|v| v.segmentation.as_ref())
        .expect("a segmentation is open");
    let layer = seg.layer.read();
    layer_voxels(&layer)
}

/// Every labelled voxel of `layer` with its label, sorted by k, j, i.
pub(crate) fn layer_voxels(layer: &strata_segment::LabelLayer) -> Vec<([u32; 3], u16)> {
    use strata_segment::LABEL_BRICK;
    let b = LABEL_BRICK as usize;
    let mut out = Vec::new();
    for (key, brick) in layer.edited_bricks() {
        let o = layer.grid().brick_origin(key);
        for (n, &label) in brick.iter().enumerate() {
            if label != 0 {
                let v = [
                    o[0] + (n % b) as u32,
                    o[1] + (n / b % b) as u32,
                    o[2] + (n / (b * b)) as u32,
                ];
                out.push((v, label));
            }
        }
    }
    out.sort_by_key(|(v, _)| [v[2], v[1], v[0]]);
    out
}

/// The screen point of the voxel at (`across`, `down`) of `view`'s slice through the cursor.
pub(crate) fn view_point(
    h: &Harness<'static, Option<StrataApp>>,
    view: SliceView,
    across: f64,
    down: f64,
) -> (egui::Pos2, glam::DVec3) {
    let v = app(h).volume.as_ref().expect("volume");
    let frame = v.data.frame(view);
    let mut index = v.scene.cursor;
    index[frame.across_axis] = across;
    index[frame.down_axis] = down;
    let lps = v
        .data
        .info
        .geometry
        .patient_from_index(glam::DVec3::from(index));
    let screen = v.slice_views[view.index()]
        .screen_of(index, &v.data)
        .expect("slice image on screen");
    (screen, lps)
}

/// The brush plane of a slice view on the primary's own grid: the index plane of its normal.
pub(crate) fn view_plane(
    app: &StrataApp,
    view: SliceView,
) -> strata_segment::tools::brush::SlicePlane {
    use strata_segment::tools::brush::SlicePlane;
    let v = app.volume.as_ref().expect("volume");
    match v.data.frame(view).normal_axis {
        0 => SlicePlane::Sagittal,
        1 => SlicePlane::Coronal,
        _ => SlicePlane::Axial,
    }
}

/// The CPU model of the last stroke: the segment crate's brush over the positions the stroke
/// was applied at, after checking they are where the pointer was pressed and released.
pub(crate) fn last_stroke_model(
    app: &StrataApp,
    view: SliceView,
    from_lps: glam::DVec3,
    to_lps: glam::DVec3,
) -> Vec<[u32; 3]> {
    let seg = app
        .volume
        .as_ref()
        .and_then(|v| v.segmentation.as_ref())
        .expect("a segmentation is open");
    let positions = &seg.last_stroke;
    assert!(positions.len() >= 2, "a drag gives a stroke: {positions:?}");
    // The pointer's f32 screen positions land within a hundredth of a voxel of the centres.
    let tolerance_mm = 0.1;
    let first = positions[0];
    let last = positions[positions.len() - 1];
    assert!(
        first.distance(from_lps) < tolerance_mm && last.distance(to_lps) < tolerance_mm,
        "stroke from {first} to {last}, pointer from {from_lps} to {to_lps}"
    );
    let brush = seg.brush(view_plane(app, view)).expect("brush");
    let layer = seg.layer.read();
    strata_segment::tools::brush::stroke_voxels(layer.grid(), &brush, positions).expect("model")
}

/// Opens the Segment section and starts a new segmentation with the brush of `diameter_mm`.
pub(crate) fn new_segmentation(h: &mut Harness<'static, Option<StrataApp>>, diameter_mm: f64) {
    h.get_by_label("Segment").click();
    h.step();
    h.get_by_label("New segmentation").click();
    step_until(h, "the new segmentation", |a| {
        a.volume
            .as_ref()
            .is_some_and(|v| v.segmentation.is_some() && v.overlay.is_some())
    });
    h.step();
    set_segment_tool(h, crate::segmentation::SegmentTool::Brush);
    if let Some(seg) = h
        .state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .and_then(|v| v.segmentation.as_mut())
    {
        seg.diameter_mm = diameter_mm;
    }
    h.step();
}

/// Chooses a segment tool with one click on its button in the Segment section's tool row, and
/// checks the click chose it.
pub(crate) fn set_segment_tool(
    h: &mut Harness<'static, Option<StrataApp>>,
    tool: crate::segmentation::SegmentTool,
) {
    use crate::segmentation::SegmentTool;
    let label = match tool {
        SegmentTool::None => "Off",
        SegmentTool::Brush => "Brush",
        SegmentTool::Eraser => "Eraser",
        SegmentTool::Fill => "Fill",
        SegmentTool::Grow => "Grow",
    };
    // The row is drawn from the frame after the segmentation opens.
    for _ in 0..10 {
        if h.query_by_label(label).is_some() {
            break;
        }
        h.step();
    }
    h.get_by_label(label).click();
    h.step();
    let chosen = app(h)
        .volume
        .as_ref()
        .and_then(|v| v.segmentation.as_ref())
        .map(|s| s.tool);
    assert_eq!(chosen, Some(tool), "one click on {label:?}");
}
