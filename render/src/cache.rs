//! The brick cache: one 3D texture cut into fixed 36³ slots; any octree level fits any slot.
//! Slot allocation is the loader's business; this module only sizes the texture and uploads.
//!
//! Format: R16Unorm where the device has TEXTURE_FORMAT_16BIT_NORM (exact for 16-bit stores,
//! half the memory of f32, hardware-filterable). Otherwise R32Float holding stored/65535, which
//! is exact too but not filterable, so the shader then does trilinear by hand. 8-bit stores may
//! ask for R8Unorm (`CacheConfig::eight_bit`): half the bytes of R16Unorm, which matters on CPU
//! rasterisers where raycasting is memory-bound. Payloads are always passed as u16 with
//! unchanged values (slope/intercept apply to the stored integer).

use crate::error::RenderError;
use crate::layout::{BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS, MAX_SLOTS, MAX_SLOTS_PER_AXIS};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum CacheFormat {
    R8Unorm,
    R16Unorm,
    R32Float,
}

impl CacheFormat {
    pub fn texture_format(self) -> wgpu::TextureFormat {
        match self {
            CacheFormat::R8Unorm => wgpu::TextureFormat::R8Unorm,
            CacheFormat::R16Unorm => wgpu::TextureFormat::R16Unorm,
            CacheFormat::R32Float => wgpu::TextureFormat::R32Float,
        }
    }

    pub fn bytes_per_voxel(self) -> u64 {
        match self {
            CacheFormat::R8Unorm => 1,
            CacheFormat::R16Unorm => 2,
            CacheFormat::R32Float => 4,
        }
    }

    pub fn filterable(self) -> bool {
        self != CacheFormat::R32Float
    }

    /// Stored value that the texture's normalised 1.0 stands for.
    pub fn stored_at_one(self) -> f64 {
        match self {
            CacheFormat::R8Unorm => 255.0,
            CacheFormat::R16Unorm | CacheFormat::R32Float => 65535.0,
        }
    }
}

#[derive(Clone, Copy, Debug)]
pub struct CacheConfig {
    /// GPU memory the cache texture may use.
    pub budget_bytes: u64,
    /// Upper bound on slots (tests use small caches); None = as many as budget and limits allow.
    pub max_slots: Option<u32>,
    /// Force the R32Float fallback even where R16Unorm exists (to test the fallback).
    pub force_fallback_format: bool,
    /// Store voxels as R8Unorm (every uploaded value must be ≤ 255): for 8-bit sources.
    pub eight_bit: bool,
}

impl Default for CacheConfig {
    fn default() -> Self {
        CacheConfig {
            budget_bytes: 512 << 20,
            max_slots: None,
            force_fallback_format: false,
            eight_bit: false,
        }
    }
}

pub struct BrickCache {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
    pub format: CacheFormat,
    /// Slots per axis; slot s sits at (s % x, (s / x) % y, s / (x·y)) · 36 texels.
    pub slots_per_axis: [u32; 3],
}

/// Slot grid holding as many of `slots` as possible with at most `per_axis_max` per axis,
/// preferring cubic shapes (keeps every texture edge far from the device's 3D limit).
fn slot_grid(slots: u64, per_axis_max: u32) -> [u32; 3] {
    let m = per_axis_max.max(1) as u64;
    let slots = slots.clamp(1, m * m * m);
    let mut best = [1u64, 1, 1];
    let score = |g: [u64; 3]| {
        (
            g[0] * g[1] * g[2],
            std::cmp::Reverse(g[0].max(g[1]).max(g[2])),
        )
    };
    for x in 1..=m.min(slots) {
        for y in 1..=m.min(slots / x) {
            let z = (slots / (x * y)).min(m);
            if z >= 1 && score([x, y, z]) > score(best) {
                best = [x, y, z];
            }
        }
    }
    best.map(|v| v as u32)
}

