//! A still view is still at any frame rate (issue 35). On an H200 one cut selection is applied
//! per ~7.5 rendered frames; on lavapipe about one per frame, which hid an oscillation: with
//! visibility remembered for a number of *frames*, every mark a fast GPU's selection saw came
//! from the current cut, and the cut flipped between two states forever. These tests drive
//! lavapipe at a fast GPU's cadence (`SelectionTiming::EveryNthFrame`, several frames per
//! selection, jitter seeded per frame as the viewer does) and at the opposite one (a
//! selection per frame, feedback several frames late), on occluded and open views, flat and
//! octree traversals, budget-bound and not, and check that once converged the cut never
//! changes again, "converged" stays true and nothing is uploaded.

use crate::common;

use common::*;
use strata_loader::{SelectionTiming, StreamingConfig};
use strata_render::{RenderSettings, TransferFunction, Traversal};

/// Frames a viewpoint gets to converge (generous: the fetch workers share two busy cores).
const SETTLE_FRAMES: u32 = 600;
/// Still frames after converging in which nothing may change: 8 selections at the fast
/// cadence, 64 at the slow one. Visibility ages by cut generation, not by frames
/// (visibility.rs: frames alone age nothing), so a cut that held through several selections
/// with nothing uploaded is a fixed point; the oscillation of issue 35 flipped at every
/// selection. 120 frames before issue 53 (CI time: these three tests were the loader's
/// slowest, 75-83 s each, 70 % of their frames in the hold).
const HOLD_FRAMES: u32 = 64;

#[derive(Clone, Copy, Debug)]
enum Cadence {
    /// Frames per selection, feedback read back a frame late (a fast GPU).
    Fast(u32),
    /// A selection per frame, feedback read back only every few frames (a slow adapter).
    Slow { readback_every: u32 },
}

struct Case {
    what: &'static str,
    tf: TransferFunction,
    traversal: Traversal,
    /// Some: a GPU budget the view's working set does not fit.
    slots: Option<u32>,
    cadence: Cadence,
}

/// The viewer's settings: jitter on, seeded by a frame index that changes every frame.
fn frame_settings(size: u32, frame: u32) -> RenderSettings {
    RenderSettings {
        jitter: true,
        frame_index: frame,
        ..settings(size)
    }
}

/// What a still view did: frames to converge, and the converged stats.
/// `store` is shared by a test's cases (one import per test, not one per case: the cut and
/// its convergence depend on the loader's state, which each case makes afresh).
fn hold_still(
    case: &Case,
    store: &std::sync::Arc<strata_storage::Store>,
) -> (u32, strata_loader::FrameStats) {
    let ctx = gpu();
    let selection = match case.cadence {
        Cadence::Fast(n) => SelectionTiming::EveryNthFrame(n),
        Cadence::Slow { .. } => SelectionTiming::EachFrame,
    };
    let mut volume = stream(
        &ctx,
        store,
        &case.tf,
        StreamingConfig {
            selection,
            traversal: Some(case.traversal),
            max_gpu_slots: case.slots,
            // Level 0 wanted over most of the view.
            max_voxel_pixels: 0.5,
            uploads_per_frame: 16,
            ..config()
        },
    );
    let camera = orbit(store, 35.0, 20.0, 1.8);
    let mut frame = 0u32;
    settle(
        &ctx,
        &mut volume,
        &camera,
        case.cadence,
        case.what,
        &mut frame,
    )
}

