//! Segmentation editing in the page (issue 52 item 7) under real input over the DevTools
//! pipe: New segmentation, Brush chosen by a click on its button, a drag across the axial
//! view, Download. The downloaded NIfTI label map, read by strata-segment's own reader, must
//! hold exactly (voxel positions, not counts) what the desktop's brush model
//! (`tools::brush::stroke_voxels`) gives for the drag's screen points mapped through the shared
//! slice mapping (strata-viewer-ui's slice_canvas, strata_slices' frame), on the primary's grid
//! and affine; an eraser stroke then removes exactly its voxels, and Undo brings them back.
//! Keep largest, clicked in the page after two separate strokes, downloads exactly what
//! strata-segment's `remove_islands` leaves of the same strokes painted natively, as one undo
//! step. After a stroke, Download SEG read back by strata-segment's SEG reader and Download
//! OME-Zarr unzipped and opened by its OME-Zarr labels reader equal the NIfTI download.

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
use strata_slices::oblique::{default_extent_mm, ObliquePlane};
use strata_slices::{SliceFrame, SliceView};
use strata_types::VolumeGeometry;
use strata_viewer_ui::segment_panel::DEFAULT_BRUSH_DIAMETER_MM;
use strata_viewer_ui::slice_canvas::{fraction_at, inner_rect, ZoomPan};
use strata_web::view_state::Fragment;

use crate::input::cdp::Cdp;
use crate::input::{close, open_page, view_rect, wait_for_link};
use crate::keys::{key_with, right_drag, CTRL};
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
                 if (!c) return [null, null, '']; \
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
    download_as(page, folder, name, "download", "application/gzip")
}

