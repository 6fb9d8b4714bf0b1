//! The data service's client in the browser (wasm32 only): a [`VolumeSource`] on `fetch()`
//! speaking `strata serve`'s protocol (strata_source::wire), for the streaming loader running
//! inline on the page's one thread.
//!
//! - Opening reads the open document (header, histogram, stats, skeleton), refuses a store
//!   this build cannot read, and fetches the root brick, which the loader reads synchronously
//!   before its first frame; every other brick comes through [`ServedBricks`].
//! - [`ServedBricks`] is the loader's [`BrickFetcher`]: the shared request policy
//!   ([`WishList`]: rewritten every frame, demand before prefetch, then by priority) run on
//!   `fetch()`, at most [`MAX_ON_THE_WIRE`] requests at once (HTTP/1.1 gives a page six
//!   connections per host; more would queue inside the browser, where priorities cannot
//!   reach them, and one stays free so that a server slow on bricks cannot hold up the
//!   page's other requests: documents, overlays, another frame, downloads); requests on the
//!   wire that two successive views no longer name are aborted with their `AbortController`.
//! - Records are decoded (and their xxh3 checksums verified) on the frame thread, at most
//!   [`DECODES_PER_FRAME`] per frame; a record that fails is fetched once more, then reported
//!   damaged. Connection failures and 429/503 are retried with backoff (at least the server's
//!   `Retry-After`, capped as the desktop's client caps it), and the status says so
//!   ("retrying") as the desktop's remote source does.
//! - A 4-D store's later frames: [`ServedStore::open_frame`] reads that frame's open document
//!   (its skeleton) and root brick, asynchronously, giving a store of its own whose bricks come
//!   from the frame's routes (`strata_source::wire::frame_brick_path`); web/src/frames.rs
//!   swaps the views to it. Before a frame is shown its bricks may be fetched ahead
//!   ([`ServedStore::fetch_ahead`], web/src/frame_ahead.rs) on connections the page's other
//!   brick requests leave free below [`MAX_ON_THE_WIRE`] (all of them counted together):
//!   its fetchers take those records instead of asking the server.
//! - The token travels as `Authorization`, never in a URL. The browser's HTTP cache is left to
//!   work (brick URLs carry the store's generation and are immutable): no `If-None-Match` here.

use std::cell::{Cell, RefCell};
use std::collections::{HashMap, HashSet, VecDeque};
use std::rc::Rc;
use std::sync::Arc;

use strata_source::wire::{
    decode_open_document, frame_brick_path, frame_document_path, retry_after, StoreList, API_PREFIX,
};
use strata_source::wish_list::{Started, WishList};
use strata_source::{
    BrickFetcher, FetchOptions, FetchResult, QueueCounters, RequestClass, SourceError,
    SourceStatus, VolumeSource,
};
use strata_storage::brick::decode_brick;
use strata_storage::histogram::Histogram;
use strata_storage::store::{Skeleton, StoreStats, KNOWN_STORE_FEATURES};
use strata_storage::StoreHeader;
use strata_types::BrickId;
use wasm_bindgen::JsCast;

use crate::frame_ahead::AheadRecords;
use wasm_bindgen_futures::JsFuture;

/// Brick requests on the wire at once: one fewer than a browser's six HTTP/1.1 connections
/// per host, so the page's other requests always find one (see the module's note). With all
/// six taken by stalled bricks, the test hook's frame post waited behind them forever.
pub const MAX_ON_THE_WIRE: usize = 5;
thread_local! {
    /// Brick requests the whole page has on the wire: every fetcher's and the frame ahead's
    /// (the page has one thread). The frame ahead asks only while this is below
    /// [`MAX_ON_THE_WIRE`].
    static BRICKS_ON_THE_WIRE: Cell<usize> = const { Cell::new(0) };
}

/// One brick request on the wire, counted in [`BRICKS_ON_THE_WIRE`] while it lives (held
/// across the request's await, dropped when it ends, answered, failed or aborted).
struct WireSlot;

impl WireSlot {
    fn take() -> WireSlot {
        BRICKS_ON_THE_WIRE.with(|n| n.set(n.get() + 1));
        WireSlot
    }
}

