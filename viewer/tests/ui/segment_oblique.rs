//! Segmentation on the oblique view and the Segment section's tool row, through real pointer
//! events (egui_kittest on wgpu, lavapipe in CI; issue 52): the label overlay drawn over a
//! tilted plane equals the nearest-label model of that plane sampled in f64, the brush and the
//! eraser dragged across a tilted plane change exactly the voxels the segment crate's model of
//! the stroke gives, a fill inside a brushed square takes exactly its inside, and one click on a
//! tool's button chooses that tool.
//!
//! Label comparisons are exact, except at pixels whose centre lies within 1e-6 (in voxels) of
//! a boundary between two label voxels, where f64 rounding may pick either neighbour.

use std::collections::BTreeMap;

use egui::Vec2;
use glam::DVec3;

use super::harness::{
    app, click, drag, harness_sized, labelled_voxels, new_segmentation, phantom_store,
    set_segment_tool, step_until, step_until_some,
};
use crate::app::{Layout, Preferences, StrataApp, ViewerOptions};
use crate::jobs::VolumeToOpen;
use crate::oblique::brush_plane;
use crate::oblique_view::pixel_patient;
use crate::overlay::tests::{label_of, write_nrrd, LABEL_DIMS, LABEL_ORIGIN, LABEL_SPACING};
use crate::segmentation::SegmentTool;
use egui_kittest::kittest::Queryable;
use egui_kittest::Harness;
use strata_slices::oblique::{default_extent_mm, ObliquePlane, ObliqueRequest};

/// Within this of a voxel boundary (in voxels) a pixel's nearest voxel is a tie.
const TIE_VOXELS: f64 = 1e-6;

/// The patient position of the centre of pixel (`x`, `y`) of the oblique image of `request`,
/// written out from the plane's definition (centre, right, down, extent) in f64.
fn pixel_centre_lps(request: &ObliqueRequest, x: usize, y: usize) -> DVec3 {
    let plane = &request.plane;
    let across = (x as f64 + 0.5) / request.width as f64 - 0.5;
    let down = (y as f64 + 0.5) / request.height as f64 - 0.5;
    plane.centre + plane.right * (across * plane.extent_mm) + plane.down * (down * plane.extent_mm)
}

/// The nearest voxel of a continuous index, or `None` at a tie or outside `dims` (the
/// overlay's inside test: `-0.5 ≤ index < dims - 0.5`).
fn nearest_voxel(index: DVec3, dims: [u32; 3]) -> Result<Option<[u32; 3]>, ()> {
    if (0..3).any(|a| index[a] < -0.5 || index[a] >= dims[a] as f64 - 0.5) {
        return Ok(None);
    }
    if (0..3).any(|a| ((index[a] - index[a].floor()) - 0.5).abs() < TIE_VOXELS) {
        return Err(());
    }
    Ok(Some([0, 1, 2].map(|a| index[a].round() as u32)))
}

/// Turns the oblique view's plane by `yaw` and `pitch` radians off axial and steps until the
/// view shows the image of that plane; returns the request it shows.
fn tilt_oblique(
    h: &mut Harness<'static, Option<StrataApp>>,
    yaw: f64,
    pitch: f64,
) -> ObliqueRequest {
    if let Some(v) = h.state_mut().as_mut().and_then(|a| a.volume.as_mut()) {
        let geometry = &v.data.info.geometry;
        let axial = ObliquePlane::axial(DVec3::ZERO, default_extent_mm(geometry));
        v.oblique_view.plane = Some(axial.rotated(yaw, pitch));
    }
    step_until_some(h, "the tilted oblique image", |a| {
        let v = a.volume.as_ref()?;
        let plane = v.oblique_view.current_plane(&v.data, &v.scene);
        v.oblique_view
            .shown()
            .filter(|i| i.request.plane == plane)
            .map(|i| i.request)
    })
}

/// The overlay values the oblique view drew for the image of `request`, once the overlay's
/// source revision is `revision` (0 for a label store).
fn shown_overlay(
    h: &mut Harness<'static, Option<StrataApp>>,
    request: ObliqueRequest,
    revision: impl Fn(&StrataApp) -> u64,
) -> std::sync::Arc<Vec<f32>> {
    step_until_some(h, "the overlay over the oblique image", |a| {
        let v = a.volume.as_ref()?;
        let o = v.overlay.as_ref()?;
        let sampled = o.latest_oblique()?;
        let (shown_for, values) = v.oblique_view.shown_overlay()?;
        (shown_for == request
            && sampled.revision == revision(a)
            && std::sync::Arc::ptr_eq(&sampled.values, &values))
        .then_some(values)
    })
}

