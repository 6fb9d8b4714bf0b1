//! Geometry, mixed levels, acceleration invariants, degenerate inputs, visibility readback.
use crate::common;
use common::*;
use glam::{DMat3, DVec3};
use strata_render::model::smooth_transitions;
use strata_render::testdata::phantom;
use strata_render::*;

const SIZE: u32 = 128;
const REFINE: f64 = 8.0;
/// The bounds of gpu_vs_reference.rs (its module doc gives the reasons).
const BOUNDS: Bounds = Bounds::REFERENCE;

fn dvr_tf_fixture(volume: BrickedVolume, table: PageTable) -> Fixture {
    Fixture::new(volume, table, test_tf())
}

fn oblique_geometry() -> VolumeGeometry {
    let rot =
        DMat3::from_rotation_z(20f64.to_radians()) * DMat3::from_rotation_x(15f64.to_radians());
    VolumeGeometry {
        dims: [80, 64, 40],
        spacing_mm: [0.8, 1.1, 2.0],
        origin_lps_mm: [-30.0, 10.0, 50.0],
        direction: [rot.x_axis.into(), rot.y_axis.into(), rot.z_axis.into()],
    }
}

fn phantom_on(geometry: VolumeGeometry, centre: DVec3, r: f64, edge: f64) -> BrickedVolume {
    let g = geometry.clone();
    BrickedVolume::from_fn(geometry, phantom::CT_MAPPING, move |x, y, z| {
        let p = g.patient_from_index(DVec3::new(x as f64, y as f64, z as f64));
        (phantom::ct_phantom_hu(p, centre, r, edge) + 1024.0)
            .round()
            .clamp(0.0, 4095.0) as u16
    })
    .unwrap()
}

#[test]
fn anisotropic_oblique_geometry_matches_reference_and_patient_space() {
    let geometry = oblique_geometry();
    let centre = geometry.centre_patient();
    // Edge 2.5 mm: wider than the coarsest spacing so both samplings represent the same object.
    let volume = phantom_on(geometry, centre, 28.0, 2.5);
    let table = volume.page_table_uniform(0);
    let f = dvr_tf_fixture(volume, table);
    let cam = Camera::look_at(
        (centre + DVec3::new(90.0, -140.0, -60.0)).into(),
        centre.into(),
        [0.0, 0.0, -1.0],
        Projection::Perspective { fov_y_deg: 30.0 },
    );
    let s = RenderSettings {
        shading: Some(Shading::default()),
        ..compare_settings(RenderMode::Dvr, SIZE)
    };
    // Same tolerance reasoning as gpu_vs_reference.rs.
    let oblique = check_against_reference("aniso-oblique", &f, &cam, &s, BOUNDS).gpu;

    // Independently built: the same patient-space object on an isotropic, axis-aligned 1 mm
    // grid. If direction/spacing/origin were mishandled anywhere, the object would move, tilt
    // or stretch. Tolerance 28 dB: the two grids resample the object differently (2 mm vs 1 mm
    // voxels across 2.5 mm edges), which no renderer can remove.
    let iso_geometry = VolumeGeometry {
        dims: [80, 80, 80],
        spacing_mm: [1.0; 3],
        origin_lps_mm: (centre - DVec3::splat(39.5)).into(),
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let iso_volume = phantom_on(iso_geometry, centre, 28.0, 2.5);
    let iso_table = iso_volume.page_table_uniform(0);
    let fi = dvr_tf_fixture(iso_volume, iso_table);
    let reference_iso = fi.reference(&cam, &s, 4.0);
    save("aniso-vs-isotropic-ref", SIZE, SIZE, &reference_iso.rgba);
    let c = compare_rgba8(&oblique.rgba, &reference_iso.rgba).unwrap();
    eprintln!("oblique GPU vs isotropic reference: {c:?}");
    assert!(c.psnr_db >= 28.0, "{c:?}");
}

#[test]
fn mixed_levels_checkerboard_matches_reference() {
    let ctx = gpu();
    let volume =
        phantom::ct_phantom(VolumeGeometry::axis_aligned([128; 3], [1.0; 3]), None, None).unwrap();
    let table = volume.page_table_with_levels(|p| ((p[0] + p[1] + p[2]) % 3) as u8);
    let levels: std::collections::BTreeSet<u8> = table.entries.iter().map(|e| e.level).collect();
    assert_eq!(levels.into_iter().collect::<Vec<_>>(), vec![0, 1, 2]);
    let f = dvr_tf_fixture(volume, table);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 40.0, 30.0, 1.5, 35.0);
    // Same 40 dB bar: the GPU steps 2^L times longer in level-L nodes (octree paper §5), but a
    // level-L field is 2^L times smoother, so the relative discretisation error is unchanged.
    // MIP max error 32: MIP keeps the largest sample, and with 2-voxel steps in level-2 nodes
    // the peak of a narrow feature can fall between samples (undersampled by up to half a
    // step); the mean stays far above 40 dB.
    for (name, mode, max_abs) in [
        ("mixed-dvr", RenderMode::Dvr, 24),
        ("mixed-mip", RenderMode::Mip, 32),
    ] {
        let s = RenderSettings {
            shading: Some(Shading::default()),
            ..compare_settings(mode, SIZE)
        };
        g.check_against_reference(&ctx, &f, name, &cam, &s, Bounds { max_abs, ..BOUNDS });
    }
}

