//! A fixed cut of a store held in memory: the bricks a page table references, read (and
//! checksum-verified) from storage, served to the renderer through [`BrickSource`].
//!
//! `GpuCut` is the in-core baseline of tests and `strata flythrough`: its cache holds the whole
//! cut, or refuses one over a given budget before anything is read (`check_cut_fits`: bricks ×
//! bytes against `--gpu-mib` of `render --up-front` and `bench timecritical`, or the 3D texture
//! limit).

use std::collections::HashMap;

use rayon::prelude::*;
use strata_render::{
    BrickCache, BrickSource, IndexTable, PageEntry, PageTable, TransferFunctionTable, ValueMapping,
    VolumeGeometry,
};
use strata_source::{SourceError, VolumeSource};
use strata_types::BrickId;

pub use crate::error::LoaderError;

/// Bricks of one cut, keyed by (level, node).
pub struct ResidentBricks {
    bricks: HashMap<(u8, [u32; 3]), Vec<u16>>,
}

impl BrickSource for ResidentBricks {
    fn brick(&self, level: u8, node: [u32; 3]) -> Option<&[u16]> {
        self.bricks.get(&(level, node)).map(|b| b.as_slice())
    }
}

impl ResidentBricks {
    /// Reads every node `table` references, in parallel. A damaged brick is an error naming it.
    pub fn load(
        store: &dyn VolumeSource,
        table: &PageTable,
    ) -> Result<ResidentBricks, LoaderError> {
        let mut nodes: Vec<(u8, [u32; 3])> = table
            .entries
            .iter()
            .enumerate()
            .filter(|(_, e)| e.resident)
            .map(|(i, e)| {
                (
                    e.level,
                    PageTable::node_of(table.page_of_linear(i), e.level),
                )
            })
            .collect();
        nodes.sort_unstable();
        nodes.dedup();
        let bricks = nodes
            .into_par_iter()
            .map(|(level, node)| Ok(((level, node), store.read_brick(BrickId::new(level, node))?)))
            .collect::<Result<HashMap<_, _>, SourceError>>()?;
        Ok(ResidentBricks { bricks })
    }

    pub fn len(&self) -> usize {
        self.bricks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.bricks.is_empty()
    }

    /// Uploads the table's nodes into their slots.
    pub fn upload(
        &self,
        cache: &BrickCache,
        queue: &wgpu::Queue,
        table: &PageTable,
    ) -> Result<(), LoaderError> {
        let mut done = std::collections::HashSet::new();
        for (i, e) in table.entries.iter().enumerate() {
            if !e.resident || !done.insert(e.slot_in_cache) {
                continue;
            }
            let node = PageTable::node_of(table.page_of_linear(i), e.level);
            let payload = self.brick(e.level, node).ok_or_else(|| {
                LoaderError::Unsupported(format!(
                    "node {node:?} of level {} was not loaded",
                    e.level
                ))
            })?;
            cache.upload_brick(queue, e.slot_in_cache, payload)?;
        }
        Ok(())
    }
}

/// A page table whose position `page` is served by level `level_of(page)` (clamped to the
/// root), with slots assigned densely in first-use order.
pub fn page_table_for_cut(
    store: &dyn VolumeSource,
    geometry: &VolumeGeometry,
    level_of: impl Fn([u32; 3]) -> u8,
) -> PageTable {
    let root = (store.layout().level_count() - 1) as u8;
    let mut table = PageTable::new(geometry.page_dims());
    let mut slots: HashMap<(u8, [u32; 3]), u32> = HashMap::new();
    for i in 0..table.entries.len() {
        let page = table.page_of_linear(i);
        let level = level_of(page).min(root);
        let node = PageTable::node_of(page, level);
        let next = slots.len() as u32;
        let slot = *slots.entry((level, node)).or_insert(next);
        table.entries[i] = PageEntry::resident(slot, level);
    }
    table
}

/// Every page position served by `level` (clamped to the root), empty pages flagged for
/// `tf_table`, and the bricks that cut needs, read and verified: what `GpuCut::upload` and the
/// CPU reference take for an in-core render of one level.
pub fn load_uniform_cut(
    store: &dyn VolumeSource,
    geometry: &VolumeGeometry,
    mapping: ValueMapping,
    tf_table: &TransferFunctionTable,
    level: u8,
) -> Result<(PageTable, ResidentBricks), LoaderError> {
    let mut table = page_table_for_cut(store, geometry, |_| level);
    classify_empty(store, &mut table, mapping, tf_table);
    let bricks = ResidentBricks::load(store, &table)?;
    Ok((table, bricks))
}

