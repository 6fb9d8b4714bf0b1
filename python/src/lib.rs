//! `strata._strata`: the native half of the `strata` Python package.
//!
//! A thin layer over the library crates: it opens stores (`strata_storage::Store`), served
//! stores and OME-Zarrs (volume sources, `streamed.rs`), reads regions of a level brick by
//! brick into a buffer Python owns, imports files or raw arrays through the same
//! `import_source` as `strata import`, and exports OME-Zarr as `strata export` does. Everything else (slicing rules,
//! dtypes, the value mapping, the affine) lives in the pure-Python package (`strata/`), which
//! is the documented API.
//!
//! Rules at this boundary: no panic crosses it (pyo3 turns one into `PanicException`, and the
//! work runs inside `catch_unwind` below as well so a panic becomes a `StrataError` carrying its
//! message); every storage error becomes a `StrataError` subclass carrying the Rust message;
//! the GIL is released during reads and imports, and Ctrl-C (a pending `KeyboardInterrupt`) is
//! checked between groups of bricks and while an import runs, which it then cancels.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;

mod render;
mod serve;
mod streamed;

use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyIndexError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyByteArray;
use rayon::prelude::*;
use strata_source::{SourceError as VolumeSourceError, VolumeSource};
use strata_storage::import::{import_source, ImportOptions, ImportProgress};
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::store::StoreStats;
use strata_storage::{BrickCodec, ByteOrder, OpenedSource, RawVolume, SampleType, SourceInfo, StorageError, Store, StoreHeader};
use strata_types::{BrickId, VolumeGeometry, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};
use streamed::StreamedReader;

create_exception!(
    _strata,
    StrataError,
    PyException,
    "Base class of every error Strata raises; the message is the Rust library's."
);
create_exception!(
    _strata,
    StoreError,
    StrataError,
    "A store cannot be opened, read or written."
);
create_exception!(
    _strata,
    StoreNotFoundError,
    StoreError,
    "No store (or no Strata store) at the path."
);
create_exception!(
    _strata,
    DamagedStoreError,
    StoreError,
    "The store is damaged or its import did not finish; import it again."
);
create_exception!(
    _strata,
    StoreInUseError,
    StoreError,
    "Another process holds the store (the message names it, and the URL it is served at)."
);
create_exception!(
    _strata,
    SourceError,
    StrataError,
    "An input to an import cannot be read (missing, unsupported or malformed)."
);
create_exception!(
    _strata,
    RemoteError,
    StrataError,
    "A served store or a remote OME-Zarr cannot be reached, or its server refused a request."
);
create_exception!(
    _strata,
    TokenError,
    RemoteError,
    "The server requires a token (pass token=...) or refused the one given."
);

/// The Python exception of a storage error.
pub(crate) fn store_error(e: StorageError) -> PyErr {
    let message = e.to_string();
    match e {
        StorageError::NotAStore { .. } => StoreNotFoundError::new_err(message),
        StorageError::InvalidInput { ref path, .. } if !path.exists() => {
            StoreNotFoundError::new_err(message)
        }
        StorageError::Corrupted { .. }
        | StorageError::IncompleteImport { .. }
        | StorageError::Database { .. } => DamagedStoreError::new_err(message),
        StorageError::InUse { .. } => StoreInUseError::new_err(message),
        _ => StoreError::new_err(message),
    }
}

/// The Python exception of an import's error: the store's kinds when it concerns the store
/// being written, a [`SourceError`] otherwise.
fn import_error(e: StorageError, dst: &Path) -> PyErr {
    let about_store = match &e {
        StorageError::Io { path, .. }
        | StorageError::InvalidInput { path, .. }
        | StorageError::Unsupported { path, .. }
        | StorageError::NotAStore { path, .. }
        | StorageError::Corrupted { path, .. }
        | StorageError::Database { path, .. }
        | StorageError::DiskFull { path, .. }
        | StorageError::InUse { path, .. }
        | StorageError::ReadOnly { path, .. }
        | StorageError::IncompleteImport { path }
        | StorageError::Cancelled { path } => path.starts_with(dst),
    };
    if about_store {
        store_error(e)
    } else {
        SourceError::new_err(e.to_string())
    }
}