fn small_object_fixture() -> Fixture {
    // Object radius 30 mm in a 128 mm cube: most of the 4×4×4 pages hold only air.
    let volume = phantom::ct_phantom(
        VolumeGeometry::axis_aligned([128; 3], [1.0; 3]),
        None,
        Some(30.0),
    )
    .unwrap();
    let table = volume.page_table_uniform(0);
    dvr_tf_fixture(volume, table)
}

#[test]
fn empty_skipping_and_early_termination_keep_the_image_and_save_samples() {
    let ctx = gpu();
    let f = small_object_fixture();
    let empty = f.page_table.entries.iter().filter(|e| e.empty).count();
    assert!(empty > 10, "phantom should leave empty pages, got {empty}");
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 25.0, 15.0, 1.4, 35.0);
    let plain = RenderSettings {
        skip_empty: false,
        early_termination: None,
        ..compare_settings(RenderMode::Dvr, SIZE)
    };
    let base = g.render(&ctx, &f, &cam, &plain);

    // Skipping jumps to the next sample on the same lattice, and skipped pages are transparent
    // by construction: the image may differ only by f32 rounding of sample positions (1/255).
    let skip = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            skip_empty: true,
            ..plain.clone()
        },
    );
    let c = compare_rgba8(&base.rgba, &skip.rgba).unwrap();
    eprintln!(
        "skip: {c:?}, samples {:?} -> {:?}",
        base.samples, skip.samples
    );
    assert!(c.max_abs_error <= 1, "{c:?}");
    assert!(
        skip.samples.unwrap() * 2 < base.samples.unwrap(),
        "skipping should at least halve samples"
    );

    // Early termination at threshold τ drops at most (1-τ) of the remaining light: with
    // τ = 0.998 that is ≤ 0.51/255, plus rounding ≤ 1/255.
    let ert = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            early_termination: Some(0.998),
            ..plain.clone()
        },
    );
    let c = compare_rgba8(&base.rgba, &ert.rgba).unwrap();
    eprintln!(
        "ert 0.998: {c:?}, samples {:?} -> {:?}",
        base.samples, ert.samples
    );
    assert!(c.max_abs_error <= 1, "{c:?}");
    assert!(ert.samples.unwrap() < base.samples.unwrap());
    // The default τ = 0.99 may drop up to 2.55/255 of light, +1 for rounding.
    let both = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            early_termination: Some(0.99),
            skip_empty: true,
            ..plain.clone()
        },
    );
    let c = compare_rgba8(&base.rgba, &both.rgba).unwrap();
    eprintln!(
        "skip + ert 0.99: {c:?}, samples {:?} -> {:?}",
        base.samples, both.samples
    );
    assert!(c.max_abs_error <= 4, "{c:?}");
}

#[test]
fn mip_skips_pages_that_cannot_beat_the_running_maximum() {
    let ctx = gpu();
    // The CT phantom is brightest in its bones and vessels: once a ray has passed one, most
    // later pages (soft tissue, air) are bounded below its maximum.
    let f = Fixture::ct(96);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 35.0, 20.0, 1.2, 35.0);
    let plain = RenderSettings {
        skip_empty: false,
        ..compare_settings(RenderMode::Mip, SIZE)
    };
    let base = g.render(&ctx, &f, &cam, &plain);
    let skip = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            skip_empty: true,
            ..plain.clone()
        },
    );
    // A skipped page holds no sample above the running maximum (node bounds cover the apron)
    // and ties keep the first maximum, so the picture may differ only by f32 rounding of
    // sample positions at page faces (1/255).
    let c = compare_rgba8(&base.rgba, &skip.rgba).unwrap();
    let (before, after) = (base.samples.unwrap(), skip.samples.unwrap());
    eprintln!("mip skip: {c:?}, samples {before} -> {after}");
    assert!(c.max_abs_error <= 1, "{c:?}");
    // Measured: 1 456 022 -> 1 164 419 samples (-20 %) with only 27 pages to skip at 96³.
    assert!(
        (after as f64) < 0.9 * before as f64,
        "skipping pages bounded by the running maximum should save samples: {before} -> {after}"
    );
    // Depth is the distance of the (first) maximum; skipping must not move it.
    let moved = base
        .depth
        .iter()
        .zip(&skip.depth)
        .filter(|(a, b)| (a.is_finite() || b.is_finite()) && (**a - **b).abs() > 1e-3)
        .count();
    assert!(
        moved * 100 <= base.depth.len(),
        "{moved} MIP depths moved by skipping"
    );
}

#[test]
fn preintegration_catches_a_narrow_band_that_samples_miss() {
    let ctx = gpu();
    // Opacity only in a 60 HU band around the contrast vessel's 300 HU: its partial-volume
    // edges cross the band in under a voxel, so 1-voxel samples land in it only sometimes.
    let band = TransferFunction::new(
        "band",
        &[
            (-1000.0, 0.0),
            (260.0, 0.0),
            (270.0, 0.6),
            (320.0, 0.6),
            (330.0, 0.0),
            (3000.0, 0.0),
        ],
        &[(-1000.0, [1.0, 0.9, 0.8]), (3000.0, [1.0, 0.9, 0.8])],
    );
    let f = {
        let volume =
            phantom::ct_phantom(VolumeGeometry::axis_aligned([64; 3], [1.0; 3]), None, None)
                .unwrap();
        let table = volume.page_table_uniform(0);
        Fixture::new(volume, table, band)
    };
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 30.0, 20.0, 1.0, 30.0);
    let classic = RenderSettings {
        quality: 1.0,
        ..compare_settings(RenderMode::Dvr, SIZE)
    };
    // Ground truth: the same field integrated at 1/16 voxel in f64.
    let reference = f.reference(&cam, &classic, 16.0);
    let plain = g.render(&ctx, &f, &cam, &classic);
    let pre = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            preintegrated: true,
            ..classic.clone()
        },
    );
    let c_plain = compare_rgba8(&plain.rgba, &reference.rgba).unwrap();
    let c_pre = compare_rgba8(&pre.rgba, &reference.rgba).unwrap();
    eprintln!("band TF at 1 voxel: classic {c_plain:?}\npre-integrated {c_pre:?}");
    assert!(
        c_pre.psnr_db >= c_plain.psnr_db + 3.0,
        "pre-integration should be clearly closer to the reference: {c_pre:?} vs {c_plain:?}"
    );
    // What is left is the linear-segment assumption (trilinear is cubic along a ray) and the
    // 256² table's value resolution.
    assert!(c_pre.psnr_db >= 30.0, "{c_pre:?}");
}