/// Cache slots `table` needs (its highest resident slot + 1; at least the root's one).
pub fn slots_needed(table: &PageTable) -> u32 {
    table
        .entries
        .iter()
        .filter(|e| e.resident)
        .map(|e| e.slot_in_cache + 1)
        .max()
        .unwrap_or(1)
}

/// Bytes of one cache slot in the format a default cache takes on `ctx`'s device.
fn slot_bytes_on(ctx: &strata_render::GpuContext) -> u64 {
    strata_render::CacheFormat::for_device(&ctx.device, &strata_render::CacheConfig::default())
        .slot_bytes()
}

/// Whether `bricks` slots of the default cache format fit `budget_bytes` (when given) and the
/// device's 3D texture limit: checked before a cut is read (reading gigabytes to then refuse
/// them helps nobody). `what` names the cut in the message ("level 0 of STORE").
pub fn check_cut_fits(
    ctx: &strata_render::GpuContext,
    bricks: u32,
    budget_bytes: Option<u64>,
    what: &str,
) -> Result<(), LoaderError> {
    let brick_bytes = slot_bytes_on(ctx);
    if let Some(budget_bytes) = budget_bytes {
        if bricks as u64 * brick_bytes > budget_bytes {
            return Err(LoaderError::CutOverBudget {
                what: what.into(),
                bricks: bricks as u64,
                brick_bytes,
                budget_bytes,
            });
        }
    }
    let max_dim = ctx.device.limits().max_texture_dimension_3d;
    let per_axis = (max_dim / strata_render::model::layout::BRICK_PAYLOAD)
        .min(strata_render::model::layout::MAX_SLOTS_PER_AXIS) as u64;
    let slots = per_axis.pow(3);
    if bricks as u64 > slots {
        return Err(LoaderError::CutOverDeviceLimit {
            what: what.into(),
            bricks: bricks as u64,
            slots,
            max_dim,
        });
    }
    Ok(())
}

/// Flags positions whose node is transparent under the transfer function (skeleton ranges).
pub fn classify_empty(
    store: &dyn VolumeSource,
    table: &mut PageTable,
    mapping: ValueMapping,
    tf: &TransferFunctionTable,
) {
    table.classify_empty(tf, mapping, |level, node| {
        store
            .node(BrickId::new(level, node))
            .map(|n| (n.min, n.max))
    });
}

/// A fixed cut resident on the GPU: cache texture, page table, transfer function and raycaster,
/// ready to render frames of it. (The streaming loader will keep these updated instead.)
pub struct GpuCut {
    pub cache: BrickCache,
    pub page_table: strata_render::GpuPageTable,
    pub transfer_function: strata_render::GpuTransferFunction,
    pub raycaster: strata_render::Raycaster,
    table: PageTable,
    node_ranges: HashMap<(u8, [u32; 3]), (u16, u16)>,
    /// The mapping the MIP value bounds on the GPU were computed with.
    bounds_for: Option<ValueMapping>,
}

impl GpuCut {
    /// Uploads `bricks` into a cache with exactly as many slots as the cut needs, however many
    /// that is (the device's limits still apply; see [`check_cut_fits`]).
    pub fn upload(
        ctx: &strata_render::GpuContext,
        bricks: &ResidentBricks,
        table: &PageTable,
        page_dims: [u32; 3],
        tf_table: &TransferFunctionTable,
    ) -> Result<GpuCut, LoaderError> {
        Self::upload_within(ctx, bricks, table, page_dims, tf_table, None)
    }

