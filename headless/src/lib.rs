//! One headless frame of a volume source, as premultiplied RGBA: what `strata render` draws
//! and what the Python package's `strata.render` returns, from the same code.
//!
//! The path is store → resident cut (or the streaming loader) → GPU frame → RGBA, or the f64
//! CPU reference instead of the GPU. [`RenderOptions`] holds every option of the still frame
//! with `strata render`'s defaults and [`RenderOptions::validate`] refuses what would render a
//! black image or nothing, naming the option by its command-line flag. Opening the store (a
//! folder, a served URL with its token) and writing the image are the callers': the command
//! line writes a PNG, Python hands the bytes to numpy.
//!
//! This crate links the loader and the renderer (wgpu) but no window system and no egui, so
//! the Python wheel can link it without the viewer.

use std::ops::RangeInclusive;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use strata_loader::store_volume::{
    check_cut_fits, classify_empty, page_table_for_cut, slots_needed, GpuCut,
};
use strata_loader::{LoaderError, ResidentBricks, StreamingConfig, StreamingVolume};
use strata_render::passes::adaptive::{
    block_oracle_with, render_adaptive_reference, AdaptiveConfig, AdaptiveOptics, AdaptivePass,
    OracleTarget,
};
use strata_render::passes::progressive::render_still;
use strata_render::reference::{render_reference, ReferenceOptions, ReferenceScene};
use strata_render::{
    Camera, FrameInputs, GpuContext, GpuPageTable, KeyLight, LightDirection, Occlusion, Projection,
    RenderError, RenderMode, RenderSettings, Scattering, SegmentIntegralTable, Shading, ShadowMode,
    Shadows, TransferFunction, Traversal, VolumeGeometry,
};
use strata_source::VolumeSource;
use strata_types::BrickId;

