//! Issue 49: the server under load from one address (no request dropped by its own limits),
//! and what it tells its operator (access log without the token, `/metrics` in the
//! Prometheus text format matching the requests made, nosniff on every answer).

use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use strata_service::server::{find_stores, start, RunningServer, ServeOptions};
use strata_service::wire::brick_path;
use strata_service::{RemoteOptions, RemoteSource};
use strata_source::VolumeSource;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::Store;
use strata_types::BrickId;

const TOKEN: &str = "0123456789abcdef0123456789abcdef";

/// The tests that load the server with hundreds of connections run one at a time: run in
/// parallel on a 2-core machine they starve each other's clients (a test binary's tests share
/// its threads), which says nothing about the server.
pub(crate) static HEAVY_LOAD: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// A phantom store of `size`³ voxels named `name` in `dir`: its path, every brick's record as
/// stored (level by level), and its generation.
pub(crate) fn store(
    dir: &Path,
    name: &str,
    size: u64,
) -> (std::path::PathBuf, Vec<(BrickId, Vec<u8>)>, String) {
    let path = dir.join(format!("{name}.strata"));
    Phantom::cube(size)
        .write_store(&path, &ImportOptions::default())
        .unwrap();
    let store = Store::open(&path).unwrap();
    let layout = store.layout().clone();
    let mut records = Vec::new();
    for level in 0..layout.level_count() {
        let n = layout.bricks_in_level(level);
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let id = BrickId::new(level as u8, [x, y, z]);
                    records.push((id, store.read_brick_record(id).unwrap()));
                }
            }
        }
    }
    (path, records, store.header().generation_id())
}

pub(crate) fn serve(path: &Path, options: ServeOptions) -> RunningServer {
    start(find_stores(&[path.to_path_buf()]).unwrap(), options).unwrap()
}

fn load(c: &AtomicU64) -> u64 {
    c.load(Ordering::Relaxed)
}

