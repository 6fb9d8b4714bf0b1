//! Flood over voxels brick by brick: what the slice fill and region growing share.
//!
//! State is kept per brick (which voxels the test admits and which were taken, as bitsets: 8 KiB),
//! so memory grows with the bricks the region reaches, not the volume.
//! The flood drains one brick at a time and works on rows of 32 voxels along i as bit masks: an
//! offered row takes the admitted runs along i that touch the offer (a few shifts), then passes
//! its taken bits to the rows beside it along j and k, and runs reaching a face to the brick
//! beside it. A voxel-by-voxel breadth-first queue over the whole volume instead walks a
//! wavefront through every brick at once and misses the cache on almost every step (on a 49 M
//! voxel region of a 512³ volume, on a loaded 2-core machine: BFS 28.9 s wall, voxel stacks per
//! brick 7.6 s wall / 2.9 s CPU, rows 3.5 s wall / 1.2 s CPU). Work lists hold rows, each taken
//! voxel is counted once, and the cap is checked as bits are taken: under a cap, what is kept
//! is connected to the seed (taken runs grow one voxel at a time at the end) but is not a
//! breadth-first ball.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};

use rustc_hash::FxHashMap;

use crate::grid::{BrickKey, LabelGrid, LABEL_BRICK, LABEL_BRICK_VOXELS};
use crate::intensity::Intensity;
use crate::layer::{EditWriter, LabelLayer};
use crate::{Label, SegmentError};

/// How often (in accepted voxels) progress is reported and the cancel flag read.
pub const PROGRESS_EVERY_VOXELS: u64 = 1 << 16;

const WORDS: usize = LABEL_BRICK_VOXELS / 64;

/// What a flood needs per brick: 8 KiB, whatever the volume's type.
pub(crate) struct FloodBrick {
    pub key: BrickKey,
    /// The voxels the test admits (inside the grid only), evaluated once for the whole brick
    /// when the flood first reaches it: a tight loop the compiler vectorises, after which the
    /// labels and values are dropped and every step is a bit test in 4 KiB.
    eligible: Box<[u64]>,
    pub accepted: Box<[u64]>,
    /// Rows (j + 32·k) that took voxels not yet passed on to their neighbour rows.
    pending: Vec<u16>,
    /// Voxels offered by neighbour bricks: (row, bits along i).
    incoming: Vec<(u16, u32)>,
    queued: bool,
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
                if word == u64::MAX {
                    // Inside a large region whole words are taken: one fill, not 64 writes.
                    work[word_at * 64..word_at * 64 + 64].fill(label);
                    continue;
                }
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

struct State<'a, F> {
    flood: &'a Flood<'a>,
    accept: &'a F,
    grid: &'a LabelGrid,
    needs_labels: bool,
    needs_values: bool,
    bricks: Vec<FloodBrick>,
    index: FxHashMap<BrickKey, usize>,
}

impl<F: Fn(Label, f32) -> bool> State<'_, F> {
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
        let origin = self.grid.brick_origin(key);
        let dims = self.grid.dims();
        let extent = [0, 1, 2].map(|a| (dims[a] - origin[a]).min(LABEL_BRICK) as usize);
        let b = LABEL_BRICK as usize;
        let mut eligible = vec![0u64; WORDS].into_boxed_slice();
        for lk in 0..extent[2] {
            for lj in 0..extent[1] {
                let row = b * (lj + b * lk);
                let mut bits = 0u64;
                for li in 0..extent[0] {
                    let at = row + li;
                    let label = labels.as_ref().map_or(0, |l| l[at]);
                    let value = values.as_ref().map_or(f32::NAN, |v| v[at]);
                    bits |= u64::from((self.accept)(label, value)) << li;
                }
                // A row of 32 voxels is half a word.
                eligible[row / 64] |= bits << (row % 64);
            }
        }
        self.bricks.push(FloodBrick {
            key,
            eligible,
            accepted: vec![0; WORDS].into_boxed_slice(),
            pending: Vec::new(),
            incoming: Vec::new(),
            queued: false,
        });
        self.index.insert(key, self.bricks.len() - 1);
        Ok(self.bricks.len() - 1)
    }
}

/// Row `row` (32 voxels along i) of a brick's bitset: rows are half words.
fn row_bits(words: &[u64], row: usize) -> u32 {
    (words[row / 2] >> ((row % 2) * 32)) as u32
}

fn or_row(words: &mut [u64], row: usize, bits: u32) {
    words[row / 2] |= u64::from(bits) << ((row % 2) * 32);
}

/// The `n` lowest set bits of `bits`.
fn lowest_bits(bits: u32, n: u32) -> u32 {
    let mut out = 0;
    let mut rest = bits;
    for _ in 0..n.min(bits.count_ones()) {
        let low = rest & rest.wrapping_neg();
        out |= low;
        rest &= !low;
    }
    out
}

