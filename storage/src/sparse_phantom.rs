//! A mostly-air synthetic volume written straight as bricks, level by level, storing only the
//! bricks that are not constant: `strata sample --sparse` (8192³-16384³ without terabytes).
//!
//! The volume is an analytic field (fixed seed): a few vessel trees of tubes, a tubular bone
//! shell and a few small spherical shells in air. Level-0 voxel `p` (index coordinates) is
//! [`SparsePhantom::value`]: per structure, its value times the coverage
//! `clamp(0.5 − d(p), 0, 1)` of its signed distance `d`, the largest over the structures,
//! rounded (air is stored 0). Every signed distance used is 1-Lipschitz, so a brick whose
//! centre lies farther than its half-diagonal + 0.5 from every structure is air without being
//! evaluated; only bricks near a structure are computed.
//!
//! Coarser levels follow the store's pyramid rule ([`crate::octree`]: a level-L+1 voxel is
//! the rounded mean of its 8 level-L voxels, an odd edge replicated; apron voxels outside a
//! level replicate its edge). A level-L+1 brick reads level-L voxels `[64c − 4, 64c + 68)` per
//! axis, i.e. level-L bricks `2c − 1 ..= 2c + 2`, so it is computed when one of those is not
//! air, from the level-L records written just before (read back and decoded, a few z-rows of
//! them at a time). Memory: the nodes computed (skeleton input) and about four z-rows of
//! decoded bricks of one level; never the volume, never a dense skeleton.

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use rayon::prelude::*;

use crate::brick::{decode_brick, encode_brick, value_range, BrickCodec};
use crate::error::{Result, StorageError};
use crate::histogram::{Histogram, StoredValueCounts};
use crate::import::VolumeMeta;
use crate::octree::{average8, BrickId, OctreeLayout, APRON, BRICK_PAYLOAD_VOXELS, CORE, PAYLOAD};
use crate::phantom::PHANTOM_INTERCEPT;
use crate::quantize::StoredScalar;
use crate::skeleton::{NodeInfo, Skeleton, FEATURE_SPARSE_SKELETON};
use crate::source::{SampleType, WindowPreset};
use crate::store::{StoreHeader, StoreStats, StoreWriter, STORE_FORMAT_VERSION};

/// Stored value of air (−1024 HU with the phantom's intercept).
pub const AIR: u16 = 0;
const BONE: u16 = 2400;
const VESSEL: u16 = 1350;
const SHELL: u16 = 1900;
/// The generator's fixed seed: every run writes the same volume.
const SEED: u64 = 0x5eed_0018_5a17_0001;

/// Largest supported edge (the 16384³; the header check allows up to 2^44 voxels).
pub const MAX_SPARSE_SIZE: u64 = 16384;

#[derive(Clone, Debug)]
enum Shape {
    /// A capsule: the segment a-b thickened by `radius`.
    Tube {
        a: [f64; 3],
        b: [f64; 3],
        radius: f64,
    },
    /// A hollow cylinder along z: centre line (x, y), mid radius, wall thickness, z extent.
    BoneTube {
        centre: [f64; 2],
        radius: f64,
        wall: f64,
        z: [f64; 2],
    },
    /// A spherical shell.
    Shell {
        centre: [f64; 3],
        radius: f64,
        wall: f64,
    },
}

#[derive(Clone, Debug)]
struct Structure {
    shape: Shape,
    value: u16,
    /// Voxel box (inclusive) outside which the signed distance exceeds 0.5.
    lo: [f64; 3],
    hi: [f64; 3],
}

impl Structure {
    fn new(shape: Shape, value: u16) -> Self {
        let (lo, hi) = match &shape {
            Shape::Tube { a, b, radius } => (
                [0, 1, 2].map(|i| a[i].min(b[i]) - radius - 1.0),
                [0, 1, 2].map(|i| a[i].max(b[i]) + radius + 1.0),
            ),
            Shape::BoneTube {
                centre,
                radius,
                wall,
                z,
            } => {
                let r = radius + wall / 2.0 + 1.0;
                (
                    [centre[0] - r, centre[1] - r, z[0] - 1.0],
                    [centre[0] + r, centre[1] + r, z[1] + 1.0],
                )
            }
            Shape::Shell {
                centre,
                radius,
                wall,
            } => {
                let r = radius + wall / 2.0 + 1.0;
                (centre.map(|c| c - r), centre.map(|c| c + r))
            }
        };
        Structure {
            shape,
            value,
            lo,
            hi,
        }
    }

