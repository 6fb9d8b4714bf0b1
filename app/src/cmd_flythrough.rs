//! `strata flythrough`: replays a scripted camera path through a store with the streaming
//! loader and writes per-frame stats as CSV. The summary reports time to first frame, time to
//! converge per viewpoint, the frame-time distribution, I/O amplification, and the same views
//! rendered in core (every brick of the converged cut loaded up front) measured in the same run.

use std::collections::HashSet;
use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Args;
use strata_loader::store_volume::{sampled_entries_only, GpuCut};
use strata_loader::{
    Distribution, FrameStats, ResidentBricks, SelectionTiming, StreamingConfig, StreamingVolume,
};
use strata_render::{compare_rgba8, Camera, GpuContext, RenderSettings};
use strata_source::VolumeSource;
use strata_types::BrickId;

use strata_viewer::camera_path::viewpoint;
use strata_viewer::export::{choose_transfer_function, parse_size};

#[derive(Args)]
pub struct FlythroughArgs {
    /// A store directory, or http://HOST:PORT/v1/stores/NAME served by `strata serve`.
    pub store: String,
    /// Bearer token for a server that requires one.
    #[arg(long)]
    pub token_file: Option<PathBuf>,
    /// Frames to render at most over the whole path.
    #[arg(long, default_value_t = 600)]
    pub frames: usize,
    /// Per-frame stats.
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Image size WxH.
    #[arg(long, default_value = "512x512")]
    pub size: String,
    #[arg(long, default_value_t = 256, value_parser = crate::cli_checks::budget_mib)]
    pub gpu_mib: u64,
    #[arg(long, default_value_t = 512, value_parser = crate::cli_checks::budget_mib)]
    pub cpu_mib: u64,
    /// Bricks uploaded per frame at most.
    #[arg(long, default_value_t = 64)]
    pub uploads: usize,
    /// Quality factor: refine while a voxel covers more than this many pixels.
    #[arg(long, default_value_t = 1.0)]
    pub quality: f64,
    /// Transfer function preset or JSON file.
    #[arg(long)]
    pub tf: Option<String>,
    /// Viewpoints on the path.
    #[arg(long, default_value_t = 5)]
    pub stops: usize,
    /// Frames spent moving between viewpoints.
    #[arg(long, default_value_t = 12)]
    pub glide_frames: usize,
    /// Frames to wait at a viewpoint for convergence before moving on.
    #[arg(long, default_value_t = 300)]
    pub settle_frames: usize,
    /// Seconds to wait at a viewpoint for convergence before moving on, whichever of this and
    /// --settle-frames ends first: a fast GPU passes 3000 frames in 9 s, lavapipe at 512² in
    /// an hour.
    #[arg(long)]
    pub settle_seconds: Option<f64>,
    /// Still frames to keep a viewpoint after it converged, counting cut changes (LOD
    /// flicker: "cut changes while still", which should be 0).
    #[arg(long, default_value_t = 30)]
    pub hold_frames: usize,
    #[arg(long, default_value_t = 2)]
    pub fetch_threads: usize,
    /// Skip the in-core comparison.
    #[arg(long)]
    pub no_in_core: bool,
    /// Turn visibility feedback off.
    #[arg(long)]
    pub no_visibility: bool,
    /// The raycaster's traversal: `flat` page table or the cut's `octree`. Not given: flat,
    /// unless its per-page buffers exceed the device's storage-binding limit or the grid has
    /// over 2^18 page cells (beyond 2048³ voxels).
    #[arg(long, value_enum)]
    pub traversal: Option<crate::cmd_render::TraversalArg>,
    /// Apply a cut selection every N-th frame, waiting for it (a fixed cadence), instead of
    /// the newest one whenever it is ready: lavapipe draws about one frame per selection, a
    /// fast GPU several (an H200 ~7.5 at 1024²), so this replays a fast GPU's cadence on a
    /// slow adapter.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub frames_per_selection: Option<u32>,
}

struct StopResult {
    stop: usize,
    converged: bool,
    /// "converged" or "converged at budget (N nodes left coarser than wanted)".
    status: String,
    seconds_to_converge: f64,
    frames_to_converge: usize,
    working_set_bricks: usize,
    /// Cut changes at this viewpoint while the camera stood still (the loader's
    /// `cut_changes_while_still_total` over the settle and hold frames).
    cut_changes_while_still: u64,
    /// Still frames held after converging, and how many of them were not converged.
    held_frames: usize,
    held_not_converged: usize,
    in_core: Option<InCore>,
}

