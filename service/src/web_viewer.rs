//! The browser viewer's page, served at `/` by `strata serve` (issue 39).
//!
//! The files (the HTML page, its boot script and style, the wasm-bindgen glue and the wasm
//! module) come from the caller: the `strata` binary embeds them when built with its `web`
//! feature (after `cargo run -p xtask -- web`), tests load them from the xtask's output. A
//! server given none answers `/` with how to build them, and nothing else changes.
//!
//! The page is as safe as the API: same origin only (a Content-Security-Policy with
//! `default-src 'self'`, no third-party scripts, styles or fonts; `wasm-unsafe-eval` is what
//! instantiating a wasm module needs), `Referrer-Policy: no-referrer`, no sniffing, not
//! framable unless the server was told who may frame it (`ServeOptions::frame_ancestors`,
//! which only the Jupyter widget sets, issue 50: its notebook shows the page in an iframe).
//! The page's files carry no data, so they are served without the bearer token: a
//! browser cannot send one when it navigates. The page reads the token from the URL fragment,
//! which browsers never send, and sends it as `Authorization` on its own requests.
//!
//! A browser that accepts gzip gets the files gzipped (the wasm module: 7.0 MB as built,
//! 2.4 MB on the wire), each compressed once, on its first such request.

use std::io::Write as _;
use std::path::Path;
use std::sync::{Arc, OnceLock};

use axum::body::Bytes;
use axum::extract::{Path as UrlPath, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;

/// The files of the page, by the name the page asks for them with.
pub const WEB_VIEWER_FILES: [(&str, &str); 5] = [
    ("index.html", "text/html; charset=utf-8"),
    ("strata.css", "text/css; charset=utf-8"),
    ("strata_boot.js", "text/javascript; charset=utf-8"),
    ("strata_web.js", "text/javascript; charset=utf-8"),
    ("strata_web_bg.wasm", "application/wasm"),
];

/// What `/` says when the server was built without the page.
pub const WEB_VIEWER_MISSING: &str = "This strata was built without the web viewer.\n\
Build it with:\n\
  rustup target add wasm32-unknown-unknown\n\
  cargo run -p xtask -- web\n\
  cargo build --release -p strata-app --features web\n\
The API is under /v1/stores.\n";

/// The page's Content-Security-Policy but its `frame-ancestors` directive.
const CONTENT_SECURITY_POLICY: &str = "default-src 'self'; script-src 'self' 'wasm-unsafe-eval'; \
style-src 'self'; img-src 'self' data: blob:; connect-src 'self'; font-src 'self'; \
object-src 'none'; base-uri 'none'; form-action 'none'";

/// Most sources a `frame-ancestors` option may list, and the longest one.
const MAX_FRAME_ANCESTORS: usize = 16;
const MAX_FRAME_ANCESTOR_LEN: usize = 256;

/// Why a `frame_ancestors` option was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameAncestorsError {
    #[error("frame_ancestors must list 1 to {max} sources, not {0}", max = MAX_FRAME_ANCESTORS)]
    Count(usize),
    /// The refused source, escaped so that it cannot break the message's line.
    #[error("frame_ancestors source '{0}' is not a scheme and host (such as http://localhost:*) or 'self'")]
    Source(String),
}

/// Checks the sources of a `frame-ancestors` option: space-separated CSP host sources
/// (`http://localhost:*`, `https://*.example.org`, `vscode-webview:`) or `'self'`. Anything
/// else is refused, so the option can add neither a directive (`;`, `,`) nor a header line
/// nor a keyword such as `*` that would let any site frame the page.
pub fn check_frame_ancestors(sources: &str) -> Result<(), FrameAncestorsError> {
    let listed: Vec<&str> = sources.split_ascii_whitespace().collect();
    if listed.is_empty() || listed.len() > MAX_FRAME_ANCESTORS {
        return Err(FrameAncestorsError::Count(listed.len()));
    }
    for source in listed {
        if source == "'self'" {
            continue;
        }
        let allowed = |b: u8| b.is_ascii_alphanumeric() || b"-._:/*[]".contains(&b);
        let scheme_ok = source.split_once(':').is_some_and(|(scheme, _)| {
            !scheme.is_empty()
                && scheme
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"+-.".contains(&b))
        });
        if source.len() > MAX_FRAME_ANCESTOR_LEN || !scheme_ok || !source.bytes().all(allowed) {
            return Err(FrameAncestorsError::Source(
                source.escape_debug().to_string(),
            ));
        }
    }
    Ok(())
}

