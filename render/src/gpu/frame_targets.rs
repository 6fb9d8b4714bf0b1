//! The targets a pass draws one frame into and their blocking readback, defined once for every
//! pass: the raycaster (raycast.rs), the adaptive pass (adaptive/gpu.rs) and the progressive
//! mean (progressive.rs) each hold a [`FrameTargets`] (the RGBA8 colour texture the app
//! displays, plus the per-pixel buffers the pass writes) and, where the pass marks visible
//! pages, a [`VisibilityTarget`]. One-off result buffers (the test probes' values) read back
//! through [`read_buffer_blocking`].
//!
//! The readback is for tests, the CLI and benchmarks: [`FrameTargets::encode_readback`] copies
//! every target into its staging buffer in the caller's encoder (so a pass adds its own
//! counters to the same submission), [`FrameTargets::read_mapped`] waits and unpads the rows.

use crate::error::RenderError;
use crate::gpu::device::map_blocking;
use crate::gpu::readback_ring::ReadbackRing;

/// Every pass's displayed colour: premultiplied RGBA8, the format the app samples.
pub(crate) const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;

/// The per-pixel buffers a pass writes beside its colour texture.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct PixelBuffers {
    /// One f32 per pixel: the pick depth (layout.rs `DEPTH_OPACITY`).
    pub(crate) depth: bool,
    /// One `vec4<f32>` per pixel: colour before quantisation (the adaptive pass's test output,
    /// the progressive running mean).
    pub(crate) rgba_f32: bool,
}

/// A per-pixel storage buffer and the staging buffer it is read back through.
struct PixelBuffer {
    buffer: wgpu::Buffer,
    readback: wgpu::Buffer,
}

/// One frame's targets at one size.
pub(crate) struct FrameTargets {
    width: u32,
    height: u32,
    color: wgpu::Texture,
    color_view: wgpu::TextureView,
    color_readback: wgpu::Buffer,
    /// Bytes per row of `color_readback`: texture copies need rows aligned to 256 bytes.
    padded_row_bytes: u32,
    depth: Option<PixelBuffer>,
    rgba_f32: Option<PixelBuffer>,
}

/// A frame read back: the colour rows unpadded, and the buffers the targets have (empty where
/// they have none).
pub(crate) struct TargetPixels {
    /// Premultiplied RGBA8, row 0 at the top.
    pub(crate) rgba: Vec<u8>,
    pub(crate) depth: Vec<f32>,
    pub(crate) rgba_f32: Vec<[f32; 4]>,
}

fn buffer(
    device: &wgpu::Device,
    label: &str,
    size: u64,
    usage: wgpu::BufferUsages,
) -> wgpu::Buffer {
    device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage,
        mapped_at_creation: false,
    })
}

/// A staging buffer the CPU maps to read `size` bytes copied from the GPU.
pub(crate) fn readback_buffer(device: &wgpu::Device, label: &str, size: u64) -> wgpu::Buffer {
    buffer(
        device,
        label,
        size,
        wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
    )
}

/// Maps `buffer` (a [`readback_buffer`] whose copy was submitted), waits, and returns its
/// bytes; the buffer is unmapped again for the next frame.
pub(crate) fn read_buffer_blocking(
    device: &wgpu::Device,
    buffer: &wgpu::Buffer,
) -> Result<Vec<u8>, RenderError> {
    map_blocking(device, buffer)?;
    let bytes = buffer
        .get_mapped_range(..)
        .map_err(|e| RenderError::Readback(e.to_string()))?
        .to_vec();
    buffer.unmap();
    Ok(bytes)
}