#[test]
fn pipelines_hold_only_the_effects_a_scene_uses_and_are_reused() {
    let ctx = gpu();
    let f = Fixture::ct(48);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let plain_dvr = RenderSettings {
        jitter: false,
        early_termination: None,
        skip_empty: false,
        ..RenderSettings::default()
    };
    let cam = orbit(&f.volume.geometry, 10.0, 10.0, 1.0, 30.0);
    let key = g.key(&f, &cam, &plain_dvr);
    assert_eq!(key.mode, RenderMode::Dvr);
    assert!(
        !(key.smooth_transitions
            || key.shading
            || key.jitter
            || key.skip_empty
            || key.early_termination
            || key.clip_plane
            || key.count_samples
            || key.preintegrated),
        "{key:?}"
    );
    // MIP never shades, never terminates early and cannot pre-integrate, whatever is asked.
    let mip = g.raycaster.key_for(&RenderSettings {
        mode: RenderMode::Mip,
        shading: Some(Shading::default()),
        preintegrated: true,
        ..RenderSettings::default()
    });
    assert!(
        !mip.shading && !mip.early_termination && !mip.preintegrated,
        "{mip:?}"
    );
    // Isosurfaces always shade.
    let iso = g.raycaster.key_for(&RenderSettings {
        mode: RenderMode::Isosurface,
        ..plain_dvr.clone()
    });
    assert!(iso.shading && !iso.preintegrated, "{iso:?}");
    // A clip plane turns on exactly the clip code.
    let clipped = g.key(
        &f,
        &cam,
        &RenderSettings {
            clip_plane: Some(ClipPlane {
                normal: [1.0, 0.0, 0.0],
                offset_mm: 10.0,
            }),
            ..plain_dvr.clone()
        },
    );
    assert_eq!(
        clipped,
        PipelineKey {
            clip_plane: true,
            ..key
        }
    );

    // Toggling an effect compiles each variant once, then reuses it.
    let small = |s: RenderSettings| RenderSettings {
        width: 32,
        height: 32,
        ..s
    };
    let with_pre = small(RenderSettings {
        preintegrated: true,
        ..plain_dvr.clone()
    });
    let before = g.raycaster.compiled_pipelines();
    for _ in 0..3 {
        g.render(&ctx, &f, &cam, &small(plain_dvr.clone()));
        g.render(&ctx, &f, &cam, &with_pre);
    }
    assert_eq!(g.raycaster.compiled_pipelines(), before + 2);
}

#[test]
fn a_new_effect_compiles_in_the_background_while_the_previous_pipeline_draws() {
    let ctx = gpu();
    let f = Fixture::ct(48);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    g.raycaster.compile_in_background = true;
    let cam = orbit(&f.volume.geometry, 20.0, 10.0, 1.0, 30.0);
    let unshaded = RenderSettings {
        jitter: false,
        ..compare_settings(RenderMode::Dvr, 48)
    };
    let shaded = RenderSettings {
        shading: Some(Shading::default()),
        ..unshaded.clone()
    };
    // No earlier frame: the first pipeline is compiled in place (nothing else to show).
    let first = g.render(&ctx, &f, &cam, &unshaded);
    let unshaded_key = g.key(&f, &cam, &unshaded);
    let shaded_key = g.key(&f, &cam, &shaded);
    assert_eq!(g.raycaster.last_pipeline_key(), Some(unshaded_key));

    // Turning shading on: this frame is drawn at once with the previous pipeline...
    let during = g.render(&ctx, &f, &cam, &shaded);
    assert_eq!(g.raycaster.last_pipeline_key(), Some(unshaded_key));
    assert!(g.raycaster.compiling_in_background());
    assert_eq!(
        during.rgba, first.rgba,
        "the stand-in frame is the previous pipeline's image"
    );

    // ...and a later frame switches to the shaded pipeline once its thread has built it.
    let started = std::time::Instant::now();
    let mut frames = 0;
    while g.raycaster.last_pipeline_key() != Some(shaded_key) {
        assert!(
            started.elapsed().as_secs() < 120,
            "the shaded pipeline never arrived ({frames} frames)"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
        g.render(&ctx, &f, &cam, &shaded);
        frames += 1;
    }
    assert!(!g.raycaster.compiling_in_background());
    let after = g.render(&ctx, &f, &cam, &shaded);
    assert_ne!(after.rgba, first.rgba, "shading must change the picture");

    // A mode switch has no stand-in even with the flag: the old mode's image is not the new
    // mode's (issue 36), so the MIP pipeline is compiled for this very frame.
    let mip = RenderSettings {
        mode: RenderMode::Mip,
        ..shaded.clone()
    };
    g.render(&ctx, &f, &cam, &mip);
    assert_eq!(g.raycaster.last_pipeline_key(), Some(g.key(&f, &cam, &mip)));

    // Without the flag (tests, CLI, benchmarks) a frame always uses its own pipeline.
    g.raycaster.compile_in_background = false;
    let iso = RenderSettings {
        mode: RenderMode::Isosurface,
        ..unshaded.clone()
    };
    g.render(&ctx, &f, &cam, &iso);
    assert_eq!(g.raycaster.last_pipeline_key(), Some(g.key(&f, &cam, &iso)));
}

#[test]
fn opacity_correction_makes_image_independent_of_step() {
    let ctx = gpu();
    let f = small_object_fixture();
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, -30.0, 20.0, 1.4, 35.0);
    let half = compare_settings(RenderMode::Dvr, SIZE);
    let a = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            quality: 0.5,
            ..half.clone()
        },
    );
    let b = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            quality: 0.25,
            ..half.clone()
        },
    );
    let c = compare_rgba8(&a.rgba, &b.rgba).unwrap();
    eprintln!("step 0.5 vs 0.25: {c:?}");
    // Without correction, halving the step would double every sample's opacity contribution
    // (tens of levels off). With it, only second-order discretisation error remains: ≥ 40 dB.
    assert!(c.psnr_db >= 40.0 && c.max_abs_error <= 8, "{c:?}");
    assert!(b.samples.unwrap() > a.samples.unwrap() * 3 / 2);
}

