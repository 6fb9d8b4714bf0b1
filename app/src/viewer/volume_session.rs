//! The one place where the viewer meets the loader and the GPU: a named render thread owns its
//! own wgpu device, the brick cache and the raycaster, takes the newest [`RenderRequest`] from
//! the UI and publishes finished frames as RGBA for the UI to show.
//!
//! Why a device of its own rather than eframe's: on one queue a raycast that takes 200 ms
//! (lavapipe, or a big volume on a real GPU, which does not preempt compute) holds every UI
//! frame behind it. On its own device and thread the UI keeps its frame rate while the volume
//! renders at whatever rate it can; the cost is one RGBA readback per volume frame.
//!
//! Residency today is the loader's fixed cut: the root level first (one brick, shown at once),
//! then the finest level whose bricks fit the GPU budget, read on a second named thread and
//! swapped in when complete. TODO(streaming): when `strata_loader::StreamingVolume` is
//! committed, replace `CutResidency` with it (`frame()` per request, `set_max_voxel_pixels`
//! from the controller's lod factor); nothing outside this file needs to change.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use strata_loader::store_volume::{classify_empty, page_table_for_cut, GpuCut};
use strata_loader::{render_geometry, render_mapping, ResidentBricks};
use strata_render::{
    Camera, FrameQuality, GpuContext, PageTable, RenderMode, RenderSettings, TimeCriticalConfig,
    TimeCriticalController, TransferFunction, TransferFunctionTable, ValueMapping, VolumeGeometry,
};
use strata_storage::{Store, StoreHeader};

/// GPU memory the fixed cut may use: the finest level whose bricks fit is loaded.
pub const DEFAULT_GPU_BUDGET_BYTES: u64 = 384 << 20;
const BRICK_SLOT_BYTES: u64 = strata_render::BRICK_PAYLOAD_VOXELS as u64 * 2;

/// What the UI wants to see; the render thread always works on the newest one.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderRequest {
    pub camera: Camera,
    pub settings: RenderSettings,
    pub transfer_function: TransferFunction,
    /// Some(fps): the time-critical controller sets the sampling rate; None: `settings.quality`.
    pub target_fps: Option<f64>,
    /// The user is dragging: interactive quality; when it stops, still frames refine.
    pub interacting: bool,
}

/// A finished volume frame, premultiplied RGBA8, row 0 at the top.
#[derive(Clone)]
pub struct RenderedFrame {
    pub width: u32,
    pub height: u32,
    pub rgba: Arc<Vec<u8>>,
    /// Increments with every published frame, so the UI re-uploads only new ones.
    pub serial: u64,
    /// The request this frame answers (the UI compares to know whether it is current).
    pub request: RenderRequest,
    pub finished_at: Instant,
}

/// Figures for the performance panel.
#[derive(Clone, Debug, Default)]
pub struct SessionStatus {
    pub adapter: String,
    pub loading: Option<String>,
    pub error: Option<String>,
    pub shown_level: Option<u8>,
    pub target_level: u8,
    pub level_count: usize,
    pub resident_bricks: usize,
    pub gpu_cache_bytes: u64,
    pub gpu_budget_bytes: u64,
    /// Volume frame times (GPU timestamps, or submit→done) with when they arrived, newest last.
    pub volume_frame_ms: Vec<(Instant, f64)>,
    pub sampling_rate: f64,
    pub lod_factor: f64,
    /// More frames are coming without input: a finer cut is loading or still frames refine.
    pub refining: bool,
    pub frames_rendered: u64,
    pub last_screenshot: Option<Result<PathBuf, String>>,
}

/// A request to write the 3D view to PNG at `scale` × the on-screen size.
#[derive(Clone, Debug)]
pub struct ScreenshotRequest {
    pub path: PathBuf,
    pub scale: u32,
}

/// Static facts of the opened volume, for the UI.
#[derive(Clone, Debug)]
pub struct VolumeInfo {
    pub header: StoreHeader,
    pub geometry: VolumeGeometry,
    pub mapping: ValueMapping,
    /// Physical range of the stored values (the transfer function's domain).
    pub physical_range: (f64, f64),
}

