//! The viewer driven through egui_kittest and drawn with wgpu (lavapipe in CI): a small phantom
//! opens, the 3D view shows it, presets change it, right-drag windows a slice, the wheel pages.
//!
//! Images stay small: the 3D render is capped at 96 px and the harness window is 560×380.
//! Comparisons use tolerances stated where they are made; nothing is compared to a stored
//! snapshot, because lavapipe's and a GPU's rasterisation differ in the last bits.

use std::path::Path;
use std::time::{Duration, Instant};

use egui::{Event, Modifiers, PointerButton, Vec2};
use egui_kittest::kittest::Queryable;
use egui_kittest::Harness;
use strata_storage::phantom::Phantom;

use super::app::{Layout, Preferences, StrataApp, ViewSlot, ViewerOptions};
use super::jobs::VolumeToOpen;
use super::orientation::SliceView;
use super::volume_session::RenderedFrame;

/// Generous: lavapipe on two shared cores compiles the raycast pipeline in seconds.
pub(crate) const WAIT: Duration = Duration::from_secs(180);

pub(crate) fn phantom_store(dir: &Path) -> std::path::PathBuf {
    let path = dir.join("phantom.strata");
    Phantom::cube(48)
        .write_store(&path, &Default::default())
        .expect("writing the test phantom");
    path
}

fn harness(store: &Path, side_panel: bool) -> Harness<'static, Option<StrataApp>> {
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.to_path_buf()));
    options.import_folder = store.parent().unwrap_or(Path::new(".")).join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: side_panel,
        ..Preferences::default()
    };
    harness_with(options, preferences)
}

fn harness_with(
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
fn settled_frame(app: &StrataApp) -> Option<RenderedFrame> {
    let frame = app.volume_frame()?;
    (frame.converged && app.volume_request().as_ref() == Some(&frame.request)).then_some(frame)
}

/// Steps until [`settled_frame`] gives a frame newer than serial `after`, and returns that
/// frame (not whatever is newest by the time the caller looks again).
fn wait_for_settled_frame(
    h: &mut Harness<'static, Option<StrataApp>>,
    what: &str,
    after: u64,
) -> RenderedFrame {
    step_until_some(h, what, |a| settled_frame(a).filter(|f| f.serial > after))
}

fn lit_fraction(rgba: &[u8]) -> f64 {
    let lit = rgba
        .chunks_exact(4)
        .filter(|p| p[0].max(p[1]).max(p[2]) > 16)
        .count();
    lit as f64 / (rgba.len() / 4).max(1) as f64
}

fn mean_abs_difference(a: &[u8], b: &[u8]) -> f64 {
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

#[test]
fn the_phantom_opens_and_the_3d_view_is_not_blank_then_a_preset_changes_it() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, true);
    let bone = wait_for_settled_frame(
        &mut h,
        "the phantom streamed in (converged frame for the current request)",
        0,
    );
    assert_eq!(
        bone.request.transfer_function.name, "ct-bone",
        "a CT opens with the bone preset"
    );
    // The harness checked accessibility when it first settled, with or without the volume
    // (which opens on a thread); check the loaded UI, side panel included, every time.
    h.check_accessibility();
    // The phantom's bone shell fills a good part of the view; a blank or failed frame is ~0.
    let lit = lit_fraction(&bone.rgba);
    assert!(
        lit > 0.05,
        "3D view is (nearly) blank: {:.1}% lit pixels",
        lit * 100.0
    );

    // The same frame on screen, drawn by egui's wgpu renderer: the 3D view rect is lit too.
    let rect = app(&h)
        .view_rect(ViewSlot::ThreeD)
        .expect("3D view laid out");
    h.step();
    let screen = h.render().expect("wgpu render of the UI");
    let on_screen = lit_fraction(&region_pixels(&screen, rect.shrink(20.0)));
    assert!(
        on_screen > 0.03,
        "3D view on screen is blank: {:.1}% lit",
        on_screen * 100.0
    );

    h.get_by_label("Soft tissue").click();
    step_until(&mut h, "the soft-tissue request after the click", |a| {
        a.volume_request()
            .is_some_and(|r| r.transfer_function.name == "ct-soft-tissue")
    });
    let soft = wait_for_settled_frame(&mut h, "the converged soft-tissue frame", bone.serial);
    assert_eq!(soft.request.transfer_function.name, "ct-soft-tissue");
    // Jitter noise between two frames of one preset is well under 1 level of 255 on average;
    // bone → soft tissue changes colour and opacity over most of the object.
    let difference = mean_abs_difference(&bone.rgba, &soft.rgba);
    assert!(
        difference > 3.0,
        "soft-tissue preset left the image almost unchanged (mean |Δ| {difference:.2})"
    );
}

#[test]
fn right_drag_in_a_slice_changes_window_level_and_the_image_and_the_wheel_pages() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, false);
    step_until(&mut h, "the axial slice on screen", |a| {
        a.slice_display(SliceView::Axial).is_some()
    });
    let rect = app(&h)
        .view_rect(ViewSlot::Slice(SliceView::Axial))
        .expect("axial view laid out");
    let shown = app(&h)
        .slice_display(SliceView::Axial)
        .expect("slice shown");
    let (values_before, window_before) = (shown.values, shown.window);
    h.step();
    let screen_before = region_pixels(&h.render().expect("render"), rect.shrink(20.0));

    // Right-drag: 60 points right (wider window) and 30 up (higher level).
    let start = rect.center();
    h.event(Event::PointerMoved(start));
    h.event(Event::PointerButton {
        pos: start,
        button: PointerButton::Secondary,
        pressed: true,
        modifiers: Modifiers::NONE,
    });
    for i in 1..=6 {
        h.event(Event::PointerMoved(
            start + Vec2::new(10.0 * i as f32, -5.0 * i as f32),
        ));
    }
    let end = start + Vec2::new(60.0, -30.0);
    h.event(Event::PointerButton {
        pos: end,
        button: PointerButton::Secondary,
        pressed: false,
        modifiers: Modifiers::NONE,
    });
    h.step();
    let window_after = app(&h).volume.as_ref().expect("volume").scene.window;
    assert!(
        window_after.width > window_before.width,
        "window width did not grow: {window_before:?} → {window_after:?}"
    );
    assert!(
        window_after.centre > window_before.centre,
        "level did not rise: {window_before:?} → {window_after:?}"
    );
    step_until(&mut h, "the re-windowed slice", |a| {
        a.slice_display(SliceView::Axial)
            .is_some_and(|s| s.window == window_after)
    });
    let values_after = app(&h)
        .slice_display(SliceView::Axial)
        .expect("slice shown")
        .values;
    assert!(
        std::sync::Arc::ptr_eq(&values_before, &values_after),
        "a window change must not re-read the slice"
    );
    h.step();
    let screen_after = region_pixels(&h.render().expect("render"), rect.shrink(20.0));
    // Grey levels move by tens of steps where the phantom has structure; noise-free rendering
    // of the same texture would give exactly 0.
    let difference = mean_abs_difference(&screen_before, &screen_after);
    assert!(
        difference > 0.5,
        "slice image unchanged after W/L drag (mean |Δ| {difference:.3})"
    );

    // Wheel: one line up pages one slice along the axial normal.
    let normal = {
        let v = app(&h).volume.as_ref().expect("volume");
        super::orientation::SliceFrame::for_view(SliceView::Axial, &v.data.info.geometry)
            .normal_axis
    };
    let before = app(&h).volume.as_ref().expect("volume").scene.cursor[normal];
    h.event(Event::PointerMoved(rect.center() + Vec2::new(3.0, 3.0)));
    h.event(Event::MouseWheel {
        unit: egui::MouseWheelUnit::Line,
        delta: Vec2::new(0.0, 1.0),
        phase: egui::TouchPhase::Move,
        source: egui::MouseWheelSource::Unknown,
        modifiers: Modifiers::NONE,
    });
    h.step();
    let after = app(&h).volume.as_ref().expect("volume").scene.cursor[normal];
    assert_eq!(
        after,
        before.round() + 1.0,
        "one wheel line pages one slice"
    );
    step_until(&mut h, "the next slice read", |a| {
        a.slice_image(SliceView::Axial)
            .is_some_and(|i| i.request.position == after)
    });
}

#[test]
fn a_scan_imports_with_progress_then_shows_and_f12_writes_a_screenshot() {
    let scan =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/niivue/chris_t1.nii.gz");
    if !scan.exists() {
        eprintln!(
            "SKIP: {} is absent (see ../shared/data/SOURCES.md)",
            scan.display()
        );
        return;
    }
    let dir = tempfile::tempdir().expect("temp dir");
    let mut options = ViewerOptions::new(VolumeToOpen::Path(scan.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        show_side_panel: false,
        screenshot_folder: dir.path().to_path_buf(),
        ..Preferences::default()
    };
    let mut h = harness_with(options, preferences);
    // The import runs on its own thread and names its stage; the first frame follows.
    let saw_stage = std::cell::Cell::new(false);
    step_until(&mut h, "the imported scan's first 3D frame", |a| {
        if a.job_progress()
            .is_some_and(|(_, _, stage)| !stage.is_empty())
        {
            saw_stage.set(true);
        }
        a.volume_frame().is_some()
    });
    assert!(
        saw_stage.get(),
        "no progress was shown while preparing the scan"
    );
    let imported: Vec<_> = std::fs::read_dir(dir.path().join("imported"))
        .expect("import folder")
        .flatten()
        .collect();
    assert_eq!(
        imported.len(),
        1,
        "one store imported into the import folder"
    );
    h.key_press(egui::Key::F12);
    step_until(&mut h, "the screenshot", |a| a.last_screenshot().is_some());
    match app(&h).last_screenshot() {
        Some(Ok(path)) => {
            let image = image::open(&path).expect("screenshot is a PNG");
            assert!(
                image.width() >= 16 && image.height() >= 16,
                "screenshot {}x{}",
                image.width(),
                image.height()
            );
        }
        other => panic!("screenshot failed: {other:?}"),
    }
}

#[test]
fn a_click_in_the_transfer_function_editor_adds_a_point_that_the_next_frame_uses() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, true);
    step_until(&mut h, "the converged first frame and the editor", |a| {
        settled_frame(a).is_some()
            && a.volume.is_some()
            && a.panels.transfer_function.editor.plot_rect.is_some()
    });
    h.check_accessibility();
    let (plot, points_before) = {
        let v = app(&h).volume.as_ref().expect("volume");
        (
            app(&h)
                .panels
                .transfer_function
                .editor
                .plot_rect
                .expect("plot drawn"),
            v.scene.transfer_function.opacity.len(),
        )
    };
    // Left of the middle, a third of the way down: high opacity where the bone preset has none,
    // away from its existing points.
    let at = plot.left_top() + Vec2::new(plot.width() * 0.42, plot.height() * 0.3);
    h.event(Event::PointerMoved(at));
    h.event(Event::PointerButton {
        pos: at,
        button: PointerButton::Primary,
        pressed: true,
        modifiers: Modifiers::NONE,
    });
    h.event(Event::PointerButton {
        pos: at,
        button: PointerButton::Primary,
        pressed: false,
        modifiers: Modifiers::NONE,
    });
    h.step();
    // Read after the step that applied the click (and sent the new request): the newest frame
    // then, or the one in flight, may predate the edit; any frame after those cannot.
    let serial_at_edit = app(&h).volume_frame().map_or(0, |f| f.serial);
    let edited = app(&h)
        .volume
        .as_ref()
        .expect("volume")
        .scene
        .transfer_function
        .clone();
    assert_eq!(
        edited.opacity.len(),
        points_before + 1,
        "a click on empty plot adds one opacity point"
    );
    assert_eq!(
        app(&h).volume_request().map(|r| r.transfer_function),
        Some(edited.clone()),
        "the edit goes out with the render request of the step that made it"
    );
    // The render thread takes the newest request each frame, so only the frame in flight at
    // the edit may answer an older one: from serial_at_edit + 2 on, every frame shows the edit.
    let settled = step_until_some(&mut h, "the converged frame after the edit", |a| {
        let frame = a.volume_frame()?;
        if frame.serial >= serial_at_edit + 2 {
            assert_eq!(
                frame.request.transfer_function, edited,
                "frame {} (edit at {serial_at_edit}) ignores the edit",
                frame.serial
            );
        }
        settled_frame(a).filter(|f| f.serial > serial_at_edit)
    });
    assert_eq!(
        settled.request.transfer_function, edited,
        "the converged frame after the edit is drawn with it"
    );
    // The edited function no longer claims to be the preset (titles, preset buttons).
    assert_eq!(edited.name, "ct-bone (edited)");
    assert!(app(&h).volume.as_ref().is_some_and(|v| v.scene.tf_edited()));
}

#[test]
fn a_file_that_cannot_be_opened_shows_its_error_once() {
    let dir = tempfile::tempdir().expect("temp dir");
    let bad = dir.path().join("broken.nii");
    std::fs::write(&bad, b"this is not a NIfTI file at all, just some bytes").expect("write");
    let mut options = ViewerOptions::new(VolumeToOpen::Path(bad));
    options.import_folder = dir.path().join("imported");
    let mut h = harness_with(options, Preferences::default());
    let start = Instant::now();
    let error = loop {
        h.step();
        if let Some(e) = app(&h).job_error() {
            break e.to_string();
        }
        assert!(start.elapsed() < WAIT, "no error for a broken file");
        std::thread::sleep(Duration::from_millis(20));
    };
    h.step();
    h.step();
    // Dialog and waiting screen used to show the same text, one behind the other.
    let shown = h.query_all_by_label(&error).count();
    assert_eq!(shown, 1, "the error {error:?} is shown {shown} times");
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

#[test]
fn the_readout_shows_the_hu_voxel_and_position_under_the_pointer() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, false);
    step_until(&mut h, "the axial slice drawn", |a| {
        a.slice_display(SliceView::Axial).is_some()
            && a.volume
                .as_ref()
                .is_some_and(|v| v.slice_views[SliceView::Axial.index()].image_rect.is_some())
    });
    let (k, at) = {
        let v = app(&h).volume.as_ref().expect("volume");
        let k = v.scene.cursor[2];
        // A voxel in the body, off the crosshair (which the readout shows otherwise).
        let target = [30.0, 20.0, k];
        let at = v.slice_views[SliceView::Axial.index()]
            .screen_of(target, &v.data)
            .expect("axial image on screen");
        (k as u32, at)
    };
    h.event(Event::PointerMoved(at));
    let readout = step_until_some(&mut h, "the value under the pointer", |a| {
        a.readout
            .clone()
            .filter(|r| r.under_pointer && r.value.is_some())
    });
    assert_eq!(readout.index, [30, 20, k], "the voxel under the pointer");
    // The phantom's own HU at that voxel (its slope is 1, so storage is exact).
    let phantom = Phantom::cube(48);
    let expected = phantom.hu(30, 20, k as u64) as f64;
    assert_eq!(readout.value, Some(expected), "HU at voxel (30, 20, {k})");
    assert_eq!(readout.unit, "HU");
    let g = phantom.geometry();
    let spacing = g.spacing_mm[0];
    for (axis, i) in [30.0, 20.0, k as f64].iter().enumerate() {
        let mm = g.origin_lps_mm[axis] + i * spacing;
        assert!(
            (readout.patient_mm[axis] - mm).abs() < 1e-9,
            "axis {axis}: {} vs {mm}",
            readout.patient_mm[axis]
        );
    }
    // And the status bar says so.
    h.step();
    let text = app(&h).readout.as_ref().expect("readout").text();
    assert!(text.contains(&format!("{expected:.0} HU")), "{text}");
    h.get_by_label(&text);
}

