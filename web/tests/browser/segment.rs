//! Segmentation editing in the page (issue 52 item 7) under real input over the DevTools
//! pipe: New segmentation, Brush chosen by a click on its button, a drag across the axial
//! view, Download. The downloaded NIfTI label map, read by strata-segment's own reader, must
//! hold exactly (voxel positions, not counts) what the desktop's brush model
//! (`tools::brush::stroke_voxels`) gives for the drag's screen points mapped through the shared
//! slice mapping (strata-viewer-ui's slice_canvas, strata_slices' frame), on the primary's grid
//! and affine; an eraser stroke then removes exactly its voxels, and Undo brings them back.
//! Keep largest, clicked in the page after two separate strokes, downloads exactly what
//! strata-segment's `remove_islands` leaves of the same strokes painted natively, as one undo
//! step.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use egui::{pos2, Pos2, Rect};
use glam::DVec3;
use serde_json::json;
use strata_segment::tools::brush::{
    self, stroke_voxels, Brush, BrushAction, BrushShape, SlicePlane,
};
use strata_segment::tools::morphology::{remove_islands, Islands};
use strata_segment::{LabelGrid, LabelLayer};
use strata_slices::{SliceFrame, SliceView};
use strata_types::VolumeGeometry;
use strata_viewer_ui::segment_panel::DEFAULT_BRUSH_DIAMETER_MM;
use strata_viewer_ui::slice_canvas::{fraction_at, inner_rect, ZoomPan};
use strata_web::view_state::Fragment;

use crate::input::cdp::Cdp;
use crate::input::{open_page, view_rect};
use crate::PAGE_DEADLINE;

/// The header stores the affine as f32: the placement agrees to f32's precision.
const AFFINE_TOLERANCE_MM: f64 = 1e-4;

/// The rectangle of the Segment section's button `name` (page CSS pixels).
fn button_rect(page: &mut Cdp, name: &str) -> Rect {
    let found = page.wait_for(
        &format!("the Segment section to place its {name} button"),
        PAGE_DEADLINE,
        |page| {
            let v = page.evaluate(
                "(() => { const c = document.getElementById('strata-canvas'); \
                 const r = c.getBoundingClientRect(); \
                 return [r.left, r.top, c.dataset.segmentButtons ?? ''] })()",
            );
            let (left, top) = (v[0].as_f64()? as f32, v[1].as_f64()? as f32);
            let numbers: Vec<f32> = v[2]
                .as_str()?
                .split(';')
                .find_map(|entry| entry.strip_prefix(&format!("{name}:")))?
                .split(',')
                .filter_map(|n| n.parse().ok())
                .collect();
            let [x, y, w, h] = numbers[..] else {
                return None;
            };
            Some(Rect::from_min_size(
                pos2(x + left, y + top),
                egui::vec2(w, h),
            ))
        },
    );
    assert!(
        found.width() > 4.0 && found.height() > 4.0,
        "{name}: {found:?}"
    );
    found
}

/// A click on the section's button `name`, once the button stays put over two frames. The
/// press and the release go out back to back: egui takes a press held longer than its click
/// time (0.8 s) as the start of a drag, and SwiftShader's frames are slow enough that one
/// frame between them would exceed it.
pub(crate) fn click_button(page: &mut Cdp, name: &str) {
    let rect = page.wait_for(
        &format!("the {name} button to stay put"),
        PAGE_DEADLINE,
        |page| {
            let before = button_rect(page, name);
            page.next_frames();
            (button_rect(page, name) == before).then_some(before)
        },
    );
    let at = rect.center().round();
    let (x, y) = (at.x as f64, at.y as f64);
    page.mouse_move(x, y, false);
    for (kind, buttons) in [("mousePressed", 1), ("mouseReleased", 0)] {
        page.command(
            "Input.dispatchMouseEvent",
            json!({ "type": kind, "x": x, "y": y, "button": "left", "buttons": buttons, "clickCount": 1 }),
        );
    }
    page.next_frames();
}

/// The page's `data-segmentation` once `done` accepts it.
pub(crate) fn wait_for_figures(page: &mut Cdp, what: &str, done: impl Fn(&str) -> bool) -> String {
    page.wait_for(what, PAGE_DEADLINE, |page| {
        let text =
            page.evaluate("document.getElementById('strata-canvas')?.dataset.segmentation ?? ''");
        let text = text.as_str()?.to_owned();
        done(&text).then_some(text)
    })
}

pub(crate) fn figure(text: &str, key: &str) -> Option<String> {
    text.split(';')
        .find_map(|entry| entry.strip_prefix(&format!("{key}=")))
        .map(str::to_owned)
}

