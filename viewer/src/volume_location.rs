//! Where a command's volume comes from: a store directory on this machine,
//! `http://host:port/v1/stores/NAME` served by `strata serve` (with `--token-file` when the
//! server asks for one), or an OME-Zarr streamed in place (`s3://bucket/x.ome.zarr`,
//! `https://host/x.ome.zarr`, or a local `.zarr` folder; S3 endpoint and region from
//! `AWS_ENDPOINT_URL` / `AWS_REGION`). Every reading command opens its volume here and reads it through the
//! volume-source seam, so a URL works wherever a store path does.

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result};
use strata_service::{RemoteOptions, RemoteSource};
use strata_source::VolumeSource;
use strata_storage::lock::LockHolder;
use strata_storage::{StorageError, Store};

pub fn is_url(location: &str) -> bool {
    location.starts_with("http://") || location.starts_with("https://")
}

/// The token in `path` (surrounding whitespace ignored).
pub fn read_token(path: &Path) -> Result<String> {
    let token = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the token file {}", path.display()))?;
    let token = token.trim().to_string();
    anyhow::ensure!(
        !token.is_empty(),
        "{}: the token file is empty",
        path.display()
    );
    Ok(token)
}

/// A local store, or a remote one over `strata serve`.
pub enum Opened {
    Local(Arc<Store>),
    Remote(Arc<RemoteSource>),
    OmeZarr(Arc<strata_omezarr::streaming::OmeZarrSource>),
}

impl Opened {
    pub fn source(&self) -> Arc<dyn VolumeSource> {
        match self {
            Opened::Local(s) => s.clone(),
            Opened::Remote(r) => r.clone(),
            Opened::OmeZarr(z) => z.clone(),
        }
    }
}

/// `STRATA_TLS_CA`: a PEM certificate an https server's chain may end at, besides the
/// system's roots (a lab's own CA, or a test's).
const TLS_CA_VARIABLE: &str = "STRATA_TLS_CA";

pub fn open_remote(url: &str, token_file: Option<&Path>) -> Result<Arc<RemoteSource>> {
    open_remote_with_token(url, token_file.map(read_token).transpose()?)
}

/// [`open_remote`] with the token itself (a viewer link's, held in memory only).
pub fn open_remote_with_token(url: &str, token: Option<String>) -> Result<Arc<RemoteSource>> {
    let tls_ca_pem = match std::env::var_os(TLS_CA_VARIABLE) {
        Some(path) => Some(std::fs::read(&path).with_context(|| {
            format!(
                "cannot read {TLS_CA_VARIABLE}={}",
                Path::new(&path).display()
            )
        })?),
        None => None,
    };
    let options = RemoteOptions {
        token,
        tls_ca_pem,
        ..RemoteOptions::default()
    };
    Ok(Arc::new(
        RemoteSource::open(url, options).with_context(|| format!("cannot open {url}"))?,
    ))
}

/// Opens `location` (a path or a URL). `sled_cache_bytes` sizes a local store's page cache.
pub fn open(location: &str, token_file: Option<&Path>, sled_cache_bytes: u64) -> Result<Opened> {
    if strata_omezarr::looks_like_ome_zarr(location) {
        let source = strata_omezarr::streaming::open_source(location, &Default::default())
            .with_context(|| format!("cannot open the OME-Zarr {location}"))?;
        // What was assumed to stream a foreign pyramid (orientation, levels, value mapping).
        for note in source.notes() {
            eprintln!("note: {note}");
        }
        return Ok(Opened::OmeZarr(source));
    }
    if is_url(location) {
        return Ok(Opened::Remote(open_remote(location, token_file)?));
    }
    let path = Path::new(location);
    match Store::open_with_cache(path, sled_cache_bytes) {
        Ok(store) => Ok(Opened::Local(Arc::new(store))),
        // A format-2 store (sled) admits one process; while `strata serve` holds it, stream
        // from the server instead of waiting or failing. Format 3 opens beside the server.
        Err(StorageError::InUse {
            holder:
                LockHolder {
                    pid,
                    url: Some(url),
                    ..
                },
            ..
        }) => {
            eprintln!(
                "{}: served by strata serve (pid {pid}); streaming from {url}",
                path.display()
            );
            Ok(Opened::Remote(open_remote(&url, token_file)?))
        }
        Err(e) => Err(e).with_context(|| format!("cannot open store {}", path.display())),
    }
}

/// [`open`] as a volume source.
pub fn open_source(
    location: &str,
    token_file: Option<&Path>,
    sled_cache_bytes: u64,
) -> Result<Arc<dyn VolumeSource>> {
    Ok(open(location, token_file, sled_cache_bytes)?.source())
}
