//! The finer oracle of the adaptive pass: the paper's "distance to the nearest voxel with
//! |∇α| > ε" (adaptive-sampling-3d §4) per 2³ block of every resident node, instead of one
//! distance per page entry (oracle.rs), whose dilation over whole 32³ nodes marks every node
//! next to bone as d = 1.
//!
//! - A block's own distance comes from the opacity variation Δα of the TF over the values its
//!   trilinear field can take (the node voxels B·b−1 ..= B·b+B of each axis, B = [`BLOCK`]:
//!   every voxel whose support reaches into the block): transparent → 2^l_max; otherwise Δα spread over the
//!   block's extent in slices estimates |∇α| per slice, and the distance is the largest power
//!   of two with d·|∇α| ≤ ε (ε the user's knob), no finer than the node's level allows.
//! - Dilation: a block takes the minimum, over the blocks within the longest skip
//!   (2^l_max slices), of max(their own distance, the gap to them in slices), so a ray about
//!   to reach a detailed block has slowed down and a thin feature is not stepped over. Inside
//!   the node the neighbours are its own blocks; across its faces, edges and corners they are
//!   the neighbouring nodes' blocks (found through the page table, their undilated distance).
//! - The table is indexed by cache slot and in-slot block (`slot · BLOCKS_PER_SLOT + block`): the shader
//!   finds the block from the in-slot coordinate that `locate` keeps apart from the slot's
//!   corner (`Location::coord`, issue 14), so no lookup depends on where a brick landed.
//!
//! Built on the CPU from the node payloads the cut uploads (what a later compute pass over
//! resident slots would compute on upload); the CPU transcription (scene.rs) and the GPU pass
//! read the same table.

use crate::model::layout::{BrickSource, BRICK_APRON, BRICK_CORE};
use crate::model::page_table::PageTable;
use crate::model::transfer_function::TransferFunction;

use super::oracle::{tf_variation, OracleTarget};

/// Block edge in node voxels. 2 rather than 4: on the 128³ bench phantom at equal PSNR
/// (50.3 dB) 2³ blocks take 0.67 M samples where 4³ blocks take 1.10 M, because a detailed
/// block's dilation shell is half as thick; 1³ took 0.47 M but its table (128 KiB per slot)
/// and its dilation (25 s on the CPU) are too large for a frame's oracle.
pub const BLOCK: u32 = 2;
/// Blocks per node axis, and per slot.
pub const BLOCKS_PER_AXIS: u32 = BRICK_CORE / BLOCK;
pub const BLOCKS_PER_SLOT: usize = (BLOCKS_PER_AXIS * BLOCKS_PER_AXIS * BLOCKS_PER_AXIS) as usize;

/// The block of payload-local coordinate `local` (voxel centres at integers, core voxel i at
/// i + apron), clamped into the node (apron samples belong to the border block). The shader's
/// `adaptive_block` is the same formula in f32.
pub fn block_of_local(local: [f64; 3]) -> usize {
    let b = local.map(|c| {
        ((c - BRICK_APRON as f64 + 0.5) / BLOCK as f64)
            .floor()
            .clamp(0.0, (BLOCKS_PER_AXIS - 1) as f64) as usize
    });
    let n = BLOCKS_PER_AXIS as usize;
    b[0] + n * (b[1] + n * b[2])
}

fn largest_power_of_two_at_most(x: f64, cap: f64) -> f64 {
    let mut d = 1.0;
    while d * 2.0 <= x && d * 2.0 <= cap {
        d *= 2.0;
    }
    d
}

/// [`block_oracle_with`] bounding the opacity's change ([`OracleTarget::Opacity`]).
pub fn block_oracle<S: BrickSource>(
    table: &PageTable,
    source: &S,
    mapping: strata_types::ValueMapping,
    tf: &TransferFunction,
    epsilon: f64,
    l_max: u32,
    quality: f64,
) -> Vec<f32> {
    block_oracle_with(
        table,
        source,
        mapping,
        tf,
        epsilon,
        l_max,
        quality,
        OracleTarget::Opacity,
    )
}

