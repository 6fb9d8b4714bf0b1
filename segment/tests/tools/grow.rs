//! Region growing equals scipy.ndimage.label's component of the seed on the same thresholded
//! volume, voxel for voxel; the cap, cancel and locks; the slice fill against its model.

use std::sync::atomic::AtomicBool;

use glam::DVec3;
use strata_segment::intensity::{DenseIntensity, ValueRange};
use strata_segment::tools::brush::{stroke, Brush, BrushAction, BrushShape, SlicePlane};
use strata_segment::tools::fill::fill_in_slice;
use strata_segment::tools::grow::{grow_from_seed, grow_range, GrowCriterion};
use strata_segment::{LabelLayer, SegmentError};
use strata_types::VolumeGeometry;

use super::common::{all_labels, python, rotated_anisotropic, scratch, voxels_of};

/// A smooth field with many bright blobs, some touching: a thresholded volume with several
/// components and winding shapes (a deterministic hash, no RNG crate).
fn blobs(dims: [u32; 3]) -> Vec<f32> {
    let [nx, ny, nz] = dims;
    let mut out = Vec::with_capacity((nx * ny * nz) as usize);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let (x, y, z) = (i as f32, j as f32, k as f32);
                let v = (x * 0.21).sin() * (y * 0.17 + 0.3 * (z * 0.11).cos()).cos()
                    + 0.6 * (z * 0.23 + x * 0.05).sin()
                    + 0.15 * ((i * 7 + j * 13 + k * 29) % 17) as f32 / 17.0;
                out.push(400.0 * v);
            }
        }
    }
    out
}

fn write_f32(path: &std::path::Path, values: &[f32]) {
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(path, bytes).expect("write the volume for the reference");
}

#[test]
fn region_growing_equals_scipy_ndimage_label_component_of_the_seed() {
    let dims = [72u32, 64, 56];
    let values = blobs(dims);
    let dir = scratch("grow-scipy");
    write_f32(&dir.join("volume.f32"), &values);
    let (lo, hi) = (250.0f32, 100000.0f32);
    let seed = (0..values.len())
        .find(|&n| values[n] >= lo && n % 7 == 3 && n > values.len() / 3)
        .expect("a bright voxel");
    let [nx, ny, _] = dims;
    let seed_voxel = [
        seed as u32 % nx,
        (seed as u32 / nx) % ny,
        seed as u32 / (nx * ny),
    ];
    let script = format!(
        r#"
import numpy as np, scipy.ndimage as ndi
v = np.fromfile("volume.f32", dtype="<f4").reshape(({nz}, {ny}, {nx}))
mask = (v >= np.float32({lo})) & (v <= np.float32({hi}))
labels, n = ndi.label(mask)  # default structure: 6-connected in 3D
comp = labels == labels[{sk}, {sj}, {si}]
comp.astype(np.uint8).tofile("component.u8")
print(n, int(comp.sum()))
"#,
        nx = dims[0],
        ny = dims[1],
        nz = dims[2],
        si = seed_voxel[0],
        sj = seed_voxel[1],
        sk = seed_voxel[2],
    );
    let printed = python(&script, &dir);
    let mut words = printed.split_whitespace();
    let components: u64 = words.next().unwrap().parse().unwrap();
    let size: u64 = words.next().unwrap().parse().unwrap();
    assert!(components > 1, "the volume must have several components");
    let want = std::fs::read(dir.join("component.u8")).unwrap();
    assert_eq!(want.len(), values.len());
    assert!(size > 1000 && size < values.len() as u64 / 2, "size {size}");

    let geometry = VolumeGeometry::axis_aligned(dims, [0.8, 0.8, 1.5]);
    let mut layer = LabelLayer::new_empty(geometry).unwrap();
    let bone = layer.segments_mut().add("bone").unwrap();
    let intensity = DenseIntensity::new(dims, values.clone(), "HU").unwrap();
    let mut reports = 0;
    let (outcome, _) = grow_from_seed(
        &mut layer,
        &intensity,
        seed_voxel,
        bone,
        GrowCriterion::Range(ValueRange::new(f64::from(lo), f64::from(hi)).unwrap()),
        u64::MAX,
        &mut |_| reports += 1,
        None,
    )
    .unwrap();
    assert!(!outcome.stopped_at_cap);
    assert_eq!(outcome.voxels, size);
    assert!(reports >= 1);
    let got = all_labels(&layer);
    let differing = got
        .iter()
        .zip(&want)
        .filter(|(&g, &w)| (g == bone) != (w == 1))
        .count();
    assert_eq!(differing, 0, "voxels differing from scipy's component");
    assert!(outcome.edit.is_some());

    // At a cap the grow keeps exactly the cap, inside scipy's component, and says it stopped.
    let mut capped = LabelLayer::new_empty(VolumeGeometry::axis_aligned(dims, [1.0; 3])).unwrap();
    let b = capped.segments_mut().add("bone").unwrap();
    let (out, _) = grow_from_seed(
        &mut capped,
        &intensity,
        seed_voxel,
        b,
        GrowCriterion::Range(ValueRange::new(f64::from(lo), f64::from(hi)).unwrap()),
        500,
        &mut |_| {},
        None,
    )
    .unwrap();
    assert!(out.stopped_at_cap && out.voxels == 500);
    let got = all_labels(&capped);
    assert_eq!(got.iter().filter(|&&l| l == b).count(), 500);
    assert!(got.iter().zip(&want).all(|(&g, &w)| g != b || w == 1));

    // Cancel: an error and the layer as it was.
    let mut cancelled =
        LabelLayer::new_empty(VolumeGeometry::axis_aligned(dims, [1.0; 3])).unwrap();
    let c = cancelled.segments_mut().add("bone").unwrap();
    let stop = AtomicBool::new(true);
    let all = ValueRange::new(f64::NEG_INFINITY, f64::INFINITY).unwrap();
    let r = grow_from_seed(
        &mut cancelled,
        &intensity,
        seed_voxel,
        c,
        GrowCriterion::Range(all),
        u64::MAX,
        &mut |_| {},
        Some(&stop),
    );
    assert!(matches!(r, Err(SegmentError::Cancelled)));
    assert_eq!(cancelled.edited_brick_count(), 0);
}