#[test]
fn constant_volume_with_shading_has_no_nan_and_matches_reference() {
    let ctx = gpu();
    let volume = BrickedVolume::from_fn(
        VolumeGeometry::axis_aligned([40, 40, 40], [1.0; 3]),
        phantom::CT_MAPPING,
        |_, _, _| 1024 + 300,
    )
    .unwrap();
    let table = volume.page_table_uniform(0);
    // The TF table spans the volume's range, which is a single value: must not divide by zero.
    let f = dvr_tf_fixture(volume, table);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 30.0, 30.0, 1.2, 40.0);
    for (name, mode) in [
        ("const-dvr", RenderMode::Dvr),
        ("const-iso", RenderMode::Isosurface),
    ] {
        let s = RenderSettings {
            shading: Some(Shading::default()),
            iso_value: 250.0,
            ..compare_settings(mode, 96)
        };
        // The isosurface of a constant block is its hard box face: silhouette rays that clip
        // a corner shorter than half a GPU step hit only in the reference, so as in the
        // oblique isosurface test bound the number of differing pixels, not their size.
        // That also caps PSNR (a few dozen full-scale silhouette pixels alone give ~28 dB).
        let bounds = if mode == RenderMode::Isosurface {
            Bounds {
                min_psnr_db: 25.0,
                max_abs: 255,
                ..BOUNDS
            }
        } else {
            BOUNDS
        };
        let c = g
            .check_against_reference(&ctx, &f, name, &cam, &s, bounds)
            .comparison;
        if mode == RenderMode::Isosurface {
            assert!(c.pixels_off_by_more_than_one * 100 <= 96 * 96, "{c:?}");
        }
    }
}

#[test]
fn single_slice_volume_and_axis_parallel_rays() {
    let ctx = gpu();
    let volume = phantom::ct_phantom(
        VolumeGeometry::axis_aligned([64, 64, 1], [1.0, 1.0, 3.0]),
        None,
        Some(30.0),
    )
    .unwrap();
    let table = volume.page_table_uniform(0);
    let f = dvr_tf_fixture(volume, table);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let c = f.volume.geometry.centre_patient();
    // Straight down the k axis (all rays parallel to it, through a 3 mm thick slab), then
    // edge-on along i (rays inside the slab plane), then oblique.
    let cams = [
        Camera::look_at(
            [c.x, c.y, c.z - 100.0],
            c.into(),
            [0.0, -1.0, 0.0],
            Projection::Orthographic { height_mm: 70.0 },
        ),
        Camera::look_at(
            [c.x - 100.0, c.y, c.z],
            c.into(),
            [0.0, 0.0, -1.0],
            Projection::Orthographic { height_mm: 70.0 },
        ),
        Camera::look_at(
            [c.x - 60.0, c.y + 40.0, c.z - 80.0],
            c.into(),
            [0.0, 0.0, -1.0],
            Projection::Perspective { fov_y_deg: 45.0 },
        ),
    ];
    for (i, cam) in cams.iter().enumerate() {
        let s = compare_settings(RenderMode::Mip, 96);
        let frame = g.render(&ctx, &f, cam, &s);
        let reference = f.reference(cam, &s, REFINE);
        if i == 1 {
            // Edge-on: the slab is 3 mm tall in a 70 mm view, only a few rows are covered, so
            // only require equality within the usual max error (PSNR of an almost empty image
            // is meaningless).
            let cmp = compare_rgba8(&frame.rgba, &reference.rgba).unwrap();
            eprintln!("slice edge-on: {cmp:?}");
            assert!(cmp.max_abs_error <= 24 && cmp.psnr_db >= 40.0, "{cmp:?}");
        } else {
            assert_close(&format!("slice-{i}"), &frame, &reference, 40.0, 24);
        }
    }
}

