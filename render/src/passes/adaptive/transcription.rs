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
use crate::model::layout::DEPTH_OPACITY;

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

    /// The four parents (indices into level l+1, clamped to the edge) of level-l pixel (x, y)
    /// and their weights, in the order SYNTHESIZE sums them.
    fn synthesis_terms(&self, level: u32, x: u32, y: u32) -> [(usize, f64); 4] {
        let (pw, ph) = (
            self.level_width(level + 1) as i64,
            self.level_height(level + 1) as i64,
        );
        let mut terms = [(0, 0.0); 4];
        for (j, (py, wy)) in synthesis_parents(y).into_iter().enumerate() {
            for (i, (px, wx)) in synthesis_parents(x).into_iter().enumerate() {
                let (cx, cy) = (px.clamp(0, pw - 1) as u32, py.clamp(0, ph - 1) as u32);
                terms[2 * j + i] = (self.index(level + 1, cx, cy), wx * wy);
            }
        }
        terms
    }

    /// SYNTHESIZE(g, l, x, y) of Fig. 5 over `parent` (level l+1), parents clamped to the edge.
    pub fn synthesize(&self, parent: &[f64], level: u32, x: u32, y: u32) -> f64 {
        self.synthesis_terms(level, x, y)
            .iter()
            .fold(0.0, |sum, &(k, w)| sum + w * parent[k])
    }

    /// [`PyramidDims::synthesize`] of a vector per pixel (the shading gradient), component by
    /// component with the same weights.
    pub fn synthesize_vector(&self, parent: &[[f64; 3]], level: u32, x: u32, y: u32) -> [f64; 3] {
        self.synthesis_terms(level, x, y)
            .iter()
            .fold([0.0; 3], |sum, &(k, w)| {
                [0, 1, 2].map(|c| sum[c] + w * parent[k][c])
            })
    }
}

/// SAMPLE and ORACLE of Fig. 5: the data value and the oracle's sampling distance (in slices)
/// at level-`level` pixel (x, y) of slice `i_slice` (the paper samples both at one point).
pub trait AdaptiveProbe: Sync {
    fn probe(&self, level: u32, x: u32, y: u32, i_slice: u32) -> (f64, f64);

    /// [`AdaptiveProbe::probe`] and the gradient of the data at the same point, for shaded
    /// optics ([`SegmentOptics::shaded`]); by default a zero gradient.
    fn probe_with_gradient(
        &self,
        level: u32,
        x: u32,
        y: u32,
        i_slice: u32,
    ) -> (f64, f64, [f64; 3]) {
        let (value, distance) = self.probe(level, x, y, i_slice);
        (value, distance, [0.0; 3])
    }

    /// Where the ray through level-0 pixel coordinates (u, v) can meet anything but the
    /// transparent default value, as fractional slice positions (entry, exit); None if
    /// nowhere. Read only by [`TileRules::slice_ranges`]; the default is every slice.
    fn ray_slices(&self, _u: f64, _v: f64) -> Option<(f64, f64)> {
        Some((0.0, f64::INFINITY))
    }
}

/// What a segment of a ray contributes (Fig. 6's C_lut and α_lut) and how MIP keeps its
/// maximum.
pub trait SegmentOptics: Sync {
    /// Premultiplied RGB and opacity of a segment of `slices` slice distances whose value runs
    /// linearly from `s_front` to `s_back`.
    fn segment(&self, s_front: f64, s_back: f64, slices: u32) -> [f64; 4];

    /// Maximum intensity projection: ACCUMULATECOLOR keeps each pixel's largest value (and
    /// its slice) instead of compositing segments; the maximum of a segment whose value runs
    /// linearly is at one of its ends, so the maximum over the accumulated values is the
    /// segments' maximum. [`Transcription::maxima`] holds it, and the pixel's colour is
    /// [`SegmentOptics::point`] of it (its pick depth the maximum's slice where that colour
    /// is not transparent), as the raycaster's MIP.
    fn maximum_intensity(&self) -> bool {
        false
    }

    /// Premultiplied RGB and opacity of the TF at one value (MIP's colour): by default a
    /// one-slice segment of that value.
    fn point(&self, s: f64) -> [f64; 4] {
        self.segment(s, s, 1)
    }

    /// Shaded optics: the pyramid then carries the data's gradient beside its value
    /// ([`AdaptiveProbe::probe_with_gradient`], synthesised with the same weights), and each
    /// segment is lit by [`SegmentOptics::shade`] at its back sample's gradient.
    fn shaded(&self) -> bool {
        false
    }

