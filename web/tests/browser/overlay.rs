//! The page's overlay (issue 47 item 3): a second served store drawn over the slices and the
//! oblique view, opened from the link (`overlay=NAME`), against the desktop's overlay code
//! (strata-viewer-ui's overlay, which the desktop's reader thread runs) on the same stores.
//!
//! The page's slice capture (`capture=1`) waits for the axial view's overlay and composites it
//! over the slice with the shared compositing (premultiplied "over", what the painters do); the
//! test computes the same slice natively (the desktop's assembler and window/level, then the
//! shared sampler on the overlay's level-0 bricks read by the desktop's client, the shared
//! colouring and compositing) and asks for the images to be equal byte for byte: the page and
//! the desktop run one f64 program on the same bricks, so no tolerance is needed. The oblique
//! view's capture is compared the same way with the oblique test's tolerance (its plane's axes
//! come from sines and cosines, which wasm32's libm and the native one may round apart).

use std::path::Path;
use std::sync::{mpsc, Arc};

use strata_render::VolumeGeometry;
use strata_service::server::{find_stores, start};
use strata_service::{CapturedFrame, FrameSink, ServeOptions};
use strata_slices::oblique::{default_extent_mm, LevelBricks, ObliquePlane};
use strata_slices::{SliceError, SliceFrame, SliceRequest, SliceView, Window};
use strata_source::VolumeSource;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_types::BrickId;
use strata_viewer_ui::overlay::{
    composite_over, kind_of_store, label_table_of, oblique_pixels, sample, slice_pixels,
    OverlayGrids, OverlayKind, OverlayLink, OverlayStyle, Sampled,
};

use super::input::cdp::Cdp;
use super::oblique::{assert_same_image, desktop_image, next_oblique_capture};
use super::{
    assert_same_slice, capture_slice, desktop_axial_slice, desktop_client, web_viewer, TOKEN,
};

/// The label map's stripes: labels 0..=4 whose boundaries cross at odd places.
fn label_of(i: u32, j: u32, k: u32) -> f64 {
    ((i / 3 + 2 * (j / 4) + k / 5) % 5) as f64
}

/// A continuous field (a PET-like ramp) in physical units.
fn field(i: u32, j: u32, k: u32) -> f64 {
    3.0 * i as f64 + 5.0 * j as f64 - 2.0 * k as f64 + 40.25
}

/// Writes an axis-aligned NRRD over the primary's box on another grid: 40³ voxels of 1.37
/// primary voxels each, shifted by a fraction of a voxel, so no overlay voxel lines up with a
/// primary voxel.
fn write_overlay_nrrd(
    path: &Path,
    primary: &VolumeGeometry,
    float: bool,
    value: fn(u32, u32, u32) -> f64,
) {
    let dims = [40u32; 3];
    let spacing = primary.spacing_mm.map(|s| s * 1.37);
    let origin: [f64; 3] = std::array::from_fn(|a| {
        primary.origin_lps_mm[a] + [0.3, -0.45, 0.2][a] * primary.spacing_mm[a]
    });
    let mut bytes = format!(
        "NRRD0004\ntype: {}\ndimension: 3\nsizes: 40 40 40\n\
         space: left-posterior-superior\n\
         space directions: ({},0,0) (0,{},0) (0,0,{})\n\
         space origin: ({},{},{})\nencoding: raw\nendian: little\n\n",
        if float { "float" } else { "uint8" },
        spacing[0],
        spacing[1],
        spacing[2],
        origin[0],
        origin[1],
        origin[2]
    )
    .into_bytes();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let v = value(i, j, k);
                if float {
                    bytes.extend_from_slice(&(v as f32).to_le_bytes());
                } else {
                    bytes.push(v as u8);
                }
            }
        }
    }
    std::fs::write(path, bytes).expect("writing the overlay NRRD");
}

/// Imports `nrrd` as the store `store`.
fn import(nrrd: &Path, store: &Path) {
    let opened = strata_storage::readers::open_source(nrrd, &Default::default())
        .expect("reading the overlay NRRD");
    strata_storage::import::import_source(opened, store, &ImportOptions::default())
        .expect("importing the overlay NRRD");
}

/// A server for the stores at `paths` with the page, the test token and a sink for captures.
fn serve_stores(
    paths: &[std::path::PathBuf],
) -> (
    strata_service::server::RunningServer,
    mpsc::Receiver<CapturedFrame>,
) {
    let (frames_in, frames) = mpsc::channel::<CapturedFrame>();
    let frames_in = std::sync::Mutex::new(frames_in);
    let server = start(
        find_stores(paths).expect("stores found"),
        ServeOptions {
            web_viewer: Some(Arc::new(web_viewer())),
            test_frame_sink: Some(FrameSink(Arc::new(move |frame| {
                if let Ok(sender) = frames_in.lock() {
                    let _ = sender.send(frame);
                }
            }))),
            token: Some(TOKEN.into()),
            ..ServeOptions::default()
        },
    )
    .expect("server starts");
    (server, frames)
}

