//! The page's oblique view (issue 47, web/src/oblique_view.rs) against the desktop's: opened
//! on a served store with an `oblique=` link, it draws, once its bricks are in, the image
//! strata-slices' shared resampling gives for the same plane, size, level and window (the
//! desktop's `resample`, fed here by the desktop's blocking client on the same server); and a
//! drag across it turns the plane as the desktop's drag mapping (`turned_by_drag`) says, in the
//! link and in the image it then draws.

use std::sync::mpsc;
use std::sync::Arc;

use strata_service::CapturedFrame;
use strata_slices::oblique::{
    default_extent_mm, oblique_rgba, resample, LevelBricks, ObliquePlane, ObliqueRequest, Resampled,
};
use strata_slices::{ColourMap, SliceError, Window};
use strata_source::VolumeSource;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_types::BrickId;

use crate::input::cdp::Cdp;
use crate::input::{view_rect, wait_for_link};
use crate::{desktop_client, metric, serve_capturing, PAGE_DEADLINE, TOKEN};

/// The largest share of pixels that may differ from the desktop's image. The plane's axes come
/// from sines and cosines, which the browser's libm (wasm32) and the native one may round
/// differently in the last bit; a pixel then changes only where its value sits on an 8-bit
/// rounding step or its centre on the volume's edge: a handful, never a region.
const MAX_DIFFERING_SHARE: f64 = 0.002;

/// The link's rounding of the angles (1e-3 degrees, 1.7e-5 rad) and a margin, on unit vectors.
const LINK_AXIS_TOLERANCE: f64 = 1e-4;

/// The desktop's client's bricks as the shared resampling reads them (blocking, as the
/// desktop's reader thread does).
struct ClientBricks<'a>(&'a strata_service::client::RemoteSource);

impl LevelBricks for ClientBricks<'_> {
    type Error = SliceError;
    fn brick(&mut self, id: BrickId) -> Result<Option<Arc<Vec<u16>>>, SliceError> {
        let brick = self
            .0
            .read_brick(id)
            .expect("the desktop's client reads the brick");
        Ok(Some(Arc::new(brick)))
    }
}

/// The next oblique image the page posts of the plane at `angles` (degrees; the capture's
/// metrics carry three decimals); its 3D frame, slice image and images of other planes are
/// passed over.
pub(crate) fn next_oblique_capture(
    frames: &mpsc::Receiver<CapturedFrame>,
    page: &Cdp,
    angles: [f64; 3],
) -> CapturedFrame {
    let of_plane = |frame: &CapturedFrame| {
        ["oblique_yaw", "oblique_pitch", "oblique_roll"]
            .iter()
            .zip(angles)
            .all(|(name, angle)| metric(frame, name).is_some_and(|m| (m - angle).abs() <= 2e-3))
    };
    let until = std::time::Instant::now() + PAGE_DEADLINE;
    loop {
        let left = until.saturating_duration_since(std::time::Instant::now());
        match frames.recv_timeout(left) {
            Ok(frame) if of_plane(&frame) => return frame,
            Ok(_) => continue,
            Err(_) => panic!(
                "the page posted no oblique image within {PAGE_DEADLINE:?}; its console:\n{}",
                page.console()
            ),
        }
    }
}

/// The desktop's image of `plane` at the posted image's size and level, coloured with the
/// link's window: strata-slices' resampling and window/level step.
pub(crate) fn desktop_image(
    client: &strata_service::client::RemoteSource,
    plane: ObliquePlane,
    posted: &CapturedFrame,
    window: Window,
) -> Vec<u8> {
    let header = client.header();
    let level = metric(posted, "oblique_level").expect("the capture names its level") as u8;
    let request = ObliqueRequest {
        plane,
        width: posted.width as usize,
        height: posted.height as usize,
        level,
    };
    let image = match resample(
        &header.geometry,
        &header.layout,
        &mut ClientBricks(client),
        &request,
        usize::MAX,
    )
    .expect("the desktop's resampling")
    {
        Resampled::Complete(image) => image,
        Resampled::Incomplete { missing } => panic!("blocking reads left {missing:?} missing"),
    };
    oblique_rgba(
        &image.values,
        window,
        ColourMap::Grey,
        header.value_mapping.mapping,
    )
}

