//! The web viewer in a real browser (issue 39): Debian's Chromium, headless, WebGPU on
//! SwiftShader, loading the page from `strata serve` on loopback.
//!
//! The page is built by the xtask (wasm32 build + wasm-bindgen into web/dist/; incremental, so
//! it costs seconds once `.ci/run`'s web stage or an earlier run built it). A missing Chromium or
//! wasm32 target fails with the install hint: the test never passes without a browser.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use strata_render::{compare_rgba8, CacheConfig, GpuContext, OffscreenRenderer, TransferFunction};
use strata_service::server::{find_stores, start};
use strata_service::{CapturedFrame, FrameSink, ServeOptions, WebViewerAssets};
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_web::view_state::{Fragment, ViewState};

/// How long the page may take to load, generate its volume and post a frame. SwiftShader
/// compiles the raycast pipeline on the CPU (tens of seconds on two busy cores): this bounds a
/// hang, it does not time anything.
const PAGE_DEADLINE: Duration = Duration::from_secs(240);

/// The page under clicks, drags and keys over the DevTools protocol (issue 47).
#[path = "browser/input.rs"]
mod input;
/// Rulers, angles and ROIs drawn in the page against the desktop's functions (issue 47).
#[path = "browser/measure.rs"]
mod measure;
/// A click in the page's 3D view picks what the desktop picks (issue 47).
#[path = "browser/picking.rs"]
mod picking;

/// The page's undo and redo, help, screenshot download, triad, colour maps and readout
/// under real keys and pointer moves (issue 47).
#[path = "browser/keys.rs"]
mod keys;

/// The page's oblique view against the desktop's shared resampling and drag (issue 47).
#[path = "browser/oblique.rs"]
mod oblique;

/// Segmentation editing in the page: brush, eraser, undo and the NIfTI download (issue 52).
#[path = "browser/segment.rs"]
mod segment;
/// The brush in the page's 3D view against the desktop's sphere stroke (issue 52).
#[path = "browser/segment_3d.rs"]
mod segment_3d;

/// Adaptive sampling of the page's still view against the native adaptive pass (issue 47).
#[path = "browser/adaptive.rs"]
mod adaptive;
/// A served 4-D store's frames and cine in the page against the desktop's client (issue 47).
#[path = "browser/frames.rs"]
mod frames;
/// A second served store over the page's slices against the desktop's overlay code (issue 47).
#[path = "browser/overlay.rs"]
mod overlay;
/// The served overlay in the page's 3D view against the native raycaster's (issue 47).
#[path = "browser/overlay_3d.rs"]
mod overlay_3d;
/// Progressive refinement of the page's still 3D view against the native mean (issue 47).
#[path = "browser/refine.rs"]
mod refine;
/// Region growing and statistics in the page, on a served store's fetched bricks (issue 52).
#[path = "browser/segment_values.rs"]
mod segment_values;

/// The side panel's cinematic preset buttons clicked, against what the desktop's set (issue 47).
#[path = "browser/cinematic.rs"]
mod cinematic;
/// The orbit movie downloaded as an animated PNG, against the native frames (issue 47).
#[path = "browser/movie.rs"]
mod movie;

const TOKEN: &str = "0123456789abcdef0123456789abcdef";

fn chromium() -> PathBuf {
    for candidate in ["/usr/bin/chromium", "/usr/bin/chromium-browser"] {
        if Path::new(candidate).exists() {
            return PathBuf::from(candidate);
        }
    }
    panic!(
        "Chromium is needed for the web viewer's browser tests: `apt-get install chromium` \
         (Debian's package; .ci/test-packages lists it)"
    );
}

/// Builds (or finds up to date) the page and returns its files.
fn web_viewer() -> WebViewerAssets {
    let dist = xtask::build_web(&xtask::workspace_root())
        .unwrap_or_else(|e| panic!("building the web viewer: {e:#}"));
    WebViewerAssets::from_dir(&dist).unwrap_or_else(|e| panic!("{e}"))
}

/// One Chromium at a time: each renders WebGPU on SwiftShader, on the CPU, and several at once
/// on CI's two cores starved each other past their deadlines (the notebook widget's test timed
/// out beside seven others; alone it takes a minute). Held from a browser's start to its end.
static ONE_BROWSER_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

struct Browser {
    child: Child,
    log: PathBuf,
    _profile: tempfile::TempDir,
    // Dropped after the child is killed (fields drop after `Drop::drop`).
    _turn: std::sync::MutexGuard<'static, ()>,
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Browser {
    /// Headless Chromium on `url`, WebGPU on SwiftShader (the flags the research note found
    /// to give an adapter and a visible canvas), no network beyond loopback.
    fn open(url: &str, scratch: &Path) -> Browser {
        // A test that failed with the lock held poisons it; the next browser may still run.
        let turn = ONE_BROWSER_AT_A_TIME
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        let profile = tempfile::tempdir().expect("browser profile folder");
        let log = scratch.join("chromium.log");
        let log_file = std::fs::File::create(&log).expect("browser log file");
        let child = Command::new(chromium())
            .args([
                "--headless=new",
                "--no-sandbox",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-quic",
                "--enable-unsafe-webgpu",
                "--enable-unsafe-swiftshader",
                "--use-webgpu-adapter=swiftshader",
                "--enable-gpu",
                "--enable-features=Vulkan",
                "--use-vulkan=swiftshader",
                "--use-angle=swiftshader",
                "--enable-logging=stderr",
                "--window-size=480,400",
                "--force-device-scale-factor=1",
            ])
            .arg(format!("--user-data-dir={}", profile.path().display()))
            .arg(url)
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .unwrap_or_else(|e| panic!("starting Chromium: {e}"));
        Browser {
            child,
            log,
            _profile: profile,
            _turn: turn,
        }
    }

    /// The console lines the page wrote (for failure messages).
    fn console(&self) -> String {
        let mut text = String::new();
        if let Ok(mut f) = std::fs::File::open(&self.log) {
            let _ = f.read_to_string(&mut text);
        }
        text.lines()
            .filter(|l| l.contains("CONSOLE") || l.contains("strata") || l.contains("WebGPU"))
            .collect::<Vec<_>>()
            .join("\n")
    }
}

#[test]
fn the_served_page_draws_the_view_its_link_names_as_the_native_renderer_does() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    // `strata serve` needs a store to serve; the page's sample volume is its own (this first
    // step draws the render crate's phantom in the page: streaming needs the loader on wasm32).
    let store = scratch.path().join("tiny.strata");
    Phantom::cube(32)
        .write_store(&store, &ImportOptions::default())
        .expect("writing a tiny store");
    let (frames_in, frames) = mpsc::channel::<CapturedFrame>();
    let frames_in = std::sync::Mutex::new(frames_in);
    let server = start(
        find_stores(&[store]).expect("store found"),
        ServeOptions {
            web_viewer: Some(std::sync::Arc::new(web_viewer())),
            test_frame_sink: Some(FrameSink(std::sync::Arc::new(move |frame| {
                if let Ok(sender) = frames_in.lock() {
                    let _ = sender.send(frame);
                }
            }))),
            // With a token, as off loopback: the page must send it (as `Authorization`,
            // from the fragment) for the sink to take its frame.
            token: Some(TOKEN.into()),
            ..ServeOptions::default()
        },
    )
    .expect("server starts");

