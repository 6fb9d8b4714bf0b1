//! A pre-check of a DICOM file's element lengths against its size, before dicom-rs parses it.
//!
//! dicom-rs reserves a value's declared length before reading it, so one damaged length field
//! (0xFFFFFFFE in a 528 KB file) allocates 4 GiB. This walks the element headers up to the pixel
//! data (seeking over values, reading ~12 bytes per element) and refuses any defined length that
//! runs past the end of the file, naming the tag and its offset. It is not a parser: it checks
//! lengths only, descends into sequences and items linearly, and leaves everything else to
//! dicom-rs. Deflated data sets (the bytes are compressed) are not walked.

use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use crate::error::{Result, StorageError};

const UNDEFINED: u32 = 0xFFFF_FFFF;
/// Most element headers walked: a real header has hundreds; beyond this the walk stops (the
/// file is then left to dicom-rs, whose own reads are bounded by what was checked so far).
const MAX_ELEMENTS: usize = 1_000_000;

const IMPLICIT_LE: &str = "1.2.840.10008.1.2";
const EXPLICIT_BE: &str = "1.2.840.10008.1.2.2";
const DEFLATED: &str = "1.2.840.10008.1.2.1.99";

/// VRs whose explicit encoding has 2 reserved bytes and a 4-byte length: all but the short
/// ones, because dicom-rs reads an unknown VR (a damaged one) as UN, which has a long length.
fn has_long_length(vr: [u8; 2]) -> bool {
    !matches!(
        &vr,
        b"AE"
            | b"AS"
            | b"AT"
            | b"CS"
            | b"DA"
            | b"DS"
            | b"DT"
            | b"FL"
            | b"FD"
            | b"IS"
            | b"LO"
            | b"LT"
            | b"PN"
            | b"SH"
            | b"SL"
            | b"SS"
            | b"ST"
            | b"TM"
            | b"UI"
            | b"UL"
            | b"US"
    )
}

struct Walker<R> {
    reader: R,
    pos: u64,
    file_len: u64,
}

impl<R: Read + Seek> Walker<R> {
    fn read<const N: usize>(&mut self) -> Option<[u8; N]> {
        let mut b = [0u8; N];
        self.reader.read_exact(&mut b).ok()?;
        self.pos += N as u64;
        Some(b)
    }
    fn skip(&mut self, n: u64) -> bool {
        self.pos += n;
        self.reader.seek(SeekFrom::Start(self.pos)).is_ok()
    }
}

