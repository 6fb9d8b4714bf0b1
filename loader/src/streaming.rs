//! The streaming working set: each frame, take what the fetch workers delivered, read the
//! visibility feedback without waiting, select the cut, upload within the frame's budget into
//! GPU slots, rewrite the page table if the cut changed, hand the missing bricks to the
//! workers, and submit the raycast. Nothing here waits for a read: the root is read once at
//! open and stays pinned, so every frame draws the whole volume and refines over frames.
//! Selecting the cut and building the page table run on the selection thread (cut_worker.rs);
//! the frame applies a finished selection: its uploads and the table's changed spans.
//!
//! Selection timing (`StreamingConfig::selection`): `Background` (viewer, flythrough: apply the
//! newest finished selection, never wait), `EachFrame` (tests, headless commands: wait for this
//! view's), `EveryNthFrame(n)` (tests: the background timing at a fast GPU's cadence,
//! deterministic). The upload budget is per frame: a selection uploads `uploads_per_frame` × the
//! frames between the last two applied selections (at most 16).
//! `FrameStats::cut_changes_while_still_total` counts LOD flicker. Traversal: flat unless its per-page buffers exceed the binding limit or the
//! grid has more than `flat_table_max_page_cells` (2^18) page cells; then the octree, with
//! `traversal_note` saying why.

use std::collections::VecDeque;

// Keys are brick ids, not attacker-chosen: a fast hash on the frame thread.
use rustc_hash::FxHashSet as HashSet;
use std::sync::Arc;
// std's Instant panics in the browser; web-time is std's natively.
use web_time::Instant;

use strata_render::{
    BrickCache, CacheConfig, Camera, FrameInputs, FrameReadback, GpuContext, GpuPageTable,
    GpuTransferFunction, IndexTable, PageEntry, PageTable, PreparedPageTable, Raycaster,
    RenderMode, RenderSettings, SparsePageTable, TransferFunction, TransferFunctionTable,
    Traversal, ValueMapping, VolumeGeometry, BRICK_PAYLOAD_VOXELS,
};
use strata_source::{BrickFetcher, FetchOptions, SourceStatus, VolumeSource};
#[cfg(feature = "local")]
use strata_storage::Store;
use strata_types::BrickId;

use crate::cpu_cache::{Brick, CpuBrickCache};
use crate::cut_payloads::CutPayloads;
use crate::cut_selection::{Cut, CutLimits, ViewSetup};
use crate::cut_worker::{
    CutWorker, MipBounds, PageTableKey, ResidencySnapshot, Selected, SelectionJob, SelectionTiming,
    SettledCut, ViewInputs,
};
use crate::error::LoaderError;
use crate::fetch_workers::{FetchWorkers, InlineReads};
use crate::gpu_slots::GpuSlots;
use crate::metrics::FrameStats;
use crate::octree_ranges::OctreeRanges;
use crate::predicted_cut::{CutPredictor, EmptinessSpec, PredictionJob};
use crate::prefetch::MotionPredictor;
use crate::visibility::PageVisibility;

/// Bytes of one decompressed brick as the loader holds it (u16 samples).
pub const BRICK_BYTES: u64 = (BRICK_PAYLOAD_VOXELS * 2) as u64;

#[derive(Clone, Debug)]
pub struct StreamingConfig {
    /// GPU memory for the brick cache texture.
    pub gpu_budget_bytes: u64,
    /// Cap on cache slots (tests use tiny caches).
    pub max_gpu_slots: Option<u32>,
    /// System memory for bricks, sled's page cache included.
    pub cpu_budget_bytes: u64,
    /// sled's cache of compressed pages, carved out of `cpu_budget_bytes`. Our decompressed
    /// LRU already keeps hot bricks, so this stays small: it mostly holds B-tree index pages.
    pub sled_cache_bytes: u64,
    /// Bricks uploaded per frame at most (octree paper §7: 200 ms stalls without a budget).
    pub uploads_per_frame: usize,
    /// Quality factor: refine while one voxel projects to more than this many pixels.
    pub max_voxel_pixels: f64,
    pub fetch_threads: usize,
    /// Bricks read but not yet taken into the CPU cache (the frame loop takes them once per
    /// frame): bounds the result channel, counted in the CPU budget. Too small a bound caps
    /// reads per frame, which on slow frames throttles loading.
    pub bricks_in_transit: usize,
    /// Bound on queued requests (stale ones are dropped each frame anyway).
    pub max_queued_requests: usize,
    pub visibility_feedback: bool,
    /// Cut generations (cut changes) a page stays visible after the one under which it was
    /// last seen contributing: never frames, whose count per selection varies with the GPU's
    /// speed (see visibility.rs).
    pub visibility_memory_generations: u64,
    pub prefetch: bool,
    /// Prefetch requests queued per frame at most.
    pub prefetch_per_frame: usize,
    /// Whether a frame waits for its own view's selection or applies the newest finished one.
    pub selection: SelectionTiming,
    /// How the raycaster finds the bricks: the flat page table or the cut's octree. None
    /// (the default): the flat table where it fits the limit below, else the octree, said in
    /// [`StreamingVolume::traversal_note`].
    pub traversal: Option<Traversal>,
    /// The most bytes the flat table's largest per-page buffer may take, where below the
    /// device's storage-binding limit (tests make the limit bind on a small volume).
    pub flat_table_limit_bytes: Option<u64>,
    /// With the traversal left open, the most page cells the flat table is chosen for even
    /// where it fits the binding limit: its CPU side is per page cell (each cut change
    /// rebuilds the table, each feedback frame walks the visibility per cell), which at
    /// 8192³ (16.7 M cells) cost 135 ms of frame-thread CPU per frame against 0.5 ms with
    /// the octree. Default 2^18: up to 2048³ voxels stays flat, whose frames are faster.
    pub flat_table_max_page_cells: u64,
    /// Where the loader's work runs: its own threads, or the frame thread alone.
    pub work: LoaderWork,
}

