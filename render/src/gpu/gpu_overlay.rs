//! The overlay on the GPU (bindings 13-15 of the raycast pass): the resampled grid as an
//! R32Float 3D texture, the colour table as a 1D Rgba32Float texture, both read with
//! textureLoad only (labels are never filtered; no float-filtering feature needed), and the
//! parameters overlay.wgsl reads. Without an overlay, 1-texel stand-ins are bound and the
//! pipelines are compiled without the overlay code (OVERLAY off).

use crate::error::RenderError;
use crate::model::overlay::{OverlayKind, OverlayLut, OverlayVolume};

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct OverlayParams {
    grid: [f32; 4],
    scale: [f32; 4],
    lut: [f32; 4],
    box_lo: [f32; 4],
    box_hi: [f32; 4],
}

pub(crate) struct GpuOverlay {
    grid: wgpu::Texture,
    pub(crate) grid_view: wgpu::TextureView,
    lut: wgpu::Texture,
    pub(crate) lut_view: wgpu::TextureView,
    pub(crate) params: wgpu::Buffer,
    /// The uploaded grid's dims, kind and the primary dims it spans; None: stand-ins only.
    loaded: Option<([u32; 3], OverlayKind)>,
    box_: Option<([f32; 3], [f32; 3])>,
    lut_entries: u32,
    /// The primary's dims the grid spans.
    primary_dims: [u32; 3],
    /// Drawn in frames (an overlay is loaded and shown).
    pub(crate) shown: bool,
}

fn grid_texture(device: &wgpu::Device, dims: [u32; 3]) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some("overlay grid"),
        size: wgpu::Extent3d {
            width: dims[0],
            height: dims[1],
            depth_or_array_layers: dims[2],
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D3,
        format: wgpu::TextureFormat::R32Float,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    })
}

fn lut_texture(device: &wgpu::Device, entries: u32) -> wgpu::Texture {
    device.create_texture(&wgpu::TextureDescriptor {
        label: Some("overlay colour table"),
        size: wgpu::Extent3d {
            width: entries,
            height: 1,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D1,
        format: wgpu::TextureFormat::Rgba32Float,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    })
}

impl GpuOverlay {
    pub(crate) fn new(device: &wgpu::Device) -> Self {
        let grid = grid_texture(device, [1, 1, 1]);
        let lut = lut_texture(device, 1);
        let params = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("overlay params"),
            size: size_of::<OverlayParams>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        GpuOverlay {
            grid_view: grid.create_view(&wgpu::TextureViewDescriptor::default()),
            grid,
            lut_view: lut.create_view(&wgpu::TextureViewDescriptor::default()),
            lut,
            params,
            loaded: None,
            box_: None,
            lut_entries: 1,
            primary_dims: [1; 3],
            shown: false,
        }
    }

    /// Whether frames draw the overlay (loaded, shown, and holding something).
    pub(crate) fn active(&self) -> bool {
        self.shown && self.loaded.is_some() && self.box_.is_some()
    }

    pub(crate) fn clear(&mut self) {
        self.loaded = None;
        self.box_ = None;
    }

    /// Uploads `volume` (a grid spanning the primary's `primary_dims` index box) and `lut`.
    pub(crate) fn set(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        volume: &OverlayVolume,
        lut: &OverlayLut,
        primary_dims: [u32; 3],
    ) -> Result<(), RenderError> {
        let max3d = device.limits().max_texture_dimension_3d;
        if volume.dims.iter().any(|&d| d > max3d) {
            return Err(RenderError::InvalidSettings(format!(
                "overlay grid {:?} exceeds the device's 3D texture limit {max3d}",
                volume.dims
            )));
        }
        if self.loaded.is_none_or(|(dims, _)| dims != volume.dims) {
            self.grid = grid_texture(device, volume.dims);
            self.grid_view = self
                .grid
                .create_view(&wgpu::TextureViewDescriptor::default());
        }
        let [w, h, d] = volume.dims;
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &self.grid,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(&volume.values),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(w * 4),
                rows_per_image: Some(h),
            },
            wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: d,
            },
        );
        self.loaded = Some((volume.dims, volume.kind));
        self.box_ = volume
            .occupied_box(primary_dims)
            .map(|(lo, hi)| (lo.as_vec3().into(), hi.as_vec3().into()));
        self.primary_dims = primary_dims;
        self.set_lut(device, queue, lut)
    }

    /// Replaces the colour table (a style change: no grid upload).
    pub(crate) fn set_lut(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        lut: &OverlayLut,
    ) -> Result<(), RenderError> {
        let n = lut.entries.len() as u32;
        let max1d = device.limits().max_texture_dimension_1d;
        if n == 0 || n > max1d {
            return Err(RenderError::InvalidSettings(format!(
                "overlay colour table has {n} entries (1..={max1d} allowed)"
            )));
        }
        if n != self.lut_entries {
            self.lut = lut_texture(device, n);
            self.lut_view = self
                .lut
                .create_view(&wgpu::TextureViewDescriptor::default());
            self.lut_entries = n;
        }
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &self.lut,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(&lut.entries),
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
        self.write_params(queue, lut);
        Ok(())
    }

    fn write_params(&self, queue: &wgpu::Queue, lut: &OverlayLut) {
        let primary_dims = self.primary_dims;
        let Some((dims, kind)) = self.loaded else {
            return;
        };
        let n = lut.entries.len() as f64;
        let (lo, hi) = self.box_.unwrap_or(([1.0; 3], [0.0; 3]));
        let empty_range = lut.hi <= lut.lo;
        let per_unit = if empty_range {
            0.0
        } else {
            (n - 1.0) / (lut.hi - lut.lo)
        };
        let f = |v: [f32; 3], w: f32| [v[0], v[1], v[2], w];
        let params = OverlayParams {
            grid: [
                dims[0] as f32,
                dims[1] as f32,
                dims[2] as f32,
                if kind == OverlayKind::Continuous {
                    1.0
                } else {
                    0.0
                },
            ],
            scale: [
                (dims[0] as f64 / primary_dims[0] as f64) as f32,
                (dims[1] as f64 / primary_dims[1] as f64) as f32,
                (dims[2] as f64 / primary_dims[2] as f64) as f32,
                n as f32,
            ],
            lut: [
                lut.lo as f32,
                per_unit as f32,
                lut.threshold as f32,
                if empty_range { 1.0 } else { 0.0 },
            ],
            box_lo: f(lo, 0.0),
            box_hi: f(hi, 0.0),
        };
        queue.write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
    }
}
