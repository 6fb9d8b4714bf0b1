//! A DICOMweb client: QIDO-RS search (studies, a study's series, a series' instances), WADO-RS
//! retrieve of a series into a folder, STOW-RS store of files.
//!
//! Retrieval follows the series' QIDO instance list. A series none of whose instances is in the
//! folder yet is asked for in one request (`/studies/S/series/T`: the whole series as one
//! multipart answer, each part saved as its `UID.dcm` once whole and checked); Orthanc spends
//! about 1.1 ms of CPU per instance request, which held even curl's per-instance retrieval to
//! half the series request's throughput (docs/bench-runs/pacs-2026-12-06.md). Whatever that answer did
//! not bring (a failure part-way, a server that refuses series retrieval) and every resume is
//! fetched per instance: a folder that already holds some instances is resumed, only the
//! missing ones are fetched. Every answer is `multipart/related; type="application/dicom"`
//! with `transfer-syntax=*` (the server sends what it stores, compressed or not; the importers
//! decode them), parsed as it streams ([`multipart`]) into a `.dcm.part` file and renamed when
//! whole. Per-instance requests run a few at a time (default 4), retry with backoff on 5xx, 429
//! and timeouts, and a body that stalls is cut.
//!
//! Safety: TLS is verified (a CA file may be added, nothing turns verification off); a redirect
//! to another host is refused; credentials (basic or bearer, read from a file or an environment
//! variable, never from the command line or the URL) are sent as headers only and appear in no
//! error, log line or `Debug` output. Errors name the server by its URL (which never carries
//! credentials: a URL with a user part is refused).

pub mod multipart;

use std::fmt;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use futures::StreamExt;
use serde::Deserialize;
use serde_json::Value;

use multipart::{boundary_of, Event, MultipartError, MultipartParser};

/// A credential: never printed (its `Debug` says `<redacted>`), sent only as a header.
#[derive(Clone)]
pub struct Secret(String);

impl Secret {
    pub fn new(value: impl Into<String>) -> Self {
        Secret(value.into())
    }
    /// The first line of a file (a trailing newline is not part of a password).
    pub fn from_file(path: &Path) -> Result<Self, PacsError> {
        let text = std::fs::read_to_string(path).map_err(|e| PacsError::Io {
            path: path.display().to_string(),
            problem: format!("cannot read the credential file: {e}"),
        })?;
        Ok(Secret(text.lines().next().unwrap_or("").to_string()))
    }
    pub fn from_env(var: &str) -> Result<Self, PacsError> {
        std::env::var(var)
            .map(Secret)
            .map_err(|_| PacsError::Config {
                server: "-".into(),
                problem: format!("the environment variable {var} (a credential) is not set"),
            })
    }
    fn expose(&self) -> &str {
        &self.0
    }
}

impl fmt::Debug for Secret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("<redacted>")
    }
}

/// How requests authenticate.
#[derive(Clone, Debug, Default)]
pub enum Auth {
    #[default]
    None,
    Basic {
        user: String,
        password: Secret,
    },
    Bearer(Secret),
}

/// Where a credential is read from (the servers file's form).
#[derive(Clone, Debug, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct SecretSource {
    /// A file whose first line is the secret.
    pub file: Option<PathBuf>,
    /// An environment variable holding it.
    pub env: Option<String>,
}

impl SecretSource {
    pub fn read(&self) -> Result<Secret, PacsError> {
        match (&self.file, &self.env) {
            (Some(f), None) => Secret::from_file(f),
            (None, Some(v)) => Secret::from_env(v),
            _ => Err(PacsError::Config {
                server: "-".into(),
                problem: "a credential needs exactly one of a file or an environment variable"
                    .into(),
            }),
        }
    }
}

/// A server's authentication as the servers file names it.
#[derive(Clone, Debug, Deserialize, Default)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum AuthConfig {
    #[default]
    None,
    Basic {
        user: String,
        password: SecretSource,
    },
    Bearer {
        token: SecretSource,
    },
}

impl AuthConfig {
    pub fn resolve(&self) -> Result<Auth, PacsError> {
        Ok(match self {
            AuthConfig::None => Auth::None,
            AuthConfig::Basic { user, password } => Auth::Basic {
                user: user.clone(),
                password: password.read()?,
            },
            AuthConfig::Bearer { token } => Auth::Bearer(token.read()?),
        })
    }
}

/// One named server of the servers file.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerConfig {
    pub name: String,
    /// The DICOMweb base URL (e.g. `https://pacs.example.org/dicom-web`).
    pub url: String,
    #[serde(default)]
    pub auth: AuthConfig,
    /// A PEM certificate to trust besides the system's roots.
    #[serde(default)]
    pub ca_file: Option<PathBuf>,
}

/// The servers file: `{"servers": [{"name": .., "url": .., "auth": .., "ca_file": ..}]}`.
#[derive(Clone, Debug, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct ServersFile {
    #[serde(default)]
    pub servers: Vec<ServerConfig>,
}

impl ServersFile {
    pub fn read(path: &Path) -> Result<Self, PacsError> {
        let io = |problem: String| PacsError::Io {
            path: path.display().to_string(),
            problem,
        };
        let text = std::fs::read_to_string(path).map_err(|e| io(format!("cannot read: {e}")))?;
        serde_json::from_str(&text).map_err(|e| io(format!("not a servers file: {e}")))
    }
    pub fn find(&self, name: &str) -> Option<&ServerConfig> {
        self.servers.iter().find(|s| s.name == name)
    }
}

/// Limits and pacing.
#[derive(Clone, Debug)]
pub struct ClientOptions {
    pub connect_timeout: Duration,
    /// A whole QIDO or STOW request.
    pub request_timeout: Duration,
    /// Longest wait for the next bytes of a response body before it counts as stalled.
    pub stall_timeout: Duration,
    /// Largest instance (one multipart part) accepted.
    pub max_part_bytes: u64,
    /// Largest QIDO/STOW JSON answer accepted.
    pub max_json_bytes: u64,
    /// Retrieve requests in flight at most.
    pub parallelism: usize,
    /// A series none of whose instances is in the folder yet is asked for in one WADO-RS
    /// request (the whole series as one multipart answer) before falling back to one request
    /// per instance for whatever that did not bring. Orthanc spends about 1.1 ms of CPU on each
    /// instance request besides the bytes: curl's 500 instance requests took 2-3 times as long
    /// as its one series request on loopback (docs/bench-runs/pacs-2026-12-06.md).
    pub whole_series: bool,
    /// Tries of one request on 5xx, 429 and timeouts (1 = no retry).
    pub attempts: u32,
    /// The first retry's wait; each next one doubles it.
    pub backoff: Duration,
    /// STOW-RS: bytes of files sent in one request at most (a larger file goes alone).
    pub stow_batch_bytes: u64,
}