impl Drop for WireSlot {
    fn drop(&mut self) {
        BRICKS_ON_THE_WIRE.with(|n| n.set(n.get().saturating_sub(1)));
    }
}

/// Records decoded per frame at most: each is ~0.1-1 ms of the page's one thread.
pub const DECODES_PER_FRAME: usize = 24;
/// Backoff after a failed request: doubles from the first to the last.
const BACKOFF_FIRST_MS: f64 = 250.0;
const BACKOFF_LAST_MS: f64 = 4000.0;

/// A store served by `strata serve` (same origin as the page).
pub struct ServedStore {
    location: String,
    name: String,
    generation: String,
    /// Which frame of a 4-D store this is (0 for a 3-D store).
    frame: u32,
    token: Option<String>,
    header: StoreHeader,
    skeleton: Skeleton,
    histogram: Histogram,
    stats: StoreStats,
    root: (BrickId, Vec<u8>),
    /// This frame's records fetched before it is shown, which its fetchers take first.
    ahead: Arc<AheadRecords>,
}

/// Why a fetch gave no body.
enum FetchFailure {
    Aborted,
    /// Worth another try: no connection, 429, 5xx; with the server's `Retry-After`, if any.
    Transient(String, Option<std::time::Duration>),
    /// The server said no (404, 401, 403, ...).
    Refused(String),
}

fn js_text(value: &wasm_bindgen::JsValue) -> String {
    value
        .as_string()
        .or_else(|| {
            value
                .dyn_ref::<js_sys::Error>()
                .map(|e| String::from(e.message()))
        })
        .unwrap_or_else(|| format!("{value:?}"))
}

/// GETs `path` (same origin) with the bearer token, as bytes.
/// `reload`: past the browser's HTTP cache to the server (and the answer stored in its place),
/// for a record that failed its checksum: the cache would give the damaged copy back.
async fn fetch_bytes(
    path: &str,
    token: Option<&str>,
    signal: Option<&web_sys::AbortSignal>,
    reload: bool,
) -> Result<Vec<u8>, FetchFailure> {
    let window = web_sys::window().ok_or(FetchFailure::Refused("no window".into()))?;
    let init = web_sys::RequestInit::new();
    init.set_method("GET");
    if reload {
        init.set_cache(web_sys::RequestCache::Reload);
    }
    if let Some(token) = token {
        let headers = web_sys::Headers::new().map_err(|e| FetchFailure::Refused(js_text(&e)))?;
        headers
            .set("Authorization", &format!("Bearer {token}"))
            .map_err(|e| FetchFailure::Refused(js_text(&e)))?;
        init.set_headers(&headers);
    }
    if let Some(signal) = signal {
        init.set_signal(Some(signal));
    }
    let request = web_sys::Request::new_with_str_and_init(path, &init)
        .map_err(|e| FetchFailure::Refused(js_text(&e)))?;
    let answer = match JsFuture::from(window.fetch_with_request(&request)).await {
        Ok(answer) => answer,
        Err(_) if signal.is_some_and(|s| s.aborted()) => return Err(FetchFailure::Aborted),
        Err(e) => return Err(FetchFailure::Transient(js_text(&e), None)),
    };
    let response: web_sys::Response = answer
        .dyn_into()
        .map_err(|_| FetchFailure::Refused("fetch gave no Response".into()))?;
    let status = response.status();
    if !response.ok() {
        let what = format!("the server answered {status} {}", response.status_text());
        return Err(match status {
            408 | 429 | 500..=599 => {
                // A busy server (or the proxy in front of it) says when to come back.
                let after = response
                    .headers()
                    .get("Retry-After")
                    .ok()
                    .flatten()
                    .and_then(|value| retry_after(&value));
                FetchFailure::Transient(what, after)
            }
            401 | 403 => FetchFailure::Refused(format!(
                "{what}: the link's token is missing or wrong (ask for a link with #token=)"
            )),
            _ => FetchFailure::Refused(what),
        });
    }
    let buffer = response
        .array_buffer()
        .map_err(|e| FetchFailure::Transient(js_text(&e), None))?;
    match JsFuture::from(buffer).await {
        Ok(body) => Ok(js_sys::Uint8Array::new(&body).to_vec()),
        Err(_) if signal.is_some_and(|s| s.aborted()) => Err(FetchFailure::Aborted),
        Err(e) => Err(FetchFailure::Transient(js_text(&e), None)),
    }
}