    // Each mode is its own pipeline (overrides), compiled by Chrome's Tint: all three must
    // compile there and draw what the native renderer draws.
    let gpu = GpuContext::headless().expect("a Vulkan adapter (lavapipe)");
    // A function edited from ct-bone (`tf=`, compact_tf.rs): denser at 300 HU and green, so a
    // page that drew the preset instead would fail the comparison (checked below).
    let mut edited = TransferFunction::preset("ct-bone").expect("preset");
    edited.opacity[2].opacity = 0.5;
    for stop in &mut edited.color {
        stop.rgb = [0.2, stop.rgb[1].max(0.6), 0.3];
    }
    let tf = strata_web::compact_tf::encode(&edited).expect("within a link's bounds");
    for fragment in [
        "#mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.3&volume=48&size=128x128&capture=1&layout=single".to_string(),
        "#mode=mip&preset=ct-soft-tissue&az=-60&el=10&zoom=1.1&volume=40&size=96x128&capture=1&layout=single".into(),
        "#mode=iso&preset=ct-bone&iso=200&az=120&el=-25&zoom=1.5&volume=48&size=128x96&capture=1&layout=single".into(),
        format!("#mode=dvr&preset=ct-bone&tf={tf}&az=35&el=20&zoom=1.3&volume=48&size=128x128&capture=1&layout=single"),
        // The cut, the shading switch and the projection, as the side panel sets them.
        "#mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.3&volume=48&size=128x128&capture=1&layout=single&crop=0.1,0,0,0.9,1,1&clip=ap,0.3&shade=off&proj=ortho".into(),
        // A directional key light with exact shadows, as the shared light panel sets them.
        "#mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.3&volume=48&size=128x128&capture=1&layout=single&light=-70,50&shadows=exact".into(),
    ] {
        let fragment = fragment.as_str();
        let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
        let launched = std::time::Instant::now();
        let browser = Browser::open(&url, scratch.path());
        let frame = frames.recv_timeout(PAGE_DEADLINE).unwrap_or_else(|_| {
            panic!(
                "{fragment}: the page posted no frame within {PAGE_DEADLINE:?}; its console:\n{}",
                browser.console()
            )
        });
        // Reported, not asserted (no wall-clock assertions in tests): browser start, wasm
        // load, the volume made in the page, pipeline compile, one frame, readback.
        println!(
            "{fragment}: first frame back {:.1} s after launching Chromium",
            launched.elapsed().as_secs_f64()
        );
        let console = browser.console();
        drop(browser);
        let view = Fragment::parse(fragment).expect("fragment").view;
        let [width, height] = view.image_size.expect("the fragment fixes the size");
        assert_eq!((frame.width, frame.height), (width, height), "{console}");

        // The same view, drawn natively by the same crate on lavapipe, with the f32 brick
        // format the browser has to use (no 16-bit normalised textures on WebGPU).
        let volume = view.sample_volume().expect("sample volume");
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
        let (camera, settings) = (view.camera(&volume.geometry), view.settings(&volume.geometry, width, height));
        let native = renderer
            .render(&gpu, &volume, &camera, &settings)
            .expect("native frame");
        let lit = frame.rgba.chunks(4).filter(|p| p[3] > 0).count();
        assert!(
            lit > (width * height / 10) as usize,
            "{fragment}: the browser's frame is nearly empty ({lit} pixels with coverage); its console:\n{console}"
        );
        // A view with shadows refines in the page (refine.rs): the picture is the mean of the
        // desktop's jittered frames, drawn natively the same way.
        let native_rgba = refine::native_refined(&gpu, &mut renderer, &volume, &camera, &settings)
            .unwrap_or_else(|| native.rgba.clone());
        let comparison = compare_rgba8(&frame.rgba, &native_rgba).expect("same size");
        println!("{fragment}: browser (SwiftShader) vs native (lavapipe): {comparison:?}");
        // Same WGSL, same inputs, both IEEE f32 on LLVM-compiled CPU drivers: measured
        // identical here (SwiftShader vs lavapipe, 2026-12-05). Drivers may still differ in how
        // they round trilinear weights of f32 textures and in the last bits of exp/pow in
        // shading, which moves single 8-bit steps near opaque edges (the native GPU-vs-f64
        // tests allow 40 dB for the same reasons). The f64 reference tests bound the renderer
        // itself; this bounds "the browser draws the same picture".
        assert!(
            comparison.psnr_db >= 40.0,
            "{fragment}: the browser's frame differs from the native one: {comparison:?}"
        );
        if view.clip.enabled {
            // The cut and the unshaded switch made the picture: the same view whole and shaded
            // is far from the browser's.
            let whole = ViewState {
                crop: Default::default(),
                clip: Default::default(),
                shading: true,
                ..view.clone()
            };
            let whole_frame = renderer
                .render(&gpu, &volume, &camera, &whole.settings(&volume.geometry, width, height))
                .expect("native frame");
            let apart = compare_rgba8(&frame.rgba, &whole_frame.rgba).expect("same size");
            println!("{fragment}: browser vs the uncut, shaded native frame: {apart:?}");
            assert!(apart.psnr_db < 30.0, "{fragment}: {apart:?}");
        }
        if !view.light.headlight {
            // The link's light, not the headlight, made the picture: the same view lit by
            // the default light is far from the browser's.
            let headlit = ViewState {
                light: Default::default(),
                ..view.clone()
            };
            let headlit_frame = renderer
                .render(
                    &gpu,
                    &volume,
                    &camera,
                    &headlit.settings(&volume.geometry, width, height),
                )
                .expect("native frame");
            let apart = compare_rgba8(&frame.rgba, &headlit_frame.rgba).expect("same size");
            println!("{fragment}: browser vs the headlit native frame: {apart:?}");
            assert!(apart.psnr_db < 30.0, "{fragment}: {apart:?}");
        }
        if view.tf.is_some() {
            // The link's function, not its preset, made the picture: the preset's frame is
            // far from the browser's.
            let preset = TransferFunction::preset(&view.preset).expect("preset");
            renderer
                .set_transfer_function(&gpu, &volume, &preset)
                .expect("the preset's table");
            let preset_frame = renderer
                .render(&gpu, &volume, &camera, &settings)
                .expect("native frame");
            let apart = compare_rgba8(&frame.rgba, &preset_frame.rgba).expect("same size");
            println!("{fragment}: browser vs the preset's native frame: {apart:?}");
            assert!(apart.psnr_db < 30.0, "{fragment}: {apart:?}");
        }
    }
    let refused = server
        .counters()
        .unauthorized
        .load(std::sync::atomic::Ordering::Relaxed);
    assert_eq!(refused, 0, "the page made requests without its token");
}

#[test]
fn a_server_without_the_page_says_how_to_build_it() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let store = scratch.path().join("tiny.strata");
    Phantom::cube(16)
        .write_store(&store, &ImportOptions::default())
        .expect("writing a tiny store");
    let server = start(
        find_stores(&[store]).expect("store found"),
        ServeOptions::default(),
    )
    .expect("server starts");
    let answer = http_get(&server.base_url(), "/");
    assert!(answer.starts_with("HTTP/1.1 404"), "{answer}");
    assert!(answer.contains("cargo run -p xtask -- web"), "{answer}");
    // The frame sink exists only on a server given one.
    let sink = http_get(&server.base_url(), "/v1/test/frame");
    assert!(sink.starts_with("HTTP/1.1 404"), "{sink}");
}

