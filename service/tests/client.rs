//! The remote fetcher against a real server on loopback (the RTT injected in the server):
//! many requests in flight over one HTTP/2 connection, the loader's priority order, stale
//! requests aborted on the wire, a record damaged in transit re-requested once and then
//! reported, and the HTTP/1.1 pool.

use std::collections::HashSet;
use std::path::Path;
use std::time::{Duration, Instant};

use strata_service::server::{find_stores, start, RunningServer, ServeOptions};
use strata_service::{RemoteOptions, RemoteSource};
use strata_source::{BrickFetcher, FetchOptions, FetchResult, SourceError, VolumeSource};
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::Store;
use strata_types::BrickId;

fn served(dir: &Path, size: u64, options: ServeOptions) -> RunningServer {
    let path = dir.join("phantom.strata");
    Phantom::cube(size)
        .write_store(&path, &ImportOptions::default())
        .unwrap();
    start(find_stores(&[path]).unwrap(), options).unwrap()
}

fn fetcher(
    server: &RunningServer,
    options: RemoteOptions,
) -> (RemoteSource, Box<dyn BrickFetcher>) {
    let remote = RemoteSource::open(&server.store_url("phantom"), options).unwrap();
    let fetcher = remote
        .start_fetching(FetchOptions {
            max_queued: 512,
            max_in_transit: 256,
            threads: 1,
        })
        .expect("a remote source has its own fetcher")
        .unwrap();
    (remote, fetcher)
}

fn level_ids(remote: &RemoteSource, level: usize) -> Vec<BrickId> {
    let n = remote.layout().bricks_in_level(level);
    let mut ids = Vec::new();
    for z in 0..n[2] {
        for y in 0..n[1] {
            for x in 0..n[0] {
                ids.push(BrickId::new(level as u8, [x, y, z]));
            }
        }
    }
    ids
}

