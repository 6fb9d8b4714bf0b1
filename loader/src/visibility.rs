//! Visibility feedback (octree paper §6): the renderer marks each page where a sample
//! contributed before its ray terminated; the loader reads that buffer a frame or two late
//! without stalling, propagates it up the octree (an inner node is visible when any of its
//! pages is) and refines only visible nodes. A page stays visible for a few feedback frames so
//! one noisy frame does not make the cut flicker; after that, invisible nodes age out.
//!
//! Marks are per level-0 page, not per node, so a frame rendered with an older cut still says
//! the right thing about the current one.

use strata_storage::BrickId;

use crate::octree_ranges::OctreeRanges;

/// Shared with the selection thread behind an `Arc` (copied on write when it still holds it).
#[derive(Clone)]
pub struct PageVisibility {
    page_dims: [u32; 3],
    /// Feedback frame (1-based count) in which each page was last seen contributing; 0 = never.
    last_visible: Vec<u64>,
    frames_received: u64,
    /// Render frame number of the newest feedback.
    newest_render_frame: u64,
    memory_frames: u64,
    /// Per level: is any page under the node visible (rebuilt on each feedback frame).
    pyramid: Vec<Vec<bool>>,
    level_bricks: Vec<[u32; 3]>,
}

impl PageVisibility {
    pub fn new(octree: &OctreeRanges, memory_frames: u64) -> Self {
        let page_dims = octree.page_dims();
        let pages = page_dims.iter().map(|&d| d as usize).product();
        let level_bricks: Vec<[u32; 3]> = (0..octree.level_count())
            .map(|l| octree.bricks_in_level(l))
            .collect();
        PageVisibility {
            page_dims,
            last_visible: vec![0; pages],
            frames_received: 0,
            newest_render_frame: 0,
            memory_frames: memory_frames.max(1),
            pyramid: Vec::new(),
            level_bricks,
        }
    }

    pub fn frames_received(&self) -> u64 {
        self.frames_received
    }

    /// Render frame number the newest feedback came from (0 before any).
    pub fn newest_render_frame(&self) -> u64 {
        self.newest_render_frame
    }

    /// Takes one feedback buffer (one u32 per page, non-zero = visible).
    pub fn record(&mut self, render_frame: u64, marks: &[u32]) {
        if marks.len() != self.last_visible.len() || render_frame <= self.newest_render_frame {
            return;
        }
        self.frames_received += 1;
        self.newest_render_frame = render_frame;
        for (last, &mark) in self.last_visible.iter_mut().zip(marks) {
            if mark != 0 {
                *last = self.frames_received;
            }
        }
        self.rebuild_pyramid();
    }

    fn rebuild_pyramid(&mut self) {
        let now = self.frames_received;
        let memory = self.memory_frames;
        let level0: Vec<bool> = self
            .last_visible
            .iter()
            .map(|&t| t > 0 && now - t < memory)
            .collect();
        let mut pyramid = vec![level0];
        for level in 1..self.level_bricks.len() {
            let [cx, cy, cz] = self.level_bricks[level - 1];
            let [px, py, pz] = self.level_bricks[level];
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
        self.pyramid = pyramid;
    }

    /// Before any feedback everything counts as visible, so the first frames refine normally.
    pub fn is_visible(&self, id: BrickId) -> bool {
        let Some(level) = self.pyramid.get(id.level as usize) else {
            return true;
        };
        let [bx, by, _] = self.level_bricks[id.level as usize];
        let [x, y, z] = id.coords;
        level
            .get((x + bx * (y + by * z)) as usize)
            .copied()
            .unwrap_or(true)
    }

    pub fn visible_pages(&self) -> usize {
        self.pyramid
            .first()
            .map_or(0, |p| p.iter().filter(|&&v| v).count())
    }

    pub fn page_dims(&self) -> [u32; 3] {
        self.page_dims
    }
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
        vis.record(2, &[0; 8]);
        assert!(vis.is_visible(leaf), "remembered for memory_frames");
        vis.record(3, &[0; 8]);
        assert!(!vis.is_visible(leaf), "aged out");
        vis.record(3, &marks);
        assert!(
            !vis.is_visible(leaf),
            "an older or repeated frame is ignored"
        );
    }
}
