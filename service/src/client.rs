//! The remote store: a [`VolumeSource`] over `strata serve`.
//!
//! Opening fetches the open document (header, histogram, stats, skeleton) in one request.
//! Bricks are fetched asynchronously on a small tokio runtime of the source's own, many at a
//! time over one HTTP/2 connection (h2c; `http1` uses a small pool of HTTP/1.1 connections
//! instead). The loader's fetcher is the shared [`TaskQueue`], which keeps the loader's
//! priority order (demand before prefetch, then the loader's priority: coarse before fine,
//! centre of the view first) and aborts requests on the wire that two successive views no
//! longer name (the HTTP/2 stream is reset); each request ([`fetch_one`]) retries (see
//! [`Retrying`]: a request cut on an open connection at once, refusals and 503/429 with
//! exponential backoff honouring `Retry-After`; reporting "connection lost, retrying" or
//! "server busy, retrying" meanwhile), and verifies every record's checksum on arrival,
//! re-requesting a damaged one once before reporting it. A blocking read (opening,
//! `read_brick_record`) gives up only after a bound in seconds (`give_up_after`), with an
//! error that says so. Decoded bricks go to the loader's CPU cache; there is no second cache
//! here.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use strata_source::task_queue::{
    BrickJobFuture, BrickJobOutcome, BrickJobs, TaskQueue, TaskRuntime,
};
use strata_source::{
    BrickFetcher, FetchOptions, QueueCounters, SourceError, SourceStatus, VolumeSource,
};
use strata_storage::brick::decode_brick;
use strata_storage::histogram::Histogram;
use strata_storage::store::{Skeleton, StoreStats};
use strata_storage::StoreHeader;
use strata_types::BrickId;

use crate::wire::{
    self, decode_open_document, frame_brick_path, frame_document_path, is_valid_store_name,
    OpenDocument, API_PREFIX, MAX_RETRY_AFTER,
};

/// How to reach a server.
#[derive(Clone, Debug)]
pub struct RemoteOptions {
    pub token: Option<String>,
    /// HTTP/1.1 with a small connection pool instead of one HTTP/2 connection.
    pub http1: bool,
    /// Requests in flight at most (HTTP/2 streams, or pooled HTTP/1.1 requests).
    pub max_in_flight: usize,
    pub connect_timeout: Duration,
    pub request_timeout: Duration,
    /// How long a blocking read (`read_brick_record`, opening) keeps retrying a server that
    /// cannot be reached, resets or answers busy before it fails (issue 49: a bound in
    /// seconds, not attempts: four attempts within 0.75 s failed renders under load).
    /// Zero: one attempt.
    pub give_up_after: Duration,
    /// For https: a PEM certificate to trust besides the system's (a lab's own CA).
    pub tls_ca_pem: Option<Vec<u8>>,
}

impl Default for RemoteOptions {
    fn default() -> Self {
        RemoteOptions {
            token: None,
            http1: false,
            max_in_flight: 64,
            connect_timeout: Duration::from_secs(3),
            request_timeout: Duration::from_secs(30),
            give_up_after: Duration::from_secs(20),
            tls_ca_pem: None,
        }
    }
}

/// A store URL that is not `http://HOST:PORT/v1/stores/NAME`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum StoreUrlError {
    #[error("{0}: not an http:// or https:// URL")]
    NotHttp(String),
    #[error("{0}: expected http://HOST:PORT{API_PREFIX}/stores/NAME")]
    NotAStorePath(String),
}

/// `http://host:port/v1/stores/NAME` split into the server's base and the store's name.
pub fn parse_store_url(url: &str) -> Result<(String, String), StoreUrlError> {
    let (scheme, rest) = if let Some(rest) = url.strip_prefix("http://") {
        ("http", rest)
    } else if let Some(rest) = url.strip_prefix("https://") {
        ("https", rest)
    } else {
        return Err(StoreUrlError::NotHttp(url.to_string()));
    };
    let not_a_store_path = || StoreUrlError::NotAStorePath(url.to_string());
    let (authority, path) = rest.split_once('/').ok_or_else(not_a_store_path)?;
    let name = path
        .trim_end_matches('/')
        .strip_prefix("v1/stores/")
        .ok_or_else(not_a_store_path)?;
    if authority.is_empty() || !is_valid_store_name(name) {
        return Err(not_a_store_path());
    }
    Ok((format!("{scheme}://{authority}"), name.to_string()))
}

