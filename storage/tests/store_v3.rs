//! Store format 3 (issue 48): brick records in pack files behind a read-only index. A v3 store
//! reads every brick as the v2 store of the same source does; opening writes nothing (a
//! read-only folder too); damage to packs or the index is an error naming the store, the file
//! and the brick, never a panic; several readers at once.

use std::path::{Path, PathBuf};

use crate::common;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::{StorageError, Store};
use strata_types::BrickId;

fn v3_and_v2(dir: &Path, size: u64) -> (PathBuf, PathBuf) {
    let v3 = dir.join("v3.strata");
    let v2 = dir.join("v2.strata");
    let phantom = Phantom::cube(size);
    phantom.write_store(&v3, &ImportOptions::default()).unwrap();
    phantom
        .write_store_as_format(&v2, &ImportOptions::default(), 2)
        .unwrap();
    (v3, v2)
}

fn all_ids(store: &Store) -> Vec<BrickId> {
    common::all_brick_ids(store)
}

/// Every file under `dir` with its size, mtime and content.
fn snapshot(dir: &Path) -> Vec<(PathBuf, u64, std::time::SystemTime, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let meta = e.metadata().unwrap();
            if meta.is_dir() {
                stack.push(e.path());
            } else {
                out.push((
                    e.path(),
                    meta.len(),
                    meta.modified().unwrap(),
                    std::fs::read(e.path()).unwrap(),
                ));
            }
        }
    }
    out.sort();
    out
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let target = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), &target).unwrap();
        }
    }
}

fn set_read_only(dir: &Path, read_only: bool) {
    use std::os::unix::fs::PermissionsExt;
    let mut paths = vec![dir.to_path_buf()];
    let mut i = 0;
    while i < paths.len() {
        if paths[i].is_dir() {
            for e in std::fs::read_dir(&paths[i]).unwrap().flatten() {
                paths.push(e.path());
            }
        }
        i += 1;
    }
    // Deepest first when locking (a folder stays listable), shallowest first when unlocking.
    if read_only {
        paths.reverse();
    }
    for p in paths {
        let mode = match (p.is_dir(), read_only) {
            (true, true) => 0o555,
            (true, false) => 0o755,
            (false, true) => 0o444,
            (false, false) => 0o644,
        };
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(mode)).unwrap();
    }
}

fn pack(store: &Path) -> PathBuf {
    store.join("packs").join("pack-00000.pack")
}

#[test]
fn v3_reads_every_brick_as_v2_and_verifies() {
    let dir = tempfile::tempdir().unwrap();
    let (v3, v2) = v3_and_v2(dir.path(), 96);
    assert!(v3.join("index.v3").is_file() && pack(&v3).is_file());
    assert!(!v3.join("db").exists(), "a v3 store has no sled database");
    let a = Store::open(&v3).unwrap();
    let b = Store::open(&v2).unwrap();
    assert_eq!(a.format_version(), 3);
    assert_eq!(b.format_version(), 2);
    assert_eq!(a.skeleton(), b.skeleton());
    assert_eq!(a.stats().compressed_bytes, b.stats().compressed_bytes);
    let ids = all_ids(&a);
    assert!(ids.len() > 30, "{}", ids.len());
    for &id in &ids {
        assert_eq!(
            a.read_brick_record(id).unwrap(),
            b.read_brick_record(id).unwrap(),
            "{id:?}"
        );
        assert_eq!(
            a.read_brick(id).unwrap(),
            b.read_brick(id).unwrap(),
            "{id:?}"
        );
        assert_eq!(
            a.stored_brick_bytes(id).unwrap(),
            b.stored_brick_bytes(id).unwrap()
        );
    }
    let report = a.verify_report(|_, _| {}).unwrap();
    assert!(report.problems.is_empty(), "{:?}", report.problems);
    assert!(report.records_read > 0);
}

#[test]
fn opening_a_v3_store_writes_nothing_and_works_read_only() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("p.strata");
    Phantom::cube(64)
        .write_store(&store, &ImportOptions::default())
        .unwrap();
    let before = snapshot(&store);
    {
        let s = Store::open(&store).unwrap();
        for id in all_ids(&s) {
            s.read_brick(id).unwrap();
        }
        assert!(s.verify(|_, _| {}).unwrap().is_empty());
        s.close().unwrap();
    }
    assert_eq!(snapshot(&store), before, "opening changed a file");
    // A read-only folder (files and folders without write permission).
    set_read_only(&store, true);
    let opened = Store::open(&store).and_then(|s| s.verify(|_, _| {}));
    set_read_only(&store, false);
    assert!(opened.unwrap().is_empty());
    assert_eq!(snapshot(&store), before, "opening changed a file");
    // Without a lock file (a store copied to read-only media without it): read without a lock.
    std::fs::remove_file(store.join("strata.lock")).unwrap();
    set_read_only(&store, true);
    let without_lock = Store::open(&store).and_then(|s| s.read_brick(BrickId::new(0, [0, 0, 0])));
    set_read_only(&store, false);
    without_lock.unwrap();
    assert!(
        !store.join("strata.lock").exists(),
        "a reader created the lock file"
    );
}

