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
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::{BrickId, Store};

fn nginx_binary() -> PathBuf {
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
struct Nginx(Child);

impl Drop for Nginx {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn free_port() -> SocketAddr {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
}

/// Starts nginx in the foreground with everything (pid, logs, temp files) under `dir`, and
/// waits (bounded) until it accepts.
fn start_nginx(dir: &Path, listen: SocketAddr, upstream: SocketAddr) -> Nginx {
    let d = dir.display();
    let conf = format!(
        r#"daemon off;
master_process off;
worker_processes 1;
pid {d}/nginx.pid;
error_log {d}/error.log warn;
events {{ worker_connections 2048; }}
http {{
    access_log off;
    client_body_temp_path {d}/body;
    proxy_temp_path {d}/proxy;
    fastcgi_temp_path {d}/fastcgi;
    uwsgi_temp_path {d}/uwsgi;
    scgi_temp_path {d}/scgi;
    upstream strata {{
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
            proxy_pass_request_headers on;
        }}
    }}
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
    let _nginx = start_nginx(&nginx_dir, listen, server.addr());
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
    let deadline = Instant::now() + Duration::from_secs(2);
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
                while Instant::now() < deadline {
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