/// Shared by the source and its fetchers.
struct Connection {
    location: String,
    base: String,
    name: String,
    generation: String,
    /// The frame of a 4-D store whose bricks this connection fetches (0 for a 3-D store).
    frame: u32,
    http: reqwest::Client,
    auth: Option<String>,
    /// When requests started failing to reach the server, and why; `None` while they succeed.
    lost: Mutex<Option<(Instant, String)>>,
}

impl Connection {
    fn lost(&self) -> MutexGuard<'_, Option<(Instant, String)>> {
        self.lost.lock().unwrap_or_else(|p| p.into_inner())
    }
    fn mark_reachable(&self) {
        let mut lost = self.lost();
        if lost.is_some() {
            tracing::info!("{}: connection restored", self.location);
            *lost = None;
        }
    }
    fn mark_lost(&self, why: String) {
        let mut lost = self.lost();
        if lost.is_none() {
            tracing::warn!("{}: connection lost ({why}), retrying", self.location);
            *lost = Some((Instant::now(), why));
        }
    }
    fn status(&self) -> SourceStatus {
        match &*self.lost() {
            None => SourceStatus::Available,
            Some((since, message)) => SourceStatus::Retrying {
                since_seconds: since.elapsed().as_secs_f64(),
                message: message.clone(),
            },
        }
    }
    fn brick_url(&self, id: BrickId) -> String {
        format!(
            "{}{}",
            self.base,
            frame_brick_path(&self.name, &self.generation, self.frame, id)
        )
    }
    /// The same server and store, fetching frame `frame`'s bricks (its own reachability).
    fn for_frame(&self, frame: u32) -> Connection {
        Connection {
            location: match frame {
                0 => format!("{}{API_PREFIX}/stores/{}", self.base, self.name),
                _ => format!(
                    "{}{API_PREFIX}/stores/{} (frame {frame})",
                    self.base, self.name
                ),
            },
            base: self.base.clone(),
            name: self.name.clone(),
            generation: self.generation.clone(),
            frame,
            http: self.http.clone(),
            auth: self.auth.clone(),
            lost: Mutex::new(None),
        }
    }
    fn get(&self, url: &str) -> reqwest::RequestBuilder {
        let request = self.http.get(url);
        match &self.auth {
            Some(a) => request.header(reqwest::header::AUTHORIZATION, a),
            None => request,
        }
    }
}

/// Why an attempt is worth repeating, which decides how soon.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Again {
    /// Failed after the connection was made (reset, closed before the answer, a body cut
    /// short): typically a kept-alive connection the server closed as the request left (the
    /// HTTP/1 keep-alive race). A brick GET is idempotent: once at once, then backoff.
    Cut,
    /// No connection (refused, unreachable, timed out): backoff.
    Unreachable,
    /// 503 or 429: backoff, at least the `Retry-After` the server gave.
    Busy(Option<Duration>),
}

/// The retry policy of one request: when to try again, and when to give up.
pub(crate) struct Retrying {
    started: Instant,
    bound: Option<Duration>,
    failures: u32,
    cut_retried: bool,
}

impl Retrying {
    /// `bound`: give up once this long has passed since the first attempt (`None`: never).
    pub(crate) fn new(bound: Option<Duration>) -> Self {
        Retrying {
            started: Instant::now(),
            bound,
            failures: 0,
            cut_retried: false,
        }
    }

