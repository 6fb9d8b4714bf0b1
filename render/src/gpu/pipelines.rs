//! The raycast pipelines: one per combination of effects a scene uses ([`PipelineKey`], WGSL
//! override constants), all on one bind-group layout, built on first use and cached; for
//! interactive callers a named thread compiles new combinations while frames keep drawing
//! with the previous one.

use std::collections::{HashMap, HashSet};

use crate::model::settings::RenderMode;

/// The effects compiled into one raycast pipeline (override constants): a scene's pipeline
/// contains only what its settings use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PipelineKey {
    pub mode: RenderMode,
    pub manual_trilinear: bool,
    pub shading: bool,
    pub jitter: bool,
    pub skip_empty: bool,
    pub early_termination: bool,
    pub clip_plane: bool,
    pub count_samples: bool,
    pub preintegrated: bool,
    pub smooth_transitions: bool,
    /// The key light instead of the headlight (shadows.wgsl): a light other than the default
    /// or shadows.
    pub key_light: bool,
    /// Shadow rays to the key light, exact mode (shadows.wgsl).
    pub shadows: bool,
    /// The shadow term read from the light cache (light_cache.rs, shadows.wgsl).
    pub light_cache: bool,
    /// Ambient occlusion of lit samples (ambient_occlusion.rs ↔ ambient_occlusion.wgsl).
    pub occlusion: bool,
    /// Single scattering, HG phase and the hybrid rule (scattering.rs ↔ scattering.wgsl).
    pub scattering: bool,
    /// The octree traversal (octree.wgsl) instead of the flat page table: set by the scene's
    /// index ([`crate::GpuPageTable::traversal`]), not by the settings.
    pub octree: bool,
    /// A label map or continuous overlay drawn in 3D (overlay.wgsl): set by the raycaster's
    /// overlay ([`crate::Raycaster::set_overlay`]), not by the settings.
    pub overlay: bool,
}

/// The raycast pass's bind-group layout: parameters (0), brick cache and its sampler (1, 2),
/// page table (3), TF table (4), colour target (5), depth (6), visibility (7), sample counter
/// (8), MIP page bounds (9; per leaf with the octree), pre-integration table (10), transition
/// masks (11), octree node buffer (12), overlay grid, colour table and parameters (13-15),
/// light cache (16: written by its build entry point, read by the raycast's).
fn bind_group_layout(device: &wgpu::Device, filterable: bool) -> wgpu::BindGroupLayout {
    use wgpu::{BindingType, BufferBindingType, TextureSampleType, TextureViewDimension};
    let entry = |binding: u32, ty: BindingType| wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty,
        count: None,
    };
    let buffer = |binding: u32, ty: BufferBindingType| {
        entry(
            binding,
            BindingType::Buffer {
                ty,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
        )
    };
    let storage =
        |binding: u32, read_only: bool| buffer(binding, BufferBindingType::Storage { read_only });
    let texture = |binding: u32, filterable: bool, view_dimension: TextureViewDimension| {
        entry(
            binding,
            BindingType::Texture {
                sample_type: TextureSampleType::Float { filterable },
                view_dimension,
                multisampled: false,
            },
        )
    };
    let sampler = if filterable {
        wgpu::SamplerBindingType::Filtering
    } else {
        wgpu::SamplerBindingType::NonFiltering
    };
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("raycast"),
        entries: &[
            buffer(0, BufferBindingType::Uniform),
            texture(1, filterable, TextureViewDimension::D3),
            entry(2, BindingType::Sampler(sampler)),
            storage(3, true),
            texture(4, false, TextureViewDimension::D1),
            entry(
                5,
                BindingType::StorageTexture {
                    access: wgpu::StorageTextureAccess::WriteOnly,
                    format: crate::gpu::frame_targets::COLOR_FORMAT,
                    view_dimension: TextureViewDimension::D2,
                },
            ),
            storage(6, false),
            storage(7, false),
            storage(8, false),
            storage(9, true),
            storage(11, true),
            storage(12, true),
            texture(13, false, TextureViewDimension::D3),
            texture(14, false, TextureViewDimension::D1),
            buffer(15, BufferBindingType::Uniform),
            texture(10, false, TextureViewDimension::D2),
            storage(16, false),
        ],
    })
}