/// Clicks the Segment section's `button` and returns the download it makes (a Blob of type
/// `mime`), written to `folder` as `name`; see [`download`].
fn download_as(page: &mut Cdp, folder: &Path, name: &str, button: &str, mime: &str) -> PathBuf {
    page.evaluate(
        "(() => { if (!window.__downloads) { window.__downloads = []; \
         const original = URL.createObjectURL; \
         URL.createObjectURL = (b) => { if (b.type && b.type.startsWith('application/')) window.__downloads.push(b); \
         return original.call(URL, b); }; } return true; })()",
    );
    let before = page
        .evaluate("window.__downloads.length")
        .as_u64()
        .unwrap_or(0);
    click_button(page, button);
    let bytes: Vec<u8> = page.wait_for("the page's download", PAGE_DEADLINE, |page| {
        let js = format!(
            "(async () => {{ const b = window.__downloads[{before}]; if (!b) return null; \
             return [b.type, Array.from(new Uint8Array(await b.arrayBuffer()))]; }})()"
        );
        let value = page.evaluate(&js);
        let pair = value.as_array()?;
        assert_eq!(
            pair.first().and_then(|t| t.as_str()),
            Some(mime),
            "the {button} button's download type"
        );
        let numbers = pair.get(1)?.as_array()?;
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

/// Every labelled voxel of `layer`, with its label. Each brick is read once: a layer loaded
/// from a file decodes a brick on every `get`, which made this loop take minutes on a 96³ grid.
pub(crate) fn layer_voxels(layer: &LabelLayer) -> BTreeSet<([u32; 3], u16)> {
    let mut out = BTreeSet::new();
    let mut bricks = std::collections::HashMap::new();
    let [nx, ny, nz] = layer.grid().dims();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let (key, at) = layer.grid().brick_of([i, j, k]);
                let brick = bricks
                    .entry(key)
                    .or_insert_with(|| layer.brick(key).expect("a brick of the grid"));
                let label = brick[at];
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
    assert_on_grid(&layer, primary, file);
    layer_voxels(&layer)
}

/// Asserts that `layer`, read from `file`, lies on the primary's grid (dims, affine).
fn assert_on_grid(layer: &LabelLayer, primary: &VolumeGeometry, file: &Path) {
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

/// Unzips the page's OME-Zarr download into `folder` (every entry under the zip's root, as
/// `unzip` would: read from the zip's central directory and each entry's local header, as
/// APPNOTE 6.3 lays them out, stored entries only) and returns the label image's folder,
/// `labels/segmentation`.
fn unzip_label_image(zip_file: &Path, folder: &Path) -> PathBuf {
    let bytes = std::fs::read(zip_file).expect("reading the zip");
    let u16_at = |at: usize| usize::from(u16::from_le_bytes([bytes[at], bytes[at + 1]]));
    let u32_at = |at: usize| {
        u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]) as usize
    };
    let end = bytes.len() - 22;
    assert_eq!(u32_at(end), 0x0605_4b50, "the zip's end record");
    let (count, mut at) = (u16_at(end + 10), u32_at(end + 16));
    for _ in 0..count {
        assert_eq!(
            u32_at(at),
            0x0201_4b50,
            "a central directory header at {at}"
        );
        assert_eq!(u16_at(at + 10), 0, "a stored entry");
        let size = u32_at(at + 20);
        let name_len = u16_at(at + 28);
        let name = std::str::from_utf8(&bytes[at + 46..at + 46 + name_len]).expect("a UTF-8 name");
        assert!(
            !name.starts_with('/') && !name.split('/').any(|p| p == ".."),
            "{name}: a relative path"
        );
        let local = u32_at(at + 42);
        assert_eq!(u32_at(local), 0x0403_4b50, "{name}: its local header");
        let data = local + 30 + u16_at(local + 26) + u16_at(local + 28);
        let path = folder.join(name);
        std::fs::create_dir_all(path.parent().expect("a parent")).expect("unzip: folder");
        std::fs::write(&path, &bytes[data..data + size]).expect("unzip: file");
        at += 46 + name_len + u16_at(at + 30) + u16_at(at + 32);
    }
    assert!(
        folder.join("zarr.json").is_file() && folder.join("labels/zarr.json").is_file(),
        "the zip's root is the image group with its labels group"
    );
    folder.join("labels/segmentation")
}

#[test]
fn a_brush_stroke_downloads_as_dicom_seg_and_zipped_omezarr_equal_to_the_nifti() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let mut painting = AxialPainting::open(scratch.path());
    let stroke = painting.horizontal(0.25, 0.75, 0.4, 4);
    drag_through(&mut painting.page, &stroke);
    wait_for_figures(
        &mut painting.page,
        "the stroke to end as one undo step",
        |t| {
            figure(t, "stroke").as_deref() == Some("0") && figure(t, "undo").as_deref() == Some("1")
        },
    );
    let nifti = download(&mut painting.page, scratch.path(), "brushed.nii.gz");
    let expected = labelled_voxels(&nifti, &painting.geometry);
    let brushed: BTreeSet<([u32; 3], u16)> = painting
        .model(&stroke)
        .into_iter()
        .map(|v| (v, 1))
        .collect();
    assert!(
        expected == brushed && expected.len() > 50,
        "the NIfTI download is the brush model's {} voxels (holds {})",
        brushed.len(),
        expected.len()
    );
    // The page's segment table: New segmentation's one segment, as strata-segment adds it.
    let mut table_layer = LabelLayer::new_empty(painting.geometry.clone()).expect("layer");
    table_layer
        .segments_mut()
        .add("Segment 1")
        .expect("a segment");
    let table = table_layer.segments().clone();

    // DICOM SEG, read by strata-segment's SEG reader: the same voxels on the same grid, the
    // segment's name, its colour through CIELab to within one step.
    let seg = download_as(
        &mut painting.page,
        scratch.path(),
        "brushed.dcm",
        "download-seg",
        "application/dicom",
    );
    assert_eq!(
        labelled_voxels(&seg, &painting.geometry),
        expected,
        "the SEG download's voxels are the NIfTI download's"
    );
    let seg_layer = strata_segment::io::load_label_file(&seg).expect("the SEG loads");
    for s in table.iter() {
        let back = seg_layer
            .segments()
            .get(s.value)
            .unwrap_or_else(|| panic!("segment {} in the SEG", s.value));
        assert_eq!(back.name, s.name);
        assert!(
            (0..3).all(|c| (i32::from(back.rgb[c]) - i32::from(s.rgb[c])).abs() <= 1),
            "the SEG's colour {:?}, the segment's {:?}",
            back.rgb,
            s.rgb
        );
    }

    // OME-Zarr labels as a zip, unzipped natively and opened by the OME-Zarr labels reader:
    // the same voxels and grid, the segment table exactly.
    let zip_file = download_as(
        &mut painting.page,
        scratch.path(),
        "brushed.ome.zarr.zip",
        "download-zarr",
        "application/zip",
    );
    let label_dir = unzip_label_image(&zip_file, &scratch.path().join("unzipped.zarr"));
    let zarr_layer = strata_segment::io::load_omezarr_labels(&label_dir)
        .unwrap_or_else(|e| panic!("opening {}: {e}", label_dir.display()));
    assert_on_grid(&zarr_layer, &painting.geometry, &label_dir);
    assert_eq!(
        layer_voxels(&zarr_layer),
        expected,
        "the OME-Zarr download's voxels are the NIfTI download's"
    );
    assert_eq!(zarr_layer.segments(), &table);
}

/// One history for the page (issue 52 item 7): a window drag (the right button on the axial
/// view), then a brush stroke; Ctrl+Z undoes the stroke (the labels go, the window stays),
/// Ctrl+Z again the window; Ctrl+Y redoes the window, Ctrl+Y again the stroke, its voxels as
/// they were (count and checksum).
#[test]
fn ctrl_z_undoes_a_stroke_then_the_window_drag_before_it_and_ctrl_y_redoes_them_in_order() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let mut painting = AxialPainting::open(scratch.path());
    let stroke = painting.horizontal(0.25, 0.75, 0.4, 4);
    let brushed = painting.model(&stroke).len();
    let page = &mut painting.page;
    let before = wait_for_link(page, "the link to carry the slices' window", |v| {
        v.window.is_some()
    });
    let same_window = |a: Option<[f64; 2]>, b: Option<[f64; 2]>| match (a, b) {
        (Some(a), Some(b)) => close(a[0], b[0]) && close(a[1], b[1]),
        _ => false,
    };
    page.evaluate("document.getElementById('strata-canvas').focus()");
    let axial = view_rect(page, "axial");
    right_drag(page, axial.center().round(), [60.0, 0.0]);
    let edited = wait_for_link(page, "the link to show the dragged window", |v| {
        v.window
            .is_some_and(|w| !close(w[1], before.window.expect("window")[1]))
    });
    drag_through(page, &stroke);
    let painted = wait_for_figures(page, "the stroke to end as one undo step", |t| {
        figure(t, "stroke").as_deref() == Some("0") && figure(t, "undo").as_deref() == Some("1")
    });
    assert_eq!(
        figure(&painted, "painted"),
        Some(brushed.to_string()),
        "{painted}"
    );
    let checksum = figure(&painted, "checksum");

    key_with(page, "z", "KeyZ", 90, CTRL);
    wait_for_figures(page, "Ctrl+Z to undo the stroke", |t| {
        figure(t, "painted").as_deref() == Some("0") && figure(t, "redo").as_deref() == Some("1")
    });
    wait_for_link(
        page,
        "the window to stay dragged after the first Ctrl+Z",
        |v| same_window(v.window, edited.window),
    );

    key_with(page, "z", "KeyZ", 90, CTRL);
    wait_for_link(page, "a second Ctrl+Z to put the window back", |v| {
        same_window(v.window, before.window)
    });
    let figures = wait_for_figures(page, "the labels after the second Ctrl+Z", |_| true);
    assert_eq!(
        figure(&figures, "painted").as_deref(),
        Some("0"),
        "{figures}"
    );

    key_with(page, "y", "KeyY", 89, CTRL);
    wait_for_link(page, "Ctrl+Y to drag the window again", |v| {
        same_window(v.window, edited.window)
    });
    let figures = wait_for_figures(page, "the labels after the first Ctrl+Y", |_| true);
    assert_eq!(
        figure(&figures, "painted").as_deref(),
        Some("0"),
        "the first Ctrl+Y redoes the window, not the stroke: {figures}"
    );

    key_with(page, "y", "KeyY", 89, CTRL);
    wait_for_figures(page, "a second Ctrl+Y to paint the stroke again", |t| {
        figure(t, "painted") == Some(brushed.to_string()) && figure(t, "checksum") == checksum
    });
    wait_for_link(page, "the window to stay dragged", |v| {
        same_window(v.window, edited.window)
    });
}

