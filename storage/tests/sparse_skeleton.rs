//! The sparse skeleton on disk: new imports write it (feature `sparse-skeleton`), stores with
//! the dense skeleton of earlier builds still open with the same nodes, and the sparse
//! generator's store opens small, verifies, and holds the analytic field and the pyramid rule.

use std::collections::HashMap;
use std::path::Path;
use std::time::Duration;

use crate::common;
use strata_storage::import::ImportOptions;
use strata_storage::octree::average8;
use strata_storage::phantom::Phantom;
use strata_storage::sparse_phantom::{SparsePhantom, AIR};
use strata_storage::store::{NodeInfo, FEATURE_SPARSE_SKELETON};
use strata_storage::{BrickCodec, Store};
use strata_types::{BrickId, OctreeLayout, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};

/// Every node's answer, in layout order.
fn all_nodes(store: &Store) -> Vec<(BrickId, NodeInfo)> {
    common::all_brick_ids(store)
        .into_iter()
        .map(|id| (id, store.node(id).unwrap()))
        .collect()
}

/// Rewrites a closed store's metadata as a build before the sparse skeleton wrote it: the
/// dense skeleton encoding and no `sparse-skeleton` feature.
fn make_dense_like_an_older_build(path: &Path, dense_skeleton: Vec<u8>) {
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    let db = loop {
        match sled::open(path.join("db")) {
            Ok(db) => break db,
            // sled lets go of its file lock a moment after the last handle drops.
            Err(_) if std::time::Instant::now() < deadline => {
                std::thread::sleep(Duration::from_millis(20))
            }
            Err(e) => panic!("{e}"),
        }
    };
    let meta = db.open_tree("meta").unwrap();
    let mut header: serde_json::Value =
        serde_json::from_slice(&meta.get("header").unwrap().unwrap()).unwrap();
    let features = header["required_features"].as_array_mut().unwrap();
    features.retain(|f| f != FEATURE_SPARSE_SKELETON);
    meta.insert("header", serde_json::to_vec(&header).unwrap())
        .unwrap();
    meta.insert("skeleton", dense_skeleton).unwrap();
    db.flush().unwrap();
}

#[test]
fn imports_write_the_sparse_skeleton_and_dense_skeleton_stores_still_open_with_the_same_nodes() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("p.strata");
    let options = ImportOptions {
        codec: BrickCodec::Fast,
        ..Default::default()
    };
    // Format 2: the older build's dense skeleton is written into its sled metadata below.
    Phantom::cube(100)
        .write_store_as_format(&path, &options, 2)
        .unwrap();
    let (nodes, dense_bytes, skeleton) = {
        let store = Store::open(&path).unwrap();
        assert!(store
            .header()
            .required_features
            .iter()
            .any(|f| f == FEATURE_SPARSE_SKELETON));
        assert!(store.verify(|_, _| {}).unwrap().is_empty());
        (
            all_nodes(&store),
            store.skeleton().encode_dense(),
            store.skeleton().clone(),
        )
    };
    make_dense_like_an_older_build(&path, dense_bytes);
    let store = Store::open(&path).unwrap();
    assert!(!store
        .header()
        .required_features
        .iter()
        .any(|f| f == FEATURE_SPARSE_SKELETON));
    assert_eq!(store.skeleton(), &skeleton);
    assert_eq!(all_nodes(&store), nodes);
    assert!(store.verify(|_, _| {}).unwrap().is_empty());
}

#[test]
fn a_format_1_store_keeps_the_dense_skeleton() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("old.strata");
    let options = ImportOptions {
        codec: BrickCodec::Lz4,
        ..Default::default()
    };
    Phantom::cube(40).write_store(&path, &options).unwrap();
    let store = Store::open(&path).unwrap();
    assert_eq!(store.header().format_version, 1);
    assert!(store.header().required_features.is_empty());
    assert!(store.verify(|_, _| {}).unwrap().is_empty());
}

/// Level-L voxel `p` (clamped into the level) read through the store's bricks.
fn stored_voxel(
    store: &Store,
    cache: &mut HashMap<BrickId, Vec<u16>>,
    level: u8,
    p: [u64; 3],
) -> u16 {
    let dims = store.layout().level_dims[level as usize];
    let p = [0, 1, 2].map(|a| p[a].min(u64::from(dims[a]) - 1));
    let id = BrickId::new(level, p.map(|c| (c / u64::from(BRICK_CORE)) as u32));
    let brick = cache
        .entry(id)
        .or_insert_with(|| store.read_brick(id).unwrap());
    let o = p.map(|c| (c % u64::from(BRICK_CORE) + u64::from(BRICK_APRON)) as usize);
    let n = BRICK_PAYLOAD as usize;
    brick[(o[2] * n + o[1]) * n + o[0]]
}

/// Payload voxel `o` of brick `id` in level coordinates (apron clamped to the level).
fn payload_coords(layout: &OctreeLayout, id: BrickId, o: [u64; 3]) -> [u64; 3] {
    let dims = layout.level_dims[id.level as usize];
    [0, 1, 2].map(|a| {
        (u64::from(id.coords[a]) * u64::from(BRICK_CORE) + o[a])
            .saturating_sub(u64::from(BRICK_APRON))
            .min(u64::from(dims[a]) - 1)
    })
}

