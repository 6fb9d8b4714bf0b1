//! strata-slices: the axis-aligned slice views' platform-independent part, one copy for the
//! desktop viewer (viewer/src/, which reads bricks on a named thread with blocking reads)
//! and the browser viewer (web/, which fetches them asynchronously on the page's one thread).
//!
//! # Modules
//! - [`orientation`]: which index axis runs across, down and through each view, so the patient
//!   shows the radiological way whatever the scan's axis order or flips.
//! - [`assembler`]: slice images at the octree level matching the view's pixels, assembled
//!   from decoded bricks as they arrive (poll-based: it lists what it still needs), over a
//!   bounded LRU of decoded bricks.
//! - [`oblique`]: the oblique reformat both viewers draw: the plane, its drag and link angles,
//!   the image a view asks for, and its trilinear resampling from level bricks, which may say
//!   "not resident yet" (the page's fetches).
//! - [`window_level`], [`colour_maps`]: stored values → window → colour map → RGBA8, and the
//!   window-dragging gesture.

pub mod assembler;
pub mod colour_maps;
pub mod oblique;
pub mod orientation;
pub mod window_level;

pub use assembler::{
    level_for_pixels, BrickLru, SliceAssembler, SliceError, SliceImage, SliceRequest, VoxelLookup,
    VoxelValue, SLICE_CACHE_BYTES,
};
pub use colour_maps::ColourMap;
pub use orientation::{SliceFrame, SliceView};
pub use window_level::{drag_window, window_level_rgba, Window};
