//! Stale brick requests are cancelled on the wire: the streaming source's own request path
//! (one task per brick) aborts a request the loader's wish lists stop naming, which closes
//! its connection, so the server never finishes sending it. Checked against a real HTTP/1.1
//! server on 127.0.0.1 that serves an exported OME-Zarr folder (HEAD, ranged GET) and, while
//! stalled, holds every chunk request (`/c/` objects: shard indices and inner chunks) until it
//! is released or the client hangs up. It counts the requests it finished after they were
//! released: zero after cancellation, all of them without (the control, so the count can fail).

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use strata_omezarr::export::{export, ExportOptions};
use strata_omezarr::streaming::OmeZarrSource;
use strata_omezarr::{ObjectLocation, ObjectStoreOptions};
use strata_source::{FetchOptions, VolumeSource};
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::Store;
use strata_types::BrickId;

#[derive(Default)]
struct Counts {
    /// Chunk requests held while stalled.
    stalled: AtomicU64,
    /// Held requests whose client closed the connection before the answer.
    hung_up: AtomicU64,
    /// Held requests answered in full after the release.
    finished_after_release: AtomicU64,
}

struct StallingServer {
    port: u16,
    stall: Arc<AtomicBool>,
    counts: Arc<Counts>,
}

impl StallingServer {
    fn start(root: PathBuf) -> StallingServer {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let stall = Arc::new(AtomicBool::new(false));
        let counts = Arc::new(Counts::default());
        let (s, c) = (stall.clone(), counts.clone());
        std::thread::Builder::new()
            .name("stalling-http-accept".into())
            .spawn(move || {
                for stream in listener.incoming().flatten() {
                    let (root, s, c) = (root.clone(), s.clone(), c.clone());
                    let _ = std::thread::Builder::new()
                        .name("stalling-http-conn".into())
                        .spawn(move || serve_connection(stream, &root, &s, &c));
                }
            })
            .unwrap();
        StallingServer {
            port,
            stall,
            counts,
        }
    }
}

