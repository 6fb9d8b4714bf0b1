//! The label layer: copy-on-write label bricks over a read-only base, and edits as brick images.

use std::sync::Arc;

use rustc_hash::FxHashMap;
use strata_types::VolumeGeometry;

use crate::grid::{BrickKey, LabelGrid, LABEL_BRICK, LABEL_BRICK_VOXELS};
use crate::{Label, SegmentError, SegmentTable};

/// The labels a layer starts from, read a brick at a time (never edited in place).
pub trait LabelBase: Send + Sync {
    /// Fills `out` (`LABEL_BRICK_VOXELS`, i fastest) with the brick's labels; voxels outside
    /// the grid are 0.
    fn read_brick(
        &self,
        grid: &LabelGrid,
        key: BrickKey,
        out: &mut [Label],
    ) -> Result<(), SegmentError>;

    /// Whether the brick is all background (lets tools and exports skip it without reading).
    fn brick_is_empty(&self, _key: BrickKey) -> bool {
        false
    }
}

/// No labels: a new, empty segmentation.
pub struct EmptyBase;

impl LabelBase for EmptyBase {
    fn read_brick(
        &self,
        _grid: &LabelGrid,
        _key: BrickKey,
        out: &mut [Label],
    ) -> Result<(), SegmentError> {
        out.fill(0);
        Ok(())
    }

    fn brick_is_empty(&self, _key: BrickKey) -> bool {
        true
    }
}

/// Labels held whole in memory (i fastest), e.g. a label file small enough to load, or a test's.
pub struct DenseLabels {
    pub dims: [u32; 3],
    pub labels: Vec<Label>,
}

impl LabelBase for DenseLabels {
    fn read_brick(
        &self,
        _grid: &LabelGrid,
        key: BrickKey,
        out: &mut [Label],
    ) -> Result<(), SegmentError> {
        copy_brick_from_dense(self.dims, &self.labels, key, out);
        Ok(())
    }
}

/// Copies one brick out of a dense i-fastest array (outside the array: 0).
pub fn copy_brick_from_dense(dims: [u32; 3], labels: &[Label], key: BrickKey, out: &mut [Label]) {
    let b = LABEL_BRICK as usize;
    let origin = key.0.map(|v| (v * LABEL_BRICK) as usize);
    let [nx, ny, nz] = dims.map(|d| d as usize);
    out.fill(0);
    for lk in 0..b {
        let z = origin[2] + lk;
        if z >= nz {
            break;
        }
        for lj in 0..b {
            let y = origin[1] + lj;
            if y >= ny {
                break;
            }
            let row = origin[0] + nx * (y + ny * z);
            let n = b.min(nx.saturating_sub(origin[0]));
            let dst = b * (lj + b * lk);
            out[dst..dst + n].copy_from_slice(&labels[row..row + n]);
        }
    }
}

/// The all-background brick image, allocated once and shared.
pub fn background_brick() -> Arc<[Label]> {
    static BACKGROUND: std::sync::OnceLock<Arc<[Label]>> = std::sync::OnceLock::new();
    BACKGROUND
        .get_or_init(|| vec![0; LABEL_BRICK_VOXELS].into())
        .clone()
}

/// One brick an edit changed: its whole image before and after (shared, not copied, with the
/// layer and the history).
#[derive(Clone, Debug)]
pub struct BrickChange {
    pub key: BrickKey,
    pub before: Arc<[Label]>,
    pub after: Arc<[Label]>,
}

/// One completed stroke or operation: what undo reverts, redo re-applies and the journal records.
#[derive(Clone, Debug)]
pub struct Edit {
    /// What the user did, for the history list ("Brush", "Grow from seed", ...).
    pub name: String,
    pub changes: Vec<BrickChange>,
    /// The segment table before and after, when the edit changed it (removing a segment: the
    /// undo brings back its name and colour with its voxels).
    pub table: Option<TableChange>,
}

/// A segment table change carried by an [`Edit`].
#[derive(Clone, Debug, PartialEq)]
pub struct TableChange {
    pub before: SegmentTable,
    pub after: SegmentTable,
}

