//! The store's part of the reliability campaign, against the real binary: damaged copies of a
//! store, a full disk, two writers, a store held by another process, read-only media, and an
//! import killed with SIGKILL. Every case must end within a time bound in a clean error that
//! names the store (or a sound result); never a panic, a hang, or a store that looks complete
//! and is not.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const STRATA: &str = env!("CARGO_BIN_EXE_strata");

/// Bound for one command on a small store; a hang is what this suite exists to catch, so the
/// limit is generous for a loaded 2-core machine and still far below "forever".
const COMMAND_LIMIT: Duration = Duration::from_secs(90);

struct Ran {
    code: Option<i32>,
    text: String,
}

/// Runs `strata args` (optionally through `bash -c` for ulimits), killing it at the limit.
fn run_limited(mut command: Command, what: &str) -> Ran {
    let mut child = command
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{what}: cannot start: {e}"));
    let started = Instant::now();
    loop {
        match child.try_wait() {
            Ok(Some(_)) => break,
            Ok(None) if started.elapsed() > COMMAND_LIMIT => {
                let _ = child.kill();
                let out = child.wait_with_output().unwrap();
                panic!(
                    "{what}: HANG, killed after {COMMAND_LIMIT:?}; output so far: {}{}",
                    String::from_utf8_lossy(&out.stdout),
                    String::from_utf8_lossy(&out.stderr)
                );
            }
            Ok(None) => std::thread::sleep(Duration::from_millis(20)),
            Err(e) => panic!("{what}: {e}"),
        }
    }
    let out = child.wait_with_output().unwrap();
    Ran {
        code: out.status.code(),
        text: format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
    }
}

fn strata(args: &[&str]) -> Command {
    let mut c = Command::new(STRATA);
    c.args(args);
    c
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A 100³ u16 volume of deterministic noise: incompressible bricks make sled keep blob files
/// beside its main file, so every kind of database file gets damaged below.
fn noise_raw(dir: &Path) -> PathBuf {
    noise_raw_of(dir, 100)
}

/// An `n`³ u16 volume of deterministic noise, `noise-N.raw` (`noise.raw` for 100).
fn noise_raw_of(dir: &Path, n: usize) -> PathBuf {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let bytes: Vec<u8> = (0..n * n * n)
        .flat_map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            ((state >> 20) as u16).to_le_bytes()
        })
        .collect();
    let path = if n == 100 {
        dir.join("noise.raw")
    } else {
        dir.join(format!("noise-{n}.raw"))
    };
    std::fs::write(&path, bytes).unwrap();
    path
}

fn import_noise(dir: &Path, store: &Path) {
    let raw = noise_raw(dir);
    let r = run_limited(
        strata(&[
            "import",
            s(&raw),
            s(store),
            "--raw-dims",
            "100,100,100",
            "--raw-type",
            "u16",
        ]),
        "import noise",
    );
    assert_eq!(r.code, Some(0), "{}", r.text);
}

fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            if e.file_type().unwrap().is_dir() {
                stack.push(e.path());
            } else {
                out.push(e.path());
            }
        }
    }
    out.sort();
    out
}

fn copy_dir(from: &Path, to: &Path) {
    for f in files_under(from) {
        let target = to.join(f.strip_prefix(from).unwrap());
        std::fs::create_dir_all(target.parent().unwrap()).unwrap();
        std::fs::copy(&f, &target).unwrap();
    }
}

