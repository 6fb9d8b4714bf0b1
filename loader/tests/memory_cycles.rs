//! Memory across volumes, measured: N create/stream/drop cycles of one part of the loader,
//! printing after each drop the process's RSS, glibc's heap (in use, free, mmapped), the RSS
//! after `malloc_trim`, and wgpu's allocator report (bytes allocated and reserved in device
//! memory blocks). Tells a leak (heap in use grows) from fragmentation (free heap grows, trim
//! gives it back) from memory outside malloc's heap (the driver's blocks).
//!
//! `STRATA_CYCLES=20 STRATA_CYCLE_PART=full|gpu|cpu STRATA_CYCLE_BUDGETS=fixed|random \
//!  cargo test -p strata-loader --test integration memory_cycles:: -- --ignored --nocapture`

use crate::common;

use std::sync::Arc;

use common::*;
use strata_loader::cpu_cache::CpuBrickCache;
use strata_loader::fetch_workers::FetchWorkers;
use strata_loader::octree_ranges::OctreeRanges;
use strata_loader::StreamingConfig;
use strata_render::{
    BrickCache, CacheConfig, Camera, FrameInputs, GpuPageTable, GpuTransferFunction, PageTable,
    Projection, Raycaster,
};
use strata_types::BrickId;

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

fn resident_bytes() -> u64 {
    let statm = std::fs::read_to_string("/proc/self/statm").unwrap_or_default();
    statm
        .split_whitespace()
        .nth(1)
        .and_then(|p| p.parse::<u64>().ok())
        .unwrap_or(0)
        * 4096
}

