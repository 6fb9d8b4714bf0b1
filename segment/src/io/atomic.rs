//! Saving that replaces a file only once the new one is complete (issue 52 item 4): the new
//! content goes to a temporary file beside the target, is synced, and is then renamed over the
//! target (atomic on POSIX within a file system), and the directory is synced so the rename
//! survives a crash. A failed or interrupted save leaves the previous file as it was and
//! removes its temporary file (`io::nifti::tests::a_failed_save_keeps_the_previous_file`).

use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::SegmentError;

/// The temporary name a save of `target` writes to first (hidden, beside it, per process).
pub fn temporary_path_for(target: &Path) -> PathBuf {
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "labels".into());
    target.with_file_name(format!(".{name}.partial-{}", std::process::id()))
}

/// Writes `target` through `write` into a temporary file, then renames it into place.
pub fn write_file_atomically<F>(target: &Path, write: F) -> Result<(), SegmentError>
where
    F: FnOnce(&mut BufWriter<File>) -> Result<(), SegmentError>,
{
    let temp = temporary_path_for(target);
    let io = |path: &Path, e| SegmentError::Io {
        path: path.to_path_buf(),
        source: e,
    };
    let result = (|| {
        let file = OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .open(&temp)
            .map_err(|e| io(&temp, e))?;
        let mut out = BufWriter::with_capacity(1 << 20, file);
        write(&mut out)?;
        out.flush().map_err(|e| io(target, e))?;
        let file = out.into_inner().map_err(|e| io(target, e.into_error()))?;
        file.sync_all().map_err(|e| io(target, e))?;
        drop(file);
        std::fs::rename(&temp, target).map_err(|e| io(target, e))?;
        sync_dir_of(target)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result
}

/// Syncs the directory holding `path`, so a rename or a new entry in it is durable (Unix).
pub fn sync_dir_of(path: &Path) -> Result<(), SegmentError> {
    #[cfg(unix)]
    {
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        File::open(dir)
            .and_then(|d| d.sync_all())
            .map_err(|e| SegmentError::Io {
                path: dir.to_path_buf(),
                source: e,
            })?;
    }
    #[cfg(not(unix))]
    let _ = path;
    Ok(())
}
