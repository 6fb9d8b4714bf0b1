//! Streaming import: slices in, brick octree out, in memory bounded by a budget.
//!
//! Slices of level 0 arrive one at a time (converted to stored values in parallel by rows). Each
//! level keeps a window of its own slices: as soon as the slices a z-row of bricks needs (its 32
//! core slices plus 2 apron slices on each side) are there, the row's bricks are cut, ranged and
//! compressed on all cores and written to sled; pairs of slices are averaged into the next level's
//! slice, which feeds that level's window the same way. So coarser levels are built as slabs
//! complete, and peak memory is about 36 slices of level 0 plus a third of that for the coarser
//! levels, whatever the volume's depth.

/// 4-D stores: every frame of a 4-D source (a child module: it builds on this one's pipeline).
mod frames;

use std::collections::VecDeque;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use crate::brick::{encode_brick, extract_brick, value_range, BrickCodec};
use crate::error::{Result, StorageError};
use crate::geometry::VolumeGeometry;
use crate::histogram::{Histogram, StoredValueCounts};
use crate::octree::{
    downsample_slice_pair, BrickId, OctreeLayout, APRON, BRICK_PAYLOAD_VOXELS, CORE, PAYLOAD,
};
use crate::quantize::{Quantizer, StoredScalar};
use crate::source::{OpenedSource, RawVolume, SampleType, WindowPreset};
use crate::store::{
    NodeInfo, Provenance, Skeleton, StoreHeader, StoreStats, StoreWriter, ValueMapping,
    ValueMappingWithUnit, STORE_FORMAT_VERSION,
};

/// Every node of every level, in brick order, while an import fills them in.
type DenseNodes = Vec<Vec<NodeInfo>>;

/// Source of level-0 slices already converted to stored values.
pub trait SliceProducer: Sync {
    fn dims(&self) -> [u64; 3];
    /// Fills `out` (nx·ny values, x fastest) with slice `k`.
    fn stored_slice(&self, k: u64, out: &mut [u16]) -> Result<()>;
    /// Slice `k` will not be asked for again (lets a memory map drop its pages).
    fn release_slice(&self, _k: u64) {}
    /// Bytes of source data per slice, for progress and throughput.
    fn source_bytes_per_slice(&self) -> u64;
}

/// Everything the header needs that is not derived from the voxels.
#[derive(Clone, Debug)]
pub struct VolumeMeta {
    pub geometry: VolumeGeometry,
    pub stored: StoredScalar,
    pub value_mapping: ValueMappingWithUnit,
    pub source_sample_type: SampleType,
    pub quantization_error: f64,
    pub non_finite_samples: u64,
    pub modality: String,
    pub windows: Vec<WindowPreset>,
    pub description: String,
    pub inputs: Vec<String>,
    pub source_format: String,
    /// A label map's labels (DICOM SEG segments), written to the header; empty otherwise.
    pub labels: Vec<crate::source::LabelInfo>,
}

/// The header of a single-volume store written from `meta` (imports and the sparse
/// generator): provenance stamped now with this build's version, a new generation.
pub(crate) fn store_header(
    meta: VolumeMeta,
    format_version: u32,
    layout: &OctreeLayout,
    stored_range: [u16; 2],
    codec: BrickCodec,
    required_features: Vec<String>,
) -> StoreHeader {
    StoreHeader {
        format_version,
        geometry: meta.geometry,
        stored: meta.stored,
        value_mapping: meta.value_mapping,
        source_sample_type: meta.source_sample_type,
        quantization_error: meta.quantization_error,
        non_finite_samples: meta.non_finite_samples,
        modality: meta.modality,
        windows: meta.windows,
        description: meta.description,
        provenance: Provenance {
            inputs: meta.inputs,
            source_format: meta.source_format,
            imported_at_unix_seconds: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs()),
            tool_version: env!("CARGO_PKG_VERSION").to_string(),
        },
        layout: layout.clone(),
        brick_core: CORE,
        brick_apron: APRON,
        stored_range,
        generation: crate::store::new_generation_id(),
        codec,
        required_features,
        labels: meta.labels,
        frames: 1,
    }
}

#[derive(Clone, Copy, Debug, Default)]
pub struct ImportProgress {
    pub source_bytes_done: u64,
    pub source_bytes_total: u64,
}