/// A brush stroke on the page's oblique view (the left button with the brush chosen paints
/// instead of turning the plane): the NIfTI download holds exactly the voxels the desktop's
/// oblique brush model gives (`stroke_voxels` with a disc in the plane spanned by the view's
/// screen right and down, the desktop's `oblique::brush_plane`) for the drag's points mapped
/// through the shared plane (strata_slices::oblique: `patient_at` of the fraction across the
/// view's square image).
#[test]
fn a_brush_stroke_on_the_oblique_view_downloads_as_the_desktops_oblique_brush_paints_it() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let angles = [30.0, -20.0, 0.0];
    let fragment = "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&layout=conventional\
                    &oblique=30,-20";
    let (mut page, _server) = open_page(fragment, scratch.path(), [1200, 800]);
    let geometry = Fragment::parse(fragment)
        .expect("fragment")
        .view
        .sample_volume()
        .expect("sample volume")
        .geometry;
    let grid = LabelGrid::new(geometry.clone()).expect("label grid");
    click_button(&mut page, "new");
    wait_for_figures(&mut page, "a new segmentation", |t| {
        figure(t, "segments").as_deref() == Some("1")
    });
    click_button(&mut page, "brush");
    let rect = page.wait_for(
        "the oblique view to stay put after the section opened",
        PAGE_DEADLINE,
        |page| {
            let before = view_rect(page, "oblique");
            page.next_frames();
            (view_rect(page, "oblique") == before).then_some(before)
        },
    );
    // The page's square image in the view (oblique_view.rs, the desktop's margins).
    let inner = Rect::from_min_max(
        rect.min + egui::vec2(18.0, 38.0),
        rect.max - egui::vec2(18.0, 36.0),
    );
    let image = Rect::from_center_size(
        inner.center(),
        egui::Vec2::splat(inner.width().min(inner.height()).max(1.0)),
    );
    assert!(
        image.width() > 60.0,
        "the oblique image {image:?} is too small to aim in"
    );
    // The plane through the crosshair, where the page starts it (the volume's centre voxel).
    let cursor = geometry
        .dims
        .map(|n| ((n as f64 - 1.0) * 0.5).floor().max(0.0));
    let plane = ObliquePlane::from_orientation_deg(
        geometry.patient_from_index(DVec3::from(cursor)),
        default_extent_mm(&geometry),
        angles,
    );
    let at = |fx: f32, fy: f32| {
        pos2(
            image.left() + image.width() * fx,
            image.top() + image.height() * fy,
        )
        .round()
    };
    let (start, end) = (at(0.3, 0.45), at(0.7, 0.45));
    let stroke: Vec<Pos2> = (0..=4)
        .map(|s| pos2(start.x + (end.x - start.x) * s as f32 / 4.0, start.y).round())
        .collect();
    let positions: Vec<DVec3> = stroke
        .iter()
        .map(|&p| {
            let (u, w) = fraction_at(image, p);
            plane.patient_at(u, w)
        })
        .collect();
    let brush = Brush {
        shape: BrushShape::Disc(SlicePlane::Oblique {
            centre_lps: plane.centre,
            u: plane.right,
            v: plane.down,
        }),
        diameter_mm: DEFAULT_BRUSH_DIAMETER_MM,
        value_range: None,
    };
    let model: BTreeSet<([u32; 3], u16)> = stroke_voxels(&grid, &brush, &positions)
        .expect("the oblique brush model")
        .into_iter()
        .map(|v| (v, 1))
        .collect();
    assert!(model.len() > 50, "the stroke paints {} voxels", model.len());

    drag_through(&mut page, &stroke);
    let figures = wait_for_figures(
        &mut page,
        "the oblique stroke to end as one undo step",
        |t| {
            figure(t, "stroke").as_deref() == Some("0") && figure(t, "undo").as_deref() == Some("1")
        },
    );
    let view = wait_for_link(&mut page, "the link's oblique angles", |v| {
        v.oblique.is_some()
    });
    let turned = view.oblique.expect("oblique");
    assert!(
        (0..3).all(|a| (turned[a] - angles[a]).abs() < 1e-6),
        "the stroke turned the plane to {turned:?}"
    );
    let file = download(&mut page, scratch.path(), "oblique.nii.gz");
    let got = labelled_voxels(&file, &geometry);
    assert!(
        got == model,
        "the download holds {} labelled voxels, the desktop's oblique brush {} ({figures}): {} \
         only in the page, {} only in the model",
        got.len(),
        model.len(),
        got.difference(&model).count(),
        model.difference(&got).count()
    );
}

