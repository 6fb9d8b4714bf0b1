//! Visibility feedback (octree paper §6): the renderer marks each page where a sample
//! contributed before its ray terminated; the loader reads that buffer a frame or two late
//! without stalling, propagates it up the octree (an inner node is visible when any of its
//! pages is) and refines only visible nodes. A page stays visible until the cut changed a few
//! times since it was last seen contributing (cut *generations*, not frames: issue 35), so
//! one noisy frame does not make the cut flicker, and after that invisible nodes age out.
//!
//! Why generations: counted in frames, the memory depended on the frame rate. A fast GPU
//! draws ~7.5 frames per selection at 1024³, so with 3 frames of memory every mark a
//! selection saw came from the cut then current, and selection became a memoryless map
//! cut → marks(cut) → cut, which at the H200 cycled between two cuts forever (leaves 8387 ↔
//! 8373; with the octree 725 cut changes in 4500 still frames). Counted in generations, a
//! mark lasts while the cut it was seen under, and the next few, are drawn, however many
//! frames that is: while a still view's cut holds, nothing ages, and the marks of two cuts
//! that would alternate are both remembered by the selection after them.
//!
//! Marks are per region of page cells, not per node, so a frame rendered with an older cut
//! still says the right thing about the current one. Two ways to keep them: per page cell for
//! the flat traversal (whose grid is bounded by a binding limit anyway), and per visible leaf
//! block for the octree traversal, whose grids reach 512³ cells (16384³ voxels) while a frame
//! sees a few thousand leaves: then memory and the work per feedback frame grow with the
//! visible part of the cut, not with the volume (issue 18).

use rustc_hash::{FxHashMap as HashMap, FxHashSet as HashSet};
use strata_render::VisibilityFrame;
use strata_types::BrickId;

use crate::octree_ranges::OctreeRanges;

/// A block of page cells: (size, origin >> size), 2^size cells per axis; the key of an octree
/// node of that level.
type Block = (u8, [u32; 3]);

#[derive(Clone)]
enum Marks {
    /// Per page cell.
    Dense {
        /// Cut generation (1-based) under which each page was last seen contributing;
        /// 0 = never.
        last_visible: Vec<u64>,
        /// Per level: is any page under the node visible (rebuilt on each feedback frame).
        pyramid: Vec<Vec<bool>>,
        level_bricks: Vec<[u32; 3]>,
    },
    /// Per visible leaf block of the frames' cuts.
    Sparse {
        /// Cut generation under which each block was last seen contributing (blocks aged
        /// out are dropped, so this holds what the last `memory` generations saw).
        last_seen: HashMap<Block, u64>,
        /// The blocks still remembered as visible.
        visible: HashSet<Block>,
        /// Every strict ancestor block of a visible block: nodes with a visible part.
        above: HashSet<Block>,
        /// The coarsest level a node or block can have.
        top_level: u8,
    },
}

/// Shared with the selection thread behind an `Arc` (copied on write when it still holds it).
#[derive(Clone)]
pub struct PageVisibility {
    page_dims: [u32; 3],
    frames_received: u64,
    /// Render frame number of the newest feedback.
    newest_render_frame: u64,
    /// Generations a mark is remembered for after the one it was last seen under.
    memory: u64,
    /// The current cut generation (1 = the first cut).
    generation: u64,
    /// (first render frame, generation) of the recent generations, oldest first: a frame's
    /// feedback arrives a frame or more late and counts for the generation it was drawn
    /// with.
    generation_starts: std::collections::VecDeque<(u64, u64)>,
    marks: Marks,
}

/// Generations whose first frames are kept for dating late feedback (feedback is at most a
/// few frames late; a frame older than all of them counts as seen long ago).
const GENERATIONS_KEPT: usize = 32;

impl PageVisibility {
    /// Marks per page cell (the flat traversal).
    pub fn new(octree: &OctreeRanges, memory_generations: u64) -> Self {
        let page_dims = octree.page_dims();
        let pages = page_dims.iter().map(|&d| d as usize).product();
        let level_bricks: Vec<[u32; 3]> = (0..octree.level_count())
            .map(|l| octree.bricks_in_level(l))
            .collect();
        PageVisibility {
            page_dims,
            frames_received: 0,
            newest_render_frame: 0,
            memory: memory_generations.max(1),
            generation: 1,
            generation_starts: [(0, 1)].into(),
            marks: Marks::Dense {
                last_visible: vec![0; pages],
                pyramid: Vec::new(),
                level_bricks,
            },
        }
    }