impl Default for ClientOptions {
    fn default() -> Self {
        ClientOptions {
            connect_timeout: Duration::from_secs(10),
            request_timeout: Duration::from_secs(300),
            stall_timeout: Duration::from_secs(60),
            max_part_bytes: 2 << 30,
            max_json_bytes: 64 << 20,
            parallelism: 4,
            whole_series: true,
            attempts: 4,
            backoff: Duration::from_millis(500),
            stow_batch_bytes: 64 << 20,
        }
    }
}

/// What went wrong, always naming the server (its URL, without credentials).
#[derive(Debug, thiserror::Error)]
pub enum PacsError {
    #[error("{server}: {problem}")]
    Config { server: String, problem: String },
    #[error("{server}: {what}: {problem}")]
    Request {
        server: String,
        what: String,
        problem: String,
        retryable: bool,
    },
    #[error("{server}: {what}: HTTP {status}{hint}")]
    Status {
        server: String,
        what: String,
        status: u16,
        hint: String,
    },
    #[error("{server}: {what}: {source}")]
    Multipart {
        server: String,
        what: String,
        source: MultipartError,
    },
    #[error("{server}: {what}: {problem}")]
    Invalid {
        server: String,
        what: String,
        problem: String,
    },
    #[error("{path}: {problem}")]
    Io { path: String, problem: String },
    #[error("cancelled")]
    Cancelled,
}

impl PacsError {
    /// Worth another try: a timeout, a lost connection, 5xx, 429 or 408.
    pub fn is_retryable(&self) -> bool {
        match self {
            PacsError::Request { retryable, .. } => *retryable,
            PacsError::Status { status, .. } => *status >= 500 || *status == 429 || *status == 408,
            _ => false,
        }
    }
}

/// A study as QIDO-RS lists it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Study {
    pub study_uid: String,
    pub patient_name: String,
    pub patient_id: String,
    pub study_date: String,
    pub accession: String,
    pub description: String,
    pub modalities: Vec<String>,
    pub series_count: Option<u64>,
    pub instance_count: Option<u64>,
}

/// A series as QIDO-RS lists it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Series {
    pub series_uid: String,
    pub modality: String,
    pub description: String,
    pub number: Option<i64>,
    pub instance_count: Option<u64>,
}

/// Study search filters (DICOM matching: `*` and `?` wildcards in names, `A-B` date ranges).
#[derive(Clone, Debug, Default)]
pub struct StudyQuery {
    pub patient_name: Option<String>,
    pub patient_id: Option<String>,
    /// `YYYYMMDD`, `YYYYMMDD-YYYYMMDD`, `-YYYYMMDD` or `YYYYMMDD-`.
    pub study_date: Option<String>,
    pub modality: Option<String>,
    pub accession: Option<String>,
    pub study_uid: Option<String>,
    pub limit: Option<u32>,
}

/// How a retrieve went.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RetrieveReport {
    /// Instances the series has (QIDO's instance list).
    pub instances: usize,
    /// Fetched by this call.
    pub fetched: usize,
    /// Already in the folder, not fetched again.
    pub already_present: usize,
    /// Bytes written by this call.
    pub bytes: u64,
    /// WADO-RS requests made (retries included).
    pub requests: u64,
    /// The series' NumberOfSeriesRelatedInstances when it differs from the instance list.
    pub count_mismatch: Option<u64>,
}

/// Progress of a retrieve: instances done (present or fetched) of the total.
#[derive(Clone, Copy, Debug)]
pub struct RetrieveProgress {
    pub done: usize,
    pub total: usize,
    pub bytes: u64,
}

/// How a STOW-RS push went.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct StowReport {
    pub sent: usize,
    pub stored: usize,
    pub failed: usize,
    pub requests: usize,
}

/// A string refused as a DICOM UID; it holds at most the first 80 characters of it, so a
/// hostile answer cannot make the message unbounded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("'{0}' is not a DICOM UID (digits and dots, at most 64)")]
pub struct NotAUid(String);

/// UIDs go into URL paths and file names: digits and dots only, as DICOM defines them.
pub fn check_uid(uid: &str) -> Result<(), NotAUid> {
    if uid.is_empty() || uid.len() > 64 || !uid.bytes().all(|b| b.is_ascii_digit() || b == b'.') {
        return Err(NotAUid(uid.chars().take(80).collect()));
    }
    Ok(())
}

/// `base` checked and normalised: http(s), a host, no credentials in it, no trailing slash.
pub fn normalise_base_url(url: &str) -> Result<String, PacsError> {
    let bad = |problem: &str| PacsError::Config {
        server: redact_url(url),
        problem: problem.to_string(),
    };
    let rest = url
        .strip_prefix("https://")
        .or_else(|| url.strip_prefix("http://"))
        .ok_or_else(|| bad("not an http:// or https:// URL"))?;
    let authority = rest.split(['/', '?', '#']).next().unwrap_or("");
    if authority.contains('@') {
        return Err(bad(
            "credentials in the URL are refused (they would show in process lists and logs): \
             use a password or token file or environment variable",
        ));
    }
    if authority.is_empty() {
        return Err(bad("no host in the URL"));
    }
    if rest.contains(['?', '#']) {
        return Err(bad("a DICOMweb base URL has no query or fragment"));
    }
    Ok(url.trim_end_matches('/').to_string())
}

/// A URL with any user part removed (for messages about a URL that was refused).
pub fn redact_url(url: &str) -> String {
    match url.split_once("://") {
        Some((scheme, rest)) => {
            let (authority, path) = match rest.find(['/', '?', '#']) {
                Some(i) => rest.split_at(i),
                None => (rest, ""),
            };
            let host = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
            format!("{scheme}://{host}{path}")
        }
        None => url.to_string(),
    }
}

