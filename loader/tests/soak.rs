//! The loader soak of the reliability campaign: random cameras, transfer functions, quality
//! factors and budgets for a long time (30 minutes by default), checking on every frame that
//! the caches stay within their budgets (+10 %), that the process's memory stays bounded, and
//! that frames keep coming (a watchdog fails the test after 60 s without one: a deadlock).
//!
//! `STRATA_SOAK_SECONDS=1800 cargo test -p strata-loader --test integration soak:: -- --ignored --nocapture`
//! (`STRATA_SOAK_MAX_FRAMES_PER_VOLUME=60` for more, shorter volumes in a shorter run;
//! `STRATA_MALLOC_ARENAS=default` to measure without the arena cap of malloc_arenas.rs)

use crate::common;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::*;
use strata_loader::StreamingConfig;
use strata_render::{Camera, Projection, RenderMode, TransferFunction};

/// Frames may be slow on lavapipe; a minute without one is a hang.
const WATCHDOG: Duration = Duration::from_secs(60);

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn resident_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096)
}

#[test]
#[ignore = "soak: 30 minutes by default; run with --ignored (STRATA_SOAK_SECONDS to shorten)"]
fn loader_soak_random_views_tfs_and_budgets() {
    let seconds: u64 = std::env::var("STRATA_SOAK_SECONDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1800);
    // Frames per volume: a quarter of this up to this (a short run shortens it to see the
    // trend over more volumes).
    let max_frames: u64 = std::env::var("STRATA_SOAK_MAX_FRAMES_PER_VOLUME")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(400)
        .max(4);
    // First, before the GPU's and the store's threads (see malloc_arenas.rs).
    strata_loader::malloc_arenas::limit_malloc_arenas();
    let ctx = gpu();
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 160));
    let geometry = store.header().geometry.clone();
    let presets = ["ct-bone", "ct-soft-tissue", "ct-lung", "ct-vessels"];
    let heartbeat = Arc::new(AtomicU64::new(0));
    let beat = heartbeat.clone();
    let watched = std::thread::Builder::new()
        .name("soak-watchdog".into())
        .spawn(move || {
            let mut last = (0, Instant::now());
            loop {
                std::thread::sleep(Duration::from_secs(1));
                let now = beat.load(Ordering::Relaxed);
                if now == u64::MAX {
                    return;
                }
                if now != last.0 {
                    last = (now, Instant::now());
                } else if last.1.elapsed() > WATCHDOG {
                    // The frame loop is stuck and cannot be joined: end the test process.
                    eprintln!("soak: no frame for {WATCHDOG:?} after frame {now}: deadlock");
                    std::process::exit(1);
                }
            }
        })
        .unwrap();
    let mut rng = Rng(0x50a6_50a6);
    let started = Instant::now();
    let rss_at_start = resident_bytes().unwrap_or(0);
    let mut frames = 0u64;
    let mut volumes = 0u64;
    let mut worst_rss_over = i64::MIN;
    // The largest budgets of any volume so far: memory a dropped volume gave back may stay in
    // the process (malloc's arenas, the driver's own pools), so the bound is the peak budget,
    // not the current one. A leak still breaks it: it grows with every volume.
    let mut peak_budgets = 0u64;
    let mut rss_at_volume_starts = Vec::new();
    while started.elapsed() < Duration::from_secs(seconds) {
        // A new volume with random budgets every few hundred frames.
        let config = StreamingConfig {
            gpu_budget_bytes: (8 + rng.next() % 120) << 20,
            // At least 16 MiB: sled's cache and the bricks in transit take 13 (below that
            // the volume refuses to start, which is tested elsewhere).
            cpu_budget_bytes: (16 + rng.next() % 240) << 20,
            sled_cache_bytes: 1 << 20,
            uploads_per_frame: 1 + (rng.next() % 64) as usize,
            ..StreamingConfig::default()
        };
        peak_budgets = peak_budgets.max(config.cpu_budget_bytes + config.gpu_budget_bytes);
        // After the last volume was dropped and wgpu, polled, has freed its GPU objects
        // (without the poll the last volume's cache texture is still counted), and not
        // before the first volume (that is the baseline, not memory a volume left).
        ctx.wait_idle().unwrap();
        if volumes > 0 {
            rss_at_volume_starts.extend(resident_bytes());
        }
        let tf = TransferFunction::preset(presets[0]).unwrap();
        let mut volume = stream(&ctx, &store, &tf, config.clone());
        volumes += 1;
        let mut settings = settings(128);
        for _ in 0..(max_frames / 4 + rng.next() % (max_frames - max_frames / 4)) {
            if rng.next().is_multiple_of(16) {
                let name = presets[(rng.next() % presets.len() as u64) as usize];
                volume
                    .set_transfer_function(&ctx, &TransferFunction::preset(name).unwrap())
                    .unwrap();
            }
            if rng.next().is_multiple_of(32) {
                volume.set_max_voxel_pixels(0.5 + 3.0 * rng.unit());
                settings.mode = if rng.next().is_multiple_of(3) {
                    RenderMode::Mip
                } else {
                    RenderMode::Dvr
                };
            }
            let camera = Camera::orbit(
                &geometry,
                360.0 * rng.unit(),
                -80.0 + 160.0 * rng.unit(),
                0.5 + 4.0 * rng.unit(),
                Projection::Perspective { fov_y_deg: 30.0 },
            );
            let stats = volume.frame(&ctx, &camera, &settings).unwrap();
            frames += 1;
            heartbeat.store(frames, Ordering::Relaxed);
            let slack = |budget: u64| budget + budget / 10;
            assert!(
                stats.cpu_bytes <= slack(config.cpu_budget_bytes),
                "frame {frames}: CPU cache {} over its budget {}",
                stats.cpu_bytes,
                config.cpu_budget_bytes
            );
            assert!(
                stats.gpu_bytes <= slack(config.gpu_budget_bytes),
                "frame {frames}: GPU cache {} over its budget {}",
                stats.gpu_bytes,
                config.gpu_budget_bytes
            );
            if frames.is_multiple_of(8) {
                ctx.wait_idle().unwrap();
            }
            if let Some(rss) = resident_bytes() {
                // The process beyond its start: both caches (at the peak budgets so far) plus a
                // fixed allowance for the device's own buffers (page table, readback ring,
                // pipelines).
                let allowed = slack(peak_budgets) + (256 << 20);
                let over = rss as i64 - rss_at_start as i64 - allowed as i64;
                worst_rss_over = worst_rss_over.max(over);
                assert!(
                    over <= 0,
                    "frame {frames}: RSS {rss} B grew beyond the budgets by {over} B"
                );
            }
        }
    }
    heartbeat.store(u64::MAX, Ordering::Relaxed);
    watched.join().unwrap();
    println!(
        "soak: {frames} frames over {volumes} volumes in {:.0} s; worst RSS margin {} MiB below the bound",
        started.elapsed().as_secs_f64(),
        (-worst_rss_over) >> 20
    );
    // The trend a leak (or memory a dropped volume keeps) would show: RSS when each new
    // volume starts, first quarter vs last. It must not rise by more than a fifth of the
    // peak budgets. Measured in a 540 s run (17 volumes, 10-40 frames each, peak budgets
    // 299 MiB): with glibc's default arenas the mean rose 237 -> 335 MiB (+98), with the cap
    // of malloc_arenas.rs 208 -> 253 MiB (+45, in two steps at volumes 5 and 12, then flat).
    // A tenth (30 MiB) is not met yet: what the remaining steps are is not known.
    let quarter = (rss_at_volume_starts.len() / 4).max(1);
    let mean_mib = |xs: &[u64]| xs.iter().sum::<u64>() as f64 / xs.len().max(1) as f64 / 1048576.0;
    let first = mean_mib(&rss_at_volume_starts[..quarter.min(rss_at_volume_starts.len())]);
    let last =
        mean_mib(&rss_at_volume_starts[rss_at_volume_starts.len().saturating_sub(quarter)..]);
    println!(
        "soak: RSS at volume start, mean of the first quarter {first:.0} MiB, of the last {last:.0} MiB (peak budgets {} MiB)",
        peak_budgets >> 20
    );
    println!(
        "soak: RSS at each volume start (MiB): {:?}",
        rss_at_volume_starts
            .iter()
            .map(|r| r >> 20)
            .collect::<Vec<_>>()
    );
    if rss_at_volume_starts.len() >= 8 {
        let allowed = (peak_budgets as f64 / 1048576.0) / 5.0;
        assert!(
            last <= first + allowed,
            "RSS at volume start rose from {first:.0} MiB (first quarter) to {last:.0} MiB \
             (last quarter), more than a fifth of the peak budgets ({allowed:.0} MiB)"
        );
    }
}