#[test]
fn the_page_is_served_with_its_security_headers_and_without_the_token() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let store = scratch.path().join("tiny.strata");
    Phantom::cube(16)
        .write_store(&store, &ImportOptions::default())
        .expect("writing a tiny store");
    let dist = scratch.path().join("dist");
    std::fs::create_dir_all(&dist).expect("dist folder");
    for (name, _) in strata_service::web_viewer::WEB_VIEWER_FILES {
        std::fs::write(dist.join(name), format!("contents of {name}")).expect("file");
    }
    let server = start(
        find_stores(&[store]).expect("store found"),
        ServeOptions {
            token: Some(TOKEN.into()),
            web_viewer: Some(std::sync::Arc::new(
                WebViewerAssets::from_dir(&dist).expect("files read"),
            )),
            ..ServeOptions::default()
        },
    )
    .expect("server starts");
    let page = http_get(&server.base_url(), "/");
    assert!(page.starts_with("HTTP/1.1 200"), "{page}");
    let lower = page.to_ascii_lowercase();
    assert!(
        lower.contains("content-security-policy: default-src 'self'"),
        "{page}"
    );
    assert!(lower.contains("referrer-policy: no-referrer"), "{page}");
    assert!(lower.contains("content-type: text/html"), "{page}");
    assert!(page.ends_with("contents of index.html"), "{page}");
    let wasm = http_get(&server.base_url(), "/strata_web_bg.wasm");
    assert!(
        wasm.to_ascii_lowercase()
            .contains("content-type: application/wasm"),
        "{wasm}"
    );
    // The data still needs the token.
    let stores = http_get(&server.base_url(), "/v1/stores");
    assert!(stores.starts_with("HTTP/1.1 401"), "{stores}");
    let unknown = http_get(&server.base_url(), "/secret.txt");
    assert!(unknown.starts_with("HTTP/1.1 404"), "{unknown}");
}

/// One HTTP/1.1 GET on a fresh connection; the whole answer as text.
fn http_get(base_url: &str, path: &str) -> String {
    use std::io::Write;
    let host = base_url.trim_start_matches("http://");
    let mut stream = std::net::TcpStream::connect(host).expect("connect");
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .expect("timeout");
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n"
    )
    .expect("request");
    let mut answer = Vec::new();
    let _ = stream.read_to_end(&mut answer);
    String::from_utf8_lossy(&answer).into_owned()
}

/// Issue 39's main path: the page opens a served store named by its link, streams it with
/// the loader inline on its one thread through `fetch()`, converges, and shows what the
/// desktop's loader shows for the same view. One brick's first answer is corrupted on the
/// server (its test hook): the page must detect it by checksum and fetch it again, or that
/// brick would be drawn from its parent and the picture would differ.
#[test]
fn the_page_streams_a_served_store_and_converges_to_the_native_loaders_picture() {
    use strata_loader::{StreamingConfig, StreamingVolume};
    use strata_types::BrickId;
    let scratch = tempfile::tempdir().expect("scratch folder");
    let path = scratch.path().join("ct.strata");
    Phantom::cube(128)
        .write_store(&path, &ImportOptions::default())
        .expect("writing the store");
    let (frames_in, frames) = mpsc::channel::<CapturedFrame>();
    let frames_in = std::sync::Mutex::new(frames_in);
    // A level-1 brick: each octant of the root holds part of the body, so every view refines
    // through it (level-0 bricks inside may stay unfetched behind bone).
    let corrupted = BrickId::new(1, [1, 0, 1]);
    let server = start(
        find_stores(std::slice::from_ref(&path)).expect("store found"),
        ServeOptions {
            web_viewer: Some(std::sync::Arc::new(web_viewer())),
            test_frame_sink: Some(FrameSink(std::sync::Arc::new(move |frame| {
                if let Ok(sender) = frames_in.lock() {
                    let _ = sender.send(frame);
                }
            }))),
            token: Some(TOKEN.into()),
            corrupt_answers: Some((corrupted, 1)),
            ..ServeOptions::default()
        },
    )
    .expect("server starts");
    // The 3D view alone: its own fetcher must meet the corrupted answer, and its bytes compare
    // with the desktop loader's (slice views fetch bricks of their own).
    let fragment = "#store=ct&mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.4&size=128x128&layout=single&capture=1";
    let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
    let launched = std::time::Instant::now();
    let browser = Browser::open(&url, scratch.path());
    let frame = frames.recv_timeout(PAGE_DEADLINE).unwrap_or_else(|_| {
        panic!(
            "the page posted no converged frame within {PAGE_DEADLINE:?}; its console:\n{}",
            browser.console()
        )
    });
    println!(
        "streamed store: converged frame back {:.1} s after launching Chromium",
        launched.elapsed().as_secs_f64()
    );
    let console = browser.console();
    drop(browser);
    let counters = server.counters();
    let bricks_served = counters.bricks.load(std::sync::atomic::Ordering::Relaxed);
    let bytes_served = counters.bytes.load(std::sync::atomic::Ordering::Relaxed);
    println!("streamed store: {bricks_served} brick answers, {bytes_served} bytes served");
    assert_eq!(
        counters
            .unauthorized
            .load(std::sync::atomic::Ordering::Relaxed),
        0,
        "the page made requests without its token"
    );
    assert!(bricks_served > 1, "the page fetched no brick past the root");
    assert_eq!(
        counters
            .corrupted
            .load(std::sync::atomic::Ordering::Relaxed),
        1,
        "the corrupted answer never reached the page"
    );

    // The desktop's loader on the same store and view through the same server (its client,
    // threads, lavapipe): the picture to match and the bytes to compare.
    let view = Fragment::parse(fragment).expect("fragment").view;
    let [width, height] = view.image_size.expect("the fragment fixes the size");
    assert_eq!((frame.width, frame.height), (width, height), "{console}");
    let gpu = GpuContext::headless().expect("a Vulkan adapter (lavapipe)");
    let remote = strata_service::client::RemoteSource::open(
        &server.store_url("ct"),
        strata_service::client::RemoteOptions {
            token: Some(TOKEN.into()),
            ..Default::default()
        },
    )
    .expect("the desktop's client opens the store");
    let mut volume = StreamingVolume::new(
        &gpu,
        std::sync::Arc::new(remote),
        &view.transfer_function(),
        StreamingConfig::default(),
    )
    .expect("native loader");
    let camera = view.camera(volume.geometry());
    let (native, history) = volume
        .render_until_converged(
            &gpu,
            &camera,
            &view.settings(volume.geometry(), width, height),
            400,
        )
        .expect("native frames");
    assert!(
        history.last().is_some_and(|s| s.converged),
        "native did not converge"
    );
    let desktop_bytes = counters.bytes.load(std::sync::atomic::Ordering::Relaxed) - bytes_served;
    // Reported (issue 39's benchmark asks <= 1.05): both run the same loader; the browser's
    // count includes the corrupted answer fetched twice.
    println!(
        "streamed store: bytes served to the browser / to the desktop = {bytes_served} / \
         {desktop_bytes} = {:.3}",
        bytes_served as f64 / desktop_bytes.max(1) as f64
    );
    let lit = frame.rgba.chunks(4).filter(|p| p[3] > 0).count();
    assert!(
        lit > (width * height / 10) as usize,
        "the browser's frame is nearly empty ({lit} pixels with coverage); its console:\n{console}"
    );
    let comparison = compare_rgba8(&frame.rgba, &native.rgba).expect("same size");
    println!("streamed store: browser (SwiftShader) vs desktop loader (lavapipe): {comparison:?}");
    // The same cut of the same bricks through the same WGSL. What may differ: the brick
    // texture's format (f32 in the browser, which has no 16-bit normalised textures; r16unorm
    // on lavapipe: 16-bit values either way, sampled with different rounding), and where
    // visibility feedback left an occluded node a level coarser (the loader tests bound that
    // at 45 dB). A corrupted brick drawn from its parent would cost far more.
    assert!(
        comparison.psnr_db >= 40.0,
        "the browser's streamed frame differs from the desktop's: {comparison:?}; console:\n{console}"
    );
}