pub struct ImportOptions<'a> {
    /// Upper bound for the import's own buffers plus sled's cache.
    pub memory_budget_bytes: u64,
    pub cancel: Option<&'a AtomicBool>,
    pub progress: Option<&'a (dyn Fn(ImportProgress) + Sync)>,
    /// The brick codec. [`BrickCodec::Lz4`] writes a format-1 store, exactly as builds before
    /// format 2 did (for tests of old stores and the codec benchmark).
    pub codec: BrickCodec,
}

impl Default for ImportOptions<'_> {
    fn default() -> Self {
        ImportOptions {
            memory_budget_bytes: 1 << 30,
            cancel: None,
            progress: None,
            codec: BrickCodec::default(),
        }
    }
}

#[derive(Clone, Debug)]
pub struct ImportReport {
    pub stats: StoreStats,
    pub header: StoreHeader,
    pub profile: ImportProfile,
}

/// Where an import's time went (what `strata-bench import` prints). The first three are spent
/// on the importing thread one after the other; the sled writes run on their own thread,
/// overlapping them; `finish` is the final metadata write and flush.
#[derive(Clone, Copy, Debug, Default)]
pub struct ImportProfile {
    pub convert: std::time::Duration,
    pub histogram: std::time::Duration,
    pub bricks: std::time::Duration,
    pub sled_writes: std::time::Duration,
    pub finish: std::time::Duration,
    /// CPU time of each thread against the import's wall time: a thread whose CPU time is far
    /// below the wall time waits (on a channel, the disk or the pool), one near it is the limit.
    pub cpu: ImportCpu,
}

/// CPU seconds per import thread (None where the platform has no per-thread clock).
#[derive(Clone, Copy, Debug, Default)]
pub struct ImportCpu {
    pub wall: std::time::Duration,
    /// The whole process over the import (every thread, the compression pool's included).
    pub process: Option<std::time::Duration>,
    pub convert_thread: Option<std::time::Duration>,
    pub builder_thread: Option<std::time::Duration>,
    pub writer_thread: Option<std::time::Duration>,
}

/// CPU time the calling thread has run (Linux, the BSDs, macOS).
pub fn thread_cpu_time() -> Option<std::time::Duration> {
    cpu_clock(CpuClock::Thread)
}

/// CPU time every thread of this process has run together.
pub fn process_cpu_time() -> Option<std::time::Duration> {
    cpu_clock(CpuClock::Process)
}

enum CpuClock {
    Thread,
    Process,
}

fn cpu_clock(clock: CpuClock) -> Option<std::time::Duration> {
    #[cfg(unix)]
    {
        let id = match clock {
            CpuClock::Thread => libc::CLOCK_THREAD_CPUTIME_ID,
            CpuClock::Process => libc::CLOCK_PROCESS_CPUTIME_ID,
        };
        let mut t = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: clock_gettime only writes the timespec we pass, which outlives the call.
        if unsafe { libc::clock_gettime(id, &mut t) } == 0 {
            return Some(std::time::Duration::new(
                u64::try_from(t.tv_sec).ok()?,
                u32::try_from(t.tv_nsec).ok()?,
            ));
        }
        None
    }
    #[cfg(not(unix))]
    {
        let _ = clock;
        None
    }
}

/// CPU time spent since `start` on the clock `now` reads (None when either is unknown).
fn cpu_since(
    start: Option<std::time::Duration>,
    now: Option<std::time::Duration>,
) -> Option<std::time::Duration> {
    Some(now?.saturating_sub(start?))
}

/// Adapts a reader's mapped raw data: converts slices with the quantiser, drops mapped pages
/// once a slice is consumed so resident memory stays bounded on huge inputs.
pub struct QuantizedSource {
    pub data: RawVolume,
    pub quantizer: Quantizer,
}

impl SliceProducer for QuantizedSource {
    fn dims(&self) -> [u64; 3] {
        self.data.dims
    }
    fn stored_slice(&self, k: u64, out: &mut [u16]) -> Result<()> {
        self.quantizer.convert_slice(&self.data, k, out);
        Ok(())
    }
    fn release_slice(&self, k: u64) {
        self.data.release_slice(k);
    }
    fn source_bytes_per_slice(&self) -> u64 {
        self.data.slice_bytes_len() as u64
    }
}

