//! The next frame of a 4-D store streamed ahead (issue 47): while the page shows one frame, the
//! bricks its 3D view holds are fetched, as records, for the frame cine shows next, so that
//! frame's views start from them instead of from the network (the desktop sends the frame
//! ahead the shown frame's requests on a second render thread, viewer/src/frames.rs; the page
//! has one thread, so it keeps the records and lets the next frame's own loader decode them).
//!
//! [`AheadRecords`] is the bookkeeping, platform independent and tested here: which bricks to
//! ask for now, the records kept, and how many a frame's fetchers took. Bounded three times:
//! at most [`AHEAD_ON_THE_WIRE`] requests at once, only on connections the page's other brick
//! requests leave free below the served store's `MAX_ON_THE_WIRE` (the page's sixth HTTP/1.1
//! connection stays free for its documents and posts, as served_store.rs keeps it), and at
//! most [`AHEAD_BYTES`] of records kept per frame, then no more are asked for. The page (web/src/frames.rs) asks only once the shown frame's 3D view
//! has converged, and clears every other frame's records then, so at most one frame's
//! records are held past that. The fetches themselves are the served store's
//! (web/src/served_store.rs, `ServedStore::fetch_ahead`), as are the fetchers that take the
//! records; web/tests/browser/frames.rs checks, with the server's access log, that the next
//! frame's bricks are requested before it is shown and that the frame then shown is the
//! desktop's.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex, PoisonError};

use strata_types::BrickId;

/// Records kept ahead for one frame at most (compressed, as the server sends them): the 3D
/// view's working set of a large volume is bounded by its GPU cache, not by this; a frame
/// past it streams the rest when shown.
pub const AHEAD_BYTES: usize = 32 << 20;
/// Requests for the frame ahead on the wire at once.
pub const AHEAD_ON_THE_WIRE: usize = 2;

#[derive(Default)]
struct AheadState {
    records: HashMap<BrickId, Arc<Vec<u8>>>,
    bytes: usize,
    /// Asked for since the last clear (on the wire, kept, or failed: each asked once).
    asked: HashSet<BrickId>,
    on_the_wire: usize,
    /// Bumped by a clear: answers to requests asked before are dropped.
    generation: u64,
    /// Records the frame's fetchers took instead of a request.
    used: u64,
}

/// What [`AheadRecords`] holds, for the page's test attribute.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct AheadCounts {
    pub asked: usize,
    pub kept: usize,
    pub bytes: usize,
    pub used: u64,
}

/// The records of one frame's bricks fetched before it is shown. Shared by that frame's store
/// and its fetchers (the page has one thread: the lock is never contended, it only makes the
/// store `Sync` as the loader's seam asks).
#[derive(Default)]
pub struct AheadRecords(Mutex<AheadState>);

impl AheadRecords {
    fn state(&self) -> std::sync::MutexGuard<'_, AheadState> {
        // Nothing here can panic while holding the lock; a poisoned one holds whole records.
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The bricks of `wanted` (most urgent first) to ask for now, each once, within
    /// [`AHEAD_ON_THE_WIRE`], the `free_connections` the page's other brick requests leave,
    /// and [`AHEAD_BYTES`], with the generation their answers belong to.
    pub fn to_ask(&self, wanted: &[BrickId], free_connections: usize) -> (u64, Vec<BrickId>) {
        let mut state = self.state();
        if state.bytes >= AHEAD_BYTES {
            return (state.generation, Vec::new());
        }
        let room = AHEAD_ON_THE_WIRE
            .saturating_sub(state.on_the_wire)
            .min(free_connections);
        let ids: Vec<BrickId> = wanted
            .iter()
            .copied()
            .filter(|id| !state.asked.contains(id))
            .take(room)
            .collect();
        for id in &ids {
            state.asked.insert(*id);
        }
        state.on_the_wire += ids.len();
        (state.generation, ids)
    }

    /// The answer to a request of generation `generation`: its record, or None where it failed
    /// (the frame's own fetchers ask for that brick when it is shown). Kept while within
    /// [`AHEAD_BYTES`].
    pub fn arrived(&self, generation: u64, id: BrickId, record: Option<Vec<u8>>) {
        let mut state = self.state();
        if generation != state.generation {
            return;
        }
        state.on_the_wire = state.on_the_wire.saturating_sub(1);
        if let Some(record) = record {
            if state.bytes + record.len() <= AHEAD_BYTES {
                state.bytes += record.len();
                state.records.insert(id, Arc::new(record));
            }
        }
    }

    /// The record of `id` if it was fetched ahead (a fetcher of the frame takes it instead of
    /// asking the server; counted).
    pub fn take_record(&self, id: BrickId) -> Option<Vec<u8>> {
        let mut state = self.state();
        let record = state.records.get(&id).map(|r| r.as_ref().clone())?;
        state.used += 1;
        Some(record)
    }

