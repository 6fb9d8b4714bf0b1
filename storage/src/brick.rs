//! Brick payloads on disk: compressed voxels behind an xxh3 checksum, or a constant marker.
//!
//! Value layout (little endian): `kind: u8 | checksum: u64 | body`. The checksum covers the
//! brick's key and the body (and, for the kinds of format 2, the kind byte), so a brick swapped
//! under another key is caught as well as a flipped bit. The kind names the codec, so every record decodes on its own (the data service sends
//! records as stored, and a client needs no store header to read them):
//!
//! | kind | body                                             | written by              |
//! |------|--------------------------------------------------|-------------------------|
//! | 0    | lz4 block of u16 samples (size-prefixed)         | format 1 (`lz4`)        |
//! | 1    | lz4 block of u8 samples (size-prefixed)          | format 1, and `fast` u8 |
//! | 2    | constant: the u16 value, no payload              | every format            |
//! | 3    | byte-shuffled u16 samples, lz4 (size-prefixed)   | format 2 `fast`         |
//! | 4    | byte-shuffled u16 samples, zstd level 1 frame    | format 2 `dense`        |
//! | 5    | u8 samples, zstd level 1 frame                   | format 2 `dense`, before `predicted-u8-bricks` |
//! | 6    | u8 x-delta residuals, zstd frame                 | `fast` u8 (`predicted-u8-bricks`)  |
//! | 7    | u8 median-edge (LOCO-I) residuals, zstd frame    | `dense` u8 before `linear3d-u8-bricks` |
//! | 8    | u8 3-D linear residuals in 6 context streams, a zstd frame each (see [`linear3d`]) | `dense` u8 (`linear3d-u8-bricks`) |
//! | 9    | u8 column-delta residuals (y neighbour), zstd frame | `fast` u8 (`column-delta-u8-bricks`) |
//!
//! u8 samples (8-bit MR) gain nothing from the byte shuffle. A prediction filter turns them into
//! residuals (the sample minus a prediction from its already decoded neighbours, wrapping byte
//! arithmetic, as JPEG-LS and other medical-image codecs do) whose values cluster around zero,
//! and zstd's Huffman stage codes that in fewer bits; lz4 has no entropy stage, and zstd's
//! negative levels store literals raw, so neither gains on residuals. `fast` predicts from the
//! y neighbour, the sample above in the same slice (kind 9): its inverse adds whole rows, so it
//! runs at memory speed (SIMD over a row) where kind 6's x neighbour, which `fast` wrote before,
//! needs a serial running sum per row and took as long as zstd itself; on chris_t1 and FLAIR the
//! y neighbour also predicts better (whole stores: 0.738 / 0.747 of lz4 against 0.759 / 0.774
//! for x). `dense` predicts from
//! seven neighbours in this slice and the one below and codes the residuals in six streams by
//! local activity (kind 8, [`linear3d`]; kind 7, the median edge detector of LOCO-I with one
//! zstd frame, is what `dense` wrote before). Measured (`strata-bench codecs`): chris_t1 and
//! FLAIR 0.74 / 0.75 of lz4 with `fast`, 0.71 / 0.72 with kind 7, 0.64 / 0.69 with kind 8; the Lorenzo predictors (2D and
//! 3D) and an x/y average landed between the two, bit shuffle before zstd was larger. u16 bricks keep the byte shuffle (kinds 3 and 4): on the
//! 16-bit MR and the CT phantom the filters made them larger.
//!
//! The byte shuffle (Blosc's, the Zarr default) stores all low bytes of a brick, then all high
//! bytes: the high plane of a 12-bit scan is nearly constant, which lz4 alone cannot see in
//! interleaved samples. Decompression never allocates more than a brick, whatever a size
//! prefix says.

use serde::{Deserialize, Serialize};
use xxhash_rust::xxh3::Xxh3;

use crate::octree::{BrickId, APRON, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS, CORE};

mod linear3d;
mod zstd_frames;

use zstd_frames::ZstdFrames;

const KIND_LZ4_U16: u8 = 0;
const KIND_LZ4_U8: u8 = 1;
const KIND_CONSTANT: u8 = 2;
const KIND_SHUFFLE_LZ4_U16: u8 = 3;
const KIND_SHUFFLE_ZSTD_U16: u8 = 4;
const KIND_ZSTD_U8: u8 = 5;
const KIND_DELTA_ZSTD_U8: u8 = 6;
const KIND_MED_ZSTD_U8: u8 = 7;
const KIND_LINEAR3D_U8: u8 = 8;
const KIND_COLUMN_DELTA_ZSTD_U8: u8 = 9;
const HEADER_LEN: usize = 9;
/// zstd level of the dense codec: level 1 keeps compression at hundreds of MB/s per core.
const ZSTD_LEVEL: i32 = 1;
/// zstd level after the prediction filters. Higher levels measured no smaller on residuals
/// (their gain is longer matches, and residuals of noisy MR have few), negative ones store the
/// literals raw: level 1 is both the fastest and, within 0.5 %, the smallest.
const PREDICTED_ZSTD_LEVEL: i32 = 1;
/// The store feature a store with kinds 6 and 7 requires: builds that cannot decode them refuse
/// the store with a message instead of failing brick by brick.
pub const PREDICTED_U8_FEATURE: &str = "predicted-u8-bricks";
/// The store feature a store with kind-8 bricks (`dense` u8) requires, on top of
/// [`PREDICTED_U8_FEATURE`]: a build that knows only kinds 0-7 refuses such a store whole.
pub const LINEAR3D_U8_FEATURE: &str = "linear3d-u8-bricks";
/// The store feature a `fast` u8 store of kind-9 bricks requires, on top of
/// [`PREDICTED_U8_FEATURE`]: a build that knows only kinds 0-8 refuses such a store whole.
pub const COLUMN_DELTA_U8_FEATURE: &str = "column-delta-u8-bricks";
/// Edge of a brick's payload (core and apron), the row length of the prediction filters.
const EDGE: usize = BRICK_PAYLOAD as usize;

/// How a store compresses its bricks: a per-store choice recorded in its header.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BrickCodec {
    /// lz4 on interleaved samples: the only codec of format-1 stores (their headers name none).
    /// Written only to produce format-1 stores (tests, the codec benchmark).
    Lz4,
    /// The default: u16 byte shuffle + lz4, u8 column delta (y neighbour) + zstd.
    #[default]
    Fast,
    /// Smaller stores, slower to decode: u16 byte shuffle + zstd, u8 3-D linear prediction +
    /// zstd per activity context.
    Dense,
}

impl BrickCodec {
    pub const ALL: [BrickCodec; 3] = [BrickCodec::Lz4, BrickCodec::Fast, BrickCodec::Dense];

