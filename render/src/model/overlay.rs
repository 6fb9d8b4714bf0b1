//! A second volume drawn inside the 3D view: a label map (segmentation) or a continuous overlay
//! (PET, a statistic map), already resampled by the caller onto a dense grid that spans the
//! primary's index box ([`OverlayVolume`]), with a colour table ([`OverlayLut`]). This module
//! is the CPU side: the sampling and the blend rule, written once in f64 and used by the
//! reference (reference.rs); `shaders/overlay.wgsl` is its twin, gpu_overlay.rs uploads it.
//!
//! # Sampling
//! Grid voxel `i` covers the primary index interval `[i·s − ½, (i+1)·s − ½)` per axis, where
//! `s = primary dims / grid dims` (so a grid of the primary's own dims is the primary's voxels,
//! and a grid of half the dims is its level 1). Labels are categories: the voxel holding the
//! point is taken (nearest, never interpolated or filtered). Continuous values are trilinear
//! between grid voxel centres, clamped at the edges, like the 2D overlay.
//!
//! # Blend rule (DVR)
//! At every sample where the overlay is drawn (a label that is shown, a value at or above the
//! threshold) with colour `c_o` and opacity `a_o` (the user's overlay opacity), the tissue's
//! straight colour `c` and per-voxel opacity `a` from the transfer function become
//!
//! ```text
//! c' = c + (c_o − c)·a_o            (mixed toward the overlay, as the 2D "over" on slices)
//! a' = max(a, a_o·OVERLAY_VOXEL_OPACITY)
//! ```
//!
//! and the sample then goes through the usual opacity correction, shading and compositing.
//! The colour mix is what the slice views show; the opacity floor makes a label inside tissue
//! the TF renders transparent a visible body (a segmented tumour in fat), while a label inside
//! opaque bone does not make the bone more transparent. A floor below one keeps depth: at
//! `a_o = 1` each finest voxel absorbs half of what reaches it, so the label's surface reads as
//! a surface and a thin label as thinner than a thick one. MIP takes the same rule with the
//! first shown overlay sample along the ray (the overlay is projected too, nearest the viewer;
//! the maximum's own position inside a homogeneous organ is decided by noise, so colouring by
//! the label there would speckle; no opacity correction: one sample); the isosurface mixes the
//! surface colour toward the overlay's at the hit (`c' = c + (c_o − c)·a_o`) before shading.

use glam::DVec3;

use crate::error::RenderError;

/// Per finest voxel, the opacity a fully opaque overlay (opacity 1) gives a sample at least.
pub const OVERLAY_VOXEL_OPACITY: f64 = 0.5;

/// A continuous overlay's value where the grid lies outside the overlay's own volume: below
/// every threshold (so nothing is drawn), finite (GPUs may assume no NaN), and small enough in
/// magnitude that a trilinear blend of eight of them stays finite in f32.
pub const OVERLAY_OUTSIDE: f32 = -1.0e30;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum OverlayKind {
    /// Values are LUT indices (whole numbers; 0 = background, never drawn).
    Labels,
    /// Values are physical; the LUT spans `lo..hi` and nothing below `threshold` is drawn.
    Continuous,
}

/// The overlay resampled onto a dense grid over the primary's index box (x fastest).
#[derive(Clone, Debug, PartialEq)]
pub struct OverlayVolume {
    pub dims: [u32; 3],
    pub kind: OverlayKind,
    pub values: Vec<f32>,
}

/// The colour table: straight RGB and the opacity the overlay has there (0: not drawn). Labels
/// index it by value; a continuous overlay maps `lo..=hi` onto its entries (nearest entry).
#[derive(Clone, Debug, PartialEq)]
pub struct OverlayLut {
    pub entries: Vec<[f32; 4]>,
    pub lo: f64,
    pub hi: f64,
    pub threshold: f64,
}

impl OverlayVolume {
    pub fn new(dims: [u32; 3], kind: OverlayKind, values: Vec<f32>) -> Result<Self, RenderError> {
        let expected: u64 = dims.iter().map(|&d| d as u64).product();
        if dims.contains(&0) || values.len() as u64 != expected {
            return Err(RenderError::InvalidVolume(format!(
                "overlay grid {dims:?} needs {expected} values, got {}",
                values.len()
            )));
        }
        Ok(OverlayVolume { dims, kind, values })
    }

