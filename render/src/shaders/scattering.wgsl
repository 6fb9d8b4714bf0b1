// Single scattering of the key light: the Henyey-Greenstein phase and Exposure Render's hybrid
// weight (scattering.rs, which documents the model). Used by shade_key_light (shadows.wgsl)
// under the override; a pipeline without it has none of this code.
override SCATTERING: bool = false;

// 4π·p_g(mu): the phase normalised to 1 when isotropic (scattering.rs `phase_hg`), its
// denominator in the cancellation-free form (1 − g)² + 2g(1 − mu).
fn scattering_phase_4pi(g: f32, mu: f32) -> f32 {
    let denom = (1.0 - g) * (1.0 - g) + 2.0 * g * (1.0 - mu);
    return (1.0 - g * g) / (denom * sqrt(denom));
}

// Exposure Render's BRDF weight P = 1 − exp(−25·b³·m) (scattering.rs `surface_weight`).
fn scattering_surface_weight(blend: f32, m: f32) -> f32 {
    return 1.0 - exp(-25.0 * blend * blend * blend * m);
}
