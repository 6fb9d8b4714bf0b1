//! The motion-extrapolated cut for prefetching (prefetch.rs), selected on a named background
//! thread: a second full cut selection per moving frame cost the frame thread as much as the
//! first. Its answer only feeds speculative reads, so arriving a frame late costs nothing;
//! the frame thread hands over a job without waiting (dropping it while the thread is still
//! busy with the previous one) and takes the newest answer when there is one.

use std::sync::Arc;
use std::thread::JoinHandle;

use crossbeam_channel::{Receiver, Sender, TrySendError};
use rustc_hash::FxHashSet;
use strata_render::{TransferFunctionTable, ValueMapping};
use strata_types::BrickId;

use crate::cut_selection::{
    select_cut, CutLimits, LeafKind, Residency, ViewSetup, PREDICTION_THREAD,
};
use crate::error::LoaderError;
use crate::octree_ranges::{Emptiness, OctreeRanges};

/// What "contributes nothing" means, owned so that it can cross to the thread.
#[derive(Clone)]
pub enum EmptinessSpec {
    TransferFunction {
        table: Arc<TransferFunctionTable>,
        mapping: ValueMapping,
    },
    Iso {
        value: f64,
        mapping: ValueMapping,
    },
}

impl EmptinessSpec {
    pub fn emptiness(&self) -> Emptiness<'_> {
        match self {
            EmptinessSpec::TransferFunction { table, mapping } => Emptiness::TransferFunction {
                table,
                mapping: *mapping,
            },
            EmptinessSpec::Iso { value, mapping } => Emptiness::Iso {
                value: *value,
                mapping: *mapping,
            },
        }
    }
}

pub struct PredictionJob {
    /// The extrapolated camera's view.
    pub view: ViewSetup,
    pub emptiness: EmptinessSpec,
    /// Bricks that failed to read (never refined into).
    pub failed: FxHashSet<BrickId>,
    pub limits: CutLimits,
}

/// Data leaves (with priorities) of a predicted cut, as if every brick were loaded.
pub type PredictedLeaves = Vec<(BrickId, f64)>;

pub struct CutPredictor {
    jobs: Option<Sender<PredictionJob>>,
    results: Receiver<PredictedLeaves>,
    thread: Option<JoinHandle<()>>,
    /// Inline ([`CutPredictor::inline`]): the octree predicted on, and the newest answer.
    inline: Option<(Arc<OctreeRanges>, std::sync::Mutex<Option<PredictedLeaves>>)>,
}

/// As if everything were loaded, so the prediction says what the view will want rather than
/// what it can show now.
struct EverythingLoaded<'a> {
    failed: &'a FxHashSet<BrickId>,
}

impl Residency for EverythingLoaded<'_> {
    fn on_gpu(&self, _: BrickId) -> bool {
        true
    }
    fn in_cpu(&self, _: BrickId) -> bool {
        true
    }
    fn failed(&self, id: BrickId) -> bool {
        self.failed.contains(&id)
    }
}

/// The predicted cut's data leaves.
pub fn predict(octree: &OctreeRanges, job: &PredictionJob) -> PredictedLeaves {
    let everything = EverythingLoaded {
        failed: &job.failed,
    };
    let cut = select_cut(
        octree,
        &job.view,
        job.emptiness.emptiness(),
        None,
        &everything,
        &FxHashSet::default(),
        CutLimits {
            uploads: usize::MAX,
            ..job.limits
        },
    );
    cut.leaves
        .iter()
        .filter(|l| l.kind == LeafKind::Data)
        .map(|l| (l.id, l.priority))
        .collect()
}

impl CutPredictor {
    pub fn start(octree: Arc<OctreeRanges>) -> Result<Self, LoaderError> {
        // One job at a time and one answer waiting: a newer frame's job replaces nothing, it
        // is dropped while the thread is busy (the next moving frame sends another).
        let (job_tx, job_rx) = crossbeam_channel::bounded::<PredictionJob>(1);
        let (result_tx, result_rx) = crossbeam_channel::bounded::<PredictedLeaves>(1);
        let stale = result_rx.clone();
        let thread = std::thread::Builder::new()
            .name(PREDICTION_THREAD.into())
            .spawn(move || {
                for job in job_rx {
                    let leaves = predict(&octree, &job);
                    // A full slot holds an older answer nobody took: replace it.
                    if let Err(TrySendError::Full(leaves)) = result_tx.try_send(leaves) {
                        let _ = stale.try_recv();
                        let _ = result_tx.try_send(leaves);
                    }
                }
            })
            .map_err(|e| LoaderError::Worker(format!("cannot start cut prediction thread: {e}")))?;
        Ok(CutPredictor {
            jobs: Some(job_tx),
            results: result_rx,
            thread: Some(thread),
            inline: None,
        })
    }

    /// Without a thread: [`CutPredictor::submit`] predicts on the calling thread, its answer
    /// taken by the next [`CutPredictor::take_newest`] as the thread's would be.
    pub fn inline(octree: Arc<OctreeRanges>) -> Self {
        let (_, results) = crossbeam_channel::bounded(1);
        CutPredictor {
            jobs: None,
            results,
            thread: None,
            inline: Some((octree, std::sync::Mutex::new(None))),
        }
    }

    /// Hands `job` to the thread unless it is still busy; never waits.
    pub fn submit(&self, job: PredictionJob) {
        if let Some((octree, answer)) = &self.inline {
            let leaves = predict(octree, &job);
            *answer.lock().unwrap_or_else(|e| e.into_inner()) = Some(leaves);
            return;
        }
        if let Some(jobs) = &self.jobs {
            let _ = jobs.try_send(job);
        }
    }

    /// The newest answer since the last call, if any; never waits.
    pub fn take_newest(&self) -> Option<PredictedLeaves> {
        if let Some((_, answer)) = &self.inline {
            return answer.lock().unwrap_or_else(|e| e.into_inner()).take();
        }
        self.results.try_iter().last()
    }
}

impl Drop for CutPredictor {
    fn drop(&mut self) {
        // Closing the job channel ends the thread's loop after its current job.
        self.jobs = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
