//! Where an OME-Zarr lives: a local folder, `s3://bucket/prefix` (AWS S3 or a compatible
//! server) or an `http(s)://` URL (read-only), opened as one object_store rooted at the
//! multiscale group.
//!
//! S3 credentials come from the usual AWS environment variables (`AWS_ACCESS_KEY_ID`,
//! `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, `AWS_REGION`, `AWS_ENDPOINT_URL`); the
//! endpoint and region flags override them. A custom endpoint is addressed path-style
//! (`endpoint/bucket/key`), as SeaweedFS, MinIO and Ceph expect.

use std::sync::Arc;

use object_store::aws::AmazonS3Builder;
use object_store::http::HttpBuilder;
use object_store::local::LocalFileSystem;
use object_store::prefix::PrefixStore;
use object_store::{ClientOptions, ObjectStore};

use crate::read_guard::{ReadGuard, ReadLimits};
use crate::{OmeZarrError, Result};

/// Flags for object stores that the URL does not carry.
#[derive(Clone, Debug, Default)]
pub struct ObjectStoreOptions {
    /// S3 endpoint, e.g. `http://127.0.0.1:8333` (default: `AWS_ENDPOINT_URL`, else AWS).
    pub endpoint: Option<String>,
    /// S3 region (default: `AWS_REGION`, else `us-east-1`).
    pub region: Option<String>,
    /// Access key id and secret, for callers that hold their own (a benchmark's test server);
    /// the environment's otherwise.
    pub credentials: Option<(String, String)>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LocationKind {
    Folder,
    S3,
    Http,
}

/// An opened location: the store rooted at the group, and how to name it in messages.
#[derive(Clone)]
pub struct ObjectLocation {
    pub display: String,
    pub kind: LocationKind,
    /// Every read bounded by the metadata and the objects' sizes ([`ReadGuard`]).
    pub store: Arc<dyn ObjectStore>,
    /// What the guard allows under each array; the levels register theirs as they open.
    pub limits: Arc<ReadLimits>,
}

impl std::fmt::Debug for ObjectLocation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ObjectLocation({})", self.display)
    }
}

impl ObjectLocation {
    /// Opens `spec` (a folder path, `s3://bucket/prefix` or `http(s)://host/path`). A folder
    /// is created when `create_folder` (for export); nothing is contacted yet for S3 or HTTP.
    pub fn open(spec: &str, options: &ObjectStoreOptions, create_folder: bool) -> Result<Self> {
        // reqwest (under object_store) is built without a TLS provider of its own: rustls on
        // ring, installed before any client exists (an error means one is installed already).
        let _ = rustls::crypto::ring::default_provider().install_default();
        if let Some(rest) = spec.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            if bucket.is_empty() {
                return Err(OmeZarrError::invalid(
                    spec,
                    "an S3 location is s3://BUCKET/PREFIX: the bucket is missing",
                ));
            }
            let mut builder = AmazonS3Builder::from_env().with_bucket_name(bucket);
            let endpoint = options
                .endpoint
                .clone()
                .or_else(|| std::env::var("AWS_ENDPOINT_URL").ok())
                .or_else(|| std::env::var("AWS_ENDPOINT").ok());
            if let Some(endpoint) = &endpoint {
                builder = builder
                    .with_endpoint(endpoint)
                    .with_allow_http(endpoint.starts_with("http://"))
                    .with_virtual_hosted_style_request(false);
            }
            let region = options
                .region
                .clone()
                .or_else(|| std::env::var("AWS_REGION").ok())
                .or_else(|| std::env::var("AWS_DEFAULT_REGION").ok())
                .unwrap_or_else(|| "us-east-1".into());
            builder = builder.with_region(region);
            if let Some((key, secret)) = &options.credentials {
                builder = builder
                    .with_access_key_id(key)
                    .with_secret_access_key(secret);
            }
            let s3 = builder
                .build()
                .map_err(|e| OmeZarrError::invalid(spec, format!("S3 configuration: {e}")))?;
            let store: Arc<dyn ObjectStore> = if prefix.trim_matches('/').is_empty() {
                Arc::new(s3)
            } else {
                Arc::new(PrefixStore::new(s3, prefix.trim_matches('/')))
            };
            return Ok(ObjectLocation::guarded(spec, LocationKind::S3, store, None));
        }
        if spec.starts_with("http://") || spec.starts_with("https://") {
            let http = HttpBuilder::new()
                .with_url(spec.trim_end_matches('/'))
                .with_client_options(ClientOptions::new().with_allow_http(true))
                .build()
                .map_err(|e| OmeZarrError::invalid(spec, format!("HTTP location: {e}")))?;
            return Ok(ObjectLocation::guarded(
                spec,
                LocationKind::Http,
                Arc::new(http),
                None,
            ));
        }
        let path = std::path::Path::new(spec);
        if create_folder {
            std::fs::create_dir_all(path).map_err(|e| OmeZarrError::access(spec, e))?;
        } else if !path.is_dir() {
            return Err(OmeZarrError::invalid(
                spec,
                "not a folder (an OME-Zarr is a folder with zarr.json, or an s3:// or http(s):// URL)",
            ));
        }
        let local =
            LocalFileSystem::new_with_prefix(path).map_err(|e| OmeZarrError::access(spec, e))?;
        Ok(ObjectLocation::guarded(
            spec,
            LocationKind::Folder,
            Arc::new(local),
            Some(path.to_path_buf()),
        ))
    }

    fn guarded(
        spec: &str,
        kind: LocationKind,
        store: Arc<dyn ObjectStore>,
        local_root: Option<std::path::PathBuf>,
    ) -> Self {
        let limits = Arc::new(ReadLimits::default());
        ObjectLocation {
            display: spec.to_string(),
            kind,
            store: Arc::new(ReadGuard::new(store, local_root, limits.clone())),
            limits,
        }
    }

    /// `store` (a cache in front of this location's) behind a guard with the same limits, so
    /// that ranges are checked as the callers ask for them, before the cache merges them.
    pub fn guard_again(&self, store: Arc<dyn ObjectStore>) -> Arc<dyn ObjectStore> {
        Arc::new(ReadGuard::new(store, None, self.limits.clone()))
    }
}
