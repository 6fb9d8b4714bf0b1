//! Smooth mixed-resolution transitions (smooth_transitions.rs): the field is continuous across
//! every face, edge and corner where levels meet, on the CPU and on the GPU (probe pass), and
//! GPU images of mixed cuts match the reference with smoothing on.
use crate::common;
use common::*;
use glam::DVec3;
use strata_render::model::field::sample_field;
use strata_render::model::smooth_transitions::transition_masks;
use strata_render::testdata::phantom;
use strata_render::*;

const SIZE: u32 = 128;
const REFINE: f64 = 8.0;

fn phantom_128() -> BrickedVolume {
    phantom::ct_phantom(VolumeGeometry::axis_aligned([128; 3], [1.0; 3]), None, None).unwrap()
}

/// Level-1 nodes in a 3D checkerboard of the 2×2×2 level-1 grid, level 0 elsewhere: every fine
/// node has coarse faces, edges and corners in all the combinations of the paper's Fig. 6.
fn checker_levels(p: [u32; 3]) -> u8 {
    ((p[0] >> 1) + (p[1] >> 1) + (p[2] >> 1)).is_multiple_of(2) as u8
}

/// One coarse level-1 node in a corner of the volume: fine nodes touch it by a face only, by an
/// edge only and by a corner only.
fn corner_block_levels(p: [u32; 3]) -> u8 {
    (p[0] >= 2 && p[1] >= 2 && p[2] >= 2) as u8
}

/// Points on both sides of every face between two pages (same level or not), half of them
/// within a voxel of the face's edges, where face, edge and corner bands meet.
fn crossings(table: &PageTable, per_face: usize, eps: f64) -> Vec<(DVec3, DVec3, bool)> {
    let mut rng = 0x9e3779b97f4a7c15u64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng >> 11) as f64 / (1u64 << 53) as f64
    };
    let d = table.page_dims;
    let mut out = Vec::new();
    for z in 0..d[2] {
        for y in 0..d[1] {
            for x in 0..d[0] {
                let page = [x, y, z];
                for axis in 0..3 {
                    if page[axis] + 1 >= d[axis] {
                        continue;
                    }
                    let mut other = page;
                    other[axis] += 1;
                    let mixed = table.get(page).level != table.get(other).level;
                    let plane = 32.0 * (page[axis] + 1) as f64 - 0.5;
                    for i in 0..per_face {
                        let mut p = DVec3::ZERO;
                        for a in 0..3 {
                            let lo = 32.0 * page[a] as f64 - 0.5;
                            p[a] = if i % 2 == 0 {
                                lo + 32.0 * next()
                            } else if next() < 0.5 {
                                lo + next()
                            } else {
                                lo + 32.0 - next()
                            };
                        }
                        p[axis] = plane;
                        let mut e = DVec3::ZERO;
                        e[axis] = eps;
                        out.push((p - e, p + e, mixed));
                    }
                }
            }
        }
    }
    out
}

/// Largest |F(a) − F(b)| over the crossings, split into level faces and same-level faces.
fn cpu_jumps(
    volume: &BrickedVolume,
    table: &PageTable,
    smooth: bool,
    lines: &[(DVec3, DVec3, bool)],
) -> (f64, f64) {
    let masks = smooth.then(|| transition_masks(table));
    let value = |p: DVec3| {
        let s = sample_field(volume, table, masks.as_deref(), volume.geometry.dims, p).unwrap();
        volume.mapping.physical(s.value)
    };
    let (mut mixed, mut same) = (0.0f64, 0.0f64);
    for (a, b, is_mixed) in lines {
        let jump = (value(*a) - value(*b)).abs();
        if *is_mixed {
            mixed = mixed.max(jump);
        } else {
            same = same.max(jump);
        }
    }
    (mixed, same)
}

