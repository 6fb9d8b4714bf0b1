//! The bricks' checksums of a Strata export, and the check of each chunk read against them and
//! the skeleton.
//!
//! Zarr reads a missing chunk as the fill value, so a deleted shard, an index entry marked
//! empty or a changed key encoding reads as a plausible image; an index entry pointing at
//! another chunk, or bit flips that zstd decodes anyway, read as another one. A Strata export
//! knows better: its skeleton says each node's range (and which are constant), and
//! `strata-checksums.bin` holds a crc32c of every varying brick's core, as read back (its
//! samples in z, y, x order, one byte each for 8-bit stores, two little-endian bytes
//! otherwise, clipped to the level). A chunk whose core disagrees with either is damage:
//! import fails naming it, streaming reports the brick damaged (the loader keeps its parent).
//! Constant nodes need no checksum: their chunk must hold that value throughout.
//!
//! The object: `SCK1`, the entry count (u64), per entry level (u8), x, y, z (u32) and the
//! checksum (u32), all little-endian, then a crc32c of everything before it. It grows with
//! the varying bricks, as the skeleton does.

use std::collections::HashMap;

use strata_storage::store::Skeleton;
use strata_types::{BrickId, OctreeLayout, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};

const MAGIC: &[u8; 4] = b"SCK1";
const ENTRY_BYTES: usize = 17;

/// A brick core's checksum and range, as read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CoreDigest {
    pub crc: u32,
    pub min: u16,
    pub max: u16,
}

/// Accumulates a core row by row (what import and streaming both do, in the same order).
#[derive(Clone, Copy, Debug)]
pub struct DigestState {
    crc: u32,
    min: u16,
    max: u16,
}

impl Default for DigestState {
    fn default() -> Self {
        DigestState {
            crc: 0,
            min: u16::MAX,
            max: 0,
        }
    }
}

impl DigestState {
    /// A row of samples as stored bytes (1 per sample when `narrow`, else 2, little-endian).
    pub fn add_row_bytes(&mut self, bytes: &[u8], narrow: bool) {
        self.crc = crc32c::crc32c_append(self.crc, bytes);
        if narrow {
            for &b in bytes {
                self.min = self.min.min(u16::from(b));
                self.max = self.max.max(u16::from(b));
            }
        } else {
            for pair in bytes.chunks_exact(2) {
                let v = u16::from_le_bytes([pair[0], pair[1]]);
                self.min = self.min.min(v);
                self.max = self.max.max(v);
            }
        }
    }

    pub fn add_row(&mut self, samples: &[u16], narrow: bool) {
        let bytes: Vec<u8> = if narrow {
            samples.iter().map(|&v| v as u8).collect()
        } else {
            samples.iter().flat_map(|v| v.to_le_bytes()).collect()
        };
        self.add_row_bytes(&bytes, narrow);
    }

    pub fn finish(self) -> CoreDigest {
        CoreDigest {
            crc: self.crc,
            min: self.min,
            max: self.max,
        }
    }
}

/// The digest of brick `id`'s core out of its 36³ payload (x fastest), clipped to the level.
pub fn core_digest(
    payload: &[u16],
    id: BrickId,
    layout: &OctreeLayout,
    narrow: bool,
) -> CoreDigest {
    let dims = layout.level_dims[id.level as usize];
    let core = BRICK_CORE;
    let n = [0, 1, 2].map(|a| (dims[a] - id.coords[a] * core).min(core) as usize);
    let (p, a) = (BRICK_PAYLOAD as usize, BRICK_APRON as usize);
    let mut state = DigestState::default();
    for z in 0..n[2] {
        for y in 0..n[1] {
            let start = ((z + a) * p + (y + a)) * p + a;
            state.add_row(&payload[start..start + n[0]], narrow);
        }
    }
    state.finish()
}

