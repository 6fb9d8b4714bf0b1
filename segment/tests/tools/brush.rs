//! Brush and eraser strokes give exactly the voxels of a brute-force model of the stroke: every
//! voxel centre of the grid tested against the swept shape in patient space.

use glam::DVec3;
use strata_segment::intensity::{DenseIntensity, ValueRange};
use strata_segment::tools::brush::{
    footprint, stroke, Brush, BrushAction, BrushShape, EraseTarget, SlicePlane,
};
use strata_segment::LabelLayer;
use strata_types::VolumeGeometry;

use super::common::{rotated_anisotropic, voxels_of};

/// The model's plane: a point and normal in patient space, plus the slab half-thickness (0 for
/// an index slice, whose voxels are chosen by index).
enum ModelPlane {
    Slice {
        axis: usize,
        slice: i64,
    },
    Slab {
        centre: DVec3,
        normal: DVec3,
        half: f64,
    },
    None,
}

fn model_plane(g: &VolumeGeometry, plane: Option<SlicePlane>, first: DVec3) -> ModelPlane {
    let slice_of = |axis: usize| ModelPlane::Slice {
        axis,
        slice: g.index_from_patient(first)[axis].round() as i64,
    };
    match plane {
        None => ModelPlane::None,
        Some(SlicePlane::Axial) => slice_of(2),
        Some(SlicePlane::Coronal) => slice_of(1),
        Some(SlicePlane::Sagittal) => slice_of(0),
        Some(SlicePlane::Oblique { centre_lps, u, v }) => {
            let normal = u.cross(v);
            let half = (0..3)
                .map(|a| g.spacing_mm[a] * normal.dot(DVec3::from(g.direction[a])).abs())
                .fold(0.0, f64::max)
                / 2.0;
            ModelPlane::Slab {
                centre: centre_lps,
                normal,
                half,
            }
        }
    }
}

/// The model: every voxel of the grid whose centre lies within `radius` of the polyline, all
/// measured in the plane (positions and centres projected onto it by its patient-space normal,
/// which on these orthonormal grids is the slice's index direction).
fn model_stroke(
    g: &VolumeGeometry,
    plane: Option<SlicePlane>,
    diameter_mm: f64,
    positions: &[DVec3],
) -> Vec<[u32; 3]> {
    let mp = model_plane(g, plane, positions[0]);
    let project = |p: DVec3| -> DVec3 {
        match &mp {
            ModelPlane::None => p,
            ModelPlane::Slice { axis, slice } => {
                let mut at = [0.0; 3];
                at[*axis] = *slice as f64;
                let point = g.patient_from_index(DVec3::from(at));
                let normal = DVec3::from(g.direction[*axis]);
                p - normal * normal.dot(p - point)
            }
            ModelPlane::Slab { centre, normal, .. } => p - *normal * normal.dot(p - *centre),
        }
    };
    let pts: Vec<DVec3> = positions.iter().map(|&p| project(p)).collect();
    let segs: Vec<(DVec3, DVec3)> = if pts.len() == 1 {
        vec![(pts[0], pts[0])]
    } else {
        pts.windows(2).map(|w| (w[0], w[1])).collect()
    };
    let r = diameter_mm / 2.0;
    let mut out = Vec::new();
    let [nx, ny, nz] = g.dims;
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let c = g.patient_from_index(DVec3::new(i as f64, j as f64, k as f64));
                let in_plane = match &mp {
                    ModelPlane::None => true,
                    ModelPlane::Slice { axis, slice } => [i, j, k][*axis] as i64 == *slice,
                    ModelPlane::Slab {
                        centre,
                        normal,
                        half,
                    } => {
                        let off = normal.dot(c - *centre);
                        -*half <= off && off < *half
                    }
                };
                if !in_plane {
                    continue;
                }
                let x = project(c);
                let near = segs.iter().any(|&(a, b)| {
                    // The distance along the segment is convex in t: a golden-section search
                    // finds its minimum (an independent route, no clamped projection formula).
                    let (mut lo, mut hi) = (0.0f64, 1.0f64);
                    for _ in 0..60 {
                        let m1 = lo + (hi - lo) * 0.382;
                        let m2 = lo + (hi - lo) * 0.618;
                        if (x - a.lerp(b, m1)).length() < (x - a.lerp(b, m2)).length() {
                            hi = m2;
                        } else {
                            lo = m1;
                        }
                    }
                    let best = [0.0, 1.0, (lo + hi) / 2.0]
                        .iter()
                        .map(|&t| (x - a.lerp(b, t)).length())
                        .fold(f64::INFINITY, f64::min);
                    best <= r + 1e-9
                });
                if near {
                    out.push([i, j, k]);
                }
            }
        }
    }
    out
}