impl TableChange {
    /// The change undone.
    pub fn reversed(&self) -> TableChange {
        TableChange {
            before: self.after.clone(),
            after: self.before.clone(),
        }
    }
}

/// Read access to a whole label grid, as exports and statistics need it.
pub trait LabelRead {
    fn geometry(&self) -> &VolumeGeometry;
    fn segments(&self) -> &SegmentTable;
    /// Fills `out` (dims\[0\]·dims\[1\] labels, i fastest) with slice `k`.
    fn read_slice_k(&self, k: u32, out: &mut [Label]) -> Result<(), SegmentError>;
}

/// An editable label layer. A clone is cheap (bricks are shared) and independent: a tool run in
/// the background works on a clone while the original stays readable.
#[derive(Clone)]
pub struct LabelLayer {
    grid: LabelGrid,
    segments: SegmentTable,
    base: Arc<dyn LabelBase>,
    /// Bricks that differ from the base (their current image).
    edited: FxHashMap<BrickKey, Arc<[Label]>>,
}

impl LabelLayer {
    /// An empty segmentation on a volume's grid.
    pub fn new_empty(geometry: VolumeGeometry) -> Result<Self, SegmentError> {
        Self::with_base(geometry, Arc::new(EmptyBase), SegmentTable::new())
    }

    pub fn with_base(
        geometry: VolumeGeometry,
        base: Arc<dyn LabelBase>,
        segments: SegmentTable,
    ) -> Result<Self, SegmentError> {
        Ok(LabelLayer {
            grid: LabelGrid::new(geometry)?,
            segments,
            base,
            edited: FxHashMap::default(),
        })
    }

    pub fn grid(&self) -> &LabelGrid {
        &self.grid
    }

    pub fn segments(&self) -> &SegmentTable {
        &self.segments
    }

    pub fn segments_mut(&mut self) -> &mut SegmentTable {
        &mut self.segments
    }

    /// The bricks that differ from the base, in no particular order.
    pub fn edited_bricks(&self) -> impl Iterator<Item = (BrickKey, &Arc<[Label]>)> {
        self.edited.iter().map(|(k, v)| (*k, v))
    }

    pub fn edited_brick_count(&self) -> usize {
        self.edited.len()
    }

    /// The current image of a brick (edited, or read from the base). A brick the base knows to
    /// be background is one shared all-zero image: the first stroke into fresh space keeps no
    /// "before" image of its own in the history.
    pub fn brick(&self, key: BrickKey) -> Result<Arc<[Label]>, SegmentError> {
        if let Some(b) = self.edited.get(&key) {
            return Ok(b.clone());
        }
        if self.base.brick_is_empty(key) {
            return Ok(background_brick());
        }
        let mut out = vec![0; LABEL_BRICK_VOXELS];
        self.base.read_brick(&self.grid, key, &mut out)?;
        Ok(out.into())
    }

    /// Whether a brick is known to be all background without reading it.
    pub fn brick_is_empty(&self, key: BrickKey) -> bool {
        !self.edited.contains_key(&key) && self.base.brick_is_empty(key)
    }

    /// The label of one voxel (outside the grid: an error).
    pub fn get(&self, voxel: [u32; 3]) -> Result<Label, SegmentError> {
        self.check(voxel)?;
        let (key, at) = self.grid.brick_of(voxel);
        if let Some(b) = self.edited.get(&key) {
            return Ok(b[at]);
        }
        if self.base.brick_is_empty(key) {
            return Ok(0);
        }
        Ok(self.brick(key)?[at])
    }

    fn check(&self, voxel: [u32; 3]) -> Result<(), SegmentError> {
        let v = voxel.map(i64::from);
        if self.grid.contains(v) {
            Ok(())
        } else {
            Err(SegmentError::OutOfBounds {
                voxel: v,
                dims: self.grid.dims(),
            })
        }
    }

