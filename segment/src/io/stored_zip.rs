//! A zip archive of stored (uncompressed) entries, written in memory: the page's OME-Zarr
//! download ([`super::omezarr_labels::omezarr_labels_zip`]), whose chunks are zstd frames
//! already. PKWARE's APPNOTE 6.3: a local header and the bytes per entry, then the central
//! directory and its end record; names UTF-8 (flag bit 11), every entry dated 1980-01-01 (the
//! format's epoch: the page's bytes do not depend on the clock), CRC-32 by flate2.
//!
//! Not the `zip` crate: its writer depends on zeroize's derive, which turns on a syn feature no
//! other crate here uses, and that rebuilds every crate of the workspace. No Zip64: at most
//! 65 535 entries and 4 GiB in all, each a [`SegmentError::FormatLimit`] naming the archive.

use std::path::{Path, PathBuf};

use crate::SegmentError;

const LOCAL_HEADER: u32 = 0x0403_4b50;
const CENTRAL_HEADER: u32 = 0x0201_4b50;
const END_OF_CENTRAL_DIRECTORY: u32 = 0x0605_4b50;
/// Version 2.0: what stored entries and folders need.
const VERSION: u16 = 20;
/// General purpose flag bit 11: names are UTF-8.
const UTF8_NAMES: u16 = 1 << 11;
/// MS-DOS date of 1980-01-01 (year 0 since 1980, month 1, day 1), time 00:00:00.
const DOS_DATE: u16 = (1 << 5) | 1;

/// One entry's central-directory facts.
struct Entry {
    name: String,
    crc: u32,
    size: u32,
    offset: u32,
}

/// A zip being written into memory; `path` is what errors call it.
pub struct StoredZip {
    bytes: Vec<u8>,
    entries: Vec<Entry>,
    path: PathBuf,
}

fn put16(out: &mut Vec<u8>, v: u16) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put32(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_le_bytes());
}

impl StoredZip {
    pub fn new(path: &Path) -> Self {
        StoredZip {
            bytes: Vec::new(),
            entries: Vec::new(),
            path: path.to_path_buf(),
        }
    }

    fn limit(&self, what: &str, limit: u64, requested: u64) -> SegmentError {
        SegmentError::FormatLimit {
            path: self.path.clone(),
            format: "zip (no Zip64)",
            what: what.to_string(),
            limit,
            requested,
        }
    }

    /// The archive's bytes so far as a 32-bit offset, or the format's limit.
    fn offset(&self, adding: usize) -> Result<u32, SegmentError> {
        let end = self.bytes.len() as u64 + adding as u64;
        u32::try_from(end)
            .map(|_| self.bytes.len() as u32)
            .map_err(|_| self.limit("bytes in the archive", u64::from(u32::MAX), end))
    }

    /// Adds `bytes` as the entry `name` (`/`-separated, relative).
    pub fn add(&mut self, name: &str, bytes: &[u8]) -> Result<(), SegmentError> {
        if self.entries.len() >= usize::from(u16::MAX) {
            return Err(self.limit(
                "entries",
                u64::from(u16::MAX),
                self.entries.len() as u64 + 1,
            ));
        }
        let name_len = u16::try_from(name.len()).map_err(|_| SegmentError::Format {
            path: self.path.clone(),
            message: format!(
                "entry name of {} bytes: a zip name is at most 65 535",
                name.len()
            ),
        })?;
        let offset = self.offset(30 + name.len() + bytes.len())?;
        let size = bytes.len() as u32;
        let mut crc = flate2::Crc::new();
        crc.update(bytes);
        let crc = crc.sum();
        let out = &mut self.bytes;
        put32(out, LOCAL_HEADER);
        put16(out, VERSION);
        put16(out, UTF8_NAMES);
        put16(out, 0); // method: stored
        put16(out, 0); // time
        put16(out, DOS_DATE);
        put32(out, crc);
        put32(out, size); // compressed size
        put32(out, size); // uncompressed size
        put16(out, name_len);
        put16(out, 0); // extra field length
        out.extend_from_slice(name.as_bytes());
        out.extend_from_slice(bytes);
        self.entries.push(Entry {
            name: name.to_owned(),
            crc,
            size,
            offset,
        });
        Ok(())
    }

    /// The central directory and its end record appended: the archive's bytes.
    pub fn finish(mut self) -> Result<Vec<u8>, SegmentError> {
        let directory_size: usize = self.entries.iter().map(|e| 46 + e.name.len()).sum();
        let directory_offset = self.offset(directory_size + 22)?;
        let count = self.entries.len() as u16;
        let out = &mut self.bytes;
        for e in &self.entries {
            put32(out, CENTRAL_HEADER);
            put16(out, VERSION); // made by (MS-DOS attributes)
            put16(out, VERSION); // needed to extract
            put16(out, UTF8_NAMES);
            put16(out, 0); // stored
            put16(out, 0);
            put16(out, DOS_DATE);
            put32(out, e.crc);
            put32(out, e.size);
            put32(out, e.size);
            put16(out, e.name.len() as u16);
            put16(out, 0); // extra field
            put16(out, 0); // comment
            put16(out, 0); // disk number start
            put16(out, 0); // internal attributes
            put32(out, 0); // external attributes
            put32(out, e.offset);
            out.extend_from_slice(e.name.as_bytes());
        }
        put32(out, END_OF_CENTRAL_DIRECTORY);
        put16(out, 0); // this disk
        put16(out, 0); // the central directory's disk
        put16(out, count);
        put16(out, count);
        put32(out, directory_size as u32);
        put32(out, directory_offset);
        put16(out, 0); // comment length
        Ok(self.bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_entry_is_a_local_header_then_its_bytes_and_the_end_record_counts_it() {
        let mut zip = StoredZip::new(Path::new("labels.zip"));
        zip.add("a/zarr.json", b"{}").expect("entry");
        let bytes = zip.finish().expect("archive");
        assert_eq!(&bytes[..4], &LOCAL_HEADER.to_le_bytes());
        assert_eq!(&bytes[30..41], b"a/zarr.json");
        assert_eq!(&bytes[41..43], b"{}");
        // CRC-32 of "{}" (zlib's crc32).
        assert_eq!(&bytes[14..18], &0xa3a6_bf43u32.to_le_bytes());
        let end = &bytes[bytes.len() - 22..];
        assert_eq!(&end[..4], &END_OF_CENTRAL_DIRECTORY.to_le_bytes());
        assert_eq!(u16::from_le_bytes([end[10], end[11]]), 1);
        let directory = u32::from_le_bytes([end[16], end[17], end[18], end[19]]) as usize;
        assert_eq!(directory, 43);
        assert_eq!(
            &bytes[directory..directory + 4],
            &CENTRAL_HEADER.to_le_bytes()
        );
    }

    #[test]
    fn more_entries_than_a_zip_without_zip64_holds_are_refused_naming_the_archive() {
        let mut zip = StoredZip::new(Path::new("big.ome.zarr.zip"));
        for n in 0..u16::MAX {
            zip.add(&n.to_string(), &[]).expect("entry under the limit");
        }
        let e = zip.add("one more", &[]).expect_err("over the limit");
        let text = e.to_string();
        assert!(
            text.contains("big.ome.zarr.zip") && text.contains("65535"),
            "{text}"
        );
    }
}
