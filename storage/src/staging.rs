//! Streaming decompression into a temporary raw file, so compressed inputs never sit in memory.
//!
//! Compressed inputs are read to their end, so gzip's CRC-32 and length and zlib's Adler-32 are
//! checked. Free space is checked before writing; the staging file is locked by its owner and
//! removed on Ctrl-C/SIGTERM (the binary's handler) and, after SIGKILL, by the next run (a dead
//! owner no longer holds the lock).

use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use tempfile::NamedTempFile;

use crate::error::{Result, StorageError};

/// Bounded buffer for every staging copy: large enough to amortise syscalls, small next to a volume.
const CHUNK: usize = 1 << 20;

/// Name prefix of every staging file; with the lock each holds, it lets a later run find and
/// delete the files of processes that were killed.
const STAGING_PREFIX: &str = "strata-staging-";
const STAGING_SUFFIX: &str = ".raw";

/// A staging file unchanged for this long and unlocked belongs to a dead process.
const STALE_AFTER: std::time::Duration = std::time::Duration::from_secs(30);

/// Slack kept free on the staging disk beyond the decompressed volume, so staging never takes
/// the last bytes another program needs.
const STAGING_FREE_MARGIN: u64 = 64 << 20;

/// Staging files of this process that a signal handler must delete ([`remove_live_staging_files`]).
static LIVE_STAGING: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

fn live_staging() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    LIVE_STAGING.lock().unwrap_or_else(|p| p.into_inner())
}

/// A temporary file of decompressed voxels: deleted on drop, locked while it lives (so a later
/// run can tell a dead process's file from a live one), and listed for signal handlers.
pub struct StagingFile {
    file: NamedTempFile,
}

impl StagingFile {
    pub(crate) fn as_file_mut(&mut self) -> &mut std::fs::File {
        self.file.as_file_mut()
    }
    pub(crate) fn path(&self) -> &Path {
        self.file.path()
    }
    pub(crate) fn reopen(&self) -> std::io::Result<std::fs::File> {
        self.file.reopen()
    }
}

impl Drop for StagingFile {
    fn drop(&mut self) {
        let path = self.file.path().to_path_buf();
        live_staging().retain(|p| p != &path);
    }
}

/// Deletes the staging files this process has open. For signal handlers (Ctrl-C, SIGTERM),
/// which end the process without running destructors; returns how many were deleted.
pub fn remove_live_staging_files() -> usize {
    let paths = std::mem::take(&mut *live_staging());
    paths
        .iter()
        .filter(|p| std::fs::remove_file(p).is_ok())
        .count()
}

/// Deletes staging files in `dir` left by processes that died (SIGKILL, power loss): a live
/// owner holds its file's lock, a dead one does not, and the file has not changed for
/// [`STALE_AFTER`] (so one being created right now is never taken). Returns how many were
/// deleted.
pub fn remove_stale_staging_files(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let mut removed = 0;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let name = name.to_string_lossy();
        if !name.starts_with(STAGING_PREFIX) || !name.ends_with(STAGING_SUFFIX) {
            continue;
        }
        if !entry.file_type().is_ok_and(|t| t.is_file()) {
            continue;
        }
        // A file created a moment ago may not be locked yet by its (live) owner: only files
        // untouched for a while are candidates. A live owner writes or holds the lock.
        let recent = entry
            .metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.elapsed().ok())
            .is_none_or(|age| age < STALE_AFTER);
        if recent {
            continue;
        }
        let path = entry.path();
        // Non-blocking, and the type checked on the open file: the entry may have been
        // replaced by a FIFO since the listing, whose open would wait for a writer.
        let mut options = std::fs::OpenOptions::new();
        options.read(true).write(true);
        #[cfg(unix)]
        std::os::unix::fs::OpenOptionsExt::custom_flags(&mut options, libc::O_NONBLOCK);
        let Ok(file) = options.open(&path) else {
            continue;
        };
        if !file.metadata().is_ok_and(|m| m.is_file()) {
            continue;
        }
        if file.try_lock().is_ok() && std::fs::remove_file(&path).is_ok() {
            removed += 1;
        }
    }
    removed
}

