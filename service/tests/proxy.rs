//! Issue 49, item 3: `strata serve` behind Debian's `nginx` as a reverse proxy (the way a
//! hospital runs every web service: TLS and single sign-on in front). The test starts nginx
//! itself on loopback with a temporary configuration (the shape of docs/deploy.md's, without
//! TLS and cache) in front of a server that trusts 127.0.0.1 as a proxy, and drives 200
//! concurrent client connections through it: not one 5xx (before the fix: 97 854 of 128 185
//! answers were 502 "upstream prematurely closed connection"). nginx missing fails the test
//! with the install hint: it is in .ci/test-packages.

use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use strata_service::server::{find_stores, start, ServeOptions};
use strata_service::wire::brick_path;
use strata_service::{RemoteOptions, RemoteSource};
use strata_source::VolumeSource;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::Store;
use strata_types::BrickId;

const TOKEN: &str = "0123456789abcdef0123456789abcdef";

pub(crate) fn nginx_binary() -> PathBuf {
    ["/usr/sbin/nginx", "/usr/bin/nginx", "/usr/local/sbin/nginx"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
        .unwrap_or_else(|| {
            panic!(
                "nginx is not installed: `apt-get install -y nginx` (Debian's package; it is \
                 listed in .ci/test-packages)"
            )
        })
}

/// nginx, killed and reaped when dropped.
pub(crate) struct Nginx(Child);

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

pub(crate) fn free_port() -> SocketAddr {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
}

/// Starts nginx in the foreground with everything (pid, logs, temp files) under `dir` and
/// `servers` inside its `http` block, and waits (bounded) until it accepts on `listen`. Its
/// one worker takes 4096 connections: each client's connection holds an upstream one while
/// its request is forwarded, so capacity.rs's 1 000 clients need over 2 000 (with 2048
/// nginx logged "worker_connections are not enough" and closed clients' connections).
pub(crate) fn start_nginx(dir: &Path, listen: SocketAddr, servers: &str) -> Nginx {
    let d = dir.display();
    let conf = format!(
        r#"daemon off;
master_process off;
worker_processes 1;
pid {d}/nginx.pid;
error_log {d}/error.log warn;
events {{ worker_connections 4096; }}
http {{
    access_log off;
    client_body_temp_path {d}/body;
    proxy_temp_path {d}/proxy;
    fastcgi_temp_path {d}/fastcgi;
    uwsgi_temp_path {d}/uwsgi;
    scgi_temp_path {d}/scgi;
{servers}
}}
"#
    );
    let path = dir.join("nginx.conf");
    std::fs::write(&path, conf).unwrap();
    let child = Command::new(nginx_binary())
        .arg("-p")
        .arg(dir)
        .arg("-e")
        .arg(dir.join("error.log"))
        .arg("-c")
        .arg(&path)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("cannot start nginx");
    let nginx = Nginx(child);
    let started = Instant::now();
    while TcpStream::connect(listen).is_err() {
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "nginx did not start: {}",
            std::fs::read_to_string(dir.join("error.log")).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    nginx
}

/// The reverse proxy without TLS and cache: keep-alive upstream, as in docs/deploy.md.
pub(crate) fn plain_proxy(listen: SocketAddr, upstream: SocketAddr) -> String {
    format!(
        r#"    upstream strata {{
        server {upstream};
        keepalive 64;
    }}
    server {{
        listen {listen};
        location / {{
            proxy_pass http://strata;
            proxy_http_version 1.1;
            proxy_set_header Connection "";
            proxy_set_header X-Forwarded-For $remote_addr;
        }}
    }}"#
    )
}

