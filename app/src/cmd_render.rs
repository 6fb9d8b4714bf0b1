//! `strata render`: one headless frame of a store, on the GPU or with the f64 CPU reference.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, ValueEnum};
use strata_loader::store_volume::{
    check_cut_fits, classify_empty, page_table_for_cut, slots_needed, GpuCut,
};
use strata_loader::{ResidentBricks, StreamingConfig, StreamingVolume};
use strata_render::adaptive::{
    block_oracle_with, render_adaptive_reference, AdaptiveConfig, AdaptiveOptics, AdaptivePass,
    OracleTarget,
};
use strata_render::progressive::render_still;
use strata_render::reference::{render_reference, ReferenceOptions, ReferenceScene};
use strata_render::{
    Camera, GpuContext, GpuPageTable, KeyLight, LightDirection, Occlusion, Projection, RenderMode,
    RenderSettings, Scattering, Scene, SegmentIntegralTable, Shading, ShadowMode, Shadows,
    Traversal,
};
use strata_storage::BrickId;
use strata_viewer::export::{
    choose_transfer_function, encode_mp4, orbit_azimuth, orbit_frame_name, parse_size, write_png,
    MAX_ORBIT_FRAMES,
};

#[derive(Clone, Copy, ValueEnum)]
pub enum ModeArg {
    Dvr,
    Mip,
    Iso,
    /// DVR by adaptive sampling in three dimensions (adaptive-sampling paper): its own pass,
    /// sampling distances from the per-block oracle (--oracle-epsilon); renders a fixed cut
    /// (--up-front).
    Adaptive,
    /// MIP by adaptive sampling in three dimensions: the same pass, oracle and fixed cut as
    /// --mode adaptive, each pixel keeping its largest value.
    AdaptiveMip,
}

/// How the GPU raycaster finds the bricks along a ray (render/src/gpu_octree.rs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum TraversalArg {
    /// The flat page table: one entry per finest brick position (the default).
    Flat,
    /// The octree of the resident cut with neighbour pointers (octree paper §5): index memory
    /// grows with the cut, not the volume; streamed or --up-front, smooth level transitions
    /// as with the flat table.
    Octree,
}

impl TraversalArg {
    pub fn traversal(self) -> Traversal {
        match self {
            TraversalArg::Flat => Traversal::Flat,
            TraversalArg::Octree => Traversal::Octree,
        }
    }
}

