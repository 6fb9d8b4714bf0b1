//! **The sampled field, defined once.** The GPU raycaster (`shaders/field.wgsl`, its twin) and
//! the f64 reference (reference.rs) both integrate exactly this function of position, so every
//! GPU pixel can be checked against ground truth, mixed-level cuts and transition bands
//! included. Change one side, change the other.
//!
//! - `p` is a continuous level-0 index (voxel centres at integers, volume box
//!   `[-0.5, dims - 0.5]`, clamped to it).
//! - Page cell `clamp(floor((p + 0.5) / 32))`; its entry gives the level `L` and the slot of
//!   the covering node `page >> L` ([`locate`], [`locate_in_page`], [`FieldLocation`]).
//! - Level-L coordinate `q = (p + 0.5) / 2^L - 0.5`, payload-local `q - (32·node - 2)`;
//!   [`trilinear`] inside the 36³ payload, central differences one level-L voxel each way for
//!   gradients ([`gradient_index`]; the 2-voxel apron covers both).
//! - Smooth transitions: inside the half-voxel band next to a coarser neighbour (the masks of
//!   smooth_transitions.rs say which exist), the value and gradient are blended with that
//!   neighbour's own trilinear field, weight [`band_weight`] of the L∞ distance
//!   [`distance_to_neighbour`] to the nearest one ([`sample_field`], [`FieldSample`]). Why this
//!   construction, and why it is continuous, is in smooth_transitions.rs.
//! - Nothing resident: no sample (`None`).

use glam::DVec3;

use crate::model::layout::{neighbour_offset, BrickSource, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};
use crate::model::page_table::PageTable;

/// Where a level-0 continuous index lands: the page entry and position inside its node payload.
pub struct FieldLocation<'b> {
    pub page_linear: usize,
    pub level: u8,
    pub brick: &'b [u16],
    /// Payload-local continuous coordinates (voxel centres at integers).
    pub local: DVec3,
}

pub fn locate<'b, S: BrickSource>(
    source: &'b S,
    table: &PageTable,
    dims: [u32; 3],
    p: DVec3,
) -> Option<FieldLocation<'b>> {
    let mut page = [0u32; 3];
    let mut pc = DVec3::ZERO;
    for a in 0..3 {
        pc[a] = p[a].clamp(-0.5, dims[a] as f64 - 0.5);
        let cell = ((pc[a] + 0.5) / BRICK_CORE as f64).floor() as i64;
        page[a] = cell.clamp(0, table.page_dims[a] as i64 - 1) as u32;
    }
    locate_in_page(source, table, page, pc)
}

/// Position `pc` (level-0 index, inside the volume) in the payload of the node serving
/// `page`; `pc` may lie outside the page, within the node's apron.
pub fn locate_in_page<'b, S: BrickSource>(
    source: &'b S,
    table: &PageTable,
    page: [u32; 3],
    pc: DVec3,
) -> Option<FieldLocation<'b>> {
    let page_linear = table.linear(page);
    let entry = table.entries[page_linear];
    if !entry.resident {
        return None;
    }
    let level = entry.level;
    let node = PageTable::node_of(page, level);
    let brick = source.brick(level, node)?;
    let scale = (1u64 << level) as f64;
    let mut local = DVec3::ZERO;
    for a in 0..3 {
        let q = (pc[a] + 0.5) / scale - 0.5;
        local[a] = q - (node[a] as f64 * BRICK_CORE as f64 - BRICK_APRON as f64);
    }
    Some(FieldLocation {
        page_linear,
        level,
        brick,
        local,
    })
}

/// Trilinear over a 36³ payload in stored units.
pub fn trilinear(brick: &[u16], local: DVec3) -> f64 {
    let max = (BRICK_PAYLOAD - 1) as f64;
    let p = local.clamp(DVec3::ZERO, DVec3::splat(max));
    let i0 = p.floor();
    let f = p - i0;
    let n = BRICK_PAYLOAD as usize;
    let idx = |x: f64, y: f64, z: f64| {
        let (x, y, z) = (
            (x as usize).min(n - 1),
            (y as usize).min(n - 1),
            (z as usize).min(n - 1),
        );
        brick[x + n * (y + n * z)] as f64
    };
    let mut acc = 0.0;
    for dz in 0..2 {
        for dy in 0..2 {
            for dx in 0..2 {
                let w = (if dx == 1 { f.x } else { 1.0 - f.x })
                    * (if dy == 1 { f.y } else { 1.0 - f.y })
                    * (if dz == 1 { f.z } else { 1.0 - f.z });
                if w != 0.0 {
                    acc += w * idx(i0.x + dx as f64, i0.y + dy as f64, i0.z + dz as f64);
                }
            }
        }
    }
    acc
}

/// Central-difference gradient in the node (the apron supplies the neighbours), in stored
/// units per level-0 index step.
pub fn gradient_index(loc: &FieldLocation) -> DVec3 {
    let h = (1u64 << loc.level) as f64;
    let mut g = DVec3::ZERO;
    for a in 0..3 {
        let mut e = DVec3::ZERO;
        e[a] = 1.0;
        g[a] =
            (trilinear(loc.brick, loc.local + e) - trilinear(loc.brick, loc.local - e)) / (2.0 * h);
    }
    g
}

/// Blend weight from the L∞ distance to the nearest coarser neighbour, in the node's voxels:
/// 1 on the shared face, 0 from half a voxel inward.
pub fn band_weight(distance_voxels: f64) -> f64 {
    (1.0 - 2.0 * distance_voxels).clamp(0.0, 1.0)
}