/// Creates a staging file for `bytes` of decompressed voxels from `source`. Removes stale
/// staging files first, and refuses (naming the staging folder, not the input) when the folder's
/// disk cannot hold the data: a header may claim terabytes.
pub(crate) fn new_staging(
    source: &Path,
    staging_dir: Option<&Path>,
    bytes: u64,
) -> Result<StagingFile> {
    let dir = staging_dir.map_or_else(std::env::temp_dir, Path::to_path_buf);
    remove_stale_staging_files(&dir);
    if let Ok(free) = fs2::available_space(&dir) {
        if free < bytes.saturating_add(STAGING_FREE_MARGIN) {
            return Err(StorageError::DiskFull {
                path: dir,
                message: format!(
                    "staging folder: decompressing {} needs {} MB, {} MB are free; choose another folder with --staging-dir",
                    source.display(),
                    bytes.div_ceil(1_000_000),
                    free / 1_000_000
                ),
            });
        }
    }
    let file = tempfile::Builder::new()
        .prefix(STAGING_PREFIX)
        .suffix(STAGING_SUFFIX)
        .tempfile_in(&dir)
        .map_err(|e| {
            StorageError::io(
                &dir,
                std::io::Error::new(e.kind(), format!("creating a staging file: {e}")),
            )
        })?;
    // A lock that cannot be taken only weakens the stale-file cleanup; staging still works.
    let _ = file.as_file().try_lock();
    live_staging().push(file.path().to_path_buf());
    Ok(StagingFile { file })
}

/// Reads and discards `n` bytes (a header or byte skip inside a compressed stream).
pub(crate) fn skip_bytes(path: &Path, reader: &mut impl Read, n: u64, what: &str) -> Result<()> {
    let copied = std::io::copy(&mut reader.by_ref().take(n), &mut std::io::sink())
        .map_err(|e| StorageError::invalid(path, format!("reading {what}: {e}")))?;
    if copied < n {
        return Err(StorageError::invalid(
            path,
            format!("truncated data: stream ended after {copied} of {n} bytes of {what}"),
        ));
    }
    Ok(())
}

/// Most decompressed bytes accepted after the volume (padding is common in the wild): they are
/// read to reach the stream's checksum trailer, so they must be bounded.
const MAX_TRAILING_BYTES: u64 = 64 << 20;

/// Copies exactly `expected` bytes of `reader` into `staging`, then reads the stream to its end
/// so the decoder checks the trailer (gzip CRC-32 and length, zlib Adler-32): a corrupt or
/// truncated compressed input is an error, never a volume of wrong voxels. A short stream is an
/// error naming both sizes; up to [`MAX_TRAILING_BYTES`] of padding after the volume are allowed.
pub(crate) fn stream_into(
    path: &Path,
    reader: &mut impl Read,
    staging: &mut StagingFile,
    expected: u64,
) -> Result<()> {
    let staging_path = staging.path().to_path_buf();
    // A write failure is the staging disk's, not the input's: name the staging file.
    let staging_write_error = |e: std::io::Error| {
        let message = format!("writing decompressed voxels: {e}");
        if crate::error::is_disk_full(&e) {
            StorageError::DiskFull {
                path: staging_path.clone(),
                message,
            }
        } else {
            StorageError::io(&staging_path, std::io::Error::new(e.kind(), message))
        }
    };
    let mut out = BufWriter::with_capacity(CHUNK, staging.as_file_mut());
    let mut buf = vec![0u8; CHUNK];
    let mut done: u64 = 0;
    while done < expected {
        let want = (expected - done).min(CHUNK as u64) as usize;
        let n = match reader.read(&mut buf[..want]) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => {
                return Err(StorageError::invalid(
                    path,
                    format!("compressed data truncated or corrupt after {done} of {expected} bytes of voxels: {e}"),
                ))
            }
        };
        out.write_all(&buf[..n]).map_err(staging_write_error)?;
        done += n as u64;
    }
    out.flush().map_err(staging_write_error)?;
    if done < expected {
        return Err(StorageError::invalid(
            path,
            format!("truncated data: expected {expected} bytes of voxels, the compressed stream holds only {done}"),
        ));
    }
    let trailing = std::io::copy(
        &mut reader.by_ref().take(MAX_TRAILING_BYTES + 1),
        &mut std::io::sink(),
    )
    .map_err(|e| {
        StorageError::invalid(
            path,
            format!("compressed data is corrupt (its checksum trailer does not match, or the stream is cut short after the voxels): {e}"),
        )
    })?;
    if trailing > MAX_TRAILING_BYTES {
        return Err(StorageError::invalid(
            path,
            format!("more than {} MB of data after the volume's {expected} bytes: the header's dimensions or type do not match the data", MAX_TRAILING_BYTES >> 20),
        ));
    }
    Ok(())
}
