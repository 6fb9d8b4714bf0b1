//! `strata render --progressive N`: the mean of N jittered frames of a still view
//! (render/src/passes/progressive.rs), closer to the f64 reference of the same model than one frame.
//! 64² on lavapipe, a 40³ phantom.

use std::path::Path;
use std::process::{Command, Output};

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

fn rgba(path: &Path) -> Vec<u8> {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgba8()
        .into_raw()
}

fn rmse(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len());
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
        .sum();
    (sum / a.len() as f64).sqrt()
}

#[test]
fn the_mean_of_jittered_frames_is_closer_to_the_reference_than_one_frame() {
    let dir = tempfile::tempdir().unwrap();
    let nrrd = dir.path().join("p.nrrd");
    let store = dir.path().join("p.strata");
    let o = strata(&["sample", "--size", "40", "--out", nrrd.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let o = strata(&["import", nrrd.to_str().unwrap(), store.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let store = store.to_str().unwrap();
    // A coarse step (2 voxels) so that one frame's sampling error is well above 8-bit
    // rounding.
    let common = [
        "--size",
        "64x64",
        "--step",
        "2",
        "--shading",
        "--azimuth",
        "35",
        "--elevation",
        "25",
    ];
    let render = |name: &str, extra: &[&str]| -> (Vec<u8>, String) {
        let out = dir.path().join(name);
        let mut args = vec!["render", store, "--out", out.to_str().unwrap()];
        args.extend(common);
        args.extend_from_slice(extra);
        let o = strata(&args);
        assert!(o.status.success(), "{}", text(&o));
        (rgba(&out), text(&o))
    };
    let (reference, _) = render("reference.png", &["--reference"]);
    let (plain, _) = render("plain.png", &["--up-front", "--no-jitter"]);
    let (one, _) = render("one.png", &["--progressive", "1"]);
    let (mean, log) = render("mean.png", &["--progressive", "32"]);
    assert!(log.contains("mean of 32 jittered frames"), "{log}");
    assert!(log.contains("loading --level up front"), "{log}");
    assert!(
        reference.chunks_exact(4).filter(|p| p[3] > 0).count() > 64 * 64 / 4,
        "image nearly empty"
    );
    let (e_plain, e_one, e_mean) = (
        rmse(&plain, &reference),
        rmse(&one, &reference),
        rmse(&mean, &reference),
    );
    eprintln!(
        "--progressive: RMSE against --reference: un-jittered {e_plain:.3}, 1 jittered frame \
         {e_one:.3}, mean of 32 {e_mean:.3}"
    );
    // Measured on lavapipe: un-jittered 2.61, one jittered frame 2.64, mean of 32 0.66 (8-bit
    // RMSE). 1/√32 on the noise part would give ≈ e_one / 5.7 down to the floor; a factor 2
    // leaves room for the floor (bias at this step, 8-bit rounding, the reference's own step).
    assert!(e_mean < e_one / 2.0, "{e_mean} vs one frame {e_one}");
    assert!(e_mean < e_plain / 2.0, "{e_mean} vs un-jittered {e_plain}");
}
