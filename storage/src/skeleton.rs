//! The octree skeleton: min, max and flags of every node, in memory and bytes that grow with
//! the non-constant part of the volume, not with the volume.
//!
//! A subtree whose every node is constant with one value is kept as one record, its root; its
//! descendants are implied. A constant node does not make its subtree constant (averages of
//! varying voxels can be equal, and a coarse brick's apron reaches past its children), so only
//! subtree constancy collapses. The invariant every skeleton keeps (checked on decode): the root
//! level is stored; a stored node above level 0 has either all of its children stored or none,
//! and one with none is constant (the root of a collapsed subtree). So [`Skeleton::node`] of an
//! implied node walks up to the first stored ancestor, which is its collapsed root.
//!
//! A level with every node stored keeps them densely (no index per node, as before); other
//! levels keep their stored nodes sorted by index in level (the layout's brick order).
//!
//! Two encodings, both ending in an xxh3 checksum: the dense one of earlier builds (every node
//! of every level) and the sparse one (stored nodes only, behind the store feature
//! [`FEATURE_SPARSE_SKELETON`]). [`Skeleton::decode`] reads both; neither allocates more than
//! the layout bounds or the bytes can hold.

use xxhash_rust::xxh3::xxh3_64;

use crate::octree::{BrickId, OctreeLayout};

/// Store feature: the skeleton uses the sparse encoding, and a constant node may have no brick
/// record (readers answer it from the skeleton).
pub const FEATURE_SPARSE_SKELETON: &str = "sparse-skeleton";

/// Starts the sparse encoding. The dense one starts with a little-endian u32 level count (at
/// most a few dozen), so its first bytes can never be these.
const SPARSE_MAGIC: &[u8; 4] = b"SSK1";

/// Per-node range and flags.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct NodeInfo {
    pub min: u16,
    pub max: u16,
    pub flags: u8,
}

impl NodeInfo {
    pub const CONSTANT: u8 = 1;
    pub fn is_constant(&self) -> bool {
        self.flags & Self::CONSTANT != 0
    }
    /// A constant node of `value`.
    pub fn constant(value: u16) -> NodeInfo {
        NodeInfo {
            min: value,
            max: value,
            flags: Self::CONSTANT,
        }
    }
    /// The value when the node is constant.
    fn constant_value(&self) -> Option<u16> {
        self.is_constant().then_some(self.min)
    }
}

#[derive(Clone, Debug, PartialEq)]
enum LevelNodes {
    /// Every node of the level, in brick order.
    Dense(Vec<NodeInfo>),
    /// The stored nodes: indices in level (strictly increasing) and their infos.
    Sparse {
        indices: Vec<u64>,
        nodes: Vec<NodeInfo>,
    },
}

#[derive(Clone, Debug, PartialEq)]
struct Level {
    bricks: [u32; 3],
    nodes: LevelNodes,
}

