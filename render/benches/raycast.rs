//! Raycast benchmark on lavapipe (or whatever adapter is found), comparable with
//! bench/peers/vtk_peer_bench.py: same 256³ u8 phantom, same transfer function, 512², step 0.5
//! voxel, camera reset to the bounding sphere with a 30° view angle, azimuth +30° per frame.
//!
//! Run: cargo bench -p strata-render --bench raycast   (or bench/peers/compare_with_vtk.sh,
//!      which runs this and VTK in one session and prints the ratios)
//! Env: STRATA_BENCH_SIZE (default 512), STRATA_BENCH_FRAMES (default 5),
//!      STRATA_BENCH_VOLUME (default 256), STRATA_BENCH_REF_SIZE (default 128),
//!      STRATA_BENCH_STEPS (default 0.5,1,2,3: the peer runs at 0.5; the rest find equal PSNR),
//!      STRATA_BENCH_SAVE=DIR (keep the PSNR images as PPM in DIR),
//!      STRATA_BENCH_EFFECTS=shadows,shading (only those rows of the effect table, nothing else;
//!      also occlusion, scattering, shadows+scattering, progressive),
//!      STRATA_BENCH_LIGHT_CACHE_RES (default 2: voxels per light-cache texel, the cache row),
//!      STRATA_BENCH_DUMP_SHADER=FILE (write the composed raycast WGSL there and go on),
//!      STRATA_BENCH_SHADER=FILE (the main table's raycaster built from that WGSL, a variant
//!      of the dumped source: ablations such as "no TF fetch" measured without a rebuild).
//!
//! Prints ms/frame (median), samples/s, the sampling-only kernel's samples/s measured in the
//! same run (the ceiling: same texture, same fetch count, no page lookup, TF or compositing),
//! and PSNR against the f64 CPU reference at a smaller image size.

use std::time::Instant;
use strata_render::gpu::light_cache;
use strata_render::passes::progressive::jittered_frame;
use strata_render::reference::metrics;
use strata_render::reference::{render_reference, ReferenceOptions, ReferenceScene};
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

const SAMPLING_ONLY: &str = r#"
@group(0) @binding(0) var cache: texture_3d<f32>;
@group(0) @binding(1) var cache_sampler: sampler;
@group(0) @binding(2) var<storage, read_write> sink: array<f32>;
@group(0) @binding(3) var<uniform> params: vec4<u32>; // width, height, samples per ray, 0
@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if gid.x >= params.x || gid.y >= params.y { return; }
    let dims = vec3<f32>(textureDimensions(cache));
    // A diagonal ray through the cache with half-texel steps, like a 0.5-voxel raycast.
    var p = vec3<f32>(f32(gid.x) * dims.x / f32(params.x), f32(gid.y) * dims.y / f32(params.y), 0.5);
    let d = normalize(vec3<f32>(0.3, 0.2, 1.0)) * 0.5;
    var acc = 0.0;
    for (var i = 0u; i < params.z; i++) {
        acc += textureSampleLevel(cache, cache_sampler, fract(p / dims), 0.0).r;
        p += d;
    }
    sink[gid.y * params.x + gid.x] = acc;
}
"#;

/// Sampling-only kernel: the same cache texture and sampler, the same number of trilinear
/// fetches per pixel, nothing else. Its rate is what the raycaster could reach if page lookup,
/// transfer function, compositing and control flow were free.
struct SamplingOnly {
    pipeline: wgpu::ComputePipeline,
    bind: wgpu::BindGroup,
    size: u32,
}

