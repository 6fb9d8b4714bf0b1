//! `strata-bench transitions`: the mixed-resolution paper's Table 1 for one input. What smooth
//! transitions between octree levels cost in frame time, and what they change in the image.
//!
//! The cut is the one a distance-based LOD makes: a plane perpendicular to the view direction
//! splits the volume, level 0 in front of it and level 1 behind (2:1 balanced by construction,
//! since only two levels exist). The plane sits at a level-1 node boundary chosen so that the
//! share of transition nodes (nodes with a coarser neighbour, the paper's "transition bricks")
//! is as close to 25 % as the grid allows (the paper's data sets have 22 % and 29 %).
//!
//! Four settings render that cut from the accuracy bench's oblique view, DVR without jitter:
//! smoothing off/on × unshaded/shaded. For each: the median GPU time of the raycast pass over
//! `--frames` frames (timestamps where the adapter has them, else submit → done; the four
//! settings are interleaved round by round so machine noise hits all alike, and a warm-up round
//! is discarded), the wall time of render + wait, and the image error (RMSE, PSNR, max abs over
//! RGBA8) against two f64 CPU references: the full-resolution level-0 cut (what the mixed cut
//! costs in accuracy) and the same mixed cut with the same smoothing setting (the GPU computes
//! the field the reference defines; expected ≥ 40 dB).

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use glam::DVec3;
use strata_loader::store_volume::{classify_empty, load_uniform_cut, page_table_for_cut, GpuCut};
use strata_loader::ResidentBricks;
use strata_render::model::smooth_transitions::{transition_masks, transition_node_fraction};
use strata_render::{
    compare_rgba8, FrameInputs, GpuContext, ImageComparison, PageTable, RenderMode, RenderSettings,
    Shading,
};

use super::common::{bench_camera, median, open_input, reference_rgba, view_split, Volume};
use strata_viewer::export::parse_size;

