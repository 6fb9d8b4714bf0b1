//! The streaming loader on lavapipe with small phantoms and images: convergence to the
//! everything-loaded render, budgets, visibility feedback, rapid view changes, corruption.
//!
//! Image tolerances: streamed and up-front frames run the same shader over the same field, so
//! where both have the same bricks they agree bit for bit. What may differ is where visibility
//! feedback left an occluded node coarser: rays reach it only after opacity ≥ 0.99, so it can
//! move a pixel by a couple of levels at most. PSNR ≥ 45 dB bounds that.

use crate::common;

use common::*;
use strata_loader::StreamingConfig;
use strata_render::{compare_rgba8, PageTable};
use strata_storage::Store;
use strata_types::BrickId;

#[test]
fn converged_image_equals_everything_loaded_up_front() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 128));
    let ctx = gpu();
    let tf = bone();
    let s = settings(256);
    let camera = orbit(&store, 30.0, 20.0, 1.0);
    // A quality factor that asks for level 0 wherever something is visible.
    let config = StreamingConfig {
        max_voxel_pixels: 0.25,
        ..config()
    };
    let mut volume = stream(&ctx, &store, &tf, config.clone());
    let (streamed, history) = converge(&ctx, &mut volume, &camera, &s, 300);
    let reference = up_front(&ctx, &store, 0, &tf, &camera, &s);
    let c = compare_rgba8(&streamed, &reference).unwrap();
    assert!(c.psnr_db >= 45.0, "streamed vs up-front: {c:?}");
    assert!(
        covered_pixels(&streamed) > 256 * 256 / 20,
        "image nearly empty"
    );
    let last = history.last().unwrap();
    assert!(
        last.gpu_resident_per_level[0] > 0,
        "level 0 never loaded: {last:#?}"
    );
    // Emptiness culling: the air around the body is never loaded at level 0.
    assert!(
        last.data_leaves < 64,
        "{} data leaves of 64 level-0 bricks",
        last.data_leaves
    );
    // Close up from the side: thin ribs and the wire at the image edge, where averaging blurs
    // them out of coarse levels and the feedback alone would never ask for level 0.
    let close = orbit(&store, 90.0, -5.0, 3.5);
    let mut volume = stream(&ctx, &store, &tf, config.clone());
    let (streamed, _) = converge(&ctx, &mut volume, &close, &s, 300);
    let c = compare_rgba8(&streamed, &up_front(&ctx, &store, 0, &tf, &close, &s)).unwrap();
    assert!(c.psnr_db >= 45.0, "close-up streamed vs up-front: {c:?}");
    // The first frame was drawn from the pinned root alone, before any read returned.
    assert!(covered_pixels(&first_frame_image(&ctx, &store, &tf, &camera, &s)) > 0);
}

fn first_frame_image(
    ctx: &strata_render::GpuContext,
    store: &std::sync::Arc<Store>,
    tf: &strata_render::TransferFunction,
    camera: &strata_render::Camera,
    s: &strata_render::RenderSettings,
) -> Vec<u8> {
    let mut volume = stream(ctx, store, tf, config());
    let stats = volume.frame(ctx, camera, s).unwrap();
    assert_eq!(stats.data_leaves, 1, "first frame is the root alone");
    volume.read_frame_blocking(ctx).unwrap().rgba
}