    /// [`GpuCut::upload`] within `budget_bytes` of GPU memory when given: a cut that does not
    /// fit is an error naming its bricks × bytes against the budget.
    pub fn upload_within(
        ctx: &strata_render::GpuContext,
        bricks: &ResidentBricks,
        table: &PageTable,
        page_dims: [u32; 3],
        tf_table: &TransferFunctionTable,
        budget_bytes: Option<u64>,
    ) -> Result<GpuCut, LoaderError> {
        let needed = slots_needed(table);
        check_cut_fits(ctx, needed, budget_bytes, "the cut")?;
        // The cache shapes its slots into a 3D grid and may round a count down by up to 3 %;
        // ask for a little more so every brick has a slot.
        let asked = needed + needed / 32 + 8;
        let slot_bytes = slot_bytes_on(ctx);
        let config = strata_render::CacheConfig {
            budget_bytes: budget_bytes.unwrap_or(asked as u64 * slot_bytes),
            max_slots: Some(asked),
            ..Default::default()
        };
        let cache = BrickCache::new(&ctx.device, config)?;
        if cache.slot_count() < needed {
            return Err(LoaderError::CutOverDeviceLimit {
                what: "the cut".into(),
                bricks: needed as u64,
                slots: cache.slot_count() as u64,
                max_dim: ctx.device.limits().max_texture_dimension_3d,
            });
        }
        bricks.upload(&cache, &ctx.queue, table)?;
        let page_table = strata_render::GpuPageTable::new(&ctx.device, page_dims, &cache)?;
        page_table.update(&ctx.queue, table)?;
        // Stored ranges of the cut's nodes, from the bricks themselves (all in memory here);
        // the MIP bounds are written once the value mapping is known (first render).
        let mut node_ranges = HashMap::new();
        for (i, e) in table.entries.iter().enumerate() {
            let node = PageTable::node_of(table.page_of_linear(i), e.level);
            if let Some(brick) = bricks.brick(e.level, node).filter(|_| e.resident) {
                if let (Some(lo), Some(hi)) = (brick.iter().min(), brick.iter().max()) {
                    node_ranges.insert((e.level, node), (*lo, *hi));
                }
            }
        }
        let transfer_function =
            strata_render::GpuTransferFunction::new(&ctx.device, &ctx.queue, tf_table);
        let raycaster = strata_render::Raycaster::new(ctx, &cache);
        Ok(GpuCut {
            cache,
            page_table,
            transfer_function,
            raycaster,
            table: table.clone(),
            node_ranges,
            bounds_for: None,
        })
    }

    /// Renders one frame and waits for it (CLI, tests, benchmarks; the viewer reads back late).
    pub fn render_blocking(
        &mut self,
        ctx: &strata_render::GpuContext,
        geometry: &VolumeGeometry,
        mapping: ValueMapping,
        camera: &strata_render::Camera,
        settings: &strata_render::RenderSettings,
    ) -> Result<strata_render::FrameReadback, LoaderError> {
        if self.bounds_for != Some(mapping) {
            let bounds = self.table.value_max_physical(mapping, |level, node| {
                self.node_ranges.get(&(level, node)).copied()
            });
            self.page_table.update_value_max(&ctx.queue, &bounds)?;
            self.bounds_for = Some(mapping);
        }
        let scene = strata_render::FrameInputs {
            cache: &self.cache,
            page_table: &self.page_table,
            transfer_function: &self.transfer_function,
            geometry,
            mapping,
            camera,
            settings,
        };
        Ok(self.raycaster.render_blocking(ctx, &scene)?)
    }

    /// The cut's GPU resources as a scene of `settings` (for a pass other than the cut's own
    /// raycaster, or a timed render through it).
    pub fn scene<'a>(
        &'a self,
        geometry: &'a VolumeGeometry,
        mapping: ValueMapping,
        camera: &'a strata_render::Camera,
        settings: &'a strata_render::RenderSettings,
    ) -> strata_render::FrameInputs<'a> {
        strata_render::FrameInputs {
            cache: &self.cache,
            page_table: &self.page_table,
            transfer_function: &self.transfer_function,
            geometry,
            mapping,
            camera,
            settings,
        }
    }
}

/// The same field as `table` with only its sampled entries (resident, not empty) and slots
/// renumbered densely: what `ResidentBricks::load` + `GpuCut::upload` need to render a
/// streamed cut in core. Skipped entries stay skipped (not resident), so nothing else loads.
pub fn sampled_entries_only(table: &IndexTable) -> PageTable {
    // Per page cell: the in-core render this feeds is per page cell too.
    let painted;
    let table = match table {
        IndexTable::Dense(t) => t,
        IndexTable::Sparse(t) => {
            painted = t.to_dense();
            &painted
        }
    };
    let mut out = PageTable::new(table.page_dims);
    let mut slots: HashMap<(u8, [u32; 3]), u32> = HashMap::new();
    for (i, e) in table.entries.iter().enumerate() {
        if e.resident && !e.empty {
            let node = PageTable::node_of(table.page_of_linear(i), e.level);
            let next = slots.len() as u32;
            let slot = *slots.entry((e.level, node)).or_insert(next);
            out.entries[i] = PageEntry::resident(slot, e.level);
        }
    }
    out
}