    /// Signed distance (voxels; negative inside), 1-Lipschitz.
    fn distance(&self, p: [f64; 3]) -> f64 {
        match &self.shape {
            Shape::Tube { a, b, radius } => {
                let ab = [0, 1, 2].map(|i| b[i] - a[i]);
                let ap = [0, 1, 2].map(|i| p[i] - a[i]);
                let len2: f64 = ab.iter().map(|v| v * v).sum();
                let t = if len2 > 0.0 {
                    ((0..3).map(|i| ap[i] * ab[i]).sum::<f64>() / len2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let d2: f64 = (0..3).map(|i| (ap[i] - t * ab[i]).powi(2)).sum();
                d2.sqrt() - radius
            }
            Shape::BoneTube {
                centre,
                radius,
                wall,
                z,
            } => {
                let r = ((p[0] - centre[0]).powi(2) + (p[1] - centre[1]).powi(2)).sqrt();
                let radial = (r - radius).abs() - wall / 2.0;
                let axial = (p[2] - (z[0] + z[1]) / 2.0).abs() - (z[1] - z[0]) / 2.0;
                radial.max(axial)
            }
            Shape::Shell {
                centre,
                radius,
                wall,
            } => {
                let r = (0..3)
                    .map(|i| (p[i] - centre[i]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                (r - radius).abs() - wall / 2.0
            }
        }
    }
}

/// splitmix64: small, seeded, the same everywhere.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }
    fn direction(&mut self) -> [f64; 3] {
        loop {
            let v = [0; 3].map(|_| self.range(-1.0, 1.0));
            let n = v.iter().map(|c| c * c).sum::<f64>().sqrt();
            if n > 0.1 && n <= 1.0 {
                return v.map(|c| c / n);
            }
        }
    }
}

/// The sparse volume of edge `size` (a cube).
#[derive(Clone, Debug)]
pub struct SparsePhantom {
    pub size: u64,
    structures: Vec<Structure>,
}

/// A computed level-0 brick: index in level, node, record (None when constant), histogram
/// of its core voxels (empty when constant: then all `core voxels` hold the node's value) and
/// its core voxels inside the volume.
type Level0Brick = (u64, NodeInfo, Option<Vec<u8>>, StoredValueCounts, u64);

/// Where the generator is: level, bricks computed of that level's candidates.
#[derive(Clone, Copy, Debug)]
pub struct SparseProgress {
    pub level: usize,
    pub levels: usize,
    pub done: u64,
    pub total: u64,
}

#[derive(Clone, Debug)]
pub struct SparseReport {
    pub header: StoreHeader,
    pub stats: StoreStats,
    /// Bricks computed (level by level) and of those written (not constant).
    pub computed_per_level: Vec<u64>,
    pub written_per_level: Vec<u64>,
    /// The skeleton's encoded bytes and nodes kept.
    pub skeleton_bytes: u64,
    pub skeleton_stored_nodes: u64,
    pub seconds: f64,
}

impl SparsePhantom {
    pub fn new(size: u64) -> Self {
        let n = size as f64;
        let mut rng = Rng(SEED);
        let mut structures = Vec::new();
        // A long bone: a hollow cylinder along z.
        structures.push(Structure::new(
            Shape::BoneTube {
                centre: [0.5 * n, 0.42 * n],
                radius: (0.05 * n).max(4.0),
                wall: (0.012 * n).max(3.0),
                z: [0.15 * n, 0.85 * n],
            },
            BONE,
        ));
        // Vessel trees: each segment forks in two, shorter and thinner.
        for _ in 0..3 {
            let root = [0; 3].map(|_| rng.range(0.2 * n, 0.8 * n));
            let mut stack = vec![(root, rng.direction(), 0.12 * n, (0.004 * n).max(2.0), 0)];
            while let Some((start, dir, length, radius, depth)) = stack.pop() {
                let end = [0, 1, 2].map(|i| start[i] + dir[i] * length);
                structures.push(Structure::new(
                    Shape::Tube {
                        a: start,
                        b: end,
                        radius,
                    },
                    VESSEL,
                ));
                if depth < 3 {
                    for _ in 0..2 {
                        let turn = rng.direction();
                        let d = [0, 1, 2].map(|i| dir[i] + 0.8 * turn[i]);
                        let norm = d.iter().map(|c| c * c).sum::<f64>().sqrt().max(1e-9);
                        stack.push((
                            end,
                            d.map(|c| c / norm),
                            length * 0.75,
                            (radius * 0.7).max(1.2),
                            depth + 1,
                        ));
                    }
                }
            }
        }
        // Small spherical shells.
        for _ in 0..5 {
            structures.push(Structure::new(
                Shape::Shell {
                    centre: [0; 3].map(|_| rng.range(0.1 * n, 0.9 * n)),
                    radius: (0.012 * n).max(6.0),
                    wall: 2.0,
                },
                SHELL,
            ));
        }
        SparsePhantom { size, structures }
    }

    /// 10 µm voxels (a micro-CT), centred on the origin.
    pub fn geometry(&self) -> crate::geometry::VolumeGeometry {
        let spacing = 0.01;
        let d = u32::try_from(self.size).unwrap_or(u32::MAX);
        let mut geometry = crate::geometry::VolumeGeometry::axis_aligned([d, d, d], [spacing; 3]);
        geometry.origin_lps_mm = [-0.5 * spacing * (self.size.max(1) - 1) as f64; 3];
        geometry
    }

    pub fn layout(&self) -> OctreeLayout {
        let d = u32::try_from(self.size).unwrap_or(u32::MAX);
        OctreeLayout::new([d, d, d])
    }

    /// The level-0 value rule (module doc) at voxel `p`.
    pub fn value(&self, p: [u64; 3]) -> u16 {
        self.value_among(
            p.map(|c| c as f64),
            &self.structures.iter().collect::<Vec<_>>(),
        )
    }

    fn value_among(&self, p: [f64; 3], near: &[&Structure]) -> u16 {
        let mut best = f64::from(AIR);
        for s in near {
            let coverage = (0.5 - s.distance(p)).clamp(0.0, 1.0);
            best = best.max(f64::from(AIR) + f64::from(s.value - AIR) * coverage);
        }
        best.round() as u16
    }

    /// The structures that may reach a level-0 brick, and whether one covers it whole (then the
    /// brick is constant at that value, when no nearer structure is brighter).
    fn near(&self, b: [u64; 3]) -> (Vec<&Structure>, Option<u16>) {
        // Payload voxels 32b − 2 ..= 32b + 33: centre 32b + 15.5, half-diagonal 17.5·√3.
        let centre = b.map(|c| (c * CORE) as f64 + (CORE as f64 - 1.0) / 2.0);
        let half = (PAYLOAD as f64 - 1.0) / 2.0 * 3f64.sqrt();
        let mut near = Vec::new();
        let mut covered: Option<u16> = None;
        for s in &self.structures {
            let d = s.distance(centre);
            if d <= half + 0.5 {
                near.push(s);
                if d <= -(half + 0.5) {
                    covered = Some(covered.map_or(s.value, |v| v.max(s.value)));
                }
            }
        }
        let whole = covered.filter(|&v| near.iter().all(|s| s.value <= v));
        (near, whole)
    }

    /// Level-0 bricks that may hold something other than air, sorted by index in level.
    fn level0_candidates(&self, layout: &OctreeLayout) -> Vec<u64> {
        let n = layout.bricks_in_level(0).map(u64::from);
        let mut out = Vec::new();
        for s in &self.structures {
            let lo = [0, 1, 2].map(|a| {
                let v = ((s.lo[a] - APRON as f64) / CORE as f64).floor();
                v.clamp(0.0, (n[a] - 1) as f64) as u64
            });
            let hi = [0, 1, 2].map(|a| {
                let v = ((s.hi[a] + APRON as f64) / CORE as f64).floor();
                v.clamp(0.0, (n[a] - 1) as f64) as u64
            });
            if (0..3).any(|a| s.hi[a] < -(APRON as f64) || s.lo[a] > (n[a] * CORE + APRON) as f64) {
                continue;
            }
            let half = (PAYLOAD as f64 - 1.0) / 2.0 * 3f64.sqrt();
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        let centre =
                            [x, y, z].map(|c| (c * CORE) as f64 + (CORE as f64 - 1.0) / 2.0);
                        if s.distance(centre) <= half + 0.5 {
                            out.push(x + n[0] * (y + n[1] * z));
                        }
                    }
                }
            }
        }
        out.sort_unstable();
        out.dedup();
        out
    }