/// Trilinear value of the phantom at a continuous index (clamped to the volume).
fn phantom_value(p: &Phantom, index: glam::DVec3) -> f64 {
    let n = p.size.map(|d| d as f64 - 1.0);
    let c = [
        index.x.clamp(0.0, n[0]),
        index.y.clamp(0.0, n[1]),
        index.z.clamp(0.0, n[2]),
    ];
    let base = c.map(|x| x.floor());
    let f = [c[0] - base[0], c[1] - base[1], c[2] - base[2]];
    let mut value = 0.0;
    for corner in 0..8 {
        let mut w = 1.0;
        let mut at = [0u64; 3];
        for a in 0..3 {
            let up = corner >> a & 1 == 1;
            w *= if up { f[a] } else { 1.0 - f[a] };
            at[a] = ((base[a] + up as u8 as f64).min(n[a])) as u64;
        }
        if w > 0.0 {
            value += w * p.hu(at[0], at[1], at[2]) as f64;
        }
    }
    value
}

#[test]
fn a_click_in_the_3d_view_picks_the_bone_surface_it_shows() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    options.initial_view = Some(super::view3d::StandardView::Anterior);
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: false,
        mode: strata_render::RenderMode::Isosurface,
        ..Preferences::default()
    };
    let mut h = harness_with(options, preferences);
    // The viewer's CT iso value (300 HU): the spine's cortical shell is 1200 HU, the contrast
    // aorta in front of it 300, so the click goes right of the aorta, onto the spine.
    const ISO: f64 = 300.0;
    step_until(&mut h, "the volume open", |a| a.volume.is_some());
    assert_eq!(
        app(&h).volume.as_ref().expect("volume").scene.iso_value,
        ISO
    );
    let frame = wait_for_settled_frame(&mut h, "the converged isosurface frame", 0);
    assert_eq!(frame.request.settings.iso_value, ISO);
    let rect = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");
    // Right of the centre (the patient's left in an anterior view), clear of the aorta.
    let at = rect.center() + Vec2::new(4.0, 2.0);
    click(&mut h, at, PointerButton::Primary);
    let picked = app(&h).volume.as_ref().expect("volume").scene.cursor;

    // The same pixel's ray, marched on the CPU through the phantom's own values in steps of
    // 1/20 voxel: the first crossing of the iso value is the surface the user sees there.
    let (px, py) = (
        ((at.x - rect.left()) / rect.width() * frame.width as f32) as u32,
        ((at.y - rect.top()) / rect.height() * frame.height as f32) as u32,
    );
    let (origin, dir) = frame
        .request
        .camera
        .basis()
        .ray(px, py, frame.width, frame.height);
    let phantom = Phantom::cube(48);
    let g = phantom.geometry();
    let geometry = strata_render::VolumeGeometry {
        dims: g.dims,
        spacing_mm: g.spacing_mm,
        origin_lps_mm: g.origin_lps_mm,
        direction: g.direction,
    };
    let step = g.spacing_mm[0] / 20.0;
    let mut expected = None;
    let mut t = 0.0;
    while t < 3000.0 {
        let index = geometry.index_from_patient(origin + dir * t);
        let inside = (0..3).all(|a| index[a] >= 0.0 && index[a] <= g.dims[a] as f64 - 1.0);
        if inside && phantom_value(&phantom, index) >= ISO {
            expected = Some(index);
            break;
        }
        t += step;
    }
    let expected = expected.expect("the test ray meets bone (move the click)");
    let off = (glam::DVec3::from(picked) - expected).abs().max_element();
    // Within a voxel: the GPU samples every half voxel and bisects, on 8-bit-weighted
    // trilinear filtering; the CPU march is exact to 1/20 voxel.
    assert!(
        off <= 1.0,
        "picked {picked:?}, the surface is at {expected:?} ({off:.2} voxels off)"
    );
    // What was hit is bone: a voxel of at least 700 HU within a voxel of the pick.
    let bone_nearby = (0..27).any(|o| {
        let offset = glam::DVec3::new(
            (o % 3) as f64 - 1.0,
            (o / 3 % 3) as f64 - 1.0,
            (o / 9) as f64 - 1.0,
        );
        let v = (glam::DVec3::from(picked) + offset).round();
        (0..3).all(|a| v[a] >= 0.0 && v[a] < 48.0)
            && phantom.hu(v.x as u64, v.y as u64, v.z as u64) >= 700
    });
    assert!(bone_nearby, "no bone within a voxel of the pick {picked:?}");
    // The readout over the 3D view names the picked voxel.
    h.event(Event::PointerMoved(at));
    h.step();
    let readout = step_until_some(&mut h, "the readout over the 3D view", |a| {
        a.readout.clone().filter(|r| r.under_pointer)
    });
    assert_eq!(
        readout.index,
        super::scene::voxel_index(picked).map(|i| i as u32)
    );
}

/// Mean of the 5×5 screen pixels around `at` (one channel).
fn screen_patch(image: &image::RgbaImage, at: egui::Pos2, channel: usize) -> f64 {
    let rect = egui::Rect::from_center_size(at, Vec2::splat(5.0));
    let pixels = region_pixels(image, rect);
    let n = pixels.len() / 4;
    pixels
        .chunks_exact(4)
        .map(|p| p[channel] as f64)
        .sum::<f64>()
        / n.max(1) as f64
}

#[test]
fn a_window_preset_and_the_inverted_colour_map_reach_the_screen() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        ..Preferences::default()
    };
    // Tall enough for the slices panel below the transfer-function editor.
    let mut h = harness_sized(options, preferences, Vec2::new(720.0, 900.0));
    step_until(&mut h, "the axial slice drawn", |a| {
        a.slice_display(SliceView::Axial).is_some()
    });
    h.get_by_label("Mediastinum").click();
    h.step();
    let mediastinum = super::scene::Window::new(50.0, 350.0);
    assert_eq!(
        app(&h).volume.as_ref().expect("volume").scene.window,
        mediastinum
    );
    step_until(&mut h, "the slice in the mediastinal window", |a| {
        a.slice_display(SliceView::Axial)
            .is_some_and(|s| s.window == mediastinum)
    });
    h.step();
    // Air outside the body (-1000 HU) is below the window: black in grey, white inverted.
    let air_at = |h: &Harness<'static, Option<StrataApp>>| {
        let v = app(h).volume.as_ref().expect("volume");
        let k = v.scene.cursor[2];
        v.slice_views[SliceView::Axial.index()]
            .screen_of([3.0, 3.0, k], &v.data)
            .expect("axial image on screen")
    };
    let at = air_at(&h);
    let grey = screen_patch(&h.render().expect("render"), at, 0);
    h.state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .expect("volume")
        .scene
        .colour_map = super::colour_maps::ColourMap::Inverted;
    step_until(&mut h, "the inverted slice", |a| {
        a.slice_display(SliceView::Axial)
            .is_some_and(|s| s.colour_map == super::colour_maps::ColourMap::Inverted)
    });
    h.step();
    let inverted = screen_patch(&h.render().expect("render"), air_at(&h), 0);
    // Exact 0 and 255 in the texture; a few levels for the UI's blending and sRGB rounding.
    assert!(
        grey < 8.0,
        "air in the mediastinal window is not black: {grey}"
    );
    assert!(inverted > 247.0, "air inverted is not white: {inverted}");
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

fn set_tool(h: &mut Harness<'static, Option<StrataApp>>, tool: super::measurements::Tool) {
    h.state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .expect("volume")
        .scene
        .measurements
        .tool = tool;
}

fn axial_point(h: &Harness<'static, Option<StrataApp>>, i: f64, j: f64) -> egui::Pos2 {
    let v = app(h).volume.as_ref().expect("volume");
    let k = v.scene.cursor[2];
    v.slice_views[SliceView::Axial.index()]
        .screen_of([i, j, k], &v.data)
        .expect("axial image on screen")
}

#[test]
fn a_ruler_reads_the_millimetres_and_a_box_roi_the_phantoms_statistics_and_undo_removes_them() {
    use super::measurements::{Shape, Tool};
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, false);
    step_until(&mut h, "the axial slice at full resolution", |a| {
        a.slice_image(SliceView::Axial)
            .is_some_and(|i| i.request.level == 0)
            && a.volume
                .as_ref()
                .is_some_and(|v| v.slice_views[SliceView::Axial.index()].image_rect.is_some())
    });
    let phantom = Phantom::cube(48);
    let spacing = phantom.geometry().spacing_mm[0];

    set_tool(&mut h, Tool::Distance);
    let (from, to) = (axial_point(&h, 10.0, 10.0), axial_point(&h, 30.0, 25.0));
    drag(&mut h, from, to);
    let (length, text) = {
        let v = app(&h).volume.as_ref().expect("volume");
        let items = &v.scene.measurements.items;
        assert_eq!(items.len(), 1, "one ruler");
        let Shape::Distance { a, b } = items[0].shape else {
            panic!("not a ruler: {:?}", items[0]);
        };
        (
            super::measurements::distance_mm(&v.data.info.geometry, a, b),
            items[0].describe(&v.data.info.geometry, "HU"),
        )
    };
    // 20 voxels across and 15 down: 25 voxels of 400/48 mm. The pointer lands within a
    // hundredth of a screen point of the voxel centres (f32 positions).
    let expected = 25.0 * spacing;
    assert!(
        (length - expected).abs() < 0.05,
        "ruler {length:.3} mm, expected {expected:.3}"
    );
    assert!(text.contains(&format!("{expected:.1} mm")), "{text}");

    set_tool(&mut h, Tool::BoxRoi);
    let (from, to) = (axial_point(&h, 14.0, 16.0), axial_point(&h, 21.0, 26.0));
    drag(&mut h, from, to);
    let stats = {
        let v = app(&h).volume.as_ref().expect("volume");
        let items = &v.scene.measurements.items;
        assert_eq!(items.len(), 2, "a ruler and a box");
        let Shape::Roi { stats, .. } = &items[1].shape else {
            panic!("not a region: {:?}", items[1]);
        };
        stats.expect("statistics of the box")
    };
    // The phantom's own HU over the voxels whose centres lie in the box: i 14..=21, j 16..=26
    // (corners on voxel centres count as inside, up to the pointer's f32 rounding).
    let k = app(&h).volume.as_ref().expect("volume").scene.cursor[2] as u64;
    let values: Vec<f64> = (16..=26)
        .flat_map(|j| (14..=21).map(move |i| (i, j)))
        .map(|(i, j)| phantom.hu(i, j, k) as f64)
        .collect();
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let sd = (values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n).sqrt();
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * (1.0 + b.abs());
    // Corners exactly on voxel centres may fall either side by f32 rounding: allow the edge
    // rows/columns to be in or out by checking the count and mean against both.
    if stats.voxels == values.len() as u64 {
        assert!(
            close(stats.mean, mean) && close(stats.sd, sd),
            "{stats:?} vs mean {mean} sd {sd}"
        );
        assert_eq!(
            stats.min,
            values.iter().cloned().fold(f64::INFINITY, f64::min)
        );
        assert_eq!(
            stats.max,
            values.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
        );
    } else {
        assert!(
            stats.voxels >= 6 * 9 && stats.voxels < values.len() as u64,
            "{} voxels (expected {} or a trimmed edge)",
            stats.voxels,
            values.len()
        );
    }
    let area = 7.0 * spacing * 10.0 * spacing;
    assert!(
        (stats.area_mm2 - area).abs() < 0.5,
        "area {} vs {area}",
        stats.area_mm2
    );

    // Undo takes the box away, then the ruler; redo brings the ruler back.
    h.key_press_modifiers(Modifiers::COMMAND, egui::Key::Z);
    h.step();
    let count = |h: &Harness<'static, Option<StrataApp>>| {
        app(h)
            .volume
            .as_ref()
            .expect("volume")
            .scene
            .measurements
            .items
            .len()
    };
    assert_eq!(count(&h), 1);
    h.key_press_modifiers(Modifiers::COMMAND, egui::Key::Z);
    h.step();
    assert_eq!(count(&h), 0);
    h.key_press_modifiers(Modifiers::COMMAND | Modifiers::SHIFT, egui::Key::Z);
    h.step();
    assert_eq!(count(&h), 1);
}

#[test]
fn undo_restores_the_transfer_function_exactly_and_redo_the_edit() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, true);
    step_until(&mut h, "the editor", |a| {
        a.volume.is_some() && a.panels.transfer_function.editor.plot_rect.is_some()
    });
    h.step();
    let tf = |h: &Harness<'static, Option<StrataApp>>| {
        app(h)
            .volume
            .as_ref()
            .expect("volume")
            .scene
            .transfer_function
            .clone()
    };
    let original = tf(&h);
    let plot = app(&h)
        .panels
        .transfer_function
        .editor
        .plot_rect
        .expect("plot");
    click(
        &mut h,
        plot.left_top() + Vec2::new(plot.width() * 0.42, plot.height() * 0.3),
        PointerButton::Primary,
    );
    h.step();
    let edited = tf(&h);
    assert_ne!(edited, original, "the click edited the function");
    h.key_press_modifiers(Modifiers::COMMAND, egui::Key::Z);
    h.step();
    assert_eq!(tf(&h), original, "undo restores the function exactly");
    assert_eq!(
        app(&h).volume_request().map(|r| r.transfer_function),
        Some(original),
        "and the renderer is asked for it"
    );
    h.key_press_modifiers(Modifiers::COMMAND | Modifiers::SHIFT, egui::Key::Z);
    h.step();
    assert_eq!(tf(&h), edited, "redo brings the edit back");
}

#[test]
fn a_screenshot_has_the_views_full_pixel_size_and_its_annotations() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let shots = dir.path().join("shots (picked folder)");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: false,
        screenshot_folder: shots.clone(),
        // The interactive render is at 60 % of the view's pixels; the screenshot must not be.
        render_scale: 0.6,
        ..Preferences::default()
    };
    let mut h = harness_with(options, preferences);
    wait_for_settled_frame(&mut h, "the first converged frame", 0);
    let interactive = app(&h).volume_frame().expect("frame");
    h.key_press(egui::Key::F12);
    let path = step_until_some(&mut h, "the screenshot written", |a| {
        a.last_screenshot()
            .map(|r| r.unwrap_or_else(|e| panic!("screenshot failed: {e}")))
    });
    assert!(
        path.starts_with(&shots),
        "{} is not in the picked folder",
        path.display()
    );
    let rect = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");
    let ppp = h.ctx.pixels_per_point();
    let expected = super::view3d::View3d::full_resolution_size(rect, ppp);
    let image = image::open(&path).expect("a PNG").to_rgb8();
    assert_eq!(
        [image.width(), image.height()],
        expected,
        "the screenshot is the view's pixel size (the interactive frame was {}x{})",
        interactive.width,
        interactive.height
    );
    assert!(
        interactive.width < expected[0],
        "the test needs a reduced interactive frame"
    );
    // The orange not-for-diagnosis label is in the bottom-right corner of the image.
    let corner = image
        .enumerate_pixels()
        .filter(|(x, y, _)| *x > image.width() * 2 / 3 && *y > image.height() - 20)
        .filter(|(_, _, p)| p[0] > 200 && (120..220).contains(&p[1]) && p[2] < 110)
        .count();
    assert!(
        corner > 5,
        "no warning label in the screenshot ({corner} orange pixels)"
    );
    // And the volume itself.
    let lit = image
        .pixels()
        .filter(|p| p.0.iter().any(|c| *c > 16))
        .count();
    assert!(
        lit * 20 > (image.width() * image.height()) as usize,
        "screenshot nearly blank"
    );
}