    /// The wait before the next attempt after a failure of this kind, or `None` when the
    /// bound is spent. A wait is cut to what is left of the bound (one last attempt then).
    fn next(&mut self, again: Again) -> Option<Duration> {
        let failures = self.failures;
        self.failures += 1;
        let backoff = Duration::from_millis(50u64 << failures.min(6)).min(Duration::from_secs(2));
        let wait = match again {
            Again::Cut if !self.cut_retried => {
                self.cut_retried = true;
                Duration::ZERO
            }
            Again::Cut | Again::Unreachable | Again::Busy(None) => backoff,
            Again::Busy(Some(after)) => after.min(MAX_RETRY_AFTER).max(backoff),
        };
        match self.bound {
            None => Some(wait),
            Some(bound) => {
                let left = bound.checked_sub(self.started.elapsed())?;
                if left.is_zero() {
                    return None;
                }
                Some(wait.min(left))
            }
        }
    }

    fn attempts(&self) -> u32 {
        self.failures
    }

    /// The error of a request that was given up: the bound, the attempts, the last reason.
    fn gave_up(&self, last: &str) -> String {
        format!(
            "the server did not answer within {:.0} s ({} attempts); last: {last}",
            self.bound.unwrap_or_default().as_secs_f64(),
            self.attempts()
        )
    }
}

fn again_after_error(e: &reqwest::Error) -> Again {
    if e.is_connect() || e.is_timeout() {
        Again::Unreachable
    } else {
        Again::Cut
    }
}

/// `Retry-After` in seconds, capped (strata_source::wire::retry_after).
fn retry_after(headers: &reqwest::header::HeaderMap) -> Option<Duration> {
    wire::retry_after(headers.get(reqwest::header::RETRY_AFTER)?.to_str().ok()?)
}

/// What one attempt at a brick came to.
enum Attempt {
    Record(Vec<u8>),
    /// Worth trying again (connection error, 429, 503, a body cut short).
    Retry(String, Again),
    /// The server answered no (404, 401, 500 with its reason).
    Refused(String),
}

async fn attempt(conn: &Connection, id: BrickId) -> Attempt {
    let response = match conn.get(&conn.brick_url(id)).send().await {
        Ok(r) => r,
        Err(e) => {
            let why = describe(&e);
            conn.mark_lost(why.clone());
            return Attempt::Retry(why, again_after_error(&e));
        }
    };
    let status = response.status();
    if status == reqwest::StatusCode::OK {
        return match response.bytes().await {
            Ok(body) => {
                conn.mark_reachable();
                Attempt::Record(body.to_vec())
            }
            Err(e) => {
                let why = describe(&e);
                conn.mark_lost(why.clone());
                Attempt::Retry(why, again_after_error(&e))
            }
        };
    }
    if status == reqwest::StatusCode::TOO_MANY_REQUESTS
        || status == reqwest::StatusCode::SERVICE_UNAVAILABLE
    {
        let after = retry_after(response.headers());
        let why = format!("server busy ({status})");
        // Shown as "server busy, retrying" while it lasts.
        conn.mark_lost(why.clone());
        return Attempt::Retry(why, Again::Busy(after));
    }
    conn.mark_reachable();
    let text = response.text().await.unwrap_or_default();
    let text = text.trim().chars().take(300).collect::<String>();
    match status {
        reqwest::StatusCode::UNAUTHORIZED => {
            Attempt::Refused("the server refused the token (401): check --token-file".into())
        }
        _ => Attempt::Refused(format!("server answered {status}: {text}")),
    }
}

fn describe(e: &reqwest::Error) -> String {
    let mut s = e.to_string();
    let mut source = std::error::Error::source(e);
    while let Some(inner) = source {
        s = format!("{s}: {inner}");
        source = inner.source();
    }
    s
}

/// A store served by `strata serve`.
pub struct RemoteSource {
    /// Owned here and by the fetchers, never by a task: a runtime must not be dropped on one
    /// of its own threads.
    runtime: Arc<tokio::runtime::Runtime>,
    conn: Arc<Connection>,
    doc: OpenDocument,
    skeleton: Skeleton,
    options: RemoteOptions,
}

