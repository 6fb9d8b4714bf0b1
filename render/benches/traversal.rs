//! Traversal benchmark: what the node-extent exit and MIP's lean march save, in one run, as
//! ratios against the march before them (the same shader built with
//! `const NODE_EXTENT: bool = false;` / `const LEAN_MIP: bool = false;`); then the flat page
//! table against the octree traversal (gpu_octree.rs, octree.wgsl) on the same cut and cache:
//! GPU index bytes, index words read per pixel, samples per pixel, ms/frame and the ratio
//! octree/flat at equal samples (the images are the same: render/tests/octree_traversal.rs).
//!
//! Run: cargo bench -p strata-render --bench traversal
//! Env: STRATA_BENCH_VOLUME (default 256: the peer phantom's size), STRATA_BENCH_SIZE
//!      (default 256), STRATA_BENCH_FRAMES (default 3), STRATA_BENCH_ONLY_OCTREE=1 (only the
//!      flat-vs-octree table).
//!
//! Cuts: uniform level 0 (nothing to gain: every node is one cell), uniform levels 1 and 2,
//! and a view-like mixed cut (level 0 in the near octant, 2 in the far half, 1 between, the
//! far-right quarter culled: not resident). Per cut and mode: page-table words read per pixel
//! and samples per pixel (debug counters), ms/frame (median of interleaved rounds).

use std::time::Instant;
use strata_render::model::octree_cut;
use strata_render::testdata::phantom;
use strata_render::*;

fn env_u32(name: &str, default: u32) -> u32 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

struct GpuCut {
    cache: BrickCache,
    table: GpuPageTable,
}

fn upload_cut(ctx: &GpuContext, volume: &BrickedVolume, table: &PageTable) -> GpuCut {
    // Slots as the table numbers them (culled entries leave gaps).
    let nodes = table
        .entries
        .iter()
        .filter(|e| e.resident)
        .map(|e| e.slot_in_cache + 1)
        .max()
        .unwrap_or(1);
    let cache = BrickCache::new(
        &ctx.device,
        CacheConfig {
            max_slots: Some(nodes.max(1)),
            ..Default::default()
        },
    )
    .expect("cache");
    volume.upload(&cache, &ctx.queue, table).expect("upload");
    let gpu_table =
        GpuPageTable::new(&ctx.device, volume.geometry.page_dims(), &cache).expect("page table");
    gpu_table.update(&ctx.queue, table).expect("page table");
    gpu_table
        .update_value_max(
            &ctx.queue,
            &table.value_max_physical(volume.mapping, |l, n| volume.node_range(l, n)),
        )
        .expect("value bounds");
    GpuCut {
        cache,
        table: gpu_table,
    }
}

fn scene_of<'a>(
    cut: &'a GpuCut,
    transfer_function: &'a GpuTransferFunction,
    volume: &'a BrickedVolume,
    camera: &'a Camera,
    settings: &'a RenderSettings,
) -> FrameInputs<'a> {
    FrameInputs {
        cache: &cut.cache,
        page_table: &cut.table,
        transfer_function,
        geometry: &volume.geometry,
        mapping: volume.mapping,
        camera,
        settings,
    }
}