    pub fn name(self) -> &'static str {
        match self {
            BrickCodec::Lz4 => "lz4",
            BrickCodec::Fast => "fast",
            BrickCodec::Dense => "dense",
        }
    }

    pub fn parse(name: &str) -> Option<BrickCodec> {
        Self::ALL
            .into_iter()
            .find(|c| c.name().eq_ignore_ascii_case(name))
    }

    /// What `strata info` prints.
    pub fn describe(self) -> &'static str {
        match self {
            BrickCodec::Lz4 => "lz4 (format 1)",
            BrickCodec::Fast => "fast (u16: byte shuffle + lz4; u8: column delta + zstd)",
            BrickCodec::Dense => {
                "dense (u16: byte shuffle + zstd; u8: 3-D linear prediction + zstd per context)"
            }
        }
    }

    /// The store features a store of this codec requires (its header's `required_features`):
    /// u8 stores of format 2 hold the predicted kinds, `fast` ones kind 9 and `dense` ones kind
    /// 8 as well.
    pub fn required_features(self, narrow: bool) -> Vec<String> {
        match (narrow, self) {
            (true, BrickCodec::Fast) => vec![
                PREDICTED_U8_FEATURE.to_string(),
                COLUMN_DELTA_U8_FEATURE.to_string(),
            ],
            (true, BrickCodec::Dense) => vec![
                PREDICTED_U8_FEATURE.to_string(),
                LINEAR3D_U8_FEATURE.to_string(),
            ],
            _ => Vec::new(),
        }
    }

    /// The codec a store without a codec field uses (format 1).
    pub fn is_format_1(&self) -> bool {
        *self == BrickCodec::Lz4
    }
}

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

