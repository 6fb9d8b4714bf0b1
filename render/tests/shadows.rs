//! Volumetric shadows from the key light, exact mode (render/src/model/shadows.rs): the GPU against
//! the f64 reference of the same model, and hard cases whose answer is known without either.
//! Images are 64² on lavapipe: every shaded sample traces a shadow ray, on the GPU and (at a
//! quarter of the shadow step) in the reference, whose cost grows with the image times the
//! volume's extent squared (shadows.rs, "Reference cost").
use crate::common;
use common::*;
use strata_render::reference::ReferenceImage;
use strata_render::*;

const SIZE: u32 = 64;
/// The primary reference step is the GPU's / 8, as in gpu_vs_reference.rs.
const REFINE: f64 = 8.0;

/// A 40³ scene: a floor (z 4..8) over the whole volume and an opaque slab (x, y 14..26, z 24..30)
/// above it. Seen from above (orthographic, looking down −z), lit from +x+z, the slab's shadow
/// falls on the floor at x ≲ 10, y 14..26, where nothing hides the floor from the camera.
fn slab_and_floor() -> Fixture {
    let volume = binary_volume(40, |x, y, z| {
        (4..8).contains(&z)
            || ((14..26).contains(&x) && (14..26).contains(&y) && (24..30).contains(&z))
    });
    let table = volume.page_table_uniform(0);
    Fixture::new(volume, table, opaque_tf())
}

fn floor_only() -> Fixture {
    let volume = binary_volume(40, |_, _, z| (4..8).contains(&z));
    let table = volume.page_table_uniform(0);
    Fixture::new(volume, table, opaque_tf())
}

fn from_above() -> Camera {
    Camera::look_at(
        [19.5, 19.5, 90.0],
        [19.5, 19.5, 0.0],
        [0.0, 1.0, 0.0],
        Projection::Orthographic { height_mm: 40.0 },
    )
}

fn shadowed(light: LightDirection, step: f64) -> RenderSettings {
    RenderSettings {
        shading: Some(Shading::default()),
        light: KeyLight {
            direction: light,
            intensity: 1.0,
        },
        shadows: Shadows {
            mode: ShadowMode::Exact,
            step,
            ..Shadows::default()
        },
        ..compare_settings(RenderMode::Dvr, SIZE)
    }
}

fn unshadowed(s: &RenderSettings) -> RenderSettings {
    RenderSettings {
        shadows: Shadows {
            mode: ShadowMode::Off,
            ..s.shadows
        },
        ..s.clone()
    }
}

/// The patient (x, y) a pixel of the from-above camera looks at.
fn floor_point(camera: &Camera, px: u32, py: u32) -> (f64, f64) {
    let (origin, _) = camera.basis().ray(px, py, SIZE, SIZE);
    (origin.x, origin.y)
}

fn assert_finite_reference(name: &str, r: &ReferenceImage) {
    let bad = r
        .rgba_f64
        .iter()
        .flatten()
        .filter(|v| !v.is_finite())
        .count();
    assert_eq!(bad, 0, "{name}: {bad} NaN/Inf channels in the reference");
    assert!(r.depth.iter().all(|d| !d.is_nan()), "{name}: NaN depth");
}

fn timed_reference(name: &str, f: &Fixture, camera: &Camera, s: &RenderSettings) -> ReferenceImage {
    let started = std::time::Instant::now();
    let r = f.reference(camera, s, REFINE);
    // Reported, never asserted: the reference's cost with shadow rays (shadows.rs).
    eprintln!("{name}: reference {:.2} s", started.elapsed().as_secs_f64());
    assert_finite_reference(name, &r);
    r
}

