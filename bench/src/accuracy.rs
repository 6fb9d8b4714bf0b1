//! `strata-bench accuracy`: what accuracy costs in time. Sweeps the quality knobs of one view
//! (step length, pre-integration, octree level as the loader's quality factor picks it,
//! jitter, shading), and for each setting measures the frame time (median of N, render and
//! wait, on whatever adapter is found) and the error against the f64 CPU reference of the
//! same view at full resolution (RMSE, PSNR, max abs error over RGBA8). Writes a CSV, a
//! markdown table and a PNG plot of error against time with the Pareto front marked.
//!
//! All settings render the same camera, so the only differences are the knobs. The
//! reference integrates level 0 at 1/16 voxel; shaded settings are compared with a shaded
//! reference.
//!
//! # Cinematic knobs (`--sweep cinematic` or `all`; issue 37)
//! Two key-lit models, lit by the directional key light [`KEY_LIGHT`] (`strata render
//! --light-dir 0.5,0.5,0.7`): **lit** (volumetric shadows, `--shadows`) and **cinematic** (the
//! same plus ambient occlusion and single scattering g = 0.5, `--occlusion`, `--scattering`).
//! Along each: the shadow step of exact shadows (`--shadow-step`), the light cache's
//! resolution (`--shadows cache --light-cache-res`), for the cinematic model the occlusion
//! radius (`--occlusion`, in voxels here), and the progressive mean of N = 1, 4, 16, 64
//! jittered frames of a cheap setting (step 1, shadow step 2; `--progressive N`, the same
//! `render_still`; its time is the whole run of N frames). Each model's rows are compared with
//! the f64 reference of that model (exact shadows at [`REFERENCE_SHADOW_STEP`] / 4 voxel,
//! occlusion over [`REFERENCE_OCCLUSION_VOXELS`]), so a light cache or a smaller radius shows
//! as the error it adds to the converged lit image; a row is never compared with the unlit
//! reference. Points of different models render different images, so the Pareto front is
//! computed per model (one front per model in the table, CSV and plot). Cache rows time the
//! cache's steady state: it is built by the untimed frame that measures the error, and
//! rebuilt only when light, TF or cut change. Figures on lavapipe (64³ phantom, 128², which
//! knob buys what, the fronts, the command): bench/accuracy/cinematic-lavapipe.md.
//!
use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use strata_loader::store_volume::{classify_empty, load_uniform_cut, page_table_for_cut, GpuCut};
use strata_loader::ResidentBricks;
use strata_render::passes::adaptive::{block_oracle, AdaptiveConfig, AdaptivePass};
use strata_render::passes::progressive::render_still;
use strata_render::{
    compare_rgba8, Camera, GpuContext, KeyLight, LightDirection, Occlusion, PageTable, RenderMode,
    RenderSettings, Scattering, Shading, ShadowMode, Shadows,
};

use super::common::{bench_camera, median, open_input, reference_rgba, view_split, Volume};
use strata_viewer::export::parse_size;

/// Which families of settings the sweep renders.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Sweep {
    /// Step, pre-integration, level, mixed cut, jitter, headlight shading, the time-critical
    /// controller and adaptive sampling: unshaded and headlight-shaded DVR.
    Base,
    /// The cinematic knobs only: shadow step, light-cache resolution, occlusion radius and
    /// progressive frame count of the key-lit models (their own f64 references).
    Cinematic,
    /// Both.
    All,
}

pub struct Options {
    /// A store, or the word `phantom` for a generated CT phantom of `phantom_size`³.
    pub input: String,
    pub phantom_size: u64,
    pub size: String,
    pub frames: usize,
    pub tf: Option<String>,
    pub out_dir: PathBuf,
    pub sweep: Sweep,
}

/// The optical model a setting renders, and with it the f64 reference its error is measured
/// against: points of different models render different images, so they are not comparable,
/// and each model has its own Pareto front.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
enum Model {
    /// Emission-absorption DVR, unshaded.
    Dvr,
    /// DVR with Blinn-Phong under the headlight.
    Shaded,
    /// Shaded DVR lit by the directional key light [`KEY_LIGHT`] with volumetric shadows.
    Lit,
    /// [`Model::Lit`] with ambient occlusion and single scattering ([`SCATTERING`]).
    Cinematic,
}