/// A drag with the left button through `points`, one egui frame per event, as a user's hand
/// moves slower than the page draws.
pub(crate) fn drag_through(page: &mut Cdp, points: &[Pos2]) {
    let first = points[0];
    page.mouse_move(first.x as f64, first.y as f64, false);
    page.mouse_press(first.x as f64, first.y as f64);
    page.next_frames();
    for p in &points[1..] {
        page.mouse_move(p.x as f64, p.y as f64, true);
        page.next_frames();
    }
    let last = points[points.len() - 1];
    page.mouse_release(last.x as f64, last.y as f64);
    page.next_frames();
}

/// Clicks Download and returns the file the page handed to the browser's download, written
/// to `folder` as `name`. The bytes are the Blob behind the anchor's object URL (the page's
/// `URL.createObjectURL` is watched before the click): headless Chromium here does not write
/// an anchor's download into a `Browser.setDownloadBehavior` folder (the page made the Blob,
/// no file arrived in 120 s), so the test reads what the page gave the download instead.
pub(crate) fn download(page: &mut Cdp, folder: &Path, name: &str) -> PathBuf {
    page.evaluate(
        "(() => { if (!window.__downloads) { window.__downloads = []; \
         const original = URL.createObjectURL; \
         URL.createObjectURL = (b) => { if (b.type === 'application/gzip') window.__downloads.push(b); \
         return original.call(URL, b); }; } return true; })()",
    );
    let before = page
        .evaluate("window.__downloads.length")
        .as_u64()
        .unwrap_or(0);
    click_button(page, "download");
    let bytes: Vec<u8> = page.wait_for("the page's download", PAGE_DEADLINE, |page| {
        let js = format!(
            "(async () => {{ const b = window.__downloads[{before}]; if (!b) return null; \
             return Array.from(new Uint8Array(await b.arrayBuffer())); }})()"
        );
        let value = page.evaluate(&js);
        let numbers = value.as_array()?;
        Some(
            numbers
                .iter()
                .map(|n| {
                    n.as_u64()
                        .and_then(|n| u8::try_from(n).ok())
                        .expect("a byte")
                })
                .collect(),
        )
    });
    let file = folder.join(name);
    std::fs::write(&file, bytes).expect("writing the download");
    file
}

/// Every labelled voxel of `layer`, with its label.
pub(crate) fn layer_voxels(layer: &LabelLayer) -> BTreeSet<([u32; 3], u16)> {
    let mut out = BTreeSet::new();
    let [nx, ny, nz] = layer.grid().dims();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let label = layer.get([i, j, k]).expect("a voxel of the grid");
                if label != 0 {
                    out.insert(([i, j, k], label));
                }
            }
        }
    }
    out
}

/// The labelled voxels of a downloaded label map (read by strata-segment's reader), after
/// checking that its grid is the primary's.
pub(crate) fn labelled_voxels(file: &Path, primary: &VolumeGeometry) -> BTreeSet<([u32; 3], u16)> {
    let layer = strata_segment::io::load_label_file(file)
        .unwrap_or_else(|e| panic!("reading the page's download {}: {e}", file.display()));
    let g = layer.grid().geometry();
    assert_eq!(g.dims, primary.dims, "{}: dims", file.display());
    for a in 0..3 {
        assert!(
            (g.spacing_mm[a] - primary.spacing_mm[a]).abs() <= AFFINE_TOLERANCE_MM
                && (g.origin_lps_mm[a] - primary.origin_lps_mm[a]).abs() <= AFFINE_TOLERANCE_MM
                && (0..3).all(|r| {
                    (g.direction[a][r] - primary.direction[a][r]).abs() <= AFFINE_TOLERANCE_MM
                }),
            "{}: the label map's affine {g:?} is not the primary's {primary:?}",
            file.display()
        );
    }
    layer_voxels(&layer)
}

/// The brush both viewers start with, on the axial plane.
pub(crate) const AXIAL_BRUSH: Brush = Brush {
    shape: BrushShape::Disc(SlicePlane::Axial),
    diameter_mm: DEFAULT_BRUSH_DIAMETER_MM,
    value_range: None,
};

/// The page with a new segmentation and the brush chosen, and the desktop's mapping of a
/// screen point on its axial view.
pub(crate) struct AxialPainting {
    pub(crate) page: Cdp,
    _server: strata_service::server::RunningServer,
    pub(crate) geometry: VolumeGeometry,
    pub(crate) grid: LabelGrid,
    pub(crate) frame: SliceFrame,
    /// The axial image on screen (page CSS pixels).
    pub(crate) image: Rect,
}

impl AxialPainting {
    fn open(scratch: &Path) -> Self {
        let fragment = "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&layout=conventional";
        let (page, server) = open_page(fragment, scratch, [1200, 800]);
        let geometry = Fragment::parse(fragment)
            .expect("fragment")
            .view
            .sample_volume()
            .expect("sample volume")
            .geometry;
        AxialPainting::on_page(page, server, geometry, "brush")
    }

