//! The octree traversal (octree paper §5.2; octree.wgsl, gpu_octree.rs): the GPU's leaf walk
//! visits exactly the leaves a brute-force test of every leaf finds, in order, with their
//! entry and exit t, on random mixed-level cuts (2:1 balanced and not); the raycaster over the
//! node buffer makes the flat table's images for DVR, shaded DVR, MIP and isosurfaces, with
//! smooth level transitions off and on (their edge and corner neighbours found by point
//! queries), within the f64 reference's bounds.
use crate::common;
use common::*;
use strata_render::model::octree_cut::test_cuts::{cuts, rays, Rng};
use strata_render::model::octree_cut::{LeafVisit, OctreeCut};
use strata_render::passes::octree_probe::walk_on_gpu;
use strata_render::testdata::phantom;
use strata_render::*;

const SIZE: u32 = 128;

/// Visits the f32 walk may see or miss by rounding: a leaf crossed for less than this (page
/// cells) at a face, edge or corner. Everything longer must match.
const SLIVER: f64 = 1e-4;

fn long_visits(v: &[LeafVisit]) -> Vec<LeafVisit> {
    v.iter()
        .copied()
        .filter(|x| x.t_exit - x.t_enter > SLIVER)
        .collect()
}

#[test]
fn gpu_walk_visits_the_brute_force_leaves_in_order() {
    let ctx = gpu();
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let (mut rays_checked, mut visits) = (0usize, 0usize);
    for (name, table) in cuts() {
        let cut = OctreeCut::from_page_table(&table);
        let rays = rays(table.page_dims, &mut rng);
        let got = walk_on_gpu(&ctx, &cut, &rays, 256).unwrap();
        for ((o, d, t0, t1), got) in rays.iter().zip(&got) {
            let want = long_visits(&cut.leaves_on_ray_brute_force(*o, *d, *t0, *t1));
            let got = long_visits(got);
            let nodes = |v: &[LeafVisit]| v.iter().map(|x| x.node).collect::<Vec<_>>();
            assert_eq!(
                nodes(&got),
                nodes(&want),
                "{name}: ray {o:?} + t {d:?} [{t0}, {t1}]"
            );
            // f32 on the GPU: a t of a few dozen cells is good to ~1e-5.
            for (g, w) in got.iter().zip(&want) {
                let tol = 1e-4 * (1.0 + w.t_enter.abs().max(w.t_exit.abs()));
                assert!(
                    (g.t_enter - w.t_enter).abs() <= tol && (g.t_exit - w.t_exit).abs() <= tol,
                    "{name}: ray {o:?} + t {d:?}: {g:?} vs {w:?}"
                );
            }
            rays_checked += 1;
            visits += got.len();
        }
    }
    eprintln!("{rays_checked} rays, {visits} leaf visits matched");
    assert!(visits > 1000, "too few leaf visits to prove much: {visits}");
}

/// 256³ phantom, 8³ pages. `mixed`: level 2 for x ≥ 4, level 1 for y ≥ 4, level 0 elsewhere
/// except page (1, 1, 1), which shows its level-1 parent (a stand-in for pending children),
/// pages z = 7, x < 4 not resident. `unbalanced`: level 2 for x ≥ 4 next to level 0 (two
/// levels apart, not 2:1).
fn fixtures() -> Vec<(&'static str, Fixture)> {
    let volume = || {
        phantom::ct_phantom(
            VolumeGeometry::axis_aligned([256; 3], [1.0; 3]),
            None,
            Some(80.0),
        )
        .unwrap()
    };
    let v = volume();
    let mut mixed = v.page_table_with_levels(|p| {
        if p[0] >= 4 {
            2
        } else if p[1] >= 4 || p == [1, 1, 1] {
            1
        } else {
            0
        }
    });
    for i in 0..mixed.entries.len() {
        let p = mixed.page_of_linear(i);
        if p[2] == 7 && p[0] < 4 {
            mixed.entries[i] = PageEntry::NOT_RESIDENT;
        }
    }
    let v2 = volume();
    let unbalanced = v2.page_table_with_levels(|p| if p[0] >= 4 { 2 } else { 0 });
    vec![
        ("mixed", Fixture::new(v, mixed, test_tf())),
        ("unbalanced", Fixture::new(v2, unbalanced, test_tf())),
    ]
}

