//! Measurements in the page (issue 47): a ruler dragged, an angle clicked and a box ROI
//! dragged on the page's axial view with real pointer events (the DevTools pipe, ../cdp), and
//! a link carrying measurements. Each figure the page publishes (`data-measurements`,
//! web/src/measure.rs) must equal what the desktop's code gives natively:
//! strata-viewer-ui's slice mapping for the screen points, its `distance_mm`, `angle_deg`, and
//! `roi_stats` over strata-slices' assembler's image of the same slice. A ruler clicked in the
//! page's 3D view measures what the desktop's picks at the same pixels give.

use std::time::Duration;

use egui::{pos2, Pos2, Rect};
use strata_render::{BrickSource, CacheConfig, GpuContext, OffscreenRenderer};
use strata_slices::{SliceAssembler, SliceError, SliceFrame, SliceImage, SliceRequest, SliceView};
use strata_types::OctreeLayout;
use strata_viewer_ui::measurements::{
    angle_deg, distance_mm, from_link_text, roi_stats, to_link_text, Measurement, Shape,
    SliceContext,
};
use strata_viewer_ui::picking::{frame_pixel, picked_index};
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

/// Clicks at `at` until `taken` says the page took the click. Press and release go out back
/// to back (`Cdp::quick_click`): egui counts a press and release more than 0.8 s apart as no
/// click, and on two busy cores the frames `Cdp::click` waits between them took that long five
/// times running (this stop's browser run beside a CI rehearsal). A click the page did take is
/// never repeated.
pub(crate) fn click_until(
    page: &mut Cdp,
    at: (f64, f64),
    what: &str,
    taken: impl Fn(&mut Cdp) -> bool,
) {
    for _attempt in 0..5 {
        page.quick_click(at.0, at.1);
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

/// One page (one Chromium and one pipeline compilation: the browser tests share two cores)
/// draws on its axial view, with real pointer events, in turn:
/// - a ruler, dragged: it measures what the desktop's `distance_mm` gives between the voxels
///   the shared slice mapping gives for the drag's two screen points;
/// - an angle, by three clicks (the second the vertex): the desktop's `angle_deg` of the three
///   voxels under them;
/// - a box ROI, dragged: the statistics `roi_stats` gives natively over the assembler's image
///   of the same slice of the same sample (the same voxel count, minimum and maximum; mean, SD
///   and area to the last bits);
///
/// and the page's link then carries all three.
#[test]
fn a_ruler_an_angle_and_a_box_roi_drawn_in_the_page_measure_what_the_desktops_functions_give() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, _server) = open_page(FRAGMENT, scratch.path(), WINDOW);
    let axial = Axial::of_page(&mut page, FRAGMENT);
    a_dragged_ruler_measures_the_desktops_millimetres(&mut page, &axial);
    three_clicks_make_the_desktops_angle(&mut page, &axial);
    a_dragged_box_has_the_desktops_statistics(&mut page, &axial);
    wait_for_link(&mut page, "the link to carry the three measurements", |v| {
        v.measurements.len() == 3
    });
}

/// The first measurement: a ruler (see the test above).
fn a_dragged_ruler_measures_the_desktops_millimetres(page: &mut Cdp, axial: &Axial) {
    choose_tool(page, "Ruler");
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
    let published = wait_for_measurements(page, "the page's ruler", |m| !m.is_empty());
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
}

