//! How long the raycast pass took, measured without stalling the render loop.
//!
//! Users of other viewers' adaptive modes complain that the frame rate target misbehaves because
//! the CPU clock around `submit` measures command recording, not the GPU work (§3.2.1 of the
//! time-critical paper needs `glFinish` for the same reason). Two sources, best first:
//!
//! - [`FrameTimingSource::GpuTimestamps`]: the compute pass writes begin/end timestamps into a
//!   query set; each frame resolves into its own slot of a small ring of staging buffers that is
//!   mapped asynchronously, so a frame's time arrives one or two frames later and nothing waits.
//!   Lavapipe exposes `TIMESTAMP_QUERY` (Vulkan `timestampValidBits` = 64).
//! - [`FrameTimingSource::SubmitToDone`]: adapters without timestamps. Only the measuring path
//!   ([`crate::Raycaster::render_measured`]) waits: it lets earlier work drain, then times
//!   submit → completion of the raycast submission on the CPU clock. UI drawing is submitted
//!   later and is never inside the interval.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;

/// Timestamp slots in flight. Three frames of latency cover lavapipe and discrete GPUs; a
/// frame that finds the ring full is simply not timed.
const TIMESTAMP_RING: usize = 4;
const SLOT_BYTES: u64 = 2 * wgpu::QUERY_SIZE as u64;

const SLOT_FREE: u8 = 0;
const SLOT_PENDING: u8 = 1;
const SLOT_READY: u8 = 2;
const SLOT_FAILED: u8 = 3;

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

struct TimestampSlot {
    staging: wgpu::Buffer,
    state: Arc<AtomicU8>,
    frame_number: u64,
}

/// Query set + resolve buffer + a ring of mappable staging buffers.
pub(crate) struct PassTimestamps {
    query_set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    ring: Vec<TimestampSlot>,
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
        let ring = (0..TIMESTAMP_RING)
            .map(|_| TimestampSlot {
                staging: device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("raycast timestamps staging"),
                    size: SLOT_BYTES,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }),
                state: Arc::new(AtomicU8::new(SLOT_FREE)),
                frame_number: 0,
            })
            .collect();
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
        self.current = self
            .ring
            .iter()
            .position(|s| s.state.load(Ordering::Acquire) == SLOT_FREE);
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
        let slot = &mut self.ring[i];
        encoder.copy_buffer_to_buffer(&self.resolve, offset, &slot.staging, 0, SLOT_BYTES);
        slot.frame_number = frame_number;
        slot.state.store(SLOT_PENDING, Ordering::Release);
    }

    /// After submit: map this frame's staging buffer; the callback fires once the GPU is done.
    pub(crate) fn after_submit(&mut self) {
        let Some(i) = self.current.take() else { return };
        let slot = &self.ring[i];
        let state = slot.state.clone();
        slot.staging
            .map_async(wgpu::MapMode::Read, .., move |result| {
                state.store(
                    if result.is_ok() {
                        SLOT_READY
                    } else {
                        SLOT_FAILED
                    },
                    Ordering::Release,
                );
            });
    }

    /// Every finished frame's pass duration, oldest first. Never blocks (the caller polls).
    pub(crate) fn take_ready(&mut self) -> Vec<FrameTiming> {
        let mut ready = Vec::new();
        for slot in self.ring.iter_mut() {
            match slot.state.load(Ordering::Acquire) {
                SLOT_READY => {
                    if let Ok(view) = slot.staging.get_mapped_range(..) {
                        let ticks: [u64; 2] = bytemuck::pod_read_unaligned(&view[..16]);
                        drop(view);
                        // A pass whose end precedes its begin (a wrapped or reset counter)
                        // has no meaningful duration; the controller is better off without it.
                        if ticks[1] > ticks[0] {
                            ready.push(FrameTiming {
                                frame_number: slot.frame_number,
                                milliseconds: (ticks[1] - ticks[0]) as f64
                                    * self.nanoseconds_per_tick
                                    / 1e6,
                                source: FrameTimingSource::GpuTimestamps,
                            });
                        }
                    }
                    slot.staging.unmap();
                    slot.state.store(SLOT_FREE, Ordering::Release);
                }
                SLOT_FAILED => slot.state.store(SLOT_FREE, Ordering::Release),
                _ => {}
            }
        }
        ready.sort_by_key(|t| t.frame_number);
        ready
    }
}