/// A stroke, Ctrl+Z, then a window drag (a view edit): the page's history can no longer redo
/// the stroke (a new step clears redo), and the layer's own history must agree: it keeps no
/// redo (`redo=0`, not an entry nothing can reach), and Ctrl+Y paints nothing back.
#[test]
fn a_view_edit_after_a_segment_undo_leaves_the_layer_no_redo_the_page_cannot_reach() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let mut painting = AxialPainting::open(scratch.path());
    let stroke = painting.horizontal(0.25, 0.75, 0.4, 4);
    let page = &mut painting.page;
    let before = wait_for_link(page, "the link to carry the slices' window", |v| {
        v.window.is_some()
    });
    page.evaluate("document.getElementById('strata-canvas').focus()");
    drag_through(page, &stroke);
    wait_for_figures(page, "the stroke to end as one undo step", |t| {
        figure(t, "stroke").as_deref() == Some("0") && figure(t, "undo").as_deref() == Some("1")
    });
    key_with(page, "z", "KeyZ", 90, CTRL);
    wait_for_figures(page, "Ctrl+Z to undo the stroke", |t| {
        figure(t, "painted").as_deref() == Some("0") && figure(t, "redo").as_deref() == Some("1")
    });
    let axial = view_rect(page, "axial");
    right_drag(page, axial.center().round(), [60.0, 0.0]);
    wait_for_link(page, "the link to show the dragged window", |v| {
        v.window
            .is_some_and(|w| !close(w[1], before.window.expect("window")[1]))
    });
    let figures = wait_for_figures(page, "the layer to drop the unreachable redo", |t| {
        figure(t, "redo").as_deref() == Some("0")
    });
    assert_eq!(
        figure(&figures, "undo").as_deref(),
        Some("0"),
        "the undone stroke is not an undo step either: {figures}"
    );
    key_with(page, "y", "KeyY", 89, CTRL);
    page.next_frames();
    page.next_frames();
    let figures = wait_for_figures(page, "the labels after Ctrl+Y", |_| true);
    assert_eq!(
        (
            figure(&figures, "painted").as_deref(),
            figure(&figures, "redo").as_deref()
        ),
        (Some("0"), Some("0")),
        "Ctrl+Y after the view edit must redo nothing: {figures}"
    );
}