impl VolumeInfo {
    pub fn of(store: &Store) -> anyhow::Result<Self> {
        let header = store.header().clone();
        let geometry = render_geometry(&header)?;
        let mapping = render_mapping(&header);
        let a = mapping.physical(header.stored_range[0] as f64);
        let b = mapping.physical(header.stored_range[1] as f64);
        Ok(VolumeInfo { header, geometry, mapping, physical_range: (a.min(b), a.max(b)) })
    }

    pub fn tf_table(&self, tf: &TransferFunction) -> TransferFunctionTable {
        let (lo, hi) = self.physical_range;
        // A constant volume still needs a non-empty domain.
        tf.table(lo, if hi > lo { hi } else { lo + 1.0 })
    }
}

struct Shared {
    request: Mutex<Option<RenderRequest>>,
    wake: Condvar,
    frame: Mutex<Option<RenderedFrame>>,
    status: Mutex<SessionStatus>,
    screenshot: Mutex<Option<ScreenshotRequest>>,
    stop: AtomicBool,
}

/// Handle held by the UI. Dropping it stops the render thread.
pub struct VolumeSession {
    shared: Arc<Shared>,
    info: VolumeInfo,
    thread: Option<std::thread::JoinHandle<()>>,
}

pub type Repaint = Arc<dyn Fn() + Send + Sync>;

impl VolumeSession {
    /// Starts the render thread on an opened store. Never blocks on the GPU or the disk.
    pub fn start(store: Arc<Store>, gpu_budget_bytes: u64, repaint: Repaint) -> anyhow::Result<Self> {
        let info = VolumeInfo::of(&store)?;
        let shared = Arc::new(Shared {
            request: Mutex::new(None),
            wake: Condvar::new(),
            frame: Mutex::new(None),
            status: Mutex::new(SessionStatus {
                loading: Some("starting the renderer".into()),
                gpu_budget_bytes,
                level_count: store.layout().level_count(),
                sampling_rate: 2.0,
                lod_factor: 1.0,
                ..Default::default()
            }),
            screenshot: Mutex::new(None),
            stop: AtomicBool::new(false),
        });
        let thread_shared = shared.clone();
        let thread_info = info.clone();
        let thread = std::thread::Builder::new().name("strata-volume-render".into()).spawn(move || {
            let mut worker = RenderWorker::new(store, thread_info, thread_shared.clone(), repaint.clone(), gpu_budget_bytes);
            if let Err(e) = worker.run() {
                lock(&thread_shared.status).error = Some(format!("{e:#}"));
                repaint();
            }
        })?;
        Ok(VolumeSession { shared, info, thread: Some(thread) })
    }

    pub fn info(&self) -> &VolumeInfo {
        &self.info
    }

    /// Replaces the pending request (older ones are never rendered).
    pub fn request(&self, request: RenderRequest) {
        let mut slot = lock(&self.shared.request);
        if slot.as_ref() != Some(&request) {
            *slot = Some(request);
            self.shared.wake.notify_all();
        }
    }

    pub fn request_screenshot(&self, request: ScreenshotRequest) {
        *lock(&self.shared.screenshot) = Some(request);
        self.shared.wake.notify_all();
    }

    /// The newest finished frame.
    pub fn latest_frame(&self) -> Option<RenderedFrame> {
        lock(&self.shared.frame).clone()
    }

    pub fn status(&self) -> SessionStatus {
        lock(&self.shared.status).clone()
    }
}

impl Drop for VolumeSession {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        self.shared.wake.notify_all();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// A poisoned lock only means another thread panicked mid-update of plain data; the data is
/// still usable for display, so keep going rather than take the UI down too.
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Without a GPU the raycast runs on lavapipe's CPU threads, which would starve the UI of the
/// same cores. Linux nice values are per thread and inherited by threads created later, so
/// lowering this thread before it creates its device lowers the driver's workers too: the UI
/// keeps its frame rate and the volume takes the rest. Harmless with a real GPU.
fn lower_this_threads_priority() {
    #[cfg(target_os = "linux")]
    // SAFETY: plain syscalls on the calling thread's id; failure only leaves the priority as is.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        let _ = libc::setpriority(libc::PRIO_PROCESS, tid, 10);
    }
}

