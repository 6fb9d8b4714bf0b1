//! Reading a segment's voxels and boxes of labels, brick by brick (for the tools that work on a
//! whole segment: interpolation, islands, margins).

use std::sync::Arc;

use rustc_hash::FxHashMap;

use crate::grid::{BrickKey, LABEL_BRICK};
use crate::layer::LabelLayer;
use crate::{Label, SegmentError};

/// Every brick key of the layer's grid that may hold labels, k slowest.
pub(crate) fn non_empty_bricks(layer: &LabelLayer) -> Vec<BrickKey> {
    let [bx, by, bz] = layer.grid().bricks();
    let mut out = Vec::new();
    for k in 0..bz {
        for j in 0..by {
            for i in 0..bx {
                let key = BrickKey([i, j, k]);
                if !layer.brick_is_empty(key) {
                    out.push(key);
                }
            }
        }
    }
    out
}

/// Calls `f` with every voxel holding `label`.
pub(crate) fn for_each_voxel_of(
    layer: &LabelLayer,
    label: Label,
    mut f: impl FnMut([u32; 3]),
) -> Result<(), SegmentError> {
    let b = LABEL_BRICK as usize;
    for key in non_empty_bricks(layer) {
        let brick = layer.brick(key)?;
        let origin = layer.grid().brick_origin(key);
        for (at, &l) in brick.iter().enumerate() {
            if l == label {
                let local = [at % b, (at / b) % b, at / (b * b)];
                f([0, 1, 2].map(|a| origin[a] + local[a] as u32));
            }
        }
    }
    Ok(())
}

/// An inclusive index box: first and last voxel.
pub(crate) type IndexBox = ([u32; 3], [u32; 3]);

/// The inclusive index box of a segment's voxels, or `None` when it has none.
pub(crate) fn segment_box(
    layer: &LabelLayer,
    label: Label,
) -> Result<Option<IndexBox>, SegmentError> {
    let mut lo = [u32::MAX; 3];
    let mut hi = [0u32; 3];
    let mut any = false;
    for_each_voxel_of(layer, label, |v| {
        any = true;
        for a in 0..3 {
            lo[a] = lo[a].min(v[a]);
            hi[a] = hi[a].max(v[a]);
        }
    })?;
    Ok(any.then_some((lo, hi)))
}

/// Refuses a working box larger than `limit` voxels (the tools allocate per box voxel).
pub(crate) fn check_box(
    what: &'static str,
    lo: [u32; 3],
    hi: [u32; 3],
    limit: u64,
) -> Result<[usize; 3], SegmentError> {
    let dims = [0, 1, 2].map(|a| u64::from(hi[a] - lo[a]) + 1);
    let voxels: u64 = dims.iter().product();
    if voxels > limit {
        return Err(SegmentError::TooLarge {
            what,
            voxels,
            limit,
        });
    }
    Ok(dims.map(|d| d as usize))
}

/// The labels of the inclusive box `lo..=hi` (i fastest), read brick by brick.
pub(crate) fn read_box(
    layer: &LabelLayer,
    lo: [u32; 3],
    hi: [u32; 3],
) -> Result<Vec<Label>, SegmentError> {
    let dims = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
    let mut out = vec![0; dims.iter().product()];
    let mut bricks: FxHashMap<BrickKey, Arc<[Label]>> = FxHashMap::default();
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let voxel = [lo[0] + x as u32, lo[1] + y as u32, lo[2] + z as u32];
                let (key, at) = layer.grid().brick_of(voxel);
                if layer.brick_is_empty(key) {
                    continue;
                }
                if let std::collections::hash_map::Entry::Vacant(e) = bricks.entry(key) {
                    e.insert(layer.brick(key)?);
                }
                out[x + dims[0] * (y + dims[1] * z)] = bricks.get(&key).map_or(0, |b| b[at]);
            }
        }
    }
    Ok(out)
}
