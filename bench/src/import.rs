//! `strata-bench import` and `strata-bench codecs`: import throughput against its physical limit
//! on this machine, the peak memory of a large import, and the brick codecs side by side.
//!
//! The limit does, in one timed run, the work no import can avoid: read every source byte (page
//! cache), compress as many bytes as the store will hold (bricks with their aprons, all levels:
//! about 1.6× the source) with the store's codec on all cores, and write the compressed bytes
//! sequentially to a file on the same disk, ending with an fsync. An import also cuts bricks,
//! averages levels and keeps a database; the ratio of the two says what that costs.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use rayon::prelude::*;
use strata_storage::brick::{compress_samples, decode_brick, encode_brick, value_range};
use strata_storage::import::{import_source, ImportOptions};
use strata_storage::phantom::Phantom;
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::{BrickCodec, Store};
use strata_types::{BrickId, BRICK_PAYLOAD_VOXELS};

pub(crate) struct Options {
    pub(crate) size: u64,
    pub(crate) rss_size: Option<u64>,
    pub(crate) memory_mib: u64,
    pub(crate) dir: PathBuf,
    pub(crate) codec: BrickCodec,
    pub(crate) runs: usize,
}

fn ensure_phantom_nrrd(dir: &Path, size: u64) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let path = dir.join(format!("phantom-{size}.nrrd"));
    let expected = size * size * size * 2;
    if std::fs::metadata(&path)
        .map(|m| m.len() > expected)
        .unwrap_or(false)
    {
        return Ok(path);
    }
    eprintln!("generating {}", path.display());
    Phantom::cube(size).write_nrrd(&path, None)?;
    Ok(path)
}

/// Brick-sized chunks per parallel step of the limit: as many bricks as the import compresses
/// at once, so both hand the writer work in the same grain.
const LIMIT_CHUNKS_PER_STEP: usize = 256;

/// Seconds the physical limit takes for a source of `source` bytes whose store holds
/// `store_bytes` uncompressed: read + compress `store_bytes` (cycling over the source in
/// brick-sized chunks) on all cores, written sequentially by one thread to `scratch`, fsynced.
/// Returns the seconds and the bytes written.
fn physical_limit(
    source: &[u8],
    store_bytes: u64,
    codec: BrickCodec,
    scratch: &Path,
) -> Result<(f64, u64)> {
    let chunk = BRICK_PAYLOAD_VOXELS * 2;
    let source_chunks = (source.len() / chunk).max(1);
    let chunk_at = |i: usize| {
        let start = (i % source_chunks) * chunk;
        &source[start..(start + chunk).min(source.len())]
    };
    let total_chunks = (store_bytes as usize).div_ceil(chunk);
    let out_path = scratch.join("limit-output.bin");
    let file = std::fs::File::create(&out_path)
        .with_context(|| format!("creating {}", out_path.display()))?;
    let (steps, steps_in) = crossbeam_channel::bounded::<Vec<Vec<u8>>>(2);
    let started = Instant::now();
    let written = std::thread::scope(|scope| -> Result<u64> {
        let writer = std::thread::Builder::new()
            .name("strata-bench-limit-writer".into())
            .spawn_scoped(scope, move || -> std::io::Result<u64> {
                let mut out = std::io::BufWriter::with_capacity(8 << 20, file);
                let mut bytes = 0u64;
                for step in steps_in {
                    for c in step {
                        out.write_all(&c)?;
                        bytes += c.len() as u64;
                    }
                }
                let file = out.into_inner().map_err(|e| e.into_error())?;
                file.sync_all()?;
                Ok(bytes)
            })?;
        for first in (0..total_chunks).step_by(LIMIT_CHUNKS_PER_STEP) {
            let last = (first + LIMIT_CHUNKS_PER_STEP).min(total_chunks);
            let step: Vec<Vec<u8>> = (first..last)
                .into_par_iter()
                .map(|i| compress_samples(chunk_at(i), false, codec))
                .collect();
            if steps.send(step).is_err() {
                break;
            }
        }
        drop(steps);
        writer
            .join()
            .map_err(|_| anyhow::anyhow!("the limit's writer thread panicked"))?
            .context("writing the limit's output")
    })?;
    let seconds = started.elapsed().as_secs_f64();
    let _ = std::fs::remove_file(&out_path);
    Ok((seconds, written))
}

/// Bytes this process has passed to write(2) and its kin so far (Linux `/proc/self/io`
/// `wchar`): what sled's log, node rewrites and blob files cost against the records' bytes.
/// None where the platform has no such count.
fn bytes_written_by_this_process() -> Option<u64> {
    let io = std::fs::read_to_string("/proc/self/io").ok()?;
    io.lines()
        .find_map(|line| line.strip_prefix("wchar:"))
        .and_then(|v| v.trim().parse().ok())
}

