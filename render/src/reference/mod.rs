//! The f64 CPU reference: ground truth for every image test. It integrates the field of
//! field.rs over the same page table and bricks the GPU sees (so mixed-level cuts match), with the
//! same camera, transfer function, compositing and opacity correction, but with a much smaller
//! step, no jitter, and without trusting the empty flags (it samples everything resident).
//! Written to be obviously correct, not fast.

pub mod metrics;

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::error::RenderError;
use crate::gpu::light_cache;
use crate::model::ambient_occlusion;
pub use crate::model::blinn_phong::{shade, smoothstep};
use crate::model::camera::{Camera, CameraBasis};
use crate::model::field::{sample_field, FieldSample};
use crate::model::layout::{BrickSource, DEPTH_OPACITY};
use crate::model::overlay::{blend, OverlayScene};
use crate::model::page_table::PageTable;
use crate::model::scattering::shade_cinematic;
use crate::model::settings::{RenderMode, RenderSettings, Shading};
use crate::model::shadows::{
    extinction, light_towards, shade_lit, transmittance, REFERENCE_SHADOW_REFINEMENT,
    REFERENCE_TAU_MAX, SHADOW_START_VOXELS,
};
use crate::model::smooth_transitions::transition_masks;
use crate::model::transfer_function::TransferFunction;
use strata_types::{ValueMapping, VolumeGeometry};

/// Everything that defines the field and its optics, independent of any GPU object.
pub struct ReferenceScene<'a, S: BrickSource> {
    pub source: &'a S,
    pub page_table: &'a PageTable,
    pub geometry: &'a VolumeGeometry,
    pub mapping: ValueMapping,
    pub transfer_function: &'a TransferFunction,
    /// Physical range the GPU table spans; the shading guard is relative to it.
    pub tf_range: (f64, f64),
}

#[derive(Clone, Debug)]
pub struct ReferenceImage {
    pub width: u32,
    pub height: u32,
    /// Premultiplied RGBA over transparent black, rounded to 8 bits like the GPU's unorm store.
    pub rgba: Vec<u8>,
    pub rgba_f64: Vec<[f64; 4]>,
    /// Pick depth (mm along the ray): DVR where accumulated opacity reaches
    /// [`DEPTH_OPACITY`], the iso hit, the MIP maximum; +inf if none.
    pub depth: Vec<f32>,
}

/// [t_start, t_end] of the ray inside the (cropped) volume box and the clip plane's half space.
pub fn ray_interval(
    geometry: &VolumeGeometry,
    settings: &RenderSettings,
    origin: DVec3,
    dir: DVec3,
) -> Option<(f64, f64)> {
    let a = geometry.index_from_patient_linear();
    let o = a * (origin - geometry.origin());
    let d = a * dir;
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for axis in 0..3 {
        let n = geometry.dims[axis] as f64;
        let lo = -0.5 + settings.crop.min[axis] as f64 * n;
        let hi = -0.5 + settings.crop.max[axis] as f64 * n;
        if d[axis].abs() < 1e-12 {
            if o[axis] < lo || o[axis] > hi {
                return None;
            }
        } else {
            let (ta, tb) = ((lo - o[axis]) / d[axis], (hi - o[axis]) / d[axis]);
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
    }
    if let Some(p) = &settings.clip_plane {
        // Non-zero: RenderSettings::validate refuses a zero clip normal.
        let n = DVec3::from(p.normal).normalize_or_zero();
        let (no, nd) = (n.dot(origin), n.dot(dir));
        if nd.abs() < 1e-12 {
            if no < p.offset_mm {
                return None;
            }
        } else {
            let tc = (p.offset_mm - no) / nd;
            if nd > 0.0 {
                t0 = t0.max(tc);
            } else {
                t1 = t1.min(tc);
            }
        }
    }
    (t1 > t0).then_some((t0, t1))
}

/// Settings for the reference itself.
#[derive(Clone, Copy, Debug)]
pub struct ReferenceOptions {
    /// Reference step = GPU base step / this.
    pub step_refinement: f64,
    /// Bisection iterations for the isosurface.
    pub bisection_steps: u32,
}

impl Default for ReferenceOptions {
    fn default() -> Self {
        ReferenceOptions {
            step_refinement: 8.0,
            bisection_steps: 40,
        }
    }
}

pub fn render_reference<S: BrickSource>(
    scene: &ReferenceScene<S>,
    camera: &Camera,
    settings: &RenderSettings,
    options: ReferenceOptions,
) -> Result<ReferenceImage, RenderError> {
    render_reference_with_overlay(scene, None, camera, settings, options)
}

/// [`render_reference`] with an overlay drawn in 3D (overlay.rs: its sampling and blend rule,
/// the same the shader applies).
pub fn render_reference_with_overlay<S: BrickSource>(
    scene: &ReferenceScene<S>,
    overlay: Option<&OverlayScene>,
    camera: &Camera,
    settings: &RenderSettings,
    options: ReferenceOptions,
) -> Result<ReferenceImage, RenderError> {
    settings.validate()?;
    scene.geometry.validate()?;
    scene.page_table.check_against(scene.geometry.page_dims())?;
    let basis = camera.basis();
    let (w, h) = (settings.width, settings.height);
    let masks = settings
        .smooth_transitions
        .then(|| transition_masks(scene.page_table));
    let masks = masks.as_deref();
    let cache = settings
        .effective_light_cache()
        .then(|| light_cache_grid(scene, masks, settings, &basis));
    let cache = cache.as_deref();
    let pixels: Vec<([f64; 4], f32)> = (0..h)
        .into_par_iter()
        .flat_map_iter(|py| {
            (0..w).map(move |px| {
                let (origin, dir) = basis.ray(px, py, w, h);
                trace(
                    scene, overlay, masks, cache, settings, &options, &basis, origin, dir,
                )
            })
        })
        .collect();
    let rgba = pixels
        .iter()
        .flat_map(|(c, _)| c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8))
        .collect();
    Ok(ReferenceImage {
        width: w,
        height: h,
        rgba,
        rgba_f64: pixels.iter().map(|p| p.0).collect(),
        depth: pixels.iter().map(|p| p.1).collect(),
    })
}

