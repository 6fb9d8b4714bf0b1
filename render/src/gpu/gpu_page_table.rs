//! The page table on the GPU (binding 3), the per-entry MIP bounds (binding 9) and the
//! per-entry transition masks with their near-side closures (binding 11), as the raycast
//! shader's page lookups read them; with [`Traversal::Octree`], the cut's octree instead
//! (gpu_octree.rs: node buffer, per-leaf bounds and transition masks), and the flat buffers
//! shrink to stubs.

use crate::error::RenderError;
use crate::gpu::cache::BrickCache;
use crate::gpu::dirty_spans::write_changed;
use crate::gpu::gpu_octree::{EncodedOctree, GpuOctreeIndex, OctreeLeaves, Traversal};
use crate::model::layout::LEVEL_MASK;
use crate::model::octree_cut::{CutLeaf, OctreeCut};
use crate::model::page_table::{PageEntry, PageTable};
use crate::model::smooth_transitions::{
    near_side_closure, transition_masks, transition_node_fraction,
};
use crate::model::sparse_page_table::{IndexTable, PageLookup, SparsePageTable};

/// What the CPU half of a page-table write needs to know of the GPU index: page grid, the
/// cache's slot grid and the traversal. Plain data, so a loader thread can prepare a table
/// ([`PreparedPageTable::new`]) without touching the GPU.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PageTableLayout {
    pub page_dims: [u32; 3],
    pub slots_per_axis: [u32; 3],
    pub traversal: Traversal,
}

/// Per page cell, bytes of the flat table's buffers: page word (binding 3), MIP bound
/// (binding 9), transition mask and closure (binding 11), visibility word (binding 7).
pub const FLAT_BYTES_PER_PAGE: u64 = 4 + 4 + 8 + 4;
/// Per page cell, bytes of the flat table's largest single binding (the transition pairs):
/// what a storage-binding limit is measured against.
pub const FLAT_LARGEST_BINDING_BYTES_PER_PAGE: u64 = 8;

/// The flat table's size against a binding limit: `Ok` when its largest per-page buffer fits
/// `limit_bytes`, else [`RenderError::FlatTableTooLarge`] naming the page count, the bytes
/// and the limit (`limit_source` says whose limit it is: the device's or a configured one).
pub fn check_flat_table_fits(
    page_dims: [u32; 3],
    limit_bytes: u64,
    limit_source: &str,
) -> Result<(), RenderError> {
    let pages: u64 = page_dims.iter().map(|&d| d.max(1) as u64).product();
    let binding_bytes = pages * FLAT_LARGEST_BINDING_BYTES_PER_PAGE;
    if binding_bytes > limit_bytes {
        return Err(RenderError::FlatTableTooLarge {
            pages,
            page_dims,
            bytes: pages * FLAT_BYTES_PER_PAGE,
            binding_bytes,
            limit_bytes,
            limit_source: limit_source.to_string(),
        });
    }
    Ok(())
}

/// The limit the flat table is checked against on `device`: the device's storage-binding
/// size, or `configured` where that is smaller (tests make it bind on a small volume).
pub fn flat_table_limit(device: &wgpu::Device, configured: Option<u64>) -> (u64, String) {
    let device_limit = device.limits().max_storage_buffer_binding_size;
    match configured {
        Some(c) if c < device_limit => (c, "the configured flat-table limit".into()),
        _ => (
            device_limit,
            "the device's max storage buffer binding size".into(),
        ),
    }
}

/// A page table with everything derived from it for the GPU index, computed on any thread:
/// for the flat buffers the GPU words with their node-extent flags and skip levels, the
/// transition masks and closures; for the octree the encoded node buffer (O(cut)).
/// [`GpuPageTable::write_prepared`] then writes only what changed (flat) or the node buffer.
#[derive(Clone, Debug)]
pub struct PreparedPageTable {
    layout: PageTableLayout,
    /// Dense for the flat traversal; per leaf when prepared by [`PreparedPageTable::sparse`].
    table: IndexTable,
    /// Binding 3's words (empty with the octree traversal, which builds its node buffer).
    words: Vec<u32>,
    /// Binding 11's pairs per page cell (empty with the octree traversal: its leaves carry
    /// theirs, `EncodedOctree::transitions`).
    transitions: Vec<[u32; 2]>,
    /// The octree traversal's node buffer, leaves and per-leaf masks.
    octree: Option<EncodedOctree>,
    transition_fraction: f64,
}