/// The floor in the slab's shadow keeps the ambient term only: each channel equals
/// ambient × colour × the pixel's opacity within ε = 2/255 (8-bit rounding of the GPU's store,
/// ≤ 0.5/255, plus the GPU shadow ray stopping at V < e⁻⁷ ≈ 0.9/1000 of a direct term ≤ 1.2;
/// the slab's ≥ 6 voxels of α clamped at 1 − 10⁻⁶ leave V < 10⁻³⁶ anyway). The lit floor
/// beside it is at least twice as bright (n·l = cos 45°: ambient 0.3 against 0.3 + 0.7·0.71),
/// so a shadow in the wrong place, or none, fails. The reference agrees on both regions.
#[test]
fn opaque_slab_leaves_the_shadowed_floor_at_the_ambient_term() {
    let ctx = gpu();
    let f = slab_and_floor();
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = from_above();
    let s = shadowed(LightDirection::Patient([1.0, 0.0, 1.0]), 1.0);
    let frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("slab", &f, &cam, &s);
    let ambient = Shading::default().ambient as f64;
    let (mut in_shadow, mut lit) = (Vec::new(), Vec::new());
    for py in 0..SIZE {
        for px in 0..SIZE {
            let (x, y) = floor_point(&cam, px, py);
            let i = ((py * SIZE + px) * 4) as usize;
            let pixel = &frame.rgba[i..i + 4];
            let reference_pixel = &reference.rgba_f64[(py * SIZE + px) as usize];
            // Well inside the shadow: the ray to the light from (x, y, ~7.8) crosses the
            // slab's bottom face at x + 15.7 ∈ [13.5, 25.5] for x ≤ 9.8.
            if (1.0..=7.0).contains(&x) && (16.0..=24.0).contains(&y) {
                let a = pixel[3] as f64 / 255.0;
                assert!(a > 0.98, "floor pixel ({px}, {py}) not opaque: {pixel:?}");
                for c in 0..3 {
                    let expected = ambient * OPAQUE_COLOUR[c] * a;
                    let got = pixel[c] as f64 / 255.0;
                    assert!(
                        (got - expected).abs() <= 2.0 / 255.0,
                        "shadowed ({px}, {py}) channel {c}: {got} vs ambient {expected}"
                    );
                    let expected_ref = ambient * OPAQUE_COLOUR[c] * reference_pixel[3];
                    assert!(
                        (reference_pixel[c] - expected_ref).abs() < 1e-6,
                        "reference shadowed ({px}, {py}): {reference_pixel:?}"
                    );
                }
                in_shadow.push(pixel[0]);
            }
            if (1.0..=7.0).contains(&x) && ((2.0..=10.0).contains(&y) || (30.0..=38.0).contains(&y))
            {
                lit.push(pixel[0]);
            }
        }
    }
    assert!(
        in_shadow.len() > 40 && lit.len() > 80,
        "{} {}",
        in_shadow.len(),
        lit.len()
    );
    let darkest_lit = *lit.iter().min().unwrap_or(&0);
    let brightest_shadow = *in_shadow.iter().max().unwrap_or(&255);
    assert!(
        darkest_lit as f64 >= 2.0 * brightest_shadow as f64,
        "lit floor {darkest_lit} not twice the shadowed {brightest_shadow}"
    );
    // Whole image against the reference. Bound 35 dB (41.4 measured). Two kinds of pixels
    // differ, and each is bounded: the rim of the slab seen from above, where the f32 view ray
    // and the f64 one cross the opaque slab's 0.1-voxel opacity band at different depths
    // (primary-ray silhouette error, as in gpu_vs_reference.rs: ≤ 24/255), and pixels where a
    // shadow ray grazes the slab's edge: with no penumbra for exact rays, the GPU's 1-voxel
    // shadow step against the reference's ¼ decides within a voxel whether the ray is blocked,
    // so such a pixel flips between lit and ambient (2 of 4096 measured; bounded at 0.5 %).
    let c = compare_rgba8(&frame.rgba, &reference.rgba).unwrap();
    save("shadows-slab-gpu", SIZE, SIZE, &frame.rgba);
    save("shadows-slab-ref", SIZE, SIZE, &reference.rgba);
    let flipped = frame
        .rgba
        .iter()
        .zip(&reference.rgba)
        .filter(|(a, b)| a.abs_diff(**b) > 24)
        .count();
    eprintln!("slab: {c:?}, channels off by > 24: {flipped}");
    assert!(c.psnr_db >= 35.0, "{c:?}");
    assert!(
        flipped <= (SIZE * SIZE * 4 / 200) as usize,
        "{flipped} channels: {c:?}"
    );
}

