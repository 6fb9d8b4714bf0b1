//! `strata render --traversal flat|octree`: the real binary renders a phantom store's fixed cut
//! through the flat page table and through the cut's octree (render/src/gpu/gpu_octree.rs), and
//! the PNGs are identical (render/tests/octree_traversal.rs shows why: same samples, same
//! words); streamed, both converge to the same PNG.

use crate::common;

use common::{render_level0, strata};
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;

#[test]
fn octree_and_flat_traversals_render_the_same_png() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("phantom.strata");
    Phantom::cube(96)
        .write_store(&store, &ImportOptions::default())
        .unwrap();
    for mode in [
        &["--mode", "dvr"][..],
        &["--mode", "mip"],
        &["--mode", "iso"],
    ] {
        let (flat, _) = render_level0(&store, &dir.path().join("flat.png"), mode);
        let octree_args: Vec<&str> = mode
            .iter()
            .copied()
            .chain(["--traversal", "octree"])
            .collect();
        let (octree, stderr) = render_level0(&store, &dir.path().join("octree.png"), &octree_args);
        assert!(stderr.contains("octree index:"), "{stderr}");
        assert!(
            flat.iter().any(|&v| v > 0),
            "{mode:?}: empty image proves nothing"
        );
        assert_eq!(flat, octree, "{mode:?}");
    }
}

/// Streamed (no --up-front): the loader converges with either traversal to the same PNG, and
/// says which traversal it used.
#[test]
fn streamed_octree_and_flat_renders_give_the_same_png() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("phantom.strata");
    Phantom::cube(96)
        .write_store(&store, &ImportOptions::default())
        .unwrap();
    for mode in ["dvr", "mip"] {
        let mut images = Vec::new();
        for traversal in ["flat", "octree"] {
            let out = dir.path().join(format!("{mode}-{traversal}.png"));
            let o = strata(&[
                "render",
                store.to_str().unwrap(),
                "--size",
                "96x96",
                "--mode",
                mode,
                "--no-jitter",
                "--traversal",
                traversal,
                "--out",
                out.to_str().unwrap(),
            ]);
            let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
            assert!(o.status.success(), "{mode} {traversal}: {stderr}");
            assert!(
                stderr.contains(&format!("{traversal} traversal:")),
                "{stderr}"
            );
            assert!(stderr.contains("converged"), "{stderr}");
            images.push(image::open(&out).unwrap().to_rgba8().into_raw());
        }
        assert!(images[0].iter().any(|&v| v > 0), "{mode}: empty image");
        assert!(images[0] == images[1], "{mode}: streamed octree differs");
    }
}