impl Model {
    fn name(self) -> &'static str {
        match self {
            Model::Dvr => "DVR",
            Model::Shaded => "shaded",
            Model::Lit => "lit (key light + shadows)",
            Model::Cinematic => "cinematic (+ occlusion + scattering)",
        }
    }

    fn shading(self) -> bool {
        self != Model::Dvr
    }

    fn key_lit(self) -> bool {
        matches!(self, Model::Lit | Model::Cinematic)
    }
}

/// The key light of the lit models, camera-relative towards the light (`strata render
/// --light-dir 0.5,0.5,0.7`): from the upper right, in front, so shadows fall visibly.
const KEY_LIGHT: [f64; 3] = [0.5, 0.5, 0.7];
/// The cinematic model's scattering (`--scattering 0.5 --scattering-blend 0.5`).
const SCATTERING: Scattering = Scattering { g: 0.5, blend: 0.5 };
/// The lit models' reference: exact shadows at this step (the reference divides it again by
/// `REFERENCE_SHADOW_REFINEMENT`), so every shadow step and light cache of the sweep is
/// measured against the same converged shadows.
const REFERENCE_SHADOW_STEP: f64 = 0.5;
/// The cinematic model's occlusion radius in finest voxels: its reference's, and the largest
/// of the sweep; smaller radii are cheaper truncations of the same occlusion integral.
const REFERENCE_OCCLUSION_VOXELS: f64 = 8.0;
/// Frame counts of the progressive rows (time = all N frames and the mean's readback).
const PROGRESSIVE_FRAMES: [u32; 4] = [1, 4, 16, 64];

/// One point of the sweep.
#[derive(Clone, Debug)]
struct Knobs {
    family: &'static str,
    model: Model,
    step: f64,
    preintegrated: bool,
    level: u8,
    /// The mixed level-0/1 cut of `strata-bench transitions` (about 25 % transition nodes)
    /// instead of a uniform level.
    mixed: bool,
    smooth: bool,
    jitter: bool,
    /// Step chosen by the time-critical controller for this frame time.
    target_ms: Option<f64>,
    /// The adaptive pass (adaptive sampling in 3D) with its per-block oracle at this ε.
    adaptive_epsilon: Option<f64>,
    /// Key-lit models: exact shadow rays or the light cache.
    shadows: ShadowMode,
    /// Key-lit models: shadow (and occlusion) ray step in finest voxels; also the light
    /// cache's rays.
    shadow_step: f64,
    /// Cache shadows: finest voxels per light-cache texel edge.
    cache_res: f64,
    /// Cinematic model: the occlusion radius in finest voxels.
    occlusion_voxels: f64,
    /// The mean of this many jittered frames (`strata render --progressive N`) instead of
    /// one frame.
    progressive: Option<u32>,
}

impl Knobs {
    /// Step 0.5 of level 0, unshaded, no jitter: the point the other settings vary from.
    fn base() -> Self {
        Knobs {
            family: "step",
            model: Model::Dvr,
            step: 0.5,
            preintegrated: false,
            level: 0,
            mixed: false,
            smooth: true,
            jitter: false,
            target_ms: None,
            adaptive_epsilon: None,
            shadows: ShadowMode::Off,
            shadow_step: 1.0,
            cache_res: 2.0,
            occlusion_voxels: REFERENCE_OCCLUSION_VOXELS,
            progressive: None,
        }
    }