/// Where the loader's work (cut selection, prediction, reads without a source's own
/// asynchronous path) runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LoaderWork {
    /// Named threads: `strata-cut-select`, `strata-cut-predict` and the reader threads.
    Threads,
    /// The frame thread alone, in bounded steps: a selection and a prediction when asked for
    /// (as the threads would give them, one frame later at the earliest with the background
    /// timing) and at most `fetch_threads` blocking reads per frame for a source without its
    /// own asynchronous path. For the browser (wasm32 has no threads without shared memory);
    /// natively for tests of that mode.
    Inline,
}

impl Default for LoaderWork {
    fn default() -> Self {
        if cfg!(target_arch = "wasm32") {
            LoaderWork::Inline
        } else {
            LoaderWork::Threads
        }
    }
}

impl Default for StreamingConfig {
    fn default() -> Self {
        StreamingConfig {
            gpu_budget_bytes: 256 << 20,
            max_gpu_slots: None,
            cpu_budget_bytes: 512 << 20,
            sled_cache_bytes: 16 << 20,
            uploads_per_frame: 32,
            max_voxel_pixels: 1.0,
            fetch_threads: 2,
            bricks_in_transit: 128,
            max_queued_requests: 256,
            visibility_feedback: true,
            visibility_memory_generations: 3,
            prefetch: true,
            prefetch_per_frame: 16,
            selection: SelectionTiming::EachFrame,
            traversal: None,
            flat_table_limit_bytes: None,
            flat_table_max_page_cells: 1 << 18,
            work: LoaderWork::default(),
        }
    }
}

impl StreamingConfig {
    /// Bricks that may sit between a worker and the CPU cache (being read, or in the result
    /// channel): counted against the CPU budget.
    fn in_transit_bytes(&self) -> u64 {
        (self.fetch_threads.max(1) + self.bricks_in_transit.max(1)) as u64 * BRICK_BYTES
    }

    fn cpu_cache_budget(&self) -> Result<u64, LoaderError> {
        let reserved = self.sled_cache_bytes + self.in_transit_bytes();
        self.cpu_budget_bytes.checked_sub(reserved).filter(|&b| b >= BRICK_BYTES).ok_or_else(|| {
            LoaderError::Unsupported(format!(
                "CPU budget of {} bytes leaves no room for a brick after sled's cache ({} bytes) and bricks in transit",
                self.cpu_budget_bytes, reserved
            ))
        })
    }
}

/// A brick that could not be read, reported once.
#[derive(Clone, Debug, PartialEq)]
pub struct BrickFailure {
    pub id: BrickId,
    pub message: String,
}

/// A page-table entry whose slot does not hold the node it names (found by
/// [`StreamingVolume::check_slot_map`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("the table names {node:?} in slot {table_slot}, slot map says {slot_map:?}")]
pub struct SlotMapMismatch {
    pub node: BrickId,
    pub table_slot: u32,
    pub slot_map: Option<u32>,
}

pub struct StreamingVolume {
    config: StreamingConfig,
    geometry: VolumeGeometry,
    mapping: ValueMapping,
    octree: Arc<OctreeRanges>,
    root: BrickId,
    /// The root's voxels: read once at construction and uploaded straight to its pinned slot,
    /// never through the CPU cache, so a CPU pass over the cut (cut_payloads.rs) takes them
    /// from here rather than reading the root again.
    root_brick: Brick,
    tf_table: Arc<TransferFunctionTable>,
    cache: BrickCache,
    gpu_page_table: GpuPageTable,
    transfer_function: GpuTransferFunction,
    raycaster: Raycaster,
    /// The table the GPU holds (shared with the selection thread's jobs): per page cell with
    /// the flat traversal, per leaf with the octree (O(cut): see sparse_page_table.rs).
    page_table: Arc<IndexTable>,
    slots: GpuSlots,
    cpu: CpuBrickCache,
    workers: Box<dyn BrickFetcher>,
    source: Arc<dyn VolumeSource>,
    /// Shared with the selection thread's job; copied on write while a job still holds it.
    visibility: Arc<PageVisibility>,
    motion: MotionPredictor,
    /// Selects the motion-extrapolated cut off the frame thread.
    predictor: CutPredictor,
    /// Selects the cut and builds the page table off the frame thread.
    selector: CutWorker,
    failed: HashSet<BrickId>,
    new_failures: Vec<BrickFailure>,
    frame: u64,
    renders: u64,
    cut_changed_at_render: u64,
    bricks_read: u64,
    stored_bytes_read: u64,
    read_history: VecDeque<(Instant, u64)>,
    last_stats: FrameStats,
    working_set: Vec<BrickId>,
    /// Nodes the last applied cut refined: the incumbents hysteresis protects.
    refined_last_frame: Arc<HashSet<BrickId>>,
    /// What the current page table was built from.
    page_table_key: Arc<PageTableKey>,
    /// The last applied cut (uploads done) with the view it was selected for.
    current: Option<SettledCut>,
    /// The current cut was complete, uploaded nothing and left the table as it was when
    /// applied: converged, while the view stays the same.
    current_converged: bool,
    /// The last complete cut applied (its uploads done) with its view: while the view stays
    /// the same, a selection may only refine it (see cut_worker.rs's keep_settled_cut).
    settled: Option<SettledCut>,
    /// Frames between the last two applied selections (1 when each frame selects): the
    /// upload budget is per frame, so a selection may upload for each frame it spans.
    frames_per_selection: u64,
    /// Frame at which the last selection was applied.
    applied_at_frame: u64,
    selections_applied: u64,
    selections_dropped: u64,
    /// See [`FrameStats::cut_changes_while_still_total`].
    cut_changes_while_still: u64,
    /// The view inputs the loader last reported converged for (flicker after that counts).
    converged_for: Option<ViewInputs>,
    /// Counts transfer-function changes (emptiness changes with them).
    tf_generation: u64,
    /// Why the traversal was chosen when the configuration left it open and the flat table
    /// did not fit.
    traversal_note: Option<String>,
    /// Incremented by every upload into a slot and every page-table rewrite: equal values mean
    /// the same bricks in the same slots under the same table (what a pass built from the cut,
    /// the viewer's adaptive oracle, is valid for).
    residency_generation: u64,
}

