//! `strata-bench adaptive <store|phantom>`: the analogue of the adaptive-sampling paper's
//! Tables 2 and 3 (adaptive-sampling-3d §4). One view at 512² (by default), rendered by
//! - the existing raycaster (classic and pre-integrated, at the same step),
//! - the adaptive pass with d ≡ 1 (the paper's "min." oracle: the worst-case overhead),
//! - the adaptive pass with the per-node oracle at the first ε and the per-block oracle
//!   (block_oracle.rs) at a sweep of ε,
//! - and for MIP the raycaster, adaptive d ≡ 1 and the block oracle at the first ε (against
//!   the f64 MIP reference, ratios to the MIP raycaster),
//! - and shaded DVR with smooth level transitions over a mixed level-0/level-1 cut (where a
//!   sample costs most) for the raycaster, adaptive d ≡ 1 and the block oracle at the first ε
//!   (against the f64 reference of that cut, ratios to the shaded raycaster),
//! - and DVR lit by the key light with exact shadows and single scattering (issue 37 item 4:
//!   "shadows + scattering on") for the raycaster, adaptive d ≡ 1 and the block oracle at
//!   every ε, once bounding the opacity's change and once the lit colour's
//!   (`OracleTarget`: before and after the lit oracle, in the same run), against the
//!   raycaster's image at a quarter of the step, same shadow step (an f64 reference with a
//!   shadow ray per fine step is quadratic per ray: hours at 256³), ratios to the shadowed
//!   raycaster; the adaptive rows also report their shadow rays (one per lit level-0
//!   segment). With `--shadowed-only` the bench renders this group alone; `--tf
//!   ct-soft-tissue` gives the scene with many semi-transparent lit samples,
//!
//! each with its sampling operations (volume samples), synthesis operations (pyramid
//! interpolations; the adaptive pass's own overhead), apron samples (what the tiling adds),
//! median frame time and the ratio to the raycaster's, measured in the same run, and PSNR /
//! RMSE against the f64 reference (level 0 at 1/16 voxel). Writes a CSV, a markdown table and
//! a PNG plot of error against sampling operations.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use strata_loader::store_volume::{
    classify_empty, load_uniform_cut, page_table_for_cut, GpuCut, ResidentBricks,
};
use strata_render::passes::adaptive::{
    block_oracle, block_oracle_with, oracle_for_cut, AdaptiveConfig, AdaptivePass, OracleKind,
    OracleTarget,
};
use strata_render::{
    compare_rgba8, Camera, FrameInputs, GpuContext, KeyLight, LightDirection, RenderMode,
    RenderSettings, Scattering, Shading, ShadowMode, Shadows,
};
use strata_types::BrickId;

use super::common::{bench_camera, median, open_input, reference_rgba, Volume};
use strata_viewer::export::parse_size;

pub struct Options {
    pub input: String,
    pub phantom_size: u64,
    pub size: String,
    pub frames: usize,
    pub tf: Option<String>,
    /// Base step (slice spacing) in finest voxels.
    pub step: f64,
    /// ε values of the oracle sweep.
    pub epsilons: Vec<f64>,
    pub l_max: u32,
    pub tile: u32,
    pub out_dir: PathBuf,
    /// Only the exact-shadow group (shadowed_rows).
    pub shadowed_only: bool,
}

#[derive(Clone)]
struct Row {
    setting: String,
    samples: u64,
    apron_samples: u64,
    syntheses: u64,
    /// Slices marched summed over tiles (adaptive rows; the raycaster has none).
    tile_slices: u64,
    /// Shadow rays traced (adaptive rows with exact shadows; the raycaster has no counter).
    shadow_rays: u64,
    median_ms: f64,
    rmse: f64,
    psnr_db: f64,
}

