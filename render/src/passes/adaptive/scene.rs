//! The transcription (transcription.rs) over a real volume: SAMPLE is the field of field.rs
//! on the frame's slices (frame.rs), ORACLE one of [`OracleKind`], and a segment is integrated
//! either exactly in f64 or from the length-free pre-integration table the GPU reads
//! (segment_integral.rs). The CPU twin of the GPU pass, and with exact optics and d ≡ 1 the
//! slice-aligned full-rate image that adaptive frames are measured against.

use glam::{DMat3, DVec3};

use super::block_oracle::{block_of_local, BLOCKS_PER_SLOT};
use super::frame::SliceFrame;
use super::oracle::{hash_distance, outside_distance, OracleKind};
use super::transcription::{
    level0_coordinate, project_volume_tiled, AdaptiveProbe, SegmentOptics, TileRules, Transcription,
};
use super::AdaptiveConfig;
use crate::error::RenderError;
use crate::model::field::{sample_field, FieldSample};
use crate::model::layout::BrickSource;
use crate::model::preintegration::integrate_segment;
use crate::model::segment_integral::SegmentIntegralTable;
use crate::model::settings::RenderSettings;
use crate::model::smooth_transitions::transition_masks;
use crate::reference::{ray_interval, shade, ReferenceScene};

/// How the CPU side integrates a segment.
#[derive(Clone, Copy, Debug)]
pub enum AdaptiveOptics<'a> {
    /// f64 integration of the exact TF with this many sub-steps per slice of length.
    Exact { substeps_per_slice: usize },
    /// The GPU's table, evaluated in f64.
    Table(&'a SegmentIntegralTable),
}

#[derive(Clone, Debug)]
pub struct AdaptiveReference {
    pub frame: SliceFrame,
    pub transcription: Transcription,
    /// Viewport pixels only (padding cropped), premultiplied RGBA.
    pub rgba_f64: Vec<[f64; 4]>,
    /// As the GPU's unorm store rounds it.
    pub rgba: Vec<u8>,
    /// Pick depth (mm): ray distance where accumulated opacity reaches ½, +inf if never.
    pub depth: Vec<f32>,
}

struct SceneProbe<'a, S: BrickSource> {
    scene: &'a ReferenceScene<'a, S>,
    settings: &'a RenderSettings,
    frame: &'a SliceFrame,
    masks: Option<Vec<u32>>,
    config: AdaptiveConfig,
    oracle_table: &'a [f32],
}

/// What SAMPLE reads at a point of a slice: the value (physical), and where it lies (page
/// entry, and the per-block oracle's table index: slot · BLOCKS_PER_SLOT + in-slot block).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SliceSample {
    pub value: f64,
    pub page: Option<usize>,
    pub block: Option<usize>,
}

/// The value (physical) and page entry SAMPLE reads at level-0 pixel coordinates (u, v) on
/// slice `i_slice`: the field where the slice's point lies in the ray's box-and-clip
/// interval and something is resident there, else the default value, the low end of the TF
/// range (which the TF maps to transparent for the CT and MR presets, §3.1), and no entry.
pub fn slice_sample<S: BrickSource>(
    scene: &ReferenceScene<S>,
    settings: &RenderSettings,
    frame: &SliceFrame,
    masks: Option<&[u32]>,
    uv: (f64, f64),
    i_slice: u32,
) -> (f64, Option<usize>) {
    let s = slice_sample_located(scene, settings, frame, masks, uv, i_slice);
    (s.value, s.page)
}

/// [`slice_sample`] with the block of the per-block oracle (block_oracle.rs).
pub fn slice_sample_located<S: BrickSource>(
    scene: &ReferenceScene<S>,
    settings: &RenderSettings,
    frame: &SliceFrame,
    masks: Option<&[u32]>,
    uv: (f64, f64),
    i_slice: u32,
) -> SliceSample {
    let located = slice_field(scene, settings, frame, masks, uv, i_slice);
    slice_sample_of(scene, located.as_ref())
}

/// The field where the slice's point lies in the ray's interval and something is resident.
fn slice_field<'a, S: BrickSource>(
    scene: &ReferenceScene<'a, S>,
    settings: &RenderSettings,
    frame: &SliceFrame,
    masks: Option<&[u32]>,
    (u, v): (f64, f64),
    i_slice: u32,
) -> Option<FieldSample<'a>> {
    let (o, d) = frame.ray(u, v);
    let t = frame.slice_t(i_slice);
    let g = scene.geometry;
    let inside = ray_interval(g, settings, o, d).is_some_and(|(t0, t1)| t >= t0 && t <= t1);
    inside
        .then(|| {
            let a = g.index_from_patient_linear();
            let p: DVec3 = a * (o + d * t - g.origin());
            sample_field(scene.source, scene.page_table, masks, g.dims, p)
        })
        .flatten()
}

