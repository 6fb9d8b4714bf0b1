//! The resident cut's node payloads for a CPU pass beside the raycaster (the viewer's adaptive
//! oracle, which reads every resident node's voxels): taken on the frame thread as a snapshot
//! of what the CPU cache still holds and of the root, whose copy the volume keeps since it
//! never passes through the CPU cache (reference counts only, nothing copied or read), the rest
//! read through the volume source later, on whichever thread builds from it. The GPU slots keep
//! no CPU copy, so a brick the CPU cache evicted since its upload must come from the source.

use std::sync::Arc;

use rustc_hash::FxHashMap as HashMap;
use strata_render::{BrickSource, PageTable};
use strata_source::VolumeSource;
use strata_types::BrickId;

use crate::cpu_cache::{Brick, CpuBrickCache};
use crate::error::LoaderError;

/// The payload of every node a page table references as resident, by (level, node).
pub struct CutPayloads {
    table: Arc<PageTable>,
    bricks: HashMap<(u8, [u32; 3]), Brick>,
    missing: Vec<BrickId>,
    source: Arc<dyn VolumeSource>,
}

impl CutPayloads {
    /// What `cpu` holds of `table`'s resident nodes; the others are listed for
    /// [`CutPayloads::read_missing`]. Cheap: one hash lookup per node, no LRU change (the
    /// snapshot must not make the loader keep or drop anything it would not have).
    pub(crate) fn snapshot(
        table: Arc<PageTable>,
        cpu: &CpuBrickCache,
        (root, root_brick): (BrickId, &Brick),
        source: Arc<dyn VolumeSource>,
    ) -> CutPayloads {
        let mut bricks = HashMap::default();
        let mut missing = Vec::new();
        for (i, e) in table.entries.iter().enumerate() {
            if !e.resident {
                continue;
            }
            let node = PageTable::node_of(table.page_of_linear(i), e.level);
            if bricks.contains_key(&(e.level, node)) {
                continue;
            }
            let id = BrickId::new(e.level, node);
            // The root never passes through the CPU cache (streaming.rs reads it once).
            let held = match id == root {
                true => Some(root_brick.clone()),
                false => cpu.peek(id),
            };
            match held {
                Some(brick) => {
                    bricks.insert((e.level, node), brick);
                }
                None => missing.push(id),
            }
        }
        missing.sort_unstable();
        missing.dedup();
        CutPayloads {
            table,
            bricks,
            missing,
            source,
        }
    }

    /// The page table the payloads belong to.
    pub fn table(&self) -> &Arc<PageTable> {
        &self.table
    }

    /// Nodes still to read from the source.
    pub fn missing(&self) -> usize {
        self.missing.len()
    }

    /// Nodes held.
    pub fn len(&self) -> usize {
        self.bricks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bricks.is_empty()
    }

    /// Reads the nodes the CPU cache no longer held, verified, through the source. Blocks on
    /// the disk or the network: never call it on a frame or UI thread. `cancelled` is checked
    /// between reads, so a superseded build stops early (Ok(false): not complete).
    pub fn read_missing(&mut self, cancelled: impl Fn() -> bool) -> Result<bool, LoaderError> {
        while let Some(&id) = self.missing.last() {
            if cancelled() {
                return Ok(false);
            }
            let brick = self.source.read_brick(id)?;
            self.bricks.insert((id.level, id.coords), Arc::new(brick));
            self.missing.pop();
        }
        Ok(true)
    }
}

impl BrickSource for CutPayloads {
    fn brick(&self, level: u8, node: [u32; 3]) -> Option<&[u16]> {
        self.bricks.get(&(level, node)).map(|b| b.as_slice())
    }
}
