//! `strata-bench`: the measurements behind the issue notes, a binary of its own so that none of
//! it (nor `plotters`) is compiled into the shipping `strata` (issue 47):
//! `cargo run --release -p strata-bench -- <bench> ...`. Every figure is reported next to a
//! baseline measured in the same run, because these machines are shared and noisy. The benches
//! that drive the viewer or an import in a child process (`idle`, `import --rss-size`) run the
//! `strata` binary beside this one (`strata_exe`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use strata_storage::{BrickCodec, Store};
use strata_types::{BrickId, BRICK_PAYLOAD_VOXELS};

mod accuracy;
mod adaptive;
mod common;
mod idle;
mod import;
mod omezarr;
mod remote;
mod time_critical;
mod transitions;

#[derive(Parser)]
#[command(
    name = "strata-bench",
    version,
    about = "Strata's benchmarks: the figures behind the issue notes (not for diagnostic use)"
)]
struct Cli {
    #[command(subcommand)]
    command: BenchCommand,
}

fn main() -> std::process::ExitCode {
    // As `strata` does: memory a closed volume gave back stays reusable.
    strata_loader::malloc_arenas::limit_malloc_arenas();
    match run(Cli::parse().command) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", strata_viewer::error_report::describe(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// The `strata` binary that the benches run as a child (`strata view`, `strata import`):
/// `$STRATA_BIN`, else the one beside this binary (cargo builds both into the same folder:
/// `cargo build --release -p strata-app -p strata-bench`).
pub(crate) fn strata_exe() -> Result<PathBuf> {
    if let Some(path) = std::env::var_os("STRATA_BIN") {
        return Ok(PathBuf::from(path));
    }
    let me = std::env::current_exe().context("finding the strata-bench binary")?;
    let exe = me.with_file_name(format!("strata{}", std::env::consts::EXE_SUFFIX));
    anyhow::ensure!(
        exe.is_file(),
        "{} is missing: build it beside strata-bench (`cargo build --release -p strata-app`) \
         or name it in STRATA_BIN",
        exe.display()
    );
    Ok(exe)
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Import throughput of a u16 phantom NRRD against its physical limit (read the source,
    /// compress every byte the store holds with its codec on all cores, write that sequentially
    /// and fsync); optional peak RSS of a large import in a child process.
    Import {
        /// Brick codec of the store (and of the limit): fast or dense.
        #[arg(long, default_value = "fast", value_parser = parse_codec)]
        codec: BrickCodec,
        /// Edge of the phantom for the throughput run.
        #[arg(long, default_value_t = 512)]
        size: u64,
        /// Edge of a second phantom imported in a child process to measure peak RSS (e.g. 1024).
        #[arg(long)]
        rss_size: Option<u64>,
        /// Memory budget for the RSS run, MiB.
        #[arg(long, default_value_t = 1024)]
        memory_mib: u64,
        /// Scratch folder for generated inputs and stores (kept between runs to save time).
        #[arg(long, default_value = "target/bench-data")]
        dir: PathBuf,
        /// Interleaved runs of import and limit; the medians are reported.
        #[arg(long, default_value_t = 5)]
        runs: usize,
    },
    /// The brick codecs side by side: stored size against lz4 (format 1), compress and
    /// decompress MB/s per core, on the phantom and the scans of SOURCES.md that are present.
    Codecs {
        /// Edge of the generated phantom.
        #[arg(long, default_value_t = 256)]
        phantom_size: u64,
        /// Folder of the real scans (see its SOURCES.md).
        #[arg(long, default_value = concat!(env!("CARGO_MANIFEST_DIR"), "/../../shared/data"))]
        scans: PathBuf,
        /// Scans to compare instead of the default ones.
        inputs: Vec<PathBuf>,
    },
    /// Random brick reads from a store: cold (fresh open, files evicted from the page cache; Linux
    /// only, elsewhere the output says so) and warm.
    Bricks {
        store: PathBuf,
        #[arg(long, default_value_t = 2000)]
        count: usize,
    },
    /// What accuracy costs in time: sweeps step, pre-integration, level, jitter and shading on
    /// one view (with --sweep cinematic or all also shadow step, light-cache resolution,
    /// occlusion radius and progressive frames of the key-lit models) and writes error vs the
    /// f64 reference of each setting's model against time (CSV, markdown, PNG plot with a
    /// Pareto front per model).
    Accuracy {
        /// A store, or `phantom` for a generated CT phantom.
        input: String,
        /// Edge of the generated phantom.
        #[arg(long, default_value_t = 192)]
        phantom_size: u64,
        /// Image size WxH (the f64 reference is rendered at the same size).
        #[arg(long, default_value = "256x256")]
        size: String,
        /// Timed frames per setting (median reported).
        #[arg(long, default_value_t = 5)]
        frames: usize,
        /// Transfer function preset or JSON file (default by modality).
        #[arg(long)]
        tf: Option<String>,
        /// Where the CSV, markdown table and plot go.
        #[arg(long, default_value = "target/bench-accuracy")]
        out_dir: PathBuf,
        /// Which settings: `base` (unshaded and headlight-shaded DVR), `cinematic` (the
        /// key-lit models: shadow step, light-cache resolution, occlusion radius, progressive
        /// frames; each against the f64 reference of its own lit model, which costs minutes
        /// of CPU) or `all`.
        #[arg(long, value_enum, default_value_t = accuracy::Sweep::Base)]
        sweep: accuracy::Sweep,
    },
    /// The time-critical paper's Table 2: a 360° orbit at a fixed sampling rate and under the
    /// frame-rate controller; mean fps and σ of the measured GPU frame time for both.
    Timecritical {
        store: PathBuf,
        /// Frame rate the controller holds.
        #[arg(long)]
        target: f64,
        /// Frames per orbit (each run).
        #[arg(long, default_value_t = 360)]
        frames: usize,
        /// Per-frame CSV of both runs.
        #[arg(long)]
        csv: Option<PathBuf>,
        /// Image size WxH.
        #[arg(long, default_value = "512x512")]
        size: String,
        /// Step in finest voxels of the fixed-rate run; also where the controller starts.
        #[arg(long, default_value_t = 0.5)]
        step: f64,
        /// Transfer function preset or JSON file (default by modality).
        #[arg(long)]
        tf: Option<String>,
        /// Finest octree level rendered (0 = full resolution).
        #[arg(long, default_value_t = 0)]
        level: u8,
        #[arg(long, default_value_t = 20.0, allow_hyphen_values = true)]
        elevation: f64,
        /// GPU memory for a level's brick cache, MiB; a level whose bricks do not fit is an
        /// error saying bricks × bytes against it. Not given: each cache holds its whole level.
        #[arg(long)]
        gpu_mib: Option<u64>,
    },
    /// The adaptive-sampling paper's Tables 2 and 3: sampling operations, synthesis
    /// operations and frame time of the raycaster, adaptive sampling with d ≡ 1 and with the
    /// oracle at a sweep of ε, with PSNR against the f64 reference (CSV, markdown, PNG plot).
    Adaptive {
        /// A store, or `phantom` for a generated CT phantom.
        input: String,
        /// Edge of the generated phantom.
        #[arg(long, default_value_t = 192)]
        phantom_size: u64,
        /// Image size WxH (the f64 reference is rendered at the same size).
        #[arg(long, default_value = "512x512")]
        size: String,
        /// Timed frames per setting (median reported).
        #[arg(long, default_value_t = 3)]
        frames: usize,
        /// Transfer function preset or JSON file (default by modality).
        #[arg(long)]
        tf: Option<String>,
        /// Base step (slice spacing) in finest voxels.
        #[arg(long, default_value_t = 0.5)]
        step: f64,
        /// Oracle ε values, comma-separated.
        #[arg(long, default_value = "0.0005,0.001,0.002,0.005,0.01,0.02,0.05")]
        epsilons: String,
        /// Coarsest pyramid level (largest sampling distance 2^l_max slices).
        #[arg(long, default_value_t = 3)]
        l_max: u32,
        /// Screen tile of one workgroup: 8, 16 or 32.
        #[arg(long, default_value_t = 16)]
        tile: u32,
        #[arg(long, default_value = "target/bench-adaptive")]
        out_dir: PathBuf,
        /// Only the lit group: raycaster and adaptive pass lit by the key light with exact
        /// shadows and single scattering (g 0.5), each ε with the opacity and the lit-colour
        /// oracle, against the raycaster at a quarter of the step (same shadow step).
        #[arg(long)]
        shadowed_only: bool,
    },
    /// The mixed-resolution paper's Table 1: a level-0/level-1 cut with about 25 % transition
    /// bricks, frame time with smoothing off/on × unshaded/shaded, and the error of each image
    /// against the f64 reference of the full-resolution cut and of the same cut.
    Transitions(transitions::Options),
    /// The flythrough from a local store and through `strata serve` on loopback with added
    /// round-trip delays: convergence time, bytes and requests in flight, remote vs local.
    Remote(remote::Options),
    /// OME-Zarr: export and import throughput vs raw read + compress, objects and bytes vs the
    /// store, and (--s3) the remote flythrough streamed from SeaweedFS.
    Omezarr(omezarr::Options),
    /// The viewer's CPU at rest: `strata view` settles, then its CPU time, UI passes and volume
    /// frames over a settled interval (needs a display; `xvfb-run -a` where there is none).
    Idle(idle::Options),
}

/// `--codec` of the import benchmark: fast or dense.
fn parse_codec(name: &str) -> Result<BrickCodec> {
    match BrickCodec::parse(name) {
        Some(c @ (BrickCodec::Fast | BrickCodec::Dense)) => Ok(c),
        _ => anyhow::bail!("'{name}' is not a codec: use fast or dense"),
    }
}

fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Remote(options) => remote::run(options),
        BenchCommand::Idle(options) => idle::run(options),
        BenchCommand::Omezarr(options) => omezarr::run(options),
        BenchCommand::Import {
            codec,
            size,
            rss_size,
            memory_mib,
            dir,
            runs,
        } => import::run(import::Options {
            size,
            rss_size,
            memory_mib,
            dir,
            codec,
            runs,
        }),
        BenchCommand::Codecs {
            phantom_size,
            scans,
            inputs,
        } => import::codecs(import::CodecOptions {
            phantom_size,
            scans,
            inputs,
        }),
        BenchCommand::Bricks { store, count } => bench_bricks(&store, count),
        BenchCommand::Accuracy {
            input,
            phantom_size,
            size,
            frames,
            tf,
            out_dir,
            sweep,
        } => accuracy::run(accuracy::Options {
            input,
            phantom_size,
            size,
            frames,
            tf,
            out_dir,
            sweep,
        }),
        BenchCommand::Timecritical {
            store,
            target,
            frames,
            csv,
            size,
            step,
            tf,
            level,
            elevation,
            gpu_mib,
        } => time_critical::run(time_critical::Options {
            store,
            target_fps: target,
            frames,
            csv,
            size,
            step,
            tf,
            level,
            elevation,
            gpu_budget_bytes: gpu_mib.map(|m| m << 20),
        }),
        BenchCommand::Transitions(options) => transitions::run(options),
        BenchCommand::Adaptive {
            input,
            phantom_size,
            size,
            frames,
            tf,
            step,
            epsilons,
            l_max,
            tile,
            out_dir,
            shadowed_only,
        } => adaptive::run(adaptive::Options {
            input,
            phantom_size,
            size,
            frames,
            tf,
            step,
            epsilons: epsilons
                .split(',')
                .filter(|e| !e.trim().is_empty())
                .map(|e| {
                    e.trim()
                        .parse::<f64>()
                        .with_context(|| format!("--epsilons: '{e}' is not a number"))
                })
                .collect::<Result<Vec<_>>>()?,
            l_max,
            tile,
            out_dir,
            shadowed_only,
        }),
    }
}

