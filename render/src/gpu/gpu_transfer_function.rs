//! The transfer function table on the GPU (binding 4).

use crate::model::transfer_function::{TransferFunction, TransferFunctionTable};

/// The sampled transfer function: a 1D Rgba32Float texture read with two textureLoads and
/// interpolated in the shader (exact f32, needs no float-filtering feature). A texture rather
/// than a storage buffer because lavapipe gathers buffers lane by lane: as a buffer the TF
/// lookup was about half of a DVR sample's cost.
pub struct GpuTransferFunction {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
    pub lo: f64,
    pub hi: f64,
    pub entries: u32,
    pub source: TransferFunction,
}

impl GpuTransferFunction {
    pub fn new(device: &wgpu::Device, queue: &wgpu::Queue, table: &TransferFunctionTable) -> Self {
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("transfer function"),
            size: wgpu::Extent3d {
                width: table.rgba.len() as u32,
                height: 1,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D1,
            format: wgpu::TextureFormat::Rgba32Float,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        let mut tf = GpuTransferFunction {
            texture,
            view,
            lo: table.lo,
            hi: table.hi,
            entries: table.rgba.len() as u32,
            source: table.source.clone(),
        };
        tf.update(queue, table);
        tf
    }

    /// Replaces the table (same entry count, as produced by `TransferFunction::table`).
    pub fn update(&mut self, queue: &wgpu::Queue, table: &TransferFunctionTable) {
        let n = (table.rgba.len() as u32).min(self.entries);
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &self.texture,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(&table.rgba[..n as usize]),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(n * 16),
                rows_per_image: None,
            },
            wgpu::Extent3d {
                width: n,
                height: 1,
                depth_or_array_layers: 1,
            },
        );
        self.lo = table.lo;
        self.hi = table.hi;
        self.source = table.source.clone();
    }
}
