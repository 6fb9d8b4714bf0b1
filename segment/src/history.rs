//! Undo and redo of [`Edit`]s with a memory bound.
//!
//! Each edit holds the before and after image of every brick it changed; the history counts
//! both (64 KiB each; a before image that is the shared background brick is free) against its
//! bound and drops the oldest edits first when a new one would
//! exceed it. A new edit clears the redo list, as every editor does. The images are shared
//! (`Arc`) with the layer and neighbouring edits, so the count is an upper bound of what the
//! history alone keeps alive.

use std::collections::VecDeque;
use std::sync::Arc;

use rustc_hash::FxHashMap;

use crate::grid::{BrickKey, LABEL_BRICK_VOXELS};
use crate::layer::{BrickChange, Edit, LabelLayer, TableChange};
use crate::Label;

/// Bytes an edit's brick images take (before and after).
pub fn edit_bytes(edit: &Edit) -> usize {
    let background = crate::layer::background_brick();
    let images = edit
        .changes
        .iter()
        .map(|c| 1 + usize::from(!Arc::ptr_eq(&c.before, &background)))
        .sum::<usize>();
    images * LABEL_BRICK_VOXELS * size_of::<Label>()
}

/// Successive edits (in the order they were applied) as one: each brick's image before the first
/// and after the last (the segment table's too); bricks that ended as they began are left out
/// (`None` when all did and the table did not change). This
/// is how a stroke shown as it is drawn, one edit per pointer event, becomes one undo step.
pub fn merge_edits(name: &str, edits: impl IntoIterator<Item = Edit>) -> Option<Edit> {
    let mut merged: FxHashMap<BrickKey, BrickChange> = FxHashMap::default();
    let mut table: Option<TableChange> = None;
    for edit in edits {
        if let Some(change) = edit.table {
            table = Some(match table {
                Some(first) => TableChange {
                    before: first.before,
                    after: change.after,
                },
                None => change,
            });
        }
        for change in edit.changes {
            merged
                .entry(change.key)
                .and_modify(|m| m.after = change.after.clone())
                .or_insert(change);
        }
    }
    let mut changes: Vec<BrickChange> = merged
        .into_values()
        .filter(|c| c.before[..] != c.after[..])
        .collect();
    if changes.is_empty() && table.is_none() {
        return None;
    }
    changes.sort_by_key(|c| c.key);
    Some(Edit {
        name: name.to_owned(),
        changes,
        table,
    })
}

/// The undo and redo lists of one layer.
#[derive(Debug)]
pub struct History {
    undo: VecDeque<Edit>,
    redo: Vec<Edit>,
    max_bytes: usize,
    bytes: usize,
}

impl History {
    /// A history that keeps at most `max_bytes` of brick images.
    pub fn new(max_bytes: usize) -> Self {
        History {
            undo: VecDeque::new(),
            redo: Vec::new(),
            max_bytes,
            bytes: 0,
        }
    }

    /// Records an edit already applied to the layer. Clears redo; drops the oldest edits while
    /// over the bound. Returns false when the edit alone exceeds the bound and so cannot be
    /// undone (the history is then empty: older edits cannot be undone past it either).
    pub fn push(&mut self, edit: Edit) -> bool {
        for e in self.redo.drain(..) {
            self.bytes -= edit_bytes(&e);
        }
        let size = edit_bytes(&edit);
        if size > self.max_bytes {
            self.undo.clear();
            self.bytes = 0;
            return false;
        }
        while self.bytes + size > self.max_bytes {
            match self.undo.pop_front() {
                Some(old) => self.bytes -= edit_bytes(&old),
                None => break,
            }
        }
        self.bytes += size;
        self.undo.push_back(edit);
        true
    }

    /// Reverts the newest edit on `layer`; returns its name (`None` when there is none).
    pub fn undo(&mut self, layer: &mut LabelLayer) -> Option<&str> {
        let edit = self.undo.pop_back()?;
        layer.revert(&edit);
        self.redo.push(edit);
        self.redo.last().map(|e| e.name.as_str())
    }

    /// Re-applies the newest undone edit; returns its name.
    pub fn redo(&mut self, layer: &mut LabelLayer) -> Option<&str> {
        let edit = self.redo.pop()?;
        layer.apply(&edit);
        self.undo.push_back(edit);
        self.undo.back().map(|e| e.name.as_str())
    }

    /// Drops every undone edit (nothing can be redone): for a caller whose own history can no
    /// longer reach them, as a new step of another kind (the page's view edits) clears its redo.
    pub fn clear_redo(&mut self) {
        for e in self.redo.drain(..) {
            self.bytes -= edit_bytes(&e);
        }
    }

    pub fn can_undo(&self) -> bool {
        !self.undo.is_empty()
    }

    pub fn can_redo(&self) -> bool {
        !self.redo.is_empty()
    }

    /// Names of the undoable edits, oldest first (for a history list).
    pub fn undo_names(&self) -> impl Iterator<Item = &str> {
        self.undo.iter().map(|e| e.name.as_str())
    }