/// A light along the view axis over a floor with nothing above it: every lit sample's shadow
/// ray leaves through air (the bias r₀ = 1 voxel clears the floor's interpolation band, which
/// is under 0.1 voxel thick for this TF, and the first sample is at most a main step of 0.5
/// voxel deep), so V = exp(0) = 1 exactly and the shadowed image is the unshadowed one, bit for
/// bit. And that key light, along the view of an orthographic camera, is the headlight: the
/// image equals the default pipeline's (shading.wgsl) within one 8-bit step (f32 rounding of
/// two formulas for the same value).
#[test]
fn light_along_the_view_with_nothing_in_the_way_changes_nothing() {
    let ctx = gpu();
    let f = floor_only();
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = from_above();
    let s = shadowed(LightDirection::Camera([0.0, 0.0, 1.0]), 1.0);
    let with = g.render(&ctx, &f, &cam, &s);
    let without = g.render(&ctx, &f, &cam, &unshadowed(&s));
    assert!(g.key(&f, &cam, &s).shadows && !g.key(&f, &cam, &unshadowed(&s)).shadows);
    assert_eq!(
        with.rgba, without.rgba,
        "shadow rays through air changed the image"
    );
    let headlight = RenderSettings {
        light: KeyLight::default(),
        ..unshadowed(&s)
    };
    assert!(!g.key(&f, &cam, &headlight).key_light);
    let old = g.render(&ctx, &f, &cam, &headlight);
    let c = compare_rgba8(&with.rgba, &old.rgba).unwrap();
    assert!(
        c.max_abs_error <= 1,
        "key light along the view vs headlight: {c:?}"
    );
    let covered = with.rgba.chunks_exact(4).filter(|p| p[3] > 0).count();
    assert_eq!(covered, (SIZE * SIZE) as usize, "the floor fills the view");
}

/// GPU against the f64 reference on the CT phantom (semi-transparent soft tissue: shadows are
/// partial, so the transmittance itself is compared, not just 0 or 1), oblique camera and
/// light. Bound 45 dB (52.0 measured): the main ray's own error is ≥ 40 dB at 128² on the 96³
/// phantom (gpu_vs_reference.rs) and smaller on this softer 32³ one; the GPU's shadow step of
/// one voxel against the reference's ¼ adds the midpoint rule's error on the optical depth
/// (second order; the phantom's 2-voxel edges bend the TF within a shadow step), and the GPU's
/// τ cut at 7 at most 10⁻³ of a direct term. Max abs 24/255: silhouette pixels as in
/// gpu_vs_reference.rs, and shadow rays grazing the bone shell's edge, which the two steps
/// resolve differently (13 measured).
#[test]
fn shadowed_phantom_matches_reference() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, 35.0, 25.0, 1.5, 35.0);
    let s = shadowed(LightDirection::Camera([0.6, 0.7, 0.4]), 1.0);
    let gpu_frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("phantom", &f, &cam, &s);
    let c = assert_close("shadows-phantom", &gpu_frame, &reference, 45.0, 24);
    // The shadows show: the same view unshadowed is measurably different (else this test
    // would pass with shadows ignored).
    let plain = g.render(&ctx, &f, &cam, &unshadowed(&s));
    let d = compare_rgba8(&plain.rgba, &gpu_frame.rgba).unwrap();
    eprintln!("phantom with vs without shadows: {d:?} (vs reference {c:?})");
    assert!(
        d.psnr_db < c.psnr_db - 6.0,
        "shadows barely change the image: {d:?}"
    );
}

/// The headlight with shadows: each shadow ray runs back along its own view ray (a light at the
/// eye), attenuated by what the view ray crossed. Same bound and reasons as above (52.1 dB
/// measured).
#[test]
fn shadowed_headlight_matches_reference() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = orbit(&f.volume.geometry, -20.0, 10.0, 1.5, 35.0);
    let s = shadowed(LightDirection::Headlight, 1.0);
    assert!(g.key(&f, &cam, &s).key_light);
    let gpu_frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("headlight", &f, &cam, &s);
    assert_close("shadows-headlight", &gpu_frame, &reference, 45.0, 24);
}

/// Light exactly along +x: every shadow ray runs parallel to four faces of the volume (zero
/// direction components) and samples on the y and z faces graze them. Against the reference,
/// finite, and continuous: a direction 10⁻⁹ off the axis gives the same image within one step.
/// Bound as above (54.1 dB measured).
#[test]
fn light_grazing_along_the_volume_faces() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = Camera::orbit(
        &f.volume.geometry,
        0.0,
        0.0,
        1.2,
        Projection::Orthographic { height_mm: 40.0 },
    );
    let s = shadowed(LightDirection::Patient([1.0, 0.0, 0.0]), 1.0);
    let gpu_frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("grazing", &f, &cam, &s);
    assert_close("shadows-grazing", &gpu_frame, &reference, 45.0, 24);
    let tilted = shadowed(LightDirection::Patient([1.0, 1e-9, -1e-9]), 1.0);
    let other = g.render(&ctx, &f, &cam, &tilted);
    let c = compare_rgba8(&gpu_frame.rgba, &other.rgba).unwrap();
    assert!(c.max_abs_error <= 1, "grazing light not continuous: {c:?}");
}