#[test]
fn several_readers_at_once_and_a_writer_is_refused_while_they_read() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("p.strata");
    let phantom = Phantom::cube(48);
    phantom
        .write_store(&store, &ImportOptions::default())
        .unwrap();
    let readers: Vec<Store> = (0..4).map(|_| Store::open(&store).unwrap()).collect();
    std::thread::scope(|s| {
        for r in &readers {
            s.spawn(move || {
                for id in all_ids(r) {
                    r.read_brick(id).unwrap();
                }
            });
        }
    });
    match phantom.write_store(&store, &ImportOptions::default()) {
        Err(StorageError::InUse { .. }) => {}
        other => panic!("an import over a store being read: {:?}", other.map(|_| ())),
    }
    drop(readers);
    assert!(Store::open(&store).is_ok());
}

/// Opens a damaged copy and verifies it: the error or the problems, as text.
fn outcome(store: &Path) -> String {
    match Store::open(store) {
        Err(e) => format!("open: {e}"),
        Ok(s) => match s.verify(|_, _| {}) {
            Err(e) => format!("verify: {e}"),
            Ok(p) => format!("verify: {}", p.join("\n")),
        },
    }
}

#[test]
fn damage_to_packs_and_index_is_an_error_naming_the_file_and_brick() {
    let dir = tempfile::tempdir().unwrap();
    let pristine = dir.path().join("pristine.strata");
    Phantom::cube(64)
        .write_store(&pristine, &ImportOptions::default())
        .unwrap();
    let case = |name: &str, damage: &dyn Fn(&Path)| -> String {
        let copy = dir.path().join(name);
        copy_dir(&pristine, &copy);
        damage(&copy);
        let out = outcome(&copy);
        assert!(
            out.contains(&copy.display().to_string()),
            "{name}: does not name the store: {out}"
        );
        out
    };
    let pack_len = std::fs::metadata(pack(&pristine)).unwrap().len();

    // A flipped byte in the middle of the pack: verify names the brick and the pack.
    let out = case("flipped", &|s| {
        let p = pack(s);
        let mut bytes = std::fs::read(&p).unwrap();
        let at = bytes.len() / 2;
        bytes[at] ^= 0x40;
        std::fs::write(&p, bytes).unwrap();
    });
    assert!(
        out.contains("pack-00000.pack") && out.contains("brick level"),
        "{out}"
    );

    // Damage through the test hook: reading that brick fails naming it.
    let copy = dir.path().join("hooked");
    copy_dir(&pristine, &copy);
    let id = BrickId::new(0, [0, 0, 0]);
    Store::corrupt_brick_for_tests(&copy, id, 20).unwrap();
    let e = Store::open(&copy)
        .unwrap()
        .read_brick(id)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("brick level 0 at [0, 0, 0]") && e.contains("pack-00000.pack"),
        "{e}"
    );

    // A pack shorter than the index says: refused at open, naming the pack.
    let out = case("short", &|s| {
        let f = std::fs::OpenOptions::new()
            .write(true)
            .open(pack(s))
            .unwrap();
        f.set_len(pack_len - 100).unwrap();
    });
    assert!(
        out.starts_with("open:") && out.contains("pack-00000.pack") && out.contains("cut short"),
        "{out}"
    );

    // The pack missing.
    let out = case("missing", &|s| std::fs::remove_file(pack(s)).unwrap());
    assert!(
        out.starts_with("open:") && out.contains("pack-00000.pack"),
        "{out}"
    );

    // A pack replaced by a folder, and by a FIFO (never blocks).
    let out = case("folder", &|s| {
        std::fs::remove_file(pack(s)).unwrap();
        std::fs::create_dir(pack(s)).unwrap();
    });
    assert!(
        out.starts_with("open:") && out.contains("pack-00000.pack"),
        "{out}"
    );
    let out = case("fifo", &|s| {
        std::fs::remove_file(pack(s)).unwrap();
        let c = std::ffi::CString::new(pack(s).to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
    });
    assert!(
        out.starts_with("open:") && out.contains("pack-00000.pack"),
        "{out}"
    );

    // The index damaged anywhere: its checksum.
    let out = case("index", &|s| {
        let p = s.join("index.v3");
        let mut bytes = std::fs::read(&p).unwrap();
        let at = bytes.len() - 20;
        bytes[at] ^= 1;
        std::fs::write(&p, bytes).unwrap();
    });
    assert!(
        out.contains("index.v3") && out.contains("checksum"),
        "{out}"
    );

    // An index entry pointing outside its pack (a consistent index, rewritten with its checksum).
    let out = case("outside", &|s| {
        let p = s.join("index.v3");
        let mut bytes = std::fs::read(&p).unwrap();
        let body = bytes.len() - 8;
        // The last entry's offset: 4 + 13 + 4 bytes into the last 33-byte entry.
        let off = body - 33 + 21;
        bytes[off..off + 8].copy_from_slice(&(pack_len * 2).to_le_bytes());
        let sum = xxhash_rust::xxh3::xxh3_64(&bytes[..body]);
        bytes[body..].copy_from_slice(&sum.to_le_bytes());
        std::fs::write(&p, bytes).unwrap();
    });
    assert!(
        out.starts_with("open:") && out.contains("brick level") && out.contains("pack-00000.pack"),
        "{out}"
    );

    // The index truncated, and missing.
    let out = case("index-short", &|s| {
        let p = s.join("index.v3");
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
    });
    assert!(
        out.starts_with("open:") && out.contains("index.v3"),
        "{out}"
    );

    // An incomplete store (the marker's last line never written): refused as incomplete.
    let out = case("incomplete", &|s| {
        std::fs::write(s.join("STRATA-STORE"), "strata store format 3\n").unwrap();
    });
    assert!(out.contains("incomplete import"), "{out}");
    assert!(Store::open(&pristine).is_ok());
}

