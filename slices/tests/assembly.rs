//! Slices assembled from a real store (the storage crate's phantom, written with its importer)
//! against values read independently: the phantom's own voxels at level 0, the 2×2×2 means of
//! those at level 1 (how the importer makes a coarser level), and bricks given in any order.

use std::sync::Arc;

use strata_slices::{SliceAssembler, SliceError, SliceFrame, SliceRequest, SliceView, VoxelLookup};
use strata_storage::phantom::Phantom;
use strata_storage::Store;
use strata_types::{BrickId, BRICK_PAYLOAD_VOXELS};

/// The phantom's edge: 80 voxels gives three levels (80, 40, 20) and 3×3 / 2×2 bricks a slice.
const EDGE: u64 = 80;

struct Fixture {
    _dir: tempfile::TempDir,
    store: Store,
    phantom: Phantom,
}

fn fixture() -> Fixture {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("p.strata");
    let phantom = Phantom::cube(EDGE);
    phantom
        .write_store(&path, &Default::default())
        .expect("phantom store");
    let store = Store::open(&path).expect("open");
    Fixture {
        _dir: dir,
        store,
        phantom,
    }
}

/// The phantom's stored value (HU + 1024) at level 0.
fn stored(phantom: &Phantom, i: [u64; 3]) -> u16 {
    (phantom.hu(i[0], i[1], i[2]) as i32 + 1024) as u16
}

fn request(fixture: &Fixture, view: SliceView, position: f64, level: u8) -> SliceRequest {
    SliceRequest {
        view,
        frame: SliceFrame::for_view(view, &fixture.store.header().geometry),
        position,
        level,
    }
}

fn read(store: &Store, id: BrickId) -> Result<Vec<u16>, SliceError> {
    // The fixture's store is intact: a failed read is a test failure.
    Ok(store.read_brick(id).expect("brick"))
}

#[test]
fn level_zero_slices_equal_the_phantom_voxels() {
    let f = fixture();
    let mut assembler = SliceAssembler::new(f.store.layout().clone(), 8 << 20);
    for (view, position) in [
        (SliceView::Axial, 37.0),
        (SliceView::Coronal, 70.2),
        (SliceView::Sagittal, 5.0),
    ] {
        let r = request(&f, view, position, 0);
        let image = assembler
            .assemble_with(r, |id| read(&f.store, id))
            .expect("slice");
        let frame = r.frame;
        assert_eq!((image.width, image.height), (EDGE as usize, EDGE as usize));
        assert_eq!(image.inside_fraction, (1.0, 1.0));
        let slice = position.round() as u64;
        let mut differing = 0;
        for y in 0..EDGE {
            for x in 0..EDGE {
                let mut index = [0u64; 3];
                index[frame.normal_axis] = slice;
                index[frame.across_axis] = x;
                index[frame.down_axis] = y;
                if image.values[(y * EDGE + x) as usize] != stored(&f.phantom, index) {
                    differing += 1;
                }
            }
        }
        assert_eq!(differing, 0, "{view:?}: voxels differing from the phantom");
    }
    // The probe reads the same values through the cache.
    let index = [33u32, 35, 38];
    let value = assembler
        .voxel_with(index, |id| read(&f.store, id))
        .expect("voxel");
    assert_eq!(value, stored(&f.phantom, index.map(u64::from)));
}

#[test]
fn coarser_slices_equal_the_means_of_level_zero() {
    let f = fixture();
    let mut assembler = SliceAssembler::new(f.store.layout().clone(), 8 << 20);
    // Level 1 (40³): its voxel k is centred at level-0 index 2k + 0.5; position 41.0 is
    // level-1 slice round(41.5/2 - 0.5) = 20.
    let r = request(&f, SliceView::Coronal, 41.0, 1);
    let image = assembler
        .assemble_with(r, |id| read(&f.store, id))
        .expect("slice");
    let half = (EDGE / 2) as usize;
    assert_eq!((image.width, image.height), (half, half));
    let frame = r.frame;
    let mut worst = 0u16;
    for y in 0..half as u64 {
        for x in 0..half as u64 {
            let mut sum = 0u32;
            for corner in 0..8u64 {
                let mut index = [0u64; 3];
                index[frame.normal_axis] = 2 * 20 + (corner & 1);
                index[frame.across_axis] = 2 * x + ((corner >> 1) & 1);
                index[frame.down_axis] = 2 * y + ((corner >> 2) & 1);
                sum += u32::from(stored(&f.phantom, index));
            }
            // Rounded mean, halves up (storage's average8).
            let mean = ((sum + 4) / 8) as u16;
            worst = worst.max(image.values[(y * half as u64 + x) as usize].abs_diff(mean));
        }
    }
    assert_eq!(worst, 0, "largest difference from the 2×2×2 means");
    // A level past the coarsest is read at the coarsest.
    let top = (f.store.layout().level_count() - 1) as u8;
    let image = assembler
        .assemble_with(request(&f, SliceView::Axial, 40.0, 9), |id| {
            read(&f.store, id)
        })
        .expect("slice");
    assert_eq!(
        image.width,
        f.store.layout().level_dims[top as usize][0] as usize
    );
}