    /// Level-0 brick payload (36³, apron clamped to the volume).
    fn level0_brick(&self, b: [u64; 3], near: &[&Structure], out: &mut Vec<u16>) {
        out.clear();
        let max = self.size - 1;
        for z in 0..PAYLOAD {
            let pz = (b[2] * CORE + z).saturating_sub(APRON).min(max);
            for y in 0..PAYLOAD {
                let py = (b[1] * CORE + y).saturating_sub(APRON).min(max);
                for x in 0..PAYLOAD {
                    let px = (b[0] * CORE + x).saturating_sub(APRON).min(max);
                    out.push(self.value_among([px as f64, py as f64, pz as f64], near));
                }
            }
        }
    }

    /// Writes the store at `path` (replacing a store there). `codec` compresses the bricks.
    pub fn write_store(
        &self,
        path: &Path,
        codec: BrickCodec,
        progress: Option<&(dyn Fn(SparseProgress) + Sync)>,
    ) -> Result<SparseReport> {
        if !(1..=MAX_SPARSE_SIZE).contains(&self.size) {
            return Err(StorageError::invalid(
                path,
                format!("sparse phantom size {} (1 to {MAX_SPARSE_SIZE})", self.size),
            ));
        }
        if codec == BrickCodec::Lz4 {
            return Err(StorageError::invalid(
                path,
                "the sparse phantom needs a format-2 codec (fast or dense)",
            ));
        }
        let started = Instant::now();
        let header_geometry = self.geometry();
        // Refused before any work, not after the bricks are written.
        crate::geometry::validate(&header_geometry, path)?;
        let layout = self.layout();
        let levels = layout.level_count();
        let writer = StoreWriter::create(path, 64 << 20)?;
        let mut listed: Vec<Vec<(u64, NodeInfo)>> = vec![Vec::new(); levels];
        let mut computed_per_level = vec![0u64; levels];
        let mut written_per_level = vec![0u64; levels];
        let mut compressed_bytes = 0u64;
        let mut counts = StoredValueCounts::default();
        let mut counted_voxels = 0u64;
        let report = |level: usize, done: u64, total: u64| {
            if let Some(p) = progress {
                p(SparseProgress {
                    level,
                    levels,
                    done,
                    total,
                });
            }
        };

        // Level 0 from the field.
        let candidates = self.level0_candidates(&layout);
        let n0 = layout.bricks_in_level(0).map(u64::from);
        let total0 = candidates.len() as u64;
        for (chunk_index, chunk) in candidates.chunks(256).enumerate() {
            let results: Vec<Level0Brick> = chunk
                .par_iter()
                .map_init(
                    || Vec::with_capacity(BRICK_PAYLOAD_VOXELS),
                    |voxels, &i| {
                        let b = [i % n0[0], (i / n0[0]) % n0[1], i / (n0[0] * n0[1])];
                        let id = BrickId::new(0, b.map(|c| c as u32));
                        let (near, whole) = self.near(b);
                        let mut brick_counts = StoredValueCounts { counts: Vec::new() };
                        let core_voxels = (0..3)
                            .map(|a| (self.size - b[a] * CORE).min(CORE))
                            .product::<u64>();
                        if let Some(v) = whole {
                            return (i, NodeInfo::constant(v), None, brick_counts, core_voxels);
                        }
                        self.level0_brick(b, &near, voxels);
                        let range = value_range(voxels);
                        // Histogram of the core voxels inside the volume.
                        brick_counts.counts = vec![0; 1 << 16];
                        let ext = [0, 1, 2].map(|a| (self.size - b[a] * CORE).min(CORE));
                        for z in 0..ext[2] {
                            for y in 0..ext[1] {
                                let row = ((z + APRON) * PAYLOAD + y + APRON) * PAYLOAD + APRON;
                                for &v in &voxels[row as usize..(row + ext[0]) as usize] {
                                    brick_counts.counts[v as usize] += 1;
                                }
                            }
                        }
                        if range.min == range.max {
                            return (
                                i,
                                NodeInfo::constant(range.min),
                                None,
                                brick_counts,
                                core_voxels,
                            );
                        }
                        let record = encode_brick(id, voxels, range, false, codec);
                        let info = NodeInfo {
                            min: range.min,
                            max: range.max,
                            flags: 0,
                        };
                        (i, info, Some(record), brick_counts, core_voxels)
                    },
                )
                .collect();
            let mut batch = Vec::new();
            for (i, info, record, brick_counts, core_voxels) in results {
                computed_per_level[0] += 1;
                counted_voxels += core_voxels;
                if brick_counts.counts.is_empty() {
                    counts.counts[info.min as usize] += core_voxels;
                } else {
                    counts = counts.merge(&brick_counts);
                }
                if info.is_constant() && info.min == AIR {
                    continue;
                }
                listed[0].push((i, info));
                if let Some(record) = record {
                    compressed_bytes += record.len() as u64;
                    written_per_level[0] += 1;
                    let b = [i % n0[0], (i / n0[0]) % n0[1], i / (n0[0] * n0[1])];
                    batch.push((BrickId::new(0, b.map(|c| c as u32)), record));
                }
            }
            writer.put_bricks(batch)?;
            report(0, ((chunk_index + 1) as u64 * 256).min(total0), total0);
        }
        let total_voxels = self.size.pow(3);
        counts.counts[AIR as usize] += total_voxels - counted_voxels;

        // Coarser levels from the one below.
        for level in 1..levels {
            let (finer_listed, rest) = listed.split_at_mut(level);
            let finer = &finer_listed[level - 1];
            let nf = layout.bricks_in_level(level - 1).map(u64::from);
            let nc = layout.bricks_in_level(level).map(u64::from);
            let mut cands: Vec<u64> = Vec::new();
            for &(i, info) in finer.iter() {
                if info.is_constant() && info.min == AIR {
                    continue;
                }
                let f = [i % nf[0], (i / nf[0]) % nf[1], i / (nf[0] * nf[1])];
                // Parents c with 2c − 1 ≤ f ≤ 2c + 2: c from ⌈(f − 2)/2⌉ to ⌊(f + 1)/2⌋.
                let lo = f.map(|v| (v.saturating_sub(1)) / 2);
                let hi = [0, 1, 2].map(|a| f[a].div_ceil(2).min(nc[a] - 1));
                for z in lo[2]..=hi[2] {
                    for y in lo[1]..=hi[1] {
                        for x in lo[0]..=hi[0] {
                            cands.push(x + nc[0] * (y + nc[1] * z));
                        }
                    }
                }
            }
            cands.sort_unstable();
            cands.dedup();
            let total = cands.len() as u64;
            let mut done = 0u64;
            let mut cache: HashMap<u64, Vec<u16>> = HashMap::new();
            let finer_dims = layout.level_dims[level - 1].map(u64::from);
            let coarse_dims = layout.level_dims[level].map(u64::from);
            let mut start = 0usize;
            while start < cands.len() {
                let cz = cands[start] / (nc[0] * nc[1]);
                let end = start + cands[start..].partition_point(|&i| i / (nc[0] * nc[1]) == cz);
                // Level-L rows this row reads: 2cz − 1 ..= 2cz + 2.
                let (row_lo, row_hi) = ((2 * cz).saturating_sub(1), (2 * cz + 2).min(nf[2] - 1));
                cache.retain(|&i, _| i / (nf[0] * nf[1]) >= row_lo);
                let first = finer.partition_point(|n| n.0 < row_lo * nf[0] * nf[1]);
                let last = finer.partition_point(|n| n.0 < (row_hi + 1) * nf[0] * nf[1]);
                let missing: Vec<u64> = finer[first..last]
                    .iter()
                    .filter(|(i, n)| !n.is_constant() && !cache.contains_key(i))
                    .map(|(i, _)| *i)
                    .collect();
                let decoded: Vec<Result<(u64, Vec<u16>)>> = missing
                    .par_iter()
                    .map(|&i| {
                        let f = [i % nf[0], (i / nf[0]) % nf[1], i / (nf[0] * nf[1])];
                        let id = BrickId::new((level - 1) as u8, f.map(|c| c as u32));
                        let record = writer.read_brick_record(id)?.ok_or_else(|| {
                            StorageError::invalid(path, format!("brick {id:?} was not written"))
                        })?;
                        let voxels = decode_brick(id, &record).map_err(|e| {
                            StorageError::invalid(path, format!("brick {id:?} reads back: {e}"))
                        })?;
                        Ok((i, voxels))
                    })
                    .collect();
                for d in decoded {
                    let (i, v) = d?;
                    cache.insert(i, v);
                }
                // A finer brick's payload, or its constant value (air when not listed).
                let finer_brick = |i: u64| -> Result<&[u16], u16> {
                    if let Some(v) = cache.get(&i) {
                        return Ok(v);
                    }
                    Err(finer
                        .binary_search_by_key(&i, |n| n.0)
                        .map_or(AIR, |at| finer[at].1.min))
                };
                let results: Vec<(u64, NodeInfo, Option<Vec<u8>>)> = cands[start..end]
                    .par_iter()
                    .map(|&i| {
                        let c = [i % nc[0], (i / nc[0]) % nc[1], i / (nc[0] * nc[1])];
                        let id = BrickId::new(level as u8, c.map(|v| v as u32));
                        // The finer voxels this brick averages, gathered once: [64c − 4, 64c + 68).
                        let lo = c.map(|v| (2 * v * CORE).saturating_sub(2 * APRON));
                        let hi = [0, 1, 2]
                            .map(|a| (2 * c[a] * CORE + 2 * (CORE + APRON)).min(finer_dims[a]));
                        let ext = [0, 1, 2].map(|a| hi[a] - lo[a]);
                        let mut block = vec![AIR; (ext[0] * ext[1] * ext[2]) as usize];
                        // Brick by brick (at most 4³): the cores' overlap with the block.
                        let b_lo = lo.map(|v| v / CORE);
                        let b_hi = hi.map(|v| (v - 1) / CORE);
                        for bz in b_lo[2]..=b_hi[2] {
                            for by in b_lo[1]..=b_hi[1] {
                                for bx in b_lo[0]..=b_hi[0] {
                                    let b = [bx, by, bz];
                                    let source = finer_brick(bx + nf[0] * (by + nf[1] * bz));
                                    let from = [0, 1, 2].map(|a| (b[a] * CORE).max(lo[a]));
                                    let to = [0, 1, 2].map(|a| ((b[a] + 1) * CORE).min(hi[a]));
                                    for z in from[2]..to[2] {
                                        for y in from[1]..to[1] {
                                            let dst = (((z - lo[2]) * ext[1] + y - lo[1]) * ext[0]
                                                + from[0]
                                                - lo[0])
                                                as usize;
                                            let len = (to[0] - from[0]) as usize;
                                            match source {
                                                Ok(payload) => {
                                                    let o = [
                                                        from[0] - b[0] * CORE + APRON,
                                                        y - b[1] * CORE + APRON,
                                                        z - b[2] * CORE + APRON,
                                                    ];
                                                    let src = ((o[2] * PAYLOAD + o[1]) * PAYLOAD
                                                        + o[0])
                                                        as usize;
                                                    block[dst..dst + len]
                                                        .copy_from_slice(&payload[src..src + len]);
                                                }
                                                Err(value) => block[dst..dst + len].fill(value),
                                            }
                                        }
                                    }
                                }
                            }
                        }
                        let at = |f: [u64; 3]| {
                            block[(((f[2] - lo[2]) * ext[1] + f[1] - lo[1]) * ext[0] + f[0] - lo[0])
                                as usize] as u32
                        };
                        let mut voxels = Vec::with_capacity(BRICK_PAYLOAD_VOXELS);
                        for z in 0..PAYLOAD {
                            let jz = (c[2] * CORE + z)
                                .saturating_sub(APRON)
                                .min(coarse_dims[2] - 1);
                            let z0 = 2 * jz;
                            let z1 = (z0 + 1).min(finer_dims[2] - 1);
                            for y in 0..PAYLOAD {
                                let jy = (c[1] * CORE + y)
                                    .saturating_sub(APRON)
                                    .min(coarse_dims[1] - 1);
                                let y0 = 2 * jy;
                                let y1 = (y0 + 1).min(finer_dims[1] - 1);
                                for x in 0..PAYLOAD {
                                    let jx = (c[0] * CORE + x)
                                        .saturating_sub(APRON)
                                        .min(coarse_dims[0] - 1);
                                    let x0 = 2 * jx;
                                    let x1 = (x0 + 1).min(finer_dims[0] - 1);
                                    let mut sum = 0u32;
                                    for zz in [z0, z1] {
                                        for yy in [y0, y1] {
                                            sum += at([x0, yy, zz]) + at([x1, yy, zz]);
                                        }
                                    }
                                    voxels.push(average8(sum));
                                }
                            }
                        }
                        let range = value_range(&voxels);
                        if range.min == range.max {
                            return (i, NodeInfo::constant(range.min), None);
                        }
                        let record = encode_brick(id, &voxels, range, false, codec);
                        let info = NodeInfo {
                            min: range.min,
                            max: range.max,
                            flags: 0,
                        };
                        (i, info, Some(record))
                    })
                    .collect();
                let mut batch = Vec::new();
                for (i, info, record) in results {
                    computed_per_level[level] += 1;
                    if info.is_constant() && info.min == AIR {
                        continue;
                    }
                    rest[0].push((i, info));
                    if let Some(record) = record {
                        compressed_bytes += record.len() as u64;
                        written_per_level[level] += 1;
                        let c = [i % nc[0], (i / nc[0]) % nc[1], i / (nc[0] * nc[1])];
                        batch.push((BrickId::new(level as u8, c.map(|v| v as u32)), record));
                    }
                }
                writer.put_bricks(batch)?;
                done += (end - start) as u64;
                report(level, done, total);
                start = end;
            }
        }

        let skeleton = Skeleton::from_listed(&layout, listed, NodeInfo::constant(AIR));
        let (stored_lo, stored_hi) = counts.stored_range().unwrap_or((AIR, AIR));
        let histogram = Histogram::from_stored(&counts, 1.0, PHANTOM_INTERCEPT);
        let geometry = header_geometry;
        let mut required_features = codec.required_features(false);
        required_features.push(FEATURE_SPARSE_SKELETON.to_string());
        let meta = VolumeMeta {
            geometry,
            stored: StoredScalar::U16,
            value_mapping: crate::phantom::phantom_value_mapping(),
            source_sample_type: SampleType::I16,
            quantization_error: 0.0,
            non_finite_samples: 0,
            modality: "CT".into(),
            windows: vec![WindowPreset {
                name: "Bone".into(),
                center: 400.0,
                width: 1800.0,
            }],
            description: format!(
                "Strata sparse synthetic micro-CT {0}x{0}x{0} (vessel trees, bone shell, spherical shells in air)",
                self.size
            ),
            inputs: Vec::new(),
            source_format: "sparse-phantom".into(),
            labels: Vec::new(),
        };
        let header = crate::import::store_header(
            meta,
            STORE_FORMAT_VERSION,
            &layout,
            [stored_lo, stored_hi],
            codec,
            required_features,
        );
        let stats = StoreStats {
            bricks_per_level: (0..levels)
                .map(|l| (skeleton.nodes_in_level(l), skeleton.constant_in_level(l)))
                .collect(),
            compressed_bytes,
            uncompressed_bytes: written_per_level.iter().sum::<u64>()
                * BRICK_PAYLOAD_VOXELS as u64
                * 2,
            source_bytes: 0,
            import_seconds: started.elapsed().as_secs_f64(),
        };
        let skeleton_bytes = skeleton.encode().len() as u64;
        let skeleton_stored_nodes = skeleton.stored_nodes() as u64;
        writer.finish(&header, &skeleton, &histogram, &stats)?;
        Ok(SparseReport {
            header,
            stats,
            computed_per_level,
            written_per_level,
            skeleton_bytes,
            skeleton_stored_nodes,
            seconds: started.elapsed().as_secs_f64(),
        })
    }
}