fn octree_index(ctx: &GpuContext, f: &Fixture, cache: &BrickCache) -> GpuPageTable {
    let index = GpuPageTable::with_traversal(
        &ctx.device,
        f.volume.geometry.page_dims(),
        cache,
        Traversal::Octree,
    )
    .unwrap();
    index.update(&ctx.queue, &f.page_table).unwrap();
    index
        .update_value_max(
            &ctx.queue,
            &f.page_table
                .value_max_physical(f.volume.mapping, |l, n| f.volume.node_range(l, n)),
        )
        .unwrap();
    index
}

fn cameras(f: &Fixture) -> Vec<(&'static str, Camera)> {
    let g = &f.volume.geometry;
    let centre = g.centre_patient();
    vec![
        ("oblique", orbit(g, 35.0, 25.0, 1.5, 35.0)),
        (
            // Orthographic rays along an index axis, on the page faces' planes.
            "axis",
            Camera::look_at(
                [centre.x, centre.y, centre.z - 600.0],
                [centre.x, centre.y, centre.z],
                [0.0, -1.0, 0.0],
                Projection::Orthographic { height_mm: 300.0 },
            ),
        ),
        (
            // Rays starting inside the volume.
            "inside",
            Camera::look_at(
                [centre.x + 90.0, centre.y - 70.0, centre.z + 40.0],
                [centre.x - 50.0, centre.y + 30.0, centre.z - 20.0],
                [0.0, 0.0, 1.0],
                Projection::Perspective { fov_y_deg: 60.0 },
            ),
        ),
    ]
}

const MODES: [(&str, RenderMode, Option<Shading>); 4] = [
    ("dvr", RenderMode::Dvr, None),
    (
        "dvr-shaded",
        RenderMode::Dvr,
        Some(Shading {
            ambient: 0.25,
            diffuse: 0.75,
            specular: 0.3,
            shininess: 24.0,
        }),
    ),
    ("mip", RenderMode::Mip, None),
    ("iso", RenderMode::Isosurface, None),
];

#[test]
fn octree_traversal_makes_the_flat_tables_images() {
    let ctx = gpu();
    for (cut_name, f) in fixtures() {
        let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
        let octree = octree_index(&ctx, &f, &g.cache);
        let leaves = octree.octree_leaves().unwrap();
        eprintln!(
            "{cut_name}: {} page cells, {} leaves; index bytes flat {} octree {}",
            g.page_table.entry_count(),
            leaves.boxes.len(),
            g.page_table.gpu_index_bytes(),
            octree.gpu_index_bytes()
        );
        for (view, cam) in cameras(&f) {
            for ((mode_name, mode, shading), smooth) in
                MODES.into_iter().flat_map(|m| [(m, false), (m, true)])
            {
                let s = RenderSettings {
                    shading,
                    iso_value: 300.0,
                    smooth_transitions: smooth,
                    ..compare_settings(mode, SIZE)
                };
                let flat = g.render(&ctx, &f, &cam, &s);
                let scene = FrameInputs {
                    cache: &g.cache,
                    page_table: &octree,
                    transfer_function: &g.tf,
                    geometry: &f.volume.geometry,
                    mapping: f.volume.mapping,
                    camera: &cam,
                    settings: &s,
                };
                let key = g.raycaster.key_for_scene(&scene);
                assert!(key.octree);
                // Both cuts have coarser neighbours: the transition code is compiled in, for
                // the flat table and the octree alike.
                assert_eq!(key.smooth_transitions, smooth);
                let flat_key = g.raycaster.key_for_scene(&FrameInputs {
                    page_table: &g.page_table,
                    ..scene
                });
                assert_eq!(flat_key.smooth_transitions, smooth);
                let tree = g.raycaster.render_blocking(&ctx, &scene).unwrap();
                assert_clean(&tree);
                let c = compare_rgba8(&flat.rgba, &tree.rgba).unwrap();
                let smoothing = if smooth { "smooth" } else { "hard" };
                let name = format!("{cut_name}/{view}/{mode_name}/{smoothing}");
                eprintln!(
                    "{name}: samples {:?} vs {:?}, index reads per pixel {:.2} vs {:.2}, image {c:?}",
                    flat.samples,
                    tree.samples,
                    flat.page_reads.unwrap() as f64 / (SIZE * SIZE) as f64,
                    tree.page_reads.unwrap() as f64 / (SIZE * SIZE) as f64,
                );
                // Same lattice, same skipped regions (a leaf's box is the flat table's whole
                // node or skip block), the same page word for every sample: the same image.
                // The one freedom is a sample within f32 rounding of a leaf face, which the two
                // lookups may give to different leaves of equal payload (the apron): a sample
                // count off by a handful, a pixel by 1/255. With smoothing, a band sample's
                // coarser neighbour is the leaf a point query finds for the neighbour cell,
                // whose word is the flat table's for that cell, and its mask the node's: the
                // same blend, the same arithmetic.
                assert!(c.max_abs_error <= 1, "{name}: {c:?}");
                assert_eq!(c.pixels_off_by_more_than_one, 0, "{name}: {c:?}");
                let (sf, so) = (flat.samples.unwrap() as i64, tree.samples.unwrap() as i64);
                assert!(
                    (sf - so).abs() * 1000 <= sf.max(1),
                    "{name}: samples {sf} vs {so}"
                );
                // Visibility per leaf, read back per page cell: every cell the flat march saw
                // lies in a leaf the octree march saw.
                assert_eq!(tree.visibility.len(), flat.visibility.len(), "{name}");
                let seen = flat.visibility.iter().filter(|&&v| v != 0).count();
                for (i, (&a, &b)) in flat.visibility.iter().zip(&tree.visibility).enumerate() {
                    assert!(a == 0 || b != 0, "{name}: page {i} seen by flat only");
                }
                assert!(
                    seen > 0 || mode == RenderMode::Mip,
                    "{name}: nothing visible"
                );
            }
        }
    }
}