impl RemoteSource {
    /// Opens `http://host:port/v1/stores/NAME`: one request for everything but the bricks.
    pub fn open(url: &str, options: RemoteOptions) -> Result<RemoteSource, SourceError> {
        let refused = |message: String| SourceError::Refused {
            location: url.to_string(),
            message,
        };
        let (base, name) = parse_store_url(url).map_err(|e| refused(e.to_string()))?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("strata-remote-io")
            .enable_all()
            .build()
            .map_err(|e| refused(format!("cannot start the client's runtime: {e}")))?;
        // reqwest's rustls verifies with the platform's roots through the process's default
        // crypto provider: ring (no cmake, no OpenSSL).
        crate::install_tls_provider();
        let mut builder = reqwest::Client::builder()
            .connect_timeout(options.connect_timeout)
            .timeout(options.request_timeout)
            .tcp_nodelay(true)
            .no_proxy();
        builder = if options.http1 {
            builder.http1_only().pool_max_idle_per_host(8)
        } else {
            builder
                .http2_prior_knowledge()
                .http2_keep_alive_interval(Duration::from_secs(15))
                .http2_keep_alive_while_idle(true)
        };
        if let Some(pem) = &options.tls_ca_pem {
            let ca = reqwest::Certificate::from_pem(pem)
                .map_err(|e| refused(format!("the CA certificate is not PEM: {e}")))?;
            builder = builder.add_root_certificate(ca);
        }
        let http = builder
            .build()
            .map_err(|e| refused(format!("cannot build the HTTP client: {e}")))?;
        let auth = options
            .token
            .as_ref()
            .map(|t| format!("Bearer {}", t.trim()));
        let mut conn = Connection {
            location: url.to_string(),
            base: base.clone(),
            name: name.clone(),
            generation: String::new(),
            frame: 0,
            http,
            auth,
            lost: Mutex::new(None),
        };
        let open_url = format!("{base}{API_PREFIX}/stores/{name}");
        let bytes = runtime
            .block_on(get_document(&conn, &open_url, options.give_up_after))
            .map_err(|e| refused(e.to_string()))?;
        let (doc, skeleton) =
            decode_open_document(&bytes, strata_storage::store::KNOWN_STORE_FEATURES)
                .map_err(|e| refused(e.to_string()))?;
        conn.generation = doc.generation.clone();
        Ok(RemoteSource {
            runtime: Arc::new(runtime),
            conn: Arc::new(conn),
            doc,
            skeleton,
            options,
        })
    }

    /// Whether the server withheld description and provenance (without --expose-identifiers).
    pub fn identifiers_withheld(&self) -> bool {
        self.doc.identifiers_withheld
    }
    pub fn generation(&self) -> &str {
        &self.doc.generation
    }

    /// Frame `frame` (≥ 1) of this 4-D store: its open document (one request, blocking, with
    /// the open's retry bound), then a source on the same runtime fetching that frame's bricks.
    fn open_frame(&self, frame: u32) -> Result<RemoteSource, SourceError> {
        let conn = self.conn.for_frame(frame);
        let url = format!(
            "{}{}",
            conn.base,
            frame_document_path(&conn.name, &conn.generation, frame)
        );
        let refused = |message: String| SourceError::Refused {
            location: conn.location.clone(),
            message,
        };
        let bytes = self
            .runtime
            .block_on(get_document(&conn, &url, self.options.give_up_after))
            .map_err(|e| refused(e.to_string()))?;
        let (doc, skeleton) =
            decode_open_document(&bytes, strata_storage::store::KNOWN_STORE_FEATURES)
                .map_err(|e| refused(e.to_string()))?;
        if doc.generation != conn.generation {
            return Err(refused(format!(
                "frame {frame} belongs to generation {}, not {} (the store was re-imported): open it again",
                doc.generation, conn.generation
            )));
        }
        Ok(RemoteSource {
            runtime: self.runtime.clone(),
            conn: Arc::new(conn),
            doc,
            skeleton,
            options: self.options.clone(),
        })
    }
}

