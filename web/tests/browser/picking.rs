//! Picking in the page's 3D view (issue 47): a real click (over the DevTools pipe, ../cdp)
//! moves the link's crosshair to the position the desktop's pick gives for the same frame
//! pixel: the pixel under the click, its pick depth in the same view drawn natively, the
//! pixel's ray (strata-viewer-ui's picking, which both viewers call).

use egui::{pos2, vec2, Rect};
use strata_render::{CacheConfig, GpuContext, OffscreenRenderer};
use strata_viewer_ui::picking::{frame_pixel, picked_index};
use strata_web::view_state::Fragment;

use crate::input::{open_page, view_rect, wait_for_link};
use crate::PAGE_DEADLINE;

/// How far the page's pick may lie from the native one, in voxels. The page draws on
/// SwiftShader and the native frame on lavapipe: the same WGSL on two f32 CPU drivers, whose
/// last bits of trilinear weights may differ and move the refined iso surface by a tiny
/// fraction of a voxel. A pick one pixel off moves by far more (checked below), so this still
/// tells the right pixel and ray from a wrong one.
const PICK_TOLERANCE_VOXELS: f64 = 0.05;

#[test]
fn a_click_on_the_pages_3d_view_moves_the_crosshair_to_what_the_desktop_picks_there() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let fragment =
        "#mode=iso&preset=ct-bone&iso=200&az=120&el=-25&zoom=1.5&volume=40&size=64x64&layout=conventional";
    let (mut page, _server) = open_page(fragment, scratch.path(), [1200, 800]);
    let view = Fragment::parse(fragment).expect("fragment").view;
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

    // The page fits its 64² image in the 3D view, keeping the aspect.
    let three_d = view_rect(&mut page, "3d");
    let side = three_d.width().min(three_d.height());
    let image = Rect::from_center_size(three_d.center(), vec2(side, side));
    // A pixel near the centre on the surface whose neighbours are on it too, clicked at its
    // centre on whole CSS pixels (what mouse events carry).
    let on_surface = |[x, y]: [u32; 2]| {
        (x.saturating_sub(1)..=x + 1)
            .all(|i| (y.saturating_sub(1)..=y + 1).all(|j| depth([i, j]).is_finite()))
    };
    let (at, pixel) = (0..20u32)
        .flat_map(|r| {
            let c = 32 - r.min(31);
            [[c, 32], [32, c], [32 + r.min(30), 32], [32, 32 + r.min(30)]]
        })
        .filter(|&p| on_surface(p))
        .find_map(|[x, y]| {
            let at = pos2(
                image.left() + (x as f32 + 0.5) / size[0] as f32 * image.width(),
                image.top() + (y as f32 + 0.5) / size[1] as f32 * image.height(),
            )
            .round();
            let pixel = frame_pixel(
                (at.x - image.left()) / image.width(),
                (at.y - image.top()) / image.height(),
                size,
            )?;
            (pixel == [x, y]).then_some((at, pixel))
        })
        .expect("a pixel of the iso surface near the image's centre");
    let expected =
        picked_index(&camera, &geometry, pixel, size, depth(pixel)).expect("the surface's depth");
    let neighbour = picked_index(
        &camera,
        &geometry,
        [pixel[0] + 1, pixel[1]],
        size,
        depth([pixel[0] + 1, pixel[1]]),
    )
    .expect("the neighbour's depth");
    let apart = (0..3)
        .map(|a| (expected[a] - neighbour[a]).abs())
        .fold(0.0, f64::max);
    assert!(
        apart > 4.0 * PICK_TOLERANCE_VOXELS,
        "one pixel over picks only {apart} voxels away: the test could not tell pixels apart"
    );

    let start = geometry
        .dims
        .map(|n| ((n as f64 - 1.0) * 0.5).floor().max(0.0));
    page.click(at.x as f64, at.y as f64);
    let picked = page.wait_for("the page's pick to end", PAGE_DEADLINE, |page| {
        let text = page.evaluate("document.getElementById('strata-canvas')?.dataset.pick ?? ''");
        let text = text.as_str()?.to_owned();
        (!text.is_empty() && !text.starts_with("reading")).then_some(text)
    });
    let what = format!(
        "the link's cursor to leave {start:?} after a click at {at:?} on the 3D view's image \
         {image:?} (pixel {pixel:?}; the desktop picks {expected:?}; the page: {picked})"
    );
    let linked = wait_for_link(&mut page, &what, |v| {
        v.cursor
            .is_some_and(|c| (0..3).any(|i| (c[i] - start[i]).abs() > 1e-3))
    });
    let cursor = linked.cursor.expect("a cursor");
    let off = (0..3)
        .map(|a| (cursor[a] - expected[a]).abs())
        .fold(0.0, f64::max);
    println!("page pick {cursor:?}, desktop pick {expected:?}: {off:.4} voxels apart");
    assert!(
        off <= PICK_TOLERANCE_VOXELS,
        "a click at {at:?} (pixel {pixel:?}) put the page's crosshair at {cursor:?}; the desktop \
         picks {expected:?} there ({off} voxels apart)"
    );
}