struct InCore {
    bricks: usize,
    load_seconds: f64,
    frame_seconds: f64,
    streamed_frame_seconds: f64,
    psnr_db: f64,
}

pub fn run(args: FlythroughArgs) -> Result<()> {
    let (width, height) = parse_size(&args.size)?;
    anyhow::ensure!(
        args.quality.is_finite() && args.quality > 0.0,
        "--quality must be positive"
    );
    let settings = RenderSettings {
        width,
        height,
        ..RenderSettings::default()
    };
    if let Some(s) = args.settle_seconds {
        anyhow::ensure!(
            s.is_finite() && s > 0.0,
            "--settle-seconds must be a positive number of seconds, not {s}"
        );
    }
    let ctx = GpuContext::headless()?;
    eprintln!("GPU: {}", ctx.adapter_name());
    let config = StreamingConfig {
        gpu_budget_bytes: args.gpu_mib << 20,
        cpu_budget_bytes: args.cpu_mib << 20,
        uploads_per_frame: args.uploads,
        max_voxel_pixels: args.quality,
        fetch_threads: args.fetch_threads,
        visibility_feedback: !args.no_visibility,
        // As the viewer: frames apply the newest finished selection and never wait for one
        // (unless a fixed cadence is asked for).
        selection: args
            .frames_per_selection
            .map_or(SelectionTiming::Background, SelectionTiming::EveryNthFrame),
        traversal: args.traversal.map(|t| t.traversal()),
        ..StreamingConfig::default()
    };
    let mut csv = match &args.csv {
        Some(path) => {
            let mut file = std::io::BufWriter::new(
                std::fs::File::create(path)
                    .with_context(|| format!("creating {}", path.display()))?,
            );
            writeln!(file, "{}", CSV_HEADER)?;
            Some(file)
        }
        None => None,
    };

    // Time to first frame: open the store, stream it, draw one frame, wait for the GPU.
    let opening = Instant::now();
    let store: Arc<dyn VolumeSource> = strata_viewer::volume_location::open_source(
        &args.store,
        args.token_file.as_deref(),
        config.sled_cache_bytes,
    )?;
    let tf = choose_transfer_function(args.tf.as_deref(), &store.header().modality)?;
    let mut volume = StreamingVolume::new(&ctx, store.clone(), &tf, config.clone())
        .with_context(|| format!("cannot stream store {}", args.store))?;
    let open_seconds = opening.elapsed().as_secs_f64();
    if let Some(note) = volume.traversal_note() {
        eprintln!("{note}");
    }
    let geometry = volume.geometry().clone();

    let mut frame_seconds = Vec::new();
    let mut loader_seconds = Vec::new();
    let mut loader_cpu_seconds = Vec::new();
    let mut first_frame_seconds = None;
    let mut stops = Vec::new();
    let mut ever_in_working_set: HashSet<BrickId> = HashSet::new();
    let mut total_frames = 0usize;
    'path: for stop in 0..args.stops.max(1) {
        // Glide from the previous viewpoint (the first stop is reached from where we are).
        let glide = if stop == 0 { 0 } else { args.glide_frames };
        for g in 1..=glide {
            if total_frames >= args.frames {
                break 'path;
            }
            let camera = viewpoint(
                &geometry,
                stop as f64 - 1.0 + g as f64 / glide as f64,
                args.stops,
            );
            let (stats, seconds) = timed_frame(&ctx, &mut volume, &camera, &settings)?;
            record(&mut csv, total_frames, stop, "glide", seconds, &stats)?;
            frame_seconds.push(seconds);
            loader_seconds.push(stats.loader_seconds);
            loader_cpu_seconds.push(stats.loader_cpu_seconds);
            total_frames += 1;
            first_frame_seconds.get_or_insert(opening.elapsed().as_secs_f64());
        }
        let camera = viewpoint(&geometry, stop as f64, args.stops);
        let arrived = Instant::now();
        let mut result = StopResult {
            stop,
            converged: false,
            status: String::new(),
            seconds_to_converge: f64::NAN,
            frames_to_converge: 0,
            working_set_bricks: 0,
            cut_changes_while_still: 0,
            held_frames: 0,
            held_not_converged: 0,
            in_core: None,
        };
        let changes_before = volume.last_stats().cut_changes_while_still_total;
        for held in 0..args.settle_frames.max(1) {
            if args
                .settle_seconds
                .is_some_and(|s| held > 0 && arrived.elapsed().as_secs_f64() >= s)
            {
                break;
            }
            if total_frames >= args.frames {
                stops.push(result);
                break 'path;
            }
            let (stats, seconds) = timed_frame(&ctx, &mut volume, &camera, &settings)?;
            record(&mut csv, total_frames, stop, "hold", seconds, &stats)?;
            frame_seconds.push(seconds);
            loader_seconds.push(stats.loader_seconds);
            loader_cpu_seconds.push(stats.loader_cpu_seconds);
            total_frames += 1;
            first_frame_seconds.get_or_insert(opening.elapsed().as_secs_f64());
            if stats.converged {
                result.converged = true;
                result.status = stats.convergence_status();
                result.seconds_to_converge = arrived.elapsed().as_secs_f64();
                result.frames_to_converge = held + 1;
                result.working_set_bricks = stats.working_set_bricks;
                ever_in_working_set.extend(volume.working_set().iter().copied());
                break;
            }
        }
        // Hold the converged view: a still view must stay still (issue 35).
        if result.converged {
            for _ in 0..args.hold_frames {
                if total_frames >= args.frames {
                    break;
                }
                let (stats, seconds) = timed_frame(&ctx, &mut volume, &camera, &settings)?;
                record(&mut csv, total_frames, stop, "still", seconds, &stats)?;
                frame_seconds.push(seconds);
                loader_seconds.push(stats.loader_seconds);
                loader_cpu_seconds.push(stats.loader_cpu_seconds);
                total_frames += 1;
                result.held_frames += 1;
                result.held_not_converged += usize::from(!stats.converged);
            }
        }
        result.cut_changes_while_still =
            volume.last_stats().cut_changes_while_still_total - changes_before;
        if result.converged && !args.no_in_core {
            result.in_core = Some(in_core(
                &ctx,
                store.as_ref(),
                &mut volume,
                &camera,
                &settings,
            )?);
        }
        print_stop(&result);
        stops.push(result);
    }
    ever_in_working_set.extend(volume.working_set().iter().copied());
    for failure in volume.take_failures() {
        eprintln!("warning: {}", failure.message);
    }
    if let Some(mut file) = csv {
        file.flush()?;
    }
    let record = RunRecord {
        open_seconds,
        first_frame_seconds,
        frame_seconds,
        loader_seconds,
        loader_cpu_seconds,
        stops,
        ever_in_working_set,
    };
    summary(&args, &volume, &record);
    Ok(())
}

