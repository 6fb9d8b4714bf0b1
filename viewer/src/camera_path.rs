//! The scripted camera path of `strata flythrough` and of the remote benchmark (`strata-bench
//! remote`), so both fly the same viewpoints.

use strata_render::{Camera, Projection, VolumeGeometry};

/// Viewpoint `k` of `n`: an orbit that swings around and closes in, ending inside the body's
/// outline where the finest level is needed.
pub fn viewpoint(geometry: &VolumeGeometry, k: f64, n: usize) -> Camera {
    let t = k / (n.max(2) - 1) as f64;
    Camera::orbit(
        geometry,
        -50.0 + 140.0 * t,
        25.0 - 30.0 * t,
        1.0 + 2.5 * t * t,
        Projection::Perspective { fov_y_deg: 30.0 },
    )
}