    /// The settings the f64 reference of `model` renders (at 1/8 of their step, shadow rays
    /// at 1/4 of theirs): step 0.5, level 0, no jitter; key-lit models with exact shadows at
    /// [`REFERENCE_SHADOW_STEP`] and occlusion over [`REFERENCE_OCCLUSION_VOXELS`].
    fn reference(model: Model) -> Self {
        Knobs {
            family: "reference",
            model,
            shadows: if model.key_lit() {
                ShadowMode::Exact
            } else {
                ShadowMode::Off
            },
            shadow_step: REFERENCE_SHADOW_STEP,
            ..Knobs::base()
        }
    }

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
        if self.model.key_lit() {
            match self.shadows {
                ShadowMode::Cache => {
                    let _ = write!(s, " light cache {}", self.cache_res);
                }
                _ => {
                    let _ = write!(s, " shadow step {}", self.shadow_step);
                }
            }
            if self.model == Model::Cinematic {
                let _ = write!(s, " AO {} vox", self.occlusion_voxels);
            }
        }
        if let Some(n) = self.progressive {
            let _ = write!(s, " progressive ×{n}");
        } else if self.jitter {
            s += " jitter";
        }
        match self.model {
            Model::Dvr => {}
            Model::Shaded => s += " shaded",
            Model::Lit => s += " [lit]",
            Model::Cinematic => s += " [cinematic]",
        }
        s
    }

    /// The frame these knobs render at `width`×`height` of a volume with finest voxel edge
    /// `voxel_mm` (the occlusion radius is in voxels): the settings `strata render` builds
    /// from the same flags.
    fn settings(&self, width: u32, height: u32, voxel_mm: f64) -> RenderSettings {
        let lit = self.model.key_lit();
        let cinematic = self.model == Model::Cinematic;
        RenderSettings {
            width,
            height,
            mode: RenderMode::Dvr,
            quality: self.step,
            jitter: self.jitter || self.progressive.is_some(),
            preintegrated: self.preintegrated,
            shading: self.model.shading().then(Shading::default),
            smooth_transitions: self.smooth,
            light: if lit {
                KeyLight {
                    direction: LightDirection::Camera(KEY_LIGHT),
                    ..KeyLight::default()
                }
            } else {
                KeyLight::default()
            },
            shadows: Shadows {
                mode: if lit { self.shadows } else { ShadowMode::Off },
                step: self.shadow_step,
                cache_res: self.cache_res,
            },
            occlusion: cinematic.then_some(Occlusion {
                radius_mm: self.occlusion_voxels * voxel_mm,
            }),
            scattering: cinematic.then_some(SCATTERING),
            ..RenderSettings::default()
        }
    }
}

struct Row {
    knobs: Knobs,
    /// Median ms per frame; progressive rows: per run of all their frames.
    median_ms: f64,
    rmse: f64,
    psnr_db: f64,
    max_abs: u8,
    pareto: bool,
}

/// The settings `which` renders (the time-critical and adaptive rows of the base sweep are
/// added by [`run`], as they depend on measured times).
fn sweep(which: Sweep) -> Vec<Knobs> {
    let mut knobs = Vec::new();
    if which != Sweep::Cinematic {
        knobs.extend(base_sweep());
    }
    if which != Sweep::Base {
        knobs.extend(cinematic_sweep());
    }
    knobs
}

fn base_sweep() -> Vec<Knobs> {
    let base = Knobs::base();
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
        for model in [Model::Dvr, Model::Shaded] {
            knobs.push(Knobs {
                family: "mixed levels: smooth transitions",
                mixed: true,
                smooth,
                model,
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
            model: Model::Shaded,
            ..base.clone()
        });
    }
    knobs
}