/// Why the page has no store list: the request failed, or its answer was not a list.
#[derive(Debug, thiserror::Error)]
pub enum ListStoresError {
    #[error("aborted")]
    Aborted,
    /// The browser's or the server's wording of the failed request.
    #[error("{0}")]
    Request(String),
    #[error(transparent)]
    NotAList(#[from] crate::volume_menu::StoreListError),
}

/// The server's stores (`GET /v1/stores`), for the page's store list.
pub async fn list_stores(token: Option<&str>) -> Result<StoreList, ListStoresError> {
    let bytes = fetch_bytes(&format!("{API_PREFIX}/stores"), token, None, false)
        .await
        .map_err(|failure| match failure {
            FetchFailure::Aborted => ListStoresError::Aborted,
            FetchFailure::Transient(message, _) | FetchFailure::Refused(message) => {
                ListStoresError::Request(message)
            }
        })?;
    Ok(crate::volume_menu::parse_store_list(&bytes)?)
}

impl ServedStore {
    /// Opens the store `name` of the server that served the page.
    pub async fn open(name: &str, token: Option<String>) -> Result<ServedStore, SourceError> {
        let location = format!("{API_PREFIX}/stores/{name}");
        open_at(location.clone(), location, name, 0, token).await
    }

    /// Frame `frame` of this 4-D store: that frame's open document (its skeleton) and root
    /// brick, fetched without blocking, as a store of its own.
    pub async fn open_frame(&self, frame: u32) -> Result<ServedStore, SourceError> {
        if frame >= self.frame_count() {
            return Err(SourceError::Refused {
                location: self.location.clone(),
                message: format!(
                    "there is no frame {frame}: the store has {} frames (numbered from 0)",
                    self.frame_count()
                ),
            });
        }
        let name = &self.name;
        let base = format!("{API_PREFIX}/stores/{name}");
        let location = match frame {
            0 => base.clone(),
            _ => format!("{base} (frame {frame})"),
        };
        let document = match frame {
            0 => base,
            _ => frame_document_path(name, &self.generation, frame),
        };
        let opened = open_at(location, document, name, frame, self.token.clone()).await?;
        if opened.generation != self.generation {
            return Err(SourceError::Refused {
                location: opened.location,
                message: "the store was imported again meanwhile: reload the page".into(),
            });
        }
        Ok(opened)
    }
}

/// Reads the open document at `document` (the store's, or a frame's) and frame `frame`'s root
/// brick.
async fn open_at(
    location: String,
    document: String,
    name: &str,
    frame: u32,
    token: Option<String>,
) -> Result<ServedStore, SourceError> {
    let failed = |failure: FetchFailure, what: &str| match failure {
        FetchFailure::Refused(message) => SourceError::Refused {
            location: location.clone(),
            message: format!("{what}: {message}"),
        },
        FetchFailure::Transient(message, _) => SourceError::Unavailable {
            location: location.clone(),
            message: format!("{what}: {message}"),
        },
        FetchFailure::Aborted => SourceError::Unavailable {
            location: location.clone(),
            message: format!("{what}: aborted"),
        },
    };
    let bytes = fetch_bytes(&document, token.as_deref(), None, false)
        .await
        .map_err(|f| failed(f, "opening the store"))?;
    let (document, skeleton) =
        decode_open_document(&bytes, KNOWN_STORE_FEATURES).map_err(|e| SourceError::Refused {
            location: location.clone(),
            message: e.to_string(),
        })?;
    let root_level = (skeleton.level_count().max(1) - 1) as u8;
    let root = BrickId::new(root_level, [0, 0, 0]);
    let path = frame_brick_path(name, &document.generation, frame, root);
    let record = fetch_bytes(&path, token.as_deref(), None, false)
        .await
        .map_err(|f| failed(f, "reading the root brick"))?;
    Ok(ServedStore {
        location,
        name: name.to_string(),
        generation: document.generation,
        frame,
        token,
        header: document.header,
        skeleton,
        histogram: document.histogram,
        stats: document.stats,
        root: (root, record),
        ahead: Arc::default(),
    })
}

impl ServedStore {
    /// This frame's records fetched ahead (counts for the page's test attribute, clearing).
    pub fn ahead(&self) -> &AheadRecords {
        &self.ahead
    }

