//! `strata render --mode adaptive|adaptive-mip`: the real binary renders a phantom store's
//! fixed cut with the adaptive pass on the GPU (lavapipe) and with `--reference`, its f64 CPU
//! transcription (render/src/passes/adaptive/transcription.rs), and the two PNGs agree (DVR, MIP and
//! shaded DVR); the command reports the pass's sampling operations.

use crate::common;

use common::render_level0;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;

// The sampler's 8-bit filter weights on lavapipe would differ from f64 trilinear by more than
// the bound below; the exact (manual) trilinear is what the CPU computes.
const EXACT: &str = "--exact-trilinear";

/// `render_level0` with the exact trilinear filter.
fn render(store: &std::path::Path, out: &std::path::Path, extra: &[&str]) -> (Vec<u8>, String) {
    let args: Vec<&str> = extra.iter().copied().chain([EXACT]).collect();
    render_level0(store, out, &args)
}

#[test]
fn adaptive_dvr_and_mip_on_the_gpu_match_their_cpu_transcription() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("phantom.strata");
    Phantom::cube(96)
        .write_store(&store, &ImportOptions::default())
        .unwrap();
    for (mode, extra) in [
        ("adaptive", None),
        ("adaptive-mip", None),
        ("adaptive", Some("--shading")),
    ] {
        let args: Vec<&str> = ["--mode", mode].into_iter().chain(extra).collect();
        let (gpu, stderr) = render(&store, &dir.path().join("gpu.png"), &args);
        assert!(stderr.contains("sampling operations"), "{mode}: {stderr}");
        let reference: Vec<&str> = args.iter().copied().chain(["--reference"]).collect();
        let (cpu, _) = render(&store, &dir.path().join("cpu.png"), &reference);
        let mode = format!("{mode} {}", extra.unwrap_or(""));
        assert_eq!(gpu.len(), cpu.len());
        let shown = cpu.chunks(4).filter(|p| p[3] > 8).count();
        assert!(
            shown > 96 * 96 / 20,
            "{mode}: image nearly empty ({shown} pixels)"
        );
        // The same samples in f32 and f64, through the same tables (render/tests/adaptive.rs
        // bounds the colours to 1e-5, 1e-4 shaded); a block face within f32 rounding of a sample may
        // still send one ray's oracle lookup to the neighbouring block: one 8-bit step, on
        // at most 1 % of the pixels.
        let off: Vec<i32> = gpu
            .iter()
            .zip(&cpu)
            .map(|(&g, &c)| (g as i32 - c as i32).abs())
            .collect();
        let worst = off.iter().copied().max().unwrap_or(0);
        let differing = off.chunks(4).filter(|p| p.iter().any(|&d| d > 0)).count();
        eprintln!("{mode}: worst channel step {worst}, {differing} pixels differ");
        assert!(
            worst <= 1 && differing * 100 <= 96 * 96,
            "{mode}: {worst}, {differing}"
        );
    }
    // MIP and DVR are different images of the same store.
    let (dvr, _) = render(&store, &dir.path().join("a.png"), &["--mode", "adaptive"]);
    let (mip, _) = render(
        &store,
        &dir.path().join("b.png"),
        &["--mode", "adaptive-mip"],
    );
    assert_ne!(dvr, mip);
}
