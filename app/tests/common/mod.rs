//! What the fixed-cut render tests share: the real binary, and one PNG rendered from a store's
//! level 0 loaded up front (render_traversal.rs, render_adaptive.rs).

pub mod orthanc;

use std::path::Path;
use std::process::{Command, Output};

pub fn strata(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_strata"))
        .args(args)
        .output()
        .expect("strata runs")
}

/// `strata render STORE --size 96x96 --up-front --level 0 --out OUT EXTRA…`: its RGBA pixels
/// and its stderr; panics (naming the arguments) when the command fails.
pub fn render_level0(store: &Path, out: &Path, extra: &[&str]) -> (Vec<u8>, String) {
    let mut args = vec![
        "render",
        store.to_str().unwrap(),
        "--size",
        "96x96",
        "--up-front",
        "--level",
        "0",
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let o = strata(&args);
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "render {extra:?} failed: {stderr}");
    let pixels = image::open(out)
        .unwrap_or_else(|e| panic!("{}: {e}", out.display()))
        .to_rgba8()
        .into_raw();
    (pixels, stderr)
}