fn options_with_oblique(store: std::path::PathBuf, dir: &std::path::Path) -> ViewerOptions {
    let mut options = ViewerOptions::new(VolumeToOpen::Path(store));
    options.import_folder = dir.join("imported");
    options
}

fn oblique_preferences(side_panel: bool) -> Preferences {
    Preferences {
        layout: Layout::TwoByTwo,
        show_oblique: true,
        show_side_panel: side_panel,
        ..Preferences::default()
    }
}

/// A label map on its own grid (10 mm voxels, shifted against the primary's) opened as the
/// overlay: over a plane tilted 0.5 and 0.3 rad off axial, the oblique view draws exactly the
/// label of the label voxel nearest to each pixel centre (ties excepted, see the module doc),
/// nothing outside the label grid, and on screen the labelled pixels are tinted while the
/// background ones are left as they are; hiding the overlay clears the tint.
#[test]
fn the_oblique_view_draws_the_nearest_label_of_each_pixel_centre_on_the_labels_own_grid() {
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
    let mut options = options_with_oblique(store, dir.path());
    options.overlay = Some(labels);
    let mut h = harness_sized(options, oblique_preferences(false), Vec2::new(800.0, 640.0));
    step_until(&mut h, "the label overlay", |a| {
        a.volume.as_ref().is_some_and(|v| v.overlay.is_some())
    });
    let request = tilt_oblique(&mut h, 0.5, 0.3);
    let values = shown_overlay(&mut h, request, |_| 0);
    assert_eq!(values.len(), request.width * request.height);

    // The model: each pixel centre in f64, into the label grid through its NRRD header (axis
    // aligned: (p − origin) / spacing), the nearest voxel's label from the label function.
    let origin = DVec3::from(LABEL_ORIGIN);
    let mut expected = vec![None; values.len()];
    let (mut compared, mut outside, mut labels) = (0, 0, std::collections::BTreeSet::new());
    for y in 0..request.height {
        for x in 0..request.width {
            let index = (pixel_centre_lps(&request, x, y) - origin) / LABEL_SPACING;
            let got = values[y * request.width + x];
            match nearest_voxel(index, LABEL_DIMS) {
                Err(()) => continue,
                Ok(None) => {
                    assert!(got.is_nan(), "pixel ({x},{y}) outside has {got}");
                    // Nothing is drawn there, as over label 0.
                    expected[y * request.width + x] = Some(0.0);
                    outside += 1;
                }
                Ok(Some(v)) => {
                    let label = label_of(v[0], v[1], v[2]);
                    assert_eq!(got as f64, label, "pixel ({x},{y}) at label index {index}");
                    expected[y * request.width + x] = Some(label);
                    compared += 1;
                    labels.insert(label as u8);
                }
            }
        }
    }
    assert!(compared > 2000, "only {compared} pixels compared");
    assert!(
        outside > 100,
        "the plane leaves the label grid ({outside} pixels)"
    );
    assert_eq!(labels.len(), 5, "the plane crosses every label: {labels:?}");

    // On screen: with the overlay shown and hidden, pixels whose 3×3 neighbourhood holds one
    // label only (away from texture-edge rounding) change exactly where that label is not 0.
    let shown = h.render().expect("render");
    if let Some(o) = h
        .state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .and_then(|v| v.overlay.as_mut())
    {
        o.style.visible = false;
    }
    step_until_some(&mut h, "the hidden overlay's texture", |a| {
        let v = a.volume.as_ref()?;
        let hidden = !v.overlay.as_ref()?.style.visible;
        hidden.then_some(())
    });
    for _ in 0..3 {
        h.step();
    }
    let hidden = h.render().expect("render");
    let rect = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.oblique_view.image_rect)
        .expect("oblique image on screen");
    let ppp = h.ctx.pixels_per_point();
    let (mut tinted, mut tinted_of, mut untouched, mut untouched_of) = (0, 0, 0, 0);
    for y in 1..request.height - 1 {
        for x in 1..request.width - 1 {
            let centre = expected[y * request.width + x];
            let uniform =
                (0..9).all(|n| expected[(y + n / 3 - 1) * request.width + x + n % 3 - 1] == centre);
            let Some(label) = centre.filter(|_| uniform) else {
                continue;
            };
            let sx = (rect.left() + (x as f32 + 0.5) / request.width as f32 * rect.width()) * ppp;
            let sy = (rect.top() + (y as f32 + 0.5) / request.height as f32 * rect.height()) * ppp;
            let (a, b) = (
                shown.get_pixel(sx as u32, sy as u32).0,
                hidden.get_pixel(sx as u32, sy as u32).0,
            );
            let difference = (0..3)
                .map(|c| (a[c] as i32 - b[c] as i32).abs())
                .max()
                .unwrap_or(0);
            if label == 0.0 {
                untouched_of += 1;
                untouched += usize::from(difference == 0);
            } else {
                tinted_of += 1;
                tinted += usize::from(difference > 4);
            }
        }
    }
    assert!(
        tinted_of > 100 && untouched_of > 100,
        "{tinted_of} labelled, {untouched_of} not"
    );
    // A label colour at opacity 0.5 moves at least one channel; the crosshair and the letters,
    // drawn over both, may hide a few.
    assert!(
        tinted as f64 > 0.98 * tinted_of as f64,
        "only {tinted} of {tinted_of} labelled pixels are tinted"
    );
    assert!(
        untouched as f64 > 0.99 * untouched_of as f64,
        "only {untouched} of {untouched_of} background pixels are untouched"
    );
}

