//! Adaptive sampling of the page's still view (issue 47): with `adaptive=EPS` in the link, once
//! the served store's cut converged the page builds the block oracle across animation frames
//! (web/src/adaptive.rs, render's `BlockOracleBuild`) and draws the still view with the
//! adaptive pass, as the desktop does (viewer/src/adaptive_view.rs). Checked against the
//! desktop's own code run natively on the same store through the same server: the loader
//! converged, the one-shot `block_oracle_with` over the cut's payloads, the adaptive pass.

use std::sync::Arc;

use strata_loader::{StreamingConfig, StreamingVolume};
use strata_render::passes::adaptive::{
    block_oracle_with, AdaptiveConfig, AdaptivePass, OracleTarget,
};
use strata_render::{compare_rgba8, GpuContext, RenderSettings};
use strata_web::view_state::Fragment;

use crate::input::cdp::Cdp;
use crate::input::open_page_capturing;
use crate::{PAGE_DEADLINE, TOKEN};

/// The lowest PSNR of the page's adaptive frame against the native one. Both are the same
/// WGSL over the same single-brick cut with the same oracle table (the incremental build
/// equals the one-shot one, render's unit test); what differs is what differs for one
/// raycaster frame in `the_page_streams_a_served_store_and_converges_to_the_native_loaders_picture`:
/// f32 brick textures in the page (WebGPU has no 16-bit normalised format) against r16unorm,
/// sampled with other rounding by another CPU driver (SwiftShader against lavapipe), single
/// 8-bit steps. The bound must stay above what the adaptive pass changes against the
/// raycaster's frame (checked below), so a page that showed the raycaster's frame fails.
const MIN_PSNR_DB: f64 = 40.0;

/// The oracle's ε in the link: the desktop's default.
const EPSILON: f64 = 0.001;

/// A still DVR view of the served tiny store (open_page_capturing's, one brick: the cut is the
/// same in the page and natively), adaptive sampling on.
const FRAGMENT: &str = "#store=tiny&mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.4&size=96x96\
     &layout=single&adaptive=0.001&capture=1";

/// The page's `data-adaptive` (web/src/adaptive.rs): its state and the drawn frame's samples.
fn adaptive_state(page: &mut Cdp) -> Option<String> {
    page.evaluate("document.getElementById('strata-canvas')?.dataset.adaptive ?? null")
        .as_str()
        .map(str::to_owned)
}

fn field<'a>(text: &'a str, name: &str) -> Option<&'a str> {
    text.split(';')
        .find_map(|part| part.strip_prefix(name)?.strip_prefix('='))
}

/// What the desktop's code draws natively of the link's view: the raycaster's converged frame
/// and its sample count, the adaptive pass's frame and its sample count.
struct Native {
    raycaster: Vec<u8>,
    raycaster_samples: u64,
    adaptive: Vec<u8>,
    adaptive_samples: u64,
}

fn native_frames(server_url: &str) -> Native {
    let view = Fragment::parse(FRAGMENT).expect("fragment").view;
    assert_eq!(view.adaptive_epsilon, Some(EPSILON));
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
    let tf = view.transfer_function();
    let mut volume = StreamingVolume::new(&gpu, Arc::new(remote), &tf, StreamingConfig::default())
        .expect("native loader");
    let camera = view.camera(volume.geometry());
    let settings = view.settings(volume.geometry(), width, height);
    let counted = RenderSettings {
        count_samples: true,
        ..settings.clone()
    };
    let (raycast, history) = volume
        .render_until_converged(&gpu, &camera, &counted, 400)
        .expect("native frames");
    assert!(
        history.last().is_some_and(|s| s.converged),
        "native did not converge"
    );
    // The desktop's oracle, built in one go from the cut's payloads (adaptive_view.rs).
    let mut payloads = volume.cut_payloads();
    assert!(payloads.read_missing(|| false).expect("the cut's bricks"));
    let distances = block_oracle_with(
        payloads.table(),
        &payloads,
        volume.mapping(),
        &tf,
        EPSILON,
        AdaptiveConfig::default().l_max,
        settings.quality,
        OracleTarget::for_settings(&settings),
    );
    let mut pass = AdaptivePass::new(&gpu, volume.brick_cache());
    pass.set_oracle(&gpu, &distances);
    let frame = pass
        .render_blocking(
            &gpu,
            &volume.scene(&camera, &settings),
            &AdaptiveConfig::default(),
        )
        .expect("the native adaptive frame");
    assert_eq!(
        frame.cut_short_invocations, 0,
        "lavapipe cut the pass short"
    );
    Native {
        raycaster: raycast.rgba,
        raycaster_samples: raycast.samples.expect("the raycaster counted its samples"),
        adaptive: frame.rgba.clone(),
        adaptive_samples: frame.total_samples(),
    }
}