#[test]
fn upgrade_of_a_v2_store_equals_a_fresh_v3_import_record_for_record() {
    let dir = tempfile::tempdir().unwrap();
    let (v3, v2) = v3_and_v2(dir.path(), 80);
    let report = strata_storage::store::upgrade_store(&v2).unwrap();
    assert!(report.problems.is_empty() && report.records_read > 0);
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names.len(), 2, "upgrade left {names:?}");
    let upgraded = Store::open(&v2).unwrap();
    let fresh = Store::open(&v3).unwrap();
    assert_eq!(upgraded.format_version(), 3);
    assert_eq!(upgraded.skeleton(), fresh.skeleton());
    assert_eq!(upgraded.header().layout, fresh.header().layout);
    assert_eq!(upgraded.header().codec, fresh.header().codec);
    for id in all_ids(&fresh) {
        assert_eq!(
            upgraded.read_brick_record(id).unwrap(),
            fresh.read_brick_record(id).unwrap(),
            "{id:?}"
        );
    }
    // A format-3 store is not upgraded again.
    drop(upgraded);
    assert!(strata_storage::store::upgrade_store(&v2).is_err());
}

/// Item 7: a later version of a brick record is appended (new pack, new index renamed in) and
/// readers that open afterwards see it, one that opened before keeps its old versions; a second
/// writer is refused; `compact_store` drops the superseded records (smaller packs, same bricks,
/// verifies) and leaves no staged or parked folder behind.
#[test]
fn appended_versions_are_read_and_compaction_drops_the_superseded() {
    use strata_storage::brick::{decode_brick, encode_brick, value_range, BrickCodec};
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("e.strata");
    Phantom::cube(64)
        .write_store(&store, &ImportOptions::default())
        .unwrap();
    let before = Store::open(&store).unwrap();
    let ids = all_ids(&before);
    let originals: Vec<Vec<u8>> = ids
        .iter()
        .map(|&id| before.read_brick_record(id).unwrap())
        .collect();
    // New versions: the same voxels under another codec (so the skeleton's ranges hold), twice
    // for the first brick (the later one wins).
    let reencode = |id: BrickId, codec: BrickCodec| {
        let voxels = before.read_brick(id).unwrap();
        encode_brick(id, &voxels, value_range(&voxels), false, codec)
    };
    let varying: Vec<usize> = (0..ids.len())
        .filter(|&i| {
            let v = decode_brick(ids[i], &originals[i]).unwrap();
            let r = value_range(&v);
            r.min != r.max
        })
        .take(6)
        .collect();
    assert!(varying.len() >= 2, "the phantom has varying bricks");
    let mut edits: Vec<(BrickId, Vec<u8>)> = varying
        .iter()
        .map(|&i| (ids[i], reencode(ids[i], BrickCodec::Lz4)))
        .collect();
    edits.push((
        ids[varying[0]],
        reencode(ids[varying[0]], BrickCodec::Dense),
    ));
    for (id, record) in &edits {
        assert_ne!(
            &before.read_brick_record(*id).unwrap(),
            record,
            "a new version differs in bytes"
        );
    }
    strata_storage::store::append_brick_versions(&store, &edits).unwrap();
    // A second round appends again: three generations of the first brick now on disk.
    let last = (
        ids[varying[1]],
        reencode(ids[varying[1]], BrickCodec::Dense),
    );
    strata_storage::store::append_brick_versions(&store, std::slice::from_ref(&last)).unwrap();
    let packs_dir = store.join("packs");
    assert_eq!(std::fs::read_dir(&packs_dir).unwrap().count(), 3);

    // The reader that opened before still reads its versions (its maps stay valid).
    for (i, &id) in ids.iter().enumerate() {
        assert_eq!(before.read_brick_record(id).unwrap(), originals[i]);
    }
    let newest = |id: BrickId| -> Vec<u8> {
        if id == last.0 {
            return last.1.clone();
        }
        match edits.iter().rev().find(|(e, _)| *e == id) {
            Some((_, r)) => r.clone(),
            None => originals[ids.iter().position(|&x| x == id).unwrap()].clone(),
        }
    };
    let after = Store::open(&store).unwrap();
    for (i, &id) in ids.iter().enumerate() {
        assert_eq!(after.read_brick_record(id).unwrap(), newest(id));
        assert_eq!(
            after.read_brick(id).unwrap(),
            before.read_brick(id).unwrap(),
            "brick {i}: same voxels"
        );
    }
    assert!(after.verify(|_, _| {}).unwrap().is_empty());
    drop(before);
    drop(after);

    // Writers exclude each other; a record that is not one is refused.
    {
        let _held = std::fs::File::open(store.join("strata.write.lock")).unwrap();
        _held.try_lock().unwrap();
        match strata_storage::store::append_brick_versions(&store, &edits) {
            Err(StorageError::InUse { .. }) => {}
            other => panic!("a second writer: {:?}", other.map(|_| ())),
        }
    }
    let mut garbled = edits[0].1.clone();
    let n = garbled.len();
    garbled[n - 1] ^= 0xff;
    assert!(
        strata_storage::store::append_brick_versions(&store, &[(edits[0].0, garbled)]).is_err()
    );

    // A killed append's leftover pack (no index names it) is ignored by readers and removed by
    // the next writer.
    std::fs::write(packs_dir.join("pack-00003.pack"), b"torn tail").unwrap();
    assert!(Store::open(&store)
        .unwrap()
        .verify(|_, _| {})
        .unwrap()
        .is_empty());

    let total = |d: &Path| -> u64 {
        std::fs::read_dir(d.join("packs"))
            .unwrap()
            .flatten()
            .map(|e| e.metadata().unwrap().len())
            .sum()
    };
    let size_before = total(&store);
    let report = strata_storage::store::compact_store(&store).unwrap();
    assert_eq!(report.records as usize, ids.len());
    assert!(report.bytes_after < report.bytes_before);
    assert!(total(&store) < size_before, "smaller packs");
    assert_eq!(std::fs::read_dir(&packs_dir).unwrap().count(), 1);
    let compacted = Store::open(&store).unwrap();
    for &id in &ids {
        assert_eq!(compacted.read_brick_record(id).unwrap(), newest(id));
    }
    assert!(compacted.verify(|_, _| {}).unwrap().is_empty());
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .flatten()
        .map(|e| e.file_name())
        .collect();
    assert_eq!(names, vec![std::ffi::OsString::from("e.strata")]);
    // Compaction needs the store free of readers for its swap, and leaves it as it was if not.
    match strata_storage::store::compact_store(&store) {
        Err(StorageError::InUse { .. }) => {}
        other => panic!("compaction under a reader: {:?}", other.map(|_| ())),
    }
    for &id in &ids {
        assert_eq!(compacted.read_brick_record(id).unwrap(), newest(id));
    }
    drop(compacted);
    assert!(Store::open(&store)
        .unwrap()
        .verify(|_, _| {})
        .unwrap()
        .is_empty());
}

