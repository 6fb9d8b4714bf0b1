//! Measurements in the page (issue 47): a ruler dragged, an angle clicked and a box ROI
//! dragged on the page's axial view with real pointer events (the DevTools pipe, ../cdp), and
//! a link carrying measurements. Each figure the page publishes (`data-measurements`,
//! web/src/measure.rs) must equal what the desktop's code gives natively:
//! strata-viewer-ui's slice mapping for the screen points, its `distance_mm`, `angle_deg`, and
//! `roi_stats` over strata-slices' assembler's image of the same slice.

use std::time::Duration;

use egui::{pos2, Pos2, Rect};
use strata_render::BrickSource;
use strata_slices::{SliceAssembler, SliceError, SliceFrame, SliceImage, SliceRequest, SliceView};
use strata_types::OctreeLayout;
use strata_viewer_ui::measurements::{angle_deg, distance_mm, roi_stats, SliceContext};
use strata_viewer_ui::slice_canvas::{inner_rect, ZoomPan};
use strata_web::view_state::{Fragment, ViewState};

use crate::input::cdp::Cdp;
use crate::input::{open_page, view_rect, wait_for_link};
use crate::PAGE_DEADLINE;

/// The page's sample (40³, 1 mm voxels) with the 3D view over the three slices; at this window
/// the axial image is large enough to aim in, at level 0.
const FRAGMENT: &str = "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&layout=conventional";
const WINDOW: [u32; 2] = [1200, 800];

/// The page's points and millimetres against the desktop's mapping of the same screen points:
/// both are the same f64 arithmetic on the same f32 pointer positions, so only a canvas offset
/// that is not a whole CSS pixel could part them, by far less than this; a wrong mapping is off
/// by a voxel or more.
const POINT_TOLERANCE: f64 = 1e-3;
/// The page's region statistics against `roi_stats` run natively on the same points and slice:
/// the same sums in the same order (wasm32's f64 is IEEE as x86-64's, and the page writes
/// each figure so that it reads back exactly), so only last-bit differences are allowed;
/// a voxel more or less moves the mean by more than 1e-3 here.
const STATS_RELATIVE_TOLERANCE: f64 = 1e-9;

/// One line of the page's `data-measurements`.
#[derive(Debug)]
struct Published {
    kind: String,
    points: Vec<[f64; 3]>,
    figures: Vec<f64>,
    text: String,
}

fn parse_published(text: &str) -> Vec<Published> {
    text.lines()
        .filter(|l| !l.is_empty())
        .map(|line| {
            let fields: Vec<&str> = line.splitn(5, '|').collect();
            let [_id, kind, points, figures, text] = fields[..] else {
                panic!("not ID|KIND|POINTS|FIGURES|TEXT: {line}");
            };
            let number = |n: &str| -> f64 {
                n.parse()
                    .unwrap_or_else(|e| panic!("{line}: `{n}` is not a number: {e}"))
            };
            let points = points
                .split(';')
                .map(|p| {
                    let v: Vec<f64> = p.split(',').map(number).collect();
                    [v[0], v[1], v[2]]
                })
                .collect();
            let figures = figures
                .split(',')
                .filter(|f| !f.is_empty())
                .map(number)
                .collect();
            Published {
                kind: kind.into(),
                points,
                figures,
                text: text.into(),
            }
        })
        .collect()
}

/// Waits until the page publishes measurements that satisfy `done`.
fn wait_for_measurements(
    page: &mut Cdp,
    what: &str,
    done: impl Fn(&[Published]) -> bool,
) -> Vec<Published> {
    page.wait_for(what, PAGE_DEADLINE, |page| {
        let text =
            page.evaluate("document.getElementById('strata-canvas')?.dataset.measurements ?? null");
        let published = parse_published(text.as_str()?);
        done(&published).then_some(published)
    })
}

/// The tool the page has chosen and the points placed of the measurement being drawn
/// (`data-measure-tool`).
fn tool_state(page: &mut Cdp) -> Option<(String, usize)> {
    let state =
        page.evaluate("document.getElementById('strata-canvas')?.dataset.measureTool ?? null");
    let (label, points) = state.as_str()?.rsplit_once(',')?;
    Some((label.to_owned(), points.parse().ok()?))
}