#[test]
fn the_pages_adaptive_still_frame_equals_the_native_adaptive_frame_with_fewer_samples() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, server, frames) = open_page_capturing(FRAGMENT, scratch.path(), [640, 480]);
    // The capture waits for the adaptive frame (or its failure): it is the still view's final
    // picture.
    let frame = frames.recv_timeout(PAGE_DEADLINE).unwrap_or_else(|_| {
        panic!(
            "the page posted no still frame within {PAGE_DEADLINE:?}; its console:\n{}",
            page.console()
        )
    });
    let drawn = page.wait_for(
        "the page's adaptive frame and its sample count",
        PAGE_DEADLINE,
        |page| {
            let text = adaptive_state(page)?;
            (field(&text, "state") != Some("drawn") || field(&text, "samples").is_some())
                .then_some(text)
        },
    );
    assert_eq!(
        field(&drawn, "state"),
        Some("drawn"),
        "the page did not draw the adaptive frame: {drawn}; console:\n{}",
        page.console()
    );
    let page_samples: u64 = field(&drawn, "samples")
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no sample count in {drawn}"));

    let native = native_frames(&server.store_url("tiny"));
    let [width, height] = Fragment::parse(FRAGMENT)
        .expect("fragment")
        .view
        .image_size
        .expect("size");
    assert_eq!((frame.width, frame.height), (width, height));
    let lit = frame.rgba.chunks(4).filter(|p| p[3] > 0).count();
    assert!(
        lit > (width * height / 10) as usize,
        "the page's adaptive frame is nearly empty ({lit} pixels with coverage)"
    );
    let against_adaptive = compare_rgba8(&frame.rgba, &native.adaptive).expect("same size");
    let against_raycaster = compare_rgba8(&frame.rgba, &native.raycaster).expect("same size");
    let native_pair = compare_rgba8(&native.adaptive, &native.raycaster).expect("same size");
    println!(
        "adaptive: page (SwiftShader) vs native adaptive (lavapipe): {against_adaptive:?}; \
         page vs native raycaster: {against_raycaster:?}; native adaptive vs raycaster: \
         {native_pair:?}; samples: page {page_samples}, native adaptive {}, native raycaster {}",
        native.adaptive_samples, native.raycaster_samples
    );
    assert!(
        against_adaptive.psnr_db >= MIN_PSNR_DB,
        "the page's adaptive frame differs from the native one: {against_adaptive:?}; \
         console:\n{}",
        page.console()
    );
    // The comparison can fail: the raycaster's frame is beyond the bound, and the page's frame
    // is as far from it as the native adaptive frame is (a page that did not run the pass
    // would be at the native raycaster's PSNR to it, far above).
    assert!(
        native_pair.psnr_db < MIN_PSNR_DB,
        "the adaptive pass changed less than the bound allows: {native_pair:?}"
    );
    assert!(
        (against_raycaster.psnr_db - native_pair.psnr_db).abs() < 3.0,
        "the page's frame is not as far from the raycaster's as the native adaptive frame: \
         {against_raycaster:?} against {native_pair:?}"
    );
    // Fewer samples than the raycaster, as natively; the same count as the native pass up to
    // the few rays that the two drivers' rounding terminates a slice apart.
    assert!(native.adaptive_samples < native.raycaster_samples);
    assert!(
        page_samples < native.raycaster_samples,
        "the page's adaptive frame took {page_samples} samples, the raycaster {}",
        native.raycaster_samples
    );
    let relative = (page_samples as f64 - native.adaptive_samples as f64).abs()
        / native.adaptive_samples.max(1) as f64;
    assert!(
        relative < 0.01,
        "the page's sample count {page_samples} is not the native pass's {}",
        native.adaptive_samples
    );
}
