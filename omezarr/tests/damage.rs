//! Damaged OME-Zarr exports (issue 38, findings 4-6): each kind of damage, made here from a
//! small export, is refused by import with its location and flagged while streaming (the
//! brick reported damaged, or the export refused at open); nothing panics, aborts or hangs
//! (each case runs on its own thread under a time limit); nothing reads silently wrong (every
//! brick streamed is either the undamaged one or reported damaged).

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use serde_json::Value;
use strata_omezarr::export::{export, ExportOptions};
use strata_omezarr::import::{import_zarr, ImportZarrOptions};
use strata_omezarr::streaming::OmeZarrSource;
use strata_omezarr::{ObjectLocation, ObjectStoreOptions};
use strata_source::{SourceError, VolumeSource};
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::Store;
use strata_types::BrickId;

/// Far above what a 64³ case takes on a loaded machine; a hang (a FIFO opened for reading
/// blocks forever) is far beyond it.
const CASE_LIMIT: Duration = Duration::from_secs(60);

fn folder(path: &Path) -> ObjectLocation {
    ObjectLocation::open(
        path.to_str().unwrap(),
        &ObjectStoreOptions::default(),
        false,
    )
    .unwrap()
}

/// A 64³ phantom store (2 levels, 8 + 1 bricks) and its export; the store's bricks.
struct Fixture {
    _work: tempfile::TempDir,
    zarr: PathBuf,
    bricks: Vec<(BrickId, Vec<u16>)>,
    size: [u64; 3],
}