    /// Fetches the records of `wanted` (most urgent first: the shown frame's working set) of
    /// this frame, not shown yet, without waiting: as many as [`AheadRecords::to_ask`] allows
    /// now; called again each page frame for the rest. The root came with the store.
    pub fn fetch_ahead(&self, wanted: &[BrickId], ctx: &egui::Context) {
        let wanted: Vec<BrickId> = wanted
            .iter()
            .copied()
            .filter(|id| *id != self.root.0)
            .collect();
        // Only connections the shown frame's views leave free, never the page's sixth.
        let free = MAX_ON_THE_WIRE.saturating_sub(BRICKS_ON_THE_WIRE.with(Cell::get));
        let (generation, ids) = self.ahead.to_ask(&wanted, free);
        for id in ids {
            let path = frame_brick_path(&self.name, &self.generation, self.frame, id);
            let (ahead, token, repaint) = (self.ahead.clone(), self.token.clone(), ctx.clone());
            let slot = WireSlot::take();
            wasm_bindgen_futures::spawn_local(async move {
                let record = fetch_bytes(&path, token.as_deref(), None, false).await;
                drop(slot);
                ahead.arrived(generation, id, record.ok());
                repaint.request_repaint();
            });
        }
    }
}

impl VolumeSource for ServedStore {
    fn location(&self) -> String {
        self.location.clone()
    }
    fn header(&self) -> &StoreHeader {
        &self.header
    }
    fn skeleton(&self) -> &Skeleton {
        &self.skeleton
    }
    fn histogram(&self) -> &Histogram {
        &self.histogram
    }
    fn stats(&self) -> &StoreStats {
        &self.stats
    }
    /// Only the root, fetched when the store was opened: the page cannot wait for a read.
    fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
        if id == self.root.0 {
            return Ok(self.root.1.clone());
        }
        Err(SourceError::Unavailable {
            location: self.location.clone(),
            message: format!(
                "brick {id:?}: the browser reads bricks asynchronously (through the loader's \
                 fetcher), never blocking"
            ),
        })
    }
    fn start_fetching(
        &self,
        options: FetchOptions,
    ) -> Option<Result<Box<dyn BrickFetcher>, SourceError>> {
        let shared = Rc::new(Shared {
            location: self.location.clone(),
            name: self.name.clone(),
            generation: self.generation.clone(),
            frame: self.frame,
            token: self.token.clone(),
            ahead: self.ahead.clone(),
            state: RefCell::new(FetchState {
                wishes: WishList::new(options.max_queued),
                on_the_wire: HashMap::new(),
                arrived: VecDeque::new(),
                refetched: HashSet::new(),
                retried: 0,
                checksum_failures: 0,
                failing: None,
                failures_in_a_row: 0,
                quiet_until: 0.0,
            }),
        });
        Some(Ok(Box::new(ServedBricks(shared))))
    }
    fn frame_count(&self) -> u32 {
        self.header.frames.max(1)
    }
    /// Only this store's own frame: the page's thread cannot wait for another frame's
    /// document, so the page opens one with [`ServedStore::open_frame`] (web/src/frames.rs).
    fn frame_source(self: Arc<Self>, frame: u32) -> Option<Arc<dyn VolumeSource>> {
        (frame == self.frame).then_some(self as Arc<dyn VolumeSource>)
    }
}

/// A record that came back, not yet decoded.
struct Arrival {
    id: BrickId,
    class: RequestClass,
    body: Result<Vec<u8>, SourceError>,
}

/// A request on the wire, and how to stop it.
struct OnTheWire {
    started: Started,
    controller: web_sys::AbortController,
}

