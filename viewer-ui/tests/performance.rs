use std::time::Duration;

use egui_kittest::kittest::Queryable;
use egui_kittest::Harness;
use strata_loader::FrameStats;
use strata_viewer_ui::performance::{self, FrameClock, PerformanceFigures};
use web_time::Instant;

/// A clock whose UI frames came every 20 ms, each spending 4 ms in `ui()`.
fn clock() -> FrameClock {
    let mut clock = FrameClock::default();
    let start = Instant::now();
    for frame in 0..10u32 {
        let end = start + Duration::from_millis(20 * u64::from(frame) + 4);
        let began = end - Duration::from_millis(4);
        clock.record_at(end, 0.02 * f64::from(frame), began, u64::from(frame), true);
    }
    clock
}

fn loader_stats() -> FrameStats {
    FrameStats {
        gpu_slots_used: 7,
        gpu_slots_capacity: 64,
        gpu_bytes: 3 << 20,
        gpu_budget_bytes: 256 << 20,
        pending: 5,
        in_flight: 2,
        bricks_read_total: 42,
        ..FrameStats::default()
    }
}

fn panel(figures: impl Fn(&FrameStats) -> PerformanceFigures<'_> + 'static) -> Harness<'static> {
    let clock = clock();
    let stats = loader_stats();
    let mut harness = Harness::new_ui(move |ui| performance::show(ui, &clock, &figures(&stats)));
    harness.run();
    harness
}

#[test]
fn the_clock_measures_intervals_and_logs_them() {
    let clock = clock();
    assert_eq!(clock.samples.len(), 10);
    assert_eq!(
        clock.samples[0].interval_ms, 0.0,
        "the first frame has no interval"
    );
    for s in clock.samples.iter().skip(1) {
        assert!((s.interval_ms - 20.0).abs() < 1e-6, "{s:?}");
        assert!((s.ui_cpu_ms - 4.0).abs() < 1e-6, "{s:?}");
    }
    assert!((clock.latest_seconds() - 0.18).abs() < 1e-12);
    let csv = clock.log_csv();
    assert_eq!(csv.lines().count(), 11);
    assert_eq!(csv.lines().nth(2), Some("0.0200,20.000,4.000,1"));
}

#[test]
fn the_panel_shows_the_figures_it_was_given() {
    let h = panel(|stats| PerformanceFigures {
        adapter: "TestGPU",
        volume_frame_ms: vec![[0.1, 10.0], [0.15, 15.0]],
        gpu_frame_ms: Some(3.25),
        sampling_rate: 1.5,
        lod_factor: 2.0,
        loader: Some(stats),
        traversal: None,
        finest_resident_level: Some(1),
        level_count: 4,
        frames_rendered: 17,
        working: Some("loading 5 bricks".into()),
    });
    // The means: 20 ms a UI frame, (10 + 15) / 2 a volume frame.
    h.get_by_label("UI frame 20.0 ms · volume frame 12.5 ms");
    h.get_by_label("volume on TestGPU");
    h.get_by_label("3.25 ms");
    h.get_by_label("1.50 samples/voxel");
    h.get_by_label("7 / 64 slots · 3 / 256 MiB");
    h.get_by_label("5 (2 reading)");
    h.get_by_label("0.0 MB/s · 42 bricks read");
    h.get_by_label("1 (0 = full resolution; root 3)");
    h.get_by_label("17");
    h.get_by_label("loading 5 bricks");
    assert!(h.query_by_label("Traversal").is_none());
    assert!(h.query_by_label("converged").is_none());
}

#[test]
fn without_a_loader_or_gpu_time_those_rows_are_absent_and_a_final_view_says_converged() {
    let h = panel(|_| PerformanceFigures {
        adapter: "TestGPU",
        sampling_rate: 1.0,
        lod_factor: 1.0,
        ..PerformanceFigures::default()
    });
    assert!(h.query_by_label("GPU time (raycast)").is_none());
    assert!(h.query_by_label("GPU cache").is_none());
    h.get_by_label("converged");
    // No volume frame yet: a dash, never the mean of nothing ("NaN ms", issue 47).
    h.get_by_label("UI frame 20.0 ms · volume frame —");
}

/// Issue 47: in a narrow panel the figures' names wrapped letter by letter (the values took
/// the width). Each name stays on one line: its height is one row's, as a short name's is.
#[test]
fn in_a_narrow_panel_every_figures_name_stays_on_one_line() {
    let clock = clock();
    let stats = loader_stats();
    let mut h = Harness::builder()
        .with_size(egui::Vec2::new(180.0, 900.0))
        .build_ui(move |ui| {
            performance::show(
                ui,
                &clock,
                &PerformanceFigures {
                    adapter: "llvmpipe (LLVM 19.1.7, 256 bits)",
                    volume_frame_ms: vec![[0.1, 10.0]],
                    gpu_frame_ms: Some(3.25),
                    sampling_rate: 1.5,
                    lod_factor: 2.0,
                    loader: Some(&stats),
                    traversal: Some("octree (sparse page table)"),
                    finest_resident_level: Some(1),
                    level_count: 4,
                    frames_rendered: 17,
                    working: None,
                },
            )
        });
    h.run();
    let one_row = h.get_by_label("Traversal").rect().height();
    for name in [
        "GPU time (raycast)",
        "Sampling rate",
        "Quality (lod) factor",
        "Finest level on GPU",
        "GPU bricks per level",
        "Cut changes while still",
    ] {
        let height = h.get_by_label(name).rect().height();
        assert!(
            height < one_row * 1.5,
            "{name:?} wrapped: {height} points high, one row is {one_row}"
        );
    }
}
