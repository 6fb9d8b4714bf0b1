//! The stores in a folder (the viewer's data folder): what each is, how much disk it takes, and
//! which can go. Backs `strata store list` and `strata store prune`.
//!
//! A store is only ever removed under its own lock, taken for writing: a store another process
//! has open (a viewer, `strata serve`, an import in progress) is reported as in use and left
//! alone, and nobody can open it while it is being removed.

use std::path::{Path, PathBuf};

use crate::brick::BrickCodec;
use crate::error::{Result, StorageError};
use crate::lock::{LockHolder, LockPurpose, StoreLock, LOCK_FILE};
use crate::store::Store;

/// What a store folder holds, as far as can be told without changing it.
#[derive(Clone, Debug, PartialEq)]
pub enum StoreState {
    /// Opens; format and codec from its header, source from its provenance.
    Complete {
        format_version: u32,
        codec: BrickCodec,
        inputs: Vec<String>,
    },
    /// An import that did not finish (killed, cancelled, crashed).
    Incomplete,
    /// Another process holds it.
    InUse(LockHolder),
    /// Written by a newer Strata (or another format this build cannot read).
    Unsupported(String),
    /// Does not open: the message says why.
    Damaged(String),
}

/// One store of a folder.
#[derive(Clone, Debug, PartialEq)]
pub struct StoreEntry {
    pub path: PathBuf,
    /// Bytes of every file under the store's folder.
    pub size_bytes: u64,
    /// The format named by the store's marker file (known even when the store does not open).
    pub marker_format_version: Option<u32>,
    pub state: StoreState,
}

/// Why `strata store prune` would remove a store; None for a store it keeps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PruneReason {
    Incomplete,
    Damaged,
    /// Format 1: still opens, but is larger than a rebuild would be and its source still exists.
    OldFormat,
    /// Its recorded source files are all gone: nothing will ask for this store by that source.
    Orphaned,
}

impl PruneReason {
    pub fn describe(self) -> &'static str {
        match self {
            PruneReason::Incomplete => "incomplete import",
            PruneReason::Damaged => "damaged",
            PruneReason::OldFormat => "old format, source still there to re-import",
            PruneReason::Orphaned => "orphaned: its source files are gone",
        }
    }
}

impl StoreEntry {
    /// Whether (and why) prune removes this store. Never for one in use or of a newer format.
    pub fn prune_reason(&self) -> Option<PruneReason> {
        match &self.state {
            StoreState::Incomplete => Some(PruneReason::Incomplete),
            StoreState::Damaged(_) => Some(PruneReason::Damaged),
            StoreState::InUse(_) | StoreState::Unsupported(_) => None,
            StoreState::Complete {
                format_version,
                inputs,
                ..
            } => {
                let any_input_left = inputs.iter().any(|i| Path::new(i).exists());
                if !inputs.is_empty() && !any_input_left {
                    Some(PruneReason::Orphaned)
                } else if *format_version < PRUNED_BELOW_FORMAT_VERSION && any_input_left {
                    Some(PruneReason::OldFormat)
                } else {
                    None
                }
            }
        }
    }
}

/// Formats below this are pruned when their source is still there. Format 2 (sled) is not:
/// it still opens, and `strata store upgrade` converts it to format 3 without the source.
const PRUNED_BELOW_FORMAT_VERSION: u32 = 2;

/// The marker file's name (see `store`), which every store folder has from its creation on.
const MARKER_FILE: &str = "STRATA-STORE";

/// The stores directly inside `folder`, sorted by path. Folders that are not stores are skipped;
/// a missing folder has no stores.
pub fn list_stores(folder: &Path) -> Result<Vec<StoreEntry>> {
    let entries = match std::fs::read_dir(folder) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(StorageError::io(folder, e)),
    };
    let mut stores = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| StorageError::io(folder, e))?;
        let path = entry.path();
        if path.join(MARKER_FILE).is_file() {
            stores.push(survey(&path));
        }
    }
    stores.sort_by(|a, b| a.path.cmp(&b.path));
    Ok(stores)
}

/// Describes one store folder (opening it briefly, read-only, when nobody holds it).
pub fn survey(path: &Path) -> StoreEntry {
    let marker = crate::regular_file::read_to_string(&path.join(MARKER_FILE)).unwrap_or_default();
    let marker_format_version = marker
        .lines()
        .next()
        .and_then(|l| l.strip_prefix("strata store format "))
        .and_then(|v| v.trim().parse().ok());
    // A small cache: only the header and skeleton are read.
    let state = match Store::open_with_cache(path, 4 << 20) {
        Ok(store) => {
            let h = store.header();
            let state = StoreState::Complete {
                format_version: h.format_version,
                codec: h.codec,
                inputs: h.provenance.inputs.clone(),
            };
            // A failure to close leaves the store as it was: still listed correctly.
            let _ = store.close();
            state
        }
        Err(StorageError::InUse { holder, .. }) => StoreState::InUse(holder),
        Err(StorageError::IncompleteImport { .. }) => StoreState::Incomplete,
        Err(e @ StorageError::Unsupported { .. }) => StoreState::Unsupported(e.to_string()),
        Err(e) => StoreState::Damaged(e.to_string()),
    };
    StoreEntry {
        path: path.to_path_buf(),
        size_bytes: folder_bytes(path),
        marker_format_version,
        state,
    }
}

