//! Measurements: the ruler and the box ROI, their undo, and that drawing one moves nothing else.

use super::harness::*;

#[test]
fn a_ruler_reads_the_millimetres_and_a_box_roi_the_phantoms_statistics_and_undo_removes_them() {
    use strata_viewer_ui::measurements::{Shape, Tool};
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
            strata_viewer_ui::measurements::distance_mm(&v.data.info.geometry, a, b),
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

/// Issue 36, the steady layout: a long ROI statistics line does not widen the side panel (the
/// views keep their rects), and the first transfer-function edit does not move the plot.
#[test]
fn a_long_roi_line_and_the_first_tf_edit_move_nothing() {
    use strata_viewer_ui::measurements::{RoiStats, Shape};

    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let options = options_for(&store, dir.path());
    let preferences = two_by_two(true);
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

/// A link with measurements (`m=`, as the page writes it) opens with them on the desktop: the
/// ruler reads the millimetres between its points, the box gets the phantom's statistics from
/// its slice once the full-resolution slice is shown (the link carries no statistics), and
/// the desktop's "Copy link" gives them back as the link wrote them.
#[test]
fn a_link_with_measurements_opens_with_them_and_copy_link_carries_them() {
    use strata_service::server::{name_for_store, start, ServeOptions};
    use strata_viewer_ui::measurements::{distance_mm, Shape};

    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let name = name_for_store(&store);
    let server = start(vec![(name.clone(), store.clone())], ServeOptions::default())
        .expect("serving the phantom");
    let measurements = "r:10,10,20,30,25,20;ba:14,16,20,21,26,20";
    let link = format!(
        "{}/#store={name}&mode=mip&cursor=24,24,20&m={measurements}",
        server.base_url()
    );
    let mut options = ViewerOptions::new(VolumeToOpen::Url {
        url: link,
        token_file: None,
        token: None,
    });
    options.import_folder = dir.path().join("imported");
    let mut h = harness_with(options, two_by_two(false));
    let stats = step_until_some(&mut h, "the link's box measured at full resolution", |a| {
        let items = &a.volume.as_ref()?.scene.measurements.items;
        match items.get(1).map(|m| &m.shape) {
            Some(Shape::Roi {
                stats: Some(stats), ..
            }) if stats.level == 0 => Some(*stats),
            _ => None,
        }
    });
    let phantom = Phantom::cube(48);
    let spacing = phantom.geometry().spacing_mm[0];
    let (ruler, copied) = {
        let a = app(&h);
        let v = a.volume.as_ref().expect("volume");
        let items = &v.scene.measurements.items;
        assert_eq!(items.len(), 2, "{items:?}");
        let Shape::Distance { a: from, b: to } = items[0].shape else {
            panic!("not a ruler: {:?}", items[0]);
        };
        (
            distance_mm(&v.data.info.geometry, from, to),
            a.share_link().expect("a served store has a link"),
        )
    };
    // 20 voxels across and 15 down: 25 voxels.
    assert!((ruler - 25.0 * spacing).abs() < 1e-9, "ruler {ruler} mm");
    // The phantom's HU at the voxel centres inside the box (corners on centres, inclusive).
    let values: Vec<f64> = (16..=26)
        .flat_map(|j| (14..=21).map(move |i| (i, j)))
        .map(|(i, j)| phantom.hu(i, j, 20) as f64)
        .collect();
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let sd = (values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n).sqrt();
    assert_eq!(stats.voxels, values.len() as u64, "{stats:?}");
    // Two summation orders (one pass of sums and squares, against mean then deviations).
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * (1.0 + b.abs());
    assert!(
        close(stats.mean, mean) && close(stats.sd, sd),
        "{stats:?} vs mean {mean} sd {sd}"
    );
    assert!(
        copied.contains(&format!("&m={measurements}")),
        "the copied link {copied}"
    );
}