/// The brush and the eraser dragged across the oblique view turned 0.5 and 0.35 rad off axial
/// paint and clear exactly the voxels of the segment crate's model of each stroke (a disc in
/// the plane swept along the pointer's patient positions), positions and not only counts; the
/// oblique view's overlay shows the painted layer; each stroke is one undo step; a locked
/// segment and the value range are respected.
#[test]
fn on_a_tilted_oblique_view_the_brush_and_eraser_change_the_models_voxels_and_undo_restores() {
    use strata_segment::tools::brush::stroke_voxels;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let options = options_with_oblique(store, dir.path());
    let mut h = harness_sized(
        options,
        oblique_preferences(true),
        Vec2::new(1100.0, 1000.0),
    );
    step_until(&mut h, "the oblique image", |a| {
        a.volume
            .as_ref()
            .is_some_and(|v| v.oblique_view.shown().is_some())
    });
    // 30 mm on the phantom's 8.3 mm voxels: a disc about 3.6 voxels across.
    new_segmentation(&mut h, 30.0);
    let request = tilt_oblique(&mut h, 0.5, 0.35);
    assert!(
        request.plane.normal().z.abs() < 0.95,
        "the plane is tilted well off axial"
    );
    let rect = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.oblique_view.image_rect)
        .expect("oblique image on screen");

    // One stroke: where the pointer was pressed and released, the model of the whole stroke.
    let stroke = |h: &mut Harness<'static, Option<StrataApp>>, from: Vec2, to: Vec2| {
        let (from, to) = (rect.center() + from, rect.center() + to);
        drag(h, from, to);
        let seg = app(h)
            .volume
            .as_ref()
            .and_then(|v| v.segmentation.as_ref())
            .expect("segmentation");
        assert_eq!(seg.error, None, "the tool reported an error");
        let positions = &seg.last_stroke;
        assert!(positions.len() >= 2, "a drag gives a stroke: {positions:?}");
        let (from_lps, to_lps) = (
            pixel_patient(&request.plane, rect, from),
            pixel_patient(&request.plane, rect, to),
        );
        // The same f32 screen points through the same plane: within rounding.
        assert!(
            positions[0].distance(from_lps) < 1e-6
                && positions[positions.len() - 1].distance(to_lps) < 1e-6,
            "stroke {positions:?} vs pointer {from_lps} → {to_lps}"
        );
        let brush = seg.brush(brush_plane(&request.plane)).expect("brush");
        let layer = seg.layer.read();
        stroke_voxels(layer.grid(), &brush, positions).expect("model")
    };

    let model = stroke(&mut h, Vec2::new(-45.0, -12.0), Vec2::new(35.0, 20.0));
    let painted = labelled_voxels(app(&h));
    assert!(model.len() > 30, "the stroke covers {} voxels", model.len());
    assert_eq!(
        painted.iter().map(|(v, _)| *v).collect::<Vec<_>>(),
        model,
        "the brush painted other voxels than the model of its stroke"
    );
    assert!(painted.iter().all(|&(_, l)| l == 1), "all with segment 1");
    let normals: std::collections::BTreeSet<u32> = painted.iter().map(|(v, _)| v[2]).collect();
    assert!(
        normals.len() > 1,
        "a tilted stroke spans several axial slices"
    );

    // The oblique view's overlay shows the edited layer: every pixel the nearest painted voxel.
    let revision = |a: &StrataApp| {
        a.volume
            .as_ref()
            .and_then(|v| v.segmentation.as_ref())
            .map_or(0, |s| s.layer.revision())
    };
    let values = shown_overlay(&mut h, request, revision);
    let (geometry, dims) = {
        let v = app(&h).volume.as_ref().expect("volume");
        (v.data.info.geometry.clone(), v.data.info.geometry.dims)
    };
    let painted_set: std::collections::BTreeSet<[u32; 3]> =
        painted.iter().map(|(v, _)| *v).collect();
    let mut shown_painted = 0;
    for y in 0..request.height {
        for x in 0..request.width {
            let index = geometry.index_from_patient(pixel_centre_lps(&request, x, y));
            let got = values[y * request.width + x];
            match nearest_voxel(index, dims) {
                Err(()) => {}
                Ok(None) => assert!(got.is_nan(), "pixel ({x},{y}) outside has {got}"),
                Ok(Some(v)) => {
                    let label = if painted_set.contains(&v) { 1.0 } else { 0.0 };
                    assert_eq!(got, label, "pixel ({x},{y}) over voxel {v:?}");
                    shown_painted += usize::from(label == 1.0);
                }
            }
        }
    }
    assert!(
        shown_painted > 20,
        "only {shown_painted} pixels show the stroke"
    );

    set_segment_tool(&mut h, SegmentTool::Eraser);
    let erased = stroke(&mut h, Vec2::new(-5.0, -45.0), Vec2::new(0.0, 50.0));
    let expected: Vec<[u32; 3]> = painted
        .iter()
        .map(|(v, _)| *v)
        .filter(|v| !erased.contains(v))
        .collect();
    assert!(
        expected.len() < painted.len() && !expected.is_empty(),
        "the eraser's line crosses the stroke"
    );
    assert_eq!(
        labelled_voxels(app(&h))
            .iter()
            .map(|(v, _)| *v)
            .collect::<Vec<_>>(),
        expected,
        "the eraser cleared other voxels than the model of its stroke"
    );

    h.get_by_label("Undo").click();
    h.step();
    assert_eq!(
        labelled_voxels(app(&h)),
        painted,
        "one undo restores the erased voxels"
    );
    h.get_by_label("Undo").click();
    h.step();
    assert!(
        labelled_voxels(app(&h)).is_empty(),
        "one undo removes the whole stroke"
    );

    // Locks hold on the oblique view as on the slices: with segment 1 back (redo) and locked,
    // the brush with a new segment 2 takes the model's voxels of its stroke except segment 1's.
    h.get_by_label("Redo").click();
    h.step();
    assert_eq!(labelled_voxels(app(&h)), painted, "redo of the stroke");
    if let Some(seg) = h
        .state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .and_then(|v| v.segmentation.as_mut())
    {
        seg.with_segments(|t| {
            if let Some(s) = t.get_mut(1) {
                s.locked = true;
            }
        });
        seg.add_segment();
        assert_eq!(seg.active, 2, "the new segment is the one the brush paints");
    }
    h.step();
    set_segment_tool(&mut h, SegmentTool::Brush);
    let crossing = stroke(&mut h, Vec2::new(-5.0, -45.0), Vec2::new(0.0, 50.0));
    let mut expected: Vec<([u32; 3], u16)> = painted.clone();
    expected.extend(
        crossing
            .iter()
            .filter(|v| !painted_set.contains(*v))
            .map(|&v| (v, 2)),
    );
    expected.sort_by_key(|(v, _)| [v[2], v[1], v[0]]);
    assert!(
        crossing.iter().any(|v| painted_set.contains(v)),
        "the second stroke crosses the locked one"
    );
    assert_eq!(
        labelled_voxels(app(&h)),
        expected,
        "the brush painted over the locked segment or missed the model's voxels"
    );

    // The value range holds too: a brush limited to soft tissue (-200..200 HU) with a new
    // segment 3 takes the model's voxels of its stroke whose phantom value is in the range,
    // except the locked segment's, and nothing else.
    let before: BTreeMap<[u32; 3], u16> = labelled_voxels(app(&h)).into_iter().collect();
    if let Some(seg) = h
        .state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .and_then(|v| v.segmentation.as_mut())
    {
        seg.add_segment();
        seg.values.limit_to_range = true;
        seg.values.range = (-200.0, 200.0);
    }
    h.step();
    let ranged = stroke(&mut h, Vec2::new(-90.0, 70.0), Vec2::new(80.0, -60.0));
    let phantom = strata_storage::phantom::Phantom::cube(48);
    let in_range = |v: &[u32; 3]| {
        let hu = f64::from(phantom.hu(v[0].into(), v[1].into(), v[2].into()));
        (-200.0..=200.0).contains(&hu)
    };
    let inside = ranged.iter().filter(|v| in_range(v)).count();
    assert!(
        inside > 0 && inside < ranged.len(),
        "the stroke crosses the range's edge ({inside} of {})",
        ranged.len()
    );
    let mut expected = before.clone();
    for v in &ranged {
        if in_range(v) && before.get(v) != Some(&1) {
            expected.insert(*v, 3);
        }
    }
    let after: BTreeMap<[u32; 3], u16> = labelled_voxels(app(&h)).into_iter().collect();
    assert_eq!(
        after, expected,
        "the brush left its value range, painted a locked voxel or missed the model's voxels"
    );
}

