//! Kind 8, `dense` on u8: a 3-D linear predictor whose residuals are split by local activity into
//! streams, each its own zstd frame (so each gets its own Huffman table).
//!
//! Why: on 8-bit MR the median-edge filter of kind 7 plus one zstd frame stores 0.70-0.72 of
//! lz4. Two things were left: the slice below (a 2-D predictor ignores it; averaging more causal
//! neighbours cancels more noise), and one Huffman table for flat background and busy edges
//! alike. Prototyped on level-0 bricks of chris_t1 and FLAIR (stored bytes vs kind 7):
//!
//! | change                                                   | chris_t1 | FLAIR |
//! |----------------------------------------------------------|----------|-------|
//! | xz (LZMA, lc=4) / brotli 11 on the MED residuals         | 0.97 / 0.95 | 0.98 / 0.97 |
//! | MED, ideal adaptive order-0 coder (no matches)           | 1.07     | 1.12  |
//! | MED, 6 gradient contexts, ideal adaptive coder           | 0.97     | 0.98  |
//! | MED, 6 gradient contexts, one zstd frame per context     | 0.97     | 0.98  |
//! | 3-D predictor (below), one zstd frame                    | 0.96     | 0.98  |
//! | 3-D predictor, 6 gradient contexts, a frame per context  | 0.94     | 0.96  |
//! | the same, weights fitted per brick (7 bytes a brick)     | **0.91** | **0.955** |
//!
//! (The last row is of whole stores, every level, as `strata-bench codecs` measures: 0.644 and
//! 0.688 of lz4 against kind 7's 0.707 and 0.720. zstd 19 on the streams was 1 % smaller, at
//! a fraction of the speed.)
//!
//! An arithmetic coder over the same contexts gained nothing over per-context Huffman (the
//! residuals of noisy MR are close to their order-0 entropy within a context) and zstd keeps
//! the long zero runs of the background as matches, which an order-0 coder cannot.
//!
//! The predictor: within a slice's first row and first column, and in a brick's first slice, the
//! rules of kind 7 (x neighbour, y neighbour, median edge detector); elsewhere
//! a weighted sum (in sixty-fourths) of the left `a`, upper `b`, upper-left `c` and upper-right
//! `d` samples and the slice below's `z` (same x, y), `za` (left of it) and `zb` (above it). The
//! weights are each brick's own least-squares fit, rounded to sixty-fourths that sum to 64 (a
//! flat region predicts itself) and stored in the body; where the fit fails, the fit on
//! chris_t1 and FLAIR together, `(35a + 34b - 14c + 4d + 34z - 13za - 16zb) / 64`.
//!
//! Body: the brick's seven weights (i8, sixty-fourths), six little-endian u32 frame lengths (0:
//! an empty stream, no frame), then the frames.
//! The decoder reads at most one brick of residuals whatever the frames claim, and a stream that
//! runs out or has residuals left over is an error.

use super::zstd_frames::ZstdFrames;
use super::{
    med_prediction, row_start_prediction, zstd_compress_level, BrickDecodeError, EDGE,
    PREDICTED_ZSTD_LEVEL,
};

/// Number of activity contexts (streams).
pub(super) const CONTEXTS: usize = 6;
/// Upper bounds (inclusive) of the activity `|a-c| + |b-c| + |d-b|` of contexts 0..5; above the
/// last is context 5. Samples without an upper-left neighbour use context 0. Six contexts with
/// these bounds measured best; 4, 8 and 12 were within 0.5 %.
const ACTIVITY_BOUNDS: [u32; CONTEXTS - 1] = [1, 3, 7, 15, 31];
const SLICE: usize = EDGE * EDGE;
/// Bytes of the weights at the start of a body (seven i8).
pub(super) const WEIGHTS: usize = 7;

/// The context of an activity value (the definition [`CONTEXT_OF`] tabulates).
#[cfg(test)]
fn context_of(activity: u32) -> usize {
    ACTIVITY_BOUNDS.iter().filter(|&&b| activity > b).count()
}

/// [`context_of`] for every activity a sample can have (three byte differences: at most 765), so
/// the serial part of the decoder is one load.
const CONTEXT_OF: [u8; 766] = {
    let mut table = [0u8; 766];
    let mut activity = 0;
    while activity < table.len() {
        let mut k = 0;
        while k < ACTIVITY_BOUNDS.len() && activity as u32 > ACTIVITY_BOUNDS[k] {
            k += 1;
        }
        table[activity] = k as u8;
        activity += 1;
    }
    table
};