#[test]
fn mean_and_sigma_come_from_the_seeds_neighbourhood_and_locks_block_growth() {
    let dims = [40u32, 40, 40];
    // 100 inside a cube, 0 outside, the seed's neighbourhood: 27 voxels of 100 → σ = 0.
    let values: Vec<f32> = (0..40 * 40 * 40)
        .map(|n: u32| {
            let (i, j, k) = (n % 40, (n / 40) % 40, n / 1600);
            if (5..30).contains(&i) && (5..30).contains(&j) && (5..30).contains(&k) {
                100.0
            } else {
                0.0
            }
        })
        .collect();
    let intensity = DenseIntensity::new(dims, values, "").unwrap();
    let mut layer = LabelLayer::new_empty(VolumeGeometry::axis_aligned(dims, [1.0; 3])).unwrap();
    let a = layer.segments_mut().add("a").unwrap();
    let wall = layer.segments_mut().add("wall").unwrap();
    let r = grow_range(
        &layer,
        &intensity,
        [10, 10, 10],
        GrowCriterion::MeanSigma { k: 2.0 },
    )
    .unwrap();
    assert_eq!((r.lo, r.hi), (100.0, 100.0));
    // At the cube's corner the neighbourhood mixes 8 × 100 and 19 × 0.
    let r = grow_range(
        &layer,
        &intensity,
        [5, 5, 5],
        GrowCriterion::MeanSigma { k: 1.0 },
    )
    .unwrap();
    let mean = 800.0 / 27.0;
    let sd = (8.0 * (100.0f64 - mean).powi(2) / 27.0 + 19.0 * mean * mean / 27.0).sqrt();
    assert!((r.lo - (mean - sd)).abs() < 1e-9 && (r.hi - (mean + sd)).abs() < 1e-9);
    // A locked wall at k = 17 splits the cube: the grow neither paints nor crosses it.
    layer
        .edit("wall", |w| {
            for j in 0..40 {
                for i in 0..40 {
                    w.set([i, j, 17], wall)?;
                }
            }
            Ok(())
        })
        .unwrap();
    layer.segments_mut().get_mut(wall).unwrap().locked = true;
    let (out, _) = grow_from_seed(
        &mut layer,
        &intensity,
        [10, 10, 10],
        a,
        GrowCriterion::MeanSigma { k: 0.5 },
        u64::MAX,
        &mut |_| {},
        None,
    )
    .unwrap();
    assert_eq!(out.voxels, 25 * 25 * 12);
    assert!(voxels_of(&layer, a).iter().all(|v| v[2] < 17));
    assert_eq!(voxels_of(&layer, wall).len(), 1600);
}

