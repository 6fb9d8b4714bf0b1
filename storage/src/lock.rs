//! Who holds a store: one lock file per store, held by every process that has it open.
//!
//! sled 0.34 opens a database read-write with an exclusive lock of its own, so one process at a
//! time can use a store. sled's lock says nothing about *who* holds it, and a second open waits
//! and then fails with a database error. This lock comes first: `strata.lock` inside the store
//! folder, locked with the OS's advisory file lock (`flock` on Unix, `LockFileEx` on Windows,
//! released by the OS when the holder dies, so a killed process never leaves a stale lock) and
//! holding a JSON record of the holder: its pid, what it does with the store, and the URL of the
//! `strata serve` that streams it, if any. A second process is refused at once with that record:
//! "in use by pid N", or "served by pid N at URL" so it can stream from there instead.
//!
//! The lock file itself is never deleted while a store lives (deleting a lock file that someone
//! else is about to lock is the classic race); its record is emptied on release.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::error::{Result, StorageError};
pub use crate::lock_holder::{LockHolder, LockPurpose};

/// The lock file's name inside a store folder.
pub const LOCK_FILE: &str = "strata.lock";

/// Bound on the holder record we read back: it is a few dozen bytes of JSON; a larger file is
/// not ours, and is never read whole.
const MAX_RECORD_BYTES: u64 = 4096;

/// A held lock; released (record emptied, OS lock dropped) when dropped.
#[derive(Debug)]
pub struct StoreLock {
    file: File,
    lock_path: PathBuf,
    holder: LockHolder,
}

impl StoreLock {
    /// Takes the lock of the store folder `store_dir` (which must exist), or says at once who
    /// holds it ([`StorageError::InUse`]) or why it cannot be taken (read-only media).
    pub fn acquire(store_dir: &Path, purpose: LockPurpose) -> Result<StoreLock> {
        let lock_path = store_dir.join(LOCK_FILE);
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&lock_path)
            .map_err(|e| open_error(store_dir, e))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                return Err(StorageError::InUse {
                    path: store_dir.to_path_buf(),
                    holder: read_record(&file).unwrap_or(LockHolder {
                        pid: 0,
                        purpose: LockPurpose::Read,
                        url: None,
                    }),
                })
            }
            Err(std::fs::TryLockError::Error(e)) => {
                return Err(StorageError::io(
                    &lock_path,
                    std::io::Error::new(e.kind(), format!("locking the store: {e}")),
                ))
            }
        }
        let mut lock = StoreLock {
            file,
            lock_path,
            holder: LockHolder {
                pid: std::process::id(),
                purpose,
                url: None,
            },
        };
        lock.write_record()?;
        Ok(lock)
    }

    /// Records the URL that streams this store, so a local open says where to go instead.
    pub fn advertise_url(&mut self, url: &str) -> Result<()> {
        self.holder.url = Some(url.to_string());
        self.write_record()
    }

    pub fn holder(&self) -> &LockHolder {
        &self.holder
    }

    fn write_record(&mut self) -> Result<()> {
        let json = serde_json::to_vec(&self.holder)
            .map_err(|e| StorageError::invalid(&self.lock_path, e.to_string()))?;
        let io = |e| StorageError::io(&self.lock_path, e);
        self.file.set_len(0).map_err(io)?;
        self.file.seek(SeekFrom::Start(0)).map_err(io)?;
        self.file.write_all(&json).map_err(io)?;
        self.file.flush().map_err(io)
    }
}

impl Drop for StoreLock {
    fn drop(&mut self) {
        // Empty the record before the OS lock goes with the file handle; failure only leaves a
        // record that `current_holder` ignores, because nobody holds the lock any more.
        let _ = self.file.set_len(0);
        let _ = self.file.unlock();
    }
}

/// A reader's shared lock on a format-3 store: taken on the lock file if it exists, opened
/// read-only, so that taking it writes nothing (a store on read-only media without a lock file
/// is read without one). Any number of readers hold it at once; a writer's exclusive
/// [`StoreLock`] is refused while one does, and a reader is refused while a writer holds that.
#[derive(Debug)]
pub struct SharedStoreLock {
    _file: File,
}