/// Why an open document (the store's or a frame's) was not had; the wording is the message.
#[derive(Debug, thiserror::Error)]
enum DocumentRefused {
    #[error("the server refused the token (401): check --token-file")]
    TokenRefused,
    #[error("the server requires a token (401): pass --token-file")]
    TokenRequired,
    #[error("the server has no store named '{0}'")]
    NoStore(String),
    /// The server's own words (which frame, how many there are).
    #[error("the server has no frame {frame} of '{name}': {text}")]
    NoFrame {
        frame: u32,
        name: String,
        text: String,
    },
    #[error("server answered {0}")]
    Status(reqwest::StatusCode),
    /// The retry bound, the attempts and the last reason.
    #[error("cannot reach the server: {0}")]
    Unreachable(String),
}

/// GETs an open document (the store's or a frame's), retrying within `give_up_after`.
async fn get_document(
    c: &Connection,
    open_url: &str,
    give_up_after: Duration,
) -> Result<Vec<u8>, DocumentRefused> {
    let name = &c.name;
    let mut retrying = Retrying::new(Some(give_up_after));
    loop {
        let (last, again) = match c.get(open_url).send().await {
            Ok(r) if r.status().is_success() => match r.bytes().await {
                Ok(b) => return Ok(b.to_vec()),
                Err(e) => (describe(&e), again_after_error(&e)),
            },
            Ok(r) if r.status() == reqwest::StatusCode::UNAUTHORIZED => {
                return Err(if c.auth.is_some() {
                    DocumentRefused::TokenRefused
                } else {
                    DocumentRefused::TokenRequired
                })
            }
            Ok(r) if r.status() == reqwest::StatusCode::NOT_FOUND => {
                let text = r.text().await.unwrap_or_default();
                let text = text.trim().chars().take(300).collect::<String>();
                return Err(if c.frame == 0 {
                    DocumentRefused::NoStore(name.clone())
                } else {
                    DocumentRefused::NoFrame {
                        frame: c.frame,
                        name: name.clone(),
                        text,
                    }
                });
            }
            Ok(r)
                if r.status() == reqwest::StatusCode::SERVICE_UNAVAILABLE
                    || r.status() == reqwest::StatusCode::TOO_MANY_REQUESTS =>
            {
                let after = retry_after(r.headers());
                (format!("server busy ({})", r.status()), Again::Busy(after))
            }
            Ok(r) if r.status().is_server_error() => (
                format!("server answered {}", r.status()),
                Again::Unreachable,
            ),
            Ok(r) => return Err(DocumentRefused::Status(r.status())),
            Err(e) => (describe(&e), again_after_error(&e)),
        };
        match retrying.next(again) {
            Some(wait) => tokio::time::sleep(wait).await,
            None => return Err(DocumentRefused::Unreachable(retrying.gave_up(&last))),
        }
    }
}