#[test]
fn missing_bricks_are_listed_and_the_slice_completes_in_any_order() {
    let f = fixture();
    let layout = f.store.layout().clone();
    let r = request(&f, SliceView::Sagittal, 50.0, 0);
    let reference = SliceAssembler::new(layout.clone(), 8 << 20)
        .assemble_with(r, |id| read(&f.store, id))
        .expect("reference");

    let mut assembler = SliceAssembler::new(layout, 8 << 20);
    assembler.start(r).expect("start");
    let missing = assembler.missing();
    // 80 voxels: 3 bricks across and down, one brick deep (x = 50 lies in brick 1).
    assert_eq!(missing.len(), 9);
    assert!(missing.iter().all(|id| id.level == 0 && id.coords[0] == 1));
    // Most useful first: the middle brick.
    assert_eq!(missing[0], BrickId::new(0, [1, 1, 1]));
    assert_eq!(assembler.pending(SliceView::Sagittal), Some(r));
    // Given from the last to the first, with a brick nobody asked for in between.
    for (n, id) in missing.iter().rev().enumerate() {
        assert!(assembler.take_finished(SliceView::Sagittal).is_none());
        assembler
            .offer(*id, Arc::new(f.store.read_brick(*id).expect("brick")))
            .expect("offer");
        if n == 3 {
            let stray = BrickId::new(1, [0, 0, 0]);
            assembler
                .offer(stray, Arc::new(f.store.read_brick(stray).expect("brick")))
                .expect("offer");
        }
        assert_eq!(assembler.missing().len(), missing.len() - n - 1);
    }
    let image = assembler
        .take_finished(SliceView::Sagittal)
        .expect("complete once every brick arrived");
    assert_eq!(image.values, reference.values);
    assert!(
        assembler.take_finished(SliceView::Sagittal).is_none(),
        "taken once"
    );
    // The next slice of the same brick row needs nothing: it finishes from the cache at once.
    assembler
        .start(request(&f, SliceView::Sagittal, 51.0, 0))
        .expect("start");
    assert!(assembler.missing().is_empty());
    assert!(assembler.take_finished(SliceView::Sagittal).is_some());
    // The probe of a cached brick needs nothing either; an uncached one names its brick.
    assert!(matches!(
        assembler.voxel([50, 1, 1]),
        Ok(VoxelLookup::Value(_))
    ));
    assert_eq!(
        assembler.voxel([5, 1, 1]),
        Ok(VoxelLookup::Needs(BrickId::new(0, [0, 0, 0])))
    );
}

#[test]
fn three_views_share_bricks_and_a_small_cache_still_completes_large_slices() {
    let f = fixture();
    // A cache of the minimum 8 bricks, under the 9 a level-0 slice needs: the slice still
    // completes (bricks are copied in as they arrive), and the cache stays within its bound.
    let mut assembler = SliceAssembler::new(f.store.layout().clone(), BRICK_PAYLOAD_VOXELS * 2);
    for view in SliceView::ALL {
        assembler.start(request(&f, view, 40.0, 0)).expect("start");
    }
    let missing = assembler.missing();
    // Each id once, though the three slices cross at the middle bricks.
    let mut unique = missing.clone();
    unique.sort();
    unique.dedup();
    assert_eq!(unique.len(), missing.len());
    assert_eq!(assembler.most_useful_missing(4), missing[..4]);
    assert!(missing.len() < 27);
    for id in &missing {
        assembler
            .offer(*id, Arc::new(f.store.read_brick(*id).expect("brick")))
            .expect("offer");
        assert!(assembler.cache().bytes() <= assembler.cache().budget_bytes());
    }
    for view in SliceView::ALL {
        let image = assembler.take_finished(view).expect("complete");
        let reference = SliceAssembler::new(f.store.layout().clone(), 8 << 20)
            .assemble_with(request(&f, view, 40.0, 0), |id| read(&f.store, id))
            .expect("reference");
        assert_eq!(image.values, reference.values, "{view:?}");
    }
}
