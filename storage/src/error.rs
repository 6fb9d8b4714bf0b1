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

    /// The store's database failed in a way that is neither damage nor a full disk.
    #[error("{path}: database error: {message}")]
    Database { path: PathBuf, message: String },

    /// The disk (or the process's file-size limit) ran out while writing.
    #[error("{path}: {message}")]
    DiskFull { path: PathBuf, message: String },

    /// Another live process holds the store (see [`crate::lock`]).
    #[error("{path}: {holder}")]
    InUse {
        path: PathBuf,
        holder: crate::lock_holder::LockHolder,
    },

    /// The store folder cannot be written, and sled 0.34 opens every database read-write.
    #[error("{path}: the store is on read-only media or not writable ({reason}); sled opens stores read-write, so copy the store to a writable disk, or run `strata serve` where it can be written and open its URL")]
    ReadOnly { path: PathBuf, reason: String },

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
    /// Classifies a sled error: a full disk, damage, or other database failure. The message
    /// is sled's text once (its `Io` variant repeats the OS error when chained).
    #[cfg(feature = "local")]
    pub fn db(path: impl Into<PathBuf>, source: sled::Error) -> Self {
        let path = path.into();
        match source {
            sled::Error::Io(e) if is_disk_full(&e) => StorageError::DiskFull {
                path,
                // sled's text for it varies (sometimes the OS error's Debug form).
                message:
                    "the disk is full, or the file-size limit was reached, while writing the store"
                        .into(),
            },
            sled::Error::Io(e) => StorageError::Database {
                path,
                message: e.to_string(),
            },
            sled::Error::Corruption { at, .. } => StorageError::Corrupted {
                path,
                message: match at {
                    Some(at) => format!("the database is damaged (at {at:?})"),
                    None => "the database is damaged".into(),
                },
            },
            sled::Error::ReportableBug(m) => StorageError::Corrupted {
                path,
                message: format!("the database is damaged or inconsistent ({m})"),
            },
            other => StorageError::Database {
                path,
                message: other.to_string(),
            },
        }
    }

    /// True for damage to a store (as opposed to a bad input or a busy store).
    pub fn is_damage(&self) -> bool {
        matches!(self, StorageError::Corrupted { .. })
    }
}

/// ENOSPC, EDQUOT, or EFBIG from a file-size limit: all mean "the bytes did not fit".
/// sled wraps the OS error in errors of its own, so the kind is looked for along the chain.
#[cfg(feature = "local")]
pub fn is_disk_full(e: &std::io::Error) -> bool {
    use std::io::ErrorKind;
    let full = |e: &std::io::Error| {
        matches!(
            e.kind(),
            ErrorKind::StorageFull | ErrorKind::QuotaExceeded | ErrorKind::FileTooLarge
        )
    };
    if full(e) {
        return true;
    }
    let mut inner: Option<&(dyn std::error::Error + 'static)> = e.get_ref().map(|i| i as _);
    while let Some(cause) = inner {
        if cause.downcast_ref::<std::io::Error>().is_some_and(full) {
            return true;
        }
        if let Some(sled::Error::Io(io)) = cause.downcast_ref::<sled::Error>() {
            if is_disk_full(io) {
                return true;
            }
        }
        inner = cause.source();
    }
    // Last resort for errors that were flattened to text on the way (sled's `Io(format!(..))`).
    let text = e.to_string();
    text.contains("StorageFull") || text.contains("FileTooLarge") || text.contains("(os error 28)")
}
