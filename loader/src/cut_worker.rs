//! Cut selection and page-table building on the named thread `strata-cut-select` (issue 18:
//! together they were ~6 ms of the frame thread's ~10 ms at 1024³, selection over ~5400
//! leaves and a table over every page cell).
//!
//! The frame thread hands over a job holding everything the selection reads: the view, a
//! snapshot of residency (GPU slot map, ids in CPU memory, failed bricks), the visibility
//! feedback, and what the last applied selection left (incumbents, the settled cut, the page
//! table and its key). The thread selects the cut, keeps a settled cut against a trade
//! ([`keep_settled_cut`]), assigns the upload slots on its copy of the slot map, builds the
//! page table when its inputs changed and prepares its GPU words ([`PreparedPageTable`]). The
//! frame thread applies a finished answer (uploads, the changed spans of the table) and never
//! waits for one unless asked to ([`SelectionTiming::EachFrame`]: tests and headless commands,
//! which want each frame's own cut). Jobs are stateless: one in flight at a time, so the slot
//! map an answer was computed on is still the frame thread's when it arrives, and an answer
//! that no longer fits (a brick to upload left the CPU cache meanwhile, or a new transfer
//! function) is dropped without any state to undo.

use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;

use crossbeam_channel::{Receiver, Sender};
// Keys are brick ids, not attacker-chosen: a fast hash.
use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};
use strata_render::gpu::gpu_octree::leaf_value_max;
use strata_render::model::octree_cut::CutLeaf as TableLeaf;
use strata_render::{
    Camera, IndexTable, PageEntry, PageLookup, PageTable, PageTableLayout, PreparedPageTable,
    RenderMode, RenderSettings, SparsePageTable, Traversal, ValueMapping,
};
use strata_types::BrickId;

use crate::cut_selection::{
    select_cut, Cut, CutLimits, LeafKind, Residency, ViewSetup, SELECTION_THREAD,
};
use crate::error::LoaderError;
use crate::gpu_slots::GpuSlots;
use crate::octree_ranges::{Emptiness, OctreeRanges, StoredRange};
use crate::predicted_cut::EmptinessSpec;
use crate::visibility::PageVisibility;

/// When a frame gets the cut selected for its own view.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SelectionTiming {
    /// Each frame waits for the selection of its own view (on the selection thread):
    /// deterministic, for tests and headless rendering.
    #[default]
    EachFrame,
    /// A frame applies the newest finished selection, if any, and hands the thread the next
    /// job when it is idle; it never waits (the viewer, the flythrough). The cut lags the
    /// camera by a frame or more.
    Background,
    /// The background timing at a fixed cadence: every `n`-th frame waits for the job handed
    /// over `n` frames before, applies it and hands over the next; the frames between apply
    /// nothing. What a fast GPU does (an H200 draws ~7.5 frames per selection at 1024³),
    /// made deterministic so lavapipe can be driven at that cadence (tests).
    EveryNthFrame(u32),
}

/// What a cut is selected for, apart from residency and visibility feedback.
#[derive(Clone, PartialEq)]
pub(crate) struct ViewInputs {
    pub camera: Camera,
    /// Only what the selection reads ([`ViewInputs::selection_settings`]).
    pub settings: RenderSettings,
    pub tf_generation: u64,
    pub failed_bricks: usize,
    pub max_voxel_pixels: f64,
}

impl ViewInputs {
    /// The settings a cut depends on: the image size, crop box and clip plane (projection and
    /// culling), the mode and iso value (emptiness); everything else at its default. The
    /// viewer changes `frame_index` (the jitter's seed) every frame and the time-critical
    /// controller the step: with the whole settings compared, a still view was a new view
    /// every frame, so it never reported "converged" and its cut was never kept (issue 35).
    pub fn selection_settings(settings: &RenderSettings) -> RenderSettings {
        RenderSettings {
            width: settings.width,
            height: settings.height,
            mode: settings.mode,
            iso_value: settings.iso_value,
            crop: settings.crop,
            clip_plane: settings.clip_plane,
            ..RenderSettings::default()
        }
    }
}

/// Everything `build_page_table` reads: each leaf with its kind and the slot it is drawn
/// from (its own, or its parent's for a pending or failed leaf), and what counts as empty.
#[derive(Default, PartialEq)]
pub(crate) struct PageTableKey {
    leaves: Vec<(BrickId, LeafKind, Option<u32>)>,
    mode: Option<RenderMode>,
    iso_bits: u64,
    tf_generation: u64,
}

