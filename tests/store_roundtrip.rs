//! The store holds exactly the octree the format promises: level 0 equal to the source, coarser
//! levels equal to the rounded 2×2×2 averages, aprons equal to the neighbouring (or replicated
//! edge) voxels; and it refuses to be read when damaged or unfinished.

use strata_e2e::{check_store_against, phantom_level0};
use strata_storage::import::{import_slices, ImportOptions, SliceProducer, VolumeMeta};
use strata_storage::phantom::Phantom;
use strata_storage::{StorageError, Store};
use strata_types::BrickId;

#[test]
fn phantom_round_trips_with_odd_sizes() {
    let dir = tempfile::tempdir().unwrap();
    // Odd and non-multiple-of-32 sizes on every axis exercise the clamped averaging and aprons.
    let p = Phantom { size: [75, 41, 67] };
    let path = dir.path().join("odd.strata");
    let report = p.write_store(&path, &ImportOptions::default()).unwrap();
    assert_eq!(
        report.header.layout.level_dims,
        vec![[75, 41, 67], [38, 21, 34], [19, 11, 17]]
    );
    let store = Store::open(&path).unwrap();
    check_store_against(&store, phantom_level0(&p));
    assert_eq!(store.histogram().total(), 75 * 41 * 67);
    assert!(store.verify(|_, _| {}).unwrap().is_empty());
}

/// Values covering the full u16 range, including constant regions (constant bricks).
struct Pattern {
    dims: [u64; 3],
}
impl Pattern {
    fn value(&self, i: u64, j: u64, k: u64) -> u16 {
        if k >= 40 {
            return 1234; // constant slab → constant bricks
        }
        (((i * 2654435761) ^ (j * 40503) ^ (k * 977)) % 65536) as u16
    }
}
impl SliceProducer for Pattern {
    fn dims(&self) -> [u64; 3] {
        self.dims
    }
    fn stored_slice(&self, k: u64, out: &mut [u16]) -> strata_storage::Result<()> {
        for (n, v) in out.iter_mut().enumerate() {
            *v = self.value(n as u64 % self.dims[0], n as u64 / self.dims[0], k);
        }
        Ok(())
    }
    fn source_bytes_per_slice(&self) -> u64 {
        self.dims[0] * self.dims[1] * 2
    }
}

#[test]
fn full_range_pattern_and_constant_bricks_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let src = Pattern {
        dims: [33, 64, 130],
    };
    let mut meta: VolumeMeta = Phantom { size: src.dims }.meta();
    meta.description = "pattern".into();
    let path = dir.path().join("pattern.strata");
    import_slices(&src, meta, &path, &ImportOptions::default()).unwrap();
    let store = Store::open(&path).unwrap();
    let mut all = Vec::new();
    let mut slice = vec![0u16; 33 * 64];
    for k in 0..130 {
        src.stored_slice(k, &mut slice).unwrap();
        all.extend_from_slice(&slice);
    }
    check_store_against(&store, all);
    let constant: u64 = store.stats().bricks_per_level.iter().map(|l| l.1).sum();
    assert!(constant > 0, "constant slab should give constant bricks");
}

#[test]
fn tiny_volumes_round_trip() {
    for dims in [[1, 1, 1], [1, 1, 50], [2, 3, 1], [40, 1, 1]] {
        let dir = tempfile::tempdir().unwrap();
        let p = Phantom { size: dims };
        let path = dir.path().join("tiny.strata");
        p.write_store(&path, &ImportOptions::default()).unwrap();
        let store = Store::open(&path).unwrap();
        check_store_against(&store, phantom_level0(&p));
    }
}

#[test]
fn flipped_byte_is_reported_by_read_and_verify() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.strata");
    Phantom::cube(64)
        .write_store(&path, &ImportOptions::default())
        .unwrap();
    let victim = BrickId::new(0, [1, 0, 1]);
    Store::corrupt_brick_for_tests(&path, victim, 40).unwrap();
    let store = Store::open(&path).unwrap();
    let err = store.read_brick(victim).unwrap_err();
    assert!(matches!(err, StorageError::Corrupted { .. }), "{err}");
    assert!(err.to_string().contains("checksum"), "{err}");
    assert!(err.to_string().contains("c.strata"), "{err}");
    let problems = store.verify(|_, _| {}).unwrap();
    assert_eq!(problems.len(), 1, "{problems:?}");
    // Other bricks still read.
    store.read_brick(BrickId::new(0, [0, 0, 0])).unwrap();
}

#[test]
fn reimport_starts_clean_and_foreign_dirs_are_left_alone() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.strata");
    Phantom::cube(48)
        .write_store(&path, &ImportOptions::default())
        .unwrap();
    Phantom { size: [20, 20, 20] }
        .write_store(&path, &ImportOptions::default())
        .unwrap();
    assert_eq!(
        Store::open(&path).unwrap().header().geometry.dims,
        [20, 20, 20]
    );

    let foreign = dir.path().join("photos");
    std::fs::create_dir(&foreign).unwrap();
    std::fs::write(foreign.join("holiday.jpg"), b"precious").unwrap();
    let err = Phantom::cube(8)
        .write_store(&foreign, &ImportOptions::default())
        .unwrap_err();
    assert!(err.to_string().contains("refusing to overwrite"), "{err}");
    assert_eq!(
        std::fs::read(foreign.join("holiday.jpg")).unwrap(),
        b"precious"
    );

    let err = Store::open(&dir.path().join("missing")).err().unwrap();
    assert!(err.to_string().contains("does not exist"), "{err}");
    let err = Store::open(&foreign).err().unwrap();
    assert!(err.to_string().contains("not a Strata store"), "{err}");
}

#[test]
fn cancelled_import_leaves_nothing_behind() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cancel.strata");
    let cancel = std::sync::atomic::AtomicBool::new(false);
    let progress = |p: strata_storage::import::ImportProgress| {
        if p.source_bytes_done * 2 > p.source_bytes_total {
            cancel.store(true, std::sync::atomic::Ordering::Relaxed);
        }
    };
    let options = ImportOptions {
        cancel: Some(&cancel),
        progress: Some(&progress),
        ..Default::default()
    };
    let err = Phantom::cube(96).write_store(&path, &options).unwrap_err();
    assert!(matches!(err, StorageError::Cancelled { .. }), "{err}");
    // The writer removes what it wrote: nothing that could be taken for a store is left.
    assert!(!path.exists(), "a cancelled import left {}", path.display());
    Phantom::cube(40)
        .write_store(&path, &ImportOptions::default())
        .unwrap();
    Store::open(&path).unwrap();
}

#[test]
fn memory_budget_too_small_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let options = ImportOptions {
        memory_budget_bytes: 8 << 20,
        ..Default::default()
    };
    let err = Phantom::cube(512)
        .write_store(&dir.path().join("b.strata"), &options)
        .unwrap_err();
    assert!(err.to_string().contains("memory budget"), "{err}");
}