impl SamplingOnly {
    fn new(ctx: &GpuContext, cache: &BrickCache, size: u32, samples_per_ray: u32) -> Self {
        let device = &ctx.device;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("sampling only"),
            source: wgpu::ShaderSource::Wgsl(SAMPLING_ONLY.into()),
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("sampling only"),
            layout: None,
            module: &module,
            entry_point: Some("main"),
            compilation_options: Default::default(),
            cache: None,
        });
        let sink = device.create_buffer(&wgpu::BufferDescriptor {
            label: None,
            size: size as u64 * size as u64 * 4,
            usage: wgpu::BufferUsages::STORAGE,
            mapped_at_creation: false,
        });
        let params = device.create_buffer(&wgpu::BufferDescriptor {
            label: None,
            size: 16,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        ctx.queue.write_buffer(
            &params,
            0,
            bytemuck::cast_slice(&[size, size, samples_per_ray, 0u32]),
        );
        let filter = if cache.format.filterable() {
            wgpu::FilterMode::Linear
        } else {
            wgpu::FilterMode::Nearest
        };
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            mag_filter: filter,
            min_filter: filter,
            ..Default::default()
        });
        let bind = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::TextureView(&cache.view),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::Sampler(&sampler),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: sink.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: params.as_entire_binding(),
                },
            ],
        });
        SamplingOnly {
            pipeline,
            bind,
            size,
        }
    }

    fn run(&self, ctx: &GpuContext) {
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &self.bind, &[]);
            pass.dispatch_workgroups(self.size.div_ceil(8), self.size.div_ceil(8), 1);
        }
        let idx = ctx.queue.submit(Some(enc.finish()));
        ctx.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(idx),
                timeout: None,
            })
            .expect("poll");
    }
}

/// What every frame of this bench draws; only camera and settings vary.
struct Drawn<'a> {
    cache: &'a BrickCache,
    page_table: &'a GpuPageTable,
    transfer_function: &'a GpuTransferFunction,
    volume: &'a BrickedVolume,
}

impl Drawn<'_> {
    fn scene<'s>(&'s self, camera: &'s Camera, settings: &'s RenderSettings) -> FrameInputs<'s> {
        FrameInputs {
            cache: self.cache,
            page_table: self.page_table,
            transfer_function: self.transfer_function,
            geometry: &self.volume.geometry,
            mapping: self.volume.mapping,
            camera,
            settings,
        }
    }
}