/// Fill on the oblique view turned 0.5 and 0.35 rad off axial: four brush strokes close a
/// square in the plane, then one click with Fill (and a new segment) inside it takes exactly
/// the voxels of the plane's slab (the brush's: `-h/2 ≤ n·(x − c) < h/2`, h the largest voxel
/// step along n) whose centre, projected into the plane, lies inside the square and that the
/// strokes left unpainted: positions, not counts. The strokes' band (30 mm) is wider than any
/// step between neighbouring voxels of the slab (√2 · 8.3 mm), so the fill cannot leak through
/// it; the fill is one undo step.
#[test]
fn on_a_tilted_oblique_view_fill_takes_the_inside_of_a_brushed_square() {
    use strata_segment::tools::brush::SlicePlane;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let options = options_with_oblique(store, dir.path());
    let mut h = harness_sized(
        options,
        oblique_preferences(true),
        Vec2::new(1100.0, 1000.0),
    );
    step_until(&mut h, "the oblique image", |a| {
        a.volume
            .as_ref()
            .is_some_and(|v| v.oblique_view.shown().is_some())
    });
    new_segmentation(&mut h, 30.0);
    let request = tilt_oblique(&mut h, 0.5, 0.35);
    let rect = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.oblique_view.image_rect)
        .expect("oblique image on screen");
    // The square's corners (screen offsets from the image's centre), each side drawn past its
    // corners so that the strokes overlap there.
    let half_side = 75.0;
    let corners = [
        Vec2::new(-half_side, -half_side),
        Vec2::new(half_side, -half_side),
        Vec2::new(half_side, half_side),
        Vec2::new(-half_side, half_side),
    ];
    for n in 0..4 {
        let (a, b) = (corners[n], corners[(n + 1) % 4]);
        let past = (b - a).normalized() * 25.0;
        drag(&mut h, rect.center() + a - past, rect.center() + b + past);
    }
    let painted: std::collections::BTreeSet<[u32; 3]> = labelled_voxels(app(&h))
        .into_iter()
        .map(|(v, _)| v)
        .collect();
    assert!(
        painted.len() > 40,
        "the square's strokes cover {} voxels",
        painted.len()
    );

    if let Some(seg) = h
        .state_mut()
        .as_mut()
        .and_then(|a| a.volume.as_mut())
        .and_then(|v| v.segmentation.as_mut())
    {
        seg.add_segment();
        assert_eq!(seg.active, 2, "the fill paints the new segment");
    }
    set_segment_tool(&mut h, SegmentTool::Fill);
    click(&mut h, rect.center(), egui::PointerButton::Primary);
    let seg = app(&h)
        .volume
        .as_ref()
        .and_then(|v| v.segmentation.as_ref())
        .expect("segmentation");
    assert_eq!(seg.error, None, "the fill reported an error");
    let filled: Vec<[u32; 3]> = labelled_voxels(app(&h))
        .into_iter()
        .filter(|&(_, l)| l == 2)
        .map(|(v, _)| v)
        .collect();

    // The model, over every voxel of the grid in f64.
    let SlicePlane::Oblique { centre_lps, u, v } = brush_plane(&request.plane) else {
        panic!("the oblique view's brush plane is oblique");
    };
    let geometry = app(&h)
        .volume
        .as_ref()
        .expect("volume")
        .data
        .info
        .geometry
        .clone();
    let normal = u.cross(v);
    let half = (0..3)
        .map(|a| geometry.spacing_mm[a] * normal.dot(DVec3::from(geometry.direction[a])).abs())
        .fold(0.0, f64::max)
        / 2.0;
    let in_plane = |x: DVec3| ((x - centre_lps).dot(u), (x - centre_lps).dot(v));
    let (a0, b0) = in_plane(pixel_patient(
        &request.plane,
        rect,
        rect.center() + corners[0],
    ));
    let (a1, b1) = in_plane(pixel_patient(
        &request.plane,
        rect,
        rect.center() + corners[2],
    ));
    let [nx, ny, nz] = geometry.dims;
    let mut want = Vec::new();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let x = geometry.patient_from_index(DVec3::new(
                    f64::from(i),
                    f64::from(j),
                    f64::from(k),
                ));
                let off = normal.dot(x - centre_lps);
                let (a, b) = in_plane(x);
                if (-half..half).contains(&off)
                    && a0.min(a1) < a
                    && a < a0.max(a1)
                    && b0.min(b1) < b
                    && b < b0.max(b1)
                    && !painted.contains(&[i, j, k])
                {
                    want.push([i, j, k]);
                }
            }
        }
    }
    want.sort_by_key(|v| [v[2], v[1], v[0]]);
    assert!(
        want.len() > 20,
        "the model's inside is too small to test: {}",
        want.len()
    );
    assert_eq!(
        filled, want,
        "the fill took other voxels than the model's inside"
    );

    h.get_by_label("Undo").click();
    h.step();
    let after_undo: std::collections::BTreeSet<[u32; 3]> = labelled_voxels(app(&h))
        .into_iter()
        .map(|(v, _)| v)
        .collect();
    assert_eq!(after_undo, painted, "one undo removes the whole fill");
}

