//! Segmentation: an editable label layer over a volume (issue 52).
//!
//! Edits are made on bricks, not on volumes: a [`LabelLayer`] holds only the bricks that were
//! edited (copy-on-write over a read-only [`LabelBase`]: nothing, an imported label file or a
//! label store), so painting on a 16384³ sparse volume costs memory in proportion to the bricks
//! touched. Every tool produces an [`Edit`] (the before and after image of each brick it
//! changed), which is what undo/redo replays and what the journal writes to disk.
//!
//! Labels are `u16`: 0 is background, 1..=65 535 are segments ([`SegmentTable`]).

pub mod error;
pub mod grid;
pub mod history;
pub mod intensity;
pub mod io;
#[cfg(feature = "local")]
pub mod journal;
pub mod layer;
pub mod nifti_map;
pub mod pyramid;
pub mod resample;
pub mod segments;
pub mod stats;
pub mod tools;

pub use error::SegmentError;
pub use grid::{BrickKey, LabelGrid, LABEL_BRICK, LABEL_BRICK_VOXELS};
pub use layer::{
    BrickChange, DenseLabels, Edit, EditWriter, EmptyBase, LabelBase, LabelLayer, LabelRead,
    TableChange,
};
pub use segments::{label_colour, Code, Segment, SegmentCategory, SegmentTable};

/// A label value: 0 is background, every other value one segment.
pub type Label = u16;

/// The largest number of segments a layer holds (every non-zero `u16`).
pub const MAX_SEGMENTS: usize = u16::MAX as usize;
