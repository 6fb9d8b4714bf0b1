use std::path::PathBuf;

pub type Result<T, E = StorageError> = std::result::Result<T, E>;

/// Every error names the file it concerns, so a user can act on it without a debugger.
#[derive(Debug, thiserror::Error)]
pub enum StorageError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },

    #[error("{path}: {message}")]
    InvalidInput { path: PathBuf, message: String },

    #[error("{path}: unsupported: {message}")]
    Unsupported { path: PathBuf, message: String },

    #[error("{path}: incomplete import (the import that wrote this store did not finish); import again to rebuild it")]
    IncompleteImport { path: PathBuf },

    #[error("{path}: not a Strata store ({message})")]
    NotAStore { path: PathBuf, message: String },

    #[error("{path}: corrupted data: {message}")]
    Corrupted { path: PathBuf, message: String },

    #[error("{path}: database error: {source}")]
    Database { path: PathBuf, source: sled::Error },

    #[error("{path}: import cancelled")]
    Cancelled { path: PathBuf },
}

impl StorageError {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        StorageError::Io {
            path: path.into(),
            source,
        }
    }
    pub fn invalid(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        StorageError::InvalidInput {
            path: path.into(),
            message: message.into(),
        }
    }
    pub fn unsupported(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        StorageError::Unsupported {
            path: path.into(),
            message: message.into(),
        }
    }
    pub fn corrupted(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        StorageError::Corrupted {
            path: path.into(),
            message: message.into(),
        }
    }
    pub fn db(path: impl Into<PathBuf>, source: sled::Error) -> Self {
        StorageError::Database {
            path: path.into(),
            source,
        }
    }
}