/// Per cache slot and block (`slot · BLOCKS_PER_SLOT + block`) the oracle's distance in slices (see the
/// module doc). Slots no resident entry uses get 2^l_max. `mapping` turns stored values into
/// the TF's physical units; `quality` is the slice spacing in finest voxels; `target` what the
/// distance bounds the change of (the opacity, or with lighting on the lit colour:
/// oracle.rs `tf_variation`). The same table, a bounded number of slots at a time:
/// block_oracle_build.rs.
#[allow(clippy::too_many_arguments)]
pub fn block_oracle_with<S: BrickSource>(
    table: &PageTable,
    source: &S,
    mapping: strata_types::ValueMapping,
    tf: &TransferFunction,
    epsilon: f64,
    l_max: u32,
    quality: f64,
    target: OracleTarget,
) -> Vec<f32> {
    let rule = DistanceRule::new(mapping, epsilon, l_max, quality, target);
    let node_of_slot = nodes_of_slots(table);
    let mut own = vec![rule.coarsest; node_of_slot.len() * BLOCKS_PER_SLOT];
    for (slot, node) in node_of_slot.iter().enumerate() {
        let Some((level, node)) = *node else { continue };
        if let Some(brick) = source.brick(level, node) {
            rule.own_distances(tf, level, brick, slot_blocks_mut(&mut own, slot));
        }
    }
    let mut out = own.clone();
    for (slot, node) in node_of_slot.iter().enumerate() {
        let Some((level, node)) = *node else { continue };
        rule.dilate(
            table,
            &own,
            slot,
            level,
            node,
            slot_blocks_mut(&mut out, slot),
        );
    }
    out.into_iter().map(|d| d as f32).collect()
}

/// The blocks of `slot` in a per-slot table.
pub(crate) fn slot_blocks_mut(table: &mut [f64], slot: usize) -> &mut [f64] {
    &mut table[slot * BLOCKS_PER_SLOT..(slot + 1) * BLOCKS_PER_SLOT]
}

/// The node of every slot the table uses (its first resident entry's), by slot; the table's
/// length is one past the highest used slot.
pub(crate) fn nodes_of_slots(table: &PageTable) -> Vec<Option<(u8, [u32; 3])>> {
    let slots = table
        .entries
        .iter()
        .filter(|e| e.resident)
        .map(|e| e.slot_in_cache as usize + 1)
        .max()
        .unwrap_or(0);
    let mut node_of_slot: Vec<Option<(u8, [u32; 3])>> = vec![None; slots];
    for (i, e) in table.entries.iter().enumerate() {
        if e.resident {
            let node = PageTable::node_of(table.page_of_linear(i), e.level);
            node_of_slot[e.slot_in_cache as usize].get_or_insert((e.level, node));
        }
    }
    node_of_slot
}

/// The knobs of one oracle, sanitised: what turns a block's values into its distance.
#[derive(Clone, Copy, Debug)]
pub(crate) struct DistanceRule {
    pub(crate) mapping: strata_types::ValueMapping,
    pub(crate) epsilon: f64,
    /// 2^l_max: the longest skip, and the distance of a transparent block.
    pub(crate) coarsest: f64,
    pub(crate) quality: f64,
    pub(crate) target: OracleTarget,
}

impl DistanceRule {
    pub(crate) fn new(
        mapping: strata_types::ValueMapping,
        epsilon: f64,
        l_max: u32,
        quality: f64,
        target: OracleTarget,
    ) -> Self {
        DistanceRule {
            mapping,
            epsilon: if epsilon.is_finite() {
                epsilon.max(0.0)
            } else {
                0.0
            },
            coarsest: (1u32 << l_max) as f64,
            quality: quality.max(1e-6),
            target,
        }
    }

