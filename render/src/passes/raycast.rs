//! The raycast pass: one compute dispatch of the composed raycast shader (shaders.rs;
//! entry point and ray loop in shaders/raycast.wgsl) writing an RGBA8 storage texture, a
//! pick-depth buffer (layout.rs `DEPTH_OPACITY`), the per-page visibility buffer and an optional sample counter.
//! [`Raycaster`] holds the pass: parameters ([`FrameInputs`] → `Params`), bind group, dispatch, and
//! the readbacks (blocking for tests and the CLI; visibility and timings through the readback
//! ring, 1-2 frames late). Pipelines per effect combination are pipelines.rs; the GPU
//! resources a scene points at are gpu_page_table.rs, gpu_transfer_function.rs and
//! gpu_preintegration.rs.

use glam::DVec3;

use crate::error::RenderError;
use crate::gpu::cache::BrickCache;
use crate::gpu::device::GpuContext;
use crate::gpu::frame_targets::{
    read_buffer_blocking, readback_buffer, FrameTargets, PixelBuffers, VisibilityTarget,
};
use crate::gpu::gpu_octree::{LeafVisibility, OctreeLeaves, Traversal};
use crate::gpu::gpu_overlay::GpuOverlay;
use crate::gpu::gpu_preintegration::GpuPreintegration;
use crate::gpu::gpu_timing::{FrameTiming, FrameTimingSource, PassTimestamps};
use crate::gpu::light_cache::{self, GpuLightCache, LightCacheKey, SWEEP_WORKGROUP};
use crate::gpu::pipelines::Pipelines;
use crate::gpu::shaders;
use crate::model::camera::Camera;
use crate::model::layout::WORKGROUP_SIZE;
use crate::model::overlay::{OverlayLut, OverlayVolume};
use crate::model::settings::{RenderMode, RenderSettings};
use strata_types::{ValueMapping, VolumeGeometry};

use crate::gpu::gpu_page_table::GpuPageTable;
use crate::gpu::gpu_transfer_function::GpuTransferFunction;
use crate::gpu::pipelines::PipelineKey;

/// Visibility staging ring: the loader reads a frame one or two frames late without stalling.
const VISIBILITY_RING: usize = 3;

/// Everything one frame needs.
pub struct FrameInputs<'a> {
    pub cache: &'a BrickCache,
    pub page_table: &'a GpuPageTable,
    pub transfer_function: &'a GpuTransferFunction,
    pub geometry: &'a VolumeGeometry,
    pub mapping: ValueMapping,
    pub camera: &'a Camera,
    pub settings: &'a RenderSettings,
}

#[derive(Clone, Debug)]
pub struct FrameReadback {
    pub width: u32,
    pub height: u32,
    /// Premultiplied RGBA8, row 0 at the top.
    pub rgba: Vec<u8>,
    /// Pick depth, ray distance in mm from the camera ray's origin: DVR where the accumulated
    /// opacity reaches [`crate::model::layout::DEPTH_OPACITY`], the MIP maximum, the iso hit; or +inf.
    pub depth: Vec<f32>,
    /// Per page entry: 1 if a sample there contributed before the ray terminated. With the
    /// octree traversal, expanded from [`FrameReadback::leaf_visibility`] only on grids of at
    /// most [`PER_PAGE_VISIBILITY_CELLS`] page cells (else empty: O(cells) per frame is what
    /// the octree avoids).
    pub visibility: Vec<u32>,
    /// The octree traversal's visibility as it is written: per leaf of the frame's cut.
    pub leaf_visibility: Option<LeafVisibility>,
    /// Samples taken, if `count_samples` was set.
    pub samples: Option<u64>,
    /// Page-table words read (the shader's `decode_entry` calls, the march's and the
    /// transition blend's), if `count_samples` was set.
    pub page_reads: Option<u64>,
}

/// A visibility buffer read back without blocking, tagged with the frame it came from.
#[derive(Clone, Debug)]
pub struct VisibilityFrame {
    pub frame_number: u64,
    /// Per page cell (see [`FrameReadback::visibility`]: empty for a large octree grid).
    pub visibility: Vec<u32>,
    /// Per leaf of the frame's cut, with the octree traversal.
    pub leaf_visibility: Option<LeafVisibility>,
}

