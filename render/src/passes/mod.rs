//! The passes: the raycaster, the progressive mean, the adaptive pass, the offscreen renderer
//! and the test probes. They draw into gpu's frame targets (render/src/lib.rs draws the
//! layers).

pub mod adaptive;
#[cfg(feature = "test-probe")]
pub mod octree_probe;
pub mod offscreen;
#[cfg(feature = "test-probe")]
pub mod probe;
pub mod progressive;
pub mod raycast;