/// A query value: only what would break the query is encoded. DICOM's wildcards and the
/// person-name separator (`*`, `?`, `^`) stay as they are, which RFC 3986 allows in a query:
/// Orthanc 1.10 matches the raw text and finds nothing for `DOE%5EJ%2A`.
fn percent_encode(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for b in s.bytes() {
        if b.is_ascii_alphanumeric()
            || matches!(
                b,
                b'-' | b'_'
                    | b'.'
                    | b'~'
                    | b'*'
                    | b'?'
                    | b'^'
                    | b'!'
                    | b'$'
                    | b'\''
                    | b'('
                    | b')'
                    | b','
                    | b';'
                    | b':'
                    | b'@'
                    | b'/'
            )
        {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// The first value of a DICOM JSON attribute as text (person names: their alphabetic form).
fn json_string(object: &Value, tag: &str) -> Option<String> {
    let first = object.get(tag)?.get("Value")?.get(0)?;
    match first {
        Value::String(s) => Some(s.clone()),
        Value::Number(n) => Some(n.to_string()),
        // A person name: its alphabetic form, else the ideographic or phonetic one (a name
        // written only in kanji or hangul has no alphabetic group).
        Value::Object(o) => ["Alphabetic", "Ideographic", "Phonetic"]
            .iter()
            .find_map(|group| o.get(*group).and_then(Value::as_str))
            .map(str::to_string),
        _ => None,
    }
}

fn json_strings(object: &Value, tag: &str) -> Vec<String> {
    object
        .get(tag)
        .and_then(|a| a.get("Value"))
        .and_then(Value::as_array)
        .map(|values| {
            values
                .iter()
                .filter_map(|v| v.as_str().map(str::to_string))
                .collect()
        })
        .unwrap_or_default()
}

fn json_int(object: &Value, tag: &str) -> Option<i64> {
    let first = object.get(tag)?.get("Value")?.get(0)?;
    first
        .as_i64()
        .or_else(|| first.as_str().and_then(|s| s.trim().parse().ok()))
}

fn is_dicom_part10(head: &[u8]) -> bool {
    head.len() >= 132 && &head[128..132] == b"DICM"
}

/// The SOP Instance and Series Instance UIDs of the DICOM file at `path` (its header read up to
/// the pixel data), or why it cannot be read.
fn instance_identity(path: &Path) -> Result<(Option<String>, Option<String>), UnreadablePart> {
    use dicom_dictionary_std::tags;
    let file = dicom_object::OpenFileOptions::new()
        .read_until(tags::PIXEL_DATA)
        .open_file(path)
        .map_err(UnreadablePart)?;
    let text = |tag| {
        file.element(tag)
            .ok()
            .and_then(|e| e.to_str().ok())
            .map(|s| s.trim_end_matches(['\0', ' ']).to_string())
    };
    Ok((
        text(tags::SOP_INSTANCE_UID),
        text(tags::SERIES_INSTANCE_UID),
    ))
}

/// A retrieved part that does not open as a DICOM file.
#[derive(Debug, thiserror::Error)]
#[error("the part is not a readable DICOM file: {0}")]
struct UnreadablePart(dicom_object::ReadError);

/// Why a part that names series `series` is not of series `series_uid`, or `None` when it is.
fn series_mismatch(series: Option<&str>, series_uid: &str) -> Option<String> {
    (series != Some(series_uid)).then(|| {
        format!(
            "the instance belongs to series {}, not the one asked for",
            series.unwrap_or("(no Series Instance UID)")
        )
    })
}

/// Why the DICOM file at `path` is not instance `sop_uid` of series `series_uid`, or `None`
/// when it is.
fn identity_mismatch(path: &Path, series_uid: &str, sop_uid: &str) -> Option<String> {
    let (sop, series) = match instance_identity(path) {
        Ok(identity) => identity,
        Err(problem) => return Some(problem.to_string()),
    };
    if sop.as_deref() != Some(sop_uid) {
        return Some(format!(
            "the server answered instance {} instead",
            sop.as_deref().unwrap_or("(no SOP Instance UID)")
        ));
    }
    series_mismatch(series.as_deref(), series_uid)
}

/// The chain of an error's causes, joined (reqwest's own text says little: "error sending
/// request"; the cause says "connection refused").
fn describe(e: &(dyn std::error::Error + 'static)) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let more = s.to_string();
        if !text.contains(&more) {
            text.push_str(": ");
            text.push_str(&more);
        }
        source = s.source();
    }
    text
}

/// What one WADO sink can fail with.
enum SinkError {
    Multipart(MultipartError),
    Io(std::io::Error),
    ExtraPart,
    /// A part that is not what was asked for (the problem, for `PacsError::Invalid`).
    Invalid(String),
    Cancelled,
}

impl From<MultipartError> for SinkError {
    fn from(e: MultipartError) -> Self {
        SinkError::Multipart(e)
    }
}

struct Inner {
    base: String,
    http: reqwest::Client,
    auth: Auth,
    options: ClientOptions,
    requests: AtomicU64,
}

/// A DICOMweb server. Blocking methods over a small tokio runtime of its own.
pub struct Client {
    inner: Arc<Inner>,
    runtime: tokio::runtime::Runtime,
}

impl Client {
    /// A client of the DICOMweb service at `base_url`; `ca_pem` adds a trusted certificate.
    pub fn new(
        base_url: &str,
        auth: Auth,
        ca_pem: Option<&[u8]>,
        options: ClientOptions,
    ) -> Result<Client, PacsError> {
        let base = normalise_base_url(base_url)?;
        let config = |problem: String| PacsError::Config {
            server: base.clone(),
            problem,
        };
        // One thread's runtime: the caller's `block_on` drives the sockets itself. With worker
        // threads every body chunk crossed threads (the I/O driver on a worker waking the
        // caller), and a series streamed at a sixth of curl's speed, mostly in context switches
        // (issue 51's benchmark, perf). Requests still overlap: they are futures on one thread.
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| config(format!("cannot start the client's runtime: {e}")))?;
        // rustls on ring, as the data service's client: no cmake, no OpenSSL.
        let _ = rustls::crypto::ring::default_provider().install_default();
        // Redirects stay on the server's own scheme, host and port: another host would receive
        // the credentials (or serve something else under the server's name).
        let policy = reqwest::redirect::Policy::custom(|attempt| {
            let first = attempt.previous().first().cloned();
            let same = first.as_ref().is_some_and(|f| {
                f.scheme() == attempt.url().scheme()
                    && f.host_str() == attempt.url().host_str()
                    && f.port_or_known_default() == attempt.url().port_or_known_default()
            });
            if !same {
                let to = redact_url(attempt.url().as_str());
                attempt.error(format!("refused a redirect to another host ({to})"))
            } else if attempt.previous().len() > 5 {
                attempt.error("more than 5 redirects".to_string())
            } else {
                attempt.follow()
            }
        });
        let mut builder = reqwest::Client::builder()
            .connect_timeout(options.connect_timeout)
            .read_timeout(options.stall_timeout)
            .redirect(policy)
            .tcp_nodelay(true)
            .no_proxy();
        if let Some(pem) = ca_pem {
            let ca = reqwest::Certificate::from_pem(pem)
                .map_err(|e| config(format!("the CA certificate is not PEM: {e}")))?;
            builder = builder.add_root_certificate(ca);
        }
        let http = builder
            .build()
            .map_err(|e| config(format!("cannot build the HTTP client: {e}")))?;
        Ok(Client {
            inner: Arc::new(Inner {
                base,
                http,
                auth,
                options,
                requests: AtomicU64::new(0),
            }),
            runtime,
        })
    }

    /// The server's base URL (never with credentials).
    pub fn base_url(&self) -> &str {
        &self.inner.base
    }

    /// HTTP requests made so far (retries included).
    pub fn requests(&self) -> u64 {
        self.inner.requests.load(Ordering::Relaxed)
    }

    pub fn find_studies(&self, query: &StudyQuery) -> Result<Vec<Study>, PacsError> {
        self.runtime.block_on(self.inner.find_studies(query))
    }

    pub fn series_of(&self, study_uid: &str) -> Result<Vec<Series>, PacsError> {
        self.runtime.block_on(self.inner.series_of(study_uid, None))
    }

    /// The SOP instance UIDs of a series, in the server's order.
    pub fn instances_of(
        &self,
        study_uid: &str,
        series_uid: &str,
    ) -> Result<Vec<String>, PacsError> {
        self.runtime
            .block_on(self.inner.instances_of(study_uid, series_uid))
    }

    /// The series' middle instance by InstanceNumber (ties and instances without one by UID):
    /// the slice a thumbnail shows. `None` for an empty series.
    pub fn middle_instance(
        &self,
        study_uid: &str,
        series_uid: &str,
    ) -> Result<Option<String>, PacsError> {
        self.runtime
            .block_on(self.inner.middle_instance(study_uid, series_uid))
    }

    /// Retrieves one instance into `dir` as `SOPInstanceUID.dcm` (checked to be that instance
    /// of that series); its path.
    pub fn retrieve_instance(
        &self,
        study_uid: &str,
        series_uid: &str,
        sop_uid: &str,
        dir: &Path,
    ) -> Result<PathBuf, PacsError> {
        self.inner.check_uid(sop_uid)?;
        self.runtime.block_on(
            self.inner
                .fetch_instance(study_uid, series_uid, sop_uid, dir, None),
        )?;
        Ok(dir.join(format!("{sop_uid}.dcm")))
    }

    /// Retrieves a series into `dir` as `SOPInstanceUID.dcm` files, fetching only those not
    /// there yet. `progress` sees every instance done; `cancel` stops between chunks.
    pub fn retrieve_series(
        &self,
        study_uid: &str,
        series_uid: &str,
        dir: &Path,
        cancel: Option<&AtomicBool>,
        progress: Option<&dyn Fn(RetrieveProgress)>,
    ) -> Result<RetrieveReport, PacsError> {
        self.runtime.block_on(
            self.inner
                .retrieve_series(study_uid, series_uid, dir, cancel, progress),
        )
    }

    /// Stores DICOM files through STOW-RS.
    pub fn store_files(
        &self,
        files: &[PathBuf],
        progress: Option<&dyn Fn(usize)>,
    ) -> Result<StowReport, PacsError> {
        self.runtime
            .block_on(self.inner.store_files(files, progress))
    }
}

/// The DICOM files under `path` (a file, or a folder searched to 32 levels): those with the
/// Part 10 preamble; the count of other files skipped.
pub fn dicom_files(path: &Path) -> Result<(Vec<PathBuf>, usize), PacsError> {
    fn walk(dir: &Path, depth: u32, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
        if depth > 32 {
            return Ok(());
        }
        let mut entries: Vec<_> = std::fs::read_dir(dir)?.collect::<Result<_, _>>()?;
        entries.sort_by_key(|e| e.file_name());
        for entry in entries {
            let kind = entry.file_type()?;
            if kind.is_dir() {
                walk(&entry.path(), depth + 1, out)?;
            } else if kind.is_file() {
                out.push(entry.path());
            }
        }
        Ok(())
    }
    let io = |e: std::io::Error| PacsError::Io {
        path: path.display().to_string(),
        problem: e.to_string(),
    };
    let mut all = Vec::new();
    if path.is_dir() {
        walk(path, 0, &mut all).map_err(io)?;
    } else {
        all.push(path.to_path_buf());
    }
    let mut dicom = Vec::new();
    let mut skipped = 0;
    for file in all {
        let mut head = [0u8; 132];
        let ok = std::fs::File::open(&file)
            .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
            .is_ok();
        if ok && is_dicom_part10(&head) {
            dicom.push(file);
        } else {
            skipped += 1;
        }
    }
    Ok((dicom, skipped))
}

impl Inner {
    fn server(&self) -> String {
        self.base.clone()
    }

    fn authed(&self, request: reqwest::RequestBuilder) -> reqwest::RequestBuilder {
        match &self.auth {
            Auth::None => request,
            Auth::Basic { user, password } => request.basic_auth(user, Some(password.expose())),
            Auth::Bearer(token) => request.bearer_auth(token.expose()),
        }
    }

    fn transport_error(&self, what: &str, e: &reqwest::Error) -> PacsError {
        let problem = if e.is_timeout() {
            // reqwest's own text ("operation timed out") does not say which bound it hit.
            format!(
                "timed out (the server stalled for {} s, or the request took longer than {} s): {}",
                self.options.stall_timeout.as_secs_f64(),
                self.options.request_timeout.as_secs_f64(),
                describe(e)
            )
        } else {
            describe(e)
        };
        PacsError::Request {
            server: self.server(),
            what: what.to_string(),
            problem,
            retryable: (e.is_timeout() || e.is_connect() || e.is_request() || e.is_body())
                && !e.is_redirect(),
        }
    }

    fn status_error(&self, what: &str, status: reqwest::StatusCode) -> PacsError {
        let hint = match status.as_u16() {
            401 => " (the server wants credentials, or refused these)",
            403 => " (these credentials may not do this)",
            404 => " (not on this server)",
            406 => " (the server cannot send this as multipart DICOM)",
            _ => "",
        };
        PacsError::Status {
            server: self.server(),
            what: what.to_string(),
            status: status.as_u16(),
            hint: hint.to_string(),
        }
    }

    /// Runs `once` up to `attempts` times while it fails with something worth retrying.
    async fn with_retries<T, F, Fut>(&self, what: &str, mut once: F) -> Result<T, PacsError>
    where
        F: FnMut() -> Fut,
        Fut: std::future::Future<Output = Result<T, PacsError>>,
    {
        let mut attempt = 0u32;
        loop {
            match once().await {
                Err(e) if e.is_retryable() && attempt + 1 < self.options.attempts.max(1) => {
                    let wait = self.options.backoff * 2u32.saturating_pow(attempt);
                    tracing::warn!("{what}: {e}; retrying in {:.1} s", wait.as_secs_f64());
                    tokio::time::sleep(wait).await;
                    attempt += 1;
                }
                other => return other,
            }
        }
    }

    /// The next chunk of a body, or `None` at its end; a stall is a retryable error.
    async fn next_chunk(
        &self,
        what: &str,
        response: &mut reqwest::Response,
    ) -> Result<Option<impl AsRef<[u8]>>, PacsError> {
        match tokio::time::timeout(self.options.stall_timeout, response.chunk()).await {
            Err(_) => Err(PacsError::Request {
                server: self.server(),
                what: what.to_string(),
                problem: format!(
                    "the server stalled: no data for {} s",
                    self.options.stall_timeout.as_secs_f64()
                ),
                retryable: true,
            }),
            Ok(Err(e)) => Err(self.transport_error(what, &e)),
            Ok(Ok(chunk)) => Ok(chunk),
        }
    }

    /// GET a QIDO-RS path: its JSON array (empty for 204), bounded.
    async fn qido(&self, what: &str, path_and_query: &str) -> Result<Vec<Value>, PacsError> {
        let url = format!("{}{}", self.base, path_and_query);
        self.with_retries(what, || async {
            self.requests.fetch_add(1, Ordering::Relaxed);
            let mut response = self
                .authed(self.http.get(&url))
                .header(reqwest::header::ACCEPT, "application/dicom+json")
                .timeout(self.options.request_timeout)
                .send()
                .await
                .map_err(|e| self.transport_error(what, &e))?;
            if response.status() == reqwest::StatusCode::NO_CONTENT {
                return Ok(Vec::new());
            }
            if !response.status().is_success() {
                return Err(self.status_error(what, response.status()));
            }
            let mut body = Vec::new();
            while let Some(chunk) = self.next_chunk(what, &mut response).await? {
                body.extend_from_slice(chunk.as_ref());
                if body.len() as u64 > self.options.max_json_bytes {
                    return Err(PacsError::Invalid {
                        server: self.server(),
                        what: what.to_string(),
                        problem: format!(
                            "the answer is larger than {} bytes",
                            self.options.max_json_bytes
                        ),
                    });
                }
            }
            if body.iter().all(u8::is_ascii_whitespace) {
                return Ok(Vec::new());
            }
            match serde_json::from_slice::<Value>(&body) {
                Ok(Value::Array(items)) => Ok(items),
                Ok(_) => Err(PacsError::Invalid {
                    server: self.server(),
                    what: what.to_string(),
                    problem: "the answer is not a JSON array".into(),
                }),
                Err(e) => Err(PacsError::Invalid {
                    server: self.server(),
                    what: what.to_string(),
                    problem: format!("the answer is not DICOM JSON: {e}"),
                }),
            }
        })
        .await
    }

    fn check_uid(&self, uid: &str) -> Result<(), PacsError> {
        check_uid(uid).map_err(|problem| PacsError::Config {
            server: self.server(),
            problem: problem.to_string(),
        })
    }

    async fn find_studies(&self, q: &StudyQuery) -> Result<Vec<Study>, PacsError> {
        let mut params: Vec<(&str, String)> = Vec::new();
        let mut add = |key: &'static str, value: &Option<String>| {
            if let Some(v) = value {
                params.push((key, v.clone()));
            }
        };
        add("PatientName", &q.patient_name);
        add("PatientID", &q.patient_id);
        add("StudyDate", &q.study_date);
        add("ModalitiesInStudy", &q.modality);
        add("AccessionNumber", &q.accession);
        add("StudyInstanceUID", &q.study_uid);
        if let Some(date) = &q.study_date {
            let ok = date.len() <= 17
                && date.bytes().all(|b| b.is_ascii_digit() || b == b'-')
                && date.split('-').all(|d| d.is_empty() || d.len() == 8);
            if !ok {
                return Err(PacsError::Config {
                    server: self.server(),
                    problem: format!(
                        "'{date}' is not a study date (YYYYMMDD or YYYYMMDD-YYYYMMDD)"
                    ),
                });
            }
        }
        if let Some(limit) = q.limit {
            params.push(("limit", limit.to_string()));
        }
        // The counts and descriptions are optional return keys: ask for them.
        for tag in ["00081030", "00080061", "00201206", "00201208"] {
            params.push(("includefield", tag.to_string()));
        }
        let query: Vec<String> = params
            .iter()
            .map(|(k, v)| format!("{k}={}", percent_encode(v)))
            .collect();
        let items = self
            .qido("study search", &format!("/studies?{}", query.join("&")))
            .await?;
        Ok(items
            .iter()
            .filter_map(|o| {
                Some(Study {
                    study_uid: json_string(o, "0020000D")?,
                    patient_name: json_string(o, "00100010").unwrap_or_default(),
                    patient_id: json_string(o, "00100020").unwrap_or_default(),
                    study_date: json_string(o, "00080020").unwrap_or_default(),
                    accession: json_string(o, "00080050").unwrap_or_default(),
                    description: json_string(o, "00081030").unwrap_or_default(),
                    modalities: json_strings(o, "00080061"),
                    series_count: json_int(o, "00201206").and_then(|n| u64::try_from(n).ok()),
                    instance_count: json_int(o, "00201208").and_then(|n| u64::try_from(n).ok()),
                })
            })
            .collect())
    }

    async fn series_of(
        &self,
        study_uid: &str,
        series_uid: Option<&str>,
    ) -> Result<Vec<Series>, PacsError> {
        self.check_uid(study_uid)?;
        let mut query = "includefield=0008103E&includefield=00201209".to_string();
        if let Some(s) = series_uid {
            self.check_uid(s)?;
            query.push_str(&format!("&SeriesInstanceUID={s}"));
        }
        let items = self
            .qido(
                "series search",
                &format!("/studies/{study_uid}/series?{query}"),
            )
            .await?;
        let mut series: Vec<Series> = items
            .iter()
            .filter_map(|o| {
                Some(Series {
                    series_uid: json_string(o, "0020000E")?,
                    modality: json_string(o, "00080060").unwrap_or_default(),
                    description: json_string(o, "0008103E").unwrap_or_default(),
                    number: json_int(o, "00200011"),
                    instance_count: json_int(o, "00201209").and_then(|n| u64::try_from(n).ok()),
                })
            })
            .collect();
        series.sort_by_key(|s| s.number.unwrap_or(i64::MAX));
        Ok(series)
    }

    /// A series' instances from QIDO: (InstanceNumber, SOP Instance UID), UIDs checked (a UID
    /// becomes a file name: a hostile one must not reach the file system).
    async fn instance_list(
        &self,
        study_uid: &str,
        series_uid: &str,
    ) -> Result<Vec<(Option<i64>, String)>, PacsError> {
        self.check_uid(study_uid)?;
        self.check_uid(series_uid)?;
        let items = self
            .qido(
                "instance list",
                &format!("/studies/{study_uid}/series/{series_uid}/instances"),
            )
            .await?;
        let mut instances = Vec::with_capacity(items.len());
        for o in &items {
            let Some(uid) = json_string(o, "00080018") else {
                continue;
            };
            self.check_uid(&uid)?;
            instances.push((json_int(o, "00200013"), uid));
        }
        Ok(instances)
    }

    async fn instances_of(
        &self,
        study_uid: &str,
        series_uid: &str,
    ) -> Result<Vec<String>, PacsError> {
        let mut uids: Vec<String> = self
            .instance_list(study_uid, series_uid)
            .await?
            .into_iter()
            .map(|(_, uid)| uid)
            .collect();
        uids.sort();
        uids.dedup();
        Ok(uids)
    }

    async fn middle_instance(
        &self,
        study_uid: &str,
        series_uid: &str,
    ) -> Result<Option<String>, PacsError> {
        let mut numbered: Vec<(i64, String)> = self
            .instance_list(study_uid, series_uid)
            .await?
            .into_iter()
            .map(|(number, uid)| (number.unwrap_or(i64::MAX), uid))
            .collect();
        numbered.sort();
        numbered.dedup();
        let middle = numbered.len() / 2;
        Ok(numbered.into_iter().nth(middle).map(|(_, uid)| uid))
    }

    async fn retrieve_series(
        &self,
        study_uid: &str,
        series_uid: &str,
        dir: &Path,
        cancel: Option<&AtomicBool>,
        progress: Option<&dyn Fn(RetrieveProgress)>,
    ) -> Result<RetrieveReport, PacsError> {
        let uids = self.instances_of(study_uid, series_uid).await?;
        let expected = self
            .series_of(study_uid, Some(series_uid))
            .await?
            .first()
            .and_then(|s| s.instance_count);
        if uids.is_empty() {
            return Err(PacsError::Invalid {
                server: self.server(),
                what: format!("series {series_uid}"),
                problem: "the server lists no instances of this series".into(),
            });
        }
        std::fs::create_dir_all(dir).map_err(|e| PacsError::Io {
            path: dir.display().to_string(),
            problem: format!("cannot create the folder: {e}"),
        })?;
        let mut report = RetrieveReport {
            instances: uids.len(),
            count_mismatch: expected.filter(|&n| n != uids.len() as u64),
            ..RetrieveReport::default()
        };
        if let Some(n) = report.count_mismatch {
            tracing::warn!(
                "{}: series {series_uid}: NumberOfSeriesRelatedInstances says {n}, the instance list has {}",
                self.base,
                uids.len()
            );
        }
        let is_missing = |uid: &&String| !dir.join(format!("{uid}.dcm")).is_file();
        let mut missing: Vec<&String> = uids.iter().filter(is_missing).collect();
        report.already_present = uids.len() - missing.len();
        let requests_before = self.requests.load(Ordering::Relaxed);
        let report_progress = |r: &RetrieveReport| {
            if let Some(p) = progress {
                p(RetrieveProgress {
                    done: r.already_present + r.fetched,
                    total: r.instances,
                    bytes: r.bytes,
                });
            }
        };
        report_progress(&report);
        if self.options.whole_series && report.already_present == 0 {
            let wanted: std::collections::HashSet<&str> = uids.iter().map(String::as_str).collect();
            let mut on_instance = |bytes: u64| {
                report.fetched += 1;
                report.bytes += bytes;
                report_progress(&report);
            };
            let streamed = self
                .fetch_series_stream(
                    study_uid,
                    series_uid,
                    &wanted,
                    dir,
                    cancel,
                    &mut on_instance,
                )
                .await;
            match streamed {
                Ok(()) => {}
                // A cancel, or our own disk failing, is not the server's doing: no fallback.
                Err(e @ (PacsError::Cancelled | PacsError::Io { .. })) => {
                    remove_partial_files(dir);
                    return Err(e);
                }
                Err(e) => tracing::warn!(
                    "series {series_uid} in one request: {e}; fetching the missing instances one by one"
                ),
            }
            missing.retain(is_missing);
        }
        let mut fetches = futures::stream::iter(missing.into_iter().map(|uid| {
            self.with_retries("instance", move || {
                self.fetch_instance(study_uid, series_uid, uid, dir, cancel)
            })
        }))
        .buffer_unordered(self.options.parallelism.max(1));
        let mut failure = None;
        while let Some(result) = fetches.next().await {
            match result {
                Ok(bytes) => {
                    report.fetched += 1;
                    report.bytes += bytes;
                    report_progress(&report);
                }
                Err(e) => {
                    failure = Some(e);
                    break;
                }
            }
        }
        // Dropping the stream aborts the requests still in flight; their `.part` files are
        // removed so the folder holds whole instances only.
        drop(fetches);
        report.requests = self.requests.load(Ordering::Relaxed) - requests_before;
        if let Some(e) = failure {
            remove_partial_files(dir);
            return Err(e);
        }
        Ok(report)
    }

    /// The whole series as one WADO-RS request: each part of the multipart answer streamed into
    /// `dir/series.dcm.part` and, once whole and checked (DICOM, of this series, one of
    /// `wanted`, not seen before), renamed to `dir/UID.dcm`; `on_instance` sees each one's size.
    /// The instances whole before a failure stay (a resume, or the per-instance fallback, does
    /// not fetch them again); fewer parts than `wanted` is not an error here (the fallback
    /// fetches the rest). `cancel` is checked between chunks and after each instance.
    async fn fetch_series_stream(
        &self,
        study_uid: &str,
        series_uid: &str,
        wanted: &std::collections::HashSet<&str>,
        dir: &Path,
        cancel: Option<&AtomicBool>,
        on_instance: &mut dyn FnMut(u64),
    ) -> Result<(), PacsError> {
        let what = format!("series {series_uid}");
        let url = format!("{}/studies/{study_uid}/series/{series_uid}", self.base);
        let cancelled = || cancel.is_some_and(|c| c.load(Ordering::Relaxed));
        if cancelled() {
            return Err(PacsError::Cancelled);
        }
        self.requests.fetch_add(1, Ordering::Relaxed);
        let mut response = self
            .authed(self.http.get(&url))
            .header(
                reqwest::header::ACCEPT,
                "multipart/related; type=\"application/dicom\"; transfer-syntax=*",
            )
            .send()
            .await
            .map_err(|e| self.transport_error(&what, &e))?;
        if !response.status().is_success() {
            return Err(self.status_error(&what, response.status()));
        }
        let content_type = response
            .headers()
            .get(reqwest::header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string();
        let multipart_error = |source| PacsError::Multipart {
            server: self.server(),
            what: what.clone(),
            source,
        };
        let boundary = boundary_of(&content_type).map_err(multipart_error)?;
        // Digits and dots name instances; this name cannot be one.
        let partial = dir.join("series.dcm.part");
        let io = |e: std::io::Error| PacsError::Io {
            path: partial.display().to_string(),
            problem: e.to_string(),
        };
        let mut parser = MultipartParser::new(&boundary, self.options.max_part_bytes, true);
        let mut file: Option<std::io::BufWriter<std::fs::File>> = None;
        let mut head: Vec<u8> = Vec::with_capacity(132);
        let mut size = 0u64;
        let mut seen: std::collections::HashSet<String> = std::collections::HashSet::new();
        let mut on_event = |event: Event<'_>| -> Result<(), SinkError> {
            match event {
                Event::PartStart { .. } => {
                    // More parts than instances: a server repeating itself is cut here.
                    if seen.len() >= wanted.len() {
                        return Err(SinkError::ExtraPart);
                    }
                    let created = std::fs::File::create(&partial).map_err(SinkError::Io)?;
                    file = Some(std::io::BufWriter::with_capacity(1 << 20, created));
                    head.clear();
                    size = 0;
                }
                Event::Data(data) => {
                    if head.len() < 132 {
                        let take = (132 - head.len()).min(data.len());
                        head.extend_from_slice(&data[..take]);
                    }
                    size += data.len() as u64;
                    if let Some(f) = file.as_mut() {
                        f.write_all(data).map_err(SinkError::Io)?;
                    }
                }
                Event::PartEnd => {
                    if let Some(mut f) = file.take() {
                        f.flush().map_err(SinkError::Io)?;
                    }
                    if !is_dicom_part10(&head) {
                        return Err(SinkError::Invalid(
                            "a part is not a DICOM file (no DICM preamble)".into(),
                        ));
                    }
                    let (sop, series) = instance_identity(&partial)
                        .map_err(|e| SinkError::Invalid(e.to_string()))?;
                    if let Some(problem) = series_mismatch(series.as_deref(), series_uid) {
                        return Err(SinkError::Invalid(problem));
                    }
                    let sop = sop.unwrap_or_default();
                    if !wanted.contains(sop.as_str()) {
                        return Err(SinkError::Invalid(format!(
                            "the server answered instance {} that its instance list lacks",
                            if sop.is_empty() {
                                "(no SOP Instance UID)"
                            } else {
                                &sop
                            }
                        )));
                    }
                    if !seen.insert(sop.clone()) {
                        return Err(SinkError::Invalid(format!("instance {sop} came twice")));
                    }
                    std::fs::rename(&partial, dir.join(format!("{sop}.dcm")))
                        .map_err(SinkError::Io)?;
                    on_instance(size);
                    if cancelled() {
                        return Err(SinkError::Cancelled);
                    }
                }
            }
            Ok(())
        };
        let sink_error = |e: SinkError| match e {
            SinkError::Multipart(m) => multipart_error(m),
            SinkError::Io(e) => io(e),
            SinkError::ExtraPart => PacsError::Invalid {
                server: self.server(),
                what: what.clone(),
                problem: "more parts than the series has instances".into(),
            },
            SinkError::Invalid(problem) => PacsError::Invalid {
                server: self.server(),
                what: what.clone(),
                problem,
            },
            SinkError::Cancelled => PacsError::Cancelled,
        };
        let streamed: Result<(), PacsError> = async {
            while !parser.is_closed() {
                if cancelled() {
                    return Err(PacsError::Cancelled);
                }
                match self.next_chunk(&what, &mut response).await? {
                    Some(chunk) => parser
                        .feed(chunk.as_ref(), &mut on_event)
                        .map_err(sink_error)?,
                    None => break,
                }
            }
            parser.finish().map_err(multipart_error)
        }
        .await;
        drop(file);
        if streamed.is_err() {
            let _ = std::fs::remove_file(&partial);
        }
        streamed
    }

    /// One WADO-RS request for one instance, streamed into `dir/UID.dcm`; its size.
    async fn fetch_instance(
        &self,
        study_uid: &str,
        series_uid: &str,
        sop_uid: &str,
        dir: &Path,
        cancel: Option<&AtomicBool>,
    ) -> Result<u64, PacsError> {
        let what = format!("instance {sop_uid}");
        let url = format!(
            "{}/studies/{study_uid}/series/{series_uid}/instances/{sop_uid}",
            self.base
        );
        // A cancel seen before the request costs no request (a resume counts on it).
        if cancel.is_some_and(|c| c.load(Ordering::Relaxed)) {
            return Err(PacsError::Cancelled);
        }
        self.requests.fetch_add(1, Ordering::Relaxed);
        let mut response = self
            .authed(self.http.get(&url))
            .header(
                reqwest::header::ACCEPT,
                "multipart/related; type=\"application/dicom\"; transfer-syntax=*",
            )
            .send()
            .await
            .map_err(|e| self.transport_error(&what, &e))?;
        if !response.status().is_success() {
            return Err(self.status_error(&what, response.status()));
        }
        let content_type = response
            .headers()
            .get(reqwest::header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string();
        let multipart_error = |source| PacsError::Multipart {
            server: self.server(),
            what: what.clone(),
            source,
        };
        let boundary = boundary_of(&content_type).map_err(multipart_error)?;
        let partial = dir.join(format!("{sop_uid}.dcm.part"));
        let io = |e: std::io::Error| PacsError::Io {
            path: partial.display().to_string(),
            problem: e.to_string(),
        };
        let mut file = std::io::BufWriter::with_capacity(
            1 << 20,
            std::fs::File::create(&partial).map_err(io)?,
        );
        let mut parser = MultipartParser::new(&boundary, self.options.max_part_bytes, true);
        let mut parts = 0u32;
        let mut size = 0u64;
        let mut head: Vec<u8> = Vec::with_capacity(132);
        let mut on_event = |event: Event<'_>| -> Result<(), SinkError> {
            match event {
                Event::PartStart { .. } => {
                    parts += 1;
                    if parts > 1 {
                        return Err(SinkError::ExtraPart);
                    }
                }
                Event::Data(data) => {
                    if head.len() < 132 {
                        let take = (132 - head.len()).min(data.len());
                        head.extend_from_slice(&data[..take]);
                    }
                    size += data.len() as u64;
                    file.write_all(data).map_err(SinkError::Io)?;
                }
                Event::PartEnd => {}
            }
            Ok(())
        };
        let sink_error = |e: SinkError| match e {
            SinkError::Multipart(m) => multipart_error(m),
            SinkError::Io(e) => io(e),
            SinkError::ExtraPart => PacsError::Invalid {
                server: self.server(),
                what: what.clone(),
                problem: "more than one part for one instance".into(),
            },
            SinkError::Invalid(problem) => PacsError::Invalid {
                server: self.server(),
                what: what.clone(),
                problem,
            },
            SinkError::Cancelled => PacsError::Cancelled,
        };
        let streamed: Result<(), PacsError> = async {
            while !parser.is_closed() {
                if cancel.is_some_and(|c| c.load(Ordering::Relaxed)) {
                    return Err(PacsError::Cancelled);
                }
                match self.next_chunk(&what, &mut response).await? {
                    Some(chunk) => parser
                        .feed(chunk.as_ref(), &mut on_event)
                        .map_err(sink_error)?,
                    None => break,
                }
            }
            parser.finish().map_err(multipart_error)
        }
        .await;
        let finished = streamed.and_then(|()| {
            if parts == 0 {
                return Err(PacsError::Invalid {
                    server: self.server(),
                    what: what.clone(),
                    problem: "the answer holds no instance".into(),
                });
            }
            if !is_dicom_part10(&head) {
                return Err(PacsError::Invalid {
                    server: self.server(),
                    what: what.clone(),
                    problem: "the part is not a DICOM file (no DICM preamble)".into(),
                });
            }
            file.flush().map_err(io)
        });
        drop(file);
        // A DICOM file, but is it the instance asked for? A misrouting proxy or a server bug
        // must not put another series' slices into this one's volume.
        let finished = finished.and_then(|()| {
            identity_mismatch(&partial, series_uid, sop_uid).map_or(Ok(()), |problem| {
                Err(PacsError::Invalid {
                    server: self.server(),
                    what: what.clone(),
                    problem,
                })
            })
        });
        if let Err(e) = finished {
            let _ = std::fs::remove_file(&partial);
            return Err(e);
        }
        // Renamed only when whole: a `.dcm` in the folder is always a complete instance, which
        // is what resuming relies on.
        std::fs::rename(&partial, dir.join(format!("{sop_uid}.dcm"))).map_err(io)?;
        Ok(size)
    }

    async fn store_files(
        &self,
        files: &[PathBuf],
        progress: Option<&dyn Fn(usize)>,
    ) -> Result<StowReport, PacsError> {
        let mut report = StowReport::default();
        let mut batch: Vec<(PathBuf, u64)> = Vec::new();
        let mut batch_bytes = 0u64;
        let mut batches = Vec::new();
        for f in files {
            let len = std::fs::metadata(f)
                .map_err(|e| PacsError::Io {
                    path: f.display().to_string(),
                    problem: e.to_string(),
                })?
                .len();
            if !batch.is_empty() && batch_bytes + len > self.options.stow_batch_bytes {
                batches.push(std::mem::take(&mut batch));
                batch_bytes = 0;
            }
            batch_bytes += len;
            batch.push((f.clone(), len));
        }
        if !batch.is_empty() {
            batches.push(batch);
        }
        for batch in batches {
            let (stored, failed) = self.stow_batch(&batch).await?;
            report.sent += batch.len();
            report.stored += stored;
            report.failed += failed;
            report.requests += 1;
            if let Some(p) = progress {
                p(report.sent);
            }
        }
        Ok(report)
    }

    /// One STOW-RS request: (stored, failed) by the server's answer.
    async fn stow_batch(&self, batch: &[(PathBuf, u64)]) -> Result<(usize, usize), PacsError> {
        // A boundary that cannot occur in the files' bytes by chance.
        let boundary = format!(
            "strata-{:016x}{:016x}",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_nanos() as u64)
                .unwrap_or(0)
        );
        let mut body = Vec::new();
        for (path, _) in batch {
            let bytes = std::fs::read(path).map_err(|e| PacsError::Io {
                path: path.display().to_string(),
                problem: e.to_string(),
            })?;
            body.extend_from_slice(
                format!("--{boundary}\r\nContent-Type: application/dicom\r\n\r\n").as_bytes(),
            );
            body.extend_from_slice(&bytes);
            body.extend_from_slice(b"\r\n");
        }
        body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
        // Shared bytes: a retry re-sends them without a copy.
        let body = bytes::Bytes::from(body);
        let url = format!("{}/studies", self.base);
        let what = "store (STOW-RS)";
        let answer = self
            .with_retries(what, || async {
                self.requests.fetch_add(1, Ordering::Relaxed);
                let response = self
                    .authed(self.http.post(&url))
                    .header(
                        reqwest::header::CONTENT_TYPE,
                        format!(
                            "multipart/related; type=\"application/dicom\"; boundary={boundary}"
                        ),
                    )
                    .header(reqwest::header::ACCEPT, "application/dicom+json")
                    .timeout(self.options.request_timeout)
                    .body(body.clone())
                    .send()
                    .await
                    .map_err(|e| self.transport_error(what, &e))?;
                let status = response.status();
                // 202: some stored, some not; 409: none stored. Both answer which.
                if !(status.is_success() || status == reqwest::StatusCode::CONFLICT) {
                    return Err(self.status_error(what, status));
                }
                let text = response
                    .bytes()
                    .await
                    .map_err(|e| self.transport_error(what, &e))?;
                Ok(serde_json::from_slice::<Value>(&text).unwrap_or(Value::Null))
            })
            .await?;
        let count = |tag: &str| {
            answer
                .get(tag)
                .and_then(|a| a.get("Value"))
                .and_then(Value::as_array)
                .map_or(0, Vec::len)
        };
        let stored = count("00081199");
        let failed = count("00081198");
        if stored == 0 && failed == 0 {
            // No answer document: count the batch as stored when the status said success.
            return Ok((batch.len(), 0));
        }
        Ok((stored, failed))
    }
}