#[derive(clap::Args)]
pub struct Options {
    /// A store, or `phantom` for a generated CT phantom.
    pub input: String,
    /// Edge of the generated phantom (256³ = 8×8×8 bricks, fine enough to hit 25 %).
    #[arg(long, default_value_t = 256)]
    pub phantom_size: u64,
    /// Image size WxH (the f64 references are rendered at the same size).
    #[arg(long, default_value = "256x256")]
    pub size: String,
    /// Timed frames per setting (median reported), after one discarded warm-up round.
    #[arg(long, default_value_t = 9)]
    pub frames: usize,
    /// Transfer function preset or JSON file (default by modality).
    #[arg(long)]
    pub tf: Option<String>,
    /// Share of transition nodes the split aims at.
    #[arg(long, default_value_t = 0.25)]
    pub target_fraction: f64,
    /// Markdown table (default `transitions-<name>.md`); the CSV goes next to it.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// One of the four measured settings.
#[derive(Clone, Copy, Debug)]
struct Variant {
    smooth: bool,
    shaded: bool,
}

const VARIANTS: [Variant; 4] = [
    Variant {
        smooth: false,
        shaded: false,
    },
    Variant {
        smooth: false,
        shaded: true,
    },
    Variant {
        smooth: true,
        shaded: false,
    },
    Variant {
        smooth: true,
        shaded: true,
    },
];

impl Variant {
    fn label(&self) -> String {
        format!(
            "{} {}",
            if self.smooth {
                "smooth"
            } else {
                "discontinuous"
            },
            if self.shaded { "shaded" } else { "unshaded" }
        )
    }
}

struct Row {
    variant: Variant,
    gpu_ms: f64,
    wall_ms: f64,
    vs_full: ImageComparison,
    vs_same: ImageComparison,
}

/// Everything the table reports about one input.
struct Report {
    name: String,
    dims: [u32; 3],
    fraction: f64,
    level0_nodes: usize,
    level1_nodes: usize,
    width: u32,
    height: u32,
    frames: usize,
    adapter: String,
    timing: String,
    rows: Vec<Row>,
    /// Largest |F(b+ε) − F(b−ε)| over points on every face between levels (physical units):
    /// discontinuous, smooth.
    seam_jump: (f64, f64),
}

pub fn run(options: Options) -> Result<()> {
    if options.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let (width, height) = parse_size(&options.size)?;
    let v = open_input(&options.input, options.phantom_size, options.tf.as_deref())?;
    if v.store.layout().level_count() < 2 {
        bail!(
            "{} has a single octree level: no mixed cut to measure",
            v.name
        );
    }
    let camera = bench_camera(&v.geometry);

    let page_dims = v.geometry.page_dims();
    let split = view_split(&v, &camera, options.target_fraction);
    let mut table = page_table_for_cut(&v.store, &v.geometry, |p| split.level_of(p));
    classify_empty(&v.store, &mut table, v.mapping, &v.tf_table);
    let fraction = transition_node_fraction(&table, &transition_masks(&table));
    let bricks = ResidentBricks::load(&v.store, &table)?;
    let mut nodes = [0usize; 2];
    for (i, e) in table.entries.iter().enumerate() {
        let page = table.page_of_linear(i);
        if PageTable::node_of(page, e.level).map(|n| n << e.level) == page {
            nodes[e.level as usize] += 1;
        }
    }
    eprintln!(
        "{}: {:?} pages, mixed cut of {} level-0 and {} level-1 nodes, {:.1} % transition nodes",
        v.name,
        page_dims,
        nodes[0],
        nodes[1],
        100.0 * fraction
    );

    let seam_jump = (
        max_level_face_jump(&bricks, &table, &v, false),
        max_level_face_jump(&bricks, &table, &v, true),
    );
    eprintln!(
        "largest field jump across level faces: {:.3} discontinuous, {:.2e} smooth",
        seam_jump.0, seam_jump.1
    );

    let ctx = GpuContext::headless()?;
    eprintln!("GPU: {}", ctx.adapter_name());
    let mut mixed = GpuCut::upload(&ctx, &bricks, &table, page_dims, &v.tf_table)?;
    let settings_of = |variant: Variant| RenderSettings {
        width,
        height,
        mode: RenderMode::Dvr,
        quality: 0.5,
        jitter: false,
        shading: variant.shaded.then(Shading::default),
        smooth_transitions: variant.smooth,
        ..RenderSettings::default()
    };

    // References: the full-resolution cut (unshaded, shaded), then the mixed cut per setting.
    let mut full_refs = HashMap::new();
    {
        let (full_table, full_bricks) =
            load_uniform_cut(&v.store, &v.geometry, v.mapping, &v.tf_table, 0)?;
        for shaded in [false, true] {
            let t = Instant::now();
            let settings = settings_of(Variant {
                smooth: false,
                shaded,
            });
            let rgba = reference_rgba(&v, &full_bricks, &full_table, &camera, &settings)?;
            eprintln!(
                "full-resolution reference ({}) in {:.1} s",
                if shaded { "shaded" } else { "unshaded" },
                t.elapsed().as_secs_f64()
            );
            full_refs.insert(shaded, rgba);
        }
    }
    let mut images = Vec::new();
    for variant in VARIANTS {
        let settings = settings_of(variant);
        let t = Instant::now();
        let same_ref = reference_rgba(&v, &bricks, &table, &camera, &settings)?;
        eprintln!(
            "mixed-cut reference ({}) in {:.1} s",
            variant.label(),
            t.elapsed().as_secs_f64()
        );
        // Also the warm-up frame of this setting (compiles its pipeline).
        let frame = mixed.render_blocking(&ctx, &v.geometry, v.mapping, &camera, &settings)?;
        let drawn = mixed.raycaster.last_pipeline_key();
        if fraction > 0.0 && drawn.map(|k| k.smooth_transitions) != Some(variant.smooth) {
            bail!("{} was drawn with pipeline {drawn:?}", variant.label());
        }
        let vs_full = compare_rgba8(&frame.rgba, &full_refs[&variant.shaded])?;
        let vs_same = compare_rgba8(&frame.rgba, &same_ref)?;
        images.push((vs_full, vs_same));
    }

    let times = time_frames(&ctx, &mut mixed, &v, &camera, &settings_of, options.frames)?;
    let rows: Vec<Row> = VARIANTS
        .iter()
        .zip(images)
        .enumerate()
        .map(|(k, (&variant, (vs_full, vs_same)))| Row {
            variant,
            gpu_ms: if times.gpu[k].is_empty() {
                f64::NAN
            } else {
                median(times.gpu[k].clone())
            },
            wall_ms: median(times.wall[k].clone()),
            vs_full,
            vs_same,
        })
        .collect();
    for r in &rows {
        eprintln!(
            "{:<24} GPU {:>7.1} ms  wall {:>7.1} ms  vs full res {:>5.1} dB (max {:>3})  vs same cut {:>5.1} dB (max {:>3})",
            r.variant.label(),
            r.gpu_ms,
            r.wall_ms,
            r.vs_full.psnr_db,
            r.vs_full.max_abs_error,
            r.vs_same.psnr_db,
            r.vs_same.max_abs_error
        );
    }

    let report = Report {
        name: v.name.clone(),
        dims: v.geometry.dims,
        fraction,
        level0_nodes: nodes[0],
        level1_nodes: nodes[1],
        width,
        height,
        frames: options.frames,
        adapter: ctx.adapter_name(),
        timing: format!("{:?}", mixed.raycaster.frame_timing_source()),
        rows,
        seam_jump,
    };
    let md_path = options
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from(format!("transitions-{}.md", v.name)));
    if let Some(dir) = md_path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let csv_path = md_path.with_extension("csv");
    let md = markdown(&report);
    std::fs::write(&md_path, &md).with_context(|| format!("writing {}", md_path.display()))?;
    write_csv(&csv_path, &report)?;
    println!("{md}");
    println!("wrote {}, {}", md_path.display(), csv_path.display());
    Ok(())
}

