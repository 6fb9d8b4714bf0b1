//! `strata bench accuracy`: what accuracy costs in time. Sweeps the quality knobs of one view
//! (step length, pre-integration, octree level as the loader's quality factor picks it,
//! jitter, shading), and for each setting measures the frame time (median of N, render and
//! wait, on whatever adapter is found) and the error against the f64 CPU reference of the
//! same view at full resolution (RMSE, PSNR, max abs error over RGBA8). Writes a CSV, a
//! markdown table and a PNG plot of error against time with the Pareto front marked.
//!
//! All settings render the same camera, so the only differences are the knobs. The
//! reference integrates level 0 at 1/16 voxel; shaded settings are compared with a shaded
//! reference.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use strata_loader::store_volume::{classify_empty, load_uniform_cut, page_table_for_cut, GpuCut};
use strata_loader::ResidentBricks;
use strata_render::adaptive::{block_oracle, AdaptiveConfig, AdaptivePass};
use strata_render::{
    compare_rgba8, Camera, GpuContext, PageTable, RenderMode, RenderSettings, Shading,
};

use super::common::{bench_camera, median, open_input, reference_rgba, view_split, Volume};
use crate::cmd_render::parse_size;

pub struct Options {
    /// A store, or the word `phantom` for a generated CT phantom of `phantom_size`³.
    pub input: String,
    pub phantom_size: u64,
    pub size: String,
    pub frames: usize,
    pub tf: Option<String>,
    pub out_dir: PathBuf,
}

/// One point of the sweep.
#[derive(Clone, Debug)]
struct Knobs {
    family: &'static str,
    step: f64,
    preintegrated: bool,
    level: u8,
    /// The mixed level-0/1 cut of `strata bench transitions` (about 25 % transition nodes)
    /// instead of a uniform level.
    mixed: bool,
    smooth: bool,
    jitter: bool,
    shading: bool,
    /// Step chosen by the time-critical controller for this frame time.
    target_ms: Option<f64>,
    /// The adaptive pass (adaptive sampling in 3D) with its per-block oracle at this ε.
    adaptive_epsilon: Option<f64>,
}

impl Knobs {
    fn label(&self) -> String {
        let mut s = format!("step {}", self.step);
        if self.preintegrated {
            s += " preint";
        }
        if self.mixed {
            s += if self.smooth {
                " mixed 0/1 smooth"
            } else {
                " mixed 0/1 seams"
            };
        } else if self.level > 0 {
            let _ = write!(s, " level {}", self.level);
        }
        if let Some(ms) = self.target_ms {
            let _ = write!(s, " (target {ms:.0} ms)");
        }
        if let Some(e) = self.adaptive_epsilon {
            let _ = write!(s, " adaptive ε {e}");
        }
        if self.jitter {
            s += " jitter";
        }
        if self.shading {
            s += " shaded";
        }
        s
    }
}

struct Row {
    knobs: Knobs,
    median_ms: f64,
    rmse: f64,
    psnr_db: f64,
    max_abs: u8,
    pareto: bool,
}

fn sweep() -> Vec<Knobs> {
    let base = Knobs {
        family: "step",
        step: 0.5,
        preintegrated: false,
        level: 0,
        mixed: false,
        smooth: true,
        jitter: false,
        shading: false,
        target_ms: None,
        adaptive_epsilon: None,
    };
    let mut knobs = Vec::new();
    for &step in &[0.125, 0.25, 0.5, 1.0, 2.0, 4.0] {
        knobs.push(Knobs {
            step,
            ..base.clone()
        });
        knobs.push(Knobs {
            family: "step + pre-integration",
            step,
            preintegrated: true,
            ..base.clone()
        });
    }
    for level in [1, 2] {
        knobs.push(Knobs {
            family: "coarser level (LOD factor)",
            level,
            ..base.clone()
        });
        knobs.push(Knobs {
            family: "coarser level (LOD factor)",
            level,
            step: 1.0,
            ..base.clone()
        });
    }
    for smooth in [false, true] {
        for shading in [false, true] {
            knobs.push(Knobs {
                family: "mixed levels: smooth transitions",
                mixed: true,
                smooth,
                shading,
                ..base.clone()
            });
        }
    }
    for &step in &[1.0, 2.0, 4.0] {
        knobs.push(Knobs {
            family: "jitter",
            step,
            jitter: true,
            ..base.clone()
        });
    }
    for &step in &[0.25, 0.5, 1.0, 2.0] {
        knobs.push(Knobs {
            family: "shaded",
            step,
            shading: true,
            ..base.clone()
        });
    }
    knobs
}