/// Answers requests on one keep-alive connection until the client closes it.
fn serve_connection(mut stream: TcpStream, root: &Path, stall: &AtomicBool, counts: &Counts) {
    let mut buffer = Vec::new();
    loop {
        let end = loop {
            if let Some(end) = buffer.windows(4).position(|w| w == b"\r\n\r\n") {
                break end;
            }
            let mut chunk = [0u8; 4096];
            match stream.read(&mut chunk) {
                Ok(0) | Err(_) => return,
                Ok(n) => buffer.extend_from_slice(&chunk[..n]),
            }
        };
        let head = String::from_utf8_lossy(&buffer[..end]).into_owned();
        buffer.drain(..end + 4);
        let mut lines = head.lines();
        let mut request = lines.next().unwrap_or("").split(' ');
        let (method, target) = (request.next().unwrap_or(""), request.next().unwrap_or(""));
        let range = lines
            .filter_map(|l| l.split_once(':'))
            .find(|(k, _)| k.eq_ignore_ascii_case("range"))
            .map(|(_, v)| v.trim().to_string());
        let path = root.join(target.trim_start_matches('/'));
        let Ok(bytes) = std::fs::read(&path) else {
            let _ = stream.write_all(b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\n\r\n");
            continue;
        };
        let size = bytes.len() as u64;
        if method == "HEAD" {
            let _ = write!(stream, "HTTP/1.1 200 OK\r\nContent-Length: {size}\r\n\r\n");
            continue;
        }
        let held = stall.load(Ordering::SeqCst) && target.contains("/c/");
        if held {
            counts.stalled.fetch_add(1, Ordering::SeqCst);
            // Hold the answer; a read of 0 bytes means the client hung up.
            stream
                .set_read_timeout(Some(Duration::from_millis(20)))
                .unwrap();
            loop {
                if !stall.load(Ordering::SeqCst) {
                    break;
                }
                let mut probe = [0u8; 1];
                match stream.read(&mut probe) {
                    Ok(0) => {
                        counts.hung_up.fetch_add(1, Ordering::SeqCst);
                        return;
                    }
                    Ok(_) => {}
                    Err(e)
                        if matches!(
                            e.kind(),
                            std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                        ) => {}
                    Err(_) => {
                        counts.hung_up.fetch_add(1, Ordering::SeqCst);
                        return;
                    }
                }
            }
            stream.set_read_timeout(None).unwrap();
        }
        let (start, end) = match range.as_deref().and_then(|r| r.strip_prefix("bytes=")) {
            Some(r) => match r.split_once('-') {
                Some(("", n)) => (size - n.parse::<u64>().unwrap().min(size), size),
                Some((a, "")) => (a.parse().unwrap(), size),
                Some((a, b)) => (a.parse().unwrap(), b.parse::<u64>().unwrap() + 1),
                None => (0, size),
            },
            None => (0, size),
        };
        let end = end.min(size);
        let body = &bytes[start as usize..end as usize];
        let status = if range.is_some() {
            format!(
                "HTTP/1.1 206 Partial Content\r\nContent-Range: bytes {start}-{}/{size}\r\n",
                end - 1
            )
        } else {
            "HTTP/1.1 200 OK\r\n".to_string()
        };
        let sent = write!(stream, "{status}Content-Length: {}\r\n\r\n", body.len())
            .and_then(|_| stream.write_all(body));
        if held && sent.is_ok() {
            counts.finished_after_release.fetch_add(1, Ordering::SeqCst);
        }
    }
}

/// Polls `done` every 20 ms for at most 20 s (a bound on a wait, not a timing assertion).
fn wait_for(what: &str, mut done: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while !done() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn stale_requests_are_aborted_on_the_wire_and_wanted_ones_finish() {
    let work = tempfile::tempdir().unwrap();
    let store_path = work.path().join("p.strata");
    Phantom { size: [96, 96, 64] }
        .write_store(&store_path, &ImportOptions::default())
        .unwrap();
    let store = Store::open(&store_path).unwrap();
    let zarr = work.path().join("x.ome.zarr");
    let options = ObjectStoreOptions::default();
    export(
        &store,
        &ObjectLocation::open(zarr.to_str().unwrap(), &options, true).unwrap(),
        &ExportOptions::default(),
        &|_, _| {},
    )
    .unwrap();
    let server = StallingServer::start(work.path().to_path_buf());
    let url = format!("http://127.0.0.1:{}/x.ome.zarr", server.port);
    let source = OmeZarrSource::open(ObjectLocation::open(&url, &options, false).unwrap()).unwrap();
    let fetch_options = FetchOptions {
        max_queued: 64,
        max_in_transit: 16,
        threads: 1,
    };
    let level0: Vec<(BrickId, f64)> = (0..3u32)
        .flat_map(|x| (0..3u32).map(move |y| (BrickId::new(0, [x, y, 0]), f64::from(x + y))))
        .collect();

    // Cancelled: the view asks for nine bricks, then (twice: one view of grace) for nothing.
    server.stall.store(true, Ordering::SeqCst);
    let fetcher = source.start_fetching(fetch_options).unwrap().unwrap();
    fetcher.set_requests(&level0, &[]);
    wait_for("the first held request", || {
        server.counts.stalled.load(Ordering::SeqCst) > 0
    });
    std::thread::sleep(Duration::from_millis(200));
    fetcher.set_requests(&[], &[]);
    fetcher.set_requests(&[], &[]);
    assert_eq!(fetcher.counters().cancelled_in_flight, level0.len() as u64);
    let stalled = server.counts.stalled.load(Ordering::SeqCst);
    wait_for("the client to hang up every held request", || {
        server.counts.hung_up.load(Ordering::SeqCst) == stalled
    });
    server.stall.store(false, Ordering::SeqCst);
    std::thread::sleep(Duration::from_millis(200));
    assert_eq!(
        server.counts.finished_after_release.load(Ordering::SeqCst),
        0,
        "requests the loader no longer wanted were answered in full"
    );
    assert!(fetcher.try_results().is_empty());
    println!("cancelled: {stalled} held requests, all hung up by the client");
    drop(fetcher);

    // The control: held, then released while still wanted: answered in full and delivered,
    // the same bricks as the blocking reader assembles.
    let before = server.counts.stalled.load(Ordering::SeqCst);
    server.stall.store(true, Ordering::SeqCst);
    let fetcher = source.start_fetching(fetch_options).unwrap().unwrap();
    let wanted: Vec<(BrickId, f64)> = (0..3u32)
        .map(|x| (BrickId::new(0, [x, 2, 1]), f64::from(x)))
        .collect();
    fetcher.set_requests(&wanted, &[]);
    wait_for("a held request", || {
        server.counts.stalled.load(Ordering::SeqCst) > before
    });
    std::thread::sleep(Duration::from_millis(200));
    fetcher.set_requests(&wanted, &[]);
    server.stall.store(false, Ordering::SeqCst);
    let mut results = Vec::new();
    wait_for("the wanted bricks", || {
        results.extend(fetcher.try_results());
        results.len() == wanted.len()
    });
    assert!(server.counts.finished_after_release.load(Ordering::SeqCst) > 0);
    assert_eq!(fetcher.counters().cancelled_in_flight, 0);
    for result in results {
        let brick = result.outcome.unwrap();
        assert!(
            *brick == store.read_brick(result.id).unwrap(),
            "{:?} differs from the store's",
            result.id
        );
        fetcher.complete(result.id);
    }
}

/// Every brick through the request tasks at once (64 in flight, their aprons sharing chunks):
/// a chunk another task is already fetching is waited for, not fetched again, so the bytes
/// read stay within the 1.3 × the chunks needed, as with one brick at a time.
#[test]
fn concurrent_requests_fetch_each_chunk_about_once() {
    let work = tempfile::tempdir().unwrap();
    let store_path = work.path().join("p.strata");
    Phantom {
        size: [160, 128, 96],
    }
    .write_store(&store_path, &ImportOptions::default())
    .unwrap();
    let store = Store::open(&store_path).unwrap();
    let zarr = work.path().join("x.ome.zarr");
    let options = ObjectStoreOptions::default();
    export(
        &store,
        &ObjectLocation::open(zarr.to_str().unwrap(), &options, true).unwrap(),
        &ExportOptions::default(),
        &|_, _| {},
    )
    .unwrap();
    let source =
        OmeZarrSource::open(ObjectLocation::open(zarr.to_str().unwrap(), &options, false).unwrap())
            .unwrap();
    let fetcher = source
        .start_fetching(FetchOptions {
            max_queued: 4096,
            max_in_transit: 64,
            threads: 1,
        })
        .unwrap()
        .unwrap();
    let layout = store.layout().clone();
    let mut all = Vec::new();
    for level in 0..layout.level_count() {
        let n = layout.bricks_in_level(level);
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    all.push((BrickId::new(level as u8, [x, y, z]), -(level as f64)));
                }
            }
        }
    }
    let mut done = 0;
    wait_for("every brick", || {
        fetcher.set_requests(&all, &[]);
        for result in fetcher.try_results() {
            let brick = result.outcome.unwrap();
            assert!(
                *brick == store.read_brick(result.id).unwrap(),
                "{:?}",
                result.id
            );
            fetcher.complete(result.id);
            all.retain(|(id, _)| *id != result.id);
            done += 1;
        }
        all.is_empty()
    });
    assert!(fetcher.counters().max_in_flight > 8);
    let counters = source.transfer_counters();
    let (bytes, requests) = (counters.bytes(), counters.requests());
    let needed = source.needed_chunk_bytes().unwrap();
    println!(
        "{done} bricks: {requests} requests, {bytes} bytes for {needed} bytes of chunks needed"
    );
    assert!(
        bytes as f64 <= 1.3 * needed as f64,
        "{bytes} bytes read for {needed} bytes of chunks needed"
    );
}
