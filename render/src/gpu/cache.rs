//! The brick cache: one 3D texture cut into fixed 36³ slots; any octree level fits any slot.
//! Slot allocation is the loader's business; this module only sizes the texture, grows it with
//! the slots in use when asked to (`CacheConfig::grow_with_use`), and uploads.
//!
//! Format: R16Unorm where the device has TEXTURE_FORMAT_16BIT_NORM (exact for 16-bit stores,
//! half the memory of f32, hardware-filterable). Otherwise R32Float holding stored/65535, which
//! is exact too but not filterable, so the shader then does trilinear by hand. 8-bit stores may
//! ask for R8Unorm (`CacheConfig::eight_bit`): half the bytes of R16Unorm, which matters on CPU
//! rasterisers where raycasting is memory-bound. Payloads are always passed as u16 with
//! unchanged values (slope/intercept apply to the stored integer).

use crate::error::RenderError;
use crate::model::layout::{BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS, MAX_SLOTS, MAX_SLOTS_PER_AXIS};

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
    /// Allocate the texture for the slots in use and grow it as higher slots are asked for
    /// ([`BrickCache::ensure_slot`]) instead of for the whole budget at once: a texture's
    /// first partial write makes wgpu zero all of it (one z-range per 3D texture), which for
    /// a budget of gigabytes put that clearing on the first frame's path (issue 35).
    pub grow_with_use: bool,
}

impl Default for CacheConfig {
    fn default() -> Self {
        CacheConfig {
            budget_bytes: 512 << 20,
            max_slots: None,
            force_fallback_format: false,
            eight_bit: false,
            grow_with_use: false,
        }
    }
}

pub struct BrickCache {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
    pub format: CacheFormat,
    /// Slots per axis of the whole budget's grid; slot s sits at (s % x, (s / x) % y,
    /// s / (x·y)) · 36 texels. Fixed for the cache's life, so slots never move when it grows.
    pub slots_per_axis: [u32; 3],
    /// Slot layers (z) the texture holds now: `slots_per_axis[2]`, or fewer while a cache
    /// made with `grow_with_use` has not needed them yet.
    layers: u32,
}

/// A cache that grows starts with layers of at least this many bytes (then doubles).
const GROWTH_START_BYTES: u64 = 32 << 20;

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

impl CacheFormat {
    /// The format a cache made with `config` takes on `device`.
    pub fn for_device(device: &wgpu::Device, config: &CacheConfig) -> CacheFormat {
        if config.eight_bit {
            CacheFormat::R8Unorm
        } else if device
            .features()
            .contains(wgpu::Features::TEXTURE_FORMAT_16BIT_NORM)
            && !config.force_fallback_format
        {
            CacheFormat::R16Unorm
        } else {
            CacheFormat::R32Float
        }
    }

    /// Bytes of one 36³ slot.
    pub fn slot_bytes(self) -> u64 {
        BRICK_PAYLOAD_VOXELS as u64 * self.bytes_per_voxel()
    }
}

/// The largest single allocation the device reports (wgpu's `max_buffer_size`: on Vulkan the
/// driver's `maxMemoryAllocationSize`, capped at 2 GiB by wgpu on Mesa), for messages only:
/// NVIDIA reports 4 GiB and allocates textures beyond it, so a budget is never refused on it.
pub fn reported_allocation_limit(device: &wgpu::Device) -> u64 {
    device.limits().max_buffer_size
}

/// Runs `f` with wgpu's out-of-memory and validation errors captured instead of reaching the
/// uncaptured-error handler (whose default panics): a budget the device cannot hold becomes
/// an error naming `what`.
pub(crate) fn captured<T>(
    device: &wgpu::Device,
    what: impl FnOnce() -> String,
    f: impl FnOnce() -> T,
) -> Result<T, RenderError> {
    // In the browser a scope's result is a promise that only the event loop resolves, so
    // waiting for it here would never return: there errors reach the device's uncaptured-error
    // handler (the web viewer's shows them) instead of becoming this call's error.
    #[cfg(target_arch = "wasm32")]
    {
        let _ = (device, what);
        Ok(f())
    }
    #[cfg(not(target_arch = "wasm32"))]
    captured_natively(device, what, f)
}

