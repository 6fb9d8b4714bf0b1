//! Slice images assembled from decoded bricks at the octree level that matches the view's
//! pixel size, without any I/O of its own: the assembler says which bricks a slice still needs
//! (most useful first), takes bricks as they arrive in any order, copies each into every slice
//! waiting for it and keeps it in a bounded LRU (the 32 neighbouring slices of a brick row come
//! from the cache), and hands the image over once complete.
//!
//! Bricks are copied into the image as they arrive rather than read back from the cache at the
//! end, so a slice needing more bricks than the cache holds (a level-0 slice of a huge volume,
//! zoomed in) still completes. The desktop feeds it from blocking reads on its reader thread
//! ([`SliceAssembler::assemble_with`]); the browser from `fetch()` answers on the page's thread
//! ([`SliceAssembler::start`], [`SliceAssembler::missing`], [`SliceAssembler::offer`]).

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::Arc;

use strata_types::{
    BrickId, OctreeLayout, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS,
};

use crate::orientation::{SliceFrame, SliceView};

/// Decompressed bricks kept for paging (bytes), the desktop's default.
pub const SLICE_CACHE_BYTES: usize = 192 << 20;
/// Bytes of one decoded brick (u16 voxels with the apron).
pub const BRICK_BYTES: usize = BRICK_PAYLOAD_VOXELS * 2;
/// The cache keeps at least this many bricks whatever its byte bound (one brick row's worth).
pub const MIN_CACHED_BRICKS: usize = 8;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SliceRequest {
    pub view: SliceView,
    pub frame: SliceFrame,
    /// Level-0 continuous index along the view's normal axis.
    pub position: f64,
    pub level: u8,
}

/// Stored values of one slice in index order: `across` fastest, then `down` (flips are applied
/// at display time through texture coordinates).
#[derive(Clone, Debug)]
pub struct SliceImage {
    pub request: SliceRequest,
    pub width: usize,
    pub height: usize,
    pub values: Arc<Vec<u16>>,
    /// Level-L voxels cover `2^L` level-0 voxels, so the level grid can overhang the volume:
    /// the fraction of the image that lies inside it, across and down.
    pub inside_fraction: (f64, f64),
}

/// The stored value of one level-0 voxel (the readout under the pointer).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct VoxelValue {
    pub index: [u32; 3],
    pub stored: u16,
}

/// What the assembler refuses (bad input, never a panic).
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum SliceError {
    #[error("voxel {index:?} is outside the volume {dims:?}")]
    OutsideVolume { index: [u32; 3], dims: [u32; 3] },
    #[error("brick level {} at {:?} has {voxels} voxels, not {}", id.level, id.coords, BRICK_PAYLOAD_VOXELS)]
    WrongBrickSize { id: BrickId, voxels: usize },
    #[error("the volume has no octree levels")]
    NoLevels,
}

/// The level whose voxels are about one screen pixel: coarser only when a level-0 voxel would
/// be smaller than half a pixel.
pub fn level_for_pixels(voxels_across: f64, pixels_across: f64, level_count: usize) -> u8 {
    // Written to also catch NaN: only positive, finite sizes pick a level.
    if !(pixels_across.is_finite()
        && voxels_across.is_finite()
        && pixels_across > 0.0
        && voxels_across > 0.0)
    {
        return 0;
    }
    let voxels_per_pixel = voxels_across / pixels_across;
    let level = voxels_per_pixel.log2().floor().max(0.0) as usize;
    level.min(level_count.saturating_sub(1)) as u8
}

/// Decoded bricks, least recently used evicted first, bounded in bytes.
pub struct BrickLru {
    budget_bricks: usize,
    bricks: HashMap<BrickId, Arc<Vec<u16>>>,
    order: VecDeque<BrickId>,
}

impl BrickLru {
    /// A cache of at most `budget_bytes` of decoded bricks (and at least
    /// [`MIN_CACHED_BRICKS`]).
    pub fn new(budget_bytes: usize) -> Self {
        BrickLru {
            budget_bricks: (budget_bytes / BRICK_BYTES).max(MIN_CACHED_BRICKS),
            bricks: HashMap::new(),
            order: VecDeque::new(),
        }
    }

    /// The brick if cached, marked as just used.
    pub fn get(&mut self, id: BrickId) -> Option<Arc<Vec<u16>>> {
        let brick = self.bricks.get(&id)?.clone();
        if let Some(pos) = self.order.iter().position(|x| *x == id) {
            self.order.remove(pos);
        }
        self.order.push_back(id);
        Some(brick)
    }

    pub fn contains(&self, id: BrickId) -> bool {
        self.bricks.contains_key(&id)
    }

