//! Volumetric shadows from the key light, cache mode (issue 37, step 1, the fast mode): the
//! transmittance towards the light on a low-resolution grid, built on the GPU from the
//! resident cut for the current TF and light, read with one trilinear lookup per shaded
//! sample instead of a shadow ray.
//!
//! **Model** (shadows.rs for the lighting it plugs V into). The grid has one texel per `res`
//! finest voxels ([`crate::Shadows::cache_res`]): texel i of an axis of n voxels sits at index
//! position (i + ½)·res − ½, ⌈n/res⌉ texels per axis (voxel centres at integers, the volume box
//! [−½, n − ½]). The build sweeps the grid slice by slice along the index axis `a` most aligned
//! with the light (|l_a| ≥ |l|/√3), starting with the slice nearest the light:
//!
//! ```text
//! first slice:  V_i = T(p_i; 0, exit)
//! later slices: V_i = T(p_i; 0, Δt) · bilinear{V of the slice before}(p_i + ω_l·Δt),
//!               Δt = res / |l_a| mm (the ray from p_i reaches that slice's plane),
//!               or T(p_i; 0, exit) alone where the ray leaves first
//! ```
//!
//! T(p; r, s) is the exact mode's shadow ray (shadows.rs: midpoint samples at
//! [`crate::Shadows::step`] through the resident cut, the GPU's optical-depth limit) over
//! [r, s], starting no earlier than where it enters the cropped box and the clip plane's
//! half-space (a texel centre may lie outside them, and cut-away matter casts no shadow; a ray
//! that never enters them has V = 1). There is no shadow bias r₀ (a texel's segments tile its
//! whole ray); the lookup offset below does its work. Each slice costs a segment of at most
//! res·√3 voxels per texel plus 4 fetches, so a build is O(texels) against O(texels · N) for a
//! full shadow ray per texel (the first version of this module: 8.6 s against 0.73 s below,
//! and further from exact: 40.1 against 44.7 dB in the phantom test). The price is diffusion:
//! each slice's bilinear step blurs a shadow's edge a little more with distance from the
//! occluder (over about √(slices) · ½ cell).
//!
//! A shaded sample at x reads
//!
//! ```text
//! V(x) = trilinear{V_i}(x + ω_l · res · unit · LOOKUP_OFFSET_CELLS)   (clamped to the grid)
//! ```
//!
//! The lookup is moved towards the light by [`LOOKUP_OFFSET_CELLS`] cells because the texels
//! around a surface sample lie half inside the surface: their rays cross up to a cell of the
//! surface's own matter and would darken every lit surface (shadow acne, a cell wide). The
//! offset trades that for contact shadows: an occluder closer than about a cell to the sample
//! along ω_l casts a weaker or no shadow, and a shadow's edge is blurred over about a cell
//! (the reason the tests' bounds against exact shadows are looser than exact's own).
//!
//! **What invalidates a built cache** ([`LightCacheKey`]): the light's direction (in index
//! space; not its intensity, which scales V outside the cache), the shadow step, the cache
//! resolution, the TF (table, range, entries) and value mapping, the crop box, the clip plane,
//! the page table's contents (the cut: [`crate::GpuPageTable`] counts its writes) and the
//! pipeline effects that change the sampled field (manual trilinear, smooth transitions, the
//! traversal, empty skipping). The camera does not: with a camera-relative light, a camera
//! move turns ω_l and so rebuilds; with a patient-relative light it does not. Bricks written
//! into cache slots without a page-table write that points at them do not invalidate it: the
//! loader only makes a brick visible through the table. Rebuilds are whole, not per brick.
//!
//! **Empty bricks.** A segment's march skips empty and not-resident pages as the main ray
//! does (a page lookup, no field or TF fetch). Texels in empty space are still swept: the
//! shadow behind an occluder reaches a lit surface through the air between them.
//!
//! **Reference.** reference.rs runs the same sweep in f64 (segments at the reference's refined
//! shadow step, no empty skipping, the same axis and slice order) and interpolates the same
//! way: O(texels) shadow segments however large the image is.
//!
//! **GPU cost.** `STRATA_BENCH_EFFECTS=shadows,shading STRATA_BENCH_SIZE=256
//! STRATA_BENCH_FRAMES=3 cargo bench -p strata-render --bench raycast --profile dev` (256³
//! VTK-peer phantom, 256², DVR step 0.5, shaded, key light (0.5, 0.5, 0.7) camera-relative,
//! empty skipping and early termination on, shadow step 1 voxel), lavapipe on the shared
//! 2-core machine, 2026-12-05, one run (the machine's load moves the base between runs:
//! compare ratios within a run): unshadowed 696-702 ms, exact shadows 9008 ms (12.8×), cache
//! at 2 voxels per texel 855 ms (1.23×; never built 756 ms, noise), its build (128³ texels, a
//! frame that rebuilds against the next that does not) 0.71 s: about one unshadowed frame,
//! under a twelfth of one exact frame, so the cache pays from its first frame. The ray-per-
//! texel build it replaced took 8.6 s in an earlier, less loaded run (cache 1.29×, unshadowed
//! 426 ms); with `STRATA_BENCH_LIGHT_CACHE_RES=4` (64³ texels) that build took 1.4 s and the
//! lookup 1.19×.