/// An empty volume: black, depth +inf everywhere, whatever the light, on GPU and reference.
#[test]
fn empty_volume_is_black_with_shadows_on() {
    let ctx = gpu();
    let volume = binary_volume(32, |_, _, _| false);
    let table = volume.page_table_uniform(0);
    let f = Fixture::new(volume, table, opaque_tf());
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = from_above();
    for skip_empty in [true, false] {
        let s = RenderSettings {
            skip_empty,
            ..shadowed(LightDirection::Camera([0.3, -0.5, 0.8]), 0.5)
        };
        let frame = g.render(&ctx, &f, &cam, &s);
        assert!(
            frame.rgba.iter().all(|&v| v == 0),
            "skip_empty {skip_empty}"
        );
        assert!(frame.depth.iter().all(|d| *d == f32::INFINITY));
        let reference = timed_reference("empty", &f, &cam, &s);
        assert!(reference.rgba.iter().all(|&v| v == 0));
    }
}

/// The isosurface is lit by the key light and shadowed too: the floor's isosurface in the
/// slab's shadow keeps the ambient term (an iso pixel is opaque, so exactly ambient × colour
/// of the TF at the iso value, within the same ε as the DVR case).
#[test]
fn isosurface_in_the_slabs_shadow_keeps_the_ambient_term() {
    let ctx = gpu();
    let f = slab_and_floor();
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = from_above();
    let s = RenderSettings {
        mode: RenderMode::Isosurface,
        iso_value: 0.0,
        ..shadowed(LightDirection::Patient([1.0, 0.0, 1.0]), 1.0)
    };
    let frame = g.render(&ctx, &f, &cam, &s);
    let ambient = Shading::default().ambient as f64;
    let mut checked = 0;
    for py in 0..SIZE {
        for px in 0..SIZE {
            let (x, y) = floor_point(&cam, px, py);
            if (1.0..=7.0).contains(&x) && (16.0..=24.0).contains(&y) {
                let i = ((py * SIZE + px) * 4) as usize;
                for (c, colour) in OPAQUE_COLOUR.iter().enumerate() {
                    let got = frame.rgba[i + c] as f64 / 255.0;
                    assert!(
                        (got - ambient * colour).abs() <= 2.0 / 255.0,
                        "iso shadowed ({px}, {py}): {:?}",
                        &frame.rgba[i..i + 4]
                    );
                }
                checked += 1;
            }
        }
    }
    assert!(checked > 40);
    let reference = timed_reference("iso-slab", &f, &cam, &s);
    let c = compare_rgba8(&frame.rgba, &reference.rgba).unwrap();
    eprintln!("iso slab: {c:?}");
    assert!(
        c.pixels_off_by_more_than_one <= (SIZE * SIZE * 3 / 100) as usize,
        "{c:?}"
    );
}

/// Default settings compile no key-light or shadow code, and shadows asked for without shading
/// (unlit DVR) or in MIP compile none either: there is no direct term to shadow.
#[test]
fn shadows_are_compiled_in_only_when_they_light_something() {
    let ctx = gpu();
    let f = floor_only();
    let g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = from_above();
    let default = compare_settings(RenderMode::Dvr, SIZE);
    let k = g.key(&f, &cam, &default);
    assert!(!k.key_light && !k.shadows);
    let on = shadowed(LightDirection::Headlight, 1.0);
    for s in [
        RenderSettings {
            shading: None,
            ..on.clone()
        },
        RenderSettings {
            mode: RenderMode::Mip,
            ..on.clone()
        },
    ] {
        let k = g.key(&f, &cam, &s);
        assert!(!k.key_light && !k.shadows, "{:?}", s.mode);
    }
    let k = g.key(&f, &cam, &on);
    assert!(k.key_light && k.shadows);
}