    /// Bytes of brick images held (undo and redo).
    pub fn bytes(&self) -> usize {
        self.bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::{BrickKey, LABEL_BRICK};
    use strata_types::VolumeGeometry;

    fn layer() -> LabelLayer {
        let mut l =
            LabelLayer::new_empty(VolumeGeometry::axis_aligned([70, 70, 40], [1.0; 3])).unwrap();
        l.segments_mut().add("a").unwrap();
        l.segments_mut().add("b").unwrap();
        l
    }

    /// Every brick image of the layer, for exact comparison.
    fn images(l: &LabelLayer) -> Vec<(BrickKey, Vec<Label>)> {
        let [bx, by, bz] = l.grid().bricks();
        let mut out = Vec::new();
        for k in 0..bz {
            for j in 0..by {
                for i in 0..bx {
                    let key = BrickKey([i, j, k]);
                    out.push((key, l.brick(key).unwrap().to_vec()));
                }
            }
        }
        out
    }

    fn paint(l: &mut LabelLayer, from: u32, label: Label) -> Edit {
        l.edit("paint", |w| {
            for n in from..from + 40 {
                w.set([n, n / 2, n % 40], label)?;
            }
            Ok(())
        })
        .unwrap()
        .unwrap()
    }

    #[test]
    fn clear_redo_drops_the_undone_edits_and_their_bytes_and_keeps_the_undo_list() {
        let mut l = layer();
        let mut h = History::new(usize::MAX);
        h.push(paint(&mut l, 0, 1));
        let one = h.bytes();
        h.push(paint(&mut l, 10, 2));
        let painted = images(&l);
        h.undo(&mut l);
        assert!(h.can_redo());
        h.clear_redo();
        assert!(!h.can_redo() && h.can_undo());
        assert_eq!(h.bytes(), one);
        assert!(h.redo(&mut l).is_none());
        assert_ne!(images(&l), painted, "the cleared redo must not come back");
        assert_eq!(h.undo(&mut l), Some("paint"));
        assert!(!h.can_undo());
    }

    #[test]
    fn undo_and_redo_restore_exact_bricks_and_a_new_edit_clears_redo() {
        let mut l = layer();
        let mut h = History::new(usize::MAX);
        let s0 = images(&l);
        let e = paint(&mut l, 0, 1);
        assert!(h.push(e));
        let s1 = images(&l);
        let e = paint(&mut l, 10, 2);
        h.push(e);
        let s2 = images(&l);
        assert_ne!(s1, s2);
        assert_eq!(h.undo(&mut l), Some("paint"));
        assert_eq!(images(&l), s1);
        h.undo(&mut l);
        assert_eq!(images(&l), s0);
        assert!(h.undo(&mut l).is_none());
        h.redo(&mut l);
        assert_eq!(images(&l), s1);
        h.redo(&mut l);
        assert_eq!(images(&l), s2);
        assert!(!h.can_redo());
        h.undo(&mut l);
        let e = paint(&mut l, 20, 1);
        h.push(e);
        assert!(!h.can_redo(), "a new edit clears redo");
        assert_eq!(h.undo_names().count(), 2);
    }

    #[test]
    fn merged_edits_undo_to_the_first_image_and_redo_to_the_last() {
        let mut l = layer();
        let s0 = images(&l);
        let edits = vec![
            paint(&mut l, 0, 1),
            paint(&mut l, 5, 2),
            paint(&mut l, 30, 1),
        ];
        let s3 = images(&l);
        let merged = merge_edits("stroke", edits).unwrap();
        let mut h = History::new(usize::MAX);
        h.push(merged);
        assert_eq!(h.undo(&mut l), Some("stroke"));
        assert_eq!(images(&l), s0);
        h.redo(&mut l);
        assert_eq!(images(&l), s3);
        // An edit and its inverse merge to nothing.
        let e = paint(&mut l, 2, 2);
        let inverse = Edit {
            name: "inverse".into(),
            table: None,
            changes: e
                .changes
                .iter()
                .map(|c| BrickChange {
                    key: c.key,
                    before: c.after.clone(),
                    after: c.before.clone(),
                })
                .collect(),
        };
        assert!(merge_edits("none", [e, inverse]).is_none());
    }

    #[test]
    fn the_memory_bound_drops_the_oldest_edits_first() {
        let mut l = layer();
        let image_bytes = (LABEL_BRICK as usize).pow(3) * 2;
        let e1 = paint(&mut l, 0, 1);
        // Painting fresh space: the "before" images are the shared background brick, not kept
        // per edit, so only the "after" images count.
        assert_eq!(edit_bytes(&e1), e1.changes.len() * image_bytes);
        let e2 = paint(&mut l, 1, 2);
        let (b1, b2) = (edit_bytes(&e1), edit_bytes(&e2));
        let mut h = History::new(b1 + b2 - 1);
        h.push(e1);
        h.push(e2);
        assert_eq!(h.undo_names().count(), 1, "the first edit was dropped");
        assert_eq!(h.bytes(), b2);
        let s1 = images(&l);
        h.undo(&mut l);
        assert_ne!(images(&l), s1);
        assert!(h.undo(&mut l).is_none());
        let mut tiny = History::new(10);
        assert!(!tiny.push(paint(&mut l, 3, 1)));
        assert!(!tiny.can_undo());
    }
}
