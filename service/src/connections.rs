//! The server's live connections: a global cap, a cap per client address below it, and
//! eviction of the connection idle longest when a cap is reached, so that sockets which send
//! nothing cannot deny service to clients that do.
//!
//! A connection is idle only while it has no request in flight (from its head being parsed
//! until its response body is sent or dropped) and no request bytes read but not yet parsed
//! (a partial head, or the bytes of a new connection before protocol detection). Issue 49:
//! the earlier registry counted a request busy only while its handler ran, so a connection
//! was "idle" while its response body was still being written and while its next keep-alive
//! request was arriving, and an eviction then dropped the whole connection with those
//! requests in it: 139 168 of 223 934 requests under load were started and never answered.
//!
//! An evicted connection is not dropped but closed gracefully by its task (see
//! `server.rs`): HTTP/2 gets a GOAWAY naming the last stream processed (every request
//! already received is answered); an HTTP/1 connection that is idle is closed between
//! requests, and one that turns out busy answers what it has with `Connection: close` and
//! closes after it. When every connection (of the address, or in all) is busy, a new one is
//! not refused at once but waits, unread, for a place ([`Connections::admit_waiting`]): the
//! client sees latency (backpressure), not a reset. Only when the waiting room is full too
//! (as many waiting as the global cap), or the wait exceeds its bound, is it closed.
//!
//! Connections from a trusted reverse proxy (`--trusted-proxy`) carry many clients over one
//! address: they are a pool of their own, limited by the global cap only, never by the
//! per-address cap meant for direct clients.

use std::collections::HashSet;
use std::net::IpAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::Notify;

/// Which pool a connection is counted in for the per-address cap.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Pool {
    Direct(IpAddr),
    /// A trusted proxy: only the global cap applies.
    Proxy,
}

/// What one admitted connection shares with the registry.
struct Shared {
    id: u64,
    pool: Pool,
    /// Requests in flight on the connection (head parsed, response body not yet finished).
    in_flight: AtomicUsize,
    /// Bytes were read that no request has claimed yet (a head being received).
    read_pending: AtomicBool,
    /// HTTP/2: a GOAWAY closes it safely at any moment, so pending bytes do not make it busy.
    http2: AtomicBool,
    /// Asked to close: HTTP/1 responses carry `Connection: close` from now on.
    closing: AtomicBool,
    /// Milliseconds since the registry started at the last request start or end (accept time
    /// before the first): the idle connection with the smallest is evicted first.
    last_active_ms: AtomicU64,
    /// Notified when the connection is asked to close (and again when a request ends on a
    /// closing connection); its task then closes it gracefully once it is idle.
    shed: Notify,
}

impl Shared {
    fn is_idle(&self) -> bool {
        self.in_flight.load(Ordering::Acquire) == 0
            && (self.http2.load(Ordering::Acquire) || !self.read_pending.load(Ordering::Acquire))
    }
}

pub(crate) struct Connections {
    started: Instant,
    max_total: usize,
    max_per_address: usize,
    trusted_proxies: HashSet<IpAddr>,
    live: Mutex<Vec<Arc<Shared>>>,
    next_id: AtomicU64,
    /// Notified (all waiters) when a connection closes or turns idle: a waiting one retries.
    freed: Notify,
    waiting: AtomicUsize,
}

/// Why a connection was not admitted.
#[derive(Debug, PartialEq)]
pub(crate) enum Refused {
    /// Every connection (of the address, or in all) has a request in flight.
    AllBusy,
    /// All busy, and as many connections are already waiting as the global cap.
    WaitingRoomFull,
    /// All busy for the whole wait.
    WaitedTooLong,
}

/// An admitted connection; dropping it frees its place.
pub(crate) struct Admitted {
    shared: Arc<Shared>,
    registry: Arc<Connections>,
    /// Whether admitting it asked another connection to close.
    pub(crate) shed_one: bool,
}