impl PageTableKey {
    fn of(cut: &Cut, slots: &GpuSlots, settings: &RenderSettings, tf_generation: u64) -> Self {
        let leaves = cut
            .leaves
            .iter()
            .map(|l| {
                let drawn_from = match l.kind {
                    LeafKind::Data => slots.slot_of(l.id),
                    LeafKind::Failed | LeafKind::Pending => slots.slot_of(l.id.parent()),
                    _ => None,
                };
                (l.id, l.kind, drawn_from)
            })
            .collect();
        PageTableKey {
            leaves,
            mode: Some(settings.mode),
            iso_bits: settings.iso_value.to_bits(),
            tf_generation,
        }
    }
}

/// Residency as the frame thread saw it when it handed over the job.
pub(crate) struct ResidencySnapshot {
    pub slots: GpuSlots,
    pub cpu: HashSet<BrickId>,
    pub failed: HashSet<BrickId>,
}

impl Residency for ResidencySnapshot {
    fn on_gpu(&self, id: BrickId) -> bool {
        self.slots.contains(id)
    }
    fn in_cpu(&self, id: BrickId) -> bool {
        self.cpu.contains(&id)
    }
    fn failed(&self, id: BrickId) -> bool {
        self.failed.contains(&id)
    }
}

/// A complete, budget-bound cut with the view it was selected for.
pub(crate) type SettledCut = Arc<(Cut, ViewInputs)>;

pub(crate) struct SelectionJob {
    pub frame: u64,
    pub root: BrickId,
    pub view: ViewSetup,
    pub emptiness: EmptinessSpec,
    pub limits: CutLimits,
    pub inputs: ViewInputs,
    /// None: feedback off.
    pub visibility: Option<Arc<PageVisibility>>,
    pub residency: ResidencySnapshot,
    /// Nodes the last applied cut refined: the incumbents hysteresis protects.
    pub incumbents: Arc<HashSet<BrickId>>,
    pub settled: Option<SettledCut>,
    pub page_table_key: Arc<PageTableKey>,
    pub page_table: Arc<IndexTable>,
    pub layout: PageTableLayout,
    pub mapping: ValueMapping,
}

/// The MIP value bounds of a new table, in the index's own unit.
pub(crate) enum MipBounds {
    /// One per page cell (the flat table).
    PerPage(Vec<f32>),
    /// One per leaf of the prepared octree, in its leaf order (the octree traversal).
    PerLeaf(Vec<f32>),
}

/// A new page table for the GPU: its words (or octree) prepared, and the MIP bounds.
pub(crate) struct NewTable {
    pub prepared: PreparedPageTable,
    pub mip_bounds: MipBounds,
}

/// A finished selection, to apply on the frame thread.
pub(crate) struct Selected {
    pub inputs: ViewInputs,
    pub cut: Cut,
    /// The job's slot map with this cut's nodes touched and its uploads allocated.
    pub slots: GpuSlots,
    /// Bricks to upload (all in CPU memory when the job was made) and their slots.
    pub uploads: Vec<(BrickId, u32)>,
    pub refined: Arc<HashSet<BrickId>>,
    pub page_table_key: Arc<PageTableKey>,
    /// Some when the table changed.
    pub new_table: Option<NewTable>,
}

/// Once a still view's cut is complete, a new selection may only refine it further, never
/// trade: one that would coarsen a node the settled cut refined is replaced by the settled
/// cut (whose bricks are all still on the GPU, so nothing is uploaded). Without this,
/// feedback flicker at the silhouette and bricks evicted and read again made two cuts that
/// each fit a budget alternate forever at 1024³, and without a binding budget the cut
/// flipped between two states at a fast GPU's cadence (issue 35): a node's own refinement
/// hid part of it, and the next selection coarsened it. The settled cut is the last
/// complete one, whether the budget binds or not, so the cut of a still view changes only
/// by refinement, which ends.
fn keep_settled_cut(
    settled: Option<&(Cut, ViewInputs)>,
    slots: &GpuSlots,
    cut: Cut,
    inputs: &ViewInputs,
) -> Cut {
    let Some((settled, settled_for)) = settled else {
        return cut;
    };
    if settled_for != inputs {
        return cut;
    }
    let refined: HashSet<BrickId> = cut.refined.iter().copied().collect();
    let coarsens = settled.refined.iter().any(|id| !refined.contains(id));
    let drawable = settled
        .data_leaves()
        .chain(settled.resident_inner.iter().copied())
        .all(|id| slots.contains(id));
    if coarsens && drawable {
        settled.clone()
    } else {
        cut
    }
}