impl PreparedPageTable {
    /// Checks `table` against `layout` and derives the GPU words (O(entries): node-extent
    /// flags and transition masks depend on neighbours). With the octree traversal the tree
    /// is built from the table's cells (see [`PreparedPageTable::with_leaves`]).
    pub fn new(layout: PageTableLayout, table: PageTable) -> Result<Self, RenderError> {
        Self::prepare(layout, table, None)
    }

    /// As [`PreparedPageTable::new`], with the cut's leaves (the blocks the table was painted
    /// from): the octree traversal builds its tree from them in O(leaves · depth) instead of
    /// from every page cell. The flat traversal ignores them.
    pub fn with_leaves(
        layout: PageTableLayout,
        table: PageTable,
        leaves: Vec<CutLeaf>,
    ) -> Result<Self, RenderError> {
        Self::prepare(layout, table, Some(leaves))
    }

    /// The octree traversal's index from the cut's table kept per leaf: nothing here is per
    /// page cell, so a 16384³ volume's cut prepares in O(leaves · depth) time and memory.
    pub fn sparse(layout: PageTableLayout, table: SparsePageTable) -> Result<Self, RenderError> {
        if layout.traversal != Traversal::Octree {
            return Err(RenderError::PageTableMismatch(
                "a table kept per leaf needs the octree traversal".into(),
            ));
        }
        if table.page_dims() != layout.page_dims {
            return Err(RenderError::PageTableMismatch(format!(
                "table is {:?}, volume needs {:?}",
                table.page_dims(),
                layout.page_dims
            )));
        }
        check_slots(layout, table.leaves().iter().map(|l| &l.entry))?;
        let cut = OctreeCut::from_leaves(layout.page_dims, table.leaves().to_vec());
        let encoded = EncodedOctree::new(&cut, &table, layout.slots_per_axis)?;
        Ok(PreparedPageTable {
            layout,
            table: IndexTable::Sparse(table),
            words: Vec::new(),
            transitions: Vec::new(),
            transition_fraction: encoded.transition_fraction,
            octree: Some(encoded),
        })
    }

    fn prepare(
        layout: PageTableLayout,
        table: PageTable,
        leaves: Option<Vec<CutLeaf>>,
    ) -> Result<Self, RenderError> {
        table.check_against(layout.page_dims)?;
        check_slots(layout, table.entries.iter())?;
        if layout.traversal == Traversal::Octree {
            let cut = match leaves {
                Some(leaves) => OctreeCut::from_leaves(layout.page_dims, leaves),
                None => OctreeCut::from_page_table(&table),
            };
            let encoded = EncodedOctree::new(&cut, &table, layout.slots_per_axis)?;
            return Ok(PreparedPageTable {
                layout,
                table: IndexTable::Dense(table),
                words: Vec::new(),
                transitions: Vec::new(),
                transition_fraction: encoded.transition_fraction,
                octree: Some(encoded),
            });
        }
        let masks = transition_masks(&table);
        let transition_fraction = transition_node_fraction(&table, &masks);
        let words = table.encoded_for_gpu(layout.slots_per_axis, &masks);
        let transitions = masks.iter().map(|&m| [m, near_side_closure(m)]).collect();
        Ok(PreparedPageTable {
            layout,
            table: IndexTable::Dense(table),
            words,
            transitions,
            octree: None,
            transition_fraction,
        })
    }

    pub fn table(&self) -> &IndexTable {
        &self.table
    }

    pub fn into_table(self) -> IndexTable {
        self.table
    }