impl FrameTargets {
    /// The targets of a `width`×`height` frame; `label` names the pass in GPU debuggers.
    pub(crate) fn new(
        device: &wgpu::Device,
        label: &str,
        width: u32,
        height: u32,
        pixel_buffers: PixelBuffers,
    ) -> Self {
        let color = device.create_texture(&wgpu::TextureDescriptor {
            label: Some(&format!("{label} colour")),
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: COLOR_FORMAT,
            usage: wgpu::TextureUsages::STORAGE_BINDING
                | wgpu::TextureUsages::TEXTURE_BINDING
                | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let color_view = color.create_view(&wgpu::TextureViewDescriptor::default());
        let padded_row_bytes = (width * 4).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
            * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let pixels = width as u64 * height as u64;
        let pixel_buffer = |name: &str, bytes_per_pixel: u64| PixelBuffer {
            buffer: buffer(
                device,
                &format!("{label} {name}"),
                pixels * bytes_per_pixel,
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            ),
            readback: readback_buffer(
                device,
                &format!("{label} {name} readback"),
                pixels * bytes_per_pixel,
            ),
        };
        FrameTargets {
            width,
            height,
            color_readback: readback_buffer(
                device,
                &format!("{label} colour readback"),
                padded_row_bytes as u64 * height as u64,
            ),
            color,
            color_view,
            padded_row_bytes,
            depth: pixel_buffers.depth.then(|| pixel_buffer("depth", 4)),
            rgba_f32: pixel_buffers.rgba_f32.then(|| pixel_buffer("rgba f32", 16)),
        }
    }

    /// Makes `slot` hold targets of this size, keeping the present ones when they already
    /// are; true when they were (re)created, so a pass can restart what it accumulated.
    pub(crate) fn ensure(
        slot: &mut Option<FrameTargets>,
        device: &wgpu::Device,
        label: &str,
        width: u32,
        height: u32,
        pixel_buffers: PixelBuffers,
    ) -> bool {
        if slot
            .as_ref()
            .is_some_and(|t| t.width == width && t.height == height)
        {
            return false;
        }
        *slot = Some(FrameTargets::new(
            device,
            label,
            width,
            height,
            pixel_buffers,
        ));
        true
    }

    pub(crate) fn width(&self) -> u32 {
        self.width
    }

    pub(crate) fn height(&self) -> u32 {
        self.height
    }

    pub(crate) fn color(&self) -> &wgpu::Texture {
        &self.color
    }

    pub(crate) fn color_view(&self) -> &wgpu::TextureView {
        &self.color_view
    }

    /// The pick-depth buffer, for the pass's bind group.
    pub(crate) fn depth(&self) -> Result<&wgpu::Buffer, RenderError> {
        self.depth
            .as_ref()
            .map(|b| &b.buffer)
            .ok_or_else(|| RenderError::Readback("these frame targets have no depth".into()))
    }

    /// The f32 colour buffer, for the pass's bind group.
    pub(crate) fn rgba_f32(&self) -> Result<&wgpu::Buffer, RenderError> {
        self.rgba_f32
            .as_ref()
            .map(|b| &b.buffer)
            .ok_or_else(|| RenderError::Readback("these frame targets have no f32 colour".into()))
    }

    /// Encodes the copy of every target into its staging buffer.
    pub(crate) fn encode_readback(&self, encoder: &mut wgpu::CommandEncoder) {
        encoder.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &self.color,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &self.color_readback,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(self.padded_row_bytes),
                    rows_per_image: Some(self.height),
                },
            },
            wgpu::Extent3d {
                width: self.width,
                height: self.height,
                depth_or_array_layers: 1,
            },
        );
        for pixel_buffer in [&self.depth, &self.rgba_f32].into_iter().flatten() {
            encoder.copy_buffer_to_buffer(
                &pixel_buffer.buffer,
                0,
                &pixel_buffer.readback,
                0,
                pixel_buffer.buffer.size(),
            );
        }
    }

    /// Waits for the copies [`FrameTargets::encode_readback`] encoded (the caller submitted
    /// them) and returns the pixels.
    pub(crate) fn read_mapped(&self, device: &wgpu::Device) -> Result<TargetPixels, RenderError> {
        let padded = read_buffer_blocking(device, &self.color_readback)?;
        let row = (self.width * 4) as usize;
        let mut rgba = Vec::with_capacity(row * self.height as usize);
        for y in 0..self.height as usize {
            let start = y * self.padded_row_bytes as usize;
            rgba.extend_from_slice(&padded[start..start + row]);
        }
        let depth = match &self.depth {
            Some(b) => bytemuck::pod_collect_to_vec(&read_buffer_blocking(device, &b.readback)?),
            None => Vec::new(),
        };
        let rgba_f32 = match &self.rgba_f32 {
            Some(b) => bytemuck::pod_collect_to_vec(&read_buffer_blocking(device, &b.readback)?),
            None => Vec::new(),
        };
        Ok(TargetPixels {
            rgba,
            depth,
            rgba_f32,
        })
    }
}