/// Takes results until `count` arrived (or 60 s passed), completing each.
fn collect(fetcher: &dyn BrickFetcher, count: usize) -> Vec<FetchResult> {
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut got = Vec::new();
    while got.len() < count && Instant::now() < deadline {
        for r in fetcher.try_results() {
            fetcher.complete(r.id);
            got.push(r);
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    got
}

#[test]
fn many_requests_fly_at_once_over_one_http2_connection() {
    let dir = tempfile::tempdir().unwrap();
    let server = served(
        dir.path(),
        160,
        ServeOptions {
            added_delay: Duration::from_millis(300),
            ..ServeOptions::default()
        },
    );
    let (remote, fetcher) = fetcher(&server, RemoteOptions::default());
    let ids = level_ids(&remote, 0);
    assert!(ids.len() >= 64, "{} bricks", ids.len());
    let demand: Vec<(BrickId, f64)> = ids.iter().map(|&id| (id, 1.0)).collect();
    fetcher.set_requests(&demand, &[]);
    let got = collect(fetcher.as_ref(), ids.len());
    assert_eq!(got.len(), ids.len());
    // A format-3 store is read by any number of processes: the server's shared lock does not
    // keep a local reader out (format 2 stores, held exclusively, still name the server's URL).
    let local = Store::open_with_cache(&dir.path().join("phantom.strata"), 1 << 20).unwrap();
    assert_eq!(local.format_version(), 3);
    drop(local);
    // Every record was verified on arrival: Ok means its checksum matched.
    for r in &got {
        let brick = r.outcome.as_ref().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(brick.len(), strata_types::BRICK_PAYLOAD_VOXELS);
        assert!(r.stored_bytes > 0);
    }
    let c = fetcher.counters();
    // One 300 ms round trip each: only overlap makes 125 of them finish; at least 32 at once.
    assert!(
        c.max_in_flight >= 32,
        "at most {} in flight",
        c.max_in_flight
    );
    assert_eq!(c.retried, 0);
}

#[test]
fn demand_comes_before_prefetch_and_higher_priority_first() {
    let dir = tempfile::tempdir().unwrap();
    let server = served(
        dir.path(),
        128,
        ServeOptions {
            added_delay: Duration::from_millis(150),
            ..ServeOptions::default()
        },
    );
    let (remote, fetcher) = fetcher(
        &server,
        RemoteOptions {
            max_in_flight: 4,
            ..RemoteOptions::default()
        },
    );
    let ids = level_ids(&remote, 0);
    // Demand: 8 bricks, priority = index (the loader's convention: higher is sooner).
    let demand: Vec<(BrickId, f64)> = ids[..8]
        .iter()
        .enumerate()
        .map(|(i, &id)| (id, i as f64))
        .collect();
    // Prefetch with higher numbers still comes after every demand request.
    let prefetch: Vec<(BrickId, f64)> = ids[8..12].iter().map(|&id| (id, 100.0)).collect();
    fetcher.set_requests(&demand, &prefetch);
    let got = collect(fetcher.as_ref(), 12);
    let order: Vec<BrickId> = got.iter().map(|r| r.id).collect();
    assert_eq!(order.len(), 12);
    // Four at a time: the four most urgent demand bricks arrive first, then the other four,
    // then the prefetch.
    let first: HashSet<BrickId> = order[..4].iter().copied().collect();
    let want_first: HashSet<BrickId> = ids[4..8].iter().copied().collect();
    assert_eq!(first, want_first, "{order:?}");
    let second: HashSet<BrickId> = order[4..8].iter().copied().collect();
    assert_eq!(second, ids[..4].iter().copied().collect(), "{order:?}");
    let last: HashSet<BrickId> = order[8..].iter().copied().collect();
    assert_eq!(last, ids[8..12].iter().copied().collect(), "{order:?}");
}

#[test]
fn requests_a_new_view_no_longer_names_are_cancelled_on_the_wire() {
    let dir = tempfile::tempdir().unwrap();
    let server = served(
        dir.path(),
        128,
        ServeOptions {
            added_delay: Duration::from_millis(1500),
            ..ServeOptions::default()
        },
    );
    let (remote, fetcher) = fetcher(
        &server,
        RemoteOptions {
            max_in_flight: 8,
            ..RemoteOptions::default()
        },
    );
    let ids = level_ids(&remote, 0);
    let old: Vec<(BrickId, f64)> = ids[..8].iter().map(|&id| (id, 1.0)).collect();
    let new: Vec<(BrickId, f64)> = ids[8..16].iter().map(|&id| (id, 1.0)).collect();
    fetcher.set_requests(&old, &[]);
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(
        fetcher.in_flight(),
        8,
        "the first view's requests are on the wire"
    );
    // Two views that want other bricks: the first eight are aborted, the new ones start.
    fetcher.set_requests(&new, &[]);
    fetcher.set_requests(&new, &[]);
    let c = fetcher.counters();
    assert_eq!(c.cancelled_in_flight, 8);
    let got = collect(fetcher.as_ref(), 8);
    let arrived: HashSet<BrickId> = got.iter().map(|r| r.id).collect();
    assert_eq!(arrived, ids[8..16].iter().copied().collect::<HashSet<_>>());
    // Nothing of the old view ever arrives.
    std::thread::sleep(Duration::from_millis(200));
    assert!(fetcher.try_results().is_empty());
}

#[test]
fn a_record_damaged_in_transit_is_fetched_again_once_then_reported() {
    let id = BrickId::new(0, [1, 1, 1]);
    for (corrupted_answers, expect_ok) in [(1, true), (2, false)] {
        let dir = tempfile::tempdir().unwrap();
        let server = served(
            dir.path(),
            96,
            ServeOptions {
                corrupt_answers: Some((id, corrupted_answers)),
                ..ServeOptions::default()
            },
        );
        let (_remote, fetcher) = fetcher(&server, RemoteOptions::default());
        fetcher.set_requests(&[(id, 1.0)], &[]);
        let got = collect(fetcher.as_ref(), 1);
        assert_eq!(got.len(), 1);
        let c = fetcher.counters();
        assert_eq!(c.checksum_failures, corrupted_answers as u64);
        match (&got[0].outcome, expect_ok) {
            (Ok(_), true) => {}
            (Err(SourceError::Damaged { message, .. }), false) => {
                assert!(message.contains("checksum"), "{message}")
            }
            (other, _) => panic!(
                "{corrupted_answers} corrupted answers gave {:?}",
                other.as_ref().map(|_| "a brick")
            ),
        }
    }
}

#[test]
fn the_http1_pool_fetches_the_same_bricks() {
    let dir = tempfile::tempdir().unwrap();
    let server = served(dir.path(), 96, ServeOptions::default());
    let (remote, fetcher) = fetcher(
        &server,
        RemoteOptions {
            http1: true,
            max_in_flight: 8,
            ..RemoteOptions::default()
        },
    );
    let ids: Vec<BrickId> = (0..remote.layout().level_count())
        .flat_map(|l| level_ids(&remote, l))
        .collect();
    let demand: Vec<(BrickId, f64)> = ids.iter().map(|&id| (id, 1.0)).collect();
    fetcher.set_requests(&demand, &[]);
    let got = collect(fetcher.as_ref(), ids.len());
    assert_eq!(got.len(), ids.len());
    for r in &got {
        let brick = r.outcome.as_ref().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(&**brick, &remote.read_brick(r.id).unwrap());
    }
}

/// A front on loopback between the client and a real server: the first `resets`
/// connections are closed as soon as their request arrives (a reset, as under load), the
/// next `busy` are answered 503 with `Retry-After: 1`, and the rest are piped to the server.
/// Returns its address and the count of connections it took. Threads named; it stops with
/// the test process (the listener thread blocks in accept).
fn flaky_front(
    upstream: std::net::SocketAddr,
    resets: usize,
    busy: usize,
) -> (
    std::net::SocketAddr,
    std::sync::Arc<std::sync::atomic::AtomicUsize>,
) {
    use std::io::{Read, Write};
    use std::sync::atomic::{AtomicUsize, Ordering};
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    let taken = std::sync::Arc::new(AtomicUsize::new(0));
    let count = taken.clone();
    std::thread::Builder::new()
        .name("strata-test-flaky-front".into())
        .spawn(move || {
            for stream in listener.incoming() {
                let Ok(mut client) = stream else { continue };
                let n = count.fetch_add(1, Ordering::Relaxed);
                let _ = client.set_read_timeout(Some(Duration::from_secs(5)));
                if n < resets + busy {
                    // Read the request's head, then cut or refuse.
                    let mut head = Vec::new();
                    let mut buf = [0u8; 1024];
                    while !head.windows(4).any(|w| w == b"\r\n\r\n") {
                        match client.read(&mut buf) {
                            Ok(0) | Err(_) => break,
                            Ok(k) => head.extend_from_slice(&buf[..k]),
                        }
                    }
                    if n >= resets {
                        let _ = client.write_all(
                            b"HTTP/1.1 503 Service Unavailable\r\nRetry-After: 1\r\n\
                              Content-Length: 0\r\nConnection: close\r\n\r\n",
                        );
                    }
                    continue;
                }
                let Ok(server) = std::net::TcpStream::connect(upstream) else {
                    continue;
                };
                let _ = client.set_read_timeout(None);
                let (mut c2, mut s2) = (client.try_clone().unwrap(), server.try_clone().unwrap());
                let (mut client, mut server) = (client, server);
                let _ = std::thread::Builder::new()
                    .name("strata-test-flaky-up".into())
                    .spawn(move || {
                        let _ = std::io::copy(&mut c2, &mut s2);
                        let _ = s2.shutdown(std::net::Shutdown::Write);
                    });
                let _ = std::thread::Builder::new()
                    .name("strata-test-flaky-down".into())
                    .spawn(move || {
                        let _ = std::io::copy(&mut server, &mut client);
                        let _ = client.shutdown(std::net::Shutdown::Write);
                    });
            }
        })
        .unwrap();
    (addr, taken)
}

/// Issue 49, item 2: a server that resets the first connections and then answers 503 with
/// `Retry-After` for a while is ridden out (opening and every brick read succeed, with the
/// default bound); a server gone for good fails within the bound, with an error that says
/// so. (No timing is asserted: the bound is 1 s, so the test is short.)
#[test]
fn a_busy_server_is_ridden_out_and_a_gone_one_fails_with_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let server = served(dir.path(), 40, ServeOptions::default());
    // The records as the server gives them directly (the store is locked by the server).
    let direct =
        RemoteSource::open(&server.store_url("phantom"), RemoteOptions::default()).unwrap();
    let (front, taken) = flaky_front(server.addr(), 3, 2);
    let url = format!("http://{front}/v1/stores/phantom");
    let remote = RemoteSource::open(
        &url,
        RemoteOptions {
            http1: true,
            ..RemoteOptions::default()
        },
    )
    .unwrap();
    let ids: Vec<BrickId> = (0..8)
        .map(|x| BrickId::new(0, [x % 2, (x / 2) % 2, x / 4]))
        .filter(|id| remote.layout().contains(*id))
        .collect();
    assert!(!ids.is_empty());
    for id in &ids {
        assert_eq!(
            remote.read_brick_record(*id).unwrap(),
            direct.read_brick_record(*id).unwrap()
        );
    }
    assert!(
        taken.load(std::sync::atomic::Ordering::Relaxed) > 5,
        "the resets and the 503s were all met"
    );
    // Gone for good: nothing listens on the port any more.
    let gone = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap()
    };
    let bound = RemoteOptions {
        http1: true,
        give_up_after: Duration::from_secs(1),
        ..RemoteOptions::default()
    };
    let error = match RemoteSource::open(&format!("http://{gone}/v1/stores/phantom"), bound.clone())
    {
        Ok(_) => panic!("opened a store on a closed port"),
        Err(e) => e.to_string(),
    };
    assert!(
        error.contains("cannot reach the server: the server did not answer within 1 s"),
        "{error}"
    );
    // Gone after opening: a brick read fails the same way.
    let remote = RemoteSource::open(&server.store_url("phantom"), bound).unwrap();
    drop(direct);
    drop(server);
    let error = remote.read_brick_record(ids[0]).unwrap_err().to_string();
    assert!(
        error.contains("the server did not answer within 1 s"),
        "{error}"
    );
}
