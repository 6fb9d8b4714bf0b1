//! In-memory octree of bricks built by the same rules as storage: used by tests, the benchmark,
//! and by the app for small volumes. Larger volumes come from storage through [`BrickSource`].

use rayon::prelude::*;
use std::collections::HashMap;

use crate::error::RenderError;
use crate::gpu::cache::BrickCache;
use crate::model::layout::{
    BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS, MAX_SLOTS,
};
use crate::model::page_table::{PageEntry, PageTable};
use crate::model::transfer_function::TransferFunctionTable;
use strata_types::{level_count, ValueMapping, VolumeGeometry};

use crate::model::layout::BrickSource;

struct Level {
    dims: [u32; 3],
    bricks_per_axis: [u32; 3],
    /// Payload per node, x fastest over nodes.
    bricks: Vec<Vec<u16>>,
    /// [min, max] over each whole payload (apron included).
    ranges: Vec<(u16, u16)>,
}

pub struct BrickedVolume {
    pub geometry: VolumeGeometry,
    pub mapping: ValueMapping,
    levels: Vec<Level>,
    /// Min and max stored value over the volume (sizes the TF table).
    pub stored_range: (u16, u16),
}

fn downsample(src: &[u16], dims: [u32; 3]) -> (Vec<u16>, [u32; 3]) {
    let out_dims = dims.map(|d| d.div_ceil(2));
    let [nx, ny, nz] = dims.map(|d| d as usize);
    let [ox, oy, _] = out_dims.map(|d| d as usize);
    let mut out = vec![0u16; out_dims.iter().map(|&d| d as usize).product()];
    out.par_chunks_mut(ox * oy)
        .enumerate()
        .for_each(|(z, plane)| {
            // Odd sizes: the missing neighbour replicates the last voxel.
            let zs = [(2 * z).min(nz - 1), (2 * z + 1).min(nz - 1)];
            for y in 0..oy {
                let ys = [(2 * y).min(ny - 1), (2 * y + 1).min(ny - 1)];
                for x in 0..ox {
                    let xs = [(2 * x).min(nx - 1), (2 * x + 1).min(nx - 1)];
                    let mut sum = 0u32;
                    for &zz in &zs {
                        for &yy in &ys {
                            for &xx in &xs {
                                sum += src[xx + nx * (yy + ny * zz)] as u32;
                            }
                        }
                    }
                    plane[x + ox * y] = ((sum + 4) / 8) as u16;
                }
            }
        });
    (out, out_dims)
}

/// Payload of node `node` from a level's voxels: voxels [32b-2, 32b+34) clamped (edge replicate).
pub fn extract_payload(voxels: &[u16], dims: [u32; 3], node: [u32; 3]) -> Vec<u16> {
    let p = BRICK_PAYLOAD as i64;
    let [nx, ny, nz] = dims.map(|d| d as i64);
    let base = node.map(|b| b as i64 * BRICK_CORE as i64 - BRICK_APRON as i64);
    let mut out = Vec::with_capacity(BRICK_PAYLOAD_VOXELS);
    for z in 0..p {
        let zz = (base[2] + z).clamp(0, nz - 1);
        for y in 0..p {
            let yy = (base[1] + y).clamp(0, ny - 1);
            let row = nx * (yy + ny * zz);
            for x in 0..p {
                let xx = (base[0] + x).clamp(0, nx - 1);
                out.push(voxels[(row + xx) as usize]);
            }
        }
    }
    out
}

impl BrickedVolume {
    /// Builds every level and brick from a function of level-0 voxel index.
    pub fn from_fn(
        geometry: VolumeGeometry,
        mapping: ValueMapping,
        f: impl Fn(u32, u32, u32) -> u16 + Sync,
    ) -> Result<Self, RenderError> {
        geometry.validate()?;
        let [nx, ny, nz] = geometry.dims;
        let mut voxels = vec![0u16; nx as usize * ny as usize * nz as usize];
        voxels
            .par_chunks_mut(nx as usize * ny as usize)
            .enumerate()
            .for_each(|(z, plane)| {
                for y in 0..ny {
                    for x in 0..nx {
                        plane[(x + nx * y) as usize] = f(x, y, z as u32);
                    }
                }
            });
        Self::from_voxels(geometry, mapping, voxels)
    }