    /// The octree's leaves (None with the flat traversal): what per-leaf MIP bounds are
    /// computed over (`gpu_octree::leaf_value_max`).
    pub fn octree_leaves(&self) -> Option<&OctreeLeaves> {
        self.octree.as_ref().map(|o| &*o.leaves)
    }

    /// CPU bytes of the GPU index this holds besides the table: the flat words and
    /// transition pairs per page cell, or the octree's encoded node buffer, leaves and
    /// per-leaf masks.
    pub fn index_cpu_bytes(&self) -> usize {
        self.words.len() * 4
            + self.transitions.len() * 8
            + self.octree.as_ref().map_or(0, |o| o.cpu_bytes())
    }
}

/// Every resident entry's slot within the cache's slot grid.
fn check_slots<'a>(
    layout: PageTableLayout,
    mut entries: impl Iterator<Item = &'a PageEntry>,
) -> Result<(), RenderError> {
    let slots: u32 = layout.slots_per_axis.iter().product();
    match entries.find(|e| e.resident && e.slot_in_cache >= slots) {
        Some(bad) => Err(RenderError::SlotOutOfRange {
            slot: bad.slot_in_cache,
            slots,
        }),
        None => Ok(()),
    }
}

/// The flat buffers' contents as last written, compared with the next write so only the
/// changed spans are written (dirty_spans.rs).
struct Written {
    /// Dense with the flat traversal (its buffers are per page cell anyway); with the octree,
    /// the table as prepared (per leaf from the loader).
    table: IndexTable,
    words: Vec<u32>,
    transitions: Vec<[u32; 2]>,
    value_max: Vec<f32>,
    /// Bytes the last table or bound write sent to the GPU (tests check it stays O(change)).
    last_write_bytes: u64,
}

/// The page table on the GPU: a storage buffer of encoded entries (see page_table.rs).
pub struct GpuPageTable {
    pub buffer: wgpu::Buffer,
    /// Per entry, the physical value bound MIP rays use to skip it (+inf: never skip);
    /// see [`PageTable::value_max_physical`].
    pub value_max: wgpu::Buffer,
    pub page_dims: [u32; 3],
    /// Slot grid of the cache the entries point into (entries store slot grid positions).
    pub slots_per_axis: [u32; 3],
    /// Per entry, the covering node's 26-neighbour mask of coarser neighbours and its
    /// near-side closure (smooth_transitions.rs), written by [`GpuPageTable::update`].
    pub transitions: wgpu::Buffer,
    /// Share of resident nodes with a coarser neighbour in the last table written; 0 means
    /// frames need no transition code at all.
    transition_fraction: std::sync::Mutex<f64>,
    /// The table and the flat buffers as last written ([`GpuPageTable::update`],
    /// [`GpuPageTable::write_entries`], [`GpuPageTable::update_value_max`]): a partial write
    /// re-encodes the words whose whole-node flag or skip level it changes, and every write
    /// sends only the spans that differ.
    written: std::sync::Mutex<Written>,
    /// Which index the raycaster traverses; the octree's buffers (stubs with the flat table).
    traversal: Traversal,
    octree: std::sync::Mutex<GpuOctreeIndex>,
    device: wgpu::Device,
    /// Unique per table and its count of table writes: together they name the cut the light
    /// cache was built from (light_cache.rs), without comparing tables.
    id: u64,
    writes: std::sync::atomic::AtomicU64,
}

/// Source of [`GpuPageTable`] ids.
static NEXT_TABLE_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

impl GpuPageTable {
    /// The flat page table. Fails if the table would exceed the device's storage-buffer
    /// binding limit.
    pub fn new(
        device: &wgpu::Device,
        page_dims: [u32; 3],
        cache: &BrickCache,
    ) -> Result<Self, RenderError> {
        Self::with_traversal(device, page_dims, cache, Traversal::Flat)
    }

