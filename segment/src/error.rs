//! The segmentation crate's errors: each names what failed and, for files, the file.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum SegmentError {
    #[error("a label layer holds at most {limit} segments; this would make {requested}")]
    TooManySegments { limit: usize, requested: usize },
    #[error("no segment has label value {0}")]
    NoSuchSegment(u16),
    #[error("segment {0} is locked")]
    Locked(u16),
    #[error("voxel {voxel:?} is outside the label grid {dims:?}")]
    OutOfBounds { voxel: [i64; 3], dims: [u32; 3] },
    #[error("label grid: {0}")]
    Grid(String),
    #[error("reading base labels of brick {brick:?}: {message}")]
    BaseRead { brick: [u32; 3], message: String },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: {format} holds at most {limit} {what}; this needs {requested}")]
    FormatLimit {
        path: PathBuf,
        format: &'static str,
        what: String,
        limit: u64,
        requested: u64,
    },
    #[error("cancelled")]
    Cancelled,
    #[error("{0}")]
    BadParameter(String),
    #[error("{what} would reach {voxels} voxels, more than the limit of {limit}: use a smaller size or region")]
    TooLarge {
        what: &'static str,
        voxels: u64,
        limit: u64,
    },
}