/// Runs `f`, turning a panic into a `StrataError` with its message (a bug, never a crash).
pub(crate) fn no_panic<T>(what: &str, f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(payload) => {
            let text = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            Err(StrataError::new_err(format!(
                "internal error while {what}: {text} (a bug in Strata: please report it)"
            )))
        }
    }
}

/// A pending Ctrl-C (or another signal handler's exception), checked with the GIL briefly held.
pub(crate) fn interrupted() -> PyResult<()> {
    Python::with_gil(|py| py.check_signals())
}

/// One store per folder per process: `Store::open` takes the folder's lock, so a second open
/// of the same store here would be refused as "in use" by ourselves. Opens share it instead.
fn open_shared(path: &Path) -> Result<Arc<Store>, StorageError> {
    static OPEN: Mutex<Option<HashMap<PathBuf, Weak<Store>>>> = Mutex::new(None);
    let key = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    let mut open = OPEN.lock().unwrap_or_else(|p| p.into_inner());
    let map = open.get_or_insert_with(HashMap::new);
    map.retain(|_, w| w.strong_count() > 0);
    if let Some(store) = map.get(&key).and_then(Weak::upgrade) {
        return Ok(store);
    }
    let store = Arc::new(Store::open(path)?);
    map.insert(key, Arc::downgrade(&store));
    Ok(store)
}

/// What a [`NativeStore`] reads.
#[derive(Clone)]
enum Opened {
    /// A store folder on this machine (one per folder per process: [`open_shared`]).
    Local(Arc<Store>),
    /// A store served by `strata serve`, or an OME-Zarr read in place (`streamed.rs`).
    Streamed(Arc<dyn VolumeSource>),
}

impl Opened {
    fn header(&self) -> &StoreHeader {
        match self {
            Opened::Local(store) => store.header(),
            Opened::Streamed(source) => source.header(),
        }
    }
    fn stats(&self) -> &StoreStats {
        match self {
            Opened::Local(store) => store.stats(),
            Opened::Streamed(source) => source.stats(),
        }
    }
    fn frame_count(&self) -> u32 {
        match self {
            Opened::Local(store) => store.frame_count(),
            Opened::Streamed(source) => source.frame_count(),
        }
    }
    fn source(&self) -> Arc<dyn VolumeSource> {
        match self {
            Opened::Local(store) => store.clone(),
            Opened::Streamed(source) => source.clone(),
        }
    }
}

/// An open volume (the Python class `strata.Volume` wraps it): a store, a served store or an
/// OME-Zarr.
#[pyclass(module = "strata._strata", frozen)]
struct NativeStore {
    opened: Mutex<Option<Opened>>,
    /// The path or URL as given (never with a token: tokens travel apart).
    location: String,
    /// "store", "served" or "ome-zarr".
    kind: &'static str,
    /// What was assumed to read it (a foreign OME-Zarr's orientation, levels, value mapping).
    notes: Vec<String>,
    /// The token the client sends, only to keep it out of messages.
    secret: Option<String>,
    /// How long a read waits on a streamed source that stopped answering.
    give_up_after: Duration,
}

impl NativeStore {
    fn get(&self) -> PyResult<Opened> {
        self.opened
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
            .ok_or_else(|| StoreError::new_err(format!("{}: the volume is closed", self.location)))
    }
}

#[pymethods]
impl NativeStore {
    /// The store's header as JSON (geometry, value mapping, layout, frames, description...).
    fn header_json(&self) -> PyResult<String> {
        let opened = self.get()?;
        serde_json::to_string(opened.header())
            .map_err(|e| StrataError::new_err(format!("header to JSON: {e}")))
    }

    /// The import's statistics as JSON.
    fn stats_json(&self) -> PyResult<String> {
        let opened = self.get()?;
        serde_json::to_string(opened.stats())
            .map_err(|e| StrataError::new_err(format!("statistics to JSON: {e}")))
    }