pub fn run(options: Options) -> Result<()> {
    if options.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let (width, height) = parse_size(&options.size)?;
    let v = open_input(&options.input, options.phantom_size, options.tf.as_deref())?;
    let ctx = GpuContext::headless()?;
    eprintln!("GPU: {}", ctx.adapter_name());
    let camera = bench_camera(&v.geometry);
    let (table, bricks) = load_uniform_cut(&v.store, &v.geometry, v.mapping, &v.tf_table, 0)?;
    let mut cut = GpuCut::upload(&ctx, &bricks, &table, v.geometry.page_dims(), &v.tf_table)?;
    let base = RenderSettings {
        width,
        height,
        mode: RenderMode::Dvr,
        quality: options.step,
        jitter: false,
        count_samples: true,
        ..RenderSettings::default()
    };
    let mut rows = Vec::new();
    if options.shadowed_only {
        shadowed_rows(
            &ctx, &v, &mut cut, &camera, &base, &bricks, &table, &options, &mut rows,
        )?;
        return write_outputs(&options, &rows, &v.name, width, height, &ctx);
    }
    let t = Instant::now();
    let reference = reference_rgba(&v, &bricks, &table, &camera, &base)?;
    eprintln!("reference in {:.1} s", t.elapsed().as_secs_f64());

    for preintegrated in [false, true] {
        let settings = RenderSettings {
            preintegrated,
            ..base.clone()
        };
        let setting = format!(
            "raycaster step {}{}",
            options.step,
            if preintegrated { " preint" } else { "" }
        );
        rows.push(raycaster_row(
            &ctx,
            &mut cut,
            &v,
            &camera,
            &settings,
            &reference,
            options.frames,
            setting,
        )?);
        report(rows.last());
    }

    // MIP: the raycaster's lean march here, the adaptive pass with d ≡ 1 and with the block
    // oracle at the first ε below, against the f64 MIP reference (its own group of ratios).
    let mip = RenderSettings {
        mode: RenderMode::Mip,
        ..base.clone()
    };
    let mip_reference = reference_rgba(&v, &bricks, &table, &camera, &mip)?;
    rows.push(raycaster_row(
        &ctx,
        &mut cut,
        &v,
        &camera,
        &mip,
        &mip_reference,
        options.frames,
        format!("MIP raycaster step {}", options.step),
    )?);
    report(rows.last());

    let mut pass = AdaptivePass::new(&ctx, &cut.cache);
    // (label, oracle, ε, tile slice ranges, idle-slice skipping, MIP)
    let mut configs = vec![(
        "adaptive d ≡ 1".to_string(),
        OracleKind::Constant(1.0),
        0.0,
        false,
        true,
        false,
    )];
    if let Some(&e) = options.epsilons.first() {
        // The coarser per-node oracle at the first ε, for comparison.
        configs.push((
            format!("adaptive per-node ε {e}"),
            OracleKind::PerNode,
            e,
            true,
            true,
            false,
        ));
    }
    for (i, &e) in options.epsilons.iter().enumerate() {
        configs.push((
            format!("adaptive ε {e}"),
            OracleKind::PerBlock,
            e,
            true,
            true,
            false,
        ));
        // The first ε once more without idle-slice skipping, and marching every slice of
        // every tile: what skipping and the tile slice ranges save (same image, bit for bit).
        if i == 0 {
            configs.push((
                format!("adaptive ε {e}, no idle-slice skipping"),
                OracleKind::PerBlock,
                e,
                true,
                false,
                false,
            ));
            configs.push((
                format!("adaptive ε {e}, every slice"),
                OracleKind::PerBlock,
                e,
                false,
                false,
                false,
            ));
        }
    }
    configs.push((
        "MIP adaptive d ≡ 1".to_string(),
        OracleKind::Constant(1.0),
        0.0,
        true,
        true,
        true,
    ));
    if let Some(&e) = options.epsilons.first() {
        configs.push((
            format!("MIP adaptive ε {e}"),
            OracleKind::PerBlock,
            e,
            true,
            true,
            true,
        ));
    }
    for (label, oracle, epsilon, tile_slice_ranges, skip_idle_slices, is_mip_row) in configs {
        let config = AdaptiveConfig {
            l_max: options.l_max,
            tile: options.tile,
            oracle,
            tile_slice_ranges,
            skip_idle_slices,
        };
        if oracle == OracleKind::PerBlock {
            let t = Instant::now();
            let distances = block_oracle(
                &table,
                &bricks,
                v.mapping,
                &v.tf,
                epsilon,
                options.l_max,
                options.step,
            );
            eprintln!(
                "block oracle ε {epsilon}: {} blocks in {:.0} ms",
                distances.len(),
                t.elapsed().as_secs_f64() * 1e3
            );
            pass.set_oracle(&ctx, &distances);
        } else if oracle == OracleKind::PerNode {
            let distances = oracle_for_cut(
                &table,
                v.mapping,
                |level, node| {
                    v.store
                        .node(BrickId::new(level, node))
                        .map(|n| (n.min, n.max))
                },
                &v.tf,
                epsilon,
                options.l_max,
                options.step,
            );
            pass.set_oracle(&ctx, &distances);
        }
        let (settings, expected) = if is_mip_row {
            (&mip, &mip_reference)
        } else {
            (&base, &reference)
        };
        let scene = cut.scene(&v.geometry, v.mapping, &camera, settings);
        let label = format!("{label} (l_max {}, tile {})", options.l_max, options.tile);
        rows.push(adaptive_row(
            &ctx,
            &mut pass,
            &scene,
            &config,
            expected,
            options.frames,
            label,
        )?);
        report(rows.last());
    }
    shaded_rows(&ctx, &v, &camera, &base, &options, &mut rows)?;
    shadowed_rows(
        &ctx, &v, &mut cut, &camera, &base, &bricks, &table, &options, &mut rows,
    )?;
    write_outputs(&options, &rows, &v.name, width, height, &ctx)
}

