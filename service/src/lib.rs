//! strata-service: the streaming data service. `server` is `strata serve` (stores, read-only,
//! over HTTP/1.1 and h2c); `client` is the remote [`strata_source::VolumeSource`] the loader
//! and the commands stream from; `wire` is what travels between them (paths, the open
//! document, ETags). See ARCHITECTURE.md, "The data service".

pub mod client;
mod connections;
mod observe;
pub mod server;
pub mod test_hooks;
pub mod web_viewer;
/// The wire format lives in strata-source, where the browser's client (strata-web) reads it too.
pub use strata_source::wire;

pub use client::{RemoteOptions, RemoteSource};
pub use server::{ServeError, ServeOptions};
pub use web_viewer::{CapturedFrame, FrameSink, WebViewerAssets};

/// Makes ring the process's rustls crypto provider (once; later calls do nothing). reqwest's
/// TLS needs one before any client is built; `RemoteSource::open` calls this itself, other
/// code that builds a reqwest client (tests, tools) calls it first.
pub fn install_tls_provider() {
    let _ = rustls::crypto::ring::default_provider().install_default();
}