#[derive(Args, Clone)]
pub struct RenderArgs {
    /// A store directory, or http://HOST:PORT/v1/stores/NAME served by `strata serve`.
    pub store: String,
    /// Bearer token for a server that requires one.
    #[arg(long)]
    pub token_file: Option<PathBuf>,
    /// Output PNG.
    #[arg(long, default_value = "strata.png")]
    pub out: PathBuf,
    /// Image size WxH.
    #[arg(long, default_value = "512x512")]
    pub size: String,
    /// Orbit angle around the patient's superior axis, degrees (0 = looking from anterior).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub azimuth: f64,
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub elevation: f64,
    #[arg(long, default_value_t = 1.0)]
    pub zoom: f64,
    #[arg(long, value_enum, default_value_t = ModeArg::Dvr)]
    pub mode: ModeArg,
    /// Preset (ct-bone, ct-soft-tissue, ct-lung, ct-vessels, mr-default) or a JSON file.
    #[arg(long)]
    pub tf: Option<String>,
    /// Step length in finest voxels (quality factor).
    #[arg(long, default_value_t = 0.5)]
    pub step: f64,
    /// Octree level to render with --up-front or --reference (0 = full resolution; clamped
    /// to the root).
    #[arg(long, default_value_t = 0)]
    pub level: u8,
    /// Load every brick of --level before the first frame instead of streaming.
    #[arg(long)]
    pub up_front: bool,
    /// Streaming: stop after this many frames if not converged by then.
    #[arg(long, default_value_t = 400)]
    pub max_frames: usize,
    /// Streaming quality factor: refine while a voxel covers more than this many pixels.
    #[arg(long, default_value_t = 1.0)]
    pub quality: f64,
    /// Render with the f64 CPU reference instead of the GPU.
    #[arg(long)]
    pub reference: bool,
    /// Blinn-Phong shading (always on for isosurfaces).
    #[arg(long)]
    pub shading: bool,
    /// Isosurface value in physical units.
    #[arg(long, default_value_t = 300.0, allow_hyphen_values = true)]
    pub iso: f64,
    /// Orthographic instead of perspective projection.
    #[arg(long)]
    pub orthographic: bool,
    /// Turn off ray-start jitter.
    #[arg(long)]
    pub no_jitter: bool,
    /// Show the seams where bricks of different levels meet (no smooth transitions).
    #[arg(long)]
    pub no_smooth: bool,
    /// Trilinear interpolation by hand in f32 instead of the texture sampler: weights from
    /// the in-slot coordinate, so the image does not depend on the order bricks arrived in
    /// (bit-identical local and streamed renders); the sampler may move a channel by one step.
    #[arg(long)]
    pub exact_trilinear: bool,
    /// --mode adaptive: the oracle's ε (opacity change per slice a 2³ block may have and
    /// still be sampled coarsely; larger = fewer samples, coarser image).
    #[arg(long, default_value_t = 0.001)]
    pub oracle_epsilon: f64,
    /// An orbit movie: N frames around the volume (azimuth steps of 360/N from --azimuth)
    /// written as frame-0000.png … into the folder --out (created); with ffmpeg on the PATH
    /// also orbit.mp4 (24 frames per second) beside them.
    #[arg(long, value_name = "N")]
    pub orbit: Option<u32>,
    /// The raycaster's traversal: `flat` page table or the cut's `octree` with ropes. Not
    /// given: flat, unless its per-page buffers exceed the device's storage-binding limit or
    /// the grid has over 2^18 page cells (beyond 2048³ voxels; streaming then takes the
    /// octree and says so).
    #[arg(long, value_enum)]
    pub traversal: Option<TraversalArg>,
    /// GPU memory for the brick cache, MiB. Streaming: the loader's budget (default 256).
    /// --up-front: the level's bricks must fit it (an error says bricks × bytes against it);
    /// not given, the cache holds the whole level.
    #[arg(long)]
    pub gpu_mib: Option<u64>,
    /// Volumetric shadows from the key light: `exact` traces a shadow ray per shaded sample
    /// (render/src/shadows.rs); `cache` reads one lookup per shaded sample from a
    /// light-transmittance volume built on the GPU (render/src/light_cache.rs; needs a
    /// directional light, so without --light-dir it lights along the view axis: 0,0,1). Turns
    /// shading on. The f64 reference (--reference) renders the same model.
    #[arg(long, value_enum, default_value_t = ShadowsArg::Off)]
    pub shadows: ShadowsArg,
    /// The key light's direction towards the light, camera-relative: X right, Y up, Z towards
    /// the viewer (0,0,1 lights along the view axis). Not given: the headlight.
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true)]
    pub light_dir: Option<String>,
    /// Shadow-ray step in finest voxels (the light cache's rays too).
    #[arg(long, default_value_t = 1.0)]
    pub shadow_step: f64,
    /// --shadows cache: finest voxels per light-cache texel edge (1-16; coarser is faster to
    /// build and blurrier).
    #[arg(long, default_value_t = 2.0)]
    pub light_cache_res: f64,
    /// Ambient occlusion over this radius in mm (render/src/ambient_occlusion.rs): 16 short
    /// rays of local extinction per shaded sample, at --shadow-step, scale the ambient term.
    /// Turns shading on. The f64 reference (--reference) renders the same model.
    #[arg(long, value_name = "MM", allow_hyphen_values = true)]
    pub occlusion: Option<f64>,
    /// Single scattering of the key light with a Henyey-Greenstein phase of asymmetry G
    /// (render/src/scattering.rs; -0.99..0.99, > 0 forward: back-lit tissue glows), blended
    /// with the surface BRDF by gradient magnitude (--scattering-blend). Turns shading on. The
    /// f64 reference (--reference) renders the same model.
    #[arg(long, value_name = "G", allow_hyphen_values = true)]
    pub scattering: Option<f64>,
    /// --scattering: Exposure Render's gradient factor, 0..1 (0: volume-like everywhere; 1:
    /// surface-like wherever the gradient is a few % of the TF range per voxel).
    #[arg(long, default_value_t = 0.5)]
    pub scattering_blend: f64,
    /// Progressive refinement of the still view: render N frames with different ray-start
    /// jitter (frame_index 0..N) and write their mean, accumulated on the GPU
    /// (render/src/progressive.rs). The jitter's wood-grain averages out as 1/√N towards the
    /// same model's fine-step image (--reference renders that in f64); 16-64 frames remove
    /// most of it. Renders a fixed cut (--level, loaded up front); GPU raycaster only (not
    /// --reference, --mode adaptive, --orbit or --no-jitter).
    #[arg(long, value_name = "N")]
    pub progressive: Option<u32>,
}