/// The cinematic knobs (issue 37) for the two key-lit models, all at level 0 without jitter
/// unless progressive: the shadow step of exact shadows, the light cache's resolution (shadow
/// step 1), the occlusion radius (cinematic model, shadow step 1), and the progressive mean of
/// N jittered frames of a cheap setting (step 1, shadow step 2: what the mean refines).
fn cinematic_sweep() -> Vec<Knobs> {
    let mut knobs = Vec::new();
    for model in [Model::Lit, Model::Cinematic] {
        let base = Knobs {
            family: "shadow step (exact)",
            model,
            shadows: ShadowMode::Exact,
            ..Knobs::base()
        };
        let shadow_steps: &[f64] = if model == Model::Lit {
            &[0.5, 1.0, 2.0, 4.0]
        } else {
            // Shadow step 1 is the occlusion family's largest radius.
            &[0.5, 2.0]
        };
        for &shadow_step in shadow_steps {
            knobs.push(Knobs {
                shadow_step,
                ..base.clone()
            });
        }
        if model == Model::Cinematic {
            for occlusion_voxels in [2.0, 4.0, REFERENCE_OCCLUSION_VOXELS] {
                knobs.push(Knobs {
                    family: "occlusion radius",
                    occlusion_voxels,
                    ..base.clone()
                });
            }
        }
        let cache_res: &[f64] = if model == Model::Lit {
            &[1.0, 2.0, 4.0, 8.0]
        } else {
            &[2.0, 8.0]
        };
        for &cache_res in cache_res {
            knobs.push(Knobs {
                family: "light-cache resolution",
                shadows: ShadowMode::Cache,
                cache_res,
                ..base.clone()
            });
        }
        for frames in PROGRESSIVE_FRAMES {
            knobs.push(Knobs {
                family: "progressive frames",
                step: 1.0,
                shadow_step: 2.0,
                progressive: Some(frames),
                ..base.clone()
            });
        }
    }
    knobs
}