/// Why a headless frame was not rendered.
#[derive(Debug, thiserror::Error)]
pub enum HeadlessError {
    /// An option out of range, or options that do not combine (the message names the flags).
    #[error("{0}")]
    Option(String),
    /// The transfer function named is neither a preset nor a readable JSON file.
    #[error("{0}")]
    TransferFunction(String),
    #[error(transparent)]
    Loader(#[from] LoaderError),
    #[error(transparent)]
    Render(#[from] RenderError),
    /// The streaming loader could not start on the source.
    #[error("cannot stream store {name}: {source}")]
    Stream { name: String, source: LoaderError },
    #[error("no frame was rendered")]
    NoFrame,
}

impl HeadlessError {
    /// True when no usable GPU adapter or device exists (install a driver, or use the f64
    /// reference), as opposed to a bad option or a failed render.
    pub fn is_no_adapter(&self) -> bool {
        let render = match self {
            HeadlessError::Render(e) => e,
            HeadlessError::Loader(LoaderError::Render(e))
            | HeadlessError::Stream {
                source: LoaderError::Render(e),
                ..
            } => e,
            _ => return false,
        };
        matches!(
            render,
            RenderError::NoAdapter { .. } | RenderError::RequestDevice(_)
        )
    }
}

pub type Result<T, E = HeadlessError> = std::result::Result<T, E>;

/// Step lengths, in finest voxels, that a render accepts: finer than 1/64 voxel only costs
/// time; coarser than 64 voxels steps over whole bricks.
pub const STEP_RANGE: RangeInclusive<f64> = (1.0 / 64.0)..=64.0;

/// The largest `--occlusion` radius: 16 rays of radius / step samples per shaded sample, so a
/// radius of 100 mm is already thousands of samples each at a 1 mm step, and no longer local.
pub const MAX_OCCLUSION_MM: f64 = 100.0;

/// The most frames `--progressive` averages: past 4096 the jitter noise is 1/64 of one
/// frame's, far under an 8-bit step; more is a typo.
pub const MAX_PROGRESSIVE_FRAMES: u32 = 4096;

/// The largest image edge, in pixels.
pub const MAX_IMAGE_EDGE: u32 = 8192;

/// A finite number within `range`, or an error naming the flag.
pub fn check_range(flag: &str, value: f64, range: RangeInclusive<f64>) -> Result<()> {
    if !value.is_finite() || !range.contains(&value) {
        return Err(HeadlessError::Option(format!(
            "--{flag} must be a number between {} and {}, got {value}",
            range.start(),
            range.end()
        )));
    }
    Ok(())
}

/// A finite number, or an error naming the flag.
pub fn check_finite(flag: &str, value: f64) -> Result<()> {
    if !value.is_finite() {
        return Err(HeadlessError::Option(format!(
            "--{flag} must be a finite number, got {value}"
        )));
    }
    Ok(())
}

fn ensure(condition: bool, message: impl FnOnce() -> String) -> Result<()> {
    if condition {
        Ok(())
    } else {
        Err(HeadlessError::Option(message()))
    }
}

/// What is drawn (`--mode`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    Dvr,
    Mip,
    Iso,
    /// DVR by adaptive sampling in three dimensions: its own pass, sampling distances from the
    /// per-block oracle, on a fixed cut.
    Adaptive,
    /// MIP by adaptive sampling: the same pass, oracle and fixed cut.
    AdaptiveMip,
}

impl Mode {
    pub const NAMES: [&'static str; 5] = ["dvr", "mip", "iso", "adaptive", "adaptive-mip"];

    /// The mode of its command-line name ("dvr", "mip", "iso", "adaptive", "adaptive-mip").
    pub fn from_name(name: &str) -> Result<Mode> {
        Ok(match name {
            "dvr" => Mode::Dvr,
            "mip" => Mode::Mip,
            "iso" => Mode::Iso,
            "adaptive" => Mode::Adaptive,
            "adaptive-mip" | "adaptive_mip" => Mode::AdaptiveMip,
            _ => {
                return Err(HeadlessError::Option(format!(
                    "--mode {name:?}: expected one of {}",
                    Mode::NAMES.join(", ")
                )))
            }
        })
    }

    fn is_adaptive(self) -> bool {
        matches!(self, Mode::Adaptive | Mode::AdaptiveMip)
    }

    fn is_mip(self) -> bool {
        matches!(self, Mode::Mip | Mode::AdaptiveMip)
    }
}

/// Volumetric shadows from the key light (`--shadows`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ShadowsOption {
    Off,
    /// A shadow ray per shaded sample.
    Exact,
    /// One lookup per shaded sample in a light-transmittance volume built on the GPU.
    Cache,
}

impl ShadowsOption {
    /// The option of its command-line name ("off", "exact", "cache").
    pub fn from_name(name: &str) -> Result<ShadowsOption> {
        Ok(match name {
            "off" => ShadowsOption::Off,
            "exact" => ShadowsOption::Exact,
            "cache" => ShadowsOption::Cache,
            _ => {
                return Err(HeadlessError::Option(format!(
                    "--shadows {name:?}: expected off, exact or cache"
                )))
            }
        })
    }
}

/// The raycaster's traversal of its name ("flat", "octree").
pub fn traversal_from_name(name: &str) -> Result<Traversal> {
    match name {
        "flat" => Ok(Traversal::Flat),
        "octree" => Ok(Traversal::Octree),
        _ => Err(HeadlessError::Option(format!(
            "--traversal {name:?}: expected flat or octree"
        ))),
    }
}

/// "X,Y,Z" as a non-zero finite vector.
pub fn parse_light_dir(text: &str) -> Result<[f64; 3]> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let bad = || {
        HeadlessError::Option(format!(
            "--light-dir {text:?}: expected three numbers X,Y,Z"
        ))
    };
    let [x, y, z] = parts[..] else {
        return Err(bad());
    };
    let v = [x, y, z].map(|p| p.parse::<f64>());
    let [Ok(x), Ok(y), Ok(z)] = v else {
        return Err(bad());
    };
    check_light_dir(&format!("{text:?}"), [x, y, z])?;
    Ok([x, y, z])
}

fn check_light_dir(shown: &str, [x, y, z]: [f64; 3]) -> Result<()> {
    ensure(
        [x, y, z].iter().all(|c| c.is_finite()) && (x * x + y * y + z * z) > 1e-24,
        || format!("--light-dir {shown}: the direction must be finite and non-zero"),
    )
}