/// The largest --occlusion radius: 16 rays of radius / step samples per shaded sample, so a
/// radius of 100 mm is already thousands of samples each at a 1 mm step, and no longer local.
pub const MAX_OCCLUSION_MM: f64 = 100.0;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ShadowsArg {
    Off,
    Exact,
    Cache,
}

/// "X,Y,Z" as a non-zero finite vector.
pub fn parse_light_dir(text: &str) -> Result<[f64; 3]> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let bad = || anyhow::anyhow!("--light-dir {text:?}: expected three numbers X,Y,Z");
    let [x, y, z] = parts[..] else {
        return Err(bad());
    };
    let v = [x, y, z].map(|p| p.parse::<f64>());
    let [Ok(x), Ok(y), Ok(z)] = v else {
        return Err(bad());
    };
    anyhow::ensure!(
        [x, y, z].iter().all(|c| c.is_finite()) && (x * x + y * y + z * z) > 1e-24,
        "--light-dir {text:?}: the direction must be finite and non-zero"
    );
    Ok([x, y, z])
}

/// The most frames --progressive averages: past 4096 the jitter noise is 1/64 of one frame's,
/// far under an 8-bit step; more is a typo.
pub const MAX_PROGRESSIVE_FRAMES: u32 = 4096;

/// Refuses values that would render a black image or nothing at all.
fn check_args(args: &RenderArgs) -> Result<()> {
    use crate::cli_checks::{check_finite, check_png_output, check_range, STEP_RANGE};
    check_finite("azimuth", args.azimuth)?;
    check_finite("elevation", args.elevation)?;
    check_range("zoom", args.zoom, 0.01..=1000.0)?;
    check_range("step", args.step, STEP_RANGE)?;
    check_range("quality", args.quality, 0.01..=1000.0)?;
    check_finite("iso", args.iso)?;
    match args.orbit {
        Some(n) => {
            anyhow::ensure!(
                (1..=MAX_ORBIT_FRAMES).contains(&n),
                "--orbit {n}: the number of frames must be 1..={MAX_ORBIT_FRAMES}"
            );
            anyhow::ensure!(
                !args.out.is_file(),
                "--out {} is a file: an orbit movie is written into a folder",
                args.out.display()
            );
            anyhow::ensure!(
                !args.up_front
                    && !args.reference
                    && !matches!(args.mode, ModeArg::Adaptive | ModeArg::AdaptiveMip),
                "--orbit streams the store: it does not combine with --up-front, --reference or \
                 --mode adaptive"
            );
        }
        None => check_png_output("out", &args.out)?,
    }
    if args.traversal == Some(TraversalArg::Octree) {
        anyhow::ensure!(
            !args.reference && !matches!(args.mode, ModeArg::Adaptive | ModeArg::AdaptiveMip),
            "--traversal octree is the GPU raycaster's: it does not apply to --reference or \
             --mode adaptive"
        );
    }
    if args.shadows != ShadowsArg::Off {
        check_range("shadow-step", args.shadow_step, 0.05..=1000.0)?;
        if args.shadows == ShadowsArg::Cache {
            check_range(
                "light-cache-res",
                args.light_cache_res,
                strata_render::light_cache::MIN_RES..=strata_render::light_cache::MAX_RES,
            )?;
        }
        anyhow::ensure!(
            !matches!(args.mode, ModeArg::Mip | ModeArg::AdaptiveMip),
            "--shadows is DVR and isosurface lighting: not for MIP"
        );
        // The adaptive pass traces exact shadow rays per lit segment; the light cache is the
        // raycaster's (adaptive/gpu.rs).
        anyhow::ensure!(
            !(matches!(args.mode, ModeArg::Adaptive) && args.shadows == ShadowsArg::Cache),
            "--mode adaptive takes --shadows exact, not cache"
        );
    }
    if let Some(radius) = args.occlusion {
        check_range("occlusion", radius, 0.0..=MAX_OCCLUSION_MM)?;
        check_range("shadow-step", args.shadow_step, 0.05..=1000.0)?;
    }
    if let Some(g) = args.scattering {
        let m = strata_render::settings::SCATTERING_MAX_ABS_G;
        check_range("scattering", g, -m..=m)?;
        check_range("scattering-blend", args.scattering_blend, 0.0..=1.0)?;
    }
    for (flag, on) in [
        ("--occlusion", args.occlusion.is_some()),
        ("--scattering", args.scattering.is_some()),
    ] {
        anyhow::ensure!(
            !on || !matches!(args.mode, ModeArg::Mip | ModeArg::AdaptiveMip),
            "{flag} is DVR and isosurface lighting: it does not apply to MIP"
        );
    }
    if let Some(n) = args.progressive {
        anyhow::ensure!(
            (1..=MAX_PROGRESSIVE_FRAMES).contains(&n),
            "--progressive {n}: the number of frames must be 1..={MAX_PROGRESSIVE_FRAMES}"
        );
        anyhow::ensure!(
            !args.reference
                && args.orbit.is_none()
                && !args.no_jitter
                && !matches!(args.mode, ModeArg::Adaptive | ModeArg::AdaptiveMip),
            "--progressive averages jittered frames of the GPU raycaster: it does not combine \
             with --reference (already the converged image), --orbit, --no-jitter or --mode \
             adaptive"
        );
    }
    if let Some(text) = &args.light_dir {
        parse_light_dir(text)?;
    }
    parse_size(&args.size)?;
    Ok(())
}

