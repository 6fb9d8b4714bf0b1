//! The server's live connections: a global cap, a cap per client address below it, and
//! shedding of the connection idle longest when a cap is reached, so that sockets which send
//! nothing cannot deny service to clients that do.
//!
//! A connection is idle while it has no request in flight (before its first request head, and
//! between keep-alive requests). When a new connection would exceed a cap, the idle connection
//! with the oldest activity (of the same address for the per-address cap, of any address for
//! the global one) is told to close and the new one is admitted; only when every connection is
//! busy is the new one refused. A flood of idle sockets thus only ever displaces idle sockets,
//! while a client that sends its request at once is answered.

use std::net::IpAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use tokio::sync::Notify;

/// What one admitted connection shares with the registry.
struct Shared {
    id: u64,
    address: IpAddr,
    /// Requests in flight on the connection.
    busy: AtomicUsize,
    /// Milliseconds since the registry started at the last request start or end (accept time
    /// before the first): the idle connection with the smallest is shed first.
    last_active_ms: AtomicU64,
    /// Notified once when the connection is shed; its task closes the socket.
    shed: Notify,
}

pub(crate) struct Connections {
    started: Instant,
    max_total: usize,
    max_per_address: usize,
    live: Mutex<Vec<Arc<Shared>>>,
    next_id: AtomicU64,
}

/// Why a connection was not admitted.
#[derive(Debug, PartialEq)]
pub(crate) enum Refused {
    /// Every connection (of the address, or in all) has a request in flight.
    AllBusy,
}

/// An admitted connection; dropping it frees its place.
pub(crate) struct Admitted {
    shared: Arc<Shared>,
    registry: Arc<Connections>,
    /// Whether admitting it shed another connection.
    pub(crate) shed_one: bool,
}

impl Connections {
    pub(crate) fn new(max_total: usize, max_per_address: usize) -> Arc<Self> {
        let max_total = max_total.max(1);
        Arc::new(Connections {
            started: Instant::now(),
            max_total,
            max_per_address: max_per_address.clamp(1, max_total),
            live: Mutex::new(Vec::new()),
            next_id: AtomicU64::new(0),
        })
    }

    fn now_ms(&self) -> u64 {
        self.started.elapsed().as_millis() as u64
    }

    /// Admits a connection from `address`, shedding the longest-idle one where a cap is reached.
    pub(crate) fn admit(self: &Arc<Self>, address: IpAddr) -> Result<Admitted, Refused> {
        let mut live = self.live.lock().unwrap_or_else(|p| p.into_inner());
        let mut shed_one = false;
        let from_address = live.iter().filter(|c| c.address == address).count();
        if from_address >= self.max_per_address {
            shed_oldest_idle(&mut live, |c| c.address == address).ok_or(Refused::AllBusy)?;
            shed_one = true;
        }
        if live.len() >= self.max_total {
            shed_oldest_idle(&mut live, |_| true).ok_or(Refused::AllBusy)?;
            shed_one = true;
        }
        let shared = Arc::new(Shared {
            id: self.next_id.fetch_add(1, Ordering::Relaxed),
            address,
            busy: AtomicUsize::new(0),
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

    /// Connections admitted and not yet closed or shed.
    #[cfg(test)]
    fn live(&self) -> usize {
        self.live.lock().unwrap_or_else(|p| p.into_inner()).len()
    }
}

/// Removes and notifies the idle connection with the oldest activity among those `which`
/// selects; `None` when all of them are busy. Linear in the connections (at most the cap).
fn shed_oldest_idle(live: &mut Vec<Arc<Shared>>, which: impl Fn(&Shared) -> bool) -> Option<()> {
    let (at, _) = live
        .iter()
        .enumerate()
        .filter(|(_, c)| which(c) && c.busy.load(Ordering::Acquire) == 0)
        .min_by_key(|(_, c)| c.last_active_ms.load(Ordering::Relaxed))?;
    let victim = live.swap_remove(at);
    // notify_one keeps a permit when the task is not waiting yet, so the shed is never lost.
    victim.shed.notify_one();
    Some(())
}

impl Admitted {
    /// Resolves when the connection has been shed to make room for another.
    pub(crate) async fn shed(&self) {
        self.shared.shed.notified().await
    }

    /// A handle the connection's request service can hold (it must be `Clone + Send`).
    pub(crate) fn handle(&self) -> ConnectionHandle {
        ConnectionHandle {
            shared: self.shared.clone(),
            registry: self.registry.clone(),
        }
    }
}

impl Drop for Admitted {
    fn drop(&mut self) {
        let mut live = self.registry.live.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(at) = live.iter().position(|c| c.id == self.shared.id) {
            live.swap_remove(at);
        }
    }
}

/// [`Admitted::request`] for the per-request service closure.
#[derive(Clone)]
pub(crate) struct ConnectionHandle {
    shared: Arc<Shared>,
    registry: Arc<Connections>,
}

impl ConnectionHandle {
    pub(crate) fn request(&self) -> RequestGuard {
        self.shared.busy.fetch_add(1, Ordering::AcqRel);
        self.shared
            .last_active_ms
            .store(self.registry.now_ms(), Ordering::Relaxed);
        RequestGuard {
            shared: self.shared.clone(),
            registry: self.registry.clone(),
        }
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
        self.shared.busy.fetch_sub(1, Ordering::AcqRel);
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
        let c = Connections::new(10, 2);
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
        let c = Connections::new(3, 3);
        let a = c.admit(ip(1)).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(5));
        let b = c.admit(ip(2)).unwrap();
        let d = c.admit(ip(3)).unwrap();
        // `a` was active most recently after b and d were admitted: b is now the oldest idle.
        std::thread::sleep(std::time::Duration::from_millis(5));
        drop(a.handle().request());
        let e = c.admit(ip(4)).unwrap();
        assert!(e.shed_one);
        let live: Vec<u64> = c.live.lock().unwrap().iter().map(|s| s.id).collect();
        assert!(!live.contains(&b.shared.id), "{live:?}");
        assert!(live.contains(&a.shared.id) && live.contains(&d.shared.id));
    }
}