/// Peak resident set size of the largest waited-for child, in bytes; None where the platform
/// has no `getrusage` (Windows) or the call fails.
pub(crate) fn peak_child_rss_bytes() -> Option<u64> {
    #[cfg(unix)]
    {
        // SAFETY: rusage is a plain C struct of integers, for which all-zero bytes are valid.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        // SAFETY: getrusage only writes into the struct we pass, which outlives the call.
        if unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut usage) } != 0 {
            return None;
        }
        Some(max_rss_bytes(usage.ru_maxrss))
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// `ru_maxrss` in bytes: macOS (and iOS) report bytes, Linux and the other Unixes KiB.
#[cfg(unix)]
fn max_rss_bytes(ru_maxrss: libc::c_long) -> u64 {
    if cfg!(any(target_os = "macos", target_os = "ios")) {
        ru_maxrss as u64
    } else {
        ru_maxrss as u64 * 1024
    }
}

/// Asks the kernel to drop a store's files from the page cache, so the next reads are cold.
/// Returns whether this platform can: only Linux has `posix_fadvise(POSIX_FADV_DONTNEED)`;
/// elsewhere nothing is evicted and reads right after may still come from memory.
fn evict_from_page_cache(dir: &Path) -> bool {
    #[cfg(target_os = "linux")]
    {
        fadvise_dontneed_all(dir);
        true
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = dir;
        false
    }
}

