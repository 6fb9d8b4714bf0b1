//! Whole-segment operations: islands (6-connected components), margins in mm, and logical
//! operations between segments. Each is one edit; a locked segment is refused.

use std::collections::VecDeque;
use std::sync::Arc;

use rustc_hash::FxHashMap;

use crate::grid::{BrickKey, LABEL_BRICK, LABEL_BRICK_VOXELS};
use crate::layer::{Edit, LabelLayer};
use crate::tools::check_tool_label;
use crate::tools::distance::squared_distance;
use crate::tools::region::{check_box, non_empty_bricks, read_box, segment_box};
use crate::{Label, SegmentError};

/// Largest box (voxels) a margin works in: two arrays per voxel (distance f64 and label).
pub const MARGIN_MAX_BOX_VOXELS: u64 = 1 << 25;

/// A centre this close beyond the margin (mm) still counts (rounding, as the brush's rim).
const MARGIN_TOLERANCE_MM: f64 = 1e-9;

/// Which islands go.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Islands {
    /// Keep only the largest (ties: the first found, scanning bricks k, j, i slowest first).
    KeepLargest,
    /// Remove the islands with fewer than this many voxels.
    RemoveSmallerThan(u64),
}

/// The 6-connected components of a segment, per brick (component id per voxel, 0 = none).
struct Components {
    bricks: FxHashMap<BrickKey, Vec<u32>>,
    sizes: Vec<u64>,
}

fn components(layer: &LabelLayer, label: Label) -> Result<Components, SegmentError> {
    let grid = layer.grid();
    let dims = grid.dims();
    let b = LABEL_BRICK as usize;
    // Only bricks that hold the segment take part.
    let mut labels: FxHashMap<BrickKey, Arc<[Label]>> = FxHashMap::default();
    let mut order = Vec::new();
    for key in non_empty_bricks(layer) {
        let brick = layer.brick(key)?;
        if brick.contains(&label) {
            order.push(key);
            labels.insert(key, brick);
        }
    }
    let mut ids: FxHashMap<BrickKey, Vec<u32>> = order
        .iter()
        .map(|&k| (k, vec![0u32; LABEL_BRICK_VOXELS]))
        .collect();
    let mut sizes = vec![0u64]; // id 0 is "no component"
    let mut queue: VecDeque<[u32; 3]> = VecDeque::new();
    for &key in &order {
        let origin = grid.brick_origin(key);
        for at in 0..LABEL_BRICK_VOXELS {
            if labels[&key][at] != label || ids[&key][at] != 0 {
                continue;
            }
            let id = u32::try_from(sizes.len()).map_err(|_| SegmentError::TooLarge {
                what: "the islands of a segment",
                voxels: sizes.len() as u64,
                limit: u64::from(u32::MAX),
            })?;
            sizes.push(0);
            let start = [at % b, (at / b) % b, at / (b * b)];
            let start = [0, 1, 2].map(|a| origin[a] + start[a] as u32);
            if let Some(v) = ids.get_mut(&key) {
                v[at] = id;
            }
            queue.push_back(start);
            while let Some(voxel) = queue.pop_front() {
                sizes[id as usize] += 1;
                for axis in 0..3 {
                    for step in [-1i64, 1] {
                        let n = i64::from(voxel[axis]) + step;
                        if n < 0 || n >= i64::from(dims[axis]) {
                            continue;
                        }
                        let mut next = voxel;
                        next[axis] = n as u32;
                        let (nkey, nat) = grid.brick_of(next);
                        let Some(nl) = labels.get(&nkey) else {
                            continue;
                        };
                        if nl[nat] != label {
                            continue;
                        }
                        if let Some(v) = ids.get_mut(&nkey) {
                            if v[nat] == 0 {
                                v[nat] = id;
                                queue.push_back(next);
                            }
                        }
                    }
                }
            }
        }
    }
    Ok(Components { bricks: ids, sizes })
}

/// Removes islands of `label` (to background), as one edit. Returns the edit and the number of
/// islands removed.
pub fn remove_islands(
    layer: &mut LabelLayer,
    label: Label,
    which: Islands,
) -> Result<(Option<Edit>, usize), SegmentError> {
    check_tool_label(layer, label)?;
    let comps = components(layer, label)?;
    let mut remove = vec![false; comps.sizes.len()];
    match which {
        Islands::KeepLargest => {
            let mut largest = 0usize;
            for (id, &size) in comps.sizes.iter().enumerate().skip(1) {
                if largest == 0 || size > comps.sizes[largest] {
                    largest = id;
                }
            }
            for (id, r) in remove.iter_mut().enumerate().skip(1) {
                *r = id != largest;
            }
        }
        Islands::RemoveSmallerThan(min_voxels) => {
            for (id, r) in remove.iter_mut().enumerate().skip(1) {
                *r = comps.sizes[id] < min_voxels;
            }
        }
    }
    let removed = remove.iter().filter(|&&r| r).count();
    let edit = layer.edit("Islands", |w| {
        for (&key, ids) in &comps.bricks {
            if !ids.iter().any(|&id| remove[id as usize]) {
                continue;
            }
            let work = w.brick_mut(key)?;
            for (at, &id) in ids.iter().enumerate() {
                if remove[id as usize] {
                    work[at] = 0;
                }
            }
        }
        Ok(())
    })?;
    Ok((edit, removed))
}