struct BackgroundCompiler {
    requests: std::sync::mpsc::Sender<PipelineKey>,
    results: std::sync::mpsc::Receiver<(PipelineKey, wgpu::ComputePipeline)>,
    pending: HashSet<PipelineKey>,
}

/// The shader's effect overrides, as named in the WGSL (raycast.wgsl, field.wgsl,
/// smooth_transitions.wgsl, overlay.wgsl, shadows.wgsl, ambient_occlusion.wgsl,
/// scattering.wgsl).
pub(crate) const OVERRIDE_NAMES: [&str; 17] = [
    "MODE",
    "MANUAL_TRILINEAR",
    "SHADING",
    "JITTER",
    "SKIP_EMPTY",
    "EARLY_TERMINATION",
    "CLIP_PLANE",
    "COUNT_SAMPLES",
    "PREINTEGRATED",
    "SMOOTH_TRANSITIONS",
    "KEY_LIGHT",
    "SHADOWS",
    "LIGHT_CACHE",
    "OCCLUSION",
    "SCATTERING",
    "OCTREE",
    "OVERLAY",
];

/// One raycast pipeline with the effects of `key` as override constants (those of
/// `declared` that the module still has).
fn build_pipeline(
    device: &wgpu::Device,
    layout: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    declared: &[&'static str],
    key: PipelineKey,
) -> wgpu::ComputePipeline {
    build_entry(device, layout, module, declared, key, "main")
}

/// The pipeline of `entry_point` in the raycast module with the effects of `key`.
fn build_entry(
    device: &wgpu::Device,
    layout: &wgpu::PipelineLayout,
    module: &wgpu::ShaderModule,
    declared: &[&'static str],
    key: PipelineKey,
    entry_point: &str,
) -> wgpu::ComputePipeline {
    let b = |v: bool| if v { 1.0 } else { 0.0 };
    let mode = match key.mode {
        RenderMode::Dvr => 0.0,
        RenderMode::Mip => 1.0,
        RenderMode::Isosurface => 2.0,
    };
    let constants = [
        ("MODE", mode),
        ("MANUAL_TRILINEAR", b(key.manual_trilinear)),
        ("SHADING", b(key.shading)),
        ("JITTER", b(key.jitter)),
        ("SKIP_EMPTY", b(key.skip_empty)),
        ("EARLY_TERMINATION", b(key.early_termination)),
        ("CLIP_PLANE", b(key.clip_plane)),
        ("COUNT_SAMPLES", b(key.count_samples)),
        ("PREINTEGRATED", b(key.preintegrated)),
        ("SMOOTH_TRANSITIONS", b(key.smooth_transitions)),
        ("KEY_LIGHT", b(key.key_light)),
        ("SHADOWS", b(key.shadows)),
        ("LIGHT_CACHE", b(key.light_cache)),
        ("OCCLUSION", b(key.occlusion)),
        ("SCATTERING", b(key.scattering)),
        ("OCTREE", b(key.octree)),
        ("OVERLAY", b(key.overlay)),
    ];
    let constants: Vec<(&str, f64)> = constants
        .into_iter()
        .filter(|(name, _)| declared.contains(name))
        .collect();
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry_point),
        layout: Some(layout),
        module,
        entry_point: Some(entry_point),
        compilation_options: wgpu::PipelineCompilationOptions {
            constants: &constants,
            zero_initialize_workgroup_memory: false,
        },
        cache: None,
    })
}

/// One raycaster's pipelines: the shader module, the layout they share, every effect
/// combination compiled so far, and the background compiler once an interactive caller needs
/// it.
pub(crate) struct Pipelines {
    pub(crate) layout: wgpu::BindGroupLayout,
    pipeline_layout: wgpu::PipelineLayout,
    /// The light cache's sweep slice (group 1 of its build pipelines only: a uniform
    /// vec4<u32> at a dynamic offset per slice, shadows.wgsl `SWEEP`).
    pub(crate) sweep_layout: wgpu::BindGroupLayout,
    build_pipeline_layout: wgpu::PipelineLayout,
    pub(crate) module: wgpu::ShaderModule,
    /// The effect overrides this raycaster's shader declares (all of them but in variants).
    pub(crate) declared_overrides: Vec<&'static str>,
    compiled: HashMap<PipelineKey, wgpu::ComputePipeline>,
    /// The light cache's build pipelines (shadows.wgsl `build_light_cache`), by
    /// [`light_cache_build_key`].
    light_cache_builds: HashMap<PipelineKey, wgpu::ComputePipeline>,
    compiler: Option<BackgroundCompiler>,
}