impl BrickCache {
    pub fn new(device: &wgpu::Device, config: CacheConfig) -> Result<Self, RenderError> {
        let format = if config.eight_bit {
            CacheFormat::R8Unorm
        } else if device
            .features()
            .contains(wgpu::Features::TEXTURE_FORMAT_16BIT_NORM)
            && !config.force_fallback_format
        {
            CacheFormat::R16Unorm
        } else {
            CacheFormat::R32Float
        };
        let limits = device.limits();
        let slot_bytes = BRICK_PAYLOAD_VOXELS as u64 * format.bytes_per_voxel();
        let mut slots = config.budget_bytes / slot_bytes;
        if let Some(m) = config.max_slots {
            slots = slots.min(m as u64);
        }
        slots = slots.min(MAX_SLOTS as u64);
        if slots == 0 {
            return Err(RenderError::CacheTooSmall {
                budget_bytes: config.budget_bytes,
            });
        }
        let per_axis_max =
            (limits.max_texture_dimension_3d / BRICK_PAYLOAD).min(MAX_SLOTS_PER_AXIS);
        if per_axis_max == 0 {
            return Err(RenderError::CacheTooSmall {
                budget_bytes: config.budget_bytes,
            });
        }
        let slots_per_axis = slot_grid(slots, per_axis_max);
        let size = wgpu::Extent3d {
            width: slots_per_axis[0] * BRICK_PAYLOAD,
            height: slots_per_axis[1] * BRICK_PAYLOAD,
            depth_or_array_layers: slots_per_axis[2] * BRICK_PAYLOAD,
        };
        let texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("brick cache"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D3,
            format: format.texture_format(),
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        Ok(BrickCache {
            texture,
            view,
            format,
            slots_per_axis,
        })
    }

    pub fn slot_count(&self) -> u32 {
        self.slots_per_axis.iter().product()
    }

    pub fn texel_dims(&self) -> [u32; 3] {
        self.slots_per_axis.map(|s| s * BRICK_PAYLOAD)
    }

    /// Texel origin of a slot.
    pub fn slot_origin(&self, slot: u32) -> [u32; 3] {
        let [x, y, _] = self.slots_per_axis;
        [
            (slot % x) * BRICK_PAYLOAD,
            ((slot / x) % y) * BRICK_PAYLOAD,
            (slot / (x * y)) * BRICK_PAYLOAD,
        ]
    }

    /// Uploads one 36³ payload (x fastest) into `slot`. Visible to the next submitted frame.
    pub fn upload_brick(
        &self,
        queue: &wgpu::Queue,
        slot: u32,
        payload: &[u16],
    ) -> Result<(), RenderError> {
        if payload.len() != BRICK_PAYLOAD_VOXELS {
            return Err(RenderError::BrickSize {
                got: payload.len(),
                expected: BRICK_PAYLOAD_VOXELS,
            });
        }
        if slot >= self.slot_count() {
            return Err(RenderError::SlotOutOfRange {
                slot,
                slots: self.slot_count(),
            });
        }
        let converted: Vec<u8>;
        let converted_float: Vec<f32>;
        let bytes: &[u8] = match self.format {
            CacheFormat::R8Unorm => {
                if let Some(&v) = payload.iter().find(|&&v| v > 255) {
                    return Err(RenderError::InvalidVolume(format!(
                        "value {v} does not fit the 8-bit brick cache"
                    )));
                }
                converted = payload.iter().map(|&v| v as u8).collect();
                &converted
            }
            CacheFormat::R16Unorm => bytemuck::cast_slice(payload),
            CacheFormat::R32Float => {
                // One pass, no second copy: write_texture stages the bytes itself.
                converted_float = payload.iter().map(|&v| v as f32 / 65535.0).collect();
                bytemuck::cast_slice(&converted_float)
            }
        };
        let o = self.slot_origin(slot);
        let bpv = self.format.bytes_per_voxel() as u32;
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &self.texture,
                mip_level: 0,
                origin: wgpu::Origin3d {
                    x: o[0],
                    y: o[1],
                    z: o[2],
                },
                aspect: wgpu::TextureAspect::All,
            },
            bytes,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(BRICK_PAYLOAD * bpv),
                rows_per_image: Some(BRICK_PAYLOAD),
            },
            wgpu::Extent3d {
                width: BRICK_PAYLOAD,
                height: BRICK_PAYLOAD,
                depth_or_array_layers: BRICK_PAYLOAD,
            },
        );
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::slot_grid;

    #[test]
    fn slot_grid_stays_within_request_and_limits() {
        for n in [1u64, 2, 7, 8, 100, 1000, 100_000] {
            let g = slot_grid(n, 56);
            let total: u64 = g.iter().map(|&v| v as u64).product();
            assert!(total <= n.min(56 * 56 * 56) && total >= 1, "{n} -> {g:?}");
            assert!(g.iter().all(|&v| v <= 56));
            assert!(
                total * 100 >= n.min(56 * 56 * 56) * 97,
                "wastes too much: {n} -> {g:?}"
            );
        }
    }
}
