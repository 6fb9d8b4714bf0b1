//! The streaming loader with the octree traversal (issue 18): the cut selected off the frame
//! thread feeds the octree's node buffer (built from the cut's leaves), MIP bounds per leaf,
//! visibility feedback read back per leaf; the flat table refused past a size limit with the
//! reason, and the octree chosen instead when the configuration left the traversal open.
//!
//! Image tolerance: none. The two traversals take the same samples in the same order
//! (render/tests/octree_traversal.rs), so over the same cut the images are byte-identical.
//! Visibility feedback is off where images are compared: the octree reads it back per leaf,
//! and a visible coarse leaf marks all its page cells (the flat table marks only the cells
//! that contributed), so with feedback on the two may refine different occluded nodes.

use crate::common;

use common::*;
use strata_loader::StreamingConfig;
use strata_render::{RenderMode, Traversal};

fn converged_with(
    store: &std::sync::Arc<strata_storage::Store>,
    traversal: Traversal,
    mode: RenderMode,
    visibility_feedback: bool,
) -> (Vec<u8>, strata_render::PageTable, u64) {
    let ctx = gpu();
    let tf = bone();
    let s = strata_render::RenderSettings {
        mode,
        ..settings(128)
    };
    let camera = orbit(store, 30.0, 20.0, 1.4);
    let config = StreamingConfig {
        max_voxel_pixels: 0.5,
        traversal: Some(traversal),
        visibility_feedback,
        ..config()
    };
    let mut volume = stream(&ctx, store, &tf, config);
    assert_eq!(volume.traversal(), traversal);
    assert!(volume.traversal_note().is_none(), "the traversal was given");
    let (image, history) = converge(&ctx, &mut volume, &camera, &s, 300);
    let last = history.last().unwrap();
    assert!(
        last.data_leaves_per_level[0] > 0,
        "{traversal:?} {mode:?}: level 0 never loaded: {last:#?}"
    );
    volume.check_slot_map().unwrap();
    (
        image,
        volume.page_table().to_page_table(),
        volume.gpu_index_bytes(),
    )
}

#[test]
fn streamed_octree_renders_equal_the_flat_table_after_both_converge() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 128));
    for mode in [RenderMode::Dvr, RenderMode::Mip] {
        let (flat, flat_cut, flat_bytes) = converged_with(&store, Traversal::Flat, mode, false);
        let (octree, octree_cut, octree_bytes) =
            converged_with(&store, Traversal::Octree, mode, false);
        assert_eq!(
            flat_cut, octree_cut,
            "{mode:?}: the same inputs select the same cut"
        );
        assert!(
            covered_pixels(&flat) > 128 * 128 / 20,
            "{mode:?}: image nearly empty"
        );
        let differing = flat.iter().zip(&octree).filter(|(a, b)| a != b).count();
        assert_eq!(
            differing, 0,
            "{mode:?}: octree image differs from the flat one"
        );
        eprintln!("{mode:?}: GPU index bytes flat {flat_bytes}, octree {octree_bytes}");
    }
}

/// With visibility feedback on (the default), the octree's per-leaf feedback lets the loader
/// converge too. Its image is compared with the flat table's, also with feedback on: the two
/// may leave different occluded nodes coarser (a visible coarse leaf marks all its cells),
/// which rays reach only after opacity ≥ 0.99, so PSNR ≥ 45 dB bounds the difference (the
/// tolerance of streaming.rs's streamed-vs-up-front test, for the same reason).
#[test]
fn the_octree_converges_with_per_leaf_visibility_feedback() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 128));
    let (octree, _, octree_bytes) =
        converged_with(&store, Traversal::Octree, RenderMode::Dvr, true);
    let (flat, _, flat_bytes) = converged_with(&store, Traversal::Flat, RenderMode::Dvr, true);
    assert!(
        covered_pixels(&octree) > 128 * 128 / 20,
        "image nearly empty"
    );
    let c = strata_render::compare_rgba8(&octree, &flat).unwrap();
    eprintln!("feedback on: {c:?}; GPU index bytes flat {flat_bytes}, octree {octree_bytes}");
    assert!(c.psnr_db >= 45.0, "octree vs flat with feedback: {c:?}");
}

#[test]
fn the_flat_table_is_refused_past_its_limit_and_the_octree_chosen_when_left_open() {
    let dir = tempfile::tempdir().unwrap();
    // 64³ voxels: 2×2×2 page cells, 8 bytes each in the largest flat binding = 64 bytes.
    let store = open(&phantom_store(dir.path(), 64));
    let ctx = gpu();
    let tf = bone();
    let limited = |traversal| StreamingConfig {
        traversal,
        flat_table_limit_bytes: Some(32),
        ..config()
    };
    let refused = match strata_loader::StreamingVolume::new(
        &ctx,
        store.clone(),
        &tf,
        limited(Some(Traversal::Flat)),
    ) {
        Ok(_) => panic!("the flat table was not refused past its limit"),
        Err(e) => e.to_string(),
    };
    for needle in [
        "8 page cells",
        "160 bytes",
        "32 bytes",
        "configured flat-table limit",
        "--traversal octree",
    ] {
        assert!(refused.contains(needle), "{needle:?} not in {refused:?}");
    }
    // Left open: the octree, and a note saying why.
    let mut volume = stream(&ctx, &store, &tf, limited(None));
    assert_eq!(volume.traversal(), Traversal::Octree);
    let note = volume
        .traversal_note()
        .expect("a note on the automatic choice");
    assert!(
        note.contains("octree traversal chosen") && note.contains("8 page cells"),
        "{note}"
    );
    let s = settings(64);
    let camera = orbit(&store, 30.0, 20.0, 1.4);
    let (image, _) = converge(&ctx, &mut volume, &camera, &s, 200);
    assert!(covered_pixels(&image) > 0);
    // At the limit the flat table fits, and an open choice stays flat without a note.
    let fits = stream(
        &ctx,
        &store,
        &tf,
        StreamingConfig {
            flat_table_limit_bytes: Some(64),
            ..config()
        },
    );
    assert_eq!(fits.traversal(), Traversal::Flat);
    assert!(fits.traversal_note().is_none());
    // Where it fits but has more page cells than the flat table is chosen for, an open choice
    // takes the octree too, and says why; a given flat traversal is still built.
    let many_cells = |traversal| StreamingConfig {
        traversal,
        flat_table_max_page_cells: 7,
        ..config()
    };
    let octree = stream(&ctx, &store, &tf, many_cells(None));
    assert_eq!(octree.traversal(), Traversal::Octree);
    let note = octree
        .traversal_note()
        .expect("a note on the automatic choice");
    assert!(
        note.contains("8 page cells exceed 7") && note.contains("--traversal flat"),
        "{note}"
    );
    let forced = stream(&ctx, &store, &tf, many_cells(Some(Traversal::Flat)));
    assert_eq!(forced.traversal(), Traversal::Flat);
}
