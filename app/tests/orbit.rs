//! `strata render --orbit N`: an orbit movie as N PNG frames in a folder (and an MP4 when
//! ffmpeg is there). Small images on lavapipe.

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

fn phantom_store(dir: &Path) -> String {
    let nrrd = dir.join("p.nrrd");
    let store = dir.join("p.strata");
    let o = strata(&["sample", "--size", "40", "--out", nrrd.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let o = strata(&["import", nrrd.to_str().unwrap(), store.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    store.to_str().unwrap().to_string()
}

fn rgb(path: &Path) -> image::RgbImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8()
}

fn mean_abs_difference(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    a.as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| (*x as f64 - *y as f64).abs())
        .sum::<f64>()
        / a.as_raw().len() as f64
}

#[test]
fn an_orbit_writes_n_frames_around_the_volume_and_each_is_that_azimuths_render() {
    let dir = tempfile::tempdir().unwrap();
    let store = phantom_store(dir.path());
    let movie = dir.path().join("movie");
    let common = ["--size", "64x48", "--no-jitter", "--elevation", "15"];
    let mut args = vec!["render", store.as_str(), "--orbit", "4"];
    args.extend(common);
    args.extend(["--out", movie.to_str().unwrap()]);
    let o = strata(&args);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("wrote 4 frames"), "{}", text(&o));
    let frames: Vec<image::RgbImage> = (0..4)
        .map(|i| rgb(&movie.join(format!("frame-{i:04}.png"))))
        .collect();
    assert!(!movie.join("frame-0004.png").exists(), "exactly 4 frames");
    for f in &frames {
        assert_eq!(f.dimensions(), (64, 48));
        assert!(f.as_raw().iter().any(|&v| v > 16), "a blank frame");
    }
    // The phantom is not symmetric under a quarter turn: consecutive frames differ.
    assert!(
        mean_abs_difference(&frames[0], &frames[1]) > 1.0,
        "frames 0 and 1 look alike"
    );
    // Frame 1 is azimuth 90°: the same as a single render from there (same streaming
    // renderer, jitter off, both converged; 0.5 of 255 allows only rounding).
    let single = dir.path().join("ninety.png");
    let mut args = vec!["render", store.as_str(), "--azimuth", "90"];
    args.extend(common);
    args.extend(["--out", single.to_str().unwrap()]);
    let o = strata(&args);
    assert!(o.status.success(), "{}", text(&o));
    let difference = mean_abs_difference(&frames[1], &rgb(&single));
    assert!(
        difference < 0.5,
        "frame 1 differs from azimuth 90 by {difference}"
    );
}

#[test]
fn bad_orbit_arguments_are_refused_naming_the_flag() {
    let dir = tempfile::tempdir().unwrap();
    let store = phantom_store(dir.path());
    let o = strata(&["render", &store, "--orbit", "0", "--out", "x"]);
    assert!(!o.status.success());
    assert!(text(&o).contains("--orbit 0"), "{}", text(&o));
    let file = dir.path().join("taken.png");
    std::fs::write(&file, b"not a folder").unwrap();
    let o = strata(&[
        "render",
        &store,
        "--orbit",
        "3",
        "--out",
        file.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("is a file"), "{}", text(&o));
    let o = strata(&[
        "render",
        &store,
        "--orbit",
        "3",
        "--reference",
        "--out",
        "y",
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("--orbit streams"), "{}", text(&o));
}
