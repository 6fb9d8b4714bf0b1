//! Segmentation through real pointer events: brush, eraser, grow, journals, locked segments.

use super::harness::*;

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

    set_segment_tool(h, crate::segmentation::SegmentTool::Eraser);
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

/// Runs `f` on the open segmentation.
fn with_seg(
    h: &mut Harness<'static, Option<StrataApp>>,
    f: impl FnOnce(&mut crate::segmentation::Segmentation),
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
fn in_3d_the_brush_paints_the_ball_around_the_picked_surface_point_and_undo_removes_it() {
    use strata_segment::tools::brush::BrushShape;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let mut options = options_for(&store, dir.path());
    options.initial_view = Some(strata_viewer_ui::orbit::StandardView::Anterior);
    let preferences = two_by_two(true);
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
    let options = options_for(&store, dir.path());
    let preferences = two_by_two(true);
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
            crate::segmentation::SaveFormat::Nifti,
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
    let note: crate::segmentation::JournalNote = serde_json::from_slice(
        &std::fs::read(crate::segmentation::note_path(&journal)).expect("the note"),
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
    set_segment_tool(&mut h, crate::segmentation::SegmentTool::Grow);
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
        seg.values.range = range;
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

#[test]
fn on_a_rotated_anisotropic_grid_the_brush_paints_the_models_voxels_in_mm() {
    let dir = tempfile::tempdir().expect("temp dir");
    let scan = dir.path().join("rotated.nrrd");
    write_rotated_nrrd(&scan, [40, 36, 30], [4.0, 5.0, 6.5]);
    let options = options_for(&scan, dir.path());
    let preferences = two_by_two(true);
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
        let journal = crate::segmentation::journal_path(&import_folder);
        let note = crate::segmentation::JournalNote {
            primary: location,
            base: None,
        };
        std::fs::write(
            crate::segmentation::note_path(&journal),
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
        let preferences = two_by_two(true);
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
    use crate::overlay::tests::{label_of, write_nrrd, LABEL_DIMS, LABEL_ORIGIN, LABEL_SPACING};
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
    let mut options = options_for(&store, dir.path());
    options.overlay = Some(labels.clone());
    let preferences = two_by_two(true);
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
    set_segment_tool(&mut h, crate::segmentation::SegmentTool::Brush);
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

#[test]
fn the_brush_leaves_locked_segments_and_values_outside_its_range_and_a_capped_grow_is_one_step() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let options = options_for(&store, dir.path());
    let preferences = two_by_two(true);
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
        seg.values.limit_to_range = true;
        seg.values.range = (-200.0, 200.0);
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
        seg.values.limit_to_range = false;
        seg.values.max_voxels = 300;
        seg.tool = crate::segmentation::SegmentTool::Grow;
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