/// Imports what a reader opened into a new store at `store_path`.
pub fn import_source(
    opened: OpenedSource,
    store_path: &Path,
    options: &ImportOptions,
) -> Result<ImportReport> {
    if opened.info.frames > 1 {
        return frames::import_frames(opened, store_path, options, None);
    }
    let info = opened.info;
    let quantizer = Quantizer::plan(&opened.data, info.slope);
    let meta = source_meta(&info, &quantizer);
    let producer = QuantizedSource {
        data: opened.data,
        quantizer,
    };
    import_slices(&producer, meta, store_path, options)
}

/// [`import_source`] writing store format `format` (2: the sled store of earlier builds, for
/// tests and benchmarks of old stores and for `strata store upgrade`'s checks), 4-D sources
/// included.
#[doc(hidden)]
pub fn import_source_as_format(
    opened: OpenedSource,
    store_path: &Path,
    options: &ImportOptions,
    format: u32,
) -> Result<ImportReport> {
    if opened.info.frames > 1 {
        return frames::import_frames(opened, store_path, options, Some(format));
    }
    let info = opened.info;
    let quantizer = Quantizer::plan(&opened.data, info.slope);
    let meta = source_meta(&info, &quantizer);
    let producer = QuantizedSource {
        data: opened.data,
        quantizer,
    };
    import_slices_as(&producer, meta, store_path, options, Some(format))
}

/// The header facts of a reader's source stored through `quantizer`.
pub(crate) fn source_meta(info: &crate::source::SourceInfo, quantizer: &Quantizer) -> VolumeMeta {
    let (slope, intercept) = quantizer.physical_mapping(info.slope, info.intercept);
    VolumeMeta {
        geometry: info.geometry.clone(),
        stored: quantizer.stored,
        value_mapping: ValueMappingWithUnit {
            mapping: ValueMapping { slope, intercept },
            unit: if info.modality.eq_ignore_ascii_case("CT") {
                "HU".into()
            } else {
                String::new()
            },
        },
        source_sample_type: info.sample_type,
        quantization_error: quantizer.max_error_physical,
        non_finite_samples: quantizer.non_finite_samples,
        modality: info.modality.clone(),
        windows: info.windows.clone(),
        description: info.description.clone(),
        inputs: info
            .inputs
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        source_format: info.format.clone(),
        labels: info.labels.clone(),
    }
}

/// Bytes the importer's slice windows need for a volume of `dims` (all levels).
pub fn window_bytes(dims: [u32; 3]) -> u64 {
    let layout = OctreeLayout::new(dims);
    // Per level: the row window (2 apron + 32 core + 2 apron) plus one slice awaiting its pair.
    let per_level_slices = PAYLOAD + 1;
    layout
        .level_dims
        .iter()
        .map(|d| u64::from(d[0]) * u64::from(d[1]) * 2 * per_level_slices)
        .sum()
}

pub fn import_slices(
    producer: &dyn SliceProducer,
    meta: VolumeMeta,
    store_path: &Path,
    options: &ImportOptions,
) -> Result<ImportReport> {
    import_slices_as(producer, meta, store_path, options, None)
}