/// The transfer function the user named (a preset or a JSON file), or a sensible default for
/// the modality.
pub fn choose_transfer_function(name: Option<&str>, modality: &str) -> Result<TransferFunction> {
    let name = name.unwrap_or(if modality.eq_ignore_ascii_case("CT") {
        "ct-bone"
    } else {
        "mr-default"
    });
    if let Some(tf) = TransferFunction::preset(name) {
        return Ok(tf);
    }
    let path = Path::new(name);
    if path.exists() {
        return TransferFunction::load(path).map_err(|e| {
            HeadlessError::TransferFunction(format!(
                "reading transfer function {}: {e}",
                path.display()
            ))
        });
    }
    let looks_like_a_file = name.to_ascii_lowercase().ends_with(".json")
        || name.contains(std::path::MAIN_SEPARATOR)
        || name.contains('/');
    if looks_like_a_file {
        return Err(HeadlessError::TransferFunction(format!(
            "transfer function file {} does not exist",
            path.display()
        )));
    }
    Err(HeadlessError::TransferFunction(format!(
        "unknown transfer function '{name}': use ct-bone, ct-soft-tissue, ct-lung, ct-vessels, \
         mr-default or a JSON file"
    )))
}

/// Every option of one still frame, with `strata render`'s defaults.
#[derive(Clone, Debug)]
pub struct RenderOptions {
    pub width: u32,
    pub height: u32,
    /// Orbit angle around the patient's superior axis, degrees (0 = looking from anterior).
    pub azimuth: f64,
    pub elevation: f64,
    pub zoom: f64,
    pub mode: Mode,
    /// A preset name or a JSON file; `None`: by modality (ct-bone or mr-default).
    pub tf: Option<String>,
    /// Step length in finest voxels.
    pub step: f64,
    /// Octree level of a fixed cut (`up_front`, `reference`, adaptive, progressive).
    pub level: u8,
    /// Load every brick of `level` before the frame instead of streaming.
    pub up_front: bool,
    /// Streaming: stop after this many frames if not converged by then.
    pub max_frames: usize,
    /// Streaming: refine while a voxel covers more than this many pixels.
    pub quality: f64,
    /// The f64 CPU reference instead of the GPU.
    pub reference: bool,
    pub shading: bool,
    /// Isosurface value in physical units.
    pub iso: f64,
    pub orthographic: bool,
    pub jitter: bool,
    /// Smooth transitions where bricks of different levels meet.
    pub smooth: bool,
    pub exact_trilinear: bool,
    /// Adaptive modes: the oracle's ε.
    pub oracle_epsilon: f64,
    /// `None`: flat, unless the loader must take the octree.
    pub traversal: Option<Traversal>,
    /// GPU memory for the brick cache, MiB.
    pub gpu_mib: Option<u64>,
    pub shadows: ShadowsOption,
    /// Towards the key light, camera-relative; `None`: the headlight.
    pub light_dir: Option<[f64; 3]>,
    pub shadow_step: f64,
    pub light_cache_res: f64,
    /// Ambient occlusion radius in mm.
    pub occlusion: Option<f64>,
    /// Henyey-Greenstein asymmetry of single scattering.
    pub scattering: Option<f64>,
    pub scattering_blend: f64,
    /// The mean of this many jittered frames of a fixed cut.
    pub progressive: Option<u32>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            width: 512,
            height: 512,
            azimuth: 0.0,
            elevation: 0.0,
            zoom: 1.0,
            mode: Mode::Dvr,
            tf: None,
            step: 0.5,
            level: 0,
            up_front: false,
            max_frames: 400,
            quality: 1.0,
            reference: false,
            shading: false,
            iso: 300.0,
            orthographic: false,
            jitter: true,
            smooth: true,
            exact_trilinear: false,
            oracle_epsilon: 0.001,
            traversal: None,
            gpu_mib: None,
            shadows: ShadowsOption::Off,
            light_dir: None,
            shadow_step: 1.0,
            light_cache_res: 2.0,
            occlusion: None,
            scattering: None,
            scattering_blend: 0.5,
            progressive: None,
        }
    }
}