/// The job's selection, slot assignment and page table (runs on `strata-cut-select`).
fn select(octree: &OctreeRanges, job: SelectionJob) -> Result<Selected, LoaderError> {
    let SelectionJob {
        frame,
        root,
        view,
        emptiness,
        limits,
        inputs,
        visibility,
        residency,
        incumbents,
        settled,
        page_table_key,
        page_table,
        layout,
        mapping,
    } = job;
    let emptiness = emptiness.emptiness();
    let cut = select_cut(
        octree,
        &view,
        emptiness,
        visibility.as_deref(),
        &residency,
        &incumbents,
        limits,
    );
    let cut = keep_settled_cut(settled.as_deref(), &residency.slots, cut, &inputs);
    let refined = Arc::new(cut.refined.iter().copied().collect());
    // Everything this cut shows is protected before any slot is reused.
    let mut slots = residency.slots;
    slots.touch(root, frame);
    for id in cut.data_leaves().chain(cut.resident_inner.iter().copied()) {
        slots.touch(id, frame);
    }
    let uploads = cut
        .uploads
        .iter()
        .map(|&id| {
            slots
                .allocate(id, frame, false)
                .map(|s| (id, s))
                .ok_or_else(|| {
                    LoaderError::Inconsistent("every GPU slot is in use by this frame".into())
                })
        })
        .collect::<Result<Vec<_>, _>>()?;
    // The table is a function of the leaves, their slots and what counts as empty: when
    // none of these changed (a settled cut, or one waiting for reads) it is not rebuilt.
    let key = PageTableKey::of(&cut, &slots, &inputs.settings, inputs.tf_generation);
    let (page_table_key, new_table) = if key == *page_table_key {
        (page_table_key, None)
    } else {
        let table = build_page_table(octree, &slots, &cut, &emptiness, layout.traversal)?;
        let new_table = if table == *page_table {
            None
        } else {
            let prepared = match table {
                // The octree is built from the cut's leaves (O(cut)), its bounds per leaf.
                IndexTable::Sparse(table) => PreparedPageTable::sparse(layout, table)?,
                IndexTable::Dense(table) => {
                    let leaves = table_leaves(octree, &cut, &table);
                    PreparedPageTable::with_leaves(layout, table, leaves)?
                }
            };
            let range_of =
                |l: u8, n: [u32; 3]| octree.own_range(BrickId::new(l, n)).map(|r| (r.min, r.max));
            let mip_bounds = match (prepared.octree_leaves(), prepared.table()) {
                (Some(leaves), table) => {
                    MipBounds::PerLeaf(leaf_value_max(table, leaves, mapping, range_of))
                }
                (None, IndexTable::Dense(table)) => {
                    MipBounds::PerPage(mip_bounds(octree, table, mapping))
                }
                (None, IndexTable::Sparse(_)) => {
                    return Err(LoaderError::Inconsistent(
                        "a table kept per leaf was prepared without its octree".into(),
                    ))
                }
            };
            Some(NewTable {
                prepared,
                mip_bounds,
            })
        };
        (Arc::new(key), new_table)
    };
    Ok(Selected {
        inputs,
        cut,
        slots,
        uploads,
        refined,
        page_table_key,
        new_table,
    })
}

/// Per page entry, the largest value its node holds (skeleton range incl. apron), so MIP
/// rays skip pages that cannot beat their running maximum.
fn mip_bounds(octree: &OctreeRanges, table: &PageTable, mapping: ValueMapping) -> Vec<f32> {
    table.value_max_physical(mapping, |level, node| {
        octree
            .own_range(BrickId::new(level, node))
            .map(|r| (r.min, r.max))
    })
}

/// The cut's leaves as the blocks of page cells `table` was painted from, each with the
/// entry its cells hold there (one per leaf: every cell of a leaf gets the same entry, and
/// the empty refinement depends on the entry's node only): the octree's input, O(leaves).
fn table_leaves(octree: &OctreeRanges, cut: &Cut, table: &PageTable) -> Vec<TableLeaf> {
    cut.leaves
        .iter()
        .map(|leaf| {
            let (lo, _) = octree.page_span(leaf.id);
            TableLeaf {
                origin: lo,
                size: leaf.id.level,
                entry: table.get(lo),
            }
        })
        .collect()
}