/// Up to this many page cells (16 MiB of words), octree frames' per-leaf visibility is also
/// expanded per page cell, which tests compare with the flat traversal's; beyond it only the
/// per-leaf words come back.
pub const PER_PAGE_VISIBILITY_CELLS: usize = 1 << 22;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct Params {
    eye_idx: [f32; 4],
    right_idx: [f32; 4],
    up_idx: [f32; 4],
    forward_idx: [f32; 4],
    a_row0: [f32; 4],
    a_row1: [f32; 4],
    a_row2: [f32; 4],
    box_lo: [f32; 4],
    box_hi: [f32; 4],
    dims: [f32; 4],
    clip: [f32; 4],
    value_map: [f32; 4],
    iso: [f32; 4],
    shading: [f32; 4],
    iso_color: [f32; 4],
    cache_inv: [f32; 4],
    image: [u32; 4],
    pages: [u32; 4],
    slots: [u32; 4],
    light: [f32; 4],
    light_dual: [f32; 4],
    shadow: [f32; 4],
    clip_idx: [f32; 4],
    light_cache: [f32; 4],
    light_cache_dims: [u32; 4],
    cinematic: [f32; 4],
}

pub struct Raycaster {
    /// The compiled effect combinations, their layout and shader module.
    pipelines: Pipelines,
    pub(crate) params: wgpu::Buffer,
    pub(crate) sampler: wgpu::Sampler,
    pub(crate) filterable: bool,
    counter: wgpu::Buffer,
    counter_readback: wgpu::Buffer,
    targets: Option<FrameTargets>,
    visibility: Option<VisibilityTarget>,
    frame_number: u64,
    /// Page cells of the last frame's volume (the length of a per-page visibility list).
    page_count: usize,
    /// The octree leaves of the last frames (per-leaf visibility is read back per page cell
    /// through them), newest last; None for flat frames.
    frame_leaves: std::collections::VecDeque<(u64, Option<std::sync::Arc<OctreeLeaves>>)>,
    last_key: Option<PipelineKey>,
    /// Interactive callers (the viewer) set this: a frame whose pipeline is not compiled yet
    /// draws with the previous frame's while a thread compiles it. Off by default, so tests,
    /// the CLI and benchmarks always get exactly the pipeline their settings ask for.
    pub compile_in_background: bool,
    /// The pre-integrated TF table of the last pre-integrated frame (rebuilt when the TF, its
    /// range or the step changes), and a 1×1 stand-in bound when a pipeline does not use it.
    preintegration: GpuPreintegration,
    /// None when the device has no `TIMESTAMP_QUERY`: then `render_measured` times on the CPU.
    timestamps: Option<PassTimestamps>,
    last_submit_at: Option<web_time::Instant>,
    submit_to_done_timings: Vec<FrameTiming>,
    /// The overlay drawn in 3D (gpu_overlay.rs), stand-ins when there is none.
    overlay: GpuOverlay,
    /// The light cache of cache-mode shadows (light_cache.rs), a stand-in until one is built.
    light_cache: GpuLightCache,
}

impl Raycaster {
    pub fn new(ctx: &GpuContext, cache: &BrickCache) -> Self {
        Self::build(
            ctx,
            cache,
            shaders::raycast_source(),
            shaders::raycast_overrides(),
        )
    }

