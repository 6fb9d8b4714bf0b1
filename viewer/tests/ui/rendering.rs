//! The rendering controls: presets, lighting, adaptive sampling and the transfer function editor with its undo.

use super::harness::*;

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

/// The rendering panel's adaptive sampling (issue 15): the checkbox shows the ε slider, both
/// reach the render request, the still view's final frame is then the adaptive pass's (the
/// status line says so), both survive the preferences' round trip, and in iso mode the
/// checkbox is disabled.
#[test]
fn the_adaptive_sampling_checkbox_and_epsilon_slider_reach_the_frame_and_persist() {
    use egui_kittest::kittest::NodeT;
    use strata_viewer_ui::adaptive::{ADAPTIVE_LABEL, EPSILON_LABEL};
    let dir = tempfile::tempdir().expect("tempdir");
    let store = phantom_store(dir.path());
    let options = options_for(&store, dir.path());
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

/// Issue 37: the Rendering panel's light controls change the settings the 3D view asks for
/// (key light, intensity, ambient, shadows, which turn shading on), the shadowed frame renders,
/// shadows are refused for MIP, and showing the controls does not move the views (issue 36:
/// the side panel keeps its width).
#[test]
fn the_light_controls_reach_the_3d_views_settings_without_widening_the_panel() {
    use egui::accesskit::Role;
    use egui_kittest::kittest::NodeT;
    use strata_render::{LightDirection, RenderSettings, ShadowMode};
    use strata_viewer_ui::lighting::{
        AMBIENT_LABEL, AZIMUTH_LABEL, DIRECTIONAL_LABEL, ELEVATION_LABEL, EXACT_SHADOWS_LABEL,
        INTENSITY_LABEL, SHADOW_STEP_LABEL,
    };

    let dir = tempfile::tempdir().expect("tempdir");
    let store = phantom_store(dir.path());
    let options = options_for(&store, dir.path());
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
    use crate::preferences::CinematicPreset;
    use egui_kittest::kittest::NodeT;
    use strata_render::{LightDirection, RenderMode, RenderSettings, ShadowMode, TransferFunction};
    use strata_viewer_ui::lighting::{CACHE_SHADOWS_LABEL, OCCLUSION_LABEL, SCATTERING_LABEL};

    let dir = tempfile::tempdir().expect("tempdir");
    let store = phantom_store(dir.path());
    let options = options_for(&store, dir.path());
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