pub fn run(args: RenderArgs) -> Result<()> {
    check_args(&args)?;
    let adaptive = matches!(args.mode, ModeArg::Adaptive | ModeArg::AdaptiveMip);
    if adaptive {
        anyhow::ensure!(
            args.oracle_epsilon.is_finite() && args.oracle_epsilon >= 0.0,
            "--oracle-epsilon must be a non-negative number, got {}",
            args.oracle_epsilon
        );
        if !args.up_front && !args.reference {
            eprintln!("--mode adaptive renders a fixed cut: loading --level up front");
        }
    } else if args.progressive.is_some() && !args.up_front {
        // A still view of a cut that changes while it streams would restart the mean.
        eprintln!("--progressive renders a fixed cut: loading --level up front");
    } else if !args.up_front && !args.reference {
        return run_streaming(&args);
    }
    let (width, height) = parse_size(&args.size)?;
    let store = strata_viewer::volume_location::open_source(
        &args.store,
        args.token_file.as_deref(),
        strata_storage::store::DEFAULT_READ_CACHE_BYTES,
    )?;
    let store = store.as_ref();
    let header = store.header().clone();
    let geometry = header.geometry.clone();
    let mapping = header.value_mapping.mapping;
    let tf = choose_transfer_function(args.tf.as_deref(), &header.modality)?;
    let physical_range = (
        mapping.physical(header.stored_range[0] as f64),
        mapping.physical(header.stored_range[1] as f64),
    );
    let tf_table = tf.table(
        physical_range.0.min(physical_range.1),
        physical_range.0.max(physical_range.1),
    );
    let mut table = page_table_for_cut(store, &geometry, |_| args.level);
    let settings = settings_of(&args)?;
    if matches!(settings.mode, RenderMode::Dvr) {
        classify_empty(store, &mut table, mapping, &tf_table);
    }
    let camera = camera_of(&args, &geometry);
    let budget = args.gpu_mib.map(|m| m << 20);
    // The GPU paths' device, made before the bricks are read: a level over the budget (or the
    // device) is refused before reading it.
    let gpu = if args.reference {
        None
    } else {
        let ctx = GpuContext::headless()?;
        eprintln!("GPU: {}", ctx.adapter_name());
        check_cut_fits(
            &ctx,
            slots_needed(&table),
            budget,
            &format!("level {} of {}", args.level, args.store),
        )?;
        Some(ctx)
    };
    let t_load = Instant::now();
    let bricks = ResidentBricks::load(store, &table)?;
    eprintln!(
        "loaded {} bricks of level {} in {:.2} s",
        bricks.len(),
        args.level,
        t_load.elapsed().as_secs_f64()
    );

    let t = Instant::now();
    // The per-block oracle (the render mode's): a distance per 2³ block of every brick,
    // bounding the lit colour's change where the settings light the samples.
    let oracle = || {
        block_oracle_with(
            &table,
            &bricks,
            mapping,
            &tf,
            args.oracle_epsilon,
            AdaptiveConfig::default().l_max,
            settings.quality,
            OracleTarget::for_settings(&settings),
        )
    };
    let rgba = if adaptive && args.reference && !settings.effective_key_light() {
        // The f64 transcription of the same frame (its oracle, its pre-integration table).
        let scene = ReferenceScene {
            source: &bricks,
            page_table: &table,
            geometry: &geometry,
            mapping,
            transfer_function: &tf,
            tf_range: (tf_table.lo, tf_table.hi),
        };
        let integral = SegmentIntegralTable::build(
            &tf,
            tf_table.lo,
            tf_table.hi,
            geometry.finest_spacing_mm(),
        );
        render_adaptive_reference(
            &scene,
            &camera,
            &settings,
            &AdaptiveConfig::default(),
            &oracle(),
            AdaptiveOptics::Table(&integral),
        )?
        .rgba
    } else if adaptive && !args.reference {
        let ctx = gpu.context("GPU context missing")?;
        let cut = GpuCut::upload_within(
            &ctx,
            &bricks,
            &table,
            geometry.page_dims(),
            &tf_table,
            budget,
        )?;
        let mut pass = AdaptivePass::new(&ctx, &cut.cache);
        pass.set_oracle(&ctx, &oracle());
        let scene = Scene {
            cache: &cut.cache,
            page_table: &cut.page_table,
            transfer_function: &cut.transfer_function,
            geometry: &geometry,
            mapping,
            camera: &camera,
            settings: &settings,
        };
        let frame = pass.render_blocking(&ctx, &scene, &AdaptiveConfig::default())?;
        eprintln!(
            "adaptive: {} sampling operations per level {:?} (+{} apron), {} synthesis operations",
            frame.total_samples(),
            frame.samples_per_level,
            frame.total_apron_samples(),
            frame.total_syntheses()
        );
        if frame.shadow_rays > 0 {
            eprintln!("adaptive: {} shadow rays", frame.shadow_rays);
        }
        frame.rgba
    } else if args.reference {
        let scene = ReferenceScene {
            source: &bricks,
            page_table: &table,
            geometry: &geometry,
            mapping,
            transfer_function: &tf,
            tf_range: (tf_table.lo, tf_table.hi),
        };
        render_reference(&scene, &camera, &settings, ReferenceOptions::default())?.rgba
    } else {
        let ctx = gpu.context("GPU context missing")?;
        let mut cut = GpuCut::upload_within(
            &ctx,
            &bricks,
            &table,
            geometry.page_dims(),
            &tf_table,
            budget,
        )?;
        match args.traversal.unwrap_or(TraversalArg::Flat) {
            TraversalArg::Flat => {
                let frame = cut.render_blocking(&ctx, &geometry, mapping, &camera, &settings)?;
                match args.progressive {
                    None => frame.rgba,
                    // The frame above also uploaded the MIP value bounds the scene needs.
                    Some(frames) => {
                        let scene = Scene {
                            cache: &cut.cache,
                            page_table: &cut.page_table,
                            transfer_function: &cut.transfer_function,
                            geometry: &geometry,
                            mapping,
                            camera: &camera,
                            settings: &settings,
                        };
                        render_still(&ctx, &mut cut.raycaster, &scene, frames)?
                    }
                }
            }
            TraversalArg::Octree => {
                // The same cut and cache, indexed by its octree instead of the flat table.
                let index = GpuPageTable::with_traversal(
                    &ctx.device,
                    geometry.page_dims(),
                    &cut.cache,
                    Traversal::Octree,
                )?;
                index.update(&ctx.queue, &table)?;
                let bounds = table.value_max_physical(mapping, |level, node| {
                    store
                        .node(BrickId::new(level, node))
                        .map(|n| (n.min, n.max))
                });
                index.update_value_max(&ctx.queue, &bounds)?;
                eprintln!(
                    "octree index: {} leaves, {} bytes on the GPU (flat table: {} bytes)",
                    index.visibility_entries(),
                    index.gpu_index_bytes(),
                    cut.page_table.gpu_index_bytes()
                );
                let scene = Scene {
                    cache: &cut.cache,
                    page_table: &index,
                    transfer_function: &cut.transfer_function,
                    geometry: &geometry,
                    mapping,
                    camera: &camera,
                    settings: &settings,
                };
                match args.progressive {
                    None => {
                        cut.raycaster
                            .render_blocking(&ctx, &scene)
                            .context("--traversal octree")?
                            .rgba
                    }
                    Some(frames) => render_still(&ctx, &mut cut.raycaster, &scene, frames)
                        .context("--traversal octree")?,
                }
            }
        }
    };
    eprintln!(
        "rendered {}x{} in {:.2} s ({})",
        width,
        height,
        t.elapsed().as_secs_f64(),
        if args.reference {
            "CPU reference".to_string()
        } else if let Some(n) = args.progressive {
            format!("GPU, mean of {n} jittered frames")
        } else {
            "GPU".to_string()
        }
    );
    write_png(&args.out, width, height, &rgba)?;
    println!("wrote {}", args.out.display());
    Ok(())
}