/// Offers voxels of a row to a brick from outside it, queueing the brick.
fn offer(fb: &mut FloodBrick, queue: &mut VecDeque<usize>, at: usize, row: u16, bits: u32) {
    fb.incoming.push((row, bits));
    if !fb.queued {
        fb.queued = true;
        queue.push_back(at);
    }
}

/// Floods from `seed` through voxels for which `accept(label, value)` holds (label and value
/// are read only when `needs_labels` / `needs_values`; otherwise 0 and NaN are passed).
/// `progress(voxels)` is called every [`PROGRESS_EVERY_VOXELS`]; the cancel flag ends it with
/// [`SegmentError::Cancelled`].
pub(crate) fn flood<F: Fn(Label, f32) -> bool>(
    flood: &Flood<'_>,
    seed: [u32; 3],
    needs_labels: bool,
    needs_values: bool,
    // Generic, not `dyn`: the test runs for every neighbour of every voxel and must inline.
    accept: F,
    progress: &mut dyn FnMut(u64),
) -> Result<FloodRegion, SegmentError> {
    let mut work = FloodWork::start(flood, seed, needs_labels, needs_values, &accept)?;
    work.step(flood, &accept, None, progress)?;
    Ok(work.into_region())
}

/// A flood under way, resumable: [`Self::step`] drains at most a given number of bricks from
/// its queue and returns, so a caller with one thread (the browser page) spreads a grow over
/// frames. Stepped to the end it is exactly [`flood`] (which is this, in one step): the queue,
/// the per-brick bits and the order are the same whatever the steps. Between steps the layer
/// must stay as it was (a brick's labels are read when the flood first reaches it), and each
/// step must be given the same inputs and `accept`.
pub(crate) struct FloodWork {
    bricks: Vec<FloodBrick>,
    index: FxHashMap<BrickKey, usize>,
    queue: VecDeque<usize>,
    needs_labels: bool,
    needs_values: bool,
    voxels: u64,
    reported: u64,
    stopped_at_cap: bool,
    finished: bool,
}

