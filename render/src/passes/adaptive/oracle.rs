//! The oracle of the adaptive pass: a sampling distance (in slices, 1..2^l_max) per page entry
//! of the cut, so it works with any cut the page table describes. From the transfer function
//! over the node's value range (PageTable::sampled_ranges, which covers the coarser field a
//! transition band blends in):
//! - transparent over the whole range (empty) → 2^l_max;
//! - otherwise the opacity variation Δα over the range, spread over the node's extent in
//!   slices, estimates |∇α| per slice; the distance is the largest power of two with
//!   d·|∇α| ≤ ε (ε the user's knob: larger ε, fewer samples), no finer than the node's level
//!   allows (a level-L node holds no detail below 2^L voxels: 2^L slices, the raycaster's own
//!   step rule);
//! - dilated over the 26 neighbouring entries (the paper's "distance to the nearest voxel with
//!   |∇α| > ε"): a ray about to enter a detailed node has already slowed down, so a thin
//!   feature at a node face is not stepped over. One entry (32 voxels) covers the largest
//!   skip (2^l_max slices ≤ 8 quality-voxels).

use crate::model::layout::BRICK_CORE;
use crate::model::page_table::PageTable;
use crate::model::transfer_function::TransferFunction;

/// Where the pass's sampling distances come from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum OracleKind {
    /// The per-entry table of [`oracle_distances`].
    PerNode,
    /// The per-slot, per-2³-block table of [`super::block_oracle::block_oracle`] (the render
    /// mode): the paper's distance to the nearest voxel with |∇α| > ε.
    PerBlock,
    /// The same distance everywhere: 1 is the worst-case overhead of the paper's Tables 2/3
    /// ("min."), 2^l_max the coarsest image.
    Constant(f32),
    /// Tests: an integer 1..=2^(l_max+1) hashed from (level, pixel, slice), identical on the
    /// CPU and the GPU.
    Hash(u32),
}

/// What the oracle's distance bounds the change of (issue 37 item 4).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum OracleTarget {
    /// The opacity α only: unlit DVR, where a sample's colour is the TF's.
    #[default]
    Opacity,
    /// The lit colour: also the TF's premultiplied colour c·α, the shaded term where the
    /// field is steep and, with `shadowed`, the light's attenuation across the node or block
    /// (see [`tf_variation`]). Never coarser than [`OracleTarget::Opacity`].
    LitColour {
        /// Shadow rays or occlusion attenuate the light inside the data.
        shadowed: bool,
    },
}

impl OracleTarget {
    /// [`OracleTarget::LitColour`] where the settings light DVR samples (shading on: the
    /// headlight or the key light with its shadows, occlusion and scattering), else opacity.
    pub fn for_settings(settings: &crate::model::settings::RenderSettings) -> Self {
        if settings.mode == crate::model::settings::RenderMode::Dvr && settings.shading.is_some() {
            OracleTarget::LitColour {
                shadowed: settings.effective_shadows()
                    || settings.effective_light_cache()
                    || settings.effective_occlusion().is_some(),
            }
        } else {
            OracleTarget::Opacity
        }
    }
}

/// Smallest and largest colour channel values of the piecewise-linear TF over [lo, hi].
fn colour_extent(tf: &TransferFunction, lo: f64, hi: f64) -> ([f64; 3], [f64; 3]) {
    let (a, b) = (tf.color_at(lo), tf.color_at(hi));
    let mut min = [0, 1, 2].map(|k| a[k].min(b[k]));
    let mut max = [0, 1, 2].map(|k| a[k].max(b[k]));
    for s in &tf.color {
        if s.value > lo && s.value < hi {
            for k in 0..3 {
                min[k] = min[k].min(s.rgb[k]);
                max[k] = max[k].max(s.rgb[k]);
            }
        }
    }
    (min, max)
}

/// Width of the values the TF makes visible (first to last stop with opacity > 0, at least
/// the whole stop list's width where a ramp starts at 0): the scale of the TF's features.
fn visible_width(tf: &TransferFunction) -> f64 {
    let visible: Vec<f64> = tf
        .opacity
        .iter()
        .enumerate()
        .filter(|(i, s)| {
            // A stop counts if it or a neighbour is opaque (a ramp's foot belongs to it).
            s.opacity > 0.0
                || (*i > 0 && tf.opacity[i - 1].opacity > 0.0)
                || tf.opacity.get(i + 1).is_some_and(|n| n.opacity > 0.0)
        })
        .map(|(_, s)| s.value)
        .collect();
    match (visible.first(), visible.last()) {
        (Some(a), Some(b)) if b > a => b - a,
        _ => f64::INFINITY,
    }
}