/// The checksums object's bytes for `entries`.
pub fn encode(entries: &[(BrickId, u32)]) -> Vec<u8> {
    let mut out = Vec::with_capacity(12 + entries.len() * ENTRY_BYTES + 4);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(entries.len() as u64).to_le_bytes());
    for (id, crc) in entries {
        out.push(id.level);
        for c in id.coords {
            out.extend_from_slice(&c.to_le_bytes());
        }
        out.extend_from_slice(&crc.to_le_bytes());
    }
    let sum = crc32c::crc32c(&out);
    out.extend_from_slice(&sum.to_le_bytes());
    out
}

/// What a Strata export's chunks are checked against.
pub struct ChunkCheck {
    pub skeleton: Skeleton,
    pub layout: OctreeLayout,
    /// `None` for a version-1 export (the skeleton's ranges are then the only check).
    pub checksums: Option<HashMap<BrickId, u32>>,
    pub narrow: bool,
    /// The arrays' fill value (what an absent chunk reads as).
    pub fill: u16,
}

/// Why a checksums object was refused; each message reads after "the bricks' checksums".
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ChecksumsDecodeError {
    #[error("is truncated")]
    Truncated,
    #[error("fails its checksum")]
    Checksum,
    #[error("is not a checksums object")]
    NotChecksums,
    #[error("says {count} entries in {bytes} bytes")]
    EntryCount { count: u64, bytes: usize },
    #[error("names brick level {level} at {coords:?}, outside the octree")]
    OutsideOctree { level: u8, coords: [u32; 3] },
}

/// Reads the checksums object; the error says what is wrong with it.
pub fn decode(
    bytes: &[u8],
    layout: &OctreeLayout,
) -> Result<HashMap<BrickId, u32>, ChecksumsDecodeError> {
    let body_len = bytes
        .len()
        .checked_sub(4)
        .ok_or(ChecksumsDecodeError::Truncated)?;
    let (body, sum) = bytes.split_at(body_len);
    let sum = sum
        .try_into()
        .map_err(|_| ChecksumsDecodeError::Truncated)?;
    if crc32c::crc32c(body) != u32::from_le_bytes(sum) {
        return Err(ChecksumsDecodeError::Checksum);
    }
    if body.len() < 12 || &body[..4] != MAGIC {
        return Err(ChecksumsDecodeError::NotChecksums);
    }
    let count = u64::from_le_bytes(
        body[4..12]
            .try_into()
            .map_err(|_| ChecksumsDecodeError::Truncated)?,
    );
    let entries = &body[12..];
    // The count must match the bytes: nothing is allocated from the header alone.
    if count != (entries.len() / ENTRY_BYTES) as u64 || entries.len() % ENTRY_BYTES != 0 {
        return Err(ChecksumsDecodeError::EntryCount {
            count,
            bytes: entries.len(),
        });
    }
    let mut map = HashMap::with_capacity(count as usize);
    for e in entries.chunks_exact(ENTRY_BYTES) {
        let word = |i: usize| u32::from_le_bytes([e[i], e[i + 1], e[i + 2], e[i + 3]]);
        let id = BrickId::new(e[0], [word(1), word(5), word(9)]);
        if !layout.contains(id) {
            return Err(ChecksumsDecodeError::OutsideOctree {
                level: id.level,
                coords: id.coords,
            });
        }
        map.insert(id, word(13));
    }
    Ok(map)
}

/// How a brick's core, as read, differs from what the export wrote; each message reads after
/// the brick's name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ChunkCheckError {
    #[error("lies outside the export's skeleton")]
    OutsideSkeleton,
    /// The chunk reads as the fill value throughout: deleted, or its key or index changed.
    #[error("is missing (its chunk reads as the fill value {fill}) where the export's skeleton says it {says}: the export is damaged (a shard or chunk deleted, or its index or key encoding changed)")]
    Missing { fill: u16, says: SkeletonSays },
    #[error("holds values {min}..={max} where the export's skeleton says it holds {value} throughout: the export is damaged")]
    NotConstant { min: u16, max: u16, value: u16 },
    #[error("holds values {min}..={max} outside the export skeleton's {node_min}..={node_max}: the export is damaged")]
    OutOfRange {
        min: u16,
        max: u16,
        node_min: u16,
        node_max: u16,
    },
    #[error("has no checksum in the export although its values vary: the export's checksums are damaged")]
    NoChecksum,
    #[error("fails its checksum (its data or its shard index is damaged)")]
    Checksum,
}

