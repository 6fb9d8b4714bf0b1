//! Opening files that must be regular files, without ever blocking on one that is not.
//!
//! `File::open` on a FIFO waits for a writer, possibly for ever, and a device may never end, so
//! a check of the path before the open leaves a window (the path can be replaced in between)
//! and is not enough. Here the file is opened non-blocking (a FIFO opens at once), its type
//! checked on the open descriptor (`fstat`), and only a regular file is handed back, switched
//! to blocking reads again.

use std::fs::File;
use std::io::Read;
use std::path::Path;

use crate::error::{Result, StorageError};

/// Opens `path` for reading if it is a regular file; anything else (a FIFO, socket, device or
/// folder) is an error naming it, returned without blocking.
pub fn open(path: &Path) -> Result<File> {
    let file = open_nonblocking(path).map_err(|e| StorageError::io(path, e))?;
    let meta = file.metadata().map_err(|e| StorageError::io(path, e))?;
    if !meta.is_file() {
        return Err(StorageError::invalid(
            path,
            "not a regular file (a FIFO, socket, device or folder); refusing to read it",
        ));
    }
    set_blocking(&file).map_err(|e| StorageError::io(path, e))?;
    Ok(file)
}

/// [`open`], then the whole file as text.
pub fn read_to_string(path: &Path) -> Result<String> {
    let mut text = String::new();
    open(path)?
        .read_to_string(&mut text)
        .map_err(|e| StorageError::io(path, e))?;
    Ok(text)
}

/// [`open`], then the whole file.
pub fn read(path: &Path) -> Result<Vec<u8>> {
    let mut bytes = Vec::new();
    open(path)?
        .read_to_end(&mut bytes)
        .map_err(|e| StorageError::io(path, e))?;
    Ok(bytes)
}

#[cfg(unix)]
fn open_nonblocking(path: &Path) -> std::io::Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
}

#[cfg(unix)]
fn set_blocking(file: &File) -> std::io::Result<()> {
    use std::os::fd::AsRawFd;
    let fd = file.as_raw_fd();
    // SAFETY: fcntl on a descriptor this function's caller owns, with no pointers.
    let flags = unsafe { libc::fcntl(fd, libc::F_GETFL) };
    if flags < 0 {
        return Err(std::io::Error::last_os_error());
    }
    // SAFETY: as above.
    if unsafe { libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_NONBLOCK) } < 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(())
}

#[cfg(not(unix))]
fn open_nonblocking(path: &Path) -> std::io::Result<File> {
    File::open(path)
}

#[cfg(not(unix))]
fn set_blocking(_: &File) -> std::io::Result<()> {
    Ok(())
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    #[test]
    fn a_fifo_is_refused_without_blocking_and_a_regular_file_reads() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a valid C string; mkfifo only creates the node.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let err = open(&fifo).unwrap_err().to_string();
        assert!(err.contains("not a regular file"), "{err}");
        assert!(err.contains("pipe"), "{err}");
        let file = dir.path().join("f");
        std::fs::write(&file, b"abc").unwrap();
        assert_eq!(read_to_string(&file).unwrap(), "abc");
        assert!(open(dir.path()).is_err());
    }
}