/// Checks every defined element length of the DICOM Part 10 file at `path`.
pub(crate) fn check_element_lengths(path: &Path) -> Result<()> {
    let file = crate::regular_file::open(path)?;
    let file_len = file
        .metadata()
        .map_err(|e| StorageError::io(path, e))?
        .len();
    let mut w = Walker {
        reader: BufReader::with_capacity(4096, file),
        pos: 0,
        file_len,
    };
    if !w.skip(128) || w.read::<4>().is_none_or(|m| &m != b"DICM") {
        return Ok(()); // not Part 10: dicom-rs says what is wrong
    }
    let damaged = |tag: (u16, u16), at: u64, len: u64, left: u64| {
        StorageError::invalid(
            path,
            format!(
                "damaged DICOM file: element ({:04X},{:04X}) at byte {at} declares {len} bytes, but only {left} remain",
                tag.0, tag.1
            ),
        )
    };
    // File meta group: always explicit VR little endian.
    let mut transfer_syntax = String::new();
    loop {
        let at = w.pos;
        let Some(head) = w.read::<8>() else {
            return Ok(());
        };
        let group = u16::from_le_bytes([head[0], head[1]]);
        if group != 0x0002 {
            // The data set starts here: step back over the 8 bytes just read.
            w.pos = at;
            if w.reader.seek(SeekFrom::Start(at)).is_err() {
                return Ok(());
            }
            break;
        }
        let element = u16::from_le_bytes([head[2], head[3]]);
        let vr = [head[4], head[5]];
        let len = if has_long_length(vr) {
            match w.read::<4>() {
                Some(l) => u32::from_le_bytes(l),
                None => return Ok(()),
            }
        } else {
            u32::from(u16::from_le_bytes([head[6], head[7]]))
        };
        let left = w.file_len.saturating_sub(w.pos);
        if len != UNDEFINED && u64::from(len) > left {
            return Err(damaged((group, element), at, u64::from(len), left));
        }
        if element == 0x0010 && len <= 64 {
            let mut uid = vec![0u8; len as usize];
            if w.reader.read_exact(&mut uid).is_err() {
                return Ok(());
            }
            w.pos += u64::from(len);
            transfer_syntax = String::from_utf8_lossy(&uid)
                .trim_end_matches(['\0', ' '])
                .to_string();
        } else if len != UNDEFINED && !w.skip(u64::from(len)) {
            return Ok(());
        }
    }
    if transfer_syntax == DEFLATED {
        return Ok(());
    }
    let explicit = transfer_syntax != IMPLICIT_LE;
    let big_endian = transfer_syntax == EXPLICIT_BE;
    let u16_of = |b: [u8; 2]| {
        if big_endian {
            u16::from_be_bytes(b)
        } else {
            u16::from_le_bytes(b)
        }
    };
    let u32_of = |b: [u8; 4]| {
        if big_endian {
            u32::from_be_bytes(b)
        } else {
            u32::from_le_bytes(b)
        }
    };
    for _ in 0..MAX_ELEMENTS {
        let at = w.pos;
        let Some(tag) = w.read::<4>() else {
            return Ok(());
        };
        let tag = (u16_of([tag[0], tag[1]]), u16_of([tag[2], tag[3]]));
        // Items and delimiters: a tag and a 4-byte length, no VR in any encoding.
        let is_item = tag.0 == 0xFFFE;
        let (len, is_sequence) = if is_item || !explicit {
            let Some(l) = w.read::<4>() else {
                return Ok(());
            };
            // Implicit VR cannot tell a sequence from a value; an undefined length means one.
            (u32_of(l), false)
        } else {
            let Some(vr) = w.read::<2>() else {
                return Ok(());
            };
            if has_long_length(vr) {
                let Some(l) = w.read::<6>() else {
                    return Ok(());
                };
                (u32_of([l[2], l[3], l[4], l[5]]), &vr == b"SQ")
            } else {
                let Some(l) = w.read::<2>() else {
                    return Ok(());
                };
                (u32::from(u16_of(l)), false)
            }
        };
        let left = w.file_len.saturating_sub(w.pos);
        if len != UNDEFINED && u64::from(len) > left {
            return Err(damaged(tag, at, u64::from(len), left));
        }
        if tag == (0x7FE0, 0x0010) {
            return Ok(()); // pixel data: its length is checked; dicom-rs stops before it
        }
        // Containers (items, sequences, undefined lengths) are walked into; values are skipped.
        let walk_into = is_item || is_sequence || len == UNDEFINED;
        if !walk_into && !w.skip(u64::from(len)) {
            return Ok(());
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn part10(dataset: &[u8]) -> Vec<u8> {
        let mut f = vec![0u8; 128];
        f.extend_from_slice(b"DICM");
        // (0002,0010) UI "1.2.840.10008.1.2.1" (explicit VR little endian), padded to even.
        let ts = b"1.2.840.10008.1.2.1\0";
        f.extend_from_slice(&[0x02, 0x00, 0x10, 0x00, b'U', b'I']);
        f.extend_from_slice(&(ts.len() as u16).to_le_bytes());
        f.extend_from_slice(ts);
        f.extend_from_slice(dataset);
        f
    }

    fn element(
        group: u16,
        elem: u16,
        vr: &[u8; 2],
        value: &[u8],
        declared: Option<u32>,
    ) -> Vec<u8> {
        let mut e = Vec::new();
        e.extend_from_slice(&group.to_le_bytes());
        e.extend_from_slice(&elem.to_le_bytes());
        e.extend_from_slice(vr);
        let len = declared.unwrap_or(value.len() as u32);
        if has_long_length(*vr) {
            e.extend_from_slice(&[0, 0]);
            e.extend_from_slice(&len.to_le_bytes());
        } else {
            e.extend_from_slice(&(len as u16).to_le_bytes());
        }
        e.extend_from_slice(value);
        e
    }

    #[test]
    fn a_length_past_the_end_names_the_tag_and_offset() {
        let dir = tempfile::tempdir().unwrap();
        let mut ds = element(0x0008, 0x0060, b"CS", b"CT", None);
        ds.extend(element(0x0010, 0x4000, b"UT", b"note", Some(0xFFFF_FFFE)));
        let p = dir.path().join("bad.dcm");
        std::fs::write(&p, part10(&ds)).unwrap();
        let e = check_element_lengths(&p).unwrap_err().to_string();
        assert!(
            e.contains("bad.dcm") && e.contains("(0010,4000)") && e.contains("4294967294"),
            "{e}"
        );
    }

    #[test]
    fn sound_files_and_sequences_pass() {
        let dir = tempfile::tempdir().unwrap();
        let item_body = element(0x0008, 0x1150, b"UI", b"1.2\0", None);
        let mut item = vec![0xFE, 0xFF, 0x00, 0xE0];
        item.extend_from_slice(&(item_body.len() as u32).to_le_bytes());
        item.extend_from_slice(&item_body);
        let mut ds = element(0x0008, 0x1140, b"SQ", &item, None);
        ds.extend(element(0x7FE0, 0x0010, b"OW", &[0u8; 16], None));
        let p = dir.path().join("good.dcm");
        std::fs::write(&p, part10(&ds)).unwrap();
        check_element_lengths(&p).unwrap();
    }
}
