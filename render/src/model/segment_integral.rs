//! Length-free pre-integration: the colour and opacity of a ray segment of any length whose
//! value runs linearly from `s_front` to `s_back`, from 1D integral tables over the TF's
//! value range at the TF table's own resolution (4096 entries).
//!
//! Why not the 2D table (preintegration.rs) the raycaster used before: measured on the
//! phantom (docs/accuracy-phantom192.md, issue 15), the 256² table lost to classic sampling at
//! every step. Its 256 cells span the whole value range (16 HU per cell on CT), and the
//! bilinear lookup interpolates a segment's colour and opacity between cells: a TF feature
//! narrower than a cell is smeared over neighbouring (front, back) pairs, and even constant
//! segments (the diagonal) see the TF at 256 points where the classic path sees 4096. Its
//! power-law rescaling to other lengths was exact only on the diagonal.
//!
//! Here the extinction κ(s) = −ln(1 − α(s))/unit and the emission κ(s)·c(s), linear between
//! the TF table's entries, are integrated over the value axis once (prefix sums K and KC). A segment of length L
//! then has, exactly for the tabulated TF,
//!   τ = L · (K(s_back) − K(s_front)) / (s_back − s_front),   α = 1 − e^(−τ),
//! for every length (so the adaptive pass's segments of 1..2^l_max slices need no table per
//! length), and colour α · (KC(b) − KC(f)) / (K(b) − K(f)): the opacity-weighted mean colour
//! over the segment. That is exact wherever colour is constant over the segment's values and
//! otherwise ignores which colour is seen first within one segment (the 2D table's one
//! advantage, which its coarse cells more than used up).
//!
//! f32 on the GPU: K reaches ~10⁴, and K(b) − K(f) for nearby values would cancel. Each prefix
//! is therefore stored as a hi/lo pair of f32 (hi + lo = the f64 prefix to ~1e-14) plus the
//! point values κ, so a difference is (hi_b − hi_f) + (rest_b − rest_f) with small rests
//! (lo + the partial cell's quadratic), all well-conditioned; within one cell the mean is κ
//! at the segment's middle value, read directly.

use crate::model::transfer_function::{TransferFunction, TABLE_ENTRIES};

/// Opacity at which extinction is clamped, as in the classic path (opacity 1 would make it
/// infinite).
const MAX_OPACITY: f64 = 0.999_999;

/// Rows of the GPU texture, each `entries` wide, RGBA32F = (K, KC.r, KC.g, KC.b): prefix hi,
/// prefix lo, and the point values (κ, κ·c) at the entry.
pub const INTEGRAL_ROWS: u32 = 3;

/// Prefix integrals of extinction and emission over the TF table's entries. Between entries
/// κ and κ·c are linear (as the classic path interpolates the TF table), so the integrals are
/// exact piecewise quadratics of the value.
#[derive(Clone, Debug, PartialEq)]
pub struct SegmentIntegralTable {
    /// Value range (the TF table's), and entries over it.
    pub lo: f64,
    pub hi: f64,
    pub entries: u32,
    /// Length (mm) the TF's opacity is defined for: the finest voxel.
    pub unit_mm: f64,
    /// Per entry, the f32 hi part of the prefix (K, KC.rgb), in entry spacings × 1/mm.
    pub prefix_hi: Vec<[f32; 4]>,
    /// Per entry, the f32 remainder: hi + lo = the f64 prefix.
    pub prefix_lo: Vec<[f32; 4]>,
    /// Per entry, κ and κ·c (1/mm) at the entry's value.
    pub point: Vec<[f32; 4]>,
}

impl SegmentIntegralTable {
    pub fn build(tf: &TransferFunction, lo: f64, hi: f64, unit_mm: f64) -> Self {
        Self::with_entries(tf, lo, hi, unit_mm, TABLE_ENTRIES as u32)
    }

    pub fn with_entries(
        tf: &TransferFunction,
        lo: f64,
        hi: f64,
        unit_mm: f64,
        entries: u32,
    ) -> Self {
        let n = entries.max(2) as usize;
        let hi = if hi > lo { hi } else { lo + 1.0 };
        let unit_mm = if unit_mm.is_finite() && unit_mm > 0.0 {
            unit_mm
        } else {
            1.0
        };
        let spacing = (hi - lo) / (n - 1) as f64;
        let point: Vec<[f32; 4]> = (0..n)
            .map(|i| {
                let s = lo + spacing * i as f64;
                let a = tf.opacity_at(s).clamp(0.0, MAX_OPACITY);
                let kappa = -(1.0 - a).ln() / unit_mm;
                let c = tf.color_at(s);
                [kappa, kappa * c[0], kappa * c[1], kappa * c[2]].map(|v| v as f32)
            })
            .collect();
        let mut prefix = [0.0f64; 4];
        let (mut prefix_hi, mut prefix_lo) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for i in 0..n {
            let h = prefix.map(|v| v as f32);
            prefix_hi.push(h);
            prefix_lo.push([0, 1, 2, 3].map(|c| (prefix[c] - h[c] as f64) as f32));
            if i + 1 < n {
                // Trapezoid of the f32 point values: exact for the linear κ the lookup uses.
                for c in 0..4 {
                    prefix[c] += 0.5 * (point[i][c] as f64 + point[i + 1][c] as f64);
                }
            }
        }
        SegmentIntegralTable {
            lo,
            hi,
            entries: n as u32,
            unit_mm,
            prefix_hi,
            prefix_lo,
            point,
        }
    }