/// The effects a light-cache build compiles in for a frame of `key`: only those that change
/// the sampled field or the shadow ray (traversal, trilinear, transitions, empty skipping, the
/// clip plane); the rest are fixed so that frames differing in them share one build pipeline
/// (and one cache: light_cache.rs keys on this).
pub(crate) fn light_cache_build_key(key: PipelineKey) -> PipelineKey {
    PipelineKey {
        mode: RenderMode::Dvr,
        shading: true,
        jitter: false,
        early_termination: false,
        count_samples: false,
        preintegrated: false,
        key_light: true,
        shadows: false,
        light_cache: false,
        occlusion: false,
        scattering: false,
        overlay: false,
        ..key
    }
}

impl Pipelines {
    /// The layout and module for `wgsl` (the composed raycast shader or a variant of it), whose
    /// IR declares the overrides `declared` (shaders.rs reads them).
    pub(crate) fn new(
        device: &wgpu::Device,
        filterable: bool,
        wgsl: &str,
        declared: &[String],
    ) -> Self {
        let layout = bind_group_layout(device, filterable);
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("raycast"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let sweep_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("light cache sweep"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::COMPUTE,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: true,
                    min_binding_size: std::num::NonZeroU64::new(16),
                },
                count: None,
            }],
        });
        let build_pipeline_layout =
            device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("light cache build"),
                bind_group_layouts: &[Some(&layout), Some(&sweep_layout)],
                immediate_size: 0,
            });
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("raycast.wgsl"),
            source: wgpu::ShaderSource::Wgsl(wgsl.to_owned().into()),
        });
        Pipelines {
            layout,
            pipeline_layout,
            sweep_layout,
            build_pipeline_layout,
            module,
            declared_overrides: OVERRIDE_NAMES
                .iter()
                .copied()
                .filter(|name| declared.iter().any(|d| d == name))
                .collect(),
            compiled: HashMap::new(),
            light_cache_builds: HashMap::new(),
            compiler: None,
        }
    }

    /// Number of distinct pipelines compiled so far.
    pub(crate) fn len(&self) -> usize {
        self.compiled.len()
    }

    pub(crate) fn get(&self, key: &PipelineKey) -> Option<&wgpu::ComputePipeline> {
        self.compiled.get(key)
    }

    /// The light cache's build pipeline for a frame of `key`, if compiled.
    pub(crate) fn get_light_cache_build(
        &self,
        key: &PipelineKey,
    ) -> Option<&wgpu::ComputePipeline> {
        self.light_cache_builds.get(&light_cache_build_key(*key))
    }

    /// The pipeline for `key`, compiled now if it is not yet.
    pub(crate) fn get_or_build(
        &mut self,
        device: &wgpu::Device,
        key: PipelineKey,
    ) -> &wgpu::ComputePipeline {
        let (layout, module, declared) = (
            &self.pipeline_layout,
            &self.module,
            &self.declared_overrides,
        );
        self.compiled
            .entry(key)
            .or_insert_with(|| build_pipeline(device, layout, module, declared, key))
    }

    /// The light cache's build pipeline for a frame of `key` (compiled now if it is not yet).
    pub(crate) fn light_cache_build(
        &mut self,
        device: &wgpu::Device,
        key: PipelineKey,
    ) -> &wgpu::ComputePipeline {
        let (layout, module, declared) = (
            &self.build_pipeline_layout,
            &self.module,
            &self.declared_overrides,
        );
        let key = light_cache_build_key(key);
        self.light_cache_builds.entry(key).or_insert_with(|| {
            build_entry(device, layout, module, declared, key, "build_light_cache")
        })
    }

    /// The pipeline this frame draws with: the wanted one if compiled; otherwise, when
    /// `in_background` is set and the previous frame's pipeline (`previous`) is compiled and
    /// draws the same mode, that one while a named thread compiles the wanted one (a compile takes long enough on CPU
    /// drivers to drop frames); otherwise the wanted one, compiled now.
    pub(crate) fn choose(
        &mut self,
        device: &wgpu::Device,
        wanted: PipelineKey,
        in_background: bool,
        previous: Option<PipelineKey>,
    ) -> PipelineKey {
        self.take_background_results();
        if self.compiled.contains_key(&wanted) {
            return wanted;
        }
        if in_background {
            // A stand-in of another mode is not the picture asked for (a DVR image under a
            // "MIP" title for the seconds a compile takes on lavapipe, issue 36): a mode switch
            // compiles its pipeline now, which is also sooner than a background compile that
            // shares the cores with stand-in frames nobody wants.
            let previous =
                previous.filter(|k| k.mode == wanted.mode && self.compiled.contains_key(k));
            if let Some(previous) = previous {
                if self.request_background_compile(device, wanted) {
                    return previous;
                }
            }
        }
        let _ = self.get_or_build(device, wanted);
        wanted
    }

    /// Keeps what the compiler thread has finished.
    fn take_background_results(&mut self) {
        if let Some(compiler) = self.compiler.as_mut() {
            while let Ok((key, pipeline)) = compiler.results.try_recv() {
                compiler.pending.remove(&key);
                self.compiled.entry(key).or_insert(pipeline);
            }
        }
    }

    /// Whether `key` is compiled; if not, queues it on the compiler thread and answers false,
    /// so a caller that can wait polls (and stays cancellable) rather than blocking in a
    /// compile. Where no thread can be lent (wasm32) it compiles now and answers true.
    pub(crate) fn ready_or_queued(&mut self, device: &wgpu::Device, key: PipelineKey) -> bool {
        self.take_background_results();
        if self.compiled.contains_key(&key) {
            return true;
        }
        if self.request_background_compile(device, key) {
            return false;
        }
        let _ = self.get_or_build(device, key);
        true
    }

    /// Queues `key` on the compiler thread (started on first use). False if the thread
    /// cannot be started, in which case the caller compiles in place.
    fn request_background_compile(&mut self, device: &wgpu::Device, key: PipelineKey) -> bool {
        // The browser has no threads to lend (wasm32-unknown-unknown), and WebGPU compiles
        // pipelines in the GPU process anyway: compile in place there.
        if cfg!(target_arch = "wasm32") {
            let _ = (device, key);
            return false;
        }
        #[cfg(not(target_arch = "wasm32"))]
        if self.compiler.is_none() {
            let (requests, requests_in) = std::sync::mpsc::channel::<PipelineKey>();
            let (results_out, results) = std::sync::mpsc::channel();
            let (device, layout, module, declared) = (
                device.clone(),
                self.pipeline_layout.clone(),
                self.module.clone(),
                self.declared_overrides.clone(),
            );
            let spawned = std::thread::Builder::new()
                .name("strata-pipeline-compiler".into())
                .spawn(move || {
                    // Ends when the raycaster (the sender) is dropped.
                    for key in requests_in {
                        let pipeline = build_pipeline(&device, &layout, &module, &declared, key);
                        if results_out.send((key, pipeline)).is_err() {
                            break;
                        }
                    }
                });
            if spawned.is_err() {
                return false;
            }
            self.compiler = Some(BackgroundCompiler {
                requests,
                results,
                pending: HashSet::new(),
            });
        }
        let Some(compiler) = self.compiler.as_mut() else {
            return false;
        };
        if compiler.pending.contains(&key) {
            return true;
        }
        if compiler.requests.send(key).is_err() {
            return false;
        }
        compiler.pending.insert(key);
        true
    }

    /// True while a background compile is outstanding.
    pub(crate) fn compiling_in_background(&self) -> bool {
        self.compiler
            .as_ref()
            .is_some_and(|c| !c.pending.is_empty())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_effect_override_is_declared_and_read_from_the_ir() {
        let declared = crate::gpu::shaders::raycast_overrides();
        for name in OVERRIDE_NAMES {
            assert!(declared.iter().any(|d| d == name), "{name} not declared");
        }
        assert_eq!(declared.len(), OVERRIDE_NAMES.len());
        // A variant with an effect compiled out ("a build that never had it") declares one less.
        let variant = crate::gpu::shaders::raycast_source().replace(
            "override SKIP_EMPTY: bool = true;",
            "const SKIP_EMPTY: bool = false;",
        );
        let declared = crate::gpu::shaders::declared_overrides(&variant).unwrap();
        assert!(!declared.iter().any(|d| d == "SKIP_EMPTY"));
        assert_eq!(declared.len(), OVERRIDE_NAMES.len() - 1);
    }
}
