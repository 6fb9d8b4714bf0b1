//! `strata.open(URL)` and `strata.open("x.ome.zarr")`: volumes read through the volume-source
//! seam instead of a local store, a store served by `strata serve` (strata-service's
//! `RemoteSource`) or an OME-Zarr read in place (strata-omezarr's `OmeZarrSource`).
//!
//! A region's bricks go through the source's own asynchronous request path (its
//! `BrickFetcher`: up to [`MAX_IN_FLIGHT`] requests on one HTTP/2 connection, each verified
//! on arrival), a group at a time, rather than one blocking request per thread: two cores
//! would otherwise keep two requests in flight. The fetcher retries a lost connection without
//! end (the viewer keeps what it has on screen meanwhile); a read here gives up once the
//! source has been retrying for `timeout_s` (20 s unless `strata.open` says otherwise, the
//! client's own bound for opening), with the source's own reason, and Ctrl-C is checked while
//! it waits.
//!
//! The token: sent by the client as `Authorization: Bearer …` (what `strata serve` checks),
//! held by the client only; messages never carry it (the client's never do, and
//! [`source_error`] removes it should one ever appear). Errors become `RemoteError`, or
//! `TokenError` for a 401, `StoreNotFoundError` for a store the server does not have.

use std::collections::HashSet;
use std::sync::Arc;
use std::time::{Duration, Instant};

use pyo3::prelude::*;
use strata_omezarr::OmeZarrError;
use strata_service::{RemoteOptions, RemoteSource};
use strata_source::{BrickFetcher, FetchOptions, SourceError, SourceStatus, VolumeSource};
use strata_types::BrickId;

use crate::{
    interrupted, store_error, Brick, ReadError, RemoteError, StoreError, StoreNotFoundError,
    TokenError,
};

/// Requests on the wire at once (the client's own default bound).
const MAX_IN_FLIGHT: usize = 64;
/// Bricks asked for at once: several round trips' worth of requests, ≈ 24 MB decoded.
pub(crate) const BRICKS_PER_REQUEST_GROUP: usize = 256;
/// Between looks at the fetcher's results while none have arrived.
const POLL: Duration = Duration::from_micros(250);
/// Between checks for Ctrl-C and for a source that stopped answering.
const CHECK_EVERY: Duration = Duration::from_millis(50);

/// `STRATA_TLS_CA`: a PEM certificate an https server's chain may end at, besides the
/// system's roots (as the `strata` commands read it).
const TLS_CA_VARIABLE: &str = "STRATA_TLS_CA";

pub(crate) fn is_url(location: &str) -> bool {
    location.starts_with("http://") || location.starts_with("https://")
}

/// The Python exception of a source's error, its message with `secret` (the token) removed and
/// the command line's `--token-file` advice in Python's terms.
pub(crate) fn source_error(e: SourceError, secret: Option<&str>) -> PyErr {
    let message = clean_message(&e.to_string(), secret);
    match e {
        SourceError::Storage(e) => store_error(e),
        // The client's words for a 401 (service/src/client.rs); `a_bad_token_is_a_token_error`
        // fails should they change.
        SourceError::Refused { .. } if message.contains("(401)") => TokenError::new_err(message),
        SourceError::Refused { .. } if message.contains("has no store named") => {
            StoreNotFoundError::new_err(message)
        }
        SourceError::Damaged { .. }
        | SourceError::Unavailable { .. }
        | SourceError::Refused { .. } => RemoteError::new_err(message),
    }
}

fn clean_message(message: &str, secret: Option<&str>) -> String {
    let message = message.replace("--token-file", "token=");
    match secret {
        Some(secret) if !secret.trim().is_empty() => message.replace(secret.trim(), "[token]"),
        _ => message,
    }
}

fn omezarr_error(e: OmeZarrError, location: &str) -> PyErr {
    match e {
        OmeZarrError::Storage(e) => store_error(e),
        OmeZarrError::Access { .. } if is_url(location) || location.starts_with("s3://") => {
            RemoteError::new_err(e.to_string())
        }
        OmeZarrError::Access { .. } if !std::path::Path::new(location).exists() => {
            StoreNotFoundError::new_err(e.to_string())
        }
        other => StoreError::new_err(other.to_string()),
    }
}

