//! `strata-bench timecritical`: the time-critical paper's Table 2 on a store. A 360° orbit is
//! rendered twice, once at a fixed sampling rate (the "standard rendering") and once under the
//! time-critical controller, and for each the mean and standard deviation of the frame rate are
//! printed. The frame rate is the one the controller sees: the GPU time of the raycast pass
//! (timestamps where the adapter has them, else submit → done). Both runs start from a viewer
//! that has been showing the first view for a few frames, as a user's rotation would.
//!
//! A third run renders the first view over and over at the fixed rate: the frame-to-frame
//! noise of this machine at that moment (on lavapipe frame time is CPU time, shared with
//! whatever else runs). No controller can make an orbit steadier than that floor.

use std::collections::{HashMap, VecDeque};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use strata_loader::store_volume::{
    check_cut_fits, classify_empty, page_table_for_cut, slots_needed, GpuCut, ResidentBricks,
};
use strata_render::{
    Camera, ControllerConfig, FrameInputs, FrameQuality, GpuContext, Projection, RenderSettings,
    Shading, TimeCriticalConfig, TimeCriticalController, TransferFunctionTable, ValueMapping,
    VolumeGeometry,
};
use strata_storage::Store;

use strata_viewer::export::choose_transfer_function;

/// Frames the CPU may run ahead of the GPU, as a swapchain would allow.
const FRAMES_IN_FLIGHT: usize = 2;
/// Frames on the first view before the orbit starts (pipeline warm-up; the controller settles,
/// as it would have while the user looked before rotating). Not in the statistics.
const LEAD_IN_FRAMES: usize = 12;
/// Frames of the noise-floor run at most (it only needs enough for a stable σ).
const NOISE_FLOOR_FRAMES: usize = 120;
/// How long to wait for the last frames' timings after the orbit.
const DRAIN_ATTEMPTS: usize = 200;

pub struct Options {
    pub store: PathBuf,
    pub target_fps: f64,
    pub frames: usize,
    pub csv: Option<PathBuf>,
    pub size: String,
    pub step: f64,
    pub tf: Option<String>,
    pub level: u8,
    pub elevation: f64,
    /// GPU memory each level's cut may use (None: as much as the level needs).
    pub gpu_budget_bytes: Option<u64>,
}

/// The fixed cuts the level-of-detail factor can ask for, one per octree level, built on
/// first use (the streaming loader would do this incrementally; this bench has no loader).
struct Cuts<'a> {
    store: &'a Store,
    geometry: &'a VolumeGeometry,
    mapping: ValueMapping,
    tf_table: &'a TransferFunctionTable,
    finest_level: u8,
    root_level: u8,
    by_level: HashMap<u8, GpuCut>,
    gpu_budget_bytes: Option<u64>,
}

impl Cuts<'_> {
    fn level_for(&self, lod_factor: f64) -> u8 {
        // A factor of 2^k lets a voxel cover 2^k pixels: k levels coarser than the finest.
        let coarser = lod_factor.max(1.0).log2().round().clamp(0.0, 32.0) as u8;
        self.finest_level
            .saturating_add(coarser)
            .min(self.root_level)
    }

    fn get(&mut self, ctx: &GpuContext, level: u8) -> Result<&GpuCut> {
        if !self.by_level.contains_key(&level) {
            // Checked before the level is read: a level over the budget is refused without
            // reading its gigabytes first.
            let mut table = page_table_for_cut(self.store, self.geometry, |_| level);
            check_cut_fits(
                ctx,
                slots_needed(&table),
                self.gpu_budget_bytes,
                &format!("level {level} of {}", self.store.path().display()),
            )?;
            classify_empty(self.store, &mut table, self.mapping, self.tf_table);
            let bricks = ResidentBricks::load(self.store, &table)?;
            let cut = GpuCut::upload_within(
                ctx,
                &bricks,
                &table,
                self.geometry.page_dims(),
                self.tf_table,
                self.gpu_budget_bytes,
            )?;
            eprintln!("  (level {level}: {} bricks resident)", bricks.len());
            self.by_level.insert(level, cut);
        }
        self.by_level
            .get(&level)
            .with_context(|| format!("cut of level {level} missing after upload"))
    }
}