/// The process's threads by name, with counts.
fn thread_names() -> std::collections::BTreeMap<String, usize> {
    let mut names = std::collections::BTreeMap::new();
    for task in std::fs::read_dir("/proc/self/task")
        .into_iter()
        .flatten()
        .flatten()
    {
        let name = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
        *names.entry(name.trim().to_string()).or_insert(0) += 1;
    }
    names
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / 1048576.0
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn heap() -> (u64, u64, u64) {
    // SAFETY: mallinfo2 only reads malloc's statistics.
    let info = unsafe { libc::mallinfo2() };
    (
        info.uordblks as u64,
        info.fordblks as u64,
        info.hblkhd as u64,
    )
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn heap() -> (u64, u64, u64) {
    (0, 0, 0)
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn trimmed_rss() -> u64 {
    // SAFETY: malloc_trim returns free heap memory to the system; no pointer is touched.
    unsafe { libc::malloc_trim(0) };
    resident_bytes()
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn trimmed_rss() -> u64 {
    resident_bytes()
}

/// Each mapping of the process: (start address, size, name, resident bytes).
fn mappings() -> Vec<(u64, u64, String, u64)> {
    let text = std::fs::read_to_string("/proc/self/smaps").unwrap_or_default();
    let mut out: Vec<(u64, u64, String, u64)> = Vec::new();
    for line in text.lines() {
        let mut fields = line.split_whitespace();
        let first = fields.next().unwrap_or("");
        if let Some((a, b)) = first.split_once('-') {
            if let (Ok(a), Ok(b)) = (u64::from_str_radix(a, 16), u64::from_str_radix(b, 16)) {
                let name = fields.nth(4).unwrap_or("[anon]").to_string();
                out.push((a, b - a, name, 0));
                continue;
            }
        }
        if first == "Rss:" {
            if let (Some(last), Some(kb)) = (out.last_mut(), fields.next()) {
                last.3 = kb.parse::<u64>().unwrap_or(0) * 1024;
            }
        }
    }
    out
}

fn camera(geometry: &strata_render::VolumeGeometry, rng: &mut Rng) -> Camera {
    Camera::orbit(
        geometry,
        360.0 * rng.unit(),
        -80.0 + 160.0 * rng.unit(),
        0.5 + 4.0 * rng.unit(),
        Projection::Perspective { fov_y_deg: 30.0 },
    )
}

#[test]
#[ignore = "measurement: prints memory per create/drop cycle (see the module doc)"]
fn memory_over_create_drop_cycles() {
    let env = |name: &str, default: &str| std::env::var(name).unwrap_or_else(|_| default.into());
    let cycles: usize = env("STRATA_CYCLES", "20").parse().unwrap();
    let frames: usize = env("STRATA_CYCLE_FRAMES", "100").parse().unwrap();
    let part = env("STRATA_CYCLE_PART", "full");
    let random_budgets = env("STRATA_CYCLE_BUDGETS", "fixed") == "random";
    // First, before the GPU's and the store's threads (see malloc_arenas.rs).
    strata_loader::malloc_arenas::limit_malloc_arenas();
    let ctx = gpu();
    let dir = tempfile::tempdir().unwrap();
    let store = open(&phantom_store(dir.path(), 160));
    let geometry = store.header().geometry.clone();
    let octree = OctreeRanges::from_source(store.as_ref());
    let all_bricks: Vec<BrickId> = (0..octree.level_count())
        .flat_map(|level| {
            let n = octree.bricks_in_level(level);
            (0..n[2]).flat_map(move |z| {
                (0..n[1]).flat_map(move |y| (0..n[0]).map(move |x| BrickId::new(level, [x, y, z])))
            })
        })
        .filter(|&id| octree.contains(id))
        .collect();
    let mut rng = Rng(0x50a6_50a6);
    println!(
        "part {part}, {} budgets, {frames} frames per cycle, {} bricks in the store",
        if random_budgets { "random" } else { "fixed" },
        all_bricks.len()
    );
    println!("cycle  rss  heap_used  heap_free  mmapped  rss_trimmed  gpu_alloc  gpu_reserved  gpu_blocks  (MiB)  threads  mappings");
    let mut first_mappings = None;
    for cycle in 0..cycles {
        let config = if random_budgets {
            StreamingConfig {
                gpu_budget_bytes: (8 + rng.next() % 120) << 20,
                cpu_budget_bytes: (16 + rng.next() % 240) << 20,
                sled_cache_bytes: 1 << 20,
                uploads_per_frame: 1 + (rng.next() % 64) as usize,
                ..StreamingConfig::default()
            }
        } else {
            StreamingConfig {
                gpu_budget_bytes: 96 << 20,
                cpu_budget_bytes: 192 << 20,
                sled_cache_bytes: 1 << 20,
                uploads_per_frame: 32,
                ..StreamingConfig::default()
            }
        };
        match part.as_str() {
            "full" => {
                let tf = bone();
                let mut volume = stream(&ctx, &store, &tf, config.clone());
                let settings = settings(128);
                for _ in 0..frames {
                    volume
                        .frame(&ctx, &camera(&geometry, &mut rng), &settings)
                        .unwrap();
                }
                ctx.wait_idle().unwrap();
            }
            "cpu" => {
                // The CPU side alone: fetch workers read every brick (a few times) into an
                // LRU cache within the budget.
                let workers = FetchWorkers::start(store.clone(), 2, 256, 128).unwrap();
                let mut cache = CpuBrickCache::new(config.cpu_budget_bytes / 2);
                for _ in 0..3 {
                    let mut pending = all_bricks.clone();
                    while !pending.is_empty() || workers.in_flight() > 0 || workers.queued() > 0 {
                        let batch: Vec<(BrickId, f64)> = pending
                            .drain(..pending.len().min(64))
                            .map(|id| (id, 1.0))
                            .collect();
                        if !batch.is_empty() {
                            workers.set_requests(&batch, &[]);
                        }
                        for r in workers.try_results() {
                            workers.complete(r.id);
                            if let Ok(brick) = r.outcome {
                                cache.insert(r.id, brick, false);
                            }
                        }
                        std::thread::sleep(std::time::Duration::from_millis(1));
                    }
                }
            }
            "gpu" => {
                // The GPU side alone: a cache texture, page table, TF and raycaster of the
                // config's size, some uploads and frames.
                let cache = BrickCache::new(
                    &ctx.device,
                    CacheConfig {
                        budget_bytes: config.gpu_budget_bytes,
                        ..Default::default()
                    },
                )
                .unwrap();
                let page_dims = geometry.page_dims();
                let table = PageTable::new(page_dims);
                let gpu_table = GpuPageTable::new(&ctx.device, page_dims, &cache).unwrap();
                gpu_table.update(&ctx.queue, &table).unwrap();
                let tf_table = strata_loader::streaming::tf_table_for(
                    &bone(),
                    store.header().value_mapping.mapping,
                    store.header().stored_range,
                );
                let tf = GpuTransferFunction::new(&ctx.device, &ctx.queue, &tf_table);
                let mut raycaster = Raycaster::new(&ctx, &cache);
                let brick = store.read_brick(all_bricks[0]).unwrap();
                let settings = settings(128);
                for frame in 0..frames {
                    let slot = (frame as u32) % cache.slot_count();
                    cache.upload_brick(&ctx.queue, slot, &brick).unwrap();
                    let cam = camera(&geometry, &mut rng);
                    let scene = FrameInputs {
                        cache: &cache,
                        page_table: &gpu_table,
                        transfer_function: &tf,
                        geometry: &geometry,
                        mapping: store.header().value_mapping.mapping,
                        camera: &cam,
                        settings: &settings,
                    };
                    raycaster.render(&ctx, &scene).unwrap();
                    if frame % 8 == 0 {
                        ctx.wait_idle().unwrap();
                    }
                }
                ctx.wait_idle().unwrap();
            }
            "pipelines" => {
                // Only the raycaster: its pipelines compiled, one frame, dropped.
                let cache = BrickCache::new(
                    &ctx.device,
                    CacheConfig {
                        budget_bytes: 8 << 20,
                        ..Default::default()
                    },
                )
                .unwrap();
                let page_dims = geometry.page_dims();
                let gpu_table = GpuPageTable::new(&ctx.device, page_dims, &cache).unwrap();
                let tf_table = strata_loader::streaming::tf_table_for(
                    &bone(),
                    store.header().value_mapping.mapping,
                    store.header().stored_range,
                );
                let tf = GpuTransferFunction::new(&ctx.device, &ctx.queue, &tf_table);
                let mut raycaster = Raycaster::new(&ctx, &cache);
                let settings = settings(128);
                let cam = camera(&geometry, &mut rng);
                let scene = FrameInputs {
                    cache: &cache,
                    page_table: &gpu_table,
                    transfer_function: &tf,
                    geometry: &geometry,
                    mapping: store.header().value_mapping.mapping,
                    camera: &cam,
                    settings: &settings,
                };
                raycaster.render(&ctx, &scene).unwrap();
                ctx.wait_idle().unwrap();
            }
            other => panic!("STRATA_CYCLE_PART={other}: expected full, gpu, cpu or pipelines"),
        }
        ctx.wait_idle().unwrap();
        let rss = resident_bytes();
        let (used, free, mmapped) = heap();
        let report = ctx.device.generate_allocator_report();
        // Trimming changes what the next cycle finds: only when asked.
        let trimmed = if env("STRATA_CYCLE_TRIM", "0") == "1" {
            trimmed_rss()
        } else {
            0
        };
        let (allocated, reserved, blocks) = report.map_or((0, 0, 0), |r| {
            (
                r.total_allocated_bytes,
                r.total_reserved_bytes,
                r.blocks.len(),
            )
        });
        println!(
            "{cycle:5} {:5.0} {:9.0} {:10.0} {:8.0} {:12.0} {:10.0} {:13.0} {blocks:11} {:8} {:9}",
            mib(rss),
            mib(used),
            mib(free),
            mib(mmapped),
            mib(trimmed),
            mib(allocated),
            mib(reserved),
            thread_names().values().sum::<usize>(),
            mappings().len()
        );
        if cycle == 0 {
            first_mappings = Some(mappings());
        }
    }
    println!("threads now: {:?}", thread_names());
    // Where the growth lives: the mappings whose resident bytes grew most since cycle 0.
    let before = first_mappings.unwrap_or_default();
    let after = mappings();
    let mut growth: Vec<(i64, u64, u64, String)> = after
        .iter()
        .map(|(start, size, name, rss)| {
            let old = before.iter().find(|(s, ..)| s == start).map_or(0, |m| m.3);
            (*rss as i64 - old as i64, *start, *size, name.clone())
        })
        .collect();
    growth.sort_by_key(|g| -g.0);
    let new_mappings = after
        .iter()
        .filter(|(s, ..)| !before.iter().any(|b| b.0 == *s))
        .count();
    println!(
        "mappings: {} after cycle 0, {} now ({new_mappings} new); largest growth:",
        before.len(),
        after.len()
    );
    for (delta, start, size, name) in growth.iter().take(12) {
        println!(
            "  {:+8.1} MiB  {start:#x} size {:8.1} MiB  {name}",
            *delta as f64 / 1048576.0,
            mib(*size)
        );
    }
    drop(Arc::clone(&store));
}