impl VolumeSource for RemoteSource {
    fn location(&self) -> String {
        self.conn.location.clone()
    }
    fn header(&self) -> &StoreHeader {
        &self.doc.header
    }
    fn skeleton(&self) -> &Skeleton {
        &self.skeleton
    }
    fn histogram(&self) -> &Histogram {
        &self.doc.histogram
    }
    fn stats(&self) -> &StoreStats {
        &self.doc.stats
    }
    /// Blocking, with a few retries; verified (a damaged record is fetched once more).
    fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
        if !self.layout().contains(id) {
            return Err(SourceError::Refused {
                location: self.location(),
                message: format!("brick {id:?} is outside the octree"),
            });
        }
        let conn = &self.conn;
        let mut retrying = Retrying::new(Some(self.options.give_up_after));
        self.runtime.block_on(async {
            let mut damaged = 0;
            loop {
                match attempt(conn, id).await {
                    Attempt::Record(record) => match decode_brick(id, &record) {
                        Ok(_) => return Ok(record),
                        Err(_) if damaged == 0 => {
                            damaged += 1;
                            continue;
                        }
                        Err(e) => return Err(SourceError::damaged(&conn.location, id, e)),
                    },
                    Attempt::Retry(why, again) => match retrying.next(again) {
                        Some(wait) => tokio::time::sleep(wait).await,
                        None => {
                            return Err(SourceError::Unavailable {
                                location: conn.location.clone(),
                                message: format!(
                                    "brick level {} at {:?}: {}",
                                    id.level,
                                    id.coords,
                                    retrying.gave_up(&why)
                                ),
                            })
                        }
                    },
                    Attempt::Refused(why) => {
                        return Err(SourceError::Refused {
                            location: conn.location.clone(),
                            message: format!("brick level {} at {:?}: {why}", id.level, id.coords),
                        })
                    }
                }
            }
        })
    }
    fn start_fetching(
        &self,
        options: FetchOptions,
    ) -> Option<Result<Box<dyn BrickFetcher>, SourceError>> {
        let max_in_flight = self
            .options
            .max_in_flight
            .min(options.max_in_transit.max(1))
            .max(1);
        let jobs = Arc::new(RemoteJobs {
            conn: self.conn.clone(),
            counters: Arc::default(),
        });
        Some(Ok(Box::new(TaskQueue::start(
            TaskRuntime::Shared(self.runtime.clone()),
            jobs,
            options.max_queued.max(1),
            max_in_flight,
        ))))
    }
    fn status(&self) -> SourceStatus {
        self.conn.status()
    }
    fn frame_count(&self) -> u32 {
        self.doc.header.frames.max(1)
    }
    /// Frame 0 is the store as opened; a later frame fetches its open document (one small
    /// request) when asked, which the viewer does for the frame ahead of the one shown.
    fn frame_source(self: Arc<Self>, frame: u32) -> Option<Arc<dyn VolumeSource>> {
        if frame == self.conn.frame {
            return Some(self);
        }
        if frame >= self.frame_count() {
            return None;
        }
        match self.open_frame(frame) {
            Ok(source) => Some(Arc::new(source)),
            Err(e) => {
                tracing::warn!("{e}");
                None
            }
        }
    }
}

/// What the retry loop counts (the queue counts the rest).
#[derive(Default)]
struct RetryCounters {
    retried: AtomicU64,
    checksum_failures: AtomicU64,
}

/// A [`RemoteSource`]'s requests, run by the shared [`TaskQueue`] (priorities, capacity,
/// cancellation on the wire): each a [`fetch_one`] with its retries, counted here.
struct RemoteJobs {
    conn: Arc<Connection>,
    counters: Arc<RetryCounters>,
}

impl BrickJobs for RemoteJobs {
    fn fetch(&self, id: BrickId) -> BrickJobFuture {
        Box::pin(fetch_one(self.conn.clone(), self.counters.clone(), id))
    }
    fn add_counters(&self, counters: &mut QueueCounters) {
        counters.retried = self.counters.retried.load(Ordering::Relaxed);
        counters.checksum_failures = self.counters.checksum_failures.load(Ordering::Relaxed);
    }
    fn status(&self) -> SourceStatus {
        self.conn.status()
    }
}