    /// The store's folder, or `None` for a URL.
    #[getter]
    fn path(&self) -> Option<PathBuf> {
        (!streamed::is_url(&self.location) && !self.location.starts_with("s3://"))
            .then(|| PathBuf::from(&self.location))
    }

    /// The path or URL as given.
    #[getter]
    fn location(&self) -> String {
        self.location.clone()
    }

    /// "store" (a folder `strata import` wrote), "served" (`strata serve`) or "ome-zarr".
    #[getter]
    fn kind(&self) -> &'static str {
        self.kind
    }

    /// What was assumed to read the volume (empty for a Strata store or export).
    fn notes(&self) -> Vec<String> {
        self.notes.clone()
    }

    /// Volumes this handle reads (a served 4-D store: its first only).
    fn frame_count(&self) -> PyResult<u32> {
        Ok(self.get()?.frame_count())
    }

    /// Releases this handle (the store closes when no other handle of this process has it).
    fn close(&self) {
        self.opened.lock().unwrap_or_else(|p| p.into_inner()).take();
    }

    /// Stored samples of frame `frame`, level `level`, voxels `lo..hi` (x, y, z; half-open),
    /// as a bytearray of native-endian u16 in C order (z, y, x). The bounds are checked here
    /// again (the Python side checks them first and raises IndexError with its own text).
    fn read_region<'py>(
        &self,
        py: Python<'py>,
        level: u8,
        frame: u32,
        lo: [u32; 3],
        hi: [u32; 3],
    ) -> PyResult<Bound<'py, PyByteArray>> {
        let opened = self.get()?;
        let header = opened.header();
        let Some(dims) = header.layout.level_dims.get(usize::from(level)).copied() else {
            return Err(PyIndexError::new_err(format!(
                "level {level} of a store with {} levels",
                header.layout.level_count()
            )));
        };
        if frame >= opened.frame_count() {
            return Err(PyIndexError::new_err(format!(
                "frame {frame} of a store with {} frames",
                opened.frame_count()
            )));
        }
        for a in 0..3 {
            if lo[a] > hi[a] || hi[a] > dims[a] {
                return Err(PyIndexError::new_err(format!(
                    "region {lo:?}..{hi:?} (x, y, z) outside level {level}'s {dims:?}"
                )));
            }
        }
        let voxels = (0..3).map(|a| (hi[a] - lo[a]) as usize).product::<usize>();
        let secret = self.secret.as_deref();
        let give_up_after = self.give_up_after;
        let mut failure: Option<PyErr> = None;
        let out = PyByteArray::new_with(py, voxels * 2, |buf| {
            let result = py.allow_threads(|| {
                no_panic("reading a region", || {
                    let read = read_region(&opened, frame, level, lo, hi, buf, give_up_after);
                    read.map_err(|e| match e {
                        ReadError::Store(e) => store_error(e),
                        ReadError::Source(e) => streamed::source_error(e, secret),
                        ReadError::Python(e) => e,
                    })
                })
            });
            if let Err(e) = result {
                failure = Some(e);
            }
            Ok(())
        })?;
        match failure {
            Some(e) => Err(e),
            None => Ok(out),
        }
    }
}

pub(crate) enum ReadError {
    Store(StorageError),
    Source(VolumeSourceError),
    Python(PyErr),
}

/// Bricks decoded at once (in parallel) before they are copied out: bounds the memory a read
/// takes beyond its output (64 × 36³ × 2 bytes ≈ 6 MB) whatever the region's size.
const BRICKS_PER_GROUP: usize = 64;

/// Where a region's bricks come from.
enum BrickReader<'a> {
    /// Decoded on rayon's threads from the local store's files.
    Local { store: &'a Store, frame: u32 },
    /// Through a source's own request path.
    Streamed(StreamedReader),
}