/// The finest level whose whole cut fits `budget` (always at least the root).
fn finest_level_within(store: &Store, budget: u64) -> u8 {
    let layout = store.layout();
    let root = layout.level_count() - 1;
    let max_slots = strata_render::page_table::MAX_SLOTS as u64;
    (0..=root)
        .find(|&l| {
            let n = layout.brick_count_in_level(l);
            n * BRICK_SLOT_BYTES <= budget && n <= max_slots
        })
        .unwrap_or(root) as u8
}

/// A cut read off the render thread, ready to upload.
struct LoadedCut {
    level: u8,
    table: PageTable,
    bricks: ResidentBricks,
}

/// What is on the GPU now.
struct CutResidency {
    level: u8,
    /// The cut's table before emptiness classification (depends on TF and mode).
    base_table: PageTable,
    gpu: GpuCut,
    bricks: usize,
    /// (TF, mode) the GPU page table was classified for.
    classified_for: Option<(TransferFunction, RenderMode)>,
}

struct RenderWorker {
    store: Arc<Store>,
    info: VolumeInfo,
    shared: Arc<Shared>,
    repaint: Repaint,
    gpu_budget_bytes: u64,
    controller: TimeCriticalController,
    serial: u64,
}

impl RenderWorker {
    fn new(store: Arc<Store>, info: VolumeInfo, shared: Arc<Shared>, repaint: Repaint, gpu_budget_bytes: u64) -> Self {
        RenderWorker {
            store,
            info,
            shared,
            repaint,
            gpu_budget_bytes,
            controller: TimeCriticalController::new(TimeCriticalConfig::default(), 1.0),
            serial: 0,
        }
    }

    fn set_status(&self, f: impl FnOnce(&mut SessionStatus)) {
        f(&mut lock(&self.shared.status));
        (self.repaint)();
    }

    fn load_cut(store: &Store, geometry: &VolumeGeometry, level: u8) -> anyhow::Result<LoadedCut> {
        let table = page_table_for_cut(store, geometry, |_| level);
        let bricks = ResidentBricks::load(store, &table)?;
        Ok(LoadedCut { level, table, bricks })
    }

    fn upload(&self, ctx: &GpuContext, cut: LoadedCut, tf: &TransferFunction) -> anyhow::Result<CutResidency> {
        let tf_table = self.info.tf_table(tf);
        let gpu = GpuCut::upload(ctx, &cut.bricks, &cut.table, self.info.geometry.page_dims(), &tf_table)?;
        Ok(CutResidency { level: cut.level, base_table: cut.table, gpu, bricks: cut.bricks.len(), classified_for: None })
    }