/// The second: an angle by three clicks, after the ruler.
fn three_clicks_make_the_desktops_angle(page: &mut Cdp, axial: &Axial) {
    choose_tool(page, "Angle");
    let clicks = [axial.at(0.8, 0.3), axial.at(0.3, 0.5), axial.at(0.7, 0.85)];
    for (placed, at) in clicks.iter().enumerate() {
        // Each click places a point (the third completes the angle): one that is not taken
        // is clicked again, one that is never twice.
        let measured = |page: &mut Cdp| {
            page.evaluate("document.getElementById('strata-canvas')?.dataset.measurements ?? ''")
                .as_str()
                .is_some_and(|m| parse_published(m).len() == 2)
        };
        click_until(
            page,
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
    let published = wait_for_measurements(page, "the page's angle", |m| m.len() == 2);
    let angle = &published[1];
    assert_eq!(
        (published.len(), angle.kind.as_str()),
        (2, "angle"),
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

/// The third: a box ROI, after the ruler and the angle.
fn a_dragged_box_has_the_desktops_statistics(page: &mut Cdp, axial: &Axial) {
    choose_tool(page, "Box ROI");
    let (from, to) = (axial.at(0.25, 0.3), axial.at(0.6, 0.7));
    page.drag(
        [from.x as f64, from.y as f64],
        [to.x as f64, to.y as f64],
        4,
    );
    let published = wait_for_measurements(page, "the page's box with statistics", |m| {
        m.get(2).is_some_and(|r| !r.figures.is_empty())
    });
    let region = &published[2];
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

/// The sample's iso surface in the 3D view over the slices (the picking test's view): every
/// pixel near the image's centre sees the surface at a depth well apart from its neighbours'.
const FRAGMENT_3D: &str =
    "#mode=iso&preset=ct-bone&iso=200&az=120&el=-25&zoom=1.5&volume=40&size=64x64&layout=conventional";

/// How far the page's 3D pick may lie from the native one, in voxels: the picking test's bound
/// (web/tests/browser/picking.rs: SwiftShader and lavapipe run the same WGSL in f32 and may
/// move the refined iso surface by a tiny fraction of a voxel; a pixel over moves it by far
/// more, checked below).
const PICK_TOLERANCE_VOXELS: f64 = 0.05;

/// Where to click to hit `pixel`'s centre of a `size` frame shown in `image`, on whole CSS
/// pixels (what mouse events carry); None where the rounded point falls in another pixel.
fn click_point_of(image: Rect, size: [u32; 2], pixel: [u32; 2]) -> Option<Pos2> {
    let at = pos2(
        image.left() + (pixel[0] as f32 + 0.5) / size[0] as f32 * image.width(),
        image.top() + (pixel[1] as f32 + 0.5) / size[1] as f32 * image.height(),
    )
    .round();
    let back = frame_pixel(
        (at.x - image.left()) / image.width(),
        (at.y - image.top()) / image.height(),
        size,
    )?;
    (back == pixel).then_some(at)
}

/// A ruler placed by two clicks in the page's 3D view (the Ruler tool chosen in the side
/// panel, as on the desktop) has for its ends what the desktop picks at the same two pixels of
/// the same view drawn natively (strata-viewer-ui's `picked_index` over lavapipe's pick
/// depth), each within [`PICK_TOLERANCE_VOXELS`], and so measures the desktop's `distance_mm`
/// within the sum of the two ends' tolerance (√3 × 0.05 voxels each, times the largest
/// spacing). The page's link then carries it (`m=`, read by the desktop's parser, at the
/// link's two decimals), and the desktop's link of its own ruler opens in the page with the
/// desktop's millimetres to the last bit.
#[test]
fn a_ruler_clicked_in_the_pages_3d_view_measures_what_the_desktops_picks_give_and_links_carry_it() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let view = Fragment::parse(FRAGMENT_3D).expect("fragment").view;
    let volume = view.sample_volume().expect("sample volume");
    let geometry = volume.geometry.clone();
    let size = [64u32, 64];

    // The same view drawn natively (the f32 brick format the browser must use), with the
    // pick depth of every pixel.
    let gpu = GpuContext::headless().expect("a Vulkan adapter (lavapipe)");
    let mut renderer = OffscreenRenderer::new(
        &gpu,
        &volume,
        &view.transfer_function(),
        0,
        CacheConfig {
            force_fallback_format: true,
            ..CacheConfig::default()
        },
    )
    .expect("native renderer");
    let camera = view.camera(&geometry);
    let settings = view.settings(&geometry, size[0], size[1]);
    let native = renderer
        .render(&gpu, &volume, &camera, &settings)
        .expect("native frame");
    let depth = |[x, y]: [u32; 2]| native.depth[(y * size[0] + x) as usize];
    let pick = |pixel: [u32; 2]| picked_index(&camera, &geometry, pixel, size, depth(pixel));
    // A pixel on the surface whose neighbours are on it too (a pick there does not fall off
    // an edge), nearest to `around`.
    let on_surface = |[x, y]: [u32; 2]| {
        (x.saturating_sub(1)..=x + 1)
            .all(|i| (y.saturating_sub(1)..=y + 1).all(|j| depth([i, j]).is_finite()))
    };

    let (mut page, server) = open_page(FRAGMENT_3D, scratch.path(), WINDOW);
    let three_d = view_rect(&mut page, "3d");
    let side = three_d.width().min(three_d.height());
    let image = Rect::from_center_size(three_d.center(), egui::vec2(side, side));
    let surface_click = |around: [u32; 2]| -> (Pos2, [u32; 2]) {
        (0..12i32)
            .flat_map(|r| {
                (-r..=r)
                    .flat_map(move |dx| (-r..=r).map(move |dy| (dx, dy)))
                    .filter(move |(dx, dy)| dx.abs().max(dy.abs()) == r)
            })
            .map(|(dx, dy)| {
                [
                    (around[0] as i32 + dx).clamp(1, 62) as u32,
                    (around[1] as i32 + dy).clamp(1, 62) as u32,
                ]
            })
            .filter(|&p| on_surface(p))
            .find_map(|p| click_point_of(image, size, p).map(|at| (at, p)))
            .unwrap_or_else(|| panic!("no pixel of the iso surface near {around:?}"))
    };
    let ends = [surface_click([25, 32]), surface_click([39, 30])];
    let [a, b] = ends.map(|(_, pixel)| pick(pixel).expect("the surface's depth"));
    let expected = distance_mm(&geometry, a, b);
    let largest_spacing = geometry.spacing_mm.iter().fold(0.0f64, |m, s| m.max(*s));
    let length_tolerance_mm = 2.0 * 3f64.sqrt() * PICK_TOLERANCE_VOXELS * largest_spacing;
    assert!(
        expected > 20.0 * length_tolerance_mm,
        "the two picks are only {expected} mm apart: the test could not tell a wrong pick"
    );
    let neighbour = pick([ends[0].1[0] + 1, ends[0].1[1]]).expect("the neighbour's depth");
    let apart = (0..3)
        .map(|i| (a[i] - neighbour[i]).abs())
        .fold(0.0, f64::max);
    assert!(
        apart > 4.0 * PICK_TOLERANCE_VOXELS,
        "one pixel over picks only {apart} voxels away: the test could not tell pixels apart"
    );

    choose_tool(&mut page, "Ruler");
    let (first, second) = (ends[0].0, ends[1].0);
    click_until(
        &mut page,
        (first.x as f64, first.y as f64),
        "the ruler's first end in 3D",
        |page| tool_state(page).is_some_and(|(_, points)| points == 1),
    );
    click_until(
        &mut page,
        (second.x as f64, second.y as f64),
        "the ruler's second end in 3D",
        |page| {
            page.evaluate("document.getElementById('strata-canvas')?.dataset.measurements ?? ''")
                .as_str()
                .is_some_and(|m| parse_published(m).len() == 1)
        },
    );
    let published = wait_for_measurements(&mut page, "the page's 3D ruler", |m| m.len() == 1);
    let ruler = &published[0];
    assert_eq!(ruler.kind, "ruler", "{published:?}");
    let off = |p: [f64; 3], q: [f64; 3]| (0..3).map(|i| (p[i] - q[i]).abs()).fold(0.0, f64::max);
    assert!(
        off(ruler.points[0], a) <= PICK_TOLERANCE_VOXELS
            && off(ruler.points[1], b) <= PICK_TOLERANCE_VOXELS,
        "clicked at {first:?} and {second:?} (pixels {:?}, {:?}): the page's ruler {:?}, the \
         desktop's picks {a:?} {b:?}",
        ends[0].1,
        ends[1].1,
        ruler.points
    );
    println!(
        "3D ruler: the page {} mm, the desktop {expected} mm",
        ruler.figures[0]
    );
    assert!(
        (ruler.figures[0] - expected).abs() <= length_tolerance_mm,
        "the page's 3D ruler measures {} mm, the desktop's picks {expected} mm",
        ruler.figures[0]
    );

    // The page's link carries it: the desktop's parser reads the page's ends at two decimals.
    let linked = wait_for_link(&mut page, "the link to carry the 3D ruler", |v| {
        v.measurements.len() == 1
    });
    let Shape::Distance {
        a: link_a,
        b: link_b,
    } = linked.measurements[0].shape
    else {
        panic!(
            "the link's measurement is not a ruler: {:?}",
            linked.measurements
        );
    };
    assert!(
        off(link_a, ruler.points[0]) <= 0.005 + 1e-9
            && off(link_b, ruler.points[1]) <= 0.005 + 1e-9,
        "the link's ruler {link_a:?} {link_b:?}, the page's {:?}",
        ruler.points
    );
    drop(page);
    drop(server);

    // And the desktop's link of its own ruler opens in the page with the desktop's length.
    let desktop_ruler = Measurement {
        id: 0,
        shape: Shape::Distance { a, b },
    };
    let text = to_link_text(&[desktop_ruler]).expect("a ruler's link text");
    let read = from_link_text(&text).expect("the desktop reads its own link");
    let Shape::Distance { a: ra, b: rb } = read[0].shape else {
        panic!("{read:?}");
    };
    let scratch = tempfile::tempdir().expect("a second scratch folder");
    let (mut page, _server) = open_page(&format!("{FRAGMENT_3D}&m={text}"), scratch.path(), WINDOW);
    let published = wait_for_measurements(&mut page, "the desktop's 3D ruler in the page", |m| {
        m.len() == 1
    });
    assert_eq!(
        (published[0].kind.as_str(), published[0].figures.as_slice()),
        ("ruler", [distance_mm(&geometry, ra, rb)].as_slice()),
        "{published:?}"
    );
}