/// The change over a node or block whose values span [lo, hi] and whose edge is
/// `extent_voxels` finest voxels that the oracle spreads over its extent (None: transparent
/// over the whole range, the coarsest distance).
/// - Opacity: Δα = α_max − α_min (the oracle's rule before lighting; bit-identical).
/// - Lit colour: the largest of Δα; the premultiplied colour's change per channel, bounded by
///   c_max·α_max − c_min·α_min (c, α ≥ 0); and the shaded term's, (c·α)_max·w with
///   w = min(1, (hi − lo) / the TF's visible width). The lit colour is c·α·S, S the shading
///   (N·L, specular, the shadow's and occlusion's transmittance, the phase), which varies
///   with the gradient's direction; a local range cannot bound that, so the test is the
///   field's steepness against the TF's feature scale: a block that crosses a surface
///   (w → 1) is sampled as if its lit colour went from 0 to (c·α)_max, one inside a
///   homogeneous tissue (w → 0, the normal is noise there and the hybrid scattering weights
///   the phase, not the gradient) as its TF dictates. With shadows (or occlusion) the light
///   reaching a sample also falls inside homogeneous data, by its own extinction: across the
///   extent at most 1 − (1 − α_max)^extent (the TF's opacity is per finest voxel), so the
///   lit colour changes by up to (c·α)_max times that. Shadow edges cast by data outside the
///   block are not bounded by anything local: the test image's PSNR is their measure.
///   ε stays the one knob.
pub(crate) fn tf_variation(
    tf: &TransferFunction,
    lo: f64,
    hi: f64,
    target: OracleTarget,
    extent_voxels: f64,
) -> Option<f64> {
    let (a_min, a_max) = opacity_extent(tf, lo, hi);
    if a_max <= 0.0 {
        return None;
    }
    let opacity = a_max - a_min;
    match target {
        OracleTarget::Opacity => Some(opacity),
        OracleTarget::LitColour { shadowed } => {
            let (c_min, c_max) = colour_extent(tf, lo, hi);
            let mut premultiplied = 0.0f64;
            let mut brightest = 0.0f64;
            for k in 0..3 {
                premultiplied = premultiplied.max(c_max[k] * a_max - c_min[k] * a_min);
                brightest = brightest.max(c_max[k] * a_max);
            }
            let steepness = ((hi - lo) / visible_width(tf)).clamp(0.0, 1.0);
            let attenuation = if shadowed {
                1.0 - (1.0 - a_max.min(1.0)).powf(extent_voxels.max(0.0))
            } else {
                0.0
            };
            Some(
                opacity
                    .max(premultiplied)
                    .max(brightest * steepness.max(attenuation)),
            )
        }
    }
}

/// Smallest and largest opacity of the piecewise-linear TF over [lo, hi].
pub(crate) fn opacity_extent(tf: &TransferFunction, lo: f64, hi: f64) -> (f64, f64) {
    let (a, b) = (tf.opacity_at(lo), tf.opacity_at(hi));
    let (mut min, mut max) = (a.min(b), a.max(b));
    for s in &tf.opacity {
        if s.value > lo && s.value < hi {
            min = min.min(s.opacity);
            max = max.max(s.opacity);
        }
    }
    (min, max)
}