fn layer_with(g: &VolumeGeometry, names: &[&str]) -> LabelLayer {
    let mut l = LabelLayer::new_empty(g.clone()).unwrap();
    for n in names {
        l.segments_mut().add(*n).unwrap();
    }
    l
}

fn check_stroke(g: &VolumeGeometry, shape: BrushShape, diameter_mm: f64, positions: &[DVec3]) {
    let mut layer = layer_with(g, &["a"]);
    let brush = Brush {
        shape,
        diameter_mm,
        value_range: None,
    };
    let edit = stroke(&mut layer, &brush, BrushAction::Paint(1), positions, None).unwrap();
    let plane = match shape {
        BrushShape::Disc(p) => Some(p),
        BrushShape::Sphere => None,
    };
    let want = model_stroke(g, plane, diameter_mm, positions);
    assert!(
        want.len() > 8,
        "{shape:?}: the model stroke is too small to test ({})",
        want.len()
    );
    assert!(edit.is_some());
    assert_eq!(voxels_of(&layer, 1), want, "{shape:?}");
}

/// A stroke crossing brick boundaries with samples far apart (the swept part matters).
fn wiggle(g: &VolumeGeometry, at: [f64; 3]) -> Vec<DVec3> {
    [
        [0.0, 0.0, 0.0],
        [9.0, 3.0, 0.4],
        [14.0, 11.0, -0.3],
        [6.0, 19.0, 0.2],
    ]
    .iter()
    .map(|o| g.patient_from_index(DVec3::from(at) + DVec3::from(*o)))
    .collect()
}

#[test]
fn brush_strokes_on_a_plain_grid_paint_exactly_the_modelled_voxels() {
    let g = VolumeGeometry::axis_aligned([48, 48, 12], [1.0; 3]);
    let pts = wiggle(&g, [20.0, 14.0, 6.3]);
    check_stroke(&g, BrushShape::Disc(SlicePlane::Axial), 6.0, &pts);
    check_stroke(&g, BrushShape::Disc(SlicePlane::Axial), 4.4, &pts[1..2]);
    check_stroke(&g, BrushShape::Sphere, 5.0, &pts);
}

#[test]
fn brush_strokes_on_a_rotated_anisotropic_grid_paint_exactly_the_modelled_voxels() {
    let g = rotated_anisotropic([44, 40, 24]);
    let pts = wiggle(&g, [18.0, 10.0, 11.6]);
    check_stroke(&g, BrushShape::Disc(SlicePlane::Axial), 7.0, &pts);
    check_stroke(&g, BrushShape::Disc(SlicePlane::Coronal), 6.0, &pts);
    check_stroke(&g, BrushShape::Disc(SlicePlane::Sagittal), 6.0, &pts);
    check_stroke(&g, BrushShape::Sphere, 6.5, &pts);
    // An oblique plane tilted against every index axis of the (already rotated) grid.
    let u = DVec3::new(0.8, 0.6, 0.0);
    let v = DVec3::new(-0.36, 0.48, 0.8);
    let centre = pts[0];
    let oblique = SlicePlane::Oblique {
        centre_lps: centre,
        u,
        v,
    };
    let in_plane: Vec<DVec3> = [(0.0, 0.0), (8.0, 3.0), (12.0, 12.0)]
        .iter()
        .map(|&(a, b)| centre + u * a + v * b)
        .collect();
    check_stroke(&g, BrushShape::Disc(oblique), 6.0, &in_plane);
}

