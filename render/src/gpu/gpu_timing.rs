//! How long the raycast pass took, measured without stalling the render loop.
//!
//! Users of other viewers' adaptive modes complain that the frame rate target misbehaves because
//! the CPU clock around `submit` measures command recording, not the GPU work (§3.2.1 of the
//! time-critical paper needs `glFinish` for the same reason). Two sources, best first:
//!
//! - [`FrameTimingSource::GpuTimestamps`]: the compute pass writes begin/end timestamps into a
//!   query set; each frame resolves into its own slot of a small ring of staging buffers that is
//!   mapped asynchronously (readback_ring.rs, the ring the visibility readback uses too), so a
//!   frame's time arrives one or two frames later and nothing waits.
//!   Lavapipe exposes `TIMESTAMP_QUERY` (Vulkan `timestampValidBits` = 64).
//! - [`FrameTimingSource::SubmitToDone`]: adapters without timestamps. Only the measuring path
//!   ([`crate::Raycaster::render_measured`]) waits: it lets earlier work drain, then times
//!   submit → completion of the raycast submission on the CPU clock. UI drawing is submitted
//!   later and is never inside the interval.

use crate::gpu::readback_ring::ReadbackRing;

/// Timestamp slots in flight. Three frames of latency cover lavapipe and discrete GPUs; a
/// frame that finds the ring full is simply not timed.
const TIMESTAMP_RING: usize = 4;
const SLOT_BYTES: u64 = 2 * wgpu::QUERY_SIZE as u64;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameTimingSource {
    /// Begin/end-of-pass timestamps written by the GPU.
    GpuTimestamps,
    /// CPU clock from submit until the GPU reports the submission done (stalls; fallback only).
    SubmitToDone,
}

/// The measured duration of one submitted raycast frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameTiming {
    /// The raycaster's frame number (see [`crate::Raycaster::frame_number`]).
    pub frame_number: u64,
    pub milliseconds: f64,
    pub source: FrameTimingSource,
}

/// Query set + resolve buffer + a ring of mappable staging buffers.
pub(crate) struct PassTimestamps {
    query_set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    ring: ReadbackRing,
    nanoseconds_per_tick: f64,
    /// Slot the pass being encoded writes into, chosen by `begin_frame`.
    current: Option<usize>,
}

impl PassTimestamps {
    /// None when the device was created without `TIMESTAMP_QUERY`.
    pub(crate) fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Option<Self> {
        if !device.features().contains(wgpu::Features::TIMESTAMP_QUERY) {
            return None;
        }
        let query_set = device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("raycast pass timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: 2 * TIMESTAMP_RING as u32,
        });
        // resolve_query_set needs 256-byte aligned destination offsets: one aligned row per slot.
        let resolve = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("raycast timestamps resolve"),
            size: wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT * TIMESTAMP_RING as u64,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let ring = ReadbackRing::new(
            device,
            "raycast timestamps staging",
            TIMESTAMP_RING,
            SLOT_BYTES,
        );
        Some(PassTimestamps {
            query_set,
            resolve,
            ring,
            nanoseconds_per_tick: queue.get_timestamp_period() as f64,
            current: None,
        })
    }

    /// Picks a free slot for the frame about to be encoded; a reader that fell behind leaves
    /// none, and that frame goes untimed.
    pub(crate) fn begin_frame(&mut self) {
        self.current = self.ring.free_slot();
    }

    /// The pass's timestamp writes for the slot `begin_frame` chose.
    pub(crate) fn pass_writes(&self) -> Option<wgpu::ComputePassTimestampWrites<'_>> {
        let slot = self.current? as u32;
        Some(wgpu::ComputePassTimestampWrites {
            query_set: &self.query_set,
            beginning_of_pass_write_index: Some(2 * slot),
            end_of_pass_write_index: Some(2 * slot + 1),
        })
    }

    /// After the pass: resolve this frame's two timestamps and copy them to its staging buffer.
    pub(crate) fn encode_resolve(&mut self, encoder: &mut wgpu::CommandEncoder, frame_number: u64) {
        let Some(i) = self.current else { return };
        let offset = wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT * i as u64;
        let first = 2 * i as u32;
        encoder.resolve_query_set(&self.query_set, first..first + 2, &self.resolve, offset);
        self.ring
            .encode_copy(encoder, i, &self.resolve, offset, SLOT_BYTES, frame_number);
    }

    /// After submit: map this frame's staging buffer; the callback fires once the GPU is done.
    pub(crate) fn after_submit(&mut self) {
        let Some(i) = self.current.take() else { return };
        self.ring.map_after_submit(i);
    }

    /// Every finished frame's pass duration, oldest first. Never blocks (the caller polls).
    pub(crate) fn take_ready(&mut self) -> Vec<FrameTiming> {
        let mut ready = Vec::new();
        let nanoseconds_per_tick = self.nanoseconds_per_tick;
        self.ring.drain(|frame_number, view| {
            let ticks: [u64; 2] = bytemuck::pod_read_unaligned(&view[..16]);
            // A pass whose end precedes its begin (a wrapped or reset counter)
            // has no meaningful duration; the controller is better off without it.
            if ticks[1] > ticks[0] {
                ready.push(FrameTiming {
                    frame_number,
                    milliseconds: (ticks[1] - ticks[0]) as f64 * nanoseconds_per_tick / 1e6,
                    source: FrameTimingSource::GpuTimestamps,
                });
            }
        });
        ready.sort_by_key(|t| t.frame_number);
        ready
    }
}
