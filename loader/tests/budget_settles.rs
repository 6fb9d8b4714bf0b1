//! A flythrough whose GPU budget is below the view's working set settles: after a bounded
//! number of frames at a viewpoint no brick is uploaded, the cut and the page table stay the
//! same, and the loader says "converged at budget" with the nodes it had to leave coarser. A
//! bigger budget refines the same view further. Frames never wait for a read (each frame is
//! drawn with what is loaded; the fetch workers run behind it).

use crate::common;

use common::*;
use strata_loader::cut_selection::selections_by_thread;
use strata_loader::{FrameStats, SelectionTiming, StreamingConfig};
use strata_render::Traversal;

/// Frames a viewpoint gets to settle. Generous against the cut's own needs (a few frames of
/// uploads and feedback) because the fetch workers share two busy cores with the test.
const SETTLE_FRAMES: usize = 150;
/// Frames the settled cut must then stay unchanged.
const STABLE_FRAMES: usize = 12;

fn budget_config(slots: u32, selection: SelectionTiming) -> StreamingConfig {
    StreamingConfig {
        selection,
        max_gpu_slots: Some(slots),
        // Asks for level 0 wherever a voxel covers more than half a pixel: far more than the
        // small budget holds.
        max_voxel_pixels: 0.5,
        uploads_per_frame: 16,
        ..config()
    }
}

/// Holds `camera` until the loader converges (at most `SETTLE_FRAMES`), then checks that
/// `STABLE_FRAMES` more frames upload nothing and keep the same page table. Returns the stats
/// of the converged frame.
fn settle(
    ctx: &strata_render::GpuContext,
    volume: &mut strata_loader::StreamingVolume,
    camera: &strata_render::Camera,
    settings: &strata_render::RenderSettings,
    what: &str,
) -> FrameStats {
    let mut converged = None;
    for frame in 0..SETTLE_FRAMES {
        let stats = volume.frame(ctx, camera, settings).unwrap();
        volume.read_frame_blocking(ctx).unwrap();
        if stats.converged {
            converged = Some(stats);
            break;
        }
        if stats.pending > 0 && stats.uploads == 0 && !stats.page_table_rewritten {
            // Waiting for reads: let the workers run rather than spin identical frames.
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        assert!(
            frame + 1 < SETTLE_FRAMES,
            "{what}: not converged: {stats:#?}"
        );
    }
    let converged = converged.unwrap_or_else(|| panic!("{what}: never converged"));
    let table = volume.page_table().clone();
    for frame in 0..STABLE_FRAMES {
        let stats = volume.frame(ctx, camera, settings).unwrap();
        volume.read_frame_blocking(ctx).unwrap();
        assert_eq!(
            stats.uploads, 0,
            "{what}: upload {frame} frames after converging"
        );
        assert!(
            !stats.page_table_rewritten && *volume.page_table() == table,
            "{what}: the cut changed {frame} frames after converging: {stats:#?}"
        );
        assert_eq!(
            stats.data_leaves_per_level, converged.data_leaves_per_level,
            "{what}: level counts moved"
        );
        assert!(stats.converged, "{what}: convergence lost: {stats:#?}");
        assert_eq!(stats.convergence_status(), converged.convergence_status());
        volume.check_slot_map().unwrap();
    }
    converged
}

#[test]
fn a_budget_bound_flythrough_settles_and_a_bigger_budget_refines_further() {
    budget_bound_flythrough(SelectionTiming::EachFrame, Traversal::Flat);
}

/// The same with the octree traversal: its per-leaf visibility feedback and MIP bounds feed
/// the same settling rules.
#[test]
fn a_budget_bound_flythrough_settles_with_the_octree_traversal() {
    budget_bound_flythrough(SelectionTiming::EachFrame, Traversal::Octree);
}

/// The same with the viewer's timing: frames apply whatever selection the thread finished
/// and never wait for one; the settling rules hold all the same.
#[test]
fn the_flythrough_settles_with_the_cut_selected_in_the_background() {
    budget_bound_flythrough(SelectionTiming::Background, Traversal::Flat);
}

/// Every cut of these streamed volumes is selected on the loader's selection threads
/// (`strata-cut-select`, `strata-cut-predict`), none on a frame thread (this binary calls
/// no selection directly, so any selection elsewhere is a frame's).
#[test]
fn frames_select_no_cut_on_their_own_thread() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 64));
    let ctx = gpu();
    let tf = bone();
    let s = settings(64);
    for selection in [SelectionTiming::EachFrame, SelectionTiming::Background] {
        let mut volume = stream(&ctx, &store, &tf, budget_config(40, selection));
        let before = selections_by_thread();
        let mut last = None;
        for k in 0..20 {
            let camera = orbit(&store, 3.0 * k as f64, 10.0, 1.6);
            let stats = volume.frame(&ctx, &camera, &s).unwrap();
            volume.read_frame_blocking(&ctx).unwrap();
            last = Some(stats);
        }
        let after = selections_by_thread();
        let last = last.unwrap();
        assert!(
            last.selections_applied_total > 0,
            "{selection:?}: no selection applied: {last:#?}"
        );
        assert!(after.on_selection_threads > before.on_selection_threads);
        assert_eq!(
            after.elsewhere, 0,
            "{selection:?}: a cut was selected outside the selection threads"
        );
        if selection == SelectionTiming::EachFrame {
            assert_eq!(last.selections_applied_total, 20, "one selection per frame");
        }
    }
}