    /// The segment `rgba` of level-0 pixel (x, y) lit at `gradient`; unlit by default.
    fn shade(&self, rgba: [f64; 4], _gradient: [f64; 3], _x: u32, _y: u32) -> [f64; 4] {
        rgba
    }
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
    /// With [`SegmentOptics::maximum_intensity`], per level-0 pixel the largest accumulated
    /// value and its slice (the first of equal ones; −∞ where nothing accumulated); empty
    /// otherwise.
    pub maxima: Vec<(f64, u32)>,
}

/// ACCUMULATECOLOR (Fig. 6) of every level-0 pixel: the previous value and slice, the
/// composited colour and pick depth (DVR), or the running maximum (MIP).
struct Accumulator {
    s_prev: Vec<f64>,
    i_prev: Vec<u32>,
    rgba: Vec<[f64; 4]>,
    depth: Vec<f64>,
    maxima: Vec<(f64, u32)>,
    segments: u64,
    mip: bool,
    /// Level-0 width (a pixel's coordinates for [`SegmentOptics::shade`]).
    width: u32,
}

impl Accumulator {
    fn new(n0: usize, width: u32, mip: bool) -> Self {
        Accumulator {
            width,
            s_prev: vec![0.0; n0],
            i_prev: vec![0; n0],
            rgba: vec![[0.0; 4]; n0],
            depth: vec![f64::INFINITY; n0],
            maxima: if mip {
                vec![(f64::NEG_INFINITY, 0); n0]
            } else {
                Vec::new()
            },
            segments: 0,
            mip,
        }
    }

    /// A pixel's march starts at `first` (before any value of it accumulated).
    fn start(&mut self, k: usize, first: u32) {
        self.i_prev[k] = first;
        self.s_prev[k] = 0.0;
    }

    /// ACCUMULATECOLOR(x, y, i_slice) with the pixel's value `value` (and its gradient, for
    /// shaded optics); `segment` is false for the march's first value, which only starts the
    /// first segment.
    fn accumulate(
        &mut self,
        k: usize,
        (value, gradient): (f64, [f64; 3]),
        i_slice: u32,
        segment: bool,
        optics: &impl SegmentOptics,
    ) {
        if self.mip {
            if value > self.maxima[k].0 {
                self.maxima[k] = (value, i_slice);
            }
            if segment {
                self.segments += 1;
            }
        } else if segment {
            let length = i_slice - self.i_prev[k];
            let mut seg = optics.segment(self.s_prev[k], value, length);
            if optics.shaded() && seg[3] > 0.0 {
                let (x, y) = (k as u32 % self.width, k as u32 / self.width);
                seg = optics.shade(seg, gradient, x, y);
            }
            let c = &mut self.rgba[k];
            let before = c[3];
            let wgt = 1.0 - c[3];
            for ch in 0..4 {
                c[ch] += wgt * seg[ch];
            }
            if self.depth[k].is_infinite() && before < DEPTH_OPACITY && c[3] >= DEPTH_OPACITY {
                let f = (DEPTH_OPACITY - before) / (c[3] - before);
                self.depth[k] = self.i_prev[k] as f64 + f * length as f64;
            }
            self.segments += 1;
        }
        self.s_prev[k] = value;
        self.i_prev[k] = i_slice;
    }

    fn into_transcription(
        mut self,
        dims: PyramidDims,
        samples_per_level: Vec<u64>,
        syntheses_per_level: Vec<u64>,
        optics: &impl SegmentOptics,
    ) -> Transcription {
        for (k, &(value, slice)) in self.maxima.iter().enumerate() {
            if value.is_finite() {
                self.rgba[k] = optics.point(value);
                if self.rgba[k][3] > 0.0 {
                    self.depth[k] = slice as f64;
                }
            }
        }
        Transcription {
            dims,
            rgba: self.rgba,
            depth_slices: self.depth,
            samples_per_level,
            syntheses_per_level,
            segments: self.segments,
            maxima: self.maxima,
        }
    }
}

impl Transcription {
    pub fn total_samples(&self) -> u64 {
        self.samples_per_level.iter().sum()
    }
}

/// The shading gradient's channel of the pyramid: sampled where the value is sampled and
/// synthesised where it is synthesised, with the same weights. Empty (and every call a no-op
/// returning zero) for unshaded optics.
struct GradientPyramid {
    dims: PyramidDims,
    levels: Vec<Vec<[f64; 3]>>,
}