    /// The raycast shader's source as composed (shaders.rs: generated constants prelude, then
    /// the WGSL files), for benchmarks that build variants of it.
    pub fn shader_source() -> &'static str {
        shaders::raycast_source()
    }

    /// A raycaster compiled from a variant of [`Raycaster::shader_source`], e.g. with an effect's
    /// `override` turned into a `const false` ("a build that never had it") to show that the
    /// specialised pipeline without the effect costs the same. Only the overrides the variant
    /// still declares (read from naga's IR of it, once, here) are passed to its pipelines.
    pub fn with_shader_source(ctx: &GpuContext, cache: &BrickCache, wgsl: &str) -> Self {
        let declared = shaders::declared_overrides(wgsl).unwrap_or_default();
        Self::build(ctx, cache, wgsl, &declared)
    }

    fn build(ctx: &GpuContext, cache: &BrickCache, wgsl: &str, declared: &[String]) -> Self {
        let device = &ctx.device;
        let filterable = cache.format.filterable();
        let pipelines = Pipelines::new(device, filterable, wgsl, declared);
        let params = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("raycast params"),
            size: size_of::<Params>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let filter = if filterable {
            wgpu::FilterMode::Linear
        } else {
            wgpu::FilterMode::Nearest
        };
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("brick cache"),
            mag_filter: filter,
            min_filter: filter,
            ..Default::default()
        });
        let counter = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("sample counter"),
            size: 16,
            usage: wgpu::BufferUsages::STORAGE
                | wgpu::BufferUsages::COPY_SRC
                | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let counter_readback = readback_buffer(device, "sample counter readback", 16);
        Raycaster {
            pipelines,
            params,
            sampler,
            filterable,
            counter,
            counter_readback,
            targets: None,
            visibility: None,
            frame_number: 0,
            page_count: 0,
            frame_leaves: std::collections::VecDeque::new(),
            last_key: None,
            compile_in_background: false,
            preintegration: GpuPreintegration::new(device, &ctx.queue),
            timestamps: PassTimestamps::new(device, &ctx.queue),
            last_submit_at: None,
            submit_to_done_timings: Vec::new(),
            overlay: GpuOverlay::new(device),
            light_cache: GpuLightCache::new(device),
        }
    }

    /// Draws `volume` (resampled onto a grid spanning the primary's index box of `primary_dims`
    /// voxels, overlay.rs) with `lut` in the following frames, which then use pipelines with the
    /// overlay code compiled in. Shown until [`Raycaster::show_overlay`] turns it off.
    pub fn set_overlay(
        &mut self,
        ctx: &GpuContext,
        volume: &OverlayVolume,
        lut: &OverlayLut,
        primary_dims: [u32; 3],
    ) -> Result<(), RenderError> {
        self.overlay
            .set(&ctx.device, &ctx.queue, volume, lut, primary_dims)?;
        self.overlay.shown = true;
        Ok(())
    }

    /// Replaces the overlay's colour table only (opacity, hidden labels, colour map, range,
    /// threshold): no grid upload.
    pub fn set_overlay_lut(
        &mut self,
        ctx: &GpuContext,
        lut: &OverlayLut,
    ) -> Result<(), RenderError> {
        self.overlay.set_lut(&ctx.device, &ctx.queue, lut)
    }

    /// Shows or hides the loaded overlay (hidden: today's pipelines, as without one).
    pub fn show_overlay(&mut self, shown: bool) {
        self.overlay.shown = shown;
    }

    /// Forgets the overlay: frames are drawn as without one.
    pub fn clear_overlay(&mut self) {
        self.overlay.clear();
    }

    /// Whether frames draw an overlay.
    pub fn overlay_active(&self) -> bool {
        self.overlay.active()
    }

    /// How many times the light cache was built (cache-mode shadows rebuild it only when
    /// what it was built from changes: light_cache.rs).
    pub fn light_cache_builds(&self) -> u64 {
        self.light_cache.builds
    }

    /// The light cache's texels as last built (x fastest, light_cache.rs's grid; empty if
    /// none was built), read back blocking: for tests against the f64 reference.
    pub fn read_light_cache_blocking(&self, ctx: &GpuContext) -> Result<Vec<f32>, RenderError> {
        self.light_cache.read_blocking(&ctx.device, &ctx.queue)
    }

    /// True while a background compile is outstanding (the UI can say "compiling…").
    pub fn compiling_in_background(&self) -> bool {
        self.pipelines.compiling_in_background()
    }

    /// The effects of the pipeline the last frame was drawn with (with background compiling,
    /// possibly not yet the one its settings asked for).
    pub fn last_pipeline_key(&self) -> Option<PipelineKey> {
        self.last_key
    }

    /// Frame `frame_number`'s visibility words as the per-page-cell list the loader speaks
    /// (per-leaf words expanded through that frame's leaves).
    fn visibility_per_page(
        &self,
        frame_number: u64,
        words: &[u32],
        pages: usize,
    ) -> (Vec<u32>, Option<LeafVisibility>) {
        let leaves = self
            .frame_leaves
            .iter()
            .find(|(n, _)| *n == frame_number)
            .and_then(|(_, l)| l.clone());
        match leaves {
            Some(leaves) => {
                let marks = words[..leaves.boxes.len().min(words.len())].to_vec();
                let per_page = if pages <= PER_PAGE_VISIBILITY_CELLS {
                    leaves.expand_to_pages(&marks)
                } else {
                    Vec::new()
                };
                (per_page, Some(LeafVisibility { leaves, marks }))
            }
            None => (words[..pages.min(words.len())].to_vec(), None),
        }
    }

    /// The colour target, for display by the app (valid after the first `render`).
    pub fn output_view(&self) -> Option<&wgpu::TextureView> {
        self.targets.as_ref().map(FrameTargets::color_view)
    }

    pub fn output_texture(&self) -> Option<&wgpu::Texture> {
        self.targets.as_ref().map(FrameTargets::color)
    }

    /// Number of distinct pipelines compiled so far (one per used effect combination).
    pub fn compiled_pipelines(&self) -> usize {
        self.pipelines.len()
    }

    /// Compiles the pipeline `settings` need ahead of the first frame that uses it (a few
    /// hundred ms on lavapipe), e.g. when the user switches mode.
    /// Whether transition code is needed depends on the cut, so with smoothing on both
    /// variants are compiled.
    pub fn prepare(&mut self, ctx: &GpuContext, settings: &RenderSettings) {
        let key = self.key_for(settings);
        let _ = self.pipelines.get_or_build(&ctx.device, key);
        if key.smooth_transitions {
            let without = PipelineKey {
                smooth_transitions: false,
                ..key
            };
            let _ = self.pipelines.get_or_build(&ctx.device, without);
        }
    }

    /// Whether the pipelines a frame with `settings` draws with are compiled; those that are not
    /// go to the compiler thread and the answer is false. An export polls this between checks
    /// of its Cancel: with every cinematic effect on, one compile takes minutes on a CPU
    /// adapter, and [`Raycaster::prepare`] would block for all of it (issue 47).
    pub fn prepare_in_background(&mut self, ctx: &GpuContext, settings: &RenderSettings) -> bool {
        let key = self.key_for(settings);
        let mut ready = self.pipelines.ready_or_queued(&ctx.device, key);
        if key.smooth_transitions {
            let without = PipelineKey {
                smooth_transitions: false,
                ..key
            };
            ready &= self.pipelines.ready_or_queued(&ctx.device, without);
        }
        ready
    }

    /// The effects a frame with `settings` compiles in (see [`PipelineKey`]).
    pub fn key_for(&self, settings: &RenderSettings) -> PipelineKey {
        let overlay = self.overlay.active();
        PipelineKey {
            mode: settings.mode,
            manual_trilinear: settings.exact_trilinear || !self.filterable,
            shading: settings.effective_shading().is_some(),
            jitter: settings.jitter,
            skip_empty: settings.skip_empty,
            early_termination: settings.early_termination.is_some()
                && settings.mode == RenderMode::Dvr,
            clip_plane: settings.clip_plane.is_some(),
            count_samples: settings.count_samples,
            // The overlay is composited per sample (its colours are categories, not a TF the
            // segment integral could hold), so with one DVR takes the classic path.
            preintegrated: settings.preintegrated && settings.mode == RenderMode::Dvr && !overlay,
            smooth_transitions: settings.smooth_transitions,
            key_light: settings.effective_key_light(),
            shadows: settings.effective_shadows(),
            light_cache: settings.effective_light_cache(),
            occlusion: settings.effective_occlusion().is_some(),
            scattering: settings.effective_scattering().is_some(),
            octree: false,
            overlay,
        }
    }

    /// The bindings that define the sampled field (parameters, cache, sampler, page table,
    /// transition masks: `transitions`, per page cell or per leaf as the traversal has them):
    /// shared by the raycast pass, the adaptive pass and the field probe.
    pub(crate) fn field_entries<'a>(
        params: &'a wgpu::Buffer,
        sampler: &'a wgpu::Sampler,
        scene: &'a FrameInputs,
        transitions: &'a wgpu::Buffer,
    ) -> [wgpu::BindGroupEntry<'a>; 5] {
        [
            wgpu::BindGroupEntry {
                binding: 0,
                resource: params.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: wgpu::BindingResource::TextureView(&scene.cache.view),
            },
            wgpu::BindGroupEntry {
                binding: 2,
                resource: wgpu::BindingResource::Sampler(sampler),
            },
            wgpu::BindGroupEntry {
                binding: 3,
                resource: scene.page_table.buffer.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 11,
                resource: transitions.as_entire_binding(),
            },
        ]
    }

    /// The effects a frame of `scene` compiles in: [`Raycaster::key_for`] its settings, with
    /// the transition code left out when no node of the cut has a coarser neighbour.
    pub fn key_for_scene(&self, scene: &FrameInputs) -> PipelineKey {
        let mut key = self.key_for(scene.settings);
        key.smooth_transitions &= scene.page_table.transition_fraction() > 0.0;
        key.octree = scene.page_table.traversal() == Traversal::Octree;
        key
    }

    /// Builds the pre-integration table for this scene's TF unless the last one still fits
    /// (gpu_preintegration.rs; it holds for every step).
    fn ensure_preintegration(&mut self, ctx: &GpuContext, scene: &FrameInputs) {
        let unit_mm = scene.geometry.finest_spacing_mm();
        self.preintegration
            .ensure(&ctx.device, &ctx.queue, scene.transfer_function, unit_mm);
    }

    /// Encodes and submits one frame. Never waits for the GPU. Also queues a copy of this
    /// frame's visibility into a free staging buffer for [`Raycaster::try_take_visibility`].
    pub fn render(
        &mut self,
        ctx: &GpuContext,
        scene: &FrameInputs,
    ) -> Result<wgpu::SubmissionIndex, RenderError> {
        // An earlier step's uncaptured GPU error ends the loop here, not in a panic.
        ctx.check_uncaptured()?;
        let settings = scene.settings;
        settings.validate()?;
        scene.geometry.validate()?;
        let page_dims = scene.geometry.page_dims();
        if scene.page_table.slots_per_axis != scene.cache.slots_per_axis {
            return Err(RenderError::PageTableMismatch(
                "GPU page table was made for a different cache".into(),
            ));
        }
        if scene.page_table.page_dims != page_dims {
            return Err(RenderError::PageTableMismatch(format!(
                "GPU page table is {:?}, volume needs {:?}",
                scene.page_table.page_dims, page_dims
            )));
        }
        let device = &ctx.device;
        let limits = device.limits();
        let max2d = limits.max_texture_dimension_2d;
        if settings.width > max2d || settings.height > max2d {
            return Err(RenderError::InvalidSettings(format!(
                "image {}x{} exceeds device limit {max2d}",
                settings.width, settings.height
            )));
        }
        let depth_bytes = settings.width as u64 * settings.height as u64 * 4;
        if depth_bytes > limits.max_storage_buffer_binding_size {
            return Err(RenderError::InvalidSettings(format!(
                "image {}x{} needs a {depth_bytes}-byte depth buffer, over the device limit {}",
                settings.width, settings.height, limits.max_storage_buffer_binding_size
            )));
        }
        let wanted = self.key_for_scene(scene);
        let key = self
            .pipelines
            .choose(device, wanted, self.compile_in_background, self.last_key);
        self.last_key = Some(key);
        if key.preintegrated {
            self.ensure_preintegration(ctx, scene);
        }
        FrameTargets::ensure(
            &mut self.targets,
            device,
            "raycast",
            settings.width,
            settings.height,
            PixelBuffers {
                depth: true,
                rgba_f32: false,
            },
        );
        VisibilityTarget::ensure(
            &mut self.visibility,
            device,
            "raycast",
            scene.page_table.visibility_entries(),
            VISIBILITY_RING,
        );
        self.page_count = page_dims.iter().map(|&d| d as usize).product();
        let leaves = scene.page_table.octree_leaves();
        let (bounds_buffer, octree_nodes, transitions) = scene.page_table.traversal_buffers()?;
        let params = build_params(scene);
        ctx.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        // Cache-mode shadows: build the light cache first if what it was built from changed
        // (light_cache.rs), in this frame's submission.
        let build_light_cache = if key.light_cache {
            let n = params.light_cache_dims;
            let bytes = (n[0] as u64 * n[1] as u64 * n[2] as u64) * 4;
            if bytes > limits.max_storage_buffer_binding_size {
                return Err(RenderError::InvalidSettings(format!(
                    "a light cache of {n:?} texels needs {bytes} bytes, over the device's \
                     storage-binding limit {}: raise --light-cache-res",
                    limits.max_storage_buffer_binding_size
                )));
            }
            let tf = scene.transfer_function;
            let cache_key = LightCacheKey {
                page_table: scene.page_table.generation(),
                transfer_function: tf.source.clone(),
                tf_range: (tf.lo, tf.hi, tf.entries),
                mapping: (scene.mapping.slope, scene.mapping.intercept),
                light_idx: [params.light[0], params.light[1], params.light[2]],
                shadow: params.shadow,
                res: settings.shadows.cache_res,
                dims: scene.geometry.dims,
                crop: settings.crop,
                clip_idx: settings.clip_plane.map(|_| params.clip_idx),
                pipeline: crate::gpu::pipelines::light_cache_build_key(key),
            };
            let build = self.light_cache.needs_build(device, &cache_key, bytes);
            if build {
                let _ = self.pipelines.light_cache_build(device, key);
            }
            build.then_some([n[0], n[1], n[2]])
        } else {
            None
        };
        let (Some(targets), Some(vis), Some(pipeline)) = (
            self.targets.as_ref(),
            self.visibility.as_mut(),
            self.pipelines.get(&key),
        ) else {
            return Err(RenderError::Readback("render targets missing".into()));
        };
        let depth = targets.depth()?;
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("raycast"),
            layout: &self.pipelines.layout,
            entries: &Self::field_entries(&self.params, &self.sampler, scene, &transitions)
                .into_iter()
                .chain([
                    wgpu::BindGroupEntry {
                        binding: 4,
                        resource: wgpu::BindingResource::TextureView(&scene.transfer_function.view),
                    },
                    wgpu::BindGroupEntry {
                        binding: 5,
                        resource: wgpu::BindingResource::TextureView(targets.color_view()),
                    },
                    wgpu::BindGroupEntry {
                        binding: 6,
                        resource: depth.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 7,
                        resource: vis.buffer().as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 8,
                        resource: self.counter.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 9,
                        resource: bounds_buffer.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 12,
                        resource: octree_nodes.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 13,
                        resource: wgpu::BindingResource::TextureView(&self.overlay.grid_view),
                    },
                    wgpu::BindGroupEntry {
                        binding: 14,
                        resource: wgpu::BindingResource::TextureView(&self.overlay.lut_view),
                    },
                    wgpu::BindGroupEntry {
                        binding: 15,
                        resource: self.overlay.params.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 16,
                        resource: self.light_cache.buffer.as_entire_binding(),
                    },
                    wgpu::BindGroupEntry {
                        binding: 10,
                        resource: wgpu::BindingResource::TextureView(
                            self.preintegration.view(key.preintegrated),
                        ),
                    },
                ])
                .collect::<Vec<_>>(),
        });
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("raycast"),
        });
        encoder.clear_buffer(vis.buffer(), 0, None);
        encoder.clear_buffer(&self.counter, 0, None);
        if let Some(n) = build_light_cache {
            // Its own pass, before the frame's: the frame reads what it writes. One dispatch
            // per slice along the sweep axis, from the light's side (light_cache.rs).
            let l = [params.light[0], params.light[1], params.light[2]];
            let sweep = light_cache::sweep_order(l, n);
            let stride = (limits.min_uniform_buffer_offset_alignment as u64).max(16);
            let mut words = vec![0u32; sweep.slices.len() * (stride as usize / 4)];
            for (k, slice) in sweep.slices.iter().enumerate() {
                let at = k * stride as usize / 4;
                words[at..at + 3].copy_from_slice(&[*slice, sweep.axis, u32::from(k == 0)]);
            }
            let slices = wgpu::util::DeviceExt::create_buffer_init(
                device,
                &wgpu::util::BufferInitDescriptor {
                    label: Some("light cache sweep"),
                    contents: bytemuck::cast_slice(&words),
                    usage: wgpu::BufferUsages::UNIFORM,
                },
            );
            let slice_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("light cache sweep"),
                layout: &self.pipelines.sweep_layout,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &slices,
                        offset: 0,
                        size: wgpu::BufferSize::new(16),
                    }),
                }],
            });
            if let Some(build) = self.pipelines.get_light_cache_build(&key) {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("light cache"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(build);
                pass.set_bind_group(0, &bind_group, &[]);
                for k in 0..sweep.slices.len() {
                    pass.set_bind_group(1, &slice_group, &[(k as u64 * stride) as u32]);
                    pass.dispatch_workgroups(
                        sweep.across[0].div_ceil(SWEEP_WORKGROUP),
                        sweep.across[1].div_ceil(SWEEP_WORKGROUP),
                        1,
                    );
                }
            }
        }
        if let Some(timestamps) = self.timestamps.as_mut() {
            timestamps.begin_frame();
        }
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("raycast"),
                timestamp_writes: self.timestamps.as_ref().and_then(|t| t.pass_writes()),
            });
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(
                settings.width.div_ceil(WORKGROUP_SIZE),
                settings.height.div_ceil(WORKGROUP_SIZE),
                1,
            );
        }
        self.frame_number += 1;
        self.frame_leaves.push_back((self.frame_number, leaves));
        while self.frame_leaves.len() > VISIBILITY_RING + 2 {
            self.frame_leaves.pop_front();
        }
        if let Some(timestamps) = self.timestamps.as_mut() {
            timestamps.encode_resolve(&mut encoder, self.frame_number);
        }
        let queued = vis.encode_ring_copy(&mut encoder, self.frame_number);
        self.last_submit_at = Some(web_time::Instant::now());
        let index = ctx.queue.submit(Some(encoder.finish()));
        if let Some(timestamps) = self.timestamps.as_mut() {
            timestamps.after_submit();
        }
        if let Some(slot) = queued {
            vis.map_after_submit(slot);
        }
        Ok(index)
    }

    /// Newest visibility buffer that finished copying, without blocking (typically one or two
    /// frames late). Older ready ones are dropped.
    pub fn try_take_visibility(&mut self, ctx: &GpuContext) -> Option<VisibilityFrame> {
        let _ = ctx.device.poll(wgpu::PollType::Poll);
        let vis = self.visibility.as_mut()?;
        let mut newest: Option<(u64, Vec<u32>)> = None;
        vis.drain_ring(|frame_number, view| {
            if newest.as_ref().is_none_or(|n| n.0 < frame_number) {
                newest = Some((frame_number, bytemuck::cast_slice(view).to_vec()));
            }
        });
        let (frame_number, words) = newest?;
        let pages = self.page_count;
        let (visibility, leaf_visibility) = self.visibility_per_page(frame_number, &words, pages);
        Some(VisibilityFrame {
            frame_number,
            visibility,
            leaf_visibility,
        })
    }

    /// The last frame's pick-depth buffer (one f32 per pixel, row 0 at the top, as
    /// [`FrameReadback::depth`]) and that frame's size: for a caller that copies a pixel back
    /// without waiting (the browser page's picking in 3D). `None` before the first frame.
    pub fn pick_depth_buffer(&self) -> Option<(&wgpu::Buffer, [u32; 2])> {
        let targets = self.targets.as_ref()?;
        let depth = targets.depth().ok()?;
        Some((depth, [targets.width(), targets.height()]))
    }

    /// Copies the last rendered frame back and waits for it. For tests and the CLI.
    pub fn read_frame_blocking(&mut self, ctx: &GpuContext) -> Result<FrameReadback, RenderError> {
        let (Some(t), Some(vis)) = (self.targets.as_ref(), self.visibility.as_ref()) else {
            return Err(RenderError::Readback("nothing rendered yet".into()));
        };
        let device = &ctx.device;
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("readback"),
        });
        t.encode_readback(&mut encoder);
        vis.encode_readback(&mut encoder);
        encoder.copy_buffer_to_buffer(&self.counter, 0, &self.counter_readback, 0, 16);
        ctx.queue.submit(Some(encoder.finish()));
        let pixels = t.read_mapped(device)?;
        let words = vis.read_mapped(device)?;
        let (visibility, leaf_visibility) =
            self.visibility_per_page(self.frame_number, &words, self.page_count);
        let counter: Vec<u32> =
            bytemuck::pod_collect_to_vec(&read_buffer_blocking(device, &self.counter_readback)?);
        let counted = self.last_key.is_some_and(|k| k.count_samples);
        let wide = |lo: usize| counter[lo] as u64 + ((counter[lo + 1] as u64) << 32);
        let samples = counted.then(|| wide(0));
        let page_reads = counted.then(|| wide(2));
        Ok(FrameReadback {
            width: t.width(),
            height: t.height(),
            rgba: pixels.rgba,
            depth: pixels.depth,
            visibility,
            leaf_visibility,
            samples,
            page_reads,
        })
    }

    /// Render, wait, read everything back.
    pub fn render_blocking(
        &mut self,
        ctx: &GpuContext,
        scene: &FrameInputs,
    ) -> Result<FrameReadback, RenderError> {
        self.render(ctx, scene)?;
        self.read_frame_blocking(ctx)
    }

    /// Number of the last submitted frame (1 for the first); frame timings carry it.
    pub fn frame_number(&self) -> u64 {
        self.frame_number
    }

    /// Where [`Raycaster::render_measured`] gets its figure from on this device.
    pub fn frame_timing_source(&self) -> FrameTimingSource {
        if self.timestamps.is_some() {
            FrameTimingSource::GpuTimestamps
        } else {
            FrameTimingSource::SubmitToDone
        }
    }

    /// [`Raycaster::render`] for a loop that wants to know how long the raycast took (the
    /// time-critical controller). With GPU timestamps it never waits and the timing arrives a
    /// frame or two later through [`Raycaster::try_take_frame_timings`]. Without, it waits: first
    /// for earlier work (a UI pass is not ours to time), then for this submission, timing
    /// submit → done on the CPU clock.
    pub fn render_measured(
        &mut self,
        ctx: &GpuContext,
        scene: &FrameInputs,
    ) -> Result<wgpu::SubmissionIndex, RenderError> {
        if self.timestamps.is_some() {
            return self.render(ctx, scene);
        }
        ctx.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        let index = self.render(ctx, scene)?;
        ctx.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(index.clone()),
                timeout: None,
            })
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        if let Some(submitted) = self.last_submit_at {
            self.submit_to_done_timings.push(FrameTiming {
                frame_number: self.frame_number,
                milliseconds: submitted.elapsed().as_secs_f64() * 1e3,
                source: FrameTimingSource::SubmitToDone,
            });
        }
        Ok(index)
    }

    /// Timings of frames that finished since the last call, oldest first. Never blocks; frames
    /// submitted with plain [`Raycaster::render`] are included when timestamps are available.
    pub fn try_take_frame_timings(&mut self, ctx: &GpuContext) -> Vec<FrameTiming> {
        let mut timings = std::mem::take(&mut self.submit_to_done_timings);
        if let Some(timestamps) = self.timestamps.as_mut() {
            let _ = ctx.device.poll(wgpu::PollType::Poll);
            timings.extend(timestamps.take_ready());
        }
        timings
    }

    /// Submits and waits for a frame without reading it back (benchmarks).
    pub fn render_and_wait(
        &mut self,
        ctx: &GpuContext,
        scene: &FrameInputs,
    ) -> Result<(), RenderError> {
        let index = self.render(ctx, scene)?;
        ctx.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(index),
                timeout: None,
            })
            .map_err(|e| RenderError::Readback(e.to_string()))?;
        // Keep the ring draining so benchmarks measure steady state.
        let _ = self.try_take_visibility(ctx);
        Ok(())
    }
}

