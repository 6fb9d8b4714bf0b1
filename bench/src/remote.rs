//! `strata-bench remote <store>`: the flythrough of `strata flythrough` (same viewpoints,
//! glides between them, each viewpoint held until converged), once from the local store and
//! once per round-trip delay through `strata serve` on loopback. The delay is injected in the
//! server (`ServeOptions::added_delay`, slept before every brick answer), not with tc netem:
//! every request then waits one RTT, as over a real link, while many requests overlap.
//!
//! Per viewpoint: time to the first frame there and to convergence, bytes that crossed the
//! network over bytes read from disk in the local run, requests in flight (mean, max over the
//! frames), and frames that waited on the network. A frame "waited" when the loader's part of
//! it (everything before the submit, where any fetch bookkeeping happens) took at least the
//! injected RTT: a frame that blocked on even one request would take a full RTT. (The frame
//! loop makes no blocking call into the source; the count checks that, and the largest loader
//! time is printed beside it, since a busy shared CPU alone can stretch one.)
//!
//! The local flythrough runs twice and the second is the baseline: the first pays the shader
//! compilation that every later run finds cached.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use strata_loader::{FrameStats, StreamingConfig, StreamingVolume};
use strata_render::{GpuContext, RenderSettings};
use strata_service::server::{find_stores, start, ServeOptions};
use strata_service::{RemoteOptions, RemoteSource};
use strata_source::VolumeSource;
use strata_storage::Store;

use strata_viewer::camera_path::viewpoint;
use strata_viewer::export::{choose_transfer_function, parse_size};

#[derive(Args)]
pub struct Options {
    pub store: PathBuf,
    /// Round-trip delays to add on loopback, milliseconds.
    #[arg(long, value_delimiter = ',', default_value = "0,20,80")]
    pub rtt_ms: Vec<u64>,
    /// Image size WxH.
    #[arg(long, default_value = "256x256")]
    pub size: String,
    #[arg(long, default_value_t = 5)]
    pub stops: usize,
    #[arg(long, default_value_t = 12)]
    pub glide_frames: usize,
    /// Give up on a viewpoint after this many frames.
    #[arg(long, default_value_t = 2000)]
    pub settle_frames: usize,
    /// Budgets large enough that the local run converges at every viewpoint.
    #[arg(long, default_value_t = 1024)]
    pub gpu_mib: u64,
    #[arg(long, default_value_t = 2048)]
    pub cpu_mib: u64,
    #[arg(long, default_value_t = 64)]
    pub uploads: usize,
    #[arg(long)]
    pub tf: Option<String>,
    /// HTTP/1.1 (a pool of connections) instead of one HTTP/2 connection.
    #[arg(long)]
    pub http1: bool,
}

impl Options {
    /// The flythrough's defaults for another bench (`bench omezarr`).
    pub(crate) fn for_bench(store: PathBuf, size: &str, stops: usize) -> Options {
        Options {
            store,
            rtt_ms: vec![0],
            size: size.to_string(),
            stops,
            glide_frames: 12,
            settle_frames: 2000,
            gpu_mib: 1024,
            cpu_mib: 2048,
            uploads: 64,
            tf: None,
            http1: false,
        }
    }
}

#[derive(Clone, Debug, Default)]
pub(crate) struct Stop {
    pub(crate) first_frame_seconds: f64,
    pub(crate) converge_seconds: Option<f64>,
    bytes: u64,
    in_flight_mean: f64,
    in_flight_max: usize,
    waited_frames: usize,
    frames: usize,
    max_loader_seconds: f64,
}

pub(crate) struct Run {
    label: String,
    pub(crate) open_seconds: f64,
    pub(crate) stops: Vec<Stop>,
    /// Bricks the loader read from the source over the whole run.
    pub(crate) bricks_read: u64,
    cancelled: u64,
    retried: u64,
    max_in_flight: u64,
}

