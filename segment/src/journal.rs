//! The edit journal: every completed edit appended to a file beside the layer, so a crash or a
//! kill loses no completed stroke (issue 52 item 4).
//!
//! Layout (all integers little-endian):
//! - a file header: `STRATASEGJOURNAL`, format version (u32), the length (u32) of the JSON
//!   [`VolumeGeometry`] the edits belong to, that JSON, and an xxh3-64 over all of it. A damaged
//!   file header is an error: without it no record can be placed on a grid.
//! - records, one per completed edit (or segment table snapshot), each a 32-byte header —
//!   magic `SJRC`, kind (u16), 0 (u16), sequence number (u64, 0, 1, 2, … in file order),
//!   payload length (u32), 0 (u32), xxh3-64 over the header's first 24 bytes and the payload —
//!   then the payload. An edit's payload is its name and, per changed brick, the brick key and
//!   one zstd frame (level 1) of the `before` and `after` images.
//!
//! Both images are stored, not only `after`: a recovered edit is then a whole [`Edit`] that the
//! history can undo step by step as before the crash, and label bricks compress to a few hundred
//! bytes each, so the second image costs little. Replaying the recovered edits' `after` images in
//! order onto a fresh layer over the same base gives the layer as it was after the last
//! completed edit (`journal::tests::replaying_the_recovered_edits_rebuilds_the_layer`).
//!
//! Durability: a record is written with one positioned write at the end of the last good record
//! and `fdatasync`ed before [`Journal::append`] returns (no group commit: a stroke is ≥ 10 ms of
//! user time, a sync ~1 ms on an SSD). A failed write (a full disk) truncates the file back to
//! the last good record and returns the error naming the file; every earlier record stays.
//!
//! Recovery ([`recover`]) reads records until the first one that is incomplete, fails its
//! checksum, is out of sequence or does not decode, and says what it dropped from there on: a
//! torn tail from a kill mid-write is dropped, never read as an edit. [`Journal::open_or_create`]
//! cuts such a tail off before appending, so new records never sit behind garbage.
//! `journal::tests::sigkilled_writers_lose_no_completed_edit_and_double_none` kills a writer
//! process at random moments (≥ 20 times) and checks every acknowledged edit is recovered, once,
//! intact.
//!
//! Bounds: a record's payload is read only if the file holds that many bytes; brick images
//! decompress into exactly one brick pair (a larger frame is damage); a name is ≤ 64 KiB.

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use strata_types::VolumeGeometry;
use xxhash_rust::xxh3::xxh3_64;

use crate::grid::LABEL_BRICK_VOXELS;
use crate::{BrickChange, BrickKey, Edit, Label, SegmentError, SegmentTable};

const FILE_MAGIC: &[u8; 16] = b"STRATASEGJOURNAL";
const FORMAT_VERSION: u32 = 1;
const RECORD_MAGIC: &[u8; 4] = b"SJRC";
const RECORD_HEADER_BYTES: usize = 32;
/// The geometry JSON is a few hundred bytes; anything far larger is damage.
const MAX_HEADER_JSON: u32 = 1 << 16;
const MAX_NAME_BYTES: usize = u16::MAX as usize;
/// One brick's `before` and `after` images as stored in a frame.
const BRICK_PAIR_BYTES: usize = 2 * LABEL_BRICK_VOXELS * 2;
/// zstd level 1: label bricks are runs of a few values, level 1 already shrinks them ~100×.
const ZSTD_LEVEL: i32 = 1;

const KIND_EDIT: u16 = 1;
const KIND_SEGMENTS: u16 = 2;

/// An open journal, appending after its last good record.
pub struct Journal {
    path: PathBuf,
    file: File,
    /// Byte offset just past the last good record: where the next one goes.
    end: u64,
    next_seq: u64,
    #[cfg(test)]
    fail_writes_after_bytes: Option<u64>,
}

/// What a journal held: every record that verified, in order.
#[derive(Debug)]
pub struct Recovery {
    pub geometry: VolumeGeometry,
    /// The completed edits, oldest first; replay their `after` images in this order.
    pub edits: Vec<Edit>,
    /// The last segment table written ([`Journal::append_segments`]), if any.
    pub segments: Option<SegmentTable>,
    /// What was dropped after the last good record, and why (`None`: the file ended cleanly).
    pub dropped: Option<String>,
    /// Where the last good record ends.
    pub good_bytes: u64,
    /// Good records read (edits and segment tables).
    pub records: u64,
}