    /// Runs one operation: `f` reads and writes voxels through an [`EditWriter`]; the bricks it
    /// changed become the layer's and are returned as one [`Edit`] (`None` if nothing changed).
    /// On an error from `f` the layer is left as it was.
    pub fn edit<F>(&mut self, name: &str, f: F) -> Result<Option<Edit>, SegmentError>
    where
        F: FnOnce(&mut EditWriter<'_>) -> Result<(), SegmentError>,
    {
        let mut writer = EditWriter {
            layer: self,
            touched: FxHashMap::default(),
        };
        f(&mut writer)?;
        let touched = std::mem::take(&mut writer.touched);
        let mut changes = Vec::new();
        for (key, (before, after)) in touched {
            if before[..] == after[..] {
                continue;
            }
            let after: Arc<[Label]> = after.into();
            changes.push(BrickChange { key, before, after });
        }
        if changes.is_empty() {
            return Ok(None);
        }
        changes.sort_by_key(|c| c.key);
        for c in &changes {
            self.edited.insert(c.key, c.after.clone());
        }
        Ok(Some(Edit {
            name: name.to_owned(),
            changes,
            table: None,
        }))
    }

    /// Removes segment `value`: its voxels become background and its entry leaves the table,
    /// as one edit, so the undo brings back the voxels, the name and the colour. Only the
    /// bricks that hold the value are copied.
    pub fn remove_segment(&mut self, value: Label) -> Result<Edit, SegmentError> {
        let [bx, by, bz] = self.grid.bricks();
        let mut holding = Vec::new();
        for k in 0..bz {
            for j in 0..by {
                for i in 0..bx {
                    let key = BrickKey([i, j, k]);
                    if !self.brick_is_empty(key) && self.brick(key)?.contains(&value) {
                        holding.push(key);
                    }
                }
            }
        }
        let before = self.segments.clone();
        let voxels = self.edit("Remove segment", |w| {
            for key in holding {
                for v in w.brick_mut(key)?.iter_mut() {
                    if *v == value {
                        *v = 0;
                    }
                }
            }
            Ok(())
        })?;
        self.segments.remove(value);
        // An edit even when no voxel held the value: the entry's removal is a step of its own.
        let mut edit = voxels.unwrap_or_else(|| Edit {
            name: "Remove segment".into(),
            changes: Vec::new(),
            table: None,
        });
        edit.table = Some(TableChange {
            before,
            after: self.segments.clone(),
        });
        Ok(edit)
    }

    /// Puts every brick of `edit` back as it was before (undo).
    pub fn revert(&mut self, edit: &Edit) {
        for c in &edit.changes {
            self.edited.insert(c.key, c.before.clone());
        }
        if let Some(table) = &edit.table {
            self.segments = table.before.clone();
        }
    }

    /// Applies `edit` again (redo, or replaying the journal).
    pub fn apply(&mut self, edit: &Edit) {
        for c in &edit.changes {
            self.edited.insert(c.key, c.after.clone());
        }
        if let Some(table) = &edit.table {
            self.segments = table.after.clone();
        }
    }
}

impl LabelRead for LabelLayer {
    fn geometry(&self) -> &VolumeGeometry {
        self.grid.geometry()
    }

    fn segments(&self) -> &SegmentTable {
        &self.segments
    }

    fn read_slice_k(&self, k: u32, out: &mut [Label]) -> Result<(), SegmentError> {
        let [nx, ny, nz] = self.grid.dims();
        let plane = nx as usize * ny as usize;
        if k >= nz || out.len() != plane {
            return Err(SegmentError::OutOfBounds {
                voxel: [0, 0, i64::from(k)],
                dims: self.grid.dims(),
            });
        }
        let b = LABEL_BRICK as usize;
        let bk = k / LABEL_BRICK;
        let lk = (k % LABEL_BRICK) as usize;
        let [bx, by, _] = self.grid.bricks();
        for bj in 0..by {
            for bi in 0..bx {
                let key = BrickKey([bi, bj, bk]);
                let (i0, j0) = ((bi * LABEL_BRICK) as usize, (bj * LABEL_BRICK) as usize);
                let w = b.min(nx as usize - i0);
                let h = b.min(ny as usize - j0);
                if self.brick_is_empty(key) {
                    for lj in 0..h {
                        let row = i0 + nx as usize * (j0 + lj);
                        out[row..row + w].fill(0);
                    }
                    continue;
                }
                let brick = self.brick(key)?;
                for lj in 0..h {
                    let row = i0 + nx as usize * (j0 + lj);
                    let src = b * (lj + b * lk);
                    out[row..row + w].copy_from_slice(&brick[src..src + w]);
                }
            }
        }
        Ok(())
    }
}

/// Reads and writes voxels for one [`LabelLayer::edit`]: a brick is copied the first time the
/// operation touches it, so an operation costs memory in proportion to the bricks it reaches.
pub struct EditWriter<'a> {
    layer: &'a LabelLayer,
    /// Per touched brick: its image before the operation and the working copy.
    touched: FxHashMap<BrickKey, (Arc<[Label]>, Vec<Label>)>,
}