#[test]
fn visibility_marks_only_contributing_pages_and_arrives_without_blocking() {
    let ctx = gpu();
    let f = small_object_fixture();
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 10.0, 10.0, 1.4, 35.0);
    let s = RenderSettings {
        jitter: true,
        ..compare_settings(RenderMode::Dvr, SIZE)
    };
    let frame = g.render(&ctx, &f, &cam, &s);
    assert_eq!(frame.visibility.len(), f.page_table.entries.len());
    let visible = frame.visibility.iter().filter(|&&v| v == 1).count();
    assert!(visible > 0);
    for (v, e) in frame.visibility.iter().zip(&f.page_table.entries) {
        assert!(*v == 0 || !e.empty, "an empty page was marked visible");
    }
    // Non-blocking path: a few frames later the ring hands back a frame's visibility.
    let scene = FrameInputs {
        cache: &g.cache,
        page_table: &g.page_table,
        transfer_function: &g.tf,
        geometry: &f.volume.geometry,
        mapping: f.volume.mapping,
        camera: &cam,
        settings: &s,
    };
    let mut got = None;
    for _ in 0..200 {
        g.raycaster.render(&ctx, &scene).unwrap();
        if let Some(v) = g.raycaster.try_take_visibility(&ctx) {
            got = Some(v);
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    let got = got.expect("visibility never arrived");
    assert_eq!(
        got.visibility, frame.visibility,
        "same view, same visible pages"
    );
}

#[test]
fn jitter_changes_samples_but_not_the_picture() {
    let ctx = gpu();
    let f = Fixture::ct(64);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 60.0, 10.0, 1.5, 35.0);
    let s = compare_settings(RenderMode::Dvr, SIZE);
    let plain = g.render(&ctx, &f, &cam, &s);
    let j0 = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            jitter: true,
            frame_index: 0,
            ..s.clone()
        },
    );
    let j0b = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            jitter: true,
            frame_index: 0,
            ..s.clone()
        },
    );
    let j1 = g.render(
        &ctx,
        &f,
        &cam,
        &RenderSettings {
            jitter: true,
            frame_index: 1,
            ..s.clone()
        },
    );
    assert_eq!(j0.rgba, j0b.rgba, "jitter hash must be deterministic");
    assert_ne!(j0.rgba, j1.rgba, "frame index must reseed jitter");
    // Jitter trades banding for noise of the order of the step's discretisation error.
    let c = compare_rgba8(&plain.rgba, &j0.rgba).unwrap();
    eprintln!("jitter vs none: {c:?}");
    assert!(c.psnr_db >= 35.0, "{c:?}");
}

#[test]
fn no_adapter_error_carries_install_hint() {
    let e = RenderError::NoAdapter {
        details: "none".into(),
    };
    assert!(e
        .to_string()
        .contains("apt-get install -y mesa-vulkan-drivers libvulkan1"));
}

#[test]
fn bad_inputs_are_errors() {
    let ctx = gpu();
    let cache = BrickCache::new(
        &ctx.device,
        CacheConfig {
            max_slots: Some(2),
            ..Default::default()
        },
    )
    .unwrap();
    assert!(cache.upload_brick(&ctx.queue, 0, &[0u16; 10]).is_err());
    assert!(cache
        .upload_brick(
            &ctx.queue,
            cache.slot_count(),
            &vec![0u16; BRICK_PAYLOAD_VOXELS]
        )
        .is_err());
    assert!(BrickCache::new(
        &ctx.device,
        CacheConfig {
            budget_bytes: 10,
            ..Default::default()
        }
    )
    .is_err());
    assert!(BrickedVolume::from_voxels(
        VolumeGeometry::axis_aligned([4, 4, 4], [1.0; 3]),
        ValueMapping::default(),
        vec![0; 3]
    )
    .is_err());
    assert!(BrickedVolume::from_voxels(
        VolumeGeometry::axis_aligned([4, 4, 4], [0.0, 1.0, 1.0]),
        ValueMapping::default(),
        vec![0; 64]
    )
    .is_err());
    let s = RenderSettings {
        quality: 0.0,
        ..Default::default()
    };
    assert!(s.validate().is_err());
}

/// One slot's 36³ texels read back from the cache texture (R16Unorm or R32Float as stored).
fn read_slot(ctx: &GpuContext, cache: &BrickCache, slot: u32) -> Vec<u8> {
    let bpv = cache.format.bytes_per_voxel() as u32;
    let row = BRICK_PAYLOAD * bpv;
    let padded =
        row.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("slot readback"),
        size: (padded * BRICK_PAYLOAD * BRICK_PAYLOAD) as u64,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    let o = cache.slot_origin(slot);
    let mut encoder = ctx.device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture: &cache.texture,
            mip_level: 0,
            origin: wgpu::Origin3d {
                x: o[0],
                y: o[1],
                z: o[2],
            },
            aspect: wgpu::TextureAspect::All,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(padded),
                rows_per_image: Some(BRICK_PAYLOAD),
            },
        },
        wgpu::Extent3d {
            width: BRICK_PAYLOAD,
            height: BRICK_PAYLOAD,
            depth_or_array_layers: BRICK_PAYLOAD,
        },
    );
    ctx.queue.submit([encoder.finish()]);
    let (tx, rx) = std::sync::mpsc::channel();
    buffer.map_async(wgpu::MapMode::Read, .., move |r| tx.send(r).unwrap());
    ctx.wait_idle().unwrap();
    rx.recv().unwrap().unwrap();
    let mapped = buffer.get_mapped_range(..).unwrap();
    mapped
        .chunks(padded as usize)
        .flat_map(|r| r[..row as usize].to_vec())
        .collect()
}

