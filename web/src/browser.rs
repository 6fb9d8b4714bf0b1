//! The page's entry point and the viewer app (wasm32 only).
//!
//! One thread: eframe's web runner calls [`WebViewer::ui`] from requestAnimationFrame, and
//! nothing here blocks (the browser's event loop resolves every GPU promise). A frame is
//! submitted only when the view or the image size changed, or while a still view refines
//! (refine.rs: one pass per animation frame, then rest) or is drawn by the adaptive pass
//! (adaptive.rs: a few oracle slots per animation frame, then one frame), so a still page does
//! no GPU work.
//! The raycaster draws into its own Rgba8Unorm texture, which egui samples directly
//! (`register_native_texture`): no readback, no copy.

use std::cell::RefCell;
use std::rc::Rc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};

use eframe::egui_wgpu;
use strata_loader::{
    FrameStats, LoaderError, LoaderWork, SelectionTiming, StreamingConfig, StreamingVolume,
};
use strata_render::{
    BrickedVolume, CacheConfig, GpuContext, OffscreenRenderer, RenderMode, TransferFunction,
    VolumeGeometry,
};
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;

use crate::adaptive::StillAdaptive;
use crate::embed_bridge::{embed_origin, EmbedBridge};
use crate::oblique_view::{oblique_toggle, place_views, ObliqueView};
use crate::orbit_movie::OrbitMovie;
use crate::page_timing::{PageTiming, BENCH_DEG_PER_FRAME};
use crate::page_tools::{self, PageTools};
use crate::picking::PendingPick;
use crate::refine::Refinement;
use crate::segment_3d::Segment3d;
use crate::served_store::{list_stores, ServedStore, DECODES_PER_FRAME, MAX_ON_THE_WIRE};
use crate::side_panel::{SidePanel, VolumeFigures};
use crate::slice_views::SliceViews;
use crate::view_motion::{ViewMotion, MOTION_HOLD_S};
use crate::view_state::{Fragment, Layout, ViewState};
use crate::volume_menu;
use strata_source::wire::StoreList;
use strata_source::VolumeSource;
use strata_viewer_ui::orbit;
use strata_viewer_ui::picking::frame_pixel;
use strata_viewer_ui::presets;
use strata_viewer_ui::render_driver::{
    OverlayIn3d, RenderChange, RenderDriver, RenderRequest, DEFAULT_PROGRESSIVE_FRAMES,
};
use strata_viewer_ui::segment_panel::SegmentTool;
use strata_viewer_ui::triad;

/// The largest image edge drawn when the canvas decides (device pixels): a 4K canvas is drawn
/// at this size and scaled, so one frame stays bounded on a software adapter.
const MAX_CANVAS_IMAGE_EDGE: f32 = 2048.0;

/// A press in the 3D view that egui calls a drag (held past its click time) is still a click
/// while the pointer moved less than this (points) before the release.
const HELD_CLICK_TRAVEL: f32 = 2.0;

/// Called by the wasm-bindgen glue when the module loads.
#[wasm_bindgen(start)]
pub fn start() {
    wasm_bindgen_futures::spawn_local(async {
        if let Err(problem) = run().await {
            show_message("The viewer could not start", &problem.to_string());
        }
    });
}

/// Replaces the canvas with a message (the page's own element, not egui: it works when the
/// GPU does not).
fn show_message(title: &str, detail: &str) {
    let Some(document) = web_sys::window().and_then(|w| w.document()) else {
        return;
    };
    if let Some(element) = document.get_element_by_id("strata-message") {
        element.set_text_content(Some(&format!("{title}: {detail}")));
        let _ = element.remove_attribute("hidden");
    }
    if let Some(canvas) = document.get_element_by_id("strata-canvas") {
        let _ = canvas.set_attribute("hidden", "");
    }
    web_sys::console::error_1(&format!("strata: {title}: {detail}").into());
}

