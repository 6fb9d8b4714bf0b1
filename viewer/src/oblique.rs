//! Oblique reformat: a slice through the crosshair at any orientation, resampled on the CPU
//! from the store's bricks at the level matching the view's pixel size, trilinearly between
//! that level's voxel centres (the same interpolation the raycaster and the f64 reference
//! use). The plane is an orthonormal pair of screen directions in patient space (LPS mm);
//! dragging turns it about its own axes, and "Align to 3D" takes the 3D camera's.
//! Resampling runs on a named thread (`strata-oblique-reader`) through a bounded brick cache.
//! The brush paints a disc in the same plane ([`ObliquePlane::brush_plane`]), and the label
//! overlay is sampled at the same pixel centres (overlay.rs).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};

use glam::{DMat3, DQuat, DVec3};
use strata_render::{Camera, VolumeGeometry};
use strata_segment::tools::brush::SlicePlane;
use strata_source::VolumeSource;
use strata_types::{BrickId, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};

use super::sync::{lock_ignoring_poison, wait_ignoring_poison, Repaint};

/// Decompressed bricks kept for oblique slices (bytes).
pub const OBLIQUE_CACHE_BYTES: usize = 96 << 20;

/// The oblique view's colour: its title, and its plane's outline in the 3D view.
pub const OBLIQUE_COLOUR: egui::Color32 = egui::Color32::from_rgb(200, 140, 255);

/// The plane of an oblique view, in patient space (LPS mm).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ObliquePlane {
    /// Patient position at the image centre (the crosshair).
    pub centre: DVec3,
    /// Unit direction of screen right, and of screen down; orthogonal.
    pub right: DVec3,
    pub down: DVec3,
    /// Side of the square image in mm.
    pub extent_mm: f64,
}

impl ObliquePlane {
    /// The axial plane as the axial view shows it (radiological: patient left on screen
    /// right is +x in LPS, posterior down is +y).
    pub fn axial(centre: DVec3, extent_mm: f64) -> Self {
        ObliquePlane {
            centre,
            right: DVec3::X,
            down: DVec3::Y,
            extent_mm,
        }
    }

    /// Through `centre`, facing like `camera`: screen right and up as the 3D view has them.
    pub fn facing(camera: &Camera, centre: DVec3, extent_mm: f64) -> Self {
        let basis = camera.basis();
        match (basis.right.try_normalize(), basis.up.try_normalize()) {
            (Some(right), Some(up)) => ObliquePlane {
                centre,
                right,
                down: -up,
                extent_mm,
            },
            // A degenerate camera (zero basis): keep a usable plane.
            _ => ObliquePlane::axial(centre, extent_mm),
        }
    }

    /// Normal, towards the viewer's back (right × down).
    pub fn normal(&self) -> DVec3 {
        self.right.cross(self.down)
    }

    /// Turned by `yaw` radians about the screen's vertical axis and `pitch` about its
    /// horizontal one (a drag right turns the plane's right edge away from the viewer).
    pub fn rotated(&self, yaw: f64, pitch: f64) -> Self {
        let turn =
            DQuat::from_axis_angle(self.down, yaw) * DQuat::from_axis_angle(self.right, pitch);
        // Re-orthogonalise: rounding accumulates over many drags.
        let Some(right) = (turn * self.right).try_normalize() else {
            return *self;
        };
        let Some(down) = (turn * self.down - right * right.dot(turn * self.down)).try_normalize()
        else {
            return *self;
        };
        ObliquePlane {
            right,
            down,
            ..*self
        }
    }

    /// Patient position at image fraction (`u` across, `w` down), both 0..1.
    pub fn patient_at(&self, u: f64, w: f64) -> DVec3 {
        self.centre
            + self.right * ((u - 0.5) * self.extent_mm)
            + self.down * ((w - 0.5) * self.extent_mm)
    }

    /// The plane as the brush's disc lies in it: through the centre, spanned by screen right
    /// and down (LPS, orthonormal), so a disc of the brush's size in mm is a circle on screen
    /// whatever the label grid's spacing or orientation.
    pub fn brush_plane(&self) -> SlicePlane {
        SlicePlane::Oblique {
            centre_lps: self.centre,
            u: self.right,
            v: self.down,
        }
    }

    /// Orientation letters at the left, right, top and bottom edges: the patient direction
    /// closest to each screen direction (LPS: +x left, +y posterior, +z superior).
    pub fn labels(&self) -> [&'static str; 4] {
        [
            direction_letter(-self.right),
            direction_letter(self.right),
            direction_letter(-self.down),
            direction_letter(self.down),
        ]
    }
}