#[test]
fn the_sparse_phantom_opens_small_verifies_and_holds_the_field_and_the_pyramid_rule() {
    // 1024³: about a thousand level-0 bricks near the structures are computed (seconds in a
    // debug build); 8192³ and 16384³ are `strata sample --sparse`'s benchmark sizes.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sparse.strata");
    let phantom = SparsePhantom::new(1024);
    let report = phantom.write_store(&path, BrickCodec::Fast, None).unwrap();
    let store = Store::open(&path).unwrap();
    let layout = store.layout().clone();
    assert_eq!(layout.level_dims[0], [1024, 1024, 1024]);
    let skeleton = store.skeleton();
    let total = layout.total_bricks();
    let written: u64 = report.written_per_level.iter().sum();
    // Mostly air: well under a tenth of the nodes hold anything.
    assert!(
        written > 100 && written * 10 < total,
        "{written} of {total}"
    );
    // Skeleton at open: every stored node is a varying one, a listed constant, or a sibling
    // of one, so it keeps at most 8 × the computed nodes (+1 root); it encodes to a small
    // fraction of the dense encoding (5 bytes per node).
    let computed: u64 = report.computed_per_level.iter().sum();
    assert!(skeleton.stored_nodes() as u64 <= 8 * computed + 1);
    let sparse_bytes = skeleton.encode().len();
    let dense_bytes = skeleton.encode_dense().len();
    assert_eq!(sparse_bytes as u64, report.skeleton_bytes);
    assert!(
        sparse_bytes * 4 < dense_bytes,
        "sparse {sparse_bytes} B, dense {dense_bytes} B"
    );
    assert!(
        skeleton.memory_bytes() < 1 << 20,
        "{}",
        skeleton.memory_bytes()
    );

    let problems = store.verify(|_, _| {}).unwrap();
    assert!(problems.is_empty(), "{problems:?}");

    // A close-up level-0 brick: every voxel is the field's value rule.
    let varying: Vec<BrickId> = skeleton
        .stored_in_level_iter(0)
        .filter(|(_, n)| !n.is_constant())
        .map(|(id, _)| id)
        .collect();
    assert!(!varying.is_empty());
    let close_up = varying[varying.len() / 2];
    let voxels = store.read_brick(close_up).unwrap();
    let n = u64::from(BRICK_PAYLOAD);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let p = payload_coords(&layout, close_up, [x, y, z]);
                assert_eq!(
                    voxels[((z * n + y) * n + x) as usize],
                    phantom.value(p),
                    "{close_up:?} voxel {p:?}"
                );
            }
        }
    }
    // An implied air brick reads as air.
    let corner = BrickId::new(0, [0, 0, 0]);
    assert!(!skeleton.is_stored(corner) || store.node(corner) == Some(NodeInfo::constant(AIR)));
    assert!(store.read_brick(corner).unwrap().iter().all(|&v| v == AIR));

    // Levels agree: one varying brick per coarser level is the rounded mean of its 8 finer
    // voxels (read from the store), the odd-edge and apron rules included.
    let mut cache = HashMap::new();
    for level in 1..layout.level_count() as u8 {
        let Some((id, _)) = skeleton
            .stored_in_level_iter(level as usize)
            .find(|(_, n)| !n.is_constant())
        else {
            continue;
        };
        let voxels = store.read_brick(id).unwrap();
        let finer = layout.level_dims[level as usize - 1].map(u64::from);
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let j = payload_coords(&layout, id, [x, y, z]);
                    let mut sum = 0u32;
                    for dz in 0..2 {
                        for dy in 0..2 {
                            for dx in 0..2 {
                                let f = [0, 1, 2]
                                    .map(|a| (2 * j[a] + [dx, dy, dz][a]).min(finer[a] - 1));
                                sum += u32::from(stored_voxel(&store, &mut cache, level - 1, f));
                            }
                        }
                    }
                    assert_eq!(
                        voxels[((z * n + y) * n + x) as usize],
                        average8(sum),
                        "{id:?} voxel {j:?}"
                    );
                }
            }
        }
    }
}

#[test]
fn a_damaged_brick_of_a_sparse_store_is_found_by_verify() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sparse.strata");
    SparsePhantom::new(200)
        .write_store(&path, BrickCodec::Fast, None)
        .unwrap();
    let victim = {
        let store = Store::open(&path).unwrap();
        assert!(store.verify(|_, _| {}).unwrap().is_empty());
        let victim = store
            .skeleton()
            .stored_in_level_iter(0)
            .find(|(_, n)| !n.is_constant())
            .unwrap()
            .0;
        victim
    };
    Store::corrupt_brick_for_tests(&path, victim, 20).unwrap();
    let store = Store::open(&path).unwrap();
    let problems = store.verify(|_, _| {}).unwrap();
    assert_eq!(problems.len(), 1, "{problems:?}");
    assert!(
        problems[0].contains(&format!("{:?}", victim.coords)) && problems[0].contains("checksum"),
        "{problems:?}"
    );
}
