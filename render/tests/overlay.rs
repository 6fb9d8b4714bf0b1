//! The overlay in 3D (overlay.rs, shaders/overlay.wgsl): GPU against the f64 reference with the
//! same sampling and blend rule, labels fetched nearest, and no overlay code in pipelines
//! without one.
//!
//! Tolerances: those of gpu_vs_reference.rs (PSNR ≥ 40 dB, max 24/255, same reasons: 0.5-voxel
//! f32 steps against 1/16-voxel f64 steps, 8-bit sampler weights), except where a test says
//! otherwise. The label faces add a discontinuity of their own (a piecewise-constant overlay
//! is not smoothed by the midpoint rule), but a sample lands on the wrong side of a face only
//! within f32 rounding of it, so it stays inside the same bounds.
use crate::common;
use common::*;
use glam::DVec3;
use strata_render::reference::{render_reference_with_overlay, ReferenceImage, ReferenceOptions};
use strata_render::testdata::phantom;
use strata_render::*;

const SIZE: u32 = 128;
const REFINE: f64 = 8.0;
const MIN_PSNR: f64 = 40.0;
const MAX_ABS: u8 = 24;
const RED: [f32; 4] = [1.0, 0.0, 0.0, 1.0];
const GREEN: [f32; 4] = [0.0, 1.0, 0.0, 1.0];

fn orbit_ct(f: &Fixture, az: f64, el: f64) -> Camera {
    orbit(&f.volume.geometry, az, el, 1.5, 35.0)
}

/// A label grid of `dims` over the primary: `label(i, j, k)` per grid voxel.
fn labels(dims: [u32; 3], label: impl Fn(u32, u32, u32) -> u32) -> OverlayVolume {
    let mut values = Vec::new();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                values.push(label(i, j, k) as f32);
            }
        }
    }
    OverlayVolume::new(dims, OverlayKind::Labels, values).unwrap()
}

/// A label box (grid voxels 10..22 of 32³) in the phantom's middle, its upper half label 2.
fn label_box() -> OverlayVolume {
    labels([32; 3], |i, j, k| {
        let inside = [i, j, k].iter().all(|c| (10..22).contains(c));
        match (inside, k >= 16) {
            (false, _) => 0,
            (true, false) => 1,
            (true, true) => 2,
        }
    })
}

fn label_lut(opacity: f32, hide_two: bool) -> OverlayLut {
    let two = if hide_two { 0.0 } else { opacity };
    OverlayLut::new(
        vec![[0.0; 4], [0.1, 0.9, 0.2, opacity], [0.2, 0.3, 1.0, two]],
        0.0,
        0.0,
        0.0,
    )
    .unwrap()
}

fn reference(
    f: &Fixture,
    overlay: Option<(&OverlayVolume, &OverlayLut)>,
    camera: &Camera,
    settings: &RenderSettings,
) -> ReferenceImage {
    let scene = ReferenceScene {
        source: &f.volume,
        page_table: &f.page_table,
        geometry: &f.volume.geometry,
        mapping: f.volume.mapping,
        transfer_function: &f.tf,
        tf_range: (f.tf_table.lo, f.tf_table.hi),
    };
    let overlay = overlay.map(|(volume, lut)| OverlayScene {
        volume,
        lut,
        primary_dims: f.volume.geometry.dims,
    });
    render_reference_with_overlay(
        &scene,
        overlay.as_ref(),
        camera,
        settings,
        ReferenceOptions {
            step_refinement: REFINE,
            ..Default::default()
        },
    )
    .unwrap()
}

/// Pixels that take label 1's hue: green over red (the phantom's tissue is red over green).
fn green_pixels(rgba: &[u8]) -> usize {
    rgba.chunks_exact(4)
        .filter(|p| p[1] > p[0] && p[1] > 30)
        .count()
}