#[test]
fn a_growing_cache_allocates_what_is_used_and_keeps_its_slots() {
    let ctx = gpu();
    let mut cache = BrickCache::new(
        &ctx.device,
        CacheConfig {
            budget_bytes: 128 << 20,
            grow_with_use: true,
            ..Default::default()
        },
    )
    .unwrap();
    let full = cache.slot_count();
    let first = cache.allocated_slots();
    assert!(
        first < full && cache.allocated_bytes() < 64 << 20,
        "a growing cache starts small: {first} of {full} slots"
    );
    let brick = |seed: u16| -> Vec<u16> {
        (0..BRICK_PAYLOAD_VOXELS)
            .map(|i| (i as u16).wrapping_mul(7).wrapping_add(seed))
            .collect()
    };
    let low = 3;
    let high = full - 2;
    cache.ensure_slot(&ctx.device, &ctx.queue, low).unwrap();
    cache.upload_brick(&ctx.queue, low, &brick(11)).unwrap();
    let before = read_slot(&ctx, &cache, low);
    // A slot beyond the allocated layers is refused until the cache grows to hold it.
    assert!(matches!(
        cache.upload_brick(&ctx.queue, high, &brick(5)),
        Err(RenderError::SlotOutOfRange { .. })
    ));
    assert!(cache.ensure_slot(&ctx.device, &ctx.queue, high).unwrap());
    assert_eq!(cache.allocated_slots(), full, "grew to the budget's grid");
    assert_eq!(cache.slot_count(), full, "the slot grid never changes");
    assert_eq!(
        cache.texel_dims(),
        cache.slots_per_axis.map(|s| s * BRICK_PAYLOAD)
    );
    assert!(!cache.ensure_slot(&ctx.device, &ctx.queue, high).unwrap());
    cache.upload_brick(&ctx.queue, high, &brick(5)).unwrap();
    // The brick uploaded before the growth is where it was, bit for bit.
    assert_eq!(read_slot(&ctx, &cache, low), before);
    let other = BrickCache::new(
        &ctx.device,
        CacheConfig {
            budget_bytes: 128 << 20,
            ..Default::default()
        },
    )
    .unwrap();
    other.upload_brick(&ctx.queue, high, &brick(5)).unwrap();
    other.upload_brick(&ctx.queue, low, &brick(11)).unwrap();
    assert_eq!(read_slot(&ctx, &cache, high), read_slot(&ctx, &other, high));
    assert_eq!(before, read_slot(&ctx, &other, low));
    assert!(cache.ensure_slot(&ctx.device, &ctx.queue, full).is_err());
}

/// A budget the device cannot hold is an error naming it, from an error scope, not a panic in
/// wgpu's uncaptured-error handler (issue 35). Lavapipe allocates at most ~2 GiB at once (its
/// reported limit is 2047 MiB); 4 × that is beyond it, with the cache growing (checked by the
/// probe of the full grid) and without (the allocation itself).
#[test]
fn a_budget_the_device_cannot_hold_is_a_clear_error() {
    let ctx = gpu();
    let limit = ctx.device.limits().max_buffer_size;
    let budget = limit.saturating_mul(4);
    let config = |grow_with_use| CacheConfig {
        budget_bytes: budget,
        grow_with_use,
        ..Default::default()
    };
    let growing = BrickCache::new(&ctx.device, config(true)).expect("a growing cache starts small");
    let probed = growing.check_full_allocation(&ctx.device, budget);
    let whole = BrickCache::new(&ctx.device, config(false)).map(|_| ());
    let on_lavapipe = ctx.adapter_name().contains("llvmpipe");
    for (what, result) in [("probe", probed), ("whole", whole)] {
        match result {
            Err(RenderError::GpuAllocation { .. }) => {
                let text = result.unwrap_err().to_string();
                assert!(text.contains("brick cache texture"), "{what}: {text}");
                assert!(text.contains("Out of Memory"), "{what}: {text}");
                assert!(
                    text.contains(&format!("largest single allocation of {} MiB", limit >> 20)),
                    "{what}: {text}"
                );
                assert!(text.contains("--gpu-mib"), "{what}: {text}");
            }
            Err(other) => panic!("{what}: not an allocation error: {other}"),
            Ok(()) => assert!(!on_lavapipe, "{what}: lavapipe held {budget} bytes"),
        }
    }
    // The device is still usable: nothing reached the uncaptured-error handler.
    ctx.check_uncaptured().unwrap();
    let small = BrickCache::new(&ctx.device, CacheConfig::default()).unwrap();
    small
        .upload_brick(&ctx.queue, 0, &vec![7u16; BRICK_PAYLOAD_VOXELS])
        .unwrap();
    ctx.wait_idle().unwrap();
}

#[test]
fn adopted_device_renders_like_headless() {
    let ctx = gpu();
    let adopted = GpuContext::from_device(ctx.device.clone(), ctx.queue.clone());
    let f = Fixture::ct(64);
    let mut g = GpuScene::new(&adopted, &f, CacheConfig::default());
    let cam = Camera::orbit(
        &f.volume.geometry,
        15.0,
        5.0,
        1.5,
        Projection::Orthographic { height_mm: 0.0 },
    );
    let s = compare_settings(RenderMode::Dvr, 96);
    g.check_against_reference(&adopted, &f, "adopted-ortho-orbit", &cam, &s, BOUNDS);
}