/// The CSV, markdown table and plot of `rows`.
fn write_outputs(
    options: &Options,
    rows: &[Row],
    name: &str,
    width: u32,
    height: u32,
    ctx: &GpuContext,
) -> Result<()> {
    let mut rows: Vec<&Row> = rows.iter().collect();
    // DVR rows first, then MIP's, the shaded and the shadowed ones (each group starts with
    // its raycaster).
    rows.sort_by_key(|r| group(r).1);
    let rows: Vec<Row> = rows.into_iter().cloned().collect();
    let v_name = name;

    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating {}", options.out_dir.display()))?;
    let stem = options.out_dir.join(format!("adaptive-{v_name}"));
    let (csv, md, png) = (
        stem.with_extension("csv"),
        stem.with_extension("md"),
        stem.with_extension("png"),
    );
    write_csv(&csv, &rows)?;
    let table_md = markdown(
        &rows,
        v_name,
        width,
        height,
        options.frames,
        &ctx.adapter_name(),
    );
    std::fs::write(&md, &table_md).with_context(|| format!("writing {}", md.display()))?;
    plot(&png, &rows, v_name)?;
    println!("{table_md}");
    println!(
        "wrote {}, {}, {}",
        csv.display(),
        md.display(),
        png.display()
    );
    Ok(())
}

/// Shaded DVR with smooth level transitions over a mixed cut (level 0 where x is below the
/// middle of the volume, level 1 beyond, so the transition band crosses the view): where a
/// sample costs most (a gradient of six more fetches, each blended across the band), the
/// issue's frame-time case. The raycaster, the adaptive pass with d ≡ 1 and with the block
/// oracle at the first ε, against the f64 reference of the same cut and settings.
fn shaded_rows(
    ctx: &GpuContext,
    v: &Volume,
    camera: &Camera,
    base: &RenderSettings,
    options: &Options,
    rows: &mut Vec<Row>,
) -> Result<()> {
    let half = v.geometry.page_dims()[0].div_ceil(2);
    let mut table = page_table_for_cut(&v.store, &v.geometry, |page| u8::from(page[0] >= half));
    classify_empty(&v.store, &mut table, v.mapping, &v.tf_table);
    let bricks = ResidentBricks::load(&v.store, &table)?;
    let mut cut = GpuCut::upload(ctx, &bricks, &table, v.geometry.page_dims(), &v.tf_table)?;
    let settings = RenderSettings {
        shading: Some(Shading::default()),
        smooth_transitions: true,
        ..base.clone()
    };
    let reference = reference_rgba(v, &bricks, &table, camera, &settings)?;
    rows.push(raycaster_row(
        ctx,
        &mut cut,
        v,
        camera,
        &settings,
        &reference,
        options.frames,
        format!("shaded raycaster step {}", options.step),
    )?);
    report(rows.last());
    let mut pass = AdaptivePass::new(ctx, &cut.cache);
    let mut configs = vec![(
        "shaded adaptive d ≡ 1".to_string(),
        OracleKind::Constant(1.0),
        0.0,
    )];
    if let Some(&e) = options.epsilons.first() {
        configs.push((format!("shaded adaptive ε {e}"), OracleKind::PerBlock, e));
    }
    for (label, oracle, epsilon) in configs {
        if oracle == OracleKind::PerBlock {
            let distances = block_oracle(
                &table,
                &bricks,
                v.mapping,
                &v.tf,
                epsilon,
                options.l_max,
                options.step,
            );
            pass.set_oracle(ctx, &distances);
        }
        let config = AdaptiveConfig {
            l_max: options.l_max,
            tile: options.tile,
            oracle,
            ..AdaptiveConfig::default()
        };
        let scene = cut.scene(&v.geometry, v.mapping, camera, &settings);
        let label = format!("{label} (l_max {}, tile {})", options.l_max, options.tile);
        rows.push(adaptive_row(
            ctx,
            &mut pass,
            &scene,
            &config,
            &reference,
            options.frames,
            label,
        )?);
        report(rows.last());
    }
    Ok(())
}