/// With the background timing a frame never waits for a selection: while the selection
/// thread is held, frames go on drawing the current cut, and once released its answer is
/// applied by a later frame.
#[test]
fn frames_go_on_while_the_selection_thread_is_held() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 64));
    let ctx = gpu();
    let tf = bone();
    let s = settings(64);
    let mut volume = stream(
        &ctx,
        &store,
        &tf,
        budget_config(40, SelectionTiming::Background),
    );
    let camera = orbit(&store, 20.0, 10.0, 1.6);
    let hold = volume.hold_selection_for_tests();
    let table = volume.page_table().clone();
    for _ in 0..10 {
        let stats = volume.frame(&ctx, &camera, &s).unwrap();
        volume.read_frame_blocking(&ctx).unwrap();
        assert_eq!(stats.selections_applied_total, 0, "{stats:#?}");
        assert!(!stats.converged && stats.uploads == 0);
        assert_eq!(*volume.page_table(), table, "no cut applied while held");
    }
    drop(hold);
    let mut applied = 0;
    for _ in 0..200 {
        let stats = volume.frame(&ctx, &camera, &s).unwrap();
        volume.read_frame_blocking(&ctx).unwrap();
        applied = stats.selections_applied_total;
        if applied > 0 && *volume.page_table() != table {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    assert!(
        applied > 0,
        "the released thread's selection was never applied"
    );
    assert_ne!(
        *volume.page_table(),
        table,
        "the released thread's selections refine the root"
    );
}

fn budget_bound_flythrough(selection: SelectionTiming, traversal: Traversal) {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 256));
    let ctx = gpu();
    let tf = bone();
    let s = settings(128);
    let slots = 40u32;
    let with_traversal = |slots| StreamingConfig {
        traversal: Some(traversal),
        ..budget_config(slots, selection)
    };
    let mut volume = stream(&ctx, &store, &tf, with_traversal(slots));
    assert_eq!(volume.traversal(), traversal);
    let stops = [
        orbit(&store, -30.0, 15.0, 1.6),
        orbit(&store, 20.0, 5.0, 2.2),
        orbit(&store, 60.0, -5.0, 2.6),
    ];
    let mut last_stop = None;
    for (k, camera) in stops.iter().enumerate() {
        // Glide in from the previous stop (moving frames refine and evict as they go).
        if k > 0 {
            for g in 1..=6 {
                let t = g as f64 / 6.0;
                let glide = orbit(
                    &store,
                    -30.0 + 50.0 * (k as f64 - 1.0 + t),
                    15.0 - 10.0 * (k as f64 - 1.0 + t),
                    1.6 + 0.5 * (k as f64 - 1.0 + t),
                );
                let stats = volume.frame(&ctx, &glide, &s).unwrap();
                volume.read_frame_blocking(&ctx).unwrap();
                assert!(stats.gpu_slots_used <= slots as usize, "{stats:#?}");
            }
        }
        let stats = settle(&ctx, &mut volume, camera, &s, &format!("stop {k}"));
        eprintln!(
            "stop {k}: {} after {} frames; data leaves per level {:?}, working set {} of {slots} slots",
            stats.convergence_status(),
            stats.frame,
            stats.data_leaves_per_level,
            stats.working_set_bricks
        );
        assert!(
            stats.converged_at_budget && stats.left_coarser > 0,
            "stop {k}: the budget should bind here: {stats:#?}"
        );
        assert!(
            stats
                .convergence_status()
                .starts_with("converged at budget ("),
            "{}",
            stats.convergence_status()
        );
        assert!(stats.working_set_bricks <= slots as usize);
        last_stop = Some(stats);
    }

    // The same last view with four times the slots: finer, with fewer nodes left coarser.
    let small = last_stop.unwrap();
    let mut bigger = stream(&ctx, &store, &tf, with_traversal(4 * slots));
    let large = settle(&ctx, &mut bigger, &stops[2], &s, "bigger budget");
    eprintln!(
        "bigger budget: {}; data leaves per level {:?}",
        large.convergence_status(),
        large.data_leaves_per_level
    );
    assert!(
        large.working_set_bricks > small.working_set_bricks,
        "a bigger budget should hold a bigger cut: {} vs {}",
        large.working_set_bricks,
        small.working_set_bricks
    );
    assert!(
        large.data_leaves_per_level[0] > small.data_leaves_per_level[0],
        "a bigger budget should refine further: {:?} vs {:?}",
        large.data_leaves_per_level,
        small.data_leaves_per_level
    );
    assert!(
        !large.converged_at_budget || large.left_coarser < small.left_coarser,
        "{} vs {}",
        large.convergence_status(),
        small.convergence_status()
    );
}