    /// The texture's texels, row by row (hi, lo, point).
    pub fn texels(&self) -> Vec<[f32; 4]> {
        let mut out = self.prefix_hi.clone();
        out.extend_from_slice(&self.prefix_lo);
        out.extend_from_slice(&self.point);
        out
    }

    /// Position of `s` in entry spacings (unclamped) and its cell: −1 below the table, n−1
    /// above it, else the entry at or below.
    fn position(&self, s: f64) -> (f64, i64) {
        let n = self.entries as i64;
        let x = (s - self.lo) / (self.hi - self.lo) * (n - 1) as f64;
        let cell = if x.is_nan() {
            -1
        } else {
            (x.floor().clamp(-1.0, (n - 1) as f64)) as i64
        };
        (x, cell)
    }

    fn get(v: &[[f32; 4]], i: i64) -> [f64; 4] {
        v[i as usize].map(|c| c as f64)
    }

    /// κ, κ·c at position x (linear between entries, constant beyond the ends).
    fn point_at(&self, x: f64, cell: i64) -> [f64; 4] {
        let last = self.entries as i64 - 1;
        if cell < 0 {
            return Self::get(&self.point, 0);
        }
        if cell >= last {
            return Self::get(&self.point, last);
        }
        let (a, b) = (
            Self::get(&self.point, cell),
            Self::get(&self.point, cell + 1),
        );
        let f = x - cell as f64;
        [0, 1, 2, 3].map(|c| a[c] + f * (b[c] - a[c]))
    }

    /// The prefix at x as (hi, rest): hi is an entry's f32 hi part, rest small.
    fn prefix_at(&self, x: f64, cell: i64) -> ([f64; 4], [f64; 4]) {
        let last = self.entries as i64 - 1;
        let (entry, dx_from) = if cell < 0 {
            (0, x)
        } else if cell >= last {
            (last, x - last as f64)
        } else {
            (cell, x - cell as f64)
        };
        let (h, l, p) = (
            Self::get(&self.prefix_hi, entry),
            Self::get(&self.prefix_lo, entry),
            Self::get(&self.point, entry),
        );
        let rest = if cell < 0 || cell >= last {
            [0, 1, 2, 3].map(|c| l[c] + dx_from * p[c])
        } else {
            let q = Self::get(&self.point, entry + 1);
            let f = dx_from;
            [0, 1, 2, 3].map(|c| l[c] + f * p[c] + 0.5 * f * f * (q[c] - p[c]))
        };
        (h, rest)
    }