/// Sampling distance per page entry (see the module doc). `ranges` are physical [min, max]
/// per entry (None: unknown, sampled finely); `quality` is the base step in finest voxels.
pub fn oracle_distances(
    table: &PageTable,
    ranges: &[Option<(f64, f64)>],
    tf: &TransferFunction,
    epsilon: f64,
    l_max: u32,
    quality: f64,
    target: OracleTarget,
) -> Vec<f32> {
    let coarsest = (1u32 << l_max) as f64;
    let epsilon = if epsilon.is_finite() {
        epsilon.max(0.0)
    } else {
        0.0
    };
    let own: Vec<f64> = table
        .entries
        .iter()
        .enumerate()
        .map(|(i, e)| {
            if !e.resident {
                // Nothing to sample: rays pass at the coarsest rate.
                return coarsest;
            }
            // The raycaster's own rule: a level-L node is stepped at 2^L base steps.
            let finest = ((1u64 << e.level.min(30)) as f64).clamp(1.0, coarsest);
            let Some((lo, hi)) = ranges.get(i).copied().flatten() else {
                return finest;
            };
            let extent_voxels = BRICK_CORE as f64 * (1u64 << e.level.min(30)) as f64;
            let Some(variation) = tf_variation(tf, lo.min(hi), lo.max(hi), target, extent_voxels)
            else {
                return coarsest;
            };
            let extent_slices = extent_voxels / quality.max(1e-6);
            let gradient = variation / extent_slices;
            let mut d = coarsest;
            while d > finest && d * gradient > epsilon {
                d *= 0.5;
            }
            d.max(finest)
        })
        .collect();
    // Dilation: the minimum over the entry and its 26 neighbours.
    let dims = table.page_dims;
    (0..own.len())
        .map(|i| {
            let p = table.page_of_linear(i);
            let mut d = own[i];
            for dz in -1i64..=1 {
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let q = [p[0] as i64 + dx, p[1] as i64 + dy, p[2] as i64 + dz];
                        if (0..3).all(|a| q[a] >= 0 && q[a] < dims[a] as i64) {
                            let j = table.linear([q[0] as u32, q[1] as u32, q[2] as u32]);
                            d = d.min(own[j]);
                        }
                    }
                }
            }
            d as f32
        })
        .collect()
}

/// [`oracle_for_cut_with`] bounding the opacity's change ([`OracleTarget::Opacity`]).
pub fn oracle_for_cut(
    table: &PageTable,
    mapping: strata_types::ValueMapping,
    range_of: impl FnMut(u8, [u32; 3]) -> Option<(u16, u16)>,
    tf: &TransferFunction,
    epsilon: f64,
    l_max: u32,
    quality: f64,
) -> Vec<f32> {
    oracle_for_cut_with(
        table,
        mapping,
        range_of,
        tf,
        epsilon,
        l_max,
        quality,
        OracleTarget::Opacity,
    )
}

/// [`oracle_distances`] for a cut whose node ranges are known in stored units (a store's node
/// headers, a volume's node ranges): widened over transition bands (PageTable::sampled_ranges)
/// and mapped to physical units first.
#[allow(clippy::too_many_arguments)]
pub fn oracle_for_cut_with(
    table: &PageTable,
    mapping: strata_types::ValueMapping,
    range_of: impl FnMut(u8, [u32; 3]) -> Option<(u16, u16)>,
    tf: &TransferFunction,
    epsilon: f64,
    l_max: u32,
    quality: f64,
    target: OracleTarget,
) -> Vec<f32> {
    let ranges: Vec<Option<(f64, f64)>> = table
        .sampled_ranges(range_of)
        .into_iter()
        .map(|r| {
            r.map(|(lo, hi)| {
                let (a, b) = (mapping.physical(lo as f64), mapping.physical(hi as f64));
                (a.min(b), a.max(b))
            })
        })
        .collect();
    oracle_distances(table, &ranges, tf, epsilon, l_max, quality, target)
}

/// The per-node oracle where a sample has no page entry (outside the cropped box or the clip
/// half-space): the largest power of two of slices not longer than a lower bound of the
/// distance to them (the larger of the distance to the box, in finest voxels, and to the
/// plane). Returning 2^l_max there would let a ray arrive with d = 2^l_max and skip up to
/// 2^l_max − 1 slices into the volume (measured: −14 dB on the phantom); this is 1-Lipschitz,
/// so it has fallen to 1 by the box face.
pub fn outside_distance(
    geometry: &strata_types::VolumeGeometry,
    settings: &crate::model::settings::RenderSettings,
    point_patient: glam::DVec3,
    spacing_mm: f64,
    l_max: u32,
) -> f64 {
    let a = geometry.index_from_patient_linear();
    let p = a * (point_patient - geometry.origin());
    let mut box_sq = 0.0;
    for axis in 0..3 {
        let n = geometry.dims[axis] as f64;
        let lo = -0.5 + settings.crop.min[axis] as f64 * n;
        let hi = -0.5 + settings.crop.max[axis] as f64 * n;
        let out = (lo - p[axis]).max(0.0) + (p[axis] - hi).max(0.0);
        box_sq += out * out;
    }
    let box_mm = box_sq.sqrt() * geometry.finest_spacing_mm();
    let plane_mm = settings.clip_plane.as_ref().map_or(0.0, |c| {
        let n = glam::DVec3::from(c.normal).normalize_or_zero();
        (c.offset_mm - n.dot(point_patient)).max(0.0)
    });
    let slices = box_mm.max(plane_mm) / spacing_mm.max(1e-12);
    let mut d = 1.0;
    while d * 2.0 <= slices && d * 2.0 <= (1u32 << l_max) as f64 {
        d *= 2.0;
    }
    d
}