/// Prediction and context of an interior sample (x ≥ 1, y ≥ 1) of slice `z` at index `i` in
/// `v`, from the samples before it: the definition the row-wise passes below must equal.
#[cfg(test)]
fn interior(v: &[u8], i: usize, x: usize, z: usize, w: &Weights) -> (u8, usize) {
    let a = v[i - 1];
    let b = v[i - EDGE];
    let c = v[i - EDGE - 1];
    let d = if x + 1 < EDGE { v[i - EDGE + 1] } else { b };
    let activity = u32::from(a.abs_diff(c)) + u32::from(b.abs_diff(c)) + u32::from(d.abs_diff(b));
    let prediction = if z == 0 {
        med_prediction(a, b, c)
    } else {
        let (zc, za, zb) = (v[i - SLICE], v[i - SLICE - 1], v[i - SLICE - EDGE]);
        let n = [a, b, c, d, zc, za, zb];
        let sum: i32 = n
            .iter()
            .zip(&w.0)
            .map(|(&n, &w)| i32::from(w) * i32::from(n))
            .sum();
        ((sum + 32) >> 6).clamp(0, 255) as u8
    };
    (prediction, context_of(activity))
}

/// The predictor's weights in sixty-fourths, for the neighbours `a, b, c, d, z, za, zb`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Weights([i8; 7]);

impl Weights {
    /// The least-squares fit on chris_t1 and FLAIR: what a brick uses when its own fit fails.
    const DEFAULT: Weights = Weights([35, 34, -14, 4, 34, -13, -16]);

    /// The least-squares weights of this brick's own interior samples (slices z ≥ 1), rounded to
    /// sixty-fourths summing to 64 (a flat region predicts itself). Fitted per brick, they
    /// measured 2.7 % smaller than [`Weights::DEFAULT`] on chris_t1 and 0.7 % on FLAIR, for 7
    /// bytes a brick. The default when the system is singular (flat bricks) or a weight leaves
    /// the i8 range.
    // Matrix code reads as the formulas with row and column indices.
    #[allow(clippy::needless_range_loop)]
    fn fit(v: &[u8]) -> Weights {
        let mut a = [[0f64; 7]; 7];
        let mut rhs = [0f64; 7];
        for z in 1..EDGE {
            for y in 1..EDGE {
                let row = z * SLICE + y * EDGE;
                for x in 1..EDGE {
                    let i = row + x;
                    let b = v[i - EDGE];
                    let d = if x + 1 < EDGE { v[i - EDGE + 1] } else { b };
                    let n = [
                        v[i - 1],
                        b,
                        v[i - EDGE - 1],
                        d,
                        v[i - SLICE],
                        v[i - SLICE - 1],
                        v[i - SLICE - EDGE],
                    ]
                    .map(f64::from);
                    let t = f64::from(v[i]);
                    for r in 0..7 {
                        rhs[r] += n[r] * t;
                        for c in r..7 {
                            a[r][c] += n[r] * n[c];
                        }
                    }
                }
            }
        }
        for r in 0..7 {
            for c in 0..r {
                a[r][c] = a[c][r];
            }
        }
        solve(a, rhs)
            .and_then(Weights::quantised)
            .unwrap_or(Weights::DEFAULT)
    }

    /// Weights in sixty-fourths summing to exactly 64 (the rounding remainder goes to `a`).
    fn quantised(w: [f64; 7]) -> Option<Weights> {
        let mut q = w.map(|w| (w * 64.0).round());
        q[0] += 64.0 - q.iter().sum::<f64>();
        let fits = q.iter().all(|q| (-128.0..=127.0).contains(q));
        fits.then(|| Weights(q.map(|q| q as i8)))
    }
}