/// Every file of a store deleted, truncated, or with one byte flipped: `info` and then
/// `verify` (the store opened once, as in the campaign) end in an error naming the store or in
/// a sound result; none panics, none hangs, and damage is never called an "incomplete import"
/// unless the completion record itself is what was lost.
#[test]
fn damaged_store_copies_give_errors_not_panics_or_hangs() {
    let dir = tempfile::tempdir().unwrap();
    let pristine = dir.path().join("pristine.strata");
    import_noise(dir.path(), &pristine);
    let files = files_under(&pristine);
    // Format 3: its packs and index (sled's own files are damaged in storage's
    // tests/store_damage.rs, on a format-2 store).
    assert!(
        files
            .iter()
            .any(|f| f.to_string_lossy().contains("pack-00000.pack"))
            && files.iter().any(|f| f.ends_with("index.v3")),
        "the test store has no packs or index: {files:?}"
    );
    let mut cases = 0;
    let mut failures = Vec::new();
    for (n, file) in files.iter().enumerate() {
        let rel = file.strip_prefix(&pristine).unwrap().to_path_buf();
        if rel.to_string_lossy() == "strata.lock" {
            continue;
        }
        for damage in ["delete", "truncate", "flip"] {
            cases += 1;
            let copy = dir.path().join(format!("copy-{n}-{damage}.strata"));
            copy_dir(&pristine, &copy);
            let target = copy.join(&rel);
            match damage {
                "delete" => std::fs::remove_file(&target).unwrap(),
                "truncate" => {
                    let len = std::fs::metadata(&target).unwrap().len();
                    let f = std::fs::OpenOptions::new()
                        .write(true)
                        .open(&target)
                        .unwrap();
                    f.set_len(len / 2).unwrap();
                }
                _ => {
                    let mut bytes = std::fs::read(&target).unwrap();
                    if bytes.is_empty() {
                        continue;
                    }
                    let at = bytes.len() / 2;
                    bytes[at] ^= 0x5a;
                    std::fs::write(&target, bytes).unwrap();
                }
            }
            let case = format!("{} {damage}", rel.display());
            for command in ["info", "verify"] {
                let r = run_limited(strata(&[command, s(&copy)]), &format!("{command} ({case})"));
                let panicked = r.text.contains("panicked") || r.code == Some(101);
                let named = r.text.contains(s(&copy));
                match r.code {
                    Some(0) | Some(1) if !panicked => {}
                    other => {
                        failures.push(format!("{command} ({case}): exit {other:?}: {}", r.text))
                    }
                }
                // Only the marker's own damage can hide that the import had finished.
                let marker_damaged = rel.to_string_lossy() == "STRATA-STORE";
                if r.text.contains("incomplete import") && !marker_damaged {
                    failures.push(format!(
                        "{command} ({case}): damage reported as an incomplete import: {}",
                        r.text
                    ));
                }
                if r.code == Some(1) && !named {
                    failures.push(format!(
                        "{command} ({case}): the error does not name the store: {}",
                        r.text
                    ));
                }
            }
            std::fs::remove_dir_all(&copy).unwrap();
        }
    }
    println!("{cases} damaged copies checked with info and verify");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Import under a small file-size limit (what a full disk does to the writes; works without
/// root, in CI): a clean, quick error that says the disk is full, and no store left behind.
#[cfg(unix)]
#[test]
fn import_onto_a_full_disk_ends_with_a_clear_error_and_no_store() {
    let dir = tempfile::tempdir().unwrap();
    let raw = noise_raw(dir.path());
    for attempt in 0..3 {
        let store = dir.path().join(format!("full-{attempt}.strata"));
        // 1 MiB limit for a 3 MB store. SIGXFSZ is ignored (inherited across exec), so the
        // writes fail with EFBIG as they would with ENOSPC, instead of killing the process.
        let script = format!(
            "ulimit -f 1024; trap '' XFSZ; exec {STRATA} import {} {} --raw-dims 100,100,100 --raw-type u16",
            s(&raw),
            s(&store)
        );
        let mut c = Command::new("bash");
        c.args(["-c", &script]);
        let r = run_limited(c, "import under RLIMIT_FSIZE");
        assert_eq!(r.code, Some(1), "{}", r.text);
        assert!(r.text.contains("disk is full"), "{}", r.text);
        assert!(!r.text.contains("panicked"), "{}", r.text);
        assert!(!store.exists(), "a failed import left {}", store.display());
    }
}

/// The same on a real full filesystem: a 2 MiB tmpfs, where the test can mount one (root).
#[cfg(target_os = "linux")]
#[test]
fn import_onto_a_full_tmpfs_ends_with_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let mount = dir.path().join("small");
    std::fs::create_dir_all(&mount).unwrap();
    let mounted = Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=2m", "tmpfs", s(&mount)])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|st| st.success());
    if !mounted {
        println!("skipped: cannot mount a tmpfs here (needs root); the RLIMIT_FSIZE test covers the writes");
        return;
    }
    let raw = noise_raw(dir.path());
    let store = mount.join("s.strata");
    let r = run_limited(
        strata(&[
            "import",
            s(&raw),
            s(&store),
            "--raw-dims",
            "100,100,100",
            "--raw-type",
            "u16",
        ]),
        "import onto a full tmpfs",
    );
    let _ = Command::new("umount").arg(&mount).status();
    assert_eq!(r.code, Some(1), "{}", r.text);
    assert!(r.text.contains("disk is full"), "{}", r.text);
}

/// A second import into a store being written is refused at once with the first one's pid; the
/// first finishes and its store opens.
#[test]
fn a_second_writer_is_refused_and_the_first_store_survives() {
    let dir = tempfile::tempdir().unwrap();
    let nrrd = dir.path().join("p.nrrd");
    let r = run_limited(
        strata(&["sample", "--size", "96", "--out", s(&nrrd)]),
        "sample",
    );
    assert_eq!(r.code, Some(0), "{}", r.text);
    let store = dir.path().join("shared.strata");
    let mut first = Command::new(STRATA)
        .args(["import", s(&nrrd), s(&store)])
        .env("STRATA_DEBUG_SLOW_IMPORT", "1")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Wait until the first import holds the store.
    let deadline = Instant::now() + COMMAND_LIMIT;
    while !store.join("strata.lock").exists() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(200));
    let started = Instant::now();
    let second = run_limited(strata(&["import", s(&nrrd), s(&store)]), "second import");
    assert_eq!(second.code, Some(1), "{}", second.text);
    assert!(
        second
            .text
            .contains(&format!("in use by pid {}", first.id())),
        "{}",
        second.text
    );
    // "At once": the refusal does not wait for the lock (generous bound, not a benchmark).
    assert!(started.elapsed() < Duration::from_secs(30));
    let status = first.wait().unwrap();
    assert!(status.success(), "the first import failed");
    let info = run_limited(strata(&["info", s(&store)]), "info after both");
    assert_eq!(info.code, Some(0), "{}", info.text);
}

