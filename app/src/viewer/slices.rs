//! Slice images read straight from the store on a named thread, at the octree level that
//! matches the view's pixel size, through a bounded LRU of decompressed bricks: only the
//! bricks a slice crosses are read, so volumes far larger than memory page smoothly (the 32
//! neighbouring slices of a brick row come from the cache).

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use strata_source::VolumeSource;
use strata_storage::{BrickId, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};

use super::orientation::{SliceFrame, SliceView};
use super::sync::{lock_ignoring_poison, wait_ignoring_poison, Repaint};

/// Decompressed bricks kept for paging (bytes).
pub const SLICE_CACHE_BYTES: usize = 192 << 20;

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

struct Shared {
    pending: Mutex<[Option<SliceRequest>; 3]>,
    results: Mutex<[Option<SliceImage>; 3]>,
    /// A voxel whose level-0 value is wanted, and the last one read.
    probe: Mutex<Option<[u32; 3]>>,
    probed: Mutex<Option<VoxelValue>>,
    error: Mutex<Option<String>>,
    wake: std::sync::Condvar,
    stop: AtomicBool,
}

pub struct SliceReader {
    shared: Arc<Shared>,
    thread: Option<std::thread::JoinHandle<()>>,
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

impl SliceReader {
    pub fn start(store: Arc<dyn VolumeSource>, repaint: Repaint) -> anyhow::Result<Self> {
        let shared = Arc::new(Shared {
            pending: Mutex::new([None; 3]),
            results: Mutex::new([None, None, None]),
            probe: Mutex::new(None),
            probed: Mutex::new(None),
            error: Mutex::new(None),
            wake: std::sync::Condvar::new(),
            stop: AtomicBool::new(false),
        });
        let thread_shared = shared.clone();
        let thread = std::thread::Builder::new()
            .name("strata-slice-reader".into())
            .spawn(move || {
                let mut cache = BrickLru::new(SLICE_CACHE_BYTES);
                loop {
                    let next = {
                        let mut pending = lock_ignoring_poison(&thread_shared.pending);
                        loop {
                            if thread_shared.stop.load(Ordering::Acquire) {
                                return;
                            }
                            // A probe is one brick (usually cached): it goes first.
                            let probe = lock_ignoring_poison(&thread_shared.probe).take();
                            if let Some(index) = probe {
                                drop(pending);
                                match read_voxel(&store, &mut cache, index) {
                                    Ok(stored) => {
                                        *lock_ignoring_poison(&thread_shared.probed) =
                                            Some(VoxelValue { index, stored })
                                    }
                                    Err(e) => {
                                        *lock_ignoring_poison(&thread_shared.error) =
                                            Some(format!("{e:#}"))
                                    }
                                }
                                repaint();
                                pending = lock_ignoring_poison(&thread_shared.pending);
                                continue;
                            }
                            if let Some(r) = pending.iter_mut().find_map(|p| p.take()) {
                                break r;
                            }
                            pending = wait_ignoring_poison(&thread_shared.wake, pending);
                        }
                    };
                    match read_slice(&store, &mut cache, next) {
                        Ok(image) => {
                            lock_ignoring_poison(&thread_shared.results)[next.view.index()] =
                                Some(image);
                            *lock_ignoring_poison(&thread_shared.error) = None;
                        }
                        Err(e) => {
                            *lock_ignoring_poison(&thread_shared.error) = Some(format!("{e:#}"))
                        }
                    }
                    repaint();
                }
            })?;
        Ok(SliceReader {
            shared,
            thread: Some(thread),
        })
    }

    /// Asks for a slice; a newer request for the same view replaces an unread older one.
    pub fn request(&self, request: SliceRequest) {
        lock_ignoring_poison(&self.shared.pending)[request.view.index()] = Some(request);
        self.shared.wake.notify_all();
    }

    /// Asks for the level-0 value of `index` (a newer probe replaces an unread older one);
    /// [`SliceReader::probed`] has it a moment later. Does nothing if it is already there.
    pub fn probe(&self, index: [u32; 3]) {
        if self.probed().is_some_and(|p| p.index == index) {
            return;
        }
        let mut probe = lock_ignoring_poison(&self.shared.probe);
        if *probe != Some(index) {
            *probe = Some(index);
            drop(probe);
            // Take the pending lock so the wake cannot slip between the reader's check and wait.
            let _pending = lock_ignoring_poison(&self.shared.pending);
            self.shared.wake.notify_all();
        }
    }

    pub fn probed(&self) -> Option<VoxelValue> {
        *lock_ignoring_poison(&self.shared.probed)
    }

    pub fn latest(&self, view: SliceView) -> Option<SliceImage> {
        lock_ignoring_poison(&self.shared.results)[view.index()].clone()
    }

    pub fn error(&self) -> Option<String> {
        lock_ignoring_poison(&self.shared.error).clone()
    }
}

impl Drop for SliceReader {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        self.shared.wake.notify_all();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

struct BrickLru {
    budget_bricks: usize,
    bricks: HashMap<BrickId, Arc<Vec<u16>>>,
    order: VecDeque<BrickId>,
}

impl BrickLru {
    fn new(budget_bytes: usize) -> Self {
        BrickLru {
            budget_bricks: (budget_bytes / (strata_storage::BRICK_PAYLOAD_VOXELS * 2)).max(8),
            bricks: HashMap::new(),
            order: VecDeque::new(),
        }
    }

