//! Single scattering of the key light with a Henyey-Greenstein phase and Exposure Render's
//! hybrid rule (issue 37, step 2): the model, written once in f64 here (the reference
//! integrates it) and twinned by shaders/scattering.wgsl.
//!
//! **Model.** A lit sample (shadows.rs for n, ω_l, w, V, I; ambient_occlusion.rs for AO; ω the
//! unit view-ray direction, away from the eye):
//!
//! ```text
//! colour = c·(k_a·AO + I·V·k_d·[P·(1 + (n·ω_l⁺ − 1)·w) + (1 − P)·4π·p_g(ω_l·ω)])
//!        + I·V·k_s·(n·h)⁺^shininess·w·P
//! p_g(μ) = (1 − g²) / (4π·(1 + g² − 2gμ)^{3/2})            (∮ p_g = 1, p_0 = 1/4π)
//! P(m)   = 1 − exp(−25·b³·m),  m = |∇f|·flatness scale (TF-range fractions per voxel)
//! ```
//!
//! P is Exposure Render's probability of a BRDF event (Kroes et al. 2012, research note §3):
//! a deterministic raycaster that weights the two lobes by P and 1 − P equals ER's stochastic
//! choice in expectation. b is [`Scattering::blend`] (ER's gradient factor): 0 is volume-like
//! everywhere, 1 surface-like wherever the gradient exceeds a few % of the TF range per voxel
//! (m = 0.05 gives P = 0.71; bone edges, m ≳ 0.3, P ≈ 1). m is ER's normalised gradient
//! magnitude with the TF range as the norm, the measure the flatness weight w already uses,
//! so both renderers read it off the same gradient. The opacity factor of ER's
//! "opacity-modulated" variant is left out: the compositor already weights by α.
//!
//! With μ = ω_l·ω, g > 0 brightens back-lit samples (light behind the sample, shining towards
//! the eye: forward scattering). The phase is normalised as VTK does (4π·p_g: isotropic = 1),
//! so at g = 0 a volume-like sample is as bright as a diffuse face turned to the light. The
//! albedo is the TF colour times k_d, the diffuse coefficient: the phase replaces the BRDF's
//! diffuse lobe in proportion to 1 − P and the highlight fades with it. V is the existing
//! shadow term (exact rays or the cache; 1 with shadows off): single scattering of the key
//! light attenuated on its way in. Scattering off is P = 1, i.e. shadows.rs's `shade_lit`.
//!
//! The denominator is evaluated as (1 − g)² + 2g(1 − μ), equal to 1 + g² − 2gμ but without
//! its cancellation near g → 1, μ → 1 (f32 on the GPU); settings.rs bounds |g| ≤ 0.99, where
//! the peak is 4π·p = (1 + g)/(1 − g)² ≈ 2·10⁴ and f32's error in μ (6·10⁻⁸) moves it by
//! 0.1 %.
//!
//! **GPU cost.** The phase and the weight are a handful of flops per shaded sample on values
//! the BRDF already has, no fetch. `STRATA_BENCH_EFFECTS=occlusion,scattering
//! STRATA_BENCH_SIZE=256 cargo bench -p strata-render --bench raycast` (256³ VTK-peer phantom,
//! 256², DVR step 0.5, shaded, key light (0.5, 0.5, 0.7), no shadows, g = 0.5, blend 0.5),
//! lavapipe (llvmpipe, LLVM 15) on the shared 2-core machine, 2026-12-05: off 213.3 ms, never
//! built 215.5 ms, on 215.3 ms (1.009×, within the machine's noise). With shadows on, each
//! sample also pays the shadows' row (shadows.rs).

use glam::DVec3;

use crate::model::settings::{Scattering, Shading};
use crate::model::shadows::brdf_terms;

/// The Henyey-Greenstein phase function p_g(μ), normalised over the sphere.
pub fn phase_hg(g: f64, mu: f64) -> f64 {
    let denom = (1.0 - g) * (1.0 - g) + 2.0 * g * (1.0 - mu);
    (1.0 - g * g) / (4.0 * std::f64::consts::PI * denom * denom.sqrt())
}

/// Exposure Render's surface (BRDF) weight P for gradient factor `blend` and normalised
/// gradient magnitude `m`.
pub fn surface_weight(blend: f64, m: f64) -> f64 {
    1.0 - (-25.0 * blend * blend * blend * m).exp()
}