/// `verify` at its default depth streams the packs and checks each record's checksum and place
/// without decoding: a sound store passes with every record read; damaged records are each
/// reported by brick and pack, as the deep check (`--decode`) reports them. A record whose
/// checksum holds but whose voxels disagree with the skeleton is found only by decoding: the
/// depths differ in what they decode, not in what they read.
#[test]
fn a_checksum_verify_streams_every_record_and_names_each_damaged_brick() {
    use strata_storage::brick::{encode_brick, value_range, BrickCodec};
    use strata_storage::store::VerifyDepth;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("c.strata");
    Phantom::cube(96)
        .write_store(&store, &ImportOptions::default())
        .unwrap();
    let opened = Store::open(&store).unwrap();
    let entries = all_ids(&opened).len() as u64;
    let varying: Vec<BrickId> = all_ids(&opened)
        .into_iter()
        .filter(|&id| {
            let r = value_range(&opened.read_brick(id).unwrap());
            r.min != r.max
        })
        .collect();
    assert!(varying.len() >= 3, "the phantom has varying bricks");
    for depth in [VerifyDepth::Checksums, VerifyDepth::Decode] {
        let report = opened.verify_report_to(depth, |_, _| {}).unwrap();
        assert!(
            report.problems.is_empty(),
            "{depth:?}: {:?}",
            report.problems
        );
        assert_eq!(report.records_read, entries, "{depth:?}");
        assert_eq!(report.intact, entries, "{depth:?}");
    }
    drop(opened);

    // Two damaged records: each named, with its pack.
    let damaged = [varying[0], varying[2]];
    for id in damaged {
        Store::corrupt_brick_for_tests(&store, id, 20).unwrap();
    }
    let opened = Store::open(&store).unwrap();
    for depth in [VerifyDepth::Checksums, VerifyDepth::Decode] {
        let report = opened.verify_report_to(depth, |_, _| {}).unwrap();
        assert_eq!(report.problems.len(), 2, "{depth:?}: {:?}", report.problems);
        for (problem, id) in report.problems.iter().zip(damaged) {
            let named = format!("brick level {} at {:?}", id.level, id.coords);
            assert!(
                problem.contains(&named)
                    && problem.contains("pack-00000.pack")
                    && problem.contains("checksum mismatch"),
                "{depth:?}: {problem} should name {named}"
            );
        }
        assert_eq!(report.intact, entries - 2, "{depth:?}");
        assert!(report.verdict.is_some(), "{depth:?}");
    }
    drop(opened);

    // A sound record (its checksum holds) whose voxels leave the skeleton's range, put in place
    // of its brick's record with the same length: only decoding shows the disagreement.
    let reader = Store::open(&store).unwrap();
    let id = varying[1];
    let old = reader.read_brick_record(id).unwrap();
    let voxels = reader.read_brick(id).unwrap();
    let above = reader.node(id).unwrap().max + 1;
    drop(reader);
    let forged = (0..voxels.len())
        .step_by(31)
        .find_map(|at| {
            let mut changed = voxels.clone();
            changed[at] = above;
            let record = encode_brick(
                id,
                &changed,
                value_range(&changed),
                false,
                BrickCodec::default(),
            );
            (record.len() == old.len()).then_some(record)
        })
        .expect("a one-voxel change that compresses to the same length");
    let pack_path = pack(&store);
    let mut bytes = std::fs::read(&pack_path).unwrap();
    let at = bytes
        .windows(old.len())
        .position(|w| w == old.as_slice())
        .unwrap();
    bytes[at..at + old.len()].copy_from_slice(&forged);
    std::fs::write(&pack_path, &bytes).unwrap();
    let opened = Store::open(&store).unwrap();
    let shallow = opened
        .verify_report_to(VerifyDepth::Checksums, |_, _| {})
        .unwrap();
    let deep = opened
        .verify_report_to(VerifyDepth::Decode, |_, _| {})
        .unwrap();
    assert_eq!(shallow.problems.len(), 2, "{:?}", shallow.problems);
    assert_eq!(deep.problems.len(), 3, "{:?}", deep.problems);
    assert!(
        deep.problems.iter().any(|p| p
            .contains(&format!("brick level {} at {:?}", id.level, id.coords))
            && p.contains("differs from the skeleton's")),
        "{:?}",
        deep.problems
    );
}