    /// The own (undilated) distances of the blocks of a level-`level` node's payload `brick`
    /// into `blocks` (one slot's run of the table).
    pub(crate) fn own_distances(
        &self,
        tf: &TransferFunction,
        level: u8,
        brick: &[u16],
        blocks: &mut [f64],
    ) {
        let payload = crate::model::layout::BRICK_PAYLOAD as usize;
        let n = BLOCKS_PER_AXIS as i64;
        let scale = (1u64 << level.min(30)) as f64;
        let finest = scale.clamp(1.0, self.coarsest);
        let extent_voxels = BLOCK as f64 * scale;
        let extent_slices = extent_voxels / self.quality;
        for bz in 0..n {
            for by in 0..n {
                for bx in 0..n {
                    let (mut lo, mut hi) = (u16::MAX, 0u16);
                    // Core voxels B·b−1 ..= B·b+B are payload voxels B·b+1 ..= B·b+B+2.
                    let first = |b: i64| (b * BLOCK as i64 + BRICK_APRON as i64 - 1) as usize;
                    for z in first(bz)..first(bz) + BLOCK as usize + 2 {
                        for y in first(by)..first(by) + BLOCK as usize + 2 {
                            let row = payload * (y + payload * z);
                            for &v in &brick[row + first(bx)..row + first(bx) + BLOCK as usize + 2]
                            {
                                lo = lo.min(v);
                                hi = hi.max(v);
                            }
                        }
                    }
                    let (a, b) = (
                        self.mapping.physical(lo as f64),
                        self.mapping.physical(hi as f64),
                    );
                    let k = (bx + n * (by + n * bz)) as usize;
                    blocks[k] =
                        match tf_variation(tf, a.min(b), a.max(b), self.target, extent_voxels) {
                            None => self.coarsest,
                            Some(variation) => {
                                let gradient = variation / extent_slices;
                                let mut d = self.coarsest;
                                while d > finest && d * gradient > self.epsilon {
                                    d *= 0.5;
                                }
                                d.max(finest)
                            }
                        };
                }
            }
        }
    }

    /// The dilated distances of `slot`'s blocks (the level-`level` node `node`) into `blocks`,
    /// from the whole table's own distances `own`.
    pub(crate) fn dilate(
        &self,
        table: &PageTable,
        own: &[f64],
        slot: usize,
        level: u8,
        node: [u32; 3],
        blocks: &mut [f64],
    ) {
        let coarsest = self.coarsest;
        let n = BLOCKS_PER_AXIS as i64;
        let scale = (1u64 << level.min(30)) as f64;
        // Blocks within the longest skip.
        let reach = ((coarsest * self.quality / (BLOCK as f64 * scale)).ceil() as i64).max(1);
        for bz in 0..n {
            for by in 0..n {
                for bx in 0..n {
                    let local = (bx + n * (by + n * bz)) as usize;
                    let mut d = own[slot * BLOCKS_PER_SLOT + local];
                    for oz in -reach..=reach {
                        for oy in -reach..=reach {
                            for ox in -reach..=reach {
                                let ring = ox.abs().max(oy.abs()).max(oz.abs());
                                if ring == 0 {
                                    continue;
                                }
                                // Gap between the blocks, in slices.
                                let gap = (ring - 1) as f64 * BLOCK as f64 * scale / self.quality;
                                let gap_d = if ring <= 1 {
                                    0.0
                                } else {
                                    largest_power_of_two_at_most(gap, coarsest)
                                };
                                if gap_d >= d {
                                    continue;
                                }
                                let b = [bx + ox, by + oy, bz + oz];
                                let theirs = if b.iter().all(|&c| (0..n).contains(&c)) {
                                    own[slot * BLOCKS_PER_SLOT
                                        + (b[0] + n * (b[1] + n * b[2])) as usize]
                                } else {
                                    match neighbour_block(table, table.page_dims, level, node, b) {
                                        Some(j) => own.get(j).copied().unwrap_or(coarsest),
                                        None => continue,
                                    }
                                };
                                d = d.min(theirs.max(gap_d));
                            }
                        }
                    }
                    blocks[local] = d;
                }
            }
        }
    }
}