impl Journal {
    /// Opens the journal at `path` for appending (cutting off a torn tail), or creates it for a
    /// layer on `geometry`. An existing journal for another grid is refused.
    pub fn open_or_create(
        path: &Path,
        geometry: &VolumeGeometry,
    ) -> Result<(Journal, Recovery), SegmentError> {
        let io = |e| SegmentError::Io {
            path: path.to_path_buf(),
            source: e,
        };
        // A crash between creating the file and syncing its header leaves it empty: start anew.
        if std::fs::metadata(path).is_ok_and(|m| m.len() == 0) {
            std::fs::remove_file(path).map_err(io)?;
        }
        if !path.exists() {
            let mut file = OpenOptions::new()
                .read(true)
                .write(true)
                .create_new(true)
                .open(path)
                .map_err(io)?;
            let header = file_header(geometry, path)?;
            file.write_all(&header).map_err(io)?;
            file.sync_all().map_err(io)?;
            crate::io::atomic::sync_dir_of(path)?;
            let journal = Journal {
                path: path.to_path_buf(),
                file,
                end: header.len() as u64,
                next_seq: 0,
                #[cfg(test)]
                fail_writes_after_bytes: None,
            };
            let recovery = Recovery {
                geometry: geometry.clone(),
                edits: Vec::new(),
                segments: None,
                dropped: None,
                good_bytes: header.len() as u64,
                records: 0,
            };
            return Ok((journal, recovery));
        }
        let recovery = recover(path)?;
        if recovery.geometry != *geometry {
            return Err(SegmentError::Format {
                path: path.to_path_buf(),
                message: format!(
                    "this journal belongs to a label grid of {:?} voxels at {:?} mm, not {:?} at {:?} mm: recover it onto its own layer or move it aside",
                    recovery.geometry.dims,
                    recovery.geometry.spacing_mm,
                    geometry.dims,
                    geometry.spacing_mm
                ),
            });
        }
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .open(path)
            .map_err(io)?;
        let len = file.metadata().map_err(io)?.len();
        if len != recovery.good_bytes {
            // A torn or damaged tail: cut it off so the next record follows a good one.
            file.set_len(recovery.good_bytes).map_err(io)?;
            file.sync_all().map_err(io)?;
        }
        let next_seq = recovery.records;
        let journal = Journal {
            path: path.to_path_buf(),
            file,
            end: recovery.good_bytes,
            next_seq,
            #[cfg(test)]
            fail_writes_after_bytes: None,
        };
        Ok((journal, recovery))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Records written so far (edits and segment tables).
    pub fn record_count(&self) -> u64 {
        self.next_seq
    }

    /// Appends one completed edit and syncs it to disk before returning.
    pub fn append(&mut self, edit: &Edit) -> Result<(), SegmentError> {
        let payload = edit_payload(edit, &self.path)?;
        self.append_record(KIND_EDIT, &payload)
    }

    /// Appends a snapshot of the segment table (names, colours, locks), synced; recovery
    /// returns the last one.
    pub fn append_segments(&mut self, segments: &SegmentTable) -> Result<(), SegmentError> {
        let payload = serde_json::to_vec(segments).map_err(|e| SegmentError::Format {
            path: self.path.clone(),
            message: format!("segment table not serialisable: {e}"),
        })?;
        self.append_record(KIND_SEGMENTS, &payload)
    }

    fn append_record(&mut self, kind: u16, payload: &[u8]) -> Result<(), SegmentError> {
        let len = u32::try_from(payload.len()).map_err(|_| SegmentError::Format {
            path: self.path.clone(),
            message: format!(
                "a journal record of {} bytes is over the 4 GiB a record holds",
                payload.len()
            ),
        })?;
        let mut record = Vec::with_capacity(RECORD_HEADER_BYTES + payload.len());
        record.extend_from_slice(RECORD_MAGIC);
        record.extend_from_slice(&kind.to_le_bytes());
        record.extend_from_slice(&0u16.to_le_bytes());
        record.extend_from_slice(&self.next_seq.to_le_bytes());
        record.extend_from_slice(&len.to_le_bytes());
        record.extend_from_slice(&0u32.to_le_bytes());
        let sum = record_checksum(&record[..24], payload);
        record.extend_from_slice(&sum.to_le_bytes());
        record.extend_from_slice(payload);
        match self.write_at_end(&record) {
            Ok(()) => {
                self.end += record.len() as u64;
                self.next_seq += 1;
                Ok(())
            }
            Err(e) => {
                // Take the partial record back off so the file ends on a good record; if even
                // that fails, the next append overwrites it from `end` and recovery drops it.
                let _ = self.file.set_len(self.end);
                let _ = self.file.sync_data();
                Err(SegmentError::Io {
                    path: self.path.clone(),
                    source: std::io::Error::new(
                        e.kind(),
                        format!(
                            "journal append failed ({e}); the {} earlier record(s) are kept, this edit is not journaled",
                            self.next_seq
                        ),
                    ),
                })
            }
        }
    }

    fn write_at_end(&mut self, record: &[u8]) -> std::io::Result<()> {
        self.file.seek(SeekFrom::Start(self.end))?;
        #[cfg(test)]
        if let Some(limit) = self.fail_writes_after_bytes {
            if self.end + record.len() as u64 > limit {
                let room = limit.saturating_sub(self.end) as usize;
                self.file.write_all(&record[..room.min(record.len())])?;
                return Err(std::io::Error::new(
                    std::io::ErrorKind::StorageFull,
                    "No space left on device (simulated)",
                ));
            }
        }
        self.file.write_all(record)?;
        self.file.sync_data()
    }
}

impl Recovery {
    /// Applies the recovered edits to `layer` in order (its segment table too, if one was
    /// journaled).
    pub fn replay_onto(&self, layer: &mut crate::LabelLayer) {
        if let Some(segments) = &self.segments {
            *layer.segments_mut() = segments.clone();
        }
        for edit in &self.edits {
            layer.apply(edit);
        }
    }
}

/// Reads every record of the journal at `path` that verifies, stopping at the first that does
/// not (and saying what was dropped).
pub fn recover(path: &Path) -> Result<Recovery, SegmentError> {
    let io = |e| SegmentError::Io {
        path: path.to_path_buf(),
        source: e,
    };
    let format = |message: String| SegmentError::Format {
        path: path.to_path_buf(),
        message,
    };
    let mut file = File::open(path).map_err(io)?;
    let file_len = file.metadata().map_err(io)?.len();
    let mut fixed = [0u8; 24];
    file.read_exact(&mut fixed).map_err(|_| {
        format(format!(
            "not a Strata segmentation journal: {file_len} bytes, shorter than its header"
        ))
    })?;
    if &fixed[..16] != FILE_MAGIC {
        return Err(format(
            "not a Strata segmentation journal (no STRATASEGJOURNAL magic)".into(),
        ));
    }
    let version = u32::from_le_bytes(fixed[16..20].try_into().expect("4 bytes"));
    if version != FORMAT_VERSION {
        return Err(format(format!(
            "journal format {version}; this build reads format {FORMAT_VERSION}"
        )));
    }
    let json_len = u32::from_le_bytes(fixed[20..24].try_into().expect("4 bytes"));
    if json_len > MAX_HEADER_JSON || u64::from(json_len) + 32 > file_len {
        return Err(format(format!(
            "journal header damaged: geometry of {json_len} bytes in a {file_len}-byte file"
        )));
    }
    let mut rest = vec![0u8; json_len as usize + 8];
    file.read_exact(&mut rest).map_err(io)?;
    let (json, sum) = rest.split_at(json_len as usize);
    let mut summed = fixed.to_vec();
    summed.extend_from_slice(json);
    if xxh3_64(&summed) != u64::from_le_bytes(sum.try_into().expect("8 bytes")) {
        return Err(format(
            "journal header damaged (checksum): its edits cannot be placed; move the file aside"
                .into(),
        ));
    }
    let geometry: VolumeGeometry = serde_json::from_slice(json)
        .map_err(|e| format(format!("journal header geometry unreadable: {e}")))?;

    let mut recovery = Recovery {
        geometry,
        edits: Vec::new(),
        segments: None,
        dropped: None,
        good_bytes: 32 + u64::from(json_len),
        records: 0,
    };
    let mut at = recovery.good_bytes;
    let mut seq = 0u64;
    let mut reader = std::io::BufReader::with_capacity(1 << 20, file);
    loop {
        if at == file_len {
            break;
        }
        let mut header = [0u8; RECORD_HEADER_BYTES];
        if file_len - at < RECORD_HEADER_BYTES as u64 {
            recovery.dropped = Some(dropped(
                file_len - at,
                at,
                seq,
                "a record header cut short (a write interrupted by a crash or kill)",
            ));
            break;
        }
        reader.read_exact(&mut header).map_err(io)?;
        let kind = u16::from_le_bytes([header[4], header[5]]);
        let record_seq = u64::from_le_bytes(header[8..16].try_into().expect("8 bytes"));
        let len = u32::from_le_bytes(header[16..20].try_into().expect("4 bytes"));
        let sum = u64::from_le_bytes(header[24..32].try_into().expect("8 bytes"));
        let problem = if &header[..4] != RECORD_MAGIC {
            Some("no record magic (damage, or a write interrupted by a crash)".to_string())
        } else if u64::from(len) > file_len - at - RECORD_HEADER_BYTES as u64 {
            Some(format!(
                "a record of {len} payload bytes cut short (a write interrupted by a crash or kill)"
            ))
        } else {
            None
        };
        if let Some(p) = problem {
            recovery.dropped = Some(dropped(file_len - at, at, seq, &p));
            break;
        }
        let mut payload = vec![0u8; len as usize];
        reader.read_exact(&mut payload).map_err(io)?;
        if record_checksum(&header[..24], &payload) != sum {
            recovery.dropped = Some(dropped(
                file_len - at,
                at,
                seq,
                "a record whose checksum fails (torn or damaged)",
            ));
            break;
        }
        if record_seq != seq {
            recovery.dropped = Some(dropped(
                file_len - at,
                at,
                seq,
                &format!("record number {record_seq} where {seq} was due"),
            ));
            break;
        }
        let decoded = match kind {
            KIND_EDIT => decode_edit(&payload).map(|e| recovery.edits.push(e)),
            KIND_SEGMENTS => serde_json::from_slice::<SegmentTable>(&payload)
                .map(|s| recovery.segments = Some(s))
                .map_err(RecordError::SegmentTable),
            other => Err(RecordError::UnknownKind(other)),
        };
        if let Err(p) = decoded {
            recovery.dropped = Some(dropped(file_len - at, at, seq, &p.to_string()));
            break;
        }
        at += RECORD_HEADER_BYTES as u64 + u64::from(len);
        seq += 1;
        recovery.good_bytes = at;
        recovery.records = seq;
    }
    Ok(recovery)
}

fn dropped(bytes: u64, at: u64, seq: u64, why: &str) -> String {
    format!(
        "dropped the last {bytes} byte(s) from offset {at} (record {seq} onward): {why}; every record before it was recovered"
    )
}

fn record_checksum(header: &[u8], payload: &[u8]) -> u64 {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(header);
    h.update(payload);
    h.digest()
}

fn file_header(geometry: &VolumeGeometry, path: &Path) -> Result<Vec<u8>, SegmentError> {
    let json = serde_json::to_vec(geometry).map_err(|e| SegmentError::Format {
        path: path.to_path_buf(),
        message: format!("geometry not serialisable: {e}"),
    })?;
    let mut out = Vec::with_capacity(32 + json.len());
    out.extend_from_slice(FILE_MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(&json);
    let sum = xxh3_64(&out);
    out.extend_from_slice(&sum.to_le_bytes());
    Ok(out)
}

fn edit_payload(edit: &Edit, path: &Path) -> Result<Vec<u8>, SegmentError> {
    let name = truncated_name(&edit.name);
    let mut out = Vec::new();
    out.extend_from_slice(&(name.len() as u16).to_le_bytes());
    out.extend_from_slice(name.as_bytes());
    out.extend_from_slice(&(edit.changes.len() as u32).to_le_bytes());
    let mut raw = Vec::with_capacity(BRICK_PAIR_BYTES);
    for change in &edit.changes {
        if change.before.len() != LABEL_BRICK_VOXELS || change.after.len() != LABEL_BRICK_VOXELS {
            return Err(SegmentError::Format {
                path: path.to_path_buf(),
                message: format!(
                    "edit '{}' has a brick image of {} voxels, not {LABEL_BRICK_VOXELS}",
                    edit.name,
                    change.before.len().max(change.after.len())
                ),
            });
        }
        raw.clear();
        raw.extend(change.before.iter().flat_map(|v| v.to_le_bytes()));
        raw.extend(change.after.iter().flat_map(|v| v.to_le_bytes()));
        let frame = zstd::bulk::compress(&raw, ZSTD_LEVEL).map_err(|e| SegmentError::Io {
            path: path.to_path_buf(),
            source: e,
        })?;
        for v in change.key.0 {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&(frame.len() as u32).to_le_bytes());
        out.extend_from_slice(&frame);
    }
    Ok(out)
}

/// Cuts a name to what a record holds, on a character boundary.
fn truncated_name(name: &str) -> &str {
    if name.len() <= MAX_NAME_BYTES {
        return name;
    }
    let mut end = MAX_NAME_BYTES;
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    &name[..end]
}

/// Why a record's payload was refused on recovery (the record and all after it are dropped).
#[derive(Debug, thiserror::Error)]
enum RecordError {
    #[error("edit record cut short: {needed} bytes needed, {left} left")]
    CutShort { needed: usize, left: usize },
    #[error("edit name is not UTF-8")]
    NameNotUtf8,
    #[error("edit record claims {bricks} bricks in {bytes} bytes")]
    BrickCount { bricks: usize, bytes: usize },
    #[error("zstd decoder unavailable: {0}")]
    DecoderUnavailable(std::io::Error),
    #[error("brick {key:?} does not decompress: {source}")]
    Decompress {
        key: [u32; 3],
        source: std::io::Error,
    },
    #[error("brick {key:?} decompresses to {got} bytes, not {expected}", expected = BRICK_PAIR_BYTES)]
    DecompressedSize { key: [u32; 3], got: usize },
    #[error("edit record has {0} stray bytes after its bricks")]
    StrayBytes(usize),
    #[error("segment table unreadable: {0}")]
    SegmentTable(serde_json::Error),
    #[error("unknown record kind {0}")]
    UnknownKind(u16),
}

/// Reads fields off the front of a payload, failing on a short one.
struct Cursor<'a>(&'a [u8]);

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], RecordError> {
        if self.0.len() < n {
            return Err(RecordError::CutShort {
                needed: n,
                left: self.0.len(),
            });
        }
        let (head, tail) = self.0.split_at(n);
        self.0 = tail;
        Ok(head)
    }

    fn u32(&mut self) -> Result<u32, RecordError> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }
}