/// Renders `camera` until converged, then holds it: once converged, the cut never changes,
/// "converged" stays true and nothing is uploaded. Returns the frames it took and the
/// converged stats.
fn settle(
    ctx: &strata_render::GpuContext,
    volume: &mut strata_loader::StreamingVolume,
    camera: &strata_render::Camera,
    cadence: Cadence,
    what: &str,
    frame: &mut u32,
) -> (u32, strata_loader::FrameStats) {
    let started_at = *frame;
    let render = |volume: &mut strata_loader::StreamingVolume, frame: &mut u32| {
        *frame += 1;
        let stats = volume
            .frame(ctx, camera, &frame_settings(64, *frame))
            .unwrap();
        let read_back = match cadence {
            Cadence::Fast(_) => true,
            Cadence::Slow { readback_every } => frame.is_multiple_of(readback_every),
        };
        if read_back {
            volume.read_frame_blocking(ctx).unwrap();
        }
        stats
    };
    let converged = loop {
        let stats = render(volume, frame);
        if stats.converged {
            break stats;
        }
        assert!(
            *frame - started_at < SETTLE_FRAMES,
            "{what}: not converged in {SETTLE_FRAMES} still frames: {stats:#?}"
        );
        if stats.pending > 0 && stats.uploads == 0 && !stats.page_table_rewritten {
            // Waiting for reads: let the workers run rather than spin identical frames.
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
    };
    let converged_at = *frame;
    let table = volume.page_table().clone();
    for held in 1..=HOLD_FRAMES {
        let stats = render(volume, frame);
        assert_eq!(
            stats.uploads, 0,
            "{what}: uploaded {held} frames after converging (frame {converged_at})"
        );
        assert!(
            !stats.page_table_rewritten && *volume.page_table() == table,
            "{what}: the cut changed {held} still frames after converging (frame \
             {converged_at}): {} leaves then, {} now",
            converged.leaves,
            stats.leaves
        );
        assert!(
            stats.converged,
            "{what}: \"converged\" lost {held} still frames after converging: {stats:#?}"
        );
        assert_eq!(
            stats.cut_changes_while_still_total, converged.cut_changes_while_still_total,
            "{what}: the cut changed while still"
        );
    }
    volume.check_slot_map().unwrap();
    (converged_at - started_at, converged)
}

fn cases(cadence: Cadence) -> Vec<Case> {
    let mut cases = Vec::new();
    for traversal in [Traversal::Flat, Traversal::Octree] {
        for (what, tf) in [("occluded", opaque()), ("open", bone())] {
            for slots in [None, Some(48)] {
                cases.push(Case {
                    what: Box::leak(
                        format!(
                            "{what} view, {} traversal, {}, {cadence:?}",
                            traversal.name(),
                            if slots.is_some() {
                                "budget-bound"
                            } else {
                                "generous budget"
                            }
                        )
                        .into_boxed_str(),
                    ),
                    tf: tf.clone(),
                    traversal,
                    slots,
                    cadence,
                });
            }
        }
    }
    cases
}

/// A fast GPU's cadence: eight frames per selection.
#[test]
fn a_still_view_settles_at_a_fast_gpus_cadence() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 128));
    for case in cases(Cadence::Fast(8)) {
        let (frames, stats) = hold_still(&case, &store);
        eprintln!(
            "{}: converged after {frames} frames, {} leaves, working set {} bricks",
            case.what, stats.leaves, stats.working_set_bricks
        );
    }
}

/// The opposite cadence: a selection per frame, feedback read back every fourth frame.
#[test]
fn a_still_view_settles_at_a_slow_adapters_cadence() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 128));
    for case in cases(Cadence::Slow { readback_every: 4 }) {
        let (frames, stats) = hold_still(&case, &store);
        eprintln!(
            "{}: converged after {frames} frames, {} leaves, working set {} bricks",
            case.what, stats.leaves, stats.working_set_bricks
        );
    }
}

/// A view reached by a jump settles on its own cut, at a fast GPU's cadence. The selection
/// applied on the first frames at the new view was made for the old one (a background
/// selection lags the camera); it was labelled with the new view, so it reported
/// "converged" there and was kept as the new view's settled cut, with the old frustum's
/// culling: on an H200 the cut then flipped between it and the new view's own cut forever
/// (9339 <-> 6686 leaves with nothing to load, issue 35). Without visibility feedback the
/// cut is a function of the view, so the jump must end on the cut a fresh loader selects
/// there; with feedback, on one that holds still.
#[test]
fn a_view_reached_by_a_jump_settles_on_its_own_cut() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 128));
    let ctx = gpu();
    // The whole volume, then close in on one side: most of what the first cut refined is
    // outside the second view's frustum.
    let before = orbit(&store, 35.0, 20.0, 1.8);
    let after = orbit(&store, -70.0, -15.0, 4.0);
    let cadence = Cadence::Fast(8);
    for traversal in [Traversal::Flat, Traversal::Octree] {
        for visibility_feedback in [false, true] {
            let what = format!(
                "{} traversal, visibility {}",
                traversal.name(),
                if visibility_feedback { "on" } else { "off" }
            );
            let config = StreamingConfig {
                selection: SelectionTiming::EveryNthFrame(8),
                traversal: Some(traversal),
                visibility_feedback,
                max_voxel_pixels: 0.5,
                uploads_per_frame: 16,
                ..config()
            };
            let mut fresh = stream(&ctx, &store, &opaque(), config.clone());
            let mut frame = 0;
            let (_, direct) = settle(
                &ctx,
                &mut fresh,
                &after,
                cadence,
                &format!("{what}, direct"),
                &mut frame,
            );
            drop(fresh);
            let mut moved = stream(&ctx, &store, &opaque(), config);
            let mut frame = 0;
            let (_, first) = settle(
                &ctx,
                &mut moved,
                &before,
                cadence,
                &format!("{what}, first view"),
                &mut frame,
            );
            let (frames, jumped) = settle(
                &ctx,
                &mut moved,
                &after,
                cadence,
                &format!("{what}, after the jump"),
                &mut frame,
            );
            eprintln!(
                "{what}: {} leaves at the first view; after the jump {} leaves in {frames} \
                 frames, {} directly",
                first.leaves, jumped.leaves, direct.leaves
            );
            if !visibility_feedback {
                assert_eq!(
                    (jumped.leaves, &jumped.data_leaves_per_level),
                    (direct.leaves, &direct.data_leaves_per_level),
                    "{what}: the view reached by a jump settled on another cut than its own"
                );
            }
        }
    }
}
