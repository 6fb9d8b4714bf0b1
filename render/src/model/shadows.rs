//! Volumetric shadows from the key light, exact mode (issue 37, step 1): the optical model,
//! written once in f64 here (the reference integrates it) and twinned by shaders/shadows.wgsl.
//!
//! **Model.** A shaded sample at x with unit gradient normal n (two-sided: turned to face the
//! viewer) and ω_l the unit direction towards the key light (settings.rs [`LightDirection`]):
//!
//! ```text
//! colour = c · (k_a + I·V·k_d·(1 + (n·ω_l⁺ − 1)·w)) + I·V·k_s·(n·h)⁺^shininess·w
//! V(x)   = exp(−∫_{r₀}^{r₁} σ(x + s·ω_l) ds),  σ = −ln(1 − min(α_TF, 1 − 10⁻⁶)) / unit
//! ```
//!
//! k_a, k_d, k_s, shininess are [`Shading`]'s, I the light's intensity, w the existing
//! flatness weight (a sample with no gradient is lit as facing the light, as before), h the
//! Blinn half vector of ω_l and the view direction. The ambient term is never shadowed. r₁ is
//! where the shadow ray leaves the cropped box or the clip plane's half-space: cut-away matter
//! casts no shadow and light enters through the cut (vtk.js's rule, research note §2). The
//! opacity clamp is the main ray's (raycast.wgsl), so a fully opaque voxel transmits 10⁻⁶ per
//! voxel rather than 0, the same in both renderers. Overlays do not absorb light.
//!
//! r₀ = [`SHADOW_START_VOXELS`] finest voxels is the shadow bias: without it a sample just
//! inside an opaque surface would be shadowed by the surface's own interpolation band between
//! it and the surface (the GPU's sample sits up to a main step deep, the reference's 1/8 of
//! that, so they would disagree by the whole direct term). It is part of the model, so the
//! reference uses it too and the images agree; its cost is that occluders thinner than r₀ in
//! front of a sample along ω_l do not shadow it.
//!
//! Ambient occlusion (ambient_occlusion.rs: k_a becomes k_a·AO) and single scattering
//! (scattering.rs: the direct term blends this BRDF with a phase function) extend this model;
//! with both off it is exactly the above.
//!
//! With the headlight, ω_l is the ray's own reversed direction and the model reproduces the
//! old Blinn-Phong exactly when V = 1 (n·h = n·ω_l = |n·d|).
//!
//! **Discretisation.** Both renderers take midpoint samples on segments of the shadow step
//! from r₀ (the last cut short at r₁): the GPU at [`Shadows::step`] voxels, the reference at
//! that step / [`REFERENCE_SHADOW_REFINEMENT`]. The GPU stops a shadow ray once its optical
//! depth passes [`GPU_TAU_MAX`] (V < 10⁻³, under half an 8-bit step of any colour ≤ 1) and
//! skips empty and not-resident regions as the main ray does (their flags are conservative:
//! an empty page has α = 0 at every sample); the reference samples everything up to τ = 30.
//! With [`crate::RenderSettings::jitter`] the GPU moves each segment's sample from the
//! midpoint to a per-pixel, per-frame fraction of the step (shadows.wgsl `shadow_jitter`), so
//! that frames averaged by progressive.rs converge to the fine-step V; comparisons run
//! without jitter and keep the midpoint.
//!
//! **Reference cost.** Every shaded reference sample traces a shadow ray of up to
//! (box diagonal) / (step / 4) field samples: for an N³ volume, a W² image and a primary
//! reference step of quality/8 voxels this is O(W² · N/(quality/8) · N·√3/(step/4)) samples in
//! the worst case (a ray shaded along its whole length), quadratic per ray. Early
//! termination at the settings' threshold and the shadow ray's own exit at τ = 30 bound it in
//! practice; the tests keep it to 64² images of 32³-48³ volumes (seconds on two cores). A
//! transmittance volume (V once per grid point, interpolated) would make it linear: the cache
//! mode's reference is exactly that (light_cache.rs), for the cache's own model. Measured: the
//! tests' references (64², 32³-40³, shadow step 1 → ¼) take 0.3-5.6 s each on two cores.
//!
//! **GPU cost.** `STRATA_BENCH_EFFECTS=shadows cargo bench -p strata-render --bench raycast`
//! (256³ VTK-peer phantom, 256², DVR step 0.5, shaded, key light (0.5, 0.5, 0.7), empty
//! skipping and early termination on, shadow step 1 voxel), lavapipe on the shared 2-core
//! machine, 2026-12-05: off 461 ms, never built 483 ms, exact shadows 5079 ms: 11.0× the
//! unshadowed frame. That is what the research note's §5 expected of exact shadow rays: the
//! cost the cache mode and the adaptive pass have to earn back.

