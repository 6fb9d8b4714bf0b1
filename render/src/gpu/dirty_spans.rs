//! Incremental buffer writes: the ranges where a new array differs from the one last written,
//! so a cut change that touches a few hundred page cells writes those (queue.write_buffer per
//! span) instead of the whole per-page buffers, which grow with the volume (issue 18: the
//! whole-table write was ~6 ms of the frame thread at 1024³).

use std::ops::Range;

/// Differing elements closer than this many equal ones are written as one span: a
/// `write_buffer` call costs more than copying a few hundred bytes along with it.
pub const MERGE_GAP: usize = 64;

/// The index ranges where `new` differs from `old` (same length), ascending; runs of equal
/// elements shorter than [`MERGE_GAP`] between two changes are included in one span.
pub fn changed_spans<T: PartialEq>(old: &[T], new: &[T]) -> Vec<Range<usize>> {
    debug_assert_eq!(old.len(), new.len());
    let mut spans: Vec<Range<usize>> = Vec::new();
    for (i, (a, b)) in old.iter().zip(new).enumerate() {
        if a == b {
            continue;
        }
        match spans.last_mut() {
            Some(last) if i - last.end < MERGE_GAP => last.end = i + 1,
            _ => spans.push(i..i + 1),
        }
    }
    spans
}

/// Writes the elements of `new` that differ from `mirror` (the buffer's contents as last
/// written, same length) and updates the mirror; returns the bytes written.
pub fn write_changed<T: bytemuck::Pod + PartialEq>(
    queue: &wgpu::Queue,
    buffer: &wgpu::Buffer,
    mirror: &mut [T],
    new: &[T],
) -> u64 {
    let size = size_of::<T>();
    let mut bytes = 0;
    for span in changed_spans(mirror, new) {
        let data: &[u8] = bytemuck::cast_slice(&new[span.clone()]);
        queue.write_buffer(buffer, (span.start * size) as u64, data);
        bytes += data.len() as u64;
        mirror[span.clone()].copy_from_slice(&new[span]);
    }
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spans_cover_every_change_and_nothing_far_from_one() {
        let old = vec![0u32; 1000];
        assert!(changed_spans(&old, &old).is_empty());
        let mut new = old.clone();
        for i in [3, 10, 500, 999] {
            new[i] = 1;
        }
        // 3 and 10 are close: one span; 500 and 999 are far from everything.
        assert_eq!(changed_spans(&old, &new), vec![3..11, 500..501, 999..1000]);
        // Applying the spans reproduces `new` exactly.
        let mut applied = old.clone();
        for s in changed_spans(&old, &new) {
            applied[s.clone()].copy_from_slice(&new[s]);
        }
        assert_eq!(applied, new);
    }
}
