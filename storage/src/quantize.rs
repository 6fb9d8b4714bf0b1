//! From source samples to stored integers, and the physical mapping that undoes it.
//!
//! Policy, by source type:
//! - u8 → stored u8, i8 → u8 with +128; u16 → u16; i16 → u16 with +32768. Exact.
//! - u32, i32, f32, f64: a pre-pass finds the finite range. If every value is an integer and the
//!   range spans ≤ 65536 values, an offset keeps it exact; otherwise values are scaled linearly
//!   onto 0..=65535 and the header records the worst-case error (half a quantisation step, in
//!   physical units).
//! - Non-finite floats: NaN becomes the lowest stored value (reads as "nothing there", like air),
//!   +Inf the highest and −Inf the lowest; their count is recorded in the header so it is never
//!   silent.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

pub use crate::header::StoredScalar;
use crate::source::{decode_samples, RawVolume, SampleType};

/// stored = round((sample − offset) · scale), clamped; physical = slope · stored + intercept.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quantizer {
    pub stored: StoredScalar,
    pub offset: f64,
    pub scale: f64,
    /// Worst-case |physical error| introduced by quantisation (0 when exact).
    pub max_error_physical: f64,
    /// NaN and ±Inf samples met in the pre-pass.
    pub non_finite_samples: u64,
}

impl Quantizer {
    /// Chooses the mapping for `data`. Reads the whole source once only for wide/float types.
    pub fn plan(data: &RawVolume, source_slope: f64) -> Quantizer {
        let exact = |stored, offset| Quantizer {
            stored,
            offset,
            scale: 1.0,
            max_error_physical: 0.0,
            non_finite_samples: 0,
        };
        match data.sample_type {
            SampleType::U8 => exact(StoredScalar::U8, 0.0),
            SampleType::I8 => exact(StoredScalar::U8, -128.0),
            SampleType::U16 => exact(StoredScalar::U16, 0.0),
            SampleType::I16 => exact(StoredScalar::U16, -32768.0),
            _ => {
                let stats = (0..data.dims[2])
                    .into_par_iter()
                    .map(|k| {
                        let mut s = RangeStats::default();
                        decode_samples(
                            data.slice_bytes(k),
                            data.sample_type,
                            data.byte_order,
                            |v| s.add(v),
                        );
                        s
                    })
                    .reduce(RangeStats::default, RangeStats::merge);
                Self::for_range(stats, source_slope)
            }
        }
    }

    fn for_range(stats: RangeStats, source_slope: f64) -> Quantizer {
        let (lo, hi) = if stats.min <= stats.max {
            (stats.min, stats.max)
        } else {
            (0.0, 0.0)
        };
        let span = hi - lo;
        if stats.all_integer && span <= 65535.0 {
            return Quantizer {
                stored: StoredScalar::U16,
                offset: lo,
                scale: 1.0,
                max_error_physical: 0.0,
                non_finite_samples: stats.non_finite,
            };
        }
        // Halves, so that a range such as ±1e308 (f64 noise, damaged files) does not overflow to
        // an infinite span and a zero scale: the mapping written to the header stays finite.
        let half_span = hi / 2.0 - lo / 2.0;
        let scale = if half_span > 0.0 {
            (65535.0 / 2.0) / half_span
        } else {
            1.0
        };
        let step_physical = (half_span / (65535.0 / 2.0)) * source_slope.abs();
        Quantizer {
            stored: StoredScalar::U16,
            offset: lo,
            scale,
            max_error_physical: (0.5 * step_physical).min(f64::MAX),
            non_finite_samples: stats.non_finite,
        }
    }

    #[inline]
    pub fn to_stored(&self, sample: f64) -> u16 {
        let max = self.stored.max_value() as f64;
        if sample.is_nan() {
            return 0;
        }
        let v = ((sample - self.offset) * self.scale).round();
        v.clamp(0.0, max) as u16
    }

    /// Converts the source's (slope, intercept) into the stored values' mapping.
    pub fn physical_mapping(&self, source_slope: f64, source_intercept: f64) -> (f64, f64) {
        // physical = s·sample + b, sample = stored/scale + offset
        (
            source_slope / self.scale,
            source_slope * self.offset + source_intercept,
        )
    }