/// The desktop's blocking reads as level bricks (always resident).
pub(crate) struct Blocking<'a>(pub(crate) &'a dyn VolumeSource);

impl LevelBricks for Blocking<'_> {
    type Error = SliceError;
    fn brick(&mut self, id: BrickId) -> Result<Option<Arc<Vec<u16>>>, SliceError> {
        Ok(Some(Arc::new(
            self.0
                .read_brick(id)
                .expect("the desktop reads the overlay brick"),
        )))
    }
}

/// Serves a 64³ CT phantom and an overlay made by `value` (labels or a float field), opens the
/// page at `extra` over the phantom, and checks its axial slice with the overlay against the
/// desktop's. Returns the kind the store opened as and the share of the slice's pixels the
/// overlay changed.
fn assert_overlay_as_the_desktops(
    what: &str,
    float: bool,
    value: fn(u32, u32, u32) -> f64,
    extra: &str,
) -> (OverlayKind, f64) {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let primary_path = scratch.path().join("ct.strata");
    Phantom::cube(64)
        .write_store(&primary_path, &ImportOptions::default())
        .expect("writing the primary");
    let primary_geometry = strata_storage::Store::open(&primary_path)
        .expect("opening the primary")
        .header()
        .geometry
        .clone();
    let nrrd = scratch.path().join("overlay.nrrd");
    write_overlay_nrrd(&nrrd, &primary_geometry, float, value);
    let overlay_path = scratch.path().join("over.strata");
    import(&nrrd, &overlay_path);
    let (server, frames) = serve_stores(&[primary_path, overlay_path]);
    let fragment = format!(
        "#store=ct&overlay=over{extra}&mode=mip&preset=ct-soft-tissue&size=64x64&capture=1"
    );
    let (slice, console) = capture_slice(&server, &fragment, scratch.path(), &frames);

    // The desktop's slice, then its overlay over it.
    let store = desktop_client(&server, "ct");
    let header = store.header();
    let preset = header
        .windows
        .first()
        .expect("the phantom names its windows");
    let (level, mut desktop) = desktop_axial_slice(
        &header.layout,
        &header.geometry,
        Window::new(preset.center, preset.width),
        header.value_mapping.mapping,
        (&slice, &console),
        |id| store.read_brick(id).expect("brick"),
    );
    let base = desktop.clone();
    let overlay = desktop_client(&server, "over");
    let overlay_header = overlay.header();
    let mapping = overlay_header.value_mapping.mapping;
    let (a, b) = (
        mapping.physical(overlay_header.stored_range[0] as f64),
        mapping.physical(overlay_header.stored_range[1] as f64),
    );
    let physical_range = (a.min(b), a.max(b));
    let kind = kind_of_store(!overlay_header.labels.is_empty(), &mapping, physical_range);
    let grids = OverlayGrids {
        primary: header.geometry.clone(),
        primary_level_dims: header.layout.level_dims.clone(),
        overlay: overlay_header.geometry.clone(),
        overlay_mapping: mapping,
        kind,
    };
    let frame = SliceFrame::for_view(SliceView::Axial, &header.geometry);
    let cursor = header
        .geometry
        .dims
        .map(|d| ((d as f64 - 1.0) * 0.5).floor().max(0.0));
    let request = SliceRequest {
        view: SliceView::Axial,
        frame,
        position: cursor[frame.normal_axis],
        level: level as u8,
    };
    let size = (slice.width as usize, slice.height as usize);
    let Sampled::Complete(values) = sample(
        &mut Blocking(&overlay),
        &grids,
        &slice_pixels(&grids, request),
        size,
        1,
    )
    .expect("the desktop's sampling") else {
        panic!("blocking reads leave nothing missing");
    };
    let mut style = OverlayStyle::opening(label_table_of(&overlay_header.labels), physical_range);
    let mut link = OverlayLink::default();
    for part in extra.split('&').filter(|p| !p.is_empty()) {
        let (key, value) = part.split_once('=').expect("key=value");
        link.parse_key(key, value).expect("the test's own link");
    }
    let opening = style.clone();
    link.apply_to(&mut style);
    composite_over(&mut desktop, kind, &style, &values);
    if (link.colour_map, link.range, link.threshold) != (None, None, None) {
        // The link's colour map, range and threshold must matter here, or a page that
        // ignored them would pass.
        let mut unstyled = base.clone();
        composite_over(&mut unstyled, kind, &opening, &values);
        let restyled = unstyled
            .chunks(4)
            .zip(desktop.chunks(4))
            .filter(|(a, b)| a != b)
            .count();
        assert!(
            restyled > size.0 * size.1 / 10,
            "{what}: the link's style changes only {restyled} pixels of the opening style's"
        );
    }
    let changed = base
        .chunks(4)
        .zip(desktop.chunks(4))
        .filter(|(a, b)| a != b)
        .count();
    println!(
        "{what}: the overlay ({kind:?}) changes {changed} of {} pixels",
        size.0 * size.1
    );
    assert_same_slice(what, level, &slice, &desktop, &console);

    // What hiding would remove: the hidden labels' pixels, coloured when shown.
    if !link.hidden_labels.is_empty() {
        let shown = OverlayStyle {
            hidden_labels: Default::default(),
            ..style
        };
        let mut unhidden = base.clone();
        composite_over(&mut unhidden, kind, &shown, &values);
        let removed = unhidden
            .chunks(4)
            .zip(slice.rgba.chunks(4))
            .filter(|(a, b)| a != b)
            .count();
        let hidden_pixels = values
            .iter()
            .filter(|v| link.hidden_labels.contains(&(**v as i64)))
            .count();
        assert!(
            hidden_pixels > 50 && removed == hidden_pixels,
            "{what}: hiding removes the hidden labels' {hidden_pixels} pixels, {removed} differ"
        );
    }
    (kind, changed as f64 / (size.0 * size.1) as f64)
}

