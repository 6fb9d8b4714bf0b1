//! `strata serve`: stores, read-only, over HTTP/1.1 and h2c (see strata-service's server).

use std::io::Write;
use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Args;
use strata_service::server::{find_stores, generate_token, start, ServeOptions};

#[derive(Args)]
pub struct ServeArgs {
    /// Stores, or folders of stores, to serve.
    #[arg(required = true)]
    pub stores: Vec<PathBuf>,
    /// Address to listen on. Default: 127.0.0.1 on an ephemeral port. Any address that is not
    /// loopback needs --token-file or --generate-token.
    #[arg(long)]
    pub bind: Option<SocketAddr>,
    /// File holding the bearer token clients must send (at least 16 characters).
    #[arg(long)]
    pub token_file: Option<PathBuf>,
    /// Generate a 128-bit token and print it once.
    #[arg(long)]
    pub generate_token: bool,
    /// Serve HTTPS with this PEM certificate chain (with --tls-key).
    #[arg(long, requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The PEM private key of --tls-cert.
    #[arg(long, requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Serve the header's description and provenance (source paths often hold patient names).
    #[arg(long)]
    pub expose_identifiers: bool,
    #[arg(long, default_value_t = 256)]
    pub max_connections: usize,
    /// Connections from one client address; at a cap the connection idle longest (for at
    /// least a second) is closed gracefully to admit a new one; otherwise the new one waits
    /// while a busy one is asked to step aside (`Connection: close` on its next answer).
    #[arg(long, default_value_t = 64)]
    pub max_connections_per_address: usize,
    /// Seconds without a request after which a connection at a cap is closed outright to
    /// admit a newcomer; one active more recently is asked to step aside instead. Raise it
    /// behind clients that pause between requests on a kept-alive connection.
    #[arg(long, default_value_t = 1.0, value_name = "SECONDS")]
    pub evict_idle_after: f64,
    /// A reverse proxy's address (repeatable): its connections carry many clients, so they are
    /// a pool of their own under --max-connections, not limited per address.
    #[arg(long = "trusted-proxy", value_name = "ADDR")]
    pub trusted_proxies: Vec<IpAddr>,
    /// Append one line per request to FILE: time, client, method, path (no query, no token),
    /// status, bytes, seconds.
    #[arg(long, value_name = "FILE")]
    pub access_log: Option<PathBuf>,
    #[arg(long, default_value_t = 512)]
    pub max_requests: usize,
    /// Seconds a client may take to send a request's first byte (from connecting), and then
    /// its headers, before it is disconnected.
    #[arg(long, default_value_t = 5.0)]
    pub header_timeout: f64,
    /// Milliseconds added before every brick answer: a round-trip delay for benchmarks on
    /// loopback.
    #[arg(long, default_value_t = 0, hide = true)]
    pub added_delay_ms: u64,
}

pub fn run(args: ServeArgs) -> Result<()> {
    let _ = tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .try_init();
    let token = match (&args.token_file, args.generate_token) {
        (Some(path), _) => Some(strata_viewer::volume_location::read_token(path)?),
        (None, true) => {
            let token = generate_token()?;
            println!("token {token}");
            Some(token)
        }
        (None, false) => None,
    };
    anyhow::ensure!(
        args.header_timeout.is_finite() && args.header_timeout > 0.0,
        "--header-timeout must be positive"
    );
    anyhow::ensure!(
        args.evict_idle_after.is_finite() && (0.0..=3600.0).contains(&args.evict_idle_after),
        "--evict-idle-after must be between 0 and 3600 seconds (got {})",
        args.evict_idle_after
    );
    let mut options = ServeOptions {
        bind: args
            .bind
            .unwrap_or_else(|| SocketAddr::from(([127, 0, 0, 1], 0))),
        token,
        expose_identifiers: args.expose_identifiers,
        max_connections: args.max_connections,
        max_connections_per_address: args.max_connections_per_address,
        evict_idle_after: Duration::from_secs_f64(args.evict_idle_after),
        max_concurrent_requests: args.max_requests,
        header_read_timeout: Duration::from_secs_f64(args.header_timeout),
        added_delay: Duration::from_millis(args.added_delay_ms),
        tls: match (args.tls_cert, args.tls_key) {
            (Some(cert), Some(key)) => Some(strata_service::server::TlsFiles { cert, key }),
            _ => None,
        },
        web_viewer: web_viewer(),
        trusted_proxies: args.trusted_proxies,
        access_log: args.access_log,
        ..ServeOptions::default()
    };
    // Failure injection for the tests' servers; a no-op in builds without the hooks.
    strata_service::test_hooks::apply_from_env(&mut options)?;
    let stores = find_stores(&args.stores)?;
    let server = start(stores, options).context("strata serve")?;
    println!("serving on {}", server.base_url());
    if cfg!(feature = "web") {
        println!(
            "  the web viewer: {}/ (WebGPU needs https or localhost; a token goes after #token=)",
            server.base_url()
        );
    }
    for (name, path, _) in server.stores() {
        println!("  {}  ({})", server.store_url(name), path.display());
        if cfg!(feature = "web") {
            // The link that opens the store in a browser (the token, if any, is added after
            // `&token=` by whoever shares it: never printed into a link here).
            println!("    in a browser: {}/#store={name}", server.base_url());
        }
    }
    std::io::stdout().flush()?;
    server.wait();
    Ok(())
}

/// The browser viewer's files, embedded by the `web` feature (issue 39).
#[cfg(feature = "web")]
fn web_viewer() -> Option<std::sync::Arc<strata_service::WebViewerAssets>> {
    macro_rules! dist {
        ($name:literal) => {
            include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/../web/dist/", $name)).as_slice()
        };
    }
    Some(std::sync::Arc::new(
        strata_service::WebViewerAssets::from_static([
            dist!("index.html"),
            dist!("strata.css"),
            dist!("strata_boot.js"),
            dist!("strata_web.js"),
            dist!("strata_web_bg.wasm"),
        ]),
    ))
}

/// Without the `web` feature `/` says how to build the viewer.
#[cfg(not(feature = "web"))]
fn web_viewer() -> Option<std::sync::Arc<strata_service::WebViewerAssets>> {
    None
}