/// The page's Content-Security-Policy: framable by `frame_ancestors` (checked by
/// [`check_frame_ancestors`] when the server started), else by nobody.
fn content_security_policy(frame_ancestors: Option<&str>) -> HeaderValue {
    let fallback = HeaderValue::from_str(&format!(
        "{CONTENT_SECURITY_POLICY}; frame-ancestors 'none'"
    ))
    .unwrap_or_else(|_| HeaderValue::from_static("frame-ancestors 'none'"));
    match frame_ancestors.filter(|s| check_frame_ancestors(s).is_ok()) {
        Some(sources) => {
            let sources = sources
                .split_ascii_whitespace()
                .collect::<Vec<_>>()
                .join(" ");
            HeaderValue::from_str(&format!(
                "{CONTENT_SECURITY_POLICY}; frame-ancestors {sources}"
            ))
            .unwrap_or(fallback)
        }
        None => fallback,
    }
}

/// A file of the page that could not be read.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {message}")]
pub struct WebViewerFilesError {
    pub path: std::path::PathBuf,
    pub message: String,
}

/// The page's files in memory.
#[derive(Clone, Debug)]
pub struct WebViewerAssets {
    files: Vec<WebViewerFile>,
}

#[derive(Clone, Debug)]
struct WebViewerFile {
    name: &'static str,
    kind: &'static str,
    body: Bytes,
    /// The body gzipped, made on the first request that accepts it.
    gzipped: OnceLock<Bytes>,
}

impl WebViewerFile {
    fn new(name: &'static str, kind: &'static str, body: Bytes) -> Self {
        WebViewerFile {
            name,
            kind,
            body,
            gzipped: OnceLock::new(),
        }
    }

    fn gzipped(&self) -> &Bytes {
        self.gzipped.get_or_init(|| {
            let mut encoder =
                flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
            // Writing into a Vec cannot fail.
            let _ = encoder.write_all(&self.body);
            Bytes::from(encoder.finish().unwrap_or_default())
        })
    }
}

/// Files smaller than this go as they are (gzip's header would eat the saving).
const MIN_GZIP_BYTES: usize = 1024;

/// Whether `Accept-Encoding` takes gzip (`gzip` or `*`, not at `q=0`).
fn accepts_gzip(headers: &HeaderMap) -> bool {
    headers
        .get_all(header::ACCEPT_ENCODING)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|coding| {
            let mut parts = coding.split(';').map(str::trim);
            let name = parts.next().unwrap_or("");
            let refused = parts.any(|p| {
                p.strip_prefix("q=")
                    .and_then(|q| q.parse::<f32>().ok())
                    .is_some_and(|q| q <= 0.0)
            });
            (name.eq_ignore_ascii_case("gzip") || name == "*") && !refused
        })
}