struct FetchState {
    /// Queued and started requests (started: on the wire, arrived, or handed to the loader
    /// and not yet completed).
    wishes: WishList,
    on_the_wire: HashMap<BrickId, OnTheWire>,
    arrived: VecDeque<Arrival>,
    /// Records that failed their checksum once (fetched again once).
    refetched: HashSet<BrickId>,
    /// Requests sent again (after a transient failure or a damaged record), for the counters.
    retried: u64,
    checksum_failures: u64,
    /// Since when requests fail to reach the server (ms, `Date.now()`), and the last reason.
    failing: Option<(f64, String)>,
    failures_in_a_row: u32,
    /// No new request before this time (ms): backoff after a failure.
    quiet_until: f64,
}

struct Shared {
    location: String,
    name: String,
    generation: String,
    frame: u32,
    token: Option<String>,
    /// The frame's records fetched ahead: taken instead of a request.
    ahead: Arc<AheadRecords>,
    state: RefCell<FetchState>,
}

/// The fetcher the loader polls every frame.
pub struct ServedBricks(Rc<Shared>);

// SAFETY: the loader's seam asks for `Send`. This type exists only on wasm32 built without
// the `atomics` target feature, where there is exactly one thread (the page's): nothing can
// move to another thread, so the `Rc`, `RefCell` and JS handles are never shared across
// threads.
#[cfg(not(target_feature = "atomics"))]
unsafe impl Send for ServedBricks {}

impl Shared {
    /// Starts the most urgent queued requests while fewer than [`MAX_ON_THE_WIRE`] are out.
    fn pump(self: &Rc<Self>) {
        let now = js_sys::Date::now();
        loop {
            let (started, controller, reload) = {
                let mut state = self.state.borrow_mut();
                if state.on_the_wire.len() >= MAX_ON_THE_WIRE
                    || now < state.quiet_until
                    || state.wishes.queued() == 0
                {
                    return;
                }
                let Ok(controller) = web_sys::AbortController::new() else {
                    return;
                };
                let Some(started) = state.wishes.take_most_urgent() else {
                    return;
                };
                // Fetched ahead (frame_ahead.rs): delivered without a request, unless it was
                // damaged once (then the server's copy, past the cache).
                let ahead = match state.refetched.contains(&started.id) {
                    true => None,
                    false => self.ahead.take_record(started.id),
                };
                if let Some(record) = ahead {
                    state.wishes.deliver(started.id, started.ticket);
                    state.arrived.push_back(Arrival {
                        id: started.id,
                        class: started.class,
                        body: Ok(record),
                    });
                    continue;
                }
                let on_the_wire = OnTheWire {
                    started,
                    controller: controller.clone(),
                };
                state.on_the_wire.insert(started.id, on_the_wire);
                (started, controller, state.refetched.contains(&started.id))
            };
            let shared = self.clone();
            let path = frame_brick_path(&self.name, &self.generation, self.frame, started.id);
            let slot = WireSlot::take();
            wasm_bindgen_futures::spawn_local(async move {
                let signal = controller.signal();
                let outcome =
                    fetch_bytes(&path, shared.token.as_deref(), Some(&signal), reload).await;
                drop(slot);
                shared.arrive(started, outcome);
            });
        }
    }

    fn arrive(self: &Rc<Self>, started: Started, outcome: Result<Vec<u8>, FetchFailure>) {
        let Started {
            id,
            class,
            priority,
            ticket,
        } = started;
        let mut state = self.state.borrow_mut();
        // Aborted meanwhile (the view moved on), perhaps started again since: already
        // accounted for.
        match state.on_the_wire.get(&id) {
            Some(wire) if wire.started.ticket == ticket => {
                state.on_the_wire.remove(&id);
            }
            _ => return,
        }
        let body = match outcome {
            Ok(body) => {
                state.failing = None;
                state.failures_in_a_row = 0;
                Ok(body)
            }
            Err(FetchFailure::Aborted) => {
                state.wishes.withdraw(id, ticket);
                return;
            }
            Err(FetchFailure::Transient(message, after)) => {
                // Asked again after a pause; what is loaded stays on screen meanwhile. The
                // server's Retry-After (capped) lengthens the pause, never shortens it.
                let now = js_sys::Date::now();
                let backoff = (BACKOFF_FIRST_MS * 2f64.powi(state.failures_in_a_row.min(8) as i32))
                    .min(BACKOFF_LAST_MS)
                    .max(after.map_or(0.0, |after| after.as_secs_f64() * 1000.0));
                state.failures_in_a_row += 1;
                state.quiet_until = now + backoff;
                state.failing.get_or_insert((now, String::new())).1 = message;
                state.retried += 1;
                state.wishes.requeue(id, class, priority);
                return;
            }
            Err(FetchFailure::Refused(message)) => Err(SourceError::Refused {
                location: self.location.clone(),
                message: format!("brick level {} at {:?}: {message}", id.level, id.coords),
            }),
        };
        state.wishes.deliver(id, ticket);
        state.arrived.push_back(Arrival { id, class, body });
    }
}

