//! The field probe, for tests only (feature `test-probe`, which render's own tests enable
//! through a dev-dependency on the crate itself): the field the raycaster samples, read back at
//! given points. Its entry point (`shaders/probe.wgsl`, bindings 12 and 13) is composed with the
//! field files into a shader module of its own, built when a probe runs, so the production
//! raycast shader never contains it.

use std::sync::OnceLock;

use crate::error::RenderError;
use crate::gpu::device::GpuContext;
use crate::gpu::frame_targets::{read_buffer_blocking, readback_buffer};
use crate::gpu::shaders;
use crate::passes::raycast::{build_params, FrameInputs, Raycaster};

const PROBE_WGSL: &str = include_str!("../shaders/probe.wgsl");
/// The probe's workgroup width (one invocation per point).
const PROBE_WORKGROUP_SIZE: u32 = 64;

/// The probe's shader (prelude, field files, probe.wgsl) and the overrides it declares, both
/// made once.
fn probe_source() -> (&'static str, &'static [String]) {
    static SOURCE: OnceLock<(String, Vec<String>)> = OnceLock::new();
    let (source, declared) = SOURCE.get_or_init(|| {
        let prelude = shaders::constants_wgsl(&[(
            "PROBE_WORKGROUP_SIZE",
            shaders::PreludeValue::U32(PROBE_WORKGROUP_SIZE),
        )]);
        let source = shaders::compose_with_field(&[
            ("probe prelude", &prelude),
            shaders::FLAT_NEIGHBOUR,
            ("probe.wgsl", PROBE_WGSL),
        ]);
        let declared = shaders::declared_overrides(&source).unwrap_or_default();
        (source, declared)
    });
    (source, declared)
}

impl Raycaster {
    /// The field the raycaster samples, read back at level-0 index `points` (physical units;
    /// NaN where nothing is resident): the same `field()` (field.wgsl) the raycaster samples,
    /// run by the `probe` entry point of a shader module of its own. For tests of continuity
    /// and of GPU-vs-reference sampling.
    pub fn probe_field(
        &mut self,
        ctx: &GpuContext,
        scene: &FrameInputs,
        points: &[[f32; 3]],
    ) -> Result<Vec<f32>, RenderError> {
        if points.is_empty() {
            return Ok(Vec::new());
        }
        let device = &ctx.device;
        let key = self.key_for_scene(scene);
        let entry = |binding: u32, ty: wgpu::BindingType| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty,
            count: None,
        };
        let storage = |read_only: bool| wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        };
        let filterable = self.filterable;
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("field probe"),
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
                        sample_type: wgpu::TextureSampleType::Float { filterable },
                        view_dimension: wgpu::TextureViewDimension::D3,
                        multisampled: false,
                    },
                ),
                entry(
                    2,
                    wgpu::BindingType::Sampler(if filterable {
                        wgpu::SamplerBindingType::Filtering
                    } else {
                        wgpu::SamplerBindingType::NonFiltering
                    }),
                ),
                entry(3, storage(true)),
                entry(11, storage(true)),
                entry(12, storage(true)),
                entry(13, storage(false)),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("field probe"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let (source, declared) = probe_source();
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("probe.wgsl"),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        let b = |v: bool| if v { 1.0 } else { 0.0 };
        let constants: Vec<(&str, f64)> = [
            ("MANUAL_TRILINEAR", b(key.manual_trilinear)),
            ("SMOOTH_TRANSITIONS", b(key.smooth_transitions)),
        ]
        .into_iter()
        .filter(|(name, _)| declared.iter().any(|d| d == name))
        .collect();
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("field probe"),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some("probe"),
            compilation_options: wgpu::PipelineCompilationOptions {
                constants: &constants,
                zero_initialize_workgroup_memory: false,
            },
            cache: None,
        });
        let params = build_params(scene);
        ctx.queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
        let padded: Vec<[f32; 4]> = points.iter().map(|p| [p[0], p[1], p[2], 0.0]).collect();
        let points_buffer = wgpu::util::DeviceExt::create_buffer_init(
            device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("probe points"),
                contents: bytemuck::cast_slice(&padded),
                usage: wgpu::BufferUsages::STORAGE,
            },
        );
        let bytes = points.len() as u64 * 4;
        let values = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("probe values"),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let readback = readback_buffer(device, "probe readback", bytes);
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("field probe"),
            layout: &layout,
            entries: &Self::field_entries(
                &self.params,
                &self.sampler,
                scene,
                &scene.page_table.transitions,
            )
            .into_iter()
            .chain([
                wgpu::BindGroupEntry {
                    binding: 12,
                    resource: points_buffer.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 13,
                    resource: values.as_entire_binding(),
                },
            ])
            .collect::<Vec<_>>(),
        });
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("field probe"),
        });
        {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("field probe"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&pipeline);
            pass.set_bind_group(0, &bind_group, &[]);
            pass.dispatch_workgroups((points.len() as u32).div_ceil(PROBE_WORKGROUP_SIZE), 1, 1);
        }
        encoder.copy_buffer_to_buffer(&values, 0, &readback, 0, bytes);
        ctx.queue.submit([encoder.finish()]);
        Ok(bytemuck::pod_collect_to_vec(&read_buffer_blocking(
            device, &readback,
        )?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn probe_shader_validates_and_declares_only_the_field_overrides() {
        let (source, declared) = probe_source();
        let module = naga::front::wgsl::parse_str(source)
            .unwrap_or_else(|e| panic!("{}", e.emit_to_string(source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::default(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{}", e.emit_to_string(source)));
        let entry_points: Vec<&str> = module
            .entry_points
            .iter()
            .map(|e| e.name.as_str())
            .collect();
        assert_eq!(entry_points, ["probe"]);
        let mut declared = declared.to_vec();
        declared.sort();
        assert_eq!(declared, ["MANUAL_TRILINEAR", "SMOOTH_TRANSITIONS"]);
    }
}
