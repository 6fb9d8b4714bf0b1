//! The f64 reference's Blinn-Phong shading on the gradient (the headlight model of
//! shading.wgsl): a module of its own because both the reference's ray loop and the shadow
//! model's lit shading (shadows.rs) use it, and neither may depend on the other.

use glam::DVec3;

use crate::model::layout::{SHADING_FLAT_BELOW, SHADING_LIT_ABOVE};
use crate::model::settings::Shading;

/// Blinn-Phong with a headlight. `gradient_patient` in physical units per mm.
pub fn shade(
    color: [f64; 3],
    gradient_patient: DVec3,
    dir: DVec3,
    shading: &Shading,
    flatness_scale: f64,
) -> [f64; 3] {
    let mag = gradient_patient.length();
    let w = smoothstep(SHADING_FLAT_BELOW, SHADING_LIT_ABOVE, mag * flatness_scale);
    let (ndl, spec) = if mag > 0.0 {
        let ndl = (gradient_patient / mag).dot(-dir).abs();
        (ndl, ndl.powf(shading.shininess as f64))
    } else {
        (1.0, 0.0)
    };
    let unlit = shading.ambient as f64 + shading.diffuse as f64;
    let lit_gain = shading.ambient as f64 + shading.diffuse as f64 * ndl;
    let gain = unlit + (lit_gain - unlit) * w;
    let highlight = shading.specular as f64 * spec * w;
    color.map(|c| c * gain + highlight)
}

pub fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}