/// Grows (`margin_mm` > 0) or shrinks (< 0) a segment by a Euclidean margin in mm between voxel
/// centres, as one edit. Growing takes background voxels within the margin of the segment
/// (never other segments); shrinking clears the segment's voxels within the margin of a voxel
/// not in it (outside the grid does not count, so a segment touching the edge keeps it).
pub fn margin(
    layer: &mut LabelLayer,
    label: Label,
    margin_mm: f64,
) -> Result<Option<Edit>, SegmentError> {
    check_tool_label(layer, label)?;
    if !margin_mm.is_finite() {
        return Err(SegmentError::BadParameter(format!(
            "a margin must be a number of mm, got {margin_mm}"
        )));
    }
    let Some((seg_lo, seg_hi)) = segment_box(layer, label)? else {
        return Ok(None);
    };
    let grid = layer.grid();
    let dims = grid.dims();
    let spacing = grid.geometry().spacing_mm;
    let m = margin_mm.abs();
    let pad = [0, 1, 2].map(|a| (m / spacing[a]).ceil().min(f64::from(dims[a])) as u32);
    let lo = [0, 1, 2].map(|a| seg_lo[a].saturating_sub(pad[a]));
    let hi = [0, 1, 2].map(|a| (seg_hi[a].saturating_add(pad[a])).min(dims[a] - 1));
    let box_dims = check_box("a margin", lo, hi, MARGIN_MAX_BOX_VOXELS)?;
    let labels = read_box(layer, lo, hi)?;
    let grow = margin_mm > 0.0;
    let feature: Vec<bool> = labels
        .iter()
        .map(|&l| if grow { l == label } else { l != label })
        .collect();
    let d2 = squared_distance(box_dims, spacing, &feature);
    let reach = m + MARGIN_TOLERANCE_MM;
    let name = if grow { "Grow margin" } else { "Shrink margin" };
    layer.edit(name, |w| {
        for (n, (&l, &d)) in labels.iter().zip(&d2).enumerate() {
            let change = if grow {
                l == 0 && d.sqrt() <= reach
            } else {
                l == label && d.sqrt() <= reach
            };
            if !change {
                continue;
            }
            let local = [
                n % box_dims[0],
                (n / box_dims[0]) % box_dims[1],
                n / (box_dims[0] * box_dims[1]),
            ];
            let voxel = [0, 1, 2].map(|a| lo[a] + local[a] as u32);
            w.set(voxel, if grow { label } else { 0 })?;
        }
        Ok(())
    })
}

/// A logical operation between a target segment and an operand.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LogicalOp {
    /// The target also takes the operand's voxels (over background and unlocked segments).
    Union,
    /// The target keeps only its voxels that are also the operand's.
    Intersect,
    /// The target loses its voxels that are also the operand's.
    Subtract,
}

/// The other side of a logical operation. Within one layer segments never overlap, so against
/// a segment of the same layer a union moves its voxels into the target, an intersection empties
/// the target and a subtraction changes nothing; against a segment of another layer on the same
/// grid (an imported label file, a second segmentation) all three are the set operations.
pub enum Operand<'a> {
    Segment(Label),
    Other(&'a LabelLayer, Label),
}

/// Applies `target = target op operand`, as one edit.
pub fn combine(
    layer: &mut LabelLayer,
    target: Label,
    op: LogicalOp,
    operand: Operand<'_>,
) -> Result<Option<Edit>, SegmentError> {
    check_tool_label(layer, target)?;
    let (other, operand_label) = match operand {
        Operand::Segment(l) => {
            if layer.segments().get(l).is_none() {
                return Err(SegmentError::NoSuchSegment(l));
            }
            if op == LogicalOp::Union && layer.segments().is_locked(l) {
                return Err(SegmentError::Locked(l));
            }
            (None, l)
        }
        Operand::Other(other, l) => {
            if l == 0 {
                return Err(SegmentError::NoSuchSegment(0));
            }
            // Same dims on another placement would pair voxels that are not the same place.
            if other.grid() != layer.grid() {
                return Err(SegmentError::Grid(format!(
                    "the operand's grid ({:?} voxels, {:?} mm) is not the target's ({:?}, {:?})",
                    other.grid().dims(),
                    other.grid().geometry().spacing_mm,
                    layer.grid().dims(),
                    layer.grid().geometry().spacing_mm
                )));
            }
            (Some(other), l)
        }
    };
    // Every brick where either side may hold something.
    let mut keys = non_empty_bricks(layer);
    if let Some(other) = other {
        keys.extend(non_empty_bricks(other));
        keys.sort();
        keys.dedup();
    }
    // Per brick: its key, the target layer's image and the operand's.
    type BrickPair = (BrickKey, Arc<[Label]>, Arc<[Label]>);
    let mut work: Vec<BrickPair> = Vec::new();
    for key in keys {
        let mine = layer.brick(key)?;
        let theirs = match other {
            Some(o) => o.brick(key)?,
            None => mine.clone(),
        };
        work.push((key, mine, theirs));
    }
    let segments = layer.segments().clone();
    let name = match op {
        LogicalOp::Union => "Union",
        LogicalOp::Intersect => "Intersect",
        LogicalOp::Subtract => "Subtract",
    };
    layer.edit(name, |w| {
        for (key, mine, theirs) in &work {
            let mut out: Option<Vec<Label>> = None;
            for at in 0..LABEL_BRICK_VOXELS {
                let (m, t) = (mine[at], theirs[at]);
                let in_operand = t == operand_label;
                let new = match op {
                    LogicalOp::Union if in_operand && m != target && !segments.is_locked(m) => {
                        target
                    }
                    LogicalOp::Intersect if m == target && !in_operand => 0,
                    LogicalOp::Subtract if m == target && in_operand => 0,
                    _ => m,
                };
                if new != m {
                    out.get_or_insert_with(|| mine.to_vec())[at] = new;
                }
            }
            if let Some(out) = out {
                w.brick_mut(*key)?.copy_from_slice(&out);
            }
        }
        Ok(())
    })
}
