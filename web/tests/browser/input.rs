//! The page under real input (issue 47): a DevTools-protocol client (../cdp) clicks, drags
//! and presses keys in headless Chromium, and the page's link (`location.hash`, which it
//! rewrites with history.replaceState) must then name what the desktop gives for the same
//! input: its drag mapping and standard views (strata-viewer-ui's orbit), its slice mapping
//! (strata-viewer-ui's slice_canvas and strata_slices).

#[path = "../cdp/mod.rs"]
pub(crate) mod cdp;

use cdp::Cdp;
use egui::{pos2, Rect};
use strata_slices::{SliceFrame, SliceView};
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_viewer_ui::orbit::{orbit_by_drag, StandardView};
use strata_viewer_ui::slice_canvas::{fraction_at, inner_rect, ZoomPan};
use strata_web::view_state::{Fragment, ViewState};

use crate::{serve_capturing, PAGE_DEADLINE, TOKEN};

/// The link's rounding (three decimals) and nothing more.
const LINK_TOLERANCE: f64 = 1e-3;

/// The page at `fragment` on a served tiny store (the page shows its own sample), ready for
/// input: its views placed (the canvas's `data-views`).
pub(crate) fn open_page(
    fragment: &str,
    scratch: &std::path::Path,
    window: [u32; 2],
) -> (Cdp, strata_service::server::RunningServer) {
    let store = scratch.join("tiny.strata");
    Phantom::cube(32)
        .write_store(&store, &ImportOptions::default())
        .expect("writing a tiny store");
    let (server, _frames) = serve_capturing(&store);
    let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
    let mut page = Cdp::open(&url, scratch, window);
    let views = |page: &mut Cdp| {
        page.evaluate("document.getElementById('strata-canvas')?.dataset.views ?? null")
            .as_str()
            .map(str::to_owned)
    };
    page.wait_for("the page to place its views", PAGE_DEADLINE, views);
    // egui sizes its side panel over its first frames: the views may still move.
    page.wait_for(
        "the page's views to stay put over two frames",
        PAGE_DEADLINE,
        |page| {
            let before = views(page);
            page.next_frames();
            (views(page) == before).then_some(())
        },
    );
    (page, server)
}

/// The view rectangle named `name` in page CSS pixels (the canvas's offset added).
pub(crate) fn view_rect(page: &mut Cdp, name: &str) -> Rect {
    let text = page.evaluate(
        "(() => { const c = document.getElementById('strata-canvas'); const r = c.getBoundingClientRect(); \
         return [r.left, r.top, c.dataset.views]; })()",
    );
    let (left, top) = (
        text[0].as_f64().expect("canvas left"),
        text[1].as_f64().expect("canvas top"),
    );
    let views = text[2].as_str().expect("data-views").to_owned();
    let numbers: Vec<f32> = views
        .split(';')
        .find_map(|entry| entry.strip_prefix(&format!("{name}:")))
        .unwrap_or_else(|| panic!("the page placed no {name} view: {views}"))
        .split(',')
        .map(|n| n.parse().unwrap_or_else(|e| panic!("{views}: {e}")))
        .collect();
    let [x, y, w, h] = numbers[..] else {
        panic!("{views}: not x,y,w,h");
    };
    Rect::from_min_size(pos2(x + left as f32, y + top as f32), egui::vec2(w, h))
}

/// Waits for the page's link to satisfy `done` and returns its view.
fn wait_for_link(page: &mut Cdp, what: &str, done: impl Fn(&ViewState) -> bool) -> ViewState {
    page.wait_for(what, PAGE_DEADLINE, |page| {
        let hash = page.evaluate("location.hash");
        let view = Fragment::parse(hash.as_str()?).ok()?.view;
        done(&view).then_some(view)
    })
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= LINK_TOLERANCE
}

