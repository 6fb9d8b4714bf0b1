//! The served overlay in the page's 3D view (issue 47): a label map served beside a CT
//! phantom, opened by the link (`overlay=`), resampled by the page onto the 3D grid a few
//! slices a frame as its bricks arrive (web/src/overlay_view.rs), against the desktop's code
//! run natively: strata-viewer-ui's `GridResampler` on the desktop's blocking reads of the same
//! bricks, the shared colour table, uploaded into the desktop's streaming loader on the same
//! server and raycast on lavapipe.
//!
//! Tolerance: PSNR ≥ 40 dB, the streamed-store test's bound and for its reasons (the page's
//! f32 brick texture against lavapipe's r16unorm, occluded nodes a level coarser); the grid
//! itself is checked equal before (one f64 program on the same bricks). A frame without the
//! overlay is far from the page's (< 30 dB), so a page that drew no overlay would fail.

use std::sync::Arc;

use strata_loader::{StreamingConfig, StreamingVolume};
use strata_render::{compare_rgba8, GpuContext};
use strata_viewer_ui::overlay_3d::{
    grid_dims, lut_for, GridProgress, GridResampler, PAGE_OVERLAY_3D_MAX_VOXELS,
};
use strata_web::view_state::Fragment;

use super::overlay::{desktop_overlay, serve_phantom_with_labels, Blocking};
use super::{desktop_client, Browser, PAGE_DEADLINE, TOKEN};

/// A label overlay with a label hidden, opened by the page's link over a streamed 64³ CT
/// phantom in the 3D view alone (DVR, CT bone: the labels in the transparent soft tissue show
/// as bodies): the page's converged frame with the overlay equals the native loader's frame
/// with the desktop's grid of the same overlay, and differs clearly from the frame without it.
#[test]
fn a_served_label_overlay_in_the_pages_3d_view_draws_as_the_native_raycaster_does() {
    let (scratch, server, frames) = serve_phantom_with_labels();
    let extra = "&overlay_opacity=0.60&overlay_hidden=2";
    let fragment = format!(
        "#store=ct&overlay=over{extra}&mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.4\
         &size=96x96&layout=single&capture=1"
    );
    let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
    let browser = Browser::open(&url, scratch.path());
    let frame = frames.recv_timeout(PAGE_DEADLINE).unwrap_or_else(|_| {
        panic!(
            "the page posted no frame within {PAGE_DEADLINE:?}; its console:\n{}",
            browser.console()
        )
    });
    let console = browser.console();
    drop(browser);
    let view = Fragment::parse(&fragment).expect("fragment").view;
    let [width, height] = view.image_size.expect("the fragment fixes the size");
    assert_eq!((frame.width, frame.height), (width, height), "{console}");

    // The desktop's grid of the overlay, from its blocking reads, at the page's bound.
    let primary = desktop_client(&server, "ct");
    let overlay = desktop_client(&server, "over");
    let (grids, style) = desktop_overlay(&primary, &overlay, extra);
    let dims = grid_dims(&grids.primary_level_dims, PAGE_OVERLAY_3D_MAX_VOXELS);
    assert_eq!(
        dims, grids.primary.dims,
        "a 64³ primary gets its own grid, as on the desktop"
    );
    let kind = grids.kind;
    let GridProgress::Complete(grid) = GridResampler::new(grids, dims)
        .step(&mut Blocking(&overlay), u64::MAX, usize::MAX)
        .expect("the desktop's resampling")
    else {
        panic!("blocking reads leave nothing missing");
    };
    assert!(
        grid.labels.len() >= 3,
        "labels in the grid: {:?}",
        grid.labels
    );
    let lut = lut_for(kind, &style, &grid.labels);

    let gpu = GpuContext::headless().expect("a Vulkan adapter (lavapipe)");
    let mut volume = StreamingVolume::new(
        &gpu,
        Arc::new(primary),
        &view.transfer_function(),
        StreamingConfig::default(),
    )
    .expect("native loader");
    let camera = view.camera(volume.geometry());
    let settings = view.settings(volume.geometry(), width, height);
    let (without, _) = volume
        .render_until_converged(&gpu, &camera, &settings, 400)
        .expect("native frames without the overlay");
    let primary_dims = volume.geometry().dims;
    volume
        .raycaster_mut()
        .set_overlay(&gpu, &grid.volume, &lut, primary_dims)
        .expect("the overlay's upload");
    let (native, history) = volume
        .render_until_converged(&gpu, &camera, &settings, 400)
        .expect("native frames with the overlay");
    assert!(
        history.last().is_some_and(|s| s.converged),
        "native did not converge"
    );
    let comparison = compare_rgba8(&frame.rgba, &native.rgba).expect("same size");
    let apart = compare_rgba8(&frame.rgba, &without.rgba).expect("same size");
    println!(
        "overlay in 3D: browser (SwiftShader) vs native with the overlay (lavapipe): \
         {comparison:?}; vs native without it: {apart:?}"
    );
    assert!(
        apart.psnr_db < 30.0,
        "the overlay changes the frame little: {apart:?}; console:\n{console}"
    );
    assert!(
        comparison.psnr_db >= 40.0,
        "the page's frame with the overlay differs from the native one: {comparison:?}; \
         console:\n{console}"
    );
}
