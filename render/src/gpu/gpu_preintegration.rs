//! The length-free pre-integration table on the GPU (binding 10; segment_integral.rs): the
//! table of the last pre-integrated frame, rebuilt only when the TF, its range or the opacity
//! unit changes (never with the step: it holds for every segment length), and a 1×3 stand-in
//! bound when a pipeline does not use it. The adaptive pass (adaptive/gpu.rs) binds it too.

use crate::gpu::gpu_transfer_function::GpuTransferFunction;
use crate::model::segment_integral::{SegmentIntegralTable, INTEGRAL_ROWS};
use crate::model::transfer_function::TransferFunction;

/// What a table was built for; a change of any part rebuilds it.
#[derive(Clone, Debug)]
struct PreintegrationKey {
    transfer_function: TransferFunction,
    lo: f64,
    hi: f64,
    entries: u32,
    unit_mm: f64,
}

struct PreintegrationTexture {
    key: PreintegrationKey,
    view: wgpu::TextureView,
}

pub(crate) struct GpuPreintegration {
    table: Option<PreintegrationTexture>,
    unused: wgpu::TextureView,
}

impl GpuPreintegration {
    pub(crate) fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Self {
        GpuPreintegration {
            table: None,
            unused: table_texture(device, queue, 1, &[[0.0; 4]; INTEGRAL_ROWS as usize]),
        }
    }

    /// What binding 10 gets: the table for a pre-integrated pipeline (once built), else the
    /// stand-in.
    pub(crate) fn view(&self, preintegrated: bool) -> &wgpu::TextureView {
        match (&self.table, preintegrated) {
            (Some(table), true) => &table.view,
            _ => &self.unused,
        }
    }

    /// Builds the table for `tf` (same range and entries as its GPU TF table, so the shader
    /// indexes both alike) with opacity unit `unit_mm`, unless the last one still fits.
    pub(crate) fn ensure(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        tf: &GpuTransferFunction,
        unit_mm: f64,
    ) {
        // Compared field by field so a frame that reuses the table clones nothing.
        if self.table.as_ref().is_some_and(|p| {
            p.key.transfer_function == tf.source
                && p.key.lo == tf.lo
                && p.key.hi == tf.hi
                && p.key.entries == tf.entries
                && p.key.unit_mm == unit_mm
        }) {
            return;
        }
        let key = PreintegrationKey {
            transfer_function: tf.source.clone(),
            lo: tf.lo,
            hi: tf.hi,
            entries: tf.entries,
            unit_mm,
        };
        let table = SegmentIntegralTable::with_entries(
            &key.transfer_function,
            key.lo,
            key.hi,
            key.unit_mm,
            key.entries,
        );
        let view = table_texture(device, queue, table.entries, &table.texels());
        self.table = Some(PreintegrationTexture { key, view });
    }
}

/// An Rgba32Float texture `entries` wide and INTEGRAL_ROWS high, read with textureLoad: exact
/// f32 and no float-filtering feature needed.
fn table_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    entries: u32,
    texels: &[[f32; 4]],
) -> wgpu::TextureView {
    let extent = wgpu::Extent3d {
        width: entries,
        height: INTEGRAL_ROWS,
        depth_or_array_layers: 1,
    };
    let texture = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("pre-integrated transfer function"),
        size: extent,
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba32Float,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    queue.write_texture(
        wgpu::TexelCopyTextureInfo {
            texture: &texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect: wgpu::TextureAspect::All,
        },
        bytemuck::cast_slice(texels),
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(entries * 16),
            rows_per_image: None,
        },
        extent,
    );
    texture.create_view(&wgpu::TextureViewDescriptor::default())
}