struct FrameRecord {
    frame: usize,
    azimuth_deg: f64,
    quality: FrameQuality,
    /// Jitter as rendered: the controller forces it below one sample per voxel, the default
    /// settings have it on anyway.
    jitter: bool,
    gpu_ms: Option<f64>,
}

struct RunSummary {
    mean_fps: f64,
    sigma_fps: f64,
    min_fps: f64,
    max_fps: f64,
    timed_frames: usize,
    /// Frames over the GPU time they took: the rate a user counts (the mean of per-frame rates
    /// reads higher by about σ²/2 of the noise).
    frames_per_gpu_second: f64,
    wall_fps: f64,
}

fn summarize(records: &[FrameRecord], wall_seconds: f64) -> Result<RunSummary> {
    let fps: Vec<f64> = records
        .iter()
        .filter_map(|r| r.gpu_ms)
        .map(|ms| 1000.0 / ms)
        .collect();
    if fps.is_empty() {
        bail!("no frame timings arrived; the GPU reported nothing");
    }
    let mean = fps.iter().sum::<f64>() / fps.len() as f64;
    let sigma = (fps.iter().map(|f| (f - mean).powi(2)).sum::<f64>() / fps.len() as f64).sqrt();
    Ok(RunSummary {
        mean_fps: mean,
        sigma_fps: sigma,
        min_fps: fps.iter().cloned().fold(f64::INFINITY, f64::min),
        max_fps: fps.iter().cloned().fold(0.0, f64::max),
        timed_frames: fps.len(),
        frames_per_gpu_second: fps.len() as f64 / fps.iter().map(|f| 1.0 / f).sum::<f64>(),
        wall_fps: records.len() as f64 / wall_seconds.max(1e-9),
    })
}