fn main() {
    let ctx = match GpuContext::headless() {
        Ok(c) => c,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(1);
        }
    };
    let n = env_u32("STRATA_BENCH_VOLUME", 256);
    let size = env_u32("STRATA_BENCH_SIZE", 256);
    let frames = env_u32("STRATA_BENCH_FRAMES", 3).max(1);
    println!("adapter: {}", ctx.adapter_name());
    let volume = phantom::vtk_peer_phantom(n).expect("phantom");
    let tf = phantom::vtk_peer_transfer_function();
    let tf_table = tf.table(0.0, 255.0);
    let gpu_tf = GpuTransferFunction::new(&ctx.device, &ctx.queue, &tf_table);
    let pages = volume.geometry.page_dims();
    let half = pages.map(|p| p / 2);
    let view_like = |p: [u32; 3]| -> Option<u8> {
        if p[0] >= half[0] && p[2] >= half[2] {
            None
        } else if p[2] >= half[2] {
            Some(2)
        } else if p[0] < half[0] && p[1] < half[1] {
            Some(0)
        } else {
            Some(1)
        }
    };
    let mut cuts: Vec<(String, PageTable)> = (0..=2u8)
        .map(|l| (format!("uniform level {l}"), volume.page_table_uniform(l)))
        .collect();
    let mut mixed = volume.page_table_with_levels(|p| view_like(p).unwrap_or(0));
    for i in 0..mixed.entries.len() {
        if view_like(mixed.page_of_linear(i)).is_none() {
            mixed.entries[i] = PageEntry::NOT_RESIDENT;
        }
    }
    cuts.push(("view-like mixed".into(), mixed));

    let source = Raycaster::shader_source();
    let cell_by_cell = source.replace(
        "const NODE_EXTENT: bool = true;",
        "const NODE_EXTENT: bool = false;",
    );
    let general_mip = source.replace(
        "const LEAN_MIP: bool = true;",
        "const LEAN_MIP: bool = false;",
    );
    let before_both = cell_by_cell.replace(
        "const LEAN_MIP: bool = true;",
        "const LEAN_MIP: bool = false;",
    );
    assert!(
        cell_by_cell != source && general_mip != source,
        "switches not in the shader"
    );

    let centre = volume.geometry.centre_patient();
    let distance = volume.geometry.bounding_radius_mm() / 15f64.to_radians().sin();
    let az = 30f64.to_radians();
    let eye = centre + glam::DVec3::new(az.sin(), 0.3, az.cos()) * distance;
    let camera = Camera::look_at(
        eye.into(),
        centre.into(),
        [0.0, 1.0, 0.0],
        Projection::Perspective { fov_y_deg: 30.0 },
    );
    let pixels = size as f64 * size as f64;
    println!(
        "\n{n}³ phantom, {size}², step 0.5, median of {frames} interleaved rounds; 'before' = cell-by-cell march (and MIP through the general march)"
    );
    println!(
        "{:<18} {:<5} {:>12} {:>12} {:>8} {:>10} {:>10} {:>10} {:>8}",
        "cut",
        "mode",
        "reads/px bef",
        "reads/px now",
        "ratio",
        "samples/px",
        "ms before",
        "ms now",
        "now/bef"
    );
    for (name, mut table) in cuts {
        volume.classify_empty(&mut table, &tf_table);
        // Index memory: the flat table's per-entry buffers (page word, MIP bound, visibility,
        // transition mask + closure: 20 B per finest brick position) against the octree of
        // the same cut (octree_cut.rs; projected at 32 B per node, 8 words, plus the same
        // 16 B of per-leaf buffers per leaf): what the GPU octree path would hold.
        let octree = octree_cut::OctreeCut::from_page_table(&table);
        let leaves = octree.nodes.iter().filter(|n| n.is_leaf()).count();
        let flat_bytes = table.entries.len() * 20;
        let octree_bytes = octree.nodes.len() * 32 + leaves * 16;
        println!(
            "{name:<18} index bytes: flat {flat_bytes} ({} entries), octree {octree_bytes} ({} nodes, {leaves} leaves): {:.3}x",
            table.entries.len(),
            octree.nodes.len(),
            octree_bytes as f64 / flat_bytes as f64
        );
        let cut = upload_cut(&ctx, &volume, &table);
        octree_vs_flat(
            &ctx, &name, &volume, &table, &cut, &gpu_tf, &camera, size, frames,
        );
        if std::env::var("STRATA_BENCH_ONLY_OCTREE").is_ok_and(|v| v == "1") {
            continue;
        }
        let mut now = Raycaster::new(&ctx, &cut.cache);
        let mut before = Raycaster::with_shader_source(&ctx, &cut.cache, &before_both);
        for mode in [RenderMode::Dvr, RenderMode::Mip] {
            let settings = RenderSettings {
                width: size,
                height: size,
                mode,
                quality: 0.5,
                ..Default::default()
            };
            let counting = RenderSettings {
                count_samples: true,
                ..settings.clone()
            };
            let a = before
                .render_blocking(&ctx, &scene_of(&cut, &gpu_tf, &volume, &camera, &counting))
                .expect("render");
            let b = now
                .render_blocking(&ctx, &scene_of(&cut, &gpu_tf, &volume, &camera, &counting))
                .expect("render");
            let mut times = [Vec::new(), Vec::new()];
            for round in 0..=frames {
                for (i, rc) in [&mut before, &mut now].into_iter().enumerate() {
                    let t = Instant::now();
                    rc.render_and_wait(&ctx, &scene_of(&cut, &gpu_tf, &volume, &camera, &settings))
                        .expect("render");
                    if round > 0 {
                        times[i].push(t.elapsed().as_secs_f64() * 1e3);
                    }
                }
            }
            let [ms_before, ms_now] = times.map(median);
            let (ra, rb) = (a.page_reads.unwrap_or(0), b.page_reads.unwrap_or(0));
            println!(
                "{:<18} {:<5} {:>12.2} {:>12.2} {:>7.2}x {:>10.1} {:>10.1} {:>10.1} {:>7.3}x",
                name,
                format!("{mode:?}"),
                ra as f64 / pixels,
                rb as f64 / pixels,
                ra as f64 / rb.max(1) as f64,
                b.samples.unwrap_or(0) as f64 / pixels,
                ms_before,
                ms_now,
                ms_now / ms_before
            );
        }
        // MIP's lean march alone (both with the node-extent exit).
        let mut general = Raycaster::with_shader_source(&ctx, &cut.cache, &general_mip);
        let settings = RenderSettings {
            width: size,
            height: size,
            mode: RenderMode::Mip,
            quality: 0.5,
            ..Default::default()
        };
        let scene = scene_of(&cut, &gpu_tf, &volume, &camera, &settings);
        let mut times = [Vec::new(), Vec::new()];
        for round in 0..=frames {
            for (i, rc) in [&mut general, &mut now].into_iter().enumerate() {
                let t = Instant::now();
                rc.render_and_wait(&ctx, &scene).expect("render");
                if round > 0 {
                    times[i].push(t.elapsed().as_secs_f64() * 1e3);
                }
            }
        }
        let [ms_general, ms_lean] = times.map(median);
        println!(
            "{:<18} MIP general march {ms_general:.1} ms, lean march {ms_lean:.1} ms: {:.3}x",
            name,
            ms_lean / ms_general
        );
    }
}