/// A clip plane that cuts the slab away lets the light in (the cut casts no shadow; shadows.rs):
/// the floor is lit as if the slab were not there. The clipped view ray starts at the plane
/// z = 20, 39 main steps below the box's top face, so its samples are the unclipped floor-only
/// view's: the images agree within one 8-bit step, and with the reference.
#[test]
fn light_enters_through_the_clip_plane() {
    let ctx = gpu();
    let cam = from_above();
    let s = shadowed(LightDirection::Patient([1.0, 0.0, 1.0]), 1.0);
    let clipped = RenderSettings {
        // Keeps −z ≥ −20: everything below z = 20, the floor but not the slab.
        clip_plane: Some(ClipPlane {
            normal: [0.0, 0.0, -1.0],
            offset_mm: -20.0,
        }),
        ..s.clone()
    };
    let f = slab_and_floor();
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cut = g.render(&ctx, &f, &cam, &clipped);
    let shadowed_floor = g.render(&ctx, &f, &cam, &s);
    let floor = floor_only();
    let mut g_floor = GpuScene::new(&ctx, &floor, CacheConfig::default());
    let open = g_floor.render(&ctx, &floor, &cam, &s);
    let c = compare_rgba8(&cut.rgba, &open.rgba).unwrap();
    assert!(c.max_abs_error <= 1, "clipped slab still shadows: {c:?}");
    // And the slab, unclipped, does shadow this floor (else the test proves nothing).
    let d = compare_rgba8(&shadowed_floor.rgba, &open.rgba).unwrap();
    assert!(d.max_abs_error > 40, "{d:?}");
    let reference = timed_reference("clip", &f, &cam, &clipped);
    let r = compare_rgba8(&cut.rgba, &reference.rgba).unwrap();
    eprintln!("clip: {r:?}");
    assert!(r.psnr_db >= 45.0, "{r:?}");
}

/// Cache-mode shadows (render/src/gpu/light_cache.rs): the light-transmittance cache swept on the
/// GPU against the f64 reference of the same model (the cache's texels themselves, then
/// images), against exact shadows, the hard cases, and when it is (not) rebuilt.
mod cache {
    use super::*;
    use strata_render::reference::{reference_light_cache, ReferenceScene};

    fn cached(light: LightDirection, res: f64) -> RenderSettings {
        let s = shadowed(light, 1.0);
        RenderSettings {
            shadows: Shadows {
                mode: ShadowMode::Cache,
                cache_res: res,
                ..s.shadows
            },
            ..s
        }
    }

    fn exact(s: &RenderSettings) -> RenderSettings {
        RenderSettings {
            shadows: Shadows {
                mode: ShadowMode::Exact,
                ..s.shadows
            },
            ..s.clone()
        }
    }

    fn reference_texels(f: &Fixture, cam: &Camera, s: &RenderSettings) -> Vec<f64> {
        let scene = ReferenceScene {
            source: &f.volume,
            page_table: &f.page_table,
            geometry: &f.volume.geometry,
            mapping: f.volume.mapping,
            transfer_function: &f.tf,
            tf_range: (f.tf_table.lo, f.tf_table.hi),
        };
        reference_light_cache(&scene, cam, s)
    }

    fn phantom_view(f: &Fixture) -> Camera {
        orbit(&f.volume.geometry, 35.0, 25.0, 1.5, 35.0)
    }

    /// The GPU's texels against the f64 reference's sweep (the cache's own error, before the
    /// lookup): finite, in [0, 1], and within 0.02 of each other. The bound is the exact
    /// shadow ray's, accumulated over the sweep: per segment the GPU's one-voxel shadow step
    /// against the reference's ¼ (midpoint rule on the optical depth), the GPU stopping a
    /// segment at τ = 7, and f32 in the bilinear steps. A segment that grazes the bone shell's
    /// edge can differ by more (the two steps resolve the edge differently, as for exact
    /// shadows), and the sweep carries that difference on; at most 1 % of the texels may.
    /// Measured: max |ΔV| 0.026 at 2 voxels per texel (2 of 4096 over 0.02), 0.018 at 4.
    #[test]
    fn cache_texels_match_the_reference_sweep() {
        let ctx = gpu();
        let f = Fixture::ct(32);
        let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
        let cam = phantom_view(&f);
        for res in [2.0, 4.0] {
            let s = cached(LightDirection::Camera([0.6, 0.7, 0.4]), res);
            g.render(&ctx, &f, &cam, &s);
            let gpu_texels = g.raycaster.read_light_cache_blocking(&ctx).unwrap();
            let ref_texels = reference_texels(&f, &cam, &s);
            assert_eq!(gpu_texels.len(), ref_texels.len());
            assert!(gpu_texels
                .iter()
                .all(|v| v.is_finite() && (0.0..=1.0).contains(v)));
            assert!(ref_texels.iter().all(|v| v.is_finite()));
            let errors: Vec<f64> = gpu_texels
                .iter()
                .zip(&ref_texels)
                .map(|(a, b)| (*a as f64 - b).abs())
                .collect();
            let off = errors.iter().filter(|e| **e > 0.02).count();
            let max = errors.iter().cloned().fold(0.0, f64::max);
            let shadowed = ref_texels.iter().filter(|v| **v < 0.9).count();
            eprintln!(
                "res {res}: {} texels, {shadowed} with V < 0.9, max |ΔV| {max:.4}, > 0.02: {off}",
                ref_texels.len()
            );
            assert!(shadowed > ref_texels.len() / 20, "nothing casts a shadow");
            assert!(off * 100 <= ref_texels.len(), "{off} texels off by > 0.02");
        }
    }

