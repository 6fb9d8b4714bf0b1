//! What the server tells its operator (issue 49): every request counted from its head to the
//! end of its answer, the access log (`--access-log FILE`, one line per request) and
//! `/metrics` in the Prometheus text format, written by hand (a few counters do not justify a
//! metrics dependency).
//!
//! A request is *started* when hyper hands its parsed head to the service and *answered* when
//! its response body has been handed to the connection in full (or it was a HEAD / empty
//! body); one whose future or body is dropped before that is *aborted*. A server that drops
//! no request has started = answered + in flight.

use std::collections::BTreeMap;
use std::io::Write;
use std::net::SocketAddr;
use std::path::Path;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Instant, SystemTime};

use axum::body::Body;
use axum::http::{Method, StatusCode};
use bytes::Bytes;
use http_body::{Body as _, Frame, SizeHint};

use crate::connections::RequestGuard;

/// Counters, logged once a minute, served at `/metrics` and readable by tests.
#[derive(Default, Debug)]
pub struct ServerCounters {
    /// Requests through the API's guard (token and concurrency checks).
    pub requests: AtomicU64,
    /// Every request whose head was parsed (API and page), and what became of it: answered
    /// (the response body handed to the connection in full) or aborted (dropped before; only
    /// when the client goes away or the server stops). Never started and not finished
    /// otherwise: a server that drops no request keeps started = answered + aborted + in
    /// flight with aborted 0 under any load of clients that stay.
    pub requests_started: AtomicU64,
    pub requests_answered: AtomicU64,
    pub requests_aborted: AtomicU64,
    /// Response body bytes of answered requests (all routes; `bytes` counts store data).
    pub response_bytes: AtomicU64,
    /// Answers the test hook `ServeOptions::corrupt_answers` damaged.
    pub corrupted: AtomicU64,
    pub bricks: AtomicU64,
    pub bytes: AtomicU64,
    pub not_modified: AtomicU64,
    pub errors: AtomicU64,
    pub unauthorized: AtomicU64,
    pub rejected_busy: AtomicU64,
    /// Connections closed unserved: every connection busy for the whole wait at a cap.
    pub connections_refused: AtomicU64,
    /// Connections closed (gracefully) to make room at a cap: idle ones evicted, and
    /// recently active ones asked to step aside (`Connection: close`, GOAWAY).
    pub connections_shed: AtomicU64,
    /// Connections closed because no request byte came within the header timeout.
    pub connections_idle_closed: AtomicU64,
}

/// Upper bounds (seconds) of the latency histogram's buckets; `+Inf` follows.
const LATENCY_BUCKETS: [f64; 12] = [
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 10.0,
];

/// An access-log path or a metrics label never quotes more of the client's input than this.
pub(crate) const MAX_QUOTED_INPUT: usize = 100;

pub(crate) struct Observer {
    counters: Arc<ServerCounters>,
    by_status: Mutex<BTreeMap<u16, u64>>,
    /// Cumulative counts are computed when written; these are per bucket (the last: +Inf).
    latency: [AtomicU64; LATENCY_BUCKETS.len() + 1],
    latency_sum_us: AtomicU64,
    /// Lines go to a writer thread, so a slow disk never blocks the server's tasks.
    access_log: Option<Mutex<mpsc::Sender<String>>>,
    token: Option<String>,
}

impl Observer {
    /// Opens (appends to) the access log and starts its writer thread (`strata-access-log`).
    pub(crate) fn new(
        counters: Arc<ServerCounters>,
        access_log: Option<&Path>,
        token: Option<String>,
    ) -> std::io::Result<Observer> {
        let access_log = match access_log {
            None => None,
            Some(path) => {
                let file = std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(path)?;
                let (tx, rx) = mpsc::channel::<String>();
                std::thread::Builder::new()
                    .name("strata-access-log".into())
                    .spawn(move || {
                        let mut out = std::io::LineWriter::new(file);
                        // Ends when the server (every sender) is gone.
                        for line in rx {
                            if let Err(e) = out.write_all(line.as_bytes()) {
                                tracing::warn!("strata serve: cannot write the access log: {e}");
                            }
                        }
                        let _ = out.flush();
                    })?;
                Some(Mutex::new(tx))
            }
        };
        Ok(Observer {
            counters,
            by_status: Mutex::new(BTreeMap::new()),
            latency: Default::default(),
            latency_sum_us: AtomicU64::new(0),
            access_log,
            token,
        })
    }

    /// A request's head arrived: counts it and returns what its answer's end records.
    pub(crate) fn start(
        self: &Arc<Self>,
        method: &Method,
        path: &str,
        peer: SocketAddr,
        guard: RequestGuard,
    ) -> Finish {
        self.counters
            .requests_started
            .fetch_add(1, Ordering::Relaxed);
        Finish {
            observer: self.clone(),
            _guard: guard,
            started: Instant::now(),
            method: method.clone(),
            path: log_path(path, self.token.as_deref()),
            peer,
            status: None,
            bytes: 0,
            complete: false,
        }
    }

