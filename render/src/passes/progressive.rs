//! Progressive refinement of a still view (issue 37, item 3): successive frames that differ only
//! in `frame_index` are averaged on the GPU into a running mean that converges to the same
//! model's un-jittered, fine-step image.
//!
//! # What is random, and what the mean converges to
//! With [`RenderSettings::jitter`] two offsets vary per pixel and frame, both hashed from the
//! pixel and `frame_index` (uniform in [0, 1), independent of each other): the main ray's
//! samples sit at `t0 + (k + j)·step`, and every shadow and occlusion ray of that pixel samples
//! its segments at the fraction `j'` of its step instead of the midpoint (shadows.wgsl
//! `shadow_jitter`; the light cache's build keeps the midpoint). Over frames the mean
//! integrates the rays at every offset inside a step, i.e. at a step that shrinks with N, so
//! one frame's wood-grain turns into noise that averages out as 1/√N until what is left is the
//! model's bias at that step (compositing and exp(−τ) are not linear in the sample positions,
//! so jittered samples are not an unbiased estimator of the fine-step integral) and the 8-bit
//! rounding of each frame. The occlusion direction set is fixed (not rotated per frame), so
//! its angular error does not average out. See `render/tests/progressive.rs` for the measured
//! slopes.
//!
//! # Cost
//! One compute pass per frame reading the raycaster's Rgba8Unorm output and updating an
//! f32×4 buffer and an Rgba8Unorm texture (what a viewer displays): 20 bytes read and 20
//! written per pixel, no CPU readback (within noise at 512² on lavapipe: the bench's
//! progressive row). The mean, not a sum, is stored (`mean_N = mean_{N-1} + (x_N -
//! mean_{N-1})/N`), so f32 never runs out of precision however long the view stays still.
//!
//! # Resets
//! A [`ViewKey`] names what a frame shows apart from its jitter: the camera, the settings with
//! `frame_index` cleared, and a generation the caller bumps for what settings do not hold (the
//! transfer function, the resident cut, the data). A frame with another key, or another size,
//! restarts the count at 1.

use crate::error::RenderError;
use crate::gpu::device::GpuContext;
use crate::gpu::frame_targets::{FrameTargets, PixelBuffers, COLOR_FORMAT};
use crate::model::camera::Camera;
use crate::model::settings::RenderSettings;
use crate::passes::raycast::{FrameInputs, Raycaster};

const WGSL: &str = include_str!("../shaders/progressive.wgsl");
const WORKGROUP: u32 = 8;

/// What a frame shows apart from its jitter; frames with equal keys may be averaged.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewKey {
    camera: Camera,
    settings: RenderSettings,
    generation: u64,
}

impl ViewKey {
    /// The key of frames of `camera` and `settings`, whatever their `frame_index`.
    pub fn new(camera: &Camera, settings: &RenderSettings) -> Self {
        ViewKey {
            camera: *camera,
            settings: RenderSettings {
                frame_index: 0,
                // Counting samples changes no pixel; a benchmark toggling it keeps its mean.
                count_samples: false,
                ..settings.clone()
            },
            generation: 0,
        }
    }

    /// Adds a counter the caller bumps whenever something outside the settings changes the
    /// image (transfer function, cut, volume data).
    pub fn with_generation(self, generation: u64) -> Self {
        ViewKey { generation, ..self }
    }
}

/// `settings` for frame `n` of a progressive sequence: jitter on, `frame_index` = n (the
/// jitter hash's seed, so every frame samples other offsets).
pub fn jittered_frame(settings: &RenderSettings, n: u32) -> RenderSettings {
    RenderSettings {
        jitter: true,
        frame_index: n,
        ..settings.clone()
    }
}

/// How many frames may be queued before the loop in [`render_still`] waits for the GPU: bounds
/// the command buffers and bind groups in flight without serialising every frame.
const FRAMES_IN_FLIGHT: u32 = 8;