impl GradientPyramid {
    fn new(dims: PyramidDims, shaded: bool) -> Self {
        let levels = if shaded {
            (0..=dims.l_max)
                .map(|l| vec![[0.0; 3]; (dims.level_width(l) * dims.level_height(l)) as usize])
                .collect()
        } else {
            Vec::new()
        };
        GradientPyramid { dims, levels }
    }

    fn at(&self, level: u32, k: usize) -> [f64; 3] {
        self.levels.get(level as usize).map_or([0.0; 3], |g| g[k])
    }

    /// SYNTHESIZE of level-`level` pixel (x, y) from the next coarser level.
    fn synthesize(&mut self, level: u32, x: u32, y: u32) {
        let l = level as usize;
        if l + 1 >= self.levels.len() {
            return;
        }
        let (finer, coarser) = self.levels.split_at_mut(l + 1);
        let k = self.dims.index(level, x, y);
        finer[l][k] = self.dims.synthesize_vector(&coarser[0], level, x, y);
    }

    /// SAMPLE: the probe's value and distance, its gradient kept when shaded.
    fn probe(
        &mut self,
        probe: &impl AdaptiveProbe,
        level: u32,
        x: u32,
        y: u32,
        i_slice: u32,
    ) -> (f64, f64) {
        let k = self.dims.index(level, x, y);
        match self.levels.get_mut(level as usize) {
            Some(g) => {
                let (value, distance, gradient) = probe.probe_with_gradient(level, x, y, i_slice);
                g[k] = gradient;
                (value, distance)
            }
            None => probe.probe(level, x, y, i_slice),
        }
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
    let mut g = GradientPyramid::new(dims, optics.shaded());
    let n0 = s[0].len();
    let mut acc = Accumulator::new(n0, dims.width, optics.maximum_intensity());
    let mut samples = vec![0u64; levels];
    let mut syntheses = vec![0u64; levels];
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
                            g.synthesize(l, x, y);
                            syntheses[l as usize] += 1;
                        }
                    }
                    if l == l_max || d_l[k] < (2u64 << l) as f64 {
                        let (value, distance) = g.probe(probe, l, x, y, i_slice);
                        d_l[k] = distance;
                        s_l[k] = value;
                        samples[l as usize] += 1;
                    }
                    if l == 0 && (ls == l_max || d_l[k] < skip_bound) {
                        let value = (s_l[k], g.at(0, k));
                        acc.accumulate(k, value, i_slice, i_slice > 0, optics);
                    }
                }
            }
        }
    }
    acc.into_transcription(dims, samples, syntheses, optics)
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

    /// Values and distances hashed from (level, pixel, slice): no structure to hide behind.
    struct Hashed;

    impl AdaptiveProbe for Hashed {
        fn probe(&self, level: u32, x: u32, y: u32, i_slice: u32) -> (f64, f64) {
            let h = crate::passes::adaptive::oracle::pcg(
                x ^ crate::passes::adaptive::oracle::pcg(y ^ (i_slice << 8) ^ level),
            );
            ((h % 1000) as f64, (1 + (h >> 10) % 16) as f64)
        }
    }

    struct Opacity;

    impl SegmentOptics for Opacity {
        fn segment(&self, s_front: f64, s_back: f64, slices: u32) -> [f64; 4] {
            let a = 1.0 - (-(s_front + s_back) * 2e-5 * slices as f64).exp();
            [a * 0.5, a * 0.25, a, a]
        }
    }

    #[test]
    fn tiles_without_rules_are_the_global_algorithm_and_termination_only_freezes_opaque_pixels() {
        let dims = PyramidDims::padded(40, 24, 3);
        let global = project_volume(dims, 64, &Hashed, &Opacity);
        for tile in [8, 16, 32] {
            let rules = TileRules {
                tile,
                early_termination: None,
                slice_ranges: true,
            };
            // Every slice is "meetable" with the default ray_slices: ranges change nothing.
            let tiled = project_volume_tiled(dims, 64, rules, &Hashed, &Opacity);
            assert_eq!(tiled, global, "tile {tile}");
            let stopped = project_volume_tiled(
                dims,
                64,
                TileRules {
                    early_termination: Some(0.3),
                    ..rules
                },
                &Hashed,
                &Opacity,
            );
            // Stopping a tile freezes its pixels at ≥ the threshold, never lowers them.
            assert!(
                stopped.total_samples() < global.total_samples(),
                "tile {tile}"
            );
            for (a, b) in stopped.rgba.iter().zip(&global.rgba) {
                assert!(a[3] <= b[3] && (a[3] >= 0.3 || a == b), "tile {tile}");
            }
        }
    }

    /// Opaque everywhere but the rays left of level-0 column 1: one open pixel per row keeps
    /// every tile of the left column voting "open".
    struct OpaqueButTheLeftColumn;

    impl AdaptiveProbe for OpaqueButTheLeftColumn {
        fn probe(&self, level: u32, x: u32, _y: u32, _i_slice: u32) -> (f64, f64) {
            let u = level0_coordinate(level, x);
            (if u < 0.25 { 0.0 } else { 1.0e5 }, 1.0)
        }
    }

    #[test]
    fn opaque_pixels_stop_sampling_while_an_open_pixel_keeps_their_tile_going() {
        // Two tiles of 32²: at level 3 a tile owns 4² pixels, the middle ones interior.
        let dims = PyramidDims::padded(64, 32, 3);
        let rules = |early_termination| TileRules {
            tile: 32,
            early_termination,
            slice_ranges: false,
        };
        let probe = OpaqueButTheLeftColumn;
        let full = project_volume_tiled(dims, 64, rules(None), &probe, &Opacity);
        let stopped = project_volume_tiled(dims, 64, rules(Some(0.99)), &probe, &Opacity);
        // Opaque pixels reach 0.99 within a few slices; the left column never does.
        let n0 = (dims.width * dims.height) as usize;
        let open = (0..n0).filter(|&k| full.rgba[k][3] < 0.99).count();
        assert_eq!(
            open, dims.height as usize,
            "only the left column stays open"
        );
        // Level 0: the open column samples all 65 slices, the rest a few each.
        assert!(
            stopped.samples_per_level[0] * 5 < full.samples_per_level[0],
            "{:?} vs {:?}",
            stopped.samples_per_level,
            full.samples_per_level
        );
        // Coarser levels: the right tile stops at its first vote; the left one closes its
        // interior pixels but those feeding the open column.
        for l in 1..=3 {
            assert!(
                stopped.samples_per_level[l] * 2 < full.samples_per_level[l],
                "level {l}: {:?} vs {:?}",
                stopped.samples_per_level,
                full.samples_per_level
            );
        }
        // Open pixels are the full march's exactly; closed ones stay at ≥ the threshold.
        for k in 0..n0 {
            if full.rgba[k][3] < 0.99 {
                assert_eq!(stopped.rgba[k], full.rgba[k], "pixel {k}");
            } else {
                assert!(stopped.rgba[k][3] >= 0.99 && stopped.rgba[k][3] <= full.rgba[k][3]);
            }
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

/// The decisions a tile of the GPU pass takes together (shaders/adaptive.wgsl), each the same
/// for every pixel of the tile so the barriers stay in uniform control flow. Tiles of
/// `tile`² level-0 pixels hold levels 1..=l_max with a one-pixel apron, which evolve exactly
/// as the same pixels of the global algorithm; what the rules change is where a tile starts
/// and stops.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TileRules {
    pub tile: u32,
    /// Early ray termination at this opacity, per pixel and per tile:
    /// - a level-0 pixel that reached it takes no more samples, syntheses or segments (level 0
    ///   feeds no other pixel, so every other pixel is unchanged);
    /// - after every slice of l_slice = l_max (where every pixel has just composited) a
    ///   coarser pixel closes once every finer pixel its synthesis feeds (children
    ///   2p−1..2p+2 per axis) is closed, and a closed pixel takes no more samples or
    ///   syntheses: only closed pixels ever read it again, so the open ones are unchanged.
    ///   Apron pixels and pixels whose children reach the apron or another tile stay open
    ///   (the tile cannot see those children);
    /// - at the same slices the tile stops once all its level-0 pixels are closed.
    pub early_termination: Option<f64>,
    /// Empty space before and behind the data: a tile none of whose rays (every level's,
    /// apron included) meets the data is transparent without a sample; otherwise it marches
    /// from the last slice of l_slice = l_max before every entry to the first one after every
    /// exit (with one such block of margin each side), which gives the image of the full
    /// march, since a slice of l_slice = l_max rebuilds the whole pyramid.
    pub slice_ranges: bool,
}

/// One tile's slice range under [`TileRules::slice_ranges`] (None: the tile meets nothing),
/// from the rays it samples; the shader's rounding, step for step.
fn tile_slice_range(
    dims: PyramidDims,
    last_slice: u32,
    tile: u32,
    (tile_x, tile_y): (u32, u32),
    probe: &impl AdaptiveProbe,
) -> Option<(u32, u32)> {
    let mut hit = false;
    let (mut entry, mut exit) = (f64::INFINITY, 0.0f64);
    let mut see = |u: f64, v: f64| {
        if let Some((t0, t1)) = probe.ray_slices(u, v) {
            if t1 >= t0 && t0 <= last_slice as f64 {
                hit = true;
                entry = entry.min(t0);
                exit = exit.max(t1);
            }
        }
    };
    for y in tile_y..tile_y + tile {
        for x in tile_x..tile_x + tile {
            see(x as f64, y as f64);
        }
    }
    for l in 1..=dims.l_max {
        let e = (tile >> l) as i64 + 2;
        for j in 0..e {
            for i in 0..e {
                let gx = (tile_x >> l) as i64 - 1 + i;
                let gy = (tile_y >> l) as i64 - 1 + j;
                let scale = (1u64 << l) as f64;
                see(
                    scale * (gx as f64 + 0.5) - 0.5,
                    scale * (gy as f64 + 0.5) - 0.5,
                );
            }
        }
    }
    if !hit {
        return None;
    }
    let block = 1u32 << dims.l_max;
    let mut first = 0;
    if entry > (2 * block) as f64 {
        first = (entry as u32 / block - 1) * block;
    }
    let mut last = last_slice;
    if exit + ((2 * block) as f64) < last_slice as f64 {
        last = (exit as u32 / block + 2)
            .saturating_mul(block)
            .min(last_slice);
    }
    Some((first.min(last_slice), last))
}

/// [`project_volume`] tile by tile under `rules`, as the GPU pass runs it: each tile marches
/// its own levels (apron included) over its own slices. Counts are of each tile's own pixels
/// (the global algorithm's, where no rule stops a tile early); with no rule in force the
/// result equals [`project_volume`]'s.
pub fn project_volume_tiled(
    dims: PyramidDims,
    last_slice: u32,
    rules: TileRules,
    probe: &impl AdaptiveProbe,
    optics: &impl SegmentOptics,
) -> Transcription {
    let l_max = dims.l_max;
    let m = 1u32 << l_max;
    let last_slice = last_slice.div_ceil(m) * m;
    let levels = (l_max + 1) as usize;
    let tile = rules.tile.max(m);
    let n0 = (dims.width * dims.height) as usize;
    let mut acc = Accumulator::new(n0, dims.width, optics.maximum_intensity());
    let mut samples = vec![0u64; levels];
    let mut syntheses = vec![0u64; levels];
    // Scratch pyramid over the whole image; each tile touches only its window.
    let mut s: Vec<Vec<f64>> = (0..=l_max)
        .map(|l| vec![0.0; (dims.level_width(l) * dims.level_height(l)) as usize])
        .collect();
    let mut d = s.clone();
    let mut g = GradientPyramid::new(dims, optics.shaded());
    // Closed pixels of levels 1..=l_max under early termination (index 0 unused: level 0
    // reads its opacity directly).
    let mut closed: Vec<Vec<bool>> = (0..=l_max)
        .map(|l| vec![false; (dims.level_width(l) * dims.level_height(l)) as usize])
        .collect();
    for tile_y in (0..dims.height).step_by(tile as usize) {
        for tile_x in (0..dims.width).step_by(tile as usize) {
            let (first, last) = if rules.slice_ranges {
                match tile_slice_range(dims, last_slice, tile, (tile_x, tile_y), probe) {
                    Some(r) => r,
                    None => continue,
                }
            } else {
                (0, last_slice)
            };
            // Level-l window of the tile: its own pixels plus the apron, inside the level.
            let window = |l: u32| {
                let (wl, hl) = (dims.level_width(l) as i64, dims.level_height(l) as i64);
                let lo = |t: u32| ((t >> l) as i64 - if l == 0 { 0 } else { 1 }).max(0);
                let hi = |t: u32, n: i64| {
                    ((t >> l) as i64 + (tile >> l) as i64 + if l == 0 { 0 } else { 1 }).min(n)
                };
                (lo(tile_x)..hi(tile_x, wl), lo(tile_y)..hi(tile_y, hl))
            };
            let owned = |l: u32, x: i64, y: i64| {
                let (ox, oy) = ((tile_x >> l) as i64, (tile_y >> l) as i64);
                let n = (tile >> l) as i64;
                x >= ox && x < ox + n && y >= oy && y < oy + n
            };
            for (x, y) in cartesian(window(0)) {
                acc.start((y as u32 * dims.width + x as u32) as usize, first);
            }
            for l in 1..=l_max {
                let w = dims.level_width(l);
                for (x, y) in cartesian(window(l)) {
                    closed[l as usize][(y as u32 * w + x as u32) as usize] = false;
                }
            }
            let opaque = |c: &[f64; 4]| {
                rules
                    .early_termination
                    .is_some_and(|threshold| c[3] >= threshold)
            };
            let mut first_value = true;
            for i_slice in first..=last {
                let ls = l_slice(i_slice, l_max);
                let skip_bound = (2u64 << ls) as f64;
                for l in (0..=ls).rev() {
                    let w = dims.level_width(l);
                    let (coarser, finer) = s.split_at_mut(l as usize + 1);
                    let (d_coarser, d_finer) = d.split_at_mut(l as usize + 1);
                    let s_l = &mut coarser[l as usize];
                    let d_l = &mut d_coarser[l as usize];
                    let s_parent = finer.first().map(|v| v.as_slice());
                    let d_parent = d_finer.first().map(|v| v.as_slice());
                    for (x, y) in cartesian(window(l)) {
                        let (x, y) = (x as u32, y as u32);
                        let k = (y * w + x) as usize;
                        let own = owned(l, x as i64, y as i64);
                        if (l == 0 && opaque(&acc.rgba[k])) || (l > 0 && closed[l as usize][k]) {
                            continue;
                        }
                        if l < ls && (ls == l_max || d_l[k] < skip_bound) {
                            if let (Some(sp), Some(dp)) = (s_parent, d_parent) {
                                d_l[k] = dims.synthesize(dp, l, x, y);
                                s_l[k] = dims.synthesize(sp, l, x, y);
                                g.synthesize(l, x, y);
                                if own {
                                    syntheses[l as usize] += 1;
                                }
                            }
                        }
                        if l == l_max || d_l[k] < (2u64 << l) as f64 {
                            let (value, distance) = g.probe(probe, l, x, y, i_slice);
                            d_l[k] = distance;
                            s_l[k] = value;
                            if own {
                                samples[l as usize] += 1;
                            }
                        }
                        if l == 0 && (ls == l_max || d_l[k] < skip_bound) {
                            let value = (s_l[k], g.at(0, k));
                            acc.accumulate(k, value, i_slice, !first_value, optics);
                        }
                    }
                }
                first_value = false;
                if rules.early_termination.is_some() && ls == l_max && i_slice > first {
                    let open = cartesian(window(0)).any(|(x, y)| {
                        !opaque(&acc.rgba[(y as u32 * dims.width + x as u32) as usize])
                    });
                    if !open {
                        break;
                    }
                    for l in 1..=l_max {
                        let (finer, coarser) = closed.split_at_mut(l as usize);
                        let child_closed = |cx: i64, cy: i64| {
                            if l == 1 {
                                let (tx, ty) = (tile_x as i64, tile_y as i64);
                                let inside = (tx..tx + tile as i64).contains(&cx)
                                    && (ty..ty + tile as i64).contains(&cy);
                                inside
                                    && opaque(
                                        &acc.rgba[(cy as u32 * dims.width + cx as u32) as usize],
                                    )
                            } else {
                                let wf = dims.level_width(l - 1);
                                owned(l - 1, cx, cy)
                                    && finer[l as usize - 1][(cy as u32 * wf + cx as u32) as usize]
                            }
                        };
                        let (wf, hf) = (
                            dims.level_width(l - 1) as i64,
                            dims.level_height(l - 1) as i64,
                        );
                        let w = dims.level_width(l);
                        for (x, y) in cartesian(window(l)) {
                            let children = |p: i64, n: i64| (2 * p - 1).max(0)..(2 * p + 3).min(n);
                            let all_closed = owned(l, x, y)
                                && cartesian((children(x, wf), children(y, hf)))
                                    .all(|(cx, cy)| child_closed(cx, cy));
                            coarser[0][(y as u32 * w + x as u32) as usize] = all_closed;
                        }
                    }
                }
            }
        }
    }
    acc.into_transcription(dims, samples, syntheses, optics)
}

fn cartesian(
    (xs, ys): (std::ops::Range<i64>, std::ops::Range<i64>),
) -> impl Iterator<Item = (i64, i64)> {
    ys.flat_map(move |y| xs.clone().map(move |x| (x, y)))
}