    /// Fast paths for the exact integer mappings (most scans): no float round trip per sample.
    /// Returns false when the general path must run.
    fn convert_integers_exactly(&self, data: &RawVolume, src: &[u8], dst: &mut [u16]) -> bool {
        use crate::source::ByteOrder::{Big, Little};
        if self.scale != 1.0 {
            return false;
        }
        let offset = self.offset;
        match (data.sample_type, data.byte_order) {
            (SampleType::U8, _) if offset == 0.0 => {
                dst.iter_mut().zip(src).for_each(|(d, &s)| *d = s as u16)
            }
            (SampleType::I8, _) if offset == -128.0 => dst
                .iter_mut()
                .zip(src)
                .for_each(|(d, &s)| *d = (s as i8 as i16 + 128) as u16),
            (SampleType::U16, order) if offset == 0.0 => {
                for (d, c) in dst.iter_mut().zip(src.chunks_exact(2)) {
                    let b = [c[0], c[1]];
                    *d = if order == Little {
                        u16::from_le_bytes(b)
                    } else {
                        u16::from_be_bytes(b)
                    };
                }
            }
            (SampleType::I16, order) if offset == -32768.0 => {
                for (d, c) in dst.iter_mut().zip(src.chunks_exact(2)) {
                    let b = [c[0], c[1]];
                    let v = if order == Big {
                        i16::from_be_bytes(b)
                    } else {
                        i16::from_le_bytes(b)
                    };
                    // Flipping the sign bit adds 32768 in two's complement.
                    *d = (v as u16) ^ 0x8000;
                }
            }
            _ => return false,
        }
        true
    }

    /// Converts slice `k` of `data` into stored values.
    pub fn convert_slice(&self, data: &RawVolume, k: u64, out: &mut [u16]) {
        let bytes = data.slice_bytes(k);
        let width = data.sample_type.size_bytes();
        let row_bytes = data.dims[0] as usize * width;
        // Rows in parallel: the conversion is the only per-voxel work before compression.
        out.par_chunks_mut(data.dims[0] as usize)
            .zip(bytes.par_chunks(row_bytes))
            .for_each(|(dst, src)| {
                if self.convert_integers_exactly(data, src, dst) {
                    return;
                }
                let mut i = 0;
                decode_samples(src, data.sample_type, data.byte_order, |v| {
                    dst[i] = self.to_stored(v);
                    i += 1;
                });
            });
    }
}

#[derive(Clone, Copy, Debug)]
struct RangeStats {
    min: f64,
    max: f64,
    all_integer: bool,
    non_finite: u64,
}

impl Default for RangeStats {
    fn default() -> Self {
        RangeStats {
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            all_integer: true,
            non_finite: 0,
        }
    }
}

impl RangeStats {
    #[inline]
    fn add(&mut self, v: f64) {
        if !v.is_finite() {
            self.non_finite += 1;
            return;
        }
        self.min = self.min.min(v);
        self.max = self.max.max(v);
        self.all_integer &= v.fract() == 0.0;
    }
    fn merge(a: Self, b: Self) -> Self {
        RangeStats {
            min: a.min.min(b.min),
            max: a.max.max(b.max),
            all_integer: a.all_integer && b.all_integer,
            non_finite: a.non_finite + b.non_finite,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn float_range_is_scaled_with_stated_error() {
        let mut s = RangeStats::default();
        for v in [-1.5, 0.25, 1000.75, f64::NAN, f64::INFINITY] {
            s.add(v);
        }
        let q = Quantizer::for_range(s, 1.0);
        assert_eq!(q.non_finite_samples, 2);
        assert_eq!(q.to_stored(-1.5), 0);
        assert_eq!(q.to_stored(1000.75), 65535);
        assert_eq!(q.to_stored(f64::NAN), 0);
        assert_eq!(q.to_stored(f64::INFINITY), 65535);
        assert_eq!(q.to_stored(f64::NEG_INFINITY), 0);
        let (slope, icpt) = q.physical_mapping(1.0, 0.0);
        for v in [-1.5, 0.25, 500.0, 1000.75] {
            let back = slope * q.to_stored(v) as f64 + icpt;
            assert!(
                (back - v).abs() <= q.max_error_physical + 1e-9,
                "{v} -> {back}"
            );
        }
    }

    #[test]
    fn integer_range_stays_exact() {
        let mut s = RangeStats::default();
        for v in [-70000.0, -20000.0] {
            s.add(v);
        }
        let q = Quantizer::for_range(s, 2.0);
        assert_eq!(q.max_error_physical, 0.0);
        let (slope, icpt) = q.physical_mapping(2.0, 5.0);
        let back = slope * q.to_stored(-33333.0) as f64 + icpt;
        assert_eq!(back, -33333.0 * 2.0 + 5.0);
    }

    #[test]
    fn the_widest_f64_range_keeps_a_finite_mapping() {
        // ±1e308 (random bits, damaged files): hi − lo overflows to infinity.
        let mut s = RangeStats::default();
        for v in [-1e308, 0.0, 1.7e308] {
            s.add(v);
        }
        let q = Quantizer::for_range(s, 1.0);
        let (slope, icpt) = q.physical_mapping(1.0, 0.0);
        assert!(q.scale.is_finite() && q.scale > 0.0, "{q:?}");
        assert!(slope.is_finite() && icpt.is_finite() && q.max_error_physical.is_finite());
        assert_eq!(q.to_stored(-1e308), 0);
        assert_eq!(q.to_stored(1.7e308), 65535);
        let back = slope * q.to_stored(0.0) as f64 + icpt;
        assert!(back.abs() <= q.max_error_physical * 1.000001, "{back}");
    }
}