/// Clicks at `at` until `taken` says the page took the click: egui counts a press and release
/// more than 0.8 s apart as no click, and on two busy cores the frames between them can take
/// that long. A click the page did take is never repeated.
fn click_until(page: &mut Cdp, at: (f64, f64), what: &str, taken: impl Fn(&mut Cdp) -> bool) {
    for _attempt in 0..5 {
        page.click(at.0, at.1);
        let until = std::time::Instant::now() + Duration::from_secs(20);
        while std::time::Instant::now() < until {
            if taken(page) {
                // Two clicks closer than a double-click's delay would read as one.
                std::thread::sleep(Duration::from_millis(600));
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
    panic!(
        "the page did not take five clicks at {at:?} for {what}; its console:\n{}",
        page.console()
    );
}

/// Clicks the side panel's button of the tool labelled `label` (the page publishes where its
/// tool buttons are, `data-measure-tools`).
fn choose_tool(page: &mut Cdp, label: &str) {
    let at = page.wait_for(
        &format!("the page to show the {label} tool"),
        PAGE_DEADLINE,
        |page| {
            let found = page.evaluate(
                "(() => { const c = document.getElementById('strata-canvas'); const r = c.getBoundingClientRect(); \
                 return [r.left, r.top, c.dataset.measureTools ?? null]; })()",
            );
            let (left, top) = (found[0].as_f64()?, found[1].as_f64()?);
            let tools = found[2].as_str()?.to_owned();
            let numbers: Vec<f64> = tools
                .split(';')
                .find_map(|entry| entry.strip_prefix(&format!("{label}:")))?
                .split(',')
                .map(|n| n.parse().ok())
                .collect::<Option<_>>()?;
            let [x, y, w, h] = numbers[..] else {
                return None;
            };
            Some(((left + x + w / 2.0).round(), (top + y + h / 2.0).round()))
        },
    );
    click_until(page, at, &format!("the {label} tool"), |page| {
        tool_state(page).is_some_and(|(chosen, _)| chosen == label)
    });
}

/// The sample's geometry, the page's start crosshair, and the axial view's frame and image
/// rectangle (zoom 1, as the page opens) in the view placed at `axial`.
struct Axial {
    view: ViewState,
    geometry: strata_render::VolumeGeometry,
    frame: SliceFrame,
    cursor: [f64; 3],
    image: Rect,
}

impl Axial {
    fn of_page(page: &mut Cdp, fragment: &str) -> Axial {
        let view = Fragment::parse(fragment).expect("fragment").view;
        let geometry = view.sample_volume().expect("sample volume").geometry;
        let frame = SliceFrame::for_view(SliceView::Axial, &geometry);
        let axial = view_rect(page, "axial");
        let image = ZoomPan::default().image_rect(inner_rect(axial), frame.extent_mm(&geometry));
        assert!(
            image.width() > 100.0 && image.height() > 100.0,
            "the axial image {image:?} in {axial:?} is too small to aim in"
        );
        let cursor = geometry
            .dims
            .map(|d| ((d as f64 - 1.0) * 0.5).floor().max(0.0));
        Axial {
            view,
            geometry,
            frame,
            cursor,
            image,
        }
    }

    /// The screen point at fractions (u, v) of the image, on whole CSS pixels (what mouse
    /// events carry).
    fn at(&self, u: f32, v: f32) -> Pos2 {
        pos2(
            self.image.left() + self.image.width() * u,
            self.image.top() + self.image.height() * v,
        )
        .round()
    }

    /// The desktop's voxel for a screen point: strata-viewer-ui's slice mapping.
    fn index_at(&self, at: Pos2) -> [f64; 3] {
        let context = SliceContext {
            view: SliceView::Axial,
            frame: self.frame,
            geometry: &self.geometry,
            mapping: Default::default(),
            cursor: self.cursor,
        };
        context.index_at(self.image, at)
    }

    /// strata-slices' assembler's image of the axial slice at the crosshair, at `level`, from
    /// the sample made natively (the bricks the page hands its own assembler).
    fn native_slice(&self, level: u8) -> SliceImage {
        let volume = self.view.sample_volume().expect("sample volume");
        let mut assembler = SliceAssembler::new(OctreeLayout::new(self.geometry.dims), 64 << 20);
        let request = SliceRequest {
            view: SliceView::Axial,
            frame: self.frame,
            position: self.cursor[self.frame.normal_axis],
            level,
        };
        assembler
            .assemble_with(request, |id| {
                Ok::<_, SliceError>(
                    volume
                        .brick(id.level, id.coords)
                        .expect("in-memory brick")
                        .to_vec(),
                )
            })
            .expect("the desktop's slice")
    }

    /// The page's region statistics (`voxels,mean,sd,min,max,area,level`) equal `roi_stats`
    /// run natively on the region's points over the assembler's image of its slice.
    fn assert_stats_are_the_desktops(&self, region: &Published, ellipse: bool) {
        let [voxels, mean, sd, min, max, area_mm2, level] = region.figures[..] else {
            panic!("no statistics: {region:?}");
        };
        let image = self.native_slice(level as u8);
        let volume = self.view.sample_volume().expect("sample volume");
        let expected = roi_stats(
            &image,
            &self.geometry,
            volume.mapping,
            ellipse,
            region.points[0],
            region.points[1],
        )
        .expect("voxels in the region");
        assert!(
            expected.voxels > 10,
            "the region is too small to say much: {expected:?}"
        );
        assert_eq!(voxels as u64, expected.voxels, "{region:?} vs {expected:?}");
        assert_eq!((min, max), (expected.min, expected.max), "{region:?}");
        let close = |a: f64, b: f64| (a - b).abs() <= STATS_RELATIVE_TOLERANCE * (1.0 + b.abs());
        assert!(
            close(mean, expected.mean)
                && close(sd, expected.sd)
                && close(area_mm2, expected.area_mm2),
            "the page's {region:?} vs the desktop's {expected:?}"
        );
    }
}

fn near(a: [f64; 3], b: [f64; 3]) -> bool {
    (0..3).all(|i| (a[i] - b[i]).abs() <= POINT_TOLERANCE)
}

/// A ruler dragged across the page's axial view measures what the desktop's `distance_mm`
/// gives between the voxels the shared slice mapping gives for the drag's two screen points.
#[test]
fn a_ruler_dragged_on_the_pages_axial_view_measures_the_desktops_millimetres() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, _server) = open_page(FRAGMENT, scratch.path(), WINDOW);
    let axial = Axial::of_page(&mut page, FRAGMENT);
    choose_tool(&mut page, "Ruler");
    let (from, to) = (axial.at(0.2, 0.3), axial.at(0.75, 0.65));
    page.drag(
        [from.x as f64, from.y as f64],
        [to.x as f64, to.y as f64],
        4,
    );
    let (a, b) = (axial.index_at(from), axial.index_at(to));
    let expected = distance_mm(&axial.geometry, a, b);
    assert!(
        expected > 10.0,
        "the drag must span the slice: {expected} mm"
    );
    let published = wait_for_measurements(&mut page, "the page's ruler", |m| !m.is_empty());
    let ruler = &published[0];
    assert_eq!(
        (published.len(), ruler.kind.as_str()),
        (1, "ruler"),
        "{published:?}"
    );
    assert!(
        near(ruler.points[0], a) && near(ruler.points[1], b),
        "dragged from {from:?} to {to:?}: the page's ruler {:?}, the desktop's mapping {a:?} \
         {b:?}",
        ruler.points
    );
    assert!(
        (ruler.figures[0] - expected).abs() <= POINT_TOLERANCE,
        "the page measures {} mm, the desktop {expected} mm",
        ruler.figures[0]
    );
    assert_eq!(ruler.text, format!("Ruler {expected:.1} mm"));
    // The link carries it.
    wait_for_link(&mut page, "the link to carry the ruler", |v| {
        v.measurements.len() == 1
    });
}

/// Three clicks with the angle tool (the second the vertex) make the angle the desktop's
/// `angle_deg` gives for the three voxels under them.
#[test]
fn an_angle_clicked_on_the_pages_axial_view_is_the_desktops_angle() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, _server) = open_page(FRAGMENT, scratch.path(), WINDOW);
    let axial = Axial::of_page(&mut page, FRAGMENT);
    choose_tool(&mut page, "Angle");
    let clicks = [axial.at(0.8, 0.3), axial.at(0.3, 0.5), axial.at(0.7, 0.85)];
    for (placed, at) in clicks.iter().enumerate() {
        // Each click places a point (the third completes the angle): one that is not taken
        // is clicked again, one that is never twice.
        let measured = |page: &mut Cdp| {
            page.evaluate("document.getElementById('strata-canvas')?.dataset.measurements ?? ''")
                .as_str()
                .is_some_and(|m| !m.is_empty())
        };
        click_until(
            &mut page,
            (at.x as f64, at.y as f64),
            &format!("the angle's point {}", placed + 1),
            |page| match placed {
                2 => measured(page),
                _ => tool_state(page).is_some_and(|(_, points)| points == placed + 1),
            },
        );
    }
    let [a, vertex, b] = clicks.map(|at| axial.index_at(at));
    let expected = angle_deg(&axial.geometry, a, vertex, b);
    let published = wait_for_measurements(&mut page, "the page's angle", |m| !m.is_empty());
    let angle = &published[0];
    assert_eq!(
        (published.len(), angle.kind.as_str()),
        (1, "angle"),
        "{published:?}"
    );
    assert!(
        near(angle.points[0], a) && near(angle.points[1], vertex) && near(angle.points[2], b),
        "clicked at {clicks:?}: the page's angle {:?}, the desktop's mapping {:?}",
        angle.points,
        [a, vertex, b]
    );
    assert!(
        (angle.figures[0] - expected).abs() <= POINT_TOLERANCE,
        "the page's angle is {}°, the desktop's {expected}°",
        angle.figures[0]
    );
    assert_eq!(angle.text, format!("Angle {expected:.1}°"));
}