pub fn run(options: Options) -> Result<()> {
    if !(options.target_fps.is_finite() && options.target_fps > 0.0) {
        bail!(
            "--target must be a positive frame rate, not {}",
            options.target_fps
        );
    }
    if options.frames == 0 {
        bail!("--frames must be at least 1");
    }
    if !(options.step.is_finite() && options.step > 0.0) {
        bail!(
            "--step must be a positive number of voxels, not {}",
            options.step
        );
    }
    let (width, height) = strata_viewer::export::parse_size(&options.size)?;
    let store = Store::open(&options.store)
        .with_context(|| format!("cannot open store {}", options.store.display()))?;
    let header = store.header().clone();
    let geometry = header.geometry.clone();
    let mapping = header.value_mapping.mapping;
    let tf = choose_transfer_function(options.tf.as_deref(), &header.modality)?;
    let physical = (
        mapping.physical(header.stored_range[0] as f64),
        mapping.physical(header.stored_range[1] as f64),
    );
    let tf_table = tf.table(physical.0.min(physical.1), physical.0.max(physical.1));
    let ctx = GpuContext::headless()?;
    let root_level = (store.layout().level_count() - 1) as u8;
    let mut cuts = Cuts {
        store: &store,
        geometry: &geometry,
        mapping,
        tf_table: &tf_table,
        finest_level: options.level.min(root_level),
        root_level,
        by_level: HashMap::new(),
        gpu_budget_bytes: options.gpu_budget_bytes,
    };
    let base_settings = RenderSettings {
        width,
        height,
        shading: Some(Shading::default()),
        ..RenderSettings::default()
    };
    let finest = cuts.finest_level;
    let mut raycaster = {
        let cut = cuts.get(&ctx, finest)?;
        strata_render::Raycaster::new(&ctx, &cut.cache)
    };
    // Both jitter variants compiled before the first timed frame.
    for jitter in [false, true] {
        raycaster.prepare(
            &ctx,
            &RenderSettings {
                jitter,
                ..base_settings.clone()
            },
        );
    }
    println!(
        "time-critical bench: {} ({:?}), {width}x{height}, {} frames per 360° orbit, target {:.1} fps",
        options.store.display(),
        geometry.dims,
        options.frames,
        options.target_fps
    );
    println!(
        "GPU: {}; frame time from {:?}",
        ctx.adapter_name(),
        raycaster.frame_timing_source()
    );

    let fixed_rate = 1.0 / options.step;
    let fixed_quality = FrameQuality {
        sampling_rate: fixed_rate,
        lod_factor: 1.0,
        jitter: false,
        interactive: true,
    };
    let config = TimeCriticalConfig {
        controller: ControllerConfig {
            target_fps: options.target_fps,
            ..Default::default()
        },
        ..Default::default()
    };
    let mut controlled = TimeCriticalController::new(config, fixed_rate);

    // `controller` None: the standard rendering at the fixed rate.
    // `degrees` 0: the noise-floor run on the first view.
    let mut orbit = |label: &str,
                     mut controller: Option<&mut TimeCriticalController>,
                     frames: usize,
                     degrees: f64|
     -> Result<(Vec<FrameRecord>, f64)> {
        let mut records: Vec<FrameRecord> = Vec::new();
        let mut frame_of: HashMap<u64, usize> = HashMap::new();
        let mut in_flight = VecDeque::new();
        let mut started = None;
        let total = LEAD_IN_FRAMES + frames;
        for i in 0..total {
            if i == LEAD_IN_FRAMES {
                started = Some(Instant::now());
            }
            let orbit_frame = i.saturating_sub(LEAD_IN_FRAMES);
            let azimuth_deg = degrees * orbit_frame as f64 / frames as f64;
            let camera = Camera::orbit(
                &geometry,
                azimuth_deg,
                options.elevation,
                1.0,
                Projection::Perspective { fov_y_deg: 30.0 },
            );
            let quality = match controller.as_deref_mut() {
                Some(c) => c.plan_frame(true),
                None => fixed_quality,
            };
            let mut settings = base_settings.clone();
            quality.apply_to(&mut settings);
            let level = cuts.level_for(quality.lod_factor);
            let cut = cuts.get(&ctx, level)?;
            let scene = FrameInputs {
                cache: &cut.cache,
                page_table: &cut.page_table,
                transfer_function: &cut.transfer_function,
                geometry: &geometry,
                mapping,
                camera: &camera,
                settings: &settings,
            };
            in_flight.push_back(raycaster.render_measured(&ctx, &scene)?);
            let frame_number = raycaster.frame_number();
            if let Some(c) = controller.as_deref_mut() {
                c.submitted(frame_number, quality);
            }
            if i >= LEAD_IN_FRAMES {
                frame_of.insert(frame_number, records.len());
                records.push(FrameRecord {
                    frame: orbit_frame,
                    azimuth_deg,
                    quality,
                    jitter: settings.jitter,
                    gpu_ms: None,
                });
            }
            if in_flight.len() > FRAMES_IN_FLIGHT {
                if let Some(oldest) = in_flight.pop_front() {
                    ctx.wait_for_submission(oldest)?;
                }
            }
            for timing in raycaster.try_take_frame_timings(&ctx) {
                if let Some(c) = controller.as_deref_mut() {
                    c.observe(timing);
                }
                if let Some(&k) = frame_of.get(&timing.frame_number) {
                    records[k].gpu_ms = Some(timing.milliseconds);
                }
            }
        }
        ctx.wait_idle()?;
        let wall_seconds = started.map(|t| t.elapsed().as_secs_f64()).unwrap_or(0.0);
        for _ in 0..DRAIN_ATTEMPTS {
            if records.iter().all(|r| r.gpu_ms.is_some()) {
                break;
            }
            for timing in raycaster.try_take_frame_timings(&ctx) {
                if let Some(&k) = frame_of.get(&timing.frame_number) {
                    records[k].gpu_ms = Some(timing.milliseconds);
                }
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        eprintln!("  {label}: done");
        Ok((records, wall_seconds))
    };

    let (floor_records, floor_wall) = orbit(
        "noise floor",
        None,
        options.frames.min(NOISE_FLOOR_FRAMES),
        0.0,
    )?;
    let (fixed_records, fixed_wall) = orbit("fixed rate", None, options.frames, 360.0)?;
    let (tc_records, tc_wall) = orbit(
        "time-critical",
        Some(&mut controlled),
        options.frames,
        360.0,
    )?;
    let floor_summary = summarize(&floor_records, floor_wall)?;
    let fixed_summary = summarize(&fixed_records, fixed_wall)?;
    let tc_summary = summarize(&tc_records, tc_wall)?;

    let mean_rate = tc_records
        .iter()
        .map(|r| r.quality.sampling_rate)
        .sum::<f64>()
        / tc_records.len() as f64;
    let max_lod = tc_records
        .iter()
        .map(|r| r.quality.lod_factor)
        .fold(1.0, f64::max);
    println!();
    println!(
        "{:<34} {:>9} {:>8} {:>8} {:>8} {:>8} {:>11} {:>9}",
        "", "mean fps", "σ", "σ/mean", "min", "max", "frames/GPUs", "wall fps"
    );
    for (name, s) in [
        (
            "noise floor (first view, fixed)".to_string(),
            &floor_summary,
        ),
        (
            format!("fixed rate ({fixed_rate:.2} samples/voxel)"),
            &fixed_summary,
        ),
        (
            format!("time-critical (mean {mean_rate:.2} s/v)"),
            &tc_summary,
        ),
    ] {
        println!(
            "{name:<34} {:>9.2} {:>8.3} {:>7.2}% {:>8.2} {:>8.2} {:>11.2} {:>9.2}",
            s.mean_fps,
            s.sigma_fps,
            100.0 * s.sigma_fps / s.mean_fps,
            s.min_fps,
            s.max_fps,
            s.frames_per_gpu_second,
            s.wall_fps
        );
    }
    println!(
        "time-critical vs target: mean {:+.1} %, frames/GPU-second {:+.1} %; σ {:.2}× the fixed run's; lod factor reached {max_lod}; {}/{} frames timed",
        100.0 * (tc_summary.mean_fps / options.target_fps - 1.0),
        100.0 * (tc_summary.frames_per_gpu_second / options.target_fps - 1.0),
        tc_summary.sigma_fps / fixed_summary.sigma_fps.max(1e-12),
        tc_summary.timed_frames,
        tc_records.len()
    );
    if let Some(path) = &options.csv {
        write_csv(
            path,
            &[
                ("noise-floor", &floor_records),
                ("fixed", &fixed_records),
                ("time-critical", &tc_records),
            ],
        )?;
        println!("per-frame CSV: {}", path.display());
    }
    Ok(())
}

fn write_csv(path: &Path, runs: &[(&str, &Vec<FrameRecord>)]) -> Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut out = std::io::BufWriter::new(file);
    writeln!(
        out,
        "run,frame,azimuth_deg,gpu_ms,fps,sampling_rate,step_voxels,lod_factor,jitter"
    )?;
    for (run, records) in runs {
        for r in records.iter() {
            let (ms, fps) = match r.gpu_ms {
                Some(ms) => (format!("{ms:.4}"), format!("{:.4}", 1000.0 / ms)),
                None => (String::new(), String::new()),
            };
            writeln!(
                out,
                "{run},{},{:.3},{ms},{fps},{:.5},{:.5},{},{}",
                r.frame,
                r.azimuth_deg,
                r.quality.sampling_rate,
                r.quality.step_factor(),
                r.quality.lod_factor,
                r.jitter
            )?;
        }
    }
    out.flush()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
