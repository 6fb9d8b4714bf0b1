//! The oblique reformat's platform-independent part, one copy for both viewers: a slice
//! through the crosshair at any orientation, resampled on the CPU from the bricks of the level
//! matching the view's pixel size, trilinearly between that level's voxel centres (the
//! interpolation the raycaster and the f64 reference use, `strata_types::trilinear_corners`).
//!
//! The plane ([`ObliquePlane`]) is an orthonormal pair of screen directions in patient space
//! (LPS mm); a left drag turns it about its own axes by [`TURN_PER_POINT`] a point
//! ([`ObliquePlane::turned_by_drag`], the one mapping both viewers apply), and a link carries its
//! orientation as three angles off axial ([`ObliquePlane::orientation_deg`]). The image asked
//! for ([`ObliqueRequest::for_view`]: at most [`MAX_OBLIQUE_PIXELS`] across, the level from
//! [`level_for_pixel_mm`]) and its resampling ([`resample`]) are the same in both viewers; only
//! where the bricks come from differs, behind [`LevelBricks`]: the desktop reads them with
//! blocking reads on its `strata-oblique-reader` thread (viewer/src/oblique.rs, never
//! "not resident"), the page from its fetch answers (web/src/oblique_view.rs), where a brick
//! not resident yet makes the resampling [`Resampled::Incomplete`] with the bricks to ask for.
//! Tested against an f64 trilinear model of the phantom generator's voxels (tests below), and
//! the page's image against this resampling in `web/tests/browser/oblique.rs`.

use std::sync::Arc;

use glam::{DMat3, DQuat, DVec3, EulerRot};
use strata_types::{
    trilinear_corners, BrickId, OctreeLayout, VolumeGeometry, BRICK_APRON, BRICK_CORE,
    BRICK_PAYLOAD, BRICK_PAYLOAD_VOXELS,
};

use crate::assembler::SliceError;

/// Radians the plane turns per point dragged.
pub const TURN_PER_POINT: f64 = 0.01;