impl Connections {
    pub(crate) fn new(
        max_total: usize,
        max_per_address: usize,
        trusted_proxies: impl IntoIterator<Item = IpAddr>,
    ) -> Arc<Self> {
        let max_total = max_total.max(1);
        Arc::new(Connections {
            started: Instant::now(),
            max_total,
            max_per_address: max_per_address.clamp(1, max_total),
            trusted_proxies: trusted_proxies.into_iter().collect(),
            live: Mutex::new(Vec::new()),
            next_id: AtomicU64::new(0),
            freed: Notify::new(),
            waiting: AtomicUsize::new(0),
        })
    }

    fn now_ms(&self) -> u64 {
        self.started.elapsed().as_millis() as u64
    }

    fn pool(&self, address: IpAddr) -> Pool {
        if self.trusted_proxies.contains(&address) {
            Pool::Proxy
        } else {
            Pool::Direct(address)
        }
    }

    /// Admits a connection from `address`, asking the longest-idle one to close where a cap
    /// is reached.
    pub(crate) fn admit(self: &Arc<Self>, address: IpAddr) -> Result<Admitted, Refused> {
        let pool = self.pool(address);
        let mut live = self.live.lock().unwrap_or_else(|p| p.into_inner());
        let mut shed_one = false;
        if let Pool::Direct(_) = pool {
            let from_address = live.iter().filter(|c| c.pool == pool).count();
            if from_address >= self.max_per_address {
                shed_oldest_idle(&mut live, |c| c.pool == pool).ok_or(Refused::AllBusy)?;
                shed_one = true;
            }
        }
        if live.len() >= self.max_total {
            shed_oldest_idle(&mut live, |_| true).ok_or(Refused::AllBusy)?;
            shed_one = true;
        }
        let shared = Arc::new(Shared {
            id: self.next_id.fetch_add(1, Ordering::Relaxed),
            pool,
            in_flight: AtomicUsize::new(0),
            read_pending: AtomicBool::new(false),
            http2: AtomicBool::new(false),
            closing: AtomicBool::new(false),
            last_active_ms: AtomicU64::new(self.now_ms()),
            shed: Notify::new(),
        });
        live.push(shared.clone());
        Ok(Admitted {
            shared,
            registry: self.clone(),
            shed_one,
        })
    }

    /// [`Self::admit`], but when every connection is busy the new one waits (unread: the
    /// client sees latency, not a reset) until one closes or turns idle, at most `wait`.
    pub(crate) async fn admit_waiting(
        self: &Arc<Self>,
        address: IpAddr,
        wait: Duration,
    ) -> Result<Admitted, Refused> {
        match self.admit(address) {
            Err(Refused::AllBusy) => {}
            other => return other,
        }
        if self.waiting.fetch_add(1, Ordering::AcqRel) >= self.max_total {
            self.waiting.fetch_sub(1, Ordering::AcqRel);
            return Err(Refused::WaitingRoomFull);
        }
        let deadline = tokio::time::Instant::now() + wait;
        let outcome = loop {
            // Registered before the retry, so a place freed in between is not missed.
            let freed = self.freed.notified();
            tokio::pin!(freed);
            freed.as_mut().enable();
            match self.admit(address) {
                Err(Refused::AllBusy) => {}
                other => break other,
            }
            if tokio::time::timeout_at(deadline, freed).await.is_err() {
                break Err(Refused::WaitedTooLong);
            }
        };
        self.waiting.fetch_sub(1, Ordering::AcqRel);
        outcome
    }

    /// Connections admitted and not yet closed or asked to close.
    pub(crate) fn live(&self) -> usize {
        self.live.lock().unwrap_or_else(|p| p.into_inner()).len()
    }
}

/// Removes, marks closing and notifies the idle connection with the oldest activity among
/// those `which` selects; `None` when all of them are busy. Linear in the connections (at
/// most the cap).
fn shed_oldest_idle(live: &mut Vec<Arc<Shared>>, which: impl Fn(&Shared) -> bool) -> Option<()> {
    let (at, _) = live
        .iter()
        .enumerate()
        .filter(|(_, c)| which(c) && c.is_idle())
        .min_by_key(|(_, c)| c.last_active_ms.load(Ordering::Relaxed))?;
    let victim = live.swap_remove(at);
    victim.closing.store(true, Ordering::Release);
    // notify_one keeps a permit when the task is not waiting yet, so the request is never lost.
    victim.shed.notify_one();
    Some(())
}