/// The table index of the block holding the centre of block `b` (node-block coordinates of
/// the level-`level` node `node`, outside the node) in whichever node serves it; None outside
/// the volume or where nothing is resident.
fn neighbour_block(
    table: &PageTable,
    page_dims: [u32; 3],
    level: u8,
    node: [u32; 3],
    b: [i64; 3],
) -> Option<usize> {
    let scale = (1u64 << level.min(30)) as f64;
    let mut cell = [0u32; 3];
    let mut p = [0.0f64; 3];
    for a in 0..3 {
        // Node voxel coordinate of the block centre, then level-0 index.
        let q = node[a] as f64 * BRICK_CORE as f64
            + b[a] as f64 * BLOCK as f64
            + 0.5 * (BLOCK as f64 - 1.0);
        p[a] = (q + 0.5) * scale - 0.5;
        let c = ((p[a] + 0.5) / BRICK_CORE as f64).floor();
        if c < 0.0 || c >= page_dims[a] as f64 {
            return None;
        }
        cell[a] = c as u32;
    }
    let e = table.get(cell);
    if !e.resident {
        return None;
    }
    let their_node = PageTable::node_of(cell, e.level);
    let their_scale = (1u64 << e.level.min(30)) as f64;
    let local = [0usize, 1, 2].map(|a| {
        (p[a] + 0.5) / their_scale
            - 0.5
            - (their_node[a] as f64 * BRICK_CORE as f64 - BRICK_APRON as f64)
    });
    Some(e.slot_in_cache as usize * BLOCKS_PER_SLOT + block_of_local(local))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::layout::BRICK_PAYLOAD_VOXELS;
    use crate::model::page_table::PageEntry;

    /// Two level-0 nodes side by side along x; node 1 holds a value step at its core voxel 10.
    struct TwoNodes {
        bricks: [Vec<u16>; 2],
    }

    impl BrickSource for TwoNodes {
        fn brick(&self, level: u8, node: [u32; 3]) -> Option<&[u16]> {
            (level == 0 && node[1] == 0 && node[2] == 0)
                .then(|| self.bricks.get(node[0] as usize).map(|b| b.as_slice()))
                .flatten()
        }
    }

    #[test]
    fn detail_is_local_to_its_blocks_and_dilated_by_the_longest_skip() {
        let p = crate::model::layout::BRICK_PAYLOAD as usize;
        let flat = vec![0u16; BRICK_PAYLOAD_VOXELS];
        let mut step = flat.clone();
        for z in 0..p {
            for y in 0..p {
                for x in 0..p {
                    if x >= 10 + BRICK_APRON as usize {
                        step[x + p * (y + p * z)] = 200;
                    }
                }
            }
        }
        let source = TwoNodes {
            bricks: [flat, step],
        };
        let mut table = PageTable::new([2, 1, 1]);
        table.entries[0] = PageEntry::resident(0, 0);
        table.entries[1] = PageEntry::resident(1, 0);
        let tf = TransferFunction::new(
            "step",
            &[(0.0, 0.0), (100.0, 0.0), (150.0, 0.8), (1000.0, 0.8)],
            &[(0.0, [1.0; 3])],
        );
        let mapping = strata_types::ValueMapping::default();
        let n = BLOCKS_PER_AXIS as usize;
        let at = |d: &[f32], slot: usize, b: [usize; 3]| {
            d[slot * BLOCKS_PER_SLOT + b[0] + n * (b[1] + n * b[2])]
        };
        // A row of blocks through the middle of the node along x.
        let mid = n / 2;
        let row = |d: &[f32], slot: usize, x: usize| at(d, slot, [x, mid, mid]);
        // Slices of half a voxel: the longest skip (8 slices, 4 voxels) reaches 2 blocks.
        let d = block_oracle(&table, &source, mapping, &tf, 0.01, 3, 0.5);
        assert_eq!(d.len(), 2 * BLOCKS_PER_SLOT);
        // Block b reads core voxels 2b−1 ..= 2b+2: the step (voxel 9 → 10) lies in what blocks
        // 4 (7..=10) and 5 (9..=12) read; block 3 reads 5..=8 (all 0), block 6 11..=14 (200).
        assert_eq!(row(&d, 1, 4), 1.0);
        assert_eq!(row(&d, 1, 5), 1.0);
        // Their neighbours slow down to d = 1 (no gap), the next ones to the 4-slice gap,
        // blocks three away not at all.
        assert_eq!(row(&d, 1, 3), 1.0);
        assert_eq!(row(&d, 1, 6), 1.0);
        assert_eq!(row(&d, 1, 2), 4.0);
        assert_eq!(row(&d, 1, 7), 4.0);
        assert_eq!(row(&d, 1, 1), 8.0);
        assert_eq!(row(&d, 1, 8), 8.0);
        // Deep inside the plateau the opacity does not vary: the coarsest distance.
        assert_eq!(row(&d, 1, 12), 8.0);
        // The empty node is coarse up to its face: the step is 4 blocks beyond it.
        assert_eq!(row(&d, 0, n - 1), 8.0);
        // ε is a knob: at ε = 0.4 the step's blocks take longer steps (Δα 0.8 over 4 slices).
        let coarse = block_oracle(&table, &source, mapping, &tf, 0.4, 3, 0.5);
        assert_eq!(row(&coarse, 1, 4), 2.0);
        // At a slice of 2 voxels the longest skip is 16 voxels (8 blocks): the empty node's
        // face block, 4 blocks from the step (a gap of 4 slices), slows down to the gap.
        let far = block_oracle(&table, &source, mapping, &tf, 0.01, 3, 2.0);
        assert_eq!(row(&far, 0, n - 1), 4.0);
        assert_eq!(row(&far, 0, 3), 8.0);
    }

    #[test]
    fn with_lighting_a_colour_change_at_constant_opacity_is_sampled_finely() {
        let p = crate::model::layout::BRICK_PAYLOAD as usize;
        let flat = vec![0u16; BRICK_PAYLOAD_VOXELS];
        let mut step = flat.clone();
        for z in 0..p {
            for y in 0..p {
                for x in 0..p {
                    if x >= 10 + BRICK_APRON as usize {
                        step[x + p * (y + p * z)] = 200;
                    }
                }
            }
        }
        let source = TwoNodes {
            bricks: [flat, step],
        };
        let mut table = PageTable::new([2, 1, 1]);
        table.entries[0] = PageEntry::resident(0, 0);
        table.entries[1] = PageEntry::resident(1, 0);
        // Constant opacity; red below 100, white above 150: only the colour changes at the step.
        let tf = TransferFunction::new(
            "colour step",
            &[(0.0, 0.3), (1000.0, 0.3)],
            &[
                (0.0, [1.0, 0.0, 0.0]),
                (100.0, [1.0, 0.0, 0.0]),
                (150.0, [1.0; 3]),
            ],
        );
        let mapping = strata_types::ValueMapping::default();
        let n = BLOCKS_PER_AXIS as usize;
        let row = |d: &[f32], x: usize| d[BLOCKS_PER_SLOT + x + n * (n / 2 + n * (n / 2))];
        let opacity = block_oracle(&table, &source, mapping, &tf, 0.01, 3, 0.5);
        let lit = block_oracle_with(
            &table,
            &source,
            mapping,
            &tf,
            0.01,
            3,
            0.5,
            OracleTarget::LitColour { shadowed: false },
        );
        // α is 0.3 everywhere: the opacity oracle steps 8 slices through the step's blocks.
        assert!(opacity.iter().all(|&d| d == 8.0));
        // c·α (green, blue) goes 0 → 0.3 over blocks 4 and 5 (4 slices: 0.075 per slice > ε
        // at d = 1): the lit oracle samples them and their dilation shell finely.
        assert_eq!(row(&lit, 4), 1.0);
        assert_eq!(row(&lit, 5), 1.0);
        assert_eq!(row(&lit, 2), 4.0);
        // Far from the step the colour and opacity are constant and the field flat: coarse.
        assert_eq!(row(&lit, 12), 8.0);
        assert!(lit.iter().zip(&opacity).all(|(l, o)| l <= o));
    }

    #[test]
    fn block_of_local_splits_the_core_into_blocks_of_two_voxels() {
        assert_eq!(BLOCK, 2);
        let n = BLOCKS_PER_AXIS as usize;
        let a = BRICK_APRON as f64;
        assert_eq!(block_of_local([a, a, a]), 0);
        assert_eq!(block_of_local([a + 1.4, a, a]), 0);
        assert_eq!(block_of_local([a + 1.6, a, a]), 1);
        // Apron samples belong to the border blocks.
        assert_eq!(block_of_local([0.0, 0.0, 0.0]), 0);
        assert_eq!(block_of_local([a + 33.0, a, a]), n - 1);
        assert_eq!(block_of_local([a, a + 2.0, a + 4.0]), n + 2 * n * n);
    }
}