/// A label map on another grid, opened from the link with a label hidden and its own opacity:
/// the page's axial slice with the labels equals the desktop's overlay compositing byte for
/// byte (nearest level-0 label at each pixel's patient position, each label's colour), and
/// the hidden label's pixels show the slice alone.
#[test]
fn a_label_overlay_from_a_served_store_draws_as_the_desktops_and_a_hidden_label_is_removed() {
    let (kind, changed) = assert_overlay_as_the_desktops(
        "label overlay",
        false,
        label_of,
        "&overlay_opacity=0.70&overlay_hidden=2",
    );
    // The labels' grid covers 85 % of the primary's box; the background, the hidden label and
    // the part outside leave the rest.
    assert_eq!(
        kind,
        OverlayKind::Labels,
        "small whole numbers open as labels"
    );
    assert!(
        changed > 0.25,
        "the labels cover the slice: {changed:.2} of it"
    );
}

/// A continuous overlay (float values) opens as continuous and draws, trilinear from level 0
/// through the Hot map above its threshold, as the desktop's compositing does, byte for byte.
#[test]
fn a_continuous_overlay_from_a_served_store_draws_as_the_desktops() {
    let (kind, changed) = assert_overlay_as_the_desktops("continuous overlay", true, field, "");
    assert_eq!(
        kind,
        OverlayKind::Continuous,
        "float values open as continuous"
    );
    assert!(
        changed > 0.25,
        "the overlay covers the slice: {changed:.2} of it"
    );
}

/// The desktop's view of a served overlay store over a served primary: both grids, the kind
/// the store opens as and the style it opens with, the link's `extra` keys applied.
pub(crate) fn desktop_overlay(
    primary: &strata_service::client::RemoteSource,
    overlay: &strata_service::client::RemoteSource,
    extra: &str,
) -> (OverlayGrids, OverlayStyle) {
    let header = primary.header();
    let overlay_header = overlay.header();
    let mapping = overlay_header.value_mapping.mapping;
    let (a, b) = (
        mapping.physical(overlay_header.stored_range[0] as f64),
        mapping.physical(overlay_header.stored_range[1] as f64),
    );
    let physical_range = (a.min(b), a.max(b));
    let kind = kind_of_store(!overlay_header.labels.is_empty(), &mapping, physical_range);
    let grids = OverlayGrids {
        primary: header.geometry.clone(),
        primary_level_dims: header.layout.level_dims.clone(),
        overlay: overlay_header.geometry.clone(),
        overlay_mapping: mapping,
        kind,
    };
    let mut style = OverlayStyle::opening(label_table_of(&overlay_header.labels), physical_range);
    let mut link = OverlayLink::default();
    for part in extra.split('&').filter(|p| !p.is_empty()) {
        let (key, value) = part.split_once('=').expect("key=value");
        link.parse_key(key, value).expect("the test's own link");
    }
    link.apply_to(&mut style);
    (grids, style)
}

