//! What every reader hands to the importer: a header ([`SourceInfo`]) and the voxels as a
//! memory-mapped raw array ([`RawVolume`]).
//!
//! Readers never decode a whole volume into memory. Uncompressed inputs are mapped in place;
//! compressed ones (gzip, zlib, DICOM pixel data) are streamed into a temporary raw file first,
//! which is then mapped. The importer reads that map slice by slice.

use std::fs::File;
use std::path::{Path, PathBuf};

use crate::error::{Result, StorageError};
use memmap2::Mmap;
// The header types live in `crate::source_info` (pure, also built for a remote viewer); their
// paths under `source` stay as they were.
pub use crate::source_info::{
    ByteOrder, LabelInfo, SampleType, SourceInfo, WindowPreset, WARNING_PREFIX,
};

/// A raw voxel array, i fastest, then j, then k, mapped from disk.
pub struct RawVolume {
    map: Mmap,
    offset: usize,
    pub sample_type: SampleType,
    pub byte_order: ByteOrder,
    pub dims: [u64; 3],
    /// Keeps a staging file alive (and deletes it on drop) when the data had to be decompressed.
    _staging: Option<crate::staging::StagingFile>,
    /// The file the bytes came from, for error messages.
    pub path: PathBuf,
}

impl RawVolume {
    /// Maps `path` and checks that `offset + dims · sample size` bytes are there.
    pub fn map_file(
        path: &Path,
        offset: u64,
        sample_type: SampleType,
        byte_order: ByteOrder,
        dims: [u64; 3],
    ) -> Result<Self> {
        let file = crate::regular_file::open(path)?;
        Self::from_file(file, path, offset, sample_type, byte_order, dims, None)
    }

    /// Maps a staging file that a reader has filled with decompressed voxels.
    pub fn from_staging(
        staging: crate::staging::StagingFile,
        source_path: &Path,
        sample_type: SampleType,
        byte_order: ByteOrder,
        dims: [u64; 3],
    ) -> Result<Self> {
        let file = staging
            .reopen()
            .map_err(|e| StorageError::io(staging.path(), e))?;
        Self::from_file(
            file,
            source_path,
            0,
            sample_type,
            byte_order,
            dims,
            Some(staging),
        )
    }

    fn from_file(
        file: File,
        path: &Path,
        offset: u64,
        sample_type: SampleType,
        byte_order: ByteOrder,
        dims: [u64; 3],
        staging: Option<crate::staging::StagingFile>,
    ) -> Result<Self> {
        let len = file
            .metadata()
            .map_err(|e| StorageError::io(path, e))?
            .len();
        let needed = dims
            .iter()
            .try_fold(sample_type.size_bytes() as u64, |acc, &d| {
                acc.checked_mul(d)
            })
            .ok_or_else(|| StorageError::invalid(path, format!("dimensions {dims:?} overflow")))?;
        let end = offset
            .checked_add(needed)
            .ok_or_else(|| StorageError::invalid(path, "data offset overflows"))?;
        if len < end {
            return Err(StorageError::invalid(
                path,
                format!(
                    "truncated data: header promises {needed} bytes of {} voxels {dims:?} at offset {offset}, file has {} bytes after it",
                    sample_type.name(),
                    len.saturating_sub(offset)
                ),
            ));
        }
        if needed == 0 {
            return Err(StorageError::invalid(
                path,
                format!("zero dimension in {dims:?}"),
            ));
        }
        // SAFETY: the file is opened read-only; Strata never writes to its inputs. Another process
        // truncating the file during import could fault, which is the same contract every
        // memory-mapping reader (ITK, nibabel) has.
        let map = unsafe { Mmap::map(&file) }.map_err(|e| StorageError::io(path, e))?;
        Ok(RawVolume {
            map,
            offset: offset as usize,
            sample_type,
            byte_order,
            dims,
            _staging: staging,
            path: path.to_path_buf(),
        })
    }

    pub fn slice_bytes_len(&self) -> usize {
        self.dims[0] as usize * self.dims[1] as usize * self.sample_type.size_bytes()
    }

    /// The raw bytes of slice `k` (as stored: not byte-swapped).
    pub fn slice_bytes(&self, k: u64) -> &[u8] {
        let len = self.slice_bytes_len();
        let start = self.offset + k as usize * len;
        &self.map[start..start + len]
    }

    /// Tells the kernel slice `k`'s pages may be dropped from this process. Page cache keeps
    /// them; only our resident set shrinks, so a 2 GiB input does not count 2 GiB against the
    /// import's memory budget. Unix only (madvise); elsewhere the OS trims the mapping's pages
    /// under memory pressure by itself, and the resident set may show the whole input.
    pub fn release_slice(&self, k: u64) {
        #[cfg(not(unix))]
        let _ = k;
        #[cfg(unix)]
        self.advise_dont_need(k);
    }

    #[cfg(unix)]
    fn advise_dont_need(&self, k: u64) {
        const PAGE: usize = 4096;
        let len = self.slice_bytes_len();
        let start = self.offset + k as usize * len;
        // Only whole pages inside this slice: a neighbouring slice's page stays mapped.
        let first = start.div_ceil(PAGE) * PAGE;
        let end = (start + len) / PAGE * PAGE;
        if end > first {
            // SAFETY: DontNeed on a read-only shared file mapping only discards our page-table
            // entries; later reads fault the same bytes back in from the file.
            let _ = unsafe {
                self.map.unchecked_advise_range(
                    memmap2::UncheckedAdvice::DontNeed,
                    first,
                    end - first,
                )
            };
        }
    }

    /// Decodes slice `k` into f64 values (before slope/intercept). Used for min/max pre-passes
    /// and tests; the import hot path converts straight to stored values instead.
    pub fn read_slice_f64(&self, k: u64, out: &mut Vec<f64>) {
        out.clear();
        let bytes = self.slice_bytes(k);
        decode_samples(bytes, self.sample_type, self.byte_order, |v| out.push(v));
    }
}

/// Calls `sink` with each sample of `bytes` as f64, honouring type and byte order.
#[inline]
pub fn decode_samples(
    bytes: &[u8],
    sample_type: SampleType,
    order: ByteOrder,
    mut sink: impl FnMut(f64),
) {
    macro_rules! each {
        ($t:ty, $n:expr) => {{
            for c in bytes.chunks_exact($n) {
                let mut a = [0u8; $n];
                a.copy_from_slice(c);
                let v = match order {
                    ByteOrder::Little => <$t>::from_le_bytes(a),
                    ByteOrder::Big => <$t>::from_be_bytes(a),
                };
                sink(v as f64);
            }
        }};
    }
    match sample_type {
        SampleType::U8 => bytes.iter().for_each(|&b| sink(b as f64)),
        SampleType::I8 => bytes.iter().for_each(|&b| sink(b as i8 as f64)),
        SampleType::U16 => each!(u16, 2),
        SampleType::I16 => each!(i16, 2),
        SampleType::U32 => each!(u32, 4),
        SampleType::I32 => each!(i32, 4),
        SampleType::F32 => each!(f32, 4),
        SampleType::F64 => each!(f64, 8),
    }
}

/// A reader's result: the header and the mapped voxels.
pub struct OpenedSource {
    pub info: SourceInfo,
    pub data: RawVolume,
}