fn secs(d: Duration) -> String {
    format!("{:.2} s", d.as_secs_f64())
}

/// The median of `values` (the mean of the middle two for an even count); 0 when empty.
fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => 0.0,
        n if n % 2 == 1 => v[n / 2],
        n => (v[n / 2 - 1] + v[n / 2]) / 2.0,
    }
}

/// `cpu` as seconds and as a share of `wall` ("n/a" where the platform has no such clock).
fn cpu_share(cpu: Option<Duration>, wall: Duration) -> String {
    match cpu {
        Some(c) => format!(
            "{:.2} s ({:.0} %)",
            c.as_secs_f64(),
            100.0 * c.as_secs_f64() / wall.as_secs_f64().max(1e-9)
        ),
        None => "n/a".into(),
    }
}

pub(crate) fn run(o: Options) -> Result<()> {
    let Options {
        size,
        rss_size,
        memory_mib,
        dir,
        codec,
        runs,
    } = o;
    anyhow::ensure!(runs >= 1, "--runs must be at least 1");
    let nrrd = ensure_phantom_nrrd(&dir, size)?;
    let data_bytes = size * size * size * 2;
    // Warm the page cache so both sides read from memory.
    std::hint::black_box(std::fs::read(&nrrd)?.len());
    let store = dir.join(format!("phantom-{size}.strata"));
    let file = std::fs::File::open(&nrrd)?;
    // SAFETY: read-only map of a file this benchmark wrote and does not modify.
    let map = unsafe { memmap2::Mmap::map(&file)? };
    let source = &map[map.len() - data_bytes as usize..];
    let options = ImportOptions {
        codec,
        ..Default::default()
    };
    // Interleave import and limit, `runs` pairs: each import is compared with the limit measured
    // right after it, so a burst of load from other processes hits one pair, and the median of
    // the pairs' ratios ignores it.
    let mb = data_bytes as f64 / 1e6;
    let (mut limit_rates, mut import_rates, mut ratios) = (vec![], vec![], vec![]);
    let mut reports = Vec::new();
    let mut written = 0;
    let mut import_writes = Vec::new();
    for _ in 0..runs {
        // Both sides start from nothing: the limit writes a new file, so the import writes a new
        // store (deleting the previous run's 100 MB is no part of an import).
        if store.exists() {
            std::fs::remove_dir_all(&store)
                .with_context(|| format!("removing {}", store.display()))?;
        }
        let opened = open_source(&nrrd, &ReadOptions::default())?;
        let written_before = bytes_written_by_this_process();
        let t = Instant::now();
        let report = import_source(opened, &store, &options)?;
        let import_rate = mb / t.elapsed().as_secs_f64();
        if let (Some(a), Some(b)) = (written_before, bytes_written_by_this_process()) {
            import_writes.push(b.saturating_sub(a) as f64);
        }
        let (limit_seconds, bytes) =
            physical_limit(source, report.stats.uncompressed_bytes, codec, &dir)?;
        let limit_rate = mb / limit_seconds;
        written = bytes;
        limit_rates.push(limit_rate);
        import_rates.push(import_rate);
        ratios.push(import_rate / limit_rate);
        reports.push((import_rate / limit_rate, report));
    }
    let ratio = median(&ratios);
    // The run whose ratio is nearest the median: its profile is the one printed.
    let Some((_, report)) = reports
        .into_iter()
        .min_by(|a, b| (a.0 - ratio).abs().total_cmp(&(b.0 - ratio).abs()))
    else {
        anyhow::bail!("no import ran");
    };
    let s = &report.stats;
    println!(
        "import throughput, {size}^3 int16 phantom NRRD ({mb:.0} MB), {} codec, {} threads, {runs} interleaved runs of import and limit (medians)",
        codec.name(),
        rayon::current_num_threads()
    );
    println!(
        "  limit: read the source + {} codec on {:.0} MB (the store's bricks, {:.2}x the source) on all cores + sequential write of {:.0} MB + fsync: {:8.0} MB/s",
        codec.name(),
        s.uncompressed_bytes as f64 / 1e6,
        s.uncompressed_bytes as f64 / data_bytes as f64,
        written as f64 / 1e6,
        median(&limit_rates)
    );
    let list = |v: &[f64], scale: f64| {
        v.iter()
            .map(|x| format!("{:.0}", x * scale))
            .collect::<Vec<_>>()
            .join(" ")
    };
    println!(
        "  runs: limit MB/s [{}], import MB/s [{}], import/limit % [{}]",
        list(&limit_rates, 1.0),
        list(&import_rates, 1.0),
        list(&ratios, 100.0)
    );
    println!(
        "  strata import:                             {:8.0} MB/s  = {:.0} % of the limit",
        median(&import_rates),
        100.0 * ratio
    );
    let p = &report.profile;
    println!(
        "  median run's phases: convert {}, histogram {}, bricks (cut + range + compress + hand-off) {}, sled writes on their own thread {}, finish (metadata + flush) {}",
        secs(p.convert),
        secs(p.histogram),
        secs(p.bricks),
        secs(p.sled_writes),
        secs(p.finish)
    );
    let c = &p.cpu;
    println!(
        "  median run's CPU time against its {} wall: all threads {}, conversion thread {}, builder thread {}, sled writer thread {}",
        secs(c.wall),
        cpu_share(c.process, c.wall),
        cpu_share(c.convert_thread, c.wall),
        cpu_share(c.builder_thread, c.wall),
        cpu_share(c.writer_thread, c.wall)
    );
    println!(
        "  stored {:.1} MB (compression ratio {:.2} over bricks with aprons)",
        s.compressed_bytes as f64 / 1e6,
        s.uncompressed_bytes as f64 / s.compressed_bytes.max(1) as f64
    );
    if !import_writes.is_empty() {
        let wrote = median(&import_writes);
        println!(
            "  the import wrote {:.0} MB (write(2) bytes, median run) for {:.0} MB of records: {:.2}x the limit's sequential write",
            wrote / 1e6,
            s.compressed_bytes as f64 / 1e6,
            wrote / written.max(1) as f64
        );
    }
    if let Some(rss_size) = rss_size {
        rss_row(&dir, rss_size, memory_mib, codec)?;
    }
    Ok(())
}