impl RenderOptions {
    /// Refuses values that would render a black image or nothing at all, and options that do
    /// not combine; the message names the flags.
    pub fn validate(&self) -> Result<()> {
        ensure(
            (1..=MAX_IMAGE_EDGE).contains(&self.width)
                && (1..=MAX_IMAGE_EDGE).contains(&self.height),
            || {
                format!(
                    "--size {}x{} is outside 1..{MAX_IMAGE_EDGE}",
                    self.width, self.height
                )
            },
        )?;
        check_finite("azimuth", self.azimuth)?;
        check_finite("elevation", self.elevation)?;
        check_range("zoom", self.zoom, 0.01..=1000.0)?;
        check_range("step", self.step, STEP_RANGE)?;
        check_range("quality", self.quality, 0.01..=1000.0)?;
        check_finite("iso", self.iso)?;
        ensure(self.max_frames >= 1, || {
            "--max-frames must be at least 1".to_string()
        })?;
        if self.mode.is_adaptive() {
            ensure(
                self.oracle_epsilon.is_finite() && self.oracle_epsilon >= 0.0,
                || {
                    format!(
                        "--oracle-epsilon must be a non-negative number, got {}",
                        self.oracle_epsilon
                    )
                },
            )?;
        }
        if self.traversal == Some(Traversal::Octree) {
            ensure(!self.reference && !self.mode.is_adaptive(), || {
                "--traversal octree is the GPU raycaster's: it does not apply to --reference or \
                 --mode adaptive"
                    .to_string()
            })?;
        }
        if self.shadows != ShadowsOption::Off {
            check_range("shadow-step", self.shadow_step, 0.05..=1000.0)?;
            if self.shadows == ShadowsOption::Cache {
                check_range(
                    "light-cache-res",
                    self.light_cache_res,
                    strata_render::gpu::light_cache::MIN_RES
                        ..=strata_render::gpu::light_cache::MAX_RES,
                )?;
            }
            ensure(!self.mode.is_mip(), || {
                "--shadows is DVR and isosurface lighting: not for MIP".to_string()
            })?;
            // The adaptive pass traces exact shadow rays per lit segment; the light cache is
            // the raycaster's (adaptive/gpu.rs).
            ensure(
                !(self.mode == Mode::Adaptive && self.shadows == ShadowsOption::Cache),
                || "--mode adaptive takes --shadows exact, not cache".to_string(),
            )?;
        }
        if let Some(radius) = self.occlusion {
            check_range("occlusion", radius, 0.0..=MAX_OCCLUSION_MM)?;
            check_range("shadow-step", self.shadow_step, 0.05..=1000.0)?;
        }
        if let Some(g) = self.scattering {
            let m = strata_render::model::settings::SCATTERING_MAX_ABS_G;
            check_range("scattering", g, -m..=m)?;
            check_range("scattering-blend", self.scattering_blend, 0.0..=1.0)?;
        }
        for (flag, on) in [
            ("--occlusion", self.occlusion.is_some()),
            ("--scattering", self.scattering.is_some()),
        ] {
            ensure(!on || !self.mode.is_mip(), || {
                format!("{flag} is DVR and isosurface lighting: it does not apply to MIP")
            })?;
        }
        if let Some(n) = self.progressive {
            ensure((1..=MAX_PROGRESSIVE_FRAMES).contains(&n), || {
                format!(
                    "--progressive {n}: the number of frames must be 1..={MAX_PROGRESSIVE_FRAMES}"
                )
            })?;
            ensure(
                !self.reference && self.jitter && !self.mode.is_adaptive(),
                || {
                    "--progressive averages jittered frames of the GPU raycaster: it does not \
                     combine with --reference (already the converged image), --orbit, \
                     --no-jitter or --mode adaptive"
                        .to_string()
                },
            )?;
        }
        if let Some(direction) = self.light_dir {
            check_light_dir(&format!("{direction:?}"), direction)?;
        }
        Ok(())
    }

    /// True when the frame is rendered from a fixed cut loaded up front (`level`), false when
    /// it streams.
    pub fn renders_fixed_cut(&self) -> bool {
        self.up_front || self.reference || self.mode.is_adaptive() || self.progressive.is_some()
    }