/// A store another process has open: a local command says who holds it at once, never a
/// database error after a wait.
#[test]
fn a_store_held_by_another_process_is_reported_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("held.strata");
    let r = run_limited(
        strata(&["sample", "--size", "40", "--out", s(&store)]),
        "sample",
    );
    assert_eq!(r.code, Some(0), "{}", r.text);
    // Readers of a format-3 store share it: one open here keeps nobody out.
    let reader = strata_storage::Store::open(&store).unwrap();
    let r = run_limited(strata(&["info", s(&store)]), "info beside a reader");
    assert_eq!(r.code, Some(0), "{}", r.text);
    drop(reader);
    // A writer holds it exclusively.
    let held =
        strata_storage::lock::StoreLock::acquire(&store, strata_storage::lock::LockPurpose::Import)
            .unwrap();
    for command in ["info", "verify"] {
        let r = run_limited(strata(&[command, s(&store)]), command);
        assert_eq!(r.code, Some(1), "{}", r.text);
        assert!(
            r.text
                .contains(&format!("in use by pid {}", std::process::id())),
            "{}",
            r.text
        );
        assert!(!r.text.contains("database error"), "{}", r.text);
    }
    drop(held);
    let r = run_limited(strata(&["info", s(&store)]), "info after release");
    assert_eq!(r.code, Some(0), "{}", r.text);
}