/// Imports a `rss_size`³ phantom in a child process and reports its peak resident memory.
fn rss_row(dir: &Path, rss_size: u64, memory_mib: u64, codec: BrickCodec) -> Result<()> {
    let big = ensure_phantom_nrrd(dir, rss_size)?;
    let big_store = dir.join(format!("phantom-{rss_size}.strata"));
    let exe = crate::strata_exe()?;
    let t = Instant::now();
    let status = std::process::Command::new(exe)
        .arg("import")
        .arg(&big)
        .arg(&big_store)
        .arg("--memory-mib")
        .arg(memory_mib.to_string())
        .arg("--codec")
        .arg(codec.name())
        .stderr(std::process::Stdio::null())
        .status()?;
    anyhow::ensure!(status.success(), "child import failed");
    let seconds = t.elapsed().as_secs_f64();
    let gb = (rss_size * rss_size * rss_size * 2) as f64 / 1e9;
    let peak = match super::peak_child_rss_bytes() {
        Some(peak) => format!(
            "{:.0} MiB ({})",
            peak as f64 / (1 << 20) as f64,
            if peak <= memory_mib << 20 {
                "within budget"
            } else {
                "OVER BUDGET"
            }
        ),
        None => "unavailable (no getrusage on this platform, or it failed)".into(),
    };
    println!(
        "peak RSS importing {rss_size}^3 u16 ({gb:.2} GB) with a {memory_mib} MiB budget: {peak}, {seconds:.1} s, {:.0} MB/s",
        gb * 1e3 / seconds
    );
    let _ = std::fs::remove_dir_all(&big_store);
    Ok(())
}

pub(crate) struct CodecOptions {
    pub(crate) phantom_size: u64,
    pub(crate) scans: PathBuf,
    pub(crate) inputs: Vec<PathBuf>,
}

/// The scans of `SOURCES.md` the codec table reads when present: MR (u8 and u16) and CT.
const DEFAULT_SCANS: [&str; 3] = [
    "niivue/chris_t1.nii.gz",
    "niivue/FLAIR.nrrd",
    "niivue/dicom-mr-3slices",
];

