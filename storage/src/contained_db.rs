//! The store's boundary around sled: what sled does wrong on damaged files or a full disk stays
//! inside it.
//!
//! sled 0.34 (the store's database) panics on some damaged files ("tried to serialize
//! Uninitialized", an index out of bounds in the segment reader), waits forever in the flush a
//! handle runs when it is dropped after a write failed ("No space left on device"), and can spin
//! in its blob reader on a damaged blob. Every sled call the store makes goes through here:
//! - [`contained`] turns a panic inside sled into a damage error naming the store (and keeps the
//!   default panic message off the terminal, since it is reported as an error instead);
//! - [`SledHandles`] closes on a named thread and waits a bounded time: a flush that never returns
//!   becomes an error (explicit close) or is abandoned (drop), never a hung process;
//! - [`call_bounded`] runs one read with a time limit, for `verify`, which must terminate.

use std::cell::Cell;
use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};
use std::sync::Once;
use std::time::Duration;

use crate::error::{Result, StorageError};

/// How long a drop waits for sled to close a store that failed: nothing more will be saved.
const ABANDON_AFTER: Duration = Duration::from_secs(2);

thread_local! {
    /// Depth of [`contained`] calls on this thread; the panic hook stays quiet inside them.
    static CONTAINED_DEPTH: Cell<u32> = const { Cell::new(0) };
}

fn install_quiet_panic_hook() {
    static HOOK: Once = Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if CONTAINED_DEPTH.with(Cell::get) == 0 {
                previous(info);
            }
        }));
    });
}

fn panic_text(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}

/// Runs one sled call for the store at `path`: its error is classified
/// ([`StorageError::db`]), a panic becomes [`StorageError::Corrupted`] saying what failed.
pub(crate) fn contained<T>(
    path: &Path,
    what: &str,
    call: impl FnOnce() -> sled::Result<T>,
) -> Result<T> {
    install_quiet_panic_hook();
    CONTAINED_DEPTH.with(|d| d.set(d.get() + 1));
    let outcome = std::panic::catch_unwind(AssertUnwindSafe(call));
    CONTAINED_DEPTH.with(|d| d.set(d.get() - 1));
    match outcome {
        Ok(Ok(value)) => Ok(value),
        Ok(Err(e)) => Err(StorageError::db(path, e)),
        Err(payload) => Err(StorageError::corrupted(
            path,
            format!(
                "the database is damaged: {what} failed inside sled ({})",
                panic_text(payload.as_ref())
            ),
        )),
    }
}

/// Runs `call` on a named thread and waits at most `limit` for it. A call that does not return
/// in time is left running (it holds only its own clones of sled handles) and reported.
pub(crate) fn call_bounded<T: Send + 'static>(
    path: &Path,
    what: &str,
    limit: Duration,
    call: impl FnOnce() -> Result<T> + Send + 'static,
) -> Result<T> {
    let (done, outcome) = crossbeam_channel::bounded(1);
    let spawned = std::thread::Builder::new()
        .name("strata-store-bounded".into())
        .spawn(move || {
            let _ = done.send(call());
        });
    if let Err(e) = spawned {
        return Err(StorageError::io(path, e));
    }
    match outcome.recv_timeout(limit) {
        Ok(result) => result,
        Err(_) => Err(StorageError::corrupted(
            path,
            format!(
                "{what} did not finish within {} s: the database is damaged or stuck",
                limit.as_secs()
            ),
        )),
    }
}

/// A store's open sled database and trees, closed within a time bound.
pub(crate) struct SledHandles {
    path: PathBuf,
    /// `None` once closed (see [`SledHandles::closed`]) or during drop.
    open: Option<(sled::Db, Vec<sled::Tree>)>,
}

impl SledHandles {
    pub(crate) fn new(path: &Path, db: sled::Db, trees: Vec<sled::Tree>) -> Self {
        SledHandles {
            path: path.to_path_buf(),
            open: Some((db, trees)),
        }
    }

    pub(crate) fn open_tree(&self, name: &str) -> sled::Result<sled::Tree> {
        match &self.open {
            Some((db, _)) => db.open_tree(name),
            None => Err(sled::Error::Unsupported("the store is closed".into())),
        }
    }

    /// Handles that hold nothing (what a closed owner keeps).
    pub(crate) fn closed(path: &Path) -> Self {
        SledHandles {
            path: path.to_path_buf(),
            open: None,
        }
    }

    /// Flushes everything written so far to disk, or says why not within `limit`.
    pub(crate) fn flush(&self, limit: Duration) -> Result<()> {
        let Some((db, _)) = &self.open else {
            return Err(StorageError::invalid(&self.path, "the store is closed"));
        };
        let db = db.clone();
        let path = self.path.clone();
        call_bounded(&self.path, "writing to disk", limit, move || {
            contained(&path, "flush", || db.flush().map(|_| ()))
        })
        .map_err(|e| match e {
            // A flush that never returns after writes is, in practice, a full disk.
            StorageError::Corrupted { path, message } if message.contains("did not finish") => {
                StorageError::DiskFull {
                    path,
                    message: format!(
                        "the database could not write its data within {} s (full disk or failing device)",
                        limit.as_secs()
                    ),
                }
            }
            other => other,
        })
    }

    /// Closes the database without flushing it again, waiting at most `limit` for sled's own
    /// close (which flushes); a close that hangs is abandoned on its thread.
    fn close_within(&mut self, limit: Duration) {
        let Some(handles) = self.open.take() else {
            return;
        };
        let (done, closed) = crossbeam_channel::bounded::<()>(1);
        let spawned = std::thread::Builder::new()
            .name("strata-store-close".into())
            .spawn(move || {
                drop(handles);
                let _ = done.send(());
            });
        if spawned.is_ok() {
            let _ = closed.recv_timeout(limit);
        }
    }
}

impl Drop for SledHandles {
    fn drop(&mut self) {
        self.close_within(ABANDON_AFTER);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_inside_the_call_becomes_a_damage_error_naming_the_store() {
        let err = contained(Path::new("/stores/x.strata"), "reading the header", || {
            if true {
                panic!("index out of bounds: the len is 3 but the index is 7");
            }
            Ok(())
        })
        .unwrap_err();
        let text = err.to_string();
        assert!(err.is_damage(), "{text}");
        assert!(text.starts_with("/stores/x.strata: "), "{text}");
        assert!(
            text.contains("reading the header failed inside sled"),
            "{text}"
        );
        assert!(text.contains("index out of bounds"), "{text}");
    }

    #[test]
    fn a_call_that_never_returns_is_reported_after_its_limit() {
        let err = call_bounded(
            Path::new("/stores/y.strata"),
            "reading brick 3",
            Duration::from_millis(50),
            || -> Result<()> {
                std::thread::sleep(Duration::from_secs(3600));
                Ok(())
            },
        )
        .unwrap_err();
        assert!(
            err.to_string().contains("reading brick 3 did not finish"),
            "{err}"
        );
    }
}