/// A drag of (60, 30) CSS pixels across the 3D view turns the link's azimuth and elevation by
/// what the desktop's drag gives for that drag in a view of that height (180° per view
/// height). The page's old mapping (0.4° a pixel whatever the view's size) misses it.
#[test]
fn a_drag_across_the_pages_3d_view_turns_it_as_the_desktops_drag_does() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, _server) = open_page(
        "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&az=30&el=15",
        scratch.path(),
        [480, 400],
    );
    let rect = view_rect(&mut page, "3d");
    let from = rect.center().round();
    let drag = [60.0, 30.0];
    page.drag(
        [from.x as f64, from.y as f64],
        [from.x as f64 + drag[0], from.y as f64 + drag[1]],
        3,
    );
    let expected = orbit_by_drag(30.0, 15.0, drag, rect.height() as f64);
    let view = wait_for_link(&mut page, "the link to show the dragged view", |v| {
        v.azimuth_deg != 30.0
    });
    assert!(
        close(view.azimuth_deg, expected.0) && close(view.elevation_deg, expected.1),
        "after a drag of {drag:?} in a {}-pixel-tall view the link has az {} el {}; the \
         desktop's drag gives {expected:?}",
        rect.height(),
        view.azimuth_deg,
        view.elevation_deg,
    );
}

/// The desktop's standard-view keys work in the page: "A" shows the anterior view, "L" the
/// patient's left, each at the orbit angles the desktop's StandardView names.
#[test]
fn the_standard_view_keys_show_the_desktops_standard_views_in_the_page() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, _server) = open_page(
        "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&az=30&el=15",
        scratch.path(),
        [480, 400],
    );
    // Keys go to the focused canvas, as after a user's click on it.
    let rect = view_rect(&mut page, "3d");
    let centre = rect.center().round();
    page.click(centre.x as f64, centre.y as f64);
    page.evaluate("document.getElementById('strata-canvas').focus()");
    for (key, code, standard) in [
        ("a", "KeyA", StandardView::Anterior),
        ("l", "KeyL", StandardView::Left),
    ] {
        page.key(key, code);
        let (az, el) = standard.angles_deg();
        wait_for_link(
            &mut page,
            &format!("the link to show the {standard:?} view after key {key:?}"),
            |v| close(v.azimuth_deg, az) && close(v.elevation_deg, el),
        );
    }
}

/// A click on the axial view moves the link's crosshair (`cursor=`) to the voxel the
/// desktop's slice mapping gives for that screen point: the view's inner rectangle, the image
/// fitted in it at zoom 1, the fraction across it, the axial frame's index.
#[test]
fn a_click_on_the_pages_axial_view_moves_the_crosshair_to_the_desktops_voxel() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let fragment = "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&layout=conventional";
    // Wide enough that the axial view, a third of the width beside the side panel, shows
    // its image at a size a click can aim in.
    let (mut page, _server) = open_page(fragment, scratch.path(), [1200, 800]);
    let geometry = Fragment::parse(fragment)
        .expect("fragment")
        .view
        .sample_volume()
        .expect("sample volume")
        .geometry;
    let axial = view_rect(&mut page, "axial");
    let frame = SliceFrame::for_view(SliceView::Axial, &geometry);
    let image = ZoomPan::default().image_rect(inner_rect(axial), frame.extent_mm(&geometry));
    assert!(
        image.width() > 60.0 && image.height() > 60.0,
        "the axial image {image:?} in {axial:?} is too small to aim in"
    );
    // A point away from the centre (where the crosshair starts) in both directions, on
    // whole pixels (the browser's mouse events carry whole CSS pixels).
    let at = pos2(
        image.left() + image.width() * 0.3,
        image.top() + image.height() * 0.7,
    )
    .round();
    let (u, v) = fraction_at(image, at);
    let dims = geometry.dims;
    let (a, d) = frame.index_at(dims, u, v);
    let start = dims.map(|n| ((n as f64 - 1.0) * 0.5).floor().max(0.0));
    let mut expected = start;
    expected[frame.across_axis] = a.clamp(0.0, dims[frame.across_axis] as f64 - 1.0);
    expected[frame.down_axis] = d.clamp(0.0, dims[frame.down_axis] as f64 - 1.0);
    assert!(
        (0..3).any(|i| !close(expected[i], start[i])),
        "the click must move the crosshair for the test to mean anything"
    );
    page.click(at.x as f64, at.y as f64);
    let what = format!(
        "the link's cursor to leave the centre {start:?} after a click at {at:?} on the axial \
         view {axial:?} (expected {expected:?})"
    );
    let view = wait_for_link(&mut page, &what, |v| {
        v.cursor
            .is_some_and(|c| (0..3).any(|i| !close(c[i], start[i])))
    });
    let cursor = view.cursor.expect("a cursor");
    assert!(
        (0..3).all(|i| close(cursor[i], expected[i])),
        "a click at {at:?} on the axial view ({axial:?}) put the link's cursor at {cursor:?}; \
         the desktop's mapping gives {expected:?}"
    );
}