impl StreamingVolume {
    /// Opens `path` with sled's cache sized from `config` and streams from it.
    #[cfg(feature = "local")]
    pub fn open(
        ctx: &GpuContext,
        path: &std::path::Path,
        tf: &TransferFunction,
        config: StreamingConfig,
    ) -> Result<Self, LoaderError> {
        let store = Arc::new(Store::open_with_cache(path, config.sled_cache_bytes)?);
        Self::new(ctx, store, tf, config)
    }

    /// Streams `source`'s octree (a local store, a remote one, or a wrapper), through the
    /// source's own asynchronous request path or else reader threads. Reads the root
    /// synchronously: one brick, before the first frame.
    pub fn new(
        ctx: &GpuContext,
        source: Arc<dyn VolumeSource>,
        tf: &TransferFunction,
        config: StreamingConfig,
    ) -> Result<Self, LoaderError> {
        // Before this volume's threads allocate bricks (see malloc_arenas.rs).
        crate::malloc_arenas::limit_malloc_arenas();
        tf.validate()?;
        let reader = source.clone();
        let header = source.header();
        let geometry = header.geometry.clone();
        let mapping = header.value_mapping.mapping;
        let octree = Arc::new(OctreeRanges::from_source(source.as_ref()));
        let root = BrickId::new(octree.root_level(), [0, 0, 0]);
        let tf_table = Arc::new(tf_table_for(tf, mapping, header.stored_range));
        let cpu = CpuBrickCache::new(config.cpu_cache_budget()?);
        // The texture grows with the slots in use: the first frame does not wait for a
        // budget-sized texture to be zeroed (render/src/gpu/cache.rs).
        let mut cache = BrickCache::new(
            &ctx.device,
            CacheConfig {
                budget_bytes: config.gpu_budget_bytes,
                max_slots: config.max_gpu_slots,
                grow_with_use: true,
                ..Default::default()
            },
        )?;
        // A budget the device cannot hold fails now, named, not when the cache grows into it.
        cache.check_full_allocation(&ctx.device, config.gpu_budget_bytes)?;
        let mut slots = GpuSlots::new(cache.slot_count());
        let root_record = reader.read_brick_record(root)?;
        let root_bytes = root_record.len() as u64;
        let root_brick: Brick = Arc::new(
            strata_storage::brick::decode_brick(root, &root_record)
                .map_err(|e| strata_source::SourceError::damaged(&reader.location(), root, e))?,
        );
        let root_slot = slots
            .allocate(root, 0, true)
            .ok_or_else(|| LoaderError::Inconsistent("no slot for the root".into()))?;
        cache.ensure_slot(&ctx.device, &ctx.queue, root_slot)?;
        cache.upload_brick(&ctx.queue, root_slot, &root_brick)?;
        let page_dims = geometry.page_dims();
        let (traversal, traversal_note) = choose_traversal(ctx, page_dims, &config)?;
        let gpu_page_table = GpuPageTable::with_traversal_limited(
            &ctx.device,
            page_dims,
            &cache,
            traversal,
            config.flat_table_limit_bytes,
        )?;
        // The root alone: every page cell shows it.
        let root_entry = PageEntry::resident(root_slot, root.level);
        let prepared = match traversal {
            Traversal::Flat => {
                let mut page_table = PageTable::new(page_dims);
                page_table.entries.fill(root_entry);
                PreparedPageTable::new(gpu_page_table.layout(), page_table)?
            }
            Traversal::Octree => PreparedPageTable::sparse(
                gpu_page_table.layout(),
                SparsePageTable::uniform(page_dims, root_entry),
            )?,
        };
        gpu_page_table.write_prepared(&ctx.queue, &prepared)?;
        let page_table = Arc::new(prepared.into_table());
        let transfer_function = GpuTransferFunction::new(&ctx.device, &ctx.queue, &tf_table);
        let raycaster = Raycaster::new(ctx, &cache);
        let options = FetchOptions {
            max_queued: config.max_queued_requests,
            max_in_transit: config.bricks_in_transit,
            threads: config.fetch_threads,
        };
        let workers: Box<dyn BrickFetcher> = match (source.start_fetching(options), config.work) {
            (Some(fetcher), _) => fetcher?,
            (None, LoaderWork::Threads) => Box::new(FetchWorkers::start(
                reader.clone(),
                config.fetch_threads,
                config.max_queued_requests,
                config.bricks_in_transit,
            )?),
            (None, LoaderWork::Inline) => Box::new(InlineReads::new(
                reader.clone(),
                config.fetch_threads,
                config.max_queued_requests,
            )),
        };
        let visibility = Arc::new(match traversal {
            Traversal::Flat => PageVisibility::new(&octree, config.visibility_memory_generations),
            Traversal::Octree => {
                PageVisibility::per_leaf(&octree, config.visibility_memory_generations)
            }
        });
        let (predictor, selector) = match config.work {
            LoaderWork::Threads => (
                CutPredictor::start(octree.clone())?,
                CutWorker::start(octree.clone())?,
            ),
            LoaderWork::Inline => (
                CutPredictor::inline(octree.clone()),
                CutWorker::inline(octree.clone()),
            ),
        };
        Ok(StreamingVolume {
            geometry,
            mapping,
            octree,
            root,
            root_brick,
            tf_table,
            cache,
            gpu_page_table,
            transfer_function,
            raycaster,
            page_table,
            slots,
            cpu,
            workers,
            source,
            visibility,
            motion: MotionPredictor::new(4.0),
            predictor,
            selector,
            failed: HashSet::default(),
            new_failures: Vec::new(),
            frame: 0,
            renders: 0,
            cut_changed_at_render: 1,
            bricks_read: 1,
            stored_bytes_read: root_bytes,
            read_history: VecDeque::new(),
            last_stats: FrameStats::default(),
            working_set: vec![root],
            refined_last_frame: Arc::default(),
            page_table_key: Arc::default(),
            current: None,
            current_converged: false,
            settled: None,
            frames_per_selection: 1,
            applied_at_frame: 0,
            selections_applied: 0,
            selections_dropped: 0,
            cut_changes_while_still: 0,
            converged_for: None,
            tf_generation: 0,
            traversal_note,
            residency_generation: 0,
            config,
        })
    }