    /// The orbit camera the options ask for.
    pub fn camera(&self, geometry: &VolumeGeometry) -> Camera {
        let projection = if self.orthographic {
            Projection::Orthographic {
                height_mm: geometry.bounding_radius_mm() * 2.0 / self.zoom.max(1e-3),
            }
        } else {
            Projection::Perspective { fov_y_deg: 30.0 }
        };
        Camera::orbit(
            geometry,
            self.azimuth,
            self.elevation,
            self.zoom,
            projection,
        )
    }

    /// The renderer's settings of these options.
    pub fn settings(&self) -> RenderSettings {
        RenderSettings {
            width: self.width,
            height: self.height,
            mode: match self.mode {
                Mode::Dvr | Mode::Adaptive => RenderMode::Dvr,
                Mode::Mip | Mode::AdaptiveMip => RenderMode::Mip,
                Mode::Iso => RenderMode::Isosurface,
            },
            quality: self.step,
            jitter: self.jitter,
            shading: (self.shading
                || self.shadows != ShadowsOption::Off
                || self.occlusion.is_some()
                || self.scattering.is_some()
                || self.mode == Mode::Iso)
                .then(Shading::default),
            smooth_transitions: self.smooth,
            iso_value: self.iso,
            exact_trilinear: self.exact_trilinear,
            light: KeyLight {
                direction: match self.light_dir {
                    Some(direction) => LightDirection::Camera(direction),
                    // The cache holds one light direction; the headlight's is each ray's own.
                    // Along the view axis it is the headlight of an orthographic view.
                    None if self.shadows == ShadowsOption::Cache => {
                        LightDirection::Camera([0.0, 0.0, 1.0])
                    }
                    None => LightDirection::Headlight,
                },
                ..KeyLight::default()
            },
            shadows: Shadows {
                mode: match self.shadows {
                    ShadowsOption::Off => ShadowMode::Off,
                    ShadowsOption::Exact => ShadowMode::Exact,
                    ShadowsOption::Cache => ShadowMode::Cache,
                },
                step: self.shadow_step,
                cache_res: self.light_cache_res,
            },
            occlusion: self.occlusion.map(|radius_mm| Occlusion { radius_mm }),
            scattering: self.scattering.map(|g| Scattering {
                g,
                blend: self.scattering_blend,
            }),
            ..RenderSettings::default()
        }
    }

    /// The streaming loader's configuration of these options.
    pub fn streaming_config(&self) -> StreamingConfig {
        let defaults = StreamingConfig::default();
        StreamingConfig {
            max_voxel_pixels: self.quality,
            traversal: self.traversal,
            gpu_budget_bytes: self.gpu_mib.map_or(defaults.gpu_budget_bytes, |m| m << 20),
            ..defaults
        }
    }
}

/// One rendered frame: `width × height` premultiplied RGBA8, rows top to bottom.
#[derive(Clone, Debug)]
pub struct RenderedFrame {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
}

/// Renders one frame of `source` as `options` say: streamed until converged (the default),
/// or from the fixed cut of `options.level`. `name` names the source in messages; `report`
/// receives the progress notes `strata render` prints (the adapter, timings, warnings).
pub fn render(
    source: Arc<dyn VolumeSource>,
    name: &str,
    options: &RenderOptions,
    report: &mut dyn FnMut(String),
) -> Result<RenderedFrame> {
    options.validate()?;
    if options.mode.is_adaptive() {
        if !options.up_front && !options.reference {
            report("--mode adaptive renders a fixed cut: loading --level up front".into());
        }
    } else if options.progressive.is_some() && !options.up_front {
        // A still view of a cut that changes while it streams would restart the mean.
        report("--progressive renders a fixed cut: loading --level up front".into());
    }
    if options.renders_fixed_cut() {
        render_fixed_cut(source.as_ref(), name, options, report)
    } else {
        let ctx = GpuContext::headless()?;
        report(format!("GPU: {}", ctx.adapter_name()));
        let started = Instant::now();
        let mut volume = open_streaming(&ctx, source, name, options, report)?;
        let opened = started.elapsed().as_secs_f64();
        let camera = options.camera(volume.geometry());
        render_streamed(&ctx, &mut volume, &camera, options, opened, report)
    }
}

