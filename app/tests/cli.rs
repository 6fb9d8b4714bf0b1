//! The `strata` binary end to end: import, info, verify, sample, and what happens when an
//! import is killed or a brick is damaged.

use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use strata_storage::{StorageError, Store};
use strata_types::BrickId;

fn strata(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_strata"))
        .args(args)
        .output()
        .expect("strata runs")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

#[test]
fn sample_nrrd_imports_and_reports() {
    let dir = tempfile::tempdir().unwrap();
    let nrrd = dir.path().join("p.nrrd");
    let store = dir.path().join("p.strata");
    let o = strata(&["sample", "--size", "40", "--out", nrrd.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let o = strata(&["import", nrrd.to_str().unwrap(), store.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let o = strata(&["info", store.to_str().unwrap()]);
    let info = text(&o);
    assert!(o.status.success(), "{info}");
    assert!(info.contains("40 x 40 x 40 voxels"), "{info}");
    assert!(info.contains("orientation  LPS"), "{info}");
    assert!(info.contains("level 1"), "{info}");
    let o = strata(&["verify", store.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("all 9 bricks verified"), "{}", text(&o));
}

/// `strata sample --sparse` writes only varying bricks; verify checks those and says how many
/// constant nodes the skeleton implies instead of claiming every node was read.
#[test]
fn a_sparse_sample_verifies_its_stored_bricks_and_counts_the_implied_ones() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("sparse.strata");
    let o = strata(&[
        "sample",
        "--sparse",
        "--size",
        "256",
        "--out",
        store.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let o = strata(&["verify", store.to_str().unwrap()]);
    let said = text(&o);
    assert!(o.status.success(), "{said}");
    let opened = Store::open(&store).unwrap();
    let total = opened.header().layout.total_bricks();
    let stored = opened.skeleton().stored_nodes() as u64;
    assert!(stored < total, "the sample is sparse: {stored} of {total}");
    assert!(
        said.contains(&format!(
            "all {stored} nodes of the sparse skeleton verified; the other {} of the octree's \
             {total} nodes are constant",
            total - stored
        )),
        "{said}"
    );
}

#[test]
fn bad_inputs_fail_with_the_file_named() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.nii");
    let store = dir.path().join("s.strata");
    let o = strata(&["import", missing.to_str().unwrap(), store.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(text(&o).contains("nope.nii"), "{}", text(&o));
    assert!(!text(&o).contains("panicked"), "{}", text(&o));

    let truncated = dir.path().join("short.nrrd");
    std::fs::write(&truncated, b"NRRD0004\ntype: uint16\ndimension: 3\nsizes: 10 10 10\nencoding: raw\nendian: little\n\n0123").unwrap();
    let o = strata(&[
        "import",
        truncated.to_str().unwrap(),
        store.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("short.nrrd"), "{}", text(&o));
    assert!(!text(&o).contains("panicked"), "{}", text(&o));
    // A failed import leaves nothing that opens as a store.
    assert!(Store::open(&store).is_err());

    let o = strata(&["info", dir.path().join("absent.strata").to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(text(&o).contains("does not exist"), "{}", text(&o));
}

#[test]
fn killed_import_leaves_an_incomplete_store_and_reimport_succeeds() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("killed.strata");
    // Slowed down (20 ms per slice) so the kill lands mid-import deterministically.
    let mut child = Command::new(env!("CARGO_BIN_EXE_strata"))
        .args(["sample", "--size", "160", "--out", store.to_str().unwrap()])
        .env("STRATA_DEBUG_SLOW_IMPORT", "1")
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let started = Instant::now();
    // Wait until the database exists and has taken some writes, then kill without warning.
    while !(store.join("db").join("conf").exists() || store.join("packs").exists())
        && started.elapsed() < Duration::from_secs(30)
    {
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_millis(1500));
    assert!(
        child.try_wait().unwrap().is_none(),
        "import finished before it could be killed"
    );
    child.kill().unwrap();
    child.wait().unwrap();

    match Store::open(&store) {
        Err(StorageError::IncompleteImport { path }) => assert_eq!(path, store),
        Err(other) => panic!("expected the incomplete-import error, got {other}"),
        Ok(_) => panic!("a killed import opened as a complete store"),
    }
    let o = strata(&["info", store.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(text(&o).contains("incomplete import"), "{}", text(&o));

    let o = strata(&["sample", "--size", "48", "--out", store.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(
        Store::open(&store).unwrap().header().geometry.dims,
        [48, 48, 48]
    );
}

#[test]
fn verify_reports_a_flipped_byte() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("v.strata");
    let o = strata(&["sample", "--size", "64", "--out", store.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    Store::corrupt_brick_for_tests(Path::new(&store), BrickId::new(1, [0, 0, 0]), 100).unwrap();
    let o = strata(&["verify", store.to_str().unwrap()]);
    assert!(!o.status.success(), "verify passed a corrupted store");
    let out = text(&o);
    assert!(
        out.contains("checksum mismatch") && out.contains("level 1"),
        "{out}"
    );
    assert!(out.contains("1 problem"), "{out}");
}

#[test]
fn import_codec_is_recorded_shown_and_listed_and_prune_keeps_complete_stores() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("stores");
    std::fs::create_dir(&data).unwrap();
    let nrrd = dir.path().join("p.nrrd");
    let o = strata(&["sample", "--size", "40", "--out", nrrd.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let dense = data.join("dense.strata");
    let o = strata(&[
        "import",
        nrrd.to_str().unwrap(),
        dense.to_str().unwrap(),
        "--codec",
        "dense",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("dense codec"), "{}", text(&o));
    let o = strata(&["info", dense.to_str().unwrap()]);
    assert!(
        text(&o).contains("store format 3, brick codec dense"),
        "{}",
        text(&o)
    );
    let o = strata(&[
        "import",
        nrrd.to_str().unwrap(),
        "x.strata",
        "--codec",
        "gzip",
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("use fast or dense"), "{}", text(&o));

    // A store whose source is gone is orphaned; prune lists it, removes it only with --yes.
    let moved = dir.path().join("moved.nrrd");
    std::fs::copy(&nrrd, &moved).unwrap();
    let orphan = data.join("orphan.strata");
    let o = strata(&["import", moved.to_str().unwrap(), orphan.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    std::fs::remove_file(&moved).unwrap();
    let data_dir = data.to_str().unwrap();
    let o = strata(&["store", "list", "--data-dir", data_dir]);
    let listing = text(&o);
    assert!(o.status.success(), "{listing}");
    assert!(listing.contains("dense.strata"), "{listing}");
    assert!(listing.contains("format 3, dense codec"), "{listing}");
    assert!(listing.contains("format 3, fast codec"), "{listing}");
    assert!(listing.contains("2 stores"), "{listing}");
    // An import onto an existing store is refused naming it, unless --replace.
    let o = strata(&["import", nrrd.to_str().unwrap(), dense.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("dense.strata already holds a complete store of format 3")
            && text(&o).contains("--replace"),
        "{}",
        text(&o)
    );
    let o = strata(&[
        "import",
        "--replace",
        nrrd.to_str().unwrap(),
        dense.to_str().unwrap(),
        "--codec",
        "dense",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let o = strata(&["store", "prune", "--data-dir", data_dir, "--dry-run"]);
    assert!(text(&o).contains("would remove"), "{}", text(&o));
    assert!(orphan.exists());
    // Without a terminal and without --yes nothing goes.
    let o = strata(&["store", "prune", "--data-dir", data_dir]);
    assert!(!o.status.success(), "{}", text(&o));
    assert!(orphan.exists());
    let o = strata(&["store", "prune", "--data-dir", data_dir, "--yes"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(!orphan.exists());
    assert!(Store::open(&dense).is_ok());
}

/// `strata info` of a format-1 store (lz4 bricks) names the command that rewrites it in the
/// current codec; a fresh store's says nothing of the kind.
#[test]
fn info_of_a_format_1_store_names_the_command_that_rewrites_it() {
    let dir = tempfile::tempdir().unwrap();
    let old = dir.path().join("old.strata");
    let options = strata_storage::import::ImportOptions {
        codec: strata_storage::BrickCodec::Lz4,
        ..Default::default()
    };
    strata_storage::phantom::Phantom::cube(40)
        .write_store(&old, &options)
        .unwrap();
    let o = strata(&["info", old.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("store format 1"), "{}", text(&o));
    assert!(
        text(&o).contains("rewrite it in the current fast codec with: strata import"),
        "{}",
        text(&o)
    );
    assert!(text(&o).contains("old.strata"), "{}", text(&o));
    let fresh = dir.path().join("fresh.strata");
    strata_storage::phantom::Phantom::cube(40)
        .write_store(&fresh, &Default::default())
        .unwrap();
    let o = strata(&["info", fresh.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(!text(&o).contains("rewrite it"), "{}", text(&o));
}

/// `strata flythrough` holds each converged viewpoint for `--hold-frames` and reports LOD
/// flicker per viewpoint ("cut changes while still: N") and per frame in the CSV (issue 35).
#[test]
fn flythrough_reports_cut_changes_while_still_per_viewpoint_and_in_the_csv() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("p.strata");
    let csv = dir.path().join("f.csv");
    let o = strata(&["sample", "--size", "64", "--out", store.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let o = strata(&[
        "flythrough",
        store.to_str().unwrap(),
        "--size",
        "64x64",
        "--stops",
        "2",
        "--glide-frames",
        "2",
        "--settle-frames",
        "400",
        "--settle-seconds",
        "120",
        "--hold-frames",
        "20",
        "--gpu-mib",
        "64",
        "--cpu-mib",
        "128",
        "--no-in-core",
        "--csv",
        csv.to_str().unwrap(),
    ]);
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    for stop in 0..2 {
        let line = out
            .lines()
            .skip_while(|l| {
                !l.trim_start()
                    .starts_with(&format!("viewpoint {stop}: converged"))
            })
            .nth(1)
            .unwrap_or_else(|| panic!("viewpoint {stop} did not converge: {out}"));
        assert!(
            line.contains("cut changes while still: 0 (held 20 frames after converging, 0 of them not converged)"),
            "viewpoint {stop}: {line}\n{out}"
        );
    }
    let table = std::fs::read_to_string(&csv).unwrap();
    let mut lines = table.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let column = header
        .iter()
        .position(|&c| c == "cut_changes_while_still_total")
        .expect("the CSV has the flicker column");
    let phase = header.iter().position(|&c| c == "phase").unwrap();
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert!(rows.iter().all(|r| r.len() == header.len()), "{table}");
    assert_eq!(rows.iter().filter(|r| r[phase] == "still").count(), 40);
    assert!(rows.iter().all(|r| r[column] == "0"), "{table}");
}

/// `--settle-seconds` must be a positive number: a clear error, before any GPU work.
#[test]
fn flythrough_refuses_a_settle_time_that_is_not_positive() {
    let o = strata(&["flythrough", "nowhere.strata", "--settle-seconds", "0"]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("--settle-seconds must be a positive"),
        "{}",
        text(&o)
    );
}

/// `strata view --overlay` twice: the viewer holds one overlay, so it says so before opening a
/// window rather than dropping one.
#[test]
fn view_with_two_overlays_says_it_shows_one() {
    let out = strata(&[
        "view",
        "scan.nrrd",
        "--overlay",
        "a.nrrd",
        "--overlay",
        "b.nrrd",
    ]);
    assert!(!out.status.success());
    assert!(
        text(&out).contains("--overlay was given 2 times"),
        "{}",
        text(&out)
    );
}

/// Issue 35: a GPU budget the adapter cannot hold is a clear error naming the limit (lavapipe
/// allocates at most 2 GiB at once), never a panic in wgpu's uncaptured-error handler; and a
/// level loaded up front that does not fit --gpu-mib says bricks × bytes against it.
#[test]
fn budgets_the_device_cannot_hold_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("p.strata");
    let o = strata(&["sample", "--size", "128", "--out", store.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let s = store.to_str().unwrap();
    // ~1 TB: far beyond what lavapipe allocates at once (~2 GiB); the cache grows with use, so
    // the probe of its full grid at open is what fails.
    let o = strata(&[
        "flythrough",
        s,
        "--frames",
        "4",
        "--size",
        "32x32",
        "--gpu-mib",
        "1000000",
        "--no-in-core",
    ]);
    let out = text(&o);
    assert!(!o.status.success(), "{out}");
    assert!(!out.contains("panicked"), "{out}");
    assert!(out.contains("for a GPU budget of 1000000 MiB"), "{out}");
    assert!(out.contains("Out of Memory"), "{out}");
    assert!(out.contains("largest single allocation of"), "{out}");
    assert!(out.contains("--gpu-mib"), "{out}");
    // Level 0 of a 128³ store: 4³ bricks of 36³ 16-bit voxels, 5.7 MiB, over 4 MiB.
    let png = dir.path().join("p.png");
    let o = strata(&[
        "render",
        s,
        "--up-front",
        "--level",
        "0",
        "--size",
        "32x32",
        "--gpu-mib",
        "4",
        "--out",
        png.to_str().unwrap(),
    ]);
    let out = text(&o);
    assert!(!o.status.success(), "{out}");
    assert!(
        out.contains(
            "needs 64 bricks × 93312 bytes = 6 MiB of GPU brick cache, over the budget of 4 MiB"
        ),
        "{out}"
    );
    assert!(!png.exists(), "nothing written for a refused render");
    // Level 1 fits the same budget.
    let o = strata(&[
        "render",
        s,
        "--up-front",
        "--level",
        "1",
        "--size",
        "32x32",
        "--gpu-mib",
        "4",
        "--out",
        png.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(png.exists());
}

/// `strata serve --evict-idle-after` takes seconds; a value that is no duration is refused by
/// name before anything is served.
#[test]
fn serve_refuses_an_eviction_delay_that_is_no_duration() {
    for bad in [
        "--evict-idle-after=-1",
        "--evict-idle-after=nan",
        "--evict-idle-after=1e9",
    ] {
        let o = strata(&["serve", bad, "nowhere.strata"]);
        assert!(!o.status.success(), "{bad}: {}", text(&o));
        assert!(
            text(&o).contains("--evict-idle-after must be between 0 and 3600 seconds"),
            "{bad}: {}",
            text(&o)
        );
    }
}

/// A password never travels as a process argument (where `ps` and /proc show it to every user
/// of the machine): `strata pacs` and `strata import <server>` take it from a file or the
/// environment only, and a `--password VALUE` attempt is refused without echoing the value.
#[test]
fn pacs_takes_no_password_as_an_argument() {
    for command in [&["pacs", "find"][..], &["pacs", "push"], &["import"]] {
        let mut args = command.to_vec();
        args.extend(["http://127.0.0.1:9/dicom-web", "--user", "alice"]);
        args.extend([
            "--password",
            "Sesame-in-argv-42",
            "--study",
            "1.2",
            "out.strata",
        ]);
        let o = strata(&args);
        let said = text(&o);
        assert!(!o.status.success(), "{command:?}: {said}");
        assert!(said.contains("--password"), "{command:?}: {said}");
        assert!(!said.contains("Sesame-in-argv-42"), "{command:?}: {said}");
    }
}