impl BrickReader<'_> {
    fn group_size(&self) -> usize {
        match self {
            BrickReader::Local { .. } => BRICKS_PER_GROUP,
            BrickReader::Streamed(_) => streamed::BRICKS_PER_REQUEST_GROUP,
        }
    }

    fn read_group(&self, group: &[BrickId]) -> Result<Vec<(BrickId, Brick)>, ReadError> {
        match self {
            BrickReader::Local { store, frame } => group
                .par_iter()
                .map(|&id| {
                    let brick = match store.frame_node(*frame, id) {
                        Some(node) if node.is_constant() => Brick::Constant(node.min),
                        _ => Brick::Voxels(Arc::new(store.read_frame_brick(*frame, id)?)),
                    };
                    Ok((id, brick))
                })
                .collect::<Result<_, StorageError>>()
                .map_err(ReadError::Store),
            BrickReader::Streamed(reader) => reader.read_group(group),
        }
    }
}

/// Fills `out` (C order z, y, x; native-endian u16) with the stored samples of `lo..hi`.
fn read_region(
    opened: &Opened,
    frame: u32,
    level: u8,
    lo: [u32; 3],
    hi: [u32; 3],
    out: &mut [u8],
    give_up_after: Duration,
) -> Result<(), ReadError> {
    if (0..3).any(|a| lo[a] >= hi[a]) {
        return Ok(());
    }
    let n = [
        (hi[0] - lo[0]) as usize,
        (hi[1] - lo[1]) as usize,
        (hi[2] - lo[2]) as usize,
    ];
    let first = lo.map(|v| v / BRICK_CORE);
    let last = hi.map(|v| (v - 1) / BRICK_CORE);
    let mut bricks = Vec::new();
    for bz in first[2]..=last[2] {
        for by in first[1]..=last[1] {
            for bx in first[0]..=last[0] {
                bricks.push(BrickId::new(level, [bx, by, bz]));
            }
        }
    }
    let reader = match opened {
        Opened::Local(store) => BrickReader::Local { store, frame },
        Opened::Streamed(source) => {
            let source = if frame == 0 {
                source.clone()
            } else {
                source.clone().frame_source(frame).ok_or_else(|| {
                    ReadError::Source(VolumeSourceError::Refused {
                        location: source.location(),
                        message: format!("frame {frame} is not served"),
                    })
                })?
            };
            BrickReader::Streamed(StreamedReader::start(source, give_up_after)?)
        }
    };
    let p = BRICK_PAYLOAD as usize;
    for group in bricks.chunks(reader.group_size()) {
        for (id, brick) in reader.read_group(group)? {
            // This brick's part of the region, in level voxels.
            let start = (0..3)
                .map(|a| lo[a].max(id.coords[a] * BRICK_CORE))
                .collect::<Vec<_>>();
            let end = (0..3)
                .map(|a| hi[a].min((id.coords[a] + 1) * BRICK_CORE))
                .collect::<Vec<_>>();
            let row = (end[0] - start[0]) as usize;
            for z in start[2]..end[2] {
                for y in start[1]..end[1] {
                    let dst = (((z - lo[2]) as usize * n[1] + (y - lo[1]) as usize) * n[0]
                        + (start[0] - lo[0]) as usize)
                        * 2;
                    let dst = &mut out[dst..dst + row * 2];
                    match &brick {
                        Brick::Constant(v) => {
                            let bytes = v.to_ne_bytes();
                            dst.chunks_exact_mut(2)
                                .for_each(|d| d.copy_from_slice(&bytes));
                        }
                        Brick::Voxels(voxels) => {
                            let local = |v: u32, a: usize| {
                                (v - id.coords[a] * BRICK_CORE + BRICK_APRON) as usize
                            };
                            let src = (local(z, 2) * p + local(y, 1)) * p + local(start[0], 0);
                            for (d, s) in dst.chunks_exact_mut(2).zip(&voxels[src..src + row]) {
                                d.copy_from_slice(&s.to_ne_bytes());
                            }
                        }
                    }
                }
            }
        }
        interrupted().map_err(ReadError::Python)?;
    }
    Ok(())
}

pub(crate) enum Brick {
    Constant(u16),
    Voxels(Arc<Vec<u16>>),
}