/// The test oracle [`OracleKind::Hash`]: an integer in 1..=2^(l_max+1) from (level, x, y,
/// slice, seed), with the same integer hash as the shader (`adaptive_hash` in adaptive.wgsl).
pub fn hash_distance(level: u32, x: u32, y: u32, i_slice: u32, seed: u32, l_max: u32) -> f64 {
    let h = pcg(x ^ pcg(y ^ pcg(i_slice ^ pcg(level ^ pcg(seed)))));
    (1 + h % (2u32 << l_max)) as f64
}

/// PCG hash, as raycast.wgsl's `pcg`.
pub fn pcg(v: u32) -> u32 {
    let state = v.wrapping_mul(747796405).wrapping_add(2891336453);
    let word = ((state >> ((state >> 28) + 4)) ^ state).wrapping_mul(277803737);
    (word >> 22) ^ word
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::page_table::PageEntry;

    #[test]
    fn empty_nodes_get_the_coarsest_distance_and_detail_is_dilated() {
        let mut table = PageTable::new([5, 1, 1]);
        for i in 0..5 {
            table.entries[i] = PageEntry::resident(i as u32, 0);
        }
        let tf = TransferFunction::new(
            "band",
            &[(0.0, 0.0), (100.0, 0.0), (110.0, 0.8), (120.0, 0.0)],
            &[(0.0, [1.0; 3])],
        );
        let ranges = vec![
            Some((0.0, 50.0)),
            Some((0.0, 50.0)),
            Some((0.0, 50.0)),
            Some((90.0, 130.0)),
            Some((0.0, 50.0)),
        ];
        let d = oracle_distances(&table, &ranges, &tf, 0.01, 3, 0.5, OracleTarget::Opacity);
        // Entry 3 holds the band (Δα 0.8 over 64 slices: 0.0125 per slice > ε at d = 1).
        assert_eq!(d, vec![8.0, 8.0, 1.0, 1.0, 1.0]);
        // A larger ε lets the band's node take longer steps.
        let d = oracle_distances(&table, &ranges, &tf, 0.05, 3, 0.5, OracleTarget::Opacity);
        assert_eq!(d[3], 4.0);
        // Level-1 nodes are never sampled finer than the raycaster steps them (2 base steps).
        let mut coarse = table.clone();
        coarse.entries[3] = PageEntry::resident(3, 1);
        let d = oracle_distances(&coarse, &ranges, &tf, 0.0, 3, 0.5, OracleTarget::Opacity);
        assert_eq!(d[3], 2.0);
        assert_eq!(d[0], 8.0);
    }

    #[test]
    fn the_lit_oracle_bounds_the_premultiplied_colour_where_opacity_is_constant() {
        let mut table = PageTable::new([3, 1, 1]);
        for i in 0..3 {
            table.entries[i] = PageEntry::resident(i as u32, 0);
        }
        // Opacity 0.5 everywhere; the colour goes from black to white over [0, 100].
        let tf = TransferFunction::new(
            "colour ramp",
            &[(0.0, 0.5), (1000.0, 0.5)],
            &[(0.0, [0.0; 3]), (100.0, [1.0; 3])],
        );
        // Entry 0 spans the ramp; entries 1 and 2 sit on the white plateau (narrow ranges).
        let ranges = vec![
            Some((0.0, 100.0)),
            Some((500.0, 510.0)),
            Some((700.0, 710.0)),
        ];
        let opacity = oracle_distances(&table, &ranges, &tf, 0.002, 3, 0.5, OracleTarget::Opacity);
        let lit = oracle_distances(
            &table,
            &ranges,
            &tf,
            0.002,
            3,
            0.5,
            OracleTarget::LitColour { shadowed: false },
        );
        // Opacity never changes: the opacity oracle takes the coarsest step everywhere.
        assert_eq!(opacity, vec![8.0; 3]);
        // c·α changes by 0.5 over entry 0's 64 slices (0.0078 per slice > ε at d = 1):
        // sampled finely, and its neighbour too (dilation); the far plateau stays coarse
        // (its shaded term 0.5 · 10/1000 over 64 slices: 0.0006 at d = 8, within ε).
        assert_eq!(lit[0], 1.0);
        assert_eq!(lit[1], 1.0);
        assert_eq!(lit[2], 8.0);
        // The lit oracle is never coarser than the opacity oracle, and ε stays the knob.
        let loose = oracle_distances(
            &table,
            &ranges,
            &tf,
            0.05,
            3,
            0.5,
            OracleTarget::LitColour { shadowed: false },
        );
        assert_eq!(loose[0], 4.0);
    }

    #[test]
    fn with_a_constant_colour_the_lit_oracle_adds_only_the_shading_term() {
        let tf = TransferFunction::new(
            "band",
            &[(0.0, 0.0), (100.0, 0.0), (110.0, 0.8), (120.0, 0.0)],
            &[(0.0, [1.0; 3])],
        );
        // Premultiplied white is the opacity: Δ(c·α) = Δα.
        assert_eq!(
            tf_variation(&tf, 90.0, 130.0, OracleTarget::Opacity, 2.0),
            tf_variation(
                &tf,
                90.0,
                130.0,
                OracleTarget::LitColour { shadowed: false },
                2.0
            )
        );
        // Transparent ranges stay transparent under both.
        assert_eq!(
            tf_variation(
                &tf,
                0.0,
                50.0,
                OracleTarget::LitColour { shadowed: true },
                2.0
            ),
            None
        );
        // On an opacity plateau α does not change, but a range of 10 against the TF's
        // visible width of 110 makes the shaded term α_max · 10/110.
        let plateau = TransferFunction::new(
            "plateau",
            &[
                (0.0, 0.0),
                (100.0, 0.0),
                (110.0, 0.8),
                (200.0, 0.8),
                (210.0, 0.0),
            ],
            &[(0.0, [1.0; 3])],
        );
        let opacity = tf_variation(&plateau, 150.0, 160.0, OracleTarget::Opacity, 2.0);
        let lit = tf_variation(
            &plateau,
            150.0,
            160.0,
            OracleTarget::LitColour { shadowed: false },
            2.0,
        )
        .unwrap_or(0.0);
        assert_eq!(opacity, Some(0.0));
        assert!((lit - 0.8 * 10.0 / 110.0).abs() < 1e-12, "{lit}");
        // Shadowed, a homogeneous block (one value) still attenuates the light across its
        // 2 voxels by 1 − 0.2² of itself: the lit colour changes by α_max · 0.96.
        let shadowed = OracleTarget::LitColour { shadowed: true };
        let lit = tf_variation(&plateau, 150.0, 150.0, shadowed, 2.0).unwrap_or(0.0);
        assert!((lit - 0.8 * 0.96).abs() < 1e-12, "{lit}");
        let unshadowed = OracleTarget::LitColour { shadowed: false };
        assert_eq!(
            tf_variation(&plateau, 150.0, 150.0, unshadowed, 2.0),
            Some(0.0)
        );
    }

    #[test]
    fn outside_the_box_the_distance_falls_to_one_at_the_face() {
        let g = strata_types::VolumeGeometry::axis_aligned([10, 10, 10], [1.0; 3]);
        let s = crate::model::settings::RenderSettings::default();
        let at = |x: f64| outside_distance(&g, &s, glam::DVec3::new(x, 4.5, 4.5), 0.5, 3);
        // The face is at index -0.5 (patient x = -0.5 here); slices of 0.5 mm.
        assert_eq!(at(-10.0), 8.0);
        assert_eq!(at(-2.0), 2.0); // 1.5 mm = 3 slices
        assert_eq!(at(-0.6), 1.0);
        assert_eq!(at(3.0), 1.0); // inside
        let clipped = crate::model::settings::RenderSettings {
            clip_plane: Some(crate::model::settings::ClipPlane {
                normal: [1.0, 0.0, 0.0],
                offset_mm: 6.0,
            }),
            ..s.clone()
        };
        // Inside the box but 4 mm on the clipped side: 8 slices.
        let d = outside_distance(&g, &clipped, glam::DVec3::new(2.0, 4.5, 4.5), 0.5, 3);
        assert_eq!(d, 8.0);
    }

    #[test]
    fn the_hash_oracle_stays_in_range() {
        for i in 0..1000 {
            let d = hash_distance(i % 4, i, i * 7, i / 3, 9, 3);
            assert!((1.0..=16.0).contains(&d) && d.fract() == 0.0);
        }
    }
}