/// A point is on the Pareto front when no other point is at least as fast and at least as
/// accurate, and strictly better in one of the two.
fn mark_pareto(rows: &mut [Row]) {
    let points: Vec<(f64, f64)> = rows.iter().map(|r| (r.median_ms, r.rmse)).collect();
    for (i, row) in rows.iter_mut().enumerate() {
        let (t, e) = points[i];
        row.pareto = !points
            .iter()
            .enumerate()
            .any(|(j, &(tj, ej))| j != i && tj <= t && ej <= e && (tj < t || ej < e));
    }
}

/// The cut of one uniform level, its bricks and GPU resources.
struct LevelCut {
    table: PageTable,
    bricks: ResidentBricks,
    gpu: GpuCut,
}

fn load_level(ctx: &GpuContext, v: &Volume, level: u8) -> Result<LevelCut> {
    let (table, bricks) = load_uniform_cut(&v.store, &v.geometry, v.mapping, &v.tf_table, level)?;
    let gpu = GpuCut::upload(ctx, &bricks, &table, v.geometry.page_dims(), &v.tf_table)?;
    Ok(LevelCut { table, bricks, gpu })
}

/// The mixed cut of `strata bench transitions` for this view.
fn load_mixed(ctx: &GpuContext, v: &Volume, camera: &Camera) -> Result<LevelCut> {
    let split = view_split(v, camera, 0.25);
    let mut table = page_table_for_cut(&v.store, &v.geometry, |p| split.level_of(p));
    classify_empty(&v.store, &mut table, v.mapping, &v.tf_table);
    let bricks = ResidentBricks::load(&v.store, &table)?;
    let gpu = GpuCut::upload(ctx, &bricks, &table, v.geometry.page_dims(), &v.tf_table)?;
    Ok(LevelCut { table, bricks, gpu })
}