/// `posix_fadvise(DONTNEED)` on every file under `dir`; errors leave that file cached.
#[cfg(target_os = "linux")]
fn fadvise_dontneed_all(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let p = entry.path();
        if p.is_dir() {
            fadvise_dontneed_all(&p);
        } else if let Ok(f) = std::fs::File::open(&p) {
            use std::os::fd::AsRawFd;
            // SAFETY: advisory call on a valid descriptor.
            unsafe { libc::posix_fadvise(f.as_raw_fd(), 0, 0, libc::POSIX_FADV_DONTNEED) };
        }
    }
}

fn bench_bricks(path: &Path, count: usize) -> Result<()> {
    let evicted = evict_from_page_cache(path);
    let store = Store::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let layout = store.layout().clone();
    // Deterministic pseudo-random brick ids over all levels, weighted like the octree itself.
    let total = layout.total_bricks();
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let ids: Vec<BrickId> = (0..count)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let mut n = state % total;
            let mut level = 0;
            while n >= layout.brick_count_in_level(level) {
                n -= layout.brick_count_in_level(level);
                level += 1;
            }
            let b = layout.bricks_in_level(level).map(u64::from);
            BrickId::new(
                level as u8,
                [
                    (n % b[0]) as u32,
                    ((n / b[0]) % b[1]) as u32,
                    (n / (b[0] * b[1])) as u32,
                ],
            )
        })
        .collect();
    let decompressed_mb = (count * BRICK_PAYLOAD_VOXELS * 2) as f64 / 1e6;
    let cold = if evicted {
        "cold"
    } else {
        "cold (page cache not evicted on this platform: may be warm)"
    };
    for label in [cold, "warm"] {
        let t = Instant::now();
        for &id in &ids {
            std::hint::black_box(store.read_brick(id)?);
        }
        let s = t.elapsed().as_secs_f64();
        println!(
            "{label}: {count} random bricks in {s:.3} s = {:.0} bricks/s, {:.0} MB/s decompressed (one thread)",
            count as f64 / s,
            decompressed_mb / s
        );
    }
    Ok(())
}

#[cfg(all(test, unix))]
mod tests {
    #[test]
    fn peak_child_rss_is_in_bytes() {
        let status = std::process::Command::new("true").status().unwrap();
        assert!(status.success());
        let peak = super::peak_child_rss_bytes().expect("getrusage works on Unix");
        // Any process keeps well over 100 KiB resident; a KiB figure taken for bytes would not.
        assert!(peak > 100 << 10, "{peak} bytes");
    }
}