/// The streaming loader over `source` with the options' budget, quality, traversal and
/// transfer function.
pub fn open_streaming(
    ctx: &GpuContext,
    source: Arc<dyn VolumeSource>,
    name: &str,
    options: &RenderOptions,
    report: &mut dyn FnMut(String),
) -> Result<StreamingVolume> {
    let tf = choose_transfer_function(options.tf.as_deref(), &source.header().modality)?;
    let volume =
        StreamingVolume::new(ctx, source, &tf, options.streaming_config()).map_err(|source| {
            HeadlessError::Stream {
                name: name.to_string(),
                source,
            }
        })?;
    if let Some(note) = volume.traversal_note() {
        report(note.to_string());
    }
    Ok(volume)
}

/// Frames of `volume` from `camera` until the image converges (or `max_frames`); the last
/// one. `opened_s` is how long opening took, for the summary line.
pub fn render_streamed(
    ctx: &GpuContext,
    volume: &mut StreamingVolume,
    camera: &Camera,
    options: &RenderOptions,
    opened_s: f64,
    report: &mut dyn FnMut(String),
) -> Result<RenderedFrame> {
    let settings = options.settings();
    let started = Instant::now();
    let (frame, history) =
        volume.render_until_converged(ctx, camera, &settings, options.max_frames.max(1))?;
    for failure in volume.take_failures() {
        report(format!(
            "warning: {}; its parent is shown there instead",
            failure.message
        ));
    }
    let Some(last) = history.last() else {
        return Err(HeadlessError::NoFrame);
    };
    if let Some(lost) = history.iter().find(|s| s.source_status.is_retrying()) {
        report(format!(
            "warning: connection to the source was lost during the render ({:?}); requests were retried",
            lost.source_status
        ));
    }
    if last.retried_total > 0 || last.cancelled_in_flight_total > 0 {
        report(format!(
            "remote: {} requests retried ({} records damaged in transit), {} stale requests cancelled in flight, at most {} in flight",
            last.retried_total,
            last.checksum_failures_total,
            last.cancelled_in_flight_total,
            last.max_in_flight
        ));
    }
    report(format!(
        "{} traversal: {} index bytes on the GPU",
        volume.traversal().name(),
        volume.gpu_index_bytes()
    ));
    report(format!(
        "{} after {} frames in {:.2} s (open {:.2} s): {} bricks on the GPU per level {:?}, {:.1} MB read",
        if last.converged {
            last.convergence_status()
        } else {
            "not converged (raise --max-frames)".into()
        },
        history.len(),
        started.elapsed().as_secs_f64(),
        opened_s,
        last.gpu_slots_used,
        last.gpu_resident_per_level,
        last.stored_bytes_read_total as f64 / 1e6
    ));
    Ok(RenderedFrame {
        width: settings.width,
        height: settings.height,
        rgba: frame.rgba,
    })
}

