//! Fill between slices against the frustum; islands, margins and logical operations against
//! brute-force models.

use glam::DVec3;
use strata_segment::tools::brush::{stroke, Brush, BrushAction, BrushShape, SlicePlane};
use strata_segment::tools::interpolate::fill_between_slices;
use strata_segment::tools::morphology::{
    combine, margin, remove_islands, Islands, LogicalOp, Operand,
};
use strata_segment::{Label, LabelLayer};
use strata_types::VolumeGeometry;

use super::common::{all_labels, voxels_of};

#[test]
fn fill_between_two_discs_gives_the_frustum_within_five_percent() {
    let spacing = [0.7, 0.9, 1.5];
    let g = VolumeGeometry::axis_aligned([64, 56, 24], spacing);
    let mut layer = LabelLayer::new_empty(g.clone()).unwrap();
    let a = layer.segments_mut().add("a").unwrap();
    let centre = |k: f64| g.patient_from_index(DVec3::new(31.0, 27.5, k));
    let (r0, r1) = (6.0, 14.0);
    for (k, r) in [(0.0, r0), (20.0, r1)] {
        let disc = Brush {
            shape: BrushShape::Disc(SlicePlane::Axial),
            diameter_mm: 2.0 * r,
            value_range: None,
        };
        stroke(&mut layer, &disc, BrushAction::Paint(a), &[centre(k)], None).unwrap();
    }
    let drawn = voxels_of(&layer, a).len();
    let edit = fill_between_slices(&mut layer, a, &SlicePlane::Axial)
        .unwrap()
        .expect("slices filled");
    assert!(!edit.changes.is_empty());
    let voxels = voxels_of(&layer, a);
    assert!(voxels.iter().all(|v| v[2] <= 20));
    let voxel_mm3 = spacing.iter().product::<f64>();
    // Each slice stands for a slab 1.5 mm thick: slices 0..=20 cover z from −0.5 to 20.5 slices,
    // where the radius runs linearly from r0 to r1 between the drawn slices' centres.
    let frustum = |z0: f64, z1: f64| {
        let r = |z: f64| r0 + (r1 - r0) * z / 20.0;
        let h = (z1 - z0) * spacing[2];
        std::f64::consts::PI * h / 3.0 * (r(z0).powi(2) + r(z0) * r(z1) + r(z1).powi(2))
    };
    let all = voxels.len() as f64 * voxel_mm3;
    let between = (voxels.len() - drawn) as f64 * voxel_mm3;
    let (want_all, want_between) = (frustum(-0.5, 20.5), frustum(0.5, 19.5));
    assert!(
        (all / want_all - 1.0).abs() < 0.05,
        "{all} vs {want_all} mm³"
    );
    assert!(
        (between / want_between - 1.0).abs() < 0.05,
        "{between} vs {want_between} mm³"
    );
    // And every slice between is the disc of the interpolated radius, give or take a voxel.
    for k in 1..20u32 {
        let r = r0 + (r1 - r0) * f64::from(k) / 20.0;
        let c = centre(f64::from(k));
        for j in 0..56 {
            for i in 0..64 {
                let d = (g.patient_from_index(DVec3::new(i as f64, j as f64, f64::from(k))) - c)
                    .length();
                let inside = layer.get([i, j, k]).unwrap() == a;
                assert!(
                    (inside || d >= r - 1.0) && (!inside || d <= r + 1.0),
                    "{i},{j},{k}"
                );
            }
        }
    }
}

/// A sparse hashed noise mask: many islands of many sizes.
fn noise(dims: [u32; 3], percent: u32) -> Vec<bool> {
    (0..dims.iter().product::<u32>())
        .map(|n| (n.wrapping_mul(2654435761) >> 7) % 100 < percent)
        .collect()
}

fn layer_from(g: &VolumeGeometry, masks: &[(&[bool], Label)]) -> LabelLayer {
    let mut layer = LabelLayer::new_empty(g.clone()).unwrap();
    let [nx, ny, _] = g.dims;
    let count = masks.iter().map(|m| m.1).max().unwrap_or(0);
    for n in 0..count {
        layer.segments_mut().add(format!("s{n}")).unwrap();
    }
    layer
        .edit("setup", |w| {
            for (mask, label) in masks {
                for (n, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
                    let n = n as u32;
                    w.set([n % nx, (n / nx) % ny, n / (nx * ny)], *label)?;
                }
            }
            Ok(())
        })
        .unwrap();
    layer
}