/// Distance (node voxels) from `p` (level-0 index) to the region across neighbour offset `o`
/// of the level-`level` node `node`: the largest of the distances to the faces `o` points at.
pub fn distance_to_neighbour(p: DVec3, level: u8, node: [u32; 3], o: [i32; 3]) -> f64 {
    let scale = (1u64 << level) as f64;
    let core = BRICK_CORE as f64;
    let mut d = f64::NEG_INFINITY;
    for a in 0..3 {
        let q = (p[a] + 0.5) / scale - 0.5;
        let lo = node[a] as f64 * core - 0.5;
        match o[a] {
            -1 => d = d.max(q - lo),
            1 => d = d.max(lo + core - q),
            _ => {}
        }
    }
    d
}

/// One sample of the (optionally smoothed) field.
pub struct FieldSample<'b> {
    /// Stored units (not physical).
    pub value: f64,
    pub location: FieldLocation<'b>,
    /// The coarser neighbour blended in and its weight, when inside a transition band.
    pub coarse: Option<(FieldLocation<'b>, f64)>,
}

impl FieldSample<'_> {
    /// Gradient in stored units per level-0 index step, blended like the value.
    pub fn gradient_index(&self) -> DVec3 {
        let fine = gradient_index(&self.location);
        match &self.coarse {
            Some((c, w)) => fine * (1.0 - w) + gradient_index(c) * *w,
            None => fine,
        }
    }
}

/// The field at level-0 index `p`: the covering node's trilinear value, blended with its nearest
/// coarser neighbour inside the half-voxel band when `masks` (from
/// `smooth_transitions::transition_masks`) is given. None where nothing is resident.
pub fn sample_field<'b, S: BrickSource>(
    source: &'b S,
    table: &PageTable,
    masks: Option<&[u32]>,
    dims: [u32; 3],
    p: DVec3,
) -> Option<FieldSample<'b>> {
    let location = locate(source, table, dims, p)?;
    let fine = trilinear(location.brick, location.local);
    let mask = masks.map_or(0, |m| m[location.page_linear]);
    let coarse = if mask != 0 {
        nearest_coarser(source, table, dims, p, &location, mask)
    } else {
        None
    };
    let value = match &coarse {
        Some((c, w)) => fine * (1.0 - w) + trilinear(c.brick, c.local) * w,
        None => fine,
    };
    Some(FieldSample {
        value,
        location,
        coarse,
    })
}

fn nearest_coarser<'b, S: BrickSource>(
    source: &'b S,
    table: &PageTable,
    dims: [u32; 3],
    p: DVec3,
    location: &FieldLocation<'b>,
    mask: u32,
) -> Option<(FieldLocation<'b>, f64)> {
    let pc = DVec3::new(
        p.x.clamp(-0.5, dims[0] as f64 - 0.5),
        p.y.clamp(-0.5, dims[1] as f64 - 0.5),
        p.z.clamp(-0.5, dims[2] as f64 - 0.5),
    );
    let page = table.page_of_linear(location.page_linear);
    let node = PageTable::node_of(page, location.level);
    let mut best: Option<(f64, [u32; 3])> = None;
    for bit in (0..27).filter(|b| mask & (1 << b) != 0) {
        let o = neighbour_offset(bit);
        let d = distance_to_neighbour(pc, location.level, node, o);
        if d >= 0.5 || best.is_some_and(|(bd, _)| d >= bd) {
            continue;
        }
        let mut neighbour = [0u32; 3];
        let mut inside = true;
        for a in 0..3 {
            let n = page[a] as i64 + o[a] as i64;
            inside &= n >= 0 && n < table.page_dims[a] as i64;
            neighbour[a] = n.max(0) as u32;
        }
        if !inside {
            continue;
        }
        let e = table.get(neighbour);
        if e.resident && e.level > location.level {
            best = Some((d, neighbour));
        }
    }
    let (d, neighbour) = best?;
    let w = band_weight(d);
    if w <= 0.0 {
        return None;
    }
    let coarse = locate_in_page(source, table, neighbour, pc)?;
    Some((coarse, w))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn band_weight_is_one_on_the_face_and_zero_half_a_voxel_in() {
        assert_eq!(band_weight(0.0), 1.0);
        assert_eq!(band_weight(0.25), 0.5);
        assert_eq!(band_weight(0.5), 0.0);
        assert_eq!(band_weight(3.0), 0.0);
        assert_eq!(band_weight(-0.1), 1.0);
        // Node 1 at level 0 spans level-0 indices [31.5, 63.5); its +x face is at 63.5.
        let d = distance_to_neighbour(DVec3::new(63.25, 40.0, 40.0), 0, [1, 1, 1], [1, 0, 0]);
        assert!((d - 0.25).abs() < 1e-12);
        // An edge neighbour is as far as the farther of its two faces.
        let d = distance_to_neighbour(DVec3::new(63.25, 63.0, 40.0), 0, [1, 1, 1], [1, 1, 0]);
        assert!((d - 0.5).abs() < 1e-12);
        // Level 1: voxels are two level-0 indices wide.
        let d = distance_to_neighbour(DVec3::new(-0.5 + 0.5, 10.0, 10.0), 1, [0, 0, 0], [-1, 0, 0]);
        assert!((d - 0.25).abs() < 1e-12);
    }
}