/// The light cache in f64 (light_cache.rs): the GPU's sweep, its rays at the reference's
/// shadow step; texels x fastest, as the GPU's (`Raycaster::read_light_cache_blocking`).
pub fn reference_light_cache<S: BrickSource>(
    scene: &ReferenceScene<S>,
    camera: &Camera,
    settings: &RenderSettings,
) -> Vec<f64> {
    let masks = settings
        .smooth_transitions
        .then(|| transition_masks(scene.page_table));
    light_cache_grid(scene, masks.as_deref(), settings, &camera.basis())
}

fn light_cache_grid<S: BrickSource>(
    scene: &ReferenceScene<S>,
    masks: Option<&[u32]>,
    settings: &RenderSettings,
    basis: &CameraBasis,
) -> Vec<f64> {
    let g = scene.geometry;
    let a: DMat3 = g.index_from_patient_linear();
    let unit = g.finest_spacing_mm();
    let res = settings.shadows.cache_res;
    let n = light_cache::grid_dims(g.dims, res);
    // Cache mode needs a directional light (validate), whose direction is the same for every
    // ray: the view axis stands in for the ray.
    let light = light_towards(&settings.light, basis, basis.forward);
    let l_idx = a * light;
    let shadow_step = settings.shadows.step * unit / REFERENCE_SHADOW_REFINEMENT;
    let (tf, mapping) = (scene.transfer_function, scene.mapping);
    let sigma = |q: DVec3| {
        sample_field(scene.source, scene.page_table, masks, g.dims, q).map_or(0.0, |loc| {
            extinction(tf.opacity_at(mapping.physical(loc.value)), unit)
        })
    };
    // The GPU's sweep (shadows.wgsl `build_light_cache`), slice by slice from the light's
    // side; the axis is chosen from the same f32 direction the GPU has.
    let order = light_cache::sweep_order([l_idx.x as f32, l_idx.y as f32, l_idx.z as f32], n);
    let axis = order.axis as usize;
    let (b, c) = ((axis + 1) % 3, (axis + 2) % 3);
    let dt = res / l_idx[axis].abs();
    let mut values = vec![1.0f64; n.iter().map(|&d| d as usize).product()];
    for (k, &slice) in order.slices.iter().enumerate() {
        let previous = if l_idx[axis] >= 0.0 {
            slice + 1
        } else {
            slice.wrapping_sub(1)
        };
        let across = order.across[0] as usize * order.across[1] as usize;
        let done = &values;
        let slice_values: Vec<(usize, f64)> = (0..across)
            .into_par_iter()
            .map(|j| {
                let mut i = [0u32; 3];
                i[axis] = slice;
                i[b] = (j % order.across[0] as usize) as u32;
                i[c] = (j / order.across[0] as usize) as u32;
                let p_idx = light_cache::texel_centre(i, res);
                let index = light_cache::texel_index(i, n);
                let Some((t0, t1)) = ray_interval(g, settings, g.patient_from_index(p_idx), light)
                else {
                    return (index, 1.0);
                };
                let on_ray = |s: f64| sigma(p_idx + l_idx * s);
                if k == 0 {
                    return (
                        index,
                        transmittance(t0, t1, shadow_step, REFERENCE_TAU_MAX, on_ray),
                    );
                }
                let v = transmittance(t0, t1.min(dt), shadow_step, REFERENCE_TAU_MAX, on_ray);
                if t1 > dt {
                    let q = p_idx + l_idx * dt;
                    let before = light_cache::interpolate_in_slice(done, n, res, q, axis, previous);
                    (index, v * before)
                } else {
                    (index, v)
                }
            })
            .collect();
        for (index, v) in slice_values {
            values[index] = v;
        }
    }
    values
}