/// Per input: each codec's stored size (a whole import) against lz4's, and its compress and
/// decompress speed on one core over the input's non-constant bricks.
pub(crate) fn codecs(o: CodecOptions) -> Result<()> {
    let scratch = tempfile::tempdir().context("creating a scratch folder")?;
    let mut inputs: Vec<(String, Option<PathBuf>)> =
        vec![(format!("phantom {}^3 (CT, u16)", o.phantom_size), None)];
    if o.inputs.is_empty() {
        for scan in DEFAULT_SCANS {
            let path = o.scans.join(scan);
            if path.exists() {
                inputs.push((scan.to_string(), Some(path)));
            } else {
                println!(
                    "skipped {}: absent (see {}/SOURCES.md)",
                    path.display(),
                    o.scans.display()
                );
            }
        }
    } else {
        inputs.extend(
            o.inputs
                .iter()
                .map(|p| (p.display().to_string(), Some(p.clone()))),
        );
    }
    println!("codec table: stored size over bricks with aprons, all levels; speeds per core (thread CPU time) over the non-constant bricks, MB/s of uncompressed samples, checksum included");
    println!(
        "{:<34} {:>6} {:>10} {:>8} {:>10} {:>14} {:>16}",
        "input", "codec", "stored MB", "ratio", "vs lz4", "compress MB/s", "decompress MB/s"
    );
    for (name, path) in inputs {
        let mut lz4_bytes = None;
        for codec in BrickCodec::ALL {
            let store_path = scratch.path().join(format!("{}.strata", codec.name()));
            let options = ImportOptions {
                codec,
                ..Default::default()
            };
            let report = match &path {
                None => Phantom::cube(o.phantom_size).write_store(&store_path, &options)?,
                Some(p) => {
                    let opened = open_source(p, &ReadOptions::default())
                        .with_context(|| format!("cannot read {}", p.display()))?;
                    import_source(opened, &store_path, &options)?
                }
            };
            let s = &report.stats;
            let lz4 = *lz4_bytes.get_or_insert(s.compressed_bytes);
            let store = Store::open(&store_path)?;
            let (compress, decompress) = codec_speeds(&store, codec)?;
            println!(
                "{:<34} {:>6} {:>10.2} {:>8.2} {:>9.3}x {:>14.0} {:>16.0}",
                name,
                codec.name(),
                s.compressed_bytes as f64 / 1e6,
                s.uncompressed_bytes as f64 / s.compressed_bytes.max(1) as f64,
                s.compressed_bytes as f64 / lz4.max(1) as f64,
                compress,
                decompress
            );
            store.close()?;
        }
    }
    Ok(())
}

/// CPU seconds the calling thread has run, where the platform says (Linux, the BSDs, macOS).
fn thread_cpu_seconds() -> Option<f64> {
    #[cfg(unix)]
    {
        let mut t = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: clock_gettime only writes the timespec we pass, which outlives the call.
        if unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) } == 0 {
            return Some(t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9);
        }
        None
    }
    #[cfg(not(unix))]
    {
        None
    }
}

/// Single-core compress and decompress MB/s of `codec` over the store's non-constant bricks
/// (at most 400 of them, the whole pass repeated until it has run for half a second).
fn codec_speeds(store: &Store, codec: BrickCodec) -> Result<(f64, f64)> {
    let layout = store.layout().clone();
    let narrow = store.header().stored == strata_storage::StoredScalar::U8;
    let mut bricks: Vec<(BrickId, Vec<u16>)> = Vec::new();
    'levels: for level in 0..layout.level_count() {
        let n = layout.bricks_in_level(level);
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let id = BrickId::new(level as u8, [x, y, z]);
                    if store.node(id).is_some_and(|node| !node.is_constant()) {
                        bricks.push((id, store.read_brick(id)?));
                        if bricks.len() >= 400 {
                            break 'levels;
                        }
                    }
                }
            }
        }
    }
    anyhow::ensure!(!bricks.is_empty(), "the store has only constant bricks");
    let sample_bytes = (BRICK_PAYLOAD_VOXELS * if narrow { 1 } else { 2 }) as f64;
    // Per core: the measuring thread's own CPU time where the platform has it (these machines
    // are shared, and wall time would count the time other processes held the core).
    let timed = |mut pass: Box<dyn FnMut() + '_>| {
        let (t, cpu, mut passes) = (Instant::now(), thread_cpu_seconds(), 0u32);
        while passes == 0 || t.elapsed() < Duration::from_millis(500) {
            pass();
            passes += 1;
        }
        let seconds = match (cpu, thread_cpu_seconds()) {
            (Some(a), Some(b)) if b > a => b - a,
            _ => t.elapsed().as_secs_f64(),
        };
        bricks.len() as f64 * f64::from(passes) * sample_bytes / 1e6 / seconds
    };
    let records: Vec<(BrickId, Vec<u8>)> = bricks
        .iter()
        .map(|(id, v)| (*id, encode_brick(*id, v, value_range(v), narrow, codec)))
        .collect();
    let compress = timed(Box::new(|| {
        for (id, v) in &bricks {
            std::hint::black_box(encode_brick(*id, v, value_range(v), narrow, codec));
        }
    }));
    let mut failures = 0usize;
    let decompress = timed(Box::new(|| {
        for (id, r) in &records {
            match decode_brick(*id, r) {
                Ok(v) => {
                    std::hint::black_box(v);
                }
                Err(_) => failures += 1,
            }
        }
    }));
    anyhow::ensure!(failures == 0, "{failures} bricks did not decode");
    Ok((compress, decompress))
}
