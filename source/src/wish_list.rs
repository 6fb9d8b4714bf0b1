//! The brick request policy, once: what every executor of brick requests (the loader's reader
//! threads and inline reads, the tokio [`TaskQueue`](crate::task_queue::TaskQueue), the
//! browser's `fetch()` queue) decides the same way. No threads, no async, no I/O: an executor
//! holds a [`WishList`] under its own lock and does the reading.
//!
//! The rules:
//! - [`WishList::replace`] replaces the queued wishes with this frame's: demand before
//!   prefetch, then by priority (higher = sooner); at most `capacity` queued, the rest counted
//!   as overflow (the loader asks again next frame if it still wants them); queued wishes the
//!   new list no longer names are counted stale and dropped, so a fast-moving camera cannot
//!   pile up work. A request already started is not queued twice: naming it again marks it
//!   still wanted, it keeps its place and takes none of the capacity.
//! - [`WishList::take_most_urgent`] starts the most urgent queued request (demand first, then
//!   the highest priority) and counts it.
//! - A started request is named by the call that queued it; [`WishList::cancel_unwanted`] ends
//!   those that neither this call nor the previous one names (executors that can stop a
//!   request abort them: a tokio task, a browser `fetch()`). The one call of grace keeps a
//!   request that flickers at the edge of the wish list from being cancelled and asked again.
//! - A started request ends when the loader [`WishList::complete`]s its delivered result, or
//!   when it is cancelled, withdrawn or put back in the queue. [`Ticket`]s tell a late answer
//!   of a request that was cancelled (and perhaps started again) from the current one.
//!
//! Tested by this module's unit tests (order, overflow, stale accounting, grace, tickets) and,
//! through the executors, by the loader's `streaming` and `slow_storage` tests and the data
//! service's and OME-Zarr source's client tests.

use std::collections::HashMap;

use strata_types::BrickId;

use crate::{QueueCounters, RequestClass};

/// One start of a request: a later start of the same brick gets another.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Ticket(u64);

/// A request [`WishList::take_most_urgent`] started.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Started {
    pub id: BrickId,
    pub class: RequestClass,
    pub priority: f64,
    pub ticket: Ticket,
}

struct InFlight {
    /// The `replace` call that last named it.
    named_at: u64,
    /// Its result is on its way to the loader: no longer cancellable, ended by `complete`.
    delivered: bool,
    ticket: Ticket,
}

/// The queued wishes and the started requests of one brick fetcher (see the module comment).
pub struct WishList {
    capacity: usize,
    queued: HashMap<BrickId, (RequestClass, f64)>,
    in_flight: HashMap<BrickId, InFlight>,
    counters: QueueCounters,
    /// `replace` calls so far.
    calls: u64,
    tickets: u64,
}

impl WishList {
    /// A wish list that queues at most `capacity` requests (at least one).
    pub fn new(capacity: usize) -> Self {
        WishList {
            capacity: capacity.max(1),
            queued: HashMap::new(),
            in_flight: HashMap::new(),
            counters: QueueCounters::default(),
            calls: 0,
            tickets: 0,
        }
    }