    /// The traversal the raycaster uses for this volume.
    pub fn traversal(&self) -> Traversal {
        self.gpu_page_table.traversal()
    }

    /// Some when the configuration left the traversal open and the flat table was refused
    /// (its size against the limit): says so, for the status line or the log.
    pub fn traversal_note(&self) -> Option<&str> {
        self.traversal_note.as_deref()
    }

    /// GPU bytes of the index the raycaster reads (flat: per page cell; octree: per node and
    /// leaf of the cut), as last written.
    pub fn gpu_index_bytes(&self) -> u64 {
        self.gpu_page_table.gpu_index_bytes()
    }

    pub fn geometry(&self) -> &VolumeGeometry {
        &self.geometry
    }

    pub fn mapping(&self) -> ValueMapping {
        self.mapping
    }

    pub fn transfer_function_table(&self) -> &TransferFunctionTable {
        &self.tf_table
    }

    pub fn config(&self) -> &StreamingConfig {
        &self.config
    }

    /// The quality factor; takes effect next frame.
    pub fn set_max_voxel_pixels(&mut self, pixels: f64) {
        if pixels.is_finite() && pixels > 0.0 {
            self.config.max_voxel_pixels = pixels;
        }
    }

    /// New transfer function: emptiness and the cut follow on the next frame.
    pub fn set_transfer_function(
        &mut self,
        ctx: &GpuContext,
        tf: &TransferFunction,
    ) -> Result<(), LoaderError> {
        tf.validate()?;
        self.tf_table = Arc::new(tf_table_for_range(tf, self.tf_table.lo, self.tf_table.hi));
        self.transfer_function.update(&ctx.queue, &self.tf_table);
        self.tf_generation += 1;
        Ok(())
    }

    /// The page table of the last frame: dense with the flat traversal, per leaf with the
    /// octree ([`IndexTable::to_page_table`] paints it per page cell, for small grids).
    pub fn page_table(&self) -> &IndexTable {
        &self.page_table
    }

    /// CPU bytes of the loader's index: the page table as last applied and the visibility
    /// marks (per page cell with the flat traversal, O(cut) with the octree).
    pub fn cpu_index_bytes(&self) -> usize {
        self.page_table.cpu_bytes() + self.visibility.memory_bytes()
    }

    /// Changes whenever a brick is uploaded or the page table rewritten (see the field).
    pub fn residency_generation(&self) -> u64 {
        self.residency_generation
    }

    /// The payloads of the current cut's resident nodes: a snapshot of the CPU cache's copies
    /// now, the others read later through the source by [`CutPayloads::read_missing`] (off
    /// this thread). For a CPU pass over the cut (the viewer's adaptive oracle).
    pub fn cut_payloads(&self) -> CutPayloads {
        // The adaptive pass reads the flat table (the viewer does not ask with the octree).
        CutPayloads::snapshot(
            Arc::new(self.page_table.to_page_table()),
            &self.cpu,
            (self.root, &self.root_brick),
            self.source.clone(),
        )
    }