/// A store on read-only media opens (format 3 writes nothing when opened), where the test can
/// mount a read-only filesystem (root).
#[cfg(target_os = "linux")]
#[test]
fn a_store_on_read_only_media_opens() {
    let dir = tempfile::tempdir().unwrap();
    let mount = dir.path().join("ro");
    std::fs::create_dir_all(&mount).unwrap();
    let mounted = Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=16m", "tmpfs", s(&mount)])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|st| st.success());
    if !mounted {
        println!("skipped: cannot mount a tmpfs here (needs root)");
        return;
    }
    let store = mount.join("ro.strata");
    let r = run_limited(
        strata(&["sample", "--size", "40", "--out", s(&store)]),
        "sample",
    );
    let remounted = Command::new("mount")
        .args(["-o", "remount,ro", s(&mount)])
        .status()
        .is_ok_and(|st| st.success());
    let r2 = run_limited(strata(&["info", s(&store)]), "info on read-only media");
    let _ = Command::new("umount").arg(&mount).status();
    assert_eq!(r.code, Some(0), "{}", r.text);
    assert!(remounted, "remount read-only failed");
    // Format 3 opens without writing: read-only media just work.
    assert_eq!(r2.code, Some(0), "{}", r2.text);
    assert!(r2.text.contains("store format 3"), "{}", r2.text);
}

/// A slowed import of `input` into `store` (staging in `staging`), returned once it is
/// writing its database: the moment the signal tests interrupt it.
fn slow_import_in_progress(input: &Path, store: &Path, staging: &Path) -> std::process::Child {
    let child = Command::new(STRATA)
        .args(["import", s(input), s(store), "--staging-dir", s(staging)])
        .env("STRATA_DEBUG_SLOW_IMPORT", "1")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + COMMAND_LIMIT;
    while !(store.join("db").exists() || store.join("packs").exists()) && Instant::now() < deadline
    {
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(250));
    child
}

/// SIGKILL during a compressed import leaves its staging file (nothing can run on SIGKILL);
/// the next import removes it, and the killed store reads as incomplete, never complete.
#[cfg(unix)]
#[test]
fn a_killed_compressed_import_leaves_no_staging_file_after_the_next_run() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let staging = dir.path().join("staging");
    std::fs::create_dir_all(&staging).unwrap();
    let nrrd = dir.path().join("p.nrrd");
    let r = run_limited(
        strata(&["sample", "--size", "96", "--out", s(&nrrd)]),
        "sample",
    );
    assert_eq!(r.code, Some(0), "{}", r.text);
    // The sample is a raw NRRD; gzip its data to make a compressed input.
    let bytes = std::fs::read(&nrrd).unwrap();
    let split = bytes.windows(2).position(|w| w == b"\n\n").unwrap() + 2;
    let header =
        String::from_utf8_lossy(&bytes[..split]).replace("encoding: raw", "encoding: gzip");
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    gz.write_all(&bytes[split..]).unwrap();
    let mut out = header.into_bytes();
    out.extend_from_slice(&gz.finish().unwrap());
    let packed = dir.path().join("packed.nrrd");
    std::fs::write(&packed, out).unwrap();

    let store = dir.path().join("killed.strata");
    let mut child = slow_import_in_progress(&packed, &store, &staging);
    child.kill().unwrap();
    child.wait().unwrap();
    assert_eq!(
        std::fs::read_dir(&staging).unwrap().count(),
        1,
        "the killed import should have left exactly its staging file"
    );
    // Age the leftover as time would (the cleanup leaves files younger than 30 s alone, since
    // a live import may not have locked its new file yet).
    for e in std::fs::read_dir(&staging).unwrap().flatten() {
        std::fs::File::options()
            .write(true)
            .open(e.path())
            .unwrap()
            .set_modified(std::time::SystemTime::now() - Duration::from_secs(3600))
            .unwrap();
    }
    let info = run_limited(strata(&["info", s(&store)]), "info of the killed store");
    assert_eq!(info.code, Some(1), "{}", info.text);
    assert!(info.text.contains("incomplete import"), "{}", info.text);
    // The next import (of anything, with the same staging folder) removes the dead file.
    let again = dir.path().join("again.strata");
    let r = run_limited(
        strata(&[
            "import",
            s(&packed),
            s(&again),
            "--staging-dir",
            s(&staging),
        ]),
        "next import",
    );
    assert_eq!(r.code, Some(0), "{}", r.text);
    assert_eq!(
        std::fs::read_dir(&staging).unwrap().count(),
        0,
        "stale staging file not removed"
    );
}