/// The record's checksum. Kinds of format 2 (3 and up) also cover the kind byte, so a flip that
/// turns a shuffled brick into a "constant" one is caught; the kinds of format 1 keep the
/// checksum they were written with (key and body). A flip from one group into the other is
/// caught because the two formulas differ.
fn checksum(kind: u8, key: &[u8], body: &[u8]) -> u64 {
    let mut h = Xxh3::new();
    if kind >= KIND_SHUFFLE_LZ4_U16 {
        h.update(&[kind]);
    }
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

/// The record of a brick whose every voxel is `value` (what [`encode_brick`] writes for it).
pub fn constant_record(id: BrickId, value: u16) -> Vec<u8> {
    let body = value.to_le_bytes();
    let mut out = vec![KIND_CONSTANT];
    out.extend_from_slice(&checksum(KIND_CONSTANT, &brick_key(id), &body).to_le_bytes());
    out.extend_from_slice(&body);
    out
}

/// Encodes a 36³ brick with `codec`. `narrow` stores u8 samples (the store's scalar type is u8).
pub fn encode_brick(
    id: BrickId,
    voxels: &[u16],
    range: ValueRange,
    narrow: bool,
    codec: BrickCodec,
) -> Vec<u8> {
    debug_assert_eq!(voxels.len(), BRICK_PAYLOAD_VOXELS);
    let key = brick_key(id);
    let (kind, body) = if range.min == range.max {
        (KIND_CONSTANT, range.min.to_le_bytes().to_vec())
    } else if narrow {
        let bytes: Vec<u8> = voxels.iter().map(|&v| v as u8).collect();
        compress_u8(&bytes, codec)
    } else {
        match codec {
            BrickCodec::Lz4 => (
                KIND_LZ4_U16,
                lz4_flex::block::compress_prepend_size(&u16_le_bytes(voxels)),
            ),
            BrickCodec::Fast => (
                KIND_SHUFFLE_LZ4_U16,
                lz4_flex::block::compress_prepend_size(&shuffle_u16(voxels)),
            ),
            BrickCodec::Dense => {
                let planes = shuffle_u16(voxels);
                match zstd_compress(&planes) {
                    Some(body) => (KIND_SHUFFLE_ZSTD_U16, body),
                    None => (
                        KIND_SHUFFLE_LZ4_U16,
                        lz4_flex::block::compress_prepend_size(&planes),
                    ),
                }
            }
        }
    };
    let mut out = Vec::with_capacity(HEADER_LEN + body.len());
    out.push(kind);
    out.extend_from_slice(&checksum(kind, &key, &body).to_le_bytes());
    out.extend_from_slice(&body);
    out
}

/// Compresses little-endian u16 sample bytes (or u8 samples when `narrow`) the way `codec`
/// stores a brick body, without the record header: what the import benchmark's limit runs.
pub fn compress_samples(sample_bytes: &[u8], narrow: bool, codec: BrickCodec) -> Vec<u8> {
    if narrow {
        return compress_u8(sample_bytes, codec).1;
    }
    match codec {
        BrickCodec::Lz4 => lz4_flex::block::compress_prepend_size(sample_bytes),
        BrickCodec::Fast => lz4_flex::block::compress_prepend_size(&shuffle_bytes(sample_bytes)),
        BrickCodec::Dense => {
            let planes = shuffle_bytes(sample_bytes);
            zstd_compress(&planes)
                .unwrap_or_else(|| lz4_flex::block::compress_prepend_size(&planes))
        }
    }
}

/// The kind and body of u8 samples (a brick, x fastest, rows of [`EDGE`]) under `codec`.
fn compress_u8(bytes: &[u8], codec: BrickCodec) -> (u8, Vec<u8>) {
    let lz4 = || (KIND_LZ4_U8, lz4_flex::block::compress_prepend_size(bytes));
    let body = match codec {
        BrickCodec::Lz4 => return lz4(),
        BrickCodec::Fast => {
            zstd_compress_level(&column_delta_residuals(bytes), PREDICTED_ZSTD_LEVEL)
                .map(|body| (KIND_COLUMN_DELTA_ZSTD_U8, body))
        }
        // Only whole bricks have the 3-D neighbourhood (the import limit passes other lengths).
        BrickCodec::Dense if bytes.len() == BRICK_PAYLOAD_VOXELS => {
            linear3d::compress(bytes).map(|body| (KIND_LINEAR3D_U8, body))
        }
        BrickCodec::Dense => zstd_compress_level(&med_residuals(bytes), PREDICTED_ZSTD_LEVEL)
            .map(|body| (KIND_MED_ZSTD_U8, body)),
    };
    body.unwrap_or_else(lz4)
}

/// zstd of a whole buffer; None only when zstd cannot allocate its context (memory to memory
/// cannot fail otherwise). Callers then store lz4 instead: the record's kind says which.
fn zstd_compress(bytes: &[u8]) -> Option<Vec<u8>> {
    zstd_compress_level(bytes, ZSTD_LEVEL)
}

#[cfg(feature = "local")]
thread_local! {
    /// One zstd context per thread, reused: a context costs more to set up than a brick costs to
    /// compress.
    static ZSTD_COMPRESSOR: std::cell::RefCell<Option<zstd::bulk::Compressor<'static>>> =
        const { std::cell::RefCell::new(None) };
}

#[cfg(feature = "local")]
fn zstd_compress_level(bytes: &[u8], level: i32) -> Option<Vec<u8>> {
    ZSTD_COMPRESSOR.with(|cell| {
        let mut slot = cell.try_borrow_mut().ok()?;
        if slot.is_none() {
            *slot = Some(zstd::bulk::Compressor::new(level).ok()?);
        }
        let compressor = slot.as_mut()?;
        compressor.set_compression_level(level).ok()?;
        compressor.compress(bytes).ok()
    })
}

/// Without `local` there is no zstd encoder (C zstd is local-only; import, the only writer, is
/// too): the encoders then store lz4, as they do when zstd cannot allocate, and the record's kind
/// says so, so what they write still decodes everywhere.
#[cfg(not(feature = "local"))]
fn zstd_compress_level(_bytes: &[u8], _level: i32) -> Option<Vec<u8>> {
    None
}

/// How far back the sample that predicts the row starting at `start` lies in the column-delta
/// filter: one row (the sample above, same slice), or one slice for a slice's first row (the
/// same place in the slice before). The brick's first row is predicted along x instead.
fn column_delta_reach(start: usize) -> usize {
    if start.is_multiple_of(EDGE * EDGE) {
        EDGE * EDGE
    } else {
        EDGE
    }
}

/// Residuals of the column-delta filter (kind 9): each sample minus the one above it in its
/// slice, a slice's first row minus the slice before's, and the very first row an x-delta (0
/// before the first sample). Any length (rows of [`EDGE`], the last may be short); wrapping
/// arithmetic, so every byte maps back exactly.
fn column_delta_residuals(v: &[u8]) -> Vec<u8> {
    let mut r = vec![0u8; v.len()];
    let first = v.len().min(EDGE);
    let mut previous = 0u8;
    for (o, &x) in r[..first].iter_mut().zip(&v[..first]) {
        *o = x.wrapping_sub(previous);
        previous = x;
    }
    for start in (EDGE..v.len()).step_by(EDGE) {
        let end = (start + EDGE).min(v.len());
        let above = start - column_delta_reach(start);
        for ((o, &x), &p) in r[start..end]
            .iter_mut()
            .zip(&v[start..end])
            .zip(&v[above..above + (end - start)])
        {
            *o = x.wrapping_sub(p);
        }
    }
    r
}

/// Inverse of [`column_delta_residuals`], in place. Each row after the first adds a row decoded
/// before it: no dependency inside a row, so the adds run a row at a time in SIMD.
fn restore_column_delta(r: &mut [u8]) {
    let first = r.len().min(EDGE);
    for x in 1..first {
        r[x] = r[x].wrapping_add(r[x - 1]);
    }
    for start in (EDGE..r.len()).step_by(EDGE) {
        let end = (start + EDGE).min(r.len());
        let above = start - column_delta_reach(start);
        let (decoded, rest) = r.split_at_mut(start);
        for (d, &p) in rest[..end - start]
            .iter_mut()
            .zip(&decoded[above..above + (end - start)])
        {
            *d = d.wrapping_add(p);
        }
    }
}

/// Residuals of the x-delta filter: each sample minus its x neighbour; a row's first sample
/// minus the one above it (the row before, or the same place in the slice before for a slice's
/// first row; 0 for the very first sample). Wrapping arithmetic: every byte maps back exactly.
/// What `fast` wrote for u8 before kind 9: kind-6 records still decode, so only the tests write
/// them now.
#[cfg(test)]
fn delta_residuals(v: &[u8]) -> Vec<u8> {
    let mut r = vec![0u8; v.len()];
    for (row_index, (row, out)) in v.chunks(EDGE).zip(r.chunks_mut(EDGE)).enumerate() {
        let start = row_index * EDGE;
        let mut previous = row_start_prediction(v, start);
        for (o, &x) in out.iter_mut().zip(row) {
            *o = x.wrapping_sub(previous);
            previous = x;
        }
    }
    r
}

/// What a row's first sample is predicted from: the sample above it, or at the same place one
/// slice before for a slice's first row, 0 for the first sample of all.
fn row_start_prediction(decoded: &[u8], start: usize) -> u8 {
    if !start.is_multiple_of(EDGE * EDGE) {
        decoded[start - EDGE]
    } else if start > 0 {
        decoded[start - EDGE * EDGE]
    } else {
        0
    }
}

/// Inverse of [`delta_residuals`], in place: a running sum per row. Each row's sum is a serial
/// chain (one add per sample), but rows depend on each other only through their first samples:
/// those are restored first (a short chain down the first column), then four rows are summed in
/// lockstep, four independent chains the core overlaps. The widening to u16 is a separate pass
/// the compiler vectorises (fused into the sum, it was a per-sample push).
fn restore_delta(r: &mut [u8]) {
    const LANES: usize = 4;
    for start in (0..r.len()).step_by(EDGE) {
        // The row-start rule of `row_start_prediction`: only first samples are read, and those
        // before `start` are restored already.
        r[start] = r[start].wrapping_add(row_start_prediction(r, start));
    }
    let mut groups = r.chunks_exact_mut(LANES * EDGE);
    for group in &mut groups {
        let mut acc: [u8; LANES] = std::array::from_fn(|k| group[k * EDGE]);
        for x in 1..EDGE {
            for (k, acc) in acc.iter_mut().enumerate() {
                let d = &mut group[k * EDGE + x];
                *acc = acc.wrapping_add(*d);
                *d = *acc;
            }
        }
    }
    for row in groups.into_remainder().chunks_mut(EDGE) {
        let mut acc = row[0];
        for d in &mut row[1..] {
            acc = acc.wrapping_add(*d);
            *d = acc;
        }
    }
}

/// u8 samples widened to the u16 voxels a brick decodes to.
fn widen(bytes: &[u8]) -> Vec<u16> {
    bytes.iter().map(|&b| u16::from(b)).collect()
}

/// LOCO-I's median edge detector (JPEG-LS): from the left `a`, upper `b` and upper-left `c`
/// neighbours, min(a, b) under a rising edge, max(a, b) under a falling one, else the plane
/// a + b - c.
fn med_prediction(a: u8, b: u8, c: u8) -> u8 {
    let (high, low) = (a.max(b), a.min(b));
    if c >= high {
        low
    } else if c <= low {
        high
    } else {
        // Between low and high, so within 0..=255.
        (i16::from(a) + i16::from(b) - i16::from(c)) as u8
    }
}

/// Residuals of the median-edge filter (wrapping, exact): the median edge detector inside a
/// slice, the x neighbour on a slice's first row, the y neighbour in its first column, the
/// row-start rule of the x-delta filter for a slice's first sample.
fn med_residuals(v: &[u8]) -> Vec<u8> {
    let mut r = vec![0u8; v.len()];
    for start in (0..v.len()).step_by(EDGE) {
        let end = (start + EDGE).min(v.len());
        let (row, out) = (&v[start..end], &mut r[start..end]);
        if (start / EDGE).is_multiple_of(EDGE) {
            let mut previous = row_start_prediction(v, start);
            for (o, &x) in out.iter_mut().zip(row) {
                *o = x.wrapping_sub(previous);
                previous = x;
            }
        } else {
            let above = &v[start - EDGE..end - EDGE];
            out[0] = row[0].wrapping_sub(above[0]);
            for x in 1..row.len() {
                out[x] = row[x].wrapping_sub(med_prediction(row[x - 1], above[x], above[x - 1]));
            }
        }
    }
    r
}

/// Inverse of [`med_residuals`]: row by row, each sample from the ones decoded before it.
fn restore_med(r: &[u8], out: &mut [u16]) {
    let mut decoded = vec![0u8; r.len()];
    for start in (0..r.len()).step_by(EDGE) {
        let end = (start + EDGE).min(r.len());
        let residuals = &r[start..end];
        if (start / EDGE).is_multiple_of(EDGE) {
            let mut previous = row_start_prediction(&decoded, start);
            for (d, &e) in decoded[start..end].iter_mut().zip(residuals) {
                previous = previous.wrapping_add(e);
                *d = previous;
            }
        } else {
            let (done, rest) = decoded.split_at_mut(start);
            let above = &done[start - EDGE..end - EDGE];
            let row = &mut rest[..end - start];
            let mut left = residuals[0].wrapping_add(above[0]);
            row[0] = left;
            for x in 1..row.len() {
                left = residuals[x].wrapping_add(med_prediction(left, above[x], above[x - 1]));
                row[x] = left;
            }
        }
    }
    for (o, &d) in out.iter_mut().zip(&decoded) {
        *o = u16::from(d);
    }
}

/// Splits little-endian u16 samples into planes: all low bytes, then all high bytes.
fn shuffle_u16(voxels: &[u16]) -> Vec<u8> {
    let n = voxels.len();
    let mut out = vec![0u8; n * 2];
    let (low, high) = out.split_at_mut(n);
    for ((v, l), h) in voxels.iter().zip(low.iter_mut()).zip(high.iter_mut()) {
        let [a, b] = v.to_le_bytes();
        *l = a;
        *h = b;
    }
    out
}

/// [`shuffle_u16`] of samples given as little-endian bytes (an odd trailing byte stays last).
fn shuffle_bytes(bytes: &[u8]) -> Vec<u8> {
    let n = bytes.len() / 2;
    let mut out = vec![0u8; bytes.len()];
    let (low, rest) = out.split_at_mut(n);
    let (high, tail) = rest.split_at_mut(n);
    for ((pair, l), h) in bytes
        .chunks_exact(2)
        .zip(low.iter_mut())
        .zip(high.iter_mut())
    {
        *l = pair[0];
        *h = pair[1];
    }
    tail.copy_from_slice(&bytes[2 * n..]);
    out
}

/// Inverse of [`shuffle_u16`]: `planes` holds `out.len()` low bytes, then as many high bytes.
/// Blocks of 32 samples with fixed-size arrays, which the compiler turns into byte unpacks.
fn unshuffle_u16(planes: &[u8], out: &mut [u16]) {
    const BLOCK: usize = 32;
    let (low, high) = planes.split_at(out.len());
    let blocks = out.len() / BLOCK * BLOCK;
    for ((o, l), h) in out[..blocks]
        .chunks_exact_mut(BLOCK)
        .zip(low[..blocks].chunks_exact(BLOCK))
        .zip(high[..blocks].chunks_exact(BLOCK))
    {
        let o: &mut [u16; BLOCK] = o.try_into().unwrap_or_else(|_| unreachable!());
        let l: &[u8; BLOCK] = l.try_into().unwrap_or_else(|_| unreachable!());
        let h: &[u8; BLOCK] = h.try_into().unwrap_or_else(|_| unreachable!());
        for i in 0..BLOCK {
            o[i] = u16::from(l[i]) | u16::from(h[i]) << 8;
        }
    }
    for ((v, &l), &h) in out[blocks..]
        .iter_mut()
        .zip(&low[blocks..])
        .zip(&high[blocks..])
    {
        *v = u16::from(l) | u16::from(h) << 8;
    }
}

/// Why a stored brick could not be decoded. The store wraps it with the file name.
#[derive(Debug, PartialEq, Eq)]
pub enum BrickDecodeError {
    TooShort,
    ChecksumMismatch { expected: u64, actual: u64 },
    UnknownKind(u8),
    Decompress(String),
    WrongSize { bytes: usize, expected: usize },
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
            BrickDecodeError::Decompress(e) => write!(f, "decompression failed: {e}"),
            BrickDecodeError::WrongSize { bytes, expected } => {
                write!(f, "holds {bytes} bytes, expected {expected}")
            }
        }
    }
}

