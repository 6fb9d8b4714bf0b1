//! Flood over voxels brick by brick: what the slice fill, region growing and island removal
//! share.
//!
//! State is kept per brick (the voxels seen and accepted as bitsets, the labels and values when
//! the test needs them), so memory grows with the bricks the region reaches, not the volume,
//! and most neighbour steps stay inside the current brick without a lookup. The queue holds each
//! accepted voxel once, so it is bounded by the voxel cap.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use rustc_hash::FxHashMap;

use crate::grid::{BrickKey, LabelGrid, LABEL_BRICK_VOXELS};
use crate::intensity::Intensity;
use crate::layer::{EditWriter, LabelLayer};
use crate::{Label, SegmentError};

/// How often (in accepted voxels) progress is reported and the cancel flag read.
pub const PROGRESS_EVERY_VOXELS: u64 = 1 << 16;

const WORDS: usize = LABEL_BRICK_VOXELS / 64;

/// What a flood needs per brick.
pub(crate) struct FloodBrick {
    pub key: BrickKey,
    labels: Option<Arc<[Label]>>,
    values: Option<Box<[f32]>>,
    seen: Box<[u64]>,
    pub accepted: Box<[u64]>,
}

/// A flood's inputs.
pub(crate) struct Flood<'a> {
    pub layer: &'a LabelLayer,
    pub intensity: Option<&'a dyn Intensity>,
    /// Index axes the flood steps along (both directions): [0, 1] for 4-connected in an axial
    /// slice, [0, 1, 2] for 6-connected in 3D.
    pub axes: &'a [usize],
    pub max_voxels: u64,
    pub cancel: Option<&'a AtomicBool>,
}

/// The region a flood reached.
pub(crate) struct FloodRegion {
    pub bricks: Vec<FloodBrick>,
    pub voxels: u64,
    /// Whether the cap stopped it with more to take.
    pub stopped_at_cap: bool,
}

impl FloodRegion {
    /// Writes `label` into every accepted voxel (the test already excluded what must stay).
    pub fn write(&self, w: &mut EditWriter<'_>, label: Label) -> Result<(), SegmentError> {
        for b in &self.bricks {
            if b.accepted.iter().all(|&word| word == 0) {
                continue;
            }
            let work = w.brick_mut(b.key)?;
            for (word_at, &word) in b.accepted.iter().enumerate() {
                let mut bits = word;
                while bits != 0 {
                    let at = word_at * 64 + bits.trailing_zeros() as usize;
                    work[at] = label;
                    bits &= bits - 1;
                }
            }
        }
        Ok(())
    }
}

struct State<'a> {
    flood: &'a Flood<'a>,
    grid: &'a LabelGrid,
    needs_labels: bool,
    needs_values: bool,
    bricks: Vec<FloodBrick>,
    index: FxHashMap<BrickKey, usize>,
}

impl State<'_> {
    fn brick(&mut self, key: BrickKey) -> Result<usize, SegmentError> {
        if let Some(&at) = self.index.get(&key) {
            return Ok(at);
        }
        let labels = if self.needs_labels {
            Some(self.flood.layer.brick(key)?)
        } else {
            None
        };
        let values = match (self.needs_values, self.flood.intensity) {
            (true, Some(intensity)) => {
                let mut v = vec![0.0; LABEL_BRICK_VOXELS].into_boxed_slice();
                intensity.read_brick(self.grid, key, &mut v)?;
                Some(v)
            }
            _ => None,
        };
        self.bricks.push(FloodBrick {
            key,
            labels,
            values,
            seen: vec![0; WORDS].into_boxed_slice(),
            accepted: vec![0; WORDS].into_boxed_slice(),
        });
        self.index.insert(key, self.bricks.len() - 1);
        Ok(self.bricks.len() - 1)
    }
}

/// Floods from `seed` through voxels for which `accept(label, value)` holds (label and value
/// are read only when `needs_labels` / `needs_values`; otherwise 0 and NaN are passed).
/// `progress(voxels)` is called every [`PROGRESS_EVERY_VOXELS`]; the cancel flag ends it with
/// [`SegmentError::Cancelled`].
pub(crate) fn flood(
    flood: &Flood<'_>,
    seed: [u32; 3],
    needs_labels: bool,
    needs_values: bool,
    accept: &dyn Fn(Label, f32) -> bool,
    progress: &mut dyn FnMut(u64),
) -> Result<FloodRegion, SegmentError> {
    let grid = flood.layer.grid();
    if !grid.contains(seed.map(i64::from)) {
        return Err(SegmentError::OutOfBounds {
            voxel: seed.map(i64::from),
            dims: grid.dims(),
        });
    }
    if needs_values && flood.intensity.is_none() {
        return Err(SegmentError::BadParameter(
            "this tool reads the primary volume, and none was given".into(),
        ));
    }
    let mut state = State {
        flood,
        grid,
        needs_labels,
        needs_values,
        bricks: Vec::new(),
        index: FxHashMap::default(),
    };
    let dims = grid.dims();
    let mut queue: VecDeque<[u32; 3]> = VecDeque::new();
    let mut voxels = 0u64;
    let mut stopped_at_cap = false;

    // Tests one voxel, marks it seen, and queues it when accepted; false once the cap is hit.
    let visit = |state: &mut State<'_>,
                 queue: &mut VecDeque<[u32; 3]>,
                 voxels: &mut u64,
                 brick_at: usize,
                 voxel: [u32; 3],
                 at: usize|
     -> bool {
        let fb = &mut state.bricks[brick_at];
        let (word, bit) = (at / 64, 1u64 << (at % 64));
        if fb.seen[word] & bit != 0 {
            return true;
        }
        let label = fb.labels.as_ref().map_or(0, |l| l[at]);
        let value = fb.values.as_ref().map_or(f32::NAN, |v| v[at]);
        if !accept(label, value) {
            fb.seen[word] |= bit;
            return true;
        }
        if *voxels >= flood.max_voxels {
            // Left unseen: the region is kept as it is and the caller is told it was cut.
            return false;
        }
        fb.seen[word] |= bit;
        fb.accepted[word] |= bit;
        *voxels += 1;
        queue.push_back(voxel);
        true
    };

    let (key, at) = grid.brick_of(seed);
    let seed_brick = state.brick(key)?;
    if !visit(&mut state, &mut queue, &mut voxels, seed_brick, seed, at) {
        stopped_at_cap = true;
    }
    let mut reported = 0u64;
    'flood: while let Some(voxel) = queue.pop_front() {
        if voxels >= reported + PROGRESS_EVERY_VOXELS {
            reported = voxels;
            progress(voxels);
            if flood.cancel.is_some_and(|c| c.load(Ordering::Relaxed)) {
                return Err(SegmentError::Cancelled);
            }
        }
        let (key, _) = grid.brick_of(voxel);
        let here = state.brick(key)?;
        for &axis in flood.axes {
            for step in [-1i64, 1] {
                let n = i64::from(voxel[axis]) + step;
                if n < 0 || n >= i64::from(dims[axis]) {
                    continue;
                }
                let mut next = voxel;
                next[axis] = n as u32;
                let (next_key, next_at) = grid.brick_of(next);
                // Most steps stay in the brick: no lookup then.
                let brick_at = if next_key == key {
                    here
                } else {
                    state.brick(next_key)?
                };
                if !visit(&mut state, &mut queue, &mut voxels, brick_at, next, next_at) {
                    stopped_at_cap = true;
                    break 'flood;
                }
            }
        }
    }
    progress(voxels);
    Ok(FloodRegion {
        bricks: state.bricks,
        voxels,
        stopped_at_cap,
    })
}