fn decode_edit(payload: &[u8]) -> Result<Edit, RecordError> {
    let mut c = Cursor(payload);
    let name_len = u16::from_le_bytes(c.take(2)?.try_into().expect("2 bytes")) as usize;
    let name = std::str::from_utf8(c.take(name_len)?)
        .map_err(|_| RecordError::NameNotUtf8)?
        .to_owned();
    let n = c.u32()? as usize;
    // Each change takes ≥ 16 bytes of payload: the count cannot ask for more than that.
    if n > c.0.len() / 16 {
        return Err(RecordError::BrickCount {
            bricks: n,
            bytes: c.0.len(),
        });
    }
    let mut changes = Vec::with_capacity(n);
    let mut decoder = zstd::bulk::Decompressor::new().map_err(RecordError::DecoderUnavailable)?;
    let mut raw = vec![0u8; BRICK_PAIR_BYTES];
    for _ in 0..n {
        let key = BrickKey([c.u32()?, c.u32()?, c.u32()?]);
        let frame_len = c.u32()? as usize;
        let frame = c.take(frame_len)?;
        let got = decoder
            .decompress_to_buffer(frame, &mut raw)
            .map_err(|source| RecordError::Decompress { key: key.0, source })?;
        if got != BRICK_PAIR_BYTES {
            return Err(RecordError::DecompressedSize { key: key.0, got });
        }
        let labels = |bytes: &[u8]| -> Arc<[Label]> {
            bytes
                .chunks_exact(2)
                .map(|b| Label::from_le_bytes([b[0], b[1]]))
                .collect()
        };
        let half = BRICK_PAIR_BYTES / 2;
        changes.push(BrickChange {
            key,
            before: labels(&raw[..half]),
            after: labels(&raw[half..]),
        });
    }
    if !c.0.is_empty() {
        return Err(RecordError::StrayBytes(c.0.len()));
    }
    Ok(Edit {
        name,
        changes,
        table: None,
    })
}