/// A server that accepts brick requests and never answers them (its test hook: everything
/// below the root stalls): the page must go on drawing (the root's picture) rather than wait
/// for a brick, and post its frame after `UNCONVERGED_CAPTURE_FRAMES` frames drawn.
#[test]
fn a_stalled_server_leaves_the_page_drawing() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let path = scratch.path().join("ct.strata");
    Phantom::cube(96)
        .write_store(&path, &ImportOptions::default())
        .expect("writing the store");
    let (frames_in, frames) = mpsc::channel::<CapturedFrame>();
    let frames_in = std::sync::Mutex::new(frames_in);
    let server = start(
        find_stores(std::slice::from_ref(&path)).expect("store found"),
        ServeOptions {
            web_viewer: Some(std::sync::Arc::new(web_viewer())),
            test_frame_sink: Some(FrameSink(std::sync::Arc::new(move |frame| {
                if let Ok(sender) = frames_in.lock() {
                    let _ = sender.send(frame);
                }
            }))),
            stall_below_root: true,
            ..ServeOptions::default()
        },
    )
    .expect("server starts");
    let fragment =
        "#store=ct&mode=mip&preset=ct-soft-tissue&az=20&el=10&size=96x96&capture=unconverged";
    let browser = Browser::open(&format!("{}/{fragment}", server.base_url()), scratch.path());
    let frame = frames.recv_timeout(PAGE_DEADLINE).unwrap_or_else(|_| {
        panic!(
            "the page stopped drawing while its server stalled: no frame within \
             {PAGE_DEADLINE:?}; its console:\n{}",
            browser.console()
        )
    });
    let console = browser.console();
    drop(browser);
    let counters = server.counters();
    let requests = counters.requests.load(std::sync::atomic::Ordering::Relaxed);
    let bricks = counters.bricks.load(std::sync::atomic::Ordering::Relaxed);
    // Answered: the root (opening); asked and stalled: the bricks below it. The frame is the
    // root's MIP (the bone preset leaves a 32³-voxel root nearly transparent).
    assert_eq!(bricks, 1, "only the root may have been answered");
    assert!(
        requests > bricks + 1,
        "the page asked for no brick below the root ({requests} requests)"
    );
    // Relative to the frame's own size: on a loaded machine the page's rate control draws the
    // unconverged frames smaller (24x24 of the asked 96x96 was seen), which is not the failure
    // this test is about.
    let lit = frame.rgba.chunks(4).filter(|p| p[3] > 0).count();
    let pixels = (frame.width * frame.height) as usize;
    assert!(
        lit > pixels / 10,
        "the page's {}x{} frame is nearly empty while its server stalls ({lit} pixels lit); \
         console:\n{console}",
        frame.width,
        frame.height
    );
}

/// The page's slice views (slice_views.rs) slice a served store as the desktop does: after its
/// converged 3D frame the page posts its axial view's image (`capture=1`), which must equal,
/// byte for byte, the desktop's path on the same store: strata-slices' assembler fed by blocking
/// reads of the store, and the same window/level step with the store's first window.
#[test]
fn the_page_slices_a_served_store_as_the_desktops_assembler_does() {
    use strata_slices::Window;
    let scratch = tempfile::tempdir().expect("scratch folder");
    let path = scratch.path().join("ct.strata");
    Phantom::cube(96)
        .write_store(&path, &ImportOptions::default())
        .expect("writing the store");
    let (server, frames) = serve_capturing(&path);
    let fragment = "#store=ct&mode=mip&preset=ct-soft-tissue&size=64x64&capture=1";
    let (slice, console) = capture_slice(&server, fragment, scratch.path(), &frames);

    // The desktop's path: its client on the same server (the server holds the store), the
    // desktop's blocking reads, the page's request (the start crosshair, the level whose grid
    // the posted image has).
    use strata_source::VolumeSource;
    let store = desktop_client(&server, "ct");
    let header = store.header();
    let preset = header
        .windows
        .first()
        .expect("the phantom names its windows");
    let (level, desktop) = desktop_axial_slice(
        &header.layout,
        &header.geometry,
        Window::new(preset.center, preset.width),
        header.value_mapping.mapping,
        (&slice, &console),
        |id| store.read_brick(id).expect("brick"),
    );
    assert_same_slice("slice views", level, &slice, &desktop, &console);
}

/// The built-in sample has slice views too (no store: the page feeds the same assembler from
/// its in-memory octree): the axial image the page posts equals, byte for byte, the desktop's
/// assembler and window/level on the same sample made natively (the page's defaults: the
/// volume's centre, CT's abdomen window 40/400 HU for a volume in HU, grey).
#[test]
fn the_page_slices_its_built_in_sample_as_the_desktops_assembler_does() {
    assert_sample_slices_as_the_desktops(
        "sample slice views",
        "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&capture=1",
    );
}

/// The 3D view over its slices (`layout=conventional`, the desktop's "3D + 1×3", placed by
/// strata-viewer-ui's layouts as the desktop places them): the page shows its slice views in
/// that layout too, and its axial view (a third of the width, under the 3D view) equals the
/// desktop's assembler and window/level byte for byte. A page without the layout refuses the
/// link or shows no slices, and posts no slice image.
#[test]
fn the_page_shows_the_3d_view_over_its_slices_as_the_desktop_does() {
    assert_sample_slices_as_the_desktops(
        "3D over slices",
        "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&capture=1&layout=conventional",
    );
}

/// Opens the page's built-in sample at `fragment` and checks its posted axial slice against
/// the desktop's assembler on the same sample made natively.
fn assert_sample_slices_as_the_desktops(what: &str, fragment: &str) {
    use strata_render::BrickSource;
    use strata_slices::Window;
    use strata_types::OctreeLayout;
    let scratch = tempfile::tempdir().expect("scratch folder");
    // The server needs a store to serve; the page shows its own sample.
    let store = scratch.path().join("tiny.strata");
    Phantom::cube(32)
        .write_store(&store, &ImportOptions::default())
        .expect("writing a tiny store");
    let (server, frames) = serve_capturing(&store);
    let (slice, console) = capture_slice(&server, fragment, scratch.path(), &frames);

    let view = Fragment::parse(fragment).expect("fragment").view;
    let volume = view.sample_volume().expect("sample volume");
    let (level, desktop) = desktop_axial_slice(
        &OctreeLayout::new(volume.geometry.dims),
        &volume.geometry,
        Window::new(40.0, 400.0),
        volume.mapping,
        (&slice, &console),
        |id| {
            volume
                .brick(id.level, id.coords)
                .expect("in-memory brick")
                .to_vec()
        },
    );
    assert_same_slice(what, level, &slice, &desktop, &console);
}