    /// The cut's GPU resources as a scene of `camera` and `settings`, for a pass other than
    /// the raycaster over the same bricks (the adaptive pass).
    pub fn scene<'a>(
        &'a self,
        camera: &'a Camera,
        settings: &'a RenderSettings,
    ) -> FrameInputs<'a> {
        FrameInputs {
            cache: &self.cache,
            page_table: &self.gpu_page_table,
            transfer_function: &self.transfer_function,
            geometry: &self.geometry,
            mapping: self.mapping,
            camera,
            settings,
        }
    }

    /// The GPU brick cache (a pass beside the raycaster is created over it).
    pub fn brick_cache(&self) -> &BrickCache {
        &self.cache
    }

    pub fn last_stats(&self) -> &FrameStats {
        &self.last_stats
    }

    /// Bricks that failed to read since the last call; each failure is reported once.
    pub fn take_failures(&mut self) -> Vec<BrickFailure> {
        std::mem::take(&mut self.new_failures)
    }

    /// Runs the loader for one frame and submits it. Never waits for a read or for the GPU;
    /// waits for the selection thread only with [`SelectionTiming::EachFrame`].
    pub fn frame(
        &mut self,
        ctx: &GpuContext,
        camera: &Camera,
        settings: &RenderSettings,
    ) -> Result<FrameStats, LoaderError> {
        let started = Instant::now();
        let started_cpu = crate::thread_cpu::thread_cpu_seconds();
        self.frame += 1;
        let fetched = self.take_fetched();
        if self.config.visibility_feedback {
            if let Some(v) = self.raycaster.try_take_visibility(ctx) {
                Arc::make_mut(&mut self.visibility).record_frame(&v);
            }
        }
        let inputs = ViewInputs {
            camera: *camera,
            settings: ViewInputs::selection_settings(settings),
            tf_generation: self.tf_generation,
            failed_bricks: self.failed.len(),
            max_voxel_pixels: self.config.max_voxel_pixels,
        };
        let applied = match self.config.selection {
            SelectionTiming::EachFrame => {
                self.submit_selection(camera, settings, inputs.clone())?;
                let selected = self.selector.wait()?;
                self.apply_selection(ctx, selected, camera, settings)?
            }
            SelectionTiming::Background => {
                let applied = match self.selector.try_take() {
                    Some(selected) => self.apply_selection(ctx, selected?, camera, settings)?,
                    None => None,
                };
                // The next job starts from what this frame applied.
                if !self.selector.busy() {
                    self.submit_selection(camera, settings, inputs.clone())?;
                }
                applied
            }
            SelectionTiming::EveryNthFrame(n) => {
                let mut applied = None;
                if self.frame.is_multiple_of(u64::from(n.max(1))) || !self.selector.busy() {
                    if self.selector.busy() {
                        let selected = self.selector.wait()?;
                        applied = self.apply_selection(ctx, selected, camera, settings)?;
                    }
                    self.submit_selection(camera, settings, inputs.clone())?;
                }
                applied
            }
        };

        let loader_seconds = started.elapsed().as_secs_f64();
        let loader_cpu_seconds = started_cpu
            .zip(crate::thread_cpu::thread_cpu_seconds())
            .map_or(f64::NAN, |(a, b)| b - a);
        let scene = FrameInputs {
            cache: &self.cache,
            page_table: &self.gpu_page_table,
            transfer_function: &self.transfer_function,
            geometry: &self.geometry,
            mapping: self.mapping,
            camera,
            settings,
        };
        // A streamed cut turns mixed as it refines. Without the background compiler, the
        // variant with transition code is built with the first frame (which compiles anyway),
        // so no later frame stalls on it when the first coarser neighbour appears.
        if !self.raycaster.compile_in_background {
            self.raycaster.prepare(ctx, settings);
        }
        self.raycaster.render(ctx, &scene)?;
        self.renders += 1;

        let visibility_seen = !self.config.visibility_feedback
            || self.visibility.newest_render_frame() >= self.cut_changed_at_render;
        let current = self.current.clone();
        let no_cut = Cut::default();
        let (cut, rewritten) = match &applied {
            Some(a) => (&a.cut, a.rewritten),
            None => (current.as_deref().map_or(&no_cut, |c| &c.0), false),
        };
        // Converged: the cut shown was selected for this very view, is complete, uploaded
        // nothing and left the table as it was. A background selection lags the camera, so
        // the cut applied on the first still frame was selected for the last moving one.
        let converged = match &applied {
            Some(a) => {
                a.cut.complete()
                    && a.cut.uploads.is_empty()
                    && !a.rewritten
                    && visibility_seen
                    && a.selected_for == inputs
            }
            None => {
                self.current_converged
                    && visibility_seen
                    && current.as_ref().is_some_and(|c| c.1 == inputs)
            }
        };
        if let (Some(a), Some(previous)) = (&applied, &current) {
            // A still view's cut changed: flicker when it gives back a refinement, or when
            // the view had already converged. Both cuts must have been selected for this
            // view: the first one selected for it replaces one that was not.
            let (before, before_inputs) = (&previous.0, &previous.1);
            if a.rewritten && *before_inputs == inputs && a.selected_for == inputs {
                let refined: HashSet<BrickId> = a.cut.refined.iter().copied().collect();
                let coarsens = before.refined.iter().any(|id| !refined.contains(id));
                if coarsens || self.converged_for.as_ref() == Some(&inputs) {
                    self.cut_changes_while_still += 1;
                }
            }
        }
        if converged {
            self.converged_for = Some(inputs.clone());
        }
        let mut stats = self.stats(cut, fetched, rewritten, converged, loader_seconds);
        stats.loader_cpu_seconds = loader_cpu_seconds;
        if let Some(AppliedCut {
            mut cut,
            rewritten,
            selected_for,
        }) = applied
        {
            self.current_converged = cut.complete() && cut.uploads.is_empty() && !rewritten;
            cut.uploads.clear();
            cut.data_leaves_on_gpu = cut.data_leaves().count();
            // Labelled with the view it was selected for, never this frame's: a cut selected
            // for a moving camera kept as the still view's settled cut held the old frustum's
            // culling (issue 35).
            self.current = Some(Arc::new((cut, selected_for)));
        }
        self.last_stats = stats.clone();
        Ok(stats)
    }

    /// Hands the selection thread this frame's view and a snapshot of residency.
    fn submit_selection(
        &mut self,
        camera: &Camera,
        settings: &RenderSettings,
        inputs: ViewInputs,
    ) -> Result<(), LoaderError> {
        let job = SelectionJob {
            frame: self.frame,
            root: self.root,
            view: ViewSetup::new(&self.geometry, camera, settings),
            emptiness: self.emptiness_spec(settings),
            limits: self.cut_limits(),
            inputs,
            visibility: self
                .config
                .visibility_feedback
                .then(|| self.visibility.clone()),
            residency: ResidencySnapshot {
                slots: self.slots.clone(),
                cpu: self.cpu.ids().collect(),
                failed: self.failed.clone(),
            },
            incumbents: self.refined_last_frame.clone(),
            settled: self.settled.clone(),
            page_table_key: self.page_table_key.clone(),
            page_table: self.page_table.clone(),
            layout: self.gpu_page_table.layout(),
            mapping: self.mapping,
        };
        self.selector.submit(job)
    }

    fn cut_limits(&self) -> CutLimits {
        CutLimits {
            max_voxel_pixels: self.config.max_voxel_pixels,
            gpu_slots: self.slots.capacity(),
            // Per frame, not per selection: a fast GPU draws several frames per selection,
            // and a budget per selection capped it at uploads_per_frame / 7.5 per frame at
            // 1024³ on an H200 (101 selections to converge). Capped at 16 frames' worth so
            // a stalled frame's selection does not upload in one go what 100 frames would.
            uploads: self.config.uploads_per_frame * self.frames_per_selection as usize,
            prefetch_candidates: self.config.prefetch_per_frame,
        }
    }

    /// Applies a finished selection: its uploads, its page table (changed spans only), its
    /// requests. Returns the cut and whether the table changed, or None when the answer no
    /// longer fits (a brick it uploads left the CPU cache, or the transfer function changed
    /// since): then nothing changed and the next job selects again.
    fn apply_selection(
        &mut self,
        ctx: &GpuContext,
        selected: Selected,
        camera: &Camera,
        settings: &RenderSettings,
    ) -> Result<Option<AppliedCut>, LoaderError> {
        let Selected {
            inputs,
            cut,
            slots,
            uploads,
            refined,
            page_table_key,
            new_table,
        } = selected;
        if inputs.tf_generation != self.tf_generation
            || !uploads.iter().all(|&(id, _)| self.cpu.contains(id))
        {
            self.selections_dropped += 1;
            return Ok(None);
        }
        self.selections_applied += 1;
        if self.applied_at_frame > 0 {
            self.frames_per_selection = (self.frame - self.applied_at_frame).clamp(1, 16);
        }
        self.applied_at_frame = self.frame;
        for _ in &cut.demand {
            self.cpu.note_miss();
        }
        // The selection thread touched this cut's nodes and allocated the uploads' slots on
        // the job's copy of the map, which nothing changed meanwhile (one job in flight).
        self.slots = slots;
        if !uploads.is_empty() || new_table.is_some() {
            self.residency_generation += 1;
        }
        for (id, slot) in uploads {
            let brick = self.cpu.get_for_use(id).ok_or_else(|| {
                LoaderError::Inconsistent(format!(
                    "brick {id:?} chosen for upload is not in CPU memory"
                ))
            })?;
            self.cache.ensure_slot(&ctx.device, &ctx.queue, slot)?;
            self.cache.upload_brick(&ctx.queue, slot, &brick)?;
        }
        let rewritten = new_table.is_some();
        if let Some(new) = new_table {
            self.gpu_page_table
                .write_prepared(&ctx.queue, &new.prepared)?;
            match &new.mip_bounds {
                MipBounds::PerPage(b) => self.gpu_page_table.update_value_max(&ctx.queue, b)?,
                MipBounds::PerLeaf(b) => {
                    self.gpu_page_table.update_leaf_value_max(&ctx.queue, b)?
                }
            }
            self.page_table = Arc::new(new.prepared.into_table());
            self.cut_changed_at_render = self.renders + 1;
            // Visibility ages by cut generations (visibility.rs), so a still view's marks
            // accumulate while its cut holds.
            Arc::make_mut(&mut self.visibility).start_generation(self.renders + 1);
        }
        self.page_table_key = page_table_key;
        self.refined_last_frame = refined;
        self.request_bricks(&cut, camera, settings);
        // The settled cut is updated here, not after the frame is drawn: the job handed over
        // right after this (background timings) must see the cut it is asked to keep beside
        // the incumbents it refines from. One applied cut late, two complete cuts took turns
        // forever (issue 35: keep_settled_cut brought back the cut before the current one
        // each time, 9339 <-> 6686 leaves on an H200 with nothing to load).
        if cut.complete() {
            let mut kept = cut.clone();
            kept.uploads.clear();
            self.settled = Some(Arc::new((kept, inputs.clone())));
        }
        Ok(Some(AppliedCut {
            cut,
            rewritten,
            selected_for: inputs,
        }))
    }

    /// Replaces the fetchers' requests with `cut`'s demand and the prefetch candidates.
    fn request_bricks(&mut self, cut: &Cut, camera: &Camera, settings: &RenderSettings) {
        // Ask for no more than half the CPU cache holds: bricks read faster than uploads and
        // refinement can use them would evict each other before use and be read again.
        self.working_set.clear();
        self.working_set.push(self.root);
        self.working_set.extend(
            cut.data_leaves()
                .chain(cut.resident_inner.iter().copied())
                .filter(|&id| id != self.root),
        );
        let demand_limit = ((self.cpu.budget_bytes() / BRICK_BYTES) as usize / 2).max(1);
        // A background selection saw residency a frame or more ago: what arrived meanwhile
        // is not asked for again.
        let demand: Vec<(BrickId, f64)> = cut
            .demand
            .iter()
            .filter(|r| !self.cpu.contains(r.id) && !self.slots.contains(r.id))
            .take(demand_limit)
            .map(|r| (r.id, r.priority))
            .collect();
        let mut prefetch: Vec<(BrickId, f64)> = Vec::new();
        if self.config.prefetch {
            prefetch.extend(cut.refine_next.iter().map(|r| (r.id, r.priority)));
            // The prediction thread answers a frame or more late; an answer that arrives once
            // the camera stopped is dropped.
            let newest_prediction = self.predictor.take_newest();
            if let Some(predicted) = self.motion.observe(camera) {
                self.predictor.submit(PredictionJob {
                    view: ViewSetup::new(&self.geometry, &predicted, settings),
                    emptiness: self.emptiness_spec(settings),
                    failed: self.failed.clone(),
                    limits: self.cut_limits(),
                });
                prefetch.extend(newest_prediction.into_iter().flatten());
            }
            prefetch.retain(|(id, _)| !self.cpu.contains(*id) && !self.slots.contains(*id));
            prefetch.truncate(self.config.prefetch_per_frame);
        }
        self.workers.set_requests(&demand, &prefetch);
    }

    /// The raycaster's number of the frame the last [`StreamingVolume::frame`] submitted; GPU
    /// timings from [`StreamingVolume::take_frame_timings`] carry it.
    pub fn last_frame_number(&self) -> u64 {
        self.raycaster.frame_number()
    }

    /// GPU time of the raycast pass of recent frames, read back a frame or two late without
    /// waiting. Empty on devices without timestamp queries.
    pub fn take_frame_timings(&mut self, ctx: &GpuContext) -> Vec<strata_render::FrameTiming> {
        self.raycaster.try_take_frame_timings(ctx)
    }

    /// The raycaster, for what it draws besides the volume (the viewer's 3D overlay:
    /// `Raycaster::set_overlay`).
    pub fn raycaster_mut(&mut self) -> &mut Raycaster {
        &mut self.raycaster
    }

    /// Interactive use: a frame that needs a pipeline not compiled yet draws with the previous
    /// one while a thread compiles it (see `Raycaster::compile_in_background`).
    pub fn set_compile_in_background(&mut self, on: bool) {
        self.raycaster.compile_in_background = on;
    }

    /// True while the last frame was drawn with a stand-in pipeline because the one its
    /// settings need is still compiling: that frame is not what was asked for, however
    /// converged the cut is (the viewer keeps rendering until the real pipeline draws).
    pub fn compiling_in_background(&self) -> bool {
        self.raycaster.compiling_in_background()
    }

    /// Waits until the GPU finished everything submitted (frame timing in benchmarks).
    pub fn wait_for_gpu(&self, ctx: &GpuContext) -> Result<(), LoaderError> {
        ctx.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map(|_| ())
            .map_err(|e| LoaderError::Render(strata_render::RenderError::Readback(e.to_string())))
    }

    /// Bricks the last frame's cut kept on the GPU (data leaves, resident ancestors, root).
    pub fn working_set(&self) -> &[BrickId] {
        &self.working_set
    }

    /// Checks that every sampled page entry points at a slot holding the node it names
    /// (for tests: a broken slot map shows up as wrong voxels, not as an error).
    pub fn check_slot_map(&self) -> Result<(), SlotMapMismatch> {
        for (level, coords, slot) in self.page_table.resident_nodes() {
            let node = BrickId::new(level, coords);
            if self.slots.slot_of(node) != Some(slot) {
                return Err(SlotMapMismatch {
                    node,
                    table_slot: slot,
                    slot_map: self.slots.slot_of(node),
                });
            }
        }
        Ok(())
    }

    /// The source's state ("connection lost, retrying" for a remote one that cannot be
    /// reached); the frame loop keeps drawing what it has either way.
    pub fn source_status(&self) -> SourceStatus {
        self.workers.status()
    }

    /// Where the volume comes from (path or URL).
    pub fn source(&self) -> &Arc<dyn VolumeSource> {
        &self.source
    }

    /// Holds the selection thread before its next job until the guard is dropped: frames go
    /// on with the current cut meanwhile (with [`SelectionTiming::Background`]; an
    /// `EachFrame` frame would wait for the guard). For tests.
    #[cfg(any(test, feature = "test-hooks"))]
    pub fn hold_selection_for_tests(&self) -> crate::cut_worker::SelectionHold {
        self.selector.hold()
    }

    /// Re-reads every brick the page table samples from `store` and uploads it into its slot
    /// again (for tests: separates wrong cache contents from a wrong cut).
    #[cfg(any(test, feature = "test-hooks"))]
    pub fn reupload_for_tests(
        &self,
        ctx: &GpuContext,
        store: &dyn VolumeSource,
    ) -> Result<(), LoaderError> {
        for (level, coords, slot) in self.page_table.resident_nodes() {
            self.cache.upload_brick(
                &ctx.queue,
                slot,
                &store.read_brick(BrickId::new(level, coords))?,
            )?;
        }
        let prepared = match &*self.page_table {
            IndexTable::Dense(t) => {
                PreparedPageTable::new(self.gpu_page_table.layout(), t.clone())?
            }
            IndexTable::Sparse(t) => {
                PreparedPageTable::sparse(self.gpu_page_table.layout(), t.clone())?
            }
        };
        self.gpu_page_table.write_prepared(&ctx.queue, &prepared)?;
        Ok(())
    }

    /// Reads the last submitted frame back, waiting for the GPU (CLI, tests, benchmarks).
    pub fn read_frame_blocking(&mut self, ctx: &GpuContext) -> Result<FrameReadback, LoaderError> {
        Ok(self.raycaster.read_frame_blocking(ctx)?)
    }

    /// Frames until converged (or `max_frames`), each read back; returns the last image and
    /// the stats of every frame. The loop itself never waits for I/O: a frame whose bricks are
    /// not there yet is drawn with what is.
    pub fn render_until_converged(
        &mut self,
        ctx: &GpuContext,
        camera: &Camera,
        settings: &RenderSettings,
        max_frames: usize,
    ) -> Result<(FrameReadback, Vec<FrameStats>), LoaderError> {
        let mut history = Vec::new();
        loop {
            let stats = self.frame(ctx, camera, settings)?;
            let image = self.read_frame_blocking(ctx)?;
            let done = stats.converged || history.len() + 1 >= max_frames;
            history.push(stats);
            if done {
                return Ok((image, history));
            }
            if self.workers.in_flight() > 0
                && self.last_stats.uploads == 0
                && !self.last_stats.page_table_rewritten
            {
                // Nothing changed on screen this frame; give the workers a moment rather than
                // spinning the GPU on identical frames.
                std::thread::sleep(std::time::Duration::from_millis(2));
            }
        }
    }

    fn take_fetched(&mut self) -> u64 {
        let mut fetched = 0;
        for result in self.workers.try_results() {
            self.workers.complete(result.id);
            match result.outcome {
                Ok(brick) => {
                    fetched += result.stored_bytes;
                    self.bricks_read += 1;
                    self.cpu.insert(
                        result.id,
                        brick,
                        result.class == strata_source::RequestClass::Prefetch,
                    );
                }
                Err(e) => {
                    if self.failed.insert(result.id) {
                        self.new_failures.push(BrickFailure {
                            id: result.id,
                            message: e.to_string(),
                        });
                    }
                }
            }
        }
        self.stored_bytes_read += fetched;
        fetched
    }

    fn emptiness_spec(&self, settings: &RenderSettings) -> EmptinessSpec {
        match settings.mode {
            RenderMode::Isosurface => EmptinessSpec::Iso {
                value: settings.iso_value,
                mapping: self.mapping,
            },
            RenderMode::Dvr | RenderMode::Mip => EmptinessSpec::TransferFunction {
                table: self.tf_table.clone(),
                mapping: self.mapping,
            },
        }
    }

    fn stats(
        &mut self,
        cut: &Cut,
        fetched: u64,
        rewritten: bool,
        converged: bool,
        loader_seconds: f64,
    ) -> FrameStats {
        let now = Instant::now();
        self.read_history.push_back((now, fetched));
        while self
            .read_history
            .front()
            .is_some_and(|(t, _)| now.duration_since(*t).as_secs_f64() > 1.0)
        {
            self.read_history.pop_front();
        }
        let window = self
            .read_history
            .front()
            .map_or(0.0, |(t, _)| now.duration_since(*t).as_secs_f64())
            .max(1e-3);
        let window_bytes: u64 = self.read_history.iter().map(|(_, b)| b).sum();
        let data_leaves = cut.data_leaves().count();
        // A settled cut keeps the count it settled with: which nodes the feedback calls
        // visible flickers at the silhouette, and with it how many blocked refinements are
        // tried, while the cut (and so what was left coarser) stays the same.
        let left_coarser = if converged && !rewritten && self.last_stats.converged {
            self.last_stats.left_coarser
        } else {
            cut.blocked_by_gpu_slots
        };
        let slot_bytes = BRICK_PAYLOAD_VOXELS as u64 * self.cache.format.bytes_per_voxel();
        let cpu_counters = self.cpu.counters();
        let queue = self.workers.counters();
        let (queued, in_flight) = (self.workers.queued(), self.workers.in_flight());
        FrameStats {
            frame: self.frame,
            loader_seconds,
            loader_cpu_seconds: f64::NAN,
            selections_applied_total: self.selections_applied,
            selections_dropped_total: self.selections_dropped,
            cut_changes_while_still_total: self.cut_changes_while_still,
            leaves: cut.leaves.len(),
            data_leaves,
            data_leaves_per_level: {
                let mut per_level = vec![0; self.octree.level_count() as usize];
                for id in cut.data_leaves() {
                    per_level[id.level as usize] += 1;
                }
                per_level
            },
            gpu_resident_per_level: self.slots.per_level(self.octree.level_count() as usize),
            gpu_slots_used: self.slots.occupied(),
            gpu_slots_capacity: self.slots.capacity(),
            gpu_bytes: self.slots.occupied() as u64 * slot_bytes,
            gpu_budget_bytes: self.slots.capacity() as u64 * slot_bytes,
            working_set_bricks: cut.slots_needed,
            working_set_bytes: cut.slots_needed as u64 * BRICK_BYTES,
            cpu_cache_bytes: self.cpu.bytes(),
            cpu_bytes: self.cpu.bytes()
                + self.config.sled_cache_bytes
                + self.config.in_transit_bytes(),
            cpu_budget_bytes: self.config.cpu_budget_bytes,
            cpu_hit_rate: ratio(cpu_counters.hits, cpu_counters.lookups),
            gpu_hit_rate: ratio(cut.data_leaves_on_gpu as u64, data_leaves as u64),
            pending: queued + in_flight,
            queued,
            in_flight,
            queue_capacity: self.workers.capacity(),
            stale_dropped_total: queue.stale_dropped,
            overflow_dropped_total: queue.overflow_dropped,
            cancelled_in_flight_total: queue.cancelled_in_flight,
            retried_total: queue.retried,
            checksum_failures_total: queue.checksum_failures,
            max_in_flight: queue.max_in_flight,
            source_status: self.workers.status(),
            bricks_read_total: self.bricks_read,
            stored_bytes_read_total: self.stored_bytes_read,
            brick_bytes_read_total: self.bricks_read * BRICK_BYTES,
            bytes_read_per_second: window_bytes as f64 / window,
            uploads: cut.uploads.len(),
            upload_bytes: cut.uploads.len() as u64 * slot_bytes,
            prefetch_loaded_total: cpu_counters.prefetch_loaded,
            prefetch_used_total: cpu_counters.prefetch_used,
            prefetch_hit_rate: ratio(cpu_counters.prefetch_used, cpu_counters.prefetch_loaded),
            failed_bricks: self.failed.len(),
            page_table_rewritten: rewritten,
            blocked: [
                cut.blocked_by_data,
                cut.blocked_by_uploads,
                cut.blocked_by_gpu_slots,
                cut.blocked_by_balance,
            ],
            gpu_budget_limited: cut.blocked_by_gpu_slots > 0,
            left_coarser,
            converged_at_budget: converged && left_coarser > 0,
            converged,
        }
    }
}