/// Flat table vs octree traversal on one cut (same cache, same raycaster, interleaved rounds):
/// GPU index bytes (visibility words included), index words read and samples per pixel,
/// ms/frame and octree/flat, for DVR, shaded DVR, MIP and isosurfaces; smooth transitions off,
/// and on where the cut has coarser neighbours (rows marked `+st`; the octree finds a band
/// sample's neighbour by a point query).
#[allow(clippy::too_many_arguments)]
fn octree_vs_flat(
    ctx: &GpuContext,
    name: &str,
    volume: &BrickedVolume,
    table: &PageTable,
    cut: &GpuCut,
    gpu_tf: &GpuTransferFunction,
    camera: &Camera,
    size: u32,
    frames: u32,
) {
    let octree = GpuPageTable::with_traversal(
        &ctx.device,
        volume.geometry.page_dims(),
        &cut.cache,
        Traversal::Octree,
    )
    .expect("octree index");
    octree.update(&ctx.queue, table).expect("octree index");
    octree
        .update_value_max(
            &ctx.queue,
            &table.value_max_physical(volume.mapping, |l, n| volume.node_range(l, n)),
        )
        .expect("value bounds");
    let flat_bytes = cut.table.gpu_index_bytes() + cut.table.visibility_entries() as u64 * 4;
    let octree_bytes = octree.gpu_index_bytes() + octree.visibility_entries() as u64 * 4;
    println!(
        "{name:<18} GPU index bytes: flat {flat_bytes} ({} page cells), octree {octree_bytes} ({} leaves): {:.3}x",
        cut.table.entry_count(),
        octree.visibility_entries(),
        octree_bytes as f64 / flat_bytes as f64
    );
    let mut rc = Raycaster::new(ctx, &cut.cache);
    let pixels = size as f64 * size as f64;
    let smooth_options: &[bool] = if cut.table.transition_fraction() > 0.0 {
        &[false, true]
    } else {
        &[false]
    };
    for (&smooth, (mode_name, mode, shading)) in smooth_options.iter().flat_map(|s| {
        [
            ("dvr", RenderMode::Dvr, None),
            ("dvr+sh", RenderMode::Dvr, Some(Shading::default())),
            ("mip", RenderMode::Mip, None),
            ("iso", RenderMode::Isosurface, None),
        ]
        .map(|m| (s, m))
    }) {
        let mode_name = format!("{mode_name}{}", if smooth { "+st" } else { "" });
        let settings = RenderSettings {
            width: size,
            height: size,
            mode,
            shading,
            iso_value: 120.0,
            quality: 0.5,
            smooth_transitions: smooth,
            ..Default::default()
        };
        let counting = RenderSettings {
            count_samples: true,
            ..settings.clone()
        };
        let indices = [&cut.table, &octree];
        fn scene<'a>(
            cut: &'a GpuCut,
            index: &'a GpuPageTable,
            gpu_tf: &'a GpuTransferFunction,
            volume: &'a BrickedVolume,
            camera: &'a Camera,
            s: &'a RenderSettings,
        ) -> FrameInputs<'a> {
            FrameInputs {
                page_table: index,
                ..scene_of(cut, gpu_tf, volume, camera, s)
            }
        }
        let counted: Vec<FrameReadback> = indices
            .iter()
            .map(|index| {
                rc.render_blocking(ctx, &scene(cut, index, gpu_tf, volume, camera, &counting))
                    .expect("render")
            })
            .collect();
        let mut times = [Vec::new(), Vec::new()];
        for round in 0..=frames {
            for (i, index) in indices.iter().enumerate() {
                let t = Instant::now();
                rc.render_and_wait(ctx, &scene(cut, index, gpu_tf, volume, camera, &settings))
                    .expect("render");
                if round > 0 {
                    times[i].push(t.elapsed().as_secs_f64() * 1e3);
                }
            }
        }
        let [ms_flat, ms_octree] = times.map(median);
        let per_px = |v: Option<u64>| v.unwrap_or(0) as f64 / pixels;
        let same = counted[0].rgba == counted[1].rgba;
        println!(
            "{:<18} {:<6} reads/px flat {:>6.2} octree {:>6.2} | samples/px flat {:>7.1} octree {:>7.1} | ms flat {:>7.1} octree {:>7.1} octree/flat {:>6.3}x | same image {same}",
            name,
            mode_name,
            per_px(counted[0].page_reads),
            per_px(counted[1].page_reads),
            per_px(counted[0].samples),
            per_px(counted[1].samples),
            ms_flat,
            ms_octree,
            ms_octree / ms_flat
        );
    }
}