fn remove_partial_files(dir: &Path) {
    if let Ok(entries) = std::fs::read_dir(dir) {
        for entry in entries.flatten() {
            if entry.file_name().to_string_lossy().ends_with(".dcm.part") {
                let _ = std::fs::remove_file(entry.path());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_with_credentials_are_refused_without_echoing_them() {
        let e = normalise_base_url("https://alice:s3cret@pacs.example/dicom-web").unwrap_err();
        let text = e.to_string();
        assert!(
            !text.contains("s3cret") && !text.contains("alice"),
            "{text}"
        );
        assert_eq!(
            normalise_base_url("http://h:8042/dicom-web/").unwrap(),
            "http://h:8042/dicom-web"
        );
        assert!(normalise_base_url("ftp://h").is_err());
        assert_eq!(format!("{:?}", Secret::new("pw")), "<redacted>");
    }

    #[test]
    fn query_values_keep_wildcards_and_encode_separators() {
        assert_eq!(percent_encode("DOE^J*"), "DOE^J*");
        assert_eq!(percent_encode("a b&c=d#e+f%"), "a%20b%26c%3Dd%23e%2Bf%25");
    }

    /// Names beyond ASCII: a query is sent as percent-encoded UTF-8 (DICOMweb's charset), and
    /// an answer's name comes back whole, in whichever component group it has.
    #[test]
    fn non_ascii_names_are_queried_as_utf8_and_read_from_any_component_group() {
        assert_eq!(percent_encode("Müller^Jörg*"), "M%C3%BCller^J%C3%B6rg*");
        assert_eq!(percent_encode("山田"), "%E5%B1%B1%E7%94%B0");
        let answer: Value = serde_json::from_str(
            r#"{"00100010": {"vr": "PN", "Value": [{"Alphabetic": "Müller^Jörg"}]},
                "00100011": {"vr": "PN", "Value": [{"Ideographic": "山田^太郎", "Phonetic": "やまだ^たろう"}]}}"#,
        )
        .unwrap();
        assert_eq!(
            json_string(&answer, "00100010").as_deref(),
            Some("Müller^Jörg")
        );
        assert_eq!(
            json_string(&answer, "00100011").as_deref(),
            Some("山田^太郎")
        );
    }

    #[test]
    fn uids_are_digits_and_dots() {
        assert!(check_uid("1.2.840.10008.1").is_ok());
        assert!(check_uid("../etc").is_err());
        assert!(check_uid("").is_err());
        assert!(check_uid(&"1".repeat(65)).is_err());
    }
}