    /// A new segmentation on the open page of a volume on `geometry`, the section's `tool`
    /// chosen.
    pub(crate) fn on_page(
        mut page: Cdp,
        server: strata_service::server::RunningServer,
        geometry: VolumeGeometry,
        tool: &str,
    ) -> Self {
        let grid = LabelGrid::new(geometry.clone()).expect("label grid");
        click_button(&mut page, "new");
        wait_for_figures(&mut page, "a new segmentation", |t| {
            figure(t, "segments").as_deref() == Some("1")
        });
        click_button(&mut page, tool);
        // The desktop's mapping of a screen point on the axial view: the view's inner
        // rectangle, the image fitted at zoom 1. The section grew by its rows: the views are
        // read once they stay put over two frames.
        let axial = page.wait_for(
            "the axial view to stay put after the section opened",
            PAGE_DEADLINE,
            |page| {
                let before = view_rect(page, "axial");
                page.next_frames();
                (view_rect(page, "axial") == before).then_some(before)
            },
        );
        let frame = SliceFrame::for_view(SliceView::Axial, &geometry);
        let image = ZoomPan::default().image_rect(inner_rect(axial), frame.extent_mm(&geometry));
        assert!(
            image.width() > 60.0,
            "the axial image {image:?} is too small to aim in"
        );
        AxialPainting {
            page,
            _server: server,
            geometry,
            grid,
            frame,
            image,
        }
    }

    /// The fraction across the image, the frame's index at the crosshair's slice (the centre,
    /// where the page starts it; a tool's drag does not move it), in patient space.
    pub(crate) fn to_lps(&self, p: Pos2) -> DVec3 {
        let dims = self.geometry.dims;
        let (u, v) = fraction_at(self.image, p);
        let (a, d) = self.frame.index_at(dims, u, v);
        let mut index = dims.map(|n| ((n as f64 - 1.0) * 0.5).floor().max(0.0));
        index[self.frame.across_axis] = a;
        index[self.frame.down_axis] = d;
        self.geometry.patient_from_index(DVec3::from(index))
    }

    pub(crate) fn positions(&self, points: &[Pos2]) -> Vec<DVec3> {
        points.iter().map(|&p| self.to_lps(p)).collect()
    }

    /// The voxels the desktop's brush model paints for a drag through `points`.
    fn model(&self, points: &[Pos2]) -> BTreeSet<[u32; 3]> {
        stroke_voxels(&self.grid, &AXIAL_BRUSH, &self.positions(points))
            .expect("the brush model")
            .into_iter()
            .collect()
    }

    /// The whole pixel at fractions `(fx, fy)` of the image.
    fn at(&self, fx: f32, fy: f32) -> Pos2 {
        pos2(
            self.image.left() + self.image.width() * fx,
            self.image.top() + self.image.height() * fy,
        )
        .round()
    }

    /// A horizontal drag from `(fx0, fy)` to `(fx1, fy)` in `steps` whole-pixel steps
    /// (collinear: whichever of its points a frame sees, the swept discs are the same).
    fn horizontal(&self, fx0: f32, fx1: f32, fy: f32, steps: usize) -> Vec<Pos2> {
        let (start, end) = (self.at(fx0, fy), self.at(fx1, fy));
        (0..=steps)
            .map(|s| {
                pos2(
                    start.x + (end.x - start.x) * s as f32 / steps as f32,
                    start.y,
                )
                .round()
            })
            .collect()
    }
}