#[cfg(not(target_arch = "wasm32"))]
fn captured_natively<T>(
    device: &wgpu::Device,
    what: impl FnOnce() -> String,
    f: impl FnOnce() -> T,
) -> Result<T, RenderError> {
    let oom = device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
    let validation = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let value = f();
    // Scopes pop in reverse order; wgpu-core resolves them at once (no device poll needed).
    let validation = pollster::block_on(validation.pop());
    let oom = pollster::block_on(oom.pop());
    match oom.or(validation) {
        None => Ok(value),
        Some(error) => Err(RenderError::GpuAllocation {
            what: what(),
            detail: error.to_string(),
            reported_limit_mib: reported_allocation_limit(device) >> 20,
        }),
    }
}

/// For a cache that grows by z-layers: as many layers as the device allows (`per_axis_max`),
/// so a layer (x·y slots), the step it grows by and the least it allocates, is small. A
/// cubic grid's layer is the budget's cube root squared: 189 MiB of an 8 GiB budget.
fn deep_slot_grid(slots: u64, per_axis_max: u32) -> [u32; 3] {
    let m = per_axis_max.max(1) as u64;
    let slots = slots.clamp(1, m * m * m);
    // x·y ≤ slots / z with x, y ≤ m: x the largest ≤ √(slots / z), y = ⌊(slots / z) / x⌋.
    let grid = |z: u64| {
        let xy = slots / z;
        let x = ((xy as f64).sqrt().floor() as u64).clamp(1, m);
        let y = (xy / x).clamp(1, m);
        [x, y, z]
    };
    let total = |g: [u64; 3]| g[0] * g[1] * g[2];
    let depths = (1..=m.min(slots)).rev();
    let best = depths.clone().map(|z| total(grid(z))).max().unwrap_or(1);
    // The deepest grid within 2 % of the most slots any depth holds.
    let g = depths
        .map(grid)
        .find(|&g| total(g) * 50 >= best * 49)
        .unwrap_or([1, 1, 1]);
    g.map(|v| v as u32)
}

impl BrickCache {
    pub fn new(device: &wgpu::Device, config: CacheConfig) -> Result<Self, RenderError> {
        let format = CacheFormat::for_device(device, &config);
        let limits = device.limits();
        let slot_bytes = format.slot_bytes();
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
        let slots_per_axis = if config.grow_with_use {
            deep_slot_grid(slots, per_axis_max)
        } else {
            slot_grid(slots, per_axis_max)
        };
        let layer_bytes = slots_per_axis[0] as u64 * slots_per_axis[1] as u64 * slot_bytes;
        let layers = if config.grow_with_use {
            (GROWTH_START_BYTES.div_ceil(layer_bytes) as u32).clamp(1, slots_per_axis[2])
        } else {
            slots_per_axis[2]
        };
        let texture = create_texture(device, format, slots_per_axis, layers)?;
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        Ok(BrickCache {
            texture,
            view,
            format,
            slots_per_axis,
            layers,
        })
    }

    /// Allocates the texture for the whole budget's grid and frees it unused (wgpu zeroes a
    /// texture at its first use, so this costs the allocation, not the clearing): a budget the
    /// device cannot hold fails here, at open, with the budget named, instead of when the cache
    /// grows into it mid-session. A no-op for a cache that does not grow (already allocated).
    pub fn check_full_allocation(
        &self,
        device: &wgpu::Device,
        budget_bytes: u64,
    ) -> Result<(), RenderError> {
        if self.layers == self.slots_per_axis[2] {
            return Ok(());
        }
        let texture = create_texture(
            device,
            self.format,
            self.slots_per_axis,
            self.slots_per_axis[2],
        )
        .map_err(|e| match e {
            RenderError::GpuAllocation {
                what,
                detail,
                reported_limit_mib,
            } => RenderError::GpuAllocation {
                what: format!("{what} for a GPU budget of {} MiB", budget_bytes >> 20),
                detail,
                reported_limit_mib,
            },
            other => other,
        })?;
        texture.destroy();
        Ok(())
    }