    /// Cache against the f64 reference of the same model (the reference sweeps and
    /// interpolates its own texels as the shader does), and against exact shadows. Reference
    /// bound 45 dB as for exact shadows (same main ray, the texel error above; the lookup is
    /// the same formula). Against exact shadows the cache is blurred by its resolution (V
    /// interpolated over 2-voxel cells, the lookup moved a cell towards the light, the
    /// sweep's bilinear steps): its shadows' edges are soft over about a cell and contact
    /// shadows within a cell are missing, so the bound is lower: 38 dB at 2 voxels per texel,
    /// and coarser cells must not agree better. Measured on lavapipe: 50.4 dB against the
    /// reference (max 15/255); against exact 44.7 dB at 2 voxels per texel, 38.6 dB at 4,
    /// where no shadows at all are 31.3 dB from exact.
    #[test]
    fn cache_matches_its_reference_and_approximates_exact_shadows() {
        let ctx = gpu();
        let f = Fixture::ct(32);
        let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
        let cam = phantom_view(&f);
        let s = cached(LightDirection::Camera([0.6, 0.7, 0.4]), 2.0);
        assert!(g.key(&f, &cam, &s).light_cache && !g.key(&f, &cam, &s).shadows);
        let frame = g.render(&ctx, &f, &cam, &s);
        let reference = timed_reference("cache-phantom", &f, &cam, &s);
        let c = assert_close("shadows-cache-phantom", &frame, &reference, 45.0, 24);
        let exact_frame = g.render(&ctx, &f, &cam, &exact(&s));
        let e = compare_rgba8(&frame.rgba, &exact_frame.rgba).unwrap();
        let coarse = g.render(
            &ctx,
            &f,
            &cam,
            &cached(LightDirection::Camera([0.6, 0.7, 0.4]), 4.0),
        );
        let e4 = compare_rgba8(&coarse.rgba, &exact_frame.rgba).unwrap();
        let plain = g.render(&ctx, &f, &cam, &unshadowed(&s));
        let d = compare_rgba8(&plain.rgba, &exact_frame.rgba).unwrap();
        eprintln!("cache vs reference {c:?}\ncache(2) vs exact {e:?}\ncache(4) vs exact {e4:?}\nunshadowed vs exact {d:?}");
        assert!(e.psnr_db >= 38.0, "cache vs exact: {e:?}");
        assert!(
            e4.psnr_db <= e.psnr_db + 0.5,
            "coarser agrees better: {e4:?} vs {e:?}"
        );
        // The cache is closer to exact shadows than no shadows are.
        assert!(e.psnr_db > d.psnr_db + 6.0, "{e:?} vs unshadowed {d:?}");
    }

