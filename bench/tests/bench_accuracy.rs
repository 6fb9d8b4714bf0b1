//! `strata-bench accuracy --sweep cinematic` end to end on a tiny phantom: every cinematic
//! knob of both key-lit models in the CSV, each model with its own Pareto front, errors
//! against the reference of the same lit model, and the progressive mean converging.

use crate::common;

#[test]
fn cinematic_sweep_for_a_small_phantom() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().to_str().unwrap();
    let o = common::strata(&[
        "accuracy",
        "phantom",
        "--phantom-size",
        "32",
        "--size",
        "32x32",
        "--frames",
        "1",
        "--sweep",
        "cinematic",
        "--out-dir",
        out_dir,
    ]);
    let text = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{text}");
    let csv = std::fs::read_to_string(dir.path().join("accuracy-phantom32.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .unwrap_or_else(|| panic!("no column {name}: {header:?}"))
    };
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let (family, model, shadows, frames) = (
        col("family"),
        col("model"),
        col("shadows"),
        col("progressive_frames"),
    );
    let (psnr, rmse, pareto) = (col("psnr_db"), col("rmse"), col("pareto"));
    let lit_models = [
        "lit (key light + shadows)",
        "cinematic (+ occlusion + scattering)",
    ];
    assert!(rows.iter().all(|r| lit_models.contains(&r[model])), "{csv}");
    for m in lit_models {
        let of = |f: &str| -> Vec<&Vec<&str>> {
            rows.iter()
                .filter(|r| r[model] == m && r[family] == f)
                .collect()
        };
        assert!(of("shadow step (exact)")
            .iter()
            .all(|r| r[shadows] == "exact"));
        assert!(of("light-cache resolution").len() >= 2, "{csv}");
        assert!(of("light-cache resolution")
            .iter()
            .all(|r| r[shadows] == "cache"));
        let progressive = of("progressive frames");
        let counts: Vec<&str> = progressive.iter().map(|r| r[frames]).collect();
        assert_eq!(counts, ["1", "4", "16", "64"], "{csv}");
        // The mean of 64 jittered frames is closer to the model's reference than one frame.
        let e = |r: &Vec<&str>| r[rmse].parse::<f64>().unwrap();
        assert!(e(progressive[3]) < e(progressive[0]), "{csv}");
        // A front of its own in every model.
        assert!(
            rows.iter().any(|r| r[model] == m && r[pareto] == "true"),
            "{csv}"
        );
        // Against the reference of the same lit model, the finest exact shadows agree closely.
        let best = of("shadow step (exact)")
            .iter()
            .map(|r| r[psnr].parse::<f64>().unwrap())
            .fold(0.0, f64::max);
        assert!(best >= 40.0, "{m}: best exact-shadow PSNR {best} dB\n{csv}");
    }
    assert!(!of_family(&rows, family, "occlusion radius").is_empty());
    assert!(dir.path().join("accuracy-phantom32.png").is_file());
    let md = std::fs::read_to_string(dir.path().join("accuracy-phantom32.md")).unwrap();
    assert!(md.contains("Pareto front of the row's model"), "{md}");
}

fn of_family<'a>(rows: &'a [Vec<&'a str>], family: usize, name: &str) -> Vec<&'a Vec<&'a str>> {
    rows.iter().filter(|r| r[family] == name).collect()
}
