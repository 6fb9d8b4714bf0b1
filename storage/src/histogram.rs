//! The level-0 histogram in physical units, for the transfer-function editor.

use serde::{Deserialize, Serialize};

/// Counts of every stored value (65536 bins), accumulated while slices stream past.
#[derive(Clone)]
pub struct StoredValueCounts {
    pub counts: Vec<u64>,
}

impl Default for StoredValueCounts {
    fn default() -> Self {
        StoredValueCounts {
            counts: vec![0; 1 << 16],
        }
    }
}

impl StoredValueCounts {
    pub fn add_slice(&mut self, values: &[u16]) {
        for &v in values {
            self.counts[v as usize] += 1;
        }
    }
    pub fn merge(mut self, other: &StoredValueCounts) -> Self {
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
        self
    }
    /// Lowest and highest stored value present, if any voxel was counted.
    pub fn stored_range(&self) -> Option<(u16, u16)> {
        let lo = self.counts.iter().position(|&c| c > 0)?;
        let hi = self.counts.iter().rposition(|&c| c > 0)?;
        Some((lo as u16, hi as u16))
    }
}

/// Histogram over [physical_min, physical_max] in `counts.len()` equal bins.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Histogram {
    pub physical_min: f64,
    pub physical_max: f64,
    pub counts: Vec<u64>,
}

pub const HISTOGRAM_BINS: usize = 1024;

impl Histogram {
    /// Rebins stored-value counts into physical units. Each stored value falls in exactly one
    /// bin, so the total equals the voxel count.
    pub fn from_stored(stored: &StoredValueCounts, slope: f64, intercept: f64) -> Histogram {
        let Some((lo, hi)) = stored.stored_range() else {
            return Histogram {
                physical_min: intercept,
                physical_max: intercept,
                counts: vec![0; HISTOGRAM_BINS],
            };
        };
        let p = |s: u16| slope * s as f64 + intercept;
        let (pmin, pmax) = if p(lo) <= p(hi) {
            (p(lo), p(hi))
        } else {
            (p(hi), p(lo))
        };
        let mut counts = vec![0u64; HISTOGRAM_BINS];
        let width = (pmax - pmin).max(f64::MIN_POSITIVE);
        for s in lo..=hi {
            let c = stored.counts[s as usize];
            if c == 0 {
                continue;
            }
            let bin = (((p(s) - pmin) / width) * HISTOGRAM_BINS as f64) as usize;
            counts[bin.min(HISTOGRAM_BINS - 1)] += c;
        }
        Histogram {
            physical_min: pmin,
            physical_max: pmax,
            counts,
        }
    }

    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rebinning_keeps_every_voxel() {
        let mut s = StoredValueCounts::default();
        s.add_slice(&[0, 24, 1024, 1024, 4000]);
        let h = Histogram::from_stored(&s, 1.0, -1024.0);
        assert_eq!(h.total(), 5);
        assert_eq!(h.physical_min, -1024.0);
        assert_eq!(h.physical_max, 4000.0 - 1024.0);
        assert_eq!(h.counts[0], 1);
        assert_eq!(*h.counts.last().unwrap(), 1);
    }
}
