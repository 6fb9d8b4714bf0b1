//! `strata serve`: stores, read-only, over HTTP/1.1 and HTTP/2 (h2c), on tokio + hyper with an
//! axum router and tower-http's CORS and timeouts.
//!
//! Safe by default: 127.0.0.1 on an ephemeral port; another address needs a bearer token,
//! compared in constant time, and a request without it gets a bare 401. Store names are looked
//! up in the table of what is served, never joined to a path. Description and provenance are
//! withheld unless asked for. Bounded: connections (excess ones are closed at accept),
//! concurrent requests (excess ones get 503 + Retry-After), header bytes (HTTP/1 buffer, HTTP/2
//! header list), time to send the headers (slow-loris clients are dropped), time per request.
//! Memory does not grow with the number of clients: each connection has a bounded buffer and
//! each request holds at most one brick record.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{Path as UrlPath, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use strata_storage::brick::verify_record;
use strata_storage::{StorageError, Store};
use strata_types::BrickId;
use tokio::sync::Semaphore;

use crate::connections::{Admitted, ConnectionHandle, Connections, MayClose};
// The counters live with what observes the server (observe.rs) and keep their old path here.
pub use crate::observe::ServerCounters;
use crate::observe::{ObservedBody, Observer};
use crate::web_viewer::{FrameSink, WebViewerAssets};
use crate::wire::{
    brick_etag, encode_open_document, is_valid_store_name, OpenDocument, StoreList, StoreListing,
    API_PREFIX, OPEN_DOCUMENT_TYPE,
};

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error(transparent)]
    Storage(#[from] StorageError),
    #[error("{path}: {message}")]
    Refused { path: PathBuf, message: String },
    #[error("{0}")]
    Config(String),
    #[error("cannot bind {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        source: std::io::Error,
    },
    #[error("cannot start the server's runtime: {0}")]
    Runtime(std::io::Error),
}

/// Limits and switches of a server. `Default` is the safe configuration.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    pub bind: SocketAddr,
    /// Bearer token; required when `bind` is not a loopback address.
    pub token: Option<String>,
    pub expose_identifiers: bool,
    pub max_connections: usize,
    /// Connections from one client address (below `max_connections`, so one address cannot
    /// take them all). When a cap is reached the connection idle longest is closed to admit
    /// the new one (see `connections.rs`); only when all are busy is the new one refused.
    pub max_connections_per_address: usize,
    /// A connection is evicted outright at a cap only after this long without a request;
    /// one active more recently is asked to step aside instead (`Connection: close` on its
    /// next answer, GOAWAY for HTTP/2) while the newcomer waits (issue 49: closing a
    /// connection idle for a moment cut the request its client had just sent).
    pub evict_idle_after: Duration,
    pub max_concurrent_requests: usize,
    /// HTTP/1 read buffer (bounds the request line and headers) and HTTP/2 header list size.
    pub max_header_bytes: usize,
    /// A client that has not sent a request's headers within this time is disconnected: the
    /// first byte must come within it from accept (an idle socket is closed), and the rest of
    /// the head within it from there (hyper's own timer, which starts at the first byte).
    pub header_read_timeout: Duration,
    /// A request not answered within this time gets 408.
    pub request_timeout: Duration,
    /// HTTP/2 streams per connection.
    pub max_streams_per_connection: u32,
    /// Added before every brick answer: a round-trip delay for benchmarks and tests on
    /// loopback (injected here, not with tc netem).
    pub added_delay: Duration,
    /// Serve HTTPS (HTTP/1.1 and HTTP/2 by ALPN) with this PEM certificate chain and key.
    pub tls: Option<TlsFiles>,
    /// Test hook: flip one byte of this brick's next N answers after the server verified them
    /// (corruption in transit).
    #[cfg(feature = "test-hooks")]
    pub corrupt_answers: Option<(BrickId, u32)>,
    /// Test hook: never answer a brick request below the root (it ends in the request
    /// timeout): a server that accepts and then stalls, for the no-frame-waits test.
    #[cfg(feature = "test-hooks")]
    pub stall_below_root: bool,
    /// The browser viewer's page, served at `/` (web_viewer.rs); None: `/` says how to build it.
    pub web_viewer: Option<Arc<WebViewerAssets>>,
    /// Who may embed the page in a frame: the sources of the page's CSP `frame-ancestors`
    /// (e.g. `http://localhost:*`). None: nobody (`'none'`). Only the Jupyter widget sets it
    /// (issue 50), for the notebook that shows the page; [`crate::web_viewer::check_frame_ancestors`] refuses
    /// anything that could add a directive or a header.
    pub frame_ancestors: Option<String>,
    /// Test hook: a sink for the frames the page posts to `/v1/test/frame` (the route exists
    /// only when this is set).
    pub test_frame_sink: Option<FrameSink>,
    /// Reverse proxies (`--trusted-proxy`): their connections carry many clients over one
    /// address, so they are a pool of their own under the global cap, never limited by the
    /// per-address cap meant for direct clients.
    pub trusted_proxies: Vec<IpAddr>,
    /// `--access-log FILE`: one line per request (appended).
    pub access_log: Option<PathBuf>,
}

impl Default for ServeOptions {
    fn default() -> Self {
        ServeOptions {
            bind: SocketAddr::from(([127, 0, 0, 1], 0)),
            token: None,
            expose_identifiers: false,
            max_connections: 256,
            max_connections_per_address: 64,
            evict_idle_after: Duration::from_secs(1),
            max_concurrent_requests: 512,
            max_header_bytes: 16 << 10,
            header_read_timeout: Duration::from_secs(5),
            request_timeout: Duration::from_secs(30),
            max_streams_per_connection: 256,
            added_delay: Duration::ZERO,
            #[cfg(feature = "test-hooks")]
            corrupt_answers: None,
            #[cfg(feature = "test-hooks")]
            stall_below_root: false,
            tls: None,
            web_viewer: None,
            frame_ancestors: None,
            test_frame_sink: None,
            trusted_proxies: Vec::new(),
            access_log: None,
        }
    }
}

/// PEM files of a TLS server: the certificate chain (leaf first) and its private key.
#[derive(Clone, Debug)]
pub struct TlsFiles {
    pub cert: PathBuf,
    pub key: PathBuf,
}

/// A rustls acceptor (ring provider) offering h2 and http/1.1 by ALPN.
fn tls_acceptor(files: &TlsFiles) -> Result<tokio_rustls::TlsAcceptor, ServeError> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let read = |path: &Path| {
        // Only a regular file: a FIFO given as a certificate would block the start for ever.
        strata_storage::regular_file::read(path).map_err(|e| ServeError::Refused {
            path: path.to_path_buf(),
            message: format!("cannot read it: {e}"),
        })
    };
    let bad = |path: &Path, message: String| ServeError::Refused {
        path: path.to_path_buf(),
        message,
    };
    let cert_pem = read(&files.cert)?;
    let certs = CertificateDer::pem_slice_iter(&cert_pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| bad(&files.cert, format!("not a PEM certificate chain: {e}")))?;
    if certs.is_empty() {
        return Err(bad(&files.cert, "holds no certificate".into()));
    }
    let key = PrivateKeyDer::from_pem_slice(&read(&files.key)?)
        .map_err(|e| bad(&files.key, format!("not a PEM private key: {e}")))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| ServeError::Config(format!("TLS: {e}")))?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .map_err(|e| bad(&files.key, format!("does not fit the certificate: {e}")))?;
    config.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
    Ok(tokio_rustls::TlsAcceptor::from(Arc::new(config)))
}

