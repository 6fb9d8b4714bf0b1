//! Storage slower than the frames: frames must not wait for it, and the image still converges.
//! In its own test binary so no other test competes for the two CPU cores.
//!
//! The always-on test holds every read behind a gate the test opens read by read, so "no frame
//! waits for storage" and "it refines over many frames" are counted, not timed: a frame that
//! waited on a read could only finish once the watchdog opens the gate, and the test fails if
//! the watchdog had to. The frame-time comparison with fast storage (50 ms per read injected)
//! runs only with `STRATA_TIMING_TESTS=1`.

use crate::common;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use common::*;
use strata_loader::{SlowReader, StreamingConfig, StreamingVolume};
use strata_render::compare_rgba8;
use strata_source::{SourceError, VolumeSource};
use strata_storage::histogram::Histogram;
use strata_storage::store::{Skeleton, StoreStats};
use strata_storage::{Store, StoreHeader};
use strata_types::BrickId;

/// Reads handed out by the test.
#[derive(Default)]
struct Gate {
    /// Reads that may still start.
    permits: usize,
    /// Reads that returned.
    finished: usize,
    /// Set by the watchdog: every read passes.
    open: bool,
}

/// A store whose brick reads block until the test grants them.
struct GatedReader {
    inner: Arc<Store>,
    gate: Mutex<Gate>,
    changed: Condvar,
}

impl GatedReader {
    fn new(inner: Arc<Store>) -> Self {
        Self {
            inner,
            gate: Mutex::new(Gate::default()),
            changed: Condvar::new(),
        }
    }
    fn lock(&self) -> std::sync::MutexGuard<'_, Gate> {
        self.gate
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
    fn grant(&self, reads: usize) {
        self.lock().permits += reads;
        self.changed.notify_all();
    }
    fn open(&self) {
        self.lock().open = true;
        self.changed.notify_all();
    }
    fn finished(&self) -> usize {
        self.lock().finished
    }
    fn permits_left(&self) -> usize {
        self.lock().permits
    }
}

impl VolumeSource for GatedReader {
    fn location(&self) -> String {
        self.inner.location()
    }
    fn header(&self) -> &StoreHeader {
        self.inner.header()
    }
    fn skeleton(&self) -> &Skeleton {
        self.inner.skeleton()
    }
    fn histogram(&self) -> &Histogram {
        self.inner.histogram()
    }
    fn stats(&self) -> &StoreStats {
        self.inner.stats()
    }
    fn read_brick_record(&self, id: BrickId) -> Result<Vec<u8>, SourceError> {
        {
            let mut gate = self.lock();
            while !gate.open && gate.permits == 0 {
                gate = self
                    .changed
                    .wait(gate)
                    .unwrap_or_else(|poisoned| poisoned.into_inner());
            }
            if !gate.open {
                gate.permits -= 1;
            }
        }
        let record = self.inner.read_brick_record(id);
        self.lock().finished += 1;
        record
    }
}

struct OpenOnDrop(Arc<GatedReader>);

impl Drop for OpenOnDrop {
    fn drop(&mut self) {
        self.0.open();
    }
}

