//! Picking in the page's 3D view: a click moves the crosshair to what is seen there, as on the
//! desktop. The raycaster keeps each frame's pick depth on the GPU; a click copies that one
//! pixel's depth back (4 bytes) and maps it, and the page goes on drawing while the browser
//! resolves the mapping (no frame waits on it). The position is then the desktop's: the same
//! pixel, ray and clamp (strata-viewer-ui's picking).

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;

use strata_render::{Camera, GpuContext, VolumeGeometry};
use strata_viewer_ui::picking::picked_index;

const MAPPING: u8 = 0;
const MAPPED: u8 = 1;
const FAILED: u8 = 2;

/// Why a pick gave no position.
#[derive(Debug, thiserror::Error)]
pub enum PickError {
    #[error("reading the 3D view's pick depth back failed: {0}")]
    Readback(String),
}

/// One pixel's depth on its way back from the GPU, with the frame it was read from.
pub struct PendingPick {
    buffer: wgpu::Buffer,
    state: Arc<AtomicU8>,
    camera: Camera,
    pixel: [u32; 2],
    size: [u32; 2],
}

impl PendingPick {
    /// Copies the depth of `pixel` from `depth` (the pick depth of a `size` frame drawn with
    /// `camera`) and starts mapping it; the browser's event loop finishes the mapping and
    /// `ctx` is asked to repaint then.
    pub fn start(
        gpu: &GpuContext,
        depth: &wgpu::Buffer,
        size: [u32; 2],
        pixel: [u32; 2],
        camera: Camera,
        ctx: &egui::Context,
    ) -> Self {
        let buffer = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("strata-web pick depth"),
            size: 4,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut encoder = gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("strata-web pick depth"),
            });
        let offset = (u64::from(pixel[1]) * u64::from(size[0]) + u64::from(pixel[0])) * 4;
        encoder.copy_buffer_to_buffer(depth, offset, &buffer, 0, 4);
        gpu.queue.submit(Some(encoder.finish()));
        let state = Arc::new(AtomicU8::new(MAPPING));
        let done = state.clone();
        let repaint = ctx.clone();
        buffer
            .slice(..)
            .map_async(wgpu::MapMode::Read, move |result| {
                done.store(
                    if result.is_ok() { MAPPED } else { FAILED },
                    Ordering::Release,
                );
                repaint.request_repaint();
            });
        PendingPick {
            buffer,
            state,
            camera,
            pixel,
            size,
        }
    }

    /// `None` while the depth is on its way; then the level-0 continuous index seen at the
    /// pixel (`Ok(None)` where the ray met nothing).
    pub fn poll(&self, geometry: &VolumeGeometry) -> Option<Result<Option<[f64; 3]>, PickError>> {
        match self.state.load(Ordering::Acquire) {
            MAPPING => None,
            FAILED => Some(Err(PickError::Readback("the mapping failed".into()))),
            _ => Some(self.read(geometry)),
        }
    }

    fn read(&self, geometry: &VolumeGeometry) -> Result<Option<[f64; 3]>, PickError> {
        let depth_mm = {
            let mapped = self
                .buffer
                .slice(..)
                .get_mapped_range()
                .map_err(|e| PickError::Readback(e.to_string()))?;
            let bytes: [u8; 4] = mapped[..4]
                .try_into()
                .map_err(|_| PickError::Readback("the mapped depth is not 4 bytes".into()))?;
            f32::from_le_bytes(bytes)
        };
        self.buffer.unmap();
        Ok(picked_index(
            &self.camera,
            geometry,
            self.pixel,
            self.size,
            depth_mm,
        ))
    }
}