#[cfg(test)]
mod tests {
    use std::io::BufRead;
    use std::process::{Command, Stdio};
    use std::time::{Duration, Instant};

    use super::*;
    use crate::{LabelLayer, LabelRead};

    const CHILD_ENV: &str = "STRATA_JOURNAL_TEST_CHILD";

    fn geometry() -> VolumeGeometry {
        VolumeGeometry::axis_aligned([96, 80, 70], [0.8, 0.8, 1.5])
    }

    /// Stroke `i`: a few hundred pseudo-random voxels in one to three bricks, labelled
    /// `i % 1000 + 1`, made through the layer's own edit path (so its before images are real).
    fn stroke(layer: &mut LabelLayer, i: u64) -> Edit {
        let mut state = i.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let dims = layer.grid().dims();
        let label = (i % 1000 + 1) as Label;
        let bricks = 1 + next() % 3;
        layer
            .edit(&format!("stroke {i}"), |w| {
                for _ in 0..bricks {
                    let centre = dims.map(|d| (next() % u64::from(d)) as u32);
                    for _ in 0..300 {
                        let v = [0, 1, 2].map(|a| {
                            let off = (next() % 9) as u32;
                            (centre[a] + off).saturating_sub(4).min(dims[a] - 1)
                        });
                        w.set(v, label)?;
                    }
                }
                Ok(())
            })
            .expect("in-grid voxels")
            .expect("a stroke's label differs from the 999 before it, so it changes voxels")
    }