    fn at(&self, i: [u32; 3]) -> f64 {
        let [x, y, z] = i.map(|v| v as usize);
        let [nx, ny, _] = self.dims.map(|v| v as usize);
        self.values[x + nx * (y + ny * z)] as f64
    }

    /// The grid's continuous coordinate (voxel `i` spans `[i, i+1)`) of primary index `p`.
    pub fn grid_coordinate(&self, primary_dims: [u32; 3], p: DVec3) -> DVec3 {
        let grid = DVec3::from(self.dims.map(|d| d as f64));
        let primary = DVec3::from(primary_dims.map(|d| d as f64));
        (p + 0.5) / primary * grid
    }

    /// The overlay's value at primary index `p`: the holding voxel's for labels, trilinear for
    /// continuous overlays (see the module doc).
    pub fn sample(&self, primary_dims: [u32; 3], p: DVec3) -> f64 {
        let g = self.grid_coordinate(primary_dims, p);
        let last = |a: usize| self.dims[a] as f64 - 1.0;
        match self.kind {
            OverlayKind::Labels => {
                let i = [0, 1, 2].map(|a| g[a].floor().clamp(0.0, last(a)) as u32);
                self.at(i)
            }
            OverlayKind::Continuous => {
                let q = [0, 1, 2].map(|a| g[a] - 0.5);
                strata_types::trilinear_corners(q, self.dims)
                    .into_iter()
                    .map(|(index, weight)| weight * self.at(index))
                    .sum()
            }
        }
    }

    /// The primary-index box `[lo, hi]` outside which the overlay draws nothing whatever its
    /// LUT: the voxels that hold a label (or lie inside the overlay's volume), grown by one grid
    /// voxel for the trilinear reach. None when the overlay holds nothing. DVR rays may skip
    /// empty pages only outside it (a label in TF-transparent tissue must still be sampled).
    pub fn occupied_box(&self, primary_dims: [u32; 3]) -> Option<(DVec3, DVec3)> {
        let mut lo = [u32::MAX; 3];
        let mut hi = [0u32; 3];
        let [nx, ny, nz] = self.dims;
        let mut any = false;
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    let v = self.at([x, y, z]);
                    let holds = match self.kind {
                        OverlayKind::Labels => v != 0.0,
                        OverlayKind::Continuous => v > OVERLAY_OUTSIDE as f64,
                    };
                    if holds {
                        any = true;
                        for (a, c) in [x, y, z].into_iter().enumerate() {
                            lo[a] = lo[a].min(c);
                            hi[a] = hi[a].max(c);
                        }
                    }
                }
            }
        }
        any.then(|| {
            let s = |a: usize| primary_dims[a] as f64 / self.dims[a] as f64;
            let lo = DVec3::from([0, 1, 2].map(|a| (lo[a] as f64 - 1.0) * s(a) - 0.5));
            let hi = DVec3::from([0, 1, 2].map(|a| (hi[a] as f64 + 2.0) * s(a) - 0.5));
            (lo, hi)
        })
    }
}

impl OverlayLut {
    pub fn new(
        entries: Vec<[f32; 4]>,
        lo: f64,
        hi: f64,
        threshold: f64,
    ) -> Result<Self, RenderError> {
        if entries.is_empty() {
            return Err(RenderError::InvalidSettings(
                "an overlay colour table needs at least one entry".into(),
            ));
        }
        Ok(OverlayLut {
            entries,
            lo,
            hi,
            threshold,
        })
    }

    /// The entry a continuous value takes: its place in `lo..=hi` (the top one when the range
    /// is empty), rounded to the nearest entry.
    pub fn continuous_index(&self, value: f64) -> usize {
        let n = self.entries.len();
        let t = if self.hi > self.lo {
            ((value - self.lo) / (self.hi - self.lo)).clamp(0.0, 1.0)
        } else {
            1.0
        };
        ((t * (n - 1) as f64 + 0.5).floor() as usize).min(n - 1)
    }

    /// Straight RGB and opacity the overlay draws for `value` (opacity 0: nothing).
    pub fn colour(&self, kind: OverlayKind, value: f64) -> [f64; 4] {
        let entry = match kind {
            OverlayKind::Labels => {
                let i = (value + 0.5).floor();
                if i < 1.0 || i >= self.entries.len() as f64 {
                    return [0.0; 4];
                }
                self.entries[i as usize]
            }
            OverlayKind::Continuous => {
                if value < self.threshold {
                    return [0.0; 4];
                }
                self.entries[self.continuous_index(value)]
            }
        };
        entry.map(|c| c as f64)
    }
}