#[test]
fn two_hundred_connections_through_nginx_get_no_5xx() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("proxied.strata");
    Phantom::cube(40)
        .write_store(&path, &ImportOptions::default())
        .unwrap();
    let (id, generation) = {
        let store = Store::open(&path).unwrap();
        (BrickId::new(0, [0, 0, 0]), store.header().generation_id())
    };
    let server = start(
        find_stores(&[path]).unwrap(),
        ServeOptions {
            trusted_proxies: vec![[127, 0, 0, 1].into()],
            ..ServeOptions::default()
        },
    )
    .unwrap();
    let listen = free_port();
    let nginx_dir = dir.path().join("nginx");
    std::fs::create_dir_all(&nginx_dir).unwrap();
    let _nginx = start_nginx(&nginx_dir, listen, &plain_proxy(listen, server.addr()));
    let url = format!("http://{listen}{}", brick_path("proxied", &generation, id));
    strata_service::install_tls_provider();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("strata-test-proxy")
        .enable_all()
        .build()
        .unwrap();
    let ok = Arc::new(AtomicU64::new(0));
    let server_errors = Arc::new(AtomicU64::new(0));
    let failed = Arc::new(AtomicU64::new(0));
    // At least 2 s of load and at least 2 answers per connection (see load.rs: a count, not a
    // duration, is what the assertions need; `give_up` only bounds a hang).
    let _alone = crate::load::HEAVY_LOAD
        .lock()
        .unwrap_or_else(|e| e.into_inner());
    let deadline = Instant::now() + Duration::from_secs(2);
    let give_up = Instant::now() + Duration::from_secs(120);
    let enough = |ok: &AtomicU64| ok.load(Ordering::Relaxed) >= 400;
    let clients: Vec<_> = (0..200)
        .map(|_| {
            let (url, ok, server_errors, failed) = (
                url.clone(),
                ok.clone(),
                server_errors.clone(),
                failed.clone(),
            );
            runtime.spawn(async move {
                let client = reqwest::Client::builder()
                    .no_proxy()
                    .http1_only()
                    .pool_max_idle_per_host(1)
                    .timeout(Duration::from_secs(10))
                    .build()
                    .unwrap();
                while Instant::now() < deadline || (!enough(&ok) && Instant::now() < give_up) {
                    let outcome = match client.get(&url).send().await {
                        Ok(r) => {
                            let status = r.status();
                            match r.bytes().await {
                                Ok(_) => Ok(status),
                                Err(e) => Err(format!("{e:?}")),
                            }
                        }
                        Err(e) => Err(format!("{e:?}")),
                    };
                    match outcome {
                        Ok(status) if status.is_success() => {
                            ok.fetch_add(1, Ordering::Relaxed);
                        }
                        Ok(status) if status.is_server_error() => {
                            if server_errors.fetch_add(1, Ordering::Relaxed) < 3 {
                                eprintln!("proxy: {status}");
                            }
                        }
                        other => {
                            if failed.fetch_add(1, Ordering::Relaxed) < 3 {
                                eprintln!("proxy: a request failed: {other:?}");
                            }
                            tokio::time::sleep(Duration::from_millis(20)).await;
                        }
                    }
                }
            })
        })
        .collect();
    runtime.block_on(async {
        for c in clients {
            c.await.unwrap();
        }
    });
    let c = server.counters();
    eprintln!(
        "proxy: {} ok, {} 5xx, {} failed through nginx; server: {} started, {} answered, \
         {} evicted, {} refused",
        ok.load(Ordering::Relaxed),
        server_errors.load(Ordering::Relaxed),
        failed.load(Ordering::Relaxed),
        c.requests_started.load(Ordering::Relaxed),
        c.requests_answered.load(Ordering::Relaxed),
        c.connections_shed.load(Ordering::Relaxed),
        c.connections_refused.load(Ordering::Relaxed),
    );
    assert!(ok.load(Ordering::Relaxed) > 200, "too few requests to test");
    assert_eq!(
        server_errors.load(Ordering::Relaxed),
        0,
        "5xx through nginx"
    );
    assert_eq!(failed.load(Ordering::Relaxed), 0, "failed through nginx");
}