/// DVR lit by the key light (from the camera's upper right) with exact shadows at one voxel:
/// the raycaster, the adaptive pass with d ≡ 1 and with the block oracle at each ε, against
/// the raycaster's image at a quarter of the step, same shadow step (issue 37 item 4:
/// the adaptive pass traces one shadow ray per lit level-0 segment, the raycaster one per lit
/// sample).
#[allow(clippy::too_many_arguments)]
fn shadowed_rows(
    ctx: &GpuContext,
    v: &Volume,
    cut: &mut GpuCut,
    camera: &Camera,
    base: &RenderSettings,
    bricks: &ResidentBricks,
    table: &strata_render::PageTable,
    options: &Options,
    rows: &mut Vec<Row>,
) -> Result<()> {
    let settings = RenderSettings {
        shading: Some(Shading::default()),
        light: KeyLight {
            direction: LightDirection::Camera([0.6, 0.7, 0.4]),
            intensity: 1.0,
        },
        shadows: Shadows {
            mode: ShadowMode::Exact,
            step: 1.0,
            ..Shadows::default()
        },
        // The goal is stated with shadows + scattering on (the raycast bench's
        // scattering row: g 0.5, blend 0.5).
        scattering: Some(Scattering { g: 0.5, blend: 0.5 }),
        ..base.clone()
    };
    // The shadow rays keep their step: both passes trace the same shadow-ray model, whose
    // own step error (measured: 23.5 dB for the raycaster against a quarter shadow step on
    // the 256³ phantom) would otherwise swamp what the primary sampling does.
    let fine = RenderSettings {
        quality: settings.quality / 4.0,
        ..settings.clone()
    };
    let t = Instant::now();
    let reference = cut
        .render_blocking(ctx, &v.geometry, v.mapping, camera, &fine)?
        .rgba;
    eprintln!(
        "shadowed reference (raycaster at step {}, shadow step {}) in {:.1} s",
        fine.quality,
        fine.shadows.step,
        t.elapsed().as_secs_f64()
    );
    rows.push(raycaster_row(
        ctx,
        cut,
        v,
        camera,
        &settings,
        &reference,
        options.frames,
        format!("shadowed raycaster step {}", options.step),
    )?);
    report(rows.last());
    let mut pass = AdaptivePass::new(ctx, &cut.cache);
    let mut configs = vec![(
        "shadowed adaptive d ≡ 1".to_string(),
        OracleKind::Constant(1.0),
        0.0,
        OracleTarget::Opacity,
    )];
    for &e in &options.epsilons {
        for (name, target) in [
            ("opacity", OracleTarget::Opacity),
            ("lit colour", OracleTarget::for_settings(&settings)),
        ] {
            configs.push((
                format!("shadowed adaptive ε {e} {name} oracle"),
                OracleKind::PerBlock,
                e,
                target,
            ));
        }
    }
    for (label, oracle, epsilon, target) in configs {
        if oracle == OracleKind::PerBlock {
            let distances = block_oracle_with(
                table,
                bricks,
                v.mapping,
                &v.tf,
                epsilon,
                options.l_max,
                options.step,
                target,
            );
            pass.set_oracle(ctx, &distances);
        }
        let config = AdaptiveConfig {
            l_max: options.l_max,
            tile: options.tile,
            oracle,
            ..AdaptiveConfig::default()
        };
        let scene = cut.scene(&v.geometry, v.mapping, camera, &settings);
        let label = format!("{label} (l_max {}, tile {})", options.l_max, options.tile);
        rows.push(adaptive_row(
            ctx,
            &mut pass,
            &scene,
            &config,
            &reference,
            options.frames,
            label,
        )?);
        report(rows.last());
    }
    Ok(())
}

