//! The slice, 3D and oblique views: what opens, what a drag or the wheel does, what reaches the screen.

use super::harness::*;

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
fn the_phantom_opens_and_the_3d_view_is_not_blank_then_a_preset_changes_it() {
    let (_dir, mut h, bone) = open_phantom_settled(
        true,
        "the phantom streamed in (converged frame for the current request)",
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
        crate::orientation::SliceFrame::for_view(SliceView::Axial, &v.data.info.geometry)
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

#[test]
fn a_click_in_the_3d_view_picks_the_bone_surface_it_shows() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = options_for(&store, dir.path());
    options.initial_view = Some(strata_viewer_ui::orbit::StandardView::Anterior);
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
        crate::scene::voxel_index(picked).map(|i| i as u32)
    );
}

#[test]
fn a_window_preset_and_the_inverted_colour_map_reach_the_screen() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let options = options_for(&store, dir.path());
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
    let mediastinum = crate::scene::Window::new(50.0, 350.0);
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
        .colour_map = crate::colour_maps::ColourMap::Inverted;
    step_until(&mut h, "the inverted slice", |a| {
        a.slice_display(SliceView::Axial)
            .is_some_and(|s| s.colour_map == crate::colour_maps::ColourMap::Inverted)
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

#[test]
fn the_crop_box_is_drawn_in_3d_and_dragging_its_superior_handle_lowers_the_top() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = options_for(&store, dir.path());
    options.initial_view = Some(strata_viewer_ui::orbit::StandardView::Anterior);
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
        crate::view3d::crop_handles(rect, &camera, &v.data, &v.scene)
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

/// Issue 16: the oblique view shows the CPU resampling of its plane (the path checked against
/// the f64 trilinear reference in oblique.rs), a drag turns the plane by the drag's angle,
/// and "Align to 3D" turns it to face the 3D camera.
#[test]
fn the_oblique_view_resamples_its_plane_turns_with_a_drag_and_aligns_to_the_3d_camera() {
    use crate::oblique::{resample, LevelBrickCache};
    use strata_slices::oblique::TURN_PER_POINT;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let options = options_for(&store, dir.path());
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
    let options = options_for(&nifti, dir.path());
    let preferences = two_by_two(true);
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
    assert_eq!(player.playback.current, 1);
    assert_eq!(player.ahead_frame(), Some(2), "frame 2 is opened ahead");
    step_until(&mut h, "a 3D frame of frame 1", |a| {
        a.volume
            .as_ref()
            .is_some_and(|v| v.data.session.latest_frame().is_some())
    });
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
    let mut options = options_for(&store, dir.path());
    options.exit_after_seconds = Some(3600.0);
    let preferences = two_by_two(true);
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

/// Issue 36: at 1024 points wide, with a volume open (all toolbar items shown), no two toolbar
/// items overlap, the warning included.
#[test]
fn toolbar_items_do_not_overlap_at_1024_points() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let options = options_for(&store, dir.path());
    let preferences = two_by_two(true);
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
        crate::widgets::NOT_FOR_DIAGNOSIS,
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
                .any(|(l, _)| l == crate::widgets::NOT_FOR_DIAGNOSIS),
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

/// Issue 36, honest motion: after DVR → MIP the 3D view never paints the DVR image again (it
/// stays empty, saying "rendering MIP…", until the first MIP frame), and the first image it
/// paints is a MIP one. The time from the switch to that first painted MIP frame is printed:
/// the switch's latency as the user sees it (not asserted: wall-clock bounds fail on loaded
/// machines).
#[test]
fn after_a_mode_switch_the_3d_view_paints_only_the_new_modes_frames() {
    use strata_render::RenderMode;
    let (_dir, mut h, _) = open_phantom_settled(false, "a converged DVR frame");
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
    let (_dir, mut h, _) = open_phantom_settled(false, "the phantom");
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
    // Turn by 40°: this pass sends the request and paints the frame it has, usually the old
    // one; the render thread may also deliver the turned frame within the pass (it did under
    // load once). Either way the outlines must carry the painted image's camera.
    if let Some(v) = h.state_mut().as_mut().and_then(|a| a.volume.as_mut()) {
        v.view_3d.orbit.azimuth_deg += 40.0;
    }
    h.step();
    let (painted, overlays, turned) = cameras(&h);
    assert_ne!(turned, live);
    assert!(
        painted == Some(live) || painted == Some(turned),
        "the painted frame is neither the old nor the turned camera's: {painted:?}"
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
