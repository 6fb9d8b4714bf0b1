//! Progressive refinement in the page (issue 47): a still view with cached shadows, occlusion
//! and scattering (and the link's light intensity and ambient) accumulates jittered frames as
//! the desktop's render thread does, and converges to the native mean of the same frames; its
//! pass count (the canvas's `data-refine`, web/src/refine.rs) rises while the view is still
//! and starts again after a drag.

use std::sync::Arc;
use std::time::Duration;

use strata_loader::{StreamingConfig, StreamingVolume};
use strata_render::passes::progressive::{jittered_frame, Accumulator, ViewKey};
use strata_render::{
    compare_rgba8, BrickedVolume, Camera, GpuContext, OffscreenRenderer, RenderSettings,
};
use strata_viewer_ui::render_driver::{jitter_refines, DEFAULT_PROGRESSIVE_FRAMES};
use strata_web::view_state::Fragment;

use crate::input::cdp::Cdp;
use crate::input::{open_page_capturing, view_rect, wait_for_link};
use crate::{PAGE_DEADLINE, TOKEN};

/// The lowest PSNR of the page's converged mean against the native one. Both are the mean of
/// the same 64 jittered frames (the jitter is a hash of the pixel and the frame number, the
/// same WGSL on both sides) over the same single-brick cut: measured identical (SwiftShader vs
/// lavapipe, 2026-12-07: rmse 0). What may differ elsewhere is what differs for one frame in
/// `the_page_streams_a_served_store_and_converges_to_the_native_loaders_picture`: f32 brick
/// textures in the page (WebGPU has no 16-bit normalised format) against r16unorm, sampled with
/// other rounding by another CPU driver, moving single 8-bit steps; averaging adds no error.
/// The bound stays above what the refinement changes (the unrefined frame is 46.7 dB from the
/// mean, max 24/255, checked below), so a page that showed the unrefined frame fails.
const MIN_PSNR_DB: f64 = 50.0;

/// A link with every refined effect, the light's intensity and ambient, on the served tiny
/// store (open_page_capturing's, one brick: the cut is the same in the page and natively).
const FRAGMENT: &str = "#store=tiny&mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.4&size=96x96\
     &layout=single&light=-45,45&shadows=cache&occlusion=4&scattering=0.3,0.8&intensity=1.25\
     &ambient=0.3&capture=1";

/// The page's `data-refine`: runs started, passes in the mean, passes asked, state.
#[derive(Debug, Clone, PartialEq)]
struct Refining {
    run: u64,
    passes: u32,
    total: u32,
    state: String,
}

fn refining(page: &mut Cdp) -> Option<Refining> {
    let text = page
        .evaluate("document.getElementById('strata-canvas')?.dataset.refine ?? null")
        .as_str()?
        .to_owned();
    let field = |name: &str| {
        text.split(';')
            .find_map(|part| part.strip_prefix(&format!("{name}=")))
            .map(str::to_owned)
    };
    let (passes, total) = field("passes")?
        .split_once('/')
        .map(|(a, b)| (a.parse().ok(), b.parse().ok()))?;
    Some(Refining {
        run: field("run")?.parse().ok()?,
        passes: passes?,
        total: total?,
        state: field("state")?,
    })
}

/// The picture the page shows of the sample's still view once refined, drawn natively: where
/// its effects refine (the shared `render_driver::jitter_refines`), the mean of the desktop's
/// jittered frames (seeds 0..64); else None (the single frame is the picture).
pub(crate) fn native_refined(
    gpu: &GpuContext,
    renderer: &mut OffscreenRenderer,
    volume: &BrickedVolume,
    camera: &Camera,
    settings: &RenderSettings,
) -> Option<Vec<u8>> {
    if !jitter_refines(settings) {
        return None;
    }
    let key = ViewKey::new(camera, settings);
    let mut mean = Accumulator::new(gpu);
    for n in 0..DEFAULT_PROGRESSIVE_FRAMES {
        renderer
            .submit(gpu, volume, camera, &jittered_frame(settings, n))
            .expect("a jittered frame");
        assert!(
            renderer
                .raycaster
                .last_pipeline_key()
                .is_some_and(|k| k.jitter),
            "the jittered pipeline drew the frame"
        );
        let output = renderer.raycaster.output_texture().expect("an output");
        mean.accumulate(gpu, &key, output).expect("accumulated");
        if n % 8 == 7 {
            // Bounds the queued frames, as render_still does.
            gpu.wait_idle().expect("the GPU finishes");
        }
    }
    Some(mean.read_mean_blocking(gpu).expect("the mean read back"))
}

