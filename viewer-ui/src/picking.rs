//! Picking in the 3D view: the volume position a click sees, from the frame's pick depth (the
//! raycaster writes, per pixel, how far along its ray the picture's depth lies: DVR where the
//! accumulated opacity reaches render's `DEPTH_OPACITY`, MIP at the maximum, iso at the
//! surface). Both viewers map a click through these two functions, so the same click on the
//! same frame moves both crosshairs to the same place; how the depth gets back differs (the
//! desktop keeps the frame's depth, the page copies one pixel back without waiting). And the
//! way back, [`project_to_view`]: where a volume position shows on the view, which both
//! viewers draw their 3D rulers and angles with (measurements' `paint_in_3d`).

use egui::{Pos2, Rect};
use glam::DVec3;
use strata_render::Camera;
use strata_types::VolumeGeometry;

/// The pixel of a `size` frame under a point at fractions `fx`, `fy` across and down the
/// image it is drawn in; `None` off the image.
pub fn frame_pixel(fx: f32, fy: f32, size: [u32; 2]) -> Option<[u32; 2]> {
    if !(0.0..1.0).contains(&fx) || !(0.0..1.0).contains(&fy) {
        return None;
    }
    let [width, height] = size;
    Some([
        ((fx * width as f32) as u32).min(width.saturating_sub(1)),
        ((fy * height as f32) as u32).min(height.saturating_sub(1)),
    ])
}

/// The level-0 continuous index (clamped into the grid) seen at `pixel` of a `size` frame
/// drawn with `camera`, whose pick depth there is `depth_mm` along the pixel's ray; `None`
/// where the ray met nothing (an infinite depth).
pub fn picked_index(
    camera: &Camera,
    geometry: &VolumeGeometry,
    pixel: [u32; 2],
    size: [u32; 2],
    depth_mm: f32,
) -> Option<[f64; 3]> {
    if !depth_mm.is_finite() {
        return None;
    }
    let (origin, direction) = camera.basis().ray(pixel[0], pixel[1], size[0], size[1]);
    let index = geometry.index_from_patient(origin + direction * f64::from(depth_mm));
    Some([0, 1, 2].map(|a| index[a].clamp(0.0, (geometry.dims[a] as f64 - 1.0).max(0.0))))
}

/// The screen point of a level-0 index, projected with `camera` into a frame filling `rect`
/// (rendered at its aspect); None behind the eye.
pub fn project_to_view(
    camera: &Camera,
    rect: Rect,
    g: &VolumeGeometry,
    index: DVec3,
) -> Option<Pos2> {
    let basis = camera.basis();
    let aspect = (rect.width() / rect.height().max(1.0)) as f64;
    let d = g.patient_from_index(index) - basis.eye;
    let depth = d.dot(basis.forward);
    let (sx, sy) = if basis.orthographic {
        (d.dot(basis.right), d.dot(basis.up))
    } else if depth > 1e-6 {
        (d.dot(basis.right) / depth, d.dot(basis.up) / depth)
    } else {
        return None;
    };
    let u = (sx / (aspect * basis.half_extent) + 1.0) * 0.5;
    let w = (1.0 - sy / basis.half_extent) * 0.5;
    Some(Pos2::new(
        rect.left() + u as f32 * rect.width(),
        rect.top() + w as f32 * rect.height(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_render::Projection;

    #[test]
    fn a_pixel_is_the_one_under_the_point_and_none_off_the_image() {
        assert_eq!(frame_pixel(0.0, 0.0, [64, 32]), Some([0, 0]));
        assert_eq!(frame_pixel(0.5, 0.5, [64, 32]), Some([32, 16]));
        assert_eq!(frame_pixel(0.9999, 0.9999, [64, 32]), Some([63, 31]));
        assert_eq!(frame_pixel(1.0, 0.5, [64, 32]), None);
        assert_eq!(frame_pixel(-0.01, 0.5, [64, 32]), None);
    }

    #[test]
    fn the_picked_index_lies_on_the_pixels_ray_at_its_depth() {
        let geometry = VolumeGeometry::axis_aligned([40, 30, 20], [0.5, 1.0, 2.0]);
        let camera = Camera::orbit(
            &geometry,
            35.0,
            20.0,
            1.3,
            Projection::Perspective { fov_y_deg: 30.0 },
        );
        let (pixel, size) = ([40, 21], [96, 64]);
        let (origin, direction) = camera.basis().ray(pixel[0], pixel[1], size[0], size[1]);
        // The ray's point nearest the volume's centre: inside the grid, so not clamped.
        let centre = geometry.patient_from_index(DVec3::new(19.5, 14.5, 9.5));
        let t = (centre - origin).dot(direction);
        let index = picked_index(&camera, &geometry, pixel, size, t as f32).expect("a depth");
        let seen = geometry.patient_from_index(DVec3::from(index));
        let on_ray = origin + direction * (seen - origin).dot(direction);
        assert!(seen.distance(on_ray) < 1e-3, "{seen} is off the ray");
        assert!(((seen - origin).dot(direction) - t).abs() < 1e-3);
        assert_eq!(
            picked_index(&camera, &geometry, pixel, size, f32::INFINITY),
            None
        );
        // Far behind the volume: clamped into the grid.
        let far = picked_index(&camera, &geometry, pixel, size, 1e6).expect("a depth");
        assert!((0..3).all(|a| (0.0..=geometry.dims[a] as f64 - 1.0).contains(&far[a])));
    }
}