/// Milliseconds per frame, one list per variant (same order as [`VARIANTS`]).
struct Timings {
    /// The raycast pass on the GPU (timestamps, else submit → done).
    gpu: Vec<Vec<f64>>,
    /// Render + wait on the CPU clock.
    wall: Vec<Vec<f64>>,
}

/// GPU and wall milliseconds per variant: `frames` rounds after one warm-up round, the four
/// settings interleaved within each round.
fn time_frames(
    ctx: &GpuContext,
    cut: &mut GpuCut,
    v: &Volume,
    camera: &strata_render::Camera,
    settings_of: &dyn Fn(Variant) -> RenderSettings,
    frames: usize,
) -> Result<Timings> {
    let mut gpu = vec![Vec::new(); VARIANTS.len()];
    let mut wall = vec![Vec::new(); VARIANTS.len()];
    let mut variant_of_frame = HashMap::new();
    let collect = |cut: &mut GpuCut, of: &HashMap<u64, usize>, gpu: &mut Vec<Vec<f64>>| {
        for timing in cut.raycaster.try_take_frame_timings(ctx) {
            if let Some(&k) = of.get(&timing.frame_number) {
                gpu[k].push(timing.milliseconds);
            }
        }
    };
    for round in 0..=frames {
        for (k, &variant) in VARIANTS.iter().enumerate() {
            let settings = settings_of(variant);
            let scene = FrameInputs {
                cache: &cut.cache,
                page_table: &cut.page_table,
                transfer_function: &cut.transfer_function,
                geometry: &v.geometry,
                mapping: v.mapping,
                camera,
                settings: &settings,
            };
            let t = Instant::now();
            let index = cut.raycaster.render_measured(ctx, &scene)?;
            ctx.wait_for_submission(index)?;
            let ms = t.elapsed().as_secs_f64() * 1e3;
            let _ = cut.raycaster.try_take_visibility(ctx);
            if round > 0 {
                wall[k].push(ms);
                variant_of_frame.insert(cut.raycaster.frame_number(), k);
            }
            collect(cut, &variant_of_frame, &mut gpu);
        }
    }
    ctx.wait_idle()?;
    for _ in 0..500 {
        if gpu.iter().all(|g| g.len() >= frames) {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(2));
        collect(cut, &variant_of_frame, &mut gpu);
    }
    Ok(Timings { gpu, wall })
}