/// What the export's skeleton says a missing brick held.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SkeletonSays {
    Constant(u16),
    Range(u16, u16),
}

impl std::fmt::Display for SkeletonSays {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SkeletonSays::Constant(value) => write!(f, "holds the value {value} throughout"),
            SkeletonSays::Range(min, max) => write!(f, "holds values {min}..={max}"),
        }
    }
}

impl ChunkCheck {
    /// Whether brick `id`'s core, as read, is what the export wrote; the error says how not.
    pub fn check(&self, id: BrickId, digest: CoreDigest) -> Result<(), ChunkCheckError> {
        let Some(node) = self.skeleton.node(id) else {
            return Err(ChunkCheckError::OutsideSkeleton);
        };
        let all_fill = digest.min == self.fill && digest.max == self.fill;
        let missing = |says| ChunkCheckError::Missing {
            fill: self.fill,
            says,
        };
        if node.min == node.max {
            if digest.min != node.min || digest.max != node.min {
                return Err(if all_fill {
                    missing(SkeletonSays::Constant(node.min))
                } else {
                    ChunkCheckError::NotConstant {
                        min: digest.min,
                        max: digest.max,
                        value: node.min,
                    }
                });
            }
            return Ok(());
        }
        if digest.min < node.min || digest.max > node.max {
            return Err(if all_fill {
                missing(SkeletonSays::Range(node.min, node.max))
            } else {
                ChunkCheckError::OutOfRange {
                    min: digest.min,
                    max: digest.max,
                    node_min: node.min,
                    node_max: node.max,
                }
            });
        }
        let Some(checksums) = &self.checksums else {
            return Ok(());
        };
        match checksums.get(&id) {
            None => Err(ChunkCheckError::NoChecksum),
            Some(&crc) if crc != digest.crc => Err(if all_fill {
                missing(SkeletonSays::Range(node.min, node.max))
            } else {
                ChunkCheckError::Checksum
            }),
            Some(_) => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checksums_round_trip_and_refuse_damage() {
        let layout = OctreeLayout::new([64, 64, 64]);
        let entries = vec![
            (BrickId::new(0, [1, 0, 1]), 7),
            (BrickId::new(1, [0, 0, 0]), 9),
        ];
        let bytes = encode(&entries);
        let map = decode(&bytes, &layout).unwrap();
        assert_eq!(map.len(), 2);
        assert_eq!(map[&BrickId::new(0, [1, 0, 1])], 7);
        let mut flipped = bytes.clone();
        flipped[14] ^= 1;
        assert!(decode(&flipped, &layout)
            .unwrap_err()
            .to_string()
            .contains("checksum"));
        assert!(decode(&bytes[..3], &layout).is_err());
        // A count that the bytes do not hold (checksum recomputed) is refused, not allocated.
        let mut lying = bytes[..bytes.len() - 4].to_vec();
        lying[4..12].copy_from_slice(&u64::MAX.to_le_bytes());
        let sum = crc32c::crc32c(&lying);
        lying.extend_from_slice(&sum.to_le_bytes());
        assert!(decode(&lying, &layout)
            .unwrap_err()
            .to_string()
            .contains("entries"));
        let outside = encode(&[(BrickId::new(0, [2, 0, 0]), 1)]);
        assert!(decode(&outside, &layout)
            .unwrap_err()
            .to_string()
            .contains("outside"));
    }
}