/// The frame of the fixed cut at `options.level`, loaded up front: on the GPU (raycaster or
/// adaptive pass, flat table or octree, one frame or the progressive mean) or the f64
/// reference.
fn render_fixed_cut(
    store: &dyn VolumeSource,
    name: &str,
    options: &RenderOptions,
    report: &mut dyn FnMut(String),
) -> Result<RenderedFrame> {
    let adaptive = options.mode.is_adaptive();
    let header = store.header().clone();
    let geometry = header.geometry.clone();
    let mapping = header.value_mapping.mapping;
    let tf = choose_transfer_function(options.tf.as_deref(), &header.modality)?;
    let physical_range = (
        mapping.physical(header.stored_range[0] as f64),
        mapping.physical(header.stored_range[1] as f64),
    );
    let tf_table = tf.table(
        physical_range.0.min(physical_range.1),
        physical_range.0.max(physical_range.1),
    );
    let mut table = page_table_for_cut(store, &geometry, |_| options.level);
    let settings = options.settings();
    if matches!(settings.mode, RenderMode::Dvr) {
        classify_empty(store, &mut table, mapping, &tf_table);
    }
    let camera = options.camera(&geometry);
    let budget = options.gpu_mib.map(|m| m << 20);
    // The GPU paths' device, made before the bricks are read: a level over the budget (or the
    // device) is refused before reading it.
    let gpu = if options.reference {
        None
    } else {
        let ctx = GpuContext::headless()?;
        report(format!("GPU: {}", ctx.adapter_name()));
        check_cut_fits(
            &ctx,
            slots_needed(&table),
            budget,
            &format!("level {} of {name}", options.level),
        )?;
        Some(ctx)
    };
    let t_load = Instant::now();
    let bricks = ResidentBricks::load(store, &table)?;
    report(format!(
        "loaded {} bricks of level {} in {:.2} s",
        bricks.len(),
        options.level,
        t_load.elapsed().as_secs_f64()
    ));

    let t = Instant::now();
    // The per-block oracle (the render mode's): a distance per 2³ block of every brick,
    // bounding the lit colour's change where the settings light the samples.
    let oracle = || {
        block_oracle_with(
            &table,
            &bricks,
            mapping,
            &tf,
            options.oracle_epsilon,
            AdaptiveConfig::default().l_max,
            settings.quality,
            OracleTarget::for_settings(&settings),
        )
    };
    let reference_scene = || ReferenceScene {
        source: &bricks,
        page_table: &table,
        geometry: &geometry,
        mapping,
        transfer_function: &tf,
        tf_range: (tf_table.lo, tf_table.hi),
    };
    let rgba = match gpu {
        None if adaptive && !settings.effective_key_light() => {
            // The f64 transcription of the same frame (its oracle, its pre-integration table).
            let integral = SegmentIntegralTable::build(
                &tf,
                tf_table.lo,
                tf_table.hi,
                geometry.finest_spacing_mm(),
            );
            render_adaptive_reference(
                &reference_scene(),
                &camera,
                &settings,
                &AdaptiveConfig::default(),
                &oracle(),
                AdaptiveOptics::Table(&integral),
            )?
            .rgba
        }
        None => {
            render_reference(
                &reference_scene(),
                &camera,
                &settings,
                ReferenceOptions::default(),
            )?
            .rgba
        }
        Some(ctx) if adaptive => {
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
            let scene = FrameInputs {
                cache: &cut.cache,
                page_table: &cut.page_table,
                transfer_function: &cut.transfer_function,
                geometry: &geometry,
                mapping,
                camera: &camera,
                settings: &settings,
            };
            let frame = pass.render_blocking(&ctx, &scene, &AdaptiveConfig::default())?;
            report(format!(
                "adaptive: {} sampling operations per level {:?} (+{} apron), {} synthesis operations",
                frame.total_samples(),
                frame.samples_per_level,
                frame.total_apron_samples(),
                frame.total_syntheses()
            ));
            if frame.shadow_rays > 0 {
                report(format!("adaptive: {} shadow rays", frame.shadow_rays));
            }
            frame.rgba
        }
        Some(ctx) => {
            let mut cut = GpuCut::upload_within(
                &ctx,
                &bricks,
                &table,
                geometry.page_dims(),
                &tf_table,
                budget,
            )?;
            match options.traversal.unwrap_or(Traversal::Flat) {
                Traversal::Flat => {
                    let frame =
                        cut.render_blocking(&ctx, &geometry, mapping, &camera, &settings)?;
                    match options.progressive {
                        None => frame.rgba,
                        // The frame above also uploaded the MIP value bounds the scene needs.
                        Some(frames) => {
                            let scene = FrameInputs {
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
                Traversal::Octree => {
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
                    report(format!(
                        "octree index: {} leaves, {} bytes on the GPU (flat table: {} bytes)",
                        index.visibility_entries(),
                        index.gpu_index_bytes(),
                        cut.page_table.gpu_index_bytes()
                    ));
                    let scene = FrameInputs {
                        cache: &cut.cache,
                        page_table: &index,
                        transfer_function: &cut.transfer_function,
                        geometry: &geometry,
                        mapping,
                        camera: &camera,
                        settings: &settings,
                    };
                    match options.progressive {
                        None => cut.raycaster.render_blocking(&ctx, &scene)?.rgba,
                        Some(frames) => render_still(&ctx, &mut cut.raycaster, &scene, frames)?,
                    }
                }
            }
        }
    };
    report(format!(
        "rendered {}x{} in {:.2} s ({})",
        settings.width,
        settings.height,
        t.elapsed().as_secs_f64(),
        if options.reference {
            "CPU reference".to_string()
        } else if let Some(n) = options.progressive {
            format!("GPU, mean of {n} jittered frames")
        } else {
            "GPU".to_string()
        }
    ));
    Ok(RenderedFrame {
        width: settings.width,
        height: settings.height,
        rgba,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn error(options: RenderOptions) -> String {
        match options.validate() {
            Ok(()) => panic!("{options:?} accepted"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn names_parse_and_unknown_names_are_refused_with_the_choices() {
        assert_eq!(Mode::from_name("adaptive-mip").unwrap(), Mode::AdaptiveMip);
        assert_eq!(Mode::from_name("iso").unwrap(), Mode::Iso);
        let e = Mode::from_name("volume").unwrap_err().to_string();
        assert!(e.contains("dvr, mip, iso, adaptive, adaptive-mip"), "{e}");
        assert_eq!(
            ShadowsOption::from_name("cache").unwrap(),
            ShadowsOption::Cache
        );
        assert!(ShadowsOption::from_name("soft").is_err());
        assert_eq!(traversal_from_name("octree").unwrap(), Traversal::Octree);
        assert!(traversal_from_name("bvh").is_err());
        assert_eq!(parse_light_dir("1, 0,-2").unwrap(), [1.0, 0.0, -2.0]);
        assert!(parse_light_dir("1,0").is_err());
        assert!(parse_light_dir("0,0,0")
            .unwrap_err()
            .to_string()
            .contains("finite and non-zero"));
    }

    #[test]
    fn bad_values_and_combinations_are_refused_naming_the_flag() {
        let ok = RenderOptions::default();
        ok.validate().unwrap();
        assert!(error(RenderOptions {
            width: 0,
            ..ok.clone()
        })
        .contains("--size 0x512"));
        assert!(error(RenderOptions {
            azimuth: f64::NAN,
            ..ok.clone()
        })
        .contains("--azimuth must be a finite number"));
        assert!(error(RenderOptions {
            step: 100.0,
            ..ok.clone()
        })
        .contains("--step must be a number between"));
        assert!(error(RenderOptions {
            mode: Mode::Mip,
            shadows: ShadowsOption::Exact,
            ..ok.clone()
        })
        .contains("not for MIP"));
        assert!(error(RenderOptions {
            progressive: Some(4),
            reference: true,
            ..ok.clone()
        })
        .contains("--progressive averages jittered frames"));
        assert!(error(RenderOptions {
            light_dir: Some([0.0, f64::INFINITY, 1.0]),
            ..ok.clone()
        })
        .contains("--light-dir"));
        assert!(error(RenderOptions {
            max_frames: 0,
            ..ok
        })
        .contains("--max-frames"));
    }

    #[test]
    fn fixed_cut_or_streaming_follows_the_options() {
        let streaming = RenderOptions::default();
        assert!(!streaming.renders_fixed_cut());
        for fixed in [
            RenderOptions {
                up_front: true,
                ..RenderOptions::default()
            },
            RenderOptions {
                mode: Mode::Adaptive,
                ..RenderOptions::default()
            },
            RenderOptions {
                progressive: Some(2),
                ..RenderOptions::default()
            },
        ] {
            assert!(fixed.renders_fixed_cut(), "{fixed:?}");
        }
    }

    #[test]
    fn transfer_functions_are_presets_files_or_a_clear_error() {
        assert_eq!(
            choose_transfer_function(None, "CT").unwrap().name,
            TransferFunction::preset("ct-bone").unwrap().name
        );
        let e = choose_transfer_function(Some("/nowhere/tf.json"), "CT")
            .unwrap_err()
            .to_string();
        assert!(e.contains("/nowhere/tf.json does not exist"), "{e}");
        let e = choose_transfer_function(Some("rainbow"), "MR")
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown transfer function 'rainbow'"), "{e}");
    }
}