impl Level {
    fn total(&self) -> u64 {
        self.bricks.iter().map(|&b| u64::from(b)).product()
    }
    fn stored(&self) -> usize {
        match &self.nodes {
            LevelNodes::Dense(n) => n.len(),
            LevelNodes::Sparse { nodes, .. } => nodes.len(),
        }
    }
    fn index(&self, coords: [u32; 3]) -> Option<u64> {
        let n = self.bricks.map(u64::from);
        let c = coords.map(u64::from);
        (c[0] < n[0] && c[1] < n[1] && c[2] < n[2]).then(|| c[0] + n[0] * (c[1] + n[1] * c[2]))
    }
    fn coords(&self, index: u64) -> [u32; 3] {
        let n = self.bricks.map(u64::from);
        [
            (index % n[0]) as u32,
            ((index / n[0]) % n[1]) as u32,
            (index / (n[0] * n[1])) as u32,
        ]
    }
    fn get_mut(&mut self, index: u64) -> Option<&mut NodeInfo> {
        match &mut self.nodes {
            LevelNodes::Dense(n) => n.get_mut(usize::try_from(index).ok()?),
            LevelNodes::Sparse { indices, nodes } => indices
                .binary_search(&index)
                .ok()
                .map(|position| &mut nodes[position]),
        }
    }
    /// Stores node `index` as `info` unless it is stored already.
    fn insert(&mut self, index: u64, info: NodeInfo) {
        if let LevelNodes::Sparse { indices, nodes } = &mut self.nodes {
            if let Err(at) = indices.binary_search(&index) {
                indices.insert(at, index);
                nodes.insert(at, info);
            }
        }
    }
    fn get(&self, index: u64) -> Option<NodeInfo> {
        match &self.nodes {
            LevelNodes::Dense(n) => n.get(usize::try_from(index).ok()?).copied(),
            LevelNodes::Sparse { indices, nodes } => indices
                .binary_search(&index)
                .ok()
                .map(|position| nodes[position]),
        }
    }
    /// Position of `index` among the stored nodes.
    fn position(&self, index: u64) -> Option<usize> {
        match &self.nodes {
            LevelNodes::Dense(n) => usize::try_from(index).ok().filter(|&i| i < n.len()),
            LevelNodes::Sparse { indices, .. } => indices.binary_search(&index).ok(),
        }
    }
    fn stored_at(&self, position: usize) -> (u64, NodeInfo) {
        match &self.nodes {
            LevelNodes::Dense(n) => (position as u64, n[position]),
            LevelNodes::Sparse { indices, nodes } => (indices[position], nodes[position]),
        }
    }
    /// A level from its stored nodes (sorted, unique), dense when none is missing.
    fn from_stored(bricks: [u32; 3], indices: Vec<u64>, nodes: Vec<NodeInfo>) -> Level {
        let mut level = Level {
            bricks,
            nodes: LevelNodes::Dense(Vec::new()),
        };
        level.nodes = if indices.len() as u64 == level.total() {
            LevelNodes::Dense(nodes)
        } else {
            LevelNodes::Sparse { indices, nodes }
        };
        level
    }
}

/// The octree's nodes with their ranges: every node answers [`Skeleton::node`], only the
/// non-implied ones take memory.
#[derive(Clone, Debug, PartialEq)]
pub struct Skeleton {
    levels: Vec<Level>,
}

/// Children of `coords` (one level finer, clipped to that level's `bricks`).
fn children(coords: [u32; 3], bricks: [u32; 3]) -> impl Iterator<Item = [u32; 3]> {
    (0..8u32).filter_map(move |i| {
        let c = [0, 1, 2].map(|a| coords[a] * 2 + ((i >> a) & 1));
        (c[0] < bricks[0] && c[1] < bricks[1] && c[2] < bricks[2]).then_some(c)
    })
}

impl Skeleton {
    /// Every node given: `levels[l][i]` is node `i` (brick order) of level `l`.
    pub fn from_dense(layout: &OctreeLayout, levels: &[Vec<NodeInfo>]) -> Skeleton {
        let listed = levels
            .iter()
            .map(|l| {
                l.iter()
                    .enumerate()
                    .map(|(i, n)| (i as u64, *n))
                    .collect::<Vec<_>>()
            })
            .collect::<Vec<_>>();
        Self::from_listed(layout, listed, NodeInfo::constant(0))
    }

    /// Every node `info` (a source whose ranges are unknown, say).
    /// Constant: one root record. Varying: every node stored, densely (no index per node).
    pub fn uniform(layout: &OctreeLayout, info: NodeInfo) -> Skeleton {
        if info.is_constant() {
            return Self::from_listed(layout, Vec::new(), info);
        }
        Skeleton {
            levels: (0..layout.level_count())
                .map(|l| Level {
                    bricks: layout.bricks_in_level(l),
                    nodes: LevelNodes::Dense(vec![info; layout.brick_count_in_level(l) as usize]),
                })
                .collect(),
        }
    }