/// The anatomical letter of the patient axis closest to `d`.
pub fn direction_letter(d: DVec3) -> &'static str {
    let a = d.abs();
    if a.x >= a.y && a.x >= a.z {
        if d.x > 0.0 {
            "L"
        } else {
            "R"
        }
    } else if a.y >= a.z {
        if d.y > 0.0 {
            "P"
        } else {
            "A"
        }
    } else if d.z > 0.0 {
        "S"
    } else {
        "I"
    }
}

/// One oblique image to resample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ObliqueRequest {
    pub plane: ObliquePlane,
    pub width: usize,
    pub height: usize,
    pub level: u8,
}

/// Stored values (interpolated, so fractional) per pixel, row 0 at the top; NaN outside.
#[derive(Clone, Debug)]
pub struct ObliqueImage {
    pub request: ObliqueRequest,
    pub values: Arc<Vec<f32>>,
}

/// The level whose voxels are about one image pixel (as for the axis-aligned slices).
pub fn level_for_pixel_mm(pixel_mm: f64, finest_spacing_mm: f64, level_count: usize) -> u8 {
    if !(pixel_mm.is_finite() && finest_spacing_mm > 0.0 && pixel_mm > 0.0) {
        return 0;
    }
    let level = (pixel_mm / finest_spacing_mm).log2().floor().max(0.0) as usize;
    level.min(level_count.saturating_sub(1)) as u8
}

/// Bricks of any level, bounded; the last brick used is kept at hand for neighbours.
pub struct LevelBrickCache {
    budget_bricks: usize,
    bricks: HashMap<BrickId, Arc<Vec<u16>>>,
    last: Option<(BrickId, Arc<Vec<u16>>)>,
}

impl LevelBrickCache {
    pub fn new(budget_bytes: usize) -> Self {
        LevelBrickCache {
            budget_bricks: (budget_bytes / (strata_types::BRICK_PAYLOAD_VOXELS * 2)).max(16),
            bricks: HashMap::new(),
            last: None,
        }
    }

    /// The stored value of voxel `index` of `level` (inside that level).
    pub fn voxel(
        &mut self,
        store: &dyn VolumeSource,
        level: u8,
        index: [u32; 3],
    ) -> anyhow::Result<u16> {
        let id = BrickId::new(level, index.map(|i| i / BRICK_CORE));
        let brick = match &self.last {
            Some((last_id, brick)) if *last_id == id => brick.clone(),
            _ => {
                let brick = match self.bricks.get(&id) {
                    Some(b) => b.clone(),
                    None => {
                        if self.bricks.len() >= self.budget_bricks {
                            self.bricks.clear();
                        }
                        let b = Arc::new(store.read_brick(id)?);
                        self.bricks.insert(id, b.clone());
                        b
                    }
                };
                self.last = Some((id, brick.clone()));
                brick
            }
        };
        let local = index.map(|i| (i % BRICK_CORE + BRICK_APRON) as usize);
        let edge = BRICK_PAYLOAD as usize;
        Ok(brick[(local[2] * edge + local[1]) * edge + local[0]])
    }
}

/// Resamples one oblique image: each pixel centre to patient space, to the level's continuous
/// index, then trilinear between that level's voxel centres (clamped at the volume's edge
/// voxels; NaN beyond the voxel-cell box).
pub fn resample(
    store: &dyn VolumeSource,
    cache: &mut LevelBrickCache,
    request: &ObliqueRequest,
) -> anyhow::Result<ObliqueImage> {
    let geometry = &store.header().geometry;
    let layout = store.layout();
    let level = (request.level as usize).min(layout.level_count() - 1);
    let dims = layout.level_dims[level];
    let scale = (1u64 << level) as f64;
    let dims0 = geometry.dims;
    let index_from_patient: DMat3 = geometry.index_from_patient_linear();
    let origin = geometry.origin();
    let (w, h) = (request.width, request.height);
    let mut values = vec![f32::NAN; w * h];
    for y in 0..h {
        for x in 0..w {
            let p = request
                .plane
                .patient_at((x as f64 + 0.5) / w as f64, (y as f64 + 0.5) / h as f64);
            let i0 = index_from_patient * (p - origin);
            if (0..3).any(|a| !(i0[a] >= -0.5 && i0[a] <= dims0[a] as f64 - 0.5)) {
                continue;
            }
            let il = (i0 + 0.5) / scale - 0.5;
            values[y * w + x] = trilinear(store, cache, level as u8, dims, il)? as f32;
        }
    }
    Ok(ObliqueImage {
        request: *request,
        values: Arc::new(values),
    })
}