/// A box ROI dragged on the page's axial view has the statistics `roi_stats` gives natively
/// over the assembler's image of the same slice of the same sample: the same voxel count,
/// minimum and maximum, and mean, SD and area to the last bits.
#[test]
fn a_box_roi_on_the_pages_axial_view_has_the_desktops_statistics() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, _server) = open_page(FRAGMENT, scratch.path(), WINDOW);
    let axial = Axial::of_page(&mut page, FRAGMENT);
    choose_tool(&mut page, "Box ROI");
    let (from, to) = (axial.at(0.25, 0.3), axial.at(0.6, 0.7));
    page.drag(
        [from.x as f64, from.y as f64],
        [to.x as f64, to.y as f64],
        4,
    );
    let published = wait_for_measurements(&mut page, "the page's box with statistics", |m| {
        m.first().is_some_and(|r| !r.figures.is_empty())
    });
    let region = &published[0];
    assert_eq!(region.kind, "box-axial", "{published:?}");
    assert!(
        near(region.points[0], axial.index_at(from)) && near(region.points[1], axial.index_at(to)),
        "dragged from {from:?} to {to:?}: the page's box {:?}",
        region.points
    );
    axial.assert_stats_are_the_desktops(region, false);
}

/// A link with measurements (`m=`) opens with them in the page: the ruler measures the
/// desktop's millimetres between its points, the ellipse gets the desktop's statistics from
/// the slice once it is shown, and the page's link still carries them as written.
#[test]
fn a_link_with_measurements_opens_with_them_in_the_page() {
    let measurements = "r:5,6,19,30,25.5,19;ea:10,10,19,24.5,22,19";
    let fragment = format!("{FRAGMENT}&m={measurements}");
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, _server) = open_page(&fragment, scratch.path(), WINDOW);
    let axial = Axial::of_page(&mut page, &fragment);
    assert_eq!(
        (axial.frame.normal_axis, axial.cursor[2]),
        (2, 19.0),
        "the link's points lie on the axial slice the page opens at"
    );
    let published = wait_for_measurements(&mut page, "the link's measurements, measured", |m| {
        m.len() == 2 && !m[1].figures.is_empty()
    });
    let expected = distance_mm(&axial.geometry, [5.0, 6.0, 19.0], [30.0, 25.5, 19.0]);
    assert_eq!(published[0].kind, "ruler");
    assert_eq!(published[0].figures, [expected], "{published:?}");
    assert_eq!(published[1].kind, "ellipse-axial");
    assert_eq!(
        published[1].points,
        [[10.0, 10.0, 19.0], [24.5, 22.0, 19.0]]
    );
    axial.assert_stats_are_the_desktops(&published[1], true);
    let hash = page.evaluate("location.hash");
    let hash = hash.as_str().expect("the page's link");
    assert!(hash.contains(&format!("m={measurements}")), "{hash}");
}