    /// Marks per visible leaf block (the octree traversal): O(visible leaves · depth).
    pub fn per_leaf(octree: &OctreeRanges, memory_generations: u64) -> Self {
        let page_dims = octree.page_dims();
        let max = page_dims.iter().copied().max().unwrap_or(1).max(1);
        let grid_level = (32 - (max - 1).leading_zeros()) as u8;
        PageVisibility {
            page_dims,
            frames_received: 0,
            newest_render_frame: 0,
            memory: memory_generations.max(1),
            generation: 1,
            generation_starts: [(0, 1)].into(),
            marks: Marks::Sparse {
                last_seen: HashMap::default(),
                visible: HashSet::default(),
                above: HashSet::default(),
                top_level: grid_level.max(octree.level_count().saturating_sub(1)),
            },
        }
    }

    pub fn frames_received(&self) -> u64 {
        self.frames_received
    }

    /// The current cut generation.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// A new cut is drawn from render frame `first_render_frame` on: marks last seen more
    /// than the memory's generations ago age out now (and only now: frames alone age
    /// nothing).
    pub fn start_generation(&mut self, first_render_frame: u64) {
        self.generation += 1;
        self.generation_starts
            .push_back((first_render_frame, self.generation));
        while self.generation_starts.len() > GENERATIONS_KEPT {
            self.generation_starts.pop_front();
        }
        self.refresh();
    }

    /// The generation render frame `render_frame` was drawn with; 0 (long ago) when older
    /// than every generation kept.
    fn generation_of(&self, render_frame: u64) -> u64 {
        self.generation_starts
            .iter()
            .rev()
            .find(|&&(first, _)| first <= render_frame)
            .map_or(0, |&(_, g)| g)
    }

    /// Rebuilds what counts as visible from the marks, the generation and the memory.
    fn refresh(&mut self) {
        let (now, memory) = (self.generation, self.memory);
        match &mut self.marks {
            Marks::Dense {
                last_visible,
                pyramid,
                level_bricks,
            } => *pyramid = dense_pyramid(last_visible, level_bricks, now, memory),
            Marks::Sparse {
                last_seen,
                visible,
                above,
                top_level,
            } => {
                last_seen.retain(|_, &mut t| now - t < memory);
                visible.clear();
                above.clear();
                for &(size, coords) in last_seen.keys() {
                    visible.insert((size, coords));
                    for level in size + 1..=*top_level {
                        let shift = (level - size) as u32;
                        if !above.insert((level, coords.map(|c| c >> shift))) {
                            // Its ancestors are in already.
                            break;
                        }
                    }
                }
            }
        }
    }

    /// Render frame number the newest feedback came from (0 before any).
    pub fn newest_render_frame(&self) -> u64 {
        self.newest_render_frame
    }

    /// Takes one frame's feedback: its per-leaf words with the per-leaf marks, else its
    /// per-page words. Older or repeated frames are ignored.
    pub fn record_frame(&mut self, frame: &VisibilityFrame) {
        match (&self.marks, &frame.leaf_visibility) {
            (Marks::Sparse { .. }, Some(leaf)) => {
                let blocks = leaf
                    .leaves
                    .boxes
                    .iter()
                    .zip(&leaf.marks)
                    .filter(|(_, &m)| m != 0)
                    .map(|(b, _)| (b.size, b.origin.map(|c| c >> b.size)));
                self.record_blocks(frame.frame_number, blocks);
            }
            _ => self.record(frame.frame_number, &frame.visibility),
        }
    }

    /// Takes one feedback buffer (one u32 per page, non-zero = visible).
    pub fn record(&mut self, render_frame: u64, marks: &[u32]) {
        let pages: usize = self.page_dims.iter().map(|&d| d as usize).product();
        if marks.len() != pages || render_frame <= self.newest_render_frame {
            return;
        }
        if let Marks::Sparse { .. } = self.marks {
            let [nx, ny, _] = self.page_dims;
            let blocks: Vec<Block> = marks
                .iter()
                .enumerate()
                .filter(|(_, &m)| m != 0)
                .map(|(i, _)| {
                    let i = i as u32;
                    (0, [i % nx, (i / nx) % ny, i / (nx * ny)])
                })
                .collect();
            self.record_blocks(render_frame, blocks.into_iter());
            return;
        }
        self.frames_received += 1;
        self.newest_render_frame = render_frame;
        let seen = self.generation_of(render_frame);
        if let Marks::Dense { last_visible, .. } = &mut self.marks {
            for (last, &mark) in last_visible.iter_mut().zip(marks) {
                if mark != 0 {
                    *last = (*last).max(seen);
                }
            }
        }
        self.refresh();
    }