/// The native mean: the desktop's loader on the same store through the same server,
/// converged, then `frames` jittered frames (seeds 0..frames) accumulated on lavapipe, as the
/// desktop's render thread accumulates them.
fn native_mean(server_url: &str, frames: u32) -> (Vec<u8>, Vec<u8>) {
    let view = Fragment::parse(FRAGMENT).expect("fragment").view;
    let [width, height] = view.image_size.expect("the link fixes the size");
    let gpu = GpuContext::headless().expect("a Vulkan adapter (lavapipe)");
    let remote = strata_service::client::RemoteSource::open(
        server_url,
        strata_service::client::RemoteOptions {
            token: Some(TOKEN.into()),
            ..Default::default()
        },
    )
    .expect("the desktop's client opens the store");
    let mut volume = StreamingVolume::new(
        &gpu,
        Arc::new(remote),
        &view.transfer_function(),
        StreamingConfig::default(),
    )
    .expect("native loader");
    let camera = view.camera(volume.geometry());
    let settings = view.settings(volume.geometry(), width, height);
    let (single, history) = volume
        .render_until_converged(&gpu, &camera, &settings, 400)
        .expect("native frames");
    assert!(
        history.last().is_some_and(|s| s.converged),
        "native did not converge"
    );
    let key = ViewKey::new(&camera, &settings);
    let mut mean = Accumulator::new(&gpu);
    for n in 0..frames {
        let jittered = jittered_frame(&settings, n);
        let deadline = std::time::Instant::now() + PAGE_DEADLINE;
        while !volume
            .raycaster_mut()
            .prepare_in_background(&gpu, &jittered)
        {
            assert!(
                std::time::Instant::now() < deadline,
                "the jittered pipeline never compiled"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        let stats = volume
            .frame(&gpu, &camera, &jittered)
            .expect("a jittered frame");
        assert!(
            stats.uploads == 0 && !stats.page_table_rewritten,
            "the cut moved under the native mean"
        );
        let output = volume
            .raycaster_mut()
            .output_texture()
            .expect("the raycaster's output");
        mean.accumulate(&gpu, &key, output).expect("accumulated");
    }
    assert_eq!(mean.frames(), frames);
    (
        mean.read_mean_blocking(&gpu).expect("the mean read back"),
        single.rgba,
    )
}

#[test]
fn a_still_cinematic_view_refines_in_the_page_to_the_native_mean_and_a_drag_starts_it_again() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, server, frames) = open_page_capturing(FRAGMENT, scratch.path(), [640, 480]);
    // The link keeps what it named, intensity and ambient included.
    let view = wait_for_link(&mut page, "the page's link", |_| true);
    assert_eq!((view.light.intensity, view.light.ambient), (1.25, 0.3));

    // While still, the pass count rises in one run.
    let total = DEFAULT_PROGRESSIVE_FRAMES;
    let first = page.wait_for("the page to start refining", PAGE_DEADLINE, |page| {
        refining(page).filter(|r| r.passes >= 1 && r.passes < total)
    });
    assert_eq!(
        (first.total, first.state.as_str()),
        (total, "refining"),
        "{first:?}"
    );
    let risen = page.wait_for("the pass count to rise", PAGE_DEADLINE, |page| {
        refining(page).filter(|r| r.run == first.run && r.passes > first.passes)
    });
    println!("refine: {first:?} then {risen:?}");

    // Converged: the capture is the complete mean.
    let frame = frames.recv_timeout(PAGE_DEADLINE).unwrap_or_else(|_| {
        panic!(
            "the page posted no refined frame within {PAGE_DEADLINE:?}; its console:\n{}",
            page.console()
        )
    });
    let done = refining(&mut page).expect("the page's refinement state");
    assert_eq!(
        (done.passes, done.total, done.state.as_str()),
        (total, total, "converged"),
        "{done:?}"
    );

    let (native, unrefined) = native_mean(&server.store_url("tiny"), total);
    let [width, height] = Fragment::parse(FRAGMENT)
        .expect("fragment")
        .view
        .image_size
        .expect("size");
    assert_eq!((frame.width, frame.height), (width, height));
    let lit = frame.rgba.chunks(4).filter(|p| p[3] > 0).count();
    assert!(
        lit > (width * height / 10) as usize,
        "the page's refined frame is nearly empty ({lit} pixels with coverage)"
    );
    let comparison = compare_rgba8(&frame.rgba, &native).expect("same size");
    println!("refine: page (SwiftShader) mean vs native (lavapipe) mean: {comparison:?}");
    assert!(
        comparison.psnr_db >= MIN_PSNR_DB,
        "the page's refined frame differs from the native mean: {comparison:?}; console:\n{}",
        page.console()
    );
    // The comparison can fail: the unrefined frame the effects start from is beyond the bound.
    let apart = compare_rgba8(&native, &unrefined).expect("same size");
    println!("refine: native mean vs its unrefined frame: {apart:?}");
    assert!(
        apart.psnr_db < MIN_PSNR_DB,
        "refinement changed less than the bound allows: {apart:?}"
    );

    // A drag moves the view: the run ends, and once still again a new one counts from 0.
    let rect = view_rect(&mut page, "3d");
    let from = rect.center().round();
    page.drag(
        [from.x as f64, from.y as f64],
        [from.x as f64 + 40.0, from.y as f64],
        3,
    );
    let again = page.wait_for("a new run after the drag", PAGE_DEADLINE, |page| {
        refining(page).filter(|r| r.run > done.run)
    });
    assert!(again.passes < total, "{again:?}");
    page.wait_for("the new run's pass count to rise", PAGE_DEADLINE, |page| {
        refining(page).filter(|r| r.run == again.run && r.passes > again.passes)
    });
}