#[test]
fn a_label_map_in_dvr_matches_the_reference_and_hiding_a_label_removes_it() {
    let ctx = gpu();
    let f = Fixture::ct(64);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let overlay = label_box();
    let lut = label_lut(0.7, false);
    g.raycaster
        .set_overlay(&ctx, &overlay, &lut, f.volume.geometry.dims)
        .unwrap();
    for (name, az, el, shading) in [
        ("overlay-dvr", 30.0, 20.0, None),
        ("overlay-dvr-shaded", -50.0, 35.0, Some(Shading::default())),
    ] {
        let cam = orbit_ct(&f, az, el);
        let s = RenderSettings {
            shading,
            ..compare_settings(RenderMode::Dvr, SIZE)
        };
        assert!(g.key(&f, &cam, &s).overlay, "the overlay is compiled in");
        let frame = g.render(&ctx, &f, &cam, &s);
        assert_close(
            name,
            &frame,
            &reference(&f, Some((&overlay, &lut)), &cam, &s),
            MIN_PSNR,
            MAX_ABS,
        );
        assert!(green_pixels(&frame.rgba) > 200, "{name}: the label shows");
    }
    // Hiding label 2 is a colour-table change only; the GPU follows the reference again.
    let hidden = label_lut(0.7, true);
    g.raycaster.set_overlay_lut(&ctx, &hidden).unwrap();
    let cam = orbit_ct(&f, 30.0, 20.0);
    let s = compare_settings(RenderMode::Dvr, SIZE);
    let frame = g.render(&ctx, &f, &cam, &s);
    assert_close(
        "overlay-dvr-hidden",
        &frame,
        &reference(&f, Some((&overlay, &hidden)), &cam, &s),
        MIN_PSNR,
        MAX_ABS,
    );
    let blue = |rgba: &[u8]| {
        rgba.chunks_exact(4)
            .filter(|p| p[2] > p[0] && p[2] > p[1] && p[2] > 30)
            .count()
    };
    let shown = g.render(&ctx, &f, &cam, &s);
    g.raycaster.set_overlay_lut(&ctx, &lut).unwrap();
    let with_two = g.render(&ctx, &f, &cam, &s);
    assert!(blue(&with_two.rgba) > 50, "label 2 is drawn when shown");
    assert!(
        blue(&shown.rgba) * 10 < blue(&with_two.rgba),
        "hidden label 2 is gone: {} vs {}",
        blue(&shown.rgba),
        blue(&with_two.rgba)
    );
}

/// A TF that shows bone only makes the soft tissue's pages empty; the label box lies in them
/// and must still be drawn (rays sample empty pages inside the overlay's box).
#[test]
fn a_label_inside_tissue_the_tf_makes_transparent_is_drawn() {
    let ctx = gpu();
    let volume =
        phantom::ct_phantom(VolumeGeometry::axis_aligned([96; 3], [1.0; 3]), None, None).unwrap();
    let table = volume.page_table_uniform(0);
    let calcification_only = TransferFunction::new(
        "calcification",
        &[(-1000.0, 0.0), (1000.0, 0.0), (1300.0, 0.6), (3000.0, 0.8)],
        &[(-1000.0, [1.0, 1.0, 1.0]), (3000.0, [1.0, 0.95, 0.9])],
    );
    let f = Fixture::new(volume, table, calcification_only);
    // The label box (grid voxels 10..22 of 32: primary voxels 30..66) overlaps empty pages.
    let pages = f.page_table.page_dims;
    let empty_in_box = (0..f.page_table.entries.len()).filter(|&i| {
        let i = i as u32;
        let cell = [
            i % pages[0],
            (i / pages[0]) % pages[1],
            i / (pages[0] * pages[1]),
        ];
        f.page_table.entries[i as usize].empty
            && cell
                .iter()
                .all(|&c| c * BRICK_CORE < 66 && (c + 1) * BRICK_CORE > 30)
    });
    assert!(
        empty_in_box.count() > 0,
        "the label box lies in pages rays skip"
    );
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit_ct(&f, 20.0, 10.0);
    let s = compare_settings(RenderMode::Dvr, SIZE);
    let before = g.render(&ctx, &f, &cam, &s);
    let overlay = label_box();
    let lut = label_lut(1.0, true);
    g.raycaster
        .set_overlay(&ctx, &overlay, &lut, f.volume.geometry.dims)
        .unwrap();
    let frame = g.render(&ctx, &f, &cam, &s);
    // Max 80/255 here: in clear surroundings the opaque label's face is a hard step of
    // per-voxel opacity from 0 to OVERLAY_VOXEL_OPACITY; a ray grazing an edge of the box has a
    // short path in it, which the GPU's 0.5-voxel midpoint samples measure with an error of up
    // to one step: one sample more or less, alpha 1 − 0.5^0.5 = 0.29 (75/255). Such pixels lie
    // on the box's silhouette only (bounded to 2 % of the image), PSNR bounds the rest.
    let c = assert_close(
        "overlay-in-transparent-tissue",
        &frame,
        &reference(&f, Some((&overlay, &lut)), &cam, &s),
        MIN_PSNR,
        80,
    );
    assert!(
        c.pixels_off_by_more_than_one * 50 <= (SIZE * SIZE) as usize,
        "more than 2% of pixels off: {c:?}"
    );
    assert!(
        green_pixels(&before.rgba) == 0,
        "no green without the label"
    );
    assert!(
        green_pixels(&frame.rgba) > 300,
        "the label shows: {}",
        green_pixels(&frame.rgba)
    );
}