/// Page entries of a cut: data leaves point at their slot; transparent, empty and culled
/// leaves are not resident (rays skip them); a failed or pending leaf shows its parent. Per
/// page cell for the flat traversal, per leaf for the octree (nothing there is O(cells)).
fn build_page_table(
    octree: &OctreeRanges,
    slots: &GpuSlots,
    cut: &Cut,
    emptiness: &Emptiness,
    traversal: Traversal,
) -> Result<IndexTable, LoaderError> {
    let leaves = leaf_entries(octree, slots, cut, emptiness)?;
    let range_of = |level: u8, node: [u32; 3]| {
        octree
            .own_range(BrickId::new(level, node))
            .map(|r| (r.min, r.max))
    };
    let is_empty = |range: Option<(u16, u16)>| {
        range.is_some_and(|(min, max)| emptiness.is_empty(StoredRange { min, max }))
    };
    match traversal {
        Traversal::Octree => {
            let table = SparsePageTable::from_leaves(octree.page_dims(), leaves);
            // Rays skip an empty entry, so it must be empty over every value sampled there,
            // which includes the coarser neighbours' field blended into its transition bands.
            let mut memo: HashMap<(u8, [u32; 3]), bool> = HashMap::default();
            let refined: Vec<TableLeaf> = table
                .leaves()
                .iter()
                .map(|leaf| {
                    let mut leaf = *leaf;
                    let e = leaf.entry;
                    if e.resident && e.empty {
                        let node = PageTable::node_of(leaf.origin, e.level);
                        leaf.entry.empty = *memo.entry((e.level, node)).or_insert_with(|| {
                            is_empty(table.sampled_range(e.level, node, range_of))
                        });
                    }
                    leaf
                })
                .collect();
            Ok(IndexTable::Sparse(SparsePageTable::from_leaves(
                octree.page_dims(),
                refined,
            )))
        }
        Traversal::Flat => {
            let mut table = PageTable::new(octree.page_dims());
            for leaf in &leaves {
                let (lo, hi) =
                    octree.page_span(BrickId::new(leaf.size, leaf.origin.map(|c| c >> leaf.size)));
                for z in lo[2]..hi[2] {
                    for y in lo[1]..hi[1] {
                        for x in lo[0]..hi[0] {
                            table.set([x, y, z], leaf.entry);
                        }
                    }
                }
            }
            // As above, per page cell.
            let sampled = table.sampled_ranges(range_of);
            for (entry, range) in table.entries.iter_mut().zip(sampled) {
                if entry.resident && entry.empty {
                    entry.empty = is_empty(range);
                }
            }
            Ok(IndexTable::Dense(table))
        }
    }
}

/// Each leaf of the cut as its block of page cells with the entry its cells hold, before the
/// empty flags are refined by the neighbours (see [`build_page_table`]).
fn leaf_entries(
    octree: &OctreeRanges,
    slots: &GpuSlots,
    cut: &Cut,
    emptiness: &Emptiness,
) -> Result<Vec<TableLeaf>, LoaderError> {
    // Leaves without data are "not resident", never "empty" with a borrowed slot: the
    // raycaster may still sample a page flagged empty (a coarse step landing in it), which is
    // harmless only when the slot holds that node's own transparent voxels.
    let own_empty = |id: BrickId| octree.own_range(id).is_some_and(|r| emptiness.is_empty(r));
    let mut memo: HashMap<BrickId, PageEntry> = HashMap::default();
    cut.leaves
        .iter()
        .map(|leaf| {
            let entry = match leaf.kind {
                LeafKind::Data => {
                    let slot = slots.slot_of(leaf.id).ok_or_else(|| {
                        LoaderError::Inconsistent(format!(
                            "data leaf {:?} has no GPU slot",
                            leaf.id
                        ))
                    })?;
                    PageEntry {
                        slot_in_cache: slot,
                        level: leaf.id.level,
                        empty: own_empty(leaf.id),
                        resident: true,
                    }
                }
                LeafKind::Transparent | LeafKind::Empty | LeafKind::Culled => {
                    PageEntry::NOT_RESIDENT
                }
                LeafKind::Failed | LeafKind::Pending => {
                    let parent = leaf.id.parent();
                    *memo
                        .entry(parent)
                        .or_insert_with(|| match slots.slot_of(parent) {
                            Some(slot) if !own_empty(parent) => {
                                PageEntry::resident(slot, parent.level)
                            }
                            _ => PageEntry::NOT_RESIDENT,
                        })
                }
            };
            let (lo, _) = octree.page_span(leaf.id);
            Ok(TableLeaf {
                origin: lo,
                size: leaf.id.level,
                entry,
            })
        })
        .collect()
}