/// Opens `url` (`http(s)://HOST:PORT/v1/stores/NAME`) with `token` (blocking: one request).
pub(crate) fn open_remote(
    url: &str,
    token: Option<String>,
    give_up_after: Duration,
) -> PyResult<Arc<dyn VolumeSource>> {
    let authority = url.split_once("://").map_or("", |(_, rest)| {
        rest.split_once('/')
            .map_or(rest, |(authority, _)| authority)
    });
    if authority.contains('@') {
        return Err(pyo3::exceptions::PyValueError::new_err(
            "credentials in a URL are not sent: pass token= instead",
        ));
    }
    if token.as_deref().is_some_and(|t| t.trim().is_empty()) {
        return Err(pyo3::exceptions::PyValueError::new_err(
            "token= is empty: pass the server's token, or None for a server without one",
        ));
    }
    let tls_ca_pem = match std::env::var_os(TLS_CA_VARIABLE) {
        Some(path) => Some(std::fs::read(&path).map_err(|e| {
            RemoteError::new_err(format!(
                "cannot read {TLS_CA_VARIABLE}={}: {e}",
                std::path::Path::new(&path).display()
            ))
        })?),
        None => None,
    };
    let secret = token.clone();
    let options = RemoteOptions {
        token,
        tls_ca_pem,
        give_up_after,
        ..RemoteOptions::default()
    };
    let source =
        RemoteSource::open(url, options).map_err(|e| source_error(e, secret.as_deref()))?;
    Ok(Arc::new(source))
}

/// Opens an OME-Zarr (a folder, `http(s)://…`, `s3://…`) to read in place; returns the source
/// and what was assumed to stream it (a foreign pyramid's orientation, levels, value mapping).
pub(crate) fn open_omezarr(location: &str) -> PyResult<(Arc<dyn VolumeSource>, Vec<String>)> {
    let source = strata_omezarr::streaming::open_source(location, &Default::default())
        .map_err(|e| omezarr_error(e, location))?;
    let notes = source.notes().to_vec();
    Ok((source, notes))
}

/// Reads groups of bricks of one streamed source (one frame) through its request path.
pub(crate) struct StreamedReader {
    source: Arc<dyn VolumeSource>,
    fetcher: Option<Box<dyn BrickFetcher>>,
    give_up_after: Duration,
}

impl StreamedReader {
    pub(crate) fn start(
        source: Arc<dyn VolumeSource>,
        give_up_after: Duration,
    ) -> Result<Self, ReadError> {
        let fetcher = source
            .start_fetching(FetchOptions {
                max_queued: BRICKS_PER_REQUEST_GROUP,
                max_in_transit: MAX_IN_FLIGHT,
                threads: 1,
            })
            .transpose()
            .map_err(ReadError::Source)?;
        Ok(StreamedReader {
            source,
            fetcher,
            give_up_after,
        })
    }

    /// The bricks of `group`, constant ones from the skeleton without a request.
    pub(crate) fn read_group(&self, group: &[BrickId]) -> Result<Vec<(BrickId, Brick)>, ReadError> {
        let mut decoded = Vec::with_capacity(group.len());
        let mut wanted = Vec::new();
        for &id in group {
            match self.source.node(id) {
                Some(node) if node.is_constant() => decoded.push((id, Brick::Constant(node.min))),
                _ => wanted.push(id),
            }
        }
        let Some(fetcher) = &self.fetcher else {
            // A source without its own request path reads on this thread, brick by brick.
            for id in wanted {
                let voxels = self.source.read_brick(id).map_err(ReadError::Source)?;
                decoded.push((id, Brick::Voxels(Arc::new(voxels))));
                interrupted().map_err(ReadError::Python)?;
            }
            return Ok(decoded);
        };
        if wanted.is_empty() {
            return Ok(decoded);
        }
        let requests: Vec<(BrickId, f64)> = wanted.iter().map(|&id| (id, 0.0)).collect();
        fetcher.set_requests(&requests, &[]);
        let mut pending: HashSet<BrickId> = wanted.into_iter().collect();
        let mut checked = Instant::now();
        while !pending.is_empty() {
            let results = fetcher.try_results();
            if results.is_empty() {
                std::thread::sleep(POLL);
            }
            for result in results {
                fetcher.complete(result.id);
                if !pending.remove(&result.id) {
                    continue;
                }
                let voxels = result.outcome.map_err(ReadError::Source)?;
                decoded.push((result.id, Brick::Voxels(voxels)));
            }
            if checked.elapsed() >= CHECK_EVERY {
                checked = Instant::now();
                interrupted().map_err(ReadError::Python)?;
                if let SourceStatus::Retrying {
                    since_seconds,
                    message,
                } = fetcher.status()
                {
                    if since_seconds >= self.give_up_after.as_secs_f64() {
                        return Err(ReadError::Source(SourceError::Unavailable {
                            location: self.source.location(),
                            message: format!(
                                "no answer for {since_seconds:.0} s while reading a region, giving up: {message}"
                            ),
                        }));
                    }
                }
            }
        }
        Ok(decoded)
    }
}