    fn same_edit(a: &Edit, b: &Edit) -> bool {
        a.name == b.name
            && a.changes.len() == b.changes.len()
            && a.changes.iter().zip(&b.changes).all(|(x, y)| {
                x.key == y.key && x.before[..] == y.before[..] && x.after[..] == y.after[..]
            })
    }

    fn all_slices(layer: &LabelLayer) -> Vec<Label> {
        let [nx, ny, nz] = layer.grid().dims();
        let mut out = vec![0; (nx * ny * nz) as usize];
        for (k, slice) in out.chunks_mut((nx * ny) as usize).enumerate() {
            layer.read_slice_k(k as u32, slice).expect("slice in grid");
        }
        out
    }

    /// The writer process of the SIGKILL test: appends strokes forever, printing `acked N`
    /// once stroke N is synced. Does nothing unless the parent test started it.
    #[test]
    #[ignore = "started by sigkilled_writers_lose_no_completed_edit_and_double_none"]
    fn journal_child_writer() {
        let Ok(path) = std::env::var(CHILD_ENV) else {
            return;
        };
        let (mut journal, recovery) =
            Journal::open_or_create(Path::new(&path), &geometry()).expect("journal opens");
        let mut layer = LabelLayer::new_empty(geometry()).expect("grid");
        recovery.replay_onto(&mut layer);
        let mut out = std::io::stdout().lock();
        for i in recovery.edits.len() as u64.. {
            let edit = stroke(&mut layer, i);
            journal.append(&edit).expect("append");
            writeln!(out, "acked {i}").expect("stdout");
            out.flush().expect("stdout");
        }
    }

