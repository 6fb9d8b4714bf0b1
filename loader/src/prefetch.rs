//! Speculative loading of what the next frames will likely ask for (issue 4): the cut of the
//! camera extrapolated along its recent motion. Its missing bricks are queued below every
//! demand request; the other prefetch source, children of visible leaves the quality factor
//! would refine next, comes straight out of the cut selection. The hit rate (prefetched bricks
//! later used / prefetched bricks loaded) is kept by the CPU cache.

use glam::DVec3;
use strata_render::{Camera, Projection};

pub struct MotionPredictor {
    previous: Option<Camera>,
    lookahead_frames: f64,
}

impl MotionPredictor {
    pub fn new(lookahead_frames: f64) -> Self {
        MotionPredictor {
            previous: None,
            lookahead_frames,
        }
    }

    /// Records this frame's camera; returns where it will be in `lookahead_frames` frames if it
    /// keeps moving as it did since the last frame, or None when it stood still.
    pub fn observe(&mut self, camera: &Camera) -> Option<Camera> {
        let previous = self.previous.replace(*camera)?;
        let k = self.lookahead_frames;
        let extrapolate = |now: [f64; 3], before: [f64; 3]| {
            let (now, before) = (DVec3::from(now), DVec3::from(before));
            (now + (now - before) * k, (now - before).length())
        };
        let (eye, eye_moved) = extrapolate(camera.eye, previous.eye);
        let (target, target_moved) = extrapolate(camera.target, previous.target);
        let projection = match (camera.projection, previous.projection) {
            (
                Projection::Orthographic { height_mm: now },
                Projection::Orthographic { height_mm: before },
            ) => Projection::Orthographic {
                height_mm: (now + (now - before) * k).max(now * 0.25),
            },
            (p, _) => p,
        };
        let zoomed = projection != camera.projection;
        if eye_moved < 1e-9 && target_moved < 1e-9 && !zoomed {
            return None;
        }
        Some(Camera {
            eye: eye.into(),
            target: target.into(),
            up: camera.up,
            projection,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extrapolates_linear_motion_and_ignores_a_still_camera() {
        let mut p = MotionPredictor::new(4.0);
        let cam = |x: f64| {
            Camera::look_at(
                [x, 0.0, 0.0],
                [0.0, 0.0, 100.0],
                [0.0, 1.0, 0.0],
                Projection::Perspective { fov_y_deg: 30.0 },
            )
        };
        assert!(p.observe(&cam(0.0)).is_none());
        let predicted = p.observe(&cam(1.0)).expect("moving");
        assert!((predicted.eye[0] - 5.0).abs() < 1e-12);
        assert!(p.observe(&cam(1.0)).is_none());
    }
}