/// Two labels of very different colours side by side on a coarse grid (each grid voxel 16
/// primary voxels wide), opaque, filling the volume: every ray runs parallel to their common
/// face, so a pixel is pure red or pure green. A filtered (interpolated) fetch would blend them
/// over a band 16 voxels wide: pixels with red and green at once.
#[test]
fn labels_are_fetched_nearest_so_no_blended_colour_appears() {
    let ctx = gpu();
    let f = Fixture::ct(64);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let overlay = labels([4; 3], |i, _, _| if i < 2 { 1 } else { 2 });
    let lut = OverlayLut::new(vec![[0.0; 4], RED, GREEN], 0.0, 0.0, 0.0).unwrap();
    g.raycaster
        .set_overlay(&ctx, &overlay, &lut, f.volume.geometry.dims)
        .unwrap();
    let centre = f.volume.geometry.centre_patient();
    // Along the volume's z axis (orthographic, x across the image): the face x = 31.5 is
    // parallel to every ray; the image is slightly wider than the volume.
    let cam = Camera::look_at(
        (centre + DVec3::new(0.0, 0.0, 200.0)).into(),
        centre.into(),
        [0.0, -1.0, 0.0],
        Projection::Orthographic { height_mm: 70.0 },
    );
    let s = compare_settings(RenderMode::Dvr, SIZE);
    let gpu_frame = g.render(&ctx, &f, &cam, &s);
    let reference = reference(&f, Some((&overlay, &lut)), &cam, &s);
    for (name, rgba) in [("gpu", &gpu_frame.rgba), ("reference", &reference.rgba)] {
        save(&format!("overlay-nearest-{name}"), SIZE, SIZE, rgba);
        let (mut red, mut green) = (0, 0);
        for (i, p) in rgba.chunks_exact(4).enumerate() {
            assert!(
                p[2] == 0 && (p[0] == 0 || p[1] == 0),
                "{name}: pixel {i} is a blend {p:?}"
            );
            red += (p[0] > 100) as usize;
            green += (p[1] > 100) as usize;
        }
        assert!(
            red > 2000 && green > 2000,
            "{name}: {red} red, {green} green"
        );
        // The face is in view: some row has a red pixel right next to a green one.
        let adjacent = (0..SIZE as usize).any(|y| {
            (0..SIZE as usize - 1).any(|x| {
                let at = |x: usize| &rgba[(y * SIZE as usize + x) * 4..][..4];
                let (a, b) = (at(x), at(x + 1));
                (a[0] > 100 && b[1] > 100) || (a[1] > 100 && b[0] > 100)
            })
        });
        assert!(adjacent, "{name}: the two labels meet in the image");
    }
    assert_close("overlay-nearest", &gpu_frame, &reference, MIN_PSNR, MAX_ABS);
}