    /// Grows the texture (doubling its slot layers, at most to the budget's grid) until it
    /// holds `slot`, copying what it held; true if it grew. Everything that binds the cache's
    /// view must bind it again after a growth (the raycaster binds per frame).
    pub fn ensure_slot(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        slot: u32,
    ) -> Result<bool, RenderError> {
        if slot >= self.slot_count() {
            return Err(RenderError::SlotOutOfRange {
                slot,
                slots: self.slot_count(),
            });
        }
        let [x, y, z] = self.slots_per_axis;
        let layer = slot / (x * y);
        if layer < self.layers {
            return Ok(false);
        }
        let layers = (self.layers * 2).max(layer + 1).min(z);
        let texture = create_texture(device, self.format, self.slots_per_axis, layers)?;
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("brick cache growth"),
        });
        // Whole layers: slots keep their texel origins (x and y never change).
        encoder.copy_texture_to_texture(
            self.texture.as_image_copy(),
            texture.as_image_copy(),
            self.texture.size(),
        );
        // Pending `write_texture`s to the old texture run before this submission's commands.
        queue.submit([encoder.finish()]);
        self.view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        self.texture = texture;
        self.layers = layers;
        Ok(true)
    }

    /// Slots the texture holds now (all of `slot_count()` unless it grows with use).
    pub fn allocated_slots(&self) -> u32 {
        self.slots_per_axis[0] * self.slots_per_axis[1] * self.layers
    }

    /// Bytes of GPU memory the texture holds now.
    pub fn allocated_bytes(&self) -> u64 {
        self.allocated_slots() as u64 * self.format.slot_bytes()
    }

    pub fn slot_count(&self) -> u32 {
        self.slots_per_axis.iter().product()
    }

    /// Texels of the texture as allocated now (what the shader normalises coordinates by).
    pub fn texel_dims(&self) -> [u32; 3] {
        let [x, y, _] = self.slots_per_axis;
        [x, y, self.layers].map(|s| s * BRICK_PAYLOAD)
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
        if slot >= self.allocated_slots() {
            return Err(RenderError::SlotOutOfRange {
                slot,
                slots: self.allocated_slots(),
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

/// The cache texture for `layers` of the `slots_per_axis` grid, allocated in an error scope.
fn create_texture(
    device: &wgpu::Device,
    format: CacheFormat,
    slots_per_axis: [u32; 3],
    layers: u32,
) -> Result<wgpu::Texture, RenderError> {
    let size = wgpu::Extent3d {
        width: slots_per_axis[0] * BRICK_PAYLOAD,
        height: slots_per_axis[1] * BRICK_PAYLOAD,
        depth_or_array_layers: layers * BRICK_PAYLOAD,
    };
    let bytes = size.width as u64
        * size.height as u64
        * size.depth_or_array_layers as u64
        * format.bytes_per_voxel();
    captured(
        device,
        || format!("the brick cache texture ({} MiB)", bytes >> 20),
        || {
            device.create_texture(&wgpu::TextureDescriptor {
                label: Some("brick cache"),
                size,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D3,
                format: format.texture_format(),
                // COPY_SRC: a growing cache copies itself into its larger successor.
                usage: wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_DST
                    | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            })
        },
    )
}

#[cfg(test)]
mod tests {
    use super::{deep_slot_grid, slot_grid};

    #[test]
    fn deep_slot_grid_keeps_layers_small_and_wastes_little() {
        for (n, m) in [
            (1u64, 56u32),
            (7, 56),
            (100, 56),
            (2876, 113),
            (92_000, 255),
            (175_616, 56),
        ] {
            let g = deep_slot_grid(n, m);
            let total: u64 = g.iter().map(|&v| v as u64).product();
            let wanted = n.min((m as u64).pow(3));
            assert!(total <= wanted && total >= 1, "{n} -> {g:?}");
            assert!(g.iter().all(|&v| v >= 1 && v <= m), "{n} -> {g:?}");
            assert!(total * 100 >= wanted * 97, "wastes too much: {n} -> {g:?}");
            // As deep as the device allows, near enough: a layer is at most twice the
            // thinnest possible (wanted / depth limit), not a cube's wanted^(2/3).
            let layer = g[0] as u64 * g[1] as u64;
            assert!(
                layer * wanted.min(m as u64) <= wanted * 2,
                "layers too thick: {n} -> {g:?}"
            );
        }
        // 8 GiB of R16 slots on a device with 255 slots per axis: layers of ~34 MiB.
        let g = deep_slot_grid((8u64 << 30) / 93_312, 255);
        assert!(g[0] as u64 * g[1] as u64 * 93_312 < 40 << 20, "{g:?}");
    }

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