impl Admitted {
    /// Resolves when the connection is asked to close (to make room for another), and again
    /// when a request ends on it afterwards.
    pub(crate) async fn shed(&self) {
        self.shared.shed.notified().await
    }

    /// Whether the connection may be closed now without losing a request: nothing in flight,
    /// nothing read and unparsed (HTTP/2 closes by GOAWAY, which loses nothing).
    pub(crate) fn is_idle(&self) -> bool {
        self.shared.is_idle()
    }

    pub(crate) fn is_http2(&self) -> bool {
        self.shared.http2.load(Ordering::Acquire)
    }

    /// A handle the connection's request service and its IO can hold (`Clone + Send`).
    pub(crate) fn handle(&self) -> ConnectionHandle {
        ConnectionHandle {
            shared: self.shared.clone(),
            registry: self.registry.clone(),
        }
    }
}

impl Drop for Admitted {
    fn drop(&mut self) {
        {
            let mut live = self.registry.live.lock().unwrap_or_else(|p| p.into_inner());
            if let Some(at) = live.iter().position(|c| c.id == self.shared.id) {
                live.swap_remove(at);
            }
        }
        self.registry.freed.notify_waiters();
    }
}

/// What the connection's request service and IO wrapper report through.
#[derive(Clone)]
pub(crate) struct ConnectionHandle {
    shared: Arc<Shared>,
    registry: Arc<Connections>,
}

impl ConnectionHandle {
    /// A request's head was parsed: busy until the guard (held by its response body) drops.
    pub(crate) fn request(&self) -> RequestGuard {
        self.shared.in_flight.fetch_add(1, Ordering::AcqRel);
        // Its bytes are claimed. (A pipelined head read with it is parsed by hyper in the
        // same poll that ends this response, before the task can act on an eviction.)
        self.shared.read_pending.store(false, Ordering::Release);
        self.shared
            .last_active_ms
            .store(self.registry.now_ms(), Ordering::Relaxed);
        RequestGuard {
            shared: self.shared.clone(),
            registry: self.registry.clone(),
        }
    }

    /// Bytes came in from the client: busy until a request claims them.
    pub(crate) fn bytes_read(&self) {
        self.shared.read_pending.store(true, Ordering::Release);
    }

    pub(crate) fn set_http2(&self) {
        self.shared.http2.store(true, Ordering::Release);
    }

    /// Asked to close: an HTTP/1 response should say `Connection: close`.
    pub(crate) fn closing(&self) -> bool {
        self.shared.closing.load(Ordering::Acquire)
    }
}

/// A request in flight; its drop makes the connection idle again (as of now).
pub(crate) struct RequestGuard {
    shared: Arc<Shared>,
    registry: Arc<Connections>,
}