#[test]
fn the_eraser_clears_only_its_segment_or_unlocked_ones_and_locks_hold() {
    let g = rotated_anisotropic([40, 40, 16]);
    let mut layer = layer_with(&g, &["a", "b", "c"]);
    let pts = wiggle(&g, [12.0, 8.0, 7.2]);
    let wide = Brush {
        shape: BrushShape::Sphere,
        diameter_mm: 9.0,
        value_range: None,
    };
    // a everywhere in a sphere stroke, then b over part of it, c locked over another part.
    stroke(&mut layer, &wide, BrushAction::Paint(1), &pts, None).unwrap();
    stroke(&mut layer, &wide, BrushAction::Paint(2), &pts[..2], None).unwrap();
    stroke(&mut layer, &wide, BrushAction::Paint(3), &pts[2..3], None).unwrap();
    layer.segments_mut().get_mut(3).unwrap().locked = true;
    // Painting b over locked c leaves c, and painting with c is refused.
    let before_c = voxels_of(&layer, 3);
    stroke(&mut layer, &wide, BrushAction::Paint(2), &pts[2..4], None).unwrap();
    assert_eq!(voxels_of(&layer, 3), before_c);
    assert!(stroke(&mut layer, &wide, BrushAction::Paint(3), &pts, None).is_err());

    let eraser = Brush {
        shape: BrushShape::Disc(SlicePlane::Axial),
        diameter_mm: 8.0,
        value_range: None,
    };
    let covered = model_stroke(&g, Some(SlicePlane::Axial), 8.0, &pts);
    let labels_before: Vec<_> = (1..=3).map(|l| voxels_of(&layer, l)).collect();
    stroke(
        &mut layer,
        &eraser,
        BrushAction::Erase(EraseTarget::Segment(2)),
        &pts,
        None,
    )
    .unwrap();
    let b_want: Vec<_> = labels_before[1]
        .iter()
        .filter(|v| !covered.contains(v))
        .copied()
        .collect();
    assert!(
        b_want.len() < labels_before[1].len(),
        "the eraser reached b"
    );
    assert_eq!(voxels_of(&layer, 2), b_want);
    assert_eq!(
        voxels_of(&layer, 1),
        labels_before[0],
        "a untouched by erasing b"
    );

    stroke(
        &mut layer,
        &eraser,
        BrushAction::Erase(EraseTarget::AnyUnlocked),
        &pts,
        None,
    )
    .unwrap();
    let a_want: Vec<_> = labels_before[0]
        .iter()
        .filter(|v| !covered.contains(v))
        .copied()
        .collect();
    assert!(a_want.len() < labels_before[0].len());
    assert_eq!(voxels_of(&layer, 1), a_want);
    assert_eq!(
        voxels_of(&layer, 3),
        before_c,
        "locked c survives the eraser"
    );
}

#[test]
fn a_value_range_limits_the_brush_to_the_primary_values_inside_it() {
    let g = rotated_anisotropic([40, 36, 12]);
    let [nx, ny, nz] = g.dims;
    // "Bone" where a smooth field is ≥ 300.
    let values: Vec<f32> = (0..nx * ny * nz)
        .map(|n| {
            let (i, j) = ((n % nx) as f32, ((n / nx) % ny) as f32);
            600.0 * ((i * 0.4).sin() * (j * 0.3).cos()).abs()
        })
        .collect();
    let intensity = DenseIntensity::new(g.dims, values.clone(), "HU").unwrap();
    let mut layer = layer_with(&g, &["bone"]);
    let brush = Brush {
        shape: BrushShape::Disc(SlicePlane::Axial),
        diameter_mm: 10.0,
        value_range: Some(ValueRange::new(300.0, f64::INFINITY).unwrap()),
    };
    let pts = wiggle(&g, [10.0, 6.0, 5.0]);
    stroke(
        &mut layer,
        &brush,
        BrushAction::Paint(1),
        &pts,
        Some(&intensity),
    )
    .unwrap();
    let want: Vec<_> = model_stroke(&g, Some(SlicePlane::Axial), 10.0, &pts)
        .into_iter()
        .filter(|v| values[(v[0] + nx * (v[1] + ny * v[2])) as usize] >= 300.0)
        .collect();
    let all = model_stroke(&g, Some(SlicePlane::Axial), 10.0, &pts).len();
    assert!(
        want.len() > 20 && want.len() < all,
        "the range must cut the stroke"
    );
    assert_eq!(voxels_of(&layer, 1), want);
    // Without the primary, a ranged brush is an error, not an unlimited one.
    assert!(stroke(&mut layer, &brush, BrushAction::Paint(1), &pts, None).is_err());
}

#[test]
fn the_cursor_footprint_is_the_disc_or_the_spheres_cut_by_the_view() {
    let g = rotated_anisotropic([40, 40, 20]);
    let p = g.patient_from_index(DVec3::new(20.2, 19.7, 9.8));
    let disc = Brush {
        shape: BrushShape::Disc(SlicePlane::Coronal),
        diameter_mm: 8.0,
        value_range: None,
    };
    let got = footprint(g_grid(&g).as_ref(), &disc, p, &SlicePlane::Coronal).unwrap();
    assert_eq!(got, model_stroke(&g, Some(SlicePlane::Coronal), 8.0, &[p]));
    let sphere = Brush {
        shape: BrushShape::Sphere,
        ..disc
    };
    let got = footprint(g_grid(&g).as_ref(), &sphere, p, &SlicePlane::Axial).unwrap();
    let k = g.index_from_patient(p).z.round() as u32;
    let want: Vec<_> = model_stroke(&g, None, 8.0, &[p])
        .into_iter()
        .filter(|v| v[2] == k)
        .collect();
    assert!(want.len() > 10);
    assert_eq!(got, want);
}

fn g_grid(g: &VolumeGeometry) -> Box<strata_segment::LabelGrid> {
    Box::new(strata_segment::LabelGrid::new(g.clone()).unwrap())
}