/// Ctrl-C (SIGINT) and SIGTERM during a compressed import remove its staging file at once.
#[cfg(unix)]
#[test]
fn an_interrupted_import_removes_its_staging_file() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let staging = dir.path().join("staging");
    std::fs::create_dir_all(&staging).unwrap();
    let raw = noise_raw(dir.path());
    let header = "NRRD0004\ntype: uint16\ndimension: 3\nsizes: 100 100 100\nendian: little\nencoding: gzip\n\n";
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    gz.write_all(&std::fs::read(&raw).unwrap()).unwrap();
    let mut bytes = header.as_bytes().to_vec();
    bytes.extend_from_slice(&gz.finish().unwrap());
    let packed = dir.path().join("noise.nrrd");
    std::fs::write(&packed, bytes).unwrap();
    let store = dir.path().join("int.strata");
    let child = slow_import_in_progress(&packed, &store, &staging);
    let term = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(term.success());
    let out = child.wait_with_output().unwrap();
    assert_eq!(
        out.status.code(),
        Some(130),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        std::fs::read_dir(&staging).unwrap().count(),
        0,
        "SIGTERM left the staging file"
    );
}

/// What a store folder left by a killed command is: 0 none (or not a store), 1 incomplete and
/// refused as such, 2 complete and verifying; any other outcome (a complete-looking store that
/// does not verify, an error of another kind) fails the test.
fn killed_outcome(store: &Path, what: &str) -> usize {
    if !store.exists() {
        return 0;
    }
    match strata_storage::Store::open(store) {
        Ok(opened) => {
            let problems = opened.verify(|_, _| {}).unwrap();
            assert!(problems.is_empty(), "{what}: {problems:?}");
            2
        }
        Err(strata_storage::StorageError::IncompleteImport { .. }) => 1,
        Err(strata_storage::StorageError::NotAStore { .. }) => 0,
        Err(e) => panic!("{what}: {e}"),
    }
}

/// The next number of a xorshift sequence.
fn next_random(state: &mut u64) -> u64 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    *state
}

/// Kill moments for `tries` kills of a command whose uninterrupted run took `span`: the k-th
/// lands at a random moment inside the k-th of `tries` equal slices of 1.2 × `span`, so the
/// kills cover the whole run (start-up, records written, the index, the marker) and a few land
/// after it, however fast the machine.
fn spread_kill_moments(span: Duration, tries: u32, seed: u64) -> Vec<Duration> {
    let span_us = (span.as_micros() as u64 * 6 / 5).max(u64::from(tries));
    let slice = span_us / u64::from(tries);
    let mut state = seed;
    (0..u64::from(tries))
        .map(|k| Duration::from_micros(k * slice + next_random(&mut state) % slice))
        .collect()
}

/// Crash fuzz (issue 48): 50 SIGKILLs at moments spread over the import of a 256³ volume (the
/// span measured by one uninterrupted import first, see `spread_kill_moments`) leave no store,
/// an incomplete store refused as such, or a complete store that verifies; never a
/// complete-looking damaged one.
#[test]
fn sigkill_at_any_moment_of_an_import_never_leaves_a_complete_looking_damaged_store() {
    let dir = tempfile::tempdir().unwrap();
    let raw = noise_raw_of(dir.path(), 256);
    let store = dir.path().join("fuzz.strata");
    let import = || {
        strata(&[
            "import",
            "--replace",
            s(&raw),
            s(&store),
            "--raw-dims",
            "256,256,256",
            "--raw-type",
            "u16",
        ])
    };
    let started = Instant::now();
    let r = run_limited(import(), "an uninterrupted import of 256³");
    assert_eq!(r.code, Some(0), "{}", r.text);
    let span = started.elapsed();
    let mut outcomes = [0u32; 3];
    for delay in spread_kill_moments(span, 50, 0x2545_f491_4f6c_dd1d) {
        let mut child = import()
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(delay);
        let _ = child.kill();
        child.wait().unwrap();
        outcomes[killed_outcome(&store, &format!("import killed after {delay:?}"))] += 1;
    }
    println!("import of 256³ in {span:?}; no store / incomplete / complete: {outcomes:?}");
    assert!(outcomes[1] > 0, "some kills landed inside the import");
}