    /// The skeleton of a volume whose nodes are `listed[l]` (index in level, info; sorted by
    /// index, unique) and, for every node not listed, `unlisted` (which must be constant).
    /// Work and memory grow with the listed nodes times the level count.
    pub fn from_listed(
        layout: &OctreeLayout,
        mut listed: Vec<Vec<(u64, NodeInfo)>>,
        unlisted: NodeInfo,
    ) -> Skeleton {
        let level_count = layout.level_count();
        listed.resize(level_count, Vec::new());
        let bricks: Vec<[u32; 3]> = (0..level_count)
            .map(|l| layout.bricks_in_level(l))
            .collect();
        let index_of = |l: usize, c: [u32; 3]| -> u64 {
            let n = bricks[l].map(u64::from);
            u64::from(c[0]) + n[0] * (u64::from(c[1]) + n[1] * u64::from(c[2]))
        };
        let coords_of = |l: usize, i: u64| -> [u32; 3] {
            let n = bricks[l].map(u64::from);
            [
                (i % n[0]) as u32,
                ((i / n[0]) % n[1]) as u32,
                (i / (n[0] * n[1])) as u32,
            ]
        };
        let parent_index = |l: usize, i: u64| -> u64 {
            let c = coords_of(l, i);
            index_of(l + 1, c.map(|v| v / 2))
        };
        // Per level, the nodes that may have a listed descendant (listed ones and their
        // ancestors), with their info and subtree value (Some when the whole subtree is
        // constant with it). A node outside these sets has a wholly unlisted, constant subtree.
        let unlisted_value = unlisted.constant_value();
        let mut known: Vec<Vec<(u64, NodeInfo, Option<u16>)>> = Vec::with_capacity(level_count);
        for level in 0..level_count {
            let mut nodes: Vec<(u64, NodeInfo, Option<u16>)> = std::mem::take(&mut listed[level])
                .into_iter()
                .map(|(i, n)| (i, n, n.constant_value()))
                .collect();
            if level > 0 {
                let mut parents: Vec<u64> = known[level - 1]
                    .iter()
                    .map(|&(i, ..)| parent_index(level - 1, i))
                    .collect();
                parents.dedup();
                parents.sort_unstable();
                parents.dedup();
                let missing: Vec<u64> = parents
                    .into_iter()
                    .filter(|p| nodes.binary_search_by_key(p, |n| n.0).is_err())
                    .collect();
                nodes.extend(missing.into_iter().map(|p| (p, unlisted, unlisted_value)));
                nodes.sort_unstable_by_key(|n| n.0);
                // Fold the children in: a child whose subtree differs ends the parent's.
                let mut child_counts = vec![0u8; nodes.len()];
                for &(i, _, sub) in &known[level - 1] {
                    let p = parent_index(level - 1, i);
                    if let Ok(at) = nodes.binary_search_by_key(&p, |n| n.0) {
                        child_counts[at] += 1;
                        if nodes[at].2 != sub {
                            nodes[at].2 = None;
                        }
                    }
                }
                for (at, node) in nodes.iter_mut().enumerate() {
                    let all = children(coords_of(level, node.0), bricks[level - 1]).count();
                    if usize::from(child_counts[at]) < all && node.2 != unlisted_value {
                        node.2 = None;
                    }
                }
            }
            known.push(nodes);
        }
        // Stored: the root level, and every child of a node whose subtree is not constant.
        let mut levels: Vec<Level> = Vec::with_capacity(level_count);
        for level in 0..level_count {
            let (indices, nodes): (Vec<u64>, Vec<NodeInfo>) = if level + 1 == level_count {
                let total = layout.brick_count_in_level(level);
                (0..total)
                    .map(|i| {
                        let info = known[level]
                            .binary_search_by_key(&i, |n| n.0)
                            .map_or(unlisted, |at| known[level][at].1);
                        (i, info)
                    })
                    .unzip()
            } else {
                let mut stored: Vec<(u64, NodeInfo)> = Vec::new();
                for &(p, _, sub) in &known[level + 1] {
                    if sub.is_some() {
                        continue;
                    }
                    for c in children(coords_of(level + 1, p), bricks[level]) {
                        let i = index_of(level, c);
                        let info = known[level]
                            .binary_search_by_key(&i, |n| n.0)
                            .map_or(unlisted, |at| known[level][at].1);
                        stored.push((i, info));
                    }
                }
                stored.sort_unstable_by_key(|s| s.0);
                stored.into_iter().unzip()
            };
            levels.push(Level::from_stored(bricks[level], indices, nodes));
        }
        Skeleton { levels }
    }

    pub fn level_count(&self) -> usize {
        self.levels.len()
    }

    /// Nodes of `level` (stored or implied).
    pub fn nodes_in_level(&self, level: usize) -> u64 {
        self.levels.get(level).map_or(0, Level::total)
    }

    /// Nodes of `level` kept in memory (the rest are implied by a collapsed ancestor).
    pub fn stored_in_level(&self, level: usize) -> usize {
        self.levels.get(level).map_or(0, Level::stored)
    }

    /// Nodes kept in memory over all levels.
    pub fn stored_nodes(&self) -> usize {
        self.levels.iter().map(Level::stored).sum()
    }

