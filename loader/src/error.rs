//! The loader's one error type.

use strata_storage::StorageError;

#[derive(Debug, thiserror::Error)]
pub enum LoaderError {
    #[error(transparent)]
    Storage(#[from] StorageError),
    #[error(transparent)]
    Source(#[from] strata_source::SourceError),
    #[error(transparent)]
    Render(#[from] strata_render::RenderError),
    #[error("{0}")]
    Unsupported(String),
    /// A cut loaded up front that the GPU budget cannot hold: the numbers that do not fit.
    #[error(
        "{what} needs {bricks} bricks × {brick_bytes} bytes = {needed_mib} MiB of GPU brick \
         cache, over the budget of {budget_mib} MiB (--gpu-mib); give a larger --gpu-mib or a \
         coarser --level",
        needed_mib = (.bricks * .brick_bytes).div_ceil(1 << 20),
        budget_mib = .budget_bytes >> 20
    )]
    CutOverBudget {
        what: String,
        bricks: u64,
        brick_bytes: u64,
        budget_bytes: u64,
    },
    /// A cut loaded up front with more bricks than the device's largest cache texture holds.
    #[error(
        "{what} needs {bricks} bricks, more than the {slots} slots of the largest brick cache \
         this adapter's 3D textures hold (max_texture_dimension_3d {max_dim} texels); give a \
         coarser --level"
    )]
    CutOverDeviceLimit {
        what: String,
        bricks: u64,
        slots: u64,
        max_dim: u32,
    },
    #[error("fetch workers: {0}")]
    Worker(String),
    #[error("streaming bookkeeping is inconsistent: {0}")]
    Inconsistent(String),
}