    /// Builds from level-0 voxels, x fastest.
    pub fn from_voxels(
        geometry: VolumeGeometry,
        mapping: ValueMapping,
        voxels: Vec<u16>,
    ) -> Result<Self, RenderError> {
        geometry.validate()?;
        let expected: usize = geometry.dims.iter().map(|&d| d as usize).product();
        if voxels.len() != expected {
            return Err(RenderError::InvalidVolume(format!(
                "{} voxels for dims {:?} ({expected} expected)",
                voxels.len(),
                geometry.dims
            )));
        }
        let stored_range = voxels
            .par_iter()
            .fold(|| (u16::MAX, 0u16), |(lo, hi), &v| (lo.min(v), hi.max(v)))
            .reduce(|| (u16::MAX, 0u16), |a, b| (a.0.min(b.0), a.1.max(b.1)));
        let count = level_count(geometry.dims);
        let mut levels = Vec::with_capacity(count as usize);
        let mut current = voxels;
        let mut dims = geometry.dims;
        for level in 0..count {
            let bricks_per_axis = dims.map(|d| d.div_ceil(BRICK_CORE));
            let n_bricks: usize = bricks_per_axis.iter().map(|&d| d as usize).product();
            let bricks: Vec<Vec<u16>> = (0..n_bricks)
                .into_par_iter()
                .map(|i| {
                    let i = i as u32;
                    let node = [
                        i % bricks_per_axis[0],
                        (i / bricks_per_axis[0]) % bricks_per_axis[1],
                        i / (bricks_per_axis[0] * bricks_per_axis[1]),
                    ];
                    extract_payload(&current, dims, node)
                })
                .collect();
            let ranges = bricks
                .iter()
                .map(|b| {
                    b.iter()
                        .fold((u16::MAX, 0u16), |(lo, hi), &v| (lo.min(v), hi.max(v)))
                })
                .collect();
            levels.push(Level {
                dims,
                bricks_per_axis,
                bricks,
                ranges,
            });
            if level + 1 < count {
                let (next, next_dims) = downsample(&current, dims);
                current = next;
                dims = next_dims;
            }
        }
        Ok(BrickedVolume {
            geometry,
            mapping,
            levels,
            stored_range,
        })
    }

    pub fn level_count(&self) -> u8 {
        self.levels.len() as u8
    }

    pub fn level_dims(&self, level: u8) -> Option<[u32; 3]> {
        self.levels.get(level as usize).map(|l| l.dims)
    }

    fn node_index(&self, level: u8, node: [u32; 3]) -> Option<usize> {
        let l = self.levels.get(level as usize)?;
        let b = l.bricks_per_axis;
        if node.iter().zip(b.iter()).any(|(n, d)| n >= d) {
            return None;
        }
        Some((node[0] + b[0] * (node[1] + b[1] * node[2])) as usize)
    }

    /// Stored [min, max] over the node's whole payload (apron included).
    pub fn node_range(&self, level: u8, node: [u32; 3]) -> Option<(u16, u16)> {
        let i = self.node_index(level, node)?;
        Some(self.levels[level as usize].ranges[i])
    }

    /// Physical value range of the volume.
    pub fn physical_range(&self) -> (f64, f64) {
        let a = self.mapping.physical(self.stored_range.0 as f64);
        let b = self.mapping.physical(self.stored_range.1 as f64);
        (a.min(b), a.max(b))
    }

    /// Page table whose every position uses `level` (clamped to the coarsest); slots are
    /// assigned densely in first-use order.
    pub fn page_table_uniform(&self, level: u8) -> PageTable {
        self.page_table_with_levels(|_| level)
    }