impl Drop for RequestGuard {
    fn drop(&mut self) {
        self.shared
            .last_active_ms
            .store(self.registry.now_ms(), Ordering::Relaxed);
        if self.shared.in_flight.fetch_sub(1, Ordering::AcqRel) == 1 {
            // Idle now: a connection waiting for a place may evict this one; a closing one's
            // task looks again whether it can close.
            self.registry.freed.notify_waiters();
            if self.shared.closing.load(Ordering::Acquire) {
                self.shared.shed.notify_one();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(last: u8) -> IpAddr {
        IpAddr::from([10, 0, 0, last])
    }

    #[test]
    fn the_per_address_cap_sheds_that_address_oldest_idle_and_busy_ones_are_kept() {
        let c = Connections::new(10, 2, []);
        let first = c.admit(ip(1)).unwrap();
        let second = c.admit(ip(1)).unwrap();
        let _busy = second.handle().request();
        let other = c.admit(ip(2)).unwrap();
        // A third from .1: the idle first is shed, not the busy second nor .2's.
        let third = c.admit(ip(1)).unwrap();
        assert!(third.shed_one);
        assert_eq!(c.live(), 3);
        let _also_busy = third.handle().request();
        // Both of .1's are busy now: a fourth is refused.
        assert_eq!(c.admit(ip(1)).err(), Some(Refused::AllBusy));
        drop(first);
        drop(other);
        assert_eq!(c.live(), 2);
    }

    #[test]
    fn the_global_cap_sheds_the_longest_idle_of_any_address() {
        let c = Connections::new(3, 3, []);
        let a = c.admit(ip(1)).unwrap();
        std::thread::sleep(Duration::from_millis(5));
        let b = c.admit(ip(2)).unwrap();
        let d = c.admit(ip(3)).unwrap();
        // `a` was active most recently after b and d were admitted: b is now the oldest idle.
        std::thread::sleep(Duration::from_millis(5));
        drop(a.handle().request());
        let e = c.admit(ip(4)).unwrap();
        assert!(e.shed_one);
        let live: Vec<u64> = c.live.lock().unwrap().iter().map(|s| s.id).collect();
        assert!(!live.contains(&b.shared.id), "{live:?}");
        assert!(live.contains(&a.shared.id) && live.contains(&d.shared.id));
    }

    #[test]
    fn a_connection_with_request_bytes_unparsed_or_a_body_unsent_is_not_evicted() {
        let c = Connections::new(10, 1, []);
        let first = c.admit(ip(1)).unwrap();
        // A head arriving: busy.
        first.handle().bytes_read();
        assert_eq!(c.admit(ip(1)).err(), Some(Refused::AllBusy));
        // Parsed and answered (the guard is held by the response body until it is sent).
        let guard = first.handle().request();
        assert_eq!(c.admit(ip(1)).err(), Some(Refused::AllBusy));
        drop(guard);
        // Between requests: evicted, marked closing (HTTP/1 answers then say so).
        let second = c.admit(ip(1)).unwrap();
        assert!(second.shed_one && first.handle().closing());
        // HTTP/2 closes by GOAWAY, which loses nothing: pending bytes do not protect it.
        second.handle().set_http2();
        second.handle().bytes_read();
        assert!(c.admit(ip(1)).unwrap().shed_one);
    }

    #[test]
    fn a_trusted_proxy_is_a_pool_of_its_own_under_the_global_cap_only() {
        let proxy = ip(9);
        let c = Connections::new(6, 2, [proxy]);
        let held: Vec<Admitted> = (0..5).map(|_| c.admit(proxy).unwrap()).collect();
        let guards: Vec<RequestGuard> = held.iter().map(|a| a.handle().request()).collect();
        assert!(held.iter().all(|a| !a.shed_one));
        // A direct client still gets its place; then the global cap holds for all.
        let direct = c.admit(ip(1)).unwrap();
        let _busy = direct.handle().request();
        assert_eq!(c.admit(proxy).err(), Some(Refused::AllBusy));
        drop(guards);
    }

    #[test]
    fn a_new_connection_waits_for_a_place_instead_of_being_refused() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .unwrap();
        runtime.block_on(async {
            let c = Connections::new(1, 1, []);
            let busy = c.admit(ip(1)).unwrap();
            let guard = busy.handle().request();
            // Nothing frees the place: refused after the wait (time is paused-free but short).
            assert_eq!(
                c.admit_waiting(ip(1), Duration::from_millis(50))
                    .await
                    .err(),
                Some(Refused::WaitedTooLong)
            );
            // The request ends meanwhile: admitted, evicting the now idle one.
            let waiting = c.admit_waiting(ip(1), Duration::from_secs(5));
            let end = async move {
                tokio::task::yield_now().await;
                drop(guard);
            };
            let (admitted, ()) = tokio::join!(waiting, end);
            assert!(admitted.unwrap().shed_one);
            drop(busy);
        });
    }
}