impl EditWriter<'_> {
    pub fn grid(&self) -> &LabelGrid {
        &self.layer.grid
    }

    pub fn segments(&self) -> &SegmentTable {
        &self.layer.segments
    }

    /// The label of a voxel as the operation sees it (its own writes included).
    pub fn get(&self, voxel: [u32; 3]) -> Result<Label, SegmentError> {
        self.layer.check(voxel)?;
        let (key, at) = self.layer.grid.brick_of(voxel);
        match self.touched.get(&key) {
            Some((_, work)) => Ok(work[at]),
            None => self.layer.get(voxel),
        }
    }

    /// The working copy of a brick (copied on first touch) for tools that write whole bricks.
    pub fn brick_mut(&mut self, key: BrickKey) -> Result<&mut [Label], SegmentError> {
        if !self.touched.contains_key(&key) {
            let before = self.layer.brick(key)?;
            let work = before.to_vec();
            self.touched.insert(key, (before, work));
        }
        match self.touched.get_mut(&key) {
            Some((_, work)) => Ok(work),
            None => Err(SegmentError::Grid(format!(
                "brick {:?} vanished during an edit",
                key.0
            ))),
        }
    }

    /// Sets a voxel, ignoring locks (for operations that decided already, e.g. undoable imports).
    pub fn set(&mut self, voxel: [u32; 3], label: Label) -> Result<(), SegmentError> {
        self.layer.check(voxel)?;
        let (key, at) = self.layer.grid.brick_of(voxel);
        self.brick_mut(key)?[at] = label;
        Ok(())
    }

    /// Paints a voxel unless it holds a locked segment; returns whether it was written.
    pub fn paint(&mut self, voxel: [u32; 3], label: Label) -> Result<bool, SegmentError> {
        let old = self.get(voxel)?;
        if old == label {
            return Ok(false);
        }
        if self.layer.segments.is_locked(old) {
            return Ok(false);
        }
        self.set(voxel, label)?;
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer(dims: [u32; 3]) -> LabelLayer {
        LabelLayer::new_empty(VolumeGeometry::axis_aligned(dims, [1.0; 3])).unwrap()
    }

    #[test]
    fn an_edit_copies_only_the_bricks_it_touches_and_undo_restores_them() {
        let mut l = layer([100, 70, 40]);
        let edit = l
            .edit("two voxels", |w| {
                w.set([1, 2, 3], 5)?;
                w.set([99, 69, 39], 7)?;
                Ok(())
            })
            .unwrap()
            .unwrap();
        assert_eq!(edit.changes.len(), 2);
        assert_eq!(l.edited_brick_count(), 2);
        assert_eq!(l.get([1, 2, 3]).unwrap(), 5);
        assert_eq!(l.get([99, 69, 39]).unwrap(), 7);
        assert_eq!(l.get([2, 2, 3]).unwrap(), 0);
        l.revert(&edit);
        assert_eq!(l.get([1, 2, 3]).unwrap(), 0);
        l.apply(&edit);
        assert_eq!(l.get([99, 69, 39]).unwrap(), 7);
        assert!(l.get([100, 0, 0]).is_err());
    }

    #[test]
    fn removing_a_segment_is_one_edit_whose_undo_restores_voxels_name_and_colour() {
        let mut l = layer([70, 40, 40]);
        let liver = l.segments_mut().add("liver").unwrap();
        let kidney = l.segments_mut().add("kidney").unwrap();
        l.segments_mut().get_mut(liver).unwrap().rgb = [1, 2, 3];
        l.edit("paint", |w| {
            w.set([3, 3, 3], liver)?;
            w.set([68, 39, 39], liver)?;
            w.set([4, 3, 3], kidney)
        })
        .unwrap();
        let table_before = l.segments().clone();
        let edit = l.remove_segment(liver).unwrap();
        assert_eq!(edit.changes.len(), 2, "only the two bricks that held it");
        assert_eq!(l.get([3, 3, 3]).unwrap(), 0);
        assert_eq!(l.get([68, 39, 39]).unwrap(), 0);
        assert_eq!(l.get([4, 3, 3]).unwrap(), kidney);
        assert!(l.segments().get(liver).is_none());
        l.revert(&edit);
        assert_eq!(l.segments(), &table_before, "name and colour back");
        assert_eq!(l.get([3, 3, 3]).unwrap(), liver);
        assert_eq!(l.get([68, 39, 39]).unwrap(), liver);
        l.apply(&edit);
        assert!(l.segments().get(liver).is_none());
        assert_eq!(l.get([3, 3, 3]).unwrap(), 0);
        // A segment no voxel holds still leaves (and comes back) as a step of its own.
        let empty = l.segments_mut().add("empty").unwrap();
        let step = l.remove_segment(empty).unwrap();
        assert!(step.changes.is_empty());
        assert!(l.segments().get(empty).is_none());
        l.revert(&step);
        assert_eq!(
            l.segments().get(empty).map(|s| s.name.as_str()),
            Some("empty")
        );
    }

    #[test]
    fn painting_leaves_locked_segments_alone_and_a_no_op_is_no_edit() {
        let mut l = layer([40, 40, 40]);
        let a = l.segments_mut().add("a").unwrap();
        let b = l.segments_mut().add("b").unwrap();
        l.edit("a", |w| w.set([3, 3, 3], a)).unwrap();
        l.segments_mut().get_mut(a).unwrap().locked = true;
        let e = l
            .edit("b", |w| {
                assert!(!w.paint([3, 3, 3], b)?);
                assert!(w.paint([4, 3, 3], b)?);
                Ok(())
            })
            .unwrap();
        assert!(e.is_some());
        assert_eq!(l.get([3, 3, 3]).unwrap(), a);
        assert_eq!(l.get([4, 3, 3]).unwrap(), b);
        assert!(l
            .edit("nothing", |w| w.set([4, 3, 3], b))
            .unwrap()
            .is_none());
    }

    #[test]
    fn slices_read_back_what_was_written_across_bricks() {
        let dims = [50, 37, 9];
        let mut l = layer(dims);
        l.edit("diagonal", |w| {
            for i in 0..37 {
                w.set([i, i, 4], (i + 1) as Label)?;
            }
            Ok(())
        })
        .unwrap();
        let mut out = vec![9; 50 * 37];
        l.read_slice_k(4, &mut out).unwrap();
        for j in 0..37usize {
            for i in 0..50usize {
                let want = if i == j { (i + 1) as Label } else { 0 };
                assert_eq!(out[i + 50 * j], want, "voxel {i},{j}");
            }
        }
        l.read_slice_k(3, &mut out).unwrap();
        assert!(out.iter().all(|&v| v == 0));
    }

    #[test]
    fn a_dense_base_is_read_brick_by_brick() {
        let dims = [35, 33, 34];
        let labels: Vec<Label> = (0..35 * 33 * 34).map(|n| (n % 7) as Label).collect();
        let geometry = VolumeGeometry::axis_aligned(dims, [0.5; 3]);
        let base = Arc::new(DenseLabels {
            dims,
            labels: labels.clone(),
        });
        let l = LabelLayer::with_base(geometry, base, SegmentTable::new()).unwrap();
        for &(i, j, k) in &[(0u32, 0u32, 0u32), (34, 32, 33), (32, 1, 33), (5, 32, 7)] {
            let n = i as usize + 35 * (j as usize + 33 * k as usize);
            assert_eq!(l.get([i, j, k]).unwrap(), labels[n]);
        }
    }
}