#[test]
fn cpu_field_is_continuous_across_faces_edges_and_corners_only_with_smoothing() {
    let volume = phantom_128();
    for (name, levels) in [
        ("checker", checker_levels as fn([u32; 3]) -> u8),
        ("corner-block", corner_block_levels),
    ] {
        let table = volume.page_table_with_levels(levels);
        // 1e-7 voxels either side: in f64 the field's slope (< 1e4 HU per voxel even in a band
        // next to a 1000 HU step) moves it by < 2e-3 HU over that distance.
        let lines = crossings(&table, 64, 1e-7);
        let (smooth_mixed, smooth_same) = cpu_jumps(&volume, &table, true, &lines);
        let (hard_mixed, hard_same) = cpu_jumps(&volume, &table, false, &lines);
        eprintln!(
            "{name}: max jump across level faces {smooth_mixed:.2e} HU smooth vs \
             {hard_mixed:.1} HU discontinuous; same-level faces {smooth_same:.2e} vs {hard_same:.2e}"
        );
        assert!(
            smooth_mixed < 2e-3 && smooth_same < 2e-3,
            "{name}: smoothing left a jump"
        );
        // The baseline really jumps (level-1 values are 2×2×2 means, so edges of the phantom's
        // structures differ by tens of HU or more), otherwise this test would prove nothing.
        assert!(
            hard_mixed > 20.0,
            "{name}: discontinuous baseline shows no jump"
        );
        assert!(
            hard_same < 2e-3,
            "{name}: same-level faces must be continuous anyway"
        );
    }
}

#[test]
fn gpu_probe_matches_cpu_field_and_is_continuous() {
    let ctx = gpu();
    let volume = phantom_128();
    let table = volume.page_table_with_levels(checker_levels);
    let f = Fixture::new(volume, table, test_tf());
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 30.0, 20.0, 1.0, 35.0);
    // ε = 1e-3 voxels: f32 positions near index 100 resolve ~1e-5; over 2ε the field moves by
    // at most 2e-3 · (steepest slope, a few hundred HU per voxel here).
    let lines = crossings(&f.page_table, 16, 1e-3);
    let points: Vec<[f32; 3]> = lines
        .iter()
        .flat_map(|(a, b, _)| [a.as_vec3().to_array(), b.as_vec3().to_array()])
        .collect();
    let masks = transition_masks(&f.page_table);
    for smooth in [true, false] {
        // Exact trilinear: lavapipe's sampler quantises weights to 8 bits, which alone moves a
        // value by up to 1/256 of a voxel-to-voxel difference; the probe must see the field.
        let settings = RenderSettings {
            smooth_transitions: smooth,
            exact_trilinear: true,
            ..compare_settings(RenderMode::Dvr, 16)
        };
        let scene = FrameInputs {
            cache: &g.cache,
            page_table: &g.page_table,
            transfer_function: &g.tf,
            geometry: &f.volume.geometry,
            mapping: f.volume.mapping,
            camera: &cam,
            settings: &settings,
        };
        assert_eq!(g.raycaster.key_for_scene(&scene).smooth_transitions, smooth);
        let values = g.raycaster.probe_field(&ctx, &scene, &points).unwrap();
        let mut worst_vs_cpu = 0.0f64;
        let (mut jump_mixed, mut jump_same) = (0.0f64, 0.0f64);
        for (i, (a, b, mixed)) in lines.iter().enumerate() {
            let (ga, gb) = (values[2 * i] as f64, values[2 * i + 1] as f64);
            assert!(ga.is_finite() && gb.is_finite());
            for (p, gv) in [(a, ga), (b, gb)] {
                let m = smooth.then_some(masks.as_slice());
                let s = sample_field(&f.volume, &f.page_table, m, f.volume.geometry.dims, *p);
                let cpu = f.volume.mapping.physical(s.unwrap().value);
                worst_vs_cpu = worst_vs_cpu.max((gv - cpu).abs());
            }
            if *mixed {
                jump_mixed = jump_mixed.max((ga - gb).abs());
            } else {
                jump_same = jump_same.max((ga - gb).abs());
            }
        }
        eprintln!(
            "smooth {smooth}: GPU vs CPU field max {worst_vs_cpu:.3} HU; GPU jumps: level faces \
             {jump_mixed:.3} HU, same-level faces {jump_same:.3} HU ({} crossings)",
            lines.len()
        );
        // f32 interpolation of 12-bit data over a ~5000 HU mapping: well under 0.5 HU.
        assert!(
            worst_vs_cpu < 0.5,
            "GPU field differs from the reference field"
        );
        assert!(jump_same < 1.0);
        if smooth {
            assert!(
                jump_mixed < 1.0,
                "GPU field jumps {jump_mixed} HU at a level face"
            );
        } else {
            assert!(
                jump_mixed > 20.0,
                "baseline shows no jump: the test proves nothing"
            );
        }
    }
}