impl BrickFetcher for ServedBricks {
    fn set_requests(&self, demand: &[(BrickId, f64)], prefetch: &[(BrickId, f64)]) -> usize {
        let shared = &self.0;
        {
            let mut state = shared.state.borrow_mut();
            state.wishes.replace(demand, prefetch);
            // On the wire but named by neither this view nor the previous one: aborted.
            for (id, _) in state.wishes.cancel_unwanted() {
                if let Some(wire) = state.on_the_wire.remove(&id) {
                    wire.controller.abort();
                }
            }
        }
        shared.pump();
        shared.state.borrow().wishes.queued()
    }

    fn try_results(&self) -> Vec<FetchResult> {
        let shared = &self.0;
        shared.pump();
        let mut results = Vec::new();
        let mut refetch = false;
        for _ in 0..DECODES_PER_FRAME {
            let Some(arrival) = shared.state.borrow_mut().arrived.pop_front() else {
                break;
            };
            let Arrival { id, class, body } = arrival;
            let stored_bytes = body.as_ref().map_or(0, |b| b.len() as u64);
            let outcome = match body {
                Err(e) => Err(e),
                Ok(record) => match crate::page_timing::time_decode(|| decode_brick(id, &record)) {
                    Ok(voxels) => Ok(Arc::new(voxels)),
                    Err(e) => {
                        let mut state = shared.state.borrow_mut();
                        state.checksum_failures += 1;
                        if state.refetched.insert(id) {
                            // Damaged on the way (or by a proxy): fetched once more, first,
                            // from the server (the HTTP cache holds the damaged copy).
                            state.retried += 1;
                            state.wishes.requeue(id, RequestClass::Demand, f64::MAX);
                            refetch = true;
                            continue;
                        }
                        Err(SourceError::damaged(&shared.location, id, e))
                    }
                },
            };
            results.push(FetchResult {
                id,
                class,
                outcome,
                stored_bytes,
            });
        }
        if refetch {
            shared.pump();
        }
        results
    }

    fn complete(&self, id: BrickId) {
        self.0.state.borrow_mut().wishes.complete(id);
    }

    fn queued(&self) -> usize {
        self.0.state.borrow().wishes.queued()
    }

    fn in_flight(&self) -> usize {
        self.0.state.borrow().wishes.in_flight()
    }

    fn capacity(&self) -> usize {
        self.0.state.borrow().wishes.capacity()
    }

    fn counters(&self) -> QueueCounters {
        let state = self.0.state.borrow();
        let mut counters = state.wishes.counters();
        counters.retried = state.retried;
        counters.checksum_failures = state.checksum_failures;
        counters
    }

    fn status(&self) -> SourceStatus {
        match &self.0.state.borrow().failing {
            None => SourceStatus::Available,
            Some((since, message)) => SourceStatus::Retrying {
                since_seconds: (js_sys::Date::now() - since) / 1000.0,
                message: message.clone(),
            },
        }
    }
}

impl Drop for ServedBricks {
    fn drop(&mut self) {
        // Nothing left to take the answers: stop the transfers.
        let mut state = self.0.state.borrow_mut();
        for (_, wire) in state.on_the_wire.drain() {
            wire.controller.abort();
        }
    }
}