fn row_of(report: &Report, smooth: bool, shaded: bool) -> &Row {
    report
        .rows
        .iter()
        .find(|r| r.variant.smooth == smooth && r.variant.shaded == shaded)
        .expect("all four variants are measured")
}

fn markdown(r: &Report) -> String {
    let [nx, ny, nz] = r.dims;
    let cell = |smooth, shaded| row_of(r, smooth, shaded).gpu_ms;
    let psnr = |smooth, shaded| row_of(r, smooth, shaded).vs_full.psnr_db;
    let mut out = format!(
        "Smooth vs discontinuous level transitions (mixed-resolution paper, Table 1), {}×{} DVR, \
         step 0.5 voxel, no jitter; median GPU time of the raycast pass over {} frames ({}) on {}. \
         Cut: a plane perpendicular to the view splits the volume into {} level-0 nodes (near) \
         and {} level-1 nodes (far). Error: PSNR of the GPU image against the f64 reference of \
         the full-resolution (level 0) cut, same shading.\n\n\
         | data set | resolution | transition bricks | discont. unshaded ms | discont. shaded ms \
         | smooth unshaded ms | smooth shaded ms | smooth/discont. unshaded | smooth/discont. shaded \
         | PSNR vs full res, discont. unshaded / shaded dB | PSNR vs full res, smooth unshaded / shaded dB |\n\
         | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n",
        r.width, r.height, r.frames, r.timing, r.adapter, r.level0_nodes, r.level1_nodes
    );
    let _ = writeln!(
        out,
        "| {} | {nx} × {ny} × {nz} | {:.0} % | {:.1} | {:.1} | {:.1} | {:.1} | {:.2} | {:.2} | {:.1} / {:.1} | {:.1} / {:.1} |",
        r.name,
        100.0 * r.fraction,
        cell(false, false),
        cell(false, true),
        cell(true, false),
        cell(true, true),
        cell(true, false) / cell(false, false),
        cell(true, true) / cell(false, true),
        psnr(false, false),
        psnr(false, true),
        psnr(true, false),
        psnr(true, true),
    );
    let _ = writeln!(
        out,
        "\nField continuity: the largest jump of the sampled field across the faces between \
         levels (64 points per face, ±1e-6 voxel, f64 CPU field) is {:.3} discontinuous and \
         {:.1e} smooth (physical units).",
        r.seam_jump.0, r.seam_jump.1
    );
    out += "\nPer setting: GPU and wall (render + wait) medians; error against the full-resolution \
            reference and against the f64 reference of the same mixed cut with the same smoothing \
            (GPU = reference check).\n\n\
            | setting | GPU ms | wall ms | vs full res: PSNR dB | RMSE | max abs | vs same cut: PSNR dB | RMSE | max abs |\n\
            | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n";
    for row in &r.rows {
        let _ = writeln!(
            out,
            "| {} | {:.1} | {:.1} | {:.1} | {:.3} | {} | {:.1} | {:.3} | {} |",
            row.variant.label(),
            row.gpu_ms,
            row.wall_ms,
            row.vs_full.psnr_db,
            row.vs_full.rmse,
            row.vs_full.max_abs_error,
            row.vs_same.psnr_db,
            row.vs_same.rmse,
            row.vs_same.max_abs_error
        );
    }
    out
}