/// The per-page (or per-leaf) visibility words a pass marks, with their blocking readback and,
/// for a pass the loader polls every frame, a staging ring read 1-2 frames late.
pub(crate) struct VisibilityTarget {
    /// Words the buffers hold (a power of two: a cut that changes its leaf count keeps them).
    capacity: usize,
    /// Words the last frame wrote: page cells (flat) or leaves (octree).
    entries: usize,
    buffer: wgpu::Buffer,
    blocking_readback: wgpu::Buffer,
    ring: Option<ReadbackRing>,
}

impl VisibilityTarget {
    /// Makes `slot` hold at least `entries` words (`ring_slots` > 0 adds a staging ring).
    pub(crate) fn ensure(
        slot: &mut Option<VisibilityTarget>,
        device: &wgpu::Device,
        label: &str,
        entries: usize,
        ring_slots: usize,
    ) {
        if let Some(v) = slot.as_mut().filter(|v| v.capacity >= entries) {
            v.entries = entries;
            return;
        }
        let capacity = entries.max(1).next_power_of_two();
        let size = (capacity * 4) as u64;
        *slot = Some(VisibilityTarget {
            capacity,
            entries,
            buffer: buffer(
                device,
                &format!("{label} visibility"),
                size,
                wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
            ),
            blocking_readback: readback_buffer(
                device,
                &format!("{label} visibility readback"),
                size,
            ),
            ring: (ring_slots > 0).then(|| {
                ReadbackRing::new(
                    device,
                    &format!("{label} visibility staging"),
                    ring_slots,
                    size,
                )
            }),
        });
    }

    /// The storage buffer, for the pass's bind group and clear.
    pub(crate) fn buffer(&self) -> &wgpu::Buffer {
        &self.buffer
    }

    /// The words the last frame wrote.
    pub(crate) fn entries(&self) -> usize {
        self.entries
    }

    /// Copies the frame's words into a free slot of the staging ring, if there is a ring and
    /// a free slot (a busy ring, the loader not reading, just drops this frame's words); the
    /// slot, for [`VisibilityTarget::map_after_submit`].
    pub(crate) fn encode_ring_copy(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        frame_number: u64,
    ) -> Option<usize> {
        let size = (self.entries.max(1) * 4) as u64;
        let ring = self.ring.as_mut()?;
        let slot = ring.free_slot()?;
        ring.encode_copy(encoder, slot, &self.buffer, 0, size, frame_number);
        Some(slot)
    }

    /// Maps ring slot `slot` once its copy is submitted.
    pub(crate) fn map_after_submit(&self, slot: usize) {
        if let Some(ring) = self.ring.as_ref() {
            ring.map_after_submit(slot);
        }
    }

    /// Hands over every ring slot whose copy finished (frame number, bytes) and frees it.
    pub(crate) fn drain_ring(&mut self, read: impl FnMut(u64, &[u8])) {
        if let Some(ring) = self.ring.as_mut() {
            ring.drain(read);
        }
    }

    /// Encodes the copy of the last frame's words into the blocking staging buffer.
    pub(crate) fn encode_readback(&self, encoder: &mut wgpu::CommandEncoder) {
        encoder.copy_buffer_to_buffer(
            &self.buffer,
            0,
            &self.blocking_readback,
            0,
            (self.entries.max(1) * 4) as u64,
        );
    }

    /// Waits for the copy [`VisibilityTarget::encode_readback`] encoded; the whole capacity
    /// comes back (the caller keeps the frame's entries).
    pub(crate) fn read_mapped(&self, device: &wgpu::Device) -> Result<Vec<u32>, RenderError> {
        Ok(bytemuck::pod_collect_to_vec(&read_buffer_blocking(
            device,
            &self.blocking_readback,
        )?))
    }
}