#[test]
fn octree_traversal_matches_the_reference() {
    let ctx = gpu();
    // One cut (the f64 reference is the slow part): the other's octree images equal its flat
    // table's bit for bit (octree_traversal_makes_the_flat_tables_images).
    for (cut_name, f) in fixtures().into_iter().take(1) {
        let g = GpuScene::new(&ctx, &f, CacheConfig::default());
        let octree = octree_index(&ctx, &f, &g.cache);
        let mut raycaster = Raycaster::new(&ctx, &g.cache);
        let cam = orbit(&f.volume.geometry, 35.0, 25.0, 2.5, 35.0);
        // The bars of gpu_vs_reference.rs and node_extent.rs: lavapipe's sampler uses 8-bit
        // trilinear weights, which 40 dB / max 24 absorbs; isosurface silhouettes are opaque,
        // so the max is free there and the count of such pixels bounded (1 %). Without smooth
        // transitions (refused with the octree) the field jumps at level faces, and where the
        // iso value lies inside a jump, f32 and f64 put the hit on different sides of the face:
        // a few opaque pixels flip (15 of 16384 here, flat and octree alike), hence 30 dB
        // for isosurfaces.
        for (name, mode, max_abs, min_psnr) in [
            ("dvr", RenderMode::Dvr, 24u8, 40.0),
            ("mip", RenderMode::Mip, 24, 40.0),
            ("iso", RenderMode::Isosurface, 255, 30.0),
        ] {
            let s = RenderSettings {
                iso_value: 300.0,
                shading: (mode != RenderMode::Mip).then(Shading::default),
                smooth_transitions: false,
                ..compare_settings(mode, SIZE)
            };
            let scene = FrameInputs {
                cache: &g.cache,
                page_table: &octree,
                transfer_function: &g.tf,
                geometry: &f.volume.geometry,
                mapping: f.volume.mapping,
                camera: &cam,
                settings: &s,
            };
            let frame = raycaster.render_blocking(&ctx, &scene).unwrap();
            let flat = raycaster
                .render_blocking(
                    &ctx,
                    &FrameInputs {
                        page_table: &g.page_table,
                        ..scene
                    },
                )
                .unwrap();
            let reference = f.reference(&cam, &s, 8.0);
            let c = assert_close(
                &format!("octree-{cut_name}-{name}"),
                &frame,
                &reference,
                min_psnr,
                max_abs,
            );
            // And the flat table's image, bit for bit (octree_traversal_makes_the_flat_tables_images
            // checks more views).
            assert_eq!(frame.rgba, flat.rgba, "{cut_name}/{name}");
            if mode == RenderMode::Isosurface {
                assert!(
                    c.pixels_off_by_more_than_one * 100 <= (SIZE * SIZE) as usize,
                    "{cut_name}/{name}: more than 1% of pixels off: {c:?}"
                );
            }
        }
    }
}