use glam::DVec3;

use crate::model::blinn_phong::smoothstep;
use crate::model::camera::CameraBasis;
use crate::model::settings::{KeyLight, LightDirection, RenderSettings, Shading};

/// The shadow bias r₀, in finest voxels (see the module doc).
pub const SHADOW_START_VOXELS: f64 = 1.0;
/// The largest opacity a sample may have, as on the main ray (raycast.wgsl's clamp).
pub const OPACITY_CLAMP: f64 = 0.999999;
/// Optical depth at which a GPU shadow ray stops: V = e⁻⁷ < 10⁻³.
pub const GPU_TAU_MAX: f64 = 7.0;
/// Optical depth at which a reference shadow ray stops: V = e⁻³⁰, nothing an image shows.
pub const REFERENCE_TAU_MAX: f64 = 30.0;
/// The reference's shadow step is the GPU's divided by this.
pub const REFERENCE_SHADOW_REFINEMENT: f64 = 4.0;
/// Longest GPU shadow ray in steps (a guard against a step that the settings let through
/// being far below the volume's size; 2^20 steps of 0.05 voxel cross 52k voxels).
pub const MAX_SHADOW_STEPS: u32 = 1 << 20;

/// Unit vector towards the key light for a ray of unit direction `ray_dir` (patient space).
pub fn light_towards(light: &KeyLight, basis: &CameraBasis, ray_dir: DVec3) -> DVec3 {
    match light.direction {
        LightDirection::Headlight => -ray_dir,
        LightDirection::Camera(v) => {
            (v[0] * basis.right + v[1] * basis.up - v[2] * basis.forward).normalize_or_zero()
        }
        LightDirection::Patient(v) => DVec3::from(v).normalize_or_zero(),
    }
}

/// Extinction per mm of a sample of TF opacity `alpha` (opacity per finest voxel of `unit`
/// mm), with the main ray's clamp.
pub fn extinction(alpha: f64, unit: f64) -> f64 {
    -(1.0 - alpha.clamp(0.0, OPACITY_CLAMP)).ln() / unit
}

/// V along a shadow ray from distance `start` to `end` (mm), midpoint rule at `step`
/// (the last segment cut at `end`), stopping once the optical depth passes `tau_max`.
/// `sigma_at(s)` is the extinction per mm at distance s along the ray.
pub fn transmittance(
    start: f64,
    end: f64,
    step: f64,
    tau_max: f64,
    mut sigma_at: impl FnMut(f64) -> f64,
) -> f64 {
    let mut tau = 0.0;
    let mut s = start;
    while s < end {
        let length = step.min(end - s);
        tau += sigma_at(s + 0.5 * length) * length;
        if tau > tau_max {
            break;
        }
        s += step;
    }
    (-tau).exp()
}

