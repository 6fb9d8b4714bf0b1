//! What the streaming loader reports each frame, for the UI, the benches and the tests.

/// One frame's view of the working set. Counters named `_total` accumulate since open.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameStats {
    pub frame: u64,
    /// Wall time of `StreamingVolume::frame` up to the submit (selection, uploads, page table):
    /// what the loader adds to a frame. Never includes a read.
    pub loader_seconds: f64,
    /// The same span in CPU time of the calling (frame) thread (`CLOCK_THREAD_CPUTIME_ID`):
    /// what the loader costs the frame thread, whatever else the machine runs. NaN where the
    /// clock is unavailable.
    pub loader_cpu_seconds: f64,
    /// Selections (made on `strata-cut-select`) applied since open: one per frame with
    /// `SelectionTiming::EachFrame`, fewer in the background when the thread lags.
    pub selections_applied_total: u64,
    /// Finished selections dropped since open because they no longer fitted (a brick to
    /// upload left the CPU cache meanwhile, or a new transfer function).
    pub selections_dropped_total: u64,
    /// Cut changes since open while the view stood still (same camera, settings and transfer
    /// function as the cut before): ones that coarsened a node the previous cut refined, and
    /// any change after the view had converged. LOD flicker: 0 when a still view is still.
    pub cut_changes_while_still_total: u64,
    pub leaves: usize,
    pub data_leaves: usize,
    /// Data leaves of this cut per level (index = level).
    pub data_leaves_per_level: Vec<usize>,
    /// Bricks in GPU slots per level (index = level).
    pub gpu_resident_per_level: Vec<usize>,
    pub gpu_slots_used: usize,
    pub gpu_slots_capacity: usize,
    pub gpu_bytes: u64,
    pub gpu_budget_bytes: u64,
    /// Bricks this cut keeps on the GPU: data leaves, their resident ancestors, the root.
    pub working_set_bricks: usize,
    /// `working_set_bricks` × decompressed brick bytes.
    pub working_set_bytes: u64,
    /// Decompressed bricks in the CPU cache.
    pub cpu_cache_bytes: u64,
    /// Decompressed bricks + sled's page cache capacity + bricks between workers and cache.
    pub cpu_bytes: u64,
    pub cpu_budget_bytes: u64,
    /// Wanted bricks found in CPU memory / wanted bricks not on the GPU (cumulative).
    pub cpu_hit_rate: f64,
    /// Data leaves of this cut already on the GPU / data leaves.
    pub gpu_hit_rate: f64,
    /// Requests queued plus being read.
    pub pending: usize,
    pub queued: usize,
    pub in_flight: usize,
    pub queue_capacity: usize,
    pub stale_dropped_total: u64,
    pub overflow_dropped_total: u64,
    /// Requests already on their way (a remote source's) aborted because the view moved on.
    pub cancelled_in_flight_total: u64,
    /// Requests sent again (connection errors, 429/503, a record that failed its checksum).
    pub retried_total: u64,
    /// Records that arrived damaged (each re-requested once, then reported as failed).
    pub checksum_failures_total: u64,
    /// Most requests in flight at once since open.
    pub max_in_flight: u64,
    /// The source's state: `Retrying` while a remote source cannot be reached ("connection
    /// lost, retrying"); the frame keeps showing what is loaded.
    pub source_status: strata_source::SourceStatus,
    pub bricks_read_total: u64,
    /// Compressed bytes read from the store.
    pub stored_bytes_read_total: u64,
    /// Decompressed bytes of the bricks read.
    pub brick_bytes_read_total: u64,
    /// Compressed bytes read per second over roughly the last second.
    pub bytes_read_per_second: f64,
    pub uploads: usize,
    pub upload_bytes: u64,
    pub prefetch_loaded_total: u64,
    pub prefetch_used_total: u64,
    pub prefetch_hit_rate: f64,
    pub failed_bricks: usize,
    pub page_table_rewritten: bool,
    /// Refinements this frame held back by: missing bricks, the upload budget, the GPU slot
    /// budget, a neighbour that could not refine first (2:1 balance).
    pub blocked: [usize; 4],
    /// Refinement stopped somewhere only because GPU slots ran out.
    pub gpu_budget_limited: bool,
    /// Leaves the quality factor wanted finer that the GPU budget kept coarser this frame.
    pub left_coarser: usize,
    /// Converged with `left_coarser` > 0: the best cut that fits the GPU budget (a bigger
    /// budget refines further).
    pub converged_at_budget: bool,
    /// Nothing the quality factor asks for is missing, the cut is stable and the visibility
    /// feedback has seen it: further frames show the same image.
    pub converged: bool,
}

impl FrameStats {
    /// One line for status bars and summaries: "converged", "converged at budget (N nodes
    /// left coarser than wanted)" or "refining".
    pub fn convergence_status(&self) -> String {
        match (self.converged, self.converged_at_budget) {
            (true, true) => format!(
                "converged at budget ({} nodes left coarser than wanted)",
                self.left_coarser
            ),
            (true, false) => "converged".into(),
            (false, _) => "refining".into(),
        }
    }
}

/// Frame-time distribution over a run.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Distribution {
    pub count: usize,
    pub min: f64,
    pub p50: f64,
    pub p95: f64,
    pub p99: f64,
    pub max: f64,
    pub mean: f64,
}

impl Distribution {
    pub fn of(values: &[f64]) -> Distribution {
        let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return Distribution::default();
        }
        v.sort_by(f64::total_cmp);
        let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
        Distribution {
            count: v.len(),
            min: v[0],
            p50: at(0.5),
            p95: at(0.95),
            p99: at(0.99),
            max: v[v.len() - 1],
            mean: v.iter().sum::<f64>() / v.len() as f64,
        }
    }
}