/// 300 keep-alive connections from 127.0.0.1 (above the 64 per address and the 256 in all)
/// hammer brick GETs for 3 s while a remote source fetches every brick. The server's own
/// counters: every request it started it answered. The remote fetch gets every record as
/// stored. Before the fix the eviction dropped connections whose response was being written
/// or whose next request was arriving (the issue: 139 168 of 223 934 started, never answered).
#[test]
fn no_request_is_dropped_under_load_from_one_address() {
    let dir = tempfile::tempdir().unwrap();
    let (path, records, generation) = store(dir.path(), "load", 72);
    let server = serve(
        &path,
        ServeOptions {
            // Idleness is judged by the wall clock: on a loaded 2-core machine this test's
            // 300 client tasks can go unscheduled for a second between a response and their
            // next request, which the server cannot tell from a client gone quiet (and
            // closing then is HTTP/1's keep-alive race). A client process like wrk is never
            // starved so; here the minimum is raised so that rotation is by `Connection:
            // close` alone, which is what the test is about.
            evict_idle_after: Duration::from_secs(4),
            ..ServeOptions::default()
        },
    );
    let url = format!(
        "{}{}",
        server.base_url(),
        brick_path("load", &generation, records[0].0)
    );
    strata_service::install_tls_provider();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("strata-test-load")
        .enable_all()
        .build()
        .unwrap();
    let ok = Arc::new(AtomicU64::new(0));
    let failed = Arc::new(AtomicU64::new(0));
    // At least 3 s of load and at least 2 answers per connection: on a loaded machine 3 s
    // alone may not make enough requests to test anything (a count, not a duration, is what
    // the assertions below need); `give_up` only bounds a hang.
    let _alone = HEAVY_LOAD.lock().unwrap_or_else(|e| e.into_inner());
    let deadline = Instant::now() + Duration::from_secs(3);
    let give_up = Instant::now() + Duration::from_secs(120);
    let enough = |ok: &AtomicU64| ok.load(Ordering::Relaxed) >= 600;
    let clients: Vec<_> = (0..300)
        .map(|_| {
            let (url, ok, failed) = (url.clone(), ok.clone(), failed.clone());
            runtime.spawn(async move {
                // One client per task with one connection: 300 connections, as wrk makes.
                let client = reqwest::Client::builder()
                    .no_proxy()
                    .http1_only()
                    .pool_max_idle_per_host(1)
                    .timeout(Duration::from_secs(10))
                    .build()
                    .unwrap();
                // The deadline is checked between requests only: no request is abandoned
                // half-way (that would be the client's abort, not the server's).
                while Instant::now() < deadline || (!enough(&ok) && Instant::now() < give_up) {
                    let answer = match client.get(&url).send().await {
                        Ok(r) if r.status().is_success() => {
                            r.bytes().await.map(drop).map_err(|e| format!("{e:?}"))
                        }
                        Ok(r) => Err(format!("status {}", r.status())),
                        Err(e) => Err(format!("{e:?}")),
                    };
                    if let Err(why) = answer {
                        if failed.fetch_add(1, Ordering::Relaxed) < 3 {
                            eprintln!("load: a request failed: {why}");
                        }
                        // A refused or closed connection: try again shortly, as clients do.
                        tokio::time::sleep(Duration::from_millis(20)).await;
                    } else {
                        ok.fetch_add(1, Ordering::Relaxed);
                    }
                }
            })
        })
        .collect();
    // The remote fetch of every brick meanwhile (HTTP/2, the viewer's client).
    let remote = RemoteSource::open(&server.store_url("load"), RemoteOptions::default()).unwrap();
    for (id, record) in &records {
        assert_eq!(&remote.read_brick_record(*id).unwrap(), record, "{id:?}");
    }
    runtime.block_on(async {
        for c in clients {
            c.await.unwrap();
        }
    });
    drop(remote);
    let c = server.counters();
    let (started, answered, aborted) = (
        load(&c.requests_started),
        load(&c.requests_answered),
        load(&c.requests_aborted),
    );
    eprintln!(
        "load: {} ok, {} failed on the client; server: {started} started, {answered} answered, \
         {aborted} aborted, {} evicted, {} refused, {} busy (503)",
        load(&ok),
        load(&failed),
        load(&c.connections_shed),
        load(&c.connections_refused),
        load(&c.rejected_busy),
    );
    assert!(
        load(&ok) > 300,
        "the load made too few requests to test anything"
    );
    // The clients' view depends on scheduling as well as on the server: a client task starved
    // past `evict_idle_after` between two requests looks to the server like one gone quiet,
    // and its connection is closed while its next request is on the way (HTTP/1's keep-alive
    // race). Measured: 0 failed on a quiet machine; 181 failed of 1 061 with a CI run's tests
    // beside it on the same 2 cores. Before the fix, with every connection evicted as soon as
    // it was idle for a moment: 5 124 answered, 8 714 failed in 3 s. So the bound asserted is
    // the one that tells the two apart on any machine (fewer failures than answers), and the
    // server's own counters below carry the criterion: nothing started is dropped.
    assert!(
        load(&failed) < load(&ok),
        "{} requests failed on the client, {} answered",
        load(&failed),
        load(&ok)
    );
    assert_eq!(aborted, 0, "requests started and dropped by the server");
    assert_eq!(started, answered);
}