/// The most pixels the CPU resamples across (the view is upscaled beyond).
pub const MAX_OBLIQUE_PIXELS: usize = 384;

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

    /// Through `centre`, with screen right and up as a camera has them (the 3D view's, for
    /// "Align to 3D"); axial where they are degenerate.
    pub fn facing_axes(centre: DVec3, right: DVec3, up: DVec3, extent_mm: f64) -> Self {
        let right = right.try_normalize();
        let down = right.and_then(|r| (-up - r * r.dot(-up)).try_normalize());
        match (right, down) {
            (Some(right), Some(down)) => ObliquePlane {
                centre,
                right,
                down,
                extent_mm,
            },
            _ => ObliquePlane::axial(centre, extent_mm),
        }
    }

    /// Turned from axial by `[yaw, pitch, roll]` degrees: yaw about the axial view's vertical
    /// (+y), then pitch about the turned horizontal, then roll about the turned normal, so
    /// `[yaw, pitch, 0]` is `axial.rotated(yaw, pitch)`. A link's `oblique=` value.
    pub fn from_orientation_deg(centre: DVec3, extent_mm: f64, angles_deg: [f64; 3]) -> Self {
        let [yaw, pitch, roll] = angles_deg.map(f64::to_radians);
        let turn = DQuat::from_euler(EulerRot::YXZ, yaw, pitch, roll);
        ObliquePlane {
            centre,
            right: turn * DVec3::X,
            down: turn * DVec3::Y,
            extent_mm,
        }
    }

    /// The `[yaw, pitch, roll]` degrees off axial that [`ObliquePlane::from_orientation_deg`]
    /// turns back into this orientation.
    pub fn orientation_deg(&self) -> [f64; 3] {
        let turn = DQuat::from_mat3(&DMat3::from_cols(self.right, self.down, self.normal()));
        let (yaw, pitch, roll) = turn.to_euler(EulerRot::YXZ);
        [yaw, pitch, roll].map(f64::to_degrees)
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

    /// Turned by a left drag of `(dx, dy)` points (one pointer move): sideways about the
    /// screen's vertical, up/down about its horizontal, [`TURN_PER_POINT`] a point.
    pub fn turned_by_drag(&self, dx_points: f64, dy_points: f64) -> Self {
        self.rotated(dx_points * TURN_PER_POINT, -dy_points * TURN_PER_POINT)
    }

    /// Patient position at image fraction (`u` across, `w` down), both 0..1.
    pub fn patient_at(&self, u: f64, w: f64) -> DVec3 {
        self.centre
            + self.right * ((u - 0.5) * self.extent_mm)
            + self.down * ((w - 0.5) * self.extent_mm)
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

impl ObliqueRequest {
    /// The square image a view `side_pixels` device pixels across asks for: that many samples
    /// (16 to [`MAX_OBLIQUE_PIXELS`]) at the level whose voxels are about one sample.
    pub fn for_view(
        plane: ObliquePlane,
        side_pixels: f64,
        geometry: &VolumeGeometry,
        level_count: usize,
    ) -> Self {
        let pixels = if side_pixels.is_finite() {
            (side_pixels.max(0.0) as usize).clamp(16, MAX_OBLIQUE_PIXELS)
        } else {
            16
        };
        let level = level_for_pixel_mm(
            plane.extent_mm / pixels as f64,
            geometry.finest_spacing_mm(),
            level_count,
        );
        ObliqueRequest {
            plane,
            width: pixels,
            height: pixels,
            level,
        }
    }
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

/// The plane's extent that shows the whole volume whatever the orientation.
pub fn default_extent_mm(geometry: &VolumeGeometry) -> f64 {
    2.0 * geometry.bounding_radius_mm()
}

/// Where the resampling gets a level's decoded bricks (36³ payloads, apron included).
pub trait LevelBricks {
    /// A read that failed (the desktop's disk or network); a brick of the wrong size is a
    /// [`SliceError`].
    type Error: From<SliceError>;
    /// Brick `id`, or `None` while it is not resident yet (the page's fetch is under way).
    fn brick(&mut self, id: BrickId) -> Result<Option<Arc<Vec<u16>>>, Self::Error>;
}

/// What one resampling gave.
#[derive(Clone, Debug)]
pub enum Resampled {
    /// Every pixel sampled.
    Complete(ObliqueImage),
    /// Bricks not resident yet, each once in the order the image first needed them (at most
    /// the `max_missing` asked for: the resampling stops there).
    Incomplete { missing: Vec<BrickId> },
}

/// Resamples one oblique image: each pixel centre to patient space, to the level's continuous
/// index, then trilinear between that level's voxel centres (clamped at the volume's edge
/// voxels; NaN beyond the voxel-cell box). Stops once `max_missing` bricks (at least one) were
/// found not resident.
pub fn resample<B: LevelBricks + ?Sized>(
    geometry: &VolumeGeometry,
    layout: &OctreeLayout,
    bricks: &mut B,
    request: &ObliqueRequest,
    max_missing: usize,
) -> Result<Resampled, B::Error> {
    let level_count = layout.level_count();
    if level_count == 0 {
        return Err(SliceError::NoLevels.into());
    }
    let level = (request.level as usize).min(level_count - 1);
    let dims = layout.level_dims[level];
    let scale = (1u64 << level) as f64;
    let dims0 = geometry.dims;
    let index_from_patient: DMat3 = geometry.index_from_patient_linear();
    let origin = geometry.origin();
    let (w, h) = (request.width, request.height);
    let mut values = vec![f32::NAN; w * h];
    let mut missing: Vec<BrickId> = Vec::new();
    // The brick of the last voxel read: a pixel's eight corners, and the next pixel's, are
    // nearly always in it.
    let mut last: Option<(BrickId, Arc<Vec<u16>>)> = None;
    'pixels: for y in 0..h {
        for x in 0..w {
            let p = request
                .plane
                .patient_at((x as f64 + 0.5) / w as f64, (y as f64 + 0.5) / h as f64);
            let i0 = index_from_patient * (p - origin);
            if (0..3).any(|a| !(i0[a] >= -0.5 && i0[a] <= dims0[a] as f64 - 0.5)) {
                continue;
            }
            let il = (i0 + 0.5) / scale - 0.5;
            let mut sum = 0.0;
            let mut complete = true;
            for (index, weight) in trilinear_corners(il.to_array(), dims) {
                if weight <= 0.0 {
                    continue;
                }
                let id = BrickId::new(level as u8, index.map(|i| i / BRICK_CORE));
                let brick = match &last {
                    Some((last_id, brick)) if *last_id == id => brick.clone(),
                    _ => {
                        if missing.contains(&id) {
                            complete = false;
                            continue;
                        }
                        match bricks.brick(id)? {
                            Some(brick) if brick.len() == BRICK_PAYLOAD_VOXELS => {
                                last = Some((id, brick.clone()));
                                brick
                            }
                            Some(brick) => {
                                return Err(SliceError::WrongBrickSize {
                                    id,
                                    voxels: brick.len(),
                                }
                                .into())
                            }
                            None => {
                                missing.push(id);
                                if missing.len() >= max_missing.max(1) {
                                    break 'pixels;
                                }
                                complete = false;
                                continue;
                            }
                        }
                    }
                };
                let local = index.map(|i| (i % BRICK_CORE + BRICK_APRON) as usize);
                let edge = BRICK_PAYLOAD as usize;
                sum += weight * brick[(local[2] * edge + local[1]) * edge + local[0]] as f64;
            }
            if complete {
                values[y * w + x] = sum as f32;
            }
        }
    }
    if !missing.is_empty() {
        return Ok(Resampled::Incomplete { missing });
    }
    Ok(Resampled::Complete(ObliqueImage {
        request: *request,
        values: Arc::new(values),
    }))
}

/// Oblique values → RGBA8 (opaque) through the window and the colour map as the slices are
/// coloured ([`crate::window_level_rgba`]'s step, on interpolated values); black outside the
/// volume (NaN). Both viewers colour their oblique image with it.
pub fn oblique_rgba(
    values: &[f32],
    window: crate::Window,
    colour_map: crate::ColourMap,
    mapping: strata_types::ValueMapping,
) -> Vec<u8> {
    let lo = window.low();
    let scale = 255.0 / window.width.max(1e-9);
    let table = colour_map.table();
    let mut rgba = Vec::with_capacity(values.len() * 4);
    for &s in values {
        if !s.is_finite() {
            rgba.extend_from_slice(&[0, 0, 0, 255]);
            continue;
        }
        let g = ((mapping.physical(s as f64) - lo) * scale).clamp(0.0, 255.0) as usize;
        let [r, g, b] = table[g];
        rgba.extend_from_slice(&[r, g, b, 255]);
    }
    rgba
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;
    use strata_storage::phantom::Phantom;
    use strata_storage::Store;

    fn phantom_store(dir: &std::path::Path, n: u64) -> (Phantom, Store) {
        let path = dir.join("p.strata");
        let phantom = Phantom::cube(n);
        phantom
            .write_store(&path, &Default::default())
            .expect("phantom store");
        (phantom, Store::open(&path).expect("open"))
    }

    /// A store's bricks read on demand (the desktop's way: never "not resident").
    struct StoreBricks<'a>(&'a Store);

    impl LevelBricks for StoreBricks<'_> {
        type Error = SliceError;
        fn brick(&mut self, id: BrickId) -> Result<Option<Arc<Vec<u16>>>, SliceError> {
            Ok(Some(Arc::new(self.0.read_brick(id).expect("brick"))))
        }
    }

    /// Only the bricks handed in so far are resident (the page's way).
    #[derive(Default)]
    struct ResidentBricks(HashMap<BrickId, Arc<Vec<u16>>>);

    impl LevelBricks for ResidentBricks {
        type Error = SliceError;
        fn brick(&mut self, id: BrickId) -> Result<Option<Arc<Vec<u16>>>, SliceError> {
            Ok(self.0.get(&id).cloned())
        }
    }

    fn complete(resampled: Resampled) -> ObliqueImage {
        match resampled {
            Resampled::Complete(image) => image,
            Resampled::Incomplete { missing } => panic!("bricks missing: {missing:?}"),
        }
    }

    fn resample_store(store: &Store, request: &ObliqueRequest) -> ObliqueImage {
        let header = store.header();
        complete(
            resample(
                &header.geometry,
                store.layout(),
                &mut StoreBricks(store),
                request,
                usize::MAX,
            )
            .expect("resample"),
        )
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
        let image = resample_store(&store, &request);
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
        let image = resample_store(&store, &request);
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

    /// With only some bricks resident the resampling names the missing ones (each once, and
    /// no more than asked for); once they are handed in, the image equals the one read from
    /// the store directly, value for value: the page's refinement ends at the desktop's image.
    #[test]
    fn missing_bricks_are_named_and_once_resident_give_the_stores_image() {
        let dir = tempfile::tempdir().expect("temp dir");
        let (_, store) = phantom_store(dir.path(), 80);
        let geometry = store.header().geometry.clone();
        let plane = ObliquePlane::axial(geometry.patient_from_index([40.0, 40.0, 40.0]), 90.0)
            .rotated(0.4, -0.3);
        let request = ObliqueRequest {
            plane,
            width: 48,
            height: 48,
            level: 0,
        };
        let expected = resample_store(&store, &request);
        let mut resident = ResidentBricks::default();
        let first =
            resample(&geometry, store.layout(), &mut resident, &request, 2).expect("resample");
        let Resampled::Incomplete { missing } = first else {
            panic!("nothing is resident yet, the image cannot be complete");
        };
        assert_eq!(missing.len(), 2, "{missing:?}");
        let mut rounds = 0;
        loop {
            rounds += 1;
            assert!(rounds < 100, "the resampling never completes");
            match resample(
                &geometry,
                store.layout(),
                &mut resident,
                &request,
                usize::MAX,
            )
            .expect("resample")
            {
                Resampled::Complete(image) => {
                    assert!(image
                        .values
                        .iter()
                        .zip(expected.values.iter())
                        .all(|(a, b)| a.to_bits() == b.to_bits()));
                    break;
                }
                Resampled::Incomplete { missing } => {
                    let unique: std::collections::HashSet<_> = missing.iter().collect();
                    assert_eq!(unique.len(), missing.len(), "listed twice: {missing:?}");
                    for id in missing {
                        assert!(!resident.0.contains_key(&id), "{id:?} is resident");
                        resident
                            .0
                            .insert(id, Arc::new(store.read_brick(id).expect("brick")));
                    }
                }
            }
        }
        // One round listed every brick the plane needs.
        assert_eq!(rounds, 2);
        // A brick of the wrong size is refused, not indexed past its end.
        let id = *resident.0.keys().next().expect("a brick");
        resident.0.insert(id, Arc::new(vec![0; 10]));
        let refused = resample(
            &geometry,
            store.layout(),
            &mut resident,
            &request,
            usize::MAX,
        )
        .expect_err("a brick of 10 voxels");
        assert_eq!(refused, SliceError::WrongBrickSize { id, voxels: 10 });
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
        let camera = strata_render::Camera::orbit(
            &geometry,
            40.0,
            25.0,
            1.0,
            strata_render::Projection::Perspective { fov_y_deg: 30.0 },
        );
        let basis = camera.basis();
        let facing = ObliquePlane::facing_axes(DVec3::ZERO, basis.right, basis.up, 10.0);
        let forward = basis.forward.normalize_or_zero();
        assert!((facing.normal().dot(forward).abs() - 1.0).abs() < 1e-9);
        assert_eq!(
            ObliquePlane::facing_axes(DVec3::ZERO, DVec3::ZERO, DVec3::Z, 10.0),
            ObliquePlane::axial(DVec3::ZERO, 10.0)
        );
    }

    /// A link's angles: `[yaw, pitch, 0]` is the drag's `rotated(yaw, pitch)` from axial, and
    /// any orientation reached by drags (which adds roll) comes back from its angles.
    #[test]
    fn a_planes_angles_give_back_its_orientation() {
        let close = |a: DVec3, b: DVec3| (a - b).length() < 1e-9;
        let axial = ObliquePlane::axial(DVec3::new(1.0, 2.0, 3.0), 50.0);
        let turned = axial.rotated(0.5, -0.25);
        let from_angles = ObliquePlane::from_orientation_deg(
            axial.centre,
            50.0,
            [0.5f64.to_degrees(), (-0.25f64).to_degrees(), 0.0],
        );
        assert!(close(from_angles.right, turned.right) && close(from_angles.down, turned.down));
        let angles = turned.orientation_deg();
        assert!((angles[0] - 0.5f64.to_degrees()).abs() < 1e-9, "{angles:?}");
        assert!(
            (angles[1] + 0.25f64.to_degrees()).abs() < 1e-9,
            "{angles:?}"
        );
        assert!(angles[2].abs() < 1e-9, "{angles:?}");
        let mut dragged = axial;
        for (dx, dy) in [(12.0, 0.0), (0.0, -30.0), (25.0, 18.0), (-7.0, 40.0)] {
            dragged = dragged.turned_by_drag(dx, dy);
        }
        let back =
            ObliquePlane::from_orientation_deg(axial.centre, 50.0, dragged.orientation_deg());
        assert!(
            dragged.orientation_deg()[2].abs() > 1e-3,
            "the drags add roll"
        );
        assert!(close(back.right, dragged.right) && close(back.down, dragged.down));
        assert_eq!(axial.orientation_deg(), [0.0, 0.0, 0.0]);
    }

    /// The image a view asks for: its pixels (bounded), the level whose voxels are about a
    /// pixel, and window/level that maps below the window to black, above it to the map's top
    /// colour, NaN to black.
    #[test]
    fn a_views_request_and_colours_follow_its_pixels_and_window() {
        let geometry = VolumeGeometry::axis_aligned([256, 256, 256], [1.0; 3]);
        let plane = ObliquePlane::axial(DVec3::ZERO, 256.0);
        let big = ObliqueRequest::for_view(plane, 1000.0, &geometry, 4);
        assert_eq!((big.width, big.height, big.level), (384, 384, 0));
        let small = ObliqueRequest::for_view(plane, 64.0, &geometry, 4);
        assert_eq!((small.width, small.level), (64, 2));
        assert_eq!(
            ObliqueRequest::for_view(plane, f64::NAN, &geometry, 4).width,
            16
        );
        assert_eq!(level_for_pixel_mm(8.0, 1.0, 2), 1);
        let rgba = oblique_rgba(
            &[f32::NAN, 0.0, 150.0, 50.0],
            crate::Window::new(50.0, 100.0),
            crate::ColourMap::Grey,
            strata_types::ValueMapping::default(),
        );
        assert_eq!(&rgba[0..4], &[0, 0, 0, 255]);
        assert_eq!(&rgba[4..8], &[0, 0, 0, 255]);
        let [r, g, b] = crate::ColourMap::Grey.table()[255];
        assert_eq!(&rgba[8..12], &[r, g, b, 255]);
        assert!(rgba[12] > 100 && rgba[12] < 150, "{rgba:?}");
    }
}
