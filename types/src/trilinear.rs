//! The corners and weights of trilinear interpolation in a voxel grid, one definition for every
//! f64 lookup that is not over a brick payload: the render crate's overlays, the viewer's
//! continuous overlays and the oblique slices both viewers resample (strata-slices), so all
//! agree at the grid's edges.

/// The eight corners and weights of trilinear interpolation at index `p` in a grid of `dims`
/// voxels (`p` clamped into the grid; corners past the last voxel repeat it). Corner bit `a`
/// set means the upper neighbour along axis `a`.
pub fn trilinear_corners(p: [f64; 3], dims: [u32; 3]) -> [([u32; 3], f64); 8] {
    let q = [0, 1, 2].map(|a| p[a].clamp(0.0, dims[a].max(1) as f64 - 1.0));
    let base = q.map(f64::floor);
    std::array::from_fn(|corner| {
        let mut weight = 1.0;
        let mut index = [0u32; 3];
        for a in 0..3 {
            let up = (corner >> a) & 1 == 1;
            let f = q[a] - base[a];
            weight *= if up { f } else { 1.0 - f };
            index[a] = (base[a] as u32 + up as u32).min(dims[a].max(1) - 1);
        }
        (index, weight)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Weights sum to one, a point on a voxel centre is that voxel alone, and a point past the
    /// last voxel is clamped to it.
    #[test]
    fn the_corners_weigh_the_neighbours_and_clamp_at_the_edges() {
        let corners = trilinear_corners([1.25, 2.5, 0.0], [4, 4, 4]);
        let total: f64 = corners.iter().map(|(_, w)| w).sum();
        assert!((total - 1.0).abs() < 1e-12);
        let at = |index: [u32; 3]| {
            corners
                .iter()
                .filter(|(i, _)| *i == index)
                .map(|(_, w)| w)
                .sum::<f64>()
        };
        assert!((at([1, 2, 0]) - 0.75 * 0.5).abs() < 1e-12);
        assert!((at([2, 3, 0]) - 0.25 * 0.5).abs() < 1e-12);
        let clamped = trilinear_corners([9.0, -3.0, 3.0], [4, 4, 4]);
        for (index, weight) in clamped {
            if weight > 0.0 {
                assert_eq!(index, [3, 0, 3]);
            }
        }
    }
}