/// Why the page stopped: shown in place of the view (or of the canvas, when it cannot start).
#[derive(Debug, thiserror::Error)]
enum PageError {
    /// A part of the page or of its result that is not there.
    #[error("{0}")]
    Missing(&'static str),
    #[error(transparent)]
    Link(#[from] crate::view_state::FragmentError),
    /// A JavaScript exception, as its debug text (a `JsValue` is neither `Send` nor an error).
    #[error("{0}")]
    Js(String),
    #[error(transparent)]
    Render(#[from] strata_render::RenderError),
    #[error(transparent)]
    Loader(#[from] LoaderError),
    #[error(transparent)]
    Source(#[from] strata_source::SourceError),
    #[error(transparent)]
    SliceViews(#[from] crate::slice_views::SliceViewsError),
    #[error(transparent)]
    ObliqueView(#[from] crate::oblique_view::ObliqueViewError),
    /// wgpu's reason a mapped buffer could not be read.
    #[error("{0}")]
    Readback(String),
    #[error(transparent)]
    Png(#[from] png::EncodingError),
    #[error("the screenshot's buffer could not be mapped")]
    ScreenshotBuffer,
    #[error("the server answered {0}")]
    ServerAnswered(u16),
}

impl PageError {
    fn js(value: JsValue) -> Self {
        PageError::Js(format!("{value:?}"))
    }
}

async fn run() -> Result<(), PageError> {
    let window = web_sys::window().ok_or(PageError::Missing("no window object"))?;
    let document = window.document().ok_or(PageError::Missing("no document"))?;
    let canvas = document
        .get_element_by_id("strata-canvas")
        .ok_or(PageError::Missing("the page has no #strata-canvas"))?
        .dyn_into::<web_sys::HtmlCanvasElement>()
        .map_err(|_| PageError::Missing("#strata-canvas is not a canvas"))?;
    let hash = window.location().hash().unwrap_or_default();
    let fragment = Fragment::parse(&hash)?;
    // Read before the address is rewritten below (the view's own keys only).
    let embed = embed_origin(&hash);
    if fragment.token.is_some() {
        // The token leaves the address bar (and history) at once; the page keeps it in memory.
        if let Ok(history) = window.history() {
            let _ = history.replace_state_with_url(
                &JsValue::NULL,
                "",
                Some(&fragment.view.to_fragment()),
            );
        }
    }
    let mut options = eframe::WebOptions::default();
    options.wgpu_options.wgpu_setup =
        egui_wgpu::WgpuSetup::CreateNew(egui_wgpu::WgpuSetupCreateNew {
            // The raycaster's needs: filterable f32 bricks (no 16-bit normalised textures on
            // WebGPU without texture-formats-tier1, and wgpu cannot ask for it there),
            // timestamps when offered, and the adapter's own limits (eframe asks for the
            // defaults, which cap 3D textures and bindings below what the cache can use).
            device_descriptor: Arc::new(|adapter| {
                let wanted = wgpu::Features::FLOAT32_FILTERABLE | wgpu::Features::TIMESTAMP_QUERY;
                wgpu::DeviceDescriptor {
                    label: Some("strata-web"),
                    required_features: adapter.features() & wanted,
                    required_limits: adapter.limits(),
                    ..Default::default()
                }
            }),
            ..egui_wgpu::WgpuSetupCreateNew::without_display_handle()
        });
    eframe::WebRunner::new()
        .start(
            canvas,
            options,
            Box::new(move |cc| {
                let viewer = WebViewer::new(cc, fragment, embed)?;
                Ok(Box::new(viewer))
            }),
        )
        .await
        .map_err(PageError::js)
}

/// Where the test capture stands (an atomic because the map callback must be `Send` on the
/// wgpu API, although the browser calls it on this one thread).
const CAPTURE_MAPPING: u8 = 1;
const CAPTURE_MAPPED: u8 = 2;
const CAPTURE_FAILED: u8 = 3;
const CAPTURE_SENT: u8 = 4;
/// The frame's post is under way: the slice image waits for it, so the server's sink gets
/// the frame first (two posts in flight at once arrived in either order).
const CAPTURE_POSTING: u8 = 5;

struct Capture {
    buffer: wgpu::Buffer,
    padded_row: u32,
    size: [u32; 2],
    state: Arc<AtomicU8>,
}

/// A served store streamed by the loader, inline on the page's thread.
struct Streamed {
    volume: StreamingVolume,
    /// What is applied to `volume` and which request its last frame answered (the render
    /// driver both viewers share, strata_viewer_ui::render_driver).
    driver: RenderDriver,
    /// The last frame's loader statistics (converged, bricks read, status).
    last: Option<FrameStats>,
    /// The three slice views beside the 3D view (slice_views.rs).
    slices: SliceViews,
    /// The oblique view, shown while the link names it (oblique_view.rs).
    oblique: ObliqueView,
    /// A 4-D store's frames: the one shown, the panel, cine (frames.rs).
    frames: Option<crate::frames::PageFrames>,
}

/// The store being opened: filled by the open's future, taken by the next frame.
type Opening = Rc<RefCell<Option<Result<ServedStore, strata_source::SourceError>>>>;

/// The server's store list, filled by its request's future.
type Stores = Rc<RefCell<Option<Result<StoreList, crate::served_store::ListStoresError>>>>;

struct WebViewer {
    render_state: egui_wgpu::RenderState,
    stores: Stores,
    streamed: Option<Streamed>,
    opening: Option<Opening>,
    gpu: GpuContext,
    view: ViewState,
    /// The sample, shared with its slice views (they read its bricks).
    volume: Option<Rc<BrickedVolume>>,
    /// The sample's three slice views (slice_views.rs), made with it.
    sample_slices: Option<SliceViews>,
    /// The sample's oblique view (oblique_view.rs), made with it.
    sample_oblique: Option<ObliqueView>,
    renderer: Option<OffscreenRenderer>,
    /// The sample renderer's applied transfer function and last drawn request (the render
    /// driver's typed difference, as the streamed volume's).
    sample_driver: Option<RenderDriver>,
    /// The transfer-function editor and the Performance panel (side_panel.rs).
    side: SidePanel,
    texture: Option<egui::TextureId>,
    /// The view and image size of the frame on screen.
    drawn: Option<(ViewState, [u32; 2])>,
    frames_submitted: u64,
    /// Frames `ui` ran before the volume was generated (the first one paints the notice).
    waited_frames: u32,
    error: Option<String>,
    gpu_error: Arc<Mutex<Option<String>>>,
    device_lost: Arc<Mutex<Option<String>>>,
    fragment_written: String,
    capture: Option<Capture>,
    /// The bearer token from the link's fragment: kept in memory, sent as `Authorization`.
    token: Option<String>,
    /// Time to first and converged image, the bench's frame times (sent with the capture).
    timing: PageTiming,
    /// The target-fps control's controller while the view moves (view_motion.rs), on the
    /// page's clock (`page_started`).
    motion: ViewMotion,
    page_started: web_time::Instant,
    /// The link named a preset: the store's own choice does not replace it.
    preset_named: bool,
    /// In a notebook (`embed=ORIGIN`): the widget's postMessage bridge (embed_bridge.rs).
    bridge: Option<EmbedBridge>,
    /// A screenshot the bridge was asked for, being read back, and the requests it answers.
    screenshot: Option<(Capture, Vec<JsValue>)>,
    /// A click in the 3D view whose pick depth is on its way back (picking.rs).
    pick: Option<PendingPick>,
    /// The segment tools' gesture in the 3D view and its picks on their way (segment_3d.rs).
    segment_3d: Segment3d,
    /// How far the pointer has moved in the 3D view's current drag (points).
    drag_travel: f32,
    /// Undo and redo, the shared keys and help, the screenshot download (page_tools.rs).
    tools: PageTools,
    /// The 3D frame being read back for a screenshot download (F12, Screenshot).
    download: Option<Capture>,
    /// Progressive refinement of the still 3D view (refine.rs).
    refine: Refinement,
    /// The still view drawn by the adaptive pass, its oracle built across frames (adaptive.rs).
    adaptive: StillAdaptive,
    /// The orbit movie being made (orbit_movie.rs) and its frame being read back.
    movie: OrbitMovie,
    movie_frame: Option<Capture>,
}

impl WebViewer {
    fn new(
        cc: &eframe::CreationContext<'_>,
        fragment: Fragment,
        embed: Option<String>,
    ) -> Result<Self, Box<dyn std::error::Error + Send + Sync>> {
        let render_state = cc
            .wgpu_render_state
            .clone()
            .ok_or("eframe started without wgpu")?;
        let info = render_state.adapter.get_info();
        if info.backend != wgpu::Backend::BrowserWebGpu {
            // WebGL2 has no compute shaders: the raycaster cannot run on it.
            return Err(format!(
                "the browser offered {:?}, not WebGPU; the raycaster needs WebGPU's compute \
                 shaders (Chrome or Edge 113+, Firefox 141+, Safari 26+)",
                info.backend
            )
            .into());
        }
        let device = render_state.device.clone();
        let gpu_error = Arc::new(Mutex::new(None::<String>));
        let slot = gpu_error.clone();
        // wgpu's default handler panics; a GPU error here becomes a message on the page.
        device.on_uncaptured_error(Arc::new(move |error: wgpu::Error| {
            let mut first = slot.lock().unwrap_or_else(|p| p.into_inner());
            first.get_or_insert_with(|| error.to_string());
        }));
        let device_lost = Arc::new(Mutex::new(None::<String>));
        let lost = device_lost.clone();
        device.set_device_lost_callback(move |reason, message| {
            let mut slot = lost.lock().unwrap_or_else(|p| p.into_inner());
            slot.get_or_insert_with(|| format!("{reason:?}: {message}"));
        });
        let gpu = GpuContext::from_device(device, render_state.queue.clone());
        let motion = ViewMotion::new(gpu.supports_timestamps());
        // Dark, as the desktop viewer and every reading room: a light page around a volume
        // rendering dazzles and changes how its contrast reads.
        cc.egui_ctx.set_theme(egui::Theme::Dark);
        let fragment_written = fragment.view.to_fragment();
        let stores: Stores = Rc::default();
        let (filled, token, repaint) =
            (stores.clone(), fragment.token.clone(), cc.egui_ctx.clone());
        wasm_bindgen_futures::spawn_local(async move {
            let listed = list_stores(token.as_deref()).await;
            *filled.borrow_mut() = Some(listed);
            repaint.request_repaint();
        });
        let side = SidePanel::new(&fragment.view, info.name.clone());
        let bridge = embed
            .map(|origin| EmbedBridge::new(origin, cc.egui_ctx.clone()))
            .transpose()?;
        Ok(WebViewer {
            render_state,
            stores,
            streamed: None,
            opening: None,
            gpu,
            timing: PageTiming::new(fragment.view.bench_frames),
            view: fragment.view,
            volume: None,
            sample_slices: None,
            sample_oblique: None,
            renderer: None,
            sample_driver: None,
            side,
            texture: None,
            drawn: None,
            frames_submitted: 0,
            waited_frames: 0,
            error: None,
            gpu_error,
            device_lost,
            fragment_written,
            capture: None,
            token: fragment.token,
            motion,
            page_started: web_time::Instant::now(),
            preset_named: fragment.preset_named,
            bridge,
            screenshot: None,
            pick: None,
            segment_3d: Segment3d::default(),
            drag_travel: 0.0,
            tools: PageTools::default(),
            download: None,
            refine: Refinement::new(),
            adaptive: StillAdaptive::default(),
            movie: OrbitMovie::default(),
            movie_frame: None,
        })
    }

    /// Makes the volume and the renderer on the second frame (the first shows the notice).
    fn ensure_renderer(&mut self, ctx: &egui::Context) -> Result<bool, PageError> {
        if self.volume.is_none() {
            self.waited_frames += 1;
            if self.waited_frames < 2 {
                ctx.request_repaint();
                return Ok(false);
            }
            let volume = Rc::new(self.view.sample_volume()?);
            let mut slices = SliceViews::for_sample(volume.clone());
            slices.set_from_link(self.view.cursor, self.view.window);
            slices.colour_map = self.view.colour_map;
            self.sample_slices = Some(slices);
            let angles = self.view.oblique.unwrap_or_default();
            self.sample_oblique = Some(ObliqueView::for_sample(volume.clone(), angles));
            self.volume = Some(volume);
            self.side.set_sample_histogram(&self.view);
        }
        let Some(volume) = self.volume.as_ref() else {
            return Ok(false);
        };
        if self.renderer.is_none() {
            let config = CacheConfig {
                // What the volume needs and no more: the page shares the GPU with the tab.
                budget_bytes: 256 << 20,
                ..CacheConfig::default()
            };
            let transfer_function = self.side.transfer_function(&self.view);
            let renderer =
                OffscreenRenderer::new(&self.gpu, volume, &transfer_function, 0, config)?;
            self.renderer = Some(renderer);
            self.sample_driver = Some(RenderDriver::new(transfer_function, None));
        }
        Ok(true)
    }

    /// Opens the fragment's store (asynchronously) and starts the loader on it once open.
    fn ensure_stream(&mut self, ctx: &egui::Context, name: &str) -> Result<bool, PageError> {
        if self.streamed.is_some() {
            return Ok(true);
        }
        let Some(opening) = self.opening.clone() else {
            let slot: Opening = Rc::default();
            let filled = slot.clone();
            let (name, token, repaint) = (name.to_string(), self.token.clone(), ctx.clone());
            wasm_bindgen_futures::spawn_local(async move {
                let opened = ServedStore::open(&name, token).await;
                *filled.borrow_mut() = Some(opened);
                repaint.request_repaint();
            });
            self.opening = Some(slot);
            return Ok(false);
        };
        let Some(opened) = opening.borrow_mut().take() else {
            return Ok(false);
        };
        let store = Arc::new(opened?);
        // The preset fits the scan: the one it opens with (the desktop's choice, issue 47: an
        // MR opened with the CT bone preset) unless the link named one.
        let scan = presets::ScanValues::of(store.header());
        if !self.preset_named {
            self.view.preset = presets::initial_preset(&scan).into();
        }
        self.side.set_scan(scan);
        self.side.set_histogram(
            store.histogram().clone(),
            &store.header().value_mapping.unit,
        );
        let mut slices = SliceViews::new(store.as_ref())?;
        // The link's crosshair and window, if it names them.
        slices.set_from_link(self.view.cursor, self.view.window);
        slices.colour_map = self.view.colour_map;
        let oblique = ObliqueView::new(store.as_ref(), self.view.oblique.unwrap_or_default())?;
        let now_s = self.page_started.elapsed().as_secs_f64();
        let frames = crate::frames::PageFrames::for_store(&store, now_s);
        let transfer_function = self.side.transfer_function(&self.view);
        let volume = StreamingVolume::new(&self.gpu, store, &transfer_function, page_streaming())?;
        self.adaptive.new_volume();
        self.streamed = Some(Streamed {
            volume,
            // The page streams with the loader's choice of traversal.
            driver: RenderDriver::new(transfer_function, None),
            last: None,
            slices,
            oblique,
            frames,
        });
        Ok(true)
    }

    /// A 4-D store: once the frame the link, the slider or cine asks for is open (frames.rs),
    /// the 3D view streams it (a new streaming volume: the old one's GPU memory goes first)
    /// and the slice and oblique views read its bricks.
    fn show_wanted_frame(&mut self, ctx: &egui::Context) -> Result<(), PageError> {
        let now_s = self.page_started.elapsed().as_secs_f64();
        let Some(frames) = self.streamed.as_mut().and_then(|s| s.frames.as_mut()) else {
            return Ok(());
        };
        let Some((frame, store)) = frames.tick(ctx, &mut self.view.frame, now_s) else {
            return Ok(());
        };
        let Some(Streamed {
            volume,
            mut slices,
            mut oblique,
            frames,
            ..
        }) = self.streamed.take()
        else {
            return Ok(());
        };
        drop(volume);
        slices.show_frame(store.as_ref())?;
        oblique.show_frame(store.as_ref())?;
        let transfer_function = self.side.transfer_function(&self.view);
        let volume = StreamingVolume::new(&self.gpu, store, &transfer_function, page_streaming())?;
        self.adaptive.new_volume();
        let mut frames = frames;
        if let Some(frames) = frames.as_mut() {
            frames.shown(frame, now_s, &mut self.view.frame);
        }
        self.streamed = Some(Streamed {
            volume,
            driver: RenderDriver::new(transfer_function, None),
            last: None,
            slices,
            oblique,
            frames,
        });
        self.drawn = None;
        ctx.request_repaint();
        Ok(())
    }

    /// A loader frame while the view changed or the cut has not converged; then idle.
    fn draw_streamed(&mut self, ctx: &egui::Context, size: [u32; 2]) -> Result<(), PageError> {
        let wanted = (self.view.of_3d_view(), size);
        let Some(geometry) = self.streamed.as_ref().map(|s| s.volume.geometry().clone()) else {
            return Ok(());
        };
        let request = self.render_request(&geometry, size);
        let Some(streamed) = self.streamed.as_mut() else {
            return Ok(());
        };
        // The driver uploads what changed (the transfer function); the page keeps the loader's
        // traversal, so the volume is never opened again here.
        streamed
            .driver
            .apply(&self.gpu, &mut streamed.volume, &request, |_, _| {
                Err(LoaderError::Unsupported(
                    "the page streams with the loader's traversal".into(),
                ))
            })?;
        let converged = streamed.last.as_ref().is_some_and(|s| s.converged);
        // A 4-D store: the next frame fetches what this one converged on (frames.rs).
        if let (true, Some(frames)) = (converged, streamed.frames.as_ref()) {
            frames.stream_ahead(streamed.volume.working_set(), ctx);
        }
        let now = self.page_started.elapsed().as_secs_f64();
        let target_fps = request.target_fps;
        if self.drawn.as_ref() == Some(&wanted)
            && !streamed.driver.is_new(&request)
            && converged
            && !self.motion.full_quality_due(now, target_fps)
        {
            // Still and final: a refinement pass where its effects want one (refine.rs).
            if let Some((camera, settings)) = self.refine.next_pass() {
                let stats = streamed.volume.frame(&self.gpu, &camera, &settings)?;
                let cut_changed = stats.uploads > 0 || stats.page_table_rewritten;
                let raycaster = streamed.volume.raycaster_mut();
                if let Some(mean) = self.refine.accumulate(&self.gpu, raycaster, cut_changed)? {
                    show_texture(&self.render_state, &self.gpu, mean, &mut self.texture);
                }
                self.frames_submitted += 1;
            }
            // Or the adaptive pass's frame, once its oracle is built (adaptive.rs).
            if let Some(epsilon) = self.view.adaptive_epsilon {
                let transfer_function = &request.transfer_function;
                let volume = &streamed.volume;
                if let Some(view) =
                    self.adaptive
                        .step(&self.gpu, volume, transfer_function, epsilon, ctx)
                {
                    show_texture(&self.render_state, &self.gpu, view, &mut self.texture);
                    self.frames_submitted += 1;
                }
            }
            if self.refine.wants_pass() || self.adaptive.wants_frames() {
                ctx.request_repaint();
            }
            self.motion.skipped();
            return Ok(());
        }
        self.refine.restart();
        self.adaptive.restart();
        let camera = request.camera;
        let mut settings = request.settings.clone();
        let (quality, lod_factor) = self.motion.plan(now, target_fps, &mut settings);
        streamed.volume.set_max_voxel_pixels(lod_factor);
        let stats = streamed.volume.frame(&self.gpu, &camera, &settings)?;
        if !stats.converged {
            ctx.request_repaint();
        }
        self.timing.submitted(stats.converged);
        let final_frame = stats.converged && quality.is_none();
        streamed.last = Some(stats);
        let timings = streamed.volume.take_frame_timings(&self.gpu);
        self.side.gpu_timings(timings.clone());
        let frame_number = streamed.volume.last_frame_number();
        self.motion.drawn(now, frame_number, quality, timings);
        self.frames_submitted += 1;
        let view = streamed
            .volume
            .raycaster_mut()
            .output_view()
            .ok_or(PageError::Missing("the raycaster drew no image"))?;
        show_texture(&self.render_state, &self.gpu, view, &mut self.texture);
        streamed.driver.drawn(&request);
        self.drawn = Some(wanted);
        let total = request.progressive_frames;
        if self
            .refine
            .start_if_final(&camera, &settings, final_frame, total)
        {
            ctx.request_repaint();
        }
        let epsilon = self.view.adaptive_epsilon;
        let overlay = request.overlay.is_some();
        if self
            .adaptive
            .start_if_final(&camera, &settings, final_frame, epsilon, overlay)
        {
            ctx.request_repaint();
        }
        Ok(())
    }

    /// What the page asks of the 3D view now, as the desktop's render thread is asked: the
    /// view's camera and settings, the side panel's function and target rate.
    fn render_request(&mut self, geometry: &VolumeGeometry, size: [u32; 2]) -> RenderRequest {
        RenderRequest {
            camera: self.view.camera(geometry),
            settings: self.view.settings(geometry, size[0], size[1]),
            transfer_function: self.side.transfer_function(&self.view),
            target_fps: self.side.target_fps(),
            // The page's own controller (view_motion.rs) paces the drag.
            interacting: false,
            // The labels being edited, else the served overlay's 3D grid once resampled; the
            // sample's 3D view has neither.
            overlay: self.streamed.as_mut().and_then(Streamed::overlay_in_3d),
            traversal: None,
            // The still view's final frame by the adaptive pass (adaptive.rs).
            adaptive_epsilon: self.view.adaptive_epsilon,
            // A still view with shadows, occlusion or scattering averages this many jittered
            // frames, as the desktop's does by default (refine.rs).
            progressive_frames: DEFAULT_PROGRESSIVE_FRAMES,
        }
    }

    fn draw_if_changed(&mut self, ctx: &egui::Context, size: [u32; 2]) -> Result<(), PageError> {
        let wanted = (self.view.of_3d_view(), size);
        let Some(geometry) = self.volume.as_ref().map(|v| v.geometry.clone()) else {
            return Ok(());
        };
        let request = self.render_request(&geometry, size);
        let (Some(volume), Some(renderer), Some(driver)) = (
            self.volume.as_ref(),
            self.renderer.as_mut(),
            self.sample_driver.as_mut(),
        ) else {
            return Ok(());
        };
        // The sample is an OffscreenRenderer, not a streaming volume: of the driver's changes
        // only the transfer function has an upload here.
        if driver
            .changes(&request)
            .contains(&RenderChange::TransferFunction)
        {
            renderer.set_transfer_function(&self.gpu, volume, &request.transfer_function)?;
            driver.transfer_function_applied(&request.transfer_function);
        }
        let now = self.page_started.elapsed().as_secs_f64();
        let target_fps = request.target_fps;
        if self.drawn.as_ref() == Some(&wanted)
            && !driver.is_new(&request)
            && !self.motion.full_quality_due(now, target_fps)
        {
            // Still: a refinement pass where its effects want one (refine.rs).
            if let Some((camera, settings)) = self.refine.next_pass() {
                renderer.submit(&self.gpu, volume, &camera, &settings)?;
                // The sample is whole on the GPU: its cut never changes.
                if let Some(mean) = self
                    .refine
                    .accumulate(&self.gpu, &renderer.raycaster, false)?
                {
                    show_texture(&self.render_state, &self.gpu, mean, &mut self.texture);
                }
                self.frames_submitted += 1;
            }
            if self.refine.wants_pass() {
                ctx.request_repaint();
            }
            self.motion.skipped();
            return Ok(());
        }
        self.refine.restart();
        let camera = request.camera;
        let mut settings = request.settings.clone();
        // The sample is drawn whole: no level of detail to coarsen, the step only.
        let (quality, _) = self.motion.plan(now, target_fps, &mut settings);
        renderer.submit(&self.gpu, volume, &camera, &settings)?;
        // The sample is drawn whole in one frame.
        self.timing.submitted(true);
        let timings = renderer.raycaster.try_take_frame_timings(&self.gpu);
        self.side.gpu_timings(timings.clone());
        let frame_number = renderer.raycaster.frame_number();
        self.motion.drawn(now, frame_number, quality, timings);
        self.frames_submitted += 1;
        let view = renderer
            .raycaster
            .output_view()
            .ok_or(PageError::Missing("the raycaster drew no image"))?;
        show_texture(&self.render_state, &self.gpu, view, &mut self.texture);
        driver.drawn(&request);
        self.drawn = Some(wanted);
        let total = request.progressive_frames;
        if self
            .refine
            .start_if_final(&camera, &settings, quality.is_none(), total)
        {
            ctx.request_repaint();
        }
        Ok(())
    }

    /// Starts reading back the pick depth under `pos` of the 3D image drawn in `image_rect`,
    /// from the frame on screen, for the crosshair. Off the image, or before a frame, nothing
    /// happens.
    fn start_pick(&mut self, ctx: &egui::Context, pos: egui::Pos2, image_rect: egui::Rect) {
        match self.pick_at(ctx, pos, image_rect) {
            Ok((pick, pixel, size)) => {
                self.pick = Some(pick);
                publish_pick(&format!(
                    "reading pixel {},{} of {}x{}",
                    pixel[0], pixel[1], size[0], size[1]
                ));
            }
            Err(why) => publish_pick(why),
        }
    }

    /// A pick of the depth under `pos` of the 3D image drawn in `image_rect`, from the frame
    /// on screen (the camera it was drawn with is the view's: a click or a segment tool's drag
    /// does not move the view), with its frame pixel and the frame's size; why not, else.
    /// The crosshair's click and the 3D segment tools (segment_3d.rs) both pick through it.
    fn pick_at(
        &mut self,
        ctx: &egui::Context,
        pos: egui::Pos2,
        image_rect: egui::Rect,
    ) -> Result<(PendingPick, [u32; 2], [u32; 2]), &'static str> {
        let geometry = self.shown_geometry().ok_or("no volume open to pick in")?;
        let camera = self.view.camera(&geometry);
        let raycaster = match (self.streamed.as_mut(), self.renderer.as_ref()) {
            (Some(streamed), _) => &*streamed.volume.raycaster_mut(),
            (None, Some(renderer)) => &renderer.raycaster,
            (None, None) => return Err("no frame drawn yet to pick from"),
        };
        let (depth, size) = raycaster
            .pick_depth_buffer()
            .ok_or("no frame drawn yet to pick from")?;
        let pixel = frame_pixel(
            (pos.x - image_rect.left()) / image_rect.width().max(1.0),
            (pos.y - image_rect.top()) / image_rect.height().max(1.0),
            size,
        )
        .ok_or("the click is off the 3D image")?;
        let pick = PendingPick::start(&self.gpu, depth, size, pixel, camera, ctx);
        Ok((pick, pixel, size))
    }

    /// The position a finished pick saw (`None` while it is on its way, or where its ray met
    /// nothing); a failed readback is the page's error.
    fn take_pick(&mut self) -> Option<[f64; 3]> {
        let geometry = self.shown_geometry()?;
        let result = self.pick.as_ref()?.poll(&geometry)?;
        self.pick = None;
        match result {
            Ok(Some(index)) => {
                publish_pick(&format!("picked {},{},{}", index[0], index[1], index[2]));
                Some(index)
            }
            Ok(None) => {
                publish_pick("nothing under the click");
                None
            }
            Err(e) => {
                publish_pick(&e.to_string());
                self.error = Some(e.to_string());
                None
            }
        }
    }

    /// The segmentation's tool as the 3D view offers it (`None` without a segmentation).
    fn segment_tool_3d(&self) -> SegmentTool {
        let slices = match &self.streamed {
            Some(streamed) => Some(&streamed.slices),
            None => self.sample_slices.as_ref(),
        };
        slices
            .and_then(|s| s.segmentation.as_ref())
            .map_or(SegmentTool::None, |seg| seg.tool_3d())
    }

    /// The 3D segment tools' picks that are in go onto the segmentation (segment_3d.rs).
    fn segment_3d_step(&mut self) {
        let Some(geometry) = self.shown_geometry() else {
            return;
        };
        let segmentation = match self.streamed.as_mut() {
            Some(streamed) => streamed.slices.segmentation.as_mut(),
            None => self
                .sample_slices
                .as_mut()
                .and_then(|s| s.segmentation.as_mut()),
        };
        if let Some(e) = self.segment_3d.apply(&geometry, segmentation) {
            self.error = Some(e.to_string());
        }
    }

    /// The geometry of the volume shown (a served store's or the sample's), once open.
    fn shown_geometry(&self) -> Option<VolumeGeometry> {
        match &self.streamed {
            Some(streamed) => Some(streamed.volume.geometry().clone()),
            None => self.volume.as_ref().map(|v| v.geometry.clone()),
        }
    }

    /// Undo and redo (page_tools.rs): the view's edits put back, the side panel's function
    /// and the slices' window following them.
    fn history_step(&mut self, ctx: &egui::Context) {
        let gesture = ctx.input(|i| i.pointer.any_down());
        // The segmentation's edits are steps in the same history (segment_editor.rs).
        let segmentation = match self.streamed.as_mut() {
            Some(streamed) => streamed.slices.segmentation.as_mut(),
            None => self
                .sample_slices
                .as_mut()
                .and_then(|s| s.segmentation.as_mut()),
        };
        let Some(restored) =
            self.tools
                .step_history(&self.view, self.drawn.is_some(), gesture, segmentation)
        else {
            if self.tools.take_edit_stepped() {
                ctx.request_repaint();
            }
            return;
        };
        self.view = restored;
        self.side.restore(&self.view);
        let slices = match self.streamed.as_mut() {
            Some(streamed) => Some(&mut streamed.slices),
            None => self.sample_slices.as_mut(),
        };
        if let Some(slices) = slices {
            slices.set_from_link(None, self.view.window);
        }
        ctx.request_repaint();
    }

    /// F12 or Screenshot: reads the 3D view's frame back at the size it was drawn and hands
    /// it to the browser as a PNG download.
    fn download_step(&mut self, ctx: &egui::Context) {
        if self.tools.take_screenshot_request() && self.download.is_none() {
            // The refined mean where it is on screen (refine.rs).
            let texture = match self.streamed.as_mut() {
                Some(streamed) => streamed.volume.raycaster_mut().output_texture(),
                None => self
                    .renderer
                    .as_ref()
                    .and_then(|r| r.raycaster.output_texture()),
            };
            // Or the adaptive pass's frame (adaptive.rs).
            let texture = self
                .refine
                .shown_texture()
                .or(self.adaptive.shown_texture())
                .or(texture);
            match (texture, self.drawn.as_ref()) {
                (Some(texture), Some((_, size))) => {
                    self.download = Some(start_readback(&self.gpu, texture, *size, ctx));
                }
                _ => self
                    .tools
                    .download_failed("no 3D frame is drawn yet to download".into()),
            }
        }
        let state = match &self.download {
            Some(capture) => capture.state.load(Ordering::Acquire),
            None => return,
        };
        if state != CAPTURE_MAPPED && state != CAPTURE_FAILED {
            ctx.request_repaint();
            return;
        }
        let Some(capture) = self.download.take() else {
            return;
        };
        let png = if state == CAPTURE_MAPPED {
            read_back(&capture).and_then(|rgba| encode_png(&rgba, capture.size))
        } else {
            Err(PageError::ScreenshotBuffer)
        };
        match png {
            Ok(png) => self.tools.download(&png, &page_tools::screenshot_name()),
            Err(e) => self
                .tools
                .download_failed(format!("the screenshot could not be made: {e}")),
        }
    }

    /// The orbit movie (orbit_movie.rs): once the frame on screen is the movie's frame and
    /// final as the test capture's is (its cut converged, its refinement complete), reads it
    /// back and takes it; after the last, downloads the animated PNG and puts the view back.
    fn movie_step(&mut self, ctx: &egui::Context) {
        self.movie.publish();
        if !self.movie.is_making() {
            return;
        }
        ctx.request_repaint();
        if self.movie_frame.is_none() {
            let Some((drawn, size)) = self.drawn.clone() else {
                return;
            };
            if drawn != self.view.of_3d_view() {
                return;
            }
            let (settled, refined) = (self.refine.settled(), self.refine.refined_texture());
            let texture = match self.streamed.as_mut() {
                Some(streamed)
                    if settled && streamed.last.as_ref().is_some_and(|s| s.converged) =>
                {
                    refined.or(streamed.volume.raycaster_mut().output_texture())
                }
                Some(_) => None,
                None if settled => refined.or(self
                    .renderer
                    .as_ref()
                    .and_then(|r| r.raycaster.output_texture())),
                None => None,
            };
            if let Some(texture) = texture {
                self.movie_frame = Some(start_readback(&self.gpu, texture, size, ctx));
            }
            return;
        }
        let state = match &self.movie_frame {
            Some(capture) => capture.state.load(Ordering::Acquire),
            None => return,
        };
        if state != CAPTURE_MAPPED && state != CAPTURE_FAILED {
            return;
        }
        let Some(capture) = self.movie_frame.take() else {
            return;
        };
        let rgba = if state == CAPTURE_MAPPED {
            read_back(&capture)
        } else {
            Err(PageError::ScreenshotBuffer)
        };
        let added = rgba.map_err(|e| e.to_string()).and_then(|rgba| {
            self.movie
                .add_frame(rgba, capture.size)
                .map_err(|e| e.to_string())
        });
        match added {
            Ok(Some(finished)) => {
                self.view.azimuth_deg = finished.start_azimuth;
                self.tools
                    .download(&finished.apng, &crate::orbit_movie::movie_name());
            }
            Ok(None) => {}
            Err(problem) => {
                if let Some(start) = self.movie.fail(&problem) {
                    self.view.azimuth_deg = start;
                }
            }
        }
        self.movie.publish();
    }

    /// The volume shown: the page's sample, or one of the server's stores (each entry is the
    /// link `#store=NAME`: choosing it streams that store, and the address then shares it).
    fn volume_choice(&mut self, ui: &mut egui::Ui) {
        let mut chosen = self.view.store.clone();
        egui::ComboBox::from_id_salt("volume")
            .selected_text(volume_menu::shown_label(chosen.as_deref()))
            .show_ui(ui, |ui| match &*self.stores.borrow() {
                Some(Ok(list)) => {
                    for entry in volume_menu::entries(list) {
                        ui.selectable_value(&mut chosen, entry.store, entry.label);
                    }
                }
                Some(Err(e)) => {
                    ui.selectable_value(&mut chosen, None, volume_menu::SAMPLE_ENTRY);
                    ui.label(format!("the server's stores: {e}"));
                }
                None => {
                    ui.selectable_value(&mut chosen, None, volume_menu::SAMPLE_ENTRY);
                    ui.label("asking the server for its stores…");
                }
            });
        if volume_menu::choose(&mut self.view, chosen) {
            self.tools.forget_history();
            self.streamed = None;
            self.opening = None;
            self.drawn = None;
        }
    }

    fn controls(&mut self, ui: &mut egui::Ui) {
        ui.horizontal_wrapped(|ui| {
            ui.strong("Strata");
            ui.separator();
            self.volume_choice(ui);
            ui.separator();
            // The desktop's layouts and their labels.
            for (layout, label, hover) in [
                (Layout::Single, "1×1", "The 3D view alone"),
                (
                    Layout::ThreeDOverSlices,
                    "3D + 1×3",
                    "3D over axial, coronal, sagittal",
                ),
                (
                    Layout::FourUp,
                    "2×2",
                    "Four-up: axial, 3D / sagittal, coronal",
                ),
            ] {
                ui.selectable_value(&mut self.view.layout, layout, label)
                    .on_hover_text(hover);
            }
            oblique_toggle(ui, &mut self.view);
            ui.separator();
            for (mode, label) in [
                (RenderMode::Dvr, "DVR"),
                (RenderMode::Mip, "MIP"),
                (RenderMode::Isosurface, "Isosurface"),
            ] {
                ui.selectable_value(&mut self.view.mode, mode, label);
            }
            ui.separator();
            let scan = self.side.scan().cloned();
            egui::ComboBox::from_id_salt("preset")
                .selected_text(self.view.preset.clone())
                .show_ui(ui, |ui| {
                    for name in TransferFunction::PRESETS {
                        // A preset that does not fit the scan is greyed out and says why.
                        let offer = scan.as_ref().map(|s| presets::offer(name, s));
                        let offered = offer.as_ref().is_none_or(presets::Offer::is_offered);
                        let selected = self.view.preset == name;
                        let response =
                            ui.add_enabled(offered, egui::Button::selectable(selected, name));
                        let response = match offer.as_ref().and_then(presets::Offer::reason) {
                            Some(reason) if offered => response.on_hover_text(reason),
                            Some(reason) => response.on_disabled_hover_text(reason),
                            None => response,
                        };
                        if response.clicked() {
                            self.view.preset = name.to_string();
                        }
                    }
                });
            if self.view.mode == RenderMode::Isosurface {
                // In the scan's unit and over its range (HU only for CT).
                let (range, label) = match &scan {
                    Some(s) => (
                        s.physical_range.0..=s.physical_range.1,
                        s.value_label("iso"),
                    ),
                    None => (-1000.0..=3000.0, "iso (HU)".to_string()),
                };
                ui.add(egui::Slider::new(&mut self.view.iso_value, range).text(label));
            }
            ui.add(
                egui::Slider::new(&mut self.view.zoom, 0.25..=8.0)
                    .logarithmic(true)
                    .text("zoom"),
            );
            ui.separator();
            self.tools.toolbar(ui);
        });
    }

    /// The status line: its own panel, so the controls above never wrap or shift when it
    /// changes.
    fn status(&self, ui: &mut egui::Ui) {
        if let Some(name) = &self.view.store {
            let detail = match &self.streamed {
                None => "opening…".to_string(),
                Some(streamed) => {
                    let dims = streamed.volume.geometry().dims;
                    let loading = match &streamed.last {
                        Some(s) if s.source_status.is_retrying() => {
                            format!("server unreachable, retrying ({:?})", s.source_status)
                        }
                        Some(s) if s.converged => "complete".to_string(),
                        Some(s) => {
                            format!("loading: {} requested, {} in flight", s.queued, s.in_flight)
                        }
                        None => "starting".to_string(),
                    };
                    let read = streamed
                        .last
                        .as_ref()
                        .map_or((0, 0), |s| (s.bricks_read_total, s.stored_bytes_read_total));
                    let adaptive = self
                        .adaptive
                        .status_line()
                        .map(|line| format!(" · {line}"))
                        .unwrap_or_default();
                    format!(
                        "{}×{}×{} · {loading} · {} bricks, {:.1} MB fetched · frames drawn \
                         {}{adaptive}",
                        dims[0],
                        dims[1],
                        dims[2],
                        read.0,
                        read.1 as f64 / 1e6,
                        self.frames_submitted
                    )
                }
            };
            ui.horizontal(|ui| {
                ui.label(format!(
                    "Store {name} · {detail} · 3D: drag to orbit, scroll to zoom; slices: click \
                     moves the crosshair, scroll pages, Ctrl+scroll zooms, middle drag pans, \
                     right drag (or Shift+drag) windows; F1 lists the keys; the address holds the \
                     view · not for diagnostic use"
                ));
            });
            return;
        }
        ui.horizontal(|ui| {
            ui.label(format!(
                "Sample volume {}³ (CT phantom made in the page) · frames drawn {} · 3D: drag to \
                 orbit, scroll to zoom; slices: click moves the crosshair, scroll pages, \
                 Ctrl+scroll zooms, middle drag pans, right drag (or Shift+drag) windows; F1 \
                 lists the keys; the address holds this view · not for diagnostic use",
                self.view.volume_edge, self.frames_submitted
            ));
        });
    }

    /// Keeps the address bar's fragment on the view (history.replaceState: no history entry
    /// per drag), so copying the address shares the view.
    fn write_fragment(&mut self, dragging: bool) {
        let fragment = self.view.to_fragment();
        if dragging || fragment == self.fragment_written {
            return;
        }
        if let Some(history) = web_sys::window().and_then(|w| w.history().ok()) {
            let _ = history.replace_state_with_url(&JsValue::NULL, "", Some(&fragment));
        }
        self.fragment_written = fragment;
    }

    /// In a notebook: reports the view to the widget once it rests, and answers its
    /// screenshot requests with the frame on screen (a streamed view as far as it loaded).
    fn bridge_step(&mut self, ctx: &egui::Context) {
        let Some(bridge) = self.bridge.as_mut() else {
            return;
        };
        let now = self.page_started.elapsed().as_secs_f64();
        let dragging = ctx.input(|i| i.pointer.any_down());
        if let Some(wait_s) = bridge.report(&self.view, now, dragging) {
            ctx.request_repaint_after(std::time::Duration::from_secs_f64(wait_s));
        }
        if self.screenshot.is_none() && bridge.screenshots_wanted() {
            // The refined mean where it is on screen (refine.rs).
            let texture = match self.streamed.as_mut() {
                Some(streamed) => streamed.volume.raycaster_mut().output_texture(),
                None => self
                    .renderer
                    .as_ref()
                    .and_then(|r| r.raycaster.output_texture()),
            };
            // Or the adaptive pass's frame (adaptive.rs).
            let texture = self
                .refine
                .shown_texture()
                .or(self.adaptive.shown_texture())
                .or(texture);
            match (texture, self.drawn.as_ref()) {
                (Some(texture), Some((_, size))) => {
                    let readback = start_readback(&self.gpu, texture, *size, ctx);
                    self.screenshot = Some((readback, bridge.take_screenshot_requests()));
                }
                _ => match &self.error {
                    Some(error) => {
                        for id in bridge.take_screenshot_requests() {
                            bridge.answer_screenshot(&id, Err(error.clone()));
                        }
                    }
                    // Nothing drawn yet: the first frame answers.
                    None => ctx.request_repaint(),
                },
            }
        }
        let state = match &self.screenshot {
            Some((capture, _)) => capture.state.load(Ordering::Acquire),
            None => return,
        };
        if state != CAPTURE_MAPPED && state != CAPTURE_FAILED {
            ctx.request_repaint();
            return;
        }
        let Some((capture, ids)) = self.screenshot.take() else {
            return;
        };
        let png = if state == CAPTURE_MAPPED {
            read_back(&capture).and_then(|rgba| encode_png(&rgba, capture.size))
        } else {
            Err(PageError::ScreenshotBuffer)
        };
        for id in ids {
            bridge.answer_screenshot(
                &id,
                png.as_ref().map(Vec::clone).map_err(ToString::to_string),
            );
        }
    }

    /// Test hook (`capture=1`): copies the frame on screen to a buffer, maps it, and posts the
    /// pixels to the server that served the page, once.
    fn capture_step(&mut self, ctx: &egui::Context) {
        if !self.view.capture || !self.timing.bench_done() {
            return;
        }
        let Some((_, size)) = self.drawn.clone() else {
            return;
        };
        if self.capture.is_none() {
            // A streamed view is captured once its cut converged (the picture a link names),
            // or, with `capture=unconverged`, once frames went on for a while without it.
            let capture_unconverged = self.view.capture_unconverged
                && self.frames_submitted >= crate::view_state::UNCONVERGED_CAPTURE_FRAMES;
            // A still view that refines is captured once its mean is complete (refine.rs), one
            // the adaptive pass draws once that frame is drawn or failed (adaptive.rs).
            let (settled, refined) = (
                self.refine.settled() && self.adaptive.settled(),
                self.refine
                    .refined_texture()
                    .or(self.adaptive.shown_texture()),
            );
            // The link's overlay is in the frame first (its grid resampled and drawn).
            let overlay_ready = self.streamed.as_mut().is_none_or(overlay_drawn_in_3d);
            let texture = match self.streamed.as_mut() {
                Some(_) if !overlay_ready => None,
                Some(streamed)
                    if capture_unconverged
                        || (settled && streamed.last.as_ref().is_some_and(|s| s.converged)) =>
                {
                    refined.or(streamed.volume.raycaster_mut().output_texture())
                }
                Some(_) => None,
                None if settled => refined.or(self
                    .renderer
                    .as_ref()
                    .and_then(|r| r.raycaster.output_texture())),
                None => None,
            };
            let Some(texture) = texture else {
                return;
            };
            self.capture = Some(start_readback(&self.gpu, texture, size, ctx));
        }
        let Some(capture) = self.capture.as_ref() else {
            return;
        };
        match capture.state.load(Ordering::Acquire) {
            CAPTURE_MAPPED => {
                let [w, h] = capture.size;
                let rgba = match read_back(capture) {
                    Ok(rgba) => rgba,
                    Err(e) => {
                        self.error = Some(format!("the test capture could not be read: {e}"));
                        return;
                    }
                };
                capture.state.store(CAPTURE_POSTING, Ordering::Release);
                let (state, repaint) = (capture.state.clone(), ctx.clone());
                let token = self.token.clone();
                let metrics = self.timing.metrics();
                wasm_bindgen_futures::spawn_local(async move {
                    if let Err(e) = post_frame(&rgba, w, h, &metrics, token.as_deref()).await {
                        show_message("The test capture could not be sent", &e.to_string());
                    }
                    state.store(CAPTURE_SENT, Ordering::Release);
                    repaint.request_repaint();
                });
            }
            CAPTURE_FAILED => {
                self.error = Some("the test capture's buffer could not be mapped".into());
            }
            CAPTURE_SENT => {
                // Then, once, the axial slice view's image (slice_views.rs), where it is shown
                // (a served store's or the sample's).
                let slices_shown = self.view.layout != Layout::Single;
                // A 4-D store's slice capture says which frame it shows (frames.rs).
                let metrics: Vec<(&str, f64)> = self
                    .streamed
                    .as_ref()
                    .and_then(|s| s.frames.as_ref())
                    .map(|f| vec![("frame", f.playback.current as f64)])
                    .unwrap_or_default();
                let slices = match self.streamed.as_mut() {
                    Some(streamed) => Some(&mut streamed.slices),
                    None => self.sample_slices.as_mut(),
                };
                if let Some(slices) = slices.filter(|_| slices_shown) {
                    if let Some((rgba, w, h)) = slices.take_capture() {
                        let token = self.token.clone();
                        wasm_bindgen_futures::spawn_local(async move {
                            if let Err(e) =
                                post_frame(&rgba, w, h, &metrics, token.as_deref()).await
                            {
                                show_message("The slice capture could not be sent", &e.to_string());
                            }
                        });
                    } else if !slices.captured() {
                        ctx.request_repaint();
                    }
                }
            }
            _ => ctx.request_repaint(),
        }
    }
}

impl Streamed {
    /// What the 3D view draws over the volume: the segmentation's labels once painted (the
    /// layer being edited, segment_editor.rs), else the served overlay's grid once resampled
    /// (overlay_view.rs). The raycaster draws one overlay, as the desktop's, whose segmentation
    /// is its overlay.
    fn overlay_in_3d(&mut self) -> Option<OverlayIn3d> {
        let labels = self
            .slices
            .segmentation
            .as_mut()
            .and_then(|s| s.request_3d());
        labels.or_else(|| self.slices.overlay.request_3d())
    }
}

/// Whether the last frame drawn shows the overlay as the link has it: no overlay named, or
/// its 3D grid resampled and in the request the frame answered.
fn overlay_drawn_in_3d(streamed: &mut Streamed) -> bool {
    if streamed.slices.overlay.pending_3d() {
        return false;
    }
    let wanted = streamed.overlay_in_3d();
    let drawn = streamed.driver.drawn_request().map(|r| &r.overlay);
    drawn.is_some_and(|d| *d == wanted)
}

/// Copies `texture` (the frame on screen, `size`) to a buffer and maps it; the capture's
/// state says when the pixels can be read ([`read_back`]).
fn start_readback(
    gpu: &GpuContext,
    texture: &wgpu::Texture,
    size: [u32; 2],
    ctx: &egui::Context,
) -> Capture {
    // Rows of a texture-to-buffer copy are padded to 256 bytes.
    let padded_row = (size[0] * 4).div_ceil(256) * 256;
    let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("strata-web capture"),
        size: padded_row as u64 * size[1] as u64,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let mut encoder = gpu
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("strata-web capture"),
        });
    encoder.copy_texture_to_buffer(
        texture.as_image_copy(),
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(padded_row),
                rows_per_image: Some(size[1]),
            },
        },
        wgpu::Extent3d {
            width: size[0],
            height: size[1],
            depth_or_array_layers: 1,
        },
    );
    gpu.queue.submit(Some(encoder.finish()));
    let state = Arc::new(AtomicU8::new(CAPTURE_MAPPING));
    let done = state.clone();
    let repaint = ctx.clone();
    buffer
        .slice(..)
        .map_async(wgpu::MapMode::Read, move |result| {
            done.store(
                if result.is_ok() {
                    CAPTURE_MAPPED
                } else {
                    CAPTURE_FAILED
                },
                Ordering::Release,
            );
            repaint.request_repaint();
        });
    Capture {
        buffer,
        padded_row,
        size,
        state,
    }
}

/// The mapped capture's RGBA8 rows without their padding; unmaps the buffer.
fn read_back(capture: &Capture) -> Result<Vec<u8>, PageError> {
    let [w, h] = capture.size;
    let mut rgba = Vec::with_capacity((w * h * 4) as usize);
    {
        let mapped = capture
            .buffer
            .slice(..)
            .get_mapped_range()
            .map_err(|e| PageError::Readback(e.to_string()))?;
        for row in 0..h as usize {
            let start = row * capture.padded_row as usize;
            rgba.extend_from_slice(&mapped[start..start + (w * 4) as usize]);
        }
    }
    capture.buffer.unmap();
    Ok(rgba)
}

/// An RGBA8 image as PNG (the embedded page's screenshots).
fn encode_png(rgba: &[u8], [width, height]: [u32; 2]) -> Result<Vec<u8>, PageError> {
    let mut png = Vec::new();
    let mut encoder = png::Encoder::new(&mut png, width, height);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    // One filter for every row: the widget's numpy decoder (widget.py) undoes Up for a whole
    // row at once, where Paeth (which the adaptive default picks) needs a loop per pixel.
    encoder.set_filter(png::Filter::Up);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(rgba)?;
    writer.finish()?;
    Ok(png)
}

/// Points egui's texture id at the raycaster's output (re-created when the size changes).
fn show_texture(
    render_state: &egui_wgpu::RenderState,
    gpu: &GpuContext,
    view: &wgpu::TextureView,
    texture: &mut Option<egui::TextureId>,
) {
    let mut egui_renderer = render_state.renderer.write();
    match *texture {
        Some(id) => egui_renderer.update_egui_texture_from_wgpu_texture(
            &gpu.device,
            view,
            wgpu::FilterMode::Linear,
            id,
        ),
        None => {
            *texture = Some(egui_renderer.register_native_texture(
                &gpu.device,
                view,
                wgpu::FilterMode::Linear,
            ))
        }
    }
}

/// How the page streams a served store (each frame of a 4-D one alike).
fn page_streaming() -> StreamingConfig {
    StreamingConfig {
        // The page shares the GPU and memory with the rest of the browser.
        gpu_budget_bytes: 256 << 20,
        cpu_budget_bytes: 384 << 20,
        sled_cache_bytes: 0,
        fetch_threads: 1,
        bricks_in_transit: MAX_ON_THE_WIRE + DECODES_PER_FRAME,
        // A frame never waits for its selection (the page must stay responsive).
        selection: SelectionTiming::Background,
        work: LoaderWork::Inline,
        ..StreamingConfig::default()
    }
}

/// Posts a captured frame to `strata serve`'s test sink (same origin).
async fn post_frame(
    rgba: &[u8],
    width: u32,
    height: u32,
    metrics: &[(&str, f64)],
    token: Option<&str>,
) -> Result<(), PageError> {
    let window = web_sys::window().ok_or(PageError::Missing("no window"))?;
    let init = web_sys::RequestInit::new();
    init.set_method("POST");
    if let Some(token) = token {
        let headers = web_sys::Headers::new().map_err(PageError::js)?;
        headers
            .set("Authorization", &format!("Bearer {token}"))
            .map_err(PageError::js)?;
        init.set_headers(&headers);
    }
    let body = js_sys::Uint8Array::from(rgba);
    init.set_body(&body.into());
    let mut url = format!("/v1/test/frame?width={width}&height={height}");
    for (name, value) in metrics {
        url.push_str(&format!("&{name}={value:.3}"));
    }
    let request = web_sys::Request::new_with_str_and_init(&url, &init).map_err(PageError::js)?;
    let answer = wasm_bindgen_futures::JsFuture::from(window.fetch_with_request(&request))
        .await
        .map_err(PageError::js)?;
    let response: web_sys::Response = answer.dyn_into().map_err(PageError::js)?;
    if !response.ok() {
        return Err(PageError::ServerAnswered(response.status()));
    }
    Ok(())
}

impl eframe::App for WebViewer {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        let ui_started = web_time::Instant::now();
        let ctx = ui.ctx().clone();
        if let Some(lost) = self.device_lost.lock().ok().and_then(|l| l.clone()) {
            self.error = Some(format!(
                "the GPU device was lost ({lost}). Reload the page: the view is in its address"
            ));
        }
        if let Some(detail) = self.gpu_error.lock().ok().and_then(|mut e| e.take()) {
            self.error.get_or_insert(format!("GPU error: {detail}"));
        }
        // The notebook's view changes land before this frame draws, so a screenshot asked
        // for after them shows them.
        if let Some(bridge) = self.bridge.as_mut() {
            bridge.apply(&mut self.view);
        }
        egui::Panel::top("controls").show(ui, |ui| self.controls(ui));
        egui::Panel::bottom("status").show(ui, |ui| self.status(ui));
        egui::Panel::right("side panel")
            .resizable(true)
            .default_size(300.0)
            .show(ui, |ui| {
                // A 4-D store's frames first (frames.rs).
                if let Some(frames) = self.streamed.as_mut().and_then(|s| s.frames.as_mut()) {
                    frames.panel(ui);
                }
                // The orbit movie's controls (orbit_movie.rs): one row on top, in sight whatever
                // the sections below take.
                if self.movie.section(ui) {
                    self.movie_frame = None;
                    if let Some(start) = self.movie.cancel() {
                        self.view.azimuth_deg = start;
                    }
                }
                // The measurements' tools and list next, always in sight (measure.rs), then
                // the Segment section on the slice views' volume (segment_editor.rs).
                let slices = match self.streamed.as_mut() {
                    Some(streamed) => Some(&mut streamed.slices),
                    None => self.sample_slices.as_mut(),
                };
                if let Some(slices) = slices {
                    crate::measure::side_panel_section(ui, &mut self.view, slices);
                    egui::CollapsingHeader::new("Segmentation")
                        .default_open(true)
                        .show(ui, |ui| crate::segment_editor::section(ui, slices));
                    egui::CollapsingHeader::new("Overlay")
                        .default_open(self.view.overlay.name.is_some())
                        .show(ui, |ui| {
                            crate::overlay_view::section(ui, &mut self.view, slices, &self.stores)
                        });
                }
                let figures = VolumeFigures {
                    loader: self.streamed.as_ref().and_then(|s| s.last.as_ref()),
                    step_factor: self.motion.shown().0,
                    lod_factor: self.motion.shown().1,
                    frames_submitted: self.frames_submitted,
                };
                self.side.ui(ui, &mut self.view, figures);
                // The address carries an edited function (`tf=`); the render driver uploads the
                // panel's function when it differs, so this adds no redraw of its own.
                let edited = self.side.edited_function();
                let differs = match (self.view.tf.as_ref(), edited) {
                    (Some(a), Some(b)) => a.opacity != b.opacity || a.color != b.color,
                    (a, b) => a.is_some() != b.is_some(),
                };
                if differs {
                    self.view.tf = edited.map(|tf| TransferFunction {
                        name: crate::view_state::edited_name(&self.view.preset),
                        ..tf.clone()
                    });
                }
            });
        // The orbit movie turns the view to the frame it takes next (orbit_movie.rs).
        self.movie.begin(self.view.azimuth_deg);
        if let Some(azimuth) = self.movie.azimuth() {
            self.view.azimuth_deg = azimuth;
        }
        egui::CentralPanel::default()
            .frame(egui::Frame::NONE.fill(egui::Color32::BLACK))
            .show(ui, |ui| {
                if let Some(error) = &self.error {
                    ui.colored_label(egui::Color32::LIGHT_RED, error);
                    return;
                }
                let ready = match self.view.store.clone() {
                    Some(name) => self.ensure_stream(&ctx, &name),
                    None => self.ensure_renderer(&ctx),
                };
                match ready {
                    Ok(true) => {}
                    Ok(false) => {
                        ui.label(match &self.view.store {
                            Some(name) => format!("Opening store {name}…"),
                            None => {
                                format!("Generating the {0}³ sample volume…", self.view.volume_edge)
                            }
                        });
                        return;
                    }
                    Err(e) => {
                        self.error = Some(e.to_string());
                        return;
                    }
                }
                if let Err(e) = self.show_wanted_frame(&ctx) {
                    self.error = Some(e.to_string());
                    return;
                }
                // The desktop's layouts of the 3D view and three slice views (a store's or
                // the sample's): the 2×2, or the 3D view over the slices.
                let area = ui.available_rect_before_wrap();
                let has_slices = self.streamed.is_some() || self.sample_slices.is_some();
                let placed = place_views(self.view.layout, self.view.oblique.is_some(), area);
                let (rect, slice_rects, oblique_rect) = match placed {
                    Some((rect, slices, oblique)) if has_slices => (rect, Some(slices), oblique),
                    _ => (area, None, None),
                };
                let response = ui.allocate_rect(rect, egui::Sense::click_and_drag());
                // With a brush, eraser or grow chosen the left button edits labels in the 3D
                // view (segment_3d.rs), as on the desktop; the other buttons still orbit.
                let segment_tool = self.segment_tool_3d();
                let segment_left = Segment3d::takes_left_button(segment_tool, ui);
                // The desktop's drag mapping (strata-viewer-ui's orbit): the same drag turns
                // both viewers' views by the same angles.
                let orbiting = response.dragged()
                    && !(segment_left && response.dragged_by(egui::PointerButton::Primary));
                if orbiting {
                    let delta = response.drag_delta();
                    (self.view.azimuth_deg, self.view.elevation_deg) = orbit::orbit_by_drag(
                        self.view.azimuth_deg,
                        self.view.elevation_deg,
                        [delta.x as f64, delta.y as f64],
                        rect.height() as f64,
                    );
                }
                // The desktop's standard-view keys (A/P/L/R/S/I), unless a text field (the
                // store path, a number) takes the keys.
                let mut keyed = false;
                if !ctx.egui_wants_keyboard_input() {
                    if let Some(standard) = ctx.input(orbit::StandardView::pressed) {
                        (self.view.azimuth_deg, self.view.elevation_deg) = standard.angles_deg();
                        keyed = true;
                    }
                    // The rest of the shared keys the page has (page_tools.rs).
                    keyed |= self.tools.keys(&ctx, &mut self.view);
                }
                publish_view_rects(rect, slice_rects, oblique_rect);
                if self.timing.orbiting() {
                    // In a notebook the orbit waits for the model to lead (embed_bridge.rs):
                    // its first answer would otherwise put an orbit made before it back.
                    let now = self.page_started.elapsed().as_secs_f64();
                    if self.bridge.as_ref().is_none_or(|b| b.model_has_led(now)) {
                        self.view.azimuth_deg += BENCH_DEG_PER_FRAME;
                        ctx.request_repaint();
                    } else {
                        ctx.request_repaint_after(std::time::Duration::from_millis(250));
                    }
                }
                let mut moved = orbiting || keyed;
                if response.hovered() {
                    let scroll = ui.input(|i| i.smooth_scroll_delta.y);
                    if scroll != 0.0 {
                        self.view.zoom =
                            (self.view.zoom * (scroll as f64 * 0.002).exp()).clamp(0.25, 8.0);
                        moved = true;
                    }
                }
                // Orbit and zoom move the view: the target-fps control's rate until it rests,
                // then one full-quality frame (a repaint is asked for that moment).
                if moved {
                    let now = self.page_started.elapsed().as_secs_f64();
                    self.motion.moved(now);
                    ctx.request_repaint_after(std::time::Duration::from_secs_f64(
                        MOTION_HOLD_S + 0.01,
                    ));
                }
                let ppp = ctx.pixels_per_point();
                let size = self.view.image_size.unwrap_or_else(|| {
                    let px = (rect.size() * ppp)
                        .min(egui::vec2(MAX_CANVAS_IMAGE_EDGE, MAX_CANVAS_IMAGE_EDGE));
                    [px.x.max(16.0) as u32, px.y.max(16.0) as u32]
                });
                let drawn = if self.view.store.is_some() {
                    self.draw_streamed(&ctx, size)
                } else {
                    self.draw_if_changed(&ctx, size)
                };
                self.refine.publish();
                self.adaptive.publish();
                if let Err(e) = drawn {
                    self.error = Some(e.to_string());
                    return;
                }
                // Fit the image in the panel, keeping its aspect (a fixed `size=` may differ).
                let aspect = size[0] as f32 / size[1] as f32;
                let mut shown = rect.size();
                if shown.x / shown.y > aspect {
                    shown.x = shown.y * aspect;
                } else {
                    shown.y = shown.x / aspect;
                }
                let image_rect = egui::Rect::from_center_size(rect.center(), shown);
                if let Some(texture) = self.texture {
                    ui.painter().image(
                        texture,
                        image_rect,
                        egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0)),
                        egui::Color32::WHITE,
                    );
                    // The desktop's orientation triad, turned with the view's camera.
                    if let Some(geometry) = self.shown_geometry() {
                        triad::paint_triad(ui.painter(), rect, &self.view.camera(&geometry));
                    }
                }
                // A click (no drag) moves the crosshair to what is seen there, as the desktop's.
                // A press held past egui's click time (a slow frame between press and release,
                // as on a loaded software adapter) counts too while the pointer stayed put.
                if response.drag_started() {
                    self.drag_travel = 0.0;
                }
                if response.dragged() {
                    self.drag_travel += response.drag_delta().length();
                }
                let held_click = response.drag_stopped_by(egui::PointerButton::Primary)
                    && self.drag_travel < HELD_CLICK_TRAVEL;
                if (response.clicked() || held_click) && !segment_left {
                    if let Some(pos) = response.interact_pointer_pos() {
                        self.start_pick(&ctx, pos, image_rect);
                    }
                }
                if segment_left {
                    let mut segment_3d = std::mem::take(&mut self.segment_3d);
                    segment_3d.input(ui, &response, segment_tool, |pos| {
                        self.pick_at(&ctx, pos, image_rect)
                            .ok()
                            .map(|(pick, _, _)| pick)
                    });
                    self.segment_3d = segment_3d;
                }
                self.segment_3d_step();
                let picked = self.take_pick();
                let camera_3d = self.shown_geometry().map(|g| self.view.camera(&g));
                let (mut slices, oblique) = match self.streamed.as_mut() {
                    Some(streamed) => (Some(&mut streamed.slices), Some(&mut streamed.oblique)),
                    None => (self.sample_slices.as_mut(), self.sample_oblique.as_mut()),
                };
                if let Some(index) = picked {
                    // The link names it even where no slice view shows it (the single layout).
                    self.view.cursor = Some(index);
                }
                // With the ruler or angle tool the picked position is a measurement's point
                // (measure.rs), as the desktop's 3D click places it; else it moves the crosshair.
                let picked = match (picked, slices.as_deref_mut()) {
                    (Some(index), Some(s)) => {
                        (!crate::measure::picked_in_3d(&mut self.view, s, index)).then_some(index)
                    }
                    (picked, _) => picked,
                };
                if let (Some(s), Some(camera)) = (slices.as_deref_mut(), camera_3d) {
                    crate::measure::paint_in_3d_view(
                        ui.painter(),
                        image_rect,
                        &camera,
                        &self.view,
                        s,
                    );
                }
                if let Some(index) = picked {
                    // The link names it even where no slice view shows it (the single layout).
                    self.view.cursor = Some(index);
                }
                if let (None, Some(slices)) = (slice_rects, slices.as_deref_mut()) {
                    // The 3D view alone: the link's overlay still opens and its 3D grid still
                    // fills (the slice views' frame pumps it otherwise).
                    let token = self.token.as_deref();
                    crate::overlay_view::follow_link(&self.view.overlay, slices, token, &ctx);
                    slices.overlay.pump(&ctx);
                }
                if let (Some(rects), Some(slices)) = (slice_rects, slices) {
                    if let Some(index) = picked {
                        slices.cursor = index;
                    }
                    crate::measure::before_slice_views(&self.view, slices);
                    let token = self.token.as_deref();
                    crate::overlay_view::follow_link(&self.view.overlay, slices, token, &ctx);
                    slices.ui(ui, rects);
                    if let (Some(rect), Some(oblique), Some(angles)) =
                        (oblique_rect, oblique, self.view.oblique.as_mut())
                    {
                        oblique.ui(ui, rect, slices, angles);
                        // Test hook (`capture=1`): each complete image once the pointer is up.
                        let pointer_down = ctx.input(|i| i.pointer.any_down());
                        let capture = match self.view.capture {
                            true => oblique.take_capture(pointer_down, &slices.overlay),
                            false => None,
                        };
                        if let Some(shot) = capture {
                            let token = self.token.clone();
                            wasm_bindgen_futures::spawn_local(async move {
                                let posted = post_frame(
                                    &shot.rgba,
                                    shot.width,
                                    shot.height,
                                    &shot.metrics,
                                    token.as_deref(),
                                );
                                if let Err(e) = posted.await {
                                    show_message(
                                        "The oblique capture could not be sent",
                                        &e.to_string(),
                                    );
                                }
                            });
                        }
                    }
                    // The address follows the crosshair and window, so a link shares them.
                    self.view.cursor = Some(slices.cursor);
                    self.view.window = Some([slices.window.centre, slices.window.width]);
                    // And the measurements (measure.rs).
                    crate::measure::after_slice_views(&mut self.view, slices);
                    self.view.colour_map = slices.colour_map;
                }
                // Not while a drag goes on (the view, a slice, the editor's points): one
                // history entry rewrite when it ends, not one per frame.
                let pointer_down = ctx.input(|i| i.pointer.any_down());
                self.write_fragment(response.dragged() || pointer_down);
            });
        self.history_step(&ctx);
        self.download_step(&ctx);
        self.movie_step(&ctx);
        self.tools.help(&ctx);
        self.capture_step(&ctx);
        self.bridge_step(&ctx);
        self.side.record_frame(ui_started, self.frames_submitted);
    }
}

/// Writes the last click's pick in the 3D view into the canvas's `data-pick` attribute (what
/// it read, or why it found nothing): the picking test says it when the crosshair stays.
fn publish_pick(text: &str) {
    crate::canvas_attributes::set("data-pick", text);
}

/// Writes where the views are on the canvas (CSS pixels, `x,y,w,h`) into the canvas's
/// `data-views` attribute: the browser tests click and drag there (web/tests/browser/input.rs)
/// and compute what the desktop's mappings give for those points. Written only on change.
fn publish_view_rects(
    three_d: egui::Rect,
    slices: Option<[Option<egui::Rect>; 3]>,
    oblique: Option<egui::Rect>,
) {
    let rect_text = |r: egui::Rect| format!("{},{},{},{}", r.min.x, r.min.y, r.width(), r.height());
    let mut text = format!("3d:{}", rect_text(three_d));
    if let Some([axial, coronal, sagittal]) = slices {
        for (name, r) in [
            ("axial", axial),
            ("coronal", coronal),
            ("sagittal", sagittal),
            ("oblique", oblique),
        ] {
            if let Some(r) = r {
                text.push_str(&format!(";{name}:{}", rect_text(r)));
            }
        }
    }
    crate::canvas_attributes::set("data-views", &text);
}