/// Opens `location`: a store folder (shared with any other handle of this process), a URL
/// `strata serve` serves (with `token`), or an OME-Zarr (a `.zarr` folder or URL, `s3://`).
/// `timeout_s`: how long opening and reading a URL keep retrying a server that does not answer.
#[pyfunction]
#[pyo3(signature = (location, token=None, timeout_s=20.0))]
fn open_store(
    py: Python<'_>,
    location: String,
    token: Option<String>,
    timeout_s: f64,
) -> PyResult<NativeStore> {
    let give_up_after = Duration::try_from_secs_f64(timeout_s)
        .ok()
        .filter(|d| *d <= Duration::from_secs(86_400))
        .ok_or_else(|| {
            PyValueError::new_err(format!(
                "timeout_s={timeout_s}: a number of seconds from 0 to 86400"
            ))
        })?;
    let secret = token.clone();
    let (opened, kind, notes) = py.allow_threads(|| {
        no_panic("opening a volume", || {
            if strata_omezarr::looks_like_ome_zarr(&location) {
                if token.is_some() {
                    return Err(PyValueError::new_err(
                        "token= is for a URL strata serve serves, not an OME-Zarr",
                    ));
                }
                let (source, notes) = streamed::open_omezarr(&location)?;
                Ok((Opened::Streamed(source), "ome-zarr", notes))
            } else if streamed::is_url(&location) {
                let source = streamed::open_remote(&location, token, give_up_after)?;
                Ok((Opened::Streamed(source), "served", Vec::new()))
            } else if token.is_some() {
                Err(PyValueError::new_err(format!(
                    "token= is for a URL strata serve serves, not the folder {location}"
                )))
            } else {
                let store = open_shared(Path::new(&location)).map_err(store_error)?;
                Ok((Opened::Local(store), "store", Vec::new()))
            }
        })
    })?;
    Ok(NativeStore {
        opened: Mutex::new(Some(opened)),
        location,
        kind,
        notes,
        secret,
        give_up_after,
    })
}

/// `strata export STORE DEST`: `volume` as OME-Zarr 0.5 at `dest` (a folder, created, or
/// `s3://BUCKET/PREFIX`), on a thread of its own; Ctrl-C cancels it. Returns (levels, shards
/// written, fill-only shards left out, shard bytes, metadata bytes).
#[pyfunction]
fn export_omezarr(
    py: Python<'_>,
    volume: &NativeStore,
    dest: String,
) -> PyResult<(usize, u64, u64, u64, u64)> {
    let source = volume.get()?.source();
    let cancel = AtomicBool::new(false);
    let finished = AtomicBool::new(false);
    std::thread::scope(|scope| {
        let worker = std::thread::Builder::new()
            .name("strata-py-export".into())
            .spawn_scoped(scope, || {
                let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    let location = strata_omezarr::ObjectLocation::open(
                        &dest,
                        &strata_omezarr::ObjectStoreOptions::default(),
                        true,
                    )?;
                    let options = strata_omezarr::export::ExportOptions {
                        cancel: Some(&cancel),
                        ..Default::default()
                    };
                    strata_omezarr::export::export(source.as_ref(), &location, &options, &|_, _| {})
                }));
                finished.store(true, Ordering::Release);
                result
            })
            .map_err(|e| StrataError::new_err(format!("cannot start the export thread: {e}")))?;
        let mut failure: Option<PyErr> = None;
        while !finished.load(Ordering::Acquire) {
            py.allow_threads(|| std::thread::sleep(Duration::from_millis(50)));
            if failure.is_none() {
                if let Err(e) = py.check_signals() {
                    cancel.store(true, Ordering::Relaxed);
                    failure = Some(e);
                }
            }
        }
        let joined = py.allow_threads(|| worker.join());
        if let Some(e) = failure {
            return Err(e);
        }
        match joined {
            Ok(Ok(Ok(report))) => Ok((
                report.levels,
                report.shards_written,
                report.shards_skipped,
                report.shard_bytes,
                report.metadata_bytes,
            )),
            Ok(Ok(Err(e))) => Err(match e {
                strata_omezarr::OmeZarrError::Storage(e) => store_error(e),
                other => StoreError::new_err(format!("export to {dest}: {other}")),
            }),
            Ok(Err(_)) | Err(_) => Err(StrataError::new_err(format!(
                "internal error during the export to {dest} (a bug in Strata: please report it)"
            ))),
        }
    })
}