/// [`import_slices`] writing format `format` (`None`: the current one, or 1 for lz4).
pub(crate) fn import_slices_as(
    producer: &dyn SliceProducer,
    meta: VolumeMeta,
    store_path: &Path,
    options: &ImportOptions,
    format: Option<u32>,
) -> Result<ImportReport> {
    let started = Instant::now();
    let dims = producer.dims();
    crate::geometry::validate(&meta.geometry, store_path)?;
    // The header is JSON, which has no infinities: a mapping that overflowed would be written
    // as null and the store would never open again. Refuse it before writing anything.
    let mapping = meta.value_mapping.mapping;
    if !(mapping.slope.is_finite()
        && mapping.slope != 0.0
        && mapping.intercept.is_finite()
        && meta.quantization_error.is_finite())
    {
        return Err(StorageError::invalid(
            store_path,
            format!(
                "the source's values cannot be mapped to stored integers with a finite scale (slope {}, intercept {}): its scaling or value range is not finite",
                mapping.slope, mapping.intercept
            ),
        ));
    }
    if meta.geometry.dims_u64() != dims {
        return Err(StorageError::invalid(
            store_path,
            format!(
                "header dims {:?} differ from data dims {dims:?}",
                meta.geometry.dims
            ),
        ));
    }
    // Validated above, and equal to the data's extents.
    let layout = OctreeLayout::new(meta.geometry.dims);
    // Budget: slice windows, per-core brick buffers, sled's cache (at least 16 MiB, at most 1/4).
    let per_core_buffers = rayon::current_num_threads() as u64 * (BRICK_PAYLOAD_VOXELS as u64 * 8);
    let converted_ahead = (SLICES_CONVERTED_AHEAD + 1) * dims[0] * dims[1] * 2;
    let fixed = window_bytes(meta.geometry.dims) + per_core_buffers + converted_ahead;
    let sled_cache =
        (options.memory_budget_bytes.saturating_sub(fixed) / 4).clamp(16 << 20, 256 << 20);
    if fixed + sled_cache > options.memory_budget_bytes {
        return Err(StorageError::invalid(
            store_path,
            format!(
                "memory budget of {} MiB is too small for slices of {}×{}: the import needs about {} MiB",
                options.memory_budget_bytes >> 20,
                dims[0],
                dims[1],
                (fixed + sled_cache).div_ceil(1 << 20)
            ),
        ));
    }
    let format_version = if options.codec == BrickCodec::Lz4 {
        1
    } else {
        format.unwrap_or(STORE_FORMAT_VERSION)
    };
    let writer = StoreWriter::create_with_format(store_path, sled_cache, format_version)?;
    let narrow = meta.stored == StoredScalar::U8;
    let mut levels: Vec<LevelBuilder> = (0..layout.level_count())
        .map(|l| LevelBuilder::new(l, layout.level_dims[l].map(u64::from), &layout))
        .collect();
    // Every node while the import runs (O(volume / 32³), small beside the slices it holds);
    // collapsed into the sparse skeleton at the end.
    let mut skeleton: DenseNodes = (0..layout.level_count())
        .map(|l| vec![NodeInfo::default(); layout.brick_count_in_level(l) as usize])
        .collect();
    let mut counts = StoredValueCounts::default();
    let total_source = producer.source_bytes_per_slice() * dims[2];
    // sled writes run on their own thread, overlapping the compression of the next batch; the
    // channel holds two batches at most, so memory stays bounded when the disk is slow.
    let (batches, batches_in) = crossbeam_channel::bounded::<Vec<(BrickId, Vec<u8>)>>(2);
    let process_cpu_start = process_cpu_time();
    let (built, written) = std::thread::scope(|scope| {
        let writer = &writer;
        let writer_thread = std::thread::Builder::new()
            .name("strata-import-writer".into())
            .spawn_scoped(scope, move || -> Result<_> {
                let mut busy = std::time::Duration::ZERO;
                for batch in batches_in {
                    let t = Instant::now();
                    writer.put_bricks(batch)?;
                    busy += t.elapsed();
                }
                Ok((busy, thread_cpu_time()))
            })
            .map_err(|e| StorageError::io(store_path, e));
        let built = match &writer_thread {
            Ok(_) => {
                let sink = BrickSink {
                    store_path,
                    direct: writer.writes_in_parallel().then_some(writer),
                    batches,
                    narrow,
                    codec: options.codec,
                    compressed_bytes: AtomicU64::new(0),
                };
                let builder_cpu_start = thread_cpu_time();
                build_levels(
                    producer,
                    &mut levels,
                    &sink,
                    &mut skeleton,
                    &mut counts,
                    options,
                    store_path,
                )
                .map(|(phases, convert_cpu)| {
                    (
                        phases,
                        convert_cpu,
                        cpu_since(builder_cpu_start, thread_cpu_time()),
                        sink.compressed_bytes.load(Ordering::Relaxed),
                    )
                })
            }
            Err(_) => Err(StorageError::invalid(
                store_path,
                "could not start the writer thread",
            )),
        };
        let written = writer_thread.and_then(|t| {
            t.join().map_err(|_| {
                StorageError::invalid(store_path, "the import's writer thread panicked")
            })?
        });
        (built, written)
    });
    // A writer failure explains a producer failure (its channel closed), so report it first.
    let (write_time, writer_cpu) = written?;
    let (phase, convert_cpu, builder_cpu, compressed_bytes) = built?;
    let cpu = ImportCpu {
        wall: started.elapsed(),
        process: cpu_since(process_cpu_start, process_cpu_time()),
        convert_thread: convert_cpu,
        builder_thread: builder_cpu,
        writer_thread: writer_cpu,
    };
    if std::env::var_os("STRATA_IMPORT_PROFILE").is_some() {
        eprintln!(
            "import phases: convert {:?}, histogram {:?}, bricks (cut + compress + hand-off) {:?}, sled writes (own thread) {write_time:?}",
            phase[0], phase[1], phase[2]
        );
    }
    for level in &levels {
        if level.next_row != level.rows() {
            return Err(StorageError::corrupted(
                store_path,
                format!(
                    "level {} ended with {} of {} brick rows",
                    level.level,
                    level.next_row,
                    level.rows()
                ),
            ));
        }
    }

    let (stored_lo, stored_hi) = counts.stored_range().unwrap_or((0, 0));
    let histogram = Histogram::from_stored(
        &counts,
        meta.value_mapping.mapping.slope,
        meta.value_mapping.mapping.intercept,
    );
    let required_features = {
        let mut features = options.codec.required_features(narrow);
        // Format 1 stays exactly what builds before format 2 read (dense skeleton).
        if format_version >= 2 {
            features.push(crate::store::FEATURE_SPARSE_SKELETON.to_string());
        }
        features
    };
    let header = store_header(
        meta,
        format_version,
        &layout,
        [stored_lo, stored_hi],
        options.codec,
        required_features,
    );
    let bytes_per_voxel = if narrow { 1 } else { 2 };
    let stats = StoreStats {
        bricks_per_level: skeleton
            .iter()
            .map(|l| {
                (
                    l.len() as u64,
                    l.iter().filter(|n| n.is_constant()).count() as u64,
                )
            })
            .collect(),
        compressed_bytes,
        uncompressed_bytes: layout.total_bricks() * BRICK_PAYLOAD_VOXELS as u64 * bytes_per_voxel,
        source_bytes: total_source,
        import_seconds: started.elapsed().as_secs_f64(),
    };
    let finishing = Instant::now();
    let skeleton = Skeleton::from_dense(&layout, &skeleton);
    writer.finish(&header, &skeleton, &histogram, &stats)?;
    let profile = ImportProfile {
        convert: phase[0],
        histogram: phase[1],
        bricks: phase[2],
        sled_writes: write_time,
        finish: finishing.elapsed(),
        cpu,
    };
    Ok(ImportReport {
        stats,
        header,
        profile,
    })
}

