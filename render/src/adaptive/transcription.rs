//! The algorithm of Kraus, Strengert, Klein & Ertl, "Adaptive Sampling in Three Dimensions for
//! Volume Rendering on GPUs" (adaptive-sampling-3d §3.1-3.3, Figs. 3, 5, 6), transcribed
//! line by line in f64 over the whole (padded) image. It is the specification the tiled GPU
//! pass (shaders/adaptive.wgsl) is tested against; what is sampled (a volume, a test
//! function) and how a segment is integrated are the caller's ([`AdaptiveProbe`],
//! [`SegmentOptics`]).
//!
//! Conventions, shared with the GPU pass:
//! - Level l has `(width >> l) × (height >> l)` pixels; width and height are multiples of
//!   2^l_max ([`PyramidDims::padded`]).
//! - Level-l pixel (x, y) samples at level-0 pixel coordinates (2^l(x+½)−½, 2^l(y+½)−½)
//!   (Fig. 5), i.e. between level-0 pixel centres: each level casts its own rays.
//! - SYNTHESIZE's parents outside the level are clamped to its edge ("image edges clamped").
//! - Slices run from 0 to `last_slice`, a multiple of 2^l_max (Fig. 6 rounds up to a power of
//!   two; a multiple is all §3.1 asks for and wastes fewer slices).
use crate::layout::DEPTH_OPACITY;

/// l_slice of §3.1: the number of trailing zeros of `i_slice`, capped at `l_max`; slice 0
/// counts as l_max (its trailing zeros are infinite, Table 1).
pub fn l_slice(i_slice: u32, l_max: u32) -> u32 {
    if i_slice == 0 {
        l_max
    } else {
        i_slice.trailing_zeros().min(l_max)
    }
}

/// Level-0 pixel coordinate of level-`level` pixel index `x` (Fig. 5's SAMPLE and ORACLE).
pub fn level0_coordinate(level: u32, x: u32) -> f64 {
    (1u64 << level) as f64 * (x as f64 + 0.5) - 0.5
}

/// The two parents of child index `x` on the next coarser level and their weights (Fig. 5 per
/// axis): `ceil(x/2) − 1` with weight ¼ + frac(x/2), `ceil(x/2)` with ¾ − frac(x/2). Indices
/// may be −1 or one past the end; [`PyramidDims`] clamps them.
pub fn synthesis_parents(x: u32) -> [(i64, f64); 2] {
    let half = x.div_ceil(2) as i64;
    let frac = if x % 2 == 1 { 0.5 } else { 0.0 };
    [(half - 1, 0.25 + frac), (half, 0.75 - frac)]
}

/// Pyramid sizes of one frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PyramidDims {
    /// Level-0 size, multiples of 2^l_max.
    pub width: u32,
    pub height: u32,
    pub l_max: u32,
}

impl PyramidDims {
    /// The viewport `width × height` padded up to multiples of 2^l_max.
    pub fn padded(width: u32, height: u32, l_max: u32) -> Self {
        let m = 1u32 << l_max;
        PyramidDims {
            width: width.div_ceil(m) * m,
            height: height.div_ceil(m) * m,
            l_max,
        }
    }

    pub fn level_width(&self, level: u32) -> u32 {
        self.width >> level
    }

    pub fn level_height(&self, level: u32) -> u32 {
        self.height >> level
    }

    fn index(&self, level: u32, x: u32, y: u32) -> usize {
        y as usize * self.level_width(level) as usize + x as usize
    }

    /// SYNTHESIZE(g, l, x, y) of Fig. 5 over `parent` (level l+1), parents clamped to the edge.
    pub fn synthesize(&self, parent: &[f64], level: u32, x: u32, y: u32) -> f64 {
        let (pw, ph) = (
            self.level_width(level + 1) as i64,
            self.level_height(level + 1) as i64,
        );
        let mut sum = 0.0;
        for (py, wy) in synthesis_parents(y) {
            for (px, wx) in synthesis_parents(x) {
                let (cx, cy) = (px.clamp(0, pw - 1) as u32, py.clamp(0, ph - 1) as u32);
                sum += wx * wy * parent[self.index(level + 1, cx, cy)];
            }
        }
        sum
    }
}

/// SAMPLE and ORACLE of Fig. 5: the data value and the oracle's sampling distance (in slices)
/// at level-`level` pixel (x, y) of slice `i_slice` (the paper samples both at one point).
pub trait AdaptiveProbe: Sync {
    fn probe(&self, level: u32, x: u32, y: u32, i_slice: u32) -> (f64, f64);
}

/// What a segment of a ray contributes (Fig. 6's C_lut and α_lut) and how MIP keeps its
/// maximum.
pub trait SegmentOptics: Sync {
    /// Premultiplied RGB and opacity of a segment of `slices` slice distances whose value runs
    /// linearly from `s_front` to `s_back`.
    fn segment(&self, s_front: f64, s_back: f64, slices: u32) -> [f64; 4];
}