#[test]
fn the_crop_box_is_drawn_in_3d_and_dragging_its_superior_handle_lowers_the_top() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    options.initial_view = Some(super::view3d::StandardView::Anterior);
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: false,
        show_crop_box: true,
        ..Preferences::default()
    };
    let mut h = harness_with(options, preferences);
    wait_for_settled_frame(&mut h, "the first converged frame", 0);
    let rect = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");
    let handles = {
        let v = app(&h).volume.as_ref().expect("volume");
        let camera = v.view_3d.orbit.camera(&v.data.info.geometry);
        super::view3d::crop_handles(rect, &camera, &v.data, &v.scene)
    };
    let labels: Vec<&str> = handles.iter().map(|h| h.label).collect();
    for face in ["R", "L", "A", "P", "S", "I"] {
        assert!(labels.contains(&face), "no {face} handle: {labels:?}");
    }
    let top = *handles.iter().find(|h| h.label == "S").expect("S handle");
    assert_eq!(
        (top.axis, top.max_side),
        (2, true),
        "the phantom's +k is superior"
    );
    // Seen from the front, superior is up: dragging the S handle 20 points down lowers the top.
    drag(&mut h, top.at, top.at + Vec2::new(0.0, 20.0));
    let crop = app(&h).volume.as_ref().expect("volume").scene.crop;
    assert!(
        crop.max[2] < 0.95 && crop.max[2] > 0.5,
        "crop top {} after the drag",
        crop.max[2]
    );
    assert_eq!(crop.min, [0.0; 3]);
    assert_eq!(&crop.max[..2], &[1.0, 1.0]);
    h.step();
    assert_eq!(
        app(&h).volume_request().map(|r| r.settings.crop),
        Some(crop),
        "the renderer is asked for the new crop"
    );
    // One undo step for the whole drag.
    h.key_press_modifiers(Modifiers::COMMAND, egui::Key::Z);
    h.step();
    assert_eq!(
        app(&h).volume.as_ref().expect("volume").scene.crop,
        strata_render::CropBox::default()
    );
}

/// Issue 13: the GPU is lost (the render thread's device destroyed for real on lavapipe) in the
/// middle of a session with an edited transfer function, a ruler and a turned camera. The
/// renderer comes back on a new device with half the brick cache, the status bar says so, and
/// the session is as it was: same scene, same camera, and the 3D view shows the same image.
#[test]
fn a_lost_gpu_device_is_rebuilt_with_a_smaller_cache_and_the_session_carries_on() {
    use super::gpu_recovery::InjectedFault;
    use super::measurements::Tool;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, true);
    let first = wait_for_settled_frame(&mut h, "the phantom", 0);
    h.get_by_label("Soft tissue").click();
    step_until(&mut h, "the axial slice on screen", |a| {
        a.volume
            .as_ref()
            .is_some_and(|v| v.slice_views[SliceView::Axial.index()].image_rect.is_some())
    });
    set_tool(&mut h, Tool::Distance);
    let (from, to) = (axial_point(&h, 10.0, 10.0), axial_point(&h, 30.0, 25.0));
    drag(&mut h, from, to);
    if let Some(v) = h.state_mut().as_mut().and_then(|a| a.volume.as_mut()) {
        v.view_3d.orbit.azimuth_deg += 40.0;
    }
    let before = wait_for_settled_frame(&mut h, "the edited session", first.serial);
    let (scene_before, orbit_before) = {
        let v = app(&h).volume.as_ref().expect("volume");
        (v.scene.clone(), v.view_3d.orbit)
    };
    assert_eq!(
        scene_before.measurements.items.len(),
        1,
        "the ruler is there"
    );
    assert_eq!(before.request.transfer_function.name, "ct-soft-tissue");

    app(&h)
        .volume
        .as_ref()
        .expect("volume")
        .data
        .session
        .inject_gpu_fault(InjectedFault::DestroyDevice);
    let after = step_until_some(&mut h, "the rebuilt renderer's frame", |a| {
        let recovered = a.volume_status().is_some_and(|s| s.gpu_recoveries == 1);
        settled_frame(a).filter(|f| recovered && f.serial > before.serial)
    });
    h.step();
    let status = app(&h).volume_status().expect("status");
    assert_eq!(
        status.gpu_budget_bytes,
        super::volume_session::DEFAULT_GPU_BUDGET_BYTES / 2
    );
    assert!(
        h.query_by_label_contains("the renderer was restarted with a 192 MiB brick cache")
            .is_some(),
        "the status bar says what happened"
    );
    let v = app(&h).volume.as_ref().expect("volume");
    assert_eq!(
        v.scene, scene_before,
        "scene (TF, window, crop, ruler) kept"
    );
    assert_eq!(v.view_3d.orbit, orbit_before, "camera kept");
    assert_eq!(after.request, before.request, "the same view is asked for");
    // Jitter is on in the viewer, keyed by the frame index, which runs on across the rebuild:
    // the two converged frames differ by sampling noise only. 3 of 255 on the mean is well
    // under what a preset change makes (tens) and above the jitter noise of a 96 px frame.
    let difference = mean_abs_difference(&before.rgba, &after.rgba);
    assert!(
        difference < 3.0,
        "the view changed across the rebuild by {difference:.2} per channel"
    );
}

/// Issue 16: a label map on a coarser, shifted grid (40³ of 10 mm over the phantom's 48³ of
/// 8.3 mm), opened from the overlay panel as a NRRD, colours exactly the axial pixels whose
/// patient position falls in a labelled overlay voxel, in that label's colour at the chosen
/// opacity; background and hidden labels leave the slice as it was; the readout names the
/// label under the pointer.
#[test]
fn a_label_map_overlay_colours_the_right_pixels_and_a_hidden_label_clears_them() {
    use super::overlay::tests::{label_of, write_nrrd, LABEL_DIMS, LABEL_ORIGIN, LABEL_SPACING};
    use super::overlay::OverlayKind;
    use strata_segment::label_colour;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let labels = dir.path().join("labels.nrrd");
    write_nrrd(
        &labels,
        LABEL_DIMS,
        LABEL_SPACING,
        LABEL_ORIGIN,
        false,
        label_of,
    );
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    // Large enough for ~6 screen pixels per phantom voxel in the axial view.
    let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 800.0));
    step_until(&mut h, "the axial slice at full resolution", |a| {
        a.slice_display(SliceView::Axial).is_some()
            && a.slice_image(SliceView::Axial)
                .is_some_and(|i| i.request.level == 0)
    });
    h.get_by_label("Overlay").click();
    h.step();
    if let Some(a) = h.state_mut().as_mut() {
        a.panels.overlay.path = labels.display().to_string();
    }
    h.step();
    h.get_by_label("Open overlay").click();
    step_until_some(&mut h, "the overlay over the axial slice", |a| {
        let v = a.volume.as_ref()?;
        let o = v.overlay.as_ref()?;
        let image = a.slice_image(SliceView::Axial)?;
        o.latest(SliceView::Axial)
            .filter(|s| s.request == image.request)
            .map(|_| ())
    });
    let kind = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.overlay.as_ref())
        .map(|o| o.kind);
    assert_eq!(kind, Some(OverlayKind::Labels));
    // A few frames for the texture upload.
    for _ in 0..3 {
        h.step();
    }
    let shown = h.render().expect("render");
    // The slice alone, in the same layout (the panel grew when the overlay opened).
    let set_style = |h: &mut Harness<'static, Option<StrataApp>>,
                     change: &dyn Fn(&mut super::overlay::OverlayStyle)| {
        if let Some(o) = h
            .state_mut()
            .as_mut()
            .and_then(|a| a.volume.as_mut())
            .and_then(|v| v.overlay.as_mut())
        {
            change(&mut o.style);
        }
        for _ in 0..3 {
            h.step();
        }
    };
    set_style(&mut h, &|s| s.visible = false);
    let base = h.render().expect("render");
    set_style(&mut h, &|s| s.visible = true);

    // Points well inside one overlay voxel's label region: the label at the voxel's centre
    // and at its four corners (half a voxel away) agree, so the 5×5 patch is one label.
    let (geometry, overlay_geometry, k) = {
        let v = app(&h).volume.as_ref().expect("volume");
        let mut g = strata_render::VolumeGeometry::axis_aligned(LABEL_DIMS, [LABEL_SPACING; 3]);
        g.origin_lps_mm = LABEL_ORIGIN;
        (v.data.info.geometry.clone(), g, v.scene.cursor[2].round())
    };
    let cursor = app(&h).volume.as_ref().expect("volume").scene.cursor;
    let label_at = |i: f64, j: f64| -> Option<u32> {
        let o = overlay_geometry.index_from_patient(geometry.patient_from_index([i, j, k]));
        if (0..3).any(|a| o[a] < -0.5 || o[a] >= LABEL_DIMS[a] as f64 - 0.5) {
            return None;
        }
        let n = o.round();
        Some(label_of(n.x as u32, n.y as u32, n.z as u32) as u32)
    };
    let mut checked = [0usize; 5];
    let mut hidden_points = Vec::new();
    // Away from the image's top rows, which the view's title bar covers.
    for j in 8..44 {
        for i in 4..44 {
            let (i, j) = (i as f64, j as f64);
            // The crosshair is drawn over the overlay: keep away from its lines.
            if (i - cursor[0]).abs() < 2.0 || (j - cursor[1]).abs() < 2.0 {
                continue;
            }
            let Some(label) = label_at(i, j) else {
                continue;
            };
            let uniform = [(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)]
                .iter()
                .all(|(di, dj)| label_at(i + di, j + dj) == Some(label));
            if !uniform || checked[label as usize] >= 6 {
                continue;
            }
            checked[label as usize] += 1;
            let at = {
                let v = app(&h).volume.as_ref().expect("volume");
                v.slice_views[SliceView::Axial.index()]
                    .screen_of([i, j, k], &v.data)
                    .expect("on screen")
            };
            let colour = label_colour(label as i64);
            // A 3×3 patch: a voxel is ~6 screen pixels here, and the overlay texture is
            // sampled nearest, so the patch must stay inside one texel.
            let patch = |image: &image::RgbaImage, c: usize| {
                let pixels =
                    region_pixels(image, egui::Rect::from_center_size(at, Vec2::splat(3.0)));
                pixels.chunks_exact(4).map(|p| p[c] as f64).sum::<f64>()
                    / (pixels.len() / 4).max(1) as f64
            };
            let before: Vec<f64> = (0..3).map(|c| patch(&base, c)).collect();
            let after: Vec<f64> = (0..3).map(|c| patch(&shown, c)).collect();
            // Premultiplied "over" at opacity 0.5, as egui blends (gamma space); 8 levels for
            // the blend's rounding and the patch mean. Background leaves the slice alone.
            let expected: Vec<f64> = before
                .iter()
                .zip(colour)
                .map(|(b, c)| {
                    if label == 0 {
                        *b
                    } else {
                        0.5 * b + 0.5 * c as f64
                    }
                })
                .collect();
            let sampled = {
                let v = app(&h).volume.as_ref().expect("volume");
                let o = v.overlay.as_ref().expect("overlay");
                o.latest(SliceView::Axial)
                    .map(|s| s.values[j as usize * s.width + i as usize])
            };
            assert!(
                after
                    .iter()
                    .zip(&expected)
                    .all(|(a, e)| (a - e).abs() <= 8.0),
                "label {label} at voxel ({i},{j}): {after:.1?} on screen, {expected:.1?} \
                 expected (slice alone {before:.1?}); sampled {sampled:?} at {at:?}"
            );
            if label == 2 {
                hidden_points.push(at);
            }
        }
    }
    assert!(
        checked.iter().all(|&n| n > 0),
        "every label (and background) checked: {checked:?}"
    );

    // The readout under the pointer names the label.
    let probe = hidden_points[0];
    h.event(Event::PointerMoved(probe));
    h.step();
    h.step();
    assert!(
        h.query_by_label_contains("label 2").is_some(),
        "the readout shows the overlay's label"
    );

    // Hide label 2: its pixels show the slice alone again.
    h.event(Event::PointerMoved(egui::Pos2::new(5.0, 5.0)));
    set_style(&mut h, &|s| {
        s.hidden_labels.insert(2);
    });
    let hidden = h.render().expect("render");
    for at in hidden_points {
        for c in 0..3 {
            // 3×3 as above: a 5×5 patch can reach a neighbouring label's texel.
            let patch = |image: &image::RgbaImage| {
                let pixels =
                    region_pixels(image, egui::Rect::from_center_size(at, Vec2::splat(3.0)));
                pixels.chunks_exact(4).map(|p| p[c] as f64).sum::<f64>()
                    / (pixels.len() / 4).max(1) as f64
            };
            let (before, after) = (patch(&base), patch(&hidden));
            assert!(
                (after - before).abs() <= 2.0,
                "hidden label 2 still drawn: {after:.1} vs {before:.1}"
            );
        }
    }
}

/// Issue 16: the oblique view shows the CPU resampling of its plane (the path checked against
/// the f64 trilinear reference in oblique.rs), a drag turns the plane by the drag's angle,
/// and "Align to 3D" turns it to face the 3D camera.
#[test]
fn the_oblique_view_resamples_its_plane_turns_with_a_drag_and_aligns_to_the_3d_camera() {
    use super::oblique::{resample, LevelBrickCache};
    use super::oblique_view::TURN_PER_POINT;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_oblique: true,
        show_side_panel: false,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(800.0, 640.0));
    let current = |a: &StrataApp| {
        let v = a.volume.as_ref()?;
        let plane = v.oblique_view.current_plane(&v.data, &v.scene);
        v.oblique_view
            .shown()
            .filter(|i| i.request.plane == plane)
            .cloned()
    };
    let first = step_until_some(&mut h, "the oblique image", current);
    // What the view shows is the resampling of its request, value for value.
    // The viewer holds its store; the same phantom written again has the same bricks.
    let twin_dir = tempfile::tempdir().expect("temp dir");
    let opened = strata_storage::Store::open(&phantom_store(twin_dir.path())).expect("open");
    let again =
        resample(&opened, &mut LevelBrickCache::new(8 << 20), &first.request).expect("resample");
    assert!(first
        .values
        .iter()
        .zip(again.values.iter())
        .all(|(a, b)| a == b || (a.is_nan() && b.is_nan())));
    assert!(
        first.values.iter().filter(|v| v.is_finite()).count() > first.values.len() / 4,
        "the axial plane through the centre crosses the volume"
    );
    let rect = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.oblique_view.image_rect)
        .expect("oblique image on screen");
    let screen = h.render().expect("render");
    assert!(
        lit_fraction(&region_pixels(&screen, rect.shrink(10.0))) > 0.05,
        "the oblique view is blank on screen"
    );

    // Drag 40 points right: the plane turns 0.4 rad about its vertical axis.
    let start = rect.center() + Vec2::new(-20.0, 30.0);
    drag(&mut h, start, start + Vec2::new(40.0, 0.0));
    let turned = step_until_some(&mut h, "the turned oblique image", current);
    let angle = turned
        .request
        .plane
        .right
        .dot(first.request.plane.right)
        .acos();
    // egui recognises a drag only after the pointer has moved past its threshold, so the
    // first of the 8 steps (5 of the 40 points) may not count: 35 to 40 points' worth.
    let (least, most) = (35.0 * TURN_PER_POINT, 40.0 * TURN_PER_POINT);
    assert!(
        angle > least - 1e-6 && angle < most + 1e-6,
        "turned by {angle} rad, expected {least}..{most}"
    );
    assert!(
        turned.request.plane.down.dot(first.request.plane.down) > 0.999,
        "a sideways drag keeps the vertical axis"
    );

    h.get_by_label("Align to 3D").click();
    let aligned = step_until_some(&mut h, "the aligned oblique image", |a| {
        current(a).filter(|i| i.request.plane != turned.request.plane)
    });
    let camera = {
        let v = app(&h).volume.as_ref().expect("volume");
        v.view_3d.orbit.camera(&v.data.info.geometry)
    };
    let forward = camera.basis().forward.normalize_or_zero();
    assert!(
        (aligned.request.plane.normal().dot(forward).abs() - 1.0).abs() < 1e-9,
        "the aligned plane faces the 3D camera"
    );
}