/// A minimal check of the Prometheus text format (0.0.4): every line a comment (`# HELP`,
/// `# TYPE` with a known type, before the family's samples) or `name{labels} value` with a
/// valid metric name, well-formed quoted labels and a float value. Returns the samples.
fn parse_prometheus(text: &str) -> HashMap<String, f64> {
    let valid_name = |n: &str| {
        !n.is_empty()
            && n.chars().enumerate().all(|(i, c)| {
                c.is_ascii_alphabetic() || c == '_' || c == ':' || (i > 0 && c.is_ascii_digit())
            })
    };
    let mut typed: HashMap<String, String> = HashMap::new();
    let mut samples = HashMap::new();
    assert!(text.ends_with('\n'), "the exposition ends with a newline");
    for line in text.lines() {
        if let Some(comment) = line.strip_prefix("# ") {
            let mut parts = comment.splitn(3, ' ');
            let (kind, name, rest) = (parts.next().unwrap(), parts.next().unwrap(), parts.next());
            assert!(valid_name(name), "{line}");
            if kind == "TYPE" {
                let t = rest.unwrap();
                assert!(
                    ["counter", "gauge", "histogram", "summary", "untyped"].contains(&t),
                    "{line}"
                );
                assert!(
                    typed.insert(name.into(), t.into()).is_none(),
                    "TYPE twice: {line}"
                );
            }
            continue;
        }
        let (series, value) = line.rsplit_once(' ').unwrap_or_else(|| panic!("{line}"));
        let value: f64 = value.parse().unwrap_or_else(|_| panic!("{line}"));
        let name = series.split('{').next().unwrap();
        assert!(valid_name(name), "{line}");
        if let Some(labels) = series.strip_prefix(name).filter(|l| !l.is_empty()) {
            let inner = labels
                .strip_prefix('{')
                .and_then(|l| l.strip_suffix('}'))
                .unwrap_or_else(|| panic!("{line}"));
            for pair in inner.split(',') {
                let (k, v) = pair.split_once('=').unwrap_or_else(|| panic!("{line}"));
                assert!(
                    valid_name(k) && v.len() >= 2 && v.starts_with('"') && v.ends_with('"'),
                    "{line}"
                );
            }
        }
        let family = ["_bucket", "_sum", "_count", "_total"]
            .iter()
            .find_map(|s| name.strip_suffix(s).filter(|f| typed.contains_key(*f)))
            .unwrap_or(name);
        assert!(
            typed.contains_key(family) || typed.contains_key(name),
            "sample before its TYPE: {line}"
        );
        assert!(
            samples.insert(series.to_string(), value).is_none(),
            "twice: {line}"
        );
    }
    samples
}