impl SharedStoreLock {
    pub fn acquire(store_dir: &Path) -> Result<Option<SharedStoreLock>> {
        let lock_path = store_dir.join(LOCK_FILE);
        let file = match crate::regular_file::open(&lock_path) {
            Ok(f) => f,
            Err(StorageError::Io { source, .. })
                if source.kind() == std::io::ErrorKind::NotFound =>
            {
                return Ok(None)
            }
            Err(e) => return Err(e),
        };
        match file.try_lock_shared() {
            Ok(()) => Ok(Some(SharedStoreLock { _file: file })),
            Err(std::fs::TryLockError::WouldBlock) => Err(StorageError::InUse {
                path: store_dir.to_path_buf(),
                holder: read_record(&file).unwrap_or(LockHolder {
                    pid: 0,
                    purpose: LockPurpose::Import,
                    url: None,
                }),
            }),
            Err(std::fs::TryLockError::Error(e)) => Err(StorageError::io(
                &lock_path,
                std::io::Error::new(e.kind(), format!("locking the store: {e}")),
            )),
        }
    }
}

/// Who holds the store at `store_dir` now, if anyone (a live process: the OS releases the lock
/// of a dead one).
pub fn current_holder(store_dir: &Path) -> Option<LockHolder> {
    let file = File::open(store_dir.join(LOCK_FILE)).ok()?;
    match file.try_lock_shared() {
        Ok(()) => {
            let _ = file.unlock();
            None
        }
        Err(std::fs::TryLockError::WouldBlock) => read_record(&file),
        Err(std::fs::TryLockError::Error(_)) => None,
    }
}

fn read_record(file: &File) -> Option<LockHolder> {
    let mut text = Vec::new();
    let mut reader = file;
    reader.seek(SeekFrom::Start(0)).ok()?;
    reader.take(MAX_RECORD_BYTES).read_to_end(&mut text).ok()?;
    serde_json::from_slice(&text).ok()
}

/// Opening the lock file is the first write a store open makes, so read-only media show here:
/// say so with the remedy, never as a database error later.
fn open_error(store_dir: &Path, e: std::io::Error) -> StorageError {
    use std::io::ErrorKind;
    match e.kind() {
        ErrorKind::ReadOnlyFilesystem | ErrorKind::PermissionDenied => StorageError::ReadOnly {
            path: store_dir.to_path_buf(),
            reason: e.to_string(),
        },
        _ => StorageError::io(
            store_dir.join(LOCK_FILE),
            std::io::Error::new(e.kind(), format!("creating the store's lock file: {e}")),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn second_holder_is_refused_with_the_first_holders_record() {
        let dir = tempfile::tempdir().unwrap();
        let mut first = StoreLock::acquire(dir.path(), LockPurpose::Serve).unwrap();
        first
            .advertise_url("http://127.0.0.1:1234/v1/stores/x")
            .unwrap();
        match StoreLock::acquire(dir.path(), LockPurpose::Read) {
            Err(StorageError::InUse { holder, .. }) => {
                assert_eq!(holder.pid, std::process::id());
                assert_eq!(holder.purpose, LockPurpose::Serve);
                assert_eq!(
                    holder.url.as_deref(),
                    Some("http://127.0.0.1:1234/v1/stores/x")
                );
            }
            other => panic!("expected InUse, got {other:?}"),
        }
        assert_eq!(
            current_holder(dir.path()).map(|h| h.purpose),
            Some(LockPurpose::Serve)
        );
        drop(first);
        assert_eq!(current_holder(dir.path()), None);
        let again = StoreLock::acquire(dir.path(), LockPurpose::Import).unwrap();
        assert_eq!(again.holder().purpose, LockPurpose::Import);
    }

    #[test]
    fn a_folder_without_a_lock_file_has_no_holder() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(current_holder(dir.path()), None);
    }
}
