//! Ambient occlusion from local extinction (issue 37, step 2): the optical model, written once
//! in f64 here (the reference integrates it) and twinned by shaders/ambient_occlusion.wgsl.
//!
//! **Model.** The local ambient occlusion of Hernell et al. 2010 (research note §1), over the
//! whole sphere and with the same extinction as the shadows (shadows.rs):
//!
//! ```text
//! AO(x) = (1/K) Σ_k exp(−∫_{r₀}^{min(R, r₁(ν_k))} σ(x + s·ν_k) ds)
//! colour = c · (k_a·AO + direct terms)      (shadows.rs, scattering.rs)
//! ```
//!
//! a K-point quadrature of (1/4π)∮ exp(−∫₀ᴿ σ) dν over [`DIRECTIONS`] fixed directions ν_k of
//! a spherical Fibonacci set in patient axes ([`direction`]), the same in both renderers, so
//! they integrate exactly the same estimator and differ only in the step. R is
//! [`Occlusion::radius_mm`]; r₀ is the shadow bias ([`SHADOW_START_VOXELS`]) for the
//! shadows' reason (a sample a main step deep inside a surface must not be occluded by the
//! surface's own interpolation band, which the GPU and the reference cross at different
//! depths); r₁ is where the ray leaves the cropped box or the clip plane's half-space:
//! cut-away matter occludes nothing, as it casts no shadow. AO scales only the ambient term
//! k_a; the direct terms are the shadows' business (V) and unaffected.
//!
//! Why this and not Schlegel's summed-area table: the SAT's box kernels need a float32 volume
//! of σ per TF edit and are exact only for axis-aligned boxes; a handful of short shadow rays
//! reuse the exact shadow ray's march (shaders/shadows.wgsl `shadow_span`: page cache, empty
//! skipping, τ cut) and the reference's `transmittance`, so the GPU and the f64 reference
//! integrate one model with no extra resource. Consequences worth knowing: the whole sphere,
//! not the hemisphere around −∇, so a sample on a flat opaque face sees about half the
//! directions blocked (AO ≈ ½), a crease less, an edge more (a hemisphere would need a choice
//! of side that flips with the gradient's sign, a discontinuity the two renderers would take
//! at different samples); and R ≤ r₀ is no occlusion at all (every ray is empty), so the
//! effect is continuous as R → 0 and exactly off below the bias.
//!
//! **Discretisation.** Midpoint samples at the shadow step ([`crate::model::settings::Shadows::step`]
//! voxels on the GPU, ¼ of it in the reference: [`REFERENCE_SHADOW_REFINEMENT`]), the GPU's
//! rays stopping at τ > [`crate::model::shadows::GPU_TAU_MAX`] (an error < 10⁻³ of the ambient term
//! per ray) and skipping empty pages as the main ray does: a sample whose neighbourhood is
//! empty pays K empty-page lookups, and empty pages are never shaded at all.
//!
//! **Cost.** K · (R − r₀) / step field samples per shaded sample on the GPU (16 · 4 = 64 at
//! R = 5 voxels, step 1); the reference takes 4× as many per shaded sample, which makes it the
//! slow part of the tests (render/tests/cinematic.rs: 0.1-4 s per 64² reference of the 32³
//! phantom on two shared cores, up to 10 s while other builds load them; primary reference
//! step ¼ of the GPU's).
//!
//! **GPU cost.** `STRATA_BENCH_EFFECTS=occlusion,scattering STRATA_BENCH_SIZE=256 cargo bench
//! -p strata-render --bench raycast` (256³ VTK-peer phantom, 256², DVR step 0.5, shaded, key
//! light (0.5, 0.5, 0.7), empty skipping and early termination on, R = 3 voxels, step 1 voxel),
//! lavapipe (llvmpipe, LLVM 15) on the shared 2-core machine, 2026-12-05: off 210.1 ms, never
//! built 218.9 ms (1.04: noise of the shared machine, the variant has no occlusion code), on
//! 2101.1 ms: 10.0× the unoccluded frame, about what 16 · 2 = 32 extra fetches per shaded sample
//! predict. Like exact shadows, it is a cost the adaptive pass (fewer shaded samples) and a
//! cached or SAT variant would have to earn back.

use glam::DVec3;