    #[test]
    fn sigkilled_writers_lose_no_completed_edit_and_double_none() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("labels.journal");
        let exe = std::env::current_exe().expect("test binary");
        let mut expected_layer = LabelLayer::new_empty(geometry()).expect("grid");
        let mut expected: Vec<Edit> = Vec::new();
        let mut rng = Instant::now().elapsed().as_nanos() as u64 | 1;
        let started = Instant::now();
        let (mut kills, mut torn_tails, mut max_acked) = (0, 0, None::<u64>);
        while kills < 24 {
            assert!(
                started.elapsed() < Duration::from_secs(120),
                "24 kills took over 2 minutes"
            );
            let mut child = Command::new(&exe)
                .args([
                    "journal::tests::journal_child_writer",
                    "--exact",
                    "--ignored",
                    "--nocapture",
                    "--test-threads=1",
                ])
                .env(CHILD_ENV, &path)
                .stdout(Stdio::piped())
                .stderr(Stdio::null())
                .spawn()
                .expect("re-run the test binary");
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            std::thread::sleep(Duration::from_millis(20 + rng % 230));
            child.kill().expect("SIGKILL the writer");
            child.wait().expect("reap");
            kills += 1;
            let stdout = child.stdout.take().expect("piped");
            for line in std::io::BufReader::new(stdout).lines() {
                let line = line.expect("utf-8 line");
                // The harness prints "test NAME ... " before the child's first line, unended.
                if let Some(n) = line.split("acked ").nth(1) {
                    let n: u64 = n.parse().expect("a number");
                    max_acked = Some(max_acked.map_or(n, |m| m.max(n)));
                }
            }
            if !path.exists() {
                continue;
            }
            let recovery = recover(&path).expect("journal header intact");
            if recovery.dropped.is_some() {
                torn_tails += 1;
            }
            let n = recovery.edits.len() as u64;
            let acked = max_acked.map_or(0, |m| m + 1);
            // Every acknowledged stroke is there; at most the one in flight beyond them.
            assert!(
                n >= acked && n <= acked + 1,
                "kill {kills}: recovered {n} edits, {acked} were acknowledged"
            );
            while (expected.len() as u64) < n {
                let i = expected.len() as u64;
                expected.push(stroke(&mut expected_layer, i));
            }
            for (i, edit) in recovery.edits.iter().enumerate() {
                assert!(
                    same_edit(edit, &expected[i]),
                    "kill {kills}: recovered edit {i} differs from stroke {i}"
                );
            }
            if n == acked + 1 {
                max_acked = Some(n - 1);
            }
        }
        let acked = max_acked.expect("some strokes completed").saturating_add(1);
        assert!(acked >= 24, "only {acked} strokes in 24 runs");
        let recovery = recover(&path).expect("journal");
        let mut layer = LabelLayer::new_empty(geometry()).expect("grid");
        recovery.replay_onto(&mut layer);
        let mut expected_final = LabelLayer::new_empty(geometry()).expect("grid");
        for e in &expected[..recovery.edits.len()] {
            expected_final.apply(e);
        }
        assert!(all_slices(&layer) == all_slices(&expected_final));
        eprintln!(
            "{kills} kills, {acked} strokes acknowledged, {} recovered, {torn_tails} recoveries dropped a torn tail",
            recovery.edits.len()
        );
    }

    fn journal_with(n: u64) -> (tempfile::TempDir, PathBuf, Vec<Edit>, LabelLayer) {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("j");
        let (mut journal, _) = Journal::open_or_create(&path, &geometry()).expect("create");
        let mut layer = LabelLayer::new_empty(geometry()).expect("grid");
        let mut edits = Vec::new();
        for i in 0..n {
            let e = stroke(&mut layer, i);
            journal.append(&e).expect("append");
            edits.push(e);
        }
        (dir, path, edits, layer)
    }

    #[test]
    fn replaying_the_recovered_edits_rebuilds_the_layer() {
        let (_dir, path, edits, mut layer) = journal_with(12);
        {
            let (mut journal, _) = Journal::open_or_create(&path, &geometry()).expect("reopen");
            let mut segments = SegmentTable::new();
            segments.add("liver").expect("add");
            journal.append_segments(&segments).expect("segments");
        }
        let recovery = recover(&path).expect("recover");
        assert!(recovery.dropped.is_none(), "{:?}", recovery.dropped);
        assert_eq!(recovery.edits.len(), 12);
        assert!(recovery
            .edits
            .iter()
            .zip(&edits)
            .all(|(a, b)| same_edit(a, b)));
        let mut fresh = LabelLayer::new_empty(geometry()).expect("grid");
        recovery.replay_onto(&mut fresh);
        assert_eq!(fresh.segments().get(1).expect("segment").name, "liver");
        let slices = all_slices(&fresh);
        assert!(slices.iter().any(|&v| v != 0));
        assert!(slices == all_slices(&layer));
        // The recovered edits undo like the originals: the last one reverted gives the 11th state.
        fresh.revert(&recovery.edits[11]);
        layer.revert(&edits[11]);
        assert!(all_slices(&fresh) == all_slices(&layer));
    }

    #[test]
    fn a_torn_or_damaged_record_ends_recovery_and_says_what_was_dropped() {
        let (_dir, path, edits, _) = journal_with(3);
        let bytes = std::fs::read(&path).expect("read");
        let good = recover(&path).expect("recover").good_bytes;
        assert_eq!(good, bytes.len() as u64);
        // Every cut inside the last record drops it and only it.
        let two = {
            std::fs::write(&path, &bytes).expect("write");
            let (j, _) = Journal::open_or_create(&path, &geometry()).expect("open");
            drop(j);
            let mut cut = bytes.clone();
            // Find where record 3 starts: recover a copy cut to two records' worth.
            let r3_len = edit_payload(&edits[2], &path).expect("payload").len() + 32;
            cut.truncate(bytes.len() - r3_len);
            cut.len()
        };
        for cut in [two + 1, two + 31, two + 32, two + 200, bytes.len() - 1] {
            std::fs::write(&path, &bytes[..cut]).expect("write");
            let r = recover(&path).expect("recover");
            assert_eq!(r.edits.len(), 2, "cut at {cut}");
            let why = r.dropped.expect("says what was dropped");
            assert!(why.contains("record 2 onward"), "{why}");
        }
        // A flipped byte inside record 2 drops records 2 and 3 (nothing after damage is trusted).
        let mut damaged = bytes.clone();
        damaged[two - 10] ^= 0x40;
        std::fs::write(&path, &damaged).expect("write");
        let r = recover(&path).expect("recover");
        assert_eq!(r.edits.len(), 1);
        assert!(r.dropped.expect("dropped").contains("checksum"));
        // Opening for append cuts the torn tail off, so a new record follows a good one.
        std::fs::write(&path, &bytes[..two + 100]).expect("write");
        let (mut journal, r) = Journal::open_or_create(&path, &geometry()).expect("open");
        assert_eq!(r.edits.len(), 2);
        journal.append(&edits[2]).expect("append");
        let r = recover(&path).expect("recover");
        assert!(r.dropped.is_none());
        assert_eq!(r.edits.len(), 3);
        assert!(same_edit(&r.edits[2], &edits[2]));
        // A damaged file header is an error naming the file, not an empty recovery.
        let mut bad = bytes.clone();
        bad[20] ^= 1;
        std::fs::write(&path, &bad).expect("write");
        let e = recover(&path).expect_err("damaged header").to_string();
        assert!(
            e.contains(&path.display().to_string()) && e.contains("damaged"),
            "{e}"
        );
    }

    #[test]
    fn a_full_disk_fails_the_append_and_keeps_every_earlier_record() {
        let (_dir, path, edits, mut layer) = journal_with(4);
        let (mut journal, _) = Journal::open_or_create(&path, &geometry()).expect("open");
        let before = std::fs::metadata(&path).expect("meta").len();
        journal.fail_writes_after_bytes = Some(before + 100);
        let fifth = stroke(&mut layer, 4);
        let e = journal.append(&fifth).expect_err("disk full").to_string();
        assert!(
            e.contains("No space left") && e.contains("4 earlier record(s) are kept"),
            "{e}"
        );
        assert!(e.contains(&path.display().to_string()), "{e}");
        assert_eq!(std::fs::metadata(&path).expect("meta").len(), before);
        let r = recover(&path).expect("recover");
        assert!(r.dropped.is_none());
        assert_eq!(r.edits.len(), 4);
        assert!(r.edits.iter().zip(&edits).all(|(a, b)| same_edit(a, b)));
        // Space again: the same edit appends after the kept ones.
        journal.fail_writes_after_bytes = None;
        journal.append(&fifth).expect("append");
        let r = recover(&path).expect("recover");
        assert_eq!(r.edits.len(), 5);
        assert!(same_edit(&r.edits[4], &fifth));
    }

    #[test]
    fn an_empty_journal_left_by_a_crash_at_creation_starts_anew() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("j");
        std::fs::write(&path, b"").expect("empty file");
        let (mut journal, r) = Journal::open_or_create(&path, &geometry()).expect("open");
        assert!(r.edits.is_empty() && r.dropped.is_none());
        let mut layer = LabelLayer::new_empty(geometry()).expect("grid");
        journal.append(&stroke(&mut layer, 0)).expect("append");
        assert_eq!(recover(&path).expect("recover").edits.len(), 1);
    }

    #[test]
    fn a_journal_for_another_grid_or_not_a_journal_is_refused() {
        let (_dir, path, _, _) = journal_with(1);
        let other = VolumeGeometry::axis_aligned([10, 10, 10], [1.0; 3]);
        let e = Journal::open_or_create(&path, &other)
            .err()
            .expect("refused")
            .to_string();
        assert!(e.contains("belongs to a label grid"), "{e}");
        std::fs::write(&path, b"hello").expect("write");
        let e = recover(&path).expect_err("not a journal").to_string();
        assert!(e.contains("not a Strata segmentation journal"), "{e}");
    }
}