/// A selection applied on the frame thread.
struct AppliedCut {
    cut: Cut,
    /// The page table changed.
    rewritten: bool,
    /// The view the cut was selected for (a background selection lags the camera).
    selected_for: ViewInputs,
}

/// The configured traversal, or when left open the flat table where its per-page buffers
/// fit the limit (the device's, or the configured one) and else the octree, with a note
/// saying why.
fn choose_traversal(
    ctx: &GpuContext,
    page_dims: [u32; 3],
    config: &StreamingConfig,
) -> Result<(Traversal, Option<String>), LoaderError> {
    if let Some(t) = config.traversal {
        return Ok((t, None));
    }
    let (limit, source) =
        strata_render::flat_table_limit(&ctx.device, config.flat_table_limit_bytes);
    let cells: u64 = page_dims.iter().map(|&d| d as u64).product();
    match strata_render::check_flat_table_fits(page_dims, limit, &source) {
        Ok(()) if cells > config.flat_table_max_page_cells => Ok((
            Traversal::Octree,
            Some(format!(
                "octree traversal chosen: the flat page table's {cells} page cells exceed \
                 {}, beyond which its per-cell CPU work outgrows a frame (--traversal flat \
                 forces it)",
                config.flat_table_max_page_cells
            )),
        )),
        Ok(()) => Ok((Traversal::Flat, None)),
        Err(strata_render::RenderError::FlatTableTooLarge {
            pages,
            bytes,
            limit_bytes,
            limit_source,
            ..
        }) => Ok((
            Traversal::Octree,
            Some(format!(
                "octree traversal chosen: the flat page table's {pages} page cells would need \
                 {bytes} bytes, over {limit_source} ({limit_bytes} bytes)"
            )),
        )),
        Err(e) => Err(e.into()),
    }
}

fn ratio(a: u64, b: u64) -> f64 {
    if b == 0 {
        1.0
    } else {
        a as f64 / b as f64
    }
}

/// The TF sampled over the store's physical value range (what the GPU table and the
/// emptiness prefix sum both use).
pub fn tf_table_for(
    tf: &TransferFunction,
    mapping: ValueMapping,
    stored_range: [u16; 2],
) -> TransferFunctionTable {
    let (a, b) = (
        mapping.physical(stored_range[0] as f64),
        mapping.physical(stored_range[1] as f64),
    );
    tf_table_for_range(tf, a.min(b), a.max(b))
}

fn tf_table_for_range(tf: &TransferFunction, lo: f64, hi: f64) -> TransferFunctionTable {
    tf.table(lo, hi)
}