    /// Keeps `brick`, evicting the least recently used past the bound.
    pub fn insert(&mut self, id: BrickId, brick: Arc<Vec<u16>>) {
        if self.bricks.insert(id, brick).is_some() {
            if let Some(pos) = self.order.iter().position(|x| *x == id) {
                self.order.remove(pos);
            }
        }
        self.order.push_back(id);
        while self.bricks.len() > self.budget_bricks {
            match self.order.pop_front() {
                Some(old) => {
                    self.bricks.remove(&old);
                }
                None => break,
            }
        }
    }

    pub fn len(&self) -> usize {
        self.bricks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bricks.is_empty()
    }

    /// Bytes of decoded voxels held.
    pub fn bytes(&self) -> usize {
        self.bricks.values().map(|b| b.len() * 2).sum()
    }

    /// The most bytes it holds.
    pub fn budget_bytes(&self) -> usize {
        self.budget_bricks * BRICK_BYTES
    }
}

/// One slice being filled.
struct Job {
    request: SliceRequest,
    /// The level actually read (the request's, capped at the coarsest).
    level: usize,
    /// Index of the slice along the normal axis, at `level`.
    slice: u32,
    width: usize,
    height: usize,
    values: Vec<u16>,
    /// Bricks not yet copied in, most useful first.
    remaining: Vec<BrickId>,
    inside_fraction: (f64, f64),
}

impl Job {
    fn new(layout: &OctreeLayout, request: SliceRequest) -> Result<Job, SliceError> {
        let level_count = layout.level_count();
        if level_count == 0 {
            return Err(SliceError::NoLevels);
        }
        let level = (request.level as usize).min(level_count - 1);
        let dims = layout.level_dims[level];
        let scale = (1u64 << level) as f64;
        let frame = request.frame;
        let (n, a, d) = (frame.normal_axis, frame.across_axis, frame.down_axis);
        let slice = ((request.position + 0.5) / scale - 0.5)
            .round()
            .clamp(0.0, dims[n].max(1) as f64 - 1.0) as u32;
        let (width, height) = (dims[a] as usize, dims[d] as usize);
        let bricks = layout.bricks_in_level(level);
        let mut remaining = Vec::with_capacity((bricks[a] * bricks[d]) as usize);
        for bd in 0..bricks[d] {
            for ba in 0..bricks[a] {
                let mut coords = [0u32; 3];
                coords[n] = slice / BRICK_CORE;
                coords[a] = ba;
                coords[d] = bd;
                remaining.push(BrickId::new(level as u8, coords));
            }
        }
        // Most useful first: the middle of the view, where the eye (and usually the anatomy)
        // is, then outwards. The sort is stable, so equal distances keep raster order.
        let centre = |count: u32| count as f64 / 2.0;
        let distance = |id: &BrickId| {
            let da = id.coords[a] as f64 + 0.5 - centre(bricks[a]);
            let dd = id.coords[d] as f64 + 0.5 - centre(bricks[d]);
            da * da + dd * dd
        };
        remaining.sort_by(|x, y| distance(x).total_cmp(&distance(y)));
        let level0 = layout.level_dims[0];
        let inside = |axis: usize| (level0[axis] as f64 / (dims[axis] as f64 * scale)).min(1.0);
        Ok(Job {
            request,
            level,
            slice,
            width,
            height,
            values: vec![0u16; width * height],
            remaining,
            inside_fraction: (inside(a), inside(d)),
        })
    }

    /// Copies the slice's part of brick `id` in, if this slice still waits for it.
    fn copy_in(&mut self, layout: &OctreeLayout, id: BrickId, brick: &[u16]) {
        let Some(pos) = self.remaining.iter().position(|x| *x == id) else {
            return;
        };
        self.remaining.remove(pos);
        let frame = self.request.frame;
        let (n, a, d) = (frame.normal_axis, frame.across_axis, frame.down_axis);
        let dims = layout.level_dims[self.level];
        let core = BRICK_CORE;
        let edge = BRICK_PAYLOAD as usize;
        let (ba, bd) = (id.coords[a], id.coords[d]);
        let mut local = [0usize; 3];
        local[n] = (self.slice - id.coords[n] * core + BRICK_APRON) as usize;
        let a_end = ((ba + 1) * core).min(dims[a]);
        let d_end = ((bd + 1) * core).min(dims[d]);
        for y in bd * core..d_end {
            local[d] = (y - bd * core + BRICK_APRON) as usize;
            let row = y as usize * self.width;
            for x in ba * core..a_end {
                local[a] = (x - ba * core + BRICK_APRON) as usize;
                self.values[row + x as usize] =
                    brick[(local[2] * edge + local[1]) * edge + local[0]];
            }
        }
    }

    fn image(self) -> SliceImage {
        SliceImage {
            request: self.request,
            width: self.width,
            height: self.height,
            values: Arc::new(self.values),
            inside_fraction: self.inside_fraction,
        }
    }
}

