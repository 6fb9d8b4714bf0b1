//! One-call rendering of an in-memory volume: what `strata render` and small-volume views need
//! without a loader. Everything resident at one level, empty pages classified for the TF.

use crate::error::RenderError;
use crate::gpu::bricked_volume::BrickedVolume;
use crate::gpu::cache::{BrickCache, CacheConfig};
use crate::gpu::device::GpuContext;
use crate::gpu::gpu_page_table::GpuPageTable;
use crate::gpu::gpu_transfer_function::GpuTransferFunction;
use crate::model::camera::Camera;
use crate::model::page_table::PageTable;
use crate::model::settings::{RenderMode, RenderSettings};
use crate::model::transfer_function::TransferFunction;
use crate::passes::raycast::{FrameInputs, FrameReadback, Raycaster};

pub struct OffscreenRenderer {
    pub cache: BrickCache,
    pub page_table: PageTable,
    pub gpu_page_table: GpuPageTable,
    pub transfer_function: GpuTransferFunction,
    pub raycaster: Raycaster,
    /// Iso value the empty flags were computed for (None: classified by the TF).
    classified_for_iso: Option<f64>,
}

impl OffscreenRenderer {
    /// Uploads every node of `level` (clamped to the coarsest) of `volume`.
    pub fn new(
        ctx: &GpuContext,
        volume: &BrickedVolume,
        tf: &TransferFunction,
        level: u8,
        config: CacheConfig,
    ) -> Result<Self, RenderError> {
        Self::with_cut(ctx, volume, tf, volume.page_table_uniform(level), config)
    }

    /// Uploads the nodes `page_table` references (any mix of levels, e.g. from
    /// [`BrickedVolume::page_table_with_levels`]).
    pub fn with_cut(
        ctx: &GpuContext,
        volume: &BrickedVolume,
        tf: &TransferFunction,
        page_table: PageTable,
        config: CacheConfig,
    ) -> Result<Self, RenderError> {
        tf.validate()?;
        page_table.check_against(volume.geometry.page_dims())?;
        let mut page_table = page_table;
        let nodes = BrickedVolume::resident_nodes(&page_table).len() as u32;
        let cache = BrickCache::new(
            &ctx.device,
            CacheConfig {
                max_slots: Some(config.max_slots.unwrap_or(nodes).min(nodes.max(1))),
                ..config
            },
        )?;
        if cache.slot_count() < nodes {
            return Err(RenderError::CacheTooSmall {
                budget_bytes: config.budget_bytes,
            });
        }
        volume.upload(&cache, &ctx.queue, &page_table)?;
        let (lo, hi) = volume.physical_range();
        let table = tf.table(lo, hi);
        volume.classify_empty(&mut page_table, &table);
        let gpu_page_table = GpuPageTable::new(&ctx.device, volume.geometry.page_dims(), &cache)?;
        gpu_page_table.update(&ctx.queue, &page_table)?;
        gpu_page_table.update_value_max(
            &ctx.queue,
            &page_table.value_max_physical(volume.mapping, |l, n| volume.node_range(l, n)),
        )?;
        let transfer_function = GpuTransferFunction::new(&ctx.device, &ctx.queue, &table);
        let raycaster = Raycaster::new(ctx, &cache);
        Ok(OffscreenRenderer {
            cache,
            page_table,
            gpu_page_table,
            transfer_function,
            raycaster,
            classified_for_iso: None,
        })
    }

    /// Replaces the transfer function: the GPU table, and the empty-page flags it implies
    /// (unless an isosurface's classification is in force, which the next DVR frame redoes).
    pub fn set_transfer_function(
        &mut self,
        ctx: &GpuContext,
        volume: &BrickedVolume,
        tf: &TransferFunction,
    ) -> Result<(), RenderError> {
        tf.validate()?;
        let (lo, hi) = volume.physical_range();
        let table = tf.table(lo, hi);
        self.transfer_function.update(&ctx.queue, &table);
        if self.classified_for_iso.is_none() {
            volume.classify_empty(&mut self.page_table, &table);
            self.gpu_page_table.update(&ctx.queue, &self.page_table)?;
        }
        Ok(())
    }

    /// Renders and reads back. Re-classifies empty pages when switching to or between
    /// isosurface values, since "empty" means "below the iso value" there.
    pub fn render(
        &mut self,
        ctx: &GpuContext,
        volume: &BrickedVolume,
        camera: &Camera,
        settings: &RenderSettings,
    ) -> Result<FrameReadback, RenderError> {
        self.submit(ctx, volume, camera, settings)?;
        self.raycaster.read_frame_blocking(ctx)
    }

    /// Encodes and submits one frame into [`Raycaster::output_texture`] without waiting for
    /// it: what a caller that cannot block (the browser's event loop) draws with.
    pub fn submit(
        &mut self,
        ctx: &GpuContext,
        volume: &BrickedVolume,
        camera: &Camera,
        settings: &RenderSettings,
    ) -> Result<wgpu::SubmissionIndex, RenderError> {
        let want_iso = (settings.mode == RenderMode::Isosurface).then_some(settings.iso_value);
        if want_iso != self.classified_for_iso {
            match want_iso {
                Some(iso) => self
                    .page_table
                    .classify_empty_for_iso(iso, volume.mapping, |l, n| volume.node_range(l, n)),
                None => {
                    let (lo, hi) = volume.physical_range();
                    let table = self.transfer_function.source.table(lo, hi);
                    volume.classify_empty(&mut self.page_table, &table);
                }
            }
            self.gpu_page_table.update(&ctx.queue, &self.page_table)?;
            self.classified_for_iso = want_iso;
        }
        let scene = FrameInputs {
            cache: &self.cache,
            page_table: &self.gpu_page_table,
            transfer_function: &self.transfer_function,
            geometry: &volume.geometry,
            mapping: volume.mapping,
            camera,
            settings,
        };
        self.raycaster.render(ctx, &scene)
    }
}
