//! The brush in the page's 3D view (issue 52): with the brush chosen, a left drag across the
//! 3D view's iso surface (a real drag over the DevTools pipe) paints balls at the surface
//! points the page picks under the pointer. The page publishes the points it picked
//! (`data-segment-3d`, continuous level-0 indices in full); the downloaded NIfTI label map must
//! hold exactly the voxels the desktop's sphere stroke (`Segmentation::sphere_stroke_to`:
//! strata-segment's `brush::stroke` with a ball of the panel's diameter, swept from each picked
//! point to the next) paints at those points, as one undo step. That the page picks what the
//! desktop picks at a pixel is picking.rs's test; this one checks the stroke made of the picks.

use egui::{pos2, vec2, Pos2, Rect};
use glam::DVec3;
use strata_segment::tools::brush::{self, Brush, BrushAction, BrushShape};
use strata_segment::LabelLayer;
use strata_viewer_ui::segment_panel::DEFAULT_BRUSH_DIAMETER_MM;
use strata_web::view_state::Fragment;

use crate::input::{open_page, view_rect};
use crate::segment::{
    download, drag_through, figure, labelled_voxels, layer_voxels, wait_for_figures, AxialPainting,
};
use crate::PAGE_DEADLINE;

/// The picked points (continuous level-0 index) of the page's last 3D stroke, once it has
/// finished `strokes` strokes.
fn stroke_points(page: &mut crate::input::cdp::Cdp, strokes: u32) -> Vec<[f64; 3]> {
    let text = page.wait_for("the page's 3D stroke to end", PAGE_DEADLINE, |page| {
        // `data-segment-3d` is not `dataset.segment3d`: the dataset name keeps a hyphen
        // before a digit, so the attribute is read by its own name.
        let text = page.evaluate(
            "document.getElementById('strata-canvas')?.getAttribute('data-segment-3d') ?? ''",
        );
        let text = text.as_str()?.to_owned();
        (figure(&text, "strokes") == Some(strokes.to_string())).then_some(text)
    });
    figure(&text, "points")
        .expect("the stroke's points")
        .split('|')
        .map(|point| {
            let numbers: Vec<f64> = point
                .split(',')
                .map(|n| n.parse().unwrap_or_else(|e| panic!("{point}: {e}")))
                .collect();
            <[f64; 3]>::try_from(numbers).unwrap_or_else(|n| panic!("a point of 3: {n:?}"))
        })
        .collect()
}

#[test]
fn a_brush_stroke_dragged_on_the_3d_view_downloads_as_the_desktops_sphere_stroke_at_the_picked_points(
) {
    let scratch = tempfile::tempdir().expect("scratch folder");
    // The picking test's view: the bone surface of the 40³ sample fills the image's centre.
    let fragment =
        "#mode=iso&preset=ct-bone&iso=200&az=120&el=-25&zoom=1.5&volume=40&size=64x64&layout=conventional";
    let (page, server) = open_page(fragment, scratch.path(), [1200, 800]);
    let geometry = Fragment::parse(fragment)
        .expect("fragment")
        .view
        .sample_volume()
        .expect("sample volume")
        .geometry;
    let mut painting = AxialPainting::on_page(page, server, geometry.clone(), "brush");
    let page = &mut painting.page;

    // A drag across the middle of the 3D image (the page fits its 64² image in the view).
    let three_d = view_rect(page, "3d");
    let side = three_d.width().min(three_d.height());
    let image = Rect::from_center_size(three_d.center(), vec2(side, side));
    let at = |fx: f32, fy: f32| -> Pos2 {
        pos2(
            image.left() + image.width() * fx,
            image.top() + image.height() * fy,
        )
        .round()
    };
    let drag: Vec<Pos2> = (0..=4)
        .map(|s| at(0.42 + 0.04 * s as f32, 0.5 + 0.01 * s as f32))
        .collect();
    drag_through(page, &drag);

    let points = stroke_points(page, 1);
    assert!(
        points.len() >= 3,
        "the drag picked only {} surface points: {points:?}",
        points.len()
    );
    let figures = wait_for_figures(page, "the 3D stroke as one undo step", |t| {
        figure(t, "stroke").as_deref() == Some("0") && figure(t, "undo").as_deref() == Some("1")
    });

    // The desktop's sphere stroke at the same points.
    let mut layer = LabelLayer::new_empty(geometry.clone()).expect("native layer");
    let label = layer.segments_mut().add("Segment 1").expect("segment");
    let ball = Brush {
        shape: BrushShape::Sphere,
        diameter_mm: DEFAULT_BRUSH_DIAMETER_MM,
        value_range: None,
    };
    let positions: Vec<DVec3> = points
        .iter()
        .map(|&p| geometry.patient_from_index(DVec3::from(p)))
        .collect();
    for (n, &to) in positions.iter().enumerate() {
        let segment: Vec<DVec3> = positions[..n]
            .last()
            .copied()
            .into_iter()
            .chain([to])
            .collect();
        brush::stroke(&mut layer, &ball, BrushAction::Paint(label), &segment, None)
            .expect("the desktop's sphere stroke");
    }
    let expected = layer_voxels(&layer);
    assert!(
        expected.len() > 50,
        "the sphere stroke paints only {} voxels",
        expected.len()
    );
    assert_eq!(
        figure(&figures, "painted"),
        Some(expected.len().to_string()),
        "{figures}"
    );
    let file = download(page, scratch.path(), "ball.nii.gz");
    let got = labelled_voxels(&file, &geometry);
    assert!(
        got == expected,
        "the download holds {} labelled voxels, the desktop's sphere stroke {}: {} only in the \
         page, {} only in the desktop's",
        got.len(),
        expected.len(),
        got.difference(&expected).count(),
        expected.difference(&got).count()
    );
}
