//! The orbit movie as both viewers make it (issue 47): how many frames may be asked for, and
//! which azimuth each frame's camera has. The desktop writes its frames as PNGs and an MP4
//! (viewer/src/export.rs), the page downloads one animated PNG (strata-web's orbit_movie.rs);
//! one copy of the path, so that both movies of a view turn through the same angles.

use std::ops::RangeInclusive;

/// The most frames an orbit movie may have: 10 per degree, 150 s at 24 frames per second.
pub const MAX_ORBIT_FRAMES: u32 = 3600;

/// The frame counts the Screenshot panels offer, and the one they start at (10° a frame).
pub const OFFERED_ORBIT_FRAMES: RangeInclusive<u32> = 4..=360;
pub const DEFAULT_ORBIT_FRAMES: u32 = 36;

/// The movie's rate: the MP4's frame rate and the animated PNG's frame delay.
pub const ORBIT_FRAMES_PER_SECOND: u32 = 24;

/// A panel's frame count as a movie is made of it: at least two frames (one frame would not
/// turn), at most [`MAX_ORBIT_FRAMES`].
pub fn orbit_frame_count(asked: u32) -> u32 {
    asked.clamp(2, MAX_ORBIT_FRAMES)
}

/// Azimuth of frame `i` of `frames`, evenly around the full turn from `start` (the view's
/// azimuth when the movie starts); the elevation and zoom stay the view's.
pub fn orbit_azimuth(start: f64, i: u32, frames: u32) -> f64 {
    start + 360.0 * i as f64 / frames.max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_turn_evenly_once_around_without_repeating_the_first() {
        let frames = 36;
        let angles: Vec<f64> = (0..frames)
            .map(|i| orbit_azimuth(30.0, i, frames))
            .collect();
        assert_eq!(angles[0], 30.0);
        for pair in angles.windows(2) {
            assert!((pair[1] - pair[0] - 10.0).abs() < 1e-9, "{pair:?}");
        }
        // The frame after the last would be the first again: the movie loops seamlessly.
        assert!((orbit_azimuth(30.0, frames, frames) - 390.0).abs() < 1e-9);
    }

    #[test]
    fn frame_counts_are_bounded() {
        assert_eq!(orbit_frame_count(0), 2);
        assert_eq!(orbit_frame_count(36), 36);
        assert_eq!(orbit_frame_count(u32::MAX), MAX_ORBIT_FRAMES);
        // No division by zero for a count no panel offers.
        assert_eq!(orbit_azimuth(5.0, 0, 0), 5.0);
    }
}