fn slice_sample_of<S: BrickSource>(
    scene: &ReferenceScene<S>,
    located: Option<&FieldSample>,
) -> SliceSample {
    match located {
        Some(s) => {
            let slot = scene.page_table.entries[s.location.page_linear].slot_in_cache as usize;
            SliceSample {
                value: scene.mapping.physical(s.value),
                page: Some(s.location.page_linear),
                block: Some(slot * BLOCKS_PER_SLOT + block_of_local(s.location.local.to_array())),
            }
        }
        None => SliceSample {
            value: scene.tf_range.0,
            page: None,
            block: None,
        },
    }
}

impl<S: BrickSource> SceneProbe<'_, S> {
    /// SAMPLE and ORACLE at level-`level` pixel (x, y) of slice `i_slice`, and the gradient
    /// when asked (index space, physical units per index step: the GPU's `field_gradient`).
    fn sample(
        &self,
        level: u32,
        x: u32,
        y: u32,
        i_slice: u32,
        gradient: bool,
    ) -> (f64, f64, [f64; 3]) {
        let located = slice_field(
            self.scene,
            self.settings,
            self.frame,
            self.masks.as_deref(),
            (level0_coordinate(level, x), level0_coordinate(level, y)),
            i_slice,
        );
        let g = match &located {
            Some(f) if gradient => (f.gradient_index() * self.scene.mapping.slope).to_array(),
            _ => [0.0; 3],
        };
        let (value, distance) = self.value_and_distance(level, x, y, i_slice, located.as_ref());
        (value, distance, g)
    }

    fn value_and_distance(
        &self,
        level: u32,
        x: u32,
        y: u32,
        i_slice: u32,
        located: Option<&FieldSample>,
    ) -> (f64, f64) {
        let l_max = self.config.l_max;
        let coarsest = (1u32 << l_max) as f64;
        let sample = slice_sample_of(self.scene, located);
        let entry = match self.config.oracle {
            OracleKind::PerBlock => sample.block,
            _ => sample.page,
        };
        let distance = match self.config.oracle {
            OracleKind::Constant(c) => c as f64,
            OracleKind::Hash(seed) => hash_distance(level, x, y, i_slice, seed, l_max),
            OracleKind::PerNode | OracleKind::PerBlock => match entry {
                Some(p) => self.oracle_table.get(p).map_or(coarsest, |&d| d as f64),
                None => {
                    let (o, d) = self
                        .frame
                        .ray(level0_coordinate(level, x), level0_coordinate(level, y));
                    outside_distance(
                        self.scene.geometry,
                        self.settings,
                        o + d * self.frame.slice_t(i_slice),
                        self.frame.spacing_mm,
                        l_max,
                    )
                }
            },
        };
        (sample.value, distance)
    }
}

impl<S: BrickSource> AdaptiveProbe for SceneProbe<'_, S> {
    fn probe(&self, level: u32, x: u32, y: u32, i_slice: u32) -> (f64, f64) {
        let (value, distance, _) = self.sample(level, x, y, i_slice, false);
        (value, distance)
    }

    fn probe_with_gradient(
        &self,
        level: u32,
        x: u32,
        y: u32,
        i_slice: u32,
    ) -> (f64, f64, [f64; 3]) {
        self.sample(level, x, y, i_slice, true)
    }

    fn ray_slices(&self, u: f64, v: f64) -> Option<(f64, f64)> {
        let (o, d) = self.frame.ray(u, v);
        let (t0, t1) = ray_interval(self.scene.geometry, self.settings, o, d)?;
        let f = self.frame;
        Some((
            (t0.max(0.0) - f.t_front) / f.spacing_mm,
            (t1.max(0.0) - f.t_front) / f.spacing_mm,
        ))
    }
}

struct Optics<'a> {
    kind: AdaptiveOptics<'a>,
    /// MIP (`RenderMode::Mip`): the transcription keeps maxima, coloured below.
    mip: bool,
    /// Shaded DVR: the shading, the frame (each level-0 pixel's ray direction), the inverse
    /// transpose map from index to patient gradients and the flatness scale, as reference.rs
    /// lights a sample.
    shading: Option<(crate::model::settings::Shading, &'a SliceFrame, DMat3, f64)>,
    tf: &'a crate::model::transfer_function::TransferFunction,
    spacing_mm: f64,
    unit_mm: f64,
}