    /// Replaces the queued wishes with this frame's (demand first, then prefetch; ids must
    /// already exclude what the loader holds). Returns how many did not fit (overflow).
    pub fn replace(&mut self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> u64 {
        self.calls += 1;
        let call = self.calls;
        let mut wanted: HashMap<BrickId, (RequestClass, f64)> = HashMap::new();
        let mut overflow = 0;
        let wishes = demand
            .iter()
            .map(|&(id, priority)| (id, RequestClass::Demand, priority))
            .chain(
                prefetch
                    .iter()
                    .map(|&(id, priority)| (id, RequestClass::Prefetch, priority)),
            );
        for (id, class, priority) in wishes {
            if let Some(started) = self.in_flight.get_mut(&id) {
                started.named_at = call;
                continue;
            }
            if wanted.contains_key(&id) {
                continue;
            }
            if wanted.len() >= self.capacity {
                overflow += 1;
                continue;
            }
            wanted.insert(id, (class, priority));
        }
        let stale = self
            .queued
            .keys()
            .filter(|id| !wanted.contains_key(id))
            .count() as u64;
        self.counters.stale_dropped += stale;
        self.counters.overflow_dropped += overflow;
        self.queued = wanted;
        overflow
    }

    /// Starts the most urgent queued request (demand before prefetch, then by priority) and
    /// counts it; `None` when nothing is queued.
    pub fn take_most_urgent(&mut self) -> Option<Started> {
        let (id, class, priority) = self
            .queued
            .iter()
            .max_by(|a, b| {
                (a.1 .0, a.1 .1)
                    .partial_cmp(&(b.1 .0, b.1 .1))
                    .unwrap_or(std::cmp::Ordering::Equal)
            })
            .map(|(&id, &(class, priority))| (id, class, priority))?;
        self.queued.remove(&id);
        self.tickets += 1;
        let ticket = Ticket(self.tickets);
        self.in_flight.insert(
            id,
            InFlight {
                named_at: self.calls,
                delivered: false,
                ticket,
            },
        );
        self.counters.max_in_flight = self.counters.max_in_flight.max(self.in_flight.len() as u64);
        match class {
            RequestClass::Demand => self.counters.demand_started += 1,
            RequestClass::Prefetch => self.counters.prefetch_started += 1,
        }
        Some(Started {
            id,
            class,
            priority,
            ticket,
        })
    }

    /// The request `ticket` of brick `id` has its result: it goes to the loader. False when
    /// that request was cancelled or withdrawn meanwhile (its answer is to be dropped).
    pub fn deliver(&mut self, id: BrickId, ticket: Ticket) -> bool {
        match self.in_flight.get_mut(&id) {
            Some(started) if started.ticket == ticket && !started.delivered => {
                started.delivered = true;
                true
            }
            _ => false,
        }
    }

    /// Ends the started, undelivered requests that neither this `replace` call nor the
    /// previous one names, counting them cancelled; returns them for the executor to abort.
    pub fn cancel_unwanted(&mut self) -> Vec<(BrickId, Ticket)> {
        let call = self.calls;
        let unwanted: Vec<(BrickId, Ticket)> = self
            .in_flight
            .iter()
            .filter(|(_, started)| !started.delivered && started.named_at + 1 < call)
            .map(|(&id, started)| (id, started.ticket))
            .collect();
        for (id, _) in &unwanted {
            self.in_flight.remove(id);
        }
        self.counters.cancelled_in_flight += unwanted.len() as u64;
        unwanted
    }

    /// The request `ticket` of brick `id` ended without a result (aborted under the executor):
    /// the brick may be queued again. False when it had already ended.
    pub fn withdraw(&mut self, id: BrickId, ticket: Ticket) -> bool {
        match self.in_flight.get(&id) {
            Some(started) if started.ticket == ticket => {
                self.in_flight.remove(&id);
                true
            }
            _ => false,
        }
    }

    /// Puts a started request back in the queue, to be started again in its turn (after a
    /// transient failure, or a record damaged on the way). It was admitted once, so the
    /// capacity does not turn it away.
    pub fn requeue(&mut self, id: BrickId, class: RequestClass, priority: f64) {
        self.in_flight.remove(&id);
        self.queued.insert(id, (class, priority));
    }

    /// The loader has taken the delivered result of `id`: the request ends. False (and nothing
    /// changes) when `id` has no delivered result, e.g. a request started again meanwhile.
    pub fn complete(&mut self, id: BrickId) -> bool {
        match self.in_flight.get(&id) {
            Some(started) if started.delivered => {
                self.in_flight.remove(&id);
                true
            }
            _ => false,
        }
    }

    /// Requests queued, not yet started.
    pub fn queued(&self) -> usize {
        self.queued.len()
    }

    /// Requests started and not yet ended (being fetched, or delivered and not completed).
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    pub fn is_in_flight(&self, id: BrickId) -> bool {
        self.in_flight.contains_key(&id)
    }

    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// What the policy counted (stale, overflow, started, cancelled, most in flight); the
    /// executor adds what only it sees (retries, checksum failures).
    pub fn counters(&self) -> QueueCounters {
        self.counters
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brick(x: u32) -> BrickId {
        BrickId::new(0, [x, 0, 0])
    }

    fn started_order(wishes: &mut WishList) -> Vec<(BrickId, RequestClass)> {
        std::iter::from_fn(|| wishes.take_most_urgent())
            .map(|s| (s.id, s.class))
            .collect()
    }

    #[test]
    fn demand_starts_before_prefetch_and_each_by_priority() {
        let mut wishes = WishList::new(16);
        let prefetch = [(brick(1), 100.0), (brick(2), 50.0)];
        let demand = [(brick(3), 0.5), (brick(4), 2.0), (brick(5), 1.0)];
        assert_eq!(wishes.replace(&demand, &prefetch), 0);
        assert_eq!(wishes.queued(), 5);
        assert_eq!(
            started_order(&mut wishes),
            vec![
                (brick(4), RequestClass::Demand),
                (brick(5), RequestClass::Demand),
                (brick(3), RequestClass::Demand),
                (brick(1), RequestClass::Prefetch),
                (brick(2), RequestClass::Prefetch),
            ]
        );
        let counters = wishes.counters();
        assert_eq!((counters.demand_started, counters.prefetch_started), (3, 2));
        assert_eq!(counters.max_in_flight, 5);
        assert_eq!((wishes.queued(), wishes.in_flight()), (0, 5));
    }

    #[test]
    fn past_the_capacity_wishes_are_counted_as_overflow_in_list_order() {
        let mut wishes = WishList::new(3);
        let demand: Vec<(BrickId, f64)> = (0..5).map(|x| (brick(x), f64::from(x))).collect();
        let prefetch = [(brick(10), 1000.0)];
        assert_eq!(wishes.replace(&demand, &prefetch), 3);
        assert_eq!(wishes.counters().overflow_dropped, 3);
        // The first three named are kept, whatever their priority: the list comes in order.
        let kept: Vec<BrickId> = started_order(&mut wishes)
            .into_iter()
            .map(|s| s.0)
            .collect();
        assert_eq!(kept, vec![brick(2), brick(1), brick(0)]);
        // A duplicate takes no room and is not overflow.
        let mut wishes = WishList::new(2);
        assert_eq!(
            wishes.replace(&[(brick(0), 1.0), (brick(0), 1.0)], &[(brick(1), 1.0)]),
            0
        );
        assert_eq!(wishes.queued(), 2);
    }

    #[test]
    fn wishes_a_new_list_no_longer_names_are_counted_stale() {
        let mut wishes = WishList::new(8);
        wishes.replace(&[(brick(0), 1.0), (brick(1), 1.0), (brick(2), 1.0)], &[]);
        wishes.replace(&[(brick(1), 1.0), (brick(7), 1.0)], &[]);
        assert_eq!(
            wishes.counters().stale_dropped,
            2,
            "bricks 0 and 2 went stale"
        );
        assert_eq!(wishes.queued(), 2);
        wishes.replace(&[], &[]);
        assert_eq!(wishes.counters().stale_dropped, 4);
        assert_eq!(wishes.take_most_urgent(), None);
    }

    #[test]
    fn a_request_named_again_keeps_its_place() {
        let mut wishes = WishList::new(2);
        wishes.replace(&[(brick(0), 2.0), (brick(1), 1.0)], &[]);
        let first = wishes.take_most_urgent().unwrap();
        assert_eq!(first.id, brick(0));
        // Named again while in flight: not queued twice, no room taken, not cancelled, and
        // the other queued wish named again is not stale (its new priority applies).
        let overflow = wishes.replace(
            &[(first.id, 5.0), (brick(1), 3.0), (brick(2), 2.0)],
            &[(brick(3), 9.0)],
        );
        assert_eq!(overflow, 1, "brick 3 overflows; brick 0 takes no room");
        assert_eq!(wishes.counters().stale_dropped, 0);
        assert_eq!((wishes.queued(), wishes.in_flight()), (2, 1));
        wishes.replace(&[(first.id, 5.0)], &[]);
        wishes.replace(&[(first.id, 5.0)], &[]);
        assert!(wishes.cancel_unwanted().is_empty());
        assert!(wishes.is_in_flight(first.id));
        assert!(wishes.deliver(first.id, first.ticket));
        assert!(wishes.complete(first.id));
        assert_eq!(wishes.in_flight(), 0);
    }

    #[test]
    fn a_started_request_is_cancelled_once_two_lists_in_a_row_leave_it_out() {
        let mut wishes = WishList::new(4);
        wishes.replace(&[(brick(0), 1.0)], &[]);
        let started = wishes.take_most_urgent().unwrap();
        wishes.replace(&[], &[(brick(5), 1.0)]);
        assert!(wishes.cancel_unwanted().is_empty(), "one list of grace");
        wishes.replace(&[], &[(brick(5), 1.0)]);
        assert_eq!(wishes.cancel_unwanted(), vec![(brick(0), started.ticket)]);
        assert_eq!(wishes.counters().cancelled_in_flight, 1);
        assert!(!wishes.is_in_flight(brick(0)));
        // Its late answer is dropped, and a fresh start of the same brick is not confused
        // with it.
        assert!(!wishes.deliver(brick(0), started.ticket));
        wishes.replace(&[(brick(0), 1.0)], &[]);
        let again = wishes.take_most_urgent().unwrap();
        assert_eq!(again.id, brick(0));
        assert_ne!(again.ticket, started.ticket);
        assert!(!wishes.withdraw(brick(0), started.ticket));
        assert!(!wishes.deliver(brick(0), started.ticket));
        assert!(wishes.deliver(brick(0), again.ticket));
    }

    #[test]
    fn a_delivered_request_is_never_cancelled_and_ends_only_when_completed() {
        let mut wishes = WishList::new(4);
        wishes.replace(&[(brick(0), 1.0)], &[]);
        let started = wishes.take_most_urgent().unwrap();
        assert!(!wishes.complete(brick(0)), "no result delivered yet");
        assert!(wishes.deliver(brick(0), started.ticket));
        assert!(!wishes.deliver(brick(0), started.ticket), "delivered once");
        for _ in 0..3 {
            wishes.replace(&[], &[]);
            assert!(wishes.cancel_unwanted().is_empty());
        }
        // While its result waits for the loader it is not asked for again.
        wishes.replace(&[(brick(0), 1.0)], &[]);
        assert_eq!(wishes.queued(), 0);
        assert!(wishes.complete(brick(0)));
        assert_eq!(wishes.in_flight(), 0);
        wishes.replace(&[(brick(0), 1.0)], &[]);
        assert_eq!(wishes.queued(), 1);
    }

    #[test]
    fn a_request_put_back_is_started_again_in_its_turn() {
        let mut wishes = WishList::new(1);
        wishes.replace(&[(brick(0), 1.0)], &[]);
        let started = wishes.take_most_urgent().unwrap();
        wishes.replace(&[(brick(1), 1.0)], &[]);
        // Back in the queue beside a full list: admitted once, so not turned away.
        wishes.requeue(started.id, RequestClass::Demand, f64::MAX);
        assert_eq!((wishes.queued(), wishes.in_flight()), (2, 0));
        assert_eq!(wishes.take_most_urgent().map(|s| s.id), Some(brick(0)));
        let withdrawn = wishes.take_most_urgent().unwrap();
        assert!(wishes.withdraw(withdrawn.id, withdrawn.ticket));
        assert_eq!(wishes.in_flight(), 1);
    }
}