/// Issue 16: the orbit movie (the screenshot panel's "Orbit movie") writes N frames of the 3D view at its full
/// pixel size into a new folder, turning about the superior axis (orbit.mp4 only with ffmpeg).
#[test]
fn the_orbit_movie_writes_the_frames_around_the_volume() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let shots = dir.path().join("shots");
    let mut h = harness(&store, false);
    wait_for_settled_frame(&mut h, "the phantom", 0);
    if let Some(a) = h.state_mut().as_mut() {
        a.preferences.screenshot_folder = shots.clone();
    }
    // What the panel's "Orbit movie" button asks the shell for (the button only sets a
    // request; a kittest click on it inside the scrolled side bar did not arrive).
    if let Some(a) = h.state_mut().as_mut() {
        a.take_orbit_movie(4);
    }
    let written = step_until_some(&mut h, "the orbit movie's frames", |a| {
        let s = a.volume_status()?;
        let failed = s.last_screenshot.as_ref().is_some_and(|r| r.is_err());
        (s.screenshots_written >= 4 || failed).then_some(s.last_screenshot)
    });
    let place = written.expect("a result").expect("the movie was written");
    let folder = if place.is_dir() {
        place
    } else {
        place.parent().expect("folder").to_path_buf()
    };
    assert!(
        folder.starts_with(&shots),
        "{} is not under the folder",
        folder.display()
    );
    let rect = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");
    let size = super::view3d::View3d::full_resolution_size(rect, h.ctx.pixels_per_point());
    let frames: Vec<image::RgbImage> = (0..4)
        .map(|i| {
            image::open(folder.join(format!("frame-{i:04}.png")))
                .expect("frame")
                .to_rgb8()
        })
        .collect();
    for f in &frames {
        assert_eq!(
            [f.width(), f.height()],
            size,
            "frames at the view's full size"
        );
        assert!(
            lit_fraction(
                image::DynamicImage::ImageRgb8(f.clone())
                    .to_rgba8()
                    .as_raw()
            ) > 0.02
        );
    }
    let difference = mean_abs_difference(frames[0].as_raw(), frames[1].as_raw());
    assert!(
        difference > 1.0,
        "a quarter turn changed nothing ({difference})"
    );
}

/// Issue 16: a DICOM SEG (written by highdicom: `storage/tests/support/make_dicom_seg.py`)
/// opened from the overlay panel, even with "Continuous" chosen, becomes a label map whose
/// panel lists every segment by number and name in its recommended colour (CIELab → sRGB as
/// highdicom converts it, ±1). Without highdicom this FAILS with the install command (CI:
/// .ci/run).
#[test]
fn a_dicom_seg_overlay_lists_its_segments_by_name_and_colour() {
    use super::overlay::OverlayKind;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let script =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../storage/tests/support/make_dicom_seg.py");
    let out = std::process::Command::new("python3")
        .arg(&script)
        .arg(dir.path().join("seg"))
        .output()
        .expect("python3 needed");
    assert!(
        out.status.success(),
        "make_dicom_seg.py failed (needs highdicom: pip install highdicom; CI: .ci/run)\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let expected: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("seg/binary.json")).expect("json"))
            .expect("json");
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 800.0));
    step_until(&mut h, "the axial slice", |a| {
        a.slice_display(SliceView::Axial).is_some()
    });
    h.get_by_label("Overlay").click();
    h.step();
    if let Some(a) = h.state_mut().as_mut() {
        a.panels.overlay.path = dir.path().join("seg/binary.dcm").display().to_string();
        a.panels.overlay.kind = OverlayKind::Continuous;
    }
    h.step();
    h.get_by_label("Open overlay").click();
    step_until_some(&mut h, "the SEG overlay", |a| {
        a.volume.as_ref()?.overlay.as_ref().map(|_| ())
    });
    h.step();
    h.step();
    let overlay = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.overlay.as_ref())
        .expect("overlay");
    assert_eq!(overlay.kind, OverlayKind::Labels, "a SEG is a label map");
    let segments = expected["segments"].as_array().expect("segments");
    assert_eq!(overlay.style.label_table.len(), segments.len());
    for s in segments {
        let number = s["number"].as_i64().expect("number");
        let name = s["name"].as_str().expect("name");
        let entry = &overlay.style.label_table[&number];
        assert_eq!(entry.name, name);
        for c in 0..3 {
            let want = s["rgb"][c].as_i64().expect("rgb");
            assert!(
                (i64::from(entry.colour[c]) - want).abs() <= 1,
                "{name}: {:?} vs {}",
                entry.colour,
                s["rgb"]
            );
        }
        assert!(
            h.query_by_label_contains(&format!("{number} {name}"))
                .is_some(),
            "the panel lists segment {number} {name}"
        );
    }
}

/// Issue 16: a 4-D NIfTI (3 time points written by nibabel) opens with a Frames panel; moving
/// its slider one step changes the crosshair readout from frame 0's value to frame 1's at a
/// known voxel, the 3D view renders the new frame, and frame 2 is opened ahead. Without
/// nibabel this FAILS with the install command (CI: .ci/run).
#[test]
fn the_frame_slider_moves_the_readout_to_the_next_frames_value() {
    let dir = tempfile::tempdir().expect("temp dir");
    let nifti = dir.path().join("cine.nii.gz");
    // value = 1000·t + 100·k + 10·j + i at voxel (i, j, k) of time point t.
    let script = format!(
        "import nibabel as nib, numpy as np\n\
         i, j, k, t = np.meshgrid(np.arange(8), np.arange(8), np.arange(6), np.arange(3), indexing='ij')\n\
         d = (1000 * t + 100 * k + 10 * j + i).astype(np.int16)\n\
         nib.save(nib.Nifti1Image(d, np.diag([-1.0, -1.0, 1.5, 1.0])), r'{}')\n",
        nifti.display()
    );
    let out = std::process::Command::new("python3")
        .args(["-c", &script])
        .output()
        .expect("python3 needed");
    assert!(
        out.status.success(),
        "nibabel needed: pip install nibabel (CI: .ci/run)\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut options = ViewerOptions::new(VolumeToOpen::Path(nifti));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 800.0));
    step_until(&mut h, "the 4-D volume open with its frames", |a| {
        a.volume.as_ref().is_some_and(|v| v.frames.is_some())
    });
    if let Some(v) = h.state_mut().as_mut().and_then(|a| a.volume.as_mut()) {
        v.scene.cursor = [2.0, 3.0, 1.0];
    }
    // Integer data reads as integers (no "132.0": issue 47's readout fix).
    let readout = |t: u32| format!("Crosshair {} · voxel (2, 3, 1)", 1000 * t + 132);
    let start = Instant::now();
    while h.query_by_label_contains(&readout(0)).is_none() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "no frame-0 readout '{}'",
            readout(0)
        );
        h.step();
        std::thread::sleep(Duration::from_millis(10));
    }
    let ahead = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.frames.as_ref())
        .and_then(|f| f.ahead_frame());
    assert_eq!(ahead, Some(1), "frame 1 is opened ahead");

    h.get_by_role_and_label(egui::accesskit::Role::Slider, "Frame")
        .increment_accesskit();
    let start = Instant::now();
    while h.query_by_label_contains(&readout(1)).is_none() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "no frame-1 readout '{}' after moving the slider",
            readout(1)
        );
        h.step();
        std::thread::sleep(Duration::from_millis(10));
    }
    let player = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.frames.as_ref())
        .expect("frames");
    assert_eq!(player.current, 1);
    assert_eq!(player.ahead_frame(), Some(2), "frame 2 is opened ahead");
    step_until(&mut h, "a 3D frame of frame 1", |a| {
        a.volume
            .as_ref()
            .is_some_and(|v| v.data.session.latest_frame().is_some())
    });
}

/// Issue 16, the overlay in 3D: a label box (label 1, on the primary's own grid) inside the
/// phantom, opened from the overlay panel, takes the label's hue in the 3D view's pixels whose
/// rays cross the box, leaves the pixels whose rays miss it alone, and hiding the label (a
/// colour-table change: the same uploaded grid) takes it out again.
#[test]
fn a_label_map_colours_the_3d_pixels_over_it_and_hiding_the_label_removes_it() {
    use super::overlay::tests::write_nrrd;
    use strata_segment::label_colour;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let geometry = Phantom::cube(48).geometry();
    let (lo, hi) = (16u32, 32u32);
    let labels = dir.path().join("box.nrrd");
    write_nrrd(
        &labels,
        geometry.dims,
        geometry.spacing_mm[0],
        geometry.origin_lps_mm,
        false,
        |i, j, k| {
            let inside = [i, j, k].iter().all(|c| (lo..hi).contains(c));
            if inside {
                1.0
            } else {
                0.0
            }
        },
    );
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    // Tall enough for the overlay panel's controls below the others.
    let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 800.0));
    let first = wait_for_settled_frame(&mut h, "the first 3D frame", 0);
    h.get_by_label("Overlay").click();
    h.step();
    if let Some(a) = h.state_mut().as_mut() {
        a.panels.overlay.path = labels.display().to_string();
    }
    h.step();
    h.get_by_label("Open overlay").click();
    let with_label = step_until_some(&mut h, "a 3D frame with the overlay", |a| {
        settled_frame(a).filter(|f| f.request.overlay.is_some() && f.serial > first.serial)
    });
    let set_style = |h: &mut Harness<'static, Option<StrataApp>>,
                     change: &dyn Fn(&mut super::overlay::OverlayStyle)| {
        if let Some(o) = h
            .state_mut()
            .as_mut()
            .and_then(|a| a.volume.as_mut())
            .and_then(|v| v.overlay.as_mut())
        {
            change(&mut o.style);
        }
        h.step();
    };
    set_style(&mut h, &|s| s.show_in_3d = false);
    let without = step_until_some(&mut h, "the 3D frame without the overlay", |a| {
        settled_frame(a).filter(|f| f.request.overlay.is_none() && f.serial > with_label.serial)
    });
    set_style(&mut h, &|s| {
        s.show_in_3d = true;
        s.hidden_labels.insert(1);
    });
    let hidden = step_until_some(&mut h, "the 3D frame with label 1 hidden", |a| {
        settled_frame(a).filter(|f| {
            f.serial > without.serial
                && f.request
                    .overlay
                    .as_ref()
                    .is_some_and(|o| o.lut.entries.iter().all(|e| e[3] == 0.0))
        })
    });
    // Hiding is a colour-table change: the very grid uploaded before.
    let grid = |f: &RenderedFrame| f.request.overlay.as_ref().map(|o| o.volume.clone());
    assert!(
        std::sync::Arc::ptr_eq(
            &grid(&with_label).expect("grid"),
            &grid(&hidden).expect("grid")
        ),
        "hiding a label re-read the overlay"
    );

    // Which pixels' rays cross the label box (index space, shrunk by a voxel for the pixel's
    // footprint), which miss it by more than two voxels.
    let (w, h_px) = (with_label.width, with_label.height);
    let basis = with_label.request.camera.basis();
    let crosses = |px: u32, py: u32, margin: f64| -> bool {
        let (origin, dir) = basis.ray(px, py, w, h_px);
        let o = geometry.index_from_patient(origin);
        let d = geometry.index_from_patient_linear() * dir;
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        for a in 0..3 {
            let (bl, bh) = (lo as f64 - 0.5 + margin, hi as f64 - 0.5 - margin);
            if d[a].abs() < 1e-12 {
                if o[a] < bl || o[a] > bh {
                    return false;
                }
                continue;
            }
            let (ta, tb) = ((bl - o[a]) / d[a], (bh - o[a]) / d[a]);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
        t1 > t0
    };
    let [lr, lg, _] = label_colour(1).map(|c| c as f64);
    let (mut over, mut towards, mut off, mut off_change) = (0usize, 0usize, 0usize, 0.0f64);
    let mut still_hued = 0usize;
    for py in 0..h_px {
        for px in 0..w {
            let i = ((py * w + px) * 4) as usize;
            let (a, b, c) = (
                &with_label.rgba[i..i + 4],
                &without.rgba[i..i + 4],
                &hidden.rgba[i..i + 4],
            );
            if crosses(px, py, 1.0) {
                over += 1;
                // Label 1 is red over green: the pixel moves that way.
                let shift = (a[0] as f64 - a[1] as f64) - (b[0] as f64 - b[1] as f64);
                towards += (shift > 0.1 * (lr - lg)) as usize;
                // Hidden: no label hue. (Not bit-equal to the frame without: with an overlay DVR
                // composites per sample instead of pre-integrated, overlay.rs.)
                let hidden_shift = (c[0] as f64 - c[1] as f64) - (b[0] as f64 - b[1] as f64);
                still_hued += (hidden_shift > 0.1 * (lr - lg)) as usize;
            } else if !crosses(px, py, -2.0) {
                off += 1;
                off_change += (0..3)
                    .map(|ch| (a[ch] as f64 - b[ch] as f64).abs())
                    .sum::<f64>();
            }
        }
    }
    assert!(
        over > 50 && off > 50,
        "{over} pixels over the box, {off} off it"
    );
    assert!(
        towards * 10 >= over * 9,
        "only {towards} of {over} pixels over the box take the label's hue"
    );
    assert!(
        still_hued * 20 <= over,
        "{still_hued} of {over} pixels keep the label's hue with the label hidden"
    );
    assert!(
        off_change / (3 * off) as f64 <= 2.0,
        "pixels off the box changed by {:.2} on average",
        off_change / (3 * off) as f64
    );
}