impl WebViewerAssets {
    /// From embedded bytes, in [`WEB_VIEWER_FILES`]' order.
    pub fn from_static(bodies: [&'static [u8]; 5]) -> Self {
        let files = WEB_VIEWER_FILES
            .iter()
            .zip(bodies)
            .map(|(&(name, kind), body)| WebViewerFile::new(name, kind, Bytes::from_static(body)))
            .collect();
        WebViewerAssets { files }
    }

    /// From a folder holding every file of [`WEB_VIEWER_FILES`] (the xtask's `dist`).
    pub fn from_dir(dir: &Path) -> Result<Self, WebViewerFilesError> {
        let mut files = Vec::with_capacity(WEB_VIEWER_FILES.len());
        for (name, kind) in WEB_VIEWER_FILES {
            let path = dir.join(name);
            let body = std::fs::read(&path).map_err(|e| WebViewerFilesError {
                path: path.clone(),
                message: format!(
                    "cannot read the web viewer's file ({e}); build it with `cargo run -p xtask -- web`"
                ),
            })?;
            files.push(WebViewerFile::new(name, kind, Bytes::from(body)));
        }
        Ok(WebViewerAssets { files })
    }

    fn get(&self, name: &str) -> Option<&WebViewerFile> {
        self.files.iter().find(|f| f.name == name)
    }
}

/// What the page's routes answer with: its files and the headers they go with.
#[derive(Clone)]
struct Page {
    assets: Option<Arc<WebViewerAssets>>,
    csp: HeaderValue,
    /// `X-Frame-Options: DENY` goes along unless someone may frame the page (it knows no
    /// list of origins; browsers that read `frame-ancestors` ignore it when both are sent).
    framable: bool,
}

/// `/` and the page's files; mounted outside the token guard (see the module doc).
pub(crate) fn router(
    assets: Option<Arc<WebViewerAssets>>,
    frame_ancestors: Option<&str>,
) -> Router {
    let page = Page {
        assets,
        csp: content_security_policy(frame_ancestors),
        framable: frame_ancestors.is_some_and(|s| check_frame_ancestors(s).is_ok()),
    };
    Router::new()
        .route("/", get(index))
        .route("/{file}", get(file))
        .with_state(page)
}

async fn index(State(page): State<Page>, request_headers: HeaderMap) -> Response {
    match &page.assets {
        Some(assets) => answer(&page, assets, "index.html", &request_headers),
        None => (
            StatusCode::NOT_FOUND,
            [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
            WEB_VIEWER_MISSING,
        )
            .into_response(),
    }
}

async fn file(
    State(page): State<Page>,
    UrlPath(name): UrlPath<String>,
    request_headers: HeaderMap,
) -> Response {
    match &page.assets {
        Some(assets) => answer(&page, assets, &name, &request_headers),
        None => (StatusCode::NOT_FOUND, "not found\n").into_response(),
    }
}

fn answer(
    page: &Page,
    assets: &WebViewerAssets,
    name: &str,
    request_headers: &HeaderMap,
) -> Response {
    let Some(file) = assets.get(name) else {
        return (StatusCode::NOT_FOUND, "not found\n").into_response();
    };
    let gzip = file.body.len() >= MIN_GZIP_BYTES && accepts_gzip(request_headers);
    let body = if gzip {
        file.gzipped().clone()
    } else {
        file.body.clone()
    };
    let mut response = (StatusCode::OK, body).into_response();
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(file.kind));
    if gzip {
        headers.insert(header::CONTENT_ENCODING, HeaderValue::from_static("gzip"));
    }
    headers.insert(header::VARY, HeaderValue::from_static("accept-encoding"));
    // The names are not content-hashed, so the browser revalidates; the files are small next
    // to the bricks, which are cached for good.
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    headers.insert(header::CONTENT_SECURITY_POLICY, page.csp.clone());
    headers.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    headers.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    if !page.framable {
        headers.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    }
    response
}

/// A frame the page posted to the test sink (`capture=1` in its fragment).
#[derive(Clone, Debug)]
pub struct CapturedFrame {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
    /// The page's own measurements sent along (`name=value` in the query besides the size:
    /// time to first image, to convergence, frame times; see strata-web's page_timing.rs).
    pub metrics: Vec<(String, f64)>,
}

/// Most measurements a captured frame carries (the page sends six).
const MAX_FRAME_METRICS: usize = 16;

/// The query's `name=value` pairs other than the size whose name is a short lowercase word
/// and whose value is a finite number; anything else is ignored (a test hook, bounded).
fn frame_metrics(query: &str) -> Vec<(String, f64)> {
    query
        .split('&')
        .filter_map(|pair| pair.split_once('='))
        .filter(|(name, _)| {
            !matches!(*name, "width" | "height")
                && (1..=32).contains(&name.len())
                && name.bytes().all(|b| b.is_ascii_lowercase() || b == b'_')
        })
        .filter_map(|(name, value)| {
            let value = value.parse::<f64>().ok().filter(|v| v.is_finite())?;
            Some((name.to_string(), value))
        })
        .take(MAX_FRAME_METRICS)
        .collect()
}

/// Test hook: receives frames the page posts to `/v1/test/frame`. The route exists only on a
/// server given a sink.
#[derive(Clone)]
pub struct FrameSink(pub Arc<dyn Fn(CapturedFrame) + Send + Sync>);

impl std::fmt::Debug for FrameSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FrameSink")
    }
}