/// Renders `frames` (at least 1) jittered frames of `scene`'s still view with `raycaster`
/// (frame n with `frame_index` n) and returns their mean as the displayed Rgba8Unorm bytes:
/// `strata render --progressive`.
pub fn render_still(
    ctx: &GpuContext,
    raycaster: &mut Raycaster,
    scene: &FrameInputs,
    frames: u32,
) -> Result<Vec<u8>, RenderError> {
    let key = ViewKey::new(scene.camera, scene.settings);
    let mut accumulator = Accumulator::new(ctx);
    for n in 0..frames.max(1) {
        let settings = jittered_frame(scene.settings, n);
        raycaster.render(
            ctx,
            &FrameInputs {
                settings: &settings,
                ..*scene
            },
        )?;
        let Some(output) = raycaster.output_texture() else {
            return Err(RenderError::Readback("the raycaster has no output".into()));
        };
        accumulator.accumulate(ctx, &key, output)?;
        if (n + 1) % FRAMES_IN_FLIGHT == 0 {
            ctx.wait_idle()?;
        }
    }
    let mean = accumulator.read_mean_blocking(ctx)?;
    ctx.check_uncaptured()?;
    Ok(mean)
}

/// The running mean of a still view's frames, on the GPU.
pub struct Accumulator {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    params: wgpu::Buffer,
    /// The mean: f32 in `rgba_f32`, quantised for display in the colour texture.
    targets: Option<FrameTargets>,
    key: Option<ViewKey>,
    frames: u32,
}