    /// Premultiplied RGB and opacity of a segment of `length_mm` from `s_front` to `s_back`,
    /// evaluated from the f32 table in f64: what the shader computes (preintegration.wgsl),
    /// without its f32 rounding.
    pub fn segment(&self, s_front: f64, s_back: f64, length_mm: f64) -> [f64; 4] {
        let (xf, cf) = self.position(s_front);
        let (xb, cb) = self.position(s_back);
        let dx = xb - xf;
        // Mean extinction and emission per mm over the segment.
        let mean: [f64; 4] = if cf == cb || dx.abs() < 1e-3 {
            let xm = 0.5 * (xf + xb);
            let (_, cm) = self.position(0.5 * (s_front + s_back));
            self.point_at(xm, cm)
        } else {
            let (hf, rf) = self.prefix_at(xf, cf);
            let (hb, rb) = self.prefix_at(xb, cb);
            [0, 1, 2, 3].map(|c| ((hb[c] - hf[c]) + (rb[c] - rf[c])) / dx)
        };
        let kappa = mean[0].max(0.0);
        let length = if length_mm.is_finite() {
            length_mm.max(0.0)
        } else {
            0.0
        };
        let alpha = 1.0 - (-kappa * length).exp();
        if kappa <= 0.0 || alpha <= 0.0 {
            return [0.0; 4];
        }
        let colour = [1, 2, 3].map(|c| (mean[c] / kappa).clamp(0.0, 1.0) * alpha);
        [colour[0], colour[1], colour[2], alpha]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::preintegration::integrate_segment;

    fn bands() -> TransferFunction {
        // Three peaks each 1 % of a CT range wide, one colour each.
        TransferFunction::new(
            "bands",
            &[
                (-1000.0, 0.0),
                (130.0, 0.0),
                (150.0, 0.6),
                (170.0, 0.0),
                (380.0, 0.0),
                (400.0, 0.4),
                (420.0, 0.0),
                (980.0, 0.0),
                (1000.0, 0.9),
                (1020.0, 0.0),
                (3000.0, 0.0),
            ],
            &[(-1000.0, [0.8, 0.2, 0.2]), (3000.0, [0.8, 0.2, 0.2])],
        )
    }

    /// 4096 entries 1 HU apart: the bands' knots (integers) are entries, so the tabulated TF
    /// is the TF and only the formulation and its f32 storage are under test. (Off the
    /// entries a knot is cut to the table's 1/4095 of the range, as in the classic path.)
    fn table_on_integers(tf: &TransferFunction) -> SegmentIntegralTable {
        SegmentIntegralTable::with_entries(tf, -1000.0, 3095.0, 1.0, 4096)
    }

    #[test]
    fn constant_colour_segments_match_exact_integration_for_every_length() {
        let tf = bands();
        let table = table_on_integers(&tf);
        for (f, b) in [
            (100.0, 200.0),
            (200.0, 100.0),
            (150.0, 150.0),
            (-500.0, 1200.0),
            (399.0, 401.0),
            (405.0, 405.3),
        ] {
            for length in [0.25, 0.5, 1.0, 2.0, 4.0, 8.0] {
                let got = table.segment(f, b, length);
                let exact = integrate_segment(&tf, f, b, length, 1.0, 20_000);
                for c in 0..4 {
                    // Colour is constant, so only the table's 1/4096 resolution separates
                    // them: ~1e-3 of a peak's width.
                    assert!(
                        (got[c] - exact[c] as f64).abs() < 2e-3,
                        "({f}, {b}) × {length}: {got:?} vs {exact:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn nearby_values_do_not_cancel() {
        // Across a bin boundary with tiny and moderate value differences the f32 hi/lo
        // difference equals the f64 one.
        let tf = bands();
        let table = table_on_integers(&tf);
        let spacing = 1.0;
        for k in 1..50 {
            let s = 1000.0 + k as f64 * 0.37;
            for ds in [spacing * 0.01, spacing * 0.5, spacing * 1.5, spacing * 7.0] {
                let a = table.segment(s, s + ds, 1.0);
                let exact = integrate_segment(&tf, s, s + ds, 1.0, 1.0, 4000);
                assert!(
                    (a[3] - exact[3] as f64).abs() < 2e-3,
                    "{s} {ds}: {a:?} {exact:?}"
                );
            }
        }
    }

    /// The measured cause of issue 15's "pre-integration loses to classic sampling": on a TF
    /// with narrow bands the former 256² table (16 HU per cell on CT) misplaces and smears
    /// them, so its segments are off by more than the classic sample's own error; this table
    /// at the TF's 4096 entries is an order of magnitude closer to exact integration.
    #[test]
    fn narrow_bands_are_integrated_an_order_of_magnitude_better_than_the_256_table() {
        use crate::model::preintegration::PreintegrationTable;
        let tf = bands();
        let (lo, hi) = (-1024.0, 3071.0);
        let old = PreintegrationTable::build(&tf, lo, hi, 1.0, 1.0, 256);
        let new = SegmentIntegralTable::build(&tf, lo, hi, 1.0);
        let (mut err_old, mut err_new, mut n) = (0.0f64, 0.0f64, 0);
        // Segments of one voxel through the bands' neighbourhoods, value changes of 0-60 HU
        // (CT edges at one-voxel steps), both directions.
        for centre in [150.0, 400.0, 1000.0] {
            for k in 0..200 {
                let f = centre - 60.0 + 0.6 * k as f64;
                for dv in [0.0, 7.0, -13.0, 29.0, -41.0, 60.0] {
                    let exact = integrate_segment(&tf, f, f + dv, 1.0, 1.0, 4000);
                    let a = old.lookup(f, f + dv)[3];
                    let b = new.segment(f, f + dv, 1.0)[3];
                    err_old += (a - exact[3] as f64).powi(2);
                    err_new += (b - exact[3] as f64).powi(2);
                    n += 1;
                }
            }
        }
        let (rms_old, rms_new) = ((err_old / n as f64).sqrt(), (err_new / n as f64).sqrt());
        eprintln!(
            "segment opacity RMS error: 256² table {rms_old:.2e}, integral table {rms_new:.2e}"
        );
        assert!(rms_new * 10.0 < rms_old, "{rms_new:e} vs {rms_old:e}");
    }

    #[test]
    fn outside_the_range_extends_the_end_values() {
        let tf = TransferFunction::new("ramp", &[(0.0, 0.2), (100.0, 0.5)], &[(0.0, [1.0; 3])]);
        let table = SegmentIntegralTable::with_entries(&tf, 0.0, 100.0, 1.0, 256);
        let below = table.segment(-50.0, -10.0, 1.0);
        assert!((below[3] - 0.2).abs() < 1e-4, "{below:?}");
        let across = table.segment(-100.0, 200.0, 3.0);
        let exact = integrate_segment(&tf, -100.0, 200.0, 3.0, 1.0, 30_000);
        assert!(
            (across[3] - exact[3] as f64).abs() < 1e-3,
            "{across:?} {exact:?}"
        );
        assert_eq!(table.segment(10.0, 90.0, 0.0), [0.0; 4]);
    }
}