/// One brick: retried until it arrives verified, the server refuses it, or it is cancelled.
async fn fetch_one(
    conn: Arc<Connection>,
    counters: Arc<RetryCounters>,
    id: BrickId,
) -> BrickJobOutcome {
    // The loader's queue retries until the brick is no longer wanted (its status shows
    // "retrying" meanwhile): no bound here.
    let mut retrying = Retrying::new(None);
    let mut damaged = 0u32;
    loop {
        match attempt(&conn, id).await {
            Attempt::Record(record) => match decode_brick(id, &record) {
                Ok(voxels) => break Ok((Arc::new(voxels), record.len() as u64)),
                Err(e) => {
                    counters.checksum_failures.fetch_add(1, Ordering::Relaxed);
                    damaged += 1;
                    if damaged >= 2 {
                        break Err(SourceError::damaged(&conn.location, id, e));
                    }
                    tracing::warn!(
                        "{}: brick level {} at {:?} arrived damaged ({e}); requesting it again",
                        conn.location,
                        id.level,
                        id.coords
                    );
                    counters.retried.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
            },
            Attempt::Retry(_, again) => {
                counters.retried.fetch_add(1, Ordering::Relaxed);
                let wait = retrying.next(again).unwrap_or(Duration::from_secs(2));
                tokio::time::sleep(wait).await;
            }
            Attempt::Refused(why) => {
                break Err(SourceError::Refused {
                    location: conn.location.clone(),
                    message: format!("brick level {} at {:?}: {why}", id.level, id.coords),
                })
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::check_store_format;

    fn phantom_header() -> StoreHeader {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("phantom.strata");
        strata_storage::phantom::Phantom::cube(16)
            .write_store(&path, &strata_storage::import::ImportOptions::default())
            .unwrap();
        strata_storage::Store::open(&path).unwrap().header().clone()
    }

    #[test]
    fn a_store_with_a_feature_this_client_lacks_is_refused_by_name() {
        let mut header = phantom_header();
        let known = strata_storage::store::KNOWN_STORE_FEATURES;
        assert_eq!(check_store_format(&header, known), Ok(()));
        // What a newer server sends of a store whose bricks this build cannot decode.
        header.required_features.push("quantum-bricks".into());
        let refusal = check_store_format(&header, known).unwrap_err().to_string();
        assert!(refusal.contains("'quantum-bricks'"), "{refusal}");
        assert!(refusal.contains("update this client"), "{refusal}");
        // Every feature this build knows is accepted.
        header.required_features = known.iter().map(|f| f.to_string()).collect();
        assert_eq!(check_store_format(&header, known), Ok(()));
        header.format_version = strata_storage::store::STORE_FORMAT_VERSION + 1;
        let refusal = check_store_format(&header, known).unwrap_err().to_string();
        assert!(refusal.contains("format version"), "{refusal}");
    }

    #[test]
    fn store_urls() {
        assert_eq!(
            parse_store_url("http://127.0.0.1:8080/v1/stores/chest").unwrap(),
            ("http://127.0.0.1:8080".to_string(), "chest".to_string())
        );
        assert!(parse_store_url("http://h:1/v1/stores/../etc").is_err());
        assert!(parse_store_url("ftp://h/v1/stores/a").is_err());
        assert!(parse_store_url("http://h:1/other/a").is_err());
        assert_eq!(
            parse_store_url("https://h:1/v1/stores/a").unwrap().0,
            "https://h:1"
        );
    }

    #[test]
    fn retries_a_cut_request_at_once_backs_off_honours_retry_after_and_gives_up_at_the_bound() {
        let mut r = Retrying::new(None);
        assert_eq!(r.next(Again::Cut), Some(Duration::ZERO));
        // Only the first cut is retried at once: the next waits like any other failure.
        let second = r.next(Again::Cut).unwrap();
        assert!(second > Duration::ZERO);
        let third = r.next(Again::Unreachable).unwrap();
        assert!(third > second, "{third:?} after {second:?}");
        for _ in 0..20 {
            assert!(r.next(Again::Unreachable).unwrap() <= Duration::from_secs(2));
        }
        assert_eq!(
            r.next(Again::Busy(Some(Duration::from_secs(7)))),
            Some(Duration::from_secs(7))
        );
        assert_eq!(
            r.next(Again::Busy(Some(Duration::from_secs(3600)))),
            Some(MAX_RETRY_AFTER)
        );
        // A bound of zero: one attempt, then given up with a message that says so.
        let mut once = Retrying::new(Some(Duration::ZERO));
        assert_eq!(once.next(Again::Cut), None);
        let message = once.gave_up("connection refused");
        assert!(message.contains("within 0 s (1 attempts)"), "{message}");
        // A wait is cut to what is left of the bound.
        let mut bounded = Retrying::new(Some(Duration::from_secs(3600)));
        let wait = bounded.next(Again::Busy(Some(Duration::from_secs(7200))));
        assert!(wait.unwrap() <= MAX_RETRY_AFTER);
        let mut headers = reqwest::header::HeaderMap::new();
        headers.insert(reqwest::header::RETRY_AFTER, "2".parse().unwrap());
        assert_eq!(retry_after(&headers), Some(Duration::from_secs(2)));
        headers.insert(
            reqwest::header::RETRY_AFTER,
            "Wed, 21 Oct 2015 07:28:00 GMT".parse().unwrap(),
        );
        assert_eq!(retry_after(&headers), None);
    }
}
