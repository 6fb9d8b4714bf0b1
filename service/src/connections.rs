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
//! Idleness alone is not enough to close an HTTP/1 connection: its client may have sent the
//! next request a moment ago (the keep-alive race; issue 49 under load: 8 714 failed client
//! requests in 3 s). So a connection is evicted outright only once idle for a minimum time
//! (`ServeOptions::evict_idle_after`, 1 s); when none is, a newcomer waits and asks one connection of
//! the pool per waiting newcomer to step aside: its next answer carries `Connection: close`
//! (HTTP/2: a GOAWAY), so its client rotates cleanly, and its place goes to a waiting one.
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

use std::collections::{HashMap, HashSet};
use std::net::IpAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::sync::Notify;

/// Which pool a connection is counted in for the per-address cap.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
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

    /// Idle for at least `min_idle` (as of `now_ms`): closing it now cannot cross a request
    /// the client has just sent, except one sent after so long a pause, which clients retry.
    fn idle_for(&self, now_ms: u64, min_idle_ms: u64) -> bool {
        self.is_idle()
            && now_ms.saturating_sub(self.last_active_ms.load(Ordering::Relaxed)) >= min_idle_ms
    }

    fn ask_to_close(&self) {
        self.closing.store(true, Ordering::Release);
        // notify_one keeps a permit when the task is not waiting yet, so the ask is never lost.
        self.shed.notify_one();
    }
}

/// The registry's state behind its lock.
#[derive(Default)]
struct Live {
    /// Connections admitted and not yet closed, nor evicted (an evicted one closes at once;
    /// one asked to step aside stays here, `closing`, until its last answer is sent).
    conns: Vec<Arc<Shared>>,
    /// Connections waiting for a place, by pool (each may have asked one to step aside).
    waiting: HashMap<Pool, usize>,
}

pub(crate) struct Connections {
    started: Instant,
    max_total: usize,
    max_per_address: usize,
    /// How long a connection must have been idle to be closed outright (see [`Self::new`]).
    min_idle_ms: u64,
    trusted_proxies: HashSet<IpAddr>,
    live: Mutex<Live>,
    next_id: AtomicU64,
    /// Notified (all waiters) when a connection closes or turns idle: a waiting one retries.
    freed: Notify,
    waiting: AtomicUsize,
    /// Notified (all waiters) when a waiting connection leaves the waiting room.
    room: Notify,
}

/// Why a connection was not admitted.
#[derive(Debug, PartialEq)]
pub(crate) enum Refused {
    /// Every connection (of the address, or in all) has a request in flight or was active
    /// too recently to be closed.
    AllBusy,
    /// All busy, and twice as many connections are already waiting as the global cap.
    WaitingRoomFull,
    /// All busy for the whole wait.
    WaitedTooLong,
}

/// An admitted connection; dropping it frees its place.
pub(crate) struct Admitted {
    shared: Arc<Shared>,
    registry: Arc<Connections>,
    /// Whether admitting it evicted another connection, or asked one to step aside.
    pub(crate) shed_one: bool,
}

/// Whether a connection asked to close may close now.
#[derive(Debug, PartialEq)]
pub(crate) enum MayClose {
    /// Not asked to close.
    No,
    /// HTTP/2 (a GOAWAY loses nothing), or HTTP/1 idle for the minimum time.
    Now,
    /// HTTP/1 idle for a moment only: its client may be sending the next request right now
    /// (closing would lose it). Look again after this long; a request arriving meanwhile is
    /// answered with `Connection: close` instead.
    After(Duration),
    /// A request in flight: its answer says `Connection: close`; its end notifies again.
    Busy,
}