    /// Constant nodes of `level`, implied ones included.
    pub fn constant_in_level(&self, level: usize) -> u64 {
        let varying = self
            .stored_in_level_iter(level)
            .filter(|(_, n)| !n.is_constant())
            .count() as u64;
        self.nodes_in_level(level) - varying
    }

    /// The stored nodes of `level` in brick order.
    pub fn stored_in_level_iter(
        &self,
        level: usize,
    ) -> impl Iterator<Item = (BrickId, NodeInfo)> + '_ {
        let l = self.levels.get(level);
        (0..l.map_or(0, Level::stored)).filter_map(move |p| {
            let l = l?;
            let (i, info) = l.stored_at(p);
            Some((BrickId::new(level as u8, l.coords(i)), info))
        })
    }

    /// Whether `id` has a record of its own (else it is implied by a collapsed ancestor).
    pub fn is_stored(&self, id: BrickId) -> bool {
        self.levels
            .get(id.level as usize)
            .and_then(|l| l.position(l.index(id.coords)?))
            .is_some()
    }

    /// Node `id`'s range and flags; `None` outside the octree. An implied node answers its
    /// collapsed ancestor's (constant) record.
    pub fn node(&self, id: BrickId) -> Option<NodeInfo> {
        let mut level = id.level as usize;
        let mut coords = id.coords;
        self.levels.get(level)?.index(coords)?;
        loop {
            let l = self.levels.get(level)?;
            if let Some(info) = l.get(l.index(coords)?) {
                return Some(info);
            }
            level += 1;
            coords = coords.map(|c| c / 2);
        }
    }

    /// Records an edit: brick `id` now holds voxels of `range` (`min`, `max`). Its node takes
    /// that range exactly (constant when it is one value) and every ancestor's range widens to
    /// include it, so culling by range never hides the edited brick (issue 48, item 3). A node
    /// implied by a collapsed constant subtree is stored first, with the nodes the skeleton's
    /// invariant then needs (the siblings on the way down, the edited node's children), each
    /// with the subtree's constant value: what they held before the edit.
    pub fn record_edit(&mut self, id: BrickId, min: u16, max: u16) -> Option<()> {
        let level = id.level as usize;
        self.levels.get(level)?.index(id.coords)?;
        // The path from the edited node up to the root, and the lowest stored node on it.
        let path: Vec<[u32; 3]> = (level..self.levels.len())
            .scan(id.coords, |c, _| {
                let here = *c;
                *c = c.map(|v| v / 2);
                Some(here)
            })
            .collect();
        let stored_at = (0..path.len()).find(|&k| {
            let l = &self.levels[level + k];
            l.index(path[k]).and_then(|i| l.get(i)).is_some()
        })?;
        let before = self.node(id)?;
        // Store the implied nodes on the way down from the collapsed root, siblings included.
        for k in (0..stored_at).rev() {
            let parent_level = level + k + 1;
            let bricks = self.levels[parent_level - 1].bricks;
            for c in children(path[k + 1], bricks) {
                let l = &mut self.levels[parent_level - 1];
                if let Some(i) = l.index(c) {
                    l.insert(i, before);
                }
            }
        }
        // A node above level 0 whose children are implied: store them (they keep the value).
        if level > 0 {
            let below = &self.levels[level - 1];
            let any_child_stored = children(id.coords, below.bricks)
                .any(|c| below.index(c).and_then(|i| below.get(i)).is_some());
            if !any_child_stored {
                let bricks = below.bricks;
                for c in children(id.coords, bricks) {
                    let l = &mut self.levels[level - 1];
                    if let Some(i) = l.index(c) {
                        l.insert(i, before);
                    }
                }
            }
        }
        for (k, coords) in path.iter().enumerate() {
            let l = &mut self.levels[level + k];
            let node = l.index(*coords).and_then(|i| l.get_mut(i))?;
            if k == 0 {
                node.min = min;
                node.max = max;
            } else {
                node.min = node.min.min(min);
                node.max = node.max.max(max);
            }
            if node.min == node.max {
                node.flags |= NodeInfo::CONSTANT;
            } else {
                node.flags &= !NodeInfo::CONSTANT;
            }
        }
        Some(())
    }

    /// Bytes this skeleton holds in memory (its node records and indices).
    pub fn memory_bytes(&self) -> usize {
        self.levels
            .iter()
            .map(|l| match &l.nodes {
                LevelNodes::Dense(n) => n.len() * size_of::<NodeInfo>(),
                LevelNodes::Sparse { indices, nodes } => {
                    indices.len() * 8 + nodes.len() * size_of::<NodeInfo>()
                }
            })
            .sum::<usize>()
            + size_of::<Self>()
    }

    /// The sparse encoding (what stores with [`FEATURE_SPARSE_SKELETON`] hold and a server of
    /// this build sends): magic, level count, per level the stored count and per stored node
    /// the index gap (LEB128), flags, min, and max unless constant; an xxh3 checksum.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(SPARSE_MAGIC);
        out.extend_from_slice(&(self.levels.len() as u32).to_le_bytes());
        for l in &self.levels {
            out.extend_from_slice(&(l.stored() as u64).to_le_bytes());
            let mut next = 0u64;
            for p in 0..l.stored() {
                let (i, n) = l.stored_at(p);
                write_varint(&mut out, i - next);
                next = i + 1;
                out.push(n.flags);
                out.extend_from_slice(&n.min.to_le_bytes());
                if !n.is_constant() {
                    out.extend_from_slice(&n.max.to_le_bytes());
                }
            }
        }
        let sum = xxh3_64(&out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    /// The dense encoding of earlier builds (every node of every level, 5 bytes each): for
    /// format-1 stores, which builds before the sparse skeleton must keep reading.
    pub fn encode_dense(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(&(self.levels.len() as u32).to_le_bytes());
        for (level, l) in self.levels.iter().enumerate() {
            out.extend_from_slice(&l.total().to_le_bytes());
            let n = l.bricks;
            for z in 0..n[2] {
                for y in 0..n[1] {
                    for x in 0..n[0] {
                        let info = self
                            .node(BrickId::new(level as u8, [x, y, z]))
                            .unwrap_or_default();
                        out.extend_from_slice(&info.min.to_le_bytes());
                        out.extend_from_slice(&info.max.to_le_bytes());
                        out.push(info.flags);
                    }
                }
            }
        }
        let sum = xxh3_64(&out);
        out.extend_from_slice(&sum.to_le_bytes());
        out
    }

    /// Reads either encoding for `layout`; the error says what is wrong (checksum, framing,
    /// a count beyond the layout, a broken invariant).
    pub fn decode(bytes: &[u8], layout: &OctreeLayout) -> Result<Skeleton, SkeletonDecodeError> {
        let (body, sum) = bytes
            .split_at_checked(
                bytes
                    .len()
                    .checked_sub(8)
                    .ok_or(SkeletonDecodeError::Truncated)?,
            )
            .ok_or(SkeletonDecodeError::Truncated)?;
        let sum = u64::from_le_bytes(sum.try_into().map_err(|_| SkeletonDecodeError::Truncated)?);
        if xxh3_64(body) != sum {
            return Err(SkeletonDecodeError::Checksum);
        }
        let mut reader = Reader { body, pos: 0 };
        let sparse = body.starts_with(SPARSE_MAGIC);
        if sparse {
            reader.take(4)?;
        }
        let level_count = u32::from_le_bytes(reader.array()?) as usize;
        if level_count != layout.level_count() {
            return Err(SkeletonDecodeError::LevelCount {
                stored: level_count,
                layout: layout.level_count(),
            });
        }
        let skeleton = if sparse {
            Self::decode_sparse(&mut reader, layout)?
        } else {
            Self::decode_dense(&mut reader, layout)?
        };
        if reader.pos != body.len() {
            return Err(SkeletonDecodeError::TrailingBytes);
        }
        Ok(skeleton)
    }

    fn decode_dense(
        reader: &mut Reader,
        layout: &OctreeLayout,
    ) -> Result<Skeleton, SkeletonDecodeError> {
        let mut levels = Vec::with_capacity(layout.level_count());
        for level in 0..layout.level_count() {
            let n = u64::from_le_bytes(reader.array()?);
            if n != layout.brick_count_in_level(level) {
                return Err(SkeletonDecodeError::NodeCount {
                    level,
                    stored: n,
                    layout: layout.brick_count_in_level(level),
                });
            }
            // take() checks the bytes are there before anything is allocated.
            let raw = reader.take(
                usize::try_from(n)
                    .map_err(|_| SkeletonDecodeError::TooLarge)?
                    .checked_mul(5)
                    .ok_or(SkeletonDecodeError::TooLarge)?,
            )?;
            levels.push(
                raw.chunks_exact(5)
                    .map(|c| NodeInfo {
                        min: u16::from_le_bytes([c[0], c[1]]),
                        max: u16::from_le_bytes([c[2], c[3]]),
                        flags: c[4],
                    })
                    .collect::<Vec<_>>(),
            );
        }
        Ok(Self::from_dense(layout, &levels))
    }

    fn decode_sparse(
        reader: &mut Reader,
        layout: &OctreeLayout,
    ) -> Result<Skeleton, SkeletonDecodeError> {
        let mut levels = Vec::with_capacity(layout.level_count());
        for level in 0..layout.level_count() {
            let bricks = layout.bricks_in_level(level);
            let total = layout.brick_count_in_level(level);
            let count = u64::from_le_bytes(reader.array()?);
            // A record takes at least 4 bytes (gap, flags, min), so the bytes bound the count.
            let remaining = (reader.body.len() - reader.pos) as u64;
            if count > total || count > remaining / 4 {
                return Err(SkeletonDecodeError::StoredNodeCount {
                    level,
                    claimed: count,
                    layout: total,
                });
            }
            let mut indices = Vec::with_capacity(count as usize);
            let mut nodes = Vec::with_capacity(count as usize);
            let mut next = 0u64;
            for _ in 0..count {
                let i = next
                    .checked_add(reader.varint()?)
                    .filter(|&i| i < total)
                    .ok_or(SkeletonDecodeError::IndexPastLayout { level })?;
                next = i + 1;
                let flags = reader.array::<1>()?[0];
                let min = u16::from_le_bytes(reader.array()?);
                let max = if flags & NodeInfo::CONSTANT != 0 {
                    min
                } else {
                    u16::from_le_bytes(reader.array()?)
                };
                indices.push(i);
                nodes.push(NodeInfo { min, max, flags });
            }
            levels.push(Level::from_stored(bricks, indices, nodes));
        }
        let skeleton = Skeleton { levels };
        skeleton.check_structure()?;
        Ok(skeleton)
    }

    /// The invariant of the module doc: the root level whole, every stored node's parent
    /// stored, and each stored node above level 0 with all of its children or none (then
    /// constant).
    fn check_structure(&self) -> Result<(), SkeletonDecodeError> {
        let Some(top) = self.levels.last() else {
            return Err(SkeletonDecodeError::NoLevels);
        };
        if top.stored() as u64 != top.total() {
            return Err(SkeletonDecodeError::IncompleteRoot);
        }
        for level in 1..self.levels.len() {
            let (finer, coarser) = (&self.levels[level - 1], &self.levels[level]);
            let mut counts = vec![0u8; coarser.stored()];
            for p in 0..finer.stored() {
                let (i, _) = finer.stored_at(p);
                let parent = coarser
                    .index(finer.coords(i).map(|c| c / 2))
                    .and_then(|pi| coarser.position(pi))
                    .ok_or(SkeletonDecodeError::Orphan { level: level - 1 })?;
                counts[parent] += 1;
            }
            for (p, &count) in counts.iter().enumerate() {
                let (i, info) = coarser.stored_at(p);
                let all = children(coarser.coords(i), finer.bricks).count();
                if count == 0 && !info.is_constant() {
                    return Err(SkeletonDecodeError::VaryingWithoutChildren { level });
                }
                if count != 0 && usize::from(count) != all {
                    return Err(SkeletonDecodeError::SomeChildren {
                        level,
                        stored: count,
                        all,
                    });
                }
            }
        }
        Ok(())
    }
}