/// Brute-force 6-connected components: an id per voxel (0 outside the mask), sizes by id.
fn model_components(dims: [u32; 3], mask: &[bool]) -> (Vec<usize>, Vec<usize>) {
    let [nx, ny, nz] = dims.map(|d| d as usize);
    let mut id = vec![0usize; mask.len()];
    let mut sizes = vec![0usize];
    for start in 0..mask.len() {
        if !mask[start] || id[start] != 0 {
            continue;
        }
        sizes.push(0);
        let c = sizes.len() - 1;
        let mut stack = vec![start];
        id[start] = c;
        while let Some(n) = stack.pop() {
            sizes[c] += 1;
            let (i, j, k) = (n % nx, (n / nx) % ny, n / (nx * ny));
            let mut near = Vec::new();
            if i > 0 {
                near.push(n - 1)
            }
            if i + 1 < nx {
                near.push(n + 1)
            }
            if j > 0 {
                near.push(n - nx)
            }
            if j + 1 < ny {
                near.push(n + nx)
            }
            if k > 0 {
                near.push(n - nx * ny)
            }
            if k + 1 < nz {
                near.push(n + nx * ny)
            }
            for m in near {
                if mask[m] && id[m] == 0 {
                    id[m] = c;
                    stack.push(m);
                }
            }
        }
    }
    (id, sizes)
}

#[test]
fn islands_are_removed_as_a_brute_force_component_labelling_says() {
    // 40 × 36 × 34: bricks meet inside the volume, so components cross brick borders.
    let dims = [40u32, 36, 34];
    let g = VolumeGeometry::axis_aligned(dims, [1.0; 3]);
    // A ball across the brick borders at 32 among noise: one large island and many small ones.
    let mask: Vec<bool> = noise(dims, 20)
        .iter()
        .enumerate()
        .map(|(n, &x)| {
            let n = n as i64;
            let (i, j, k) = (n % 40 - 27, (n / 40) % 36 - 28, n / (40 * 36) - 27);
            x || i * i + j * j + k * k < 81
        })
        .collect();
    let other = noise(dims, 3);
    let other: Vec<bool> = other.iter().zip(&mask).map(|(&o, &m)| o && !m).collect();
    let (id, sizes) = model_components(dims, &mask);
    assert!(sizes.len() > 100, "many islands: {}", sizes.len());

    let mut layer = layer_from(&g, &[(&mask, 1), (&other, 2)]);
    let (_, removed) = remove_islands(&mut layer, 1, Islands::RemoveSmallerThan(4)).unwrap();
    let want: Vec<Label> = (0..mask.len())
        .map(|n| {
            if mask[n] && sizes[id[n]] >= 4 {
                1
            } else if other[n] {
                2
            } else {
                0
            }
        })
        .collect();
    assert_eq!(removed, sizes.iter().skip(1).filter(|&&s| s < 4).count());
    assert_eq!(all_labels(&layer), want);

    let mut layer = layer_from(&g, &[(&mask, 1), (&other, 2)]);
    remove_islands(&mut layer, 1, Islands::KeepLargest).unwrap();
    let largest = (1..sizes.len()).max_by_key(|&c| sizes[c]).unwrap();
    assert!(sizes[largest] > 1000, "a large component crossing bricks");
    let want: Vec<Label> = (0..mask.len())
        .map(|n| {
            if mask[n] && id[n] == largest {
                1
            } else if other[n] {
                2
            } else {
                0
            }
        })
        .collect();
    assert_eq!(all_labels(&layer), want);
}

