//! Controllers: the time-critical sampling-rate and level-of-detail controller and the
//! target-frame-rate driver both viewers use (render/src/lib.rs draws the layers).

pub mod target_rate;
pub mod time_critical;