/// Set `STRATA_DEBUG_SLOW_IMPORT=1` to sleep 20 ms per slice: lets tests kill an import midway.
fn debug_slow_import() -> bool {
    static SLOW: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *SLOW.get_or_init(|| std::env::var_os("STRATA_DEBUG_SLOW_IMPORT").is_some())
}

/// Level-0 slices converted ahead of the brick builder: conversion and the histogram run on
/// their own thread while the previous slices' bricks are cut and compressed.
pub const SLICES_CONVERTED_AHEAD: u64 = 4;

/// Streams level-0 slices through every level's window. Returns time spent converting,
/// counting the histogram (both on the conversion thread, overlapping the rest), and building
/// bricks, and the conversion thread's CPU time.
fn build_levels(
    producer: &dyn SliceProducer,
    levels: &mut [LevelBuilder],
    sink: &BrickSink,
    skeleton: &mut DenseNodes,
    counts: &mut StoredValueCounts,
    options: &ImportOptions,
    store_path: &Path,
) -> Result<([std::time::Duration; 3], Option<std::time::Duration>)> {
    let dims = producer.dims();
    let slice_len = (dims[0] * dims[1]) as usize;
    let total_source = producer.source_bytes_per_slice() * dims[2];
    let cancelled = || options.cancel.is_some_and(|c| c.load(Ordering::Relaxed));
    let (converted, converted_in) =
        crossbeam_channel::bounded::<Result<(u64, Vec<u16>)>>(SLICES_CONVERTED_AHEAD as usize);
    std::thread::scope(|scope| {
        let conversion = std::thread::Builder::new()
            .name("strata-import-convert".into())
            .spawn_scoped(scope, move || {
                let mut counts = StoredValueCounts::default();
                let mut phase = [std::time::Duration::ZERO; 2];
                for k in 0..dims[2] {
                    if cancelled() {
                        break;
                    }
                    let t0 = Instant::now();
                    let mut slice = vec![0u16; slice_len];
                    let result = producer.stored_slice(k, &mut slice);
                    producer.release_slice(k);
                    let t1 = Instant::now();
                    if let Err(e) = result {
                        let _ = converted.send(Err(e));
                        break;
                    }
                    counts.add_slice(&slice);
                    phase[0] += t1 - t0;
                    phase[1] += t1.elapsed();
                    // A closed channel: the builder stopped (an error, a cancel).
                    if converted.send(Ok((k, slice))).is_err() {
                        break;
                    }
                }
                (counts, phase, thread_cpu_time())
            })
            .map_err(|e| StorageError::io(store_path, e))?;
        let mut bricks_time = std::time::Duration::ZERO;
        let built = (|| -> Result<()> {
            for k in 0..dims[2] {
                if cancelled() {
                    return Err(StorageError::Cancelled {
                        path: store_path.to_path_buf(),
                    });
                }
                let (index, slice) = match converted_in.recv() {
                    Ok(r) => r?,
                    // The conversion thread ended early only on a cancel (an error is sent).
                    Err(_) => {
                        return Err(StorageError::Cancelled {
                            path: store_path.to_path_buf(),
                        })
                    }
                };
                debug_assert_eq!(index, k);
                let t = Instant::now();
                push_slice(levels, 0, k, slice, sink, skeleton)?;
                bricks_time += t.elapsed();
                if let Some(progress) = options.progress {
                    progress(ImportProgress {
                        source_bytes_done: producer.source_bytes_per_slice() * (k + 1),
                        source_bytes_total: total_source,
                    });
                }
                if debug_slow_import() {
                    std::thread::sleep(std::time::Duration::from_millis(20));
                }
            }
            Ok(())
        })();
        // Lets a conversion thread blocked on a full channel end.
        drop(converted_in);
        let (slice_counts, phase, convert_cpu) = conversion.join().map_err(|_| {
            StorageError::invalid(store_path, "the import's conversion thread panicked")
        })?;
        built?;
        *counts = slice_counts;
        Ok(([phase[0], phase[1], bricks_time], convert_cpu))
    })
}