/// docs/deploy.md's nginx configuration itself (its `nginx` block, with loopback ports, test
/// certificates and a temporary cache put in): TLS terminated by nginx, the token passed
/// through, bricks cached (the second reading of the same bricks makes no brick request to
/// the service), a request without the token never served from the cache (401), and with the
/// service stopped the cached bricks still served (they are fresh for a year; expired ones
/// would be served stale on error by `proxy_cache_use_stale`).
#[test]
fn the_documented_nginx_configuration_terminates_tls_caches_and_serves_stale() {
    let dir = tempfile::tempdir().unwrap();
    let certificates = dir.path().join("tls");
    std::fs::create_dir_all(&certificates).unwrap();
    let (ca, cert, key) = crate::server::test_certificates(&certificates).unwrap_or_else(|| {
        panic!("the openssl tool is needed to make test certificates: `apt-get install -y openssl`")
    });
    let path = dir.path().join("proxied.strata");
    Phantom::cube(40)
        .write_store(&path, &ImportOptions::default())
        .unwrap();
    let server = start(
        find_stores(&[path]).unwrap(),
        ServeOptions {
            token: Some(TOKEN.into()),
            trusted_proxies: vec![[127, 0, 0, 1].into()],
            ..ServeOptions::default()
        },
    )
    .unwrap();
    let docs =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/deploy.md"))
            .unwrap();
    // The site's block (the `events` block above it belongs to nginx.conf; the test's own
    // nginx.conf sets it).
    let block = docs
        .split("```nginx\n")
        .skip(1)
        .filter_map(|rest| rest.split("```").next())
        .find(|block| block.contains("upstream strata {"))
        .expect("docs/deploy.md has the site's nginx block (`upstream strata`)");
    let (https, http) = (free_port(), free_port());
    let cache = dir.path().join("cache");
    let substitutions = [
        ("listen 443 ssl", format!("listen {https} ssl")),
        ("listen 80;", format!("listen {http};")),
        (
            "server 127.0.0.1:8600;",
            format!("server {};", server.addr()),
        ),
        ("/var/cache/nginx/strata", cache.display().to_string()),
        ("/etc/ssl/strata/fullchain.pem", cert.display().to_string()),
        ("/etc/ssl/strata/privkey.pem", key.display().to_string()),
    ];
    let mut servers = block.to_string();
    for (from, to) in &substitutions {
        assert!(
            servers.contains(from),
            "docs/deploy.md no longer has {from:?}"
        );
        servers = servers.replace(from, to);
    }
    let nginx_dir = dir.path().join("nginx");
    std::fs::create_dir_all(&nginx_dir).unwrap();
    let _nginx = start_nginx(&nginx_dir, https, &servers);
    let options = RemoteOptions {
        token: Some(TOKEN.into()),
        tls_ca_pem: Some(std::fs::read(&ca).unwrap()),
        give_up_after: Duration::from_secs(5),
        ..RemoteOptions::default()
    };
    let url = format!("https://{https}/v1/stores/proxied");
    let direct = RemoteSource::open(
        &server.store_url("proxied"),
        RemoteOptions {
            token: Some(TOKEN.into()),
            ..RemoteOptions::default()
        },
    )
    .unwrap();
    let ids: Vec<BrickId> = (0..8)
        .map(|x| BrickId::new(0, [x % 2, (x / 2) % 2, x / 4]))
        .filter(|id| direct.layout().contains(*id))
        .collect();
    let want: Vec<Vec<u8>> = ids
        .iter()
        .map(|id| direct.read_brick_record(*id).unwrap())
        .collect();
    let bricks =
        |s: &strata_service::server::RunningServer| s.counters().bricks.load(Ordering::Relaxed);
    let before = bricks(&server);
    let first = RemoteSource::open(&url, options.clone()).unwrap();
    for (id, record) in ids.iter().zip(&want) {
        assert_eq!(&first.read_brick_record(*id).unwrap(), record);
    }
    let origin_first = bricks(&server) - before;
    assert_eq!(
        origin_first,
        ids.len() as u64,
        "the first reading goes to the service"
    );
    // Again, through a new client: from nginx's cache, no brick request reaches the service.
    let second = RemoteSource::open(&url, options.clone()).unwrap();
    for (id, record) in ids.iter().zip(&want) {
        assert_eq!(&second.read_brick_record(*id).unwrap(), record);
    }
    assert_eq!(
        bricks(&server) - before,
        origin_first,
        "the second reading was cached"
    );
    // Without the token: the service's 401, not the cached brick.
    strata_service::install_tls_provider();
    let brick_url = format!(
        "https://{https}{}",
        brick_path("proxied", direct.generation(), ids[0])
    );
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let status = runtime.block_on(async {
        let client = reqwest::Client::builder()
            .no_proxy()
            .add_root_certificate(
                reqwest::Certificate::from_pem(&std::fs::read(&ca).unwrap()).unwrap(),
            )
            .timeout(Duration::from_secs(10))
            .build()
            .unwrap();
        client.get(&brick_url).send().await.unwrap().status()
    });
    assert_eq!(
        status.as_u16(),
        401,
        "a cached brick served without the token"
    );
    // The service gone: the cached bricks are still served.
    drop(direct);
    drop(server);
    for (id, record) in ids.iter().zip(&want) {
        assert_eq!(
            &second.read_brick_record(*id).unwrap(),
            record,
            "stale on error"
        );
    }
}