fn trilinear(
    store: &dyn VolumeSource,
    cache: &mut LevelBrickCache,
    level: u8,
    dims: [u32; 3],
    p: DVec3,
) -> anyhow::Result<f64> {
    let mut sum = 0.0;
    for (index, weight) in strata_render::model::field::trilinear_corners(p.to_array(), dims) {
        if weight > 0.0 {
            sum += weight * cache.voxel(store, level, index)? as f64;
        }
    }
    Ok(sum)
}

struct Shared {
    pending: Mutex<Option<ObliqueRequest>>,
    result: Mutex<Option<ObliqueImage>>,
    error: Mutex<Option<String>>,
    wake: Condvar,
    stop: AtomicBool,
}

/// The oblique view's reader thread: the newest request wins.
pub struct ObliqueReader {
    shared: Arc<Shared>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl ObliqueReader {
    pub fn start(store: Arc<dyn VolumeSource>, repaint: Repaint) -> anyhow::Result<Self> {
        let shared = Arc::new(Shared {
            pending: Mutex::new(None),
            result: Mutex::new(None),
            error: Mutex::new(None),
            wake: Condvar::new(),
            stop: AtomicBool::new(false),
        });
        let thread_shared = shared.clone();
        let thread = std::thread::Builder::new()
            .name("strata-oblique-reader".into())
            .spawn(move || {
                let mut cache = LevelBrickCache::new(OBLIQUE_CACHE_BYTES);
                loop {
                    let next = {
                        let mut pending = lock_ignoring_poison(&thread_shared.pending);
                        loop {
                            if thread_shared.stop.load(Ordering::Acquire) {
                                return;
                            }
                            if let Some(r) = pending.take() {
                                break r;
                            }
                            pending = wait_ignoring_poison(&thread_shared.wake, pending);
                        }
                    };
                    match resample(store.as_ref(), &mut cache, &next) {
                        Ok(image) => {
                            *lock_ignoring_poison(&thread_shared.result) = Some(image);
                            *lock_ignoring_poison(&thread_shared.error) = None;
                        }
                        Err(e) => {
                            *lock_ignoring_poison(&thread_shared.error) = Some(format!("{e:#}"))
                        }
                    }
                    repaint();
                }
            })?;
        Ok(ObliqueReader {
            shared,
            thread: Some(thread),
        })
    }

    pub fn request(&self, request: ObliqueRequest) {
        if self.latest().is_some_and(|l| l.request == request) {
            return;
        }
        let mut pending = lock_ignoring_poison(&self.shared.pending);
        if *pending != Some(request) {
            *pending = Some(request);
            self.shared.wake.notify_all();
        }
    }

    pub fn latest(&self) -> Option<ObliqueImage> {
        lock_ignoring_poison(&self.shared.result).clone()
    }

    pub fn error(&self) -> Option<String> {
        lock_ignoring_poison(&self.shared.error).clone()
    }
}

impl Drop for ObliqueReader {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
        self.shared.wake.notify_all();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The plane's extent that shows the whole volume whatever the orientation.
pub fn default_extent_mm(geometry: &VolumeGeometry) -> f64 {
    2.0 * geometry.bounding_radius_mm()
}

#[cfg(test)]
mod tests {
    use super::*;
    use strata_storage::phantom::Phantom;

    fn phantom_store(dir: &std::path::Path, n: u64) -> (Phantom, strata_storage::Store) {
        let path = dir.join("p.strata");
        let phantom = Phantom::cube(n);
        phantom
            .write_store(&path, &Default::default())
            .expect("phantom store");
        (phantom, strata_storage::Store::open(&path).expect("open"))
    }

    /// The whole phantom's stored values, straight from its generator (not from bricks).
    fn stored_volume(phantom: &Phantom, n: usize) -> Vec<u16> {
        let mut all = vec![0u16; n * n * n];
        for (k, slice) in all.chunks_exact_mut(n * n).enumerate() {
            phantom.stored_slice(k as u64, slice);
        }
        all
    }

    /// f64 trilinear reference at level 0 from the generator's values, clamped at the edges.
    fn reference(all: &[u16], n: usize, p: DVec3) -> f64 {
        let q = [0, 1, 2].map(|a| p[a].clamp(0.0, n as f64 - 1.0));
        let b = q.map(f64::floor);
        let t = [q[0] - b[0], q[1] - b[1], q[2] - b[2]];
        let at = |i: usize, j: usize, k: usize| all[(k * n + j) * n + i] as f64;
        let mut sum = 0.0;
        for c in 0..8 {
            let idx = [0, 1, 2].map(|a| ((b[a] as usize) + ((c >> a) & 1)).min(n - 1));
            let w: f64 = (0..3)
                .map(|a| if (c >> a) & 1 == 1 { t[a] } else { 1.0 - t[a] })
                .product();
            sum += w * at(idx[0], idx[1], idx[2]);
        }
        sum
    }