/// A point is on the Pareto front of its model when no other point of the same model is at
/// least as fast and at least as accurate, and strictly better in one of the two. Points of
/// different models are never compared: their errors are against different references.
fn mark_pareto(rows: &mut [Row]) {
    let points: Vec<(Model, f64, f64)> = rows
        .iter()
        .map(|r| (r.knobs.model, r.median_ms, r.rmse))
        .collect();
    for (i, row) in rows.iter_mut().enumerate() {
        let (m, t, e) = points[i];
        row.pareto = !points.iter().enumerate().any(|(j, &(mj, tj, ej))| {
            j != i && mj == m && tj <= t && ej <= e && (tj < t || ej < e)
        });
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

/// The mixed cut of `strata-bench transitions` for this view.
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
    let scene = strata_render::FrameInputs {
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
    let voxel_mm = v.geometry.finest_spacing_mm();
    let settings_of = |k: &Knobs| k.settings(width, height, voxel_mm);

    let mut knobs = sweep(options.sweep);
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

    // Ground truth of every model the sweep renders: level 0 at 1/16 voxel in f64, the
    // key-lit models with exact shadows (and occlusion) at their reference step.
    let mut references = HashMap::new();
    let finest = cuts.get(&(0, false)).context("level 0 cut missing")?;
    let models: std::collections::BTreeSet<Model> = knobs.iter().map(|k| k.model).collect();
    for model in models {
        let t = Instant::now();
        let settings = settings_of(&Knobs::reference(model));
        let reference = reference_rgba(&v, &finest.bricks, &finest.table, &camera, &settings)?;
        eprintln!(
            "reference ({}) in {:.1} s",
            model.name(),
            t.elapsed().as_secs_f64()
        );
        references.insert(model, reference);
    }

    let measure = |cut: &mut LevelCut, k: &Knobs| -> Result<Row> {
        let settings = settings_of(k);
        // Error from one frame (jittered frames differ; frame 0's pattern stands for all).
        // It also builds what later frames reuse (pipelines, MIP bounds, the light cache), so
        // the timed frames of a cache setting are the cache's steady state.
        let frame = cut
            .gpu
            .render_blocking(&ctx, &v.geometry, v.mapping, &camera, &settings)?;
        let reference = references.get(&k.model).context("reference missing")?;
        let mut times = Vec::with_capacity(options.frames);
        let c = if let Some(n) = k.progressive {
            // `strata render --progressive n`: the mean of n jittered frames on the GPU; the
            // time is the whole run (n frames, the accumulation and the mean's readback).
            let scene = strata_render::FrameInputs {
                cache: &cut.gpu.cache,
                page_table: &cut.gpu.page_table,
                transfer_function: &cut.gpu.transfer_function,
                geometry: &v.geometry,
                mapping: v.mapping,
                camera: &camera,
                settings: &settings,
            };
            let mut mean = None;
            for _ in 0..options.frames {
                let t = Instant::now();
                let rgba = render_still(&ctx, &mut cut.gpu.raycaster, &scene, n)?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
                mean.get_or_insert(rgba);
            }
            compare_rgba8(&mean.context("no progressive run")?, reference)?
        } else {
            for i in 0..options.frames {
                let settings = RenderSettings {
                    frame_index: i as u32,
                    ..settings.clone()
                };
                let t = Instant::now();
                render_and_wait(&ctx, cut, &v, &camera, &settings)?;
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
            compare_rgba8(&frame.rgba, reference)?
        };
        let row = Row {
            knobs: k.clone(),
            median_ms: median(times),
            rmse: c.rmse,
            psnr_db: c.psnr_db,
            max_abs: c.max_abs_error,
            pareto: false,
        };
        print_row(&row);
        Ok(row)
    };
    let mut rows = Vec::new();
    for k in &knobs {
        let cut = cuts
            .get_mut(&(k.level.min(root), k.mixed))
            .context("cut missing")?;
        rows.push(measure(cut, k)?);
    }
    // The base sweep's rows that depend on what it measured.
    if options.sweep != Sweep::Cinematic {
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
                    ..Knobs::base()
                })
            })?;
            let k = Knobs {
                family: "time-critical target",
                step: (1.0 / rate * 1000.0).round() / 1000.0,
                jitter: rate < 1.0,
                target_ms: Some(target_ms),
                ..Knobs::base()
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
                    ..Knobs::base()
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
                let scene = strata_render::FrameInputs {
                    cache: &cut.gpu.cache,
                    page_table: &cut.gpu.page_table,
                    transfer_function: &cut.gpu.transfer_function,
                    geometry: &v.geometry,
                    mapping: v.mapping,
                    camera: &camera,
                    settings: &settings,
                };
                let frame = pass.render_blocking(&ctx, &scene, &config)?;
                let reference = references.get(&Model::Dvr).context("reference missing")?;
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
                print_row(&row);
                rows.push(row);
            }
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

fn print_row(row: &Row) {
    eprintln!(
        "{:<52} {:>8.1} ms  PSNR {:>5.1} dB  RMSE {:>6.3}  max {:>3}",
        row.knobs.label(),
        row.median_ms,
        row.psnr_db,
        row.rmse,
        row.max_abs
    );
}

fn write_csv(path: &Path, rows: &[Row]) -> Result<()> {
    let mut out = String::from(
        "family,model,setting,step_voxels,preintegrated,level,jitter,shading,shadows,\
         shadow_step_voxels,light_cache_res,occlusion_voxels,progressive_frames,median_ms,rmse,\
         psnr_db,max_abs,pareto\n",
    );
    for r in rows {
        let k = &r.knobs;
        let lit = k.model.key_lit();
        let shadows = match (lit, k.shadows) {
            (true, ShadowMode::Exact) => "exact",
            (true, ShadowMode::Cache) => "cache",
            _ => "off",
        };
        let or_empty = |on: bool, x: f64| if on { x.to_string() } else { String::new() };
        let _ = writeln!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{:.3},{:.4},{:.2},{},{}",
            k.family,
            k.model.name(),
            k.label(),
            k.step,
            k.preintegrated,
            k.level,
            k.jitter || k.progressive.is_some(),
            k.model.shading(),
            shadows,
            or_empty(lit, k.shadow_step),
            or_empty(lit && k.shadows == ShadowMode::Cache, k.cache_res),
            or_empty(k.model == Model::Cinematic, k.occlusion_voxels),
            k.progressive.unwrap_or(1),
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
        "Accuracy vs time, {name}, {width}×{height} DVR, median of {frames} frames (progressive \
         rows: of {frames} runs of all their frames) on {adapter}; error against the f64 \
         reference of the row's model (level 0, 1/16 voxel; key-lit models with exact shadows \
         at 1/8 voxel and occlusion over {REFERENCE_OCCLUSION_VOXELS} voxels). ★ = Pareto front \
         of the row's model (models are not compared with each other).\n\n\
         | setting | family | model | ms | PSNR dB | RMSE | max abs | front |\n\
         | --- | --- | --- | ---: | ---: | ---: | ---: | :---: |\n"
    );
    for r in rows {
        let _ = writeln!(
            out,
            "| {} | {} | {} | {:.1} | {:.1} | {:.3} | {} | {} |",
            r.knobs.label(),
            r.knobs.family,
            r.knobs.model.name(),
            r.median_ms,
            r.psnr_db,
            r.rmse,
            r.max_abs,
            if r.pareto { "★" } else { "" }
        );
    }
    out
}

/// The plot's pixels: room for a legend of every family and front of `--sweep all`.
const PLOT_SIZE: (u32, u32) = (1100, 750);

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
    let root = BitMapBackend::new(path, PLOT_SIZE).into_drawing_area();
    root.fill(&WHITE).map_err(draw_error)?;
    let positive = |x: f64| x.max(1e-3);
    let (t_lo, t_hi) = rows.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
        (lo.min(r.median_ms), hi.max(r.median_ms))
    });
    let (e_lo, e_hi) = rows.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
        (lo.min(positive(r.rmse)), hi.max(positive(r.rmse)))
    });
    let mut chart = ChartBuilder::on(&root)
        .caption(format!("{name}: error vs time (DVR)"), ("sans-serif", 24))
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
        .x_desc("ms per frame, median (progressive: all N frames)")
        .x_labels(8)
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| format!("{v}"))
        .y_desc("RMSE vs the model's f64 reference (0-255)")
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
        "shadow step (exact)",
        "light-cache resolution",
        "occlusion radius",
        "progressive frames",
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
        RGBColor(0, 140, 140),
        RGBColor(150, 0, 150),
        RGBColor(90, 90, 220),
        RGBColor(220, 0, 90),
    ];
    // Colour = family; marker = model (circles: unlit and headlight-shaded DVR, triangles:
    // lit, crosses: cinematic); one front per model.
    let models = [Model::Dvr, Model::Shaded, Model::Lit, Model::Cinematic];
    for (family, color) in families.iter().zip(colors) {
        let mut any = false;
        for model in models {
            let points: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| r.knobs.family == *family && r.knobs.model == model)
                .map(|r| (r.median_ms, positive(r.rmse)))
                .collect();
            any |= !points.is_empty();
            let style = color.filled();
            match model {
                Model::Dvr | Model::Shaded => chart
                    .draw_series(points.iter().map(|&p| Circle::new(p, 5, style)))
                    .map(|_| ()),
                Model::Lit => chart
                    .draw_series(points.iter().map(|&p| TriangleMarker::new(p, 7, style)))
                    .map(|_| ()),
                Model::Cinematic => chart
                    .draw_series(
                        points
                            .iter()
                            .map(|&p| Cross::new(p, 6, color.stroke_width(3))),
                    )
                    .map(|_| ()),
            }
            .map_err(draw_error)?;
        }
        if any {
            chart
                .draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())
                .map_err(draw_error)?
                .label(*family)
                .legend(move |(x, y)| Circle::new((x + 8, y), 5, color.filled()));
        }
    }
    let front_colors = [
        BLACK,
        RGBColor(120, 120, 120),
        RGBColor(170, 0, 0),
        RGBColor(0, 0, 170),
    ];
    for (model, color) in models.into_iter().zip(front_colors) {
        let mut front: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.pareto && r.knobs.model == model)
            .map(|r| (r.median_ms, positive(r.rmse)))
            .collect();
        if front.is_empty() {
            continue;
        }
        front.sort_by(|a, b| a.0.total_cmp(&b.0));
        let marker = match model {
            Model::Dvr | Model::Shaded => "circles",
            Model::Lit => "triangles",
            Model::Cinematic => "crosses",
        };
        chart
            .draw_series(LineSeries::new(
                front.clone(),
                ShapeStyle::from(&color.mix(0.6)).stroke_width(2),
            ))
            .map_err(draw_error)?
            .label(format!("Pareto front: {} ({marker})", model.name()))
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 16, y)], color.stroke_width(2))
            });
        chart
            .draw_series(
                front
                    .iter()
                    .map(|&p| Circle::new(p, 9, color.stroke_width(2))),
            )
            .map_err(draw_error)?;
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

    fn row(ms: f64, rmse: f64) -> Row {
        model_row(Model::Dvr, ms, rmse)
    }

    fn model_row(model: Model, ms: f64, rmse: f64) -> Row {
        Row {
            knobs: Knobs {
                step: 1.0,
                model,
                ..Knobs::base()
            },
            median_ms: ms,
            rmse,
            psnr_db: 0.0,
            max_abs: 0,
            pareto: false,
        }
    }

    fn values<T: PartialEq + Copy>(knobs: &[&Knobs], f: impl Fn(&Knobs) -> T) -> Vec<T> {
        knobs.iter().map(|k| f(k)).collect()
    }

    #[test]
    fn cinematic_sweep_varies_each_knob_of_both_lit_models() {
        let knobs = cinematic_sweep();
        assert!(knobs.iter().all(|k| k.model.key_lit() && k.level == 0));
        let family = |model: Model, family: &str| -> Vec<&Knobs> {
            knobs
                .iter()
                .filter(|k| k.model == model && k.family == family)
                .collect()
        };
        for model in [Model::Lit, Model::Cinematic] {
            let exact = family(model, "shadow step (exact)");
            assert!(exact.iter().all(|k| k.shadows == ShadowMode::Exact));
            assert!(exact.len() >= 2, "{model:?}");
            let cache = family(model, "light-cache resolution");
            assert!(cache.iter().all(|k| k.shadows == ShadowMode::Cache));
            let res = values(&cache, |k| k.cache_res);
            assert!(
                res.len() >= 2 && res.windows(2).all(|w| w[0] < w[1]),
                "{res:?}"
            );
            let progressive = family(model, "progressive frames");
            assert_eq!(
                values(&progressive, |k| k.progressive),
                PROGRESSIVE_FRAMES.map(Some).to_vec()
            );
            // Only the frame count varies along the progressive family.
            assert!(progressive.iter().all(|k| k.step == progressive[0].step
                && k.shadow_step == progressive[0].shadow_step
                && k.shadows == progressive[0].shadows));
        }
        assert_eq!(
            values(&family(Model::Lit, "shadow step (exact)"), |k| k
                .shadow_step),
            [0.5, 1.0, 2.0, 4.0]
        );
        assert_eq!(
            values(&family(Model::Lit, "light-cache resolution"), |k| k
                .cache_res),
            [1.0, 2.0, 4.0, 8.0]
        );
        let radii = family(Model::Cinematic, "occlusion radius");
        assert_eq!(
            values(&radii, |k| k.occlusion_voxels),
            [2.0, 4.0, REFERENCE_OCCLUSION_VOXELS]
        );
        assert!(family(Model::Lit, "occlusion radius").is_empty());
    }

    #[test]
    fn sweep_selects_its_families() {
        assert!(sweep(Sweep::Base).iter().all(|k| !k.model.key_lit()));
        assert!(sweep(Sweep::Cinematic).iter().all(|k| k.model.key_lit()));
        assert_eq!(
            sweep(Sweep::All).len(),
            base_sweep().len() + cinematic_sweep().len()
        );
    }

    #[test]
    fn labels_are_unique_and_name_the_cinematic_knobs() {
        let knobs = sweep(Sweep::All);
        let labels: std::collections::HashSet<String> = knobs.iter().map(Knobs::label).collect();
        assert_eq!(labels.len(), knobs.len(), "{labels:?}");
        let lit = |f: &dyn Fn(&Knobs) -> bool| {
            cinematic_sweep()
                .into_iter()
                .find(|k| f(k))
                .expect("such a knob")
                .label()
        };
        assert_eq!(
            lit(&|k| k.model == Model::Lit
                && k.shadows == ShadowMode::Exact
                && k.shadow_step == 2.0),
            "step 0.5 shadow step 2 [lit]"
        );
        assert_eq!(
            lit(&|k| k.model == Model::Lit && k.shadows == ShadowMode::Cache && k.cache_res == 4.0),
            "step 0.5 light cache 4 [lit]"
        );
        assert_eq!(
            lit(&|k| k.model == Model::Cinematic && k.occlusion_voxels == 2.0),
            "step 0.5 shadow step 1 AO 2 vox [cinematic]"
        );
        assert_eq!(
            lit(&|k| k.model == Model::Lit && k.progressive == Some(16)),
            "step 1 shadow step 2 progressive ×16 [lit]"
        );
        // The base sweep's labels are what they were.
        assert_eq!(
            Knobs {
                model: Model::Shaded,
                ..Knobs::base()
            }
            .label(),
            "step 0.5 shaded"
        );
    }

    #[test]
    fn settings_follow_the_knobs_and_each_reference_renders_the_same_model() {
        let voxel_mm = 2.5;
        for k in sweep(Sweep::All) {
            let s = k.settings(64, 48, voxel_mm);
            s.validate()
                .unwrap_or_else(|e| panic!("{}: {e}", k.label()));
            let r = Knobs::reference(k.model).settings(64, 48, voxel_mm);
            r.validate().unwrap();
            // Same optical model: light, scattering and shading; the reference traces exact
            // shadows and occludes over the model's full radius, without jitter.
            assert_eq!(s.light, r.light, "{}", k.label());
            assert_eq!(s.scattering, r.scattering, "{}", k.label());
            assert_eq!(s.shading, r.shading, "{}", k.label());
            assert_eq!(
                s.occlusion.is_some(),
                r.occlusion.is_some(),
                "{}",
                k.label()
            );
            assert_eq!(s.effective_key_light(), k.model.key_lit(), "{}", k.label());
            assert!(!r.jitter && r.quality == 0.5);
            assert_eq!(s.jitter, k.jitter || k.progressive.is_some());
            if k.model.key_lit() {
                assert_eq!(s.shadows.mode, k.shadows);
                assert_eq!(s.shadows.step, k.shadow_step);
                assert_eq!(s.shadows.cache_res, k.cache_res);
                assert_eq!(r.shadows.mode, ShadowMode::Exact);
                assert_eq!(r.shadows.step, REFERENCE_SHADOW_STEP);
                assert!(s.shadows.step >= r.shadows.step);
            } else {
                assert_eq!(s.shadows.mode, ShadowMode::Off);
                assert_eq!(r.shadows.mode, ShadowMode::Off);
            }
            if k.model == Model::Cinematic {
                let radius = s.occlusion.unwrap().radius_mm;
                assert_eq!(radius, k.occlusion_voxels * voxel_mm);
                assert_eq!(
                    r.occlusion.unwrap().radius_mm,
                    REFERENCE_OCCLUSION_VOXELS * voxel_mm
                );
                assert!(radius <= r.occlusion.unwrap().radius_mm);
            }
        }
    }

    #[test]
    fn pareto_front_is_drawn_per_model() {
        let mut rows = vec![
            model_row(Model::Dvr, 10.0, 1.0),
            model_row(Model::Dvr, 20.0, 2.0),
            // Slower and worse than both DVR points, but the best of its own model.
            model_row(Model::Lit, 30.0, 3.0),
            model_row(Model::Lit, 40.0, 4.0),
            model_row(Model::Lit, 50.0, 1.5),
            model_row(Model::Cinematic, 100.0, 9.0),
        ];
        mark_pareto(&mut rows);
        let front: Vec<bool> = rows.iter().map(|r| r.pareto).collect();
        assert_eq!(front, vec![true, false, true, false, true, true]);
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
        let mut rows = vec![
            row(10.0, 5.0),
            row(20.0, 2.0),
            row(5.0, 0.0),
            model_row(Model::Lit, 40.0, 3.0),
            model_row(Model::Cinematic, 80.0, 4.0),
        ];
        mark_pareto(&mut rows);
        plot(&path, &rows, "test").unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), PLOT_SIZE);
        // Not blank: the axes, labels and points draw dark pixels on the white background.
        let dark = img
            .pixels()
            .filter(|p| p.0.iter().all(|&c| c < 100))
            .count();
        assert!(dark > 1000, "{dark} dark pixels");
    }
}