/// Why stored skeleton bytes were refused. Each message reads after "its octree skeleton"
/// (the callers prefix the store and frame), so the wording is the predicate alone.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SkeletonDecodeError {
    #[error("truncated")]
    Truncated,
    #[error("fails its checksum")]
    Checksum,
    #[error("has {stored} levels, the layout {layout}")]
    LevelCount { stored: usize, layout: usize },
    #[error("has bytes after its last level")]
    TrailingBytes,
    #[error("level {level} has {stored} nodes, the layout {layout}")]
    NodeCount {
        level: usize,
        stored: u64,
        layout: u64,
    },
    #[error("too large")]
    TooLarge,
    #[error("level {level} claims {claimed} stored nodes (the layout has {layout})")]
    StoredNodeCount {
        level: usize,
        claimed: u64,
        layout: u64,
    },
    #[error("level {level} has a node index past the layout")]
    IndexPastLayout { level: usize },
    #[error("has an overlong index gap")]
    OverlongIndexGap,
    #[error("has no levels")]
    NoLevels,
    #[error("its root level is incomplete")]
    IncompleteRoot,
    #[error("a level-{level} node has no stored parent")]
    Orphan { level: usize },
    #[error("a varying level-{level} node has no stored children")]
    VaryingWithoutChildren { level: usize },
    #[error("a level-{level} node has {stored} of its {all} children stored")]
    SomeChildren {
        level: usize,
        stored: u8,
        all: usize,
    },
}