    /// Forgets the records and what was asked (the frame is not the next one, or it is shown
    /// and its view loaded), keeping the count of records used.
    pub fn clear(&self) {
        let mut state = self.state();
        if state.asked.is_empty() {
            return;
        }
        let used = state.used;
        let generation = state.generation + 1;
        *state = AheadState {
            generation,
            used,
            ..AheadState::default()
        };
    }

    pub fn counts(&self) -> AheadCounts {
        let state = self.state();
        AheadCounts {
            asked: state.asked.len(),
            kept: state.records.len(),
            bytes: state.bytes,
            used: state.used,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Connections free enough never to be the bound.
    const ALL_FREE: usize = 5;

    fn brick(i: u32) -> BrickId {
        BrickId::new(0, [i, 0, 0])
    }

    #[test]
    fn only_connections_the_pages_other_bricks_leave_free_are_taken() {
        let ahead = AheadRecords::default();
        let wanted: Vec<BrickId> = (0..3).map(brick).collect();
        assert!(
            ahead.to_ask(&wanted, 0).1.is_empty(),
            "no connection free: nothing asked"
        );
        let (generation, first) = ahead.to_ask(&wanted, 1);
        assert_eq!(first, [brick(0)], "one free: one asked");
        assert_eq!(
            ahead.to_ask(&wanted, ALL_FREE).1,
            [brick(1)],
            "within the frame ahead's own two"
        );
        ahead.arrived(generation, brick(0), Some(vec![1; 4]));
        assert_eq!(ahead.to_ask(&wanted, ALL_FREE).1, [brick(2)]);
    }

    #[test]
    fn bricks_are_asked_once_within_the_wire_bound_and_taken_by_the_frames_fetchers() {
        let ahead = AheadRecords::default();
        let wanted: Vec<BrickId> = (0..5).map(brick).collect();
        let (generation, first) = ahead.to_ask(&wanted, ALL_FREE);
        assert_eq!(first, [brick(0), brick(1)], "the most urgent, two at once");
        assert_eq!(
            ahead.to_ask(&wanted, ALL_FREE).1,
            Vec::<BrickId>::new(),
            "none while two are on the wire"
        );
        ahead.arrived(generation, brick(0), Some(vec![7; 10]));
        assert_eq!(
            ahead.to_ask(&wanted, ALL_FREE).1,
            [brick(2)],
            "one answered, one more"
        );
        ahead.arrived(generation, brick(1), None);
        ahead.arrived(generation, brick(2), Some(vec![8; 10]));
        assert_eq!(ahead.to_ask(&wanted, ALL_FREE).1, [brick(3), brick(4)]);
        assert_eq!(
            ahead.to_ask(&wanted, ALL_FREE).1,
            Vec::<BrickId>::new(),
            "a failed brick is not asked again"
        );
        assert_eq!(ahead.take_record(brick(0)), Some(vec![7; 10]));
        assert_eq!(ahead.take_record(brick(1)), None, "it failed");
        assert_eq!(
            ahead.counts(),
            AheadCounts {
                asked: 5,
                kept: 2,
                bytes: 20,
                used: 1
            }
        );
    }

    #[test]
    fn records_stop_at_the_byte_bound_and_a_clear_drops_them_and_late_answers() {
        let ahead = AheadRecords::default();
        let (generation, asked) = ahead.to_ask(&[brick(0), brick(1)], ALL_FREE);
        ahead.arrived(generation, asked[0], Some(vec![0; AHEAD_BYTES - 4]));
        ahead.arrived(generation, asked[1], Some(vec![0; 8]));
        assert_eq!(ahead.counts().kept, 1, "the second would pass the bound");
        let (_, more) = ahead.to_ask(&[brick(2)], ALL_FREE);
        assert_eq!(more, [brick(2)], "still under the bound: asked");
        ahead.arrived(generation, brick(2), Some(vec![0; 4]));
        assert_eq!(ahead.counts().bytes, AHEAD_BYTES);
        assert!(
            ahead.to_ask(&[brick(3)], ALL_FREE).1.is_empty(),
            "full: nothing more asked"
        );
        assert!(ahead.take_record(brick(2)).is_some());

        let (old_generation, _) = ahead.to_ask(&[], ALL_FREE);
        ahead.clear();
        assert_eq!(
            ahead.counts(),
            AheadCounts {
                used: 1,
                ..AheadCounts::default()
            },
            "cleared, the use count kept"
        );
        let (generation, asked) = ahead.to_ask(&[brick(0)], ALL_FREE);
        assert_ne!(generation, old_generation);
        assert_eq!(asked, [brick(0)], "asked again after a clear");
        ahead.arrived(old_generation, brick(5), Some(vec![1; 4]));
        assert_eq!(
            ahead.take_record(brick(5)),
            None,
            "an answer from before the clear"
        );
    }
}
