//! `strata-bench transitions` end to end on a tiny phantom: the Table-1 row, the CSV with all
//! four settings, and GPU images that match the f64 reference of the same mixed cut.

use std::process::Command;

#[test]
fn table_and_csv_for_a_small_phantom() {
    let dir = tempfile::tempdir().unwrap();
    let md = dir.path().join("t.md");
    let o = Command::new(env!("CARGO_BIN_EXE_strata-bench"))
        .args(["transitions", "phantom", "--phantom-size", "128"])
        .args(["--size", "32x32", "--frames", "2", "--out"])
        .arg(&md)
        .output()
        .expect("strata runs");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(o.status.success(), "{text}");
    let table = std::fs::read_to_string(&md).unwrap();
    assert!(
        table.contains("| phantom128 | 128 × 128 × 128 |"),
        "{table}"
    );
    let csv = std::fs::read_to_string(md.with_extension("csv")).unwrap();
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(rows.len(), 4, "{csv}");
    for row in rows {
        let fraction: f64 = row[2].parse().unwrap();
        assert!(fraction > 0.0, "{csv}");
        let gpu_ms: f64 = row[5].parse().unwrap();
        assert!(gpu_ms > 0.0, "{csv}");
        // GPU image against the f64 reference of the same cut and smoothing.
        let psnr_same: f64 = row[12].parse().unwrap();
        assert!(psnr_same >= 40.0, "{csv}");
    }
}