    /// The index for `traversal`: the flat table (one word per page cell, limited by the
    /// device's storage-binding size), or the octree of the cut (GPU buffers O(cut); the flat
    /// buffers are one-entry stubs then).
    pub fn with_traversal(
        device: &wgpu::Device,
        page_dims: [u32; 3],
        cache: &BrickCache,
        traversal: Traversal,
    ) -> Result<Self, RenderError> {
        Self::with_traversal_limited(device, page_dims, cache, traversal, None)
    }

    /// As [`GpuPageTable::with_traversal`], the flat table refused
    /// ([`RenderError::FlatTableTooLarge`]) already when its largest per-page buffer exceeds
    /// `flat_limit_bytes` (below the device's limit; see [`flat_table_limit`]).
    pub fn with_traversal_limited(
        device: &wgpu::Device,
        page_dims: [u32; 3],
        cache: &BrickCache,
        traversal: Traversal,
        flat_limit_bytes: Option<u64>,
    ) -> Result<Self, RenderError> {
        let pages: u64 = page_dims.iter().map(|&d| d.max(1) as u64).product();
        let n = if traversal == Traversal::Octree {
            1
        } else {
            pages
        };
        // The page word's level field holds levels 0..=LEVEL_MASK (layout.rs).
        let max_pages = 1u32 << LEVEL_MASK;
        if page_dims.iter().any(|&d| d > max_pages) {
            return Err(RenderError::PageTableMismatch(format!(
                "a page grid of {page_dims:?} exceeds {max_pages} pages per axis, the most the \
                 page word's level field addresses"
            )));
        }
        if traversal == Traversal::Flat {
            let (limit, source) = flat_table_limit(device, flat_limit_bytes);
            check_flat_table_fits(page_dims, limit, &source)?;
        }
        let buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("page table"),
            size: n * 4,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        // Starts at +inf so a caller that never writes bounds gets correct, unskipped MIP.
        let value_max = wgpu::util::DeviceExt::create_buffer_init(
            device,
            &wgpu::util::BufferInitDescriptor {
                label: Some("page value max"),
                contents: bytemuck::cast_slice(&vec![f32::INFINITY; n as usize]),
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            },
        );
        let transitions = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("page transitions"),
            size: n * 8,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(GpuPageTable {
            buffer,
            value_max,
            page_dims,
            slots_per_axis: cache.slots_per_axis,
            transitions,
            transition_fraction: std::sync::Mutex::new(0.0),
            // Fresh buffers are zero-filled (wgpu clears them), the bounds +inf as written above.
            written: std::sync::Mutex::new(Written {
                table: match traversal {
                    Traversal::Flat => IndexTable::Dense(PageTable::new(page_dims)),
                    Traversal::Octree => IndexTable::Sparse(SparsePageTable::uniform(
                        page_dims,
                        PageEntry::NOT_RESIDENT,
                    )),
                },
                words: vec![0; n as usize],
                transitions: vec![[0; 2]; n as usize],
                value_max: vec![f32::INFINITY; n as usize],
                last_write_bytes: 0,
            }),
            traversal,
            octree: std::sync::Mutex::new(GpuOctreeIndex::new(device, page_dims)),
            device: device.clone(),
            id: NEXT_TABLE_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            writes: std::sync::atomic::AtomicU64::new(0),
        })
    }

    /// The traversal this index was made for (the raycaster compiles the matching pipeline).
    pub fn traversal(&self) -> Traversal {
        self.traversal
    }

    /// What [`PreparedPageTable::new`] needs to prepare a table for this index.
    pub fn layout(&self) -> PageTableLayout {
        PageTableLayout {
            page_dims: self.page_dims,
            slots_per_axis: self.slots_per_axis,
            traversal: self.traversal,
        }
    }

    /// Bytes the last table or MIP-bound write sent to the GPU (the flat buffers' changed
    /// spans; with the octree traversal, 0: its node buffer is rewritten whole).
    pub fn last_write_bytes(&self) -> u64 {
        self.written.lock().map_or(0, |w| w.last_write_bytes)
    }