#[test]
fn a_slice_fill_takes_the_inside_of_a_ring_and_nothing_in_other_slices() {
    let dims = [48u32, 40, 6];
    let mut layer =
        LabelLayer::new_empty(VolumeGeometry::axis_aligned(dims, [0.7, 0.9, 2.0])).unwrap();
    let a = layer.segments_mut().add("a").unwrap();
    let ring = layer.segments_mut().add("ring").unwrap();
    let d2 = |i: u32, j: u32| (i as i64 - 24).pow(2) + (j as i64 - 20).pow(2);
    layer
        .edit("ring", |w| {
            for k in 0..6 {
                for j in 0..40 {
                    for i in 0..48 {
                        if (36..64).contains(&d2(i, j)) {
                            w.set([i, j, k], ring)?;
                        }
                    }
                }
            }
            Ok(())
        })
        .unwrap();
    let out = fill_in_slice(
        &mut layer,
        &SlicePlane::Axial,
        [24, 20, 3],
        a,
        None,
        None,
        u64::MAX,
    )
    .unwrap();
    let want: Vec<[u32; 3]> = (0..40)
        .flat_map(|j| (0..48).map(move |i| [i, j, 3]))
        .filter(|&[i, j, _]| d2(i, j) < 36)
        .collect();
    assert_eq!(voxels_of(&layer, a), want);
    assert_eq!(out.voxels, want.len() as u64);
    // The coronal slice through the centre: left of the ring (i ≤ 16) in every k, bounded by
    // the ring's voxels at |i − 24| ∈ {6, 7}; the right part is another region.
    let out = fill_in_slice(
        &mut layer,
        &SlicePlane::Coronal,
        [0, 20, 0],
        a,
        None,
        None,
        u64::MAX,
    )
    .unwrap();
    assert_eq!(out.voxels, 17 * 6);
    assert_eq!(layer.get([16, 20, 5]).unwrap(), a);
    assert_eq!(layer.get([33, 20, 5]).unwrap(), 0);
    // The sagittal slice through the centre (steps along j and k only): inside the ring,
    // |j − 20| < 6, for k below 3: row k = 3 was filled with a above and cuts the region off
    // from k = 4 and 5.
    let fresh = |layer: &LabelLayer| layer.get([24, 20, 0]).unwrap();
    assert_eq!(fresh(&layer), 0);
    let out = fill_in_slice(
        &mut layer,
        &SlicePlane::Sagittal,
        [24, 20, 0],
        ring,
        None,
        None,
        u64::MAX,
    )
    .unwrap();
    assert_eq!(out.voxels, 11 * 3);
    assert_eq!(layer.get([24, 25, 2]).unwrap(), ring);
    assert_eq!(layer.get([24, 25, 4]).unwrap(), 0);
    assert_eq!(
        layer.get([25, 20, 0]).unwrap(),
        0,
        "nothing outside the sagittal slice"
    );
    // An oblique plane whose directions are not orthonormal is refused, naming them.
    let bad = fill_in_slice(
        &mut layer,
        &SlicePlane::Oblique {
            centre_lps: DVec3::ZERO,
            u: DVec3::X,
            v: DVec3::X,
        },
        [1, 1, 1],
        a,
        None,
        None,
        10,
    );
    assert!(
        matches!(&bad, Err(SegmentError::BadParameter(m)) if m.contains("orthonormal")),
        "{bad:?}"
    );
}

/// The oblique plane of the test below: tilted against every index axis of the rotated grid.
fn tilted_plane(g: &VolumeGeometry) -> (SlicePlane, DVec3, DVec3, DVec3) {
    let centre = g.patient_from_index(DVec3::new(21.3, 19.6, 11.2));
    let u = DVec3::new(0.8, 0.6, 0.0);
    let v = DVec3::new(-0.36, 0.48, 0.8);
    (
        SlicePlane::Oblique {
            centre_lps: centre,
            u,
            v,
        },
        centre,
        u,
        v,
    )
}