/// The orbit camera the arguments ask for.
fn camera_of(args: &RenderArgs, geometry: &strata_render::VolumeGeometry) -> Camera {
    let projection = if args.orthographic {
        Projection::Orthographic {
            height_mm: geometry.bounding_radius_mm() * 2.0 / args.zoom.max(1e-3),
        }
    } else {
        Projection::Perspective { fov_y_deg: 30.0 }
    };
    Camera::orbit(
        geometry,
        args.azimuth,
        args.elevation,
        args.zoom,
        projection,
    )
}

fn settings_of(args: &RenderArgs) -> Result<RenderSettings> {
    let (width, height) = parse_size(&args.size)?;
    Ok(RenderSettings {
        width,
        height,
        mode: match args.mode {
            ModeArg::Dvr | ModeArg::Adaptive => RenderMode::Dvr,
            ModeArg::Mip | ModeArg::AdaptiveMip => RenderMode::Mip,
            ModeArg::Iso => RenderMode::Isosurface,
        },
        quality: args.step,
        jitter: !args.no_jitter,
        shading: (args.shading
            || args.shadows != ShadowsArg::Off
            || args.occlusion.is_some()
            || args.scattering.is_some()
            || matches!(args.mode, ModeArg::Iso))
        .then(Shading::default),
        smooth_transitions: !args.no_smooth,
        iso_value: args.iso,
        exact_trilinear: args.exact_trilinear,
        light: KeyLight {
            direction: match &args.light_dir {
                Some(text) => LightDirection::Camera(parse_light_dir(text)?),
                // The cache holds one light direction; the headlight's is each ray's own.
                // Along the view axis it is the headlight of an orthographic view.
                None if args.shadows == ShadowsArg::Cache => {
                    LightDirection::Camera([0.0, 0.0, 1.0])
                }
                None => LightDirection::Headlight,
            },
            ..KeyLight::default()
        },
        shadows: Shadows {
            mode: match args.shadows {
                ShadowsArg::Off => ShadowMode::Off,
                ShadowsArg::Exact => ShadowMode::Exact,
                ShadowsArg::Cache => ShadowMode::Cache,
            },
            step: args.shadow_step,
            cache_res: args.light_cache_res,
        },
        occlusion: args.occlusion.map(|radius_mm| Occlusion { radius_mm }),
        scattering: args.scattering.map(|g| Scattering {
            g,
            blend: args.scattering_blend,
        }),
        ..RenderSettings::default()
    })
}