    fn record(&self, finish: &Finish) {
        let Some(status) = finish.status.filter(|_| finish.complete) else {
            self.counters
                .requests_aborted
                .fetch_add(1, Ordering::Relaxed);
            return;
        };
        self.counters
            .requests_answered
            .fetch_add(1, Ordering::Relaxed);
        let elapsed = finish.started.elapsed();
        *self
            .by_status
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .entry(status.as_u16())
            .or_default() += 1;
        let seconds = elapsed.as_secs_f64();
        let bucket = LATENCY_BUCKETS
            .iter()
            .position(|&b| seconds <= b)
            .unwrap_or(LATENCY_BUCKETS.len());
        self.latency[bucket].fetch_add(1, Ordering::Relaxed);
        self.latency_sum_us
            .fetch_add(elapsed.as_micros() as u64, Ordering::Relaxed);
        self.counters
            .response_bytes
            .fetch_add(finish.bytes, Ordering::Relaxed);
        if let Some(log) = &self.access_log {
            let line = format!(
                "{} {} {} {} {} {} {:.6}\n",
                rfc3339_utc(SystemTime::now()),
                finish.peer.ip(),
                finish.method,
                finish.path,
                status.as_u16(),
                finish.bytes,
                seconds
            );
            let _ = log.lock().unwrap_or_else(|p| p.into_inner()).send(line);
        }
    }

    /// `/metrics`: the Prometheus text exposition format (version 0.0.4).
    pub(crate) fn metrics_text(&self, open_connections: usize) -> String {
        use std::fmt::Write as _;
        let c = &self.counters;
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let mut out = String::new();
        let mut counter = |name: &str, help: &str, value: u64| {
            let _ = writeln!(
                out,
                "# HELP {name} {help}\n# TYPE {name} counter\n{name} {value}"
            );
        };
        counter(
            "strata_requests_started_total",
            "Requests whose head was received.",
            load(&c.requests_started),
        );
        counter(
            "strata_requests_aborted_total",
            "Requests dropped before their answer was complete (connection gone).",
            load(&c.requests_aborted),
        );
        counter(
            "strata_response_body_bytes_total",
            "Response body bytes of answered requests.",
            load(&c.response_bytes),
        );
        counter(
            "strata_bricks_total",
            "Brick records answered (200 or 206).",
            load(&c.bricks),
        );
        counter(
            "strata_not_modified_total",
            "Conditional requests answered 304 (the client's cache was current).",
            load(&c.not_modified),
        );
        counter(
            "strata_requests_refused_busy_total",
            "Requests answered 503 because too many were in flight.",
            load(&c.rejected_busy),
        );
        counter(
            "strata_unauthorized_total",
            "Requests without the right token (401).",
            load(&c.unauthorized),
        );
        counter(
            "strata_connections_refused_total",
            "Connections closed unserved: every connection busy for the whole wait.",
            load(&c.connections_refused),
        );
        counter(
            "strata_connections_evicted_total",
            "Idle connections closed gracefully to admit another at a cap.",
            load(&c.connections_shed),
        );
        counter(
            "strata_connections_idle_closed_total",
            "Connections closed for sending no request within the header timeout.",
            load(&c.connections_idle_closed),
        );
        let _ = writeln!(
            out,
            "# HELP strata_open_connections Connections admitted and open.\n# TYPE strata_open_connections gauge\nstrata_open_connections {open_connections}"
        );
        let _ = writeln!(
            out,
            "# HELP strata_requests_total Answered requests by status.\n# TYPE strata_requests_total counter"
        );
        for (status, n) in self
            .by_status
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
        {
            let _ = writeln!(out, "strata_requests_total{{status=\"{status}\"}} {n}");
        }
        let _ = writeln!(
            out,
            "# HELP strata_request_duration_seconds Time from a request's head to the end of its answer.\n# TYPE strata_request_duration_seconds histogram"
        );
        let mut cumulative = 0;
        for (i, bound) in LATENCY_BUCKETS.iter().enumerate() {
            cumulative += load(&self.latency[i]);
            let _ = writeln!(
                out,
                "strata_request_duration_seconds_bucket{{le=\"{bound}\"}} {cumulative}"
            );
        }
        cumulative += load(&self.latency[LATENCY_BUCKETS.len()]);
        let _ = writeln!(
            out,
            "strata_request_duration_seconds_bucket{{le=\"+Inf\"}} {cumulative}\nstrata_request_duration_seconds_sum {}\nstrata_request_duration_seconds_count {cumulative}",
            load(&self.latency_sum_us) as f64 / 1e6
        );
        out
    }
}