/// MIP takes the first shown overlay sample along the ray, the isosurface the overlay at the
/// hit; both follow the reference.
#[test]
fn mip_takes_the_first_shown_overlay_colour_and_the_isosurface_the_colour_at_the_hit() {
    let ctx = gpu();
    let f = Fixture::ct(64);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let overlay = label_box();
    let lut = label_lut(0.8, false);
    g.raycaster
        .set_overlay(&ctx, &overlay, &lut, f.volume.geometry.dims)
        .unwrap();
    let cam = orbit_ct(&f, 35.0, 25.0);
    let mip = compare_settings(RenderMode::Mip, SIZE);
    let frame = g.render(&ctx, &f, &cam, &mip);
    let r = reference(&f, Some((&overlay, &lut)), &cam, &mip);
    // PSNR 35 dB, max 255: the first shown overlay sample is found on the 0.5-voxel lattice
    // against the reference's 1/16, so along a label's silhouette a ray may see the label or
    // just miss it (full label colour or none); the 1 % rule below bounds how many.
    let c = assert_close("overlay-mip", &frame, &r, 35.0, 255);
    assert!(
        c.pixels_off_by_more_than_one * 100 <= (SIZE * SIZE) as usize,
        "more than 1% of MIP pixels off: {c:?}"
    );
    let iso = RenderSettings {
        iso_value: 300.0,
        ..compare_settings(RenderMode::Isosurface, SIZE)
    };
    let frame = g.render(&ctx, &f, &cam, &iso);
    let r = reference(&f, Some((&overlay, &lut)), &cam, &iso);
    // PSNR 35 dB: a handful of silhouette pixels where one ray hits the surface and the other
    // misses it are off by up to 255 and dominate the mean over the small surface; the 1 %
    // rule below bounds how many.
    let c = assert_close("overlay-iso", &frame, &r, 35.0, 255);
    assert!(
        c.pixels_off_by_more_than_one * 100 <= (SIZE * SIZE) as usize,
        "more than 1% of iso pixels off: {c:?}"
    );
    // The overlay changed both images (a test that could not fail proves nothing).
    g.raycaster.show_overlay(false);
    for s in [&mip, &iso] {
        let plain = g.render(&ctx, &f, &cam, s);
        g.raycaster.show_overlay(true);
        let coloured = g.render(&ctx, &f, &cam, s);
        g.raycaster.show_overlay(false);
        assert_ne!(plain.rgba, coloured.rgba, "{:?}", s.mode);
    }
}

/// An unused effect is not compiled in: without an overlay (none loaded, or one loaded but
/// hidden) the pipeline key has no overlay and the image is bit-identical to a raycaster whose
/// shader never had the overlay code (`const OVERLAY: bool = false;`).
#[test]
fn without_an_overlay_the_overlay_code_is_not_compiled_in() {
    let ctx = gpu();
    let f = Fixture::ct(64);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let variant = Raycaster::shader_source().replace(
        "override OVERLAY: bool = false;",
        "const OVERLAY: bool = false;",
    );
    assert_ne!(
        variant,
        Raycaster::shader_source(),
        "the override was replaced"
    );
    let mut never_had_it = Raycaster::with_shader_source(&ctx, &g.cache, &variant);
    let cam = orbit_ct(&f, 30.0, 20.0);
    for mode in [RenderMode::Dvr, RenderMode::Mip, RenderMode::Isosurface] {
        let s = RenderSettings {
            iso_value: 300.0,
            ..compare_settings(mode, SIZE)
        };
        assert!(!g.key(&f, &cam, &s).overlay);
        let today = g.render(&ctx, &f, &cam, &s);
        let scene = FrameInputs {
            cache: &g.cache,
            page_table: &g.page_table,
            transfer_function: &g.tf,
            geometry: &f.volume.geometry,
            mapping: f.volume.mapping,
            camera: &cam,
            settings: &s,
        };
        let without = never_had_it.render_blocking(&ctx, &scene).unwrap();
        assert_eq!(today.rgba, without.rgba, "{mode:?}");
        assert_eq!(today.depth, without.depth, "{mode:?}");

        // Loaded but hidden: the same pipeline, the same image; shown: a different one.
        let overlay = label_box();
        g.raycaster
            .set_overlay(
                &ctx,
                &overlay,
                &label_lut(0.7, false),
                f.volume.geometry.dims,
            )
            .unwrap();
        g.raycaster.show_overlay(false);
        assert!(!g.key(&f, &cam, &s).overlay);
        assert_eq!(g.render(&ctx, &f, &cam, &s).rgba, today.rgba, "{mode:?}");
        g.raycaster.show_overlay(true);
        assert!(g.key(&f, &cam, &s).overlay);
        assert_ne!(g.render(&ctx, &f, &cam, &s).rgba, today.rgba, "{mode:?}");
        g.raycaster.clear_overlay();
    }
}