/// The default: stream the store, frame after frame, until the image converges (or
/// --max-frames), and write the last frame.
fn run_streaming(args: &RenderArgs) -> Result<()> {
    let settings = settings_of(args)?;
    let started = Instant::now();
    let ctx = GpuContext::headless()?;
    eprintln!("GPU: {}", ctx.adapter_name());
    let defaults = StreamingConfig::default();
    let config = StreamingConfig {
        max_voxel_pixels: args.quality,
        traversal: args.traversal.map(TraversalArg::traversal),
        gpu_budget_bytes: args.gpu_mib.map_or(defaults.gpu_budget_bytes, |m| m << 20),
        ..defaults
    };
    anyhow::ensure!(
        args.quality.is_finite() && args.quality > 0.0,
        "--quality must be positive, got {}",
        args.quality
    );
    let store = strata_viewer::volume_location::open_source(
        &args.store,
        args.token_file.as_deref(),
        config.sled_cache_bytes,
    )?;
    let tf = choose_transfer_function(args.tf.as_deref(), &store.header().modality)?;
    let mut volume = StreamingVolume::new(&ctx, store, &tf, config)
        .with_context(|| format!("cannot stream store {}", args.store))?;
    let opened = Instant::now();
    if let Some(note) = volume.traversal_note() {
        eprintln!("{note}");
    }
    let geometry = volume.geometry().clone();
    if let Some(frames) = args.orbit {
        return write_orbit(args, &ctx, &mut volume, &settings, frames);
    }
    let camera = camera_of(args, &geometry);
    let (frame, history) =
        volume.render_until_converged(&ctx, &camera, &settings, args.max_frames.max(1))?;
    for failure in volume.take_failures() {
        eprintln!(
            "warning: {}; its parent is shown there instead",
            failure.message
        );
    }
    let Some(last) = history.last() else {
        bail!("no frame was rendered")
    };
    if let Some(lost) = history.iter().find(|s| s.source_status.is_retrying()) {
        eprintln!(
            "warning: connection to the source was lost during the render ({:?}); requests were retried",
            lost.source_status
        );
    }
    if last.retried_total > 0 || last.cancelled_in_flight_total > 0 {
        eprintln!(
            "remote: {} requests retried ({} records damaged in transit), {} stale requests cancelled in flight, at most {} in flight",
            last.retried_total,
            last.checksum_failures_total,
            last.cancelled_in_flight_total,
            last.max_in_flight
        );
    }
    eprintln!(
        "{} traversal: {} index bytes on the GPU",
        volume.traversal().name(),
        volume.gpu_index_bytes()
    );
    eprintln!(
        "{} after {} frames in {:.2} s (open {:.2} s): {} bricks on the GPU per level {:?}, {:.1} MB read",
        if last.converged {
            last.convergence_status()
        } else {
            "not converged (raise --max-frames)".into()
        },
        history.len(),
        opened.elapsed().as_secs_f64(),
        (opened - started).as_secs_f64(),
        last.gpu_slots_used,
        last.gpu_resident_per_level,
        last.stored_bytes_read_total as f64 / 1e6
    );
    write_png(&args.out, settings.width, settings.height, &frame.rgba)?;
    println!("wrote {}", args.out.display());
    Ok(())
}