#[test]
fn pipeline_without_coarser_neighbours_has_no_transition_code() {
    let ctx = gpu();
    let volume = phantom_128();
    let uniform = volume.page_table_uniform(0);
    let f = Fixture::new(volume, uniform, test_tf());
    let g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 0.0, 0.0, 1.0, 35.0);
    let settings = compare_settings(RenderMode::Dvr, 32);
    assert!(settings.smooth_transitions, "smoothing is on by default");
    let scene = FrameInputs {
        cache: &g.cache,
        page_table: &g.page_table,
        transfer_function: &g.tf,
        geometry: &f.volume.geometry,
        mapping: f.volume.mapping,
        camera: &cam,
        settings: &settings,
    };
    assert_eq!(g.page_table.transition_fraction(), 0.0);
    assert!(!g.raycaster.key_for_scene(&scene).smooth_transitions);
    // A mixed cut written to the same GPU table turns it on.
    let mixed = f.volume.page_table_with_levels(corner_block_levels);
    let mut mixed_classified = mixed.clone();
    f.volume.classify_empty(&mut mixed_classified, &f.tf_table);
    f.volume
        .upload(&g.cache, &ctx.queue, &mixed_classified)
        .unwrap();
    g.page_table.update(&ctx.queue, &mixed_classified).unwrap();
    // 7 fine octants of 8 level-0 nodes each; those next to the block: all but the far octant's.
    let fraction = g.page_table.transition_fraction();
    assert!(fraction > 0.0 && fraction < 1.0, "{fraction}");
    let scene = FrameInputs {
        page_table: &g.page_table,
        ..scene
    };
    assert!(g.raycaster.key_for_scene(&scene).smooth_transitions);
}

#[test]
fn gpu_matches_reference_on_mixed_cuts_with_smoothing() {
    let ctx = gpu();
    let volume = phantom_128();
    let table = volume.page_table_with_levels(checker_levels);
    let f = Fixture::new(volume, table, test_tf());
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 35.0, 25.0, 1.5, 35.0);
    // Same bars as the single-level comparisons (gpu_vs_reference.rs): the blend adds one
    // f32 lerp, far below the sampler's 8-bit weight error the 40 dB bar already absorbs.
    // Isosurface pixels are opaque, so a silhouette pixel classified differently is off by
    // the whole surface colour: the max is free there and the count of such pixels bounded.
    let cases = [
        ("smooth-dvr", RenderMode::Dvr, None, 24u8),
        (
            "smooth-dvr-shaded",
            RenderMode::Dvr,
            Some(Shading::default()),
            24,
        ),
        (
            "smooth-iso",
            RenderMode::Isosurface,
            Some(Shading::default()),
            255,
        ),
    ];
    for (name, mode, shading, max_abs) in cases {
        let s = RenderSettings {
            shading,
            iso_value: 300.0,
            ..compare_settings(mode, SIZE)
        };
        assert!(s.smooth_transitions);
        let gpu_frame = g.render(&ctx, &f, &cam, &s);
        let reference = f.reference(&cam, &s, REFINE);
        let c = assert_close(name, &gpu_frame, &reference, 40.0, max_abs);
        if mode == RenderMode::Isosurface {
            assert!(
                c.pixels_off_by_more_than_one * 100 <= (SIZE * SIZE) as usize,
                "{name}: more than 1% of pixels off: {c:?}"
            );
        }
        // Smoothing changes the picture where levels meet: the discontinuous reference differs.
        let hard = f.reference(
            &cam,
            &RenderSettings {
                smooth_transitions: false,
                ..s.clone()
            },
            REFINE,
        );
        let c = compare_rgba8(&reference.rgba, &hard.rgba).unwrap();
        eprintln!("{name}: smooth vs discontinuous reference {c:?}");
        assert!(c.max_abs_error > 0, "{name}: smoothing had no effect");
    }
}