/// Serves a 64³ CT phantom and a label map on another grid (as above) and returns the
/// scratch folder (the stores'), the server (the primary as `ct`, the labels as `over`) and
/// its captures.
pub(crate) fn serve_phantom_with_labels() -> (
    tempfile::TempDir,
    strata_service::server::RunningServer,
    mpsc::Receiver<CapturedFrame>,
) {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let primary_path = scratch.path().join("ct.strata");
    Phantom::cube(64)
        .write_store(&primary_path, &ImportOptions::default())
        .expect("writing the primary");
    let primary_geometry = strata_storage::Store::open(&primary_path)
        .expect("opening the primary")
        .header()
        .geometry
        .clone();
    let nrrd = scratch.path().join("overlay.nrrd");
    write_overlay_nrrd(&nrrd, &primary_geometry, false, label_of);
    let overlay_path = scratch.path().join("over.strata");
    import(&nrrd, &overlay_path);
    let (server, frames) = serve_stores(&[primary_path, overlay_path]);
    (scratch, server, frames)
}

/// The label map over the page's oblique view (`oblique=30,-20` in the 2×2's sagittal place):
/// the image it posts equals the desktop's oblique image of that plane with the desktop's
/// overlay composited over it (the shared sampler at the oblique image's pixel centres, the
/// shared colouring and "over"), within the oblique test's share of last-bit pixels; and the
/// overlay changes much of the image, so a page that drew no overlay would fail.
#[test]
fn a_label_overlay_over_the_pages_oblique_view_draws_as_the_desktops_compositing() {
    let (scratch, server, frames) = serve_phantom_with_labels();
    let extra = "&overlay_opacity=0.70&overlay_hidden=2";
    let (angles, cursor, window) = ([30.0, -20.0, 0.0], [30.5, 33.25, 31.0], [40.0, 400.0]);
    let fragment = format!(
        "#store=ct&overlay=over{extra}&mode=mip&preset=ct-soft-tissue&size=64x64&capture=1\
         &oblique={},{}&cursor={},{},{}&window={},{}",
        angles[0], angles[1], cursor[0], cursor[1], cursor[2], window[0], window[1]
    );
    let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
    let page = Cdp::open(&url, scratch.path(), [1000, 800]);
    let posted = next_oblique_capture(&frames, &page, angles);
    let console = page.console();

    let primary = desktop_client(&server, "ct");
    let overlay = desktop_client(&server, "over");
    let geometry = primary.header().geometry.clone();
    let plane = ObliquePlane::from_orientation_deg(
        geometry.patient_from_index(glam::DVec3::from(cursor)),
        default_extent_mm(&geometry),
        angles,
    );
    let window = Window::new(window[0], window[1]);
    let base = desktop_image(&primary, plane, &posted, window);
    let (grids, style) = desktop_overlay(&primary, &overlay, extra);
    assert_eq!(grids.kind, OverlayKind::Labels);
    let size = (posted.width as usize, posted.height as usize);
    let Sampled::Complete(values) = sample(
        &mut Blocking(&overlay),
        &grids,
        &oblique_pixels(&grids, &plane, size.0, size.1),
        size,
        1,
    )
    .expect("the desktop's sampling") else {
        panic!("blocking reads leave nothing missing");
    };
    let mut desktop = base.clone();
    composite_over(&mut desktop, grids.kind, &style, &values);
    let changed = base
        .chunks(4)
        .zip(desktop.chunks(4))
        .filter(|(a, b)| a != b)
        .count();
    let pixels = size.0 * size.1;
    println!("oblique overlay: the labels change {changed} of {pixels} pixels");
    // The oblique image's square is wider than the volume (its default extent), so the labels
    // cover a smaller share of it than of an axial slice: 17 % measured.
    assert!(
        changed as f64 > 0.1 * pixels as f64,
        "the labels cover the oblique image: {changed} of {pixels} pixels"
    );
    assert_same_image(
        "the oblique view with the overlay",
        &posted,
        &desktop,
        &console,
    );
}

/// A continuous overlay opened from a link that names its colour map, range and threshold
/// (`overlay_cmap=`, `overlay_range=`, `overlay_threshold=`, read by the shared
/// `OverlayLink`): the page's axial slice equals the desktop's compositing with that style
/// byte for byte, and that style changes the slice against the opening one (Hot over the
/// store's range), so a page that ignored the keys fails.
#[test]
fn a_continuous_overlay_link_with_its_colour_map_range_and_threshold_draws_as_the_desktops() {
    let (kind, changed) = assert_overlay_as_the_desktops(
        "continuous overlay, styled by its link",
        true,
        field,
        "&overlay_cmap=viridis&overlay_range=50.5,250&overlay_threshold=100.25",
    );
    assert_eq!(kind, OverlayKind::Continuous);
    assert!(
        changed > 0.1,
        "the overlay covers part of the slice: {changed:.2} of it"
    );
}
