//! The page's segmentation tools that read the primary's values (issue 52 item 7), on a served
//! store whose bricks the page fetches as the tools need them: a brush stroke limited to a
//! value range (bone, the panel's default) paints exactly what strata-segment's brush with
//! that range paints natively on the phantom's own voxels, its pieces applied as the bricks
//! under them arrive.

use egui::{pos2, Pos2};
use strata_segment::intensity::{DenseIntensity, ValueRange};
use strata_segment::tools::brush::{self, stroke_voxels, Brush, BrushAction};
use strata_segment::LabelLayer;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_viewer_ui::segment_panel::ValueSettings;

use crate::input::cdp::Cdp;
use crate::segment::{
    click_button, download, drag_through, figure, labelled_voxels, layer_voxels, wait_for_figures,
    AxialPainting, AXIAL_BRUSH,
};
use crate::{serve_capturing, TOKEN};

/// The phantom's values (HU) as a dense intensity: what the store's bricks hold, computed
/// from the phantom's definition, not read from the store.
fn phantom_intensity(phantom: &Phantom, dims: [u32; 3]) -> DenseIntensity {
    let [nx, ny, nz] = dims.map(u64::from);
    let mut values = Vec::with_capacity((nx * ny * nz) as usize);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                values.push(f32::from(phantom.hu(i, j, k)));
            }
        }
    }
    DenseIntensity::new(dims, values, "HU").expect("dense phantom")
}

/// A served 96³ phantom (3³ level-0 bricks) and the page on it, a new segmentation open with
/// `tool` chosen; the phantom's own values.
fn page_on_phantom(scratch: &std::path::Path, tool: &str) -> (AxialPainting, DenseIntensity) {
    let path = scratch.join("ct.strata");
    let phantom = Phantom::cube(96);
    phantom
        .write_store(&path, &ImportOptions::default())
        .expect("writing the store");
    let (server, _frames) = serve_capturing(&path);
    let fragment = "#store=ct&mode=mip&preset=ct-soft-tissue&size=64x64&layout=conventional";
    let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
    let page = Cdp::open(&url, scratch, [1200, 900]);
    let geometry = phantom.geometry();
    let intensity = phantom_intensity(&phantom, geometry.dims);
    (
        AxialPainting::on_page(page, server, geometry, tool),
        intensity,
    )
}

/// The voxel (rounded index) under a point of the axial image, as the page takes a click.
fn voxel_under(painting: &AxialPainting, p: Pos2) -> [u32; 3] {
    let index = painting.grid.index_from_patient(painting.to_lps(p)).round();
    [index.x, index.y, index.z].map(|c| c as u32)
}

/// The whole pixels of the axial image, row by row.
fn image_pixels(painting: &AxialPainting) -> Vec<Pos2> {
    let image = painting.image;
    let inner = image.shrink(2.0);
    (0..image.height() as i32)
        .flat_map(|y| (0..image.width() as i32).map(move |x| (x, y)))
        .map(|(x, y)| {
            pos2(
                image.left().round() + x as f32,
                image.top().round() + y as f32,
            )
        })
        .filter(|p| inner.contains(*p))
        .collect()
}

#[test]
fn a_value_range_stroke_in_the_page_paints_what_the_native_stroke_with_the_range_paints() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut painting, intensity) = page_on_phantom(scratch.path(), "brush");
    click_button(&mut painting.page, "only-values");
    // Across the spine (its bony ring ≥ 300 HU, its core 250 HU), on the row through its
    // centre: the pieces cross from one brick row into the next (j = 64).
    let pixels = image_pixels(&painting);
    let at = |target: [u32; 3]| {
        *pixels
            .iter()
            .find(|p| voxel_under(&painting, **p) == target)
            .unwrap_or_else(|| panic!("no pixel over voxel {target:?}"))
    };
    let (start, end) = (at([38, 64, 47]), at([58, 64, 47]));
    let points: Vec<Pos2> = (0..=4)
        .map(|s| pos2(start.x + (end.x - start.x) * s as f32 / 4.0, start.y).round())
        .collect();
    drag_through(&mut painting.page, &points);

    let settings = ValueSettings::default();
    let range = ValueRange::new(settings.range.0, settings.range.1).expect("the default range");
    let brush_with_range = Brush {
        value_range: Some(range),
        ..AXIAL_BRUSH
    };
    let mut layer = LabelLayer::new_empty(painting.geometry.clone()).expect("native layer");
    let label = layer.segments_mut().add("Segment 1").expect("segment");
    brush::stroke(
        &mut layer,
        &brush_with_range,
        BrushAction::Paint(label),
        &painting.positions(&points),
        Some(&intensity),
    )
    .expect("the native stroke");
    let native = layer_voxels(&layer);
    let unlimited = stroke_voxels(&painting.grid, &AXIAL_BRUSH, &painting.positions(&points))
        .expect("the brush model");
    assert!(
        !native.is_empty() && native.len() < unlimited.len(),
        "the range must keep some of the stroke and leave some: {} of {} voxels",
        native.len(),
        unlimited.len()
    );
    wait_for_figures(
        &mut painting.page,
        "the stroke to end as one undo step",
        |t| {
            figure(t, "stroke").as_deref() == Some("0") && figure(t, "undo").as_deref() == Some("1")
        },
    );
    let file = download(&mut painting.page, scratch.path(), "ranged.nii.gz");
    let got = labelled_voxels(&file, &painting.geometry);
    assert!(
        got == native,
        "the download holds {} labelled voxels, the native stroke with the range {}: {} only in \
         the page, {} only in the native layer",
        got.len(),
        native.len(),
        got.difference(&native).count(),
        native.difference(&got).count()
    );
}