/// What the transcription accumulates per level-0 pixel and counts.
#[derive(Clone, Debug, PartialEq)]
pub struct Transcription {
    pub dims: PyramidDims,
    /// Premultiplied RGBA per level-0 pixel of the padded image, row-major.
    pub rgba: Vec<[f64; 4]>,
    /// Slice position (fractional) where accumulated opacity reaches ½ (+inf if never):
    /// the pick depth, interpolated linearly in opacity within the segment that crosses ½.
    pub depth_slices: Vec<f64>,
    /// SAMPLE (and ORACLE) calls per level.
    pub samples_per_level: Vec<u64>,
    /// SYNTHESIZE calls per level (each synthesises s and d).
    pub syntheses_per_level: Vec<u64>,
    /// ACCUMULATECOLOR calls with a segment (i_slice > 0).
    pub segments: u64,
}

impl Transcription {
    pub fn total_samples(&self) -> u64 {
        self.samples_per_level.iter().sum()
    }
}

/// PROJECTVOLUME of Fig. 6 with PROJECTSLICE of Fig. 3 for slices 0..=`last_slice`
/// (rounded up to a multiple of 2^l_max).
pub fn project_volume(
    dims: PyramidDims,
    last_slice: u32,
    probe: &impl AdaptiveProbe,
    optics: &impl SegmentOptics,
) -> Transcription {
    let l_max = dims.l_max;
    let m = 1u32 << l_max;
    let last_slice = last_slice.div_ceil(m) * m;
    let levels = (l_max + 1) as usize;
    let mut s: Vec<Vec<f64>> = (0..=l_max)
        .map(|l| vec![0.0; (dims.level_width(l) * dims.level_height(l)) as usize])
        .collect();
    let mut d = s.clone();
    let n0 = s[0].len();
    let mut s_prev = vec![0.0; n0];
    let mut i_prev = vec![0u32; n0];
    let mut rgba = vec![[0.0f64; 4]; n0];
    let mut depth = vec![f64::INFINITY; n0];
    let mut samples = vec![0u64; levels];
    let mut syntheses = vec![0u64; levels];
    let mut segments = 0u64;
    for i_slice in 0..=last_slice {
        let ls = l_slice(i_slice, l_max);
        let skip_bound = (2u64 << ls) as f64; // 2^(l_slice+1)
        for l in (0..=ls).rev() {
            let (w, h) = (dims.level_width(l), dims.level_height(l));
            let (coarser, finer) = s.split_at_mut(l as usize + 1);
            let (d_coarser, d_finer) = d.split_at_mut(l as usize + 1);
            let s_l = &mut coarser[l as usize];
            let d_l = &mut d_coarser[l as usize];
            let s_parent = finer.first().map(|v| v.as_slice());
            let d_parent = d_finer.first().map(|v| v.as_slice());
            for x in 0..w {
                for y in 0..h {
                    let k = dims.index(l, x, y);
                    if l < ls && (ls == l_max || d_l[k] < skip_bound) {
                        if let (Some(sp), Some(dp)) = (s_parent, d_parent) {
                            d_l[k] = dims.synthesize(dp, l, x, y);
                            s_l[k] = dims.synthesize(sp, l, x, y);
                            syntheses[l as usize] += 1;
                        }
                    }
                    if l == l_max || d_l[k] < (2u64 << l) as f64 {
                        let (value, distance) = probe.probe(l, x, y, i_slice);
                        d_l[k] = distance;
                        s_l[k] = value;
                        samples[l as usize] += 1;
                    }
                    if l == 0 && (ls == l_max || d_l[k] < skip_bound) {
                        // ACCUMULATECOLOR(x, y, i_slice)
                        if i_slice > 0 {
                            let length = i_slice - i_prev[k];
                            let seg = optics.segment(s_prev[k], s_l[k], length);
                            let c = &mut rgba[k];
                            let before = c[3];
                            let wgt = 1.0 - c[3];
                            for ch in 0..4 {
                                c[ch] += wgt * seg[ch];
                            }
                            if depth[k].is_infinite()
                                && before < DEPTH_OPACITY
                                && c[3] >= DEPTH_OPACITY
                            {
                                let f = (DEPTH_OPACITY - before) / (c[3] - before);
                                depth[k] = i_prev[k] as f64 + f * length as f64;
                            }
                            segments += 1;
                        }
                        s_prev[k] = s_l[k];
                        i_prev[k] = i_slice;
                    }
                }
            }
        }
    }
    Transcription {
        dims,
        rgba,
        depth_slices: depth,
        samples_per_level: samples,
        syntheses_per_level: syntheses,
        segments,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn l_slice_is_table_1_and_capped_at_l_max() {
        // Table 1 (l_max = ∞): slice 0 is ∞; a large cap stands in for it.
        let table_1 = [u32::MAX, 0, 1, 0, 2, 0, 1, 0, 3];
        for (i, &expected) in table_1.iter().enumerate() {
            let got = l_slice(i as u32, u32::MAX);
            assert_eq!(got, expected, "slice {i}");
            if i > 0 {
                // 2^(l_slice + 1) row of Table 1.
                assert_eq!(2u32 << got, [0, 2, 4, 2, 8, 2, 4, 2, 16][i]);
            }
        }
        for i in 0..64u32 {
            let capped = l_slice(i, 2);
            let uncapped = if i == 0 { u32::MAX } else { i.trailing_zeros() };
            assert_eq!(capped, uncapped.min(2), "slice {i}");
        }
    }

    #[test]
    fn synthesis_reproduces_the_fig_4_example() {
        // s0[4,1] = 3/16 s1[1,0] + 9/16 s1[2,0] + 1/16 s1[1,1] + 3/16 s1[2,1]: level 1 holds
        // distinct powers of two so every weight is read off exactly.
        let dims = PyramidDims::padded(8, 4, 1);
        let (w1, h1) = (dims.level_width(1), dims.level_height(1));
        let parent: Vec<f64> = (0..w1 * h1).map(|i| (1u64 << (4 * i)) as f64).collect();
        let at = |x: u32, y: u32| parent[(y * w1 + x) as usize];
        let got = dims.synthesize(&parent, 0, 4, 1);
        let expected = 3.0 / 16.0 * at(1, 0)
            + 9.0 / 16.0 * at(2, 0)
            + 1.0 / 16.0 * at(1, 1)
            + 3.0 / 16.0 * at(2, 1);
        assert_eq!(got, expected);
        // And the weights are the bilinear ones at the child's centre (a single filtered
        // fetch, §3.2).
        assert_eq!(synthesis_parents(4), [(1, 0.25), (2, 0.75)]);
        assert_eq!(synthesis_parents(1), [(0, 0.75), (1, 0.25)]);
    }

    #[test]
    fn a_linear_field_synthesises_exactly_in_the_interior() {
        let dims = PyramidDims::padded(64, 32, 3);
        for level in 0..3 {
            let (pw, ph) = (dims.level_width(level + 1), dims.level_height(level + 1));
            let field = |u: f64, v: f64| 0.75 * u - 1.25 * v + 3.0;
            let parent: Vec<f64> = (0..ph)
                .flat_map(|y| {
                    (0..pw).map(move |x| {
                        field(
                            level0_coordinate(level + 1, x),
                            level0_coordinate(level + 1, y),
                        )
                    })
                })
                .collect();
            let (w, h) = (dims.level_width(level), dims.level_height(level));
            let mut edge_differs = false;
            for y in 0..h {
                for x in 0..w {
                    let got = dims.synthesize(&parent, level, x, y);
                    let exact = field(level0_coordinate(level, x), level0_coordinate(level, y));
                    let interior = x > 0 && y > 0 && x + 1 < w && y + 1 < h;
                    if interior {
                        assert!((got - exact).abs() < 1e-12, "level {level} ({x},{y})");
                    } else {
                        edge_differs |= (got - exact).abs() > 1e-6;
                    }
                }
            }
            // Clamping at the edge is not linear extrapolation: the test can tell them apart.
            assert!(edge_differs);
        }
    }

    /// Constant-distance oracle over a value that depends on the slice only.
    struct SliceField {
        distance: f64,
    }

    impl AdaptiveProbe for SliceField {
        fn probe(&self, _level: u32, _x: u32, _y: u32, i_slice: u32) -> (f64, f64) {
            (i_slice as f64, self.distance)
        }
    }

    struct RecordLengths;

    impl SegmentOptics for RecordLengths {
        fn segment(&self, s_front: f64, s_back: f64, slices: u32) -> [f64; 4] {
            // The value is the slice index: a segment must span exactly its length.
            assert_eq!(s_back - s_front, slices as f64);
            [0.0, 0.0, 0.0, 0.01 * slices as f64]
        }
    }

    #[test]
    fn distance_one_samples_every_pixel_on_every_slice_and_the_maximum_skips() {
        let dims = PyramidDims::padded(16, 8, 2);
        let n0 = 16 * 8u64;
        let full = project_volume(dims, 16, &SliceField { distance: 1.0 }, &RecordLengths);
        // d = 1: every level-0 pixel is sampled on every slice (plus the pyramid above it).
        assert_eq!(full.samples_per_level[0], n0 * 17);
        assert_eq!(full.segments, n0 * 16);
        // d = 2^l_max: level l_max samples every 4th slice, nothing finer is sampled after
        // slice 0... level 0 never (slice 0 samples level 0 only where d < 2).
        let coarse = project_volume(dims, 16, &SliceField { distance: 4.0 }, &RecordLengths);
        assert_eq!(coarse.samples_per_level[2], (n0 / 16) * 5);
        assert_eq!(coarse.samples_per_level[1], 0);
        assert_eq!(coarse.samples_per_level[0], 0);
        assert_eq!(coarse.segments, n0 * 4);
    }
}