/// Solves the 7×7 system `a · w = rhs` by Gaussian elimination with partial pivoting; None when
/// it is (nearly) singular.
// Matrix code reads as the formulas with row and column indices.
#[allow(clippy::needless_range_loop)]
fn solve(mut a: [[f64; 7]; 7], mut rhs: [f64; 7]) -> Option<[f64; 7]> {
    let scale = a
        .iter()
        .map(|r| r.iter().fold(0f64, |m, v| m.max(v.abs())))
        .fold(0f64, f64::max);
    for col in 0..7 {
        let pivot = (col..7).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        let p = a[pivot][col].abs();
        if p.is_nan() || p <= scale * 1e-9 {
            return None;
        }
        a.swap(col, pivot);
        rhs.swap(col, pivot);
        for r in col + 1..7 {
            let f = a[r][col] / a[col][col];
            for c in col..7 {
                a[r][c] -= f * a[col][c];
            }
            rhs[r] -= f * rhs[col];
        }
    }
    let mut w = [0f64; 7];
    for r in (0..7).rev() {
        let s: f64 = (r + 1..7).map(|c| a[r][c] * w[c]).sum();
        w[r] = (rhs[r] - s) / a[r][r];
    }
    w.iter().all(|w| w.is_finite()).then_some(w)
}

/// What a row's interior samples (x ≥ 1) take from the rows before it, computed for the whole row
/// at once (vectorisable): the left neighbour `a` is all that stays serial.
struct RowParts {
    /// The upper-left neighbour `c` (for `|a - c|`).
    c: [u8; EDGE],
    /// The upper row's part of the activity, `|b - c| + |d - b|`.
    activity: [u16; EDGE],
    /// The prediction's sum without `35a`, rounding included (slices z ≥ 1), or the upper
    /// neighbour `b` (slice 0, for the median edge detector).
    rest: [i32; EDGE],
}

impl RowParts {
    /// The parts of row `row` (index of its first sample, y ≥ 1) in slice `z`.
    #[inline(always)]
    fn of(v: &[u8], row: usize, z: usize, w: &Weights) -> RowParts {
        let mut p = RowParts {
            c: [0; EDGE],
            activity: [0; EDGE],
            rest: [0; EDGE],
        };
        let up = &v[row - EDGE..row];
        for x in 1..EDGE {
            let (b, c) = (up[x], up[x - 1]);
            let d = if x + 1 < EDGE { up[x + 1] } else { b };
            p.c[x] = c;
            p.activity[x] = u16::from(b.abs_diff(c)) + u16::from(d.abs_diff(b));
            p.rest[x] = i32::from(b);
        }
        if z > 0 {
            let below = &v[row - SLICE..row - SLICE + EDGE];
            let below_up = &v[row - SLICE - EDGE..row - SLICE];
            for x in 1..EDGE {
                let (b, c) = (up[x], up[x - 1]);
                let d = if x + 1 < EDGE { up[x + 1] } else { b };
                let n = [b, c, d, below[x], below[x - 1], below_up[x]];
                p.rest[x] = n
                    .iter()
                    .zip(&w.0[1..])
                    .map(|(&n, &w)| i32::from(w) * i32::from(n))
                    .sum::<i32>()
                    + 32;
            }
        }
        p
    }

    /// Prediction and context of sample `x` of the row, given its left neighbour `a`.
    #[inline(always)]
    fn predict(&self, x: usize, a: u8, z: usize, w: &Weights) -> (u8, usize) {
        let c = self.c[x];
        let context = CONTEXT_OF[usize::from(a.abs_diff(c)) + usize::from(self.activity[x])];
        let prediction = if z == 0 {
            med_prediction(a, self.rest[x] as u8, c)
        } else {
            ((i32::from(w.0[0]) * i32::from(a) + self.rest[x]) >> 6).clamp(0, 255) as u8
        };
        (prediction, usize::from(context))
    }
}

/// Prediction of an edge sample (first row or first column of a slice), context 0.
#[inline(always)]
fn edge(v: &[u8], i: usize, x: usize, y: usize) -> u8 {
    if y == 0 {
        if x == 0 {
            row_start_prediction(v, i)
        } else {
            v[i - 1]
        }
    } else {
        v[i - EDGE]
    }
}

/// The residual streams of a brick's u8 samples (x fastest, rows of [`EDGE`]).
fn residual_streams(v: &[u8], w: &Weights) -> [Vec<u8>; CONTEXTS] {
    let mut streams: [Vec<u8>; CONTEXTS] = Default::default();
    for z in 0..EDGE {
        for y in 0..EDGE {
            let row = z * SLICE + y * EDGE;
            streams[0].push(v[row].wrapping_sub(edge(v, row, 0, y)));
            if y == 0 {
                for i in row + 1..row + EDGE {
                    streams[0].push(v[i].wrapping_sub(v[i - 1]));
                }
            } else {
                let parts = RowParts::of(v, row, z, w);
                for x in 1..EDGE {
                    let (prediction, context) = parts.predict(x, v[row + x - 1], z, w);
                    streams[context].push(v[row + x].wrapping_sub(prediction));
                }
            }
        }
    }
    streams
}

