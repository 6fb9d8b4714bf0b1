//! Brick payloads on disk: lz4-compressed voxels behind an xxh3 checksum, or a constant marker.
//!
//! Value layout (little endian): `kind: u8 | checksum: u64 | body`. The checksum covers the
//! brick's key and the body, so a brick swapped under another key is caught as well as a flipped
//! bit. Kinds: 0 = lz4 block of u16 samples, 1 = lz4 block of u8 samples, 2 = constant (body is
//! the u16 value, no payload).

use xxhash_rust::xxh3::Xxh3;

use crate::octree::{BrickId, APRON, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS, CORE};

const KIND_U16: u8 = 0;
const KIND_U8: u8 = 1;
const KIND_CONSTANT: u8 = 2;
const HEADER_LEN: usize = 9;

/// sled key of a brick: level first, then z, y, x big-endian, so a level's bricks are contiguous
/// and a z-row of bricks is contiguous within it.
pub fn brick_key(id: BrickId) -> [u8; 13] {
    let mut k = [0u8; 13];
    k[0] = id.level;
    k[1..5].copy_from_slice(&id.coords[2].to_be_bytes());
    k[5..9].copy_from_slice(&id.coords[1].to_be_bytes());
    k[9..13].copy_from_slice(&id.coords[0].to_be_bytes());
    k
}

pub fn brick_id_from_key(key: &[u8]) -> Option<BrickId> {
    if key.len() != 13 {
        return None;
    }
    let be = |r: std::ops::Range<usize>| -> Option<u32> {
        Some(u32::from_be_bytes(key[r].try_into().ok()?))
    };
    Some(BrickId {
        level: key[0],
        coords: [be(9..13)?, be(5..9)?, be(1..5)?],
    })
}

fn checksum(key: &[u8], body: &[u8]) -> u64 {
    let mut h = Xxh3::new();
    h.update(key);
    h.update(body);
    h.digest()
}

/// The samples as little-endian bytes: a free view on little-endian machines, a copy elsewhere.
fn u16_le_bytes(voxels: &[u16]) -> std::borrow::Cow<'_, [u8]> {
    if cfg!(target_endian = "little") {
        std::borrow::Cow::Borrowed(bytemuck::cast_slice(voxels))
    } else {
        std::borrow::Cow::Owned(voxels.iter().flat_map(|v| v.to_le_bytes()).collect())
    }
}

/// Range of a brick's voxels (min, max over core and apron).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ValueRange {
    pub min: u16,
    pub max: u16,
}

pub fn value_range(voxels: &[u16]) -> ValueRange {
    let (mut min, mut max) = (u16::MAX, u16::MIN);
    for &v in voxels {
        min = min.min(v);
        max = max.max(v);
    }
    ValueRange { min, max }
}

/// Encodes a 36³ brick. `narrow` stores u8 samples (the store's scalar type is u8).
pub fn encode_brick(id: BrickId, voxels: &[u16], range: ValueRange, narrow: bool) -> Vec<u8> {
    debug_assert_eq!(voxels.len(), BRICK_PAYLOAD_VOXELS);
    let key = brick_key(id);
    let (kind, body) = if range.min == range.max {
        (KIND_CONSTANT, range.min.to_le_bytes().to_vec())
    } else if narrow {
        let bytes: Vec<u8> = voxels.iter().map(|&v| v as u8).collect();
        (KIND_U8, lz4_flex::block::compress_prepend_size(&bytes))
    } else {
        (
            KIND_U16,
            lz4_flex::block::compress_prepend_size(&u16_le_bytes(voxels)),
        )
    };
    let mut out = Vec::with_capacity(HEADER_LEN + body.len());
    out.push(kind);
    out.extend_from_slice(&checksum(&key, &body).to_le_bytes());
    out.extend_from_slice(&body);
    out
}

/// Why a stored brick could not be decoded. The store wraps it with the file name.
#[derive(Debug, PartialEq, Eq)]
pub enum BrickDecodeError {
    TooShort,
    ChecksumMismatch { expected: u64, actual: u64 },
    UnknownKind(u8),
    Decompress(String),
    WrongSize(usize),
}

impl std::fmt::Display for BrickDecodeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BrickDecodeError::TooShort => write!(f, "record too short"),
            BrickDecodeError::ChecksumMismatch { expected, actual } => {
                write!(
                    f,
                    "checksum mismatch (stored {expected:016x}, computed {actual:016x})"
                )
            }
            BrickDecodeError::UnknownKind(k) => write!(f, "unknown brick kind {k}"),
            BrickDecodeError::Decompress(e) => write!(f, "lz4 decompression failed: {e}"),
            BrickDecodeError::WrongSize(n) => {
                write!(f, "decoded {n} voxels, expected {BRICK_PAYLOAD_VOXELS}")
            }
        }
    }
}

/// Checks a stored record's checksum without decompressing it; returns the checksum (what the
/// data service puts in its ETag). A record that fails here is never served as valid bytes.
pub fn verify_record(id: BrickId, record: &[u8]) -> Result<u64, BrickDecodeError> {
    if record.len() < HEADER_LEN {
        return Err(BrickDecodeError::TooShort);
    }
    let mut sum = [0u8; 8];
    sum.copy_from_slice(&record[1..9]);
    let expected = u64::from_le_bytes(sum);
    let actual = checksum(&brick_key(id), &record[HEADER_LEN..]);
    if actual != expected {
        return Err(BrickDecodeError::ChecksumMismatch { expected, actual });
    }
    Ok(expected)
}