struct BrickSink<'a> {
    store_path: &'a Path,
    /// Format 3: each worker appends its records itself (no writer thread, no batches).
    direct: Option<&'a StoreWriter>,
    batches: crossbeam_channel::Sender<Vec<(BrickId, Vec<u8>)>>,
    narrow: bool,
    codec: BrickCodec,
    compressed_bytes: AtomicU64,
}

/// One level's sliding window of slices.
struct LevelBuilder {
    level: usize,
    dims: [u64; 3],
    bricks: [u64; 3],
    /// Contiguous slices, the first with index `first_slice`.
    window: VecDeque<Vec<u16>>,
    first_slice: u64,
    next_row: u64,
    is_top: bool,
}

impl LevelBuilder {
    fn new(level: usize, dims: [u64; 3], layout: &OctreeLayout) -> Self {
        LevelBuilder {
            level,
            dims,
            bricks: layout.bricks_in_level(level).map(u64::from),
            window: VecDeque::new(),
            first_slice: 0,
            next_row: 0,
            is_top: level + 1 == layout.level_count(),
        }
    }
    fn rows(&self) -> u64 {
        self.bricks[2]
    }
    fn last_index(&self) -> u64 {
        self.first_slice + self.window.len() as u64 - 1
    }
    fn slice(&self, k: u64) -> &[u16] {
        &self.window[(k - self.first_slice) as usize]
    }
    /// Last slice brick row `row` reads (apron included, clamped to the level).
    fn last_slice_for_row(&self, row: u64) -> u64 {
        ((row + 1) * CORE + APRON - 1).min(self.dims[2] - 1)
    }
}