#[test]
fn budgets_hold_along_a_scripted_camera_path() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 256));
    let ctx = gpu();
    let tf = bone();
    let s = settings(128);
    let slots = 40u32;
    let uploads = 3usize;
    let config = StreamingConfig {
        max_gpu_slots: Some(slots),
        // sled 1 MiB, 2 bricks being read + 4 in transit, and room for 64 decompressed bricks.
        bricks_in_transit: 4,
        cpu_budget_bytes: (1 << 20)
            + 6 * strata_loader::streaming::BRICK_BYTES
            + 64 * strata_loader::streaming::BRICK_BYTES,
        sled_cache_bytes: 1 << 20,
        uploads_per_frame: uploads,
        max_voxel_pixels: 0.5,
        ..config()
    };
    let mut volume = stream(&ctx, &store, &tf, config);
    let mut limited = false;
    let mut max_level0 = 0;
    // Four stops along an orbit that closes in; the camera glides between stops for 5 frames
    // and holds still for 15, so refinement gets deep enough to meet the slot budget.
    for frame in 0..80 {
        let stop = (frame / 20) as f64;
        let glide = ((frame % 20) as f64 / 5.0).min(1.0);
        let t = (stop + glide) / 4.0;
        let camera = orbit(&store, -40.0 + 120.0 * t, 10.0 + 20.0 * t, 1.0 + 2.0 * t);
        let stats = volume.frame(&ctx, &camera, &s).unwrap();
        assert!(
            stats.gpu_slots_used <= slots as usize && stats.gpu_slots_capacity == slots as usize,
            "{stats:#?}"
        );
        assert!(stats.data_leaves <= slots as usize, "{stats:#?}");
        assert!(stats.cpu_bytes <= stats.cpu_budget_bytes, "{stats:#?}");
        assert!(stats.uploads <= uploads, "{stats:#?}");
        // Queued requests are bounded by the queue; in flight: one per worker being read plus
        // the result channel.
        assert!(
            stats.queued <= stats.queue_capacity && stats.in_flight <= 2 + 4,
            "{stats:#?}"
        );
        check_page_table_points_at_resident_slots(&volume.page_table().to_page_table(), slots);
        volume
            .check_slot_map()
            .unwrap_or_else(|e| panic!("frame {frame}: {e}"));
        let image = volume.read_frame_blocking(&ctx).unwrap();
        assert!(
            covered_pixels(&image.rgba) > 100,
            "frame {frame} nearly empty"
        );
        if frame % 10 == 0 {
            eprintln!("frame {frame}: {:?} conv {} slots {} data {} blocked {} pending {} cpu {} read {} per-level {:?}", stats.blocked, stats.converged, stats.gpu_slots_used, stats.data_leaves, stats.gpu_budget_limited, stats.pending, stats.cpu_bytes, stats.bricks_read_total, stats.gpu_resident_per_level);
        }
        limited |= stats.gpu_budget_limited;
        max_level0 = max_level0.max(stats.gpu_resident_per_level[0]);
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    assert!(
        limited,
        "the path never hit the GPU slot budget; the test would not notice a leak"
    );
    assert!(max_level0 > 0, "never refined to level 0");
}

fn check_page_table_points_at_resident_slots(table: &PageTable, slots: u32) {
    for e in &table.entries {
        if e.resident && !e.empty {
            assert!(e.slot_in_cache < slots);
        }
    }
}

#[test]
fn visibility_feedback_shrinks_the_opaque_working_set() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 256));
    let ctx = gpu();
    let tf = opaque();
    let s = settings(192);
    // From the side at mid-height: the body's cut ends (the volume's top and bottom) are edge-on.
    let camera = orbit(&store, 0.0, 0.0, 1.0);
    let run = |feedback: bool| {
        let config = StreamingConfig {
            visibility_feedback: feedback,
            max_voxel_pixels: 0.25,
            ..config()
        };
        let mut volume = stream(&ctx, &store, &tf, config);
        let (image, history) = converge(&ctx, &mut volume, &camera, &s, 300);
        let last = history.last().unwrap();
        eprintln!(
            "feedback {feedback}: leaves per level {:?}, working set {} bricks, {} frames",
            last.data_leaves_per_level,
            last.working_set_bricks,
            history.len()
        );
        (image, last.working_set_bricks)
    };
    let (without_image, without) = run(false);
    let (with_image, with) = run(true);
    assert!(
        (with as f64) <= 0.6 * without as f64,
        "feedback kept a working set of {with} bricks of {without} (needs ≥ 40 % fewer)"
    );
    let c = compare_rgba8(&with_image, &without_image).unwrap();
    // Occluded nodes stay coarse; they are reached only after opacity ≥ 0.99.
    assert!(c.psnr_db >= 45.0, "feedback changed the image: {c:?}");
}

#[test]
fn rapid_view_changes_keep_the_queue_bounded_and_drop_stale_requests() {
    let dir = tempfile::tempdir().unwrap();
    let path = phantom_store(dir.path(), 128);
    let store = open(&path);
    let ctx = gpu();
    let tf = bone();
    let s = settings(128);
    let capacity = 8;
    let reader = std::sync::Arc::new(strata_loader::SlowReader {
        inner: store.clone(),
        delay: std::time::Duration::from_millis(20),
    });
    let config = StreamingConfig {
        max_queued_requests: capacity,
        max_voxel_pixels: 0.25,
        fetch_threads: 1,
        bricks_in_transit: 2,
        ..config()
    };
    let mut volume = strata_loader::StreamingVolume::new(&ctx, reader, &tf, config).unwrap();
    // Jump around the volume every frame: each view wants different bricks.
    for frame in 0..40 {
        let camera = orbit(
            &store,
            (frame * 97 % 360) as f64,
            ((frame * 37) % 120) as f64 - 60.0,
            1.0 + (frame % 3) as f64,
        );
        let stats = volume.frame(&ctx, &camera, &s).unwrap();
        assert!(stats.queued <= capacity, "{stats:#?}");
        assert!(stats.in_flight <= 1 + 2, "{stats:#?}");
        volume.read_frame_blocking(&ctx).unwrap();
    }
    let stats = volume.last_stats().clone();
    assert!(
        stats.stale_dropped_total > 0,
        "no stale request was dropped: {stats:#?}"
    );
    // Every read is one the loader still wanted when it started: far fewer than were asked for.
    assert!(stats.bricks_read_total < 40 * capacity as u64, "{stats:#?}");
    // Holding still converges.
    let camera = orbit(&store, 0.0, 0.0, 1.0);
    let (_, history) = converge(&ctx, &mut volume, &camera, &s, 2000);
    assert!(history.last().unwrap().pending <= capacity);
}

