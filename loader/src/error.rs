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
    #[error("fetch workers: {0}")]
    Worker(String),
    #[error("streaming bookkeeping is inconsistent: {0}")]
    Inconsistent(String),
}