    fn written(&self) -> Result<std::sync::MutexGuard<'_, Written>, RenderError> {
        self.written
            .lock()
            .map_err(|_| RenderError::PageTableMismatch("page table mirror poisoned".into()))
    }

    /// GPU bytes of the index the raycaster reads, as last written: the flat table's page
    /// words, MIP bounds and transition masks per page cell, or the octree's node buffer and
    /// per-leaf bounds. The visibility words (one per page cell / per leaf) come on top:
    /// [`GpuPageTable::visibility_entries`].
    pub fn gpu_index_bytes(&self) -> u64 {
        match self.traversal {
            Traversal::Flat => self.entry_count() as u64 * 16,
            Traversal::Octree => self.octree.lock().map(|o| o.bytes()).unwrap_or(0),
        }
    }

    /// Visibility words a frame writes: one per page cell (flat) or per leaf (octree).
    pub fn visibility_entries(&self) -> usize {
        match self.traversal {
            Traversal::Flat => self.entry_count(),
            Traversal::Octree => self.octree_leaves().map_or(0, |l| l.boxes.len()),
        }
    }

    /// The leaves of the octree last written (None with the flat table).
    pub fn octree_leaves(&self) -> Option<std::sync::Arc<OctreeLeaves>> {
        if self.traversal != Traversal::Octree {
            return None;
        }
        self.octree.lock().ok().map(|o| o.leaves.clone())
    }

    /// The octree root's reference (`OCTREE_NULL` with the flat table or before a write).
    pub(crate) fn octree_root(&self) -> u32 {
        self.octree
            .lock()
            .map(|o| o.root)
            .unwrap_or(crate::model::layout::OCTREE_NULL)
    }

    /// The buffers bound at 9 (MIP bounds), 12 (octree nodes) and 11 (transition masks) for
    /// the traversal.
    pub(crate) fn traversal_buffers(
        &self,
    ) -> Result<(wgpu::Buffer, wgpu::Buffer, wgpu::Buffer), RenderError> {
        let octree = self
            .octree
            .lock()
            .map_err(|_| RenderError::PageTableMismatch("octree index poisoned".into()))?;
        Ok(match self.traversal {
            Traversal::Flat => (
                self.value_max.clone(),
                octree.nodes.clone(),
                self.transitions.clone(),
            ),
            Traversal::Octree => (
                octree.leaf_value_max.clone(),
                octree.nodes.clone(),
                octree.leaf_transitions.clone(),
            ),
        })
    }

    pub fn entry_count(&self) -> usize {
        self.page_dims.iter().map(|&d| d as usize).product()
    }

    /// Writes `entries` starting at linear index `first` (x fastest, then y, z) into the table
    /// as last written. Takes effect for the next submitted frame. Re-encodes the whole table
    /// with its transition masks, as [`GpuPageTable::update`] does (O(entries): node-extent
    /// flags and transition masks depend on neighbours).
    pub fn write_entries(
        &self,
        queue: &wgpu::Queue,
        first: usize,
        entries: &[PageEntry],
    ) -> Result<(), RenderError> {
        let slots: u32 = self.slots_per_axis.iter().product();
        if first + entries.len() > self.entry_count() {
            return Err(RenderError::PageTableMismatch(format!(
                "entries {first}..{} beyond {} page entries",
                first + entries.len(),
                self.entry_count()
            )));
        }
        if let Some(bad) = entries
            .iter()
            .find(|e| e.resident && e.slot_in_cache >= slots)
        {
            return Err(RenderError::SlotOutOfRange {
                slot: bad.slot_in_cache,
                slots,
            });
        }
        // A word's whole-node flag and skip level depend on its neighbours (see
        // PageTable::encoded_for_gpu), so the table as last written is re-encoded whole.
        let mut table = self.written()?.table.to_page_table();
        table.entries[first..first + entries.len()].copy_from_slice(entries);
        self.update(queue, &table)?;
        Ok(())
    }

    /// Writes the per-entry MIP bounds (from [`PageTable::value_max_physical`]); takes
    /// effect for the next submitted frame.
    pub fn update_value_max(&self, queue: &wgpu::Queue, bounds: &[f32]) -> Result<(), RenderError> {
        if bounds.len() != self.entry_count() {
            return Err(RenderError::PageTableMismatch(format!(
                "{} value bounds for {} page entries",
                bounds.len(),
                self.entry_count()
            )));
        }
        if self.traversal == Traversal::Octree {
            let mut octree = self
                .octree
                .lock()
                .map_err(|_| RenderError::PageTableMismatch("octree index poisoned".into()))?;
            octree.update_value_max(&self.device, queue, bounds);
            return Ok(());
        }
        let mut written = self.written()?;
        let Written {
            value_max,
            last_write_bytes,
            ..
        } = &mut *written;
        *last_write_bytes = write_changed(queue, &self.value_max, value_max, bounds);
        Ok(())
    }

    /// Writes per-leaf MIP bounds (`gpu_octree::leaf_value_max`, in the leaf order of the
    /// cut last written) for the octree traversal; takes effect for the next submitted frame.
    pub fn update_leaf_value_max(
        &self,
        queue: &wgpu::Queue,
        per_leaf: &[f32],
    ) -> Result<(), RenderError> {
        if self.traversal != Traversal::Octree {
            return Err(RenderError::PageTableMismatch(
                "per-leaf value bounds need the octree traversal".into(),
            ));
        }
        let mut octree = self
            .octree
            .lock()
            .map_err(|_| RenderError::PageTableMismatch("octree index poisoned".into()))?;
        octree.update_leaf_value_max(&self.device, queue, per_leaf)
    }

    /// Writes the whole table; takes effect for the next submitted frame. Only the spans of
    /// the flat buffers that differ from the last write are sent.
    pub fn update(&self, queue: &wgpu::Queue, table: &PageTable) -> Result<(), RenderError> {
        self.write_prepared(
            queue,
            &PreparedPageTable::new(self.layout(), table.clone())?,
        )
    }

    /// Writes a table prepared (possibly on another thread) for this index: the flat
    /// buffers' changed spans, or the octree's node buffer rebuilt; takes effect for the next
    /// submitted frame.
    pub fn write_prepared(
        &self,
        queue: &wgpu::Queue,
        prepared: &PreparedPageTable,
    ) -> Result<(), RenderError> {
        if prepared.layout != self.layout() {
            return Err(RenderError::PageTableMismatch(format!(
                "table prepared for {:?}, index is {:?}",
                prepared.layout,
                self.layout()
            )));
        }
        let mut written = self.written()?;
        self.writes
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        written.table.clone_from(&prepared.table);
        if let Some(encoded) = &prepared.octree {
            // The cut changed: its node buffer (encoded where the table was prepared) is
            // written whole: a few thousand leaves.
            let mut octree = self
                .octree
                .lock()
                .map_err(|_| RenderError::PageTableMismatch("octree index poisoned".into()))?;
            octree.write_encoded(&self.device, queue, encoded);
            written.last_write_bytes = 0;
        } else {
            let w = &mut *written;
            w.last_write_bytes = write_changed(queue, &self.buffer, &mut w.words, &prepared.words)
                + write_changed(
                    queue,
                    &self.transitions,
                    &mut w.transitions,
                    &prepared.transitions,
                );
        }
        if let Ok(mut f) = self.transition_fraction.lock() {
            *f = prepared.transition_fraction;
        }
        Ok(())
    }

    /// This table's id and its count of table writes (light_cache.rs keys on them: any write
    /// may change the cut, so every write invalidates a cache built from the table).
    pub fn generation(&self) -> (u64, u64) {
        (
            self.id,
            self.writes.load(std::sync::atomic::Ordering::Relaxed),
        )
    }

    /// Share of resident nodes next to a coarser node in the last table written by
    /// [`GpuPageTable::update`] (the paper's "transition bricks").
    pub fn transition_fraction(&self) -> f64 {
        self.transition_fraction.lock().map(|f| *f).unwrap_or(1.0)
    }
}