/// The model's colour of a sample (module doc): `gradient_patient` in physical units per mm,
/// `dir` the unit ray direction, `light` the unit direction towards the light, `visibility`
/// the shadow term V.
#[allow(clippy::too_many_arguments)]
pub fn shade_lit(
    color: [f64; 3],
    gradient_patient: DVec3,
    dir: DVec3,
    light: DVec3,
    shading: &Shading,
    intensity: f64,
    visibility: f64,
    flatness_scale: f64,
) -> [f64; 3] {
    let b = brdf_terms(gradient_patient, dir, light, shading, flatness_scale);
    let direct = intensity * visibility;
    let gain =
        shading.ambient as f64 + direct * shading.diffuse as f64 * (1.0 + (b.ndl - 1.0) * b.w);
    let highlight = direct * shading.specular as f64 * b.spec * b.w;
    color.map(|c| c * gain + highlight)
}

/// The Blinn-Phong pieces of [`shade_lit`] at a sample, shared with scattering.rs's hybrid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BrdfTerms {
    /// (n·ω_l)⁺ (1 without a gradient: lit as facing the light).
    pub ndl: f64,
    /// (n·h)⁺^shininess (0 without a gradient).
    pub spec: f64,
    /// The flatness weight w (0 flat … 1 lit).
    pub w: f64,
    /// |∇| (physical per mm) times the flatness scale: TF-range fractions per finest voxel.
    pub gradient_fraction: f64,
}

/// [`BrdfTerms`] of a sample: arguments as [`shade_lit`]'s.
pub fn brdf_terms(
    gradient_patient: DVec3,
    dir: DVec3,
    light: DVec3,
    shading: &Shading,
    flatness_scale: f64,
) -> BrdfTerms {
    let mag = gradient_patient.length();
    let w = smoothstep(
        crate::model::layout::SHADING_FLAT_BELOW,
        crate::model::layout::SHADING_LIT_ABOVE,
        mag * flatness_scale,
    );
    let (ndl, spec) = if mag > 0.0 {
        let n = gradient_patient / mag;
        let view = -dir;
        // Two-sided: the normal that faces the viewer.
        let n = if n.dot(view) < 0.0 { -n } else { n };
        let half = light + view;
        let ndh = if half.length() > 1e-6 {
            n.dot(half.normalize_or_zero()).max(0.0)
        } else {
            0.0
        };
        (n.dot(light).max(0.0), ndh.powf(shading.shininess as f64))
    } else {
        (1.0, 0.0)
    };
    BrdfTerms {
        ndl,
        spec,
        w,
        gradient_fraction: mag * flatness_scale,
    }
}

/// What the shader needs of the light per frame, in index space (raycast.rs `Params`).
pub(crate) struct GpuLight {
    /// A·ω_l (index-space image of the unit patient direction: t stays in mm), intensity.
    pub light: [f32; 4],
    /// A^{-T}·ω_l, so that ω_l·d_patient = dot(this, d_idx); w: 1 for the headlight.
    pub light_dual: [f32; 4],
    /// Shadow step (mm), shadow bias r₀ (mm), optical depth limit, unused.
    pub shadow: [f32; 4],
    /// The clip plane in index space: kept where dot(xyz, p_idx) + w >= 0 (0 when none).
    pub clip_idx: [f32; 4],
}