#[test]
fn orbit_camera_centres_the_volume() {
    let g = oblique_geometry();
    for proj in [
        Projection::Perspective { fov_y_deg: 30.0 },
        Projection::Orthographic { height_mm: 1.0 },
    ] {
        for (az, el) in [(0.0, 0.0), (45.0, 30.0), (180.0, -89.0), (10.0, 90.0)] {
            let cam = Camera::orbit(&g, az, el, 1.0, proj);
            let basis = cam.basis();
            // The ray through the image centre (even size: between the 4 middle pixels) passes
            // through the volume centre.
            let (o, dir) = basis.ray(0, 0, 1, 1);
            let c = g.centre_patient();
            let to_centre = c - o;
            let miss = (to_centre - dir * to_centre.dot(dir)).length();
            assert!(miss < 1e-6, "az {az} el {el}: miss {miss}");
            assert!(basis.right.is_finite() && (basis.right.length() - 1.0).abs() < 1e-9);
        }
    }
}

#[test]
fn orbit_camera_shows_the_patient_upright_from_the_front() {
    // LPS: +x patient left, +y posterior, +z superior.
    let g = VolumeGeometry::axis_aligned([40, 50, 60], [1.0, 1.0, 2.0]);
    let c = g.centre_patient();
    let front = orbit(&g, 0.0, 0.0, 1.0, 30.0);
    let basis = front.basis();
    assert!(front.eye[1] < c.y, "azimuth 0 looks from anterior (-y)");
    assert!(
        basis.up.z > 0.999,
        "superior is up on screen: {:?}",
        basis.up
    );
    // Facing the patient, the patient's left is on the viewer's right (radiological frontal).
    assert!(
        basis.right.x > 0.999,
        "patient left on screen right: {:?}",
        basis.right
    );
    let above = orbit(&g, 0.0, 30.0, 1.0, 30.0);
    assert!(above.eye[2] > c.z, "positive elevation looks from above");
    let side = orbit(&g, 90.0, 0.0, 1.0, 30.0);
    assert!(
        side.eye[0] > c.x,
        "azimuth 90 looks from the patient's left"
    );
}

#[test]
fn partial_page_table_writes_equal_full_writes() {
    let ctx = gpu();
    let f = Fixture::ct(64);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 40.0, 20.0, 1.5, 35.0);
    let s = compare_settings(RenderMode::Dvr, 64);
    let full = g.render(&ctx, &f, &cam, &s);
    // Mark everything not resident, then restore entry by entry: same picture as before.
    let mut hidden = f.page_table.clone();
    hidden.entries.iter_mut().for_each(|e| e.resident = false);
    g.page_table.update(&ctx.queue, &hidden).unwrap();
    let blank = g.render(&ctx, &f, &cam, &s);
    assert!(
        blank.rgba.iter().all(|&v| v == 0),
        "non-resident pages must render nothing"
    );
    for (i, e) in f.page_table.entries.iter().enumerate() {
        g.page_table
            .write_entries(&ctx.queue, i, std::slice::from_ref(e))
            .unwrap();
    }
    let restored = g.render(&ctx, &f, &cam, &s);
    assert_eq!(full.rgba, restored.rgba);
    assert!(g
        .page_table
        .write_entries(
            &ctx.queue,
            f.page_table.entries.len(),
            &[PageEntry::NOT_RESIDENT]
        )
        .is_err());
}

/// A cut change writes only the spans of the page-table buffers that changed (issue 18: the
/// whole-table write cost the frame thread ~6 ms at 1024³), and the index so patched draws
/// the same image, byte for byte, as an index written whole.
#[test]
fn a_changed_cut_writes_only_its_changed_spans() {
    let ctx = gpu();
    let f = Fixture::ct(128);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 40.0, 20.0, 1.5, 35.0);
    let s = compare_settings(RenderMode::Dvr, 64);
    let original = g.render(&ctx, &f, &cam, &s);
    let entries = f.page_table.entries.len() as u64;
    // Words (4 bytes) and transition pairs (8 bytes) of the whole table.
    let whole_bytes = entries * 12;
    let bounds =
        |t: &PageTable| t.value_max_physical(f.volume.mapping, |l, n| f.volume.node_range(l, n));

    // The drawn page nearest the middle hidden: a local change of a level-0 cut.
    let centre = [2i64; 3];
    let middle = (0..f.page_table.entries.len())
        .filter(|&i| f.page_table.entries[i].resident && !f.page_table.entries[i].empty)
        .min_by_key(|&i| {
            let p = f.page_table.page_of_linear(i);
            (0..3).map(|a| (p[a] as i64 - centre[a]).abs()).sum::<i64>()
        })
        .unwrap();
    let mut changed = f.page_table.clone();
    changed.entries[middle] = PageEntry::NOT_RESIDENT;
    // Which GPU words the change touches (its own and the neighbours' flags and masks).
    let gpu_words = |t: &PageTable| {
        let masks = smooth_transitions::transition_masks(t);
        (
            t.encoded_for_gpu(g.page_table.slots_per_axis, &masks),
            masks,
        )
    };
    let (before, after) = (gpu_words(&f.page_table), gpu_words(&changed));
    let touched: Vec<usize> = (0..before.0.len())
        .filter(|&i| before.0[i] != after.0[i] || before.1[i] != after.1[i])
        .collect();
    let hull = (touched[touched.len() - 1] - touched[0] + 1) as u64;
    assert!(hull < entries, "the change should be local");
    g.page_table.update(&ctx.queue, &changed).unwrap();
    let written = g.page_table.last_write_bytes();
    assert!(
        written >= touched.len() as u64 * 4 && written <= hull * 12,
        "{} changed words wrote {written} of {whole_bytes} bytes",
        touched.len()
    );
    g.page_table
        .update_value_max(&ctx.queue, &bounds(&changed))
        .unwrap();
    assert!(g.page_table.last_write_bytes() <= hull * 4);
    let patched = g.render(&ctx, &f, &cam, &s);

    // The same table written into a fresh index: the same image.
    let fresh = GpuPageTable::new(&ctx.device, f.volume.geometry.page_dims(), &g.cache).unwrap();
    fresh.update(&ctx.queue, &changed).unwrap();
    fresh
        .update_value_max(&ctx.queue, &bounds(&changed))
        .unwrap();
    let patched_index = std::mem::replace(&mut g.page_table, fresh);
    let whole = g.render(&ctx, &f, &cam, &s);
    assert_eq!(patched.rgba, whole.rgba);
    assert_ne!(patched.rgba, original.rgba, "the hidden page should show");

    // Back to the original table: the patched index draws the original image again, and
    // writing bounds it already holds sends nothing.
    g.page_table = patched_index;
    g.page_table.update(&ctx.queue, &f.page_table).unwrap();
    g.page_table
        .update_value_max(&ctx.queue, &bounds(&f.page_table))
        .unwrap();
    assert!(g.page_table.last_write_bytes() <= hull * 4);
    g.page_table
        .update_value_max(&ctx.queue, &bounds(&f.page_table))
        .unwrap();
    assert_eq!(g.page_table.last_write_bytes(), 0);
    let restored = g.render(&ctx, &f, &cam, &s);
    assert_eq!(restored.rgba, original.rgba);
}

