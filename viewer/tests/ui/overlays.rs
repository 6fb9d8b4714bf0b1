//! Label-map and DICOM SEG overlays over the slices and the 3D view.

use super::harness::*;

/// Issue 16: a label map on a coarser, shifted grid (40³ of 10 mm over the phantom's 48³ of
/// 8.3 mm), opened from the overlay panel as a NRRD, colours exactly the axial pixels whose
/// patient position falls in a labelled overlay voxel, in that label's colour at the chosen
/// opacity; background and hidden labels leave the slice as it was; the readout names the
/// label under the pointer.
#[test]
fn a_label_map_overlay_colours_the_right_pixels_and_a_hidden_label_clears_them() {
    use crate::overlay::tests::{label_of, write_nrrd, LABEL_DIMS, LABEL_ORIGIN, LABEL_SPACING};
    use crate::overlay::OverlayKind;
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
    let options = options_for(&store, dir.path());
    let preferences = two_by_two(true);
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
                     change: &dyn Fn(&mut crate::overlay::OverlayStyle)| {
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

/// Issue 16: a DICOM SEG (written by highdicom: `storage/tests/support/make_dicom_seg.py`)
/// opened from the overlay panel, even with "Continuous" chosen, becomes a label map whose
/// panel lists every segment by number and name in its recommended colour (CIELab → sRGB as
/// highdicom converts it, ±1). Without highdicom this FAILS with the install command (CI:
/// .ci/run).
#[test]
fn a_dicom_seg_overlay_lists_its_segments_by_name_and_colour() {
    use crate::overlay::OverlayKind;
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
    let options = options_for(&store, dir.path());
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

/// Issue 16, the overlay in 3D: a label box (label 1, on the primary's own grid) inside the
/// phantom, opened from the overlay panel, takes the label's hue in the 3D view's pixels whose
/// rays cross the box, leaves the pixels whose rays miss it alone, and hiding the label (a
/// colour-table change: the same uploaded grid) takes it out again.
#[test]
fn a_label_map_colours_the_3d_pixels_over_it_and_hiding_the_label_removes_it() {
    use crate::overlay::tests::write_nrrd;
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
    let options = options_for(&store, dir.path());
    let preferences = two_by_two(true);
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
                     change: &dyn Fn(&mut crate::overlay::OverlayStyle)| {
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

/// `strata view SCAN --overlay LABELS`: the option opens the label map over the volume once it
/// is shown, as the panel's button does.
#[test]
fn the_overlay_option_opens_the_label_map_with_the_volume() {
    use crate::overlay::tests::{label_of, write_nrrd, LABEL_DIMS, LABEL_ORIGIN, LABEL_SPACING};
    use crate::overlay::OverlayKind;
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
    let mut options = options_for(&store, dir.path());
    options.overlay = Some(labels.clone());
    let mut h = harness_with(options, two_by_two(true));
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