    /// A plane turned 30° and 20° off axial through an off-centre point: every pixel equals the
    /// f64 trilinear reference computed from the phantom generator's voxels, to f32 rounding
    /// (values are ≤ 65535, so 1e-2 is a few f32 ulps there), NaN exactly outside the volume.
    #[test]
    fn an_oblique_slice_matches_the_f64_trilinear_reference() {
        let dir = tempfile::tempdir().expect("temp dir");
        let n = 40usize;
        let (phantom, store) = phantom_store(dir.path(), n as u64);
        let all = stored_volume(&phantom, n);
        let geometry = store.header().geometry.clone();
        let centre = geometry.patient_from_index([17.3, 21.6, 19.2]);
        let plane = ObliquePlane::axial(centre, default_extent_mm(&geometry))
            .rotated(30f64.to_radians(), 20f64.to_radians());
        let request = ObliqueRequest {
            plane,
            width: 64,
            height: 64,
            level: 0,
        };
        let mut cache = LevelBrickCache::new(8 << 20);
        let image = resample(&store, &mut cache, &request).expect("resample");
        let mut inside = 0;
        for y in 0..64 {
            for x in 0..64 {
                let p = plane.patient_at((x as f64 + 0.5) / 64.0, (y as f64 + 0.5) / 64.0);
                let i = geometry.index_from_patient(p);
                let got = image.values[y * 64 + x];
                if (0..3).any(|a| i[a] < -0.5 || i[a] > n as f64 - 0.5) {
                    assert!(got.is_nan(), "({x},{y}) outside has {got}");
                    continue;
                }
                let expected = reference(&all, n, i);
                assert!(
                    (got as f64 - expected).abs() < 1e-2,
                    "({x},{y}) at index {i:?}: {got} vs {expected}"
                );
                inside += 1;
            }
        }
        assert!(inside > 1000, "only {inside} pixels inside the volume");
    }

    /// Unturned and centred on voxel centres with one voxel per pixel, the oblique image is the
    /// axial slice: exactly the stored values of that slice (weights are 0 and 1).
    #[test]
    fn an_unturned_plane_on_voxel_centres_is_the_axial_slice() {
        let dir = tempfile::tempdir().expect("temp dir");
        let n = 40usize;
        let (phantom, store) = phantom_store(dir.path(), n as u64);
        let all = stored_volume(&phantom, n);
        let geometry = store.header().geometry.clone();
        let spacing = geometry.spacing_mm[0];
        // The image spans voxel cells 0..40 across and down, at slice k = 13.
        let centre = geometry.patient_from_index([19.5, 19.5, 13.0]);
        let request = ObliqueRequest {
            plane: ObliquePlane::axial(centre, spacing * n as f64),
            width: n,
            height: n,
            level: 0,
        };
        let mut cache = LevelBrickCache::new(8 << 20);
        let image = resample(&store, &mut cache, &request).expect("resample");
        for j in 0..n {
            for i in 0..n {
                let expected = all[(13 * n + j) * n + i] as f32;
                let got = image.values[j * n + i];
                assert!(
                    (got - expected).abs() < 1e-3,
                    "({i},{j}): {got} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn labels_follow_the_plane_and_rotation_keeps_it_orthonormal() {
        let axial = ObliquePlane::axial(DVec3::ZERO, 100.0);
        assert_eq!(axial.labels(), ["R", "L", "A", "P"]);
        // A quarter turn about the screen's horizontal axis: the plane becomes coronal-like,
        // top and bottom are now superior/inferior.
        let tilted = axial.rotated(0.0, 90f64.to_radians());
        let [_, _, top, bottom] = tilted.labels();
        assert!(
            matches!((top, bottom), ("S", "I") | ("I", "S")),
            "{top} {bottom}"
        );
        let mut p = axial;
        for _ in 0..1000 {
            p = p.rotated(0.013, -0.007);
        }
        assert!((p.right.length() - 1.0).abs() < 1e-9);
        assert!((p.down.length() - 1.0).abs() < 1e-9);
        assert!(p.right.dot(p.down).abs() < 1e-9);
        // Facing the 3D camera: the normal is the camera's viewing direction.
        let geometry = VolumeGeometry::axis_aligned([10, 10, 10], [1.0; 3]);
        let camera = Camera::orbit(
            &geometry,
            40.0,
            25.0,
            1.0,
            strata_render::Projection::Perspective { fov_y_deg: 30.0 },
        );
        let facing = ObliquePlane::facing(&camera, DVec3::ZERO, 10.0);
        let forward = camera.basis().forward.normalize_or_zero();
        assert!((facing.normal().dot(forward).abs() - 1.0).abs() < 1e-9);
    }
}
