//! `strata render`: one headless frame of a store, on the GPU or with the f64 CPU reference.
//!
//! The frame itself is strata-headless's (the Python package's `strata.render` calls the same
//! code): this module turns the flags into its [`RenderOptions`], opens the store or URL,
//! writes the PNG, and renders the orbit movie.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use strata_headless::{Mode, RenderOptions, ShadowsOption};
use strata_loader::StreamingVolume;
use strata_render::{GpuContext, RenderSettings, Traversal};
use strata_viewer::export::{
    encode_mp4, orbit_azimuth, orbit_frame_name, parse_size, write_png, MAX_ORBIT_FRAMES,
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

/// How the GPU raycaster finds the bricks along a ray (render/src/gpu/gpu_octree.rs).
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
    /// (render/src/model/shadows.rs); `cache` reads one lookup per shaded sample from a
    /// light-transmittance volume built on the GPU (render/src/gpu/light_cache.rs; needs a
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
    /// Ambient occlusion over this radius in mm (render/src/model/ambient_occlusion.rs): 16 short
    /// rays of local extinction per shaded sample, at --shadow-step, scale the ambient term.
    /// Turns shading on. The f64 reference (--reference) renders the same model.
    #[arg(long, value_name = "MM", allow_hyphen_values = true)]
    pub occlusion: Option<f64>,
    /// Single scattering of the key light with a Henyey-Greenstein phase of asymmetry G
    /// (render/src/model/scattering.rs; -0.99..0.99, > 0 forward: back-lit tissue glows), blended
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
    /// (render/src/passes/progressive.rs). The jitter's wood-grain averages out as 1/√N towards the
    /// same model's fine-step image (--reference renders that in f64); 16-64 frames remove
    /// most of it. Renders a fixed cut (--level, loaded up front); GPU raycaster only (not
    /// --reference, --mode adaptive, --orbit or --no-jitter).
    #[arg(long, value_name = "N")]
    pub progressive: Option<u32>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum ShadowsArg {
    Off,
    Exact,
    Cache,
}

/// The still frame's options of the flags (the orbit's and the output's are this module's).
fn options_of(args: &RenderArgs) -> Result<RenderOptions> {
    let (width, height) = parse_size(&args.size)?;
    Ok(RenderOptions {
        width,
        height,
        azimuth: args.azimuth,
        elevation: args.elevation,
        zoom: args.zoom,
        mode: match args.mode {
            ModeArg::Dvr => Mode::Dvr,
            ModeArg::Mip => Mode::Mip,
            ModeArg::Iso => Mode::Iso,
            ModeArg::Adaptive => Mode::Adaptive,
            ModeArg::AdaptiveMip => Mode::AdaptiveMip,
        },
        tf: args.tf.clone(),
        step: args.step,
        level: args.level,
        up_front: args.up_front,
        max_frames: args.max_frames.max(1),
        quality: args.quality,
        reference: args.reference,
        shading: args.shading,
        iso: args.iso,
        orthographic: args.orthographic,
        jitter: !args.no_jitter,
        smooth: !args.no_smooth,
        exact_trilinear: args.exact_trilinear,
        oracle_epsilon: args.oracle_epsilon,
        traversal: args.traversal.map(TraversalArg::traversal),
        gpu_mib: args.gpu_mib,
        shadows: match args.shadows {
            ShadowsArg::Off => ShadowsOption::Off,
            ShadowsArg::Exact => ShadowsOption::Exact,
            ShadowsArg::Cache => ShadowsOption::Cache,
        },
        light_dir: args
            .light_dir
            .as_deref()
            .map(strata_headless::parse_light_dir)
            .transpose()?,
        shadow_step: args.shadow_step,
        light_cache_res: args.light_cache_res,
        occlusion: args.occlusion,
        scattering: args.scattering,
        scattering_blend: args.scattering_blend,
        progressive: args.progressive,
    })
}

/// Refuses values that would render a black image or nothing at all: the frame's options
/// (strata-headless checks them), then the orbit's and the output's.
fn check_args(args: &RenderArgs) -> Result<RenderOptions> {
    use crate::cli_checks::check_png_output;
    let options = options_of(args)?;
    options.validate()?;
    anyhow::ensure!(
        args.progressive.is_none() || args.orbit.is_none(),
        "--progressive averages jittered frames of the GPU raycaster: it does not combine \
         with --orbit"
    );
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
                !options.renders_fixed_cut(),
                "--orbit streams the store: it does not combine with --up-front, --reference, \
                 --mode adaptive or --progressive"
            );
        }
        None => check_png_output("out", &args.out)?,
    }
    Ok(options)
}

pub fn run(args: RenderArgs) -> Result<()> {
    let options = check_args(&args)?;
    let mut report = |note: String| eprintln!("{note}");
    let sled_cache_bytes = if options.renders_fixed_cut() {
        strata_storage::store::DEFAULT_READ_CACHE_BYTES
    } else {
        options.streaming_config().sled_cache_bytes
    };
    if let Some(frames) = args.orbit {
        let started = Instant::now();
        let ctx = GpuContext::headless()?;
        eprintln!("GPU: {}", ctx.adapter_name());
        let store = strata_viewer::volume_location::open_source(
            &args.store,
            args.token_file.as_deref(),
            sled_cache_bytes,
        )?;
        let mut volume =
            strata_headless::open_streaming(&ctx, store, &args.store, &options, &mut report)?;
        eprintln!("opened in {:.2} s", started.elapsed().as_secs_f64());
        return write_orbit(&args, &options, &ctx, &mut volume, frames);
    }
    let store = strata_viewer::volume_location::open_source(
        &args.store,
        args.token_file.as_deref(),
        sled_cache_bytes,
    )?;
    let frame = strata_headless::render(store, &args.store, &options, &mut report)?;
    write_png(&args.out, frame.width, frame.height, &frame.rgba)?;
    println!("wrote {}", args.out.display());
    Ok(())
}

/// The orbit movie: one converged frame per azimuth step, on one streaming volume (bricks
/// stay resident from frame to frame), then ffmpeg when it is there.
fn write_orbit(
    args: &RenderArgs,
    options: &RenderOptions,
    ctx: &GpuContext,
    volume: &mut StreamingVolume,
    frames: u32,
) -> Result<()> {
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating the orbit folder {}", args.out.display()))?;
    let geometry = volume.geometry().clone();
    let settings: RenderSettings = options.settings();
    let started = Instant::now();
    let mut not_converged = 0;
    for i in 0..frames {
        let camera = RenderOptions {
            azimuth: orbit_azimuth(args.azimuth, i, frames),
            ..options.clone()
        }
        .camera(&geometry);
        let (frame, history) =
            volume.render_until_converged(ctx, &camera, &settings, options.max_frames)?;
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
    use strata_render::{Occlusion, Scattering};

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
            Ok(_) => panic!("{extra:?} accepted"),
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
        let s = options_of(&a).unwrap().settings();
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
        let plain = options_of(&args(&[])).unwrap().settings();
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
        let s = options_of(&a).unwrap().settings();
        assert!(s.effective_shadows() && s.effective_key_light());
        assert!(
            error(&["--mode", "adaptive", "--up-front", "--shadows", "cache"])
                .contains("--shadows exact, not cache")
        );
    }
}
