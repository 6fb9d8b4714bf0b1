//! `strata.serve`: `strata serve` on a thread of this process (strata-service's server).

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::sync::Mutex;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use strata_service::server::{find_stores, start, RunningServer, ServeError, ServeOptions};
use strata_service::WebViewerAssets;

use crate::{no_panic, store_error, StrataError};

fn serve_error(e: ServeError) -> PyErr {
    match e {
        ServeError::Storage(e) => store_error(e),
        other => StrataError::new_err(other.to_string()),
    }
}

/// A running server (the Python class `strata.Server` wraps it).
#[pyclass(module = "strata._strata", frozen)]
pub struct NativeServer {
    server: Mutex<Option<RunningServer>>,
    base_url: String,
    stores: Vec<(String, String)>,
}

#[pymethods]
impl NativeServer {
    /// `http://HOST:PORT`.
    #[getter]
    fn base_url(&self) -> String {
        self.base_url.clone()
    }

    /// (name, URL) of every served store.
    fn stores(&self) -> Vec<(String, String)> {
        self.stores.clone()
    }

    /// Stops the server (the listener closes, connections are dropped); idempotent.
    fn stop(&self, py: Python<'_>) {
        let server = self.server.lock().unwrap_or_else(|p| p.into_inner()).take();
        if let Some(server) = server {
            py.allow_threads(|| server.stop());
        }
    }
}

/// Serves the stores at `paths` (a store, or a folder of stores) on `host:port` (0: any free
/// port), as `strata serve` does: read-only, identifiers withheld, a token required off
/// loopback. `web_viewer`: a folder with the browser viewer's files (`cargo run -p xtask --
/// web` writes web/dist/), served at `/`; `frame_ancestors`: who may frame that page (the
/// Jupyter widget's notebook; default nobody).
#[pyfunction]
#[pyo3(signature = (paths, port=0, host="127.0.0.1", token=None, web_viewer=None, frame_ancestors=None))]
pub fn serve(
    py: Python<'_>,
    paths: Vec<PathBuf>,
    port: u16,
    host: &str,
    token: Option<String>,
    web_viewer: Option<PathBuf>,
    frame_ancestors: Option<String>,
) -> PyResult<NativeServer> {
    let ip: IpAddr = host
        .parse()
        .map_err(|e| PyValueError::new_err(format!("host '{host}' is not an IP address: {e}")))?;
    py.allow_threads(|| {
        no_panic("starting the server", || {
            let web_viewer = match web_viewer {
                Some(dir) => Some(std::sync::Arc::new(
                    WebViewerAssets::from_dir(&dir)
                        .map_err(|e| StrataError::new_err(e.to_string()))?,
                )),
                None => None,
            };
            let options = ServeOptions {
                bind: SocketAddr::new(ip, port),
                token,
                web_viewer,
                frame_ancestors,
                ..ServeOptions::default()
            };
            let stores = find_stores(&paths).map_err(serve_error)?;
            let server = start(stores, options).map_err(serve_error)?;
            let stores = server
                .stores()
                .iter()
                .map(|(name, _, _)| (name.clone(), server.store_url(name)))
                .collect();
            Ok(NativeServer {
                base_url: server.base_url(),
                stores,
                server: Mutex::new(Some(server)),
            })
        })
    })
}