    fn run(&mut self) -> anyhow::Result<()> {
        lower_this_threads_priority();
        let ctx = GpuContext::headless()?;
        let adapter = ctx.adapter_name();
        let root = (self.store.layout().level_count() - 1) as u8;
        let target_level = finest_level_within(&self.store, self.gpu_budget_bytes);
        self.set_status(|s| {
            s.adapter = adapter;
            s.target_level = target_level;
            s.loading = Some("reading the coarsest level".into());
        });
        // The root is one brick: read it here so the first frame comes at once.
        let root_cut = Self::load_cut(&self.store, &self.info.geometry, root)?;
        let default_tf = TransferFunction::preset("ct-bone").ok_or_else(|| anyhow::anyhow!("missing preset"))?;
        let mut residency = self.upload(&ctx, root_cut, &default_tf)?;
        let (cut_tx, cut_rx) = crossbeam_channel::bounded::<anyhow::Result<LoadedCut>>(1);
        if target_level < root {
            let store = self.store.clone();
            let geometry = self.info.geometry.clone();
            std::thread::Builder::new().name("strata-cut-reader".into()).spawn(move || {
                let _ = cut_tx.send(Self::load_cut(&store, &geometry, target_level));
            })?;
            self.set_status(|s| s.loading = Some(format!("reading level {target_level} bricks")));
        } else {
            self.set_status(|s| s.loading = None);
        }
        self.set_status(|s| {
            s.shown_level = Some(residency.level);
            s.resident_bricks = residency.bricks;
            s.gpu_cache_bytes = residency.bricks as u64 * BRICK_SLOT_BYTES;
        });

        let mut last_rendered: Option<RenderRequest> = None;
        let mut cut_changed = false;
        let mut frame_ms_history: Vec<(Instant, f64)> = Vec::new();
        loop {
            if self.shared.stop.load(Ordering::Acquire) {
                return Ok(());
            }
            if let Ok(loaded) = cut_rx.try_recv() {
                match loaded.and_then(|cut| {
                    let tf = last_rendered.as_ref().map(|r| r.transfer_function.clone()).unwrap_or_else(|| default_tf.clone());
                    self.upload(&ctx, cut, &tf)
                }) {
                    Ok(finer) => {
                        residency = finer;
                        cut_changed = true;
                        self.set_status(|s| {
                            s.loading = None;
                            s.shown_level = Some(residency.level);
                            s.resident_bricks = residency.bricks;
                            s.gpu_cache_bytes = residency.bricks as u64 * BRICK_SLOT_BYTES;
                        });
                    }
                    // The coarse cut stays usable; say why it stays coarse.
                    Err(e) => self.set_status(|s| {
                        s.loading = None;
                        s.error = Some(format!("finer level not loaded: {e:#}"));
                    }),
                }
            }
            let screenshot = lock(&self.shared.screenshot).take();
            if let Some(shot) = screenshot {
                let result = match last_rendered.clone() {
                    Some(request) => self.screenshot(&ctx, &mut residency, &request, &shot),
                    None => Err(anyhow::anyhow!("nothing rendered yet")),
                };
                self.set_status(|s| s.last_screenshot = Some(result.map(|_| shot.path.clone()).map_err(|e| format!("{e:#}"))));
            }
            let request = lock(&self.shared.request).clone();
            let Some(request) = request else {
                self.wait(Duration::from_millis(50));
                continue;
            };
            let new_request = last_rendered.as_ref() != Some(&request);
            let still_refining = request.target_fps.is_some() && !request.interacting && !self.controller.still_refinement_done();
            if !(new_request || cut_changed || still_refining) {
                let loading = lock(&self.shared.status).loading.is_some();
                self.set_status(|s| s.refining = loading);
                self.wait(Duration::from_millis(if loading { 20 } else { 100 }));
                continue;
            }
            cut_changed = false;
            let quality = self.render(&ctx, &mut residency, &request)?;
            for timing in residency.gpu.raycaster.try_take_frame_timings(&ctx) {
                if request.target_fps.is_some() {
                    self.controller.observe(timing);
                }
                frame_ms_history.push((Instant::now(), timing.milliseconds));
            }
            if frame_ms_history.len() > 240 {
                frame_ms_history.drain(..frame_ms_history.len() - 240);
            }
            let refining = lock(&self.shared.status).loading.is_some()
                || (request.target_fps.is_some() && !request.interacting && !self.controller.still_refinement_done());
            let history = frame_ms_history.clone();
            self.set_status(|s| {
                s.frames_rendered += 1;
                s.volume_frame_ms = history;
                s.refining = refining;
                if let Some(q) = quality {
                    s.sampling_rate = q.sampling_rate;
                    s.lod_factor = q.lod_factor;
                } else {
                    s.sampling_rate = 1.0 / request.settings.quality;
                    s.lod_factor = 1.0;
                }
            });
            last_rendered = Some(request);
        }
    }

    fn wait(&self, timeout: Duration) {
        let guard = lock(&self.shared.request);
        let _ = self.shared.wake.wait_timeout(guard, timeout);
    }