#[test]
fn an_oblique_fill_takes_the_inside_of_a_ring_brushed_in_that_plane_and_nothing_off_it() {
    // A ring drawn with the brush in a tilted plane of a rotated, anisotropic grid, then a fill
    // clicked at its centre. The model, voxel by voxel: the voxels whose centre lies in the
    // plane's slab (as brush.rs defines it: -h/2 ≤ n·(x − c) < h/2, h the largest spacing along
    // n), that the ring left unpainted, and whose centre projected into the plane lies within
    // the ring's radius. The ring's band (4 mm) is wider than any step between neighbouring
    // columns (at most √(0.9² + 1.6²) ≈ 1.84 mm), so nothing leaks, and the 48-gon's sagitta
    // (0.02 mm) is far below the band's half width, so "inside the circle" is "inside the ring".
    let g = rotated_anisotropic([44, 40, 24]);
    let (plane, centre, u, v) = tilted_plane(&g);
    let mut layer = LabelLayer::new_empty(g.clone()).unwrap();
    let ring = layer.segments_mut().add("ring").unwrap();
    let inside = layer.segments_mut().add("inside").unwrap();
    let radius_mm = 9.0;
    let circle: Vec<DVec3> = (0..=48)
        .map(|n| {
            let t = std::f64::consts::TAU * f64::from(n) / 48.0;
            centre + (u * t.cos() + v * t.sin()) * radius_mm
        })
        .collect();
    let brush = Brush {
        shape: BrushShape::Disc(plane),
        diameter_mm: 4.0,
        value_range: None,
    };
    stroke(&mut layer, &brush, BrushAction::Paint(ring), &circle, None).unwrap();
    let painted = voxels_of(&layer, ring);
    let painted_set: std::collections::BTreeSet<[u32; 3]> = painted.iter().copied().collect();
    let seed = g.index_from_patient(centre).round();
    let seed = [seed.x as u32, seed.y as u32, seed.z as u32];
    let out = fill_in_slice(&mut layer, &plane, seed, inside, None, None, u64::MAX).unwrap();

    let normal = u.cross(v);
    let half = (0..3)
        .map(|a| g.spacing_mm[a] * normal.dot(DVec3::from(g.direction[a])).abs())
        .fold(0.0, f64::max)
        / 2.0;
    let [nx, ny, nz] = g.dims;
    let mut want = Vec::new();
    let mut outside = Vec::new();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let x = g.patient_from_index(DVec3::new(f64::from(i), f64::from(j), f64::from(k)));
                let off = normal.dot(x - centre);
                let in_plane = (x - normal * off - centre).length();
                if (-half..half).contains(&off)
                    && in_plane < radius_mm
                    && !painted_set.contains(&[i, j, k])
                {
                    want.push([i, j, k]);
                }
                if (-half..half).contains(&off) && in_plane > radius_mm + 3.0 {
                    outside.push([i, j, k]);
                }
            }
        }
    }
    assert!(
        want.len() > 100,
        "the model's inside is too small to test: {}",
        want.len()
    );
    assert_eq!(voxels_of(&layer, inside), want);
    assert_eq!(out.voxels, want.len() as u64);
    assert!(!out.stopped_at_cap);
    assert_eq!(voxels_of(&layer, ring), painted, "the ring is kept");

    // Clicked outside the ring, the fill takes the rest of the slice but never the inside; a
    // cap stops it early, keeping a region connected to the seed, and says so.
    let mut capped = layer.clone();
    let out = fill_in_slice(&mut capped, &plane, outside[0], ring, None, None, 50).unwrap();
    assert_eq!(out.voxels, 50);
    assert!(out.stopped_at_cap);
    assert_eq!(voxels_of(&capped, inside), want);
    assert_eq!(voxels_of(&capped, ring).len(), painted.len() + 50);
}

/// The page's grow, one brick a step (`GrowPlanner`, issue 52 item 4): it takes many steps and
/// ends in exactly the plan `plan_grow` makes in one, for a range and for mean ± k·σ, and under
/// a cap; a step that stops early leaves a partial plan that is not the whole.
#[test]
fn a_grow_planned_one_brick_a_step_equals_the_grow_planned_at_once() {
    use strata_segment::tools::grow::{plan_grow, GrowPlanner};
    let dims = [72u32, 64, 56];
    let values = blobs(dims);
    let intensity = DenseIntensity::new(dims, values.clone(), "HU").unwrap();
    let geometry = VolumeGeometry::axis_aligned(dims, [0.8, 0.7, 1.1]);
    let seed = (0..values.len())
        .find(|&n| values[n] >= 250.0 && n % 7 == 3 && n > values.len() / 3)
        .expect("a bright voxel");
    let [nx, ny, _] = dims;
    let seed: [u32; 3] = [
        seed as u32 % nx,
        (seed as u32 / nx) % ny,
        seed as u32 / (nx * ny),
    ];
    // Half the volume's values: a region through all twelve bricks, each met many times.
    let wide = GrowCriterion::Range(ValueRange::new(0.0, 100000.0).unwrap());
    for (criterion, cap, min_steps) in [
        (wide, u64::MAX, 11),
        (GrowCriterion::MeanSigma { k: 2.0 }, u64::MAX, 0),
        (wide, 5000, 0),
    ] {
        let mut at_once = LabelLayer::new_empty(geometry.clone()).unwrap();
        let label = at_once.segments_mut().add("a").unwrap();
        let mut stepped = at_once.clone();
        let plan = plan_grow(
            &at_once,
            &intensity,
            seed,
            label,
            criterion,
            cap,
            &mut |_| {},
            None,
        )
        .unwrap();
        let voxels = plan.voxels();
        plan.apply(&mut at_once).unwrap();

        let mut planner =
            GrowPlanner::start(&stepped, &intensity, seed, label, criterion, cap).unwrap();
        let mut steps = 0;
        while !planner
            .step(&stepped, &intensity, Some(1), &mut |_| {}, None)
            .unwrap()
        {
            steps += 1;
            assert!(planner.voxels() <= voxels);
        }
        assert!(steps >= min_steps, "{criterion:?}: only {steps} steps");
        assert_eq!(planner.voxels(), voxels, "{criterion:?}");
        planner.into_plan().apply(&mut stepped).unwrap();
        assert_eq!(
            all_labels(&stepped),
            all_labels(&at_once),
            "{criterion:?} cap {cap}"
        );
    }
}
