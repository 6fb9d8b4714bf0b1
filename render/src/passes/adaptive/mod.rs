//! Adaptive sampling in three dimensions (Kraus, Strengert, Klein & Ertl; adaptive-sampling-3d
//! §3.1-3.4) as a render mode of its own: samples sit on view-aligned slices (shells around
//! the eye in perspective), a ray skips slices by the trailing zeros of the slice index, and
//! an image pyramid per slice synthesises skipped pixels with the biquadratic B-spline
//! subdivision (9/16, 3/16, 3/16, 1/16), all driven by an oracle's sampling distance.
//!
//! - [`transcription`]: Figs. 3, 5, 6 in f64 over the whole image: the specification.
//! - [`frame`]: the frame-wide slices and the rays of pyramid pixels, shared by the CPU and the
//!   GPU pass.
//! - [`oracle`]: the sampling distance per page entry from the TF over node value ranges,
//!   dilated over neighbours, with ε the user's knob; with lighting on it bounds the lit
//!   colour's change, not only the opacity's ([`OracleTarget`]).
//! - [`block_oracle`]: the finer oracle, a distance per 2³ block of every resident node (the
//!   paper's distance to the nearest voxel with |∇α| > ε), indexed by slot and in-slot block.
//! - [`block_oracle_build`]: the same table a bounded number of slots at a time (the browser
//!   page builds it across animation frames on its one thread).
//! - [`scene`]: the transcription over a real volume (the field of field.rs, the length-free
//!   pre-integration of segment_integral.rs): the CPU twin of the GPU pass.
//! - [`gpu`]: the tiled compute pass (shaders/adaptive.wgsl).

pub mod block_oracle;
pub mod block_oracle_build;
pub mod frame;
pub mod gpu;
pub mod oracle;
pub mod scene;
pub mod transcription;

pub use block_oracle::{block_oracle, block_oracle_with};
pub use block_oracle_build::BlockOracleBuild;
pub use frame::SliceFrame;
pub use gpu::{AdaptiveCounts, AdaptiveFrame, AdaptivePass, CountsReadback};
pub use oracle::{oracle_distances, oracle_for_cut, oracle_for_cut_with, OracleKind, OracleTarget};
pub use scene::{render_adaptive_reference, slice_sample, AdaptiveOptics, AdaptiveReference};
pub use transcription::{
    l_slice, project_volume, project_volume_tiled, PyramidDims, TileRules, Transcription,
};

/// The adaptive pass's own settings (the rest comes from [`crate::RenderSettings`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptiveConfig {
    /// Coarsest pyramid level: the largest sampling distance is 2^l_max slices. The paper
    /// uses 3.
    pub l_max: u32,
    /// Screen tile edge of one workgroup, level-0 pixels: 8, 16 or 32 (≥ 2^l_max).
    pub tile: u32,
    /// Where sampling distances come from.
    pub oracle: OracleKind,
    /// Data oracles (per node, per block): each tile marches only the slices between its rays' nearest entry
    /// into the box and farthest exit (rounded out to slices of l_slice = l_max), which
    /// gives the same image as marching every slice. Off only to test exactly that.
    pub tile_slice_ranges: bool,
    /// After each slice the tile goes straight to the next slice in which one of its open
    /// pixels acts (adaptive.wgsl `SKIP_IDLE_SLICES`): the same image and counters with fewer
    /// passes through the slice loop. Off only to test exactly that.
    pub skip_idle_slices: bool,
}

impl Default for AdaptiveConfig {
    fn default() -> Self {
        AdaptiveConfig {
            l_max: 3,
            tile: 16,
            oracle: OracleKind::PerBlock,
            tile_slice_ranges: true,
            skip_idle_slices: true,
        }
    }
}

/// Largest supported l_max (workgroup memory holds levels 1..=MAX_L_MAX).
pub const MAX_L_MAX: u32 = 3;

/// Supported tile edges.
pub const TILE_SIZES: [u32; 3] = [8, 16, 32];

impl AdaptiveConfig {
    pub fn validate(&self) -> Result<(), crate::RenderError> {
        if self.l_max == 0 || self.l_max > MAX_L_MAX {
            return Err(crate::RenderError::InvalidSettings(format!(
                "adaptive l_max {} outside 1..={MAX_L_MAX}",
                self.l_max
            )));
        }
        if !TILE_SIZES.contains(&self.tile) || self.tile < (1 << self.l_max) {
            return Err(crate::RenderError::InvalidSettings(format!(
                "adaptive tile {} must be one of {TILE_SIZES:?} and at least 2^l_max",
                self.tile
            )));
        }
        Ok(())
    }
}