fn write_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

struct Reader<'a> {
    body: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], SkeletonDecodeError> {
        let end = self
            .pos
            .checked_add(n)
            .ok_or(SkeletonDecodeError::Truncated)?;
        let s = self
            .body
            .get(self.pos..end)
            .ok_or(SkeletonDecodeError::Truncated)?;
        self.pos = end;
        Ok(s)
    }
    fn array<const N: usize>(&mut self) -> Result<[u8; N], SkeletonDecodeError> {
        self.take(N)?
            .try_into()
            .map_err(|_| SkeletonDecodeError::Truncated)
    }
    fn varint(&mut self) -> Result<u64, SkeletonDecodeError> {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let b = self.array::<1>()?[0];
            v |= u64::from(b & 0x7f) << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err(SkeletonDecodeError::OverlongIndexGap)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small layout: 5 levels over 160×96×64 voxels (5×3×2 bricks at level 0).
    fn layout() -> OctreeLayout {
        OctreeLayout::new([160, 96, 64])
    }

    /// A dense skeleton: air (0) everywhere except a few varying level-0 bricks, their
    /// ancestors varying, plus a coarse node constant at 0 over varying children.
    fn mostly_air(layout: &OctreeLayout, seed: u64) -> Vec<Vec<NodeInfo>> {
        let mut rng = seed;
        let mut next = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            rng >> 33
        };
        let mut levels: Vec<Vec<NodeInfo>> = (0..layout.level_count())
            .map(|l| vec![NodeInfo::constant(0); layout.brick_count_in_level(l) as usize])
            .collect();
        for (l, level) in levels.iter_mut().enumerate() {
            for n in level.iter_mut() {
                match next() % 10 {
                    0 => {
                        *n = NodeInfo {
                            min: 0,
                            max: 100 + l as u16,
                            flags: 0,
                        }
                    }
                    1 => *n = NodeInfo::constant(7),
                    _ => {}
                }
            }
        }
        levels
    }

    fn assert_same_answers(layout: &OctreeLayout, dense: &[Vec<NodeInfo>], s: &Skeleton) {
        for (l, level) in dense.iter().enumerate() {
            let n = layout.bricks_in_level(l);
            for z in 0..n[2] {
                for y in 0..n[1] {
                    for x in 0..n[0] {
                        let id = BrickId::new(l as u8, [x, y, z]);
                        let i = layout.index_in_level(id).unwrap();
                        assert_eq!(s.node(id), Some(level[i]), "{id:?}");
                    }
                }
            }
        }
        assert_eq!(s.node(BrickId::new(0, [n_past(layout), 0, 0])), None);
        assert_eq!(
            s.node(BrickId::new(layout.level_count() as u8, [0, 0, 0])),
            None
        );
    }

    fn n_past(layout: &OctreeLayout) -> u32 {
        layout.bricks_in_level(0)[0]
    }

    #[test]
    fn a_constant_coarse_node_over_varying_children_keeps_its_children() {
        let layout = layout();
        let mut dense: Vec<Vec<NodeInfo>> = (0..layout.level_count())
            .map(|l| vec![NodeInfo::constant(0); layout.brick_count_in_level(l) as usize])
            .collect();
        // One varying level-0 brick under an all-constant-0 ancestry: the averages hid it.
        let varying = BrickId::new(0, [3, 1, 1]);
        dense[0][layout.index_in_level(varying).unwrap()] = NodeInfo {
            min: 0,
            max: 900,
            flags: 0,
        };
        let s = Skeleton::from_dense(&layout, &dense);
        assert_same_answers(&layout, &dense, &s);
        assert!(s.is_stored(varying));
        // Only the chain of ancestors is open, each with its 8 (or fewer) children.
        assert!(s.stored_nodes() < 8 * layout.level_count());
        let decoded = Skeleton::decode(&s.encode(), &layout).unwrap();
        assert_eq!(decoded, s);
        assert_same_answers(&layout, &dense, &decoded);
    }

    #[test]
    fn sparse_and_dense_encodings_answer_every_node_as_the_dense_skeleton() {
        let layout = layout();
        for seed in 0..20 {
            let dense = mostly_air(&layout, seed);
            let s = Skeleton::from_dense(&layout, &dense);
            assert_same_answers(&layout, &dense, &s);
            let sparse_bytes = s.encode();
            let dense_bytes = s.encode_dense();
            let from_sparse = Skeleton::decode(&sparse_bytes, &layout).unwrap();
            let from_dense = Skeleton::decode(&dense_bytes, &layout).unwrap();
            assert_eq!(from_sparse, s);
            assert_eq!(from_dense, s);
            assert_same_answers(&layout, &dense, &from_sparse);
        }
    }

    #[test]
    fn a_mostly_constant_skeleton_encodes_far_smaller_than_the_dense_one() {
        // 1024×1024×512: 32×32×16 level-0 bricks, a handful varying.
        let layout = OctreeLayout::new([1024, 1024, 512]);
        let mut levels: Vec<Vec<NodeInfo>> = (0..layout.level_count())
            .map(|l| vec![NodeInfo::constant(0); layout.brick_count_in_level(l) as usize])
            .collect();
        for c in [[0, 0, 0], [31, 31, 15], [10, 20, 5]] {
            let mut id = BrickId::new(0, c);
            while layout.contains(id) {
                levels[id.level as usize][layout.index_in_level(id).unwrap()] = NodeInfo {
                    min: 0,
                    max: 50,
                    flags: 0,
                };
                id = id.parent();
            }
        }
        let s = Skeleton::from_dense(&layout, &levels);
        let (sparse, dense) = (s.encode().len(), s.encode_dense().len());
        assert!(sparse * 100 < dense, "sparse {sparse} B vs dense {dense} B");
        assert_same_answers(
            &layout,
            &levels,
            &Skeleton::decode(&s.encode(), &layout).unwrap(),
        );
    }

    #[test]
    fn broken_bytes_are_refused_without_allocating_from_their_counts() {
        let layout = layout();
        let s = Skeleton::from_dense(&layout, &mostly_air(&layout, 3));
        let mut bytes = s.encode();
        // A count of 2^60 stored nodes at level 0, checksum fixed up: refused by the bound.
        bytes[8..16].copy_from_slice(&(1u64 << 60).to_le_bytes());
        let n = bytes.len() - 8;
        let sum = xxh3_64(&bytes[..n]);
        bytes[n..].copy_from_slice(&sum.to_le_bytes());
        assert!(matches!(
            Skeleton::decode(&bytes, &layout),
            Err(SkeletonDecodeError::StoredNodeCount { level: 0, .. })
        ));
        // A flipped byte fails the checksum; another layout is refused.
        let mut flipped = s.encode();
        flipped[10] ^= 1;
        assert!(Skeleton::decode(&flipped, &layout).is_err());
        assert!(Skeleton::decode(&s.encode(), &OctreeLayout::new([64, 64, 64])).is_err());
        assert!(Skeleton::decode(&s.encode_dense(), &OctreeLayout::new([64, 64, 64])).is_err());
    }

    #[test]
    fn a_stored_node_missing_its_siblings_is_refused() {
        let layout = layout();
        let mut dense: Vec<Vec<NodeInfo>> = (0..layout.level_count())
            .map(|l| vec![NodeInfo::constant(0); layout.brick_count_in_level(l) as usize])
            .collect();
        dense[0][0] = NodeInfo {
            min: 0,
            max: 9,
            flags: 0,
        };
        dense[1][0] = NodeInfo {
            min: 0,
            max: 9,
            flags: 0,
        };
        let s = Skeleton::from_dense(&layout, &dense);
        // Drop one level-0 node from the encoding: its parent then has 7 of 8 children.
        let mut broken = s.clone();
        if let LevelNodes::Sparse { indices, nodes } = &mut broken.levels[0].nodes {
            indices.pop();
            nodes.pop();
        } else {
            panic!("level 0 should be sparse");
        }
        let err = Skeleton::decode(&broken.encode(), &layout).unwrap_err();
        assert!(err.to_string().contains("children stored"), "{err}");
    }
}