/// A new version of a brick with new values (a bright spot painted into empty space, as a
/// label edit would) updates the skeleton: the brick's node takes its range, every ancestor's
/// range widens to include it, so culling by range cannot hide the edit; the index gives the
/// record version 2, then 3, and compaction keeps the versions, the ranges and a store that
/// verifies at both depths. A store whose skeleton may imply bricks is refused.
#[test]
fn an_appended_brick_with_new_values_widens_its_own_and_its_ancestors_ranges() {
    use strata_storage::brick::{encode_brick, value_range, BrickCodec};
    use strata_storage::store::{append_brick_versions, compact_store, VerifyDepth};
    use strata_types::BRICK_PAYLOAD_VOXELS;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("edit.strata");
    Phantom::cube(96)
        .write_store(&store, &ImportOptions::default())
        .unwrap();
    let before = Store::open(&store).unwrap();
    let levels = before.layout().level_count();
    assert!(levels >= 3, "a brick with at least two ancestors");
    // A level-0 brick in the phantom's empty corner whose ancestors are all below the paint.
    let id = BrickId::new(0, [0, 0, 0]);
    let ancestors: Vec<BrickId> = (1..levels)
        .map(|l| BrickId::new(l as u8, [0, 0, 0]))
        .collect();
    let paint = ancestors
        .iter()
        .map(|&a| before.node(a).unwrap().max)
        .max()
        .unwrap()
        + 1000;
    assert_eq!(before.brick_version(id), Some(1));
    let mut voxels = before.read_brick(id).unwrap();
    assert_eq!(voxels.len(), BRICK_PAYLOAD_VOXELS);
    for v in voxels.iter_mut().take(500) {
        *v = paint;
    }
    let range = value_range(&voxels);
    assert_eq!(range.max, paint);
    let record = encode_brick(id, &voxels, range, false, BrickCodec::Lz4);
    let ancestors_before: Vec<_> = ancestors.iter().map(|&a| before.node(a).unwrap()).collect();
    let sibling = BrickId::new(0, [1, 0, 0]);
    let sibling_before = before.node(sibling);
    drop(before);
    append_brick_versions(&store, &[(id, record.clone())]).unwrap();

    let check = |path: &Path, version: u32| {
        let after = Store::open(path).unwrap();
        assert_eq!(after.brick_version(id), Some(version));
        let edited = after.node(id).unwrap();
        assert_eq!((edited.min, edited.max), (range.min, paint));
        assert!(!edited.is_constant());
        for (&a, was) in ancestors.iter().zip(&ancestors_before) {
            let n = after.node(a).unwrap();
            assert!(
                n.min <= range.min && n.max == paint && !n.is_constant(),
                "ancestor {a:?}: {n:?} (was {was:?}) must bound the edit"
            );
            assert_eq!(
                after.brick_version(a),
                Some(1),
                "its record is the import's"
            );
        }
        // Bricks off the edited path keep their ranges.
        assert_eq!(after.node(sibling), sibling_before);
        assert_eq!(after.read_brick(id).unwrap(), voxels);
        for depth in [VerifyDepth::Checksums, VerifyDepth::Decode] {
            let report = after.verify_report_to(depth, |_, _| {}).unwrap();
            assert!(
                report.problems.is_empty(),
                "{depth:?}: {:?}",
                report.problems
            );
        }
    };
    check(&store, 2);
    append_brick_versions(&store, &[(id, record)]).unwrap();
    check(&store, 3);
    compact_store(&store).unwrap();
    check(&store, 3);

    // In a sparse skeleton, painting a brick inside a constant subtree makes its implied
    // parent vary, and that parent has no record: refused, naming both, until a record of the
    // parent comes with it; then both verify and read back.
    let sparse = dir.path().join("sparse.strata");
    strata_storage::sparse_phantom::SparsePhantom::new(256)
        .write_store(&sparse, BrickCodec::Fast, None)
        .unwrap();
    let opened = Store::open(&sparse).unwrap();
    let (id, parent) = all_ids(&opened)
        .into_iter()
        .filter(|id| id.level == 0)
        .map(|id| (id, BrickId::new(1, id.coords.map(|c| c / 2))))
        .find(|(id, parent)| {
            !opened.skeleton().is_stored(*id) && opened.brick_version(*parent).is_none()
        })
        .expect("a level-0 brick in an implied constant subtree");
    // The ancestors without a record of their own (the parent, and maybe more above it).
    let recordless: Vec<BrickId> = (1..opened.layout().level_count())
        .map(|l| BrickId::new(l as u8, id.coords.map(|c| c >> l)))
        .filter(|a| opened.brick_version(*a).is_none())
        .collect();
    assert_eq!(recordless.first(), Some(&parent));
    let mut painted = opened.read_brick(id).unwrap();
    drop(opened);
    for v in painted.iter_mut().take(500) {
        *v = 60000;
    }
    let record_of =
        |b: BrickId| encode_brick(b, &painted, value_range(&painted), false, BrickCodec::Fast);
    match append_brick_versions(&sparse, &[(id, record_of(id))]) {
        Err(e) => assert!(
            e.to_string().contains("has no record")
                && e.to_string()
                    .contains(&format!("level 1 at {:?}", parent.coords)),
            "{e}"
        ),
        Ok(()) => panic!("an edit that makes an implied node vary was accepted"),
    }
    let mut edit = vec![(id, record_of(id))];
    edit.extend(recordless.iter().map(|&a| (a, record_of(a))));
    append_brick_versions(&sparse, &edit).unwrap();
    let edited = Store::open(&sparse).unwrap();
    assert_eq!(edited.brick_version(id), Some(2));
    assert_eq!(edited.brick_version(parent), Some(2));
    assert_eq!(edited.read_brick(id).unwrap(), painted);
    assert_eq!(edited.node(id).unwrap().max, 60000);
    assert_eq!(edited.node(parent).unwrap().max, 60000);
    for depth in [VerifyDepth::Checksums, VerifyDepth::Decode] {
        let report = edited.verify_report_to(depth, |_, _| {}).unwrap();
        assert!(
            report.problems.is_empty(),
            "{depth:?}: {:?}",
            report.problems
        );
    }
}

