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

    /// The bin physical value `p` falls in, as [`Histogram::from_stored`] bins it (`counts` is
    /// not empty).
    fn bin_of(&self, p: f64) -> usize {
        let width = (self.physical_max - self.physical_min).max(f64::MIN_POSITIVE);
        let bin = (((p - self.physical_min) / width) * self.counts.len() as f64) as usize;
        bin.min(self.counts.len() - 1)
    }

    /// Keeps the histogram true across an edit of level-0 voxels: each of `removed` (the
    /// physical values the edit overwrote) leaves its bin and each of `added` enters its own,
    /// so the total stays the voxel count. A value beyond the range widens it first: the
    /// counts so far move by each bin's centre into the wider bins (a voxel counted before
    /// lands within one old bin's width of its value; the added ones exactly).
    pub fn replace_values(&mut self, removed: &[f64], added: &[f64]) {
        if self.counts.is_empty() {
            return;
        }
        for &p in removed {
            let b = self.bin_of(p);
            self.counts[b] = self.counts[b].saturating_sub(1);
        }
        let lo = added.iter().copied().fold(self.physical_min, f64::min);
        let hi = added.iter().copied().fold(self.physical_max, f64::max);
        if lo < self.physical_min || hi > self.physical_max {
            let bins = self.counts.len();
            let old = std::mem::replace(&mut self.counts, vec![0; bins]);
            let (old_min, old_width) = (self.physical_min, self.physical_max - self.physical_min);
            self.physical_min = lo;
            self.physical_max = hi;
            let bins = bins as f64;
            for (i, &c) in old.iter().enumerate().filter(|(_, &c)| c > 0) {
                let centre = old_min + old_width * (i as f64 + 0.5) / bins;
                let b = self.bin_of(centre);
                self.counts[b] += c;
            }
        }
        for &p in added {
            let b = self.bin_of(p);
            self.counts[b] += 1;
        }
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

    /// An edit inside the range moves voxels between bins exactly as a rebuild would; one past
    /// the range widens it and keeps every voxel.
    #[test]
    fn replacing_values_matches_a_rebuild_and_widens_for_new_extremes() {
        let mut before = StoredValueCounts::default();
        before.add_slice(&[0, 10, 10, 500, 4000]);
        let mut h = Histogram::from_stored(&before, 1.0, -1024.0);
        h.replace_values(&[10.0 - 1024.0], &[2000.0 - 1024.0]);
        let mut after = StoredValueCounts::default();
        after.add_slice(&[0, 10, 2000, 500, 4000]);
        assert_eq!(h, Histogram::from_stored(&after, 1.0, -1024.0));
        h.replace_values(&[0.0 - 1024.0], &[9000.0 - 1024.0]);
        assert_eq!(h.total(), 5);
        assert_eq!(h.physical_max, 9000.0 - 1024.0);
        assert_eq!(h.physical_min, -1024.0);
        assert_eq!(
            *h.counts.last().unwrap(),
            1,
            "the new extreme in the last bin"
        );
    }
}