/// The selection thread: one job in flight at a time. Or, inline ([`CutWorker::inline`]), the
/// same jobs run on the frame thread when handed over, their answers taken as the thread's.
pub(crate) struct CutWorker {
    jobs: Option<Sender<SelectionJob>>,
    results: Receiver<Result<Selected, LoaderError>>,
    thread: Option<JoinHandle<()>>,
    in_flight: bool,
    gate: Arc<Gate>,
    inline: Option<InlineSelection>,
}

/// The inline worker's octree and the answer to the job handed over, not yet taken.
struct InlineSelection {
    octree: Arc<OctreeRanges>,
    answer: Option<Result<Selected, LoaderError>>,
}

/// Test hook: while closed, the thread takes no job (a test shows frames go on without it).
#[derive(Default)]
struct Gate {
    closed: Mutex<bool>,
    opened: Condvar,
}

impl Gate {
    fn set(&self, closed: bool) {
        *self.closed.lock().unwrap_or_else(|e| e.into_inner()) = closed;
        self.opened.notify_all();
    }

    fn wait_open(&self) {
        let mut closed = self.closed.lock().unwrap_or_else(|e| e.into_inner());
        while *closed {
            closed = self.opened.wait(closed).unwrap_or_else(|e| e.into_inner());
        }
    }
}

/// Holds the selection thread until dropped (`StreamingVolume::hold_selection_for_tests`).
#[cfg(any(test, feature = "test-hooks"))]
pub struct SelectionHold {
    gate: Arc<Gate>,
}

#[cfg(any(test, feature = "test-hooks"))]
impl Drop for SelectionHold {
    fn drop(&mut self) {
        self.gate.set(false);
    }
}

impl CutWorker {
    pub fn start(octree: Arc<OctreeRanges>) -> Result<Self, LoaderError> {
        let (job_tx, job_rx) = crossbeam_channel::bounded::<SelectionJob>(1);
        let (result_tx, result_rx) = crossbeam_channel::bounded(1);
        let gate = Arc::new(Gate::default());
        let thread_gate = gate.clone();
        let thread = std::thread::Builder::new()
            .name(SELECTION_THREAD.into())
            .spawn(move || {
                for job in job_rx {
                    thread_gate.wait_open();
                    if result_tx.send(select(&octree, job)).is_err() {
                        return;
                    }
                }
            })
            .map_err(|e| LoaderError::Worker(format!("cannot start cut selection thread: {e}")))?;
        Ok(CutWorker {
            jobs: Some(job_tx),
            results: result_rx,
            thread: Some(thread),
            in_flight: false,
            gate,
            inline: None,
        })
    }

    /// Without a thread: [`CutWorker::submit`] selects on the calling thread (the browser,
    /// where wasm32 has no threads; `LoaderWork::Inline`).
    pub fn inline(octree: Arc<OctreeRanges>) -> Self {
        let (_, results) = crossbeam_channel::bounded(1);
        CutWorker {
            jobs: None,
            results,
            thread: None,
            in_flight: false,
            gate: Arc::new(Gate::default()),
            inline: Some(InlineSelection {
                octree,
                answer: None,
            }),
        }
    }

    /// Holds the thread before its next job until the guard is dropped (tests).
    #[cfg(any(test, feature = "test-hooks"))]
    pub fn hold(&self) -> SelectionHold {
        self.gate.set(true);
        SelectionHold {
            gate: self.gate.clone(),
        }
    }

    /// A job is being worked on (or its answer waits to be taken).
    pub fn busy(&self) -> bool {
        self.in_flight
    }

    /// Hands over `job`; call only when not [`CutWorker::busy`] (then it never waits).
    pub fn submit(&mut self, job: SelectionJob) -> Result<(), LoaderError> {
        if let Some(inline) = &mut self.inline {
            inline.answer = Some(select(&inline.octree, job));
            self.in_flight = true;
            return Ok(());
        }
        let sent = self
            .jobs
            .as_ref()
            .is_some_and(|jobs| jobs.send(job).is_ok());
        if !sent {
            return Err(stopped());
        }
        self.in_flight = true;
        Ok(())
    }