/// Crash fuzz of `strata store upgrade` (issue 48): 20 SIGKILLs spread over the upgrade of a
/// format-2 store of a 256³ volume (the span measured by one full upgrade first, see
/// `spread_kill_moments`). Each of the store, its `.upgrading` copy, its `.format2-old`
/// original and the `.upgrade-source` copy the upgrade reads that exists is incomplete (refused
/// as such) or complete and verifying, and a complete store holding the volume always remains.
/// (A kill 9 ms in once damaged the original: sled wrote to it on open; the upgrade now opens
/// a copy.)
#[test]
fn sigkill_at_any_moment_of_an_upgrade_never_leaves_a_complete_looking_damaged_store() {
    let dir = tempfile::tempdir().unwrap();
    let raw = noise_raw_of(dir.path(), 256);
    let template = dir.path().join("template.strata");
    let r = run_limited(
        strata(&[
            "import",
            "--format",
            "2",
            s(&raw),
            s(&template),
            "--raw-dims",
            "256,256,256",
            "--raw-type",
            "u16",
        ]),
        "import a format-2 store",
    );
    assert_eq!(r.code, Some(0), "{}", r.text);
    let store = dir.path().join("up.strata");
    let staged = dir.path().join("up.strata.upgrading");
    let parked = dir.path().join("up.strata.format2-old");
    // The copy the upgrade reads (the original is never opened by sled, which writes on open).
    let source = dir.path().join("up.strata.upgrade-source");
    let fresh = || {
        for p in [&store, &staged, &parked, &source] {
            let _ = std::fs::remove_dir_all(p);
        }
        copy_dir(&template, &store);
    };
    fresh();
    let started = Instant::now();
    let r = run_limited(strata(&["store", "upgrade", s(&store)]), "a full upgrade");
    assert_eq!(r.code, Some(0), "{}", r.text);
    let span = started.elapsed();
    let mut upgraded = 0;
    for delay in spread_kill_moments(span, 20, 0x9e37_79b9_7f4a_7c15) {
        fresh();
        let mut child = strata(&["store", "upgrade", s(&store)])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(delay);
        let _ = child.kill();
        child.wait().unwrap();
        let what = format!("upgrade killed after {delay:?}");
        let here = killed_outcome(&store, &what);
        let copy = killed_outcome(&staged, &what);
        let old = killed_outcome(&parked, &what);
        // A copy cut short has no marker (it is copied last): not a store at all.
        killed_outcome(&source, &what);
        assert!(
            here == 2 || old == 2,
            "{what}: no complete store left ({here}, {copy}, {old})"
        );
        if here == 2 && !parked.exists() && !staged.exists() {
            upgraded += u32::from(
                strata_storage::Store::open(&store)
                    .unwrap()
                    .format_version()
                    == 3,
            );
        }
    }
    println!("upgrade of 256³ in {span:?}; kills after it finished: {upgraded} of 20");
}

/// Crash fuzz of `strata store compact` (issue 48): 20 SIGKILLs spread over the compaction of a
/// format-3 store of a 256³ volume (the span measured by one full compaction first). The store,
/// its `.compacting` copy and its `.compact-old` original that exist are each incomplete
/// (refused as such) or complete and verifying, and a complete store always remains.
#[test]
fn sigkill_at_any_moment_of_a_compaction_never_leaves_a_complete_looking_damaged_store() {
    let dir = tempfile::tempdir().unwrap();
    let raw = noise_raw_of(dir.path(), 256);
    let template = dir.path().join("template.strata");
    let r = run_limited(
        strata(&[
            "import",
            s(&raw),
            s(&template),
            "--raw-dims",
            "256,256,256",
            "--raw-type",
            "u16",
        ]),
        "import a format-3 store",
    );
    assert_eq!(r.code, Some(0), "{}", r.text);
    let store = dir.path().join("c.strata");
    let staged = dir.path().join("c.strata.compacting");
    let parked = dir.path().join("c.strata.compact-old");
    let fresh = || {
        for p in [&store, &staged, &parked] {
            let _ = std::fs::remove_dir_all(p);
        }
        copy_dir(&template, &store);
    };
    fresh();
    let started = Instant::now();
    let r = run_limited(
        strata(&["store", "compact", s(&store)]),
        "a full compaction",
    );
    assert_eq!(r.code, Some(0), "{}", r.text);
    let span = started.elapsed();
    let mut outcomes = [0u32; 3];
    for delay in spread_kill_moments(span, 20, 0x5851_f42d_4c95_7f2d) {
        fresh();
        let mut child = strata(&["store", "compact", s(&store)])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(delay);
        let _ = child.kill();
        child.wait().unwrap();
        let what = format!("compaction killed after {delay:?}");
        let here = killed_outcome(&store, &what);
        killed_outcome(&staged, &what);
        let old = killed_outcome(&parked, &what);
        assert!(
            here == 2 || old == 2,
            "{what}: no complete store left ({here}, {old})"
        );
        outcomes[here] += 1;
    }
    println!("compaction of 256³ in {span:?}; the store after each kill (none / incomplete / complete): {outcomes:?}");
}

