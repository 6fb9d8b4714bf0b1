//! Issue 49, item 5: the service's capacity figures, measured (not asserted: a shared machine's
//! timings are loose; the ratios are what to read). Debian's `wrk` requests a phantom store's
//! bricks round-robin at 10, 100 and 1 000 connections, direct and through Debian's `nginx` as
//! a reverse proxy without cache (proxy.rs's configuration); then N remote viewers (the
//! desktop's HTTP/2 client, each its own connection) stream every brick of the store at once,
//! N increasing until one fails or the median time per viewer passes a bound.
//!
//! `cargo test -p strata-service --test integration capacity -- --ignored --nocapture`
//! Env: STRATA_BENCH_VOLUME (phantom edge, default 256), STRATA_BENCH_SECONDS (per wrk run,
//! default 4), STRATA_BENCH_VIEWERS (viewer counts, default 8,16,32,64,128),
//! STRATA_BENCH_VIEWER_BOUND_S (median seconds per viewer, default 10).
//! Writes the table to docs/bench-runs/service-capacity-DATE.md.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

use strata_service::server::{RunningServer, ServeOptions};
use strata_service::wire::brick_path;
use strata_service::{RemoteOptions, RemoteSource};
use strata_source::{FetchOptions, VolumeSource};
use strata_types::BrickId;

use crate::load::{serve, store};
use crate::proxy::{free_port, plain_proxy, start_nginx};

fn wrk_binary() -> PathBuf {
    ["/usr/bin/wrk", "/usr/local/bin/wrk"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
        .unwrap_or_else(|| {
            panic!("wrk is not installed: `apt-get install -y wrk` (Debian's package)")
        })
}

/// What one wrk run reports (latencies in milliseconds).
#[derive(Debug, Default, Clone)]
struct Wrk {
    requests: u64,
    per_second: f64,
    p50: f64,
    p90: f64,
    p99: f64,
    /// connect, read, write, timeout
    socket_errors: [u64; 4],
    non_2xx: u64,
}

/// `812.00us`, `1.23ms`, `2.00s`, `1.50m` in milliseconds.
fn millis(text: &str) -> f64 {
    let split = text
        .find(|c: char| c.is_ascii_alphabetic())
        .unwrap_or(text.len());
    let (number, unit) = text.split_at(split);
    let number: f64 = number
        .parse()
        .unwrap_or_else(|_| panic!("wrk latency {text:?}"));
    number
        * match unit {
            "us" => 0.001,
            "ms" => 1.0,
            "s" => 1000.0,
            "m" => 60_000.0,
            "h" => 3_600_000.0,
            _ => panic!("wrk latency unit {text:?}"),
        }
}

fn parse_wrk(out: &str) -> Wrk {
    let mut w = Wrk::default();
    let mut percentiles = 0;
    for line in out.lines().map(str::trim) {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["50%", v] => (w.p50, percentiles) = (millis(v), percentiles + 1),
            ["90%", v] => (w.p90, percentiles) = (millis(v), percentiles + 1),
            ["99%", v] => (w.p99, percentiles) = (millis(v), percentiles + 1),
            ["Requests/sec:", v] => w.per_second = v.parse().unwrap(),
            [n, "requests", "in", ..] => w.requests = n.parse().unwrap(),
            ["Non-2xx", "or", "3xx", "responses:", n] => w.non_2xx = n.parse().unwrap(),
            ["Socket", "errors:", ..] => {
                // Socket errors: connect 0, read 12, write 0, timeout 0
                let numbers: Vec<u64> = words[2..]
                    .iter()
                    .filter_map(|x| x.trim_end_matches(',').parse().ok())
                    .collect();
                w.socket_errors = numbers.try_into().unwrap_or_else(|_| panic!("{line}"));
            }
            _ => {}
        }
    }
    assert!(
        percentiles == 3 && w.requests > 0,
        "wrk's output not understood:\n{out}"
    );
    w
}