/// The restarted viewer end to end: a saved session for the phantom's store is put back when
/// that store opens, camera and scene exactly. (Here rather than in session_restore.rs: a test
/// there reaching back into `viewer::app` made a module cycle.)
#[test]
fn a_restarted_viewer_opens_its_volume_with_the_saved_session() {
    use super::scene::{Scene, Window};
    use super::session_restore::SavedSession;
    use super::view3d::OrbitCamera;
    use strata_viewer_ui::crop_clip::ClipSettings;
    let dir = tempfile::tempdir().expect("tempdir");
    let store = dir.path().join("phantom.strata");
    Phantom::cube(32)
        .write_store(&store, &Default::default())
        .expect("phantom store");
    let location = strata_storage::Store::open(&store)
        .map(|s| std::path::PathBuf::from(strata_source::VolumeSource::location(&s)))
        .expect("store opens");
    let tf = strata_render::TransferFunction::preset("ct-bone").expect("preset");
    let edited = Scene {
        cursor: [10.0, 20.0, 30.0],
        window: Window::new(-300.0, 900.0),
        colour_map: Default::default(),
        transfer_function: tf.clone(),
        tf_source: tf,
        iso_value: 77.0,
        crop: strata_render::CropBox::default(),
        clip: ClipSettings {
            enabled: true,
            ..ClipSettings::default()
        },
        measurements: Default::default(),
    };
    let orbit = OrbitCamera {
        azimuth_deg: 123.0,
        ..OrbitCamera::default()
    };
    let saved = SavedSession::capture(&location, &Preferences::default(), &edited, &orbit);
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    options.max_render_pixels = 64;
    options.persist_settings = false;
    let mut harness = Harness::builder()
        .with_size(Vec2::new(400.0, 300.0))
        .wgpu()
        .build_ui_state(
            move |ui, state: &mut Option<StrataApp>| {
                state
                    .get_or_insert_with(|| {
                        let mut app = StrataApp::new(
                            ui.ctx().clone(),
                            Preferences::default(),
                            options.clone(),
                        );
                        app.pending_restore = Some(saved.clone());
                        app
                    })
                    .ui(ui);
            },
            None,
        );
    let restored = step_until_some(&mut harness, "the phantom to open", |a| a.saved_session());
    assert_eq!(restored.orbit, orbit);
    assert_eq!(restored.window, edited.window);
    assert_eq!(restored.iso_value, 77.0);
    assert!(restored.clip.enabled);
    assert_eq!(restored.transfer_function, edited.transfer_function);
}

/// The rendering panel's adaptive sampling (issue 15): the checkbox shows the ε slider, both
/// reach the render request, the still view's final frame is then the adaptive pass's (the
/// status line says so), both survive the preferences' round trip, and in iso mode the
/// checkbox is disabled.
#[test]
fn the_adaptive_sampling_checkbox_and_epsilon_slider_reach_the_frame_and_persist() {
    use super::panels::rendering::{ADAPTIVE_LABEL, EPSILON_LABEL};
    use egui_kittest::kittest::NodeT;
    let dir = tempfile::tempdir().expect("tempdir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::Single,
        show_side_panel: true,
        ..Preferences::default()
    };
    // Tall, so the rendering panel is on screen below the others.
    let mut h = harness_sized(options, preferences, Vec2::new(700.0, 1600.0));
    wait_for_settled_frame(&mut h, "the first converged frame", 0);
    assert!(
        h.query_by_label(EPSILON_LABEL).is_none(),
        "no ε slider while adaptive sampling is off"
    );
    assert_eq!(
        app(&h).volume_request().and_then(|r| r.adaptive_epsilon),
        None
    );

    h.get_by_label(ADAPTIVE_LABEL).click_accesskit();
    h.step();
    h.step();
    assert!(app(&h).preferences.adaptive_sampling);
    h.get_by_role_and_label(egui::accesskit::Role::Slider, EPSILON_LABEL)
        .set_value_accesskit(0.02);
    h.step();
    h.step();
    let epsilon = app(&h).preferences.adaptive_epsilon;
    assert!((epsilon - 0.02).abs() < 1e-9, "ε {epsilon}");
    step_until(&mut h, "the request with ε 0.02", |a| {
        a.volume_request()
            .is_some_and(|r| r.adaptive_epsilon == Some(epsilon))
    });
    let frame = step_until_some(&mut h, "the adaptive final frame", |a| {
        settled_frame(a).filter(|f| f.adaptive.is_some())
    });
    assert_eq!(frame.request.adaptive_epsilon, Some(epsilon));
    step_until(&mut h, "the adaptive status line", |a| {
        a.volume_status()
            .and_then(|s| s.adaptive)
            .is_some_and(|l| l.starts_with("adaptive: ") && l.ends_with("ε 0.02"))
    });

    // Persisted with the other preferences (eframe's storage and the session autosave hold
    // them as this JSON).
    let text = serde_json::to_string(&app(&h).preferences).expect("serialise");
    let read: Preferences = serde_json::from_str(&text).expect("parse");
    assert!(read.adaptive_sampling);
    assert_eq!(read.adaptive_epsilon, epsilon);
    assert_eq!(read, app(&h).preferences);

    // Isosurface: no adaptive pass, the checkbox is disabled (its tooltip says why).
    h.get_by_label("Isosurface").click_accesskit();
    h.step();
    h.step();
    assert!(h
        .get_by_label(ADAPTIVE_LABEL)
        .accesskit_node()
        .is_disabled());
}

/// Issue 36: once the view has converged and nothing moves (no pointer over the window), the UI
/// asks for no repaint and the render thread renders nothing over a settled interval. The run
/// has `--exit-after` set, which used to repaint at 10 Hz, and the controller's still
/// refinement on, which must end.
#[test]
fn a_settled_viewer_asks_for_no_repaint_and_renders_nothing() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    options.exit_after_seconds = Some(3600.0);
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_with(options, preferences);
    h.step();
    h.state_mut()
        .as_mut()
        .expect("the app is created on the first step")
        .preferences
        .target_fps_enabled = true;
    wait_for_settled_frame(&mut h, "a converged 3D frame", 0);
    step_until(&mut h, "the status to leave refining", |a| {
        a.volume_status().is_some_and(|s| !s.refining)
    });
    // The UI takes the final frame, the slices their images.
    for _ in 0..5 {
        h.step();
        std::thread::sleep(Duration::from_millis(20));
    }
    let requests = Arc::new(AtomicUsize::new(0));
    let counter = requests.clone();
    // Counted: requests for a repaint due within a minute. The `--exit-after` deadline is
    // asked again each pass (egui keeps a delayed request for one pass only) but is an hour
    // away: it repaints nothing at rest.
    h.ctx.set_repaint_observer(move |info| {
        if info.delay < Duration::from_secs(60) {
            counter.fetch_add(1, Ordering::Relaxed);
        }
    });
    let rendered = app(&h).volume_status().expect("status").frames_rendered;
    // The settled interval: passes at about a display's rate would drive them if asked.
    for _ in 0..30 {
        h.step();
        std::thread::sleep(Duration::from_millis(30));
    }
    assert_eq!(
        requests.load(Ordering::Relaxed),
        0,
        "repaints asked for at rest: {:?}",
        h.ctx.repaint_causes()
    );
    let status = app(&h).volume_status().expect("status");
    assert_eq!(
        status.frames_rendered,
        rendered,
        "the render thread drew at rest (refining {}, {})",
        status.refining,
        status.refining_line()
    );
}

/// Issue 36, the steady layout: a long ROI statistics line does not widen the side panel (the
/// views keep their rects), and the first transfer-function edit does not move the plot.
#[test]
fn a_long_roi_line_and_the_first_tf_edit_move_nothing() {
    use super::measurements::{RoiStats, Shape};

    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1024.0, 700.0));
    step_until(&mut h, "the converged first frame and the TF plot", |a| {
        settled_frame(a).is_some()
            && a.volume.is_some()
            && a.panels.transfer_function.editor.plot_rect.is_some()
    });
    for _ in 0..3 {
        h.step();
    }
    let views_before = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");
    let plot_before = app(&h)
        .panels
        .transfer_function
        .editor
        .plot_rect
        .expect("plot drawn");
    {
        let v = h
            .state_mut()
            .as_mut()
            .expect("app")
            .volume
            .as_mut()
            .expect("volume");
        v.scene.measurements.add(Shape::Roi {
            view: SliceView::Axial,
            ellipse: false,
            a: [1.0, 1.0, 10.0],
            b: [40.0, 40.0, 10.0],
            stats: Some(RoiStats {
                mean: -123_456.789,
                sd: 98_765.432,
                min: -1_000_000.0,
                max: 3_000_000.0,
                voxels: 123_456_789,
                area_mm2: 987_654.3,
                level: 3,
            }),
        });
    }
    for _ in 0..3 {
        h.step();
    }
    // The line is there (elided, the whole text on hover), the views did not move.
    assert!(h.query_all_by_label_contains("Box mean").count() > 0);
    let views_after = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");
    assert_eq!(
        views_before, views_after,
        "the long ROI line moved the views"
    );

    // The first edit: a click in the plot adds a point (the TF becomes "edited").
    assert!(!app(&h).volume.as_ref().expect("volume").scene.tf_edited());
    let at =
        plot_before.left_top() + Vec2::new(plot_before.width() * 0.42, plot_before.height() * 0.3);
    h.event(Event::PointerMoved(at));
    for pressed in [true, false] {
        h.event(Event::PointerButton {
            pos: at,
            button: PointerButton::Primary,
            pressed,
            modifiers: Modifiers::NONE,
        });
    }
    h.step();
    h.step();
    assert!(app(&h).volume.as_ref().expect("volume").scene.tf_edited());
    let plot_after = app(&h)
        .panels
        .transfer_function
        .editor
        .plot_rect
        .expect("plot drawn");
    assert_eq!(plot_before, plot_after, "the first TF edit moved the plot");
}

/// Issue 36: at 1024 points wide, with a volume open (all toolbar items shown), no two toolbar
/// items overlap, the warning included.
#[test]
fn toolbar_items_do_not_overlap_at_1024_points() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1024.0, 600.0));
    step_until(&mut h, "the volume", |a| a.volume.is_some());
    h.step();
    let labels = [
        "Open…",
        "Open from PACS…",
        "1×1",
        "3D + 1×3",
        "2×2",
        "DVR",
        "MIP",
        "Iso",
        "Shading",
        "A",
        "P",
        "L",
        "R",
        "S",
        "I",
        "Reset",
        "Screenshot",
        "Layout",
        "Undo",
        "Redo",
        "Oblique",
        "Panels",
        "?",
        super::widgets::NOT_FOR_DIAGNOSIS,
    ];
    let mut rects: Vec<(String, egui::Rect)> = Vec::new();
    for label in labels {
        for node in h.query_all_by_label(label) {
            rects.push((label.to_string(), node.rect()));
        }
    }
    assert!(
        rects.iter().any(|(l, _)| l == "Panels")
            && rects
                .iter()
                .any(|(l, _)| l == super::widgets::NOT_FOR_DIAGNOSIS),
        "toolbar items not found: {rects:?}"
    );
    // Only the toolbar's: the top rows of the window.
    let toolbar_bottom = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view").top();
    rects.retain(|(_, r)| r.bottom() <= toolbar_bottom);
    for (i, (a, ra)) in rects.iter().enumerate() {
        assert!(ra.right() <= 1024.0, "{a} runs off the window: {ra:?}");
        for (b, rb) in &rects[i + 1..] {
            // Shrunk by a hair: adjacent items may share an edge.
            assert!(
                !ra.shrink(0.5).intersects(rb.shrink(0.5)),
                "'{a}' {ra:?} overlaps '{b}' {rb:?}"
            );
        }
    }
}

/// `strata view SCAN --overlay LABELS`: the option opens the label map over the volume once it
/// is shown, as the panel's button does.
#[test]
fn the_overlay_option_opens_the_label_map_with_the_volume() {
    use super::overlay::tests::{label_of, write_nrrd, LABEL_DIMS, LABEL_ORIGIN, LABEL_SPACING};
    use super::overlay::OverlayKind;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let labels = dir.path().join("labels.nrrd");
    write_nrrd(
        &labels,
        LABEL_DIMS,
        LABEL_SPACING,
        LABEL_ORIGIN,
        false,
        label_of,
    );
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    options.overlay = Some(labels.clone());
    let mut h = harness_with(
        options,
        Preferences {
            layout: Layout::TwoByTwo,
            show_side_panel: true,
            ..Preferences::default()
        },
    );
    let kind = step_until_some(&mut h, "the overlay from the option", |a| {
        a.volume.as_ref()?.overlay.as_ref().map(|o| o.kind)
    });
    assert_eq!(kind, OverlayKind::Labels);
    assert_eq!(app(&h).panels.overlay.path, labels.display().to_string());
    // Listed by the file given, not by the imported store's internal name.
    let name = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.overlay.as_ref())
        .map(|o| o.name.clone());
    assert_eq!(name, Some(labels.display().to_string()));
    assert!(app(&h).panels.overlay.error.is_none());
}

/// Issue 36, honest motion: after DVR → MIP the 3D view never paints the DVR image again (it
/// stays empty, saying "rendering MIP…", until the first MIP frame), and the first image it
/// paints is a MIP one. The time from the switch to that first painted MIP frame is printed:
/// the switch's latency as the user sees it (not asserted: wall-clock bounds fail on loaded
/// machines).
#[test]
fn after_a_mode_switch_the_3d_view_paints_only_the_new_modes_frames() {
    use strata_render::RenderMode;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, false);
    wait_for_settled_frame(&mut h, "a converged DVR frame", 0);
    h.step();
    assert_eq!(app(&h).painted_3d_mode(), Some(RenderMode::Dvr));
    h.state_mut()
        .as_mut()
        .expect("the app is created on the first step")
        .preferences
        .mode = RenderMode::Mip;
    let switched = Instant::now();
    let mut painted = Vec::new();
    loop {
        h.step();
        let mode = app(&h).painted_3d_mode();
        assert_ne!(
            mode,
            Some(RenderMode::Dvr),
            "the DVR image was painted {:.0} ms after the switch to MIP",
            switched.elapsed().as_secs_f64() * 1e3
        );
        if mode == Some(RenderMode::Mip) {
            break;
        }
        assert!(switched.elapsed() < WAIT, "no MIP frame was painted");
        std::thread::sleep(Duration::from_millis(10));
    }
    eprintln!(
        "mode switch DVR -> MIP in the viewer: first MIP frame painted after {:.0} ms",
        switched.elapsed().as_secs_f64() * 1e3
    );
    // From here on every pass paints MIP (a late DVR frame would be refused, not shown).
    for _ in 0..10 {
        h.step();
        painted.push(app(&h).painted_3d_mode());
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(
        painted.iter().all(|m| *m == Some(RenderMode::Mip)),
        "{painted:?}"
    );
}