use crate::model::shadows::transmittance;
pub use crate::model::shadows::{REFERENCE_SHADOW_REFINEMENT, SHADOW_START_VOXELS};

/// K, the number of occlusion rays per shaded sample.
pub const DIRECTIONS: u32 = 16;

/// The golden angle π(3 − √5), the Fibonacci set's azimuth increment.
pub const GOLDEN_ANGLE: f64 = 2.399_963_229_728_653;

/// The k-th occlusion direction (unit, patient axes): z_k = 1 − (2k + 1)/K, azimuth k times
/// the golden angle (equal-area bands, so each direction stands for 4π/K of the sphere).
pub fn direction(k: u32) -> DVec3 {
    let z = 1.0 - (2.0 * k as f64 + 1.0) / DIRECTIONS as f64;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = k as f64 * GOLDEN_ANGLE;
    DVec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// AO at a sample (module doc): `radius` and `r0` in mm, `step` the march's step (mm),
/// `tau_max` the optical depth at which a ray stops. `exit(ν)` is r₁ along ν (mm; ≤ 0 if the
/// ray does not run inside), `sigma(ν, s)` the extinction per mm at distance s along ν.
pub fn occlusion(
    radius: f64,
    r0: f64,
    step: f64,
    tau_max: f64,
    mut exit: impl FnMut(DVec3) -> f64,
    mut sigma: impl FnMut(DVec3, f64) -> f64,
) -> f64 {
    let sum: f64 = (0..DIRECTIONS)
        .map(|k| {
            let nu = direction(k);
            let end = exit(nu).min(radius);
            transmittance(r0, end, step, tau_max, |s| sigma(nu, s))
        })
        .sum();
    sum / DIRECTIONS as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_directions_are_unit_and_balanced() {
        let mut mean = DVec3::ZERO;
        for k in 0..DIRECTIONS {
            let d = direction(k);
            assert!((d.length() - 1.0).abs() < 1e-12, "{k}: {d:?}");
            mean += d / DIRECTIONS as f64;
        }
        // A balanced set: no preferred side (each axis' mean well under one direction's 1/K).
        assert!(mean.length() < 0.5 / DIRECTIONS as f64, "{mean:?}");
        assert!((GOLDEN_ANGLE - std::f64::consts::PI * (3.0 - 5f64.sqrt())).abs() < 1e-15);
    }

    #[test]
    fn a_homogeneous_medium_occludes_as_beer_lambert() {
        // Inside a medium of σ everywhere within reach: every ray e^{−σ(R − r₀)}
        // (research note §4, hard case 5, with the bias).
        let ao = occlusion(5.0, 1.0, 0.3, 100.0, |_| 1e9, |_, _| 0.2);
        assert!((ao - (-0.2f64 * 4.0).exp()).abs() < 1e-12, "{ao}");
    }

    #[test]
    fn a_radius_within_the_bias_is_no_occlusion() {
        for r in [0.0, 0.5, 1.0] {
            assert_eq!(occlusion(r, 1.0, 0.25, 7.0, |_| 1e9, |_, _| 50.0), 1.0);
        }
        // And it grows continuously from there.
        let ao = occlusion(1.01, 1.0, 0.25, 7.0, |_| 1e9, |_, _| 1.0);
        assert!((ao - (-0.01f64).exp()).abs() < 1e-12, "{ao}");
    }

    #[test]
    fn an_opaque_half_space_blocks_the_directions_that_enter_it() {
        // Matter at z < 0 (opaque), the sample on its face: rays with ν_z < 0 go in, the
        // others see nothing; K/2 of the set have ν_z < 0.
        let ao = occlusion(
            4.0,
            0.0,
            0.1,
            30.0,
            |_| 1e9,
            |nu, s| if nu.z * s < 0.0 { 1e3 } else { 0.0 },
        );
        assert!((ao - 0.5).abs() < 1e-9, "{ao}");
    }

    #[test]
    fn the_exit_ends_each_ray() {
        // Everything beyond 2 mm is cut away: only [r₀, 2] absorbs.
        let ao = occlusion(10.0, 0.5, 0.1, 100.0, |_| 2.0, |_, _| 0.3);
        assert!((ao - (-0.3f64 * 1.5).exp()).abs() < 1e-12, "{ao}");
    }
}