/// The round-robin script: every brick path in turn (each wrk thread from the first).
fn lua_script(paths: &[String], token: Option<&str>) -> String {
    let mut s = String::from("local paths = {\n");
    for p in paths {
        writeln!(s, "  \"{p}\",").unwrap();
    }
    s.push_str("}\nlocal i = 0\n");
    if let Some(token) = token {
        writeln!(s, "wrk.headers[\"Authorization\"] = \"Bearer {token}\"").unwrap();
    }
    s.push_str(
        "request = function()\n  i = i % #paths + 1\n  return wrk.format(nil, paths[i])\nend\n",
    );
    s
}

fn run_wrk(base: &str, script: &Path, connections: u32, seconds: u32) -> Wrk {
    let out = Command::new(wrk_binary())
        .arg(format!("-t{}", connections.min(2)))
        .arg(format!("-c{connections}"))
        .arg(format!("-d{seconds}s"))
        .arg("--timeout")
        .arg("10s")
        .arg("--latency")
        .arg("-s")
        .arg(script)
        .arg(base)
        .output()
        .expect("cannot run wrk");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "wrk failed: {text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    parse_wrk(&text)
}

/// The server's counters that matter here, as a difference over one run.
#[derive(Clone, Copy, Default)]
struct Counters {
    started: u64,
    answered: u64,
    aborted: u64,
    shed: u64,
    refused: u64,
    busy: u64,
}

fn counters(server: &RunningServer) -> Counters {
    let c = server.counters();
    Counters {
        started: c.requests_started.load(Relaxed),
        answered: c.requests_answered.load(Relaxed),
        aborted: c.requests_aborted.load(Relaxed),
        shed: c.connections_shed.load(Relaxed),
        refused: c.connections_refused.load(Relaxed),
        busy: c.rejected_busy.load(Relaxed),
    }
}

fn since(a: Counters, b: Counters) -> Counters {
    Counters {
        started: b.started - a.started,
        answered: b.answered - a.answered,
        aborted: b.aborted - a.aborted,
        shed: b.shed - a.shed,
        refused: b.refused - a.refused,
        busy: b.busy - a.busy,
    }
}

/// One viewer: opens the store and streams every brick through the client's asynchronous
/// queue (as the loader does: all asked at once, up to 64 in flight over one HTTP/2
/// connection). The time from open to the last brick, or why it failed.
fn view(url: &str, ids: &[BrickId], deadline: Duration) -> Result<(Duration, u64), String> {
    let started = Instant::now();
    let remote = RemoteSource::open(url, RemoteOptions::default()).map_err(|e| e.to_string())?;
    let fetcher = remote
        .start_fetching(FetchOptions {
            max_queued: ids.len(),
            max_in_transit: 64,
            threads: 1,
        })
        .expect("the remote source fetches asynchronously")
        .map_err(|e| e.to_string())?;
    let demand: Vec<(BrickId, f64)> = ids.iter().map(|id| (*id, id.level as f64)).collect();
    fetcher.set_requests(&demand, &[]);
    let (mut got, mut bytes) = (0, 0);
    while got < ids.len() {
        if started.elapsed() > deadline {
            return Err(format!("{got} of {} bricks after {deadline:?}", ids.len()));
        }
        let results = fetcher.try_results();
        if results.is_empty() {
            std::thread::sleep(Duration::from_millis(2));
        }
        for r in results {
            r.outcome.map_err(|e| e.to_string())?;
            fetcher.complete(r.id);
            bytes += r.stored_bytes;
            got += 1;
        }
    }
    Ok((started.elapsed(), bytes))
}

struct Viewers {
    n: usize,
    completed: usize,
    failures: Vec<String>,
    median: Duration,
    slowest: Duration,
    wall: Duration,
    bytes: u64,
}