/// One click on each button of the Segment section's tool row chooses that tool, starting on
/// the frame after the segmentation opens, where the row first appears; opening it leaves the
/// views where they were (the side panel keeps its width: its rows wrap instead).
#[test]
fn one_click_on_a_tool_button_chooses_that_tool() {
    use crate::app::ViewSlot;
    let dir = tempfile::tempdir().expect("temp dir");
    let store = phantom_store(dir.path());
    let options = options_with_oblique(store, dir.path());
    let mut h = harness_sized(
        options,
        oblique_preferences(true),
        Vec2::new(1100.0, 1000.0),
    );
    step_until(&mut h, "the volume open", |a| a.volume.is_some());
    h.get_by_label("Segment").click();
    h.step();
    let view_before = app(&h).view_rect(ViewSlot::ThreeD).expect("3D view");
    h.get_by_label("New segmentation").click();
    step_until(&mut h, "the new segmentation", |a| {
        a.volume.as_ref().is_some_and(|v| v.segmentation.is_some())
    });
    h.step();
    for (label, chosen) in [
        ("Brush", SegmentTool::Brush),
        ("Eraser", SegmentTool::Eraser),
        ("Fill", SegmentTool::Fill),
        ("Grow", SegmentTool::Grow),
        ("Brush", SegmentTool::Brush),
        ("Off", SegmentTool::None),
    ] {
        h.get_by_label(label).click();
        h.step();
        let tool = app(&h)
            .volume
            .as_ref()
            .and_then(|v| v.segmentation.as_ref())
            .map(|s| s.tool);
        assert_eq!(tool, Some(chosen), "one click on {label:?}");
    }
    assert_eq!(
        app(&h).view_rect(ViewSlot::ThreeD),
        Some(view_before),
        "opening the segmentation moved the views (the side panel widened)"
    );
}