use glam::DVec3;

use crate::model::settings::CropBox;
use crate::model::transfer_function::TransferFunction;

// The valid resolutions live with the settings that validate them (settings.rs), which must
// not depend on this module (it depends on the pipelines, which depend on the settings).
pub use crate::model::settings::{LIGHT_CACHE_MAX_RES as MAX_RES, LIGHT_CACHE_MIN_RES as MIN_RES};
/// The lookup is moved this many cells towards the light (module doc: acne vs contact shadows).
pub const LOOKUP_OFFSET_CELLS: f64 = 1.0;
/// The sweep kernel's workgroup edge (8² texels of a slice).
pub const SWEEP_WORKGROUP: u32 = 8;

/// The order of the build's sweep: along `axis`, the index-space axis the light's direction
/// `l` (index-space image of the unit direction towards the light) is most aligned with, the
/// slices from the light's side; `across` the texel counts of the axes after it (axis + 1,
/// axis + 2, mod 3), which a slice's dispatch spans.
pub struct SweepOrder {
    pub axis: u32,
    pub slices: Vec<u32>,
    pub across: [u32; 2],
}

pub fn sweep_order(l: [f32; 3], n: [u32; 3]) -> SweepOrder {
    let axis = (0..3)
        .max_by(|&a, &b| l[a].abs().total_cmp(&l[b].abs()))
        .unwrap_or(0);
    let slices: Vec<u32> = if l[axis] >= 0.0 {
        (0..n[axis]).rev().collect()
    } else {
        (0..n[axis]).collect()
    };
    SweepOrder {
        axis: axis as u32,
        slices,
        across: [n[(axis + 1) % 3], n[(axis + 2) % 3]],
    }
}

/// Texels per axis for a volume of `dims` voxels at `res` voxels per texel.
pub fn grid_dims(dims: [u32; 3], res: f64) -> [u32; 3] {
    dims.map(|n| ((n as f64 / res).ceil() as u32).max(1))
}

/// Index-space centre of texel `i`.
pub fn texel_centre(i: [u32; 3], res: f64) -> DVec3 {
    DVec3::new(i[0] as f64, i[1] as f64, i[2] as f64) * res + DVec3::splat(0.5 * res - 0.5)
}

/// The linear index of texel `i` (x fastest), as the shader stores it.
pub fn texel_index(i: [u32; 3], n: [u32; 3]) -> usize {
    i[0] as usize + n[0] as usize * (i[1] as usize + n[1] as usize * i[2] as usize)
}