#[test]
fn offscreen_renderer_handles_iso_classification() {
    let ctx = gpu();
    let volume = phantom::ct_phantom(
        VolumeGeometry::axis_aligned([96; 3], [1.0; 3]),
        None,
        Some(30.0),
    )
    .unwrap();
    let tf = test_tf();
    let mut r = OffscreenRenderer::new(&ctx, &volume, &tf, 0, CacheConfig::default()).unwrap();
    let cam = orbit(&volume.geometry, 20.0, 20.0, 1.5, 35.0);
    // Iso value below the TF's first visible value: TF-empty pages hold this surface, so the
    // renderer must reclassify or the surface would vanish.
    let s = RenderSettings {
        iso_value: -500.0,
        ..compare_settings(RenderMode::Isosurface, 64)
    };
    let with_skip = r.render(&ctx, &volume, &cam, &s).unwrap();
    let without = r
        .render(
            &ctx,
            &volume,
            &cam,
            &RenderSettings {
                skip_empty: false,
                ..s.clone()
            },
        )
        .unwrap();
    let c = compare_rgba8(&with_skip.rgba, &without.rgba).unwrap();
    assert!(c.max_abs_error <= 1, "{c:?}");
    assert!(
        with_skip
            .rgba
            .chunks_exact(4)
            .filter(|p| p[3] == 255)
            .count()
            > 200
    );
    let dvr = r
        .render(&ctx, &volume, &cam, &compare_settings(RenderMode::Dvr, 64))
        .unwrap();
    assert!(dvr.rgba.chunks_exact(4).any(|p| p[3] > 0));
}

/// Issue 35's first-frame cost of the cache, measured (not asserted): for each budget in
/// STRATA_CACHE_BUDGETS_MIB (default 256,8192), the time to create the cache, upload one brick
/// (the root) and wait for the GPU, with the texture allocated for the whole budget and with
/// it growing with use. Run on a real GPU:
/// `cargo test --release -p strata-render --test integration features::cache_first_upload_cost -- --ignored --nocapture`.
#[test]
#[ignore]
fn cache_first_upload_cost() {
    let ctx = gpu();
    let limits = ctx.device.limits();
    println!(
        "{}: max_buffer_size {} MiB, max_texture_dimension_3d {}",
        ctx.adapter_name(),
        limits.max_buffer_size >> 20,
        limits.max_texture_dimension_3d
    );
    let budgets = std::env::var("STRATA_CACHE_BUDGETS_MIB").unwrap_or("256,8192".into());
    let root: Vec<u16> = (0..BRICK_PAYLOAD_VOXELS).map(|i| i as u16).collect();
    for mib in budgets.split(',').map(|v| v.trim().parse::<u64>().unwrap()) {
        for grow in [false, true] {
            let t = std::time::Instant::now();
            let made = BrickCache::new(
                &ctx.device,
                CacheConfig {
                    budget_bytes: mib << 20,
                    grow_with_use: grow,
                    ..Default::default()
                },
            );
            let created = t.elapsed().as_secs_f64();
            let cache = match made {
                Ok(c) => c,
                Err(e) => {
                    println!("budget {mib} MiB grow {grow}: {e}");
                    continue;
                }
            };
            cache.upload_brick(&ctx.queue, 0, &root).unwrap();
            ctx.queue.submit([]);
            let waited = ctx.wait_idle();
            println!(
                "budget {mib} MiB grow {grow}: allocated {} MiB, create {:.3} s, create + first upload done {:.3} s ({waited:?})",
                cache.allocated_bytes() >> 20,
                created,
                t.elapsed().as_secs_f64()
            );
        }
    }
}