pub(crate) fn gpu_light(
    settings: &RenderSettings,
    basis: &CameraBasis,
    geometry: &strata_types::VolumeGeometry,
) -> GpuLight {
    let a = geometry.index_from_patient_linear();
    let m = a.inverse();
    let unit = geometry.finest_spacing_mm();
    let headlight = settings.light.direction == LightDirection::Headlight;
    // The headlight's direction is per ray (the shader takes −d); these are unused then.
    let l = light_towards(&settings.light, basis, basis.forward);
    let l_idx = a * l;
    let dual = m.transpose() * l;
    let clip_idx = match &settings.clip_plane {
        Some(p) => {
            let n = DVec3::from(p.normal).normalize_or_zero();
            let n_idx = m.transpose() * n;
            [
                n_idx.x as f32,
                n_idx.y as f32,
                n_idx.z as f32,
                (n.dot(geometry.origin()) - p.offset_mm) as f32,
            ]
        }
        None => [0.0; 4],
    };
    GpuLight {
        light: [
            l_idx.x as f32,
            l_idx.y as f32,
            l_idx.z as f32,
            settings.light.intensity,
        ],
        light_dual: [
            dual.x as f32,
            dual.y as f32,
            dual.z as f32,
            if headlight { 1.0 } else { 0.0 },
        ],
        shadow: [
            (settings.shadows.step * unit) as f32,
            (SHADOW_START_VOXELS * unit) as f32,
            GPU_TAU_MAX as f32,
            0.0,
        ],
        clip_idx,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::blinn_phong::shade;

    #[test]
    fn the_headlight_unshadowed_is_the_old_blinn_phong() {
        let s = Shading::default();
        let dir = DVec3::new(0.3, -0.2, 0.9).normalize_or_zero();
        for g in [
            DVec3::new(1.0, 2.0, -3.0),
            DVec3::new(-50.0, 0.1, 7.0),
            DVec3::ZERO,
            DVec3::new(0.0, 0.0, 1e-3),
        ] {
            for flat in [0.0, 0.01, 1.0] {
                let old = shade([0.8, 0.5, 0.2], g, dir, &s, flat);
                let new = shade_lit([0.8, 0.5, 0.2], g, dir, -dir, &s, 1.0, 1.0, flat);
                for i in 0..3 {
                    assert!(
                        (old[i] - new[i]).abs() < 1e-12,
                        "{g:?} {flat}: {old:?} {new:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_fully_shadowed_sample_keeps_only_the_ambient_term() {
        let s = Shading::default();
        let dir = DVec3::new(0.0, 0.0, 1.0);
        let c = shade_lit(
            [0.5, 1.0, 0.25],
            DVec3::new(0.0, 0.0, -100.0),
            dir,
            DVec3::new(0.0, 0.6, -0.8),
            &s,
            1.0,
            0.0,
            1.0,
        );
        let a = s.ambient as f64;
        assert_eq!(c, [0.5 * a, a, 0.25 * a]);
    }

    #[test]
    fn a_light_behind_the_surface_lights_nothing_directly() {
        let s = Shading::default();
        // Normal faces the viewer (−z), light comes from behind the surface (+z side).
        let c = shade_lit(
            [1.0; 3],
            DVec3::new(0.0, 0.0, 100.0),
            DVec3::Z,
            DVec3::new(0.0, 0.0, 1.0),
            &s,
            1.0,
            1.0,
            1.0,
        );
        assert!((c[0] - s.ambient as f64).abs() < 1e-12, "{c:?}");
    }

    #[test]
    fn transmittance_of_a_homogeneous_medium_is_beer_lambert() {
        // σ = 0.2/mm over [1, 11.3] mm, any step, last segment short: exp(−σ·10.3).
        for step in [0.1, 0.7, 3.0, 20.0] {
            let v = transmittance(1.0, 11.3, step, 100.0, |_| 0.2);
            assert!((v - (-0.2f64 * 10.3).exp()).abs() < 1e-12, "{step}: {v}");
        }
        assert_eq!(transmittance(5.0, 5.0, 1.0, 100.0, |_| 1.0), 1.0);
        assert_eq!(transmittance(5.0, 1.0, 1.0, 100.0, |_| 1.0), 1.0);
        // A slab of 2 mm at σ = 1 along [0, 10]: midpoint samples see it for its length.
        let v = transmittance(0.0, 10.0, 0.25, 100.0, |s| {
            if (4.0..6.0).contains(&s) {
                1.0
            } else {
                0.0
            }
        });
        assert!((v - (-2.0f64).exp()).abs() < 1e-12, "{v}");
    }

    #[test]
    fn extinction_matches_the_main_rays_opacity_correction() {
        // (1 − α)^(L/unit) = exp(−σL).
        let (alpha, unit, length) = (0.3, 0.7, 0.35);
        let corrected = (1.0f64 - alpha).powf(length / unit);
        assert!((corrected - (-extinction(alpha, unit) * length).exp()).abs() < 1e-15);
        assert!(extinction(1.0, 1.0).is_finite());
        assert_eq!(extinction(0.0, 1.0), 0.0);
    }
}
