//! Pre-integrated transfer functions (Engel, Kraus & Ertl 2001; used by Kraus et al.,
//! adaptive-sampling-3d §3.3): a 2D table of the colour and opacity of a ray segment of
//! length D whose scalar runs linearly from `s_front` to `s_back`. With it, a segment between
//! two samples integrates everything the transfer function does in between, so a narrow or
//! step-shaped TF no longer needs tiny steps to be hit.
//!
//! Optics match the classic path exactly: the TF's opacity α(s) is per finest voxel (length
//! `unit_mm`), i.e. extinction κ(s) = −ln(1 − α(s)) / unit, and colour is emitted in proportion
//! to absorption, so on the diagonal (`s_front = s_back`) an entry is `(c·α', α')` with
//! α' = 1 − (1 − α)^(D/unit): the opacity-corrected classic sample.
//!
//! The table holds premultiplied colour and opacity for the base step D. Coarse octree levels
//! take steps of 2^L·D; the raycaster rescales an entry with the same power law
//! (α'' = 1 − (1 − α')^(Δ/D), colour scaled by α''/α'), which is exact on the diagonal and the
//! usual approximation off it.

use crate::model::transfer_function::TransferFunction;

/// Table edge: 256² entries over the TF's value range. Finer than the 8-bit data it is mostly
/// used with, and 1 MiB as RGBA f32; features narrower than range/255 are
/// integrated correctly but placed to within one table cell.
pub const PREINTEGRATION_SIZE: u32 = 256;

/// Sub-steps along one segment: one per TF-table entry the segment's value range crosses, so
/// every TF feature is integrated, but at most this many (the entries far off the diagonal,
/// which only very steep gradients reach).
const MAX_SUBSTEPS: usize = 512;

/// One entry: premultiplied RGB and opacity of a segment.
pub type SegmentRgba = [f32; 4];

#[derive(Clone, Debug, PartialEq)]
pub struct PreintegrationTable {
    /// Value range the table spans (the TF texture's range).
    pub lo: f64,
    pub hi: f64,
    /// Segment length the table was integrated for, mm.
    pub segment_mm: f64,
    /// Length the TF's opacity is defined for (finest voxel), mm.
    pub unit_mm: f64,
    pub size: u32,
    /// `rgba[back * size + front]`.
    pub rgba: Vec<SegmentRgba>,
}

impl PreintegrationTable {
    /// Integrates every (front, back) pair on all cores. Non-finite or non-positive lengths
    /// and an empty range are clamped so the table is always finite.
    pub fn build(
        tf: &TransferFunction,
        lo: f64,
        hi: f64,
        segment_mm: f64,
        unit_mm: f64,
        size: u32,
    ) -> Self {
        use rayon::prelude::*;
        let size = size.max(2);
        let hi = if hi > lo { hi } else { lo + 1.0 };
        let segment_mm = if segment_mm.is_finite() {
            segment_mm.max(0.0)
        } else {
            0.0
        };
        let unit_mm = if unit_mm.is_finite() && unit_mm > 0.0 {
            unit_mm
        } else {
            1.0
        };
        let n = size as usize;
        let value_at = |i: usize| lo + (hi - lo) * i as f64 / (n - 1) as f64;
        // TF table entries per table cell: how finely a segment must be sub-sampled.
        let tf_entries_per_cell =
            (crate::model::transfer_function::TABLE_ENTRIES as f64 / n as f64).max(1.0);
        let rgba: Vec<SegmentRgba> = (0..n * n)
            .into_par_iter()
            .map(|k| {
                let (front, back) = (k % n, k / n);
                let cells = front.abs_diff(back) as f64;
                let substeps =
                    ((cells * tf_entries_per_cell).ceil() as usize).clamp(1, MAX_SUBSTEPS);
                integrate_segment(
                    tf,
                    value_at(front),
                    value_at(back),
                    segment_mm,
                    unit_mm,
                    substeps,
                )
            })
            .collect();
        PreintegrationTable {
            lo,
            hi,
            segment_mm,
            unit_mm,
            size,
            rgba,
        }
    }

    /// Bilinear lookup, as the shader does it (for tests and the CPU side).
    pub fn lookup(&self, s_front: f64, s_back: f64) -> [f64; 4] {
        let n = self.size as usize;
        let coord = |s: f64| {
            ((s - self.lo) / (self.hi - self.lo) * (n - 1) as f64).clamp(0.0, (n - 1) as f64)
        };
        let (x, y) = (coord(s_front), coord(s_back));
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(n - 1), (y0 + 1).min(n - 1));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let at = |i: usize, j: usize| self.rgba[j * n + i].map(|c| c as f64);
        let mix = |a: [f64; 4], b: [f64; 4], t: f64| [0, 1, 2, 3].map(|c| a[c] + (b[c] - a[c]) * t);
        mix(
            mix(at(x0, y0), at(x1, y0), fx),
            mix(at(x0, y1), at(x1, y1), fx),
            fy,
        )
    }
}