impl SegmentOptics for Optics<'_> {
    fn segment(&self, s_front: f64, s_back: f64, slices: u32) -> [f64; 4] {
        let length = slices as f64 * self.spacing_mm;
        match self.kind {
            AdaptiveOptics::Exact { substeps_per_slice } => integrate_segment(
                self.tf,
                s_front,
                s_back,
                length,
                self.unit_mm,
                substeps_per_slice.max(1) * slices as usize,
            )
            .map(|c| c as f64),
            AdaptiveOptics::Table(table) => table.segment(s_front, s_back, length),
        }
    }

    fn maximum_intensity(&self) -> bool {
        self.mip
    }

    fn shaded(&self) -> bool {
        self.shading.is_some()
    }

    /// reference.rs `shade` of the segment's colour (un-premultiplied) at the gradient, along
    /// the level-0 pixel's ray; opacity unchanged.
    fn shade(&self, rgba: [f64; 4], gradient: [f64; 3], x: u32, y: u32) -> [f64; 4] {
        let Some((shading, frame, patient_from_index_gradient, flatness_scale)) = &self.shading
        else {
            return rgba;
        };
        let (_, dir) = frame.ray(x as f64, y as f64);
        let g = *patient_from_index_gradient * DVec3::from(gradient);
        let a = rgba[3];
        let lit = shade(
            [rgba[0] / a, rgba[1] / a, rgba[2] / a],
            g,
            dir,
            shading,
            *flatness_scale,
        );
        [lit[0] * a, lit[1] * a, lit[2] * a, a]
    }

    /// The TF at one value, as the raycaster's MIP colours its maximum: exactly, or through
    /// the table as the GPU pass does (a segment of one opacity unit is the TF's own opacity
    /// and colour, up to the table's interpolation).
    fn point(&self, s: f64) -> [f64; 4] {
        match self.kind {
            AdaptiveOptics::Exact { .. } => {
                let (c, a) = (self.tf.color_at(s), self.tf.opacity_at(s));
                [c[0] * a, c[1] * a, c[2] * a, a]
            }
            AdaptiveOptics::Table(table) => table.segment(s, s, self.unit_mm),
        }
    }
}

/// The adaptive frame of `settings` on the CPU (DVR, shaded as `settings` says, or MIP: the TF's colour and
/// opacity at each pixel's maximum, premultiplied, the pick depth at the maximum). `oracle_table` is per page
/// entry (oracle.rs) with [`OracleKind::PerNode`], per slot and block (block_oracle.rs) with
/// [`OracleKind::PerBlock`], and not read otherwise.
pub fn render_adaptive_reference<S: BrickSource>(
    scene: &ReferenceScene<S>,
    camera: &crate::model::camera::Camera,
    settings: &RenderSettings,
    config: &AdaptiveConfig,
    oracle_table: &[f32],
    optics: AdaptiveOptics,
) -> Result<AdaptiveReference, RenderError> {
    settings.validate()?;
    config.validate()?;
    scene.geometry.validate()?;
    scene.page_table.check_against(scene.geometry.page_dims())?;
    let frame = SliceFrame::new(scene.geometry, settings, camera, config.l_max);
    let probe = SceneProbe {
        scene,
        settings,
        frame: &frame,
        masks: settings
            .smooth_transitions
            .then(|| transition_masks(scene.page_table)),
        config: *config,
        oracle_table,
    };
    let mip = match settings.mode {
        crate::model::settings::RenderMode::Dvr => false,
        crate::model::settings::RenderMode::Mip => true,
        other => {
            return Err(RenderError::InvalidSettings(format!(
                "the adaptive pass renders DVR and MIP, not {other:?}"
            )))
        }
    };
    let g = scene.geometry;
    let shading = (!mip)
        .then(|| settings.effective_shading())
        .flatten()
        .map(|shading| {
            let flatness_scale = scene.mapping.slope.abs() * g.finest_spacing_mm()
                / (scene.tf_range.1 - scene.tf_range.0).max(1e-30);
            (
                shading,
                &frame,
                g.index_from_patient_linear().transpose(),
                flatness_scale,
            )
        });
    let optics = Optics {
        kind: optics,
        mip,
        shading,
        tf: scene.transfer_function,
        spacing_mm: frame.spacing_mm,
        unit_mm: scene.geometry.finest_spacing_mm(),
    };
    // The tile's decisions, as the GPU pass takes them (gpu.rs): early termination from the
    // settings; slice ranges only with a data oracle and a transparent default value.
    let data_oracle = matches!(config.oracle, OracleKind::PerNode | OracleKind::PerBlock);
    let rules = TileRules {
        tile: config.tile,
        early_termination: settings.early_termination.map(|t| t as f64),
        slice_ranges: data_oracle
            && config.tile_slice_ranges
            && scene.transfer_function.opacity_at(scene.tf_range.0) <= 0.0,
    };
    let transcription = project_volume_tiled(frame.dims, frame.last_slice, rules, &probe, &optics);
    let (w, h) = frame.viewport;
    let pw = frame.dims.width as usize;
    let mut rgba_f64 = Vec::with_capacity((w * h) as usize);
    let mut depth = Vec::with_capacity((w * h) as usize);
    for y in 0..h as usize {
        for x in 0..w as usize {
            let k = y * pw + x;
            rgba_f64.push(transcription.rgba[k]);
            let slices = transcription.depth_slices[k];
            depth.push(if slices.is_finite() {
                (frame.t_front + slices * frame.spacing_mm) as f32
            } else {
                f32::INFINITY
            });
        }
    }
    let rgba = rgba_f64
        .iter()
        .flat_map(|c| c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
        .collect();
    Ok(AdaptiveReference {
        frame,
        transcription,
        rgba_f64,
        rgba,
        depth,
    })
}