/// Imports `opened` into `dst` on a thread of its own; this thread waits with the GIL
/// released, calls `progress(done, total)` (bytes of the source) about ten times a second,
/// and cancels the import on Ctrl-C. Returns the import's report as JSON (statistics).
fn run_import(
    py: Python<'_>,
    opened: OpenedSource,
    dst: &Path,
    memory_mib: u64,
    codec: BrickCodec,
    progress: Option<&Bound<'_, PyAny>>,
) -> PyResult<String> {
    let done = AtomicU64::new(0);
    let total = AtomicU64::new(0);
    let cancel = AtomicBool::new(false);
    let finished = AtomicBool::new(false);
    std::thread::scope(|scope| {
        let worker = std::thread::Builder::new()
            .name("strata-py-import".into())
            .spawn_scoped(scope, || {
                let report_progress = |p: ImportProgress| {
                    done.store(p.source_bytes_done, Ordering::Relaxed);
                    total.store(p.source_bytes_total, Ordering::Relaxed);
                };
                let options = ImportOptions {
                    memory_budget_bytes: memory_mib << 20,
                    cancel: Some(&cancel),
                    progress: Some(&report_progress),
                    codec,
                };
                let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    import_source(opened, dst, &options)
                }));
                finished.store(true, Ordering::Release);
                result
            })
            .map_err(|e| StrataError::new_err(format!("cannot start the import thread: {e}")))?;
        let mut failure: Option<PyErr> = None;
        while !finished.load(Ordering::Acquire) {
            py.allow_threads(|| std::thread::sleep(Duration::from_millis(50)));
            if failure.is_some() {
                continue;
            }
            let step = match progress {
                Some(callback) => callback
                    .call1((done.load(Ordering::Relaxed), total.load(Ordering::Relaxed)))
                    .map(|_| ()),
                None => Ok(()),
            };
            if let Err(e) = step.and_then(|_| py.check_signals()) {
                cancel.store(true, Ordering::Relaxed);
                failure = Some(e);
            }
        }
        let joined = py.allow_threads(|| worker.join());
        let report = match joined {
            Ok(Ok(r)) => r,
            Ok(Err(payload)) | Err(payload) => {
                let text = payload
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| payload.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".into());
                return Err(StrataError::new_err(format!(
                    "internal error during the import into {}: {text} (a bug in Strata: please report it)",
                    dst.display()
                )));
            }
        };
        if let Some(e) = failure {
            return Err(e);
        }
        let report = report.map_err(|e| import_error(e, dst))?;
        if let Some(callback) = progress {
            let t = total.load(Ordering::Relaxed);
            callback.call1((t, t))?;
        }
        serde_json::to_string(&report.stats)
            .map_err(|e| StrataError::new_err(format!("statistics to JSON: {e}")))
    })
}

fn parse_codec(name: &str) -> PyResult<BrickCodec> {
    match BrickCodec::parse(name) {
        Some(c @ (BrickCodec::Fast | BrickCodec::Dense)) => Ok(c),
        _ => Err(PyValueError::new_err(format!(
            "'{name}' is not a codec: use 'fast' or 'dense'"
        ))),
    }
}

/// `strata import SRC DST`: opens `src` with the readers of `strata import` and imports it.
#[pyfunction]
#[pyo3(signature = (src, dst, progress=None, memory_mib=1024, codec="fast", series=None))]
fn import_file(
    py: Python<'_>,
    src: PathBuf,
    dst: PathBuf,
    progress: Option<&Bound<'_, PyAny>>,
    memory_mib: u64,
    codec: &str,
    series: Option<String>,
) -> PyResult<String> {
    let codec = parse_codec(codec)?;
    let options = ReadOptions {
        dicom_series: series,
        ..ReadOptions::default()
    };
    let opened = py.allow_threads(|| {
        no_panic("reading the input", || {
            open_source(&src, &options)
                .map_err(|e| SourceError::new_err(format!("cannot read {}: {e}", src.display())))
        })
    })?;
    run_import(py, opened, &dst, memory_mib, codec, progress)
}