/// The histogram built from every level-0 voxel `store` holds now (cores cut at the volume's
/// far faces), as an import builds it.
fn histogram_of_the_stored_voxels(store: &Store) -> strata_storage::histogram::Histogram {
    use strata_storage::histogram::{Histogram, StoredValueCounts};
    use strata_types::{BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};
    let layout = store.layout();
    let dims = layout.level_dims[0];
    let n = layout.bricks_in_level(0);
    let (p, a) = (BRICK_PAYLOAD as usize, BRICK_APRON as usize);
    let mut counts = StoredValueCounts::default();
    for z in 0..n[2] {
        for y in 0..n[1] {
            for x in 0..n[0] {
                let voxels = store.read_brick(BrickId::new(0, [x, y, z])).unwrap();
                let extent = [x, y, z].map(|c| c * BRICK_CORE);
                let extent: Vec<usize> = (0..3)
                    .map(|i| (dims[i] - extent[i]).min(BRICK_CORE) as usize)
                    .collect();
                for k in 0..extent[2] {
                    for j in 0..extent[1] {
                        for i in 0..extent[0] {
                            counts.add_slice(&[voxels[(i + a) + p * ((j + a) + p * (k + a))]]);
                        }
                    }
                }
            }
        }
    }
    let m = &store.header().value_mapping.mapping;
    Histogram::from_stored(&counts, m.slope, m.intercept)
}