/// Trilinear interpolation of the grid `values` (n texels, `res` voxels each) at index-space
/// point `q`, clamped to the texel centres: the shader's `light_cache_visibility`.
pub fn interpolate(values: &[f64], n: [u32; 3], res: f64, q: DVec3) -> f64 {
    let mut i0 = [0u32; 3];
    let mut i1 = [0u32; 3];
    let mut f = [0.0f64; 3];
    for a in 0..3 {
        let hi = (n[a] - 1) as f64;
        let u = ((q[a] + 0.5) / res - 0.5).clamp(0.0, hi);
        let fl = u.floor();
        i0[a] = fl as u32;
        i1[a] = (i0[a] + 1).min(n[a] - 1);
        f[a] = u - fl;
    }
    let at = |x: u32, y: u32, z: u32| values[texel_index([x, y, z], n)];
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let y0 = lerp(
        lerp(at(i0[0], i0[1], i0[2]), at(i1[0], i0[1], i0[2]), f[0]),
        lerp(at(i0[0], i1[1], i0[2]), at(i1[0], i1[1], i0[2]), f[0]),
        f[1],
    );
    let y1 = lerp(
        lerp(at(i0[0], i0[1], i1[2]), at(i1[0], i0[1], i1[2]), f[0]),
        lerp(at(i0[0], i1[1], i1[2]), at(i1[0], i1[1], i1[2]), f[0]),
        f[1],
    );
    lerp(y0, y1, f[2])
}

/// V of slice `slice` along `axis` at index-space point `q`, bilinear in the two other axes,
/// clamped to the grid: the sweep's step to the slice before (shadows.wgsl
/// `light_cache_previous`).
pub fn interpolate_in_slice(
    values: &[f64],
    n: [u32; 3],
    res: f64,
    q: DVec3,
    axis: usize,
    slice: u32,
) -> f64 {
    let (b, c) = ((axis + 1) % 3, (axis + 2) % 3);
    let mut i0 = [0u32; 3];
    let mut f = [0.0f64; 3];
    for a in 0..3 {
        let u = ((q[a] + 0.5) / res - 0.5).clamp(0.0, (n[a] - 1) as f64);
        i0[a] = u.floor() as u32;
        f[a] = u - u.floor();
    }
    i0[axis] = slice;
    let mut i1 = i0.map(|_| 0);
    for a in 0..3 {
        i1[a] = (i0[a] + 1).min(n[a] - 1);
    }
    i1[axis] = slice;
    let (mut ib, mut ic) = (i0, i0);
    ib[b] = i1[b];
    ic[c] = i1[c];
    let at = |i: [u32; 3]| values[texel_index(i, n)];
    let lerp = |x: f64, y: f64, t: f64| x + (y - x) * t;
    lerp(lerp(at(i0), at(ib), f[b]), lerp(at(ic), at(i1), f[b]), f[c])
}

/// Everything a built cache depends on (module doc); a frame whose key differs rebuilds it.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct LightCacheKey {
    /// Which page table and how many writes it had seen.
    pub page_table: (u64, u64),
    pub transfer_function: TransferFunction,
    pub tf_range: (f64, f64, u32),
    pub mapping: (f64, f64),
    /// The frame's `GpuLight`: direction in index space, shadow step, bias, depth limit.
    pub light_idx: [f32; 3],
    pub shadow: [f32; 4],
    pub res: f64,
    pub dims: [u32; 3],
    pub crop: CropBox,
    pub clip_idx: Option<[f32; 4]>,
    /// The build pipeline's effects (manual trilinear, smooth transitions, octree, ...).
    pub pipeline: crate::gpu::pipelines::PipelineKey,
}

/// The cache on the GPU: a storage buffer of f32 texels (binding 16), what it was built from,
/// and how often it was built (tests count rebuilds).
pub(crate) struct GpuLightCache {
    pub buffer: wgpu::Buffer,
    capacity_bytes: u64,
    key: Option<LightCacheKey>,
    pub builds: u64,
}