impl Accumulator {
    pub fn new(ctx: &GpuContext) -> Self {
        let device = &ctx.device;
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("progressive"),
            source: wgpu::ShaderSource::Wgsl(WGSL.into()),
        });
        let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty,
            count: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("progressive"),
            entries: &[
                entry(
                    0,
                    wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                ),
                entry(
                    1,
                    wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: false },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                ),
                entry(
                    2,
                    wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only: false },
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                ),
                entry(
                    3,
                    wgpu::BindingType::StorageTexture {
                        access: wgpu::StorageTextureAccess::WriteOnly,
                        format: COLOR_FORMAT,
                        view_dimension: wgpu::TextureViewDimension::D2,
                    },
                ),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("progressive"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("progressive accumulate"),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some("accumulate"),
            compilation_options: Default::default(),
            cache: None,
        });
        let params = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("progressive params"),
            size: 16,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Accumulator {
            pipeline,
            layout,
            params,
            targets: None,
            key: None,
            frames: 0,
        }
    }

    /// Frames in the current mean (0 before the first and after [`Accumulator::reset`]).
    pub fn frames(&self) -> u32 {
        self.frames
    }

    /// The key of the current mean.
    pub fn key(&self) -> Option<&ViewKey> {
        self.key.as_ref()
    }

    /// Forgets the mean: the next frame starts a new one whatever its key.
    pub fn reset(&mut self) {
        self.frames = 0;
        self.key = None;
    }

    /// The running mean as a viewer displays it (premultiplied, like the raycaster's output);
    /// None before the first frame.
    pub fn mean_texture(&self) -> Option<&wgpu::Texture> {
        self.targets.as_ref().map(FrameTargets::color)
    }

    pub fn mean_view(&self) -> Option<&wgpu::TextureView> {
        self.targets.as_ref().map(FrameTargets::color_view)
    }

    /// Folds `frame` (the raycaster's Rgba8Unorm output, e.g.
    /// [`crate::Raycaster::output_texture`], rendered with `key`'s view) into the mean and submits the pass; the
    /// queue orders it after the frame's own submission. A new key or size restarts the mean.
    /// Returns the number of frames now in it.
    pub fn accumulate(
        &mut self,
        ctx: &GpuContext,
        key: &ViewKey,
        frame: &wgpu::Texture,
    ) -> Result<u32, RenderError> {
        if frame.format() != COLOR_FORMAT
            || !frame.usage().contains(wgpu::TextureUsages::TEXTURE_BINDING)
        {
            return Err(RenderError::InvalidSettings(format!(
                "progressive accumulation needs an Rgba8Unorm texture bindable for sampling, got {:?} ({:?})",
                frame.format(),
                frame.usage()
            )));
        }
        let (width, height) = (frame.width(), frame.height());
        if self.key.as_ref() != Some(key) {
            self.frames = 0;
        }
        self.ensure_targets(&ctx.device, width, height);
        let Some(t) = self.targets.as_ref() else {
            return Err(RenderError::Readback("progressive targets missing".into()));
        };
        let n = self.frames.saturating_add(1);
        ctx.queue.write_buffer(
            &self.params,
            0,
            bytemuck::cast_slice(&[width, height, n, 0]),
        );
        let frame_view = frame.create_view(&wgpu::TextureViewDescriptor::default());
        let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("progressive"),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: self.params.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(&frame_view),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: t.rgba_f32()?.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: wgpu::BindingResource::TextureView(t.color_view()),
                },
            ],
        });
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("progressive"),
            });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("progressive accumulate"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups(width.div_ceil(WORKGROUP), height.div_ceil(WORKGROUP), 1);
        }
        ctx.queue.submit(Some(encoder.finish()));
        self.frames = n;
        self.key = Some(key.clone());
        Ok(n)
    }

    fn ensure_targets(&mut self, device: &wgpu::Device, width: u32, height: u32) {
        let pixel_buffers = PixelBuffers {
            depth: false,
            rgba_f32: true,
        };
        if FrameTargets::ensure(
            &mut self.targets,
            device,
            "progressive mean",
            width,
            height,
            pixel_buffers,
        ) {
            // A new size is a new view: the old mean cannot continue.
            self.frames = 0;
        }
    }

    /// The mean in f32 (premultiplied RGBA in [0, 1], row-major), read back and waited for:
    /// for tests and the CLI, never per frame.
    pub fn read_mean_f32_blocking(&self, ctx: &GpuContext) -> Result<Vec<[f32; 4]>, RenderError> {
        Ok(self.read_blocking(ctx)?.rgba_f32)
    }

    /// The displayed mean (the Rgba8Unorm texture), read back and waited for.
    pub fn read_mean_blocking(&self, ctx: &GpuContext) -> Result<Vec<u8>, RenderError> {
        Ok(self.read_blocking(ctx)?.rgba)
    }

    fn read_blocking(
        &self,
        ctx: &GpuContext,
    ) -> Result<crate::gpu::frame_targets::TargetPixels, RenderError> {
        let t = self.filled_targets()?;
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("progressive readback"),
            });
        t.encode_readback(&mut encoder);
        ctx.queue.submit(Some(encoder.finish()));
        t.read_mapped(&ctx.device)
    }

    fn filled_targets(&self) -> Result<&FrameTargets, RenderError> {
        match self.targets.as_ref() {
            Some(t) if self.frames > 0 => Ok(t),
            _ => Err(RenderError::Readback(
                "no frame accumulated since the last reset".into(),
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shader_parses_and_validates() {
        let module = naga::front::wgsl::parse_str(WGSL).unwrap();
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::default(),
        )
        .validate(&module)
        .unwrap();
    }

    #[test]
    fn key_ignores_frame_index_and_sample_counting_only() {
        let cam = Camera::look_at(
            [0.0, 0.0, 10.0],
            [0.0; 3],
            [0.0, 1.0, 0.0],
            crate::model::camera::Projection::Orthographic { height_mm: 4.0 },
        );
        let s = RenderSettings::default();
        let k = ViewKey::new(&cam, &s);
        assert_eq!(k, ViewKey::new(&cam, &jittered_frame(&s, 7)));
        let counted = RenderSettings {
            count_samples: true,
            ..s.clone()
        };
        assert_eq!(k, ViewKey::new(&cam, &counted));
        let finer = RenderSettings {
            quality: 0.25,
            ..s.clone()
        };
        assert_ne!(k, ViewKey::new(&cam, &finer));
        assert_ne!(k, k.clone().with_generation(1));
        let moved = Camera::look_at(
            [0.0, 0.1, 10.0],
            [0.0; 3],
            [0.0, 1.0, 0.0],
            crate::model::camera::Projection::Orthographic { height_mm: 4.0 },
        );
        assert_ne!(k, ViewKey::new(&moved, &s));
    }
}