/// Issue 36, honest motion: the slice outlines (and every overlay) of the 3D view are drawn
/// with the camera of the frame on screen, not the orbit's newest: in the pass right after a
/// turn the image is still the old frame (the new one is not rendered yet), and its outlines
/// use its camera; once the turned frame arrives, the outlines follow it.
#[test]
fn the_outlines_of_a_frame_are_drawn_with_that_frames_camera() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut h = harness(&store, false);
    wait_for_settled_frame(&mut h, "the phantom", 0);
    h.step();
    let cameras = |h: &Harness<'static, Option<StrataApp>>| {
        let v = app(h).volume.as_ref().expect("open volume");
        let (painted, overlays) = v.view_3d.painted_and_overlay_cameras();
        (
            painted,
            overlays,
            v.view_3d.orbit.camera(&v.data.info.geometry),
        )
    };
    let (painted, overlays, live) = cameras(&h);
    assert!(painted.is_some(), "no frame painted");
    assert_eq!(overlays, painted);
    assert_eq!(
        painted,
        Some(live),
        "the settled frame is the live camera's"
    );
    // Turn by 40°: this pass sends the request and paints the frame it has, the old one.
    if let Some(v) = h.state_mut().as_mut().and_then(|a| a.volume.as_mut()) {
        v.view_3d.orbit.azimuth_deg += 40.0;
    }
    h.step();
    let (painted, overlays, turned) = cameras(&h);
    assert_ne!(turned, live);
    assert_eq!(
        painted,
        Some(live),
        "the turned frame came within the same pass"
    );
    assert_eq!(
        overlays, painted,
        "the outlines were drawn with another camera than the image under them"
    );
    // The turned frame arrives: image and outlines move together.
    step_until(&mut h, "the turned frame on screen", |a| {
        let v = a.volume.as_ref().expect("open volume");
        v.view_3d.painted_and_overlay_cameras().0 == Some(turned)
    });
    let (painted, overlays, _) = cameras(&h);
    assert_eq!(painted, Some(turned));
    assert_eq!(overlays, painted);
}

/// Issue 37: the Rendering panel's light controls change the settings the 3D view asks for
/// (key light, intensity, ambient, shadows, which turn shading on), the shadowed frame renders,
/// shadows are refused for MIP, and showing the controls does not move the views (issue 36:
/// the side panel keeps its width).
#[test]
fn the_light_controls_reach_the_3d_views_settings_without_widening_the_panel() {
    use super::panels::rendering::{
        AMBIENT_LABEL, AZIMUTH_LABEL, DIRECTIONAL_LABEL, ELEVATION_LABEL, EXACT_SHADOWS_LABEL,
        INTENSITY_LABEL, SHADOW_STEP_LABEL,
    };
    use egui::accesskit::Role;
    use egui_kittest::kittest::NodeT;
    use strata_render::{LightDirection, RenderSettings, ShadowMode};

    let dir = tempfile::tempdir().expect("tempdir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::Single,
        show_side_panel: true,
        // Off, so that turning shadows on visibly turns it on.
        shading: false,
        ..Preferences::default()
    };
    // Tall, so the rendering panel is on screen below the others.
    let mut h = harness_sized(options, preferences, Vec2::new(700.0, 1600.0));
    let first = wait_for_settled_frame(&mut h, "the first converged frame", 0);
    let settings = |h: &Harness<'static, Option<StrataApp>>| -> RenderSettings {
        app(h).volume_request().expect("a request").settings
    };
    let before = settings(&h);
    assert_eq!(before.light.direction, LightDirection::Headlight);
    assert!(before.light.is_default());
    assert_eq!(before.shadows.mode, ShadowMode::Off);
    assert_eq!(before.shading, None);
    let view_before = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");

    h.get_by_label(DIRECTIONAL_LABEL).click_accesskit();
    h.step();
    h.step();
    h.get_by_role_and_label(Role::Slider, AZIMUTH_LABEL)
        .set_value_accesskit(90.0);
    h.step();
    h.get_by_role_and_label(Role::Slider, ELEVATION_LABEL)
        .set_value_accesskit(0.0);
    h.step();
    h.get_by_role_and_label(Role::Slider, INTENSITY_LABEL)
        .set_value_accesskit(1.5);
    h.step();
    h.get_by_role_and_label(Role::Slider, AMBIENT_LABEL)
        .set_value_accesskit(0.1);
    h.step();
    h.get_by_label(EXACT_SHADOWS_LABEL).click_accesskit();
    h.step();
    h.step();
    h.get_by_role_and_label(Role::Slider, SHADOW_STEP_LABEL)
        .set_value_accesskit(2.0);
    h.step();
    h.step();
    assert!(app(&h).preferences.shading, "shadows turn shading on");

    let lit = settings(&h);
    match lit.light.direction {
        // Azimuth 90°, elevation 0: from the right, in camera axes.
        LightDirection::Camera(v) => assert!(
            (v[0] - 1.0).abs() < 1e-9 && v[1].abs() < 1e-9 && v[2].abs() < 1e-9,
            "{v:?}"
        ),
        other => panic!("expected a camera-relative light, got {other:?}"),
    }
    assert_eq!(lit.light.intensity, 1.5);
    assert_eq!(lit.shading.map(|s| s.ambient), Some(0.1));
    assert_eq!(lit.shadows.mode, ShadowMode::Exact);
    assert_eq!(lit.shadows.step, 2.0);
    assert!(lit.effective_shadows());
    assert_eq!(
        app(&h).view_rect(ViewSlot::ThreeD).expect("3D view"),
        view_before,
        "the light controls widened the side panel"
    );

    // The shadowed frame renders (the raycaster accepts the viewer's settings) and differs
    // from the unshaded headlight frame.
    let shadowed = step_until_some(&mut h, "the converged shadowed frame", |a| {
        settled_frame(a).filter(|f| f.request.settings.effective_shadows())
    });
    assert!(
        mean_abs_difference(&shadowed.rgba, &first.rgba) > 0.5,
        "the light changed nothing on screen"
    );

    // MIP is never lit: the shadow control is disabled (its tooltip says why) and the request
    // carries no shadows, while the choice is kept for DVR.
    // The toolbar and the panel both offer "MIP"; either switches the mode.
    h.query_all_by_label("MIP")
        .next()
        .expect("a MIP button")
        .click_accesskit();
    h.step();
    h.step();
    assert_eq!(app(&h).preferences.mode, strata_render::RenderMode::Mip);
    assert!(h
        .get_by_label(EXACT_SHADOWS_LABEL)
        .accesskit_node()
        .is_disabled());
    assert_eq!(settings(&h).shadows.mode, ShadowMode::Off);
    assert_eq!(app(&h).preferences.light.shadows, ShadowMode::Exact);
}

/// Issue 37: under MIP the shadow, occlusion and scattering controls are disabled (their
/// tooltips say why) and the request carries none of them; each cinematic preset then sets, in
/// one click, the transfer function and the lighting the 3D view renders with (DVR, a
/// directional light from the upper left, cached shadows, occlusion, scattering), and the
/// raycaster draws that frame.
#[test]
fn the_cinematic_presets_set_the_tf_and_lighting_the_3d_view_renders_with() {
    use super::panels::rendering::{CACHE_SHADOWS_LABEL, OCCLUSION_LABEL, SCATTERING_LABEL};
    use super::preferences::CinematicPreset;
    use egui_kittest::kittest::NodeT;
    use strata_render::{LightDirection, RenderMode, RenderSettings, ShadowMode, TransferFunction};

    let dir = tempfile::tempdir().expect("tempdir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::Single,
        show_side_panel: true,
        mode: RenderMode::Mip,
        ..Preferences::default()
    };
    // Tall, so the rendering panel is on screen below the others.
    let mut h = harness_sized(options, preferences, Vec2::new(700.0, 1800.0));
    wait_for_settled_frame(&mut h, "the first converged MIP frame", 0);
    let request =
        |h: &Harness<'static, Option<StrataApp>>| app(h).volume_request().expect("a request");
    for label in [CACHE_SHADOWS_LABEL, OCCLUSION_LABEL, SCATTERING_LABEL] {
        assert!(
            h.get_by_label(label).accesskit_node().is_disabled(),
            "{label} is enabled under MIP"
        );
    }
    let view_before = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");
    let mip: RenderSettings = request(&h).settings;
    assert_eq!(mip.shadows.mode, ShadowMode::Off);
    assert_eq!((mip.occlusion, mip.scattering), (None, None));

    for preset in CinematicPreset::ALL {
        h.get_by_label(preset.label).click_accesskit();
        h.step();
        h.step();
        let asked = request(&h);
        let tf = TransferFunction::preset(preset.tf_preset).expect("the preset exists");
        assert_eq!(
            asked.transfer_function.opacity, tf.opacity,
            "{}",
            preset.label
        );
        assert_eq!(asked.transfer_function.color, tf.color, "{}", preset.label);
        assert_eq!(app(&h).preferences.preset, preset.tf_preset);
        let s = asked.settings;
        assert_eq!(
            s.mode,
            RenderMode::Dvr,
            "a cinematic preset draws DVR, not MIP"
        );
        assert!(s.shading.is_some());
        match s.light.direction {
            LightDirection::Camera([x, y, z]) => {
                assert!(x < 0.0 && y > 0.0 && z > 0.0, "upper left: {x} {y} {z}")
            }
            other => panic!(
                "{}: expected a camera-relative light, got {other:?}",
                preset.label
            ),
        }
        assert_eq!(s.shadows.mode, ShadowMode::Cache);
        assert!(s.effective_light_cache());
        assert_eq!(
            s.effective_occlusion().map(|o| o.radius_mm),
            Some(preset.occlusion_radius_mm)
        );
        let scattering = s.effective_scattering().expect("scattering on");
        assert_eq!(
            (scattering.g, scattering.blend),
            (preset.scattering_g, preset.scattering_blend)
        );
        s.validate()
            .expect("the raycaster accepts the preset's settings");
        // The controls are enabled again and show the choice.
        assert!(!h
            .get_by_label(OCCLUSION_LABEL)
            .accesskit_node()
            .is_disabled());
    }

    assert_eq!(
        app(&h).view_rect(ViewSlot::ThreeD).expect("3D view"),
        view_before,
        "the effect sliders widened the side panel (issue 36)"
    );

    // The raycaster draws the lit frame (the last preset's) to convergence.
    step_until_some(&mut h, "the converged cinematic frame", |a| {
        settled_frame(a).filter(|f| f.request.settings.effective_occlusion().is_some())
    });
}

/// Issue 39, shareable views: the browser viewer's link to a served store opens that store in
/// the desktop viewer with the link's view (camera, mode, preset), the server's token taken
/// from the link; "Copy link" gives the view back as a link without the token.
#[test]
fn a_viewer_link_opens_its_store_and_view_and_copy_link_gives_it_back_without_the_token() {
    use super::links;
    use super::view3d::OrbitCamera;
    use strata_render::RenderMode;
    use strata_service::server::{name_for_store, start, ServeOptions};

    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let name = name_for_store(&store);
    let token = "link-token-0123456789abcdef";
    let server = start(
        vec![(name.clone(), store.clone())],
        ServeOptions {
            token: Some(token.into()),
            ..ServeOptions::default()
        },
    )
    .expect("serving the phantom");
    // A function edited from the preset, as the editor leaves points (f32 pixel maths).
    let mut edited_tf = strata_render::TransferFunction::preset("ct-soft-tissue").expect("preset");
    edited_tf.opacity[2].value = -1024.0 + f64::from(0.2213_f32) * 4095.0;
    edited_tf.opacity[2].opacity = f64::from(0.3377_f32);
    edited_tf.color[1].rgb = [0.12_f32, 0.8, 0.4].map(f64::from);
    let tf_text =
        strata_viewer_ui::compact_tf::encode(&edited_tf).expect("within the link's bounds");
    let link = format!(
        "{}/#store={name}&mode=mip&preset=ct-soft-tissue&tf={tf_text}&az=-60&el=25&zoom=1.5&pan=0.1,-0.05&layout=single&cursor=5,40,12.5&window=300,1200&token={token}",
        server.base_url()
    );
    let mut options = ViewerOptions::new(VolumeToOpen::Url {
        url: link,
        token_file: None,
        token: None,
    });
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        ..Preferences::default()
    };
    // Wide enough for the whole toolbar, "Copy link" included.
    let mut h = harness_sized(options, preferences, Vec2::new(1400.0, 300.0));
    step_until(&mut h, "the linked store to open", |a| a.volume.is_some());
    let expected_orbit = OrbitCamera {
        azimuth_deg: -60.0,
        elevation_deg: 25.0,
        zoom: 1.5,
        pan: [0.1, -0.05],
        orthographic: false,
    };
    let copied = {
        let a = app(&h);
        let v = a.volume.as_ref().expect("opened");
        assert_eq!(v.view_3d.orbit, expected_orbit);
        assert_eq!(a.preferences.mode, RenderMode::Mip);
        assert_eq!(a.preferences.preset, "ct-soft-tissue");
        let tf = &v.scene.transfer_function;
        assert_eq!(
            (&tf.opacity, &tf.color),
            (&edited_tf.opacity, &edited_tf.color),
            "the link's edited transfer function"
        );
        assert!(
            v.scene.tf_edited(),
            "shown as edited from the link's preset"
        );
        assert_eq!(tf.name, "ct-soft-tissue (edited)");
        assert_eq!(a.preferences.layout, Layout::Single, "the link's layout");
        // The phantom is 48³: the crosshair's 40 is inside, as given.
        assert_eq!(v.scene.cursor, [5.0, 40.0, 12.5], "the link's crosshair");
        assert_eq!(
            (v.scene.window.centre, v.scene.window.width),
            (300.0, 1200.0),
            "the link's window"
        );
        assert_eq!(
            v.data.store_path.to_string_lossy(),
            server.store_url(&name),
            "streamed from the link's server"
        );
        a.share_link().expect("a served store has a link")
    };
    assert!(!copied.contains(token), "{copied}");
    let reopened = links::parse_link(&copied).expect("the copied link parses");
    assert_eq!(reopened.store_url, server.store_url(&name));
    assert_eq!(links::desktop_view(&reopened.view).orbit, expected_orbit);
    assert_eq!(reopened.view.mode, RenderMode::Mip);
    assert_eq!(reopened.view.cursor, Some([5.0, 40.0, 12.5]));
    assert_eq!(reopened.view.window, Some([300.0, 1200.0]));
    assert_eq!(reopened.view.preset, "ct-soft-tissue");
    let carried = reopened
        .view
        .tf
        .as_ref()
        .expect("the copy carries the edit");
    assert_eq!(
        (&carried.opacity, &carried.color),
        (&edited_tf.opacity, &edited_tf.color),
        "bit for bit"
    );

    h.get_by_label("Copy link").click();
    let mut clipboard = None;
    for _ in 0..3 {
        h.step();
        clipboard = clipboard.or_else(|| {
            h.output()
                .platform_output
                .commands
                .iter()
                .find_map(|c| match c {
                    egui::OutputCommand::CopyText(text) => Some(text.clone()),
                    _ => None,
                })
        });
    }
    assert_eq!(clipboard.as_deref(), Some(copied.as_str()));
    assert_eq!(
        server
            .counters()
            .unauthorized
            .load(std::sync::atomic::Ordering::Relaxed),
        0,
        "every request carried the link's token"
    );
    server.stop();
}