/// One frame of `cut`, waited for but not read back: what the frame-time columns measure.
fn render_and_wait(
    ctx: &GpuContext,
    cut: &mut LevelCut,
    v: &Volume,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<()> {
    let scene = strata_render::Scene {
        cache: &cut.gpu.cache,
        page_table: &cut.gpu.page_table,
        transfer_function: &cut.gpu.transfer_function,
        geometry: &v.geometry,
        mapping: v.mapping,
        camera,
        settings,
    };
    Ok(cut.gpu.raycaster.render_and_wait(ctx, &scene)?)
}

/// Lets the time-critical sampling-rate controller (time-critical paper Eq. 1) settle on this
/// view for `target_ms` per frame; returns the rate (samples per finest voxel) it chose.
fn controller_rate(
    ctx: &GpuContext,
    v: &Volume,
    camera: &Camera,
    cut: &mut LevelCut,
    target_ms: f64,
    settings_for_rate: impl Fn(f64) -> RenderSettings,
) -> Result<f64> {
    let config = strata_render::ControllerConfig {
        target_fps: 1000.0 / target_ms,
        ..Default::default()
    };
    let mut controller = strata_render::SamplingRateController::new(config, 2.0);
    for _ in 0..16 {
        let rate = controller.rate();
        let settings = settings_for_rate(rate);
        let t = Instant::now();
        render_and_wait(ctx, cut, v, camera, &settings)?;
        controller.observe(t.elapsed().as_secs_f64() * 1e3, rate);
    }
    Ok(controller.rate())
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
    let settings_of = |k: &Knobs| RenderSettings {
        width,
        height,
        mode: RenderMode::Dvr,
        quality: k.step,
        jitter: k.jitter,
        preintegrated: k.preintegrated,
        shading: k.shading.then(Shading::default),
        smooth_transitions: k.smooth,
        ..RenderSettings::default()
    };

    let mut knobs = sweep();
    let mut cuts: HashMap<(u8, bool), LevelCut> = HashMap::new();
    let root = (v.store.layout().level_count() - 1) as u8;
    if root == 0 {
        knobs.retain(|k| !k.mixed);
    }
    for k in &knobs {
        let key = (k.level.min(root), k.mixed);
        if let std::collections::hash_map::Entry::Vacant(e) = cuts.entry(key) {
            e.insert(if k.mixed {
                load_mixed(&ctx, &v, &camera)?
            } else {
                load_level(&ctx, &v, key.0)?
            });
        }
    }

    // Ground truth, unshaded and shaded: level 0 at 1/16 voxel in f64.
    let mut references = HashMap::new();
    let finest = cuts.get(&(0, false)).context("level 0 cut missing")?;
    for shading in [false, true] {
        let t = Instant::now();
        let settings = RenderSettings {
            jitter: false,
            ..settings_of(&Knobs {
                step: 0.5,
                shading,
                ..knobs[0].clone()
            })
        };
        let reference = reference_rgba(&v, &finest.bricks, &finest.table, &camera, &settings)?;
        eprintln!(
            "reference ({}) in {:.1} s",
            if shading { "shaded" } else { "unshaded" },
            t.elapsed().as_secs_f64()
        );
        references.insert(shading, reference);
    }

    let measure = |cut: &mut LevelCut, k: &Knobs| -> Result<Row> {
        let settings = settings_of(k);
        // Error from one frame (jittered frames differ; frame 0's pattern stands for all).
        let frame = cut
            .gpu
            .render_blocking(&ctx, &v.geometry, v.mapping, &camera, &settings)?;
        let reference = references.get(&k.shading).context("reference missing")?;
        let c = compare_rgba8(&frame.rgba, reference)?;
        let mut times = Vec::with_capacity(options.frames);
        for i in 0..options.frames {
            let settings = RenderSettings {
                frame_index: i as u32,
                ..settings.clone()
            };
            let t = Instant::now();
            render_and_wait(&ctx, cut, &v, &camera, &settings)?;
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        let row = Row {
            knobs: k.clone(),
            median_ms: median(times),
            rmse: c.rmse,
            psnr_db: c.psnr_db,
            max_abs: c.max_abs_error,
            pareto: false,
        };
        eprintln!(
            "{:<28} {:>8.1} ms  PSNR {:>5.1} dB  RMSE {:>6.3}  max {:>3}",
            row.knobs.label(),
            row.median_ms,
            row.psnr_db,
            row.rmse,
            row.max_abs
        );
        Ok(row)
    };
    let mut rows = Vec::new();
    for k in &knobs {
        let cut = cuts
            .get_mut(&(k.level.min(root), k.mixed))
            .context("cut missing")?;
        rows.push(measure(cut, k)?);
    }
    // The time-critical controller's choice for two frame budgets, three quarters and half of
    // the step-0.5 frame measured above: its rows show where on the error/time curve it lands.
    let base_ms = rows[knobs
        .iter()
        .position(|k| k.family == "step" && k.step == 0.5)
        .context("step 0.5 row missing")?]
    .median_ms;
    for fraction in [0.75, 0.5] {
        let target_ms = base_ms * fraction;
        let cut = cuts.get_mut(&(0, false)).context("level 0 cut missing")?;
        let rate = controller_rate(&ctx, &v, &camera, cut, target_ms, |rate| {
            settings_of(&Knobs {
                step: 1.0 / rate,
                jitter: rate < 1.0,
                ..knobs[0].clone()
            })
        })?;
        let k = Knobs {
            family: "time-critical target",
            step: (1.0 / rate * 1000.0).round() / 1000.0,
            jitter: rate < 1.0,
            target_ms: Some(target_ms),
            ..knobs[0].clone()
        };
        rows.push(measure(cut, &k)?);
    }
    // Adaptive sampling in 3D (its own pass, pre-integrated, l_max 3) at the base step on the
    // finest cut, at two oracle ε: where it lands on the same error/time plane.
    {
        let cut = cuts.get_mut(&(0, false)).context("level 0 cut missing")?;
        let mut pass = AdaptivePass::new(&ctx, &cut.gpu.cache);
        for epsilon in [0.005, 0.02] {
            let k = Knobs {
                family: "adaptive sampling (3D)",
                adaptive_epsilon: Some(epsilon),
                preintegrated: true,
                step: 0.5,
                ..knobs[0].clone()
            };
            let settings = settings_of(&k);
            let config = AdaptiveConfig::default();
            pass.set_oracle(
                &ctx,
                &block_oracle(
                    &cut.table,
                    &cut.bricks,
                    v.mapping,
                    &v.tf,
                    epsilon,
                    config.l_max,
                    settings.quality,
                ),
            );
            let scene = strata_render::Scene {
                cache: &cut.gpu.cache,
                page_table: &cut.gpu.page_table,
                transfer_function: &cut.gpu.transfer_function,
                geometry: &v.geometry,
                mapping: v.mapping,
                camera: &camera,
                settings: &settings,
            };
            let frame = pass.render_blocking(&ctx, &scene, &config)?;
            let reference = references.get(&false).context("reference missing")?;
            let c = compare_rgba8(&frame.rgba, reference)?;
            let mut times = Vec::with_capacity(options.frames);
            for _ in 0..options.frames {
                let t = Instant::now();
                pass.render_and_wait(&ctx, &scene, &config)?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
            let row = Row {
                knobs: k,
                median_ms: median(times),
                rmse: c.rmse,
                psnr_db: c.psnr_db,
                max_abs: c.max_abs_error,
                pareto: false,
            };
            eprintln!(
                "{:<28} {:>8.1} ms  PSNR {:>5.1} dB  RMSE {:>6.3}  max {:>3}",
                row.knobs.label(),
                row.median_ms,
                row.psnr_db,
                row.rmse,
                row.max_abs
            );
            rows.push(row);
        }
    }
    mark_pareto(&mut rows);

    std::fs::create_dir_all(&options.out_dir)
        .with_context(|| format!("creating {}", options.out_dir.display()))?;
    let stem = options.out_dir.join(format!("accuracy-{}", v.name));
    let csv = stem.with_extension("csv");
    let md = stem.with_extension("md");
    let png = stem.with_extension("png");
    write_csv(&csv, &rows)?;
    let table = markdown(
        &rows,
        &v.name,
        width,
        height,
        options.frames,
        &ctx.adapter_name(),
    );
    std::fs::write(&md, &table).with_context(|| format!("writing {}", md.display()))?;
    plot(&png, &rows, &v.name)?;
    println!("{table}");
    println!(
        "wrote {}, {}, {}",
        csv.display(),
        md.display(),
        png.display()
    );
    Ok(())
}

fn write_csv(path: &Path, rows: &[Row]) -> Result<()> {
    let mut out = String::from("family,setting,step_voxels,preintegrated,level,jitter,shading,median_ms,rmse,psnr_db,max_abs,pareto\n");
    for r in rows {
        let k = &r.knobs;
        let _ = writeln!(
            out,
            "{},{},{},{},{},{},{},{:.3},{:.4},{:.2},{},{}",
            k.family,
            k.label(),
            k.step,
            k.preintegrated,
            k.level,
            k.jitter,
            k.shading,
            r.median_ms,
            r.rmse,
            r.psnr_db,
            r.max_abs,
            r.pareto
        );
    }
    std::fs::write(path, out).with_context(|| format!("writing {}", path.display()))
}

fn markdown(
    rows: &[Row],
    name: &str,
    width: u32,
    height: u32,
    frames: usize,
    adapter: &str,
) -> String {
    let mut out = format!(
        "Accuracy vs time, {name}, {width}×{height} DVR, median of {frames} frames on {adapter}; \
         error against the f64 reference (level 0, 1/16 voxel). ★ = Pareto front.\n\n\
         | setting | family | ms/frame | PSNR dB | RMSE | max abs | front |\n| --- | --- | ---: | ---: | ---: | ---: | :---: |\n"
    );
    for r in rows {
        let _ = writeln!(
            out,
            "| {} | {} | {:.1} | {:.1} | {:.3} | {} | {} |",
            r.knobs.label(),
            r.knobs.family,
            r.median_ms,
            r.psnr_db,
            r.rmse,
            r.max_abs,
            if r.pareto { "★" } else { "" }
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
    let (t_lo, t_hi) = rows.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
        (lo.min(r.median_ms), hi.max(r.median_ms))
    });
    let (e_lo, e_hi) = rows.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
        (lo.min(positive(r.rmse)), hi.max(positive(r.rmse)))
    });
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!("{name}: error vs frame time (DVR)"),
            ("sans-serif", 24),
        )
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(64)
        .build_cartesian_2d(
            (t_lo * 0.8..t_hi * 1.25).log_scale(),
            (e_lo * 0.8..e_hi * 1.25).log_scale(),
        )
        .map_err(draw_error)?;
    chart
        .configure_mesh()
        .x_desc("ms per frame (median)")
        .x_labels(8)
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| format!("{v}"))
        .y_desc("RMSE vs f64 reference (0-255)")
        .label_style(("sans-serif", 15))
        .draw()
        .map_err(draw_error)?;
    let families = [
        "step",
        "step + pre-integration",
        "coarser level (LOD factor)",
        "mixed levels: smooth transitions",
        "jitter",
        "shaded",
        "time-critical target",
        "adaptive sampling (3D)",
    ];
    let colors = [
        BLUE,
        RED,
        GREEN,
        CYAN,
        MAGENTA,
        BLACK,
        RGBColor(230, 130, 0),
        RGBColor(120, 60, 0),
    ];
    for (family, color) in families.iter().zip(colors) {
        let points: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.knobs.family == *family)
            .map(|r| (r.median_ms, positive(r.rmse)))
            .collect();
        chart
            .draw_series(points.iter().map(|&p| Circle::new(p, 5, color.filled())))
            .map_err(draw_error)?
            .label(*family)
            .legend(move |(x, y)| Circle::new((x + 8, y), 5, color.filled()));
    }
    let mut front: Vec<(f64, f64)> = rows
        .iter()
        .filter(|r| r.pareto)
        .map(|r| (r.median_ms, positive(r.rmse)))
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    chart
        .draw_series(LineSeries::new(
            front.clone(),
            ShapeStyle::from(&BLACK.mix(0.6)).stroke_width(2),
        ))
        .map_err(draw_error)?
        .label("Pareto front")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], BLACK.stroke_width(2)));
    chart
        .draw_series(
            front
                .iter()
                .map(|&p| Circle::new(p, 9, BLACK.stroke_width(2))),
        )
        .map_err(draw_error)?;
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

    fn row(ms: f64, rmse: f64) -> Row {
        Row {
            knobs: Knobs {
                family: "step",
                step: 1.0,
                preintegrated: false,
                level: 0,
                mixed: false,
                smooth: true,
                jitter: false,
                shading: false,
                target_ms: None,
                adaptive_epsilon: None,
            },
            median_ms: ms,
            rmse,
            psnr_db: 0.0,
            max_abs: 0,
            pareto: false,
        }
    }

    #[test]
    fn pareto_front_keeps_only_undominated_points() {
        let mut rows = vec![
            row(10.0, 5.0),
            row(20.0, 2.0),
            row(15.0, 6.0),
            row(30.0, 2.0),
            row(5.0, 9.0),
        ];
        mark_pareto(&mut rows);
        let front: Vec<bool> = rows.iter().map(|r| r.pareto).collect();
        // (15, 6) is slower and worse than (10, 5); (30, 2) is slower than (20, 2) at equal error.
        assert_eq!(front, vec![true, true, false, false, true]);
    }

    #[test]
    fn plot_writes_a_png() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.png");
        let mut rows = vec![row(10.0, 5.0), row(20.0, 2.0), row(5.0, 0.0)];
        mark_pareto(&mut rows);
        plot(&path, &rows, "test").unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (900, 600));
        // Not blank: the axes, labels and points draw dark pixels on the white background.
        let dark = img
            .pixels()
            .filter(|p| p.0.iter().all(|&c| c < 100))
            .count();
        assert!(dark > 1000, "{dark} dark pixels");
    }
}