/// Issue 48, item 7: after new versions of level-0 bricks the store's histogram is the one
/// built from the voxels it now holds (an edit inside the value range: exactly; one past it:
/// the range widened to the new extreme, every voxel still counted once) and each edited
/// brick's node carries its record's range; a compaction keeps both.
#[test]
fn the_histogram_and_skeleton_after_an_edit_are_those_of_the_voxels_now_stored() {
    use strata_storage::brick::{encode_brick, value_range, BrickCodec};
    use strata_storage::store::{append_brick_versions, compact_store};
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("h.strata");
    // 80 = 2 × 32 + 16: the far bricks are cut by the volume's faces.
    Phantom::cube(80)
        .write_store(&store, &ImportOptions::default())
        .unwrap();
    let before = Store::open(&store).unwrap();
    let imported = histogram_of_the_stored_voxels(&before);
    assert_eq!(before.histogram(), &imported, "as imported");
    // The far corner brick takes the centre brick's voxels: values the volume holds elsewhere.
    let corner = BrickId::new(0, [2, 2, 2]);
    let centre = before.read_brick(BrickId::new(0, [1, 1, 1])).unwrap();
    assert_ne!(before.read_brick(corner).unwrap(), centre);
    let range = value_range(&centre);
    let record = encode_brick(corner, &centre, range, false, BrickCodec::Fast);
    drop(before);
    append_brick_versions(&store, &[(corner, record)]).unwrap();
    let after = Store::open(&store).unwrap();
    let rebuilt = histogram_of_the_stored_voxels(&after);
    assert_eq!(
        (rebuilt.physical_min, rebuilt.physical_max),
        (imported.physical_min, imported.physical_max),
        "the edit keeps the volume's extremes (else pick another brick)"
    );
    assert_ne!(rebuilt, imported, "the edit moved voxels between bins");
    assert_eq!(after.histogram(), &rebuilt);
    let node = after.node(corner).unwrap();
    assert_eq!((node.min, node.max), (range.min, range.max));
    drop(after);

    // Past the range: the same brick painted above the volume's maximum.
    let paint = range.max.max(imported_max_stored(&store)) + 500;
    let painted = vec![paint; centre.len()];
    let record = encode_brick(
        corner,
        &painted,
        value_range(&painted),
        false,
        BrickCodec::Fast,
    );
    append_brick_versions(&store, &[(corner, record)]).unwrap();
    compact_store(&store).unwrap();
    let after = Store::open(&store).unwrap();
    let h = after.histogram();
    let mapping = &after.header().value_mapping;
    assert_eq!(h.total(), imported.total(), "every voxel counted once");
    assert_eq!(h.physical_max, mapping.physical(paint));
    assert_eq!(h.physical_min, imported.physical_min);
    // The corner's 16³ voxels inside the volume, all at the new maximum.
    assert!(
        *h.counts.last().unwrap() >= 16 * 16 * 16,
        "{:?}",
        h.counts.last()
    );
    let node = after.node(corner).unwrap();
    assert_eq!((node.min, node.max), (paint, paint));
    assert!(after.verify(|_, _| {}).unwrap().is_empty());
}