/// Colour and opacity of a segment of `length_mm` whose value runs linearly from `s_front` to
/// `s_back`, by front-to-back compositing of `substeps` midpoint sub-segments in f64.
pub fn integrate_segment(
    tf: &TransferFunction,
    s_front: f64,
    s_back: f64,
    length_mm: f64,
    unit_mm: f64,
    substeps: usize,
) -> SegmentRgba {
    let substeps = substeps.max(1);
    let exponent = length_mm / unit_mm / substeps as f64;
    let mut color = [0.0f64; 3];
    let mut alpha = 0.0f64;
    for m in 0..substeps {
        let s = s_front + (s_back - s_front) * (m as f64 + 0.5) / substeps as f64;
        // Same clamp as the raycaster: opacity 1 would make the extinction infinite.
        let a_tf = tf.opacity_at(s).clamp(0.0, 0.999_999);
        if a_tf <= 0.0 {
            continue;
        }
        let a = 1.0 - (1.0 - a_tf).powf(exponent);
        let w = (1.0 - alpha) * a;
        let c = tf.color_at(s);
        for (acc, c) in color.iter_mut().zip(c) {
            *acc += w * c;
        }
        alpha += w;
    }
    [
        color[0] as f32,
        color[1] as f32,
        color[2] as f32,
        alpha as f32,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp() -> TransferFunction {
        TransferFunction::new(
            "ramp",
            &[(0.0, 0.0), (100.0, 0.0), (200.0, 0.5), (255.0, 0.9)],
            &[(0.0, [1.0, 0.0, 0.0]), (255.0, [0.0, 0.5, 1.0])],
        )
    }

    #[test]
    fn diagonal_equals_the_opacity_corrected_classic_sample() {
        let tf = ramp();
        let table = PreintegrationTable::build(&tf, 0.0, 255.0, 0.5, 1.0, 256);
        for i in [0usize, 90, 150, 200, 255] {
            let s = 255.0 * i as f64 / 255.0;
            let a = tf.opacity_at(s).min(0.999_999);
            let expected_alpha = 1.0 - (1.0 - a).powf(0.5);
            let got = table.rgba[i * 256 + i];
            assert!(
                (got[3] as f64 - expected_alpha).abs() < 1e-6,
                "s {s}: {got:?}"
            );
            let c = tf.color_at(s);
            for k in 0..3 {
                assert!((got[k] as f64 - c[k] * expected_alpha).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn opacity_is_symmetric_and_colour_is_not() {
        let table = PreintegrationTable::build(&ramp(), 0.0, 255.0, 2.0, 1.0, 64);
        let n = 64;
        let (f, b) = (20, 60);
        let forward = table.rgba[b * n + f];
        let backward = table.rgba[f * n + b];
        // Total absorption does not depend on the direction; what is seen first does.
        assert!(
            (forward[3] - backward[3]).abs() < 1e-5,
            "{forward:?} {backward:?}"
        );
        assert!(
            (forward[0] - backward[0]).abs() > 1e-3,
            "colour should depend on order"
        );
    }

    #[test]
    fn zero_length_segments_are_transparent_and_short_ones_vanish_continuously() {
        let tf = ramp();
        let table = PreintegrationTable::build(&tf, 0.0, 255.0, 0.0, 1.0, 32);
        assert!(table.rgba.iter().flatten().all(|&c| c == 0.0));
        let mut previous = f32::INFINITY;
        for d in [1.0, 0.1, 1e-3, 1e-6, 1e-9] {
            let seg = integrate_segment(&tf, 150.0, 250.0, d, 1.0, 64);
            assert!(seg.iter().all(|c| c.is_finite() && *c >= 0.0), "{seg:?}");
            assert!(seg[3] < previous, "opacity must shrink with the length");
            previous = seg[3];
        }
        assert!(previous < 1e-8);
    }

    #[test]
    fn a_step_between_samples_is_integrated() {
        // Opacity only in a band [120, 122]: a classic sample at either end sees nothing,
        // the segment from 100 to 140 crosses the band and must absorb.
        let band = TransferFunction::new(
            "band",
            &[
                (0.0, 0.0),
                (119.9, 0.0),
                (120.0, 0.9),
                (122.0, 0.9),
                (122.1, 0.0),
                (255.0, 0.0),
            ],
            &[(0.0, [1.0, 1.0, 1.0]), (255.0, [1.0, 1.0, 1.0])],
        );
        let table = PreintegrationTable::build(&band, 0.0, 255.0, 1.0, 1.0, 256);
        assert_eq!(band.opacity_at(100.0), 0.0);
        assert_eq!(band.opacity_at(140.0), 0.0);
        let seg = table.lookup(100.0, 140.0);
        // The band is 2/40 of the segment: α ≈ 1 − (1 − 0.9)^(1/20) ≈ 0.109.
        assert!((seg[3] - 0.109).abs() < 0.02, "{seg:?}");
        // Sub-segments at every TF entry keep a finer step from changing the answer.
        let fine = integrate_segment(&band, 100.0, 140.0, 1.0, 1.0, 4096);
        assert!(
            (seg[3] - fine[3] as f64).abs() < 0.01,
            "{seg:?} vs {fine:?}"
        );
    }

    #[test]
    fn degenerate_inputs_stay_finite() {
        let tf = ramp();
        for (lo, hi, seg, unit) in [
            (10.0, 10.0, 1.0, 1.0),
            (0.0, 255.0, f64::NAN, 1.0),
            (0.0, 255.0, 1.0, 0.0),
            (0.0, 255.0, 1e6, 1.0),
        ] {
            let t = PreintegrationTable::build(&tf, lo, hi, seg, unit, 8);
            assert!(t
                .rgba
                .iter()
                .flatten()
                .all(|c| c.is_finite() && (0.0..=1.0).contains(c)));
        }
    }
}