/// The page's posted image against the desktop's, within [`MAX_DIFFERING_SHARE`], and
/// showing something (the plane crosses the phantom).
pub(crate) fn assert_same_image(what: &str, posted: &CapturedFrame, desktop: &[u8], console: &str) {
    assert_eq!(posted.rgba.len(), desktop.len(), "{what}: image sizes");
    let differing = posted
        .rgba
        .chunks(4)
        .zip(desktop.chunks(4))
        .filter(|(a, b)| a != b)
        .count();
    let pixels = desktop.len() / 4;
    let distinct: std::collections::BTreeSet<u8> = desktop.chunks(4).map(|p| p[0]).collect();
    println!(
        "{what}: {}×{} at level {:?}, {differing} of {pixels} pixels differ from the desktop's \
         resampling, {} grey levels",
        posted.width,
        posted.height,
        metric(posted, "oblique_level"),
        distinct.len()
    );
    assert!(
        distinct.len() > 8,
        "{what}: the image shows nearly nothing: {distinct:?}"
    );
    assert!(
        differing as f64 <= MAX_DIFFERING_SHARE * pixels as f64,
        "{what}: {differing} of {pixels} pixels differ from the desktop's image; console:\n{console}"
    );
}

/// An `oblique=30,-20` link on a served 96³ CT phantom (crosshair and window in the link): the
/// page's oblique view, in the 2×2's sagittal place, posts the image the desktop's shared
/// resampling gives for that plane through that crosshair at the posted size and level,
/// coloured with that window; the size and level are the shared choice for a square of that
/// many pixels. Then a drag of 40 CSS pixels to the right across it: the link's plane is the
/// start plane turned by the desktop's drag mapping (`turned_by_drag(40, 0)`: moves along one
/// screen axis turn about one fixed axis, so how the moves fall into frames does not matter),
/// and the image it posts once the pointer is up is the desktop's resampling of that plane.
#[test]
fn the_pages_oblique_view_draws_and_turns_as_the_desktops() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let path = scratch.path().join("ct.strata");
    Phantom::cube(96)
        .write_store(&path, &ImportOptions::default())
        .expect("writing the store");
    let (server, frames) = serve_capturing(&path);
    let (angles, cursor, window) = ([30.0, -20.0, 0.0], [40.5, 50.25, 47.0], [40.0, 400.0]);
    let fragment = format!(
        "#store=ct&mode=mip&preset=ct-soft-tissue&size=64x64&capture=1&oblique={},{}\
         &cursor={},{},{}&window={},{}",
        angles[0], angles[1], cursor[0], cursor[1], cursor[2], window[0], window[1]
    );
    let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
    let mut page = Cdp::open(&url, scratch.path(), [1000, 800]);

    let client = desktop_client(&server, "ct");
    let geometry = client.header().geometry.clone();
    let levels = client.header().layout.level_count();
    let window = Window::new(window[0], window[1]);
    let start = ObliquePlane::from_orientation_deg(
        geometry.patient_from_index(cursor),
        default_extent_mm(&geometry),
        angles,
    );
    let first = next_oblique_capture(&frames, &page, angles);
    let console = page.console();
    assert_eq!(first.width, first.height, "the oblique image is square");
    let level = metric(&first, "oblique_level").expect("level") as u8;
    let shared = ObliqueRequest::for_view(start, first.width as f64, &geometry, levels);
    assert_eq!(
        (shared.width, shared.level),
        (first.width as usize, level),
        "the page's size and level are not the shared choice for its pixels"
    );
    let desktop = desktop_image(&client, start, &first, window);
    assert_same_image("the linked plane", &first, &desktop, &console);

    // The drag: four moves of 10 CSS pixels (each its own frame), from left of the image's
    // centre, so the view keeps the pointer throughout.
    let rect = view_rect(&mut page, "oblique");
    let from = (rect.center() - egui::vec2(30.0, 0.0)).round();
    let drag_px = 40.0;
    page.drag(
        [from.x as f64, from.y as f64],
        [from.x as f64 + drag_px, from.y as f64],
        4,
    );
    let expected = start.turned_by_drag(drag_px, 0.0);
    let view = wait_for_link(
        &mut page,
        "the link to show the turned oblique plane",
        |v| {
            v.oblique
                .is_some_and(|a| (a[0] - angles[0]).abs() > 1e-3 || (a[1] - angles[1]).abs() > 1e-3)
        },
    );
    let linked = ObliquePlane::from_orientation_deg(
        start.centre,
        start.extent_mm,
        view.oblique.expect("the oblique view is still shown"),
    );
    let off = (linked.right - expected.right)
        .length()
        .max((linked.down - expected.down).length());
    assert!(
        off < LINK_AXIS_TOLERANCE,
        "after a drag of {drag_px} px the link's plane {:?} is {off} off the desktop's \
         turned_by_drag {expected:?}",
        view.oblique
    );
    let turned = next_oblique_capture(&frames, &page, expected.orientation_deg());
    let console = page.console();
    let desktop = desktop_image(&client, expected, &turned, window);
    assert_same_image("the dragged plane", &turned, &desktop, &console);
}
