//! The pre-integrated transfer function on the GPU (binding 10): the table of the last
//! pre-integrated frame, rebuilt only when the TF, its range or the step changes, and a 1×1
//! stand-in bound when a pipeline does not use it.

use crate::gpu_transfer_function::GpuTransferFunction;
use crate::preintegration::{PreintegrationTable, PREINTEGRATION_SIZE};
use crate::transfer_function::TransferFunction;

/// What a pre-integration table was built for; a change of any part rebuilds it.
#[derive(Clone, Debug)]
struct PreintegrationKey {
    transfer_function: TransferFunction,
    lo: f64,
    hi: f64,
    segment_mm: f64,
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
            unused: table_texture(device, queue, 1, &[[0.0; 4]]),
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

    /// Builds the table for `tf` and a base step of `segment_mm` (opacity unit `unit_mm`)
    /// unless the last one still fits. Integrating 256² segments takes tens of milliseconds on
    /// two cores, so it happens only when the TF, its range or the step changes, not per frame.
    pub(crate) fn ensure(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        tf: &GpuTransferFunction,
        segment_mm: f64,
        unit_mm: f64,
    ) {
        // Compared field by field so a frame that reuses the table clones nothing.
        if self.table.as_ref().is_some_and(|p| {
            p.key.transfer_function == tf.source
                && p.key.lo == tf.lo
                && p.key.hi == tf.hi
                && p.key.segment_mm == segment_mm
                && p.key.unit_mm == unit_mm
        }) {
            return;
        }
        let key = PreintegrationKey {
            transfer_function: tf.source.clone(),
            lo: tf.lo,
            hi: tf.hi,
            segment_mm,
            unit_mm,
        };
        let table = PreintegrationTable::build(
            &key.transfer_function,
            key.lo,
            key.hi,
            key.segment_mm,
            key.unit_mm,
            PREINTEGRATION_SIZE,
        );
        let view = table_texture(device, queue, table.size, &table.rgba);
        self.table = Some(PreintegrationTexture { key, view });
    }
}

/// A square Rgba32Float texture of `size`² entries (row = back value, column = front value),
/// read with textureLoad: exact f32 and no float-filtering feature needed.
fn table_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    size: u32,
    rgba: &[[f32; 4]],
) -> wgpu::TextureView {
    let extent = wgpu::Extent3d {
        width: size,
        height: size,
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
        bytemuck::cast_slice(rgba),
        wgpu::TexelCopyBufferLayout {
            offset: 0,
            bytes_per_row: Some(size * 16),
            rows_per_image: None,
        },
        extent,
    );
    texture.create_view(&wgpu::TextureViewDescriptor::default())
}