/// The path as logged: no query (it may hold anything), the token replaced wherever it
/// appears, at most [`MAX_QUOTED_INPUT`] bytes, and only printable ASCII (hyper has already
/// refused spaces and control bytes; this also keeps a log line one line).
pub(crate) fn log_path(path: &str, token: Option<&str>) -> String {
    let path = path.split('?').next().unwrap_or("");
    let path = match token {
        Some(t) if !t.is_empty() && path.contains(t) => path.replace(t, "[token]"),
        _ => path.to_string(),
    };
    quote_input(&path)
}

/// User input for a log line or an error message: printable ASCII kept (others as `?`), at
/// most [`MAX_QUOTED_INPUT`] bytes, cut marked with `…`.
pub(crate) fn quote_input(input: &str) -> String {
    let mut out: String = input
        .bytes()
        .take(MAX_QUOTED_INPUT)
        .map(|b| {
            if b.is_ascii_graphic() {
                char::from(b)
            } else {
                '?'
            }
        })
        .collect();
    if input.len() > MAX_QUOTED_INPUT {
        out.push('…');
    }
    out
}

/// `2025-01-31T12:00:00.123Z` without a date crate (civil-from-days, H. Hinnant).
fn rfc3339_utc(t: SystemTime) -> String {
    let since = t.duration_since(SystemTime::UNIX_EPOCH).unwrap_or_default();
    let secs = since.as_secs() as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{:03}Z",
        rem / 3600,
        rem / 60 % 60,
        rem % 60,
        since.subsec_millis()
    )
}

/// One request from its head to the end of its answer; its drop records it (answered when
/// `complete`, else aborted) and frees the connection's in-flight place.
pub(crate) struct Finish {
    observer: Arc<Observer>,
    _guard: RequestGuard,
    started: Instant,
    method: Method,
    path: String,
    peer: SocketAddr,
    status: Option<StatusCode>,
    bytes: u64,
    complete: bool,
}

impl Drop for Finish {
    fn drop(&mut self) {
        self.observer.record(self);
    }
}

/// A response body that counts its bytes and records the request when it ends.
pub(crate) struct ObservedBody {
    inner: Body,
    finish: Option<Finish>,
}

impl ObservedBody {
    pub(crate) fn new(inner: Body, mut finish: Finish, status: StatusCode) -> ObservedBody {
        finish.status = Some(status);
        // A HEAD answer's body is never sent: the head is the whole answer.
        if finish.method == Method::HEAD {
            finish.complete = true;
        }
        ObservedBody {
            inner,
            finish: Some(finish),
        }
    }

    fn end(&mut self, complete: bool) {
        if let Some(mut f) = self.finish.take() {
            f.complete |= complete;
        }
    }
}

impl http_body::Body for ObservedBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        let polled = Pin::new(&mut self.inner).poll_frame(cx);
        match &polled {
            Poll::Ready(Some(Ok(frame))) => {
                let n = frame.data_ref().map_or(0, |d| d.len() as u64);
                if let Some(f) = self.finish.as_mut() {
                    f.bytes += n;
                }
                if self.inner.is_end_stream() {
                    self.end(true);
                }
            }
            Poll::Ready(None) => self.end(true),
            Poll::Ready(Some(Err(_))) => self.end(false),
            Poll::Pending => {}
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

impl Drop for ObservedBody {
    fn drop(&mut self) {
        // hyper drops an empty body (or one whose last frame it took) without polling to the
        // end: that is an answer sent in full.
        let complete = self.inner.is_end_stream();
        self.end(complete);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn logged_paths_hold_no_query_no_token_and_little_input() {
        let t = "0123456789abcdef0123456789abcdef";
        assert_eq!(
            log_path(&format!("/v1/stores/a?token={t}"), Some(t)),
            "/v1/stores/a"
        );
        assert_eq!(
            log_path(&format!("/v1/stores/{t}/x"), Some(t)),
            "/v1/stores/[token]/x"
        );
        let long = format!("/{}", "a".repeat(100_000));
        let logged = log_path(&long, None);
        assert!(
            logged.len() <= MAX_QUOTED_INPUT + '…'.len_utf8(),
            "{}",
            logged.len()
        );
        assert_eq!(quote_input("a b\nc"), "a?b?c");
    }

    #[test]
    fn times_are_rfc3339_utc() {
        let t = SystemTime::UNIX_EPOCH + std::time::Duration::from_millis(951_782_400_123);
        assert_eq!(rfc3339_utc(t), "2000-02-29T00:00:00.123Z");
        assert_eq!(
            rfc3339_utc(SystemTime::UNIX_EPOCH),
            "1970-01-01T00:00:00.000Z"
        );
    }
}