/// The model's colour of a sample (module doc); arguments as shadows.rs's `shade_lit`, plus
/// the ambient occlusion `ao` (1 without it) and the scattering (None: the BRDF alone).
#[allow(clippy::too_many_arguments)]
pub fn shade_cinematic(
    color: [f64; 3],
    gradient_patient: DVec3,
    dir: DVec3,
    light: DVec3,
    shading: &Shading,
    intensity: f64,
    visibility: f64,
    flatness_scale: f64,
    ao: f64,
    scattering: Option<&Scattering>,
) -> [f64; 3] {
    let b = brdf_terms(gradient_patient, dir, light, shading, flatness_scale);
    let (surface, volume) = match scattering {
        Some(sc) => {
            let p = surface_weight(sc.blend, b.gradient_fraction);
            let phase = 4.0 * std::f64::consts::PI * phase_hg(sc.g, light.dot(dir));
            (p, (1.0 - p) * phase)
        }
        None => (1.0, 0.0),
    };
    let direct = intensity * visibility;
    let gain = shading.ambient as f64 * ao
        + direct * shading.diffuse as f64 * (surface * (1.0 + (b.ndl - 1.0) * b.w) + volume);
    let highlight = direct * shading.specular as f64 * b.spec * b.w * surface;
    color.map(|c| c * gain + highlight)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::shadows::shade_lit;
    use std::f64::consts::PI;

    #[test]
    fn g_zero_is_isotropic() {
        for mu in [-1.0, -0.3, 0.0, 0.7, 1.0] {
            assert!((phase_hg(0.0, mu) - 1.0 / (4.0 * PI)).abs() < 1e-15, "{mu}");
        }
    }

    #[test]
    fn the_phase_integrates_to_one_and_matches_the_textbook_form() {
        for g in [-0.9, -0.5, 0.0, 0.3, 0.8, 0.99] {
            // ∮ p dΩ = 2π ∫_{-1}^{1} p(μ) dμ, midpoint rule fine enough for the peak at 0.99.
            let n = 2_000_000;
            let h = 2.0 / n as f64;
            let integral: f64 = (0..n)
                .map(|i| phase_hg(g, -1.0 + (i as f64 + 0.5) * h) * h)
                .sum::<f64>()
                * 2.0
                * PI;
            assert!((integral - 1.0).abs() < 1e-4, "g {g}: {integral}");
            for mu in [-1.0, -0.2, 0.5, 0.999] {
                let textbook = (1.0 - g * g) / (4.0 * PI * (1.0 + g * g - 2.0 * g * mu).powf(1.5));
                let p = phase_hg(g, mu);
                assert!((p - textbook).abs() <= 1e-9 * textbook, "{g} {mu}");
            }
        }
        // Forward scattering: g > 0 peaks at μ = 1 (light behind the sample).
        assert!(phase_hg(0.6, 1.0) > phase_hg(0.6, -1.0));
    }

    #[test]
    fn surface_weight_follows_exposure_render() {
        assert_eq!(surface_weight(0.0, 10.0), 0.0);
        assert_eq!(surface_weight(0.7, 0.0), 0.0);
        assert!((surface_weight(1.0, 0.05) - (1.0 - (-1.25f64).exp())).abs() < 1e-15);
        assert!(surface_weight(1.0, 0.3) > 0.999);
    }

    #[test]
    fn without_scattering_or_occlusion_it_is_shade_lit() {
        let s = Shading::default();
        let dir = DVec3::new(0.3, -0.2, 0.9).normalize_or_zero();
        let light = DVec3::new(-0.5, 0.6, 0.2).normalize_or_zero();
        for g in [
            DVec3::new(1.0, 2.0, -3.0),
            DVec3::ZERO,
            DVec3::new(0.0, 0.0, 1e-3),
        ] {
            for v in [0.0, 0.4, 1.0] {
                let a = shade_lit([0.8, 0.5, 0.2], g, dir, light, &s, 0.9, v, 0.01);
                let b =
                    shade_cinematic([0.8, 0.5, 0.2], g, dir, light, &s, 0.9, v, 0.01, 1.0, None);
                assert_eq!(a, b, "{g:?} {v}");
            }
        }
    }

    #[test]
    fn occlusion_scales_only_the_ambient_term() {
        let s = Shading::default();
        let dir = DVec3::Z;
        // Fully shadowed: only k_a·AO·c remains.
        let c = shade_cinematic(
            [1.0, 0.5, 0.25],
            DVec3::new(0.0, 0.0, -5.0),
            dir,
            DVec3::new(0.0, 0.6, -0.8),
            &s,
            1.0,
            0.0,
            1.0,
            0.4,
            Some(&Scattering { g: 0.5, blend: 0.3 }),
        );
        let a = s.ambient as f64 * 0.4;
        for (got, want) in c.iter().zip([a, 0.5 * a, 0.25 * a]) {
            assert!((got - want).abs() < 1e-15, "{c:?}");
        }
    }

    #[test]
    fn volume_like_isotropic_scattering_ignores_the_light_direction() {
        // b = 0: P = 0, the phase alone, and at g = 0 it is 1 whatever the angle: the direct
        // term is I·V·k_d·c for any light.
        let s = Shading::default();
        let sc = Scattering { g: 0.0, blend: 0.0 };
        let dir = DVec3::new(0.0, 0.6, 0.8);
        let grad = DVec3::new(3.0, -1.0, 2.0);
        let want = (s.ambient + s.diffuse) as f64;
        for light in [DVec3::X, -DVec3::Z, dir, -dir] {
            let c = shade_cinematic(
                [1.0; 3],
                grad,
                dir,
                light,
                &s,
                1.0,
                1.0,
                1.0,
                1.0,
                Some(&sc),
            );
            assert!((c[0] - want).abs() < 1e-12, "{light:?}: {c:?}");
        }
    }
}