/// A scan that names no window and is not a CT (an MR's non-negative values, no unit, no
/// modality) opens in the page at the window the desktop opens it with: strata-viewer-ui's
/// `initial_window`, one rule for both (here the 1st to 99th percentile of the store's
/// histogram). The page's axial image equals, byte for byte, the desktop's assembler and
/// window/level at that window; the page's old rule (the full stored range) gives a window
/// over twice as wide, which colours the slice visibly differently, so the comparison fails
/// for it.
#[test]
fn the_page_opens_a_scan_at_the_window_the_desktop_opens_it_with() {
    use strata_source::VolumeSource;
    use strata_viewer_ui::presets::looks_like_ct;
    use strata_viewer_ui::window_presets::{header_window, initial_window};
    let scratch = tempfile::tempdir().expect("scratch folder");
    let nrrd = scratch.path().join("mr.nrrd");
    write_mr_like_nrrd(&nrrd, 64);
    let path = scratch.path().join("mr.strata");
    let opened = strata_storage::readers::open_source(&nrrd, &Default::default())
        .expect("the NRRD reader opens the MR-like scan");
    strata_storage::import::import_source(opened, &path, &ImportOptions::default())
        .expect("importing the MR-like scan");
    let (server, frames) = serve_capturing(&path);
    let fragment = "#store=mr&mode=mip&preset=mr-default&size=64x64&capture=1";
    let (slice, console) = capture_slice(&server, fragment, scratch.path(), &frames);

    let store = desktop_client(&server, "mr");
    let header = store.header();
    let mapping = header.value_mapping.mapping;
    let (a, b) = (
        mapping.physical(header.stored_range[0] as f64),
        mapping.physical(header.stored_range[1] as f64),
    );
    let physical_range = (a.min(b), a.max(b));
    let is_ct = looks_like_ct(&header.modality, &header.value_mapping.unit, physical_range);
    assert!(
        header.windows.is_empty() && !is_ct,
        "the scan must name no window and not look like a CT: {:?}, modality {:?}, unit {:?}, \
         range {physical_range:?}",
        header.windows,
        header.modality,
        header.value_mapping.unit
    );
    let window = initial_window(header_window(&header.windows), is_ct, store.histogram());
    let full_range = physical_range.1 - physical_range.0;
    println!("MR-like scan: the desktop opens it at {window:?}; its range is {physical_range:?}");
    assert!(
        window.width < 0.5 * full_range,
        "the percentile window {window:?} is not narrower than the full range {physical_range:?}: \
         the test could not tell the two rules apart"
    );
    let (level, desktop) = desktop_axial_slice(
        &header.layout,
        &header.geometry,
        window,
        mapping,
        (&slice, &console),
        |id| store.read_brick(id).expect("brick"),
    );
    assert_same_slice("MR-like slice views", level, &slice, &desktop, &console);
}

/// An MR-like scan as NRRD (uint16, no unit, no window, no modality): air at 0, a sphere whose
/// values rise along x (300-800), and a few bright voxels (4000, well under 1 % of the volume)
/// that stretch the stored range far past the tissue's, as flow or fat artefacts do.
fn write_mr_like_nrrd(path: &Path, edge: usize) {
    let mut bytes = format!(
        "NRRD0004\ntype: uint16\ndimension: 3\nspace: left-posterior-superior\n\
         sizes: {edge} {edge} {edge}\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n\
         kinds: domain domain domain\nendian: little\nencoding: raw\n\
         space origin: (0,0,0)\n\n"
    )
    .into_bytes();
    let centre = (edge as f64 - 1.0) / 2.0;
    let radius = edge as f64 * 0.4;
    for k in 0..edge {
        for j in 0..edge {
            for i in 0..edge {
                let r = ((i as f64 - centre).powi(2)
                    + (j as f64 - centre).powi(2)
                    + (k as f64 - centre).powi(2))
                .sqrt();
                let value: u16 = if j == 0 && k == 0 && i < edge / 2 {
                    4000
                } else if r <= radius {
                    300 + (500 * i / edge) as u16
                } else {
                    0
                };
                bytes.extend_from_slice(&value.to_le_bytes());
            }
        }
    }
    std::fs::write(path, bytes).expect("writing the NRRD");
}

/// The desktop's path to the page's posted axial slice: the level whose grid the posted image
/// has, the page's start crosshair (the volume's centre), strata-slices' assembler fed by
/// `read` (blocking), and the window/level step in grey. Returns the level and the RGBA.
fn desktop_axial_slice(
    layout: &strata_types::OctreeLayout,
    geometry: &strata_render::VolumeGeometry,
    window: strata_slices::Window,
    mapping: strata_render::ValueMapping,
    posted: (&CapturedFrame, &str),
    read: impl FnMut(strata_types::BrickId) -> Vec<u16>,
) -> (usize, Vec<u8>) {
    let grey = strata_slices::ColourMap::Grey;
    desktop_axial_slice_coloured(layout, geometry, (window, grey), mapping, posted, read)
}

/// [`desktop_axial_slice`] through the colour map named with the window.
fn desktop_axial_slice_coloured(
    layout: &strata_types::OctreeLayout,
    geometry: &strata_render::VolumeGeometry,
    (window, colour_map): (strata_slices::Window, strata_slices::ColourMap),
    mapping: strata_render::ValueMapping,
    (posted, console): (&CapturedFrame, &str),
    mut read: impl FnMut(strata_types::BrickId) -> Vec<u16>,
) -> (usize, Vec<u8>) {
    use strata_slices::{window_level_rgba, SliceAssembler, SliceFrame, SliceRequest, SliceView};
    let frame = SliceFrame::for_view(SliceView::Axial, geometry);
    let level = level_of_grid(layout, &frame, posted, console);
    let cursor = geometry
        .dims
        .map(|d| ((d as f64 - 1.0) * 0.5).floor().max(0.0));
    let request = SliceRequest {
        view: SliceView::Axial,
        frame,
        position: cursor[frame.normal_axis],
        level: level as u8,
    };
    let mut assembler = SliceAssembler::new(layout.clone(), 64 << 20);
    let image = assembler
        .assemble_with(request, |id| Ok::<_, strata_slices::SliceError>(read(id)))
        .expect("the desktop's slice");
    let rgba = window_level_rgba(&image.values, window, colour_map, mapping);
    (level, rgba)
}