    fn record_blocks(&mut self, render_frame: u64, blocks: impl Iterator<Item = Block>) {
        if render_frame <= self.newest_render_frame {
            return;
        }
        self.frames_received += 1;
        self.newest_render_frame = render_frame;
        let seen = self.generation_of(render_frame);
        let Marks::Sparse { last_seen, .. } = &mut self.marks else {
            return;
        };
        for b in blocks {
            let last = last_seen.entry(b).or_insert(seen);
            *last = (*last).max(seen);
        }
        self.refresh();
    }

    /// Before any feedback everything counts as visible, so the first frames refine normally.
    pub fn is_visible(&self, id: BrickId) -> bool {
        if self.frames_received == 0 {
            return true;
        }
        match &self.marks {
            Marks::Dense {
                pyramid,
                level_bricks,
                ..
            } => {
                let Some(level) = pyramid.get(id.level as usize) else {
                    return true;
                };
                let [bx, by, _] = level_bricks[id.level as usize];
                let [x, y, z] = id.coords;
                level
                    .get((x + bx * (y + by * z)) as usize)
                    .copied()
                    .unwrap_or(true)
            }
            Marks::Sparse {
                visible,
                above,
                top_level,
                ..
            } => {
                if above.contains(&(id.level, id.coords)) {
                    return true;
                }
                // Inside a visible block (the block itself or one of its ancestors).
                (id.level..=(*top_level).max(id.level)).any(|level| {
                    let shift = (level - id.level) as u32;
                    visible.contains(&(level, id.coords.map(|c| c >> shift)))
                })
            }
        }
    }

    /// Page cells remembered as visible.
    pub fn visible_pages(&self) -> usize {
        match &self.marks {
            Marks::Dense { pyramid, .. } => pyramid
                .first()
                .map_or(0, |p| p.iter().filter(|&&v| v).count()),
            Marks::Sparse { visible, .. } => visible
                .iter()
                .map(|&(size, coords)| {
                    (0..3)
                        .map(|a| {
                            let lo = (coords[a] as u64) << size;
                            let hi = ((coords[a] as u64 + 1) << size).min(self.page_dims[a] as u64);
                            hi.saturating_sub(lo) as usize
                        })
                        .product::<usize>()
                })
                .sum(),
        }
    }

    pub fn page_dims(&self) -> [u32; 3] {
        self.page_dims
    }

    /// CPU bytes of the marks (the dense ones are per page cell).
    pub fn memory_bytes(&self) -> usize {
        match &self.marks {
            Marks::Dense {
                last_visible,
                pyramid,
                ..
            } => last_visible.capacity() * 8 + pyramid.iter().map(Vec::capacity).sum::<usize>(),
            Marks::Sparse {
                last_seen,
                visible,
                above,
                ..
            } => {
                let entry = size_of::<Block>() + 1;
                last_seen.capacity() * (entry + 8) + (visible.capacity() + above.capacity()) * entry
            }
        }
    }
}