#[test]
fn a_brush_stroke_downloads_as_the_desktops_brush_paints_it_and_eraser_and_undo_follow() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let downloads = scratch.path();
    let mut painting = AxialPainting::open(scratch.path());
    let stroke = painting.horizontal(0.25, 0.75, 0.4, 4);
    drag_through(&mut painting.page, &stroke);
    let brushed = painting.model(&stroke);
    assert!(
        brushed.len() > 50,
        "the stroke paints {} voxels",
        brushed.len()
    );
    let figures = wait_for_figures(
        &mut painting.page,
        "the stroke to end as one undo step",
        |t| {
            figure(t, "stroke").as_deref() == Some("0") && figure(t, "undo").as_deref() == Some("1")
        },
    );
    assert_eq!(
        figure(&figures, "painted"),
        Some(brushed.len().to_string()),
        "{figures}"
    );
    let file = download(&mut painting.page, downloads, "brushed.nii.gz");
    let expected: BTreeSet<([u32; 3], u16)> = brushed.iter().map(|&v| (v, 1)).collect();
    let got = labelled_voxels(&file, &painting.geometry);
    assert!(
        got == expected,
        "the download holds {} labelled voxels, the desktop's brush {}: {} only in the page, \
         {} only in the model",
        got.len(),
        expected.len(),
        got.difference(&expected).count(),
        expected.difference(&got).count()
    );

    // The eraser across the painted band, downwards through its middle.
    click_button(&mut painting.page, "eraser");
    let erase: Vec<Pos2> = (0..=3)
        .map(|s| {
            pos2(
                painting.at(0.5, 0.0).x,
                painting.at(0.5, 0.3).y + 10.0 * s as f32,
            )
        })
        .collect();
    drag_through(&mut painting.page, &erase);
    let erased = painting.model(&erase);
    let left: BTreeSet<([u32; 3], u16)> = brushed.difference(&erased).map(|&v| (v, 1)).collect();
    assert!(
        left.len() < expected.len() && !left.is_empty(),
        "the eraser stroke must take some of the paint and leave some ({} of {})",
        left.len(),
        expected.len()
    );
    wait_for_figures(&mut painting.page, "the eraser stroke to end", |t| {
        figure(t, "painted") == Some(left.len().to_string())
            && figure(t, "stroke").as_deref() == Some("0")
    });
    let file = download(&mut painting.page, downloads, "erased.nii.gz");
    assert_eq!(
        labelled_voxels(&file, &painting.geometry),
        left,
        "the eraser removes exactly its voxels"
    );

    click_button(&mut painting.page, "undo");
    wait_for_figures(
        &mut painting.page,
        "Undo to bring the erased voxels back",
        |t| figure(t, "redo").as_deref() == Some("1"),
    );
    let file = download(&mut painting.page, downloads, "undone.nii.gz");
    assert!(
        labelled_voxels(&file, &painting.geometry) == expected,
        "after Undo the download is the brush stroke again"
    );
}

#[test]
fn keep_largest_in_the_page_leaves_what_strata_segments_islands_leave() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let mut painting = AxialPainting::open(scratch.path());
    // Two strokes far enough apart (a third of the image, the brush a tenth of it) that they
    // are separate islands, the first much the larger.
    let long = painting.horizontal(0.2, 0.8, 0.3, 4);
    let short = painting.horizontal(0.45, 0.55, 0.75, 2);
    drag_through(&mut painting.page, &long);
    wait_for_figures(&mut painting.page, "the first stroke to end", |t| {
        figure(t, "stroke").as_deref() == Some("0") && figure(t, "undo").as_deref() == Some("1")
    });
    drag_through(&mut painting.page, &short);
    let model: BTreeSet<([u32; 3], u16)> = painting
        .model(&long)
        .union(&painting.model(&short))
        .map(|&v| (v, 1))
        .collect();
    wait_for_figures(&mut painting.page, "the second stroke to end", |t| {
        figure(t, "painted") == Some(model.len().to_string())
            && figure(t, "stroke").as_deref() == Some("0")
    });

    // The same strokes painted natively, then strata-segment's Keep largest.
    let mut layer = LabelLayer::new_empty(painting.geometry.clone()).expect("native layer");
    let label = layer.segments_mut().add("Segment 1").expect("segment");
    for points in [&long, &short] {
        brush::stroke(
            &mut layer,
            &AXIAL_BRUSH,
            BrushAction::Paint(label),
            &painting.positions(points),
            None,
        )
        .expect("the native stroke");
    }
    assert_eq!(
        layer_voxels(&layer),
        model,
        "the native strokes are the model's"
    );
    let (_, removed) =
        remove_islands(&mut layer, label, Islands::KeepLargest).expect("native Keep largest");
    let kept = layer_voxels(&layer);
    assert!(
        removed == 1 && !kept.is_empty() && kept.len() < model.len(),
        "the strokes must be two islands, one removed: {removed} removed, {} of {} voxels kept",
        kept.len(),
        model.len()
    );

    click_button(&mut painting.page, "largest");
    wait_for_figures(
        &mut painting.page,
        "Keep largest to remove the small island",
        |t| figure(t, "painted") == Some(kept.len().to_string()),
    );
    let file = download(&mut painting.page, scratch.path(), "largest.nii.gz");
    let got = labelled_voxels(&file, &painting.geometry);
    assert!(
        got == kept,
        "the download holds {} labelled voxels, strata-segment's Keep largest {}: {} only in \
         the page, {} only in the native layer",
        got.len(),
        kept.len(),
        got.difference(&kept).count(),
        kept.difference(&got).count()
    );

    // One undo step brings the small island back.
    click_button(&mut painting.page, "undo");
    wait_for_figures(
        &mut painting.page,
        "Undo to bring the small island back",
        |t| {
            figure(t, "painted") == Some(model.len().to_string())
                && figure(t, "redo").as_deref() == Some("1")
        },
    );
}