    /// The opaque slab over the floor, cache mode: the floor well inside the shadow keeps the
    /// ambient term within ε = 4/255 (exact's 2/255 plus the cache's blur: V is interpolated
    /// between texels whose rays pass 1-2 voxels apart and diffused by the sweep's bilinear
    /// steps over the 16 voxels from slab to floor, and the region stops 2 voxels, one cell,
    /// from the shadow's edges so that only the leak of a cell reaches it), and is
    /// at most half as bright as the lit floor. Against the reference of the same model,
    /// 35 dB (the exact case's bound: the same silhouette and grazing pixels). Measured:
    /// 0.5/255 off ambient (the region lies a cell inside the edges, where every texel read
    /// is fully shadowed), 43.1 dB against the reference.
    #[test]
    fn opaque_slab_shadow_from_the_cache_is_ambient() {
        let ctx = gpu();
        let f = slab_and_floor();
        let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
        let cam = from_above();
        let s = cached(LightDirection::Patient([1.0, 0.0, 1.0]), 2.0);
        let frame = g.render(&ctx, &f, &cam, &s);
        let ambient = Shading::default().ambient as f64;
        let (mut in_shadow, mut lit, mut worst) = (Vec::new(), Vec::new(), 0.0f64);
        for py in 0..SIZE {
            for px in 0..SIZE {
                let (x, y) = floor_point(&cam, px, py);
                let i = ((py * SIZE + px) * 4) as usize;
                let pixel = &frame.rgba[i..i + 4];
                if (1.0..=7.0).contains(&x) && (16.0..=24.0).contains(&y) {
                    let a = pixel[3] as f64 / 255.0;
                    for c in 0..3 {
                        let got = pixel[c] as f64 / 255.0;
                        worst = worst.max((got - ambient * OPAQUE_COLOUR[c] * a).abs());
                    }
                    in_shadow.push(pixel[0]);
                }
                if (1.0..=7.0).contains(&x)
                    && ((2.0..=10.0).contains(&y) || (30.0..=38.0).contains(&y))
                {
                    lit.push(pixel[0]);
                }
            }
        }
        eprintln!("cache slab: worst shadowed error {:.2}/255", worst * 255.0);
        assert!(
            worst <= 4.0 / 255.0,
            "shadowed floor {:.2}/255 off ambient",
            worst * 255.0
        );
        assert!(in_shadow.len() > 40 && lit.len() > 80);
        let darkest_lit = *lit.iter().min().unwrap_or(&0);
        let brightest_shadow = *in_shadow.iter().max().unwrap_or(&255);
        assert!(darkest_lit as f64 >= 2.0 * brightest_shadow as f64);
        let reference = timed_reference("cache-slab", &f, &cam, &s);
        let c = compare_rgba8(&frame.rgba, &reference.rgba).unwrap();
        save("shadows-cache-slab-gpu", SIZE, SIZE, &frame.rgba);
        eprintln!("cache slab vs reference: {c:?}");
        assert!(c.psnr_db >= 35.0, "{c:?}");
    }

    /// The cache is built once and kept while only the camera moves (patient-relative light),
    /// or the light's intensity changes; rebuilt when the light turns, the TF changes, the crop
    /// changes or the page table is written; and a camera-relative light turns with the camera,
    /// so orbiting rebuilds it.
    #[test]
    fn cache_is_rebuilt_only_when_what_it_was_built_from_changes() {
        let ctx = gpu();
        let f = Fixture::ct(32);
        let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
        let orbit = |az: f64| {
            Camera::orbit(
                &f.volume.geometry,
                az,
                20.0,
                1.5,
                Projection::Orthographic { height_mm: 40.0 },
            )
        };
        let s = RenderSettings {
            width: 32,
            height: 32,
            ..cached(LightDirection::Patient([0.3, 0.5, 0.8]), 2.0)
        };
        assert_eq!(g.raycaster.light_cache_builds(), 0);
        for az in [0.0, 30.0, 60.0, 90.0] {
            g.render(&ctx, &f, &orbit(az), &s);
        }
        assert_eq!(
            g.raycaster.light_cache_builds(),
            1,
            "camera moves rebuilt it"
        );
        let dimmer = RenderSettings {
            light: KeyLight {
                intensity: 0.5,
                ..s.light
            },
            ..s.clone()
        };
        g.render(&ctx, &f, &orbit(0.0), &dimmer);
        // Shadows off and on again with nothing changed: still the same cache.
        g.render(&ctx, &f, &orbit(0.0), &unshadowed(&s));
        g.render(&ctx, &f, &orbit(0.0), &s);
        assert_eq!(g.raycaster.light_cache_builds(), 1, "intensity rebuilt it");
        let turned = cached(LightDirection::Patient([-0.3, 0.5, 0.8]), 2.0);
        let turned = RenderSettings {
            width: 32,
            height: 32,
            ..turned
        };
        g.render(&ctx, &f, &orbit(0.0), &turned);
        assert_eq!(g.raycaster.light_cache_builds(), 2, "light turned");
        g.render(&ctx, &f, &orbit(45.0), &turned);
        assert_eq!(g.raycaster.light_cache_builds(), 2);
        // A different TF (bone only): rebuilt once, then kept.
        let bone = TransferFunction::new(
            "bone",
            &[(-1024.0, 0.0), (200.0, 0.0), (600.0, 0.8), (3000.0, 0.8)],
            &[(-1024.0, [1.0; 3]), (3000.0, [1.0; 3])],
        );
        g.tf.update(&ctx.queue, &bone.table(f.tf_table.lo, f.tf_table.hi));
        g.tf.source = bone;
        g.render(&ctx, &f, &orbit(0.0), &turned);
        g.render(&ctx, &f, &orbit(10.0), &turned);
        assert_eq!(g.raycaster.light_cache_builds(), 3, "TF change");
        let cropped = RenderSettings {
            crop: CropBox {
                min: [0.0, 0.0, 0.0],
                max: [1.0, 1.0, 0.6],
            },
            ..turned.clone()
        };
        g.render(&ctx, &f, &orbit(0.0), &cropped);
        assert_eq!(g.raycaster.light_cache_builds(), 4, "crop change");
        g.page_table.update(&ctx.queue, &f.page_table).unwrap();
        g.render(&ctx, &f, &orbit(0.0), &cropped);
        assert_eq!(g.raycaster.light_cache_builds(), 5, "page table written");
        let camera_light = RenderSettings {
            width: 32,
            height: 32,
            ..cached(LightDirection::Camera([0.3, 0.5, 0.8]), 2.0)
        };
        g.render(&ctx, &f, &orbit(0.0), &camera_light);
        g.render(&ctx, &f, &orbit(0.0), &camera_light);
        assert_eq!(g.raycaster.light_cache_builds(), 6);
        g.render(&ctx, &f, &orbit(40.0), &camera_light);
        assert_eq!(
            g.raycaster.light_cache_builds(),
            7,
            "camera light turned with the camera"
        );
    }