#[test]
fn margins_grow_and_shrink_as_brute_force_distances_in_mm_say() {
    let dims = [30u32, 28, 20];
    let spacing = [0.7, 1.1, 1.6];
    let g = VolumeGeometry::axis_aligned(dims, spacing);
    let [nx, ny, _] = dims;
    let at = |n: usize| [n as u32 % nx, (n as u32 / nx) % ny, n as u32 / (nx * ny)];
    let mm = |a: [u32; 3], b: [u32; 3]| {
        (0..3)
            .map(|x| ((a[x] as f64 - b[x] as f64) * spacing[x]).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    // Two blobs (one touching the grid's edge) and another segment in the way.
    let n = (nx * ny * dims[2]) as usize;
    let seg: Vec<bool> = (0..n)
        .map(|x| {
            let v = at(x);
            mm(v, [10, 12, 8]) < 4.0 || mm(v, [26, 5, 18]) < 3.5
        })
        .collect();
    let wall: Vec<bool> = (0..n).map(|x| at(x)[0] == 16 && !seg[x]).collect();
    let seg_voxels: Vec<[u32; 3]> = (0..n).filter(|&x| seg[x]).map(at).collect();

    let mut layer = layer_from(&g, &[(&seg, 1), (&wall, 2)]);
    margin(&mut layer, 1, 2.3).unwrap();
    let want: Vec<Label> = (0..n)
        .map(|x| {
            if wall[x] {
                2
            } else if seg[x] || seg_voxels.iter().any(|&s| mm(at(x), s) <= 2.3 + 1e-9) {
                1
            } else {
                0
            }
        })
        .collect();
    assert!(want.iter().filter(|&&l| l == 1).count() > 2 * seg_voxels.len());
    assert_eq!(all_labels(&layer), want);

    let mut layer = layer_from(&g, &[(&seg, 1), (&wall, 2)]);
    margin(&mut layer, 1, -1.9).unwrap();
    let not_seg: Vec<[u32; 3]> = (0..n).filter(|&x| !seg[x]).map(at).collect();
    let want: Vec<Label> = (0..n)
        .map(|x| {
            if wall[x] {
                2
            } else if seg[x] && !not_seg.iter().any(|&s| mm(at(x), s) <= 1.9 + 1e-9) {
                1
            } else {
                0
            }
        })
        .collect();
    let kept = want.iter().filter(|&&l| l == 1).count();
    assert!(kept > 0 && kept < seg_voxels.len() / 2, "kept {kept}");
    assert_eq!(all_labels(&layer), want);
}

#[test]
fn logical_operations_act_on_the_masks_and_respect_locks() {
    let dims = [36u32, 34, 10];
    let g = VolumeGeometry::axis_aligned(dims, [1.0; 3]);
    let a = noise(dims, 40);
    let b = noise([36, 34, 11], 40)[..a.len()].to_vec();
    let locked: Vec<bool> = (0..a.len()).map(|n| n % 97 == 0).collect();
    let a_only: Vec<bool> = a.iter().zip(&locked).map(|(&x, &l)| x && !l).collect();
    // The operand lives in another layer on the same grid.
    let other = layer_from(&g, &[(&b, 1)]);
    for op in [LogicalOp::Union, LogicalOp::Intersect, LogicalOp::Subtract] {
        let mut layer = layer_from(&g, &[(&a_only, 1), (&locked, 2)]);
        layer.segments_mut().get_mut(2).unwrap().locked = true;
        combine(&mut layer, 1, op, Operand::Other(&other, 1)).unwrap();
        let want: Vec<Label> = (0..a.len())
            .map(|n| {
                if locked[n] {
                    return 2;
                }
                let inside = match op {
                    LogicalOp::Union => a_only[n] || b[n],
                    LogicalOp::Intersect => a_only[n] && b[n],
                    LogicalOp::Subtract => a_only[n] && !b[n],
                };
                if inside {
                    1
                } else {
                    0
                }
            })
            .collect();
        assert_eq!(all_labels(&layer), want, "{op:?}");
    }
    // An operand on another grid is refused.
    let elsewhere = layer_from(&VolumeGeometry::axis_aligned(dims, [0.5; 3]), &[(&b, 1)]);
    let mut layer = layer_from(&g, &[(&a_only, 1)]);
    assert!(combine(
        &mut layer,
        1,
        LogicalOp::Union,
        Operand::Other(&elsewhere, 1)
    )
    .is_err());
    // Within one layer a union moves the operand's voxels into the target.
    let b_only: Vec<bool> = b.iter().zip(&a).map(|(&x, &y)| x && !y).collect();
    let mut layer = layer_from(&g, &[(&a, 1), (&b_only, 2)]);
    combine(&mut layer, 1, LogicalOp::Union, Operand::Segment(2)).unwrap();
    assert!(voxels_of(&layer, 2).is_empty());
    assert_eq!(
        voxels_of(&layer, 1).len(),
        a.iter().zip(&b).filter(|(&x, &y)| x || y).count()
    );
}