#[test]
fn frames_never_wait_for_storage_and_refine_read_by_read() {
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 128));
    let ctx = gpu();
    let tf = bone();
    let s = settings(128);
    let camera = orbit(&store, 30.0, 20.0, 1.0);
    let config = StreamingConfig {
        max_voxel_pixels: 0.25,
        ..config()
    };
    let mut fast = stream(&ctx, &store, &tf, config.clone());
    let (fast_image, _) = converge(&ctx, &mut fast, &camera, &s, 300);
    drop(fast);

    let reader = Arc::new(GatedReader::new(store.clone()));
    // The watchdog opens the gate if the frames below do not finish in time: only a frame that
    // waits for a read needs it, and then the test fails below instead of hanging.
    let watchdog_fired = Arc::new(AtomicBool::new(false));
    let (done, finished) = mpsc::channel::<()>();
    let watchdog = {
        let reader = reader.clone();
        let fired = watchdog_fired.clone();
        std::thread::Builder::new()
            .name("slow-storage-watchdog".into())
            .spawn(move || {
                if finished.recv_timeout(Duration::from_secs(120)).is_err() {
                    fired.store(true, Ordering::SeqCst);
                    reader.open();
                }
            })
            .unwrap()
    };
    // Opening reads the root brick (a volume is never drawn without one); frames read nothing.
    reader.grant(1);
    let mut slow = StreamingVolume::new(&ctx, reader.clone(), &tf, config).unwrap();
    assert_eq!(reader.finished(), 1, "opening read more than the root");
    // Reader threads may still wait at the gate when the test ends (or fails): dropped before
    // the volume, this opens the gate so the volume's threads can be joined.
    let _open_at_exit = OpenOnDrop(reader.clone());
    // Gate shut: no read can finish, yet every frame returns.
    for _ in 0..8 {
        let stats = slow.frame(&ctx, &camera, &s).unwrap();
        slow.read_frame_blocking(&ctx).unwrap();
        assert!(!stats.converged, "converged without reading a brick");
    }
    assert!(
        !watchdog_fired.load(Ordering::SeqCst),
        "a frame waited for a blocked read"
    );
    assert_eq!(reader.finished(), 1, "a read passed the shut gate");
    assert!(
        {
            let s = slow.last_stats();
            s.pending + s.queued + s.in_flight > 0
        },
        "frames asked for no bricks: {:#?}",
        slow.last_stats()
    );

    // Two reads at a time: each grant is followed by frames until those reads have returned and
    // been taken up, so the image can only refine in steps.
    let mut frames = 8;
    let mut refinements = 0;
    let mut converged_image = None;
    let mut granted = 1;
    'grants: for _ in 0..2000 {
        reader.grant(2);
        granted += 2;
        let mut frames_after_grant = 0;
        loop {
            let stats = slow.frame(&ctx, &camera, &s).unwrap();
            let image = slow.read_frame_blocking(&ctx).unwrap();
            frames += 1;
            frames_after_grant += 1;
            refinements += usize::from(stats.page_table_rewritten);
            if stats.converged {
                converged_image = Some(image.rgba);
                break 'grants;
            }
            // The granted reads returned (or nobody wants them) and two more frames took them up.
            let reads_done = reader.finished() >= granted - reader.permits_left();
            if reads_done && frames_after_grant >= 3 {
                break;
            }
            if frames_after_grant > 500 {
                panic!("granted reads did not return: {:#?}", slow.last_stats());
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    let _ = done.send(());
    watchdog.join().unwrap();
    assert!(
        !watchdog_fired.load(Ordering::SeqCst),
        "a frame waited for a blocked read"
    );
    let converged_image =
        converged_image.unwrap_or_else(|| panic!("did not converge: {:#?}", slow.last_stats()));
    eprintln!("{refinements} refinements in {frames} frames, {granted} reads granted");
    assert!(
        refinements >= 3 && frames > refinements,
        "{refinements} refinements in {frames} frames"
    );
    let c = compare_rgba8(&converged_image, &fast_image).unwrap();
    assert!(
        c.psnr_db >= 45.0,
        "gated-storage image differs from fast: {c:?}"
    );
}

/// Opt-in (`STRATA_TIMING_TESTS=1`): with 50 ms per read, frame times stay those of fast storage.
#[test]
fn slow_storage_keeps_fast_frame_times() {
    if !timing_assertions_enabled() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 128));
    let ctx = gpu();
    let tf = bone();
    let s = settings(128);
    let camera = orbit(&store, 30.0, 20.0, 1.0);
    let config = StreamingConfig {
        max_voxel_pixels: 0.25,
        ..config()
    };

    let mut fast = stream(&ctx, &store, &tf, config.clone());
    converge(&ctx, &mut fast, &camera, &s, 300);
    let mut fast_frames = Vec::new();
    for _ in 0..20 {
        let t = Instant::now();
        fast.frame(&ctx, &camera, &s).unwrap();
        fast.read_frame_blocking(&ctx).unwrap();
        fast_frames.push(t.elapsed().as_secs_f64());
    }

    let delay = Duration::from_millis(50);
    let reader = Arc::new(SlowReader {
        inner: store.clone(),
        delay,
    });
    let mut slow = StreamingVolume::new(&ctx, reader, &tf, config).unwrap();
    let started = Instant::now();
    let mut slow_frames = Vec::new();
    let mut loader_max: f64 = 0.0;
    while started.elapsed() < Duration::from_secs(60) {
        let t = Instant::now();
        let stats = slow.frame(&ctx, &camera, &s).unwrap();
        slow.read_frame_blocking(&ctx).unwrap();
        slow_frames.push(t.elapsed().as_secs_f64());
        loader_max = loader_max.max(stats.loader_seconds);
        if stats.converged {
            break;
        }
    }
    // No frame's loader work came near one read.
    assert!(
        loader_max < delay.as_secs_f64() / 2.0,
        "loader took {loader_max:.4} s in a frame"
    );
    // The median within 1.5× (+3 ms of scheduling noise) and no frame as long as two reads.
    let fast_median = strata_loader::Distribution::of(&fast_frames).p50;
    // The first frame of a new volume compiles its raycast pipeline; that is not I/O.
    let slow_dist = strata_loader::Distribution::of(&slow_frames[1..]);
    assert!(
        slow_dist.p50 <= 1.5 * fast_median + 0.003,
        "median frame {:.4} s vs {fast_median:.4} s",
        slow_dist.p50
    );
    assert!(
        slow_dist.max < fast_median + 2.0 * delay.as_secs_f64(),
        "{slow_dist:?} vs {fast_median:.4} s"
    );
}