/// Issue 51, end to end against Orthanc: the toolbar's "Open from PACS…" opens the dialog; a
/// patient name typed and Search list the study; clicking it lists its series; "Open series"
/// retrieves and imports it in the background and the viewer shows it in place of the phantom,
/// the dialog closed.
#[test]
fn open_from_pacs_finds_a_study_and_shows_its_series_in_the_viewer() {
    use super::orthanc_fixture::{filled_orthanc, CT_SLICES};
    let dir = tempfile::tempdir().expect("temp dir");
    let orthanc = filled_orthanc(dir.path());
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::Single,
        show_side_panel: false,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1024.0, 768.0));
    step_until(&mut h, "the phantom", |a| a.volume.is_some());
    h.get_by_label("Open from PACS…").click();
    h.step();
    assert!(app(&h).pacs_dialog.open);
    if let Some(a) = h.state_mut().as_mut() {
        a.pacs_dialog.model.server = orthanc.url.clone();
    }
    h.step();
    let name = h.get_by_label("Patient name");
    name.focus();
    name.type_text("DOE^J*");
    h.step();
    h.get_by_label("Search").click();
    step_until(&mut h, "the study", |a| {
        assert_eq!(a.pacs_dialog.model.error, None);
        a.pacs_dialog.model.studies.len() == 1
    });
    h.step();
    h.get_by_label("DOE^JOHN").click();
    step_until(&mut h, "the series", |a| {
        assert_eq!(a.pacs_dialog.model.error, None);
        a.pacs_dialog.model.series.len() == 1
    });
    h.step();
    h.get_by_label("Open series").click();
    step_until(&mut h, "the series from the PACS", |a| {
        a.volume.as_ref().is_some_and(|v| {
            v.data
                .store_path
                .file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("pacs-"))
        })
    });
    let a = app(&h);
    assert!(
        !a.pacs_dialog.open,
        "the dialog stays open after the series opened"
    );
    let dims = a.volume.as_ref().map(|v| v.data.info.geometry.dims);
    assert_eq!(dims, Some([40, 48, CT_SLICES as u32]));
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
fn layer_voxels(layer: &strata_segment::LabelLayer) -> Vec<([u32; 3], u16)> {
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
fn view_point(
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
fn view_plane(app: &StrataApp, view: SliceView) -> strata_segment::tools::brush::SlicePlane {
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
fn last_stroke_model(
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
    set_segment_tool(h, super::segmentation::SegmentTool::Brush);
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
    tool: super::segmentation::SegmentTool,
) {
    use super::segmentation::SegmentTool;
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

/// Drags the brush and then the eraser across `view`, checking each against the CPU model
/// voxel for voxel, then undoes both and redoes the brush; the journal replays to the same
/// labels. Returns the voxels the brush painted.
fn brush_eraser_and_undo_on(
    h: &mut Harness<'static, Option<StrataApp>>,
    view: SliceView,
    brush_line: [[f64; 2]; 2],
    eraser_line: [[f64; 2]; 2],
) -> Vec<[u32; 3]> {
    let (from, from_lps) = view_point(h, view, brush_line[0][0], brush_line[0][1]);
    let (to, to_lps) = view_point(h, view, brush_line[1][0], brush_line[1][1]);
    drag(h, from, to);
    let painted = labelled_voxels(app(h));
    let tool_error = app(h)
        .volume
        .as_ref()
        .and_then(|v| v.segmentation.as_ref())
        .and_then(|s| s.error.clone());
    assert_eq!(tool_error, None, "the brush reported an error");
    let model = last_stroke_model(app(h), view, from_lps, to_lps);
    assert!(model.len() > 50, "the stroke covers {} voxels", model.len());
    assert_eq!(
        painted.iter().map(|(v, _)| *v).collect::<Vec<_>>(),
        model,
        "the brush painted other voxels than the model of its stroke"
    );
    assert!(painted.iter().all(|&(_, l)| l == 1), "all with segment 1");

    // The stroke reaches the screen: the overlay's sample of this slice at the new revision
    // holds the label at a painted voxel.
    let at = painted[painted.len() / 2].0.map(f64::from);
    step_until_some(h, "the stroke in the overlay", |a| {
        let v = a.volume.as_ref()?;
        let o = v.overlay.as_ref()?;
        let seg = v.segmentation.as_ref()?;
        let image = a.slice_image(view)?;
        let slice = o.latest(view)?;
        (slice.revision == seg.layer.revision())
            .then(|| v.slice_views[view.index()].overlay_value_at(o, at, &image))
            .flatten()
            .filter(|&value| value == 1.0)
    });

    set_segment_tool(h, super::segmentation::SegmentTool::Eraser);
    let (from, from_lps) = view_point(h, view, eraser_line[0][0], eraser_line[0][1]);
    let (to, to_lps) = view_point(h, view, eraser_line[1][0], eraser_line[1][1]);
    drag(h, from, to);
    let erased = last_stroke_model(app(h), view, from_lps, to_lps);
    let expected: Vec<[u32; 3]> = painted
        .iter()
        .map(|(v, _)| *v)
        .filter(|v| !erased.contains(v))
        .collect();
    assert!(
        expected.len() < painted.len() && !expected.is_empty(),
        "the eraser's line crosses the stroke"
    );
    let after = labelled_voxels(app(h));
    assert_eq!(
        after.iter().map(|(v, _)| *v).collect::<Vec<_>>(),
        expected,
        "the eraser cleared other voxels than the model of its stroke"
    );

    h.get_by_label("Undo").click();
    h.step();
    assert_eq!(labelled_voxels(app(h)), painted, "undo of the eraser");
    h.get_by_label("Undo").click();
    h.step();
    assert!(labelled_voxels(app(h)).is_empty(), "undo of the brush");
    h.get_by_label("Redo").click();
    h.step();
    assert_eq!(labelled_voxels(app(h)), painted, "redo of the brush");

    // The journal holds every step, undo and redo included: replayed, it gives these labels.
    let (journal, geometry) = {
        let seg = app(h)
            .volume
            .as_ref()
            .and_then(|v| v.segmentation.as_ref())
            .expect("segmentation");
        let journal = seg.journal_file().expect("a journal").to_path_buf();
        let geometry = seg.layer.read().grid().geometry().clone();
        (journal, geometry)
    };
    let recovery = strata_segment::journal::recover(&journal).expect("journal");
    assert_eq!(recovery.edits.len(), 5, "brush, eraser, two undos, redo");
    let mut replayed = strata_segment::LabelLayer::new_empty(geometry).expect("layer");
    recovery.replay_onto(&mut replayed);
    for &(v, label) in &painted {
        assert_eq!(replayed.get(v).expect("voxel"), label, "replayed {v:?}");
    }
    assert_eq!(
        replayed
            .edited_bricks()
            .map(|(_, b)| b.iter().filter(|&&l| l != 0).count())
            .sum::<usize>(),
        painted.len(),
        "the replayed journal has no other labels"
    );
    painted.iter().map(|(v, _)| *v).collect()
}

#[test]
fn in_3d_the_brush_paints_the_ball_around_the_picked_surface_point_and_undo_removes_it() {
    use strata_segment::tools::brush::BrushShape;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store));
    options.import_folder = dir.path().join("imported");
    options.initial_view = Some(super::view3d::StandardView::Anterior);
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 1000.0));
    step_until(&mut h, "the volume open", |a| a.volume.is_some());
    // 30 mm on the phantom's 8.3 mm voxels: a ball about 3.6 voxels across.
    new_segmentation(&mut h, 30.0);
    wait_for_settled_frame(&mut h, "a converged frame with the segmentation open", 0);
    let rect = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");
    let at = rect.center() + Vec2::new(4.0, 2.0);
    // The point the frame on screen shows under the pointer (the pick itself is checked
    // against a CPU ray march by the crosshair test).
    let centre_lps = {
        let v = app(&h).volume.as_ref().expect("volume");
        let index = v
            .view_3d
            .pick(at, rect, &v.data)
            .expect("the pixel's ray meets the phantom");
        v.data
            .info
            .geometry
            .patient_from_index(glam::DVec3::from(index))
    };
    let cursor_before = app(&h).volume.as_ref().expect("volume").scene.cursor;
    click(&mut h, at, PointerButton::Primary);
    h.step();
    let painted: Vec<[u32; 3]> = labelled_voxels(app(&h))
        .into_iter()
        .map(|(v, _)| v)
        .collect();
    let model = {
        let seg = app(&h)
            .volume
            .as_ref()
            .and_then(|v| v.segmentation.as_ref())
            .expect("segmentation");
        let brush = seg.brush_shaped(BrushShape::Sphere).expect("brush");
        let layer = seg.layer.read();
        strata_segment::tools::brush::stroke_voxels(layer.grid(), &brush, &[centre_lps])
            .expect("model")
    };
    assert!(
        model.len() > 8,
        "the model ball holds {} voxels",
        model.len()
    );
    assert_eq!(
        painted, model,
        "the 3D brush painted other voxels than the ball"
    );
    assert_eq!(
        app(&h).volume.as_ref().expect("volume").scene.cursor,
        cursor_before,
        "a click with the brush paints; it does not move the crosshair"
    );
    h.key_press_modifiers(Modifiers::COMMAND, egui::Key::Z);
    h.step();
    assert!(
        labelled_voxels(app(&h)).is_empty(),
        "one undo removes the whole ball"
    );
}

#[test]
fn brush_and_eraser_drags_paint_exactly_the_cpu_models_voxels_and_undo_restores_them() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 1000.0));
    step_until(&mut h, "the axial slice at full resolution", |a| {
        a.slice_image(SliceView::Axial)
            .is_some_and(|i| i.request.level == 0)
            && a.volume
                .as_ref()
                .is_some_and(|v| v.slice_views[SliceView::Axial.index()].image_rect.is_some())
    });
    // 30 mm on the phantom's 8.3 mm voxels: a disc about 3.6 voxels across.
    new_segmentation(&mut h, 30.0);
    let painted = brush_eraser_and_undo_on(
        &mut h,
        SliceView::Axial,
        [[10.0, 12.0], [33.0, 27.0]],
        [[22.0, 4.0], [22.0, 40.0]],
    );
    let k = painted[0][2];
    assert!(painted.iter().all(|v| v[2] == k), "all on one axial slice");

    // The statistics table: the painted voxels, their volume and the phantom's HU under them.
    h.get_by_label("Statistics").click();
    let stats = step_until_some(&mut h, "the statistics", |a| {
        let seg = a.volume.as_ref()?.segmentation.as_ref()?;
        seg.stats.as_ref()?.as_ref().ok().cloned()
    });
    let phantom = Phantom::cube(48);
    let voxel_ml = phantom.geometry().spacing_mm.iter().product::<f64>() / 1000.0;
    let row = &stats.segments[0];
    assert_eq!((row.label, row.voxels), (1, painted.len() as u64));
    assert!((row.volume_ml - painted.len() as f64 * voxel_ml).abs() < 1e-9 * row.volume_ml);
    let mean = painted
        .iter()
        .map(|v| phantom.hu(v[0].into(), v[1].into(), v[2].into()) as f64)
        .sum::<f64>()
        / painted.len() as f64;
    let got = row.mean.expect("a mean over the primary");
    assert!(
        (got - mean).abs() <= 1e-6 * mean.abs().max(1.0),
        "mean {got} vs {mean}"
    );

    // Save As NIfTI (the file chooser is the system's; its answer is the path) loads back as
    // the same labels.
    let saved = dir.path().join("painted.nii.gz");
    {
        let ctx = h.ctx.clone();
        let seg = h
            .state_mut()
            .as_mut()
            .and_then(|a| a.volume.as_mut())
            .and_then(|v| v.segmentation.as_mut())
            .expect("segmentation");
        seg.start_save(
            saved.clone(),
            super::segmentation::SaveFormat::Nifti,
            std::sync::Arc::new(move || ctx.request_repaint()),
        );
    }
    let written = step_until_some(&mut h, "the saved file", |a| {
        let seg = a.volume.as_ref()?.segmentation.as_ref()?;
        seg.saved.clone()
    });
    assert_eq!(written, Ok(saved.clone()));
    let loaded = strata_segment::io::load_label_file(&saved).expect("loading the saved file");
    // Read slice by slice: a loaded file's labels are its base, not edited bricks.
    use strata_segment::LabelRead;
    let [nx, ny, nz] = loaded.grid().dims();
    let mut slice = vec![0; (nx * ny) as usize];
    let mut from_file = Vec::new();
    for z in 0..nz {
        loaded.read_slice_k(z, &mut slice).expect("slice");
        for (n, &label) in slice.iter().enumerate() {
            if label != 0 {
                assert_eq!(label, 1);
                from_file.push([n as u32 % nx, n as u32 / nx, z]);
            }
        }
    }
    assert_eq!(from_file, painted, "the saved file holds other voxels");
    // The saved file holds every edit: the crash journal starts again on it, so a restart
    // offers nothing already saved.
    let journal = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.segmentation.as_ref())
        .and_then(|s| s.journal_file().map(Path::to_path_buf))
        .expect("a journal");
    let after_save = strata_segment::journal::recover(&journal).expect("the journal reads");
    assert!(
        after_save.edits.is_empty(),
        "saved edits left in the journal"
    );
    let note: super::segmentation::JournalNote = serde_json::from_slice(
        &std::fs::read(super::segmentation::note_path(&journal)).expect("the note"),
    )
    .expect("a note");
    assert_eq!(note.base.as_deref(), Some(saved.as_path()));

    // Grow in 3D from a clicked seed, into a second segment, within ±80 HU of the seed's value:
    // the same as the segment crate's grow over the phantom's own values from the same layer.
    if let Some(seg) = h
        .state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .and_then(|v| v.segmentation.as_mut())
    {
        seg.add_segment();
    }
    set_segment_tool(&mut h, super::segmentation::SegmentTool::Grow);
    let seed_index = [24u32, 20, k];
    let seed_hu = f64::from(phantom.hu(24, 20, k.into()));
    let range = (seed_hu - 80.0, seed_hu + 80.0);
    let before = {
        let a = h.state_mut().as_mut().expect("app");
        let seg = a
            .volume
            .as_mut()
            .and_then(|v| v.segmentation.as_mut())
            .expect("segmentation");
        seg.range = range;
        assert_eq!(seg.active, 2, "the added segment is the active one");
        seg.layer.read().clone()
    };
    let (at, _) = view_point(&h, SliceView::Axial, 24.0, 20.0);
    click(&mut h, at, PointerButton::Primary);
    step_until(&mut h, "the grow", |a| {
        a.volume
            .as_ref()
            .and_then(|v| v.segmentation.as_ref())
            .is_some_and(|s| !s.busy())
    });
    h.step();
    let mut model = before;
    let dims = model.grid().dims();
    let mut values = Vec::with_capacity((dims[0] * dims[1] * dims[2]) as usize);
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                values.push(f32::from(phantom.hu(x.into(), y.into(), z.into())));
            }
        }
    }
    let intensity =
        strata_segment::intensity::DenseIntensity::new(dims, values, "HU").expect("intensity");
    let (outcome, _) = strata_segment::tools::grow::grow_from_seed(
        &mut model,
        &intensity,
        seed_index,
        2,
        strata_segment::tools::grow::GrowCriterion::Range(
            strata_segment::intensity::ValueRange::new(range.0, range.1).expect("range"),
        ),
        50_000_000,
        &mut |_| {},
        None,
    )
    .expect("the model's grow");
    assert!(
        outcome.voxels > 100,
        "the grow took {} voxels",
        outcome.voxels
    );
    assert_eq!(
        labelled_voxels(app(&h)),
        layer_voxels(&model),
        "the grow from the clicked seed differs from the model"
    );
}