pub(crate) fn fly(
    ctx: &GpuContext,
    label: String,
    open: &dyn Fn() -> Result<Arc<dyn VolumeSource>>,
    options: &Options,
    settings: &RenderSettings,
    wait_threshold: Option<Duration>,
) -> Result<Run> {
    let config = StreamingConfig {
        gpu_budget_bytes: options.gpu_mib << 20,
        cpu_budget_bytes: options.cpu_mib << 20,
        uploads_per_frame: options.uploads,
        bricks_in_transit: 256,
        max_queued_requests: 512,
        ..StreamingConfig::default()
    };
    let opening = Instant::now();
    let source = open()?;
    let tf = choose_transfer_function(options.tf.as_deref(), &source.header().modality)?;
    let mut volume = StreamingVolume::new(ctx, source, &tf, config)?;
    let open_seconds = opening.elapsed().as_secs_f64();
    let geometry = volume.geometry().clone();
    let mut stops = Vec::new();
    let mut last: FrameStats = volume.last_stats().clone();
    let mut bytes_before = 0u64;
    for stop in 0..options.stops.max(1) {
        let glide = if stop == 0 { 0 } else { options.glide_frames };
        let mut s = Stop::default();
        let mut in_flight_sum = 0usize;
        let mut frame = |volume: &mut StreamingVolume,
                         camera: &strata_render::Camera,
                         s: &mut Stop|
         -> Result<FrameStats> {
            let stats = volume.frame(ctx, camera, settings)?;
            volume.wait_for_gpu(ctx)?;
            s.frames += 1;
            in_flight_sum += stats.in_flight;
            s.in_flight_max = s.in_flight_max.max(stats.in_flight);
            s.max_loader_seconds = s.max_loader_seconds.max(stats.loader_seconds);
            if wait_threshold.is_some_and(|t| stats.loader_seconds >= t.as_secs_f64()) {
                s.waited_frames += 1;
            }
            Ok(stats)
        };
        for g in 1..=glide {
            let camera = viewpoint(
                &geometry,
                stop as f64 - 1.0 + g as f64 / glide as f64,
                options.stops,
            );
            last = frame(&mut volume, &camera, &mut s)?;
        }
        let camera = viewpoint(&geometry, stop as f64, options.stops);
        let arrived = Instant::now();
        for held in 0..options.settle_frames.max(1) {
            last = frame(&mut volume, &camera, &mut s)?;
            if held == 0 {
                s.first_frame_seconds = arrived.elapsed().as_secs_f64();
            }
            if last.converged {
                s.converge_seconds = Some(arrived.elapsed().as_secs_f64());
                break;
            }
            if last.in_flight > 0 && last.uploads == 0 && !last.page_table_rewritten {
                // Nothing new on screen: let the requests progress rather than spin.
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        s.in_flight_mean = in_flight_sum as f64 / s.frames.max(1) as f64;
        s.bytes = last.stored_bytes_read_total - bytes_before;
        bytes_before = last.stored_bytes_read_total;
        stops.push(s);
    }
    Ok(Run {
        label,
        open_seconds,
        stops,
        bricks_read: last.bricks_read_total,
        cancelled: last.cancelled_in_flight_total,
        retried: last.retried_total,
        max_in_flight: last.max_in_flight,
    })
}

pub fn run(options: Options) -> Result<()> {
    let (width, height) = parse_size(&options.size)?;
    let settings = RenderSettings {
        width,
        height,
        ..RenderSettings::default()
    };
    let ctx = GpuContext::headless()?;
    eprintln!("GPU: {}", ctx.adapter_name());
    let path = options.store.clone();
    let _warm_up = fly(
        &ctx,
        "warm-up".into(),
        &|| {
            let store = Store::open(&path)
                .with_context(|| format!("cannot open store {}", path.display()))?;
            Ok(Arc::new(store) as Arc<dyn VolumeSource>)
        },
        &options,
        &settings,
        None,
    )?;
    std::thread::sleep(Duration::from_millis(200));
    let local = fly(
        &ctx,
        "local".into(),
        &|| {
            let store = Store::open(&path)
                .with_context(|| format!("cannot open store {}", path.display()))?;
            Ok(Arc::new(store) as Arc<dyn VolumeSource>)
        },
        &options,
        &settings,
        None,
    )?;
    // Let sled and the lock go before the server opens the same store.
    std::thread::sleep(Duration::from_millis(200));
    let mut runs = Vec::new();
    for &rtt in &options.rtt_ms {
        let server = start(
            find_stores(std::slice::from_ref(&options.store))?,
            ServeOptions {
                added_delay: Duration::from_millis(rtt),
                ..ServeOptions::default()
            },
        )?;
        let (name, _, _) = server.stores()[0].clone();
        let url = server.store_url(&name);
        let remote_options = RemoteOptions {
            http1: options.http1,
            ..RemoteOptions::default()
        };
        let run = fly(
            &ctx,
            format!("remote, RTT {rtt} ms"),
            &|| {
                Ok(Arc::new(RemoteSource::open(&url, remote_options.clone())?)
                    as Arc<dyn VolumeSource>)
            },
            &options,
            &settings,
            (rtt > 0).then(|| Duration::from_millis(rtt)),
        )?;
        server.stop();
        runs.push(run);
    }
    print_report(&options, &local, &runs);
    Ok(())
}

fn print_report(options: &Options, local: &Run, runs: &[Run]) {
    println!(
        "bench remote: {} at {}, {} viewpoints (flythrough path), RTT injected in the test server ({}), lavapipe timings",
        options.store.display(),
        options.size,
        options.stops,
        if options.http1 { "HTTP/1.1 pool" } else { "one HTTP/2 connection" }
    );
    println!(
        "local: open {:.3} s; largest loader time of a frame {:.1} ms (the same CPU noise the remote runs see); per viewpoint first frame / converge: {}",
        local.open_seconds,
        local
            .stops
            .iter()
            .map(|s| s.max_loader_seconds)
            .fold(0.0, f64::max)
            * 1e3,
        local
            .stops
            .iter()
            .map(|s| format!(
                "{:.3}/{}",
                s.first_frame_seconds,
                s.converge_seconds
                    .map_or("not converged".into(), |c| format!("{c:.3} s"))
            ))
            .collect::<Vec<_>>()
            .join(", ")
    );
    println!();
    println!("| run | stop | first frame s | converge s | remote/local converge | bytes remote/local | in flight mean | in flight max | frames waited on network (max loader ms) |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for run in runs {
        for (i, (s, l)) in run.stops.iter().zip(&local.stops).enumerate() {
            let ratio = match (s.converge_seconds, l.converge_seconds) {
                (Some(r), Some(l)) if l > 0.0 => format!("{:.2}", r / l),
                _ => "n/a".into(),
            };
            let bytes = if l.bytes > 0 {
                format!("{:.3}", s.bytes as f64 / l.bytes as f64)
            } else {
                format!("{} / 0", s.bytes)
            };
            println!(
                "| {} | {i} | {:.3} | {} | {ratio} | {bytes} | {:.1} | {} | {} of {} ({:.1}) |",
                run.label,
                s.first_frame_seconds,
                s.converge_seconds
                    .map_or("not converged".into(), |c| format!("{c:.3}")),
                s.in_flight_mean,
                s.in_flight_max,
                s.waited_frames,
                s.frames,
                s.max_loader_seconds * 1e3
            );
        }
        let total = |r: &Run| {
            r.stops
                .iter()
                .filter_map(|s| s.converge_seconds)
                .sum::<f64>()
        };
        let bytes = |r: &Run| r.stops.iter().map(|s| s.bytes).sum::<u64>();
        println!(
            "| {} | all | open {:.3} | {:.3} | {:.2} | {:.3} | | max {} | cancelled in flight {}, retried {} |",
            run.label,
            run.open_seconds,
            total(run),
            total(run) / total(local).max(1e-9),
            bytes(run) as f64 / bytes(local).max(1) as f64,
            run.max_in_flight,
            run.cancelled,
            run.retried
        );
    }
}
