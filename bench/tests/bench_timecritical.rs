//! `strata-bench timecritical` end to end on a tiny phantom: the Table-2 summary, the per-frame
//! CSV, and clear errors for bad arguments. Speed is judged by the bench itself, not here.

use std::process::{Command, Output};

fn strata(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_strata-bench"))
        .args(args)
        .output()
        .expect("strata-bench runs")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

#[test]
fn orbit_summary_and_csv_for_both_runs() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("p.strata");
    let csv = dir.path().join("frames.csv");
    // What `strata sample --size 64` writes (that binary is not this package's).
    crate::common::sample_store(&store, 64);
    // A target no machine reaches: the controller drops to its rate floor and then coarsens the
    // level of detail, which this run exercises through the bench's per-level cuts.
    let o = strata(&[
        "timecritical",
        store.to_str().unwrap(),
        "--target",
        "100000",
        "--frames",
        "8",
        "--size",
        "32x32",
        "--csv",
        csv.to_str().unwrap(),
    ]);
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    assert!(out.contains("fixed rate (2.00 samples/voxel)"), "{out}");
    assert!(out.contains("time-critical (mean"), "{out}");
    assert!(out.contains("mean fps"), "{out}");
    assert!(out.contains("noise floor"), "{out}");
    let rows = std::fs::read_to_string(&csv).unwrap();
    let lines: Vec<&str> = rows.lines().collect();
    assert_eq!(
        lines[0],
        "run,frame,azimuth_deg,gpu_ms,fps,sampling_rate,step_voxels,lod_factor,jitter"
    );
    assert_eq!(lines.iter().filter(|l| l.starts_with("fixed,")).count(), 8);
    assert_eq!(
        lines
            .iter()
            .filter(|l| l.starts_with("noise-floor,"))
            .count(),
        8
    );
    let controlled: Vec<Vec<&str>> = lines
        .iter()
        .filter(|l| l.starts_with("time-critical,"))
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(controlled.len(), 8);
    // After the lead-in the controller sits at its floor with jitter on, and the lod factor
    // has started to coarsen.
    let last = &controlled[7];
    assert_eq!(last[5], "0.12500", "{last:?}");
    assert_eq!(last[8], "true", "{last:?}");
    let max_lod = controlled
        .iter()
        .map(|r| r[7].parse::<f64>().unwrap())
        .fold(1.0, f64::max);
    assert!(max_lod > 1.0, "lod never coarsened: {rows}");
}

#[test]
fn bad_arguments_are_refused_with_a_reason() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.strata");
    let o = strata(&["timecritical", missing.to_str().unwrap(), "--target", "10"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("missing.strata"), "{}", text(&o));
    for (flag, value) in [
        ("--target", "0"),
        ("--target", "NaN"),
        ("--frames", "0"),
        ("--step", "-1"),
    ] {
        let mut args = vec!["timecritical", missing.to_str().unwrap(), flag, value];
        if flag != "--target" {
            args.extend(["--target", "10"]);
        }
        let o = strata(&args);
        assert!(!o.status.success(), "{flag} {value} accepted");
        assert!(!text(&o).contains("panicked"), "{}", text(&o));
    }
}

/// Issue 35: a level over --gpu-mib is refused before it is read, with its bricks × bytes
/// against the budget (on a 1024³ store level 0 needs 32768 bricks, 2.8 GiB: the same message
/// at scale); a level that fits runs.
#[test]
fn a_level_over_the_gpu_budget_is_named_with_its_bricks_and_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("p.strata");
    // What `strata sample --size 128` writes (that binary is not this package's).
    crate::common::sample_store(&store, 128);
    let run = |level: &str| {
        strata(&[
            "timecritical",
            store.to_str().unwrap(),
            "--target",
            "100000",
            "--frames",
            "4",
            "--size",
            "32x32",
            "--gpu-mib",
            "4",
            "--level",
            level,
        ])
    };
    let o = run("0");
    let out = text(&o);
    assert!(!o.status.success(), "{out}");
    assert!(!out.contains("panicked"), "{out}");
    assert!(
        out.contains(&format!(
            "level 0 of {} needs 64 bricks × 93312 bytes = 6 MiB of GPU brick cache, over the budget of 4 MiB (--gpu-mib)",
            store.display()
        )),
        "{out}"
    );
    let o = run("1");
    assert!(o.status.success(), "{}", text(&o));
}
