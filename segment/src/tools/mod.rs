//! The editing tools. Each takes the layer (and, where it reads the primary, an
//! [`Intensity`](crate::intensity::Intensity)) and makes one [`Edit`]: one undo step, one
//! journal record.

pub mod brush;
mod distance;
pub mod fill;
mod fill_oblique;
mod flood;
pub mod grow;
pub mod interpolate;
pub mod morphology;
mod region;

use crate::layer::{Edit, LabelLayer};
use crate::{Label, SegmentError};

/// What a region tool did.
#[derive(Debug)]
pub struct Outcome {
    /// The edit (`None` when nothing changed).
    pub edit: Option<Edit>,
    /// Voxels in the region it took.
    pub voxels: u64,
    /// Whether it stopped at its voxel cap with more to take (what it took is kept).
    pub stopped_at_cap: bool,
}

impl Outcome {
    fn nothing() -> Self {
        Outcome {
            edit: None,
            voxels: 0,
            stopped_at_cap: false,
        }
    }
}

/// A tool paints with an existing, unlocked segment (a lock means "leave it alone").
fn check_tool_label(layer: &LabelLayer, label: Label) -> Result<(), SegmentError> {
    if label == 0 || layer.segments().get(label).is_none() {
        return Err(SegmentError::NoSuchSegment(label));
    }
    if layer.segments().is_locked(label) {
        return Err(SegmentError::Locked(label));
    }
    Ok(())
}