#[test]
fn corrupted_brick_is_reported_once_and_its_parent_keeps_serving() {
    let dir = tempfile::tempdir().unwrap();
    let path = phantom_store(dir.path(), 96);
    // The centre brick of the body: visible under the bone TF (spine) and non-empty.
    let broken = BrickId::new(0, [1, 1, 1]);
    Store::corrupt_brick_for_tests(&path, broken, 40).unwrap();
    let store = open(&path);
    let ctx = gpu();
    let tf = bone();
    let s = settings(128);
    let camera = orbit(&store, 30.0, 20.0, 1.5);
    let config = StreamingConfig {
        max_voxel_pixels: 0.1,
        visibility_feedback: false,
        ..config()
    };
    let mut volume = stream(&ctx, &store, &tf, config);
    let mut failures = Vec::new();
    let mut converged = false;
    for _ in 0..300 {
        let stats = volume.frame(&ctx, &camera, &s).unwrap();
        volume.read_frame_blocking(&ctx).unwrap();
        failures.extend(volume.take_failures());
        if stats.converged {
            converged = true;
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    assert!(converged, "{:#?}", volume.last_stats());
    for _ in 0..5 {
        volume.frame(&ctx, &camera, &s).unwrap();
        volume.read_frame_blocking(&ctx).unwrap();
        failures.extend(volume.take_failures());
    }
    assert_eq!(failures.len(), 1, "{failures:?}");
    assert_eq!(failures[0].id, broken);
    assert!(
        failures[0].message.contains("brick"),
        "{}",
        failures[0].message
    );
    let table = volume.page_table().to_page_table();
    let served = table.get([1, 1, 1]);
    assert!(
        served.resident && served.level == 1,
        "broken page served by {served:?}"
    );
    let neighbour = table.get([1, 1, 0]);
    assert!(
        !neighbour.resident || neighbour.empty || neighbour.level == 0,
        "neighbour at {neighbour:?}"
    );
}

/// The browser's mode (`LoaderWork::Inline`: wasm32 has no threads): selection, prediction
/// and reads on the frame thread, at most `fetch_threads` reads per frame, with the
/// background timing the viewer uses. It converges to the image the threads give (the same
/// selection over the same bricks: identical, PSNR bound as above for feedback order).
#[test]
fn inline_work_on_the_frame_thread_converges_like_the_threads() {
    use strata_loader::streaming::LoaderWork;
    use strata_loader::SelectionTiming;
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 96));
    let ctx = gpu();
    let tf = bone();
    let s = settings(128);
    let camera = orbit(&store, 30.0, 20.0, 1.0);
    let base = StreamingConfig {
        max_voxel_pixels: 0.25,
        fetch_threads: 3,
        selection: SelectionTiming::Background,
        ..config()
    };
    let inline = StreamingConfig {
        work: LoaderWork::Inline,
        ..base.clone()
    };
    let mut volume = stream(&ctx, &store, &tf, inline);
    let (inline_image, history) = converge(&ctx, &mut volume, &camera, &s, 400);
    let last = history.last().unwrap();
    assert!(last.converged, "inline work did not converge: {last:#?}");
    assert!(last.gpu_resident_per_level[0] > 0, "level 0 never loaded");
    // Bounded work per frame: never more reads than the budget (the root is read up front).
    let mut read_before = 1;
    for stats in &history {
        let read = stats.bricks_read_total - read_before;
        assert!(read <= 3, "frame {} read {read} bricks", stats.frame);
        read_before = stats.bricks_read_total;
    }
    let mut volume = stream(&ctx, &store, &tf, base);
    let (threaded_image, _) = converge(&ctx, &mut volume, &camera, &s, 400);
    let c = compare_rgba8(&inline_image, &threaded_image).unwrap();
    assert!(c.psnr_db >= 45.0, "inline vs threads: {c:?}");
    assert!(covered_pixels(&inline_image) > 128 * 128 / 20);
}