/// The orbit movie: one converged frame per azimuth step, on one streaming volume (bricks
/// stay resident from frame to frame), then ffmpeg when it is there.
fn write_orbit(
    args: &RenderArgs,
    ctx: &GpuContext,
    volume: &mut StreamingVolume,
    settings: &RenderSettings,
    frames: u32,
) -> Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating the orbit folder {}", args.out.display()))?;
    let geometry = volume.geometry().clone();
    let started = Instant::now();
    let mut not_converged = 0;
    for i in 0..frames {
        let azimuth = orbit_azimuth(args.azimuth, i, frames);
        let camera = camera_of(
            &RenderArgs {
                azimuth,
                ..args.clone()
            },
            &geometry,
        );
        let (frame, history) =
            volume.render_until_converged(ctx, &camera, settings, args.max_frames.max(1))?;
        if !history.last().is_some_and(|s| s.converged) {
            not_converged += 1;
        }
        let path = args.out.join(orbit_frame_name(i));
        write_png(&path, settings.width, settings.height, &frame.rgba)?;
    }
    for failure in volume.take_failures() {
        eprintln!(
            "warning: {}; its parent is shown there instead",
            failure.message
        );
    }
    if not_converged > 0 {
        eprintln!("warning: {not_converged} frames had not converged (raise --max-frames)");
    }
    eprintln!(
        "{frames} orbit frames in {:.2} s",
        started.elapsed().as_secs_f64()
    );
    println!("wrote {frames} frames to {}", args.out.display());
    match encode_mp4(&args.out) {
        Ok(Some(movie)) => println!("wrote {}", movie.display()),
        Ok(None) => eprintln!("ffmpeg is not on the PATH: the frames are the movie (no MP4)"),
        Err(e) => eprintln!("warning: ffmpeg failed, the frames are kept: {e:#}"),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        render: RenderArgs,
    }

    fn args(extra: &[&str]) -> RenderArgs {
        let mut argv = vec!["strata", "store"];
        argv.extend_from_slice(extra);
        Cli::parse_from(argv).render
    }

    fn error(extra: &[&str]) -> String {
        match check_args(&args(extra)) {
            Ok(()) => panic!("{extra:?} accepted"),
            Err(e) => format!("{e:#}"),
        }
    }

    #[test]
    fn occlusion_and_scattering_flags_reach_the_settings() {
        let a = args(&[
            "--occlusion",
            "3.5",
            "--scattering",
            "-0.4",
            "--scattering-blend",
            "0.2",
        ]);
        assert!(check_args(&a).is_ok());
        let s = settings_of(&a).unwrap();
        assert_eq!(s.occlusion, Some(Occlusion { radius_mm: 3.5 }));
        assert_eq!(
            s.scattering,
            Some(Scattering {
                g: -0.4,
                blend: 0.2
            })
        );
        assert!(s.shading.is_some(), "the effects turn shading on");
        assert!(s.validate().is_ok());
        let plain = settings_of(&args(&[])).unwrap();
        assert!(plain.occlusion.is_none() && plain.scattering.is_none());
    }

    #[test]
    fn out_of_range_or_inapplicable_flags_are_refused_clearly() {
        assert!(error(&["--occlusion", "-1"]).contains("--occlusion must be a number between 0"));
        assert!(error(&["--occlusion", "nan"]).contains("--occlusion"));
        assert!(error(&["--occlusion", "500"]).contains("--occlusion"));
        assert!(error(&["--scattering", "1"]).contains("--scattering must be a number between"));
        assert!(error(&["--scattering", "0.3", "--scattering-blend", "2"])
            .contains("--scattering-blend"));
        for mode in ["mip", "adaptive-mip"] {
            let e = error(&["--mode", mode, "--occlusion", "2"]);
            assert!(
                e.contains("--occlusion") && e.contains("does not apply to MIP"),
                "{e}"
            );
            let e = error(&["--mode", mode, "--scattering", "0.2"]);
            assert!(
                e.contains("--scattering") && e.contains("does not apply to MIP"),
                "{e}"
            );
            assert!(error(&["--mode", mode, "--shadows", "exact"]).contains("not for MIP"));
        }
    }

    #[test]
    fn progressive_is_checked_and_refused_where_it_cannot_apply() {
        assert!(check_args(&args(&["--progressive", "16"])).is_ok());
        assert_eq!(args(&["--progressive", "16"]).progressive, Some(16));
        assert!(error(&["--progressive", "0"]).contains("1..=4096"));
        assert!(error(&["--progressive", "5000"]).contains("1..=4096"));
        for extra in [
            &["--reference"][..],
            &["--no-jitter"],
            &["--orbit", "4"],
            &["--mode", "adaptive"],
        ] {
            let mut a = vec!["--progressive", "4"];
            a.extend_from_slice(extra);
            let e = error(&a);
            assert!(e.contains("--progressive averages jittered frames"), "{e}");
        }
    }

    /// The adaptive pass lights its segments by the key light (adaptive/gpu.rs): exact
    /// shadows, occlusion and scattering are accepted; the raycaster's light cache is not.
    #[test]
    fn adaptive_mode_takes_exact_shadows_occlusion_and_scattering() {
        let a = args(&[
            "--mode",
            "adaptive",
            "--up-front",
            "--shadows",
            "exact",
            "--occlusion",
            "2",
            "--scattering",
            "0.3",
        ]);
        check_args(&a).unwrap();
        let s = settings_of(&a).unwrap();
        assert!(s.effective_shadows() && s.effective_key_light());
        assert!(
            error(&["--mode", "adaptive", "--up-front", "--shadows", "cache"])
                .contains("--shadows exact, not cache")
        );
    }
}