    /// Brings the GPU transfer function and page-table emptiness in line with the request.
    fn sync_transfer_function(&self, ctx: &GpuContext, residency: &mut CutResidency, request: &RenderRequest) -> anyhow::Result<()> {
        let key = (request.transfer_function.clone(), request.settings.mode);
        if residency.classified_for.as_ref() == Some(&key) {
            return Ok(());
        }
        let tf_table = self.info.tf_table(&request.transfer_function);
        residency.gpu.transfer_function.update(&ctx.queue, &tf_table);
        let mut table = residency.base_table.clone();
        // Skipping transparent bricks is exact for DVR only (MIP and iso look at raw values).
        if request.settings.mode == RenderMode::Dvr {
            classify_empty(&self.store, &mut table, self.info.mapping, &tf_table);
        }
        residency.gpu.page_table.update(&ctx.queue, &table)?;
        residency.classified_for = Some(key);
        Ok(())
    }

    fn render(&mut self, ctx: &GpuContext, residency: &mut CutResidency, request: &RenderRequest) -> anyhow::Result<Option<FrameQuality>> {
        self.sync_transfer_function(ctx, residency, request)?;
        let mut settings = request.settings.clone();
        let quality = request.target_fps.map(|fps| {
            if (self.controller.config().controller.target_fps - fps).abs() > 1e-9 {
                self.controller.set_target_fps(fps);
            }
            let q = self.controller.plan_frame(request.interacting);
            q.apply_to(&mut settings);
            q
        });
        settings.frame_index = self.serial as u32;
        let scene = strata_render::Scene {
            cache: &residency.gpu.cache,
            page_table: &residency.gpu.page_table,
            transfer_function: &residency.gpu.transfer_function,
            geometry: &self.info.geometry,
            mapping: self.info.mapping,
            camera: &request.camera,
            settings: &settings,
        };
        let raycaster = &mut residency.gpu.raycaster;
        raycaster.render(ctx, &scene)?;
        if let Some(q) = quality {
            self.controller.submitted(raycaster.frame_number(), q);
        }
        let frame = raycaster.read_frame_blocking(ctx)?;
        self.serial += 1;
        *lock(&self.shared.frame) = Some(RenderedFrame {
            width: frame.width,
            height: frame.height,
            rgba: Arc::new(frame.rgba),
            serial: self.serial,
            request: request.clone(),
            finished_at: Instant::now(),
        });
        (self.repaint)();
        Ok(quality)
    }

    /// Renders the last request at `scale` × its size at full quality and writes a PNG.
    fn screenshot(&mut self, ctx: &GpuContext, residency: &mut CutResidency, request: &RenderRequest, shot: &ScreenshotRequest) -> anyhow::Result<()> {
        self.sync_transfer_function(ctx, residency, request)?;
        let scale = shot.scale.clamp(1, 4);
        let mut settings = request.settings.clone();
        settings.width = (settings.width * scale).min(4096);
        settings.height = (settings.height * scale).min(4096);
        settings.quality = settings.quality.min(0.5);
        let scene = strata_render::Scene {
            cache: &residency.gpu.cache,
            page_table: &residency.gpu.page_table,
            transfer_function: &residency.gpu.transfer_function,
            geometry: &self.info.geometry,
            mapping: self.info.mapping,
            camera: &request.camera,
            settings: &settings,
        };
        let frame = residency.gpu.raycaster.render_blocking(ctx, &scene)?;
        crate::cmd_render::write_png(&shot.path, frame.width, frame.height, &frame.rgba)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_generous_budget_takes_level_zero_and_a_tiny_one_the_root() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("p.strata");
        strata_storage::phantom::Phantom::cube(70)
            .write_store(&path, &Default::default())
            .expect("phantom store");
        let store = Store::open(&path).expect("open");
        assert_eq!(finest_level_within(&store, 1 << 30), 0);
        let root = (store.layout().level_count() - 1) as u8;
        assert_eq!(finest_level_within(&store, BRICK_SLOT_BYTES), root);
    }
}
