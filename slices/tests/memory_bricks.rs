//! The browser's built-in sample has no store: its slice views feed the assembler from the
//! render crate's in-memory octree (`BrickedVolume`). That works only if the in-memory octree
//! is bricked exactly as a store is (levels, brick grid, apron, 2×2×2 means), which these
//! tests check against a store the importer wrote from the same voxels.

use std::sync::Arc;

use strata_render::{BrickSource, BrickedVolume};
use strata_slices::{SliceAssembler, SliceFrame, SliceRequest, SliceView, SLICE_CACHE_BYTES};
use strata_storage::phantom::{phantom_value_mapping, Phantom};
use strata_storage::Store;
use strata_types::{BrickId, OctreeLayout};

/// 80 voxels: three levels (80, 40, 20), 3×3×3 bricks at level 0 with a partial last one.
const EDGE: u64 = 80;

fn phantom_pair() -> (tempfile::TempDir, Store, BrickedVolume) {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("p.strata");
    let phantom = Phantom::cube(EDGE);
    phantom
        .write_store(&path, &Default::default())
        .expect("phantom store");
    let store = Store::open(&path).expect("open");
    let volume = BrickedVolume::from_fn(
        phantom.geometry(),
        phantom_value_mapping().mapping,
        |i, j, k| (phantom.hu(i as u64, j as u64, k as u64) as i32 + 1024) as u16,
    )
    .expect("in-memory octree");
    (dir, store, volume)
}

#[test]
fn in_memory_bricks_equal_the_stores_bricks_at_every_level() {
    let (_dir, store, volume) = phantom_pair();
    let layout = OctreeLayout::new(volume.geometry.dims);
    assert_eq!(
        &layout,
        store.layout(),
        "the page builds the store's layout"
    );
    assert_eq!(volume.level_count() as usize, layout.level_count());
    let mut compared = 0;
    for level in 0..layout.level_count() {
        assert_eq!(
            volume.level_dims(level as u8),
            Some(layout.level_dims[level])
        );
        let [bx, by, bz] = layout.bricks_in_level(level);
        for coords in
            (0..bz).flat_map(|z| (0..by).flat_map(move |y| (0..bx).map(move |x| [x, y, z])))
        {
            let id = BrickId::new(level as u8, coords);
            let stored = store.read_brick(id).expect("stored brick");
            let in_memory = volume.brick(id.level, id.coords).expect("in-memory brick");
            assert!(stored == in_memory, "brick {id:?} differs");
            compared += 1;
        }
    }
    assert_eq!(compared, 27 + 8 + 1);
}

#[test]
fn the_assembler_slices_in_memory_bricks_as_it_slices_the_store() {
    let (_dir, store, volume) = phantom_pair();
    let layout = OctreeLayout::new(volume.geometry.dims);
    let mut from_memory = SliceAssembler::new(layout, SLICE_CACHE_BYTES);
    let mut from_store = SliceAssembler::new(store.layout().clone(), SLICE_CACHE_BYTES);
    for (view, position, level) in [
        (SliceView::Axial, 37.0, 0),
        (SliceView::Coronal, 41.0, 1),
        (SliceView::Sagittal, 12.6, 0),
    ] {
        let request = SliceRequest {
            view,
            frame: SliceFrame::for_view(view, &volume.geometry),
            position,
            level,
        };
        // The page's way: start, then offer what the assembler lists as missing.
        from_memory.start(request).expect("start");
        for id in from_memory.missing() {
            let brick = volume.brick(id.level, id.coords).expect("in-memory brick");
            from_memory
                .offer(id, Arc::new(brick.to_vec()))
                .expect("offer");
        }
        let image = from_memory.take_finished(view).expect("slice complete");
        let reference = from_store
            .assemble_with(request, |id| {
                Ok::<_, strata_slices::SliceError>(store.read_brick(id).expect("stored brick"))
            })
            .expect("store's slice");
        assert_eq!(
            (image.width, image.height),
            (reference.width, reference.height)
        );
        assert!(image.values == reference.values, "{view:?} differs");
    }
}