fn v4(v: DVec3, w: f64) -> [f32; 4] {
    [v.x as f32, v.y as f32, v.z as f32, w as f32]
}

/// Everything is converted from f64 here, once per frame, so the shader works in index space
/// with well-conditioned f32 values.
pub(crate) fn build_params(scene: &FrameInputs) -> Params {
    let g = scene.geometry;
    let s = scene.settings;
    let a = g.index_from_patient_linear();
    let basis = scene.camera.basis();
    let eye_idx = g.index_from_patient(basis.eye);
    let aspect = s.width as f64 / s.height as f64;
    let dims = DVec3::new(g.dims[0] as f64, g.dims[1] as f64, g.dims[2] as f64);
    let lo = DVec3::from(s.crop.min.map(|v| v as f64)) * dims - 0.5;
    let hi = DVec3::from(s.crop.max.map(|v| v as f64)) * dims - 0.5;
    let unit = g.finest_spacing_mm();
    let base_step = s.quality * unit;
    let clip = match &s.clip_plane {
        Some(p) => {
            // Non-zero: RenderSettings::validate refuses a zero clip normal.
            let n = DVec3::from(p.normal).normalize_or_zero();
            [
                n.dot(basis.forward) as f32,
                n.dot(basis.right) as f32,
                n.dot(basis.up) as f32,
                (p.offset_mm - n.dot(basis.eye)) as f32,
            ]
        }
        None => [0.0; 4],
    };
    let tf = scene.transfer_function;
    let range = (tf.hi - tf.lo).max(1e-30);
    let shading = s.effective_shading().unwrap_or_default();
    let flatness = scene.mapping.slope.abs() * unit / range;
    let texel = scene.cache.texel_dims();
    let iso_color = tf.source.color_at(s.iso_value);
    let light = crate::model::shadows::gpu_light(s, &basis, g);
    let cache_res = s.shadows.cache_res;
    let cache_dims = light_cache::grid_dims(g.dims, cache_res);
    Params {
        eye_idx: v4(eye_idx, basis.half_extent),
        right_idx: v4(a * basis.right, aspect),
        up_idx: v4(a * basis.up, if basis.orthographic { 1.0 } else { 0.0 }),
        forward_idx: v4(a * basis.forward, 0.0),
        a_row0: v4(a.row(0), 0.0),
        a_row1: v4(a.row(1), 0.0),
        a_row2: v4(a.row(2), 0.0),
        box_lo: v4(lo, base_step),
        box_hi: v4(hi, unit),
        dims: v4(dims, s.early_termination.unwrap_or(1.0) as f64),
        clip,
        value_map: [
            (scene.cache.format.stored_at_one() * scene.mapping.slope) as f32,
            scene.mapping.intercept as f32,
            tf.lo as f32,
            ((tf.entries - 1) as f64 / range) as f32,
        ],
        iso: [s.iso_value as f32, flatness as f32, 0.0, 0.0],
        iso_color: [
            iso_color[0] as f32,
            iso_color[1] as f32,
            iso_color[2] as f32,
            0.0,
        ],
        shading: [
            shading.ambient,
            shading.diffuse,
            shading.specular,
            shading.shininess,
        ],
        cache_inv: [
            1.0 / texel[0] as f32,
            1.0 / texel[1] as f32,
            1.0 / texel[2] as f32,
            0.0,
        ],
        image: [s.width, s.height, s.frame_index, tf.entries],
        // w: the octree's root reference (octree.wgsl; the traversal reads it from here).
        pages: [
            g.page_dims()[0],
            g.page_dims()[1],
            g.page_dims()[2],
            scene.page_table.octree_root(),
        ],
        slots: [
            scene.cache.slots_per_axis[0],
            scene.cache.slots_per_axis[1],
            scene.cache.slots_per_axis[2],
            0,
        ],
        light: light.light,
        light_dual: light.light_dual,
        shadow: light.shadow,
        clip_idx: light.clip_idx,
        light_cache: [
            (cache_res * unit * light_cache::LOOKUP_OFFSET_CELLS) as f32,
            cache_res as f32,
            0.0,
            0.0,
        ],
        light_cache_dims: [cache_dims[0], cache_dims[1], cache_dims[2], 0],
        // Occlusion radius (mm; ambient_occlusion.rs), scattering g and blend (scattering.rs).
        cinematic: [
            s.occlusion.map_or(0.0, |o| o.radius_mm) as f32,
            s.scattering.map_or(0.0, |c| c.g) as f32,
            s.scattering.map_or(0.0, |c| c.blend) as f32,
            0.0,
        ],
    }
}