#[test]
fn smooth_octree_traversal_matches_the_reference() {
    let ctx = gpu();
    // Both cuts: the unbalanced one's level-0 nodes blend into level-2 neighbours two levels
    // up (not guaranteed continuous, smooth_transitions.rs, but the reference blends the same
    // way); the mixed one has a parent standing in for its children and a not-resident slab.
    for (cut_name, f) in fixtures() {
        let g = GpuScene::new(&ctx, &f, CacheConfig::default());
        let octree = octree_index(&ctx, &f, &g.cache);
        assert!(octree.transition_fraction() > 0.0, "{cut_name}");
        let mut raycaster = Raycaster::new(&ctx, &g.cache);
        let cam = orbit(&f.volume.geometry, 35.0, 25.0, 2.5, 35.0);
        // The bars of the flat table's smooth-transition test (smooth_transitions.rs,
        // gpu_matches_reference_on_mixed_cuts_with_smoothing): 40 dB / max 24 (lavapipe's 8-bit
        // trilinear weights; the blend adds one f32 lerp); isosurface pixels are opaque, so
        // the max is free there and the count of pixels off by more than 1/255 bounded (1 %).
        // MIP with the bar of the single-level comparisons.
        for (name, mode, shading, max_abs) in [
            ("dvr", RenderMode::Dvr, None, 24u8),
            ("dvr-shaded", RenderMode::Dvr, Some(Shading::default()), 24),
            ("mip", RenderMode::Mip, None, 24),
            ("iso", RenderMode::Isosurface, Some(Shading::default()), 255),
        ] {
            let s = RenderSettings {
                iso_value: 300.0,
                shading,
                ..compare_settings(mode, SIZE)
            };
            assert!(s.smooth_transitions);
            let scene = FrameInputs {
                cache: &g.cache,
                page_table: &octree,
                transfer_function: &g.tf,
                geometry: &f.volume.geometry,
                mapping: f.volume.mapping,
                camera: &cam,
                settings: &s,
            };
            let key = raycaster.key_for_scene(&scene);
            assert!(key.octree && key.smooth_transitions);
            let frame = raycaster.render_blocking(&ctx, &scene).unwrap();
            assert_clean(&frame);
            let reference = f.reference(&cam, &s, 8.0);
            // The unbalanced cut's two-level jumps stay discontinuous with the blend (it is
            // C0 only for 2:1 cuts, smooth_transitions.rs): where the iso value lies inside such
            // a jump, f32 and f64 put the hit on different sides of the face and a few opaque
            // pixels flip (19 of 16384, flat and octree alike), hence the unsmoothed iso bar of
            // octree_traversal_matches_the_reference (30 dB) there.
            let min_psnr = if cut_name == "unbalanced" && mode == RenderMode::Isosurface {
                30.0
            } else {
                40.0
            };
            let c = assert_close(
                &format!("octree-smooth-{cut_name}-{name}"),
                &frame,
                &reference,
                min_psnr,
                max_abs,
            );
            if mode == RenderMode::Isosurface {
                assert!(
                    c.pixels_off_by_more_than_one * 100 <= (SIZE * SIZE) as usize,
                    "{cut_name}/{name}: more than 1% of pixels off: {c:?}"
                );
            }
            // Smoothing changes this picture (else the test would prove nothing about it).
            let hard = raycaster
                .render_blocking(
                    &ctx,
                    &FrameInputs {
                        settings: &RenderSettings {
                            smooth_transitions: false,
                            ..s.clone()
                        },
                        ..scene
                    },
                )
                .unwrap();
            assert_ne!(
                hard.rgba, frame.rgba,
                "{cut_name}/{name}: smoothing had no effect"
            );
        }
    }
}