/// Where a level-0 voxel's value stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VoxelLookup {
    Value(u16),
    /// Its brick is not cached: offer it, then ask again.
    Needs(BrickId),
}

/// Slices of one store being assembled, one per view, over a shared brick cache.
pub struct SliceAssembler {
    layout: OctreeLayout,
    cache: BrickLru,
    jobs: [Option<Job>; 3],
    /// A slice whose bricks all arrived, until taken.
    finished: [Option<SliceImage>; 3],
}

impl SliceAssembler {
    /// An assembler for a store of this octree shape, caching up to `cache_bytes` of bricks.
    pub fn new(layout: OctreeLayout, cache_bytes: usize) -> Self {
        SliceAssembler {
            layout,
            cache: BrickLru::new(cache_bytes),
            jobs: [None, None, None],
            finished: [None, None, None],
        }
    }

    pub fn layout(&self) -> &OctreeLayout {
        &self.layout
    }

    pub fn cache(&self) -> &BrickLru {
        &self.cache
    }

    /// Starts assembling `request`, replacing its view's unfinished slice (and one finished
    /// but not taken). Cached bricks are copied in at once, so a slice whose bricks are all
    /// cached is finished when this returns.
    pub fn start(&mut self, request: SliceRequest) -> Result<(), SliceError> {
        let view = request.view.index();
        self.finished[view] = None;
        self.jobs[view] = None;
        let mut job = Job::new(&self.layout, request)?;
        for id in job.remaining.clone() {
            if let Some(brick) = self.cache.get(id) {
                job.copy_in(&self.layout, id, &brick);
            }
        }
        self.jobs[view] = Some(job);
        self.settle(request.view);
        Ok(())
    }

    /// The request being assembled for `view`, if unfinished.
    pub fn pending(&self, view: SliceView) -> Option<SliceRequest> {
        self.jobs[view.index()].as_ref().map(|j| j.request)
    }

    /// Drops `view`'s unfinished slice.
    pub fn cancel(&mut self, view: SliceView) {
        self.jobs[view.index()] = None;
    }

    /// The bricks `view`'s slice still needs, most useful first.
    pub fn missing_for(&self, view: SliceView) -> &[BrickId] {
        self.jobs[view.index()]
            .as_ref()
            .map_or(&[], |j| &j.remaining[..])
    }

    /// The bricks every unfinished slice still needs, each once: the views take turns, each
    /// giving its next most useful brick, so no view waits for another's whole slice.
    pub fn missing(&self) -> Vec<BrickId> {
        self.most_useful_missing(usize::MAX)
    }

    /// The first `limit` of [`SliceAssembler::missing`] (a page asking for a few bricks a
    /// frame need not list a large slice's thousands).
    pub fn most_useful_missing(&self, limit: usize) -> Vec<BrickId> {
        let lists: Vec<&[BrickId]> = SliceView::ALL
            .iter()
            .map(|v| self.missing_for(*v))
            .collect();
        let longest = lists.iter().map(|l| l.len()).max().unwrap_or(0);
        let mut out = Vec::new();
        let mut listed = HashSet::new();
        for rank in 0..longest {
            for list in &lists {
                if out.len() >= limit {
                    return out;
                }
                if let Some(&id) = list.get(rank) {
                    if listed.insert(id) {
                        out.push(id);
                    }
                }
            }
        }
        out
    }

    /// A decoded brick arrived (in any order): copied into every slice waiting for it and
    /// kept in the cache. A brick no slice waits for (a probe's) is cached only.
    pub fn offer(&mut self, id: BrickId, brick: Arc<Vec<u16>>) -> Result<(), SliceError> {
        if brick.len() != BRICK_PAYLOAD_VOXELS {
            return Err(SliceError::WrongBrickSize {
                id,
                voxels: brick.len(),
            });
        }
        for view in SliceView::ALL {
            if let Some(job) = self.jobs[view.index()].as_mut() {
                job.copy_in(&self.layout, id, &brick);
            }
            self.settle(view);
        }
        self.cache.insert(id, brick);
        Ok(())
    }

    /// Moves a slice with no bricks left to the finished ones.
    fn settle(&mut self, view: SliceView) {
        let slot = &mut self.jobs[view.index()];
        if slot.as_ref().is_some_and(|j| j.remaining.is_empty()) {
            if let Some(job) = slot.take() {
                self.finished[view.index()] = Some(job.image());
            }
        }
    }

    /// `view`'s slice, once all its bricks arrived (once: the next call gives `None`).
    pub fn take_finished(&mut self, view: SliceView) -> Option<SliceImage> {
        self.finished[view.index()].take()
    }