impl Connections {
    /// `min_idle`: an idle connection is evicted outright only after this long without a
    /// request (issue 49: evicting one idle for a moment closed it while its client's next
    /// request was already on the wire, and the client saw a reset). A connection active
    /// more recently is asked to step aside instead: its next answer carries
    /// `Connection: close` (HTTP/1) or it gets a GOAWAY (HTTP/2), and the newcomer waits.
    pub(crate) fn new(
        max_total: usize,
        max_per_address: usize,
        trusted_proxies: impl IntoIterator<Item = IpAddr>,
        min_idle: Duration,
    ) -> Arc<Self> {
        let max_total = max_total.max(1);
        Arc::new(Connections {
            started: Instant::now(),
            max_total,
            max_per_address: max_per_address.clamp(1, max_total),
            min_idle_ms: min_idle.as_millis() as u64,
            trusted_proxies: trusted_proxies.into_iter().collect(),
            live: Mutex::new(Live::default()),
            next_id: AtomicU64::new(0),
            freed: Notify::new(),
            waiting: AtomicUsize::new(0),
            room: Notify::new(),
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

    fn lock(&self) -> MutexGuard<'_, Live> {
        self.live.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Admits a connection from `address`, evicting the longest-idle one where a cap is
    /// reached; refuses it when none has been idle for the minimum time.
    pub(crate) fn admit(self: &Arc<Self>, address: IpAddr) -> Result<Admitted, Refused> {
        let pool = self.pool(address);
        let mut live = self.lock();
        self.admit_locked(&mut live, pool, &mut false)
    }

    /// `asked` is set when a connection was asked to step aside for this one.
    fn admit_locked(
        self: &Arc<Self>,
        live: &mut Live,
        pool: Pool,
        asked: &mut bool,
    ) -> Result<Admitted, Refused> {
        let now = self.now_ms();
        let mut shed_one = false;
        if let Pool::Direct(_) = pool {
            let from_address = live.conns.iter().filter(|c| c.pool == pool).count();
            if from_address >= self.max_per_address {
                if !self.evict_oldest_idle(&mut live.conns, now, |c| c.pool == pool) {
                    let waiting = live.waiting.get(&pool).copied().unwrap_or(0);
                    *asked |= step_aside(&live.conns, waiting, |c| c.pool == pool);
                    return Err(Refused::AllBusy);
                }
                shed_one = true;
            }
        }
        if live.conns.len() >= self.max_total {
            if !self.evict_oldest_idle(&mut live.conns, now, |_| true) {
                let waiting = live.waiting.values().sum();
                *asked |= step_aside(&live.conns, waiting, |_| true);
                return Err(Refused::AllBusy);
            }
            shed_one = true;
        }
        let shared = Arc::new(Shared {
            id: self.next_id.fetch_add(1, Ordering::Relaxed),
            pool,
            in_flight: AtomicUsize::new(0),
            read_pending: AtomicBool::new(false),
            http2: AtomicBool::new(false),
            closing: AtomicBool::new(false),
            last_active_ms: AtomicU64::new(now),
            shed: Notify::new(),
        });
        live.conns.push(shared.clone());
        Ok(Admitted {
            shared,
            registry: self.clone(),
            shed_one,
        })
    }

    /// [`Self::admit`], but when no connection can be evicted the new one waits (unread: the
    /// client sees latency, not a reset) until one closes or turns idle, at most `wait`.
    /// Meanwhile as many connections of the pool as are waiting are asked to step aside
    /// (`Connection: close` on their next answer, or GOAWAY), so the waiting ones get places
    /// without a request being cut.
    pub(crate) async fn admit_waiting(
        self: &Arc<Self>,
        address: IpAddr,
        wait: Duration,
    ) -> Result<Admitted, Refused> {
        match self.admit(address) {
            Err(Refused::AllBusy) => {}
            other => return other,
        }
        if self.waiting.fetch_add(1, Ordering::AcqRel) >= 2 * self.max_total {
            self.waiting.fetch_sub(1, Ordering::AcqRel);
            return Err(Refused::WaitingRoomFull);
        }
        let pool = self.pool(address);
        *self.lock().waiting.entry(pool).or_default() += 1;
        let deadline = tokio::time::Instant::now() + wait;
        let mut asked = false;
        let outcome = loop {
            // Registered before the retry, so a place freed in between is not missed.
            let freed = self.freed.notified();
            tokio::pin!(freed);
            freed.as_mut().enable();
            let admitted = {
                let mut live = self.lock();
                match self.admit_locked(&mut live, pool, &mut asked) {
                    Ok(mut a) => {
                        a.shed_one |= asked;
                        Ok(a)
                    }
                    other => other,
                }
            };
            match admitted {
                Err(Refused::AllBusy) => {}
                other => break other,
            }
            if tokio::time::timeout_at(deadline, freed).await.is_err() {
                break Err(Refused::WaitedTooLong);
            }
        };
        {
            let mut live = self.lock();
            if let Some(n) = live.waiting.get_mut(&pool) {
                *n -= 1;
                if *n == 0 {
                    live.waiting.remove(&pool);
                }
            }
        }
        self.waiting.fetch_sub(1, Ordering::AcqRel);
        self.room.notify_waiters();
        outcome
    }

    /// Resolves when fewer connections wait for a place than the global cap: the server
    /// accepts no more meanwhile (backpressure: new ones wait in the kernel's backlog, and
    /// the waiting room's bound, twice the cap, is not reached by connections accepted
    /// before the pause).
    pub(crate) async fn room_to_wait(&self) {
        loop {
            let room = self.room.notified();
            tokio::pin!(room);
            room.as_mut().enable();
            if self.waiting.load(Ordering::Acquire) < self.max_total {
                return;
            }
            room.await;
        }
    }

    /// Connections admitted and not yet closed or evicted.
    pub(crate) fn live(&self) -> usize {
        self.lock().conns.len()
    }

    /// Removes and asks to close the connection idle longest (for at least the minimum)
    /// among those `which` selects; false when there is none. Linear in the connections.
    fn evict_oldest_idle(
        &self,
        conns: &mut Vec<Arc<Shared>>,
        now: u64,
        which: impl Fn(&Shared) -> bool,
    ) -> bool {
        let Some((at, _)) = conns
            .iter()
            .enumerate()
            // One asked to step aside already counts too: its task would close it anyway.
            .filter(|(_, c)| which(c) && c.idle_for(now, self.min_idle_ms))
            .min_by_key(|(_, c)| c.last_active_ms.load(Ordering::Relaxed))
        else {
            return false;
        };
        conns.swap_remove(at).ask_to_close();
        true
    }
}

/// Asks one more connection among those `which` selects to step aside, unless as many are
/// closing already as connections wait: an HTTP/1 one before an HTTP/2 one (a client of many
/// streams loses more by reconnecting), the oldest first (so the places rotate).
fn step_aside(conns: &[Arc<Shared>], waiting: usize, which: impl Fn(&Shared) -> bool) -> bool {
    let mut closing = 0;
    let mut candidate: Option<&Arc<Shared>> = None;
    for c in conns.iter().filter(|c| which(c)) {
        if c.closing.load(Ordering::Acquire) {
            closing += 1;
        } else {
            let key = |c: &Shared| (c.http2.load(Ordering::Acquire), c.id);
            if candidate.is_none_or(|b| key(c) < key(b)) {
                candidate = Some(c);
            }
        }
    }
    match candidate {
        Some(c) if closing < waiting => {
            c.ask_to_close();
            true
        }
        _ => false,
    }
}

impl Admitted {
    /// Resolves when the connection is asked to close (to make room for another), and again
    /// when a request ends on it afterwards.
    pub(crate) async fn shed(&self) {
        self.shared.shed.notified().await
    }

    /// Whether the connection, asked to close, may close now without losing a request.
    pub(crate) fn may_close(&self) -> MayClose {
        let s = &self.shared;
        if !s.closing.load(Ordering::Acquire) {
            return MayClose::No;
        }
        if s.http2.load(Ordering::Acquire) {
            return MayClose::Now;
        }
        if !s.is_idle() {
            return MayClose::Busy;
        }
        let idle = self
            .registry
            .now_ms()
            .saturating_sub(s.last_active_ms.load(Ordering::Relaxed));
        match self.registry.min_idle_ms.checked_sub(idle) {
            Some(left) if left > 0 => MayClose::After(Duration::from_millis(left)),
            _ => MayClose::Now,
        }
    }

    /// Whether it was asked to close (evicted, or asked to step aside).
    pub(crate) fn asked_to_close(&self) -> bool {
        self.shared.closing.load(Ordering::Acquire)
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
            let mut live = self.registry.lock();
            if let Some(at) = live.conns.iter().position(|c| c.id == self.shared.id) {
                live.conns.swap_remove(at);
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
        let c = Connections::new(10, 2, [], Duration::ZERO);
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
        let c = Connections::new(3, 3, [], Duration::ZERO);
        let a = c.admit(ip(1)).unwrap();
        std::thread::sleep(Duration::from_millis(5));
        let b = c.admit(ip(2)).unwrap();
        let d = c.admit(ip(3)).unwrap();
        // `a` was active most recently after b and d were admitted: b is now the oldest idle.
        std::thread::sleep(Duration::from_millis(5));
        drop(a.handle().request());
        let e = c.admit(ip(4)).unwrap();
        assert!(e.shed_one);
        let live: Vec<u64> = c.lock().conns.iter().map(|s| s.id).collect();
        assert!(!live.contains(&b.shared.id), "{live:?}");
        assert!(live.contains(&a.shared.id) && live.contains(&d.shared.id));
    }

    #[test]
    fn a_connection_with_request_bytes_unparsed_or_a_body_unsent_is_not_evicted() {
        let c = Connections::new(10, 1, [], Duration::ZERO);
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
        let c = Connections::new(6, 2, [proxy], Duration::ZERO);
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
            let c = Connections::new(1, 1, [], Duration::ZERO);
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

    #[test]
    fn a_connection_active_a_moment_ago_is_asked_to_step_aside_not_closed() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .unwrap();
        runtime.block_on(async {
            // An hour of minimum idle: nothing here is ever idle long enough to be evicted.
            let c = Connections::new(10, 2, [], Duration::from_secs(3600));
            let first = c.admit(ip(1)).unwrap();
            let second = c.admit(ip(1)).unwrap();
            second.handle().set_http2();
            drop(first.handle().request());
            // Idle a moment only: a plain admission is refused, nobody is asked to close.
            assert_eq!(c.admit(ip(1)).err(), Some(Refused::AllBusy));
            assert_eq!(first.may_close(), MayClose::No);
            // A waiting one asks one (HTTP/1 before HTTP/2) to step aside: it is not closed
            // at once (its client may be sending) but answers its next request with
            // `Connection: close`; busy meanwhile, it may close only after that answer.
            let waiting = c.admit_waiting(ip(1), Duration::from_secs(5));
            let rotate = async {
                tokio::task::yield_now().await;
                assert!(first.handle().closing());
                assert!(!second.handle().closing());
                assert!(matches!(first.may_close(), MayClose::After(_)));
                let guard = first.handle().request();
                assert_eq!(first.may_close(), MayClose::Busy);
                drop(guard);
                drop(first);
            };
            let (admitted, ()) = tokio::join!(waiting, rotate);
            let third = admitted.unwrap();
            assert!(third.shed_one);
            assert_eq!(c.live(), 2);
            // HTTP/2 closes by GOAWAY at any moment once asked.
            let fourth = c.admit_waiting(ip(1), Duration::from_millis(20));
            assert_eq!(fourth.await.err(), Some(Refused::WaitedTooLong));
            assert!(second.handle().closing() || third.handle().closing());
            drop(third);
            drop(second);
        });
    }
}
