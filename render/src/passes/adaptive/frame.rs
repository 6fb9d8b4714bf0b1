//! The frame-wide slices of the adaptive pass and the rays of pyramid pixels: the same rules
//! for the CPU transcription (scene.rs) and the GPU pass (gpu.rs fills `AdaptiveParams` from
//! this).
//!
//! Slice i sits at ray distance t_front + i·spacing on every ray: planes perpendicular to the
//! view direction in orthographic views (rays start on the eye plane and t is measured along
//! the view direction), shells around the eye in perspective (rays are unit vectors from the
//! eye, so equal t is equal distance), with the slice spacing equal to the base step. The
//! front is a frame-wide bound in front of the cropped box, never per ray, so slice indices are
//! global and the skipping pattern (trailing zeros) is the same on every ray.

use glam::DVec3;

use super::transcription::PyramidDims;
use crate::model::camera::{Camera, CameraBasis};
use crate::model::settings::RenderSettings;
use strata_types::VolumeGeometry;

/// Hard cap on slices per frame (a 4096-voxel diagonal at quarter-voxel steps): a degenerate
/// step or camera cannot make a frame loop for ever.
pub const MAX_SLICES: u32 = 1 << 16;

#[derive(Clone, Debug)]
pub struct SliceFrame {
    /// The viewport (what the caller sees), and the pyramid it is padded to.
    pub viewport: (u32, u32),
    pub dims: PyramidDims,
    pub basis: CameraBasis,
    /// Ray distance (mm) of slice 0, and between slices.
    pub t_front: f64,
    pub spacing_mm: f64,
    /// Index of the last slice: a multiple of 2^l_max at or behind the back of the box.
    pub last_slice: u32,
}

impl SliceFrame {
    pub fn new(
        geometry: &VolumeGeometry,
        settings: &RenderSettings,
        camera: &Camera,
        l_max: u32,
    ) -> Self {
        let basis = camera.basis();
        let m = geometry.patient_from_index_linear();
        let dims = DVec3::new(
            geometry.dims[0] as f64,
            geometry.dims[1] as f64,
            geometry.dims[2] as f64,
        );
        let lo = DVec3::from(settings.crop.min.map(|v| v as f64)) * dims - 0.5;
        let hi = DVec3::from(settings.crop.max.map(|v| v as f64)) * dims - 0.5;
        let (mut near, mut far) = (f64::INFINITY, 0.0f64);
        for corner in 0..8 {
            let c = DVec3::new(
                if corner & 1 == 0 { lo.x } else { hi.x },
                if corner & 2 == 0 { lo.y } else { hi.y },
                if corner & 4 == 0 { lo.z } else { hi.z },
            );
            let p = geometry.origin() + m * c - basis.eye;
            // Along the view direction: a lower bound of the distance too (|p| ≥ p·forward),
            // so the front is in front of the box for shells as well as planes.
            near = near.min(p.dot(basis.forward));
            far = far.max(if basis.orthographic {
                p.dot(basis.forward)
            } else {
                p.length()
            });
        }
        let t_front = near.max(0.0);
        let spacing_mm = (settings.quality * geometry.finest_spacing_mm()).max(1e-6);
        let step = 1u32 << l_max;
        let slices = ((far - t_front) / spacing_mm)
            .ceil()
            .clamp(1.0, MAX_SLICES as f64) as u32;
        SliceFrame {
            viewport: (settings.width, settings.height),
            dims: PyramidDims::padded(settings.width, settings.height, l_max),
            basis,
            t_front,
            spacing_mm,
            last_slice: slices.div_ceil(step) * step,
        }
    }

    /// Ray distance of slice `i`.
    pub fn slice_t(&self, i: u32) -> f64 {
        self.t_front + i as f64 * self.spacing_mm
    }

    /// The ray through level-0 pixel coordinates (u, v) (pixel centres at integers, as
    /// [`CameraBasis::ray`] has them; padding pixels continue the same mapping).
    pub fn ray(&self, u: f64, v: f64) -> (DVec3, DVec3) {
        let (w, h) = (self.viewport.0 as f64, self.viewport.1 as f64);
        let b = &self.basis;
        let sx = (2.0 * (u + 0.5) / w - 1.0) * (w / h) * b.half_extent;
        let sy = (1.0 - 2.0 * (v + 0.5) / h) * b.half_extent;
        if b.orthographic {
            (b.eye + b.right * sx + b.up * sy, b.forward)
        } else {
            (
                b.eye,
                (b.forward + b.right * sx + b.up * sy).normalize_or_zero(),
            )
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::camera::Projection;

    #[test]
    fn slices_cover_the_box_and_pixel_rays_match_the_camera() {
        let g = VolumeGeometry::axis_aligned([64, 48, 40], [1.0, 1.0, 2.0]);
        for projection in [
            Projection::Perspective { fov_y_deg: 30.0 },
            Projection::Orthographic { height_mm: 120.0 },
        ] {
            let camera = Camera::orbit(&g, 30.0, 20.0, 1.0, projection);
            let settings = RenderSettings {
                width: 100,
                height: 60,
                ..Default::default()
            };
            let f = SliceFrame::new(&g, &settings, &camera, 3);
            assert_eq!((f.dims.width, f.dims.height), (104, 64));
            assert_eq!(f.last_slice % 8, 0);
            // Every ray's box interval lies within [slice 0, last slice].
            for (px, py) in [(0, 0), (50, 30), (99, 59)] {
                let (o, d) = f.ray(px as f64, py as f64);
                let (o2, d2) = f.basis.ray(px, py, 100, 60);
                assert!((o - o2).length() < 1e-9 && (d - d2).length() < 1e-12);
                if let Some((t0, t1)) = crate::reference::ray_interval(&g, &settings, o, d) {
                    assert!(t0 >= f.slice_t(0) - 1e-9, "{projection:?}");
                    assert!(t1 <= f.slice_t(f.last_slice) + 1e-9, "{projection:?}");
                }
            }
        }
    }
}