/// A record of `kind` with `body` and the right checksum, whatever the body holds: lets the
/// malformed-input tests hand the decoders bodies that pass the checksum but lie.
#[cfg(any(test, feature = "test-hooks"))]
pub fn seal_record_for_tests(id: BrickId, kind: u8, body: &[u8]) -> Vec<u8> {
    let mut out = vec![kind];
    out.extend_from_slice(&checksum(kind, &brick_key(id), body).to_le_bytes());
    out.extend_from_slice(body);
    out
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
    let actual = checksum(record[0], &brick_key(id), &record[HEADER_LEN..]);
    if actual != expected {
        return Err(BrickDecodeError::ChecksumMismatch { expected, actual });
    }
    Ok(expected)
}

/// Decodes and verifies a stored brick into its 36³ voxels.
pub fn decode_brick(id: BrickId, record: &[u8]) -> Result<Vec<u16>, BrickDecodeError> {
    decode_brick_with::<zstd_frames::Native>(id, record)
}

/// [`decode_brick`] with zstd frames decoded by the pure-Rust ruzstd whatever the build: what a
/// build without `local` decodes with. For the tests that compare it with C zstd on stores.
#[doc(hidden)]
pub fn decode_brick_pure_rust(id: BrickId, record: &[u8]) -> Result<Vec<u16>, BrickDecodeError> {
    decode_brick_with::<zstd_frames::PureZstd>(id, record)
}