/// Decodes and verifies a stored brick into its 36³ voxels.
pub fn decode_brick(id: BrickId, record: &[u8]) -> Result<Vec<u16>, BrickDecodeError> {
    if record.len() < HEADER_LEN {
        return Err(BrickDecodeError::TooShort);
    }
    let kind = record[0];
    let mut sum = [0u8; 8];
    sum.copy_from_slice(&record[1..9]);
    let expected = u64::from_le_bytes(sum);
    let body = &record[HEADER_LEN..];
    let actual = checksum(&brick_key(id), body);
    if actual != expected {
        return Err(BrickDecodeError::ChecksumMismatch { expected, actual });
    }
    match kind {
        KIND_CONSTANT => {
            let v = body.get(0..2).ok_or(BrickDecodeError::TooShort)?;
            Ok(vec![u16::from_le_bytes([v[0], v[1]]); BRICK_PAYLOAD_VOXELS])
        }
        KIND_U8 => {
            let bytes = lz4_flex::block::decompress_size_prepended(body)
                .map_err(|e| BrickDecodeError::Decompress(e.to_string()))?;
            if bytes.len() != BRICK_PAYLOAD_VOXELS {
                return Err(BrickDecodeError::WrongSize(bytes.len()));
            }
            Ok(bytes.into_iter().map(u16::from).collect())
        }
        KIND_U16 => {
            let bytes = lz4_flex::block::decompress_size_prepended(body)
                .map_err(|e| BrickDecodeError::Decompress(e.to_string()))?;
            if bytes.len() != BRICK_PAYLOAD_VOXELS * 2 {
                return Err(BrickDecodeError::WrongSize(bytes.len() / 2));
            }
            Ok(bytes
                .chunks_exact(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .collect())
        }
        other => Err(BrickDecodeError::UnknownKind(other)),
    }
}

/// Cuts brick `(bx, by)` of a z-row out of a level's slices. `slice_at(z)` returns the level
/// slice with index `z` (already clamped to the level by the caller's window).
pub fn extract_brick<'a>(
    bx: u64,
    by: u64,
    bz: u64,
    level_dims: [u64; 3],
    slice_at: &dyn Fn(u64) -> &'a [u16],
    out: &mut Vec<u16>,
) {
    out.clear();
    let [nx, ny, nz] = level_dims;
    let clamp = |v: i64, n: u64| v.clamp(0, n as i64 - 1) as u64;
    let origin = |b: u64| (b * CORE) as i64 - APRON as i64;
    let (x0, y0, z0) = (origin(bx), origin(by), origin(bz));
    // Column indices are the same for every row of the brick; computing them once keeps the
    // hot loop a gather.
    let x_interior = x0 >= 0 && x0 + BRICK_PAYLOAD as i64 <= nx as i64;
    // Column indices only matter at the volume's x edges; interior rows are one contiguous copy.
    let xs: Vec<usize> = (0..BRICK_PAYLOAD as i64)
        .map(|dx| clamp(x0 + dx, nx) as usize)
        .collect();
    for dz in 0..BRICK_PAYLOAD as i64 {
        let slice = slice_at(clamp(z0 + dz, nz));
        for dy in 0..BRICK_PAYLOAD as i64 {
            let row = clamp(y0 + dy, ny) as usize * nx as usize;
            let row = &slice[row..row + nx as usize];
            if x_interior {
                out.extend_from_slice(&row[x0 as usize..x0 as usize + BRICK_PAYLOAD as usize]);
            } else {
                out.extend(xs.iter().map(|&x| row[x]));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_brick() -> Vec<u16> {
        (0..BRICK_PAYLOAD_VOXELS)
            .map(|i| (i * 7 % 5000) as u16)
            .collect()
    }

    #[test]
    fn round_trip_and_checksum() {
        let id = BrickId::new(1, [2, 3, 4]);
        let v = sample_brick();
        let rec = encode_brick(id, &v, value_range(&v), false);
        assert_eq!(decode_brick(id, &rec).unwrap(), v);
        // Any flipped byte in the record is caught.
        for pos in [0usize, 3, 9, rec.len() / 2, rec.len() - 1] {
            let mut bad = rec.clone();
            bad[pos] ^= 0x10;
            assert!(
                decode_brick(id, &bad).is_err(),
                "flip at {pos} not detected"
            );
        }
        // The same record under another key is caught too.
        assert!(matches!(
            decode_brick(BrickId::new(1, [2, 3, 5]), &rec),
            Err(BrickDecodeError::ChecksumMismatch { .. })
        ));
    }

    #[test]
    fn constant_and_narrow_bricks() {
        let id = BrickId::new(0, [0, 0, 0]);
        let c = vec![77u16; BRICK_PAYLOAD_VOXELS];
        let rec = encode_brick(id, &c, value_range(&c), false);
        assert!(
            rec.len() < 16,
            "constant brick stored as marker, got {} bytes",
            rec.len()
        );
        assert_eq!(decode_brick(id, &rec).unwrap(), c);
        let n: Vec<u16> = (0..BRICK_PAYLOAD_VOXELS)
            .map(|i| (i % 251) as u16)
            .collect();
        let rec = encode_brick(id, &n, value_range(&n), true);
        assert_eq!(decode_brick(id, &rec).unwrap(), n);
    }

    #[test]
    fn key_order_keeps_levels_contiguous() {
        let a = brick_key(BrickId::new(0, [100, 100, 100]));
        let b = brick_key(BrickId::new(1, [0, 0, 0]));
        assert!(a < b);
        let id = BrickId::new(3, [5, 6, 7]);
        assert_eq!(brick_id_from_key(&brick_key(id)), Some(id));
    }
}