impl GpuLightCache {
    /// A one-texel stand-in, bound while no pipeline reads the cache.
    pub fn new(device: &wgpu::Device) -> Self {
        GpuLightCache {
            buffer: Self::buffer(device, 16),
            capacity_bytes: 16,
            key: None,
            builds: 0,
        }
    }

    fn buffer(device: &wgpu::Device, bytes: u64) -> wgpu::Buffer {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("light cache"),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        })
    }

    /// Whether a frame with `key` must build the cache first; makes the buffer large enough
    /// for `bytes` (a new buffer is unbuilt). The key is recorded as built: the caller encodes
    /// the build in the same submission as the frame that reads it.
    pub fn needs_build(&mut self, device: &wgpu::Device, key: &LightCacheKey, bytes: u64) -> bool {
        if bytes > self.capacity_bytes {
            self.buffer = Self::buffer(device, bytes.next_power_of_two());
            self.capacity_bytes = bytes.next_power_of_two();
            self.key = None;
        }
        if self.key.as_ref() == Some(key) {
            return false;
        }
        self.key = Some(key.clone());
        self.builds += 1;
        true
    }
}

impl GpuLightCache {
    /// The texels of the last build (x fastest; empty if none was built), read back blocking:
    /// for tests that compare them with the f64 reference's.
    pub fn read_blocking(
        &self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
    ) -> Result<Vec<f32>, crate::error::RenderError> {
        let Some(key) = &self.key else {
            return Ok(Vec::new());
        };
        let n = grid_dims(key.dims, key.res);
        let bytes = n.iter().map(|&d| d as u64).product::<u64>() * 4;
        let readback = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("light cache readback"),
            size: bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("light cache readback"),
        });
        encoder.copy_buffer_to_buffer(&self.buffer, 0, &readback, 0, bytes);
        queue.submit(Some(encoder.finish()));
        crate::gpu::device::map_blocking(device, &readback)?;
        let bytes = readback
            .get_mapped_range(..)
            .map_err(|e| crate::error::RenderError::Readback(e.to_string()))?
            .to_vec();
        readback.unmap();
        let texels = bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        Ok(texels)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texel_centres_tile_the_volume_box() {
        // 10 voxels at 4 per texel: 3 texels whose cells [−½ + 4i, −½ + 4(i+1)] cover [−½, 9½].
        assert_eq!(grid_dims([10, 8, 1], 4.0), [3, 2, 1]);
        assert_eq!(texel_centre([0, 1, 2], 4.0), DVec3::new(1.5, 5.5, 9.5));
        assert_eq!(grid_dims([7, 7, 7], 1.0), [7, 7, 7]);
        assert_eq!(texel_centre([3, 0, 6], 1.0), DVec3::new(3.0, 0.0, 6.0));
    }

    #[test]
    fn interpolation_hits_texels_and_is_linear_between_them() {
        let n = [3, 2, 2];
        let values: Vec<f64> = (0..12)
            .map(|k| {
                let (x, y, z) = (k % 3, (k / 3) % 2, k / 6);
                1.0 + 2.0 * x as f64 + 3.0 * y as f64 - 0.5 * z as f64
            })
            .collect();
        let res = 2.0;
        for k in 0..12u32 {
            let i = [k % 3, (k / 3) % 2, k / 6];
            let v = interpolate(&values, n, res, texel_centre(i, res));
            assert!((v - values[k as usize]).abs() < 1e-12);
        }
        // Halfway between texels x = 0 and 1 at y = z = 0: the mean; beyond the last centre: clamped.
        let q = (texel_centre([0, 0, 0], res) + texel_centre([1, 0, 0], res)) * 0.5;
        assert!((interpolate(&values, n, res, q) - 2.0).abs() < 1e-12);
        let far = DVec3::new(100.0, -100.0, 0.5);
        assert!((interpolate(&values, n, res, far) - 5.0).abs() < 1e-12);
    }
}