/// Issue 48: a format-3 store in a folder made read-only (every file 0444, every folder 0555)
/// is rendered, verified, described, listed and served, and no file under it changes: the same files
/// with the same size, modification time and bytes (the lock file included). Root ignores the
/// permissions, so the unchanged files are what shows that nothing wrote.
#[cfg(unix)]
#[test]
fn a_v3_store_in_a_read_only_folder_renders_verifies_lists_and_serves_without_changing_a_file() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("ro.strata");
    let r = run_limited(
        strata(&["sample", "--size", "40", "--out", s(&store)]),
        "sample",
    );
    assert_eq!(r.code, Some(0), "{}", r.text);
    let snapshot = || -> Vec<(PathBuf, u64, std::time::SystemTime, Vec<u8>)> {
        files_under(&store)
            .into_iter()
            .map(|p| {
                let m = std::fs::metadata(&p).unwrap();
                let bytes = std::fs::read(&p).unwrap();
                (p, m.len(), m.modified().unwrap(), bytes)
            })
            .collect()
    };
    let set_read_only = |read_only: bool| {
        let mut paths = files_under(&store);
        let mut folders: Vec<PathBuf> = paths
            .iter()
            .filter_map(|p| p.parent().map(Path::to_path_buf))
            .collect();
        folders.sort();
        folders.dedup();
        paths.extend(folders);
        for p in paths {
            let mode = match (p.is_dir(), read_only) {
                (true, true) => 0o555,
                (true, false) => 0o755,
                (false, true) => 0o444,
                (false, false) => 0o644,
            };
            std::fs::set_permissions(&p, std::fs::Permissions::from_mode(mode)).unwrap();
        }
    };
    let before = snapshot();
    assert!(before.len() >= 3, "marker, index and a pack: {before:?}");
    let png = dir.path().join("ro.png");
    set_read_only(true);
    let runs: Vec<(&str, Ran)> = [
        (
            "render",
            vec!["render", s(&store), "--size", "32x32", "--out", s(&png)],
        ),
        ("verify", vec!["verify", s(&store)]),
        ("info", vec!["info", s(&store)]),
        (
            "store list",
            vec!["store", "list", "--data-dir", s(dir.path())],
        ),
    ]
    .into_iter()
    .map(|(what, args)| (what, run_limited(strata(&args), what)))
    .collect();
    // Served from the read-only folder, and read beside the server by a local render: the
    // served image equals the local one.
    let (local, served) = (dir.path().join("local.png"), dir.path().join("served.png"));
    {
        let server = crate::remote::Served::start(&store, &[]);
        crate::remote::render(s(&store), &local, &[]);
        crate::remote::render(&server.url, &served, &[]);
    }
    set_read_only(false);
    assert!(
        crate::remote::png_pixels(&local) == crate::remote::png_pixels(&served),
        "the store served from a read-only folder renders unlike the local one"
    );
    for (what, r) in &runs {
        assert_eq!(r.code, Some(0), "{what}: {}", r.text);
    }
    assert!(runs[3].1.text.contains("ro.strata"), "{}", runs[3].1.text);
    assert!(png.is_file(), "render wrote no image");
    assert!(
        snapshot() == before,
        "a command changed a file under the read-only store"
    );
}