    /// The answer to the job in flight if it is finished; never waits.
    pub fn try_take(&mut self) -> Option<Result<Selected, LoaderError>> {
        if let Some(inline) = &mut self.inline {
            let answer = inline.answer.take()?;
            self.in_flight = false;
            return Some(answer);
        }
        let answer = match self.results.try_recv() {
            Ok(answer) => answer,
            Err(crossbeam_channel::TryRecvError::Empty) => return None,
            Err(crossbeam_channel::TryRecvError::Disconnected) => Err(stopped()),
        };
        self.in_flight = false;
        Some(answer)
    }

    /// Waits for the answer to the job in flight ([`SelectionTiming::EachFrame`] only).
    pub fn wait(&mut self) -> Result<Selected, LoaderError> {
        if let Some(inline) = &mut self.inline {
            self.in_flight = false;
            return inline.answer.take().unwrap_or_else(|| Err(stopped()));
        }
        let answer = self.results.recv().map_err(|_| stopped())?;
        self.in_flight = false;
        answer
    }
}

fn stopped() -> LoaderError {
    LoaderError::Worker("the cut selection thread stopped".into())
}

impl Drop for CutWorker {
    fn drop(&mut self) {
        // Closing the job channel ends the thread's loop after its current job (its answer
        // is dropped with the channel).
        self.jobs = None;
        self.gate.set(false);
        while self.results.try_recv().is_ok() {}
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cut_selection::CutLeaf;
    use strata_render::{Projection, VolumeGeometry};

    fn inputs(azimuth: f64) -> ViewInputs {
        let geometry = VolumeGeometry::axis_aligned([256, 256, 256], [1.0; 3]);
        ViewInputs {
            camera: Camera::orbit(
                &geometry,
                azimuth,
                10.0,
                2.0,
                Projection::Perspective { fov_y_deg: 30.0 },
            ),
            settings: RenderSettings::default(),
            tf_generation: 0,
            failed_bricks: 0,
            max_voxel_pixels: 1.0,
        }
    }

    /// A cut refining `refined` (level-1 nodes) into data leaves at level 0.
    fn cut(refined: &[u32]) -> Cut {
        let inner: Vec<BrickId> = refined
            .iter()
            .map(|&x| BrickId::new(1, [x, 0, 0]))
            .collect();
        Cut {
            leaves: inner
                .iter()
                .flat_map(|p| {
                    (0..2).map(move |i| CutLeaf {
                        id: BrickId::new(0, [p.coords[0] * 2 + i, 0, 0]),
                        kind: LeafKind::Data,
                        priority: 1.0,
                    })
                })
                .collect(),
            resident_inner: inner.clone(),
            refined: inner,
            blocked_by_gpu_slots: 1,
            ..Cut::default()
        }
    }

    fn slots_holding(cut: &Cut) -> GpuSlots {
        let mut slots = GpuSlots::new(64);
        for id in cut.data_leaves().chain(cut.resident_inner.iter().copied()) {
            slots.allocate(id, 1, false);
        }
        slots
    }

    fn refined_of(cut: &Cut) -> Vec<u32> {
        cut.refined.iter().map(|id| id.coords[0]).collect()
    }

    #[test]
    fn a_settled_cut_is_kept_against_a_trade_but_not_against_progress_or_a_new_view() {
        let settled = (cut(&[0, 1]), inputs(30.0));
        let slots = slots_holding(&settled.0);
        // The same view offers a trade (node 1 coarsened for node 2): the settled cut stays.
        let kept = keep_settled_cut(Some(&settled), &slots, cut(&[0, 2]), &inputs(30.0));
        assert_eq!(refined_of(&kept), vec![0, 1]);
        assert!(kept.uploads.is_empty());
        // Refining further is progress: taken.
        let more = keep_settled_cut(Some(&settled), &slots, cut(&[0, 1, 2]), &inputs(30.0));
        assert_eq!(refined_of(&more), vec![0, 1, 2]);
        // A new view selects freely.
        let moved = keep_settled_cut(Some(&settled), &slots, cut(&[0, 2]), &inputs(31.0));
        assert_eq!(refined_of(&moved), vec![0, 2]);
        // A settled cut whose bricks left the GPU cannot be drawn: the new cut is taken.
        let empty_slots = GpuSlots::new(64);
        let redrawn = keep_settled_cut(Some(&settled), &empty_slots, cut(&[0, 2]), &inputs(30.0));
        assert_eq!(refined_of(&redrawn), vec![0, 2]);
    }
}