/// Points on both sides (±1e-6 voxel) of every face between pages of different levels, on an
/// 8×8 grid per face reaching to within a voxel of its edges, where face, edge and corner bands
/// meet: the largest jump of the (smoothed or discontinuous) field there, in physical units.
fn max_level_face_jump(
    bricks: &ResidentBricks,
    table: &PageTable,
    v: &Volume,
    smooth: bool,
) -> f64 {
    let masks = smooth.then(|| transition_masks(table));
    let dims = v.geometry.dims;
    let value = |p: DVec3| {
        strata_render::model::field::sample_field(bricks, table, masks.as_deref(), dims, p)
            .map(|s| v.mapping.physical(s.value))
    };
    let mut worst = 0.0f64;
    for_each_level_face(table, |page, axis| {
        let plane = 32.0 * (page[axis] + 1) as f64 - 0.5;
        for i in 0..8 {
            for j in 0..8 {
                let mut p = DVec3::ZERO;
                let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
                p[axis] = plane;
                p[a] = 32.0 * page[a] as f64 - 0.5 + 0.3 + 31.4 * i as f64 / 7.0;
                p[b] = 32.0 * page[b] as f64 - 0.5 + 0.3 + 31.4 * j as f64 / 7.0;
                let mut e = DVec3::ZERO;
                e[axis] = 1e-6;
                if let (Some(lo), Some(hi)) = (value(p - e), value(p + e)) {
                    worst = worst.max((hi - lo).abs());
                }
            }
        }
    });
    worst
}

/// Calls `f(page, axis)` for every page whose +axis neighbour has another level.
fn for_each_level_face(table: &PageTable, mut f: impl FnMut([u32; 3], usize)) {
    let d = table.page_dims;
    for i in 0..table.entries.len() {
        let page = table.page_of_linear(i);
        for axis in 0..3 {
            if page[axis] + 1 >= d[axis] {
                continue;
            }
            let mut other = page;
            other[axis] += 1;
            let (a, b) = (table.get(page), table.get(other));
            if a.resident && b.resident && a.level != b.level {
                f(page, axis);
            }
        }
    }
}

fn write_csv(path: &Path, r: &Report) -> Result<()> {
    let mut out = String::from(
        "input,dims,transition_fraction,smooth,shaded,gpu_median_ms,wall_median_ms,timing_source,\
         rmse_vs_full,psnr_vs_full_db,max_abs_vs_full,rmse_vs_same_cut,psnr_vs_same_cut_db,max_abs_vs_same_cut\n",
    );
    for row in &r.rows {
        let _ = writeln!(
            out,
            "{},{}x{}x{},{:.4},{},{},{:.3},{:.3},{},{:.4},{:.2},{},{:.4},{:.2},{}",
            r.name,
            r.dims[0],
            r.dims[1],
            r.dims[2],
            r.fraction,
            row.variant.smooth,
            row.variant.shaded,
            row.gpu_ms,
            row.wall_ms,
            r.timing,
            row.vs_full.rmse,
            row.vs_full.psnr_db,
            row.vs_full.max_abs_error,
            row.vs_same.rmse,
            row.vs_same.psnr_db,
            row.vs_same.max_abs_error
        );
    }
    std::fs::write(path, out).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn markdown_has_the_paper_columns() {
        let same = compare_rgba8(&[1, 2, 3, 4], &[1, 2, 3, 4]).unwrap();
        let rows = VARIANTS
            .iter()
            .map(|&variant| Row {
                variant,
                gpu_ms: if variant.smooth { 20.0 } else { 10.0 },
                wall_ms: 30.0,
                vs_full: same,
                vs_same: same,
            })
            .collect();
        let md = markdown(&Report {
            name: "x".into(),
            dims: [8, 8, 8],
            fraction: 0.25,
            level0_nodes: 1,
            level1_nodes: 2,
            width: 4,
            height: 4,
            frames: 3,
            adapter: "a".into(),
            timing: "GpuTimestamps".into(),
            rows,
            seam_jump: (312.5, 1e-4),
        });
        assert!(
            md.contains("312.500 discontinuous and 1.0e-4 smooth"),
            "{md}"
        );
        assert!(
            md.contains("| x | 8 × 8 × 8 | 25 % | 10.0 | 10.0 | 20.0 | 20.0 | 2.00 | 2.00 |"),
            "{md}"
        );
    }
}