/// Per level, is any page under the node visible within the last `memory` cut generations.
fn dense_pyramid(
    last_visible: &[u64],
    level_bricks: &[[u32; 3]],
    now: u64,
    memory: u64,
) -> Vec<Vec<bool>> {
    let level0: Vec<bool> = last_visible
        .iter()
        .map(|&t| t > 0 && now - t < memory)
        .collect();
    let mut pyramid = vec![level0];
    for level in 1..level_bricks.len() {
        let [cx, cy, cz] = level_bricks[level - 1];
        let [px, py, pz] = level_bricks[level];
        let mut up = vec![false; (px * py * pz) as usize];
        let child = &pyramid[level - 1];
        for z in 0..cz {
            for y in 0..cy {
                for x in 0..cx {
                    if child[(x + cx * (y + cy * z)) as usize] {
                        up[(x / 2 + px * (y / 2 + py * (z / 2))) as usize] = true;
                    }
                }
            }
        }
        pyramid.push(up);
    }
    pyramid
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::octree_ranges::StoredRange;

    #[test]
    fn marks_propagate_up_and_age_out() {
        let octree = OctreeRanges::from_fn(&[[2, 2, 2], [1, 1, 1]], |_, _| StoredRange {
            min: 0,
            max: 1,
        });
        let mut vis = PageVisibility::new(&octree, 2);
        let leaf = BrickId::new(0, [1, 0, 0]);
        let other = BrickId::new(0, [0, 1, 0]);
        assert!(vis.is_visible(other), "no feedback yet: everything visible");
        let mut marks = vec![0u32; 8];
        marks[1] = 1;
        vis.record(1, &marks);
        assert!(vis.is_visible(leaf) && !vis.is_visible(other));
        assert!(
            vis.is_visible(BrickId::new(1, [0, 0, 0])),
            "parent of a visible page is visible"
        );
        // Frames alone age nothing: a still view's cut may be drawn any number of times.
        for frame in 2..50 {
            vis.record(frame, &[0; 8]);
        }
        assert!(vis.is_visible(leaf), "frames must not age a mark");
        vis.start_generation(50);
        vis.record(50, &[0; 8]);
        assert!(
            vis.is_visible(leaf),
            "remembered for the memory's generations"
        );
        vis.start_generation(51);
        assert!(!vis.is_visible(leaf), "aged out two cuts later");
        vis.record(50, &marks);
        assert!(
            !vis.is_visible(leaf),
            "an older or repeated frame is ignored"
        );
    }

    /// Feedback arrives a frame or more late: a frame drawn with the previous cut counts for
    /// that cut's generation, not for the one current when it arrives.
    #[test]
    fn late_feedback_counts_for_the_cut_it_was_drawn_with() {
        let octree = OctreeRanges::from_fn(&[[2, 2, 2], [1, 1, 1]], |_, _| StoredRange {
            min: 0,
            max: 1,
        });
        let mut vis = PageVisibility::new(&octree, 2);
        let leaf = BrickId::new(0, [1, 0, 0]);
        let mut marks = vec![0u32; 8];
        marks[1] = 1;
        // Cuts change at frames 5 and 9; frame 4 (generation 1) is read back after both.
        vis.start_generation(5);
        vis.start_generation(9);
        vis.record(4, &marks);
        assert!(
            !vis.is_visible(leaf),
            "a mark two generations old is aged out on arrival"
        );
        vis.record(8, &marks);
        assert!(
            vis.is_visible(leaf),
            "a mark of the previous generation counts"
        );
        vis.start_generation(12);
        assert!(!vis.is_visible(leaf));
    }

    /// Every node of a 4³-page octree.
    fn nodes() -> Vec<BrickId> {
        (0..3u8)
            .flat_map(|level| {
                let n = 4u32 >> level;
                (0..n * n * n).map(move |i| BrickId::new(level, [i % n, (i / n) % n, i / (n * n)]))
            })
            .collect()
    }

    fn octree() -> OctreeRanges {
        OctreeRanges::from_fn(&[[4, 4, 4], [2, 2, 2], [1, 1, 1]], |_, _| StoredRange {
            min: 0,
            max: 1,
        })
    }

    #[test]
    fn marks_per_leaf_block_answer_as_marks_per_page() {
        let octree = octree();
        let mut dense = PageVisibility::new(&octree, 2);
        let mut sparse = PageVisibility::per_leaf(&octree, 2);
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        for frame in 1..=12 {
            let marks: Vec<u32> = (0..64)
                .map(|_| {
                    seed ^= seed << 13;
                    seed ^= seed >> 7;
                    seed ^= seed << 17;
                    u32::from(seed.is_multiple_of(9))
                })
                .collect();
            if frame % 3 == 0 {
                dense.start_generation(frame);
                sparse.start_generation(frame);
            }
            dense.record(frame, &marks);
            sparse.record(frame, &marks);
            for id in nodes() {
                assert_eq!(
                    sparse.is_visible(id),
                    dense.is_visible(id),
                    "frame {frame}: {id:?}"
                );
            }
            assert_eq!(
                sparse.visible_pages(),
                dense.visible_pages(),
                "frame {frame}"
            );
        }
    }

    #[test]
    fn a_visible_coarse_block_covers_its_descendants_and_ancestors_only() {
        let octree = octree();
        let mut vis = PageVisibility::per_leaf(&octree, 1);
        // The level-1 block at (1, 0, 0): page cells x 2..4, y 0..2, z 0..2.
        vis.record_blocks(1, [(1, [1, 0, 0])].into_iter());
        for id in nodes() {
            let inside = (0..3).all(|a| {
                let lo = id.coords[a] << id.level;
                let hi = (id.coords[a] + 1) << id.level;
                let (blo, bhi) = if a == 0 { (2, 4) } else { (0, 2) };
                lo < bhi && blo < hi
            });
            assert_eq!(vis.is_visible(id), inside, "{id:?}");
        }
        assert_eq!(vis.visible_pages(), 8);
        // The next cut's frame sees nothing: with one generation of memory, nothing stays
        // visible, and nothing stays held.
        vis.start_generation(2);
        vis.record_blocks(2, std::iter::empty());
        assert!(nodes().iter().all(|&id| !vis.is_visible(id)));
        assert_eq!(vis.visible_pages(), 0);
    }
}