/// The largest frame the sink takes (a 2048² RGBA8 image).
pub const MAX_CAPTURED_BYTES: usize = 2048 * 2048 * 4;

struct FrameSize {
    width: u32,
    height: u32,
}

/// `width=W&height=H` of the sink's query (axum's `Query` extractor is not compiled in).
fn frame_size(query: &str) -> Option<(u32, u32)> {
    let mut width = None;
    let mut height = None;
    for pair in query.split('&') {
        match pair.split_once('=') {
            Some(("width", v)) => width = v.parse::<u32>().ok(),
            Some(("height", v)) => height = v.parse::<u32>().ok(),
            _ => {}
        }
    }
    Some((width?, height?))
}

pub(crate) async fn receive_frame(
    State(sink): State<FrameSink>,
    uri: axum::http::Uri,
    body: Bytes,
) -> Response {
    let Some((width, height)) = frame_size(uri.query().unwrap_or("")) else {
        return (StatusCode::BAD_REQUEST, "width and height are required\n").into_response();
    };
    let size = FrameSize { width, height };
    let expected = size.width as usize * size.height as usize * 4;
    if expected == 0 || expected != body.len() {
        return (
            StatusCode::BAD_REQUEST,
            format!(
                "{}x{} RGBA8 is {expected} bytes, the body has {}\n",
                size.width,
                size.height,
                body.len()
            ),
        )
            .into_response();
    }
    (sink.0)(CapturedFrame {
        width: size.width,
        height: size.height,
        rgba: body.to_vec(),
        metrics: frame_metrics(uri.query().unwrap_or("")),
    });
    (StatusCode::NO_CONTENT, ()).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read as _;

    fn assets() -> WebViewerAssets {
        // The module's stand-in: large and compressible, as a wasm module is.
        let wasm: &'static [u8] = Box::leak(
            (0..200_000u32)
                .flat_map(|i| (i % 251).to_le_bytes())
                .collect::<Vec<u8>>()
                .into_boxed_slice(),
        );
        WebViewerAssets::from_static([b"<html></html>", b"body{}", b"boot()", b"glue()", wasm])
    }

    fn page(frame_ancestors: Option<&str>) -> Page {
        Page {
            assets: None,
            csp: content_security_policy(frame_ancestors),
            framable: frame_ancestors.is_some_and(|s| check_frame_ancestors(s).is_ok()),
        }
    }

    #[test]
    fn the_page_is_framed_only_by_the_ancestors_it_was_told() {
        let assets = assets();
        let answered = |frame_ancestors: Option<&str>| {
            let response = answer(
                &page(frame_ancestors),
                &assets,
                "index.html",
                &headers(None),
            );
            let csp = response.headers()[header::CONTENT_SECURITY_POLICY]
                .to_str()
                .unwrap()
                .to_string();
            let deny = response.headers().get(header::X_FRAME_OPTIONS).cloned();
            (csp, deny)
        };
        let (csp, deny) = answered(None);
        assert!(csp.ends_with("; frame-ancestors 'none'"), "{csp}");
        assert!(csp.starts_with("default-src 'self'"), "{csp}");
        assert_eq!(deny.unwrap(), "DENY");
        let (csp, deny) = answered(Some("http://localhost:*  http://127.0.0.1:*"));
        assert!(
            csp.ends_with("; frame-ancestors http://localhost:* http://127.0.0.1:*"),
            "{csp}"
        );
        assert!(
            csp.contains("script-src 'self' 'wasm-unsafe-eval'"),
            "{csp}"
        );
        assert!(deny.is_none(), "X-Frame-Options would forbid every frame");

        // Nothing that adds a directive, a header or any-site framing gets through.
        for bad in [
            "",
            "*",
            "http://a; script-src *",
            "http://a, *",
            "http://a\r\nX-Evil: 1",
            "'unsafe-inline'",
            "http://a\"",
            ":8888",
        ] {
            let e = check_frame_ancestors(bad).expect_err(bad);
            assert!(e.to_string().contains("frame_ancestors"), "{e}");
            let (csp, deny) = answered(Some(bad));
            assert!(csp.ends_with("; frame-ancestors 'none'"), "{bad}: {csp}");
            assert!(deny.is_some(), "{bad}");
        }
        let many = vec!["http://localhost:*"; MAX_FRAME_ANCESTORS + 1].join(" ");
        assert!(check_frame_ancestors(&many).is_err());
        for good in ["'self'", "vscode-webview:", "https://*.example.org:8443"] {
            check_frame_ancestors(good).unwrap_or_else(|e| panic!("{good}: {e}"));
        }
    }

    fn headers(accept: Option<&str>) -> HeaderMap {
        let mut h = HeaderMap::new();
        if let Some(a) = accept {
            h.insert(header::ACCEPT_ENCODING, HeaderValue::from_str(a).unwrap());
        }
        h
    }

    async fn body_of(response: Response) -> Vec<u8> {
        axum::body::to_bytes(response.into_body(), usize::MAX)
            .await
            .unwrap()
            .to_vec()
    }

    #[test]
    fn a_captured_frames_metrics_are_bounded_named_numbers() {
        let metrics = frame_metrics(
            "width=4&height=2&first_image_ms=812.5&converged_ms=20113.25&bad-name=1&\
             UPPER=2&nan_ms=NaN&inf_ms=inf&text_ms=abc&frame_ms_median=41.000",
        );
        assert_eq!(
            metrics,
            vec![
                ("first_image_ms".to_string(), 812.5),
                ("converged_ms".to_string(), 20113.25),
                ("frame_ms_median".to_string(), 41.0),
            ]
        );
        let many: Vec<String> = (0..40)
            .map(|i| format!("m_{}=1", "x".repeat(i % 5 + 1)))
            .collect();
        assert_eq!(frame_metrics(&many.join("&")).len(), MAX_FRAME_METRICS);
    }

    #[test]
    fn the_module_goes_gzipped_to_a_browser_that_accepts_it_and_as_is_otherwise() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let assets = assets();
        let original = assets.get("strata_web_bg.wasm").unwrap().body.clone();
        let page = page(None);
        let gz = answer(
            &page,
            &assets,
            "strata_web_bg.wasm",
            &headers(Some("gzip, deflate, br, zstd")),
        );
        assert_eq!(gz.headers()[header::CONTENT_ENCODING], "gzip");
        assert_eq!(gz.headers()[header::VARY], "accept-encoding");
        assert_eq!(gz.headers()[header::CONTENT_TYPE], "application/wasm");
        let wire = runtime.block_on(body_of(gz));
        assert!(wire.len() * 4 < original.len(), "{} bytes", wire.len());
        let mut unpacked = Vec::new();
        flate2::read::GzDecoder::new(wire.as_slice())
            .read_to_end(&mut unpacked)
            .unwrap();
        assert_eq!(unpacked, original);
        for refused in [None, Some("br"), Some("gzip;q=0, identity")] {
            let plain = answer(&page, &assets, "strata_web_bg.wasm", &headers(refused));
            assert!(plain.headers().get(header::CONTENT_ENCODING).is_none());
            assert_eq!(runtime.block_on(body_of(plain)), original, "{refused:?}");
        }
        // A file too small to gain goes as it is.
        let small = answer(&page, &assets, "index.html", &headers(Some("gzip")));
        assert!(small.headers().get(header::CONTENT_ENCODING).is_none());
        assert!(accepts_gzip(&headers(Some("*"))));
        assert!(accepts_gzip(&headers(Some("GZIP;q=0.5"))));
    }
}