/// The largest stored value of level 0 in `store` (its root's range covers them all).
fn imported_max_stored(store: &Path) -> u16 {
    let s = Store::open(store).unwrap();
    let root = BrickId::new((s.layout().level_count() - 1) as u8, [0, 0, 0]);
    s.node(root).unwrap().max
}

/// The "every reader test's scan imports to v3 and renders bit for bit as from v2": each
/// real scan of the reader tests (shared/data, skipped with a message when absent) imported as
/// format 3 and as format 2 gives the same skeleton, every brick record equal and every brick
/// decoding to the same voxels (so every renderer draws the same image from either); and the
/// format-2 store upgraded equals the fresh format-3 import record for record.
#[test]
fn every_shared_scan_imports_to_v3_as_to_v2_and_upgrades_record_for_record() {
    use strata_storage::import::import_source_as_format;
    use strata_storage::readers::{open_source, ReadOptions};
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/niivue");
    if !data.is_dir() {
        eprintln!(
            "SKIP: real test data not found at {} (see shared/data/SOURCES.md)",
            data.display()
        );
        return;
    }
    let scans = [
        "FLAIR.nrrd",
        "chris_t1.nii.gz",
        "mha.mha",
        "enh.dcm",
        "dicom-mr-3slices",
        "nifti_space/AIL.nii.gz",
        "nifti_space/IRP.nii.gz",
    ];
    let dir = tempfile::tempdir().unwrap();
    for (n, name) in scans.iter().enumerate() {
        let path = data.join(name);
        if !path.exists() {
            eprintln!("SKIP {name}: not in {}", data.display());
            continue;
        }
        let open = || open_source(&path, &ReadOptions::default()).unwrap();
        let v3 = dir.path().join(format!("{n}-v3.strata"));
        let v2 = dir.path().join(format!("{n}-v2.strata"));
        import_source_as_format(open(), &v3, &ImportOptions::default(), 3).unwrap();
        import_source_as_format(open(), &v2, &ImportOptions::default(), 2).unwrap();
        {
            let a = Store::open(&v3).unwrap();
            let b = Store::open(&v2).unwrap();
            assert_eq!((a.format_version(), b.format_version()), (3, 2), "{name}");
            assert_eq!(a.skeleton(), b.skeleton(), "{name}");
            assert_eq!(a.histogram(), b.histogram(), "{name}");
            for id in all_ids(&a) {
                assert_eq!(
                    a.read_brick_record(id).unwrap(),
                    b.read_brick_record(id).unwrap(),
                    "{name} {id:?}"
                );
                assert_eq!(
                    a.read_brick(id).unwrap(),
                    b.read_brick(id).unwrap(),
                    "{name} {id:?}"
                );
            }
        }
        let report = strata_storage::store::upgrade_store(&v2).unwrap();
        assert!(report.problems.is_empty(), "{name}: {:?}", report.problems);
        let upgraded = Store::open(&v2).unwrap();
        let fresh = Store::open(&v3).unwrap();
        assert_eq!(upgraded.format_version(), 3, "{name}");
        assert_eq!(upgraded.skeleton(), fresh.skeleton(), "{name}");
        for id in all_ids(&fresh) {
            assert_eq!(
                upgraded.read_brick_record(id).unwrap(),
                fresh.read_brick_record(id).unwrap(),
                "{name} {id:?}: upgraded against fresh"
            );
        }
    }
}