/// The effect table: what an effect costs on, off and never built (see the comment inside).
/// `only`: effect names (prefixes) to run, from STRATA_BENCH_EFFECTS; None: all.
#[allow(clippy::too_many_arguments)]
fn effect_table(
    ctx: &GpuContext,
    cache: &BrickCache,
    drawn: &Drawn,
    raycaster: &mut Raycaster,
    camera_at: &dyn Fn(u32) -> Camera,
    size: u32,
    frames: u32,
    only: Option<&[String]>,
) {
    let volume = drawn.volume;
    // What an effect costs, and what it costs when off. "never" is a raycaster built from the
    // shader with that effect's override turned into `const false`, i.e. a build that never had
    // the effect: the specialised pipeline with the effect off should take the same time.
    // DVR at step 0.5 with every effect off is the base; rounds interleave all variants.
    let base = RenderSettings {
        width: size,
        height: size,
        mode: RenderMode::Dvr,
        quality: 0.5,
        jitter: false,
        early_termination: None,
        skip_empty: false,
        smooth_transitions: false,
        ..Default::default()
    };
    let shaded = RenderSettings {
        shading: Some(Shading::default()),
        ..base.clone()
    };
    // The shadows row's "off": shaded, key-lit, and with empty skipping and early termination
    // on as any real frame has them (without them every sample of the volume would trace a
    // shadow ray, a cost no view pays).
    let key_lit = RenderSettings {
        light: KeyLight {
            direction: LightDirection::Camera([0.5, 0.5, 0.7]),
            intensity: 1.0,
        },
        early_termination: Some(0.99),
        skip_empty: true,
        ..shaded.clone()
    };
    let cache_res = env_u32("STRATA_BENCH_LIGHT_CACHE_RES", 2) as f64;
    let clip = ClipPlane {
        normal: [0.0, 0.0, 1.0],
        offset_mm: volume.geometry.centre_patient().z - 40.0,
    };
    // (name, override, on); "off" is `base`, or for effects that need another effect on
    // (shadows need shading), the settings in `off_for`.
    let effects: Vec<(&str, &str, RenderSettings)> = vec![
        ("shading", "SHADING", shaded.clone()),
        (
            "jitter",
            "JITTER",
            RenderSettings {
                jitter: true,
                ..base.clone()
            },
        ),
        (
            "clip plane",
            "CLIP_PLANE",
            RenderSettings {
                clip_plane: Some(clip),
                ..base.clone()
            },
        ),
        (
            "pre-integration",
            "PREINTEGRATED",
            RenderSettings {
                preintegrated: true,
                ..base.clone()
            },
        ),
        (
            "sample counter",
            "COUNT_SAMPLES",
            RenderSettings {
                count_samples: true,
                ..base.clone()
            },
        ),
        (
            "early termination",
            "EARLY_TERMINATION",
            RenderSettings {
                early_termination: Some(0.99),
                ..base.clone()
            },
        ),
        (
            "empty skipping",
            "SKIP_EMPTY",
            RenderSettings {
                skip_empty: true,
                ..base.clone()
            },
        ),
        // This cut is uniform, so "on" asks for smoothing and gets the same pipeline as "off"
        // (the cut decides); what smoothing costs on a mixed cut is `strata-bench transitions`.
        (
            "smooth transitions",
            "SMOOTH_TRANSITIONS",
            RenderSettings {
                smooth_transitions: true,
                ..base.clone()
            },
        ),
        // Exact shadow rays (shadows.rs, step 1 voxel), shaded DVR with a key light from the
        // upper right: "off" is the same key light unshadowed (`key_lit`), "never built" a
        // shader without SHADOWS.
        (
            "shadows (exact)",
            "SHADOWS",
            RenderSettings {
                shadows: Shadows {
                    mode: ShadowMode::Exact,
                    step: 1.0,
                    ..Shadows::default()
                },
                ..key_lit.clone()
            },
        ),
        // Cache-mode shadows (light_cache.rs, 2 voxels per texel unless the environment says,
        // its rays at step 1 voxel):
        // the same light; the cache is built in the warm-up round and kept (nothing it was
        // built from changes), so "on" is the lookup's cost. Its build time is printed below.
        (
            "shadows (cache)",
            "LIGHT_CACHE",
            RenderSettings {
                shadows: Shadows {
                    mode: ShadowMode::Cache,
                    step: 1.0,
                    cache_res,
                },
                ..key_lit.clone()
            },
        ),
        // Ambient occlusion (ambient_occlusion.rs): 16 rays of 3 voxels at the shadow step of
        // 1 voxel, the same key light unshadowed: "off" is `key_lit`, "never built" a shader
        // without OCCLUSION.
        (
            "occlusion",
            "OCCLUSION",
            RenderSettings {
                occlusion: Some(Occlusion {
                    radius_mm: 3.0 * volume.geometry.finest_spacing_mm(),
                }),
                ..key_lit.clone()
            },
        ),
        // Single scattering (scattering.rs, g = 0.5, blend 0.5) without shadows: the phase and
        // the hybrid weight alone (with shadows each sample also pays the shadows row).
        (
            "scattering",
            "SCATTERING",
            RenderSettings {
                scattering: Some(Scattering { g: 0.5, blend: 0.5 }),
                ..key_lit.clone()
            },
        ),
        // Both at once, as VTK's VolumetricScatteringBlending does them (its shadow rays only
        // light the volumetric part): exact shadows and scattering g = 0.5, blend 0.5 (the VTK
        // peer, bench/peers/vtk_cine_bench.py). "never built" drops SCATTERING only.
        (
            "shadows+scattering",
            "SCATTERING",
            RenderSettings {
                shadows: Shadows {
                    mode: ShadowMode::Exact,
                    step: 1.0,
                    ..Shadows::default()
                },
                scattering: Some(Scattering { g: 0.5, blend: 0.5 }),
                ..key_lit.clone()
            },
        ),
    ];
    let effects: Vec<_> = effects
        .into_iter()
        .filter(|(name, _, _)| only.is_none_or(|o| o.iter().any(|w| name.starts_with(w.as_str()))))
        .collect();
    let off_for = |name: &str| {
        if ["shadows", "occlusion", "scattering"]
            .iter()
            .any(|lit| name.starts_with(lit))
        {
            &key_lit
        } else {
            &base
        }
    };
    let mut never_had: Vec<Raycaster> = effects
        .iter()
        .map(|(_, name, _)| {
            let declared = ["false", "true"]
                .map(|default| format!("override {name}: bool = {default};"))
                .into_iter()
                .find(|d| Raycaster::shader_source().contains(d))
                .unwrap_or_else(|| panic!("override {name} not in the shader"));
            let variant = Raycaster::shader_source()
                .replace(&declared, &format!("const {name}: bool = false;"));
            Raycaster::with_shader_source(ctx, cache, &variant)
        })
        .collect();
    let camera = camera_at(1);
    let mut effect_times = vec![[Vec::new(), Vec::new(), Vec::new()]; effects.len()];
    for round in 0..=frames {
        for (i, (name, _, on)) in effects.iter().enumerate() {
            let off = off_for(name);
            for (variant, settings) in [(0, off), (1, off), (2, on)] {
                let scene = drawn.scene(&camera, settings);
                let rc = if variant == 1 {
                    &mut never_had[i]
                } else {
                    &mut *raycaster
                };
                let t = Instant::now();
                rc.render_and_wait(ctx, &scene).expect("render");
                if round > 0 {
                    effect_times[i][variant].push(t.elapsed().as_secs_f64() * 1e3);
                }
            }
        }
    }
    println!("\nEffect cost, DVR step 0.5 at {size}², median of {frames} interleaved rounds (ms):");
    println!(
        "{:<20} {:>10} {:>14} {:>12} {:>10} {:>10}",
        "effect", "off", "never built", "never/off", "on", "on/off"
    );
    for (i, (name, _, _)) in effects.iter().enumerate() {
        let [off, never, on] = effect_times[i].clone().map(median);
        println!(
            "{name:<20} {off:>10.1} {never:>14.1} {:>12.3} {on:>10.1} {:>10.3}",
            never / off,
            on / off
        );
    }
    // Progressive refinement (progressive.rs): a jittered base frame alone against the same
    // frame folded into the running mean, interleaved; the difference is the accumulate pass
    // (one compute pass over the image), which only a still view pays.
    if only.is_none_or(|o| o.iter().any(|w| "progressive".starts_with(w.as_str()))) {
        let jittered = RenderSettings {
            jitter: true,
            ..base.clone()
        };
        let key = ViewKey::new(&camera, &jittered);
        let mut accumulator = Accumulator::new(ctx);
        let (mut alone, mut folded) = (Vec::new(), Vec::new());
        for round in 0..=frames {
            for fold in [false, true] {
                let s = jittered_frame(&jittered, round);
                let scene = drawn.scene(&camera, &s);
                let t = Instant::now();
                raycaster.render(ctx, &scene).expect("render");
                if fold {
                    let output = raycaster.output_texture().expect("rendered");
                    accumulator
                        .accumulate(ctx, &key, output)
                        .expect("accumulate");
                }
                ctx.wait_idle().expect("wait");
                if round > 0 {
                    let ms = t.elapsed().as_secs_f64() * 1e3;
                    if fold {
                        folded.push(ms)
                    } else {
                        alone.push(ms)
                    }
                }
            }
        }
        let (alone, folded) = (median(alone), median(folded));
        println!(
            "progressive {:<8} {alone:>10.1} {:>14} {:>12} {folded:>10.1} {:>10.3}   \
             (off: a jittered frame; on: it plus the accumulate pass, {} frames in the mean)",
            "",
            "-",
            "-",
            folded / alone,
            accumulator.frames()
        );
    }
    // The light cache's build: frames whose light turned by a hair (each rebuilds the cache)
    // against the next frame with that same light (which does not), interleaved; the
    // difference of the medians is the build.
    if let Some((_, _, cached)) = effects
        .iter()
        .find(|(name, _, _)| *name == "shadows (cache)")
    {
        let builds_before = raycaster.light_cache_builds();
        let (mut rebuilt, mut kept) = (Vec::new(), Vec::new());
        for round in 0..=frames {
            // A new direction (rebuilds), then the same again (kept).
            for rebuild in [true, false] {
                let mut s = cached.clone();
                s.light.direction =
                    LightDirection::Camera([0.5, 0.5, 0.7 + 1e-3 * (round + 1) as f64]);
                let scene = drawn.scene(&camera, &s);
                let t = Instant::now();
                raycaster.render_and_wait(ctx, &scene).expect("render");
                if round > 0 {
                    let ms = t.elapsed().as_secs_f64() * 1e3;
                    if rebuild {
                        rebuilt.push(ms)
                    } else {
                        kept.push(ms)
                    }
                }
            }
        }
        let (rebuilt, kept) = (median(rebuilt), median(kept));
        let dims = light_cache::grid_dims(volume.geometry.dims, cache_res);
        println!(
            "light cache {dims:?} texels ({cache_res} voxels each): frame with a rebuild {rebuilt:.1} ms, \
             without {kept:.1} ms, build ≈ {:.1} ms ({} builds)",
            rebuilt - kept,
            raycaster.light_cache_builds() - builds_before
        );
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
    let size = env_u32("STRATA_BENCH_SIZE", 512);
    let frames = env_u32("STRATA_BENCH_FRAMES", 5).max(1);
    let ref_size = env_u32("STRATA_BENCH_REF_SIZE", 128);
    println!("adapter: {}", ctx.adapter_name());
    let t = Instant::now();
    let volume = phantom::vtk_peer_phantom(n).expect("phantom");
    println!(
        "phantom {n}³ bricked in {:.0} ms ({} levels)",
        t.elapsed().as_secs_f64() * 1e3,
        volume.level_count()
    );
    let tf = phantom::vtk_peer_transfer_function();
    let tf_table = tf.table(0.0, 255.0);
    let mut page_table = volume.page_table_uniform(0);
    volume.classify_empty(&mut page_table, &tf_table);
    let nodes = BrickedVolume::resident_nodes(&page_table).len() as u32;
    // R16Unorm by default; STRATA_BENCH_R8=1 uses the 8-bit cache (as VTK's 8-bit texture).
    // On lavapipe it made no measurable difference: the raycast is compute-bound there.
    let eight_bit = std::env::var("STRATA_BENCH_R8").is_ok();
    let cache = BrickCache::new(
        &ctx.device,
        CacheConfig {
            max_slots: Some(nodes),
            eight_bit,
            ..Default::default()
        },
    )
    .expect("cache");
    volume
        .upload(&cache, &ctx.queue, &page_table)
        .expect("upload");
    let gpu_table =
        GpuPageTable::new(&ctx.device, volume.geometry.page_dims(), &cache).expect("page table");
    gpu_table
        .update(&ctx.queue, &page_table)
        .expect("page table");
    gpu_table
        .update_value_max(
            &ctx.queue,
            &page_table.value_max_physical(volume.mapping, |l, n| volume.node_range(l, n)),
        )
        .expect("page value bounds");
    let gpu_tf = GpuTransferFunction::new(&ctx.device, &ctx.queue, &tf_table);
    if let Ok(path) = std::env::var("STRATA_BENCH_DUMP_SHADER") {
        std::fs::write(&path, Raycaster::shader_source()).expect("dump shader");
    }
    let mut raycaster = match std::env::var("STRATA_BENCH_SHADER") {
        Ok(path) => {
            let wgsl = std::fs::read_to_string(&path).expect("read STRATA_BENCH_SHADER");
            println!("raycast shader: {path}");
            Raycaster::with_shader_source(&ctx, &cache, &wgsl)
        }
        Err(_) => Raycaster::new(&ctx, &cache),
    };
    let drawn = Drawn {
        cache: &cache,
        page_table: &gpu_table,
        transfer_function: &gpu_tf,
        volume: &volume,
    };
    println!(
        "cache {:?} ({} slots, {} used, {:?}), empty pages {}/{}",
        cache.texel_dims(),
        cache.slot_count(),
        nodes,
        cache.format,
        page_table.entries.iter().filter(|e| e.empty).count(),
        page_table.entries.len()
    );

    // As vtkRenderer::ResetCamera then Azimuth(30) per frame: looking down -z with +y up,
    // view angle 30°, distance = bounding-sphere radius / sin(15°), orbiting about +y.
    let centre = volume.geometry.centre_patient();
    let distance = volume.geometry.bounding_radius_mm() / 15f64.to_radians().sin();
    let camera_at = |frame: u32| {
        let az = (30.0 * frame as f64).to_radians();
        let eye = centre + glam::DVec3::new(az.sin(), 0.0, az.cos()) * distance;
        Camera::look_at(
            eye.into(),
            centre.into(),
            [0.0, 1.0, 0.0],
            Projection::Perspective { fov_y_deg: 30.0 },
        )
    };
    // STRATA_BENCH_EFFECTS=shadows,shading: only those rows of the effect table, nothing else.
    if let Ok(list) = std::env::var("STRATA_BENCH_EFFECTS") {
        let only: Vec<String> = list.split(',').map(|w| w.trim().to_owned()).collect();
        effect_table(
            &ctx,
            &cache,
            &drawn,
            &mut raycaster,
            &camera_at,
            size,
            frames,
            Some(&only),
        );
        return;
    }
    let quick = std::env::var("STRATA_BENCH_QUICK").is_ok();
    // Steps in finest voxels. 0.5 is the peer's setting; coarser steps show what the same
    // accuracy as the peer costs here (the goal is "at equal or better PSNR").
    let steps: Vec<f64> = std::env::var("STRATA_BENCH_STEPS")
        .ok()
        .map(|v| v.split(',').filter_map(|s| s.trim().parse().ok()).collect())
        .filter(|v: &Vec<f64>| !v.is_empty())
        .unwrap_or_else(|| {
            if quick {
                vec![0.5]
            } else {
                vec![0.5, 1.0, 2.0, 3.0]
            }
        });
    // (name, mode, skip empty pages, step); the no-skip rows show what empty-space skipping saves.
    let mut configs: Vec<(String, RenderMode, bool, f64)> = Vec::new();
    for &step in &steps {
        configs.push((format!("dvr step {step}"), RenderMode::Dvr, true, step));
        configs.push((format!("mip step {step}"), RenderMode::Mip, true, step));
        configs.push((
            format!("iso step {step}"),
            RenderMode::Isosurface,
            true,
            step,
        ));
    }
    if !quick {
        configs.push(("dvr step 0.5 no-skip".into(), RenderMode::Dvr, false, 0.5));
        configs.push(("mip step 0.5 no-skip".into(), RenderMode::Mip, false, 0.5));
    }
    let settings_for = |mode, skip, step| RenderSettings {
        width: size,
        height: size,
        mode,
        quality: step,
        skip_empty: skip,
        // The isosurface at the TF's first visible value (the ramp starts at 60).
        iso_value: 120.0,
        ..Default::default()
    };

    // Samples per ray first (one counting frame per config, untimed): the sampling-only kernel
    // takes the DVR count so the ceiling does the same number of fetches.
    let mut samples_per_frame = Vec::new();
    for &(_, mode, skip, step) in &configs {
        let camera = camera_at(1);
        let counting = RenderSettings {
            count_samples: true,
            ..settings_for(mode, skip, step)
        };
        let scene = drawn.scene(&camera, &counting);
        samples_per_frame.push(
            raycaster
                .render_blocking(&ctx, &scene)
                .expect("render")
                .samples
                .unwrap_or(0) as f64,
        );
    }
    let ceiling_per_ray =
        ((samples_per_frame[0] / (size as f64 * size as f64)).round() as u32).max(16);
    let ceiling = SamplingOnly::new(&ctx, &cache, size, ceiling_per_ray);

    // Rounds interleave every configuration with the ceiling, so load changes on a shared
    // machine hit all of them alike; medians over rounds. One warm-up round compiles pipelines.
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); configs.len() + 1];
    for round in 0..=frames {
        for (i, &(_, mode, skip, step)) in configs.iter().enumerate() {
            let camera = camera_at(round + 1);
            let settings = settings_for(mode, skip, step);
            let scene = drawn.scene(&camera, &settings);
            let t = Instant::now();
            raycaster.render_and_wait(&ctx, &scene).expect("render");
            if round > 0 {
                times[i].push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        let t = Instant::now();
        ceiling.run(&ctx);
        if round > 0 {
            times[configs.len()].push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    // The fixed per-frame cost: a 16² frame (its rays cost next to nothing) split into
    // encode + submit on the CPU (`render`) and the wait for the GPU, a 16² frame looking away
    // from the volume (every ray misses: the frame's cost outside the rays), and the
    // sampling-only kernel's 16² dispatch (submit + wait alone).
    let tiny = 16;
    let small_ceiling = SamplingOnly::new(&ctx, &cache, tiny, ceiling_per_ray);
    for (name, mode) in [
        ("dvr", RenderMode::Dvr),
        ("mip", RenderMode::Mip),
        ("iso", RenderMode::Isosurface),
    ] {
        let (mut encode, mut total, mut bare) = (Vec::new(), Vec::new(), Vec::new());
        let mut missing = Vec::new();
        for round in 0..=2 * frames.max(9) + 1 {
            let away = round % 2 == 1;
            let camera = if away {
                let c = camera_at(1);
                let eye = glam::DVec3::from(c.eye);
                let ahead = eye - (glam::DVec3::from(c.target) - eye);
                Camera::look_at(c.eye, ahead.into(), [0.0, 1.0, 0.0], c.projection)
            } else {
                camera_at(round + 1)
            };
            let settings = RenderSettings {
                width: tiny,
                height: tiny,
                ..settings_for(mode, true, steps[0])
            };
            let scene = drawn.scene(&camera, &settings);
            let t = Instant::now();
            let index = raycaster.render(&ctx, &scene).expect("render");
            let encoded = t.elapsed().as_secs_f64() * 1e3;
            ctx.device
                .poll(wgpu::PollType::Wait {
                    submission_index: Some(index),
                    timeout: None,
                })
                .expect("poll");
            let _ = raycaster.try_take_visibility(&ctx);
            let frame = t.elapsed().as_secs_f64() * 1e3;
            let t = Instant::now();
            small_ceiling.run(&ctx);
            if round > 1 && away {
                missing.push(frame);
            } else if round > 1 {
                encode.push(encoded);
                total.push(frame);
                bare.push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        println!(
            "fixed per-frame cost ({name} at {tiny}²): {:.2} ms/frame, of which encode+submit \
             {:.2} ms; every ray missing {:.2} ms; sampling-only kernel at {tiny}²: {:.2} ms",
            median(total),
            median(encode),
            median(missing),
            median(bare)
        );
    }
    let ceiling_ms = median(times[configs.len()].clone());
    let ceiling_samples = ceiling_per_ray as f64 * size as f64 * size as f64;
    let ceiling_rate = ceiling_samples / ceiling_ms * 1e-3;
    println!("\n{size}x{size}, median of {frames} interleaved rounds");
    println!(
        "{:<24} {:>10} {:>12} {:>12} {:>16}",
        "config", "ms/frame", "Msamples/s", "samples/ray", "rate vs ceiling"
    );
    for (i, (name, _, _, _)) in configs.iter().enumerate() {
        let ms = median(times[i].clone());
        let rate = samples_per_frame[i] / ms * 1e-3;
        println!(
            "{:<24} {:>10.1} {:>12.1} {:>12.1} {:>15.3}x",
            name,
            ms,
            rate,
            samples_per_frame[i] / (size as f64 * size as f64),
            rate / ceiling_rate
        );
    }
    println!(
        "{:<24} {:>10.1} {:>12.1} {:>12} {:>15.3}x",
        "sampling-only ceiling", ceiling_ms, ceiling_rate, ceiling_per_ray, 1.0
    );

    if quick {
        return;
    }

    effect_table(
        &ctx,
        &cache,
        &drawn,
        &mut raycaster,
        &camera_at,
        size,
        frames,
        None,
    );

    // Accuracy against the f64 reference at a smaller image (the reference at 512² takes
    // minutes on two cores). One reference per mode at a 1/16-voxel step: opacity correction
    // makes the integral independent of the step, so every GPU step is scored against the same
    // ground truth. Jitter off for the comparison, as in the tests.
    println!("\nPSNR vs f64 CPU reference at {ref_size}² (reference step 1/16 voxel):");
    let camera = camera_at(1);
    for (name, mode) in [("dvr", RenderMode::Dvr), ("mip", RenderMode::Mip)] {
        let settings_at = |step: f64| RenderSettings {
            width: ref_size,
            height: ref_size,
            mode,
            quality: step,
            jitter: false,
            ..Default::default()
        };
        let t = Instant::now();
        let reference = render_reference(
            &ReferenceScene {
                source: &volume,
                page_table: &page_table,
                geometry: &volume.geometry,
                mapping: volume.mapping,
                transfer_function: &tf,
                tf_range: (0.0, 255.0),
            },
            &camera,
            &settings_at(0.5),
            ReferenceOptions {
                step_refinement: 8.0,
                ..Default::default()
            },
        )
        .expect("reference");
        let reference_s = t.elapsed().as_secs_f64();
        // Strata's own converged image (the GPU at 1/16 voxel), the other yardstick: the f64
        // reference shares Strata's optical model, which a peer does not, so each renderer is
        // also scored against its own converged image (bench/peers/vtk_peer_bench.py does the
        // same for VTK at sample distance 1/16).
        let converged = raycaster
            .render_blocking(&ctx, &drawn.scene(&camera, &settings_at(1.0 / 16.0)))
            .expect("render")
            .rgba;
        for &step in &steps {
            let settings = settings_at(step);
            let scene = drawn.scene(&camera, &settings);
            let gpu = raycaster.render_blocking(&ctx, &scene).expect("render");
            let c = compare_rgba8(&gpu.rgba, &reference.rgba).expect("compare");
            let own = compare_rgba8(&gpu.rgba, &converged).expect("compare");
            println!(
                "{name} step {step}: PSNR {:.1} dB, RMSE {:.3}, max abs {} (reference {reference_s:.1} s); \
                 against its own step 1/16: {:.1} dB",
                c.psnr_db, c.rmse, c.max_abs_error, own.psnr_db,
            );
            // STRATA_BENCH_SAVE=DIR keeps the images, so bench/peers/vtk_peer_bench.py
            // --reference-dir DIR can score VTK's frame of the same view against this reference.
            if let Ok(dir) = std::env::var("STRATA_BENCH_SAVE") {
                let dir = std::path::Path::new(&dir);
                let _ = std::fs::create_dir_all(dir);
                let mut images = vec![(format!("gpu-step{step}"), &gpu.rgba)];
                if step == steps[0] {
                    images.push(("ref".to_string(), &reference.rgba));
                    images.push(("gpu-converged".to_string(), &converged));
                }
                for (kind, rgba) in images {
                    let path = dir.join(format!("strata-bench-{name}-{kind}.ppm"));
                    if let Err(e) = metrics::write_ppm(&path, ref_size, ref_size, rgba) {
                        eprintln!("{e}");
                    }
                }
            }
        }
    }
}