/// Bytes of the files under `path` (links not followed; unreadable entries count 0).
pub fn folder_bytes(path: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(path) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => folder_bytes(&e.path()),
            Ok(t) if t.is_file() => e.metadata().map_or(0, |m| m.len()),
            _ => 0,
        })
        .sum()
}

/// Removes the store at `path` under its lock; refuses a folder that is not a store, and a store
/// another process holds ([`StorageError::InUse`]). Returns the bytes freed.
pub fn remove_store(path: &Path) -> Result<u64> {
    if !path.join(MARKER_FILE).is_file() {
        return Err(StorageError::NotAStore {
            path: path.to_path_buf(),
            message: format!("no {MARKER_FILE} marker: not removed"),
        });
    }
    let lock = StoreLock::acquire(path, LockPurpose::Import)?;
    let bytes = folder_bytes(path);
    for entry in std::fs::read_dir(path).map_err(|e| StorageError::io(path, e))? {
        let entry = entry.map_err(|e| StorageError::io(path, e))?;
        if entry.file_name() == LOCK_FILE {
            continue;
        }
        let p = entry.path();
        let removed = if entry.file_type().is_ok_and(|t| t.is_dir()) {
            std::fs::remove_dir_all(&p)
        } else {
            std::fs::remove_file(&p)
        };
        removed.map_err(|e| StorageError::io(&p, e))?;
    }
    // The lock file goes last, with the folder, while still held: a process that opened it in
    // the meantime finds no marker and no store.
    std::fs::remove_dir_all(path).map_err(|e| StorageError::io(path, e))?;
    drop(lock);
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::import::{import_source, ImportOptions};
    use crate::phantom::Phantom;
    use crate::readers::{open_source, ReadOptions};

    #[test]
    fn lists_complete_incomplete_old_and_in_use_stores_and_prunes_only_what_may_go() {
        let dir = tempfile::tempdir().unwrap();
        let folder = dir.path();
        let source = folder.join("scan.nrrd");
        // Stores imported from real files, so their provenance names them.
        let import = |name: &str, input: &Path, codec: BrickCodec| {
            Phantom::cube(24).write_nrrd(input, None).unwrap();
            let path = folder.join(name);
            let options = ImportOptions {
                codec,
                ..Default::default()
            };
            let opened = open_source(input, &ReadOptions::default()).unwrap();
            import_source(opened, &path, &options).unwrap();
            path
        };
        let current = import("current.strata", &source, BrickCodec::Dense);
        let old = import("old.strata", &source, BrickCodec::Lz4);
        let gone = folder.join("deleted.nrrd");
        let orphan = import("orphan.strata", &gone, BrickCodec::Fast);
        let busy = import("busy.strata", &gone, BrickCodec::Fast);
        std::fs::remove_file(&gone).unwrap();
        // What a killed import leaves: a marker and a database with bricks, no completion.
        let incomplete = folder.join("incomplete.strata");
        std::fs::create_dir(&incomplete).unwrap();
        std::fs::write(incomplete.join(MARKER_FILE), "strata store format 2\n").unwrap();
        {
            let db = sled::open(incomplete.join("db")).unwrap();
            db.open_tree("bricks").unwrap().insert(b"k", b"v").unwrap();
            db.flush().unwrap();
        }
        std::fs::create_dir(folder.join("not-a-store")).unwrap();

        // A reader of a format-3 store does not make it busy (readers share it); a writer does.
        let reader = Store::open(&current).unwrap();
        let held = StoreLock::acquire(&busy, LockPurpose::Import).unwrap();
        let stores = list_stores(folder).unwrap();
        let names: Vec<_> = stores
            .iter()
            .map(|s| s.path.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(
            names,
            [
                "busy.strata",
                "current.strata",
                "incomplete.strata",
                "old.strata",
                "orphan.strata"
            ]
        );
        let reasons: Vec<_> = stores.iter().map(|s| s.prune_reason()).collect();
        assert_eq!(
            reasons,
            [
                None,
                None,
                Some(PruneReason::Incomplete),
                Some(PruneReason::OldFormat),
                Some(PruneReason::Orphaned)
            ]
        );
        assert!(matches!(stores[0].state, StoreState::InUse(_)));
        assert!(matches!(
            stores[1].state,
            StoreState::Complete {
                format_version: 3,
                codec: BrickCodec::Dense,
                ..
            }
        ));
        assert_eq!(stores[3].marker_format_version, Some(1));
        assert!(stores.iter().all(|s| s.size_bytes > 0));

        // In use: refused, and still there.
        assert!(matches!(
            remove_store(&busy),
            Err(StorageError::InUse { .. })
        ));
        assert!(Store::open(&current).is_ok());
        drop(held);
        drop(reader);
        let _ = old;
        assert!(busy.join(MARKER_FILE).is_file());
        // Not a store: refused.
        assert!(remove_store(&folder.join("not-a-store")).is_err());
        assert!(folder.join("not-a-store").is_dir());
        let freed = remove_store(&orphan).unwrap();
        assert!(freed > 0);
        assert!(!orphan.exists());
        assert!(source.exists());
        assert!(remove_store(&incomplete).unwrap() > 0);
        assert_eq!(list_stores(folder).unwrap().len(), 3);
    }
}
