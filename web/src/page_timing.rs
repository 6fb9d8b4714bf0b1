//! What the page measures about itself for issue 39's benchmark, posted with its test capture
//! (`capture=1`): time to the first image and to the converged image, from the module's start
//! and from navigation (loading and compiling the module), and with `bench=N` the frame time
//! while the camera orbits for N frames once the view converged (2° a frame, as a drag would).
//!
//! Times come from `performance.now()` (ms since navigation). A frame's time is the interval
//! between two consecutive submitted frames while orbiting: everything the page does per frame
//! (loader, raycast, egui, presentation), which is what a user feels. Nothing here decides
//! what is drawn except the bench's orbit.

/// Degrees of azimuth per frame while the bench orbits.
pub const BENCH_DEG_PER_FRAME: f64 = 2.0;

thread_local! {
    /// Time the page's one thread spent decoding and verifying brick records: (total ms,
    /// records, the most in one frame so far, this frame's ms). Kept here rather than in the
    /// fetcher's counters (strata_source's, shared with the desktop) because it answers one
    /// question of the benchmark: does decoding need web workers (issue 39 item 2)?
    static DECODING: std::cell::Cell<DecodeTime> = const { std::cell::Cell::new(DecodeTime::ZERO) };
}

#[derive(Clone, Copy)]
struct DecodeTime {
    total_ms: f64,
    records: u32,
    worst_frame_ms: f64,
    this_frame_ms: f64,
}

impl DecodeTime {
    const ZERO: DecodeTime = DecodeTime {
        total_ms: 0.0,
        records: 0,
        worst_frame_ms: 0.0,
        this_frame_ms: 0.0,
    };
}

/// Runs `decode` (one record's decoding and checksum) and adds its time to the page's.
pub fn time_decode<T>(decode: impl FnOnce() -> T) -> T {
    let started = now_ms();
    let out = decode();
    let spent = now_ms() - started;
    DECODING.with(|d| {
        let mut t = d.get();
        t.total_ms += spent;
        t.records += 1;
        t.this_frame_ms += spent;
        d.set(t);
    });
    out
}

/// Milliseconds since navigation; 0 where the page has no `performance` (not a browser).
fn now_ms() -> f64 {
    web_sys::window()
        .and_then(|w| w.performance())
        .map_or(0.0, |p| p.now())
}

pub struct PageTiming {
    /// When the module started (ms since navigation).
    boot_ms: f64,
    first_image_ms: Option<f64>,
    converged_ms: Option<f64>,
    /// Frames the bench orbits for (0: no bench).
    bench_frames: u32,
    /// Submission times of the bench's frames.
    bench_submits: Vec<f64>,
}

impl PageTiming {
    pub fn new(bench_frames: u32) -> Self {
        PageTiming {
            boot_ms: now_ms(),
            first_image_ms: None,
            converged_ms: None,
            bench_frames,
            bench_submits: Vec::new(),
        }
    }

    /// A frame was submitted; `converged`: it is the complete picture of its view.
    pub fn submitted(&mut self, converged: bool) {
        let at = now_ms();
        DECODING.with(|d| {
            let mut t = d.get();
            t.worst_frame_ms = t.worst_frame_ms.max(t.this_frame_ms);
            t.this_frame_ms = 0.0;
            d.set(t);
        });
        self.first_image_ms.get_or_insert(at);
        if converged {
            self.converged_ms.get_or_insert(at);
        }
        if self.orbiting() {
            self.bench_submits.push(at);
        }
    }

    /// The bench is moving the camera: from the first converged image until its frames ran.
    pub fn orbiting(&self) -> bool {
        self.bench_frames > 0
            && self.converged_ms.is_some()
            // One more submit than frames: N intervals.
            && self.bench_submits.len() <= self.bench_frames as usize
    }

    /// The capture may go: no bench, or the bench's frames ran.
    pub fn bench_done(&self) -> bool {
        self.bench_frames == 0 || self.bench_submits.len() > self.bench_frames as usize
    }

    /// `name=value` pairs for the capture's query (ms; absent values left out).
    pub fn metrics(&self) -> Vec<(&'static str, f64)> {
        let mut out = vec![("boot_ms", self.boot_ms)];
        if let Some(first) = self.first_image_ms {
            out.push(("first_image_ms", first));
        }
        if let Some(converged) = self.converged_ms {
            out.push(("converged_ms", converged));
        }
        let decoding = DECODING.with(|d| d.get());
        if decoding.records > 0 {
            out.push(("decode_ms_total", decoding.total_ms));
            out.push(("decoded_records", f64::from(decoding.records)));
            out.push(("decode_ms_worst_frame", decoding.worst_frame_ms));
        }
        let mut intervals: Vec<f64> = self
            .bench_submits
            .windows(2)
            .map(|pair| pair[1] - pair[0])
            .collect();
        if !intervals.is_empty() {
            intervals.sort_by(f64::total_cmp);
            let mean = intervals.iter().sum::<f64>() / intervals.len() as f64;
            out.push(("frame_ms_median", intervals[intervals.len() / 2]));
            out.push(("frame_ms_mean", mean));
            out.push(("bench_frames", intervals.len() as f64));
        }
        out
    }
}