/// The access log has a line per request (time, client, method, path, status, bytes,
/// duration) and never the token, wherever a client put it (header, query, path; a fragment
/// is never sent by a client, and a raw one is logged with the token replaced); `/metrics` parses and its counters
/// match the requests made; every answer says nosniff.
#[test]
fn access_log_and_metrics_count_every_request_and_never_show_the_token() {
    let dir = tempfile::tempdir().unwrap();
    let (path, records, generation) = store(dir.path(), "ops", 40);
    let log = dir.path().join("access.log");
    let server = serve(
        &path,
        ServeOptions {
            token: Some(TOKEN.into()),
            access_log: Some(log.clone()),
            ..ServeOptions::default()
        },
    );
    strata_service::install_tls_provider();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let client = reqwest::Client::builder()
        .no_proxy()
        .timeout(Duration::from_secs(10))
        .build()
        .unwrap();
    // (status, content type, nosniff, body)
    let get = |url: &str, token: bool| {
        runtime.block_on(async {
            let mut request = client.get(url);
            if token {
                request = request.header("authorization", format!("Bearer {TOKEN}"));
            }
            let r = request.send().await.unwrap();
            let header = |name: &str| {
                r.headers()
                    .get(name)
                    .map(|v| v.to_str().unwrap().to_string())
                    .unwrap_or_default()
            };
            let (status, kind, nosniff) = (
                r.status().as_u16(),
                header("content-type"),
                header("x-content-type-options"),
            );
            (status, kind, nosniff, r.bytes().await.unwrap())
        })
    };
    let base = server.base_url();
    let brick = format!("{base}{}", brick_path("ops", &generation, records[0].0));
    let mut statuses: HashMap<u16, u64> = HashMap::new();
    let mut body_bytes = 0;
    let mut expect = |url: String, token: bool, status: u16| {
        let (got, _, nosniff, body) = get(&url, token);
        assert_eq!(got, status, "{url}");
        assert_eq!(nosniff, "nosniff", "{url}");
        *statuses.entry(status).or_default() += 1;
        body_bytes += body.len() as u64;
    };
    expect(brick.clone(), true, 200);
    expect(format!("{base}/v1/stores"), true, 200);
    // The token in the query, without the header: 401, and not logged.
    expect(format!("{brick}?token={TOKEN}"), false, 401);
    // In the path: 404 (no such store), and not logged.
    expect(format!("{base}/v1/stores/{TOKEN}"), true, 404);
    // As a fragment (`#`): reqwest never sends it.
    expect(format!("{base}/v1/stores#token={TOKEN}"), true, 200);
    // Metrics without the token: 401 (a server with a token shows them only with it).
    expect(format!("{base}/metrics"), false, 401);
    // A raw fragment on the wire (no browser sends one) reaches the guard: 401, logged with
    // the token replaced.
    {
        use std::io::{Read, Write};
        let mut s = std::net::TcpStream::connect(server.addr()).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        write!(
            s,
            "GET /v1/stores#token={TOKEN} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut out = String::new();
        let _ = s.read_to_string(&mut out);
        assert!(out.starts_with("HTTP/1.1 401"), "{out}");
        assert!(!out.contains(TOKEN), "{out}");
        *statuses.entry(401).or_default() += 1;
        body_bytes += out
            .split_once("\r\n\r\n")
            .map_or(0, |(_, b)| b.len() as u64);
    }
    let made: u64 = statuses.values().sum();
    let (status, kind, _, body) = get(&format!("{base}/metrics"), true);
    assert_eq!(status, 200);
    assert!(kind.starts_with("text/plain; version=0.0.4"), "{kind}");
    let text = String::from_utf8(body.to_vec()).unwrap();
    let m = parse_prometheus(&text);
    for (status, n) in &statuses {
        assert_eq!(
            m.get(&format!("strata_requests_total{{status=\"{status}\"}}")),
            Some(&(*n as f64)),
            "{text}"
        );
    }
    // The metrics request itself is in flight while they are written: started counts it.
    assert_eq!(
        m["strata_requests_started_total"],
        (made + 1) as f64,
        "{text}"
    );
    assert_eq!(
        m["strata_request_duration_seconds_count"], made as f64,
        "{text}"
    );
    assert_eq!(
        m["strata_request_duration_seconds_bucket{le=\"+Inf\"}"],
        made as f64
    );
    assert_eq!(
        m["strata_response_body_bytes_total"], body_bytes as f64,
        "{text}"
    );
    assert_eq!(m["strata_unauthorized_total"], 3.0);
    assert_eq!(m["strata_bricks_total"], 1.0);
    assert_eq!(m["strata_requests_aborted_total"], 0.0);
    assert!(m["strata_open_connections"] >= 1.0);
    assert!(m.contains_key("strata_connections_evicted_total"));
    assert!(m.contains_key("strata_requests_refused_busy_total"));
    // The log: written by its own thread, so wait (bounded) for every line.
    let want_lines = made as usize + 1;
    let started = Instant::now();
    let text = loop {
        let text = std::fs::read_to_string(&log).unwrap_or_default();
        if text.lines().count() >= want_lines || started.elapsed() > Duration::from_secs(5) {
            break text;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(
        !text.contains(TOKEN),
        "the token in the access log:\n{text}"
    );
    let lines: Vec<Vec<&str>> = text.lines().map(|l| l.split(' ').collect()).collect();
    assert_eq!(lines.len(), want_lines, "{text}");
    for fields in &lines {
        assert_eq!(fields.len(), 7, "{fields:?}");
        assert!(
            fields[0].ends_with('Z') && fields[0].contains('T'),
            "{fields:?}"
        );
        assert_eq!(fields[1], "127.0.0.1");
        assert_eq!(fields[2], "GET");
        assert!(
            fields[3].starts_with('/') && !fields[3].contains('?'),
            "{fields:?}"
        );
        fields[4].parse::<u16>().unwrap();
        fields[5].parse::<u64>().unwrap();
        fields[6].parse::<f64>().unwrap();
    }
    assert!(text.contains(" /v1/stores/[token] 404 "), "{text}");
    let logged_statuses: u64 = lines.iter().filter(|f| f[4] == "401").count() as u64;
    assert_eq!(logged_statuses, statuses[&401]);
    assert_eq!(
        lines[0][5].parse::<usize>().unwrap(),
        records[0].1.len(),
        "the brick line's bytes"
    );
}