/// Adds slice `k` to `level`, emits the brick rows it completes and cascades the averaged slice
/// to the next level.
fn push_slice(
    levels: &mut [LevelBuilder],
    level: usize,
    k: u64,
    slice: Vec<u16>,
    sink: &BrickSink,
    skeleton: &mut DenseNodes,
) -> Result<()> {
    let builder = &mut levels[level];
    if builder.window.is_empty() {
        builder.first_slice = k;
    }
    builder.window.push_back(slice);
    let [nx, ny, nz] = builder.dims;
    // Pair slices (2j, 2j+1) into slice j of the next level; an odd depth's last slice pairs with itself.
    let coarser = if builder.is_top {
        None
    } else if k % 2 == 1 || k == nz - 1 {
        let first = builder.slice(k - k % 2);
        let next = if k % 2 == 1 {
            Some(builder.slice(k))
        } else {
            None
        };
        let mut out = vec![0u16; (nx.div_ceil(2) * ny.div_ceil(2)) as usize];
        downsample_slice_pair(first, next, nx as usize, ny as usize, &mut out);
        Some((k / 2, out))
    } else {
        None
    };
    while builder.next_row < builder.rows()
        && builder.last_index() >= builder.last_slice_for_row(builder.next_row)
    {
        emit_row(builder, sink, skeleton)?;
        builder.next_row += 1;
        // The next row starts reading 2 slices below its core.
        let keep_from = (builder.next_row * CORE).saturating_sub(APRON);
        while builder.first_slice < keep_from && builder.window.len() > 1 {
            builder.window.pop_front();
            builder.first_slice += 1;
        }
    }
    if let Some((j, out)) = coarser {
        push_slice(levels, level + 1, j, out, sink, skeleton)?;
    }
    Ok(())
}

/// Bricks compressed in parallel before one ordered batch write: bounded memory (≤ 128 records
/// in flight, ~12 MB even when incompressible) and in-order appends, which sled handles with far
/// less node rewriting than scattered concurrent inserts.
const BRICKS_PER_BATCH: u64 = 128;

fn emit_row(builder: &LevelBuilder, sink: &BrickSink, skeleton: &mut DenseNodes) -> Result<()> {
    let bz = builder.next_row;
    let [nbx, nby, _] = builder.bricks;
    let slice_at = |z: u64| builder.slice(z);
    let level = builder.level;
    let row_bricks = nbx * nby;
    let row_start = (bz * row_bricks) as usize;
    for batch_start in (0..row_bricks).step_by(BRICKS_PER_BATCH as usize) {
        let batch_end = (batch_start + BRICKS_PER_BATCH).min(row_bricks);
        let encoded: Vec<(BrickId, NodeInfo, Option<Vec<u8>>, u64)> = (batch_start..batch_end)
            .into_par_iter()
            .map_init(
                || Vec::with_capacity(BRICK_PAYLOAD_VOXELS),
                |voxels, i| -> Result<_> {
                    let (bx, by) = (i % nbx, i / nbx);
                    extract_brick(bx, by, bz, builder.dims, &slice_at, voxels);
                    let range = value_range(voxels);
                    let id = BrickId::new(level as u8, [bx as u32, by as u32, bz as u32]);
                    let record = encode_brick(id, voxels, range, sink.narrow, sink.codec);
                    let flags = if range.min == range.max {
                        NodeInfo::CONSTANT
                    } else {
                        0
                    };
                    let node = NodeInfo {
                        min: range.min,
                        max: range.max,
                        flags,
                    };
                    let len = record.len() as u64;
                    if let Some(writer) = sink.direct {
                        // Written by this worker; only the length goes on.
                        writer.put_brick(id, &record)?;
                        return Ok((id, node, None, len));
                    }
                    Ok((id, node, Some(record), len))
                },
            )
            .collect::<Result<_>>()?;
        let mut bytes = 0;
        let mut records = Vec::with_capacity(encoded.len());
        for (offset, (id, node, record, len)) in encoded.into_iter().enumerate() {
            skeleton[level][row_start + batch_start as usize + offset] = node;
            bytes += len;
            if let Some(record) = record {
                records.push((id, record));
            }
        }
        sink.compressed_bytes.fetch_add(bytes, Ordering::Relaxed);
        // A closed channel means the writer failed; its error is reported by the caller.
        if !records.is_empty() && sink.batches.send(records).is_err() {
            return Err(StorageError::invalid(
                sink.store_path,
                "brick writer stopped",
            ));
        }
    }
    Ok(())
}