/// [`decode_brick`] with zstd frames decoded by `Z` (C zstd or ruzstd, see [`zstd_frames`]).
fn decode_brick_with<Z: ZstdFrames>(
    id: BrickId,
    record: &[u8],
) -> Result<Vec<u16>, BrickDecodeError> {
    if record.len() < HEADER_LEN {
        return Err(BrickDecodeError::TooShort);
    }
    let kind = record[0];
    let mut sum = [0u8; 8];
    sum.copy_from_slice(&record[1..9]);
    let expected = u64::from_le_bytes(sum);
    let body = &record[HEADER_LEN..];
    let actual = checksum(kind, &brick_key(id), body);
    if actual != expected {
        return Err(BrickDecodeError::ChecksumMismatch { expected, actual });
    }
    match kind {
        KIND_CONSTANT => {
            // Exactly the value: a compressed body under a flipped kind byte is never taken for
            // a constant (format-1 checksums do not cover the kind).
            let [a, b] = body else {
                return Err(BrickDecodeError::WrongSize {
                    bytes: body.len(),
                    expected: 2,
                });
            };
            Ok(vec![u16::from_le_bytes([*a, *b]); BRICK_PAYLOAD_VOXELS])
        }
        KIND_LZ4_U8 => Ok(lz4_exact(body, BRICK_PAYLOAD_VOXELS)?
            .into_iter()
            .map(u16::from)
            .collect()),
        KIND_ZSTD_U8 => Ok(zstd_exact::<Z>(body, BRICK_PAYLOAD_VOXELS)?
            .into_iter()
            .map(u16::from)
            .collect()),
        KIND_DELTA_ZSTD_U8 => with_scratch(BRICK_PAYLOAD_VOXELS, |samples| {
            zstd_exact_into::<Z>(body, samples)?;
            restore_delta(samples);
            Ok(widen(samples))
        }),
        KIND_COLUMN_DELTA_ZSTD_U8 => with_scratch(BRICK_PAYLOAD_VOXELS, |samples| {
            zstd_exact_into::<Z>(body, samples)?;
            restore_column_delta(samples);
            Ok(widen(samples))
        }),
        KIND_MED_ZSTD_U8 => {
            let residuals = zstd_exact::<Z>(body, BRICK_PAYLOAD_VOXELS)?;
            let mut out = vec![0u16; BRICK_PAYLOAD_VOXELS];
            restore_med(&residuals, &mut out);
            Ok(out)
        }
        KIND_LINEAR3D_U8 => linear3d::decompress::<Z>(body),
        KIND_LZ4_U16 => Ok(lz4_exact(body, BRICK_PAYLOAD_VOXELS * 2)?
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect()),
        KIND_SHUFFLE_LZ4_U16 => with_scratch(BRICK_PAYLOAD_VOXELS * 2, |planes| {
            lz4_exact_into(body, planes)?;
            let mut out = vec![0u16; BRICK_PAYLOAD_VOXELS];
            unshuffle_u16(planes, &mut out);
            Ok(out)
        }),
        KIND_SHUFFLE_ZSTD_U16 => {
            let planes = zstd_exact::<Z>(body, BRICK_PAYLOAD_VOXELS * 2)?;
            let mut out = vec![0u16; BRICK_PAYLOAD_VOXELS];
            unshuffle_u16(&planes, &mut out);
            Ok(out)
        }
        other => Err(BrickDecodeError::UnknownKind(other)),
    }
}

/// Decompresses a size-prefixed lz4 block that must hold exactly `expected` bytes. What is
/// allocated is the caller's `expected` (one brick), never the prefix's claim, so a damaged
/// prefix cannot ask for gigabytes.
fn lz4_exact(body: &[u8], expected: usize) -> Result<Vec<u8>, BrickDecodeError> {
    let mut out = vec![0u8; expected];
    lz4_exact_into(body, &mut out)?;
    Ok(out)
}

/// Refuses a size-prefixed lz4 block whose prefix claims other than `expected` bytes.
fn check_lz4_prefix(body: &[u8], expected: usize) -> Result<(), BrickDecodeError> {
    let prefix = body.get(0..4).ok_or(BrickDecodeError::TooShort)?;
    let claimed = u32::from_le_bytes([prefix[0], prefix[1], prefix[2], prefix[3]]) as usize;
    if claimed != expected {
        return Err(BrickDecodeError::WrongSize {
            bytes: claimed,
            expected,
        });
    }
    Ok(())
}

/// Decompresses a size-prefixed lz4 block that must fill `out` exactly.
fn lz4_exact_into(body: &[u8], out: &mut [u8]) -> Result<(), BrickDecodeError> {
    let expected = out.len();
    check_lz4_prefix(body, expected)?;
    let n = lz4_flex::block::decompress_into(&body[4..], out)
        .map_err(|e| BrickDecodeError::Decompress(format!("lz4: {e}")))?;
    if n != expected {
        return Err(BrickDecodeError::WrongSize { bytes: n, expected });
    }
    Ok(())
}

thread_local! {
    /// The u8 residuals or u16 byte planes of the brick being decoded on this thread: the fast
    /// paths allocate only the voxels they return (a second brick-sized allocation per decode
    /// measured as a large share of the time after zstd).
    static SCRATCH: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Runs `f` on this thread's scratch buffer of `len` bytes, at most two bricks' samples (a
/// fresh one if re-entered).
fn with_scratch<T>(len: usize, f: impl FnOnce(&mut [u8]) -> T) -> T {
    SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut buffer) => {
            buffer.resize(len, 0);
            f(&mut buffer)
        }
        Err(_) => f(&mut vec![0u8; len]),
    })
}

/// Decompresses a zstd frame that must fill `out` exactly, with this thread's reused context.
fn zstd_exact_into<Z: ZstdFrames>(body: &[u8], out: &mut [u8]) -> Result<(), BrickDecodeError> {
    let n = Z::decode_into(body, out)?;
    if n != out.len() {
        return Err(BrickDecodeError::WrongSize {
            bytes: n,
            expected: out.len(),
        });
    }
    Ok(())
}