impl FloodWork {
    /// Checks the inputs and offers the seed; no voxel is taken yet.
    pub fn start<F: Fn(Label, f32) -> bool>(
        flood: &Flood<'_>,
        seed: [u32; 3],
        needs_labels: bool,
        needs_values: bool,
        accept: &F,
    ) -> Result<Self, SegmentError> {
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
            accept,
            grid,
            needs_labels,
            needs_values,
            bricks: Vec::new(),
            index: FxHashMap::default(),
        };
        let b = LABEL_BRICK as usize;
        let (key, at) = grid.brick_of(seed);
        let seed_brick = state.brick(key)?;
        state.bricks[seed_brick]
            .incoming
            .push(((at / b) as u16, 1u32 << (at % b)));
        state.bricks[seed_brick].queued = true;
        Ok(FloodWork {
            bricks: state.bricks,
            index: state.index,
            queue: VecDeque::from([seed_brick]),
            needs_labels,
            needs_values,
            voxels: 0,
            reported: 0,
            stopped_at_cap: false,
            finished: false,
        })
    }

    /// Voxels taken so far.
    pub fn voxels(&self) -> u64 {
        self.voxels
    }

    pub fn finished(&self) -> bool {
        self.finished
    }

    /// Drains at most `max_bricks` bricks from the queue (all with `None`); returns whether
    /// the flood is finished. `progress(voxels)` is called every [`PROGRESS_EVERY_VOXELS`] and
    /// at the end.
    pub fn step<F: Fn(Label, f32) -> bool>(
        &mut self,
        flood: &Flood<'_>,
        accept: &F,
        max_bricks: Option<usize>,
        progress: &mut dyn FnMut(u64),
    ) -> Result<bool, SegmentError> {
        if self.finished {
            return Ok(true);
        }
        let mut state = State {
            flood,
            accept,
            grid: flood.layer.grid(),
            needs_labels: self.needs_labels,
            needs_values: self.needs_values,
            bricks: std::mem::take(&mut self.bricks),
            index: std::mem::take(&mut self.index),
        };
        let drained = self.drain(&mut state, max_bricks, progress);
        self.bricks = state.bricks;
        self.index = state.index;
        self.finished = drained?;
        if self.finished {
            progress(self.voxels);
        }
        Ok(self.finished)
    }

    /// The region taken (the flood finished, or what it took so far).
    pub fn into_region(self) -> FloodRegion {
        FloodRegion {
            bricks: self.bricks,
            voxels: self.voxels,
            stopped_at_cap: self.stopped_at_cap,
        }
    }

    fn drain<F: Fn(Label, f32) -> bool>(
        &mut self,
        state: &mut State<'_, F>,
        max_bricks: Option<usize>,
        progress: &mut dyn FnMut(u64),
    ) -> Result<bool, SegmentError> {
        let flood = state.flood;
        let grid = state.grid;
        let b = LABEL_BRICK as usize;
        let along = [0, 1, 2].map(|a| flood.axes.contains(&a));
        let queue = &mut self.queue;
        let mut voxels = self.voxels;
        let mut stopped_at_cap = self.stopped_at_cap;
        let mut reported = self.reported;
        let mut drained = 0usize;
        let finished = 'flood: loop {
            if max_bricks.is_some_and(|max| drained >= max) {
                break 'flood false;
            }
            let Some(here) = queue.pop_front() else {
                break 'flood true;
            };
            drained += 1;
            state.bricks[here].queued = false;
            let key = state.bricks[here].key;
            // Offers from outside, then the rows that grew, until this brick is quiet.
            loop {
                if voxels >= reported + PROGRESS_EVERY_VOXELS {
                    reported = voxels;
                    progress(voxels);
                    if flood.cancel.is_some_and(|c| c.load(Ordering::Relaxed)) {
                        self.voxels = voxels;
                        return Err(SegmentError::Cancelled);
                    }
                }
                let fb = &mut state.bricks[here];
                let (row, bits) = if let Some(offer) = fb.incoming.pop() {
                    offer
                } else if let Some(row) = fb.pending.pop() {
                    // Pass the row's voxels on to the rows beside it along j and k.
                    let taken = row_bits(&fb.accepted, usize::from(row));
                    let (lj, lk) = (usize::from(row) % b, usize::from(row) / b);
                    for (axis, local) in [(1usize, lj), (2, lk)] {
                        if !along[axis] {
                            continue;
                        }
                        let step = if axis == 1 { 1 } else { b };
                        for up in [false, true] {
                            let inside = if up { local + 1 < b } else { local > 0 };
                            if inside {
                                let next = if up {
                                    row as usize + step
                                } else {
                                    row as usize - step
                                };
                                state.bricks[here].incoming.push((next as u16, taken));
                                continue;
                            }
                            let mut next_key = key.0;
                            if up {
                                next_key[axis] += 1;
                            } else if next_key[axis] == 0 {
                                continue;
                            } else {
                                next_key[axis] -= 1;
                            }
                            let next_key = BrickKey(next_key);
                            if !grid.contains(grid.brick_origin(next_key).map(i64::from)) {
                                continue;
                            }
                            let next = if up {
                                row as usize - (b - 1) * step
                            } else {
                                row as usize + (b - 1) * step
                            };
                            let there = state.brick(next_key)?;
                            offer(&mut state.bricks[there], queue, there, next as u16, taken);
                        }
                    }
                    continue;
                } else {
                    break;
                };
                // Take the offered voxels that are admitted and new, and the runs along i they
                // belong to (only up to the cap, keeping what is taken connected).
                let row = usize::from(row);
                let admitted = row_bits(&fb.eligible, row);
                let old = row_bits(&fb.accepted, row);
                let mut taken = bits & admitted & !old;
                if taken == 0 {
                    continue;
                }
                let room = flood.max_voxels - voxels;
                if u64::from(taken.count_ones()) > room {
                    taken = lowest_bits(taken, room as u32);
                    stopped_at_cap = true;
                } else if along[0] {
                    loop {
                        let grown = (taken | (taken << 1) | (taken >> 1)) & admitted & !old;
                        let added = grown & !taken;
                        if added == 0 {
                            break;
                        }
                        let left = room - u64::from(taken.count_ones());
                        if u64::from(added.count_ones()) > left {
                            // Each added voxel touches the taken ones: any of them keeps it connected.
                            taken |= lowest_bits(added, left as u32);
                            stopped_at_cap = true;
                            break;
                        }
                        taken = grown;
                    }
                }
                if taken == 0 {
                    break 'flood true;
                }
                or_row(&mut fb.accepted, row, taken);
                voxels += u64::from(taken.count_ones());
                fb.pending.push(row as u16);
                if along[0] {
                    // Runs that reach the brick's faces along i go on in the bricks beside it.
                    for (bit, up) in [(0u32, false), (31, true)] {
                        if taken & (1 << bit) == 0 {
                            continue;
                        }
                        let mut next_key = key.0;
                        if up {
                            next_key[0] += 1;
                        } else if next_key[0] == 0 {
                            continue;
                        } else {
                            next_key[0] -= 1;
                        }
                        let next_key = BrickKey(next_key);
                        if !grid.contains(grid.brick_origin(next_key).map(i64::from)) {
                            continue;
                        }
                        let there = state.brick(next_key)?;
                        let bits = if up { 1 } else { 1 << 31 };
                        offer(&mut state.bricks[there], queue, there, row as u16, bits);
                    }
                }
                if stopped_at_cap {
                    break 'flood true;
                }
            }
        };
        self.voxels = voxels;
        self.stopped_at_cap = stopped_at_cap;
        self.reported = reported;
        Ok(finished)
    }
}