fn timed_frame(
    ctx: &GpuContext,
    volume: &mut StreamingVolume,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<(FrameStats, f64)> {
    let t = Instant::now();
    let stats = volume.frame(ctx, camera, settings)?;
    volume.wait_for_gpu(ctx)?;
    Ok((stats, t.elapsed().as_secs_f64()))
}

/// The converged cut loaded up front into its own cache and rendered: same view, same
/// field, no streaming. Also checks the streamed image equals it.
fn in_core(
    ctx: &GpuContext,
    store: &dyn VolumeSource,
    volume: &mut StreamingVolume,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<InCore> {
    let streamed = volume.read_frame_blocking(ctx)?;
    let mut streamed_times = Vec::new();
    for _ in 0..3 {
        let (_, seconds) = timed_frame(ctx, volume, camera, settings)?;
        streamed_times.push(seconds);
    }
    let table = sampled_entries_only(volume.page_table());
    let load = Instant::now();
    let bricks = ResidentBricks::load(store, &table)?;
    let mut cut = GpuCut::upload(
        ctx,
        &bricks,
        &table,
        table.page_dims,
        volume.transfer_function_table(),
    )?;
    let load_seconds = load.elapsed().as_secs_f64();
    let geometry = volume.geometry().clone();
    let mapping = volume.mapping();
    let in_core_image = cut.render_blocking(ctx, &geometry, mapping, camera, settings)?;
    let mut times = Vec::new();
    for _ in 0..3 {
        let t = Instant::now();
        cut.render_blocking(ctx, &geometry, mapping, camera, settings)?;
        times.push(t.elapsed().as_secs_f64());
    }
    let psnr_db = compare_rgba8(&streamed.rgba, &in_core_image.rgba)?.psnr_db;
    Ok(InCore {
        bricks: bricks.len(),
        load_seconds,
        frame_seconds: Distribution::of(&times).p50,
        streamed_frame_seconds: Distribution::of(&streamed_times).p50,
        psnr_db,
    })
}

/// "cut changes while still: N" with the hold that followed convergence.
fn still_line(r: &StopResult) -> String {
    format!(
        "cut changes while still: {} (held {} frames after converging, {} of them not converged)",
        r.cut_changes_while_still, r.held_frames, r.held_not_converged
    )
}

fn print_stop(r: &StopResult) {
    let converge = if r.converged {
        format!(
            "{} in {:.2} s ({} frames), working set {} bricks",
            r.status, r.seconds_to_converge, r.frames_to_converge, r.working_set_bricks
        )
    } else {
        "did not converge within --settle-frames / --settle-seconds".to_string()
    };
    eprintln!("viewpoint {}: {converge}", r.stop);
    eprintln!("  {}", still_line(r));
    if let Some(c) = &r.in_core {
        eprintln!(
            "  in core: {} bricks loaded in {:.2} s; frame {:.1} ms in core vs {:.1} ms streamed (ratio {:.2}); streamed vs in-core PSNR {:.1} dB",
            c.bricks,
            c.load_seconds,
            c.frame_seconds * 1e3,
            c.streamed_frame_seconds * 1e3,
            c.streamed_frame_seconds / c.frame_seconds.max(1e-9),
            c.psnr_db
        );
    }
}

/// What one run measured, for the summary.
struct RunRecord {
    open_seconds: f64,
    first_frame_seconds: Option<f64>,
    frame_seconds: Vec<f64>,
    loader_seconds: Vec<f64>,
    /// Frame-thread CPU time of the same span (thread CPU clock).
    loader_cpu_seconds: Vec<f64>,
    stops: Vec<StopResult>,
    ever_in_working_set: HashSet<BrickId>,
}

fn summary(args: &FlythroughArgs, volume: &StreamingVolume, record: &RunRecord) {
    let RunRecord {
        open_seconds,
        first_frame_seconds,
        frame_seconds,
        loader_seconds,
        loader_cpu_seconds,
        stops,
        ever_in_working_set,
    } = record;
    let last = volume.last_stats();
    let frames = Distribution::of(frame_seconds);
    let loader = Distribution::of(loader_seconds);
    let loader_cpu = Distribution::of(loader_cpu_seconds);
    println!(
        "flythrough of {} ({} frames, {} viewpoints)",
        args.store,
        frames.count,
        stops.len()
    );
    println!(
        "  traversal {}: {} index bytes on the GPU at the end",
        volume.traversal().name(),
        volume.gpu_index_bytes()
    );
    println!(
        "  time to first frame (open + first frame on the GPU): {:.3} s, of which opening the store and reading the root {:.3} s",
        first_frame_seconds.unwrap_or(f64::NAN),
        open_seconds
    );
    for r in stops {
        println!(
            "  viewpoint {}: {}",
            r.stop,
            if r.converged {
                format!(
                    "{} in {:.2} s / {} frames",
                    r.status, r.seconds_to_converge, r.frames_to_converge
                )
            } else {
                "not converged".into()
            }
        );
        println!("    {}", still_line(r));
    }
    println!(
        "  frame time ms: p50 {:.1} p95 {:.1} p99 {:.1} max {:.1} mean {:.1}",
        frames.p50 * 1e3,
        frames.p95 * 1e3,
        frames.p99 * 1e3,
        frames.max * 1e3,
        frames.mean * 1e3
    );
    println!(
        "  loader share per frame ms: p50 {:.2} p95 {:.2} max {:.2} (never a read)",
        loader.p50 * 1e3,
        loader.p95 * 1e3,
        loader.max * 1e3
    );
    println!(
        "  loader frame-thread CPU ms: p50 {:.2} p95 {:.2} max {:.2} (thread CPU clock; cuts selected on strata-cut-select: {} applied, {} dropped as stale)",
        loader_cpu.p50 * 1e3,
        loader_cpu.p95 * 1e3,
        loader_cpu.max * 1e3,
        last.selections_applied_total,
        last.selections_dropped_total
    );
    let distinct = ever_in_working_set.len().max(1) as u64;
    println!(
        "  I/O: {} bricks read ({:.1} MB decompressed, {:.1} MB from the store) for {} distinct working-set bricks: amplification {:.2} (bricks read / working-set bricks)",
        last.bricks_read_total,
        last.brick_bytes_read_total as f64 / 1e6,
        last.stored_bytes_read_total as f64 / 1e6,
        distinct,
        last.bricks_read_total as f64 / distinct as f64
    );
    println!(
        "  caches: GPU {} of {} slots ({:.0} MiB budget), CPU {:.0} of {:.0} MiB (sled {:.0} MiB included), CPU hit rate {:.2}, prefetch {} loaded / {} used (hit rate {:.2}), stale requests dropped {}",
        last.gpu_slots_used,
        last.gpu_slots_capacity,
        last.gpu_budget_bytes as f64 / (1 << 20) as f64,
        last.cpu_bytes as f64 / (1 << 20) as f64,
        last.cpu_budget_bytes as f64 / (1 << 20) as f64,
        volume.config().sled_cache_bytes as f64 / (1 << 20) as f64,
        last.cpu_hit_rate,
        last.prefetch_loaded_total,
        last.prefetch_used_total,
        last.prefetch_hit_rate,
        last.stale_dropped_total
    );
    let in_core: Vec<&InCore> = stops.iter().filter_map(|s| s.in_core.as_ref()).collect();
    if !in_core.is_empty() {
        let ratio: Vec<f64> = in_core
            .iter()
            .map(|c| c.streamed_frame_seconds / c.frame_seconds.max(1e-9))
            .collect();
        let psnr = in_core
            .iter()
            .map(|c| c.psnr_db)
            .fold(f64::INFINITY, f64::min);
        println!(
            "  in core (converged cut loaded up front, same views): streamed/in-core frame time p50 ratio {:.2}, min PSNR streamed vs in-core {:.1} dB, up-front load {:.2}-{:.2} s",
            Distribution::of(&ratio).p50,
            psnr,
            in_core.iter().map(|c| c.load_seconds).fold(f64::INFINITY, f64::min),
            in_core.iter().map(|c| c.load_seconds).fold(0.0, f64::max)
        );
    }
}

const CSV_HEADER: &str = "frame,viewpoint,phase,frame_ms,loader_ms,loader_cpu_ms,converged,leaves,data_leaves,working_set_bricks,gpu_slots_used,gpu_mib,cpu_mib,cpu_hit_rate,gpu_hit_rate,pending,queued,in_flight,stale_dropped_total,uploads,upload_mib,bricks_read_total,stored_mb_read_total,read_mb_per_s,prefetch_loaded_total,prefetch_used_total,prefetch_hit_rate,failed_bricks,gpu_budget_limited,left_coarser,gpu_resident_per_level,blocked_data_upload_slots_balance,data_leaves_per_level,cut_changes_while_still_total";

fn record(
    csv: &mut Option<std::io::BufWriter<std::fs::File>>,
    frame: usize,
    stop: usize,
    phase: &str,
    seconds: f64,
    s: &FrameStats,
) -> Result<()> {
    let Some(file) = csv else { return Ok(()) };
    let join = |v: &[usize]| {
        v.iter()
            .map(|x| x.to_string())
            .collect::<Vec<_>>()
            .join(";")
    };
    writeln!(
        file,
        "{frame},{stop},{phase},{:.3},{:.3},{:.3},{},{},{},{},{},{:.2},{:.2},{:.4},{:.4},{},{},{},{},{},{:.3},{},{:.3},{:.3},{},{},{:.4},{},{},{},{},{},{},{}",
        seconds * 1e3,
        s.loader_seconds * 1e3,
        s.loader_cpu_seconds * 1e3,
        s.converged,
        s.leaves,
        s.data_leaves,
        s.working_set_bricks,
        s.gpu_slots_used,
        s.gpu_bytes as f64 / (1 << 20) as f64,
        s.cpu_bytes as f64 / (1 << 20) as f64,
        s.cpu_hit_rate,
        s.gpu_hit_rate,
        s.pending,
        s.queued,
        s.in_flight,
        s.stale_dropped_total,
        s.uploads,
        s.upload_bytes as f64 / (1 << 20) as f64,
        s.bricks_read_total,
        s.stored_bytes_read_total as f64 / 1e6,
        s.bytes_read_per_second / 1e6,
        s.prefetch_loaded_total,
        s.prefetch_used_total,
        s.prefetch_hit_rate,
        s.failed_bricks,
        s.gpu_budget_limited,
        s.left_coarser,
        join(&s.gpu_resident_per_level),
        join(&s.blocked),
        join(&s.data_leaves_per_level),
        s.cut_changes_while_still_total
    )?;
    Ok(())
}
