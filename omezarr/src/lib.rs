//! strata-omezarr: Strata stores as OME-Zarr 0.5 (Zarr v3, sharded) and back, over any object
//! store (a local folder, S3 and compatibles, HTTP).
//!
//! - [`export`]: a store's octree levels, apron stripped, as the arrays `0..N` of a multiscale
//!   group; the full Strata geometry rides along under the group's `strata` attribute.
//! - [`import`]: an OME-Zarr (Strata's own or anyone's) into a local store.
//! - [`streaming`]: an OME-Zarr pyramid read in place as a [`strata_source::VolumeSource`]:
//!   bricks with their 2-voxel apron assembled from the chunks they overlap; [`fetcher`]: its
//!   own request path, one task per brick, stale requests aborted on the wire.
//! - [`metadata`]: the multiscales document, the `strata` attribute, RFC-4 orientation labels.
//! - [`object_location`]: a folder, `s3://bucket/prefix` or `http(s)://...` as an object store.
//!
//! The Zarr format (sharding, zstd, crc32c) is zarrs'; the stores and the S3 signer are
//! object_store's. Nothing here encodes a Zarr codec or signs a request by hand.

pub mod checksums;
pub mod export;
pub mod fetcher;
pub mod import;
pub mod metadata;
pub mod object_location;
pub mod range_cache;
pub mod read_guard;
pub mod streaming;
pub mod view;
mod zarr_store;

pub use object_location::{ObjectLocation, ObjectStoreOptions};

/// What went wrong, with the place (folder, URL, array) it went wrong at.
#[derive(Debug, thiserror::Error)]
pub enum OmeZarrError {
    /// The data is not what an OME-Zarr 0.5 multiscale image should be.
    #[error("{location}: {message}")]
    Invalid { location: String, message: String },
    /// The object store or the Zarr library failed (network, permissions, missing objects).
    #[error("{location}: {message}")]
    Access { location: String, message: String },
    #[error(transparent)]
    Storage(#[from] strata_storage::StorageError),
    #[error("cancelled")]
    Cancelled,
}

impl OmeZarrError {
    pub fn invalid(location: impl std::fmt::Display, message: impl Into<String>) -> Self {
        OmeZarrError::Invalid {
            location: location.to_string(),
            message: message.into(),
        }
    }
    /// An object-store failure; a refusal by the server (403, bad signature, unknown key) says
    /// which credentials were used.
    pub fn access(location: impl std::fmt::Display, message: impl std::fmt::Display) -> Self {
        let mut message = message.to_string();
        const REFUSALS: [&str; 5] = [
            "403",
            "AccessDenied",
            "SignatureDoesNotMatch",
            "InvalidAccessKeyId",
            "Forbidden",
        ];
        if REFUSALS.iter().any(|r| message.contains(r)) {
            message = format!(
                "access denied by the object store: check AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY (and AWS_SESSION_TOKEN, the endpoint and the region) ({message})"
            );
        }
        OmeZarrError::Access {
            location: location.to_string(),
            message,
        }
    }
}

pub type Result<T, E = OmeZarrError> = std::result::Result<T, E>;

/// Whether a volume location names an OME-Zarr the way users write it: an `s3://` URL, a path
/// or URL ending in `.zarr` / `.ome.zarr` (optionally with a trailing slash), or a local folder
/// whose `zarr.json` carries OME multiscales.
pub fn looks_like_ome_zarr(location: &str) -> bool {
    let trimmed = location.trim_end_matches('/');
    if location.starts_with("s3://") || trimmed.ends_with(".zarr") {
        return true;
    }
    let path = std::path::Path::new(location);
    // A folder with a zarr.json file is a Zarr, whatever that file holds: a damaged one must be
    // named as such by the OME-Zarr reader, not sent to another format's ("no DICOM files").
    // Nothing is read here (a FIFO would block): a zarr.json that is not a regular file is
    // the OME-Zarr reader's to refuse, which it does before opening it.
    path.is_dir() && std::fs::metadata(path.join("zarr.json")).is_ok_and(|m| !m.is_dir())
}