/// Writes a NRRD whose index axes are rotated against LPS (30° about S, then 20° about L),
/// with anisotropic spacing.
fn write_rotated_nrrd(path: &Path, dims: [u32; 3], spacing: [f64; 3]) {
    let (a, b) = (30f64.to_radians(), 20f64.to_radians());
    let about_s = glam::DMat3::from_rotation_z(a);
    let about_l = glam::DMat3::from_rotation_x(b);
    let r = about_l * about_s;
    let d: Vec<glam::DVec3> = (0..3).map(|c| r.col(c) * spacing[c]).collect();
    let mut bytes = format!(
        "NRRD0004\ntype: uint8\ndimension: 3\nsizes: {} {} {}\n\
         space: left-posterior-superior\n\
         space directions: ({},{},{}) ({},{},{}) ({},{},{})\n\
         space origin: (-90,-80,-70)\nencoding: raw\nendian: little\n\n",
        dims[0],
        dims[1],
        dims[2],
        d[0].x,
        d[0].y,
        d[0].z,
        d[1].x,
        d[1].y,
        d[1].z,
        d[2].x,
        d[2].y,
        d[2].z
    )
    .into_bytes();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                bytes.push(((i / 5 + j / 4 + k / 3) % 4 * 60) as u8);
            }
        }
    }
    std::fs::write(path, bytes).expect("writing the rotated NRRD");
}

#[test]
fn on_a_rotated_anisotropic_grid_the_brush_paints_the_models_voxels_in_mm() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scan = dir.path().join("rotated.nrrd");
    write_rotated_nrrd(&scan, [40, 36, 30], [4.0, 5.0, 6.5]);
    let mut options = ViewerOptions::new(VolumeToOpen::Path(scan));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 1000.0));
    step_until(&mut h, "the coronal slice at full resolution", |a| {
        a.slice_image(SliceView::Coronal)
            .is_some_and(|i| i.request.level == 0)
            && a.volume.as_ref().is_some_and(|v| {
                v.slice_views[SliceView::Coronal.index()]
                    .image_rect
                    .is_some()
            })
    });
    let direction = app(&h)
        .volume
        .as_ref()
        .expect("volume")
        .data
        .info
        .geometry
        .direction;
    assert!(
        direction[0][1].abs() > 0.3,
        "the grid is rotated: {direction:?}"
    );
    // 22 mm: about 5 voxels along i, 3.4 along k.
    new_segmentation(&mut h, 22.0);
    brush_eraser_and_undo_on(
        &mut h,
        SliceView::Coronal,
        [[6.0, 5.0], [26.0, 22.0]],
        [[16.0, 2.0], [16.0, 27.0]],
    );
}

#[test]
fn a_journal_left_by_an_ended_session_is_offered_then_recovered_or_discarded() {
    use strata_segment::journal::Journal;
    use strata_source::VolumeSource;
    let dir = tempfile::tempdir().expect("temp dir");
    let expected_count = (20..23).count() * (10..30).sum::<usize>();
    // One volume whose journal is recovered, one whose journal is discarded.
    for recover in [true, false] {
        let folder = dir
            .path()
            .join(if recover { "recovered" } else { "discarded" });
        std::fs::create_dir_all(&folder).expect("folder");
        let store = phantom_store(&folder);
        let import_folder = folder.join("imported");
        let (location, geometry) = {
            let opened = strata_storage::Store::open(&store).expect("open the phantom");
            (
                std::path::PathBuf::from(VolumeSource::location(&opened)),
                VolumeSource::header(&opened).geometry.clone(),
            )
        };
        // What a session ended after one stroke leaves: the note, and a journal with the
        // segment table and the stroke.
        let journal = super::segmentation::journal_path(&import_folder);
        let note = super::segmentation::JournalNote {
            primary: location,
            base: None,
        };
        std::fs::write(
            super::segmentation::note_path(&journal),
            serde_json::to_vec(&note).expect("note"),
        )
        .expect("writing the note");
        let mut layer = strata_segment::LabelLayer::new_empty(geometry.clone()).expect("layer");
        let liver = layer.segments_mut().add("Liver").expect("segment");
        let edit = layer
            .edit("Brush", |w| {
                for k in 20..23 {
                    for j in 10..30 {
                        for i in 5..(5 + j) {
                            w.set([i, j, k], liver)?;
                        }
                    }
                }
                Ok(())
            })
            .expect("edit")
            .expect("changed");
        {
            let (mut j, _) = Journal::open_or_create(&journal, &geometry).expect("journal");
            j.append_segments(layer.segments()).expect("segments");
            j.append(&edit).expect("edit");
        }

        let mut options = ViewerOptions::new(VolumeToOpen::Path(store.clone()));
        options.import_folder = import_folder.clone();
        let preferences = Preferences {
            layout: Layout::TwoByTwo,
            show_side_panel: true,
            ..Preferences::default()
        };
        let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 1000.0));
        step_until(&mut h, "the recovery offer", |a| {
            a.volume.as_ref().is_some_and(|v| v.recovery.is_some())
        });
        h.step();
        assert!(
            h.query_by_label_contains("1 unsaved edits").is_some(),
            "the dialog says what it recovers"
        );
        if recover {
            h.get_by_label("Recover").click();
            step_until(&mut h, "the recovered segmentation", |a| {
                a.volume.as_ref().is_some_and(|v| v.segmentation.is_some())
            });
            let voxels = labelled_voxels(app(&h));
            assert_eq!(voxels.len(), expected_count);
            for (v, label) in &voxels {
                assert_eq!(*label, liver);
                assert!((20..23).contains(&v[2]) && (10..30).contains(&v[1]));
                assert!(v[0] >= 5 && v[0] < 5 + v[1], "voxel {v:?}");
            }
            let names: Vec<String> = app(&h)
                .volume
                .as_ref()
                .and_then(|v| v.segmentation.as_ref())
                .expect("segmentation")
                .segments()
                .iter()
                .map(|s| s.name.clone())
                .collect();
            assert_eq!(names, ["Liver"]);
        } else {
            h.get_by_label("Discard").click();
            h.step();
            assert!(!journal.exists(), "the discarded journal is removed");
            let v = app(&h).volume.as_ref().expect("volume");
            assert!(v.recovery.is_none() && v.segmentation.is_none());
        }
    }
}

#[test]
fn the_label_overlay_made_editable_keeps_its_grid_and_the_brush_paints_the_oblique_models_voxels() {
    use super::overlay::tests::{label_of, write_nrrd, LABEL_DIMS, LABEL_ORIGIN, LABEL_SPACING};
    use strata_segment::tools::brush::{stroke_voxels, SlicePlane};
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let labels = dir.path().join("labels.nrrd");
    write_nrrd(
        &labels,
        LABEL_DIMS,
        LABEL_SPACING,
        LABEL_ORIGIN,
        false,
        label_of,
    );
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store));
    options.import_folder = dir.path().join("imported");
    options.overlay = Some(labels.clone());
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 1000.0));
    step_until(&mut h, "the label overlay", |a| {
        a.volume.as_ref().is_some_and(|v| v.overlay.is_some())
            && a.slice_image(SliceView::Axial)
                .is_some_and(|i| i.request.level == 0)
    });
    h.step();
    h.get_by_label("Segment").click();
    h.step();
    h.get_by_label("Edit overlay").click();
    step_until(&mut h, "the overlay's file as an editable layer", |a| {
        a.volume.as_ref().is_some_and(|v| {
            v.segmentation.is_some() && v.overlay.as_ref().is_some_and(|o| o.layer().is_some())
        })
    });
    // On the file's own grid, with the file's labels.
    let original = |v: [u32; 3]| label_of(v[0], v[1], v[2]) as u16;
    {
        let seg = app(&h)
            .volume
            .as_ref()
            .and_then(|v| v.segmentation.as_ref())
            .expect("segmentation");
        assert_eq!(seg.base_file.as_deref(), Some(labels.as_path()));
        let layer = seg.layer.read();
        assert_eq!(layer.grid().dims(), LABEL_DIMS);
        for v in [[0, 0, 0], [13, 22, 31], [39, 39, 39], [7, 30, 2]] {
            assert_eq!(layer.get(v).expect("voxel"), original(v), "voxel {v:?}");
        }
    }
    set_segment_tool(&mut h, super::segmentation::SegmentTool::Brush);
    if let Some(seg) = h
        .state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .and_then(|v| v.segmentation.as_mut())
    {
        seg.diameter_mm = 30.0;
        seg.active = 1;
    }
    h.step();
    let (from, from_lps) = view_point(&h, SliceView::Axial, 9.0, 11.0);
    let (to, to_lps) = view_point(&h, SliceView::Axial, 36.0, 30.0);
    drag(&mut h, from, to);
    // The model: the segment crate's disc in the view's plane (oblique to nothing here but
    // the labels' own grid, which it cuts between voxel centres) through the stroke's start.
    let (frame, primary) = {
        let v = app(&h).volume.as_ref().expect("volume");
        (v.data.frame(SliceView::Axial), v.data.info.geometry.clone())
    };
    let seg = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.segmentation.as_ref())
        .expect("segmentation");
    assert_eq!(seg.error, None);
    let positions = seg.last_stroke.clone();
    assert!(
        positions[0].distance(from_lps) < 0.1
            && positions[positions.len() - 1].distance(to_lps) < 0.1,
        "stroke {positions:?}"
    );
    let plane = SlicePlane::Oblique {
        centre_lps: positions[0],
        u: glam::DVec3::from(primary.direction[frame.across_axis]),
        v: glam::DVec3::from(primary.direction[frame.down_axis]),
    };
    let brush = seg.brush(plane).expect("brush");
    let layer = seg.layer.read();
    let model = stroke_voxels(layer.grid(), &brush, &positions).expect("model");
    assert!(model.len() > 20, "the stroke covers {} voxels", model.len());
    let mut changed = 0;
    for k in 0..LABEL_DIMS[2] {
        for j in 0..LABEL_DIMS[1] {
            for i in 0..LABEL_DIMS[0] {
                let v = [i, j, k];
                let got = layer.get(v).expect("voxel");
                if model
                    .binary_search_by_key(&[k, j, i], |m| [m[2], m[1], m[0]])
                    .is_ok()
                {
                    assert_eq!(got, 1, "painted voxel {v:?}");
                    changed += usize::from(original(v) != 1);
                } else {
                    assert_eq!(got, original(v), "voxel {v:?} outside the stroke");
                }
            }
        }
    }
    assert!(changed > 0, "the stroke changed no label");
}

/// Runs `f` on the open segmentation.
fn with_seg(
    h: &mut Harness<'static, Option<StrataApp>>,
    f: impl FnOnce(&mut super::segmentation::Segmentation),
) {
    let seg = h
        .state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .and_then(|v| v.segmentation.as_mut())
        .expect("segmentation");
    f(seg);
    h.step();
}

#[test]
fn the_brush_leaves_locked_segments_and_values_outside_its_range_and_a_capped_grow_is_one_step() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store));
    options.import_folder = dir.path().join("imported");
    let preferences = Preferences {
        layout: Layout::TwoByTwo,
        show_side_panel: true,
        ..Preferences::default()
    };
    let mut h = harness_sized(options, preferences, Vec2::new(1100.0, 1000.0));
    step_until(&mut h, "the axial slice at full resolution", |a| {
        a.slice_image(SliceView::Axial)
            .is_some_and(|i| i.request.level == 0)
            && a.volume
                .as_ref()
                .is_some_and(|v| v.slice_views[SliceView::Axial.index()].image_rect.is_some())
    });
    new_segmentation(&mut h, 30.0);
    let phantom = Phantom::cube(48);
    let label_at = |h: &Harness<'static, Option<StrataApp>>, v: [u32; 3]| {
        let seg = app(h)
            .volume
            .as_ref()
            .and_then(|v| v.segmentation.as_ref())
            .expect("segmentation");
        let layer = seg.layer.read();
        layer.get(v).expect("voxel")
    };

    // Segment 1 along a diagonal, locked; segment 2 across it leaves it alone.
    let (from, from_lps) = view_point(&h, SliceView::Axial, 8.0, 10.0);
    let (to, to_lps) = view_point(&h, SliceView::Axial, 38.0, 34.0);
    drag(&mut h, from, to);
    let first = last_stroke_model(app(&h), SliceView::Axial, from_lps, to_lps);
    with_seg(&mut h, |seg| {
        seg.with_segments(|t| t.get_mut(1).expect("segment 1").locked = true);
        seg.add_segment();
    });
    let (from, from_lps) = view_point(&h, SliceView::Axial, 10.0, 36.0);
    let (to, to_lps) = view_point(&h, SliceView::Axial, 36.0, 8.0);
    drag(&mut h, from, to);
    let second = last_stroke_model(app(&h), SliceView::Axial, from_lps, to_lps);
    let crossing = second.iter().filter(|v| first.contains(v)).count();
    assert!(crossing > 0, "the strokes cross");
    for v in &first {
        assert_eq!(label_at(&h, *v), 1, "locked voxel {v:?}");
    }
    for v in second.iter().filter(|v| !first.contains(v)) {
        assert_eq!(label_at(&h, *v), 2, "voxel {v:?}");
    }

    // A brush limited to soft tissue (-200..200 HU) paints only the voxels whose value is in it.
    with_seg(&mut h, |seg| {
        seg.add_segment();
        seg.limit_to_range = true;
        seg.range = (-200.0, 200.0);
    });
    let k = first[0][2];
    let (from, from_lps) = view_point(&h, SliceView::Axial, 1.0, 24.0);
    let (to, to_lps) = view_point(&h, SliceView::Axial, 24.0, 44.0);
    drag(&mut h, from, to);
    let third = last_stroke_model(app(&h), SliceView::Axial, from_lps, to_lps);
    let in_range = |v: &[u32; 3]| {
        let hu = f64::from(phantom.hu(v[0].into(), v[1].into(), v[2].into()));
        (-200.0..=200.0).contains(&hu)
    };
    let inside = third.iter().filter(|v| in_range(v)).count();
    assert!(
        inside > 0 && inside < third.len(),
        "the stroke crosses the range's edge ({inside} of {})",
        third.len()
    );
    for v in &third {
        let before = if first.contains(v) {
            1
        } else if second.contains(v) {
            2
        } else {
            0
        };
        let expected = if in_range(v) && before != 1 {
            3
        } else {
            before
        };
        assert_eq!(label_at(&h, *v), expected, "voxel {v:?}");
    }

    // A grow capped at 300 voxels stops there, says so, and is one undo step.
    with_seg(&mut h, |seg| {
        seg.add_segment();
        seg.limit_to_range = false;
        seg.grow.max_voxels = 300;
        seg.tool = super::segmentation::SegmentTool::Grow;
    });
    let before = labelled_voxels(app(&h));
    let (at, _) = view_point(&h, SliceView::Axial, 24.0, 20.0);
    assert!(in_range(&[24, 20, k]), "the seed is soft tissue");
    click(&mut h, at, PointerButton::Primary);
    step_until(&mut h, "the capped grow", |a| {
        a.volume
            .as_ref()
            .and_then(|v| v.segmentation.as_ref())
            .is_some_and(|s| !s.busy() && s.notice.is_some())
    });
    h.step();
    let notice = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.segmentation.as_ref())
        .and_then(|s| s.notice.clone())
        .expect("notice");
    assert!(notice.contains("cap"), "{notice}");
    let grown = labelled_voxels(app(&h))
        .into_iter()
        .filter(|&(_, l)| l == 4)
        .count();
    assert!(grown > 0 && grown <= 300, "the grow took {grown} voxels");
    h.get_by_label("Undo").click();
    h.step();
    assert_eq!(
        labelled_voxels(app(&h)),
        before,
        "one undo takes the grow back"
    );
}