/// Decompresses a zstd frame that must hold exactly `expected` bytes (at most that is allocated),
/// with this thread's reused context.
fn zstd_exact<Z: ZstdFrames>(body: &[u8], expected: usize) -> Result<Vec<u8>, BrickDecodeError> {
    let out = Z::decode_vec(body, expected)?;
    if out.len() != expected {
        return Err(BrickDecodeError::WrongSize {
            bytes: out.len(),
            expected,
        });
    }
    Ok(out)
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

    /// Deterministic noise over the whole u16 range (xorshift), the worst case for every codec.
    fn full_range_brick(bits: u32) -> Vec<u16> {
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut v: Vec<u16> = (0..BRICK_PAYLOAD_VOXELS)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 40) as u16 & ((1u32 << bits) - 1) as u16
            })
            .collect();
        // Both ends of the range are present.
        v[0] = 0;
        v[1] = ((1u32 << bits) - 1) as u16;
        v
    }

    #[test]
    fn every_codec_round_trips_u8_and_u16_constant_and_full_range() {
        let id = BrickId::new(2, [1, 0, 3]);
        let cases: Vec<(&str, Vec<u16>, bool)> = vec![
            ("u16 constant 0", vec![0; BRICK_PAYLOAD_VOXELS], false),
            (
                "u16 constant max",
                vec![u16::MAX; BRICK_PAYLOAD_VOXELS],
                false,
            ),
            ("u16 full range", full_range_brick(16), false),
            ("u16 12-bit", full_range_brick(12), false),
            ("u16 smooth", sample_brick(), false),
            ("u8 constant", vec![200; BRICK_PAYLOAD_VOXELS], true),
            ("u8 constant 0", vec![0; BRICK_PAYLOAD_VOXELS], true),
            ("u8 constant 255", vec![255; BRICK_PAYLOAD_VOXELS], true),
            ("u8 full range", full_range_brick(8), true),
            ("u8 MR-like", mr_like_u8_brick(), true),
        ];
        for codec in BrickCodec::ALL {
            for (name, voxels, narrow) in &cases {
                let rec = encode_brick(id, voxels, value_range(voxels), *narrow, codec);
                assert_eq!(
                    decode_brick(id, &rec).as_ref(),
                    Ok(voxels),
                    "{} {name}",
                    codec.name()
                );
                if value_range(voxels).min == value_range(voxels).max {
                    assert_eq!(rec[0], KIND_CONSTANT, "{} {name}", codec.name());
                }
                assert!(verify_record(id, &rec).is_ok());
            }
        }
    }

    #[test]
    fn each_codec_writes_its_own_kind() {
        let id = BrickId::new(0, [0, 0, 0]);
        let v = sample_brick();
        let r = value_range(&v);
        let kinds: Vec<u8> = BrickCodec::ALL
            .into_iter()
            .map(|c| encode_brick(id, &v, r, false, c)[0])
            .collect();
        assert_eq!(
            kinds,
            [KIND_LZ4_U16, KIND_SHUFFLE_LZ4_U16, KIND_SHUFFLE_ZSTD_U16]
        );
        let n: Vec<u16> = v.iter().map(|x| x % 256).collect();
        let rn = value_range(&n);
        let narrow_kinds: Vec<u8> = BrickCodec::ALL
            .into_iter()
            .map(|c| encode_brick(id, &n, rn, true, c)[0])
            .collect();
        assert_eq!(
            narrow_kinds,
            [KIND_LZ4_U8, KIND_COLUMN_DELTA_ZSTD_U8, KIND_LINEAR3D_U8]
        );
    }

    /// 8-bit MR in miniature: a smooth field (slow gradients in x, y and z) plus a few levels of
    /// noise, clamped to the byte range.
    fn mr_like_u8_brick() -> Vec<u16> {
        let noise = full_range_brick(3);
        (0..BRICK_PAYLOAD_VOXELS)
            .map(|i| {
                let (x, y, z) = (i % EDGE, i / EDGE % EDGE, i / (EDGE * EDGE));
                let smooth = 40 + 3 * x + 2 * y + z;
                (smooth + noise[i] as usize).min(255) as u16
            })
            .collect()
    }

    #[test]
    fn prediction_filters_invert_exactly_on_every_byte_pattern() {
        // Wrapping residuals: the extremes next to each other (0 beside 255, in x, y and z), the
        // slice and row starts, and noise over the whole byte range.
        let mut cases: Vec<Vec<u8>> = vec![
            full_range_brick(8).iter().map(|&v| v as u8).collect(),
            (0..BRICK_PAYLOAD_VOXELS)
                .map(|i| {
                    if (i + i / EDGE + i / (EDGE * EDGE)).is_multiple_of(2) {
                        0
                    } else {
                        255
                    }
                })
                .collect(),
            vec![255; BRICK_PAYLOAD_VOXELS],
        ];
        cases.push(mr_like_u8_brick().iter().map(|&v| v as u8).collect());
        for (n, v) in cases.iter().enumerate() {
            let mut out = delta_residuals(v);
            restore_delta(&mut out);
            assert_eq!(&out, v, "delta case {n}");
            // The column delta at every length: whole bricks, and the short rows and partial
            // slices the import limit's chunks end in.
            for len in [v.len(), 1, EDGE - 1, EDGE + 7, EDGE * EDGE, EDGE * EDGE + 3] {
                let mut out = column_delta_residuals(&v[..len]);
                restore_column_delta(&mut out);
                assert_eq!(&out[..], &v[..len], "column delta case {n}, length {len}");
            }
            let mut out = vec![0u16; v.len()];
            restore_med(&med_residuals(v), &mut out);
            assert!(
                out.iter().zip(v).all(|(&o, &x)| o == u16::from(x)),
                "med case {n}"
            );
            let body = linear3d::compress(v).unwrap();
            let out = linear3d::decompress::<zstd_frames::Native>(&body).unwrap();
            assert!(
                out.iter().zip(v).all(|(&o, &x)| o == u16::from(x)),
                "linear3d case {n}"
            );
        }
        // The MED predictor picks min, max or the plane as LOCO-I does.
        assert_eq!(med_prediction(10, 20, 25), 10);
        assert_eq!(med_prediction(10, 20, 5), 20);
        assert_eq!(med_prediction(10, 20, 12), 18);
        assert_eq!(med_prediction(255, 0, 128), 127);
    }

    #[test]
    fn predicted_kinds_make_8_bit_mr_smaller_than_lz4() {
        let id = BrickId::new(0, [0, 0, 0]);
        let v = mr_like_u8_brick();
        let r = value_range(&v);
        let size = |c| encode_brick(id, &v, r, true, c).len();
        let (lz4, fast, dense) = (
            size(BrickCodec::Lz4),
            size(BrickCodec::Fast),
            size(BrickCodec::Dense),
        );
        assert!(fast < lz4, "fast {fast} vs lz4 {lz4}");
        assert!(dense < lz4, "dense {dense} vs lz4 {lz4}");
    }

    #[test]
    fn narrow_bricks_of_every_codec_catch_every_flipped_bit() {
        let id = BrickId::new(1, [0, 2, 1]);
        for v in [mr_like_u8_brick(), full_range_brick(8)] {
            for codec in BrickCodec::ALL {
                let rec = encode_brick(id, &v, value_range(&v), true, codec);
                assert_eq!(decode_brick(id, &rec).as_ref(), Ok(&v), "{}", codec.name());
                for pos in [0usize, 1, 8, 9, 10, rec.len() / 2, rec.len() - 1] {
                    for bit in [0x01, 0x08, 0x80] {
                        let mut bad = rec.clone();
                        bad[pos] ^= bit;
                        assert!(
                            decode_brick(id, &bad).is_err(),
                            "{}: flip of bit {bit:#x} at {pos} not detected",
                            codec.name()
                        );
                    }
                }
            }
        }
    }

    /// Records of the kinds this build no longer writes for u8 (format 1's lz4, issue 17's plain
    /// zstd) keep decoding: stores written before keep opening.
    #[test]
    fn superseded_u8_kinds_still_decode() {
        let id = BrickId::new(0, [3, 1, 2]);
        let v = mr_like_u8_brick();
        let bytes: Vec<u8> = v.iter().map(|&x| x as u8).collect();
        let lz4 = seal_record_for_tests(
            id,
            KIND_LZ4_U8,
            &lz4_flex::block::compress_prepend_size(&bytes),
        );
        let zstd =
            seal_record_for_tests(id, KIND_ZSTD_U8, &zstd::bulk::compress(&bytes, 1).unwrap());
        // Kind 7, what `dense` wrote for u8 before kind 8.
        let med = seal_record_for_tests(
            id,
            KIND_MED_ZSTD_U8,
            &zstd::bulk::compress(&med_residuals(&bytes), 1).unwrap(),
        );
        // Kind 6, what `fast` wrote for u8 before kind 9.
        let delta = seal_record_for_tests(
            id,
            KIND_DELTA_ZSTD_U8,
            &zstd::bulk::compress(&delta_residuals(&bytes), 1).unwrap(),
        );
        assert_eq!(decode_brick(id, &lz4), Ok(v.clone()));
        assert_eq!(decode_brick(id, &zstd), Ok(v.clone()));
        assert_eq!(decode_brick(id, &med), Ok(v.clone()));
        assert_eq!(decode_brick(id, &delta), Ok(v));
    }

    /// The column delta's residuals of a field that changes along y only by a constant step
    /// are that step everywhere off the first row and the slice starts: the predictor is the
    /// sample above, not the one to the left.
    #[test]
    fn the_column_delta_predicts_from_the_sample_above() {
        let v: Vec<u8> = (0..BRICK_PAYLOAD_VOXELS)
            .map(|i| (i / EDGE % EDGE * 3 + i % EDGE * 7) as u8)
            .collect();
        let r = column_delta_residuals(&v);
        for (i, &residual) in r.iter().enumerate().skip(EDGE) {
            if i % (EDGE * EDGE) >= EDGE {
                assert_eq!(residual, 3, "sample {i}");
            } else {
                // A slice's first row: the same place one slice before holds the same value.
                assert_eq!(residual, 0, "sample {i}");
            }
        }
        assert_eq!(r[1], 7);
    }

    #[test]
    fn only_u8_stores_of_format_2_require_the_predicted_feature() {
        assert_eq!(
            BrickCodec::Fast.required_features(true),
            vec![
                PREDICTED_U8_FEATURE.to_string(),
                COLUMN_DELTA_U8_FEATURE.to_string()
            ]
        );
        assert_eq!(
            BrickCodec::Dense.required_features(true),
            vec![
                PREDICTED_U8_FEATURE.to_string(),
                LINEAR3D_U8_FEATURE.to_string()
            ]
        );
        assert!(BrickCodec::Dense.required_features(false).is_empty());
        assert!(BrickCodec::Fast.required_features(false).is_empty());
        assert!(BrickCodec::Lz4.required_features(true).is_empty());
    }

    #[test]
    fn shuffle_makes_12_bit_samples_smaller() {
        // Noisy MR: a smooth 12-bit signal plus 6 bits of noise. The high bytes change slowly,
        // so shuffled into their own plane they form runs that lz4 finds; interleaved with the
        // noisy low bytes they do not.
        let id = BrickId::new(0, [0, 0, 0]);
        let noise = full_range_brick(6);
        let v: Vec<u16> = noise
            .iter()
            .enumerate()
            .map(|(i, n)| 1000 + (i / 1296) as u16 * 40 + n)
            .collect();
        let r = value_range(&v);
        let size = |c| encode_brick(id, &v, r, false, c).len();
        assert!(size(BrickCodec::Fast) < size(BrickCodec::Lz4));
        assert!(size(BrickCodec::Dense) < size(BrickCodec::Fast));
    }

    #[test]
    fn compress_samples_matches_the_brick_body() {
        let id = BrickId::new(0, [0, 0, 0]);
        let v = sample_brick();
        for codec in BrickCodec::ALL {
            let rec = encode_brick(id, &v, value_range(&v), false, codec);
            let body = compress_samples(bytemuck::cast_slice(&v), false, codec);
            assert_eq!(&rec[HEADER_LEN..], &body[..], "{}", codec.name());
            let n: Vec<u16> = v.iter().map(|x| x % 256).collect();
            let rec = encode_brick(id, &n, value_range(&n), true, codec);
            let bytes: Vec<u8> = n.iter().map(|&x| x as u8).collect();
            let body = compress_samples(&bytes, true, codec);
            assert_eq!(&rec[HEADER_LEN..], &body[..], "{} u8", codec.name());
        }
    }

    #[test]
    fn round_trip_and_checksum() {
        for codec in BrickCodec::ALL {
            let id = BrickId::new(1, [2, 3, 4]);
            let v = sample_brick();
            let rec = encode_brick(id, &v, value_range(&v), false, codec);
            assert_eq!(decode_brick(id, &rec).unwrap(), v);
            // Any flipped bit in the record is caught, the kind byte's included.
            for pos in [0usize, 3, 9, 12, rec.len() / 2, rec.len() - 1] {
                for bit in [0x01, 0x02, 0x04, 0x10, 0x80] {
                    let mut bad = rec.clone();
                    bad[pos] ^= bit;
                    assert!(
                        decode_brick(id, &bad).is_err(),
                        "{}: flip of bit {bit:#x} at {pos} not detected",
                        codec.name()
                    );
                }
            }
            // The same record under another key is caught too.
            assert!(matches!(
                decode_brick(BrickId::new(1, [2, 3, 5]), &rec),
                Err(BrickDecodeError::ChecksumMismatch { .. })
            ));
        }
    }

    /// A record whose checksum is right but whose body lies (a bug in another writer, or a
    /// crafted file): decoding fails with a message, never allocates what a prefix claims.
    #[test]
    fn lying_bodies_fail_cleanly() {
        lying_bodies_fail_cleanly_with::<zstd_frames::CZstd>();
    }

    /// ruzstd (the decoder without `local`) refuses the same lies as C zstd, without panicking.
    #[test]
    fn lying_bodies_fail_cleanly_through_ruzstd() {
        lying_bodies_fail_cleanly_with::<zstd_frames::PureZstd>();
    }

    fn lying_bodies_fail_cleanly_with<Z: ZstdFrames>() {
        let id = BrickId::new(0, [1, 1, 1]);
        let reseal = |kind: u8, body: &[u8]| {
            let mut out = vec![kind];
            out.extend_from_slice(&checksum(kind, &brick_key(id), body).to_le_bytes());
            out.extend_from_slice(body);
            out
        };
        // An lz4 prefix claiming 4 GiB.
        let mut huge = u32::MAX.to_le_bytes().to_vec();
        huge.extend_from_slice(&[0u8; 16]);
        for kind in [KIND_LZ4_U16, KIND_SHUFFLE_LZ4_U16, KIND_LZ4_U8] {
            assert!(matches!(
                decode_brick_with::<Z>(id, &reseal(kind, &huge)),
                Err(BrickDecodeError::WrongSize { .. })
            ));
        }
        // A zstd frame of the wrong size, and garbage where a frame should be.
        let small = zstd::bulk::compress(&[1u8; 100], 1).unwrap();
        for kind in [
            KIND_SHUFFLE_ZSTD_U16,
            KIND_ZSTD_U8,
            KIND_DELTA_ZSTD_U8,
            KIND_MED_ZSTD_U8,
            KIND_COLUMN_DELTA_ZSTD_U8,
        ] {
            assert!(decode_brick_with::<Z>(id, &reseal(kind, &small)).is_err());
            assert!(matches!(
                decode_brick_with::<Z>(id, &reseal(kind, &[0xAB; 40])),
                Err(BrickDecodeError::Decompress(_))
            ));
        }
        // Kind 8: a frame-length table cut short, lengths past the body, a frame in a stream
        // that claims more than a brick (at most one brick is ever decompressed), streams whose
        // totals are right but whose contexts do not match the samples they decode, and
        // leftover bytes after the frames.
        let v: Vec<u8> = mr_like_u8_brick().iter().map(|&x| x as u8).collect();
        let good = linear3d::compress(&v).unwrap();
        assert!(linear3d::decompress::<Z>(&good).is_ok());
        assert_eq!(
            decode_brick_with::<Z>(id, &reseal(KIND_LINEAR3D_U8, &good[..10])),
            Err(BrickDecodeError::TooShort)
        );
        let mut past = good.clone();
        let w = linear3d::WEIGHTS;
        past[w..w + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(
            decode_brick_with::<Z>(id, &reseal(KIND_LINEAR3D_U8, &past)),
            Err(BrickDecodeError::TooShort)
        );
        let big = zstd::bulk::compress(&vec![0u8; 4 * BRICK_PAYLOAD_VOXELS], 1).unwrap();
        // Weights of zero: every interior prediction is 0.
        let mut oversized = vec![0u8; w];
        oversized.extend_from_slice(&(big.len() as u32).to_le_bytes());
        oversized.extend_from_slice(&[0u8; 4 * (linear3d::CONTEXTS - 1)]);
        oversized.extend_from_slice(&big);
        assert!(matches!(
            decode_brick_with::<Z>(id, &reseal(KIND_LINEAR3D_U8, &oversized)),
            Err(BrickDecodeError::Decompress(_))
        ));
        // All residuals in stream 0: the right total, but the noisy brick needs other streams.
        let all = zstd::bulk::compress(&vec![0u8; BRICK_PAYLOAD_VOXELS], 1).unwrap();
        let mut one_stream = vec![0u8; w];
        one_stream.extend_from_slice(&(all.len() as u32).to_le_bytes());
        one_stream.extend_from_slice(&[0u8; 4 * (linear3d::CONTEXTS - 1)]);
        one_stream.extend_from_slice(&all);
        // Zero residuals decode a constant brick: stream 0 alone is consistent, so this one
        // decodes; the same total spread over the last stream runs stream 0 dry.
        assert_eq!(
            decode_brick_with::<Z>(id, &reseal(KIND_LINEAR3D_U8, &one_stream)),
            Ok(vec![0; BRICK_PAYLOAD_VOXELS])
        );
        let mut last_stream = vec![0u8; w + 4 * (linear3d::CONTEXTS - 1)];
        last_stream.extend_from_slice(&(all.len() as u32).to_le_bytes());
        last_stream.extend_from_slice(&all);
        assert!(matches!(
            decode_brick_with::<Z>(id, &reseal(KIND_LINEAR3D_U8, &last_stream)),
            Err(BrickDecodeError::Decompress(_))
        ));
        let mut trailing = good.clone();
        trailing.push(0);
        assert!(matches!(
            decode_brick_with::<Z>(id, &reseal(KIND_LINEAR3D_U8, &trailing)),
            Err(BrickDecodeError::WrongSize { .. })
        ));
        assert!(matches!(
            decode_brick_with::<Z>(id, &reseal(KIND_LINEAR3D_U8, &[0xAB; 40])),
            Err(BrickDecodeError::TooShort | BrickDecodeError::Decompress(_))
        ));
        // An unknown kind is named.
        assert_eq!(
            decode_brick_with::<Z>(id, &reseal(99, &[0; 8])),
            Err(BrickDecodeError::UnknownKind(99))
        );
    }

    #[test]
    fn codec_names_parse() {
        for codec in BrickCodec::ALL {
            assert_eq!(BrickCodec::parse(codec.name()), Some(codec));
        }
        assert_eq!(BrickCodec::parse("DENSE"), Some(BrickCodec::Dense));
        assert_eq!(BrickCodec::parse("gzip"), None);
    }

    #[test]
    fn constant_and_narrow_bricks() {
        let id = BrickId::new(0, [0, 0, 0]);
        let c = vec![77u16; BRICK_PAYLOAD_VOXELS];
        let rec = encode_brick(id, &c, value_range(&c), false, BrickCodec::Fast);
        assert!(
            rec.len() < 16,
            "constant brick stored as marker, got {} bytes",
            rec.len()
        );
        assert_eq!(decode_brick(id, &rec).unwrap(), c);
        let n: Vec<u16> = (0..BRICK_PAYLOAD_VOXELS)
            .map(|i| (i % 251) as u16)
            .collect();
        let rec = encode_brick(id, &n, value_range(&n), true, BrickCodec::Fast);
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

    /// The records the crate writes (every codec, u8 and u16, constant, the legacy zstd kinds 5-7
    /// that older stores hold) decode to the same voxels through ruzstd as through C zstd, and
    /// to what was encoded: what a browser viewer (ruzstd) shows is what the desktop shows.
    #[test]
    fn ruzstd_decodes_every_record_as_c_zstd_does() {
        use zstd_frames::{CZstd, PureZstd};
        let id = BrickId::new(1, [2, 3, 4]);
        let mut records: Vec<(String, Vec<u16>, Vec<u8>)> = Vec::new();
        let bricks: [(&str, Vec<u16>, bool); 6] = [
            ("u16 smooth", sample_brick(), false),
            ("u16 noise", full_range_brick(16), false),
            ("u16 12-bit", full_range_brick(12), false),
            ("u8 mr-like", mr_like_u8_brick(), true),
            ("u8 noise", full_range_brick(8), true),
            ("constant", vec![77; BRICK_PAYLOAD_VOXELS], true),
        ];
        for codec in BrickCodec::ALL {
            for (name, voxels, narrow) in &bricks {
                let record = encode_brick(id, voxels, value_range(voxels), *narrow, codec);
                records.push((format!("{} {name}", codec.name()), voxels.clone(), record));
            }
        }
        let bytes: Vec<u8> = mr_like_u8_brick().iter().map(|&v| v as u8).collect();
        let zstd1 = |b: &[u8]| zstd::bulk::compress(b, 1).unwrap();
        for (kind, body) in [
            (KIND_ZSTD_U8, zstd1(&bytes)),
            (KIND_DELTA_ZSTD_U8, zstd1(&delta_residuals(&bytes))),
            (KIND_MED_ZSTD_U8, zstd1(&med_residuals(&bytes))),
        ] {
            let record = seal_record_for_tests(id, kind, &body);
            records.push((format!("legacy kind {kind}"), widen(&bytes), record));
        }
        let mut kinds: Vec<u8> = records.iter().map(|(_, _, r)| r[0]).collect();
        kinds.sort_unstable();
        kinds.dedup();
        assert_eq!(kinds, (0..=9).collect::<Vec<u8>>(), "every kind is covered");
        for (name, voxels, record) in &records {
            let c = decode_brick_with::<CZstd>(id, record);
            let pure = decode_brick_with::<PureZstd>(id, record);
            assert_eq!(c.as_ref(), Ok(voxels), "C zstd, {name}");
            assert_eq!(pure, c, "ruzstd, {name}");
        }
        // Damage reads as an error through both, never as other voxels or a panic: a zstd
        // frame cut short and one that holds more than a brick (the checksum is resealed, so
        // the decoders see the bodies).
        let planes = zstd1(&vec![1u8; BRICK_PAYLOAD_VOXELS * 2]);
        let too_big = zstd1(&vec![1u8; BRICK_PAYLOAD_VOXELS * 3]);
        for body in [&planes[..planes.len() / 2], &too_big[..], &[][..]] {
            let record = seal_record_for_tests(id, KIND_SHUFFLE_ZSTD_U16, body);
            assert!(decode_brick_with::<CZstd>(id, &record).is_err());
            assert!(decode_brick_with::<PureZstd>(id, &record).is_err());
        }
    }
}