/// One served store.
struct ServedStore {
    name: String,
    path: PathBuf,
    generation: String,
    store: Store,
    open_document: axum::body::Bytes,
    /// The open document's JSON part, kept to build a later frame's document on request (a
    /// frame's skeleton is encoded when asked for: a long series would hold every one).
    document: OpenDocument,
    listing: StoreListing,
    /// The store as a read-only OME-Zarr 0.5 image (`/v1/stores/{name}/zarr/...`).
    zarr_view: strata_omezarr::view::ZarrView,
}

struct AppState {
    stores: HashMap<String, Arc<ServedStore>>,
    token: Option<Vec<u8>>,
    cache_control: HeaderValue,
    counters: Arc<ServerCounters>,
    requests: Arc<Semaphore>,
    added_delay: Duration,
    #[cfg(feature = "test-hooks")]
    corrupt_answers: std::sync::Mutex<Option<(BrickId, u32)>>,
    #[cfg(feature = "test-hooks")]
    stall_below_root: bool,
    observer: Arc<Observer>,
    connections: Arc<Connections>,
}

/// A store found on the command line: its name in URLs and its directory.
pub fn name_for_store(path: &Path) -> String {
    let file = path
        .file_name()
        .map_or_else(|| "store".to_string(), |n| n.to_string_lossy().into_owned());
    let stem = file.strip_suffix(".strata").unwrap_or(&file);
    let cleaned: String = stem
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect();
    cleaned.trim_start_matches('.').to_string()
}

/// Expands the command line: a store is served as itself; a folder that is not a store serves
/// every store directly inside it. An incomplete or damaged store is an error with the reason.
pub fn find_stores(inputs: &[PathBuf]) -> Result<Vec<(String, PathBuf)>, ServeError> {
    let mut found = Vec::new();
    for input in inputs {
        match Store::open_with_cache(input, 1 << 20) {
            Ok(store) => {
                drop(store);
                found.push((name_for_store(input), input.clone()));
            }
            Err(StorageError::NotAStore { .. }) if input.is_dir() => {
                let mut entries: Vec<PathBuf> = std::fs::read_dir(input)
                    .map_err(|e| StorageError::io(input, e))?
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.is_dir())
                    .collect();
                entries.sort();
                let before = found.len();
                for entry in entries {
                    match Store::open_with_cache(&entry, 1 << 20) {
                        Ok(store) => {
                            drop(store);
                            found.push((name_for_store(&entry), entry));
                        }
                        Err(StorageError::NotAStore { .. }) => {}
                        Err(e) => return Err(e.into()),
                    }
                }
                if found.len() == before {
                    return Err(ServeError::Refused {
                        path: input.clone(),
                        message: "neither a store nor a folder holding stores".into(),
                    });
                }
            }
            Err(e) => return Err(e.into()),
        }
    }
    let mut seen = std::collections::HashSet::new();
    for (name, path) in &found {
        if !is_valid_store_name(name) {
            return Err(ServeError::Refused {
                path: path.clone(),
                message: format!("cannot serve it under the name '{name}'"),
            });
        }
        if !seen.insert(name.clone()) {
            return Err(ServeError::Refused {
                path: path.clone(),
                message: format!("a second store would be served as '{name}'; rename one"),
            });
        }
    }
    Ok(found)
}

fn open_served(
    name: String,
    path: &Path,
    expose_identifiers: bool,
    base_url: &str,
) -> Result<ServedStore, ServeError> {
    let mut store = Store::open(path)?;
    // The store's lock names this server, so `strata render|info|view` of the same folder is
    // told at once to stream from here (sled lets one process open it).
    store.advertise_url(&format!("{base_url}{API_PREFIX}/stores/{name}"))?;
    // Opening checked completeness, the header and the skeleton's checksum; the root brick is
    // read and verified too, so a store damaged where every client starts is refused here.
    let layout = store.layout().clone();
    let root = BrickId::new((layout.level_count() - 1) as u8, [0, 0, 0]);
    store.read_brick(root)?;
    let mut header = store.header().clone();
    let generation = header.generation_id();
    if !expose_identifiers {
        header.description = String::new();
        header.provenance.inputs = Vec::new();
    }
    let doc = OpenDocument {
        name: name.clone(),
        generation: generation.clone(),
        identifiers_withheld: !expose_identifiers,
        header,
        histogram: store.histogram().clone(),
        stats: store.stats().clone(),
    };
    let open_document = encode_open_document(&doc, store.skeleton())
        .map_err(|e| ServeError::Config(format!("cannot encode {}: {e}", path.display())))?;
    let zarr_view = strata_omezarr::view::ZarrView::new(
        &name,
        store.header(),
        store.histogram(),
        store.stats(),
        store.skeleton(),
        expose_identifiers,
    )
    .map_err(|e| ServeError::Config(format!("{}: {e}", path.display())))?;
    let listing = StoreListing {
        name: name.clone(),
        generation: generation.clone(),
        dims: store.header().geometry.dims,
        levels: layout.level_count(),
    };
    Ok(ServedStore {
        name,
        path: path.to_path_buf(),
        generation,
        store,
        open_document: open_document.into(),
        document: doc,
        listing,
        zarr_view,
    })
}

/// A 128-bit random token, hex.
pub fn generate_token() -> Result<String, ServeError> {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes)
        .map_err(|e| ServeError::Config(format!("no random source for a token: {e}")))?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// Equal in time that does not depend on where the inputs differ (only on the length of the
/// presented value).
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    let mut diff = (a.len() ^ b.len()) as u8 | u8::from(a.len() != b.len());
    for (i, &x) in a.iter().enumerate() {
        diff |= x ^ b.get(i).copied().unwrap_or(0);
    }
    diff == 0
}