    fn get(&mut self, store: &dyn VolumeSource, id: BrickId) -> anyhow::Result<Arc<Vec<u16>>> {
        if let Some(b) = self.bricks.get(&id) {
            let b = b.clone();
            if let Some(pos) = self.order.iter().position(|x| *x == id) {
                self.order.remove(pos);
            }
            self.order.push_back(id);
            return Ok(b);
        }
        let brick = Arc::new(store.read_brick(id)?);
        while self.bricks.len() >= self.budget_bricks {
            match self.order.pop_front() {
                Some(old) => {
                    self.bricks.remove(&old);
                }
                None => break,
            }
        }
        self.bricks.insert(id, brick.clone());
        self.order.push_back(id);
        Ok(brick)
    }
}

/// One level-0 voxel's stored value, through the brick cache.
fn read_voxel(
    store: &dyn VolumeSource,
    cache: &mut BrickLru,
    index: [u32; 3],
) -> anyhow::Result<u16> {
    let dims = store.layout().level_dims[0];
    if (0..3).any(|a| index[a] >= dims[a]) {
        anyhow::bail!("voxel {index:?} is outside the volume {dims:?}");
    }
    let brick = cache.get(store, BrickId::new(0, index.map(|i| i / BRICK_CORE)))?;
    let local = index.map(|i| (i % BRICK_CORE + BRICK_APRON) as usize);
    let edge = BRICK_PAYLOAD as usize;
    Ok(brick[(local[2] * edge + local[1]) * edge + local[0]])
}

fn read_slice(
    store: &dyn VolumeSource,
    cache: &mut BrickLru,
    request: SliceRequest,
) -> anyhow::Result<SliceImage> {
    let layout = store.layout();
    let level = (request.level as usize).min(layout.level_count() - 1);
    let dims = layout.level_dims[level];
    let scale = (1u64 << level) as f64;
    let frame = request.frame;
    let (n, a, d) = (frame.normal_axis, frame.across_axis, frame.down_axis);
    let slice = ((request.position + 0.5) / scale - 0.5)
        .round()
        .clamp(0.0, dims[n] as f64 - 1.0) as u32;
    let (width, height) = (dims[a] as usize, dims[d] as usize);
    let mut values = vec![0u16; width * height];
    let bricks = layout.bricks_in_level(level);
    let core = BRICK_CORE;
    let edge = BRICK_PAYLOAD as usize;
    let brick_n = slice / core;
    for bd in 0..bricks[d] {
        for ba in 0..bricks[a] {
            let mut coords = [0u32; 3];
            coords[n] = brick_n;
            coords[a] = ba;
            coords[d] = bd;
            let brick = cache.get(store, BrickId::new(level as u8, coords))?;
            let mut local = [0usize; 3];
            local[n] = (slice - brick_n * core + BRICK_APRON) as usize;
            let a_end = ((ba + 1) * core).min(dims[a]);
            let d_end = ((bd + 1) * core).min(dims[d]);
            for y in bd * core..d_end {
                local[d] = (y - bd * core + BRICK_APRON) as usize;
                for x in ba * core..a_end {
                    local[a] = (x - ba * core + BRICK_APRON) as usize;
                    values[y as usize * width + x as usize] =
                        brick[(local[2] * edge + local[1]) * edge + local[0]];
                }
            }
        }
    }
    let level0 = layout.level_dims[0];
    let inside = |axis: usize| (level0[axis] as f64 / (dims[axis] as f64 * scale)).min(1.0);
    Ok(SliceImage {
        request,
        width,
        height,
        values: Arc::new(values),
        inside_fraction: (inside(a), inside(d)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_render::VolumeGeometry;

    #[test]
    fn level_follows_voxels_per_pixel() {
        assert_eq!(level_for_pixels(512.0, 600.0, 5), 0);
        assert_eq!(level_for_pixels(512.0, 256.0, 5), 1);
        assert_eq!(level_for_pixels(4096.0, 300.0, 8), 3);
        assert_eq!(level_for_pixels(4096.0, 1.0, 3), 2);
    }

    #[test]
    fn slice_values_match_the_level_zero_bricks() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("p.strata");
        strata_storage::phantom::Phantom::cube(40)
            .write_store(&path, &Default::default())
            .expect("phantom");
        let store = strata_storage::Store::open(&path).expect("open");
        let g = store.header().geometry.clone();
        let geometry = VolumeGeometry {
            dims: g.dims.map(|d| d),
            spacing_mm: g.spacing_mm,
            origin_lps_mm: g.origin_lps_mm,
            direction: g.direction,
        };
        let frame = SliceFrame::for_view(SliceView::Coronal, &geometry);
        let mut cache = BrickLru::new(1 << 20);
        let request = SliceRequest {
            view: SliceView::Coronal,
            frame,
            position: 35.0,
            level: 0,
        };
        let image = read_slice(&store, &mut cache, request).expect("slice");
        assert_eq!((image.width, image.height), (40, 40));
        // Voxel (x=33, y=35, z=38) lives in brick (1,1,1) at local (1+2, 3+2, 6+2).
        let brick = store.read_brick(BrickId::new(0, [1, 1, 1])).expect("brick");
        let e = BRICK_PAYLOAD as usize;
        let expected = brick[(8 * e + 5) * e + 3];
        assert_eq!(image.values[38 * 40 + 33], expected);
        // A probe of the same voxel reads the same value.
        assert_eq!(
            read_voxel(&store, &mut cache, [33, 35, 38]).expect("voxel"),
            expected
        );
        assert!(read_voxel(&store, &mut cache, [40, 0, 0]).is_err());
    }
}