    /// The cache's lookup is compiled in only for cache shadows in a lit mode, never together
    /// with exact shadow rays, and none of it without shading or in MIP.
    #[test]
    fn the_cache_is_compiled_in_only_when_it_lights_something() {
        let ctx = gpu();
        let f = floor_only();
        let g = GpuScene::new(&ctx, &f, CacheConfig::default());
        let cam = from_above();
        let on = cached(LightDirection::Patient([1.0, 0.0, 1.0]), 2.0);
        let k = g.key(&f, &cam, &on);
        assert!(k.key_light && k.light_cache && !k.shadows);
        let k = g.key(&f, &cam, &exact(&on));
        assert!(k.shadows && !k.light_cache);
        let k = g.key(&f, &cam, &unshadowed(&on));
        assert!(!k.light_cache && !k.shadows);
        for s in [
            RenderSettings {
                shading: None,
                ..on.clone()
            },
            RenderSettings {
                mode: RenderMode::Mip,
                ..on.clone()
            },
        ] {
            assert!(!g.key(&f, &cam, &s).light_cache, "{:?}", s.mode);
        }
    }

    /// An empty volume with cache shadows: black, depth +inf, every texel V = 1 (nothing casts
    /// a shadow; with empty skipping no field is even sampled), on GPU and reference; and the
    /// headlight, whose direction is each ray's own, is refused, not drawn wrong.
    #[test]
    fn empty_volume_is_black_and_the_headlight_is_refused() {
        let ctx = gpu();
        let volume = binary_volume(32, |_, _, _| false);
        let table = volume.page_table_uniform(0);
        let f = Fixture::new(volume, table, opaque_tf());
        let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
        let cam = from_above();
        for skip_empty in [true, false] {
            let s = RenderSettings {
                skip_empty,
                ..cached(LightDirection::Camera([0.3, -0.5, 0.8]), 2.0)
            };
            let frame = g.render(&ctx, &f, &cam, &s);
            assert!(
                frame.rgba.iter().all(|&v| v == 0),
                "skip_empty {skip_empty}"
            );
            assert!(frame.depth.iter().all(|d| *d == f32::INFINITY));
            let texels = g.raycaster.read_light_cache_blocking(&ctx).unwrap();
            assert!(!texels.is_empty() && texels.iter().all(|v| *v == 1.0));
            let reference = timed_reference("cache-empty", &f, &cam, &s);
            assert!(reference.rgba.iter().all(|&v| v == 0));
        }
        let headlight = cached(LightDirection::Headlight, 2.0);
        let scene = FrameInputs {
            cache: &g.cache,
            page_table: &g.page_table,
            transfer_function: &g.tf,
            geometry: &f.volume.geometry,
            mapping: f.volume.mapping,
            camera: &cam,
            settings: &headlight,
        };
        assert!(matches!(
            g.raycaster.render(&ctx, &scene),
            Err(RenderError::InvalidSettings(_))
        ));
    }
}
