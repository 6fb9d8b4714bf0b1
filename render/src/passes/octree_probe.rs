//! The octree traversal's leaf walk on the GPU, for tests only (feature `test-probe`): the
//! same `octree.wgsl` lookups the raycaster's march uses (point query, rope + descent), driven
//! leaf by leaf by `shaders/octree_walk.wgsl` in a shader module of its own, and the leaves
//! each ray visited (with entry/exit t) read back from a debug buffer. Tests compare them with
//! [`OctreeCut::leaves_on_ray_brute_force`].

use crate::error::RenderError;
use crate::gpu::device::GpuContext;
use crate::gpu::frame_targets::{read_buffer_blocking, readback_buffer};
use crate::gpu::gpu_octree::encode_node_buffer;
use crate::gpu::shaders;
use crate::model::octree_cut::{LeafVisit, OctreeCut};

const WALK_WGSL: &str = include_str!("../shaders/octree_walk.wgsl");

/// A ray in page-cell units: origin, direction, [t0, t1] (t1 may be +inf).
pub type WalkRay = ([f64; 3], [f64; 3], f64, f64);

/// The leaves each ray crosses by the GPU traversal (node indices of `cut`, f32 t widened),
/// at most `max_visits` per ray.
pub fn walk_on_gpu(
    ctx: &GpuContext,
    cut: &OctreeCut,
    rays: &[WalkRay],
    max_visits: u32,
) -> Result<Vec<Vec<LeafVisit>>, RenderError> {
    if rays.is_empty() {
        return Ok(Vec::new());
    }
    let device = &ctx.device;
    let (words, _, node_of_record) = encode_node_buffer(cut, [1, 1, 1])?;
    let source = shaders::compose_alone(&[
        ("octree.wgsl", shaders::OCTREE_WGSL),
        ("octree_walk.wgsl", WALK_WGSL),
    ]);
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some("octree_walk.wgsl"),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some("octree walk"),
        layout: None,
        module: &module,
        entry_point: Some("octree_walk"),
        compilation_options: Default::default(),
        cache: None,
    });
    let init = |label: &str, contents: &[u8], usage| {
        wgpu::util::DeviceExt::create_buffer_init(
            device,
            &wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents,
                usage,
            },
        )
    };
    let d = cut.page_dims;
    let params: [u32; 8] = [d[0], d[1], d[2], rays.len() as u32, max_visits, 0, 0, 0];
    let params = init(
        "walk params",
        bytemuck::cast_slice(&params),
        wgpu::BufferUsages::UNIFORM,
    );
    // f32 on the GPU; +inf as the largest finite f32 (the walk only compares with it).
    let f = |v: f64| v.clamp(-3.0e38, 3.0e38) as f32;
    let packed: Vec<[f32; 4]> = rays
        .iter()
        .flat_map(|(o, dir, t0, t1)| {
            [
                [f(o[0]), f(o[1]), f(o[2]), f(*t0)],
                [f(dir[0]), f(dir[1]), f(dir[2]), f(*t1)],
            ]
        })
        .collect();
    let rays_buffer = init(
        "walk rays",
        bytemuck::cast_slice(&packed),
        wgpu::BufferUsages::STORAGE,
    );
    let nodes = init(
        "octree nodes",
        bytemuck::cast_slice(&words),
        wgpu::BufferUsages::STORAGE,
    );
    let stride = 1 + 3 * max_visits as u64;
    let bytes = rays.len() as u64 * stride * 4;
    let out = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("walk visits"),
        size: bytes,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        mapped_at_creation: false,
    });
    let readback = readback_buffer(device, "walk readback", bytes);
    let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("octree walk"),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &[
            wgpu::BindGroupEntry {
                binding: 0,
                resource: params.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 1,
                resource: rays_buffer.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 2,
                resource: out.as_entire_binding(),
            },
            wgpu::BindGroupEntry {
                binding: 12,
                resource: nodes.as_entire_binding(),
            },
        ],
    });
    let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
        label: Some("octree walk"),
    });
    {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("octree walk"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&pipeline);
        pass.set_bind_group(0, &bind_group, &[]);
        pass.dispatch_workgroups((rays.len() as u32).div_ceil(64), 1, 1);
    }
    encoder.copy_buffer_to_buffer(&out, 0, &readback, 0, bytes);
    ctx.queue.submit([encoder.finish()]);
    let words: Vec<u32> = bytemuck::pod_collect_to_vec(&read_buffer_blocking(device, &readback)?);
    Ok((0..rays.len())
        .map(|r| {
            let base = r * stride as usize;
            let n = (words[base] as usize).min(max_visits as usize);
            (0..n)
                .map(|i| {
                    let v = &words[base + 1 + 3 * i..base + 4 + 3 * i];
                    LeafVisit {
                        node: node_of_record
                            .get(v[0] as usize)
                            .copied()
                            .unwrap_or(u32::MAX),
                        t_enter: f32::from_bits(v[1]) as f64,
                        t_exit: f32::from_bits(v[2]) as f64,
                    }
                })
                .collect()
        })
        .collect())
}
