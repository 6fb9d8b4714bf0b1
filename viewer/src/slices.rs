//! Slice images read straight from the store on a named thread, at the octree level that
//! matches the view's pixel size: the thread reads the bricks strata-slices' assembler asks
//! for with blocking reads and hands them to it (the slicing itself, its brick LRU and the
//! image types are the assembler's, shared with the browser viewer). Only the bricks a slice
//! crosses are read, so volumes far larger than memory page smoothly (the 32 neighbouring
//! slices of a brick row come from the cache).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use strata_slices::{SliceAssembler, SliceView};
use strata_source::VolumeSource;

use super::sync::{lock_ignoring_poison, wait_ignoring_poison, Repaint};

pub use strata_slices::{
    level_for_pixels, SliceImage, SliceRequest, VoxelValue, SLICE_CACHE_BYTES,
};

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
                let mut assembler = SliceAssembler::new(store.layout().clone(), SLICE_CACHE_BYTES);
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
                                match read_voxel(&store, &mut assembler, index) {
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
                    match read_slice(&store, &mut assembler, next) {
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

/// One level-0 voxel's stored value, through the assembler's brick cache.
fn read_voxel(
    store: &dyn VolumeSource,
    assembler: &mut SliceAssembler,
    index: [u32; 3],
) -> anyhow::Result<u16> {
    assembler.voxel_with(index, |id| -> anyhow::Result<Vec<u16>> {
        Ok(store.read_brick(id)?)
    })
}

/// One slice, its bricks read (blocking) as the assembler asks for them.
fn read_slice(
    store: &dyn VolumeSource,
    assembler: &mut SliceAssembler,
    request: SliceRequest,
) -> anyhow::Result<SliceImage> {
    assembler.assemble_with(request, |id| -> anyhow::Result<Vec<u16>> {
        Ok(store.read_brick(id)?)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_render::VolumeGeometry;
    use strata_slices::SliceFrame;
    use strata_types::{BrickId, BRICK_PAYLOAD};

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
        let mut cache = SliceAssembler::new(store.layout().clone(), 1 << 20);
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