/// The blend rule of the module doc: tissue colour `rgb` and per-voxel opacity `alpha`, with
/// the overlay's straight colour and opacity `overlay`.
pub fn blend(rgb: [f64; 3], alpha: f64, overlay: [f64; 4]) -> ([f64; 3], f64) {
    let a_o = overlay[3];
    if a_o <= 0.0 {
        return (rgb, alpha);
    }
    let mixed = [0, 1, 2].map(|i| rgb[i] + (overlay[i] - rgb[i]) * a_o);
    (mixed, alpha.max(a_o * OVERLAY_VOXEL_OPACITY))
}

/// What the reference needs: the grid, its colours, and the primary's dims it spans.
#[derive(Clone, Copy, Debug)]
pub struct OverlayScene<'a> {
    pub volume: &'a OverlayVolume,
    pub lut: &'a OverlayLut,
    pub primary_dims: [u32; 3],
}

impl OverlayScene<'_> {
    /// The overlay's straight colour and opacity at primary index `p`.
    pub fn colour_at(&self, p: DVec3) -> [f64; 4] {
        let v = self.volume.sample(self.primary_dims, p);
        self.lut.colour(self.volume.kind, v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_are_taken_from_the_holding_voxel_and_values_interpolate() {
        // A 2×1×1 label grid over a primary 4 voxels wide: voxels 0, 1 → label 1; 2, 3 → 2.
        let labels = OverlayVolume::new([2, 1, 1], OverlayKind::Labels, vec![1.0, 2.0]).unwrap();
        let dims = [4, 1, 1];
        for (x, expected) in [(0.0, 1.0), (1.0, 1.0), (1.49, 1.0), (1.51, 2.0), (3.0, 2.0)] {
            assert_eq!(
                labels.sample(dims, DVec3::new(x, 0.0, 0.0)),
                expected,
                "{x}"
            );
        }
        let values =
            OverlayVolume::new([2, 1, 1], OverlayKind::Continuous, vec![10.0, 20.0]).unwrap();
        // Grid centres sit at primary 0.5 and 2.5; halfway between is 15; clamped outside.
        assert_eq!(values.sample(dims, DVec3::new(1.5, 0.0, 0.0)), 15.0);
        assert_eq!(values.sample(dims, DVec3::new(0.0, 0.0, 0.0)), 10.0);
        assert_eq!(values.sample(dims, DVec3::new(3.0, 0.0, 0.0)), 20.0);
        let (lo, hi) = labels.occupied_box(dims).unwrap();
        assert!(lo.x <= -0.5 && hi.x >= 3.5);
    }

    #[test]
    fn the_lut_hides_background_hidden_labels_and_values_below_the_threshold() {
        let lut = OverlayLut::new(
            vec![[0.0; 4], [1.0, 0.0, 0.0, 0.8], [0.0, 1.0, 0.0, 0.0]],
            0.0,
            10.0,
            5.0,
        )
        .unwrap();
        assert_eq!(lut.colour(OverlayKind::Labels, 0.0)[3], 0.0);
        assert_eq!(
            lut.colour(OverlayKind::Labels, 1.0),
            [1.0, 0.0, 0.0, 0.8f32 as f64]
        );
        assert_eq!(lut.colour(OverlayKind::Labels, 2.0)[3], 0.0, "hidden");
        assert_eq!(lut.colour(OverlayKind::Labels, 7.0)[3], 0.0, "unknown");
        assert_eq!(lut.colour(OverlayKind::Continuous, 4.9)[3], 0.0);
        assert_eq!(lut.colour(OverlayKind::Continuous, 5.0)[3], 0.8f32 as f64);
        assert_eq!(lut.continuous_index(10.0), 2);
        let (rgb, a) = blend([0.0, 0.0, 1.0], 0.1, [1.0, 0.0, 0.0, 0.5]);
        assert_eq!((rgb, a), ([0.5, 0.0, 0.5], 0.25));
        assert_eq!(blend([0.2; 3], 0.9, [1.0, 0.0, 0.0, 0.0]), ([0.2; 3], 0.9));
    }
}