    /// The stored value of level-0 voxel `index`, if its brick is cached.
    pub fn voxel(&mut self, index: [u32; 3]) -> Result<VoxelLookup, SliceError> {
        let dims = self
            .layout
            .level_dims
            .first()
            .copied()
            .ok_or(SliceError::NoLevels)?;
        if (0..3).any(|a| index[a] >= dims[a]) {
            return Err(SliceError::OutsideVolume { index, dims });
        }
        let id = BrickId::new(0, index.map(|i| i / BRICK_CORE));
        let Some(brick) = self.cache.get(id) else {
            return Ok(VoxelLookup::Needs(id));
        };
        let local = index.map(|i| (i % BRICK_CORE + BRICK_APRON) as usize);
        let edge = BRICK_PAYLOAD as usize;
        Ok(VoxelLookup::Value(
            brick[(local[2] * edge + local[1]) * edge + local[0]],
        ))
    }

    /// Assembles `request` now, reading each brick it needs with `read` (the desktop's reader
    /// thread, with blocking reads).
    pub fn assemble_with<E: From<SliceError>>(
        &mut self,
        request: SliceRequest,
        mut read: impl FnMut(BrickId) -> Result<Vec<u16>, E>,
    ) -> Result<SliceImage, E> {
        let view = request.view;
        self.start(request)?;
        while let Some(&id) = self.missing_for(view).first() {
            let brick = match read(id) {
                Ok(brick) => brick,
                Err(e) => {
                    self.cancel(view);
                    return Err(e);
                }
            };
            if let Err(e) = self.offer(id, Arc::new(brick)) {
                self.cancel(view);
                return Err(e.into());
            }
        }
        // `start` or the last offer finished it.
        self.take_finished(view)
            .ok_or(E::from(SliceError::NoLevels))
    }

    /// The stored value of level-0 voxel `index`, reading its brick with `read` if needed.
    pub fn voxel_with<E: From<SliceError>>(
        &mut self,
        index: [u32; 3],
        read: impl FnOnce(BrickId) -> Result<Vec<u16>, E>,
    ) -> Result<u16, E> {
        match self.voxel(index)? {
            VoxelLookup::Value(v) => Ok(v),
            VoxelLookup::Needs(id) => {
                self.offer(id, Arc::new(read(id)?))?;
                match self.voxel(index)? {
                    VoxelLookup::Value(v) => Ok(v),
                    VoxelLookup::Needs(_) => Err(E::from(SliceError::NoLevels)),
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_follows_voxels_per_pixel() {
        assert_eq!(level_for_pixels(512.0, 600.0, 5), 0);
        assert_eq!(level_for_pixels(512.0, 256.0, 5), 1);
        assert_eq!(level_for_pixels(4096.0, 300.0, 8), 3);
        assert_eq!(level_for_pixels(4096.0, 1.0, 3), 2);
        assert_eq!(level_for_pixels(f64::NAN, 1.0, 3), 0);
    }

    #[test]
    fn the_cache_stays_within_its_byte_bound_and_evicts_the_least_recently_used() {
        let budget = 10 * BRICK_BYTES + BRICK_BYTES / 2;
        let mut lru = BrickLru::new(budget);
        assert_eq!(lru.budget_bytes(), 10 * BRICK_BYTES);
        let brick = |v: u16| Arc::new(vec![v; BRICK_PAYLOAD_VOXELS]);
        for i in 0..30u32 {
            lru.insert(BrickId::new(0, [i, 0, 0]), brick(i as u16));
            assert!(lru.bytes() <= budget, "after {i}: {} bytes", lru.bytes());
            // Brick 0 is used after every insert: it must survive.
            assert!(lru.get(BrickId::new(0, [0, 0, 0])).is_some(), "after {i}");
        }
        assert_eq!(lru.len(), 10);
        assert!(!lru.contains(BrickId::new(0, [1, 0, 0])));
        assert!(lru.contains(BrickId::new(0, [29, 0, 0])));
        // Brick 0 and the nine newest.
        assert!(lru.contains(BrickId::new(0, [21, 0, 0])));
        assert!(!lru.contains(BrickId::new(0, [20, 0, 0])));
    }

    #[test]
    fn a_brick_of_the_wrong_size_is_refused() {
        let mut assembler = SliceAssembler::new(OctreeLayout::new([40, 40, 40]), 1 << 20);
        let id = BrickId::new(0, [0, 0, 0]);
        assert_eq!(
            assembler.offer(id, Arc::new(vec![0; 10])),
            Err(SliceError::WrongBrickSize { id, voxels: 10 })
        );
        assert!(matches!(
            assembler.voxel([40, 0, 0]),
            Err(SliceError::OutsideVolume { .. })
        ));
        assert_eq!(assembler.voxel([1, 2, 3]), Ok(VoxelLookup::Needs(id)));
    }
}