/// A server for the store at `path` with the page, the test token and a sink for the page's
/// captures.
fn serve_capturing(
    path: &Path,
) -> (
    strata_service::server::RunningServer,
    mpsc::Receiver<CapturedFrame>,
) {
    let (frames_in, frames) = mpsc::channel::<CapturedFrame>();
    let frames_in = std::sync::Mutex::new(frames_in);
    let server = start(
        find_stores(&[path.to_path_buf()]).expect("store found"),
        ServeOptions {
            web_viewer: Some(std::sync::Arc::new(web_viewer())),
            test_frame_sink: Some(FrameSink(std::sync::Arc::new(move |frame| {
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

/// Opens the page at `fragment` (a 64² 3D view with `capture=1`) and takes what it posts: its
/// 3D frame, then its axial slice view's image; returns that and the page's console.
fn capture_slice(
    server: &strata_service::server::RunningServer,
    fragment: &str,
    scratch: &Path,
    frames: &mpsc::Receiver<CapturedFrame>,
) -> (CapturedFrame, String) {
    let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
    let browser = Browser::open(&url, scratch);
    let wait = |what: &str| {
        frames.recv_timeout(PAGE_DEADLINE).unwrap_or_else(|_| {
            panic!(
                "the page posted no {what} within {PAGE_DEADLINE:?}; its console:\n{}",
                browser.console()
            )
        })
    };
    let three_d = wait("3D frame");
    assert_eq!((three_d.width, three_d.height), (64, 64));
    let slice = wait("slice image");
    let console = browser.console();
    (slice, console)
}

/// The desktop's client on the store `name` the server serves (with the test token): the
/// desktop's blocking reads of the same bricks the page fetched.
fn desktop_client(
    server: &strata_service::server::RunningServer,
    name: &str,
) -> strata_service::client::RemoteSource {
    strata_service::client::RemoteSource::open(
        &server.store_url(name),
        strata_service::client::RemoteOptions {
            token: Some(TOKEN.into()),
            ..Default::default()
        },
    )
    .expect("the desktop's client opens the store")
}

/// The octree level whose grid the posted slice image has.
fn level_of_grid(
    layout: &strata_types::OctreeLayout,
    frame: &strata_slices::SliceFrame,
    slice: &CapturedFrame,
    console: &str,
) -> usize {
    (0..layout.level_count())
        .find(|&l| {
            let dims = layout.level_dims[l];
            (dims[frame.across_axis], dims[frame.down_axis]) == (slice.width, slice.height)
        })
        .unwrap_or_else(|| {
            panic!(
                "the posted slice is {}×{}, no level's grid; console:\n{console}",
                slice.width, slice.height
            )
        })
}

/// The page's slice image equals the desktop's byte for byte (and shows something).
fn assert_same_slice(
    what: &str,
    level: usize,
    slice: &CapturedFrame,
    desktop: &[u8],
    console: &str,
) {
    let differing = slice
        .rgba
        .chunks(4)
        .zip(desktop.chunks(4))
        .filter(|(a, b)| a != b)
        .count();
    let distinct: std::collections::BTreeSet<u8> = desktop.chunks(4).map(|p| p[0]).collect();
    println!(
        "{what}: axial level {level}, {}×{}, {differing} pixels differ from the desktop's \
         assembler, {} grey levels",
        slice.width,
        slice.height,
        distinct.len()
    );
    assert!(
        distinct.len() > 8,
        "the slice shows nearly nothing: {distinct:?}"
    );
    assert_eq!(slice.rgba.len(), desktop.len());
    assert_eq!(
        differing, 0,
        "{what}: the page's axial slice differs from the desktop's; console:\n{console}"
    );
}

/// The page's measurements sent with its capture (strata-web's page_timing.rs), by name.
fn metric(frame: &CapturedFrame, name: &str) -> Option<f64> {
    frame
        .metrics
        .iter()
        .find_map(|(n, v)| (n == name).then_some(*v))
}

fn median_ms(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Issue 39's benchmark: the browser (Chromium, WebGPU on SwiftShader, the loader inline on
/// one thread, fetch()) against the desktop's loader (its HTTP client and threads, lavapipe)
/// on the same store through the same server: time to the first image and to convergence at
/// 128², bytes fetched; and the frame time while orbiting the page's 128³ sample at 512²
/// against the desktop's renderer on the same volume. Ratios are printed, not asserted
/// (two different software rasterisers on shared cores; see the closing note); the bytes
/// ratio is the issue's bound and is asserted.
///
/// `cargo test -p strata-web --test browser benchmark -- --ignored --nocapture`
/// Env: STRATA_BENCH_VOLUME (phantom edge, default 128), STRATA_BENCH_FRAMES (orbit frames,
/// default 24).
#[test]
#[ignore = "measurement: run with --ignored --nocapture"]
fn benchmark_the_browser_against_the_desktop_on_one_served_store() {
    use std::sync::atomic::Ordering::Relaxed;
    use std::time::Instant;
    use strata_loader::{StreamingConfig, StreamingVolume};
    let env_u32 = |name: &str, default: u32| {
        std::env::var(name)
            .ok()
            .and_then(|v| v.parse::<u32>().ok())
            .unwrap_or(default)
    };
    let edge = env_u32("STRATA_BENCH_VOLUME", 128);
    let orbit_frames = env_u32("STRATA_BENCH_FRAMES", 24);
    let scratch = tempfile::tempdir().expect("scratch folder");
    let path = scratch.path().join("ct.strata");
    Phantom::cube(edge as u64)
        .write_store(&path, &ImportOptions::default())
        .expect("writing the store");
    let (frames_in, frames) = mpsc::channel::<CapturedFrame>();
    let frames_in = std::sync::Mutex::new(frames_in);
    let server = start(
        find_stores(std::slice::from_ref(&path)).expect("store found"),
        ServeOptions {
            web_viewer: Some(std::sync::Arc::new(web_viewer())),
            test_frame_sink: Some(FrameSink(std::sync::Arc::new(move |frame| {
                if let Ok(sender) = frames_in.lock() {
                    let _ = sender.send(frame);
                }
            }))),
            token: Some(TOKEN.into()),
            ..ServeOptions::default()
        },
    )
    .expect("server starts");
    let counters = server.counters();
    // The 3D view alone, as the desktop loader it is compared with.
    let view_fragment = "store=ct&mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.4&layout=single";
    let page = |fragment: String| -> CapturedFrame {
        let url = format!("{}/#{fragment}&token={TOKEN}", server.base_url());
        let browser = Browser::open(&url, scratch.path());
        frames.recv_timeout(PAGE_DEADLINE * 2).unwrap_or_else(|_| {
            panic!(
                "the page posted no frame; its console:\n{}",
                browser.console()
            )
        })
    };

    // The browser: time to first image and convergence at 128² (as the streaming test).
    let converged = page(format!("{view_fragment}&size=128x128&capture=1"));
    let browser_bytes = counters.bytes.load(Relaxed);
    let (boot, first, done) = (
        metric(&converged, "boot_ms").expect("boot_ms"),
        metric(&converged, "first_image_ms").expect("first_image_ms"),
        metric(&converged, "converged_ms").expect("converged_ms"),
    );
    // The browser's frame time while orbiting at 512²: the page's own 128³ sample, drawn
    // whole every frame (a streamed store at 512² keeps refining while it moves, so its frame
    // time mixes loading in), against the desktop's renderer on the same volume below.
    let orbiting = page(format!(
        "mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.4&size=512x512&layout=single&capture=1&bench={orbit_frames}"
    ));
    let browser_frame_ms = metric(&orbiting, "frame_ms_median").expect("frame_ms_median");

    // The desktop's loader on the same store through the same server.
    let view = Fragment::parse(view_fragment).expect("fragment").view;
    let gpu = GpuContext::headless().expect("a Vulkan adapter (lavapipe)");
    let bytes_before = counters.bytes.load(Relaxed);
    let opened_at = Instant::now();
    let remote = strata_service::client::RemoteSource::open(
        &server.store_url("ct"),
        strata_service::client::RemoteOptions {
            token: Some(TOKEN.into()),
            ..Default::default()
        },
    )
    .expect("the desktop's client opens the store");
    let mut volume = StreamingVolume::new(
        &gpu,
        std::sync::Arc::new(remote),
        &view.transfer_function(),
        StreamingConfig::default(),
    )
    .expect("native loader");
    let camera = view.camera(volume.geometry());
    let settings = view.settings(volume.geometry(), 256, 256);
    let mut desktop_first = None;
    let desktop_converged = loop {
        let stats = volume.frame(&gpu, &camera, &settings).expect("frame");
        volume.wait_for_gpu(&gpu).expect("GPU");
        desktop_first.get_or_insert(opened_at.elapsed().as_secs_f64() * 1e3);
        if stats.converged {
            break opened_at.elapsed().as_secs_f64() * 1e3;
        }
        assert!(
            opened_at.elapsed() < PAGE_DEADLINE,
            "the desktop's loader did not converge"
        );
        std::thread::sleep(Duration::from_millis(1));
    };
    let desktop_first = desktop_first.unwrap_or(desktop_converged);
    let desktop_bytes = counters.bytes.load(Relaxed) - bytes_before;
    // The desktop's frame time orbiting at 512² on the page's sample, as the page's bench: 2°
    // a frame, each frame finished before the next (the page's frames are presented).
    let sample_view = Fragment::parse("mode=dvr&preset=ct-bone&az=35&el=20&zoom=1.4")
        .expect("fragment")
        .view;
    let sample = sample_view.sample_volume().expect("the sample volume");
    let mut renderer = OffscreenRenderer::new(
        &gpu,
        &sample,
        &sample_view.transfer_function(),
        0,
        CacheConfig::default(),
    )
    .expect("renderer");
    let settings = sample_view.settings(&sample.geometry, 512, 512);
    let mut moving = sample_view.clone();
    let mut desktop_frames = Vec::new();
    for _ in 0..=orbit_frames {
        moving.azimuth_deg += 2.0;
        let camera = moving.camera(&sample.geometry);
        let started = Instant::now();
        renderer
            .submit(&gpu, &sample, &camera, &settings)
            .expect("frame");
        gpu.wait_idle().expect("GPU");
        desktop_frames.push(started.elapsed().as_secs_f64() * 1e3);
    }
    // The first frame compiles the pipeline.
    desktop_frames.remove(0);
    let desktop_frame_ms = median_ms(desktop_frames);

    let bytes_ratio = browser_bytes as f64 / desktop_bytes.max(1) as f64;
    println!("| {edge}³ phantom store, DVR, token | browser (SwiftShader) | desktop loader (lavapipe) | browser / desktop |");
    println!("|---|---:|---:|---:|");
    println!(
        "| first image at 128² (ms, from module start / from open) | {:.0} | {desktop_first:.0} | {:.2} |",
        first - boot,
        (first - boot) / desktop_first
    );
    println!(
        "| converged at 128² (ms) | {:.0} | {desktop_converged:.0} | {:.2} |",
        done - boot,
        (done - boot) / desktop_converged
    );
    println!(
        "| frame while orbiting the 128³ sample at 512² (ms, median of {orbit_frames}) | {browser_frame_ms:.1} | {desktop_frame_ms:.1} | {:.2} |",
        browser_frame_ms / desktop_frame_ms
    );
    println!("| bytes to convergence | {browser_bytes} | {desktop_bytes} | {bytes_ratio:.3} |");
    println!(
        "browser: page navigation to module start {boot:.0} ms (loading and compiling the wasm), \
         navigation to first image {first:.0} ms, to convergence {done:.0} ms"
    );
    // Whether decoding needs web workers (issue 39 item 2): the page's one thread decodes and
    // verifies every record inline, at most DECODES_PER_FRAME a frame.
    if let (Some(total), Some(records), Some(worst)) = (
        metric(&converged, "decode_ms_total"),
        metric(&converged, "decoded_records"),
        metric(&converged, "decode_ms_worst_frame"),
    ) {
        println!(
            "browser decoding: {records:.0} records in {total:.0} ms ({:.2} ms each, {:.1} % of \
             module start to convergence), at most {worst:.1} ms in one frame",
            total / records.max(1.0),
            100.0 * total / (done - boot).max(1.0)
        );
    }
    assert!(
        bytes_ratio <= 1.05,
        "the browser fetched more than the desktop: {browser_bytes} / {desktop_bytes}"
    );
    server.stop();
}

/// The notebook widget's front end (python/strata/widget.js, issue 50) in a minimal
/// anywidget-style host: a page of another origin that imports the module and calls its
/// `render({ model, el })` with a model object as anywidget gives one (get, set, on, off,
/// send, save_changes, custom messages), and plays the kernel's part itself. It reports what
/// it saw to this test over HTTP.
const WIDGET_JS: &str = include_str!("../../python/strata/widget.js");

/// The host's script: the steps of the test, run in the browser.
const WIDGET_HOST_JS: &str = r#"
import widget from "/widget.js";
const config = JSON.parse(document.getElementById("config").textContent);
const report = (name, body) => fetch(`/report/${name}`, { method: "POST", body });
const fail = (e) => report("error", String((e && e.stack) || e));
window.addEventListener("error", (e) => fail(e.message));
window.addEventListener("unhandledrejection", (e) => fail(e.reason));
const VIEW = ["azimuth", "elevation", "zoom", "preset"];

// anywidget's model contract: a change fires `change:NAME`; the kernel's custom messages
// arrive as `msg:custom`; `send` goes to the kernel (played below).
class Model {
  constructor(state, kernel) {
    this.state = { ...state };
    this.listeners = new Map();
    this.kernel = kernel;
    this.saves = 0;
  }
  get(name) { return this.state[name]; }
  set(name, value) {
    const old = this.state[name];
    this.state[name] = value;
    if (old !== value) this.emit(`change:${name}`, this, value);
  }
  on(event, fn) {
    if (!this.listeners.has(event)) this.listeners.set(event, []);
    this.listeners.get(event).push(fn);
  }
  off(event, fn) {
    const list = this.listeners.get(event) || [];
    const i = list.indexOf(fn);
    if (i >= 0) list.splice(i, 1);
  }
  emit(event, ...args) { for (const fn of [...(this.listeners.get(event) || [])]) fn(...args); }
  save_changes() { this.saves += 1; }
  send(content, _callbacks, buffers) { this.kernel(content, buffers || []); }
}

const shots = new Map();
let nextShot = 1;
// Python's side: the page's address on `ready`, screenshots' answers.
const model = new Model(
  { azimuth: 30, elevation: 15, zoom: 1.2, preset: "ct-bone", height: 300, store: "" },
  (content, buffers) => {
    if (content.type === "ready") {
      setTimeout(() => model.emit("msg:custom", { type: "connect", url: config.page }, []), 0);
    } else if (content.type === "screenshot") {
      const waiting = shots.get(content.id);
      shots.delete(content.id);
      if (content.error || !(buffers[0] instanceof ArrayBuffer)) waiting.reject(content.error);
      else waiting.resolve(buffers[0]);
    }
  },
);
const screenshot = () => new Promise((resolve, reject) => {
  const id = nextShot++;
  shots.set(id, { resolve, reject });
  model.emit("msg:custom", { type: "screenshot", id }, []);
});
const view = () => Object.fromEntries(VIEW.map((n) => [n, model.get(n)]));
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
// Resolves once `name` left `from` and then stayed put for `quietMs`.
const settled = (name, from, quietMs) => new Promise((resolve) => {
  let timer = null;
  const changed = () => {
    if (model.get(name) === from) return;
    clearTimeout(timer);
    timer = setTimeout(() => { model.off(`change:${name}`, changed); resolve(); }, quietMs);
  };
  model.on(`change:${name}`, changed);
});

const cleanup = widget.render({ model, el: document.getElementById("cell") });
// 1. The page's own orbit (its bench hook turns the view once drawn) reaches the model.
await settled("azimuth", 30, 5000);
const orbited = view();
const first = await screenshot();
await report("orbited", JSON.stringify({ view: orbited, saves: model.saves }));
await report("shot-orbited", first);
// 2. Python's side sets the traits: the page moves (its screenshot shows the new view).
model.set("azimuth", -70);
model.set("elevation", -25);
model.set("zoom", 1.4);
model.set("preset", "ct-soft-tissue");
const second = await screenshot();
await report("shot-set", second);
// 3. The page's report of the view it was given leaves the model as set.
await sleep(1500);
await report("after-set", JSON.stringify({ view: view() }));
if (typeof cleanup === "function") cleanup();
await report("done", "");
"#;

/// A tiny HTTP/1.1 server for the host page (its own origin: another port) that passes
/// `POST /report/NAME` bodies to the test.
fn serve_widget_host(
    listener: std::net::TcpListener,
    page_url: String,
) -> mpsc::Receiver<(String, Vec<u8>)> {
    let (reports_in, reports) = mpsc::channel();
    let html = format!(
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>widget host</title></head>\
         <body><div id=\"cell\" style=\"width:460px\"></div>\
         <script type=\"application/json\" id=\"config\">{}</script>\
         <script type=\"module\" src=\"/host.js\"></script></body></html>",
        serde_json::json!({ "page": page_url })
    );
    let html = std::sync::Arc::new(html);
    // One thread per connection: Chromium opens speculative connections that may never send a
    // request, and a server reading connections one after another waits on such a socket forever
    // while the page's reports queue behind it (how this test hung here, four runs in five).
    std::thread::Builder::new()
        .name("widget-host".into())
        .spawn(move || {
            for stream in listener.incoming() {
                let Ok(stream) = stream else { continue };
                let (html, reports_in) = (html.clone(), reports_in.clone());
                let _ = std::thread::Builder::new()
                    .name("widget-host-connection".into())
                    .spawn(move || answer_widget_host_request(stream, &html, &reports_in));
            }
        })
        .expect("host thread");
    reports
}

/// Answers one request of the widget host's server: its page, its scripts, a report.
fn answer_widget_host_request(
    mut stream: std::net::TcpStream,
    html: &str,
    reports_in: &mpsc::Sender<(String, Vec<u8>)>,
) {
    use std::io::{BufRead, BufReader, Write};
    let Ok(clone) = stream.try_clone() else {
        return;
    };
    let mut reader = BufReader::new(clone);
    let mut request_line = String::new();
    if reader.read_line(&mut request_line).unwrap_or(0) == 0 {
        return;
    }
    let mut length = 0usize;
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line).unwrap_or(0) == 0 || line.trim().is_empty() {
            break;
        }
        if let Some((name, value)) = line.split_once(':') {
            if name.eq_ignore_ascii_case("content-length") {
                length = value.trim().parse().unwrap_or(0);
            }
        }
    }
    let mut body = vec![0u8; length];
    if reader.read_exact(&mut body).is_err() {
        return;
    }
    let mut parts = request_line.split_whitespace();
    let (method, path) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""));
    let (status, kind, answer): (&str, &str, &[u8]) = match (method, path) {
        ("GET", "/") => ("200 OK", "text/html", html.as_bytes()),
        ("GET", "/host.js") => ("200 OK", "text/javascript", WIDGET_HOST_JS.as_bytes()),
        ("GET", "/widget.js") => ("200 OK", "text/javascript", WIDGET_JS.as_bytes()),
        ("POST", report) if report.starts_with("/report/") => {
            let name = report.trim_start_matches("/report/").to_string();
            let _ = reports_in.send((name, body));
            ("204 No Content", "text/plain", b"")
        }
        _ => ("404 Not Found", "text/plain", b"not found"),
    };
    let _ = write!(
        stream,
        "HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\n\
         Connection: close\r\n\r\n",
        answer.len()
    );
    let _ = stream.write_all(answer);
}

fn decode_png(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes))
        .read_info()
        .expect("the screenshot is a PNG");
    let mut rgba = vec![0; reader.output_buffer_size().expect("size")];
    let info = reader.next_frame(&mut rgba).expect("PNG pixels");
    assert_eq!(info.color_type, png::ColorType::Rgba, "RGBA expected");
    rgba.truncate(info.buffer_size());
    (info.width, info.height, rgba)
}

#[test]
fn the_notebook_widget_draws_the_volume_and_syncs_its_view_both_ways() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let store = scratch.path().join("tiny.strata");
    Phantom::cube(32)
        .write_store(&store, &ImportOptions::default())
        .expect("writing a tiny store");
    let host = std::net::TcpListener::bind("127.0.0.1:0").expect("host port");
    let host_origin = format!("http://{}", host.local_addr().expect("host address"));
    // The widget's server: framable by the notebook's origin only (the default is nobody).
    let server = start(
        find_stores(&[store]).expect("store found"),
        ServeOptions {
            web_viewer: Some(std::sync::Arc::new(web_viewer())),
            token: Some(TOKEN.into()),
            frame_ancestors: Some(host_origin.clone()),
            ..ServeOptions::default()
        },
    )
    .expect("server starts");
    // The page's sample volume, a fixed image size and one view; `bench=6`: the page orbits
    // six frames once drawn, as a user's drag would (a drag cannot be sent into a
    // cross-origin frame from the host page).
    let page = format!(
        "{}/#volume=48&size=128x128&layout=single&bench=6&token={TOKEN}",
        server.base_url()
    );
    let reports = serve_widget_host(host, page);
    let browser = Browser::open(&format!("{host_origin}/"), scratch.path());
    let next = |expected: &str| -> Vec<u8> {
        let (name, body) = reports.recv_timeout(PAGE_DEADLINE).unwrap_or_else(|_| {
            panic!(
                "the host page reported no `{expected}` within {PAGE_DEADLINE:?}; console:\n{}",
                browser.console()
            )
        });
        assert_ne!(
            name,
            "error",
            "the host page failed: {}\nconsole:\n{}",
            String::from_utf8_lossy(&body),
            browser.console()
        );
        assert_eq!(name, expected, "{}", browser.console());
        body
    };
    let orbited: serde_json::Value = serde_json::from_slice(&next("orbited")).expect("JSON");
    let shot_orbited = next("shot-orbited");
    let shot_set = next("shot-set");
    let after_set: serde_json::Value = serde_json::from_slice(&next("after-set")).expect("JSON");
    next("done");
    let console = browser.console();
    drop(browser);

    // The page's orbit moved the model's azimuth, and only that.
    let azimuth = orbited["view"]["azimuth"].as_f64().expect("azimuth");
    assert!(
        azimuth > 31.0,
        "the orbit did not reach the model: {orbited}"
    );
    assert_eq!(orbited["view"]["elevation"], 15.0, "{orbited}");
    assert_eq!(orbited["view"]["zoom"], 1.2, "{orbited}");
    assert_eq!(orbited["view"]["preset"], "ct-bone", "{orbited}");
    assert!(orbited["saves"].as_u64() >= Some(1), "{orbited}");
    // Python's values stay as set: the page's report of them is no change.
    assert_eq!(
        after_set["view"],
        serde_json::json!({"azimuth": -70, "elevation": -25, "zoom": 1.4, "preset": "ct-soft-tissue"}),
    );

    // Each screenshot is the view the model names, as the native renderer draws it.
    let gpu = GpuContext::headless().expect("a Vulkan adapter (lavapipe)");
    let native = |fragment: &str| {
        let view = Fragment::parse(fragment).expect("fragment").view;
        let volume = view.sample_volume().expect("sample volume");
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
        let (camera, settings) = (
            view.camera(&volume.geometry),
            view.settings(&volume.geometry, 128, 128),
        );
        renderer
            .render(&gpu, &volume, &camera, &settings)
            .expect("native frame")
            .rgba
    };
    let mut frames = Vec::new();
    for (shot, fragment) in [
        (
            &shot_orbited,
            format!("#volume=48&size=128x128&az={azimuth}&el=15&zoom=1.2&preset=ct-bone"),
        ),
        (
            &shot_set,
            "#volume=48&size=128x128&az=-70&el=-25&zoom=1.4&preset=ct-soft-tissue".to_string(),
        ),
    ] {
        let (width, height, rgba) = decode_png(shot);
        assert_eq!((width, height), (128, 128), "{console}");
        // The ct-bone view shows the phantom's bone only: about a tenth of the image.
        let lit = rgba.chunks(4).filter(|p| p[3] > 0).count();
        assert!(
            lit > 128 * 128 / 25,
            "{fragment}: the widget's screenshot is nearly empty ({lit} pixels); console:\n{console}"
        );
        let comparison = compare_rgba8(&rgba, &native(&fragment)).expect("same size");
        println!("{fragment}: widget screenshot vs native: {comparison:?}");
        // As the page's own capture above: same WGSL on two CPU drivers.
        assert!(
            comparison.psnr_db >= 40.0,
            "{fragment}: the screenshot is not this view: {comparison:?}"
        );
        frames.push(rgba);
    }
    let apart = compare_rgba8(&frames[0], &frames[1]).expect("same size");
    assert!(
        apart.psnr_db < 30.0,
        "setting the traits did not move the view: {apart:?}"
    );
    let refused = server
        .counters()
        .unauthorized
        .load(std::sync::atomic::Ordering::Relaxed);
    assert_eq!(refused, 0, "the page made requests without its token");
}