fn sample_type(name: &str) -> PyResult<SampleType> {
    Ok(match name {
        "uint8" => SampleType::U8,
        "int8" => SampleType::I8,
        "uint16" => SampleType::U16,
        "int16" => SampleType::I16,
        "uint32" => SampleType::U32,
        "int32" => SampleType::I32,
        "float32" => SampleType::F32,
        "float64" => SampleType::F64,
        other => {
            return Err(PyValueError::new_err(format!(
                "dtype {other} is not importable (use uint8, int8, uint16, int16, uint32, int32, float32 or float64)"
            )))
        }
    })
}

/// Imports a raw file of `frames` volumes of `dims` (x, y, z) samples, x fastest, with the
/// geometry given (the numpy path: `strata.from_numpy` writes the array to `raw` first).
#[pyfunction]
#[pyo3(signature = (raw, dst, dims, frames, dtype, little_endian, spacing, origin, direction, slope, intercept, modality, description, progress=None, memory_mib=1024, codec="fast"))]
#[allow(clippy::too_many_arguments)]
fn import_raw(
    py: Python<'_>,
    raw: PathBuf,
    dst: PathBuf,
    dims: [u32; 3],
    frames: u32,
    dtype: &str,
    little_endian: bool,
    spacing: [f64; 3],
    origin: [f64; 3],
    direction: [[f64; 3]; 3],
    slope: f64,
    intercept: f64,
    modality: String,
    description: String,
    progress: Option<&Bound<'_, PyAny>>,
    memory_mib: u64,
    codec: &str,
) -> PyResult<String> {
    let codec = parse_codec(codec)?;
    let sample_type = sample_type(dtype)?;
    let geometry = VolumeGeometry {
        dims,
        spacing_mm: spacing,
        origin_lps_mm: origin,
        direction,
    };
    geometry
        .validate()
        .map_err(|e| PyValueError::new_err(format!("geometry: {e}")))?;
    if frames == 0 {
        return Err(PyValueError::new_err("an array of zero frames"));
    }
    let byte_order = if little_endian {
        ByteOrder::Little
    } else {
        ByteOrder::Big
    };
    let data_dims = [
        u64::from(dims[0]),
        u64::from(dims[1]),
        u64::from(dims[2]) * u64::from(frames),
    ];
    let data = py.allow_threads(|| {
        RawVolume::map_file(&raw, 0, sample_type, byte_order, data_dims)
            .map_err(|e| SourceError::new_err(e.to_string()))
    })?;
    let info = SourceInfo {
        path: raw.clone(),
        format: "numpy".into(),
        geometry,
        sample_type,
        slope,
        intercept,
        modality,
        windows: Vec::new(),
        description,
        inputs: Vec::new(),
        labels: Vec::new(),
        frames,
    };
    run_import(
        py,
        OpenedSource { info, data },
        &dst,
        memory_mib,
        codec,
        progress,
    )
}

#[pymodule]
fn _strata(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("StrataError", py.get_type::<StrataError>())?;
    m.add("StoreError", py.get_type::<StoreError>())?;
    m.add("StoreNotFoundError", py.get_type::<StoreNotFoundError>())?;
    m.add("DamagedStoreError", py.get_type::<DamagedStoreError>())?;
    m.add("StoreInUseError", py.get_type::<StoreInUseError>())?;
    m.add("SourceError", py.get_type::<SourceError>())?;
    m.add("RemoteError", py.get_type::<RemoteError>())?;
    m.add("TokenError", py.get_type::<TokenError>())?;
    m.add("RenderError", py.get_type::<render::RenderError>())?;
    m.add_class::<NativeStore>()?;
    m.add_function(wrap_pyfunction!(open_store, m)?)?;
    m.add_function(wrap_pyfunction!(import_file, m)?)?;
    m.add_function(wrap_pyfunction!(import_raw, m)?)?;
    m.add_function(wrap_pyfunction!(export_omezarr, m)?)?;
    m.add_class::<serve::NativeServer>()?;
    m.add_function(wrap_pyfunction!(serve::serve, m)?)?;
    m.add_function(wrap_pyfunction!(render::render, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