    /// Page table with an arbitrary level per page position, e.g. a checkerboard of levels.
    pub fn page_table_with_levels(&self, mut level_of: impl FnMut([u32; 3]) -> u8) -> PageTable {
        let page_dims = self.geometry.page_dims();
        let mut table = PageTable::new(page_dims);
        let mut slots: HashMap<(u8, [u32; 3]), u32> = HashMap::new();
        for i in 0..table.entries.len() {
            let page = table.page_of_linear(i);
            let level = level_of(page).min(self.level_count() - 1);
            let node = PageTable::node_of(page, level);
            let next = slots.len() as u32;
            let slot = *slots.entry((level, node)).or_insert(next);
            table.entries[i] = PageEntry::resident(slot.min(MAX_SLOTS - 1), level);
        }
        table
    }

    /// (slot, level, node) of every distinct resident node the table references.
    pub fn resident_nodes(table: &PageTable) -> Vec<(u32, u8, [u32; 3])> {
        let mut seen = HashMap::new();
        for (i, e) in table.entries.iter().enumerate() {
            if e.resident {
                seen.entry(e.slot_in_cache).or_insert((
                    e.level,
                    PageTable::node_of(table.page_of_linear(i), e.level),
                ));
            }
        }
        let mut out: Vec<_> = seen.into_iter().map(|(s, (l, n))| (s, l, n)).collect();
        out.sort_by_key(|x| x.0);
        out
    }

    /// Uploads every node the table references into its slot.
    pub fn upload(
        &self,
        cache: &BrickCache,
        queue: &wgpu::Queue,
        table: &PageTable,
    ) -> Result<(), RenderError> {
        for (slot, level, node) in Self::resident_nodes(table) {
            let payload = self.brick(level, node).ok_or_else(|| {
                RenderError::PageTableMismatch(format!("no node {node:?} at level {level}"))
            })?;
            cache.upload_brick(queue, slot, payload)?;
        }
        Ok(())
    }

    /// Marks entries transparent under `table` (TF) as empty.
    pub fn classify_empty(&self, page_table: &mut PageTable, tf_table: &TransferFunctionTable) {
        page_table.classify_empty(tf_table, self.mapping, |l, n| self.node_range(l, n));
    }
}

impl BrickSource for BrickedVolume {
    fn brick(&self, level: u8, node: [u32; 3]) -> Option<&[u16]> {
        let i = self.node_index(level, node)?;
        Some(&self.levels[level as usize].bricks[i])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levels_follow_the_storage_rules() {
        let g = VolumeGeometry::axis_aligned([70, 33, 5], [1.0; 3]);
        let v = BrickedVolume::from_fn(g, ValueMapping::default(), |x, y, z| {
            (x * 7 + y * 3 + z * 100) as u16
        })
        .unwrap();
        assert_eq!(v.level_count(), 3); // 70 -> 35 -> 18
        assert_eq!(v.level_dims(1), Some([35, 17, 3]));
        // Level-1 voxel (34, 16, 2): x pair (68, 69), y pair (32, 32 replicated), z (4, 4).
        let l1 = v.brick(1, [1, 0, 0]).unwrap();
        let idx = |x: usize, y: usize, z: usize| x + 36 * (y + 36 * z);
        let expect = |x: u32, y: u32, z: u32| x * 7 + y * 3 + z * 100;
        let sum = expect(68, 32, 4) + expect(69, 32, 4);
        let want = ((sum * 4 + 4) / 8) as u16;
        assert_eq!(l1[idx(34 - 32 + 2, 16 + 2, 2 + 2)], want);
        // Apron clamps at the low edge.
        let b0 = v.brick(0, [0, 0, 0]).unwrap();
        assert_eq!(b0[idx(0, 0, 0)], b0[idx(2, 2, 2)]);
        assert_eq!(b0[idx(5, 2, 2)], 3 * 7);
    }
}