/// The kind-8 body of u8 samples; None when zstd cannot allocate its context.
pub(super) fn compress(v: &[u8]) -> Option<Vec<u8>> {
    let weights = Weights::fit(v);
    let streams = residual_streams(v, &weights);
    let mut header = Vec::with_capacity(WEIGHTS + 4 * CONTEXTS);
    header.extend(weights.0.map(|w| w as u8));
    let mut frames = Vec::new();
    for stream in &streams {
        if stream.is_empty() {
            header.extend_from_slice(&0u32.to_le_bytes());
            continue;
        }
        let frame = zstd_compress_level(stream, PREDICTED_ZSTD_LEVEL)?;
        header.extend_from_slice(&(frame.len() as u32).to_le_bytes());
        frames.extend_from_slice(&frame);
    }
    header.extend_from_slice(&frames);
    Some(header)
}

/// Inverse of [`compress`]: the brick's samples, widened to u16.
pub(super) fn decompress<Z: ZstdFrames>(body: &[u8]) -> Result<Vec<u16>, BrickDecodeError> {
    let total = EDGE * SLICE;
    let head = body
        .get(..WEIGHTS + 4 * CONTEXTS)
        .ok_or(BrickDecodeError::TooShort)?;
    // Any weights decode (the prediction is clamped to a byte): nothing to validate.
    let weights = Weights(std::array::from_fn(|k| head[k] as i8));
    let lengths = &head[WEIGHTS..];
    let mut residuals = vec![0u8; total];
    // Where each stream starts in `residuals`, and its end.
    let mut cursor = [0usize; CONTEXTS];
    let mut end = [0usize; CONTEXTS];
    let (mut at, mut used) = (WEIGHTS + 4 * CONTEXTS, 0usize);
    for (k, length) in lengths.chunks_exact(4).enumerate() {
        let length = u32::from_le_bytes([length[0], length[1], length[2], length[3]]) as usize;
        let frame = at
            .checked_add(length)
            .and_then(|stop| body.get(at..stop))
            .ok_or(BrickDecodeError::TooShort)?;
        at += length;
        cursor[k] = used;
        if length > 0 {
            used += Z::decode_into(frame, &mut residuals[used..])?;
        }
        end[k] = used;
    }
    if at != body.len() || used != total {
        return Err(BrickDecodeError::WrongSize {
            bytes: used,
            expected: total,
        });
    }
    let mut v = vec![0u8; total];
    let mut next = |context: usize| -> Result<u8, BrickDecodeError> {
        let c = cursor[context];
        if c >= end[context] {
            return Err(BrickDecodeError::Decompress(format!(
                "residual stream {context} ran out"
            )));
        }
        cursor[context] = c + 1;
        Ok(residuals[c])
    };
    for z in 0..EDGE {
        for y in 0..EDGE {
            let row = z * SLICE + y * EDGE;
            let first = edge(&v, row, 0, y).wrapping_add(next(0)?);
            v[row] = first;
            if y == 0 {
                for i in row + 1..row + EDGE {
                    v[i] = v[i - 1].wrapping_add(next(0)?);
                }
            } else {
                let parts = RowParts::of(&v, row, z, &weights);
                let mut left = first;
                for (x, out) in v[row + 1..row + EDGE].iter_mut().enumerate() {
                    let (prediction, context) = parts.predict(x + 1, left, z, &weights);
                    left = prediction.wrapping_add(next(context)?);
                    *out = left;
                }
            }
        }
    }
    // Every stream is used up exactly (the totals matched, so none ran over either).
    Ok(v.into_iter().map(u16::from).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn contexts_follow_the_activity_bounds() {
        assert_eq!(context_of(0), 0);
        assert_eq!(context_of(1), 0);
        assert_eq!(context_of(2), 1);
        assert_eq!(context_of(31), 4);
        assert_eq!(context_of(32), 5);
        assert_eq!(context_of(765), 5);
    }

    #[test]
    fn a_flat_neighbourhood_predicts_itself() {
        // Weights sum to 64: every neighbour equal gives that value back, at both ends of the
        // byte range (no overflow of the clamp).
        for value in [0u8, 1, 128, 254, 255] {
            let v = vec![value; 2 * SLICE + 2 * EDGE + 2];
            let i = SLICE + EDGE + 1;
            assert_eq!(interior(&v, i, 1, 1, &Weights::DEFAULT), (value, 0));
            assert_eq!(
                interior(&v, i, 1, 1, &Weights([64, 10, -10, 3, -3, 0, 0])),
                (value, 0)
            );
        }
    }

    #[test]
    fn the_row_wise_passes_equal_the_per_sample_definition() {
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        let mut v: Vec<u8> = (0..EDGE * SLICE)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 56) as u8
            })
            .collect();
        // Extremes side by side, where the clamp and the wrapping matter.
        for (i, s) in v.iter_mut().enumerate().step_by(3) {
            *s = if i % 2 == 0 { 0 } else { 255 };
        }
        // Any weights a body holds decode, the extremes included.
        let extreme = Weights([127, -128, 127, -128, 127, -128, 127]);
        for w in [Weights::DEFAULT, Weights::fit(&v), extreme] {
            for z in [0, 1, EDGE - 1] {
                for y in [1, 2, EDGE - 1] {
                    let row = z * SLICE + y * EDGE;
                    let parts = RowParts::of(&v, row, z, &w);
                    for x in 1..EDGE {
                        assert_eq!(
                            parts.predict(x, v[row + x - 1], z, &w),
                            interior(&v, row + x, x, z, &w),
                            "{w:?} z {z} y {y} x {x}"
                        );
                    }
                }
            }
        }
        for (activity, &context) in CONTEXT_OF.iter().enumerate() {
            assert_eq!(usize::from(context), context_of(activity as u32));
        }
    }

    #[test]
    fn weights_are_fitted_per_brick_or_fall_back_to_the_default(
    ) -> Result<(), Box<dyn std::error::Error>> {
        // A flat brick leaves the system singular.
        assert_eq!(Weights::fit(&vec![7u8; EDGE * SLICE]), Weights::DEFAULT);
        // The solver finds a known solution.
        let mut a = [[0f64; 7]; 7];
        for (r, row) in a.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = if r == c {
                    4.0
                } else {
                    1.0 / (1 + r + c) as f64
                };
            }
        }
        let w = [0.5, -0.25, 0.125, 1.0, -1.0, 0.0, 2.0];
        let rhs: [f64; 7] = std::array::from_fn(|r| (0..7).map(|c| a[r][c] * w[c]).sum());
        let solved = solve(a, rhs).ok_or("singular")?;
        assert!(solved.iter().zip(&w).all(|(s, w)| (s - w).abs() < 1e-9));
        // Quantised weights sum to 64; out-of-range ones are refused.
        let q = Weights::quantised([0.55, 0.52, -0.2, 0.05, 0.6, -0.24, -0.27]).ok_or("range")?;
        assert_eq!(q.0.iter().map(|&w| i32::from(w)).sum::<i32>(), 64);
        assert_eq!(
            Weights::quantised([3.0, -2.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
            None
        );
        // A smooth ramp plus noise: fitted, and the fit sums to 64.
        let mut state = 0x9E37_79B9u64;
        let v: Vec<u8> = (0..EDGE * SLICE)
            .map(|i| {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
                ((i % EDGE + i / EDGE % EDGE * 2 + i / SLICE * 3) as u64 + (state >> 61)) as u8
            })
            .collect();
        let fitted = Weights::fit(&v);
        assert_eq!(fitted.0.iter().map(|&w| i32::from(w)).sum::<i32>(), 64);
        Ok(())
    }

    #[test]
    fn streams_hold_every_sample_once() -> Result<(), Box<dyn std::error::Error>> {
        let v: Vec<u8> = (0..EDGE * SLICE).map(|i| (i * 31 % 251) as u8).collect();
        let streams = residual_streams(&v, &Weights::fit(&v));
        assert_eq!(streams.iter().map(Vec::len).sum::<usize>(), v.len());
        let body = compress(&v).ok_or("zstd could not allocate")?;
        let back =
            decompress::<super::super::zstd_frames::Native>(&body).map_err(|e| e.to_string())?;
        assert!(back.iter().zip(&v).all(|(&b, &x)| b == u16::from(x)));
        Ok(())
    }
}
