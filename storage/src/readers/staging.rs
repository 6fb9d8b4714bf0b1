//! Streaming decompression into a temporary raw file, so compressed inputs never sit in memory.

use std::io::{BufWriter, Read, Write};
use std::path::Path;

use tempfile::NamedTempFile;

use crate::error::{Result, StorageError};
use crate::readers::ReadOptions;

/// Bounded buffer for every staging copy: large enough to amortise syscalls, small next to a volume.
const CHUNK: usize = 1 << 20;

pub(crate) fn new_staging(source: &Path, options: &ReadOptions) -> Result<NamedTempFile> {
    let mut b = tempfile::Builder::new();
    b.prefix("strata-staging-").suffix(".raw");
    match &options.staging_dir {
        Some(dir) => b.tempfile_in(dir).map_err(|e| StorageError::io(dir, e)),
        None => b.tempfile().map_err(|e| {
            StorageError::io(
                source,
                std::io::Error::new(e.kind(), format!("creating staging file: {e}")),
            )
        }),
    }
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

/// Copies exactly `expected` bytes of `reader` into `staging`. A short stream is an error naming
/// both sizes; trailing bytes after the volume are ignored (padding is common in the wild).
pub(crate) fn stream_into(
    path: &Path,
    reader: &mut impl Read,
    staging: &mut NamedTempFile,
    expected: u64,
) -> Result<()> {
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
        out.write_all(&buf[..n])
            .map_err(|e| StorageError::io(path, e))?;
        done += n as u64;
    }
    out.flush().map_err(|e| StorageError::io(path, e))?;
    if done < expected {
        return Err(StorageError::invalid(
            path,
            format!("truncated data: expected {expected} bytes of voxels, the compressed stream holds only {done}"),
        ));
    }
    Ok(())
}