fn fixture(size: [u64; 3]) -> Fixture {
    let work = tempfile::tempdir().unwrap();
    let store_path = work.path().join("p.strata");
    Phantom { size }
        .write_store(&store_path, &ImportOptions::default())
        .unwrap();
    let store = Store::open(&store_path).unwrap();
    let zarr = work.path().join("x.ome.zarr");
    let dest =
        ObjectLocation::open(zarr.to_str().unwrap(), &ObjectStoreOptions::default(), true).unwrap();
    export(&store, &dest, &ExportOptions::default(), &|_, _| {}).unwrap();
    let layout = store.layout().clone();
    let mut bricks = Vec::new();
    for level in 0..layout.level_count() {
        let n = layout.bricks_in_level(level);
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let id = BrickId::new(level as u8, [x, y, z]);
                    bricks.push((id, store.read_brick(id).unwrap()));
                }
            }
        }
    }
    Fixture {
        _work: work,
        zarr,
        bricks,
        size,
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

fn edit_json(path: &Path, edit: impl FnOnce(&mut Value)) {
    let mut doc: Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
    edit(&mut doc);
    std::fs::write(path, serde_json::to_vec_pretty(&doc).unwrap()).unwrap();
}

/// Entries of a shard's index (at its end, crc32c after it): (offset, length) each.
fn read_index(shard: &[u8], entries: usize) -> Vec<(u64, u64)> {
    let start = shard.len() - 4 - 16 * entries;
    shard[start..shard.len() - 4]
        .chunks_exact(16)
        .map(|e| {
            (
                u64::from_le_bytes(e[..8].try_into().unwrap()),
                u64::from_le_bytes(e[8..].try_into().unwrap()),
            )
        })
        .collect()
}

/// Rewrites a shard's index entries and recomputes its crc32c (so only the range checks can
/// tell).
fn write_index(path: &Path, edit: impl FnOnce(&mut Vec<(u64, u64)>)) {
    let mut shard = std::fs::read(path).unwrap();
    let entries = 8;
    let mut index = read_index(&shard, entries);
    edit(&mut index);
    let start = shard.len() - 4 - 16 * entries;
    let bytes: Vec<u8> = index
        .iter()
        .flat_map(|(o, l)| o.to_le_bytes().into_iter().chain(l.to_le_bytes()))
        .collect();
    shard[start..start + bytes.len()].copy_from_slice(&bytes);
    let crc = crc32c::crc32c(&bytes);
    let end = shard.len();
    shard[end - 4..].copy_from_slice(&crc.to_le_bytes());
    std::fs::write(path, shard).unwrap();
}

#[derive(Debug, PartialEq)]
enum Outcome {
    /// Refused or flagged, with the message.
    Clean(String),
    /// Passed with data that differs from the undamaged export (or passed when it must not).
    SilentWrong(String),
    Panic(String),
    Hang,
}

/// Runs `f` on its own thread within [`CASE_LIMIT`]; a panic or a timeout is an outcome.
fn guarded<F>(name: &str, f: F) -> Outcome
where
    F: FnOnce() -> Outcome + Send + 'static,
{
    let (tx, rx) = mpsc::channel();
    std::thread::Builder::new()
        .name(format!("damage-{name}"))
        .spawn(move || {
            let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
            let _ = tx.send(result);
        })
        .unwrap();
    match rx.recv_timeout(CASE_LIMIT) {
        Ok(Ok(outcome)) => outcome,
        Ok(Err(panic)) => Outcome::Panic(
            panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default(),
        ),
        Err(_) => Outcome::Hang,
    }
}

fn import_outcome(zarr: PathBuf) -> Outcome {
    let work = tempfile::tempdir().unwrap();
    let result = import_zarr(
        folder(&zarr),
        &work.path().join("back.strata"),
        &ImportZarrOptions::default(),
        &|_, _| {},
        &ImportOptions::default(),
    );
    match result {
        Ok(_) => Outcome::SilentWrong("import succeeded".into()),
        Err(e) => Outcome::Clean(e.to_string()),
    }
}

/// Streams every brick: each must be the undamaged one or reported damaged, and at least one
/// must be reported (or the export refused at open).
fn stream_outcome(zarr: PathBuf, bricks: Vec<(BrickId, Vec<u16>)>) -> Outcome {
    let source = match OmeZarrSource::open(folder(&zarr)) {
        Ok(source) => source,
        Err(e) => return Outcome::Clean(format!("refused at open: {e}")),
    };
    let mut flagged = Vec::new();
    for (id, expected) in &bricks {
        match source.read_brick(*id) {
            Ok(got) if &got == expected => {}
            Ok(_) => {
                return Outcome::SilentWrong(format!(
                    "brick level {} at {:?} streamed different data without a warning",
                    id.level, id.coords
                ))
            }
            Err(SourceError::Damaged { message, .. }) => flagged.push(message),
            Err(e) => flagged.push(format!("(not reported as damage) {e}")),
        }
    }
    match flagged.first() {
        None => Outcome::SilentWrong("every brick streamed as undamaged".into()),
        Some(m) if m.starts_with("(not reported") => Outcome::SilentWrong(m.clone()),
        Some(m) => Outcome::Clean(m.clone()),
    }
}

type Damage = Box<dyn Fn(&Path)>;

/// The kinds of damage, each applied to a fresh copy of the export; `import: false` where the
/// damage is to something import does not read (coarser levels), so only streaming must flag it.
fn damages() -> Vec<(&'static str, bool, Damage)> {
    let shard0 = |z: &Path| z.join("0/c/0/0/0");
    vec![
        (
            "level-0 shard deleted",
            true,
            Box::new(move |z: &Path| std::fs::remove_file(shard0(z)).unwrap()),
        ),
        (
            "every shard deleted",
            true,
            Box::new(|z: &Path| {
                for level in 0..2 {
                    std::fs::remove_dir_all(z.join(format!("{level}/c"))).unwrap();
                }
            }),
        ),
        (
            "level-0 shard replaced by an empty folder",
            true,
            Box::new(move |z: &Path| {
                std::fs::remove_file(shard0(z)).unwrap();
                std::fs::create_dir(shard0(z)).unwrap();
            }),
        ),
        (
            "index entry marked empty",
            true,
            Box::new(move |z: &Path| write_index(&shard0(z), |i| i[3] = (u64::MAX, u64::MAX))),
        ),
        (
            "index entry pointing at another chunk",
            true,
            Box::new(move |z: &Path| write_index(&shard0(z), |i| i[3] = i[5])),
        ),
        (
            "three bit flips in level-0 compressed data",
            true,
            Box::new(move |z: &Path| {
                let path = shard0(z);
                let mut shard = std::fs::read(&path).unwrap();
                let index = read_index(&shard, 8);
                // Inside chunk 3's data (past zstd's frame header).
                let (offset, length) = index[3];
                assert!(length > 64, "{index:?}");
                for k in 1..=3u64 {
                    let at = (offset + k * length / 4) as usize;
                    shard[at] ^= 0x10;
                }
                std::fs::write(&path, shard).unwrap();
            }),
        ),
        (
            "chunk_key_encoding changed to v2",
            true,
            Box::new(|z: &Path| {
                edit_json(
                    &z.join("0/zarr.json"),
                    |d| {
                        d["chunk_key_encoding"] =
                            serde_json::json!({"name": "v2", "configuration": {"separator": "."}})
                    },
                )
            }),
        ),
        (
            "index entry length 2^63 (checksum recomputed)",
            true,
            Box::new(move |z: &Path| write_index(&shard0(z), |i| i[0].1 = 1 << 63)),
        ),
        (
            "crc32c removed from the index codecs",
            true,
            Box::new(|z: &Path| {
                edit_json(&z.join("0/zarr.json"), |d| {
                    let codecs = d["codecs"][0]["configuration"]["index_codecs"]
                        .as_array_mut()
                        .unwrap();
                    codecs.retain(|c| c["name"] != "crc32c");
                })
            }),
        ),
        (
            "level-0 shard replaced by a FIFO",
            true,
            Box::new(move |z: &Path| {
                std::fs::remove_file(shard0(z)).unwrap();
                mkfifo(&shard0(z));
            }),
        ),
        (
            "level-1 shard deleted",
            false,
            Box::new(|z: &Path| std::fs::remove_file(z.join("1/c/0/0/0")).unwrap()),
        ),
        (
            "level-1 shard replaced by a FIFO",
            false,
            Box::new(|z: &Path| {
                std::fs::remove_file(z.join("1/c/0/0/0")).unwrap();
                mkfifo(&z.join("1/c/0/0/0"));
            }),
        ),
        (
            "level-1 index entry length 2^63 (checksum recomputed)",
            false,
            Box::new(|z: &Path| {
                // Level 1 of 64³ is one 32³ chunk: a shard of one entry.
                let path = z.join("1/c/0/0/0");
                let mut shard = std::fs::read(&path).unwrap();
                let start = shard.len() - 4 - 16;
                shard[start + 8..start + 16].copy_from_slice(&(1u64 << 63).to_le_bytes());
                let crc = crc32c::crc32c(&shard[start..start + 16]);
                let end = shard.len();
                shard[end - 4..].copy_from_slice(&crc.to_le_bytes());
                std::fs::write(&path, shard).unwrap();
            }),
        ),
        (
            "checksums object deleted",
            true,
            Box::new(|z: &Path| std::fs::remove_file(z.join("strata-checksums.bin")).unwrap()),
        ),
        (
            "dimensions changed in the strata attribute",
            true,
            Box::new(|z: &Path| {
                edit_json(&z.join("zarr.json"), |d| {
                    d["attributes"]["strata"]["header"]["geometry"]["dims"][0] = 63.into()
                })
            }),
        ),
        (
            "value_mapping.slope 0",
            true,
            Box::new(|z: &Path| {
                edit_json(&z.join("zarr.json"), |d| {
                    d["attributes"]["strata"]["header"]["value_mapping"]["slope"] = 0.0.into()
                })
            }),
        ),
        (
            "scale negative",
            true,
            Box::new(|z: &Path| set_scale(z, -1.0)),
        ),
        ("scale zero", true, Box::new(|z: &Path| set_scale(z, 0.0))),
        (
            "scale 1e308",
            true,
            Box::new(|z: &Path| set_scale(z, 1e308)),
        ),
        (
            "unknown required feature",
            true,
            Box::new(|z: &Path| {
                edit_json(&z.join("zarr.json"), |d| {
                    d["attributes"]["strata"]["header"]["required_features"] =
                        serde_json::json!(["teleportation"])
                })
            }),
        ),
        (
            "format_version 99",
            true,
            Box::new(|z: &Path| {
                edit_json(&z.join("zarr.json"), |d| {
                    d["attributes"]["strata"]["header"]["format_version"] = 99.into()
                })
            }),
        ),
        (
            "OME version 9.9",
            true,
            Box::new(|z: &Path| {
                edit_json(&z.join("zarr.json"), |d| {
                    d["attributes"]["ome"]["version"] = "9.9".into()
                })
            }),
        ),
        (
            "top-level zarr.json broken",
            true,
            Box::new(|z: &Path| {
                std::fs::write(z.join("zarr.json"), b"{\"zarr_format\": 3, \"node_t").unwrap()
            }),
        ),
    ]
}

fn set_scale(z: &Path, value: f64) {
    edit_json(&z.join("zarr.json"), |d| {
        d["attributes"]["ome"]["multiscales"][0]["datasets"][0]["coordinateTransformations"][0]
            ["scale"][1] = value.into()
    })
}

fn mkfifo(path: &Path) {
    let status = std::process::Command::new("mkfifo")
        .arg(path)
        .status()
        .expect("mkfifo");
    assert!(status.success());
}

#[derive(Default, Debug)]
struct Counts {
    clean: usize,
    silent: Vec<String>,
    panics: Vec<String>,
    hangs: Vec<String>,
}

impl Counts {
    fn add(&mut self, case: &str, outcome: Outcome) {
        match outcome {
            Outcome::Clean(_) => self.clean += 1,
            Outcome::SilentWrong(m) => self.silent.push(format!("{case}: {m}")),
            Outcome::Panic(m) => self.panics.push(format!("{case}: {m}")),
            Outcome::Hang => self.hangs.push(case.to_string()),
        }
    }
}

#[test]
fn each_damage_is_refused_on_import_and_flagged_while_streaming() {
    let fixture = fixture([64, 64, 64]);
    assert_eq!(fixture.size, [64, 64, 64]);
    // The undamaged export imports and streams as the store (the checks refuse nothing good).
    let control = guarded("control-stream", {
        let (zarr, bricks) = (fixture.zarr.clone(), fixture.bricks.clone());
        move || stream_outcome(zarr, bricks)
    });
    assert_eq!(
        control,
        Outcome::SilentWrong("every brick streamed as undamaged".into())
    );
    let control = guarded("control-import", {
        let zarr = fixture.zarr.clone();
        move || import_outcome(zarr)
    });
    assert_eq!(control, Outcome::SilentWrong("import succeeded".into()));

    let mut counts = Counts::default();
    let work = tempfile::tempdir().unwrap();
    for (n, (case, import_reads_it, damage)) in damages().into_iter().enumerate() {
        let zarr = work.path().join(format!("case{n}.ome.zarr"));
        copy_dir(&fixture.zarr, &zarr);
        damage(&zarr);
        if import_reads_it {
            let outcome = guarded(case, {
                let zarr = zarr.clone();
                move || import_outcome(zarr)
            });
            println!("import, {case}: {outcome:?}");
            counts.add(&format!("import, {case}"), outcome);
        }
        let outcome = guarded(case, {
            let (zarr, bricks) = (zarr.clone(), fixture.bricks.clone());
            move || stream_outcome(zarr, bricks)
        });
        println!("stream, {case}: {outcome:?}");
        counts.add(&format!("stream, {case}"), outcome);
    }
    println!(
        "damaged OME-Zarr: {} clean errors, {} silent wrong, {} panics, {} hangs",
        counts.clean,
        counts.silent.len(),
        counts.panics.len(),
        counts.hangs.len()
    );
    assert!(
        counts.silent.is_empty() && counts.panics.is_empty() && counts.hangs.is_empty(),
        "{counts:#?}"
    );
}

/// Finding 4 as it was reported: the process must not abort on a 2^63 index length, nor on an
/// index read without its crc32c; the error names the shard.
#[test]
fn damaged_shard_indices_are_refused_with_the_shard_named() {
    let fixture = fixture([64, 64, 64]);
    let work = tempfile::tempdir().unwrap();
    let cases: Vec<(&str, Damage)> = vec![
        (
            "length",
            Box::new(|z: &Path| write_index(&z.join("0/c/0/0/0"), |i| i[0].1 = 1 << 63)),
        ),
        (
            "no-crc",
            Box::new(|z: &Path| {
                edit_json(&z.join("0/zarr.json"), |d| {
                    d["codecs"][0]["configuration"]["index_codecs"]
                        .as_array_mut()
                        .unwrap()
                        .retain(|c| c["name"] != "crc32c");
                })
            }),
        ),
    ];
    for (name, damage) in cases {
        let zarr = work.path().join(name);
        copy_dir(&fixture.zarr, &zarr);
        damage(&zarr);
        let outcome = guarded(name, move || import_outcome(zarr));
        match outcome {
            Outcome::Clean(m) => assert!(
                m.contains("0/c/0/0/0") && m.contains("damaged"),
                "{name}: {m}"
            ),
            other => panic!("{name}: {other:?}"),
        }
    }
}

/// Finding 5: a FIFO where a shard should be is refused before it is opened, by streaming
/// (which hung) and by import.
#[test]
fn a_fifo_shard_is_refused_not_waited_on() {
    let fixture = fixture([64, 64, 64]);
    let zarr = fixture.zarr.clone();
    std::fs::remove_file(zarr.join("1/c/0/0/0")).unwrap();
    mkfifo(&zarr.join("1/c/0/0/0"));
    let outcome = guarded("fifo", {
        let bricks = fixture.bricks.clone();
        move || stream_outcome(zarr, bricks)
    });
    match outcome {
        Outcome::Clean(m) => assert!(m.contains("FIFO") && m.contains("1/c/0/0/0"), "{m}"),
        other => panic!("{other:?}"),
    }
}

/// The missing-chunk check names the brick and says what the skeleton expected.
#[test]
fn a_deleted_shard_is_named_on_import() {
    let fixture = fixture([64, 64, 64]);
    std::fs::remove_file(fixture.zarr.join("0/c/0/0/0")).unwrap();
    let zarr = fixture.zarr.clone();
    match guarded("deleted", move || import_outcome(zarr)) {
        Outcome::Clean(m) => assert!(
            m.contains("level 0 brick") && m.contains("missing") && m.contains("skeleton"),
            "{m}"
        ),
        other => panic!("{other:?}"),
    }
}

/// A broken top-level zarr.json is an OME-Zarr with a broken zarr.json, not another format
/// ("no DICOM files in this folder"), also in a folder whose name does not say `.zarr`.
#[test]
fn a_broken_group_document_is_named() {
    let fixture = fixture([64, 64, 64]);
    let plain = fixture.zarr.with_file_name("scan-export");
    std::fs::rename(&fixture.zarr, &plain).unwrap();
    std::fs::write(plain.join("zarr.json"), b"{ not json").unwrap();
    assert!(strata_omezarr::looks_like_ome_zarr(plain.to_str().unwrap()));
    match guarded("broken", move || import_outcome(plain)) {
        Outcome::Clean(m) => assert!(m.contains("zarr.json"), "{m}"),
        other => panic!("{other:?}"),
    }
}

/// The campaign as a corpus: 300 byte-level mutations of the export's binary objects (both
/// levels' shards, the skeleton, the checksums), from a fixed seed: bit flips, bytes set to
/// 0x80 or 0xff, runs overwritten with random words (index entries among them), truncations,
/// garbage appended. Each imports and streams under the time limit; every outcome is a clean
/// error or the undamaged image (a flip in bytes nothing reads), never a panic, a hang or a
/// silently different image.
#[test]
fn mutated_exports_never_panic_hang_or_read_silently_wrong() {
    let fixture = fixture([64, 64, 64]);
    let work = tempfile::tempdir().unwrap();
    let targets = [
        "0/c/0/0/0",
        "1/c/0/0/0",
        "strata-skeleton.bin",
        "strata-checksums.bin",
    ];
    let mut seed = 0x5eed_0038_u64;
    let mut next = move || {
        // xorshift64*: reproducible without a dependency.
        seed ^= seed >> 12;
        seed ^= seed << 25;
        seed ^= seed >> 27;
        seed.wrapping_mul(0x2545_f491_4f6c_dd1d)
    };
    let (mut clean, mut intact, mut counts) = (0usize, 0usize, Counts::default());
    for case in 0..300 {
        let zarr = work.path().join(format!("m{case}.ome.zarr"));
        copy_dir(&fixture.zarr, &zarr);
        let target = zarr.join(targets[(next() % targets.len() as u64) as usize]);
        let mut bytes = std::fs::read(&target).unwrap();
        let len = bytes.len() as u64;
        let at = (next() % len) as usize;
        let what = match next() % 6 {
            0 => {
                bytes[at] ^= 1 << (next() % 8);
                "bit flip"
            }
            1 => {
                bytes[at] ^= 0x80;
                "xor 0x80"
            }
            2 => {
                bytes[at] = 0xff;
                "byte 0xff"
            }
            3 => {
                let word = next().to_le_bytes();
                let end = (at + 8).min(bytes.len());
                bytes[at..end].copy_from_slice(&word[..end - at]);
                "random word"
            }
            4 => {
                bytes.truncate(at);
                "truncated"
            }
            _ => {
                bytes.extend((0..1 + next() % 64).map(|_| next() as u8));
                "garbage appended"
            }
        };
        std::fs::write(&target, &bytes).unwrap();
        let name = format!("{case}: {what} at {at} of {}", target.display());
        let import = guarded(&name, {
            let zarr = zarr.clone();
            let bricks = fixture.bricks.clone();
            move || {
                let work = tempfile::tempdir().unwrap();
                let back = work.path().join("back.strata");
                match import_zarr(
                    folder(&zarr),
                    &back,
                    &ImportZarrOptions::default(),
                    &|_, _| {},
                    &ImportOptions::default(),
                ) {
                    Err(e) => Outcome::Clean(e.to_string()),
                    Ok(_) => {
                        let store = Store::open(&back).unwrap();
                        match bricks
                            .iter()
                            .find(|(id, b)| store.read_brick(*id).ok().as_ref() != Some(b))
                        {
                            Some((id, _)) => Outcome::SilentWrong(format!(
                                "imported, brick level {} at {:?} differs",
                                id.level, id.coords
                            )),
                            None => Outcome::SilentWrong("intact".into()),
                        }
                    }
                }
            }
        });
        let stream = guarded(&name, {
            let (zarr, bricks) = (zarr.clone(), fixture.bricks.clone());
            move || stream_outcome(zarr, bricks)
        });
        for (side, outcome) in [("import", import), ("stream", stream)] {
            match outcome {
                Outcome::Clean(_) => clean += 1,
                // The undamaged image, whole: the mutation hit bytes nothing reads.
                Outcome::SilentWrong(m)
                    if m == "intact" || m == "every brick streamed as undamaged" =>
                {
                    intact += 1
                }
                other => counts.add(&format!("{side}, {name}"), other),
            }
        }
        let _ = std::fs::remove_dir_all(&zarr);
    }
    println!(
        "mutated OME-Zarr (300 cases, import and stream): {clean} clean errors, {intact} read intact, {} silent wrong, {} panics, {} hangs",
        counts.silent.len(),
        counts.panics.len(),
        counts.hangs.len()
    );
    assert!(
        counts.silent.is_empty() && counts.panics.is_empty() && counts.hangs.is_empty(),
        "{counts:#?}"
    );
}

/// A FIFO as the group's zarr.json: taken for an OME-Zarr (not handed to another format's
/// reader, which would open it) and refused before it is opened.
#[test]
fn a_fifo_group_document_is_refused_not_waited_on() {
    let fixture = fixture([64, 64, 64]);
    let plain = fixture.zarr.with_file_name("scan-export");
    std::fs::rename(&fixture.zarr, &plain).unwrap();
    std::fs::remove_file(plain.join("zarr.json")).unwrap();
    mkfifo(&plain.join("zarr.json"));
    assert!(strata_omezarr::looks_like_ome_zarr(plain.to_str().unwrap()));
    match guarded("fifo-group", move || import_outcome(plain)) {
        Outcome::Clean(m) => assert!(m.contains("FIFO") && m.contains("zarr.json"), "{m}"),
        other => panic!("{other:?}"),
    }
}

/// A foreign OME-Zarr (no `strata` attribute) keeps Zarr's fill-value semantics: a level
/// without any chunk imports as the fill value, and the report says so.
#[test]
fn a_foreign_level_without_chunks_imports_as_fill_with_a_note() {
    let fixture = fixture([64, 64, 64]);
    edit_json(&fixture.zarr.join("zarr.json"), |d| {
        d["attributes"].as_object_mut().unwrap().remove("strata");
    });
    std::fs::remove_dir_all(fixture.zarr.join("0/c")).unwrap();
    let work = tempfile::tempdir().unwrap();
    let report = import_zarr(
        folder(&fixture.zarr),
        &work.path().join("back.strata"),
        &ImportZarrOptions::default(),
        &|_, _| {},
        &ImportOptions::default(),
    )
    .unwrap();
    assert!(!report.strata_export);
    assert!(
        report
            .notes
            .iter()
            .any(|n| n.contains("level 0") && n.contains("no chunk") && n.contains("fill value")),
        "{:?}",
        report.notes
    );
    let source = OmeZarrSource::open(folder(&fixture.zarr)).unwrap();
    assert!(
        source.notes().iter().any(|n| n.contains("no chunk")),
        "{:?}",
        source.notes()
    );
}
