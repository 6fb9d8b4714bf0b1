//! A ring of mappable staging buffers for results the CPU reads a frame or two late without
//! ever blocking the frame path: the raycast pass's timestamps (gpu_timing.rs) and its
//! per-page visibility (raycast.rs).
//!
//! Per frame: [`ReadbackRing::free_slot`] picks a slot (none free: the reader fell behind and
//! this frame's result is dropped), [`ReadbackRing::encode_copy`] copies the result into it,
//! [`ReadbackRing::map_after_submit`] maps it once the submission is queued, and the map
//! callback marks it ready when the GPU is done. [`ReadbackRing::drain`], called by a reader
//! that polls, hands over every ready slot and frees it.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;

const SLOT_FREE: u8 = 0;
const SLOT_PENDING: u8 = 1;
const SLOT_READY: u8 = 2;
const SLOT_FAILED: u8 = 3;

struct Slot {
    buffer: wgpu::Buffer,
    state: Arc<AtomicU8>,
    frame_number: u64,
}

pub(crate) struct ReadbackRing {
    slots: Vec<Slot>,
}

impl ReadbackRing {
    /// `count` staging buffers of `size` bytes each.
    pub(crate) fn new(device: &wgpu::Device, label: &str, count: usize, size: u64) -> Self {
        let slots = (0..count)
            .map(|_| Slot {
                buffer: device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                }),
                state: Arc::new(AtomicU8::new(SLOT_FREE)),
                frame_number: 0,
            })
            .collect();
        ReadbackRing { slots }
    }

    /// A slot no frame is using, or None when every slot still waits for its reader.
    pub(crate) fn free_slot(&self) -> Option<usize> {
        self.slots
            .iter()
            .position(|s| s.state.load(Ordering::Acquire) == SLOT_FREE)
    }

    /// Copies `size` bytes of `source` from `offset` into slot `slot` and tags it with
    /// `frame_number`; the slot is pending until mapped.
    pub(crate) fn encode_copy(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        slot: usize,
        source: &wgpu::Buffer,
        offset: u64,
        size: u64,
        frame_number: u64,
    ) {
        let slot = &mut self.slots[slot];
        encoder.copy_buffer_to_buffer(source, offset, &slot.buffer, 0, size);
        slot.frame_number = frame_number;
        slot.state.store(SLOT_PENDING, Ordering::Release);
    }

    /// After submit: maps slot `slot`; the callback marks it ready once the GPU is done.
    pub(crate) fn map_after_submit(&self, slot: usize) {
        let slot = &self.slots[slot];
        let state = slot.state.clone();
        slot.buffer
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

    /// Calls `read(frame_number, bytes)` for every ready slot, in slot order, then frees it;
    /// failed slots are freed unread. Never blocks (the caller polls the device first).
    pub(crate) fn drain(&mut self, mut read: impl FnMut(u64, &[u8])) {
        for slot in self.slots.iter_mut() {
            match slot.state.load(Ordering::Acquire) {
                SLOT_READY => {
                    if let Ok(view) = slot.buffer.get_mapped_range(..) {
                        read(slot.frame_number, &view);
                        drop(view);
                    }
                    slot.buffer.unmap();
                    slot.state.store(SLOT_FREE, Ordering::Release);
                }
                SLOT_FAILED => slot.state.store(SLOT_FREE, Ordering::Release),
                _ => {}
            }
        }
    }
}