/// One raycaster frame's samples and error against `reference`, and the median time of
/// `frames` more.
#[allow(clippy::too_many_arguments)]
fn raycaster_row(
    ctx: &GpuContext,
    cut: &mut GpuCut,
    v: &Volume,
    camera: &Camera,
    settings: &RenderSettings,
    reference: &[u8],
    frames: usize,
    setting: String,
) -> Result<Row> {
    let frame = cut.render_blocking(ctx, &v.geometry, v.mapping, camera, settings)?;
    let c = compare_rgba8(&frame.rgba, reference)?;
    let mut times = Vec::new();
    for _ in 0..frames {
        // Field by field: the raycaster below is borrowed mutably beside these.
        let scene = FrameInputs {
            cache: &cut.cache,
            page_table: &cut.page_table,
            transfer_function: &cut.transfer_function,
            geometry: &v.geometry,
            mapping: v.mapping,
            camera,
            settings,
        };
        let t = Instant::now();
        cut.raycaster.render_and_wait(ctx, &scene)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok(Row {
        setting,
        samples: frame.samples.unwrap_or(0),
        apron_samples: 0,
        syntheses: 0,
        tile_slices: 0,
        shadow_rays: 0,
        median_ms: median(times),
        rmse: c.rmse,
        psnr_db: c.psnr_db,
    })
}

/// One adaptive frame's counts and error against `reference`, and the median time of
/// `frames` more.
fn adaptive_row(
    ctx: &GpuContext,
    pass: &mut AdaptivePass,
    scene: &FrameInputs,
    config: &AdaptiveConfig,
    reference: &[u8],
    frames: usize,
    setting: String,
) -> Result<Row> {
    let frame = pass.render_blocking(ctx, scene, config)?;
    if frame.cut_short_invocations > 0 {
        // llvmpipe's shared loop limit (adaptive/gpu.rs module doc): not the algorithm's frame.
        eprintln!(
            "warning: {setting}: the device cut {} invocations' march short; this row's image \
             and counts are not the algorithm's",
            frame.cut_short_invocations
        );
    }
    let c = compare_rgba8(&frame.rgba, reference)?;
    let mut times = Vec::new();
    for _ in 0..frames {
        let t = Instant::now();
        pass.render_and_wait(ctx, scene, config)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok(Row {
        setting,
        samples: frame.total_samples(),
        apron_samples: frame.total_apron_samples(),
        syntheses: frame.total_syntheses(),
        tile_slices: frame.tile_slices,
        shadow_rays: frame.shadow_rays,
        median_ms: median(times),
        rmse: c.rmse,
        psnr_db: c.psnr_db,
    })
}

/// Rows form groups by their setting's first word ("MIP …", "shaded …", the rest DVR); each
/// group's ratios are to its first row (its raycaster). The group's order in the table.
fn group(row: &Row) -> (&'static str, u8) {
    if row.setting.starts_with("MIP ") {
        ("MIP", 1)
    } else if row.setting.starts_with("shaded ") {
        ("shaded", 2)
    } else if row.setting.starts_with("shadowed ") {
        ("shadowed", 3)
    } else {
        ("DVR", 0)
    }
}

fn report(row: Option<&Row>) {
    if let Some(r) = row {
        eprintln!(
            "{:<40} {:>11} samples {:>10} apron {:>11} synth {:>9} tile slices {:>8.1} ms  \
             PSNR {:>5.1} dB",
            r.setting,
            r.samples,
            r.apron_samples,
            r.syntheses,
            r.tile_slices,
            r.median_ms,
            r.psnr_db
        );
        if r.shadow_rays > 0 {
            eprintln!("{:<40} {:>11} shadow rays", "", r.shadow_rays);
        }
    }
}

fn write_csv(path: &Path, rows: &[Row]) -> Result<()> {
    let mut out = String::from(
        "setting,sampling_ops,apron_samples,synthesis_ops,tile_slices,median_ms,rmse,psnr_db\n",
    );
    for r in rows {
        let _ = writeln!(
            out,
            "{},{},{},{},{},{:.3},{:.4},{:.2}",
            r.setting,
            r.samples,
            r.apron_samples,
            r.syntheses,
            r.tile_slices,
            r.median_ms,
            r.rmse,
            r.psnr_db
        );
    }
    std::fs::write(path, out).with_context(|| format!("writing {}", path.display()))
}

fn markdown(rows: &[Row], name: &str, w: u32, h: u32, frames: usize, adapter: &str) -> String {
    let mut out = format!(
        "Adaptive sampling in 3D, {name}, {w}×{h} DVR and MIP, median of {frames} frames on \
         {adapter}; error against the f64 reference of the same mode (level 0, 1/16 voxel). \
         Ratios are to the first row of the same mode (the raycaster), measured in the same \
         run.\n\n\
         | setting | sampling ops | × fewer | apron samples | synthesis ops | tile slices | ms/frame | time ratio | PSNR dB | RMSE |\n\
         | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n"
    );
    for r in rows {
        let base = rows.iter().find(|b| group(b) == group(r));
        let (base_samples, base_ms) =
            base.map_or((1.0, 1.0), |b| (b.samples.max(1) as f64, b.median_ms));
        let _ = writeln!(
            out,
            "| {} | {} | {:.1} | {} | {} | {} | {:.1} | {:.2} | {:.1} | {:.3} |",
            r.setting,
            r.samples,
            base_samples / r.samples.max(1) as f64,
            r.apron_samples,
            r.syntheses,
            r.tile_slices,
            r.median_ms,
            r.median_ms / base_ms.max(1e-9),
            r.psnr_db,
            r.rmse
        );
    }
    out
}

fn plot(path: &Path, rows: &[Row], name: &str) -> Result<()> {
    use plotters::prelude::*;
    plotters::style::register_font(
        "sans-serif",
        FontStyle::Normal,
        epaint_default_fonts::UBUNTU_LIGHT,
    )
    .map_err(|_| anyhow::anyhow!("the bundled plot font did not load"))?;
    let draw_error =
        |e: DrawingAreaErrorKind<_>| anyhow::anyhow!("plotting {}: {e:?}", path.display());
    let root = BitMapBackend::new(path, (900, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(draw_error)?;
    let positive = |x: f64| x.max(1e-3);
    let (s_lo, s_hi) = rows.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
        let s = r.samples.max(1) as f64;
        (lo.min(s), hi.max(s))
    });
    let (e_lo, e_hi) = rows.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
        (lo.min(positive(r.rmse)), hi.max(positive(r.rmse)))
    });
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("{name}: error vs sampling operations (DVR)"),
            ("sans-serif", 24),
        )
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(64)
        .build_cartesian_2d(
            (s_lo * 0.7..s_hi * 1.4).log_scale(),
            (e_lo * 0.8..e_hi * 1.25).log_scale(),
        )
        .map_err(draw_error)?;
    chart
        .configure_mesh()
        .x_desc("sampling operations per frame")
        .x_label_formatter(&|v| format!("{v:.1e}"))
        .y_desc("RMSE vs f64 reference (0-255)")
        .label_style(("sans-serif", 15))
        .draw()
        .map_err(draw_error)?;
    for (family, color) in [("raycaster", BLUE), ("adaptive", RED)] {
        let points: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.setting.starts_with(family))
            .map(|r| (r.samples.max(1) as f64, positive(r.rmse)))
            .collect();
        chart
            .draw_series(points.iter().map(|&p| Circle::new(p, 6, color.filled())))
            .map_err(draw_error)?
            .label(family)
            .legend(move |(x, y)| Circle::new((x + 8, y), 5, color.filled()));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .label_font(("sans-serif", 15))
        .draw()
        .map_err(draw_error)?;
    root.present().map_err(draw_error)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn markdown_reports_ratios_against_the_first_row_of_the_same_group() {
        let row = |setting: &str, samples: u64, ms: f64| Row {
            setting: setting.into(),
            samples,
            apron_samples: 0,
            syntheses: 0,
            tile_slices: 0,
            shadow_rays: 0,
            median_ms: ms,
            rmse: 1.0,
            psnr_db: 48.0,
        };
        let md = markdown(
            &[
                row("raycaster", 1000, 10.0),
                row("adaptive", 100, 5.0),
                row("MIP raycaster", 400, 8.0),
                row("MIP adaptive", 100, 16.0),
                row("shaded raycaster", 500, 40.0),
                row("shaded adaptive", 50, 10.0),
            ],
            "x",
            8,
            8,
            1,
            "cpu",
        );
        assert!(
            md.contains("| adaptive | 100 | 10.0 | 0 | 0 | 0 | 5.0 | 0.50 |"),
            "{md}"
        );
        // MIP rows are measured against the MIP raycaster, not the DVR one.
        assert!(
            md.contains("| MIP adaptive | 100 | 4.0 | 0 | 0 | 0 | 16.0 | 2.00 |"),
            "{md}"
        );
        // And shaded rows against the shaded raycaster.
        assert!(
            md.contains("| shaded adaptive | 50 | 10.0 | 0 | 0 | 0 | 10.0 | 0.25 |"),
            "{md}"
        );
    }
}