#[allow(clippy::too_many_arguments)]
fn trace<S: BrickSource>(
    scene: &ReferenceScene<S>,
    overlay: Option<&OverlayScene>,
    masks: Option<&[u32]>,
    cache: Option<&[f64]>,
    settings: &RenderSettings,
    options: &ReferenceOptions,
    basis: &CameraBasis,
    origin: DVec3,
    dir: DVec3,
) -> ([f64; 4], f32) {
    let Some((t0, t1)) = ray_interval(scene.geometry, settings, origin, dir) else {
        return ([0.0; 4], f32::INFINITY);
    };
    let g = scene.geometry;
    let a: DMat3 = g.index_from_patient_linear();
    let o_idx = a * (origin - g.origin());
    let d_idx = a * dir;
    let unit = g.finest_spacing_mm();
    let step = settings.quality * unit / options.step_refinement;
    let tf = scene.transfer_function;
    let mapping = scene.mapping;
    let flatness_scale =
        mapping.slope.abs() * unit / (scene.tf_range.1 - scene.tf_range.0).max(1e-30);
    let shading = settings.effective_shading();
    let at = |t: f64| {
        sample_field(
            scene.source,
            scene.page_table,
            masks,
            g.dims,
            o_idx + d_idx * t,
        )
    };
    // Physical gradient per mm: d(value)/d(patient) = A^T · d(value)/d(index).
    // The overlay's colour and opacity at ray distance t (none: nothing drawn).
    let overlay_at = |t: f64| overlay.map_or([0.0; 4], |o| o.colour_at(o_idx + d_idx * t));
    let gradient_patient = |s: &FieldSample| a.transpose() * s.gradient_index() * mapping.slope;
    // The key light and its shadows (shadows.rs, the model both renderers follow); with the
    // default headlight and no shadows the old `shade`, so default images are unchanged.
    let key_light = settings.effective_key_light();
    let light = light_towards(&settings.light, basis, dir);
    let l_idx = a * light;
    let shadow_step = settings.shadows.step * unit / REFERENCE_SHADOW_REFINEMENT;
    // V at ray distance t: an exact shadow ray through the same field (module doc of
    // shadows.rs for its cost), transparent where nothing is resident.
    let cache_res = settings.shadows.cache_res;
    let cache_dims = light_cache::grid_dims(g.dims, cache_res);
    let cache_offset = cache_res * unit * light_cache::LOOKUP_OFFSET_CELLS;
    let visibility = |t: f64| -> f64 {
        if let Some(values) = cache {
            let q = o_idx + d_idx * t + l_idx * cache_offset;
            return light_cache::interpolate(values, cache_dims, cache_res, q);
        }
        if !settings.effective_shadows() {
            return 1.0;
        }
        let p = origin + dir * t;
        let Some((_, r1)) = ray_interval(g, settings, p, light) else {
            return 1.0;
        };
        let p_idx = o_idx + d_idx * t;
        transmittance(
            SHADOW_START_VOXELS * unit,
            r1,
            shadow_step,
            REFERENCE_TAU_MAX,
            |s| {
                sample_field(
                    scene.source,
                    scene.page_table,
                    masks,
                    g.dims,
                    p_idx + l_idx * s,
                )
                .map_or(0.0, |loc| {
                    extinction(tf.opacity_at(mapping.physical(loc.value)), unit)
                })
            },
        )
    };
    // Ambient occlusion (ambient_occlusion.rs) at ray distance t: its rays at the reference's
    // shadow step, ending where they leave the cropped box or the clip half-space.
    let occlusion = settings.effective_occlusion();
    let scattering = settings.effective_scattering();
    let ambient_occlusion = |t: f64| -> f64 {
        let Some(o) = occlusion else { return 1.0 };
        let p = origin + dir * t;
        let p_idx = o_idx + d_idx * t;
        ambient_occlusion::occlusion(
            o.radius_mm,
            SHADOW_START_VOXELS * unit,
            shadow_step,
            REFERENCE_TAU_MAX,
            |nu| ray_interval(g, settings, p, nu).map_or(0.0, |(_, r1)| r1),
            |nu, s| {
                sample_field(
                    scene.source,
                    scene.page_table,
                    masks,
                    g.dims,
                    p_idx + (a * nu) * s,
                )
                .map_or(0.0, |loc| {
                    extinction(tf.opacity_at(mapping.physical(loc.value)), unit)
                })
            },
        )
    };
    let lit = |col: [f64; 3], loc: &FieldSample, t: f64, s: &Shading| -> [f64; 3] {
        if occlusion.is_some() || scattering.is_some() {
            shade_cinematic(
                col,
                gradient_patient(loc),
                dir,
                light,
                s,
                settings.light.intensity as f64,
                visibility(t),
                flatness_scale,
                ambient_occlusion(t),
                scattering.as_ref(),
            )
        } else if key_light {
            shade_lit(
                col,
                gradient_patient(loc),
                dir,
                light,
                s,
                settings.light.intensity as f64,
                visibility(t),
                flatness_scale,
            )
        } else {
            shade(col, gradient_patient(loc), dir, s, flatness_scale)
        }
    };
    let n_steps = ((t1 - t0) / step).ceil() as u64;
    // Segment k is [t0 + k·step, t0 + (k+1)·step) cut at t1, sampled at its midpoint; the
    // last one is usually shorter and absorbs only for its own length (a grazing ray through
    // a box corner still sees what it passes).
    let segment = |k: u64| -> Option<(f64, f64)> {
        let start = t0 + k as f64 * step;
        (start < t1).then(|| {
            let length = step.min(t1 - start);
            (start + 0.5 * length, length)
        })
    };
    match settings.mode {
        RenderMode::Dvr => {
            let (mut c, mut alpha, mut depth) = ([0.0f64; 3], 0.0f64, f32::INFINITY);
            for k in 0..n_steps {
                let Some((t, length)) = segment(k) else { break };
                let Some(loc) = at(t) else { continue };
                let v = mapping.physical(loc.value);
                let (mut col, op) = blend(tf.color_at(v), tf.opacity_at(v), overlay_at(t));
                if op <= 0.0 {
                    continue;
                }
                let op = 1.0 - (1.0 - op).powf(length / unit);
                if let Some(s) = &shading {
                    col = lit(col, &loc, t, s);
                }
                let wgt = (1.0 - alpha) * op;
                for i in 0..3 {
                    c[i] += wgt * col[i];
                }
                alpha += wgt;
                // The pick depth: where the accumulated opacity reaches DEPTH_OPACITY.
                if depth.is_infinite() && alpha >= DEPTH_OPACITY {
                    depth = t as f32;
                }
                if let Some(th) = settings.early_termination {
                    if alpha >= th as f64 {
                        break;
                    }
                }
            }
            ([c[0], c[1], c[2], alpha], depth)
        }
        RenderMode::Mip => {
            let mut best: Option<(f64, f64)> = None;
            for k in 0..n_steps {
                let Some((t, _)) = segment(k) else { break };
                let Some(loc) = at(t) else { continue };
                let v = mapping.physical(loc.value);
                if best.is_none_or(|(bv, _)| v > bv) {
                    best = Some((v, t));
                }
            }
            match best {
                Some((v, t)) => {
                    // The overlay projected too: its first shown sample on the ray.
                    let first_shown = (0..n_steps)
                        .map_while(&segment)
                        .map(|(t, _)| overlay_at(t))
                        .find(|c| c[3] > 0.0)
                        .unwrap_or([0.0; 4]);
                    let (col, op) = blend(tf.color_at(v), tf.opacity_at(v), first_shown);
                    let depth = if op > 0.0 { t as f32 } else { f32::INFINITY };
                    ([col[0] * op, col[1] * op, col[2] * op, op], depth)
                }
                None => ([0.0; 4], f32::INFINITY),
            }
        }
        RenderMode::Isosurface => {
            let iso = settings.iso_value;
            let value = |t: f64| at(t).map(|loc| mapping.physical(loc.value));
            let mut prev: Option<f64> = None;
            for k in 0..n_steps {
                let Some((t, _)) = segment(k) else { break };
                let Some(v) = value(t) else {
                    prev = None;
                    continue;
                };
                if v >= iso {
                    let mut hit = t;
                    if let Some(tp) = prev {
                        let (mut lo, mut hi) = (tp, t);
                        for _ in 0..options.bisection_steps {
                            let mid = 0.5 * (lo + hi);
                            if value(mid).is_some_and(|m| m >= iso) {
                                hi = mid;
                            } else {
                                lo = mid;
                            }
                        }
                        hit = hi;
                    }
                    let Some(loc) = at(hit) else { break };
                    let surface = tf.color_at(iso);
                    let o = overlay_at(hit);
                    let surface = [0, 1, 2].map(|i| surface[i] + (o[i] - surface[i]) * o[3]);
                    let col = lit(surface, &loc, hit, &shading.unwrap_or_default());
                    return ([col[0], col[1], col[2], 1.0], hit as f32);
                }
                prev = Some(t);
            }
            ([0.0; 4], f32::INFINITY)
        }
    }
}