fn viewers_at_once(url: &str, ids: &[BrickId], n: usize, deadline: Duration) -> Viewers {
    let barrier = Arc::new(Barrier::new(n));
    let started = Instant::now();
    let outcomes: Vec<_> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..n)
            .map(|_| {
                let barrier = barrier.clone();
                s.spawn(move || {
                    barrier.wait();
                    view(url, ids, deadline)
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let wall = started.elapsed();
    let mut times = Vec::new();
    let (mut failures, mut bytes) = (Vec::new(), 0);
    for o in outcomes {
        match o {
            Ok((t, b)) => {
                times.push(t);
                bytes += b;
            }
            Err(e) => failures.push(e),
        }
    }
    times.sort();
    Viewers {
        n,
        completed: times.len(),
        failures,
        median: times.get(times.len() / 2).copied().unwrap_or(deadline),
        slowest: times.last().copied().unwrap_or(deadline),
        wall,
        bytes,
    }
}

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn command_line(program: &str, args: &[&str]) -> Option<String> {
    let out = Command::new(program).args(args).output().ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

#[test]
#[ignore = "measurement: run with --ignored --nocapture"]
fn capacity_figures_direct_and_through_nginx() {
    let edge: u64 = env_or("STRATA_BENCH_VOLUME", 256);
    let seconds: u32 = env_or("STRATA_BENCH_SECONDS", 4);
    let bound = Duration::from_secs_f64(env_or("STRATA_BENCH_VIEWER_BOUND_S", 10.0));
    let steps: Vec<usize> = std::env::var("STRATA_BENCH_VIEWERS")
        .unwrap_or_else(|_| "8,16,32,64,128".into())
        .split(',')
        .map(|n| n.trim().parse().expect("STRATA_BENCH_VIEWERS: counts"))
        .collect();
    let wrk = wrk_binary();
    let dir = tempfile::tempdir().unwrap();
    let (path, records, generation) = store(dir.path(), "bench", edge);
    let ids: Vec<BrickId> = records.iter().map(|(id, _)| *id).collect();
    let stored: usize = records.iter().map(|(_, r)| r.len()).sum();
    drop(records);
    // As docs/deploy.md runs it: nginx on the same machine is a trusted proxy, 512
    // connections in all. Loopback clients (wrk, the viewers) are then that pool too: limited
    // by the global cap alone, as many direct clients from distinct addresses would be.
    let server = serve(
        &path,
        ServeOptions {
            trusted_proxies: vec![[127, 0, 0, 1].into()],
            max_connections: 512,
            ..ServeOptions::default()
        },
    );
    let listen = free_port();
    let nginx_dir = dir.path().join("nginx");
    std::fs::create_dir_all(&nginx_dir).unwrap();
    let _nginx = start_nginx(&nginx_dir, listen, &plain_proxy(listen, server.addr()));
    let paths: Vec<String> = ids
        .iter()
        .map(|id| brick_path("bench", &generation, *id))
        .collect();
    let script = dir.path().join("bricks.lua");
    std::fs::write(&script, lua_script(&paths, None)).unwrap();

    let mut report = String::new();
    let commit = command_line("git", &["rev-parse", "--short", "HEAD"]).unwrap_or("?".into());
    let wrk_version = command_line("wrk", &["--version"])
        .or_else(|| {
            // wrk prints its version with the usage and exits 1.
            let out = Command::new(&wrk).arg("--version").output().ok()?;
            let text = String::from_utf8_lossy(&out.stdout).to_string();
            text.lines().next().map(str::to_string)
        })
        .unwrap_or_default();
    let nginx_version = Command::new(crate::proxy::nginx_binary())
        .arg("-v")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stderr).trim().to_string())
        .unwrap_or_default();
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    writeln!(
        report,
        "# Service capacity (issue 49, item 5)\n\n\
         `cargo test -p strata-service --test integration capacity -- --ignored --nocapture` \
         (service/tests/capacity.rs) at {commit}, {} profile, on {cores} shared cores (the \
         server, nginx, wrk and the viewers all on this machine: absolute figures are loose, \
         read the ratios).\n\n\
         Store: {edge}³ phantom, {} bricks ({:.1} MB stored). Server: `strata serve \
         --trusted-proxy 127.0.0.1 --max-connections 512` in-process (loopback clients are \
         then the trusted pool, capped by the 512 alone). nginx ({nginx_version}): one worker, \
         no cache, upstream keepalive 64 (service/tests/proxy.rs). {}: {seconds} s per run, \
         2 threads, brick paths round-robin, `--latency`.\n",
        if cfg!(debug_assertions) {
            "dev"
        } else {
            "release"
        },
        ids.len(),
        stored as f64 / 1e6,
        wrk_version.split(" [").next().unwrap_or("wrk"),
    )
    .unwrap();
    writeln!(
        report,
        "## Brick GETs\n\n\
         | path | connections | requests/s | p50 ms | p90 ms | p99 ms | socket errors \
         (connect/read/write/timeout) | non-2xx | server: started / answered / aborted | \
         server: shed / refused / 503 |\n|---|---|---|---|---|---|---|---|---|---|"
    )
    .unwrap();
    let mut figures = Vec::new();
    let error_log = nginx_dir.join("error.log");
    let mut nginx_notes = Vec::new();
    for (route, base) in [
        ("direct", server.base_url()),
        ("nginx", format!("http://{listen}")),
    ] {
        for connections in [10u32, 100, 1000] {
            let before = counters(&server);
            let logged = std::fs::read_to_string(&error_log)
                .unwrap_or_default()
                .len();
            let w = run_wrk(&base, &script, connections, seconds);
            // wrk is gone: what the server still had in flight settles.
            std::thread::sleep(Duration::from_millis(300));
            let c = since(before, counters(&server));
            let e = w.socket_errors;
            let row = format!(
                "| {route} | {connections} | {:.0} | {:.2} | {:.2} | {:.2} | {}/{}/{}/{} | {} | \
                 {} / {} / {} | {} / {} / {} |",
                w.per_second,
                w.p50,
                w.p90,
                w.p99,
                e[0],
                e[1],
                e[2],
                e[3],
                w.non_2xx,
                c.started,
                c.answered,
                c.aborted,
                c.shed,
                c.refused,
                c.busy
            );
            eprintln!("{row}");
            writeln!(report, "{row}").unwrap();
            figures.push((route, connections, w));
            // What nginx said meanwhile (its error log, warn and above): how many lines, and
            // the first (what a read error through nginx was).
            let log = std::fs::read_to_string(&error_log).unwrap_or_default();
            let new: Vec<&str> = log.get(logged..).unwrap_or("").lines().collect();
            if !new.is_empty() {
                let first = new[0].split_once(" [").map_or(new[0], |(_, rest)| rest);
                nginx_notes.push(format!(
                    "- {route}, {connections} connections: nginx's error log has {} line(s); \
                     the first: `[{}`",
                    new.len(),
                    first.chars().take(300).collect::<String>()
                ));
            }
        }
    }
    for note in &nginx_notes {
        eprintln!("{note}");
    }
    if !nginx_notes.is_empty() {
        writeln!(report, "\n{}", nginx_notes.join("\n")).unwrap();
    }
    writeln!(
        report,
        "\n## Through nginx / direct\n\n\
         | connections | requests/s | p50 | p99 |\n|---|---|---|---|"
    )
    .unwrap();
    let find = |route: &str, c: u32| {
        figures
            .iter()
            .find(|(r, n, _)| *r == route && *n == c)
            .map(|(_, _, w)| w.clone())
            .unwrap()
    };
    for c in [10, 100, 1000] {
        let (d, n) = (find("direct", c), find("nginx", c));
        writeln!(
            report,
            "| {c} | {:.2} | {:.2} | {:.2} |",
            n.per_second / d.per_second,
            n.p50 / d.p50,
            n.p99 / d.p99
        )
        .unwrap();
    }
    let (d, n) = (find("direct", 100), find("nginx", 100));
    let within = |r: f64| if r <= 1.5 { "met" } else { "not met" };
    writeln!(
        report,
        "\nGoal (issue 49): brick GET latency at 100 connections through nginx within 1.5× of \
         direct: p50 {:.2} ms / {:.2} ms = {:.2} ({}), p99 {:.2} ms / {:.2} ms = {:.2} ({}).",
        n.p50,
        d.p50,
        n.p50 / d.p50,
        within(n.p50 / d.p50),
        n.p99,
        d.p99,
        n.p99 / d.p99,
        within(n.p99 / d.p99),
    )
    .unwrap();

    // Concurrent viewers, direct (the client speaks HTTP/2 to the service; nginx here is
    // HTTP/1.1 without TLS).
    let url = server.store_url("bench");
    let deadline = bound * 4;
    writeln!(
        report,
        "\n## Concurrent viewers\n\n\
         N viewers at once (each a `RemoteSource` with its own runtime and HTTP/2 connection, \
         every one of the {} bricks asked at once, 64 in flight), direct; N grows until one \
         fails (or passes {deadline:?}) or the median time per viewer passes {bound:?}. A 503 \
         is the server's `--max-requests 512` (requests at once) answering busy; the client \
         backs off and retries it.\n\n\
         | viewers | completed | median s | slowest s | wall s | MB/s in all | server: shed / \
         refused / 503 |\n|---|---|---|---|---|---|---|",
        ids.len()
    )
    .unwrap();
    let mut largest = 0;
    for n in steps {
        let before = counters(&server);
        let v = viewers_at_once(&url, &ids, n, deadline);
        let c = since(before, counters(&server));
        let row = format!(
            "| {} | {} | {:.2} | {:.2} | {:.2} | {:.1} | {} / {} / {} |",
            v.n,
            v.completed,
            v.median.as_secs_f64(),
            v.slowest.as_secs_f64(),
            v.wall.as_secs_f64(),
            v.bytes as f64 / 1e6 / v.wall.as_secs_f64(),
            c.shed,
            c.refused,
            c.busy
        );
        eprintln!("{row}");
        writeln!(report, "{row}").unwrap();
        for f in v.failures.iter().take(3) {
            eprintln!("viewer failed: {f}");
            writeln!(report, "\n(a viewer failed: {f})").unwrap();
        }
        if !v.failures.is_empty() || v.median > bound {
            break;
        }
        largest = n;
    }
    writeln!(
        report,
        "\nLargest number of viewers that all completed within the bound: {largest}."
    )
    .unwrap();
    let total = counters(&server);
    writeln!(
        report,
        "\nServer over the whole run: {} requests started, {} answered, {} aborted (an abort \
         is a client gone with its request in flight: wrk stops mid-request at its end).",
        total.started, total.answered, total.aborted
    )
    .unwrap();

    println!("\n{report}");
    let date = command_line("date", &["-u", "+%Y-%m-%d"]).unwrap_or("undated".into());
    let out = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../docs/bench-runs")
        .join(format!("service-capacity-{date}.md"));
    std::fs::write(&out, &report).unwrap();
    eprintln!("written to {}", out.display());
}

#[test]
fn wrk_output_is_understood() {
    let out = "Running 4s test @ http://127.0.0.1:1/\n  2 threads and 10 connections\n  \
               Thread Stats   Avg      Stdev     Max   +/- Stdev\n    Latency   1.02ms  \
               400.00us  12.00ms   90.00%\n  Latency Distribution\n     50%  812.00us\n     \
               75%    1.10ms\n     90%    1.50ms\n     99%    2.01s\n  12345 requests in \
               4.00s, 1.20MB read\n  Socket errors: connect 0, read 12, write 0, timeout 3\n  \
               Non-2xx or 3xx responses: 7\nRequests/sec:   3086.25\nTransfer/sec:    \
               307.20KB\n";
    let w = parse_wrk(out);
    assert_eq!(w.requests, 12345);
    assert_eq!(w.socket_errors, [0, 12, 0, 3]);
    assert_eq!(w.non_2xx, 7);
    assert!((w.p50 - 0.812).abs() < 1e-9 && (w.p90 - 1.5).abs() < 1e-9);
    assert!((w.p99 - 2010.0).abs() < 1e-9 && (w.per_second - 3086.25).abs() < 1e-9);
}