/// A running server.
pub struct RunningServer {
    scheme: &'static str,
    addr: SocketAddr,
    stores: Vec<(String, PathBuf, String)>,
    counters: Arc<ServerCounters>,
    shutdown: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl RunningServer {
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }
    /// `http://ADDR` or `https://ADDR` (no trailing slash).
    pub fn base_url(&self) -> String {
        format!("{}://{}", self.scheme, self.addr)
    }
    /// Served stores: (name, directory, generation).
    pub fn stores(&self) -> &[(String, PathBuf, String)] {
        &self.stores
    }
    pub fn store_url(&self, name: &str) -> String {
        format!("{}{API_PREFIX}/stores/{name}", self.base_url())
    }
    pub fn counters(&self) -> &ServerCounters {
        &self.counters
    }
    /// Blocks until the server stops (ctrl-c ends the process).
    pub fn wait(mut self) {
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
    /// Stops at once: the listener closes and every connection is dropped.
    pub fn stop(mut self) {
        self.stop_now();
    }
    fn stop_now(&mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for RunningServer {
    fn drop(&mut self) {
        self.stop_now();
    }
}

/// Opens the stores, binds, and serves on a thread of its own (`strata-serve`).
pub fn start(
    stores: Vec<(String, PathBuf)>,
    options: ServeOptions,
) -> Result<RunningServer, ServeError> {
    let loopback = options.bind.ip().is_loopback();
    if !loopback && options.token.is_none() {
        return Err(ServeError::Config(format!(
            "binding {} (not loopback) needs a token: pass --token-file, or --generate-token to print a new one",
            options.bind
        )));
    }
    if options.token.as_ref().is_some_and(|t| t.len() < 16) {
        return Err(ServeError::Config(
            "the token is shorter than 16 characters".into(),
        ));
    }
    if let Some(sources) = &options.frame_ancestors {
        crate::web_viewer::check_frame_ancestors(sources)
            .map_err(|e| ServeError::Config(e.to_string()))?;
    }
    if stores.is_empty() {
        return Err(ServeError::Config("no store to serve".into()));
    }
    let listener =
        std::net::TcpListener::bind(options.bind).map_err(|source| ServeError::Bind {
            addr: options.bind,
            source,
        })?;
    listener
        .set_nonblocking(true)
        .map_err(ServeError::Runtime)?;
    let addr = listener.local_addr().map_err(ServeError::Runtime)?;
    let tls_acceptor = options.tls.as_ref().map(tls_acceptor).transpose()?;
    let scheme = if tls_acceptor.is_some() {
        "https"
    } else {
        "http"
    };
    let mut served = HashMap::new();
    for (name, path) in stores {
        let s = open_served(
            name.clone(),
            &path,
            options.expose_identifiers,
            &format!("{scheme}://{addr}"),
        )?;
        served.insert(name, Arc::new(s));
    }
    let mut listing: Vec<(String, PathBuf, String)> = served
        .values()
        .map(|s| (s.name.clone(), s.path.clone(), s.generation.clone()))
        .collect();
    listing.sort();
    let counters = Arc::new(ServerCounters::default());
    let observer = Observer::new(
        counters.clone(),
        options.access_log.as_deref(),
        options.token.clone(),
    )
    .map_err(|e| ServeError::Refused {
        path: options.access_log.clone().unwrap_or_default(),
        message: format!("cannot open the access log: {e}"),
    })?;
    let connections = Connections::new(
        options.max_connections,
        options.max_connections_per_address,
        options.trusted_proxies.iter().copied(),
        options.evict_idle_after,
    );
    let state = Arc::new(AppState {
        stores: served,
        token: options.token.as_ref().map(|t| t.as_bytes().to_vec()),
        cache_control: HeaderValue::from_static(if options.token.is_some() {
            "private, max-age=31536000, immutable"
        } else {
            "public, max-age=31536000, immutable"
        }),
        counters: counters.clone(),
        requests: Arc::new(Semaphore::new(options.max_concurrent_requests.max(1))),
        added_delay: options.added_delay,
        #[cfg(feature = "test-hooks")]
        corrupt_answers: std::sync::Mutex::new(options.corrupt_answers),
        #[cfg(feature = "test-hooks")]
        stall_below_root: options.stall_below_root,
        observer: Arc::new(observer),
        connections,
    });
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .max_blocking_threads(16)
        .thread_name("strata-serve-io")
        .enable_all()
        .build()
        .map_err(ServeError::Runtime)?;
    let (tx, rx) = tokio::sync::oneshot::channel();
    let names: Vec<String> = listing.iter().map(|(n, _, _)| n.clone()).collect();
    tracing::info!(
        "strata serve: listening on {scheme}://{addr} ({}), token {}, stores: {}",
        if scheme == "https" {
            "HTTP/1.1 and HTTP/2 over TLS"
        } else {
            "HTTP/1.1 and h2c"
        },
        if options.token.is_some() {
            "required"
        } else {
            "not required (loopback)"
        },
        names.join(", ")
    );
    let thread = std::thread::Builder::new()
        .name("strata-serve".into())
        .spawn(move || {
            runtime.block_on(serve(listener, state, tls_acceptor, options, rx));
            // Connections still open are dropped with the runtime.
            runtime.shutdown_timeout(Duration::from_millis(100));
        })
        .map_err(ServeError::Runtime)?;
    Ok(RunningServer {
        scheme,
        addr,
        stores: listing,
        counters,
        shutdown: Some(tx),
        thread: Some(thread),
    })
}

fn router(state: Arc<AppState>, options: &ServeOptions) -> Router {
    let cors = tower_http::cors::CorsLayer::new()
        .allow_origin(tower_http::cors::Any)
        .allow_methods([Method::GET, Method::HEAD])
        .allow_headers([header::AUTHORIZATION, header::RANGE, header::IF_NONE_MATCH])
        .expose_headers([
            header::CONTENT_RANGE,
            header::CONTENT_LENGTH,
            header::ETAG,
            header::ACCEPT_RANGES,
        ])
        .max_age(Duration::from_secs(3600));
    let mut api = Router::new();
    if let Some(sink) = options.test_frame_sink.clone() {
        api = api.route(
            "/v1/test/frame",
            axum::routing::post(crate::web_viewer::receive_frame)
                .with_state(sink)
                .layer(axum::extract::DefaultBodyLimit::max(
                    crate::web_viewer::MAX_CAPTURED_BYTES,
                )),
        );
    }
    let api = api
        .route("/v1/stores", get(list_stores))
        .route("/v1/stores/{name}", get(open_store))
        .route(
            "/v1/stores/{name}/g/{generation}/bricks/{level}/{z}/{y}/{x}",
            get(brick),
        )
        .route(
            "/v1/stores/{name}/g/{generation}/f/{frame}",
            get(open_frame),
        )
        .route(
            "/v1/stores/{name}/g/{generation}/f/{frame}/bricks/{level}/{z}/{y}/{x}",
            get(frame_brick),
        )
        .route("/v1/stores/{name}/zarr/{*key}", get(zarr_key))
        // Inside the guard: off loopback only with the token.
        .route("/metrics", get(metrics))
        .fallback(not_found)
        .layer(axum::middleware::from_fn_with_state(state.clone(), guard))
        .layer(tower_http::timeout::TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            options.request_timeout,
        ))
        // Outermost: preflights are answered before authentication (browsers send no
        // Authorization header with them).
        .layer(cors)
        .with_state(state);
    // The page's files carry no data and a browser cannot send the token when it navigates:
    // outside the guard, inside the timeout.
    let page = crate::web_viewer::router(
        options.web_viewer.clone(),
        options.frame_ancestors.as_deref(),
    )
    .layer(tower_http::timeout::TimeoutLayer::with_status_code(
        StatusCode::REQUEST_TIMEOUT,
        options.request_timeout,
    ));
    api.merge(page)
}

async fn serve(
    listener: std::net::TcpListener,
    state: Arc<AppState>,
    tls_acceptor: Option<tokio_rustls::TlsAcceptor>,
    options: ServeOptions,
    mut shutdown: tokio::sync::oneshot::Receiver<()>,
) {
    let listener = match tokio::net::TcpListener::from_std(listener) {
        Ok(l) => l,
        Err(e) => {
            tracing::error!("strata serve: cannot listen: {e}");
            return;
        }
    };
    let app = router(state.clone(), &options);
    let tls = tls_acceptor.map(Arc::new);
    let mut builder = hyper_util::server::conn::auto::Builder::new(TokioExecutor::new());
    builder
        .http1()
        .timer(TokioTimer::new())
        .header_read_timeout(options.header_read_timeout)
        .max_buf_size(options.max_header_bytes.max(8192))
        .keep_alive(true);
    builder
        .http2()
        .timer(TokioTimer::new())
        .max_concurrent_streams(options.max_streams_per_connection)
        .max_header_list_size(options.max_header_bytes as u32)
        .max_pending_accept_reset_streams(Some(64))
        .keep_alive_interval(Some(Duration::from_secs(20)))
        .keep_alive_timeout(Duration::from_secs(20));
    let mut tasks = tokio::task::JoinSet::new();
    let mut minute = tokio::time::interval(Duration::from_secs(60));
    minute.tick().await;
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            _ = minute.tick() => log_counters(&state.counters),
            // Backpressure: while the waiting room is full, accept nothing.
            accepted = async {
                state.connections.room_to_wait().await;
                listener.accept().await
            } => {
                let (stream, peer) = match accepted {
                    Ok(a) => a,
                    Err(e) => {
                        tracing::warn!("strata serve: accept failed: {e}");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                        continue;
                    }
                };
                let _ = stream.set_nodelay(true);
                tasks.spawn(serve_connection(
                    stream,
                    peer,
                    state.clone(),
                    builder.clone(),
                    app.clone(),
                    tls.clone(),
                    options.header_read_timeout,
                ));
                // Reap finished connection tasks so the set does not grow.
                while tasks.try_join_next().is_some() {}
            }
        }
    }
    tasks.shutdown().await;
    log_counters(&state.counters);
}

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// One connection from accept to close: admission (waiting for a place while every one is
/// busy), the first byte within the header timeout, TLS, hyper, and a graceful close when the
/// registry asks for one (never a drop of a connection with a request in it).
async fn serve_connection(
    stream: tokio::net::TcpStream,
    peer: SocketAddr,
    state: Arc<AppState>,
    builder: hyper_util::server::conn::auto::Builder<TokioExecutor>,
    app: Router,
    tls: Option<Arc<tokio_rustls::TlsAcceptor>>,
    header_timeout: Duration,
) {
    let counters = state.counters.clone();
    // Backpressure: while every place is busy the socket waits here unread (its client sees
    // latency), for at most the header timeout.
    let admitted = match state
        .connections
        .admit_waiting(peer.ip(), header_timeout)
        .await
    {
        Ok(a) => a,
        Err(why) => {
            counters.connections_refused.fetch_add(1, Ordering::Relaxed);
            tracing::debug!("strata serve: connection from {peer} refused: {why:?}");
            return;
        }
    };
    // Counted when it closes, if it was asked to (evicted or asked to step aside).
    let admitted = CountedWhenAsked {
        admitted,
        counters: counters.clone(),
    };
    let handle = admitted.handle();
    // hyper's header timer starts only at the first byte (its protocol detection waits for it
    // without a limit): bound that wait here, so a socket that sends nothing is closed. An
    // eviction meanwhile closes it at once: it has sent nothing.
    // An eviction meanwhile closes it once it has been silent for the minimum idle time
    // and nothing waits in its socket (its first request may be on the wire).
    let probe = KernelProbe::new(&stream);
    let mut first = [0u8; 4];
    let peeked = tokio::select! {
        biased;
        peeked = tokio::time::timeout(header_timeout, stream.peek(&mut first)) => peeked,
        () = async {
            loop {
                match admitted.may_close() {
                    MayClose::Now if !probe.bytes_waiting() => return,
                    MayClose::Now => tokio::time::sleep(LOOK_AGAIN).await,
                    MayClose::After(d) => tokio::time::sleep(d).await,
                    MayClose::No | MayClose::Busy => admitted.shed().await,
                }
            }
        } => return,
    };
    match peeked {
        Ok(Ok(n)) if n > 0 => {
            handle.bytes_read();
            // h2c with prior knowledge starts with the preface "PRI * HTTP/2.0".
            if first[..n] == b"PRI "[..n] && n == 4 {
                handle.set_http2();
            }
        }
        Ok(Ok(_)) => return,
        Ok(Err(e)) => {
            tracing::debug!("strata serve: connection from {peer} ended: {e}");
            return;
        }
        Err(_) => {
            counters
                .connections_idle_closed
                .fetch_add(1, Ordering::Relaxed);
            return;
        }
    }
    let io = match tls {
        None => Io::Plain(stream),
        Some(acceptor) => {
            // The handshake is bounded like the headers: a client that stalls in it is dropped.
            match tokio::time::timeout(header_timeout, acceptor.accept(stream)).await {
                Ok(Ok(tls_stream)) => {
                    if tls_stream.get_ref().1.alpn_protocol() == Some(b"h2") {
                        handle.set_http2();
                    }
                    Io::Tls(Box::new(tls_stream))
                }
                Ok(Err(e)) => {
                    tracing::debug!("strata serve: TLS from {peer} failed: {e}");
                    return;
                }
                Err(_) => return,
            }
        }
    };
    let service = {
        let handle = handle.clone();
        let observer = state.observer.clone();
        hyper::service::service_fn(move |req: hyper::Request<hyper::body::Incoming>| {
            let mut app = app.clone();
            let http2 = req.version() == axum::http::Version::HTTP_2;
            if http2 {
                handle.set_http2();
            }
            // Busy from the head until the body is sent: a busy connection is never closed.
            let finish = observer.start(req.method(), req.uri().path(), peer, handle.request());
            let handle = handle.clone();
            async move {
                let Ok(response) = tower_service::Service::call(&mut app, req).await;
                let (mut parts, body) = response.into_parts();
                parts.headers.insert(
                    header::X_CONTENT_TYPE_OPTIONS,
                    HeaderValue::from_static("nosniff"),
                );
                // Asked to close: HTTP/1 answers this request and says it closes after it
                // (hyper then closes); HTTP/2 closes by GOAWAY, which needs no header.
                if !http2 && handle.closing() {
                    parts
                        .headers
                        .insert(header::CONNECTION, HeaderValue::from_static("close"));
                }
                let body = Body::new(ObservedBody::new(body, finish, parts.status));
                Ok::<_, std::convert::Infallible>(Response::from_parts(parts, body))
            }
        })
    };
    let conn = builder.serve_connection(
        TokioIo::new(ReadTracked {
            inner: io,
            handle: handle.clone(),
        }),
        service,
    );
    tokio::pin!(conn);
    let mut closing = false;
    // An HTTP/1 connection asked to close while idle for a moment only is looked at again
    // when it has been idle for the minimum (a request arriving first is answered with
    // `Connection: close`, and hyper closes after it).
    // (Asked already during the first read: look at once.)
    let mut look_again = Some(tokio::time::Instant::now());
    let served: Result<(), BoxError> = loop {
        let timer = async {
            match look_again {
                Some(at) => tokio::time::sleep_until(at).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            // The connection first: bytes that arrived with the eviction notice are read (and
            // make it busy) before the notice is judged.
            biased;
            served = conn.as_mut() => break served,
            () = admitted.shed(), if !closing => {}
            () = timer, if !closing => look_again = None,
        }
        match admitted.may_close() {
            // The runtime may not have seen bytes the kernel holds already (a stalled
            // machine): the client's request is there, so not closed; hyper reads it soon.
            MayClose::Now if !admitted.is_http2() && probe.bytes_waiting() => {
                look_again = Some(tokio::time::Instant::now() + LOOK_AGAIN);
            }
            MayClose::Now => {
                closing = true;
                conn.as_mut().graceful_shutdown();
            }
            MayClose::After(d) => look_again = Some(tokio::time::Instant::now() + d),
            // Busy: its answers carry `Connection: close`, and the end of its last request
            // notifies again.
            MayClose::No | MayClose::Busy => {}
        }
    };
    if let Err(e) = served {
        tracing::debug!("strata serve: connection from {peer} ended: {e}");
    }
    drop(admitted);
}

/// An admitted connection that counts itself in `connections_shed` when it closes having
/// been asked to (so the counter is the connections closed to make room, however admitted).
struct CountedWhenAsked {
    admitted: Admitted,
    counters: Arc<ServerCounters>,
}

impl std::ops::Deref for CountedWhenAsked {
    type Target = Admitted;
    fn deref(&self) -> &Admitted {
        &self.admitted
    }
}

impl Drop for CountedWhenAsked {
    fn drop(&mut self) {
        if self.admitted.asked_to_close() {
            self.counters
                .connections_shed
                .fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// How soon a connection asked to close is looked at again when its socket holds bytes that
/// the runtime has not read yet.
const LOOK_AGAIN: Duration = Duration::from_millis(20);

/// A second handle on a connection's socket (a duplicated descriptor), to ask the kernel
/// whether request bytes wait in it: the runtime learns of them only when its reactor runs,
/// and on a stalled machine an HTTP/1 connection could look idle for the minimum time with
/// its client's next request already received (issue 49: such a close is a failed request
/// for the client). Dropped with the connection's task, so the socket closes with it.
struct KernelProbe(Option<socket2::Socket>);

impl KernelProbe {
    fn new(stream: &tokio::net::TcpStream) -> Self {
        #[cfg(unix)]
        let handle = std::os::fd::AsFd::as_fd(stream).try_clone_to_owned();
        #[cfg(windows)]
        let handle = std::os::windows::io::AsSocket::as_socket(stream).try_clone_to_owned();
        KernelProbe(handle.ok().map(socket2::Socket::from))
    }

    /// Bytes wait to be read (a non-blocking peek: the descriptor shares the stream's
    /// non-blocking mode). Unknown counts as none: the minimum idle time still applies.
    fn bytes_waiting(&self) -> bool {
        let Some(socket) = &self.0 else {
            return false;
        };
        let mut byte = [std::mem::MaybeUninit::<u8>::uninit(); 1];
        matches!(socket.peek(&mut byte), Ok(n) if n > 0)
    }
}

/// The connection's transport: TCP, or TLS over it.
enum Io {
    Plain(tokio::net::TcpStream),
    Tls(Box<tokio_rustls::server::TlsStream<tokio::net::TcpStream>>),
}

/// The transport as hyper reads it, telling the registry when request bytes arrive (a
/// connection with unparsed bytes is not idle).
struct ReadTracked {
    inner: Io,
    handle: ConnectionHandle,
}

impl tokio::io::AsyncRead for ReadTracked {
    fn poll_read(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let polled = match &mut self.inner {
            Io::Plain(s) => std::pin::Pin::new(s).poll_read(cx, buf),
            Io::Tls(s) => std::pin::Pin::new(s.as_mut()).poll_read(cx, buf),
        };
        if matches!(polled, std::task::Poll::Ready(Ok(()))) && buf.filled().len() > before {
            self.handle.bytes_read();
        }
        polled
    }
}

impl tokio::io::AsyncWrite for ReadTracked {
    fn poll_write(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &[u8],
    ) -> std::task::Poll<std::io::Result<usize>> {
        match &mut self.inner {
            Io::Plain(s) => std::pin::Pin::new(s).poll_write(cx, buf),
            Io::Tls(s) => std::pin::Pin::new(s.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_write_vectored(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> std::task::Poll<std::io::Result<usize>> {
        match &mut self.inner {
            Io::Plain(s) => std::pin::Pin::new(s).poll_write_vectored(cx, bufs),
            Io::Tls(s) => std::pin::Pin::new(s.as_mut()).poll_write_vectored(cx, bufs),
        }
    }

    fn is_write_vectored(&self) -> bool {
        match &self.inner {
            Io::Plain(s) => s.is_write_vectored(),
            Io::Tls(s) => s.is_write_vectored(),
        }
    }

    fn poll_flush(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        match &mut self.inner {
            Io::Plain(s) => std::pin::Pin::new(s).poll_flush(cx),
            Io::Tls(s) => std::pin::Pin::new(s.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        match &mut self.inner {
            Io::Plain(s) => std::pin::Pin::new(s).poll_shutdown(cx),
            Io::Tls(s) => std::pin::Pin::new(s.as_mut()).poll_shutdown(cx),
        }
    }
}

fn log_counters(c: &ServerCounters) {
    tracing::info!(
        "strata serve: {} requests ({} started, {} answered, {} aborted), {} bricks, {:.1} MB sent, {} not modified (304), {} errors, {} unauthorized, {} busy (503), {} connections refused, {} evicted",
        c.requests.load(Ordering::Relaxed),
        c.requests_started.load(Ordering::Relaxed),
        c.requests_answered.load(Ordering::Relaxed),
        c.requests_aborted.load(Ordering::Relaxed),
        c.bricks.load(Ordering::Relaxed),
        c.bytes.load(Ordering::Relaxed) as f64 / 1e6,
        c.not_modified.load(Ordering::Relaxed),
        c.errors.load(Ordering::Relaxed),
        c.unauthorized.load(Ordering::Relaxed),
        c.rejected_busy.load(Ordering::Relaxed),
        c.connections_refused.load(Ordering::Relaxed),
        c.connections_shed.load(Ordering::Relaxed),
    );
}

/// Authentication and the concurrent-request bound, before any handler runs.
async fn guard(State(state): State<Arc<AppState>>, request: Request, next: Next) -> Response {
    state.counters.requests.fetch_add(1, Ordering::Relaxed);
    if let Some(token) = &state.token {
        let presented = request
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.as_bytes().strip_prefix(b"Bearer "))
            .unwrap_or(b"");
        if !constant_time_eq(presented, token) {
            state.counters.unauthorized.fetch_add(1, Ordering::Relaxed);
            return (
                StatusCode::UNAUTHORIZED,
                [(header::WWW_AUTHENTICATE, "Bearer")],
                "unauthorized\n",
            )
                .into_response();
        }
    }
    let Ok(_permit) = state.requests.clone().try_acquire_owned() else {
        state.counters.rejected_busy.fetch_add(1, Ordering::Relaxed);
        return (
            StatusCode::SERVICE_UNAVAILABLE,
            [(header::RETRY_AFTER, "1")],
            "busy, retry\n",
        )
            .into_response();
    };
    let response = next.run(request).await;
    if response.status().is_server_error() || response.status().is_client_error() {
        state.counters.errors.fetch_add(1, Ordering::Relaxed);
    }
    response
}

async fn metrics(State(state): State<Arc<AppState>>) -> Response {
    (
        [
            (
                header::CONTENT_TYPE,
                "text/plain; version=0.0.4; charset=utf-8",
            ),
            (header::CACHE_CONTROL, "no-store"),
        ],
        state.observer.metrics_text(state.connections.live()),
    )
        .into_response()
}

async fn not_found() -> Response {
    (StatusCode::NOT_FOUND, "not found\n").into_response()
}

async fn list_stores(State(state): State<Arc<AppState>>) -> Response {
    let mut stores: Vec<StoreListing> = state.stores.values().map(|s| s.listing.clone()).collect();
    stores.sort_by(|a, b| a.name.cmp(&b.name));
    match serde_json::to_vec(&StoreList { stores }) {
        Ok(json) => (
            [
                (header::CONTENT_TYPE, "application/json"),
                (header::CACHE_CONTROL, "no-cache"),
            ],
            json,
        )
            .into_response(),
        Err(e) => (StatusCode::INTERNAL_SERVER_ERROR, format!("{e}\n")).into_response(),
    }
}

async fn open_store(
    State(state): State<Arc<AppState>>,
    UrlPath(name): UrlPath<String>,
    headers: HeaderMap,
) -> Response {
    let Some(store) = state.stores.get(&name) else {
        return not_found().await;
    };
    // The name can be re-imported and served again: revalidate, keyed by the generation.
    let etag = format!("\"{}-open\"", store.generation);
    if if_none_match(&headers, &etag) {
        state.counters.not_modified.fetch_add(1, Ordering::Relaxed);
        return (StatusCode::NOT_MODIFIED, [(header::ETAG, etag)]).into_response();
    }
    state
        .counters
        .bytes
        .fetch_add(store.open_document.len() as u64, Ordering::Relaxed);
    (
        [
            (header::CONTENT_TYPE, OPEN_DOCUMENT_TYPE.to_string()),
            (header::CACHE_CONTROL, "no-cache".to_string()),
            (header::ETAG, etag),
        ],
        store.open_document.clone(),
    )
        .into_response()
}

fn if_none_match(headers: &HeaderMap, etag: &str) -> bool {
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|t| {
            let t = t.trim();
            t == "*" || t == etag || t.strip_prefix("W/") == Some(etag)
        })
}

type BrickPath = (String, String, String, String, String, String);
type FrameBrickPath = (String, String, String, String, String, String, String);

/// Why a store, generation or frame in a URL is not served: the status and the text a client
/// gets (small, so the lookups' results stay small; made a response where it is sent).
struct NotServed(StatusCode, String);

impl IntoResponse for NotServed {
    fn into_response(self) -> Response {
        (self.0, self.1).into_response()
    }
}

/// The served store `name` at `generation`, or the 404 a client gets.
fn served_generation(
    state: &AppState,
    name: &str,
    generation: &str,
) -> Result<Arc<ServedStore>, NotServed> {
    let Some(store) = state.stores.get(name).cloned() else {
        return Err(NotServed(StatusCode::NOT_FOUND, "not found\n".into()));
    };
    if generation != store.generation {
        return Err(NotServed(
            StatusCode::NOT_FOUND,
            "this generation of the store is not served (it was re-imported): open the store again\n"
                .into(),
        ));
    }
    Ok(store)
}

/// Frame `frame` (as written in the URL) of `store`, or the 400/404 naming it.
fn served_frame(store: &ServedStore, frame: &str) -> Result<u32, NotServed> {
    let Ok(frame) = frame.parse::<u32>() else {
        return Err(NotServed(
            StatusCode::BAD_REQUEST,
            format!("bad frame number '{frame}'\n"),
        ));
    };
    let count = store.store.frame_count();
    if frame >= count {
        return Err(NotServed(
            StatusCode::NOT_FOUND,
            format!(
                "frame {frame} is past the last frame of store '{}' ({count} frames, numbered from 0)\n",
                store.name
            ),
        ));
    }
    Ok(frame)
}

/// Frame `frame`'s open document: the store's, with that frame's skeleton. Its URL carries the
/// generation, so it is immutable (cached as bricks are).
async fn open_frame(
    State(state): State<Arc<AppState>>,
    UrlPath((name, generation, frame)): UrlPath<(String, String, String)>,
    headers: HeaderMap,
) -> Response {
    let store = match served_generation(&state, &name, &generation) {
        Ok(store) => store,
        Err(refused) => return refused.into_response(),
    };
    let frame = match served_frame(&store, &frame) {
        Ok(frame) => frame,
        Err(refused) => return refused.into_response(),
    };
    let etag = format!("\"{}-f{frame}-open\"", store.generation);
    if if_none_match(&headers, &etag) {
        state.counters.not_modified.fetch_add(1, Ordering::Relaxed);
        return (StatusCode::NOT_MODIFIED, [(header::ETAG, etag)]).into_response();
    }
    let Some(skeleton) = store.store.frame_skeleton(frame) else {
        return not_found().await;
    };
    let document = match encode_open_document(&store.document, skeleton) {
        Ok(document) => document,
        Err(e) => {
            return (
                StatusCode::INTERNAL_SERVER_ERROR,
                format!("cannot encode frame {frame} of '{name}': {e}\n"),
            )
                .into_response()
        }
    };
    state
        .counters
        .bytes
        .fetch_add(document.len() as u64, Ordering::Relaxed);
    let mut builder = Response::builder()
        .header(header::CONTENT_TYPE, OPEN_DOCUMENT_TYPE)
        .header(header::ETAG, etag);
    builder = builder.header(header::CACHE_CONTROL, state.cache_control.clone());
    builder
        .body(Body::from(document))
        .unwrap_or_else(|_| StatusCode::INTERNAL_SERVER_ERROR.into_response())
}

async fn brick(
    State(state): State<Arc<AppState>>,
    UrlPath((name, generation, level, z, y, x)): UrlPath<BrickPath>,
    headers: HeaderMap,
) -> Response {
    let store = match served_generation(&state, &name, &generation) {
        Ok(store) => store,
        Err(refused) => return refused.into_response(),
    };
    brick_of_frame(state, store, 0, [level, z, y, x], headers).await
}

/// A brick of any frame (frame 0 too: the same record as [`brick`]'s route).
async fn frame_brick(
    State(state): State<Arc<AppState>>,
    UrlPath((name, generation, frame, level, z, y, x)): UrlPath<FrameBrickPath>,
    headers: HeaderMap,
) -> Response {
    let store = match served_generation(&state, &name, &generation) {
        Ok(store) => store,
        Err(refused) => return refused.into_response(),
    };
    let frame = match served_frame(&store, &frame) {
        Ok(frame) => frame,
        Err(refused) => return refused.into_response(),
    };
    brick_of_frame(state, store, frame, [level, z, y, x], headers).await
}

/// One brick record of frame `frame` as stored, with the guard's limits, ETag, 304 and ranges.
async fn brick_of_frame(
    state: Arc<AppState>,
    store: Arc<ServedStore>,
    frame: u32,
    [level, z, y, x]: [String; 4],
    headers: HeaderMap,
) -> Response {
    let id = match (
        level.parse::<u8>(),
        z.parse::<u32>(),
        y.parse::<u32>(),
        x.parse::<u32>(),
    ) {
        (Ok(level), Ok(z), Ok(y), Ok(x)) => BrickId::new(level, [x, y, z]),
        _ => return (StatusCode::BAD_REQUEST, "bad brick coordinates\n").into_response(),
    };
    if !store.store.layout().contains(id) {
        return not_found().await;
    }
    if !state.added_delay.is_zero() {
        tokio::time::sleep(state.added_delay).await;
    }
    #[cfg(feature = "test-hooks")]
    if state.stall_below_root && usize::from(id.level) + 1 < store.store.layout().level_count() {
        std::future::pending::<()>().await;
    }
    let reader = store.clone();
    // A format-3 record is a share of its pack's map, sent without a copy (the map lives as
    // long as the body); other stores' records are read out.
    let record = match tokio::task::spawn_blocking(move || match frame {
        0 => match reader.store.brick_record_mapped(id) {
            Some(mapped) => Ok(bytes::Bytes::from_owner(mapped)),
            None => reader.store.read_brick_record(id).map(bytes::Bytes::from),
        },
        // Later frames' records are read out (the store maps frame 0's for the server).
        _ => reader
            .store
            .read_frame_brick_record(frame, id)
            .map(bytes::Bytes::from),
    })
    .await
    {
        Ok(Ok(record)) => record,
        Ok(Err(e)) => {
            tracing::error!("strata serve: {e}");
            return (StatusCode::INTERNAL_SERVER_ERROR, format!("{e}\n")).into_response();
        }
        Err(e) => {
            return (
                StatusCode::INTERNAL_SERVER_ERROR,
                format!("read failed: {e}\n"),
            )
                .into_response()
        }
    };
    let checksum = match verify_record(id, &record) {
        Ok(c) => c,
        Err(e) => {
            let message = format!(
                "{}: brick level {} at {:?} of frame {frame} fails its check on the server: {e}",
                store.path.display(),
                id.level,
                id.coords
            );
            tracing::error!("strata serve: {message}");
            return (StatusCode::INTERNAL_SERVER_ERROR, format!("{message}\n")).into_response();
        }
    };
    let etag = brick_etag(&store.generation, checksum);
    let common = [
        (header::ETAG, HeaderValue::from_str(&etag).ok()),
        (header::CACHE_CONTROL, Some(state.cache_control.clone())),
        (
            header::ACCEPT_RANGES,
            Some(HeaderValue::from_static("bytes")),
        ),
    ];
    let mut builder = Response::builder();
    for (k, v) in common.iter() {
        if let Some(v) = v {
            builder = builder.header(k, v);
        }
    }
    if if_none_match(&headers, &etag) {
        state.counters.not_modified.fetch_add(1, Ordering::Relaxed);
        return builder
            .status(StatusCode::NOT_MODIFIED)
            .body(Body::empty())
            .unwrap_or_else(|_| StatusCode::INTERNAL_SERVER_ERROR.into_response());
    }
    #[cfg_attr(not(feature = "test-hooks"), allow(unused_mut))]
    let mut body = record;
    #[cfg(feature = "test-hooks")]
    {
        let mut corrupt = state
            .corrupt_answers
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        if let Some((_, left)) = corrupt.as_mut().filter(|(t, n)| *t == id && *n > 0) {
            *left -= 1;
            let mut flipped = body.to_vec();
            let at = flipped.len() - 1;
            flipped[at] ^= 0x40;
            body = bytes::Bytes::from(flipped);
            state.counters.corrupted.fetch_add(1, Ordering::Relaxed);
            tracing::warn!("strata serve: test hook flipped a byte of brick {id:?} in transit");
        }
    }
    let total = body.len() as u64;
    let range = match headers.get(header::RANGE).map(|v| parse_range(v, total)) {
        None => None,
        Some(RangeAsk::Ignore) => None,
        Some(RangeAsk::Unsatisfiable) => {
            return builder
                .status(StatusCode::RANGE_NOT_SATISFIABLE)
                .header(header::CONTENT_RANGE, format!("bytes */{total}"))
                .body(Body::empty())
                .unwrap_or_else(|_| StatusCode::INTERNAL_SERVER_ERROR.into_response());
        }
        Some(RangeAsk::Bytes(a, b)) => Some((a, b)),
    };
    state.counters.bricks.fetch_add(1, Ordering::Relaxed);
    let builder = builder.header(header::CONTENT_TYPE, "application/octet-stream");
    let response = match range {
        Some((a, b)) => {
            let part = body.slice(a as usize..=b as usize);
            state
                .counters
                .bytes
                .fetch_add(part.len() as u64, Ordering::Relaxed);
            builder
                .status(StatusCode::PARTIAL_CONTENT)
                .header(header::CONTENT_RANGE, format!("bytes {a}-{b}/{total}"))
                .body(Body::from(part))
        }
        None => {
            state.counters.bytes.fetch_add(total, Ordering::Relaxed);
            builder.status(StatusCode::OK).body(Body::from(body))
        }
    };
    response.unwrap_or_else(|_| StatusCode::INTERNAL_SERVER_ERROR.into_response())
}

/// The store's read-only OME-Zarr 0.5 view: group and array metadata, the skeleton object, and
/// each 32³ chunk built from its brick (apron stripped). Chunks of fill value only are 404,
/// which Zarr readers take as the fill value. Bodies carry the generation in their ETag.
async fn zarr_key(
    State(state): State<Arc<AppState>>,
    UrlPath((name, key)): UrlPath<(String, String)>,
    headers: HeaderMap,
) -> Response {
    use strata_omezarr::view::ViewAnswer;
    let Some(store) = state.stores.get(&name).cloned() else {
        return not_found().await;
    };
    // Keys are matched against the view below; the tag keeps only their plain characters.
    let plain: String = key
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '/' | '.' | '_' | '-'))
        .collect();
    let etag = format!("\"{}-zarr-{plain}\"", store.generation);
    if if_none_match(&headers, &etag) {
        state.counters.not_modified.fetch_add(1, Ordering::Relaxed);
        return (StatusCode::NOT_MODIFIED, [(header::ETAG, etag)]).into_response();
    }
    let answer = match store.zarr_view.metadata(&key) {
        Some(answer) => Ok(answer),
        None => {
            let reader = store.clone();
            let read = tokio::task::spawn_blocking(move || {
                let Some(id) = reader.zarr_view.chunk_brick(&key) else {
                    return Ok(ViewAnswer::NotFound);
                };
                if reader.zarr_view.chunk_is_fill(reader.store.node(id)) {
                    return Ok(ViewAnswer::NotFound);
                }
                let payload = reader.store.read_brick(id).map_err(|e| e.to_string())?;
                reader
                    .zarr_view
                    .encode_chunk(id, &payload)
                    .map_err(|e| e.to_string())
            })
            .await;
            match read {
                Ok(answer) => answer,
                Err(e) => Err(format!("read failed: {e}")),
            }
        }
    };
    match answer {
        Ok(ViewAnswer::Found(body)) => {
            let total = body.len() as u64;
            let builder = Response::builder()
                .header(header::CONTENT_TYPE, "application/octet-stream")
                .header(header::CACHE_CONTROL, "no-cache")
                .header(header::ACCEPT_RANGES, "bytes")
                .header(header::ETAG, etag);
            let response = match headers.get(header::RANGE).map(|v| parse_range(v, total)) {
                Some(RangeAsk::Unsatisfiable) => builder
                    .status(StatusCode::RANGE_NOT_SATISFIABLE)
                    .header(header::CONTENT_RANGE, format!("bytes */{total}"))
                    .body(Body::empty()),
                Some(RangeAsk::Bytes(a, b)) => {
                    let part = body[a as usize..=b as usize].to_vec();
                    state
                        .counters
                        .bytes
                        .fetch_add(part.len() as u64, Ordering::Relaxed);
                    builder
                        .status(StatusCode::PARTIAL_CONTENT)
                        .header(header::CONTENT_RANGE, format!("bytes {a}-{b}/{total}"))
                        .body(Body::from(part))
                }
                None | Some(RangeAsk::Ignore) => {
                    state.counters.bytes.fetch_add(total, Ordering::Relaxed);
                    builder.status(StatusCode::OK).body(Body::from(body))
                }
            };
            response.unwrap_or_else(|_| StatusCode::INTERNAL_SERVER_ERROR.into_response())
        }
        Ok(ViewAnswer::NotFound) => not_found().await,
        Err(e) => {
            tracing::error!("strata serve: {e}");
            (StatusCode::INTERNAL_SERVER_ERROR, format!("{e}\n")).into_response()
        }
    }
}

enum RangeAsk {
    /// Absent, multiple ranges or not bytes: the whole record (RFC 9110 allows ignoring).
    Ignore,
    Unsatisfiable,
    /// Inclusive byte positions.
    Bytes(u64, u64),
}

fn parse_range(value: &HeaderValue, total: u64) -> RangeAsk {
    let Some(spec) = value
        .to_str()
        .ok()
        .and_then(|v| v.trim().strip_prefix("bytes="))
    else {
        return RangeAsk::Ignore;
    };
    if spec.contains(',') {
        return RangeAsk::Ignore;
    }
    let Some((a, b)) = spec.trim().split_once('-') else {
        return RangeAsk::Ignore;
    };
    let (a, b) = (a.trim(), b.trim());
    if total == 0 {
        return RangeAsk::Unsatisfiable;
    }
    let last = total - 1;
    match (a.parse::<u64>(), b.parse::<u64>()) {
        (Ok(a), Ok(b)) if a <= b && a <= last => RangeAsk::Bytes(a, b.min(last)),
        (Ok(a), Err(_)) if b.is_empty() && a <= last => RangeAsk::Bytes(a, last),
        (Err(_), Ok(n)) if a.is_empty() && n > 0 => RangeAsk::Bytes(total - n.min(total), last),
        (Ok(_), _) | (_, Ok(_)) => RangeAsk::Unsatisfiable,
        _ => RangeAsk::Ignore,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_time_comparison_is_equality() {
        assert!(constant_time_eq(b"abcdef0123456789", b"abcdef0123456789"));
        assert!(!constant_time_eq(b"abcdef0123456789", b"abcdef012345678"));
        assert!(!constant_time_eq(b"", b"abcdef0123456789"));
        assert!(!constant_time_eq(b"abcdef0123456788", b"abcdef0123456789"));
        // A longer value that starts with the token is not the token.
        assert!(!constant_time_eq(b"abcdef0123456789x", b"abcdef0123456789"));
    }

    #[test]
    fn ranges() {
        let v = |s: &str| HeaderValue::from_str(s).unwrap();
        assert!(matches!(
            parse_range(&v("bytes=0-9"), 100),
            RangeAsk::Bytes(0, 9)
        ));
        assert!(matches!(
            parse_range(&v("bytes=90-"), 100),
            RangeAsk::Bytes(90, 99)
        ));
        assert!(matches!(
            parse_range(&v("bytes=-10"), 100),
            RangeAsk::Bytes(90, 99)
        ));
        assert!(matches!(
            parse_range(&v("bytes=95-200"), 100),
            RangeAsk::Bytes(95, 99)
        ));
        assert!(matches!(
            parse_range(&v("bytes=100-"), 100),
            RangeAsk::Unsatisfiable
        ));
        assert!(matches!(
            parse_range(&v("bytes=0-1,5-6"), 100),
            RangeAsk::Ignore
        ));
        assert!(matches!(
            parse_range(&v("items=0-1"), 100),
            RangeAsk::Ignore
        ));
    }

    #[test]
    fn names_are_derived_safely() {
        assert_eq!(
            name_for_store(Path::new("/data/chest ct.strata")),
            "chest_ct"
        );
        assert_eq!(name_for_store(Path::new("/data/..hidden")), "hidden");
    }
}
