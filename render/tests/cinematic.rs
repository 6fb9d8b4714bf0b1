//! Ambient occlusion (render/src/model/ambient_occlusion.rs) and single scattering
//! (render/src/model/scattering.rs): the GPU against the f64 reference of the same model, and hard
//! cases whose answer is known without either. Images are 64² on lavapipe, volumes 32³-40³:
//! every shaded reference sample traces 16 occlusion rays and a shadow ray at a quarter of the
//! GPU's step (ambient_occlusion.rs, "Cost"), so the references take seconds on two cores.
use crate::common;
use common::*;
use strata_render::reference::ReferenceImage;
use strata_render::*;

const SIZE: u32 = 64;
/// The primary reference step is the GPU's / 4 (shadows.rs uses 8): each shaded reference
/// sample costs 16 occlusion rays, and the main ray's midpoint error at ¼ of the GPU's step is
/// already 1/16 of the GPU's own (second order), well under the bounds below.
const REFINE: f64 = 4.0;

fn binary_fixture(n: u32, solid: impl Fn(u32, u32, u32) -> bool + Sync) -> Fixture {
    let volume = binary_volume(n, solid);
    let table = volume.page_table_uniform(0);
    Fixture::new(volume, table, opaque_tf())
}

/// shadows.rs's scene: a floor (z 4..8) and an opaque slab (x, y 14..26, z 24..30) above it.
fn slab_and_floor() -> Fixture {
    binary_fixture(40, |x, y, z| {
        (4..8).contains(&z)
            || ((14..26).contains(&x) && (14..26).contains(&y) && (24..30).contains(&z))
    })
}

fn from_above() -> Camera {
    Camera::look_at(
        [19.5, 19.5, 90.0],
        [19.5, 19.5, 0.0],
        [0.0, 1.0, 0.0],
        Projection::Orthographic { height_mm: 40.0 },
    )
}

fn oblique(f: &Fixture, azimuth: f64, elevation: f64) -> Camera {
    orbit(&f.volume.geometry, azimuth, elevation, 1.5, 35.0)
}

/// Shaded DVR lit by `light`, shadows off, no effect yet.
fn lit(light: LightDirection) -> RenderSettings {
    RenderSettings {
        shading: Some(Shading::default()),
        light: KeyLight {
            direction: light,
            intensity: 1.0,
        },
        ..compare_settings(RenderMode::Dvr, SIZE)
    }
}

fn with_occlusion(s: RenderSettings, radius_mm: f64) -> RenderSettings {
    RenderSettings {
        occlusion: Some(Occlusion { radius_mm }),
        ..s
    }
}

fn with_scattering(s: RenderSettings, g: f64, blend: f64) -> RenderSettings {
    RenderSettings {
        scattering: Some(Scattering { g, blend }),
        ..s
    }
}

fn with_exact_shadows(s: RenderSettings) -> RenderSettings {
    RenderSettings {
        shadows: Shadows {
            mode: ShadowMode::Exact,
            step: 1.0,
            ..Shadows::default()
        },
        ..s
    }
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
    // Reported, never asserted: the reference's cost with occlusion and shadow rays.
    eprintln!("{name}: reference {:.2} s", started.elapsed().as_secs_f64());
    assert_finite_reference(name, &r);
    r
}

/// The image differs measurably from `other` (so a test passes only if the effect is drawn).
fn assert_changes(name: &str, with: &FrameReadback, without: &FrameReadback, vs_ref: f64) {
    let d = compare_rgba8(&with.rgba, &without.rgba).unwrap();
    eprintln!("{name}: with vs without the effect {d:?}");
    assert!(
        d.psnr_db < vs_ref - 6.0,
        "{name}: the effect barely changes the image: {d:?}"
    );
}

/// Occlusion on the CT phantom (soft tissue semi-transparent, so AO is partial), oblique camera
/// and light, radius 3 mm. The bound and its reasons are those of shadows.rs's phantom test:
/// the main ray's own error (≥ 40 dB at 128² on the 96³ phantom, less on this softer 32³ one),
/// the occlusion rays' 1-voxel step against the reference's ¼ (midpoint rule on each ray's
/// optical depth) and the GPU's τ cut at 7 (< 10⁻³ of the ambient term); AO only scales the
/// ambient term (0.3), so its errors are damped by that factor. 46.9 dB measured, max abs 23:
/// the tightest margin of this file; the large channels are silhouette pixels of the bone
/// shell, as in gpu_vs_reference.rs.
#[test]
fn occlusion_on_the_phantom_matches_reference() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = oblique(&f, 35.0, 25.0);
    let plain = lit(LightDirection::Camera([0.6, 0.7, 0.4]));
    let s = with_occlusion(plain.clone(), 3.0);
    assert!(g.key(&f, &cam, &s).occlusion && !g.key(&f, &cam, &plain).occlusion);
    let frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("occlusion-phantom", &f, &cam, &s);
    let c = assert_close("occlusion-phantom", &frame, &reference, 45.0, 24);
    let without = g.render(&ctx, &f, &cam, &plain);
    assert_changes("occlusion-phantom", &frame, &without, c.psnr_db);
}

/// Scattering (g = 0.5, blend 0.5) with exact shadows on the phantom, light from behind and
/// to the side (so the forward lobe matters). Bound as above: the phase depends only on the
/// light and ray directions, which both renderers evaluate from the same f64 inputs; the
/// hybrid weight on the gradient magnitude, which differs as the main ray's samples do.
/// 60.1 dB measured.
#[test]
fn scattering_on_the_phantom_matches_reference() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = oblique(&f, -30.0, 20.0);
    let plain = with_exact_shadows(lit(LightDirection::Camera([0.5, 0.3, -0.8])));
    let s = with_scattering(plain.clone(), 0.5, 0.5);
    let k = g.key(&f, &cam, &s);
    assert!(k.scattering && k.shadows && !k.occlusion);
    let frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("scattering-phantom", &f, &cam, &s);
    let c = assert_close("scattering-phantom", &frame, &reference, 45.0, 24);
    let without = g.render(&ctx, &f, &cam, &plain);
    assert_changes("scattering-phantom", &frame, &without, c.psnr_db);
}

/// Both effects at once under the headlight (per-ray light direction, μ = −1:
/// back-scattering; shadows under the headlight are shadows.rs's). Bound as above (61.8 dB
/// measured).
#[test]
fn occlusion_and_scattering_under_the_headlight_match_reference() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = oblique(&f, 60.0, -15.0);
    let s = with_scattering(
        with_occlusion(lit(LightDirection::Headlight), 2.0),
        -0.3,
        0.3,
    );
    let frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("cinematic-headlight", &f, &cam, &s);
    assert_close("cinematic-headlight", &frame, &reference, 45.0, 24);
}

/// Scattering and occlusion with the light cache as the shadow term (V from either shadow
/// mode, scattering.rs): against the reference, which builds the same cache in f64 and reads
/// it at the same points. Bound as above; the cache's own error is the model's here, not a
/// difference (both read one grid). 60.6 dB measured.
#[test]
fn cinematic_with_cache_shadows_matches_reference() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = oblique(&f, -30.0, 20.0);
    let s = with_scattering(
        with_occlusion(
            RenderSettings {
                shadows: Shadows {
                    mode: ShadowMode::Cache,
                    step: 1.0,
                    cache_res: 2.0,
                },
                ..lit(LightDirection::Camera([0.5, 0.3, -0.8]))
            },
            2.0,
        ),
        0.5,
        0.5,
    );
    let k = g.key(&f, &cam, &s);
    assert!(k.light_cache && k.scattering && k.occlusion && !k.shadows);
    let frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("cinematic-cache", &f, &cam, &s);
    assert_close("cinematic-cache", &frame, &reference, 45.0, 24);
}

/// An empty volume with occlusion, scattering and exact shadows on: black, depth +inf, on the
/// GPU (with and without empty skipping) and in the reference.
#[test]
fn empty_volume_is_black_with_every_effect_on() {
    let ctx = gpu();
    let f = binary_fixture(32, |_, _, _| false);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = from_above();
    for skip_empty in [true, false] {
        let s = RenderSettings {
            skip_empty,
            ..with_scattering(
                with_occlusion(
                    with_exact_shadows(lit(LightDirection::Camera([0.3, -0.5, 0.8]))),
                    4.0,
                ),
                0.4,
                0.5,
            )
        };
        let k = g.key(&f, &cam, &s);
        assert!(k.occlusion && k.scattering && k.shadows);
        let frame = g.render(&ctx, &f, &cam, &s);
        assert!(
            frame.rgba.iter().all(|&v| v == 0),
            "skip_empty {skip_empty}"
        );
        assert!(frame.depth.iter().all(|d| *d == f32::INFINITY));
        let reference = timed_reference("cinematic-empty", &f, &cam, &s);
        assert!(reference.rgba.iter().all(|&v| v == 0));
    }
}

/// Scattering with exact shadows: the floor in the slab's shadow keeps the ambient term only
/// (V ≈ 0 scales the whole direct term, BRDF and phase lobes alike). Each channel equals
/// ambient × colour × the pixel's opacity within ε = 2/255 (8-bit rounding ≤ 0.5/255, plus the
/// GPU shadow ray stopping at V < e⁻⁷: < 10⁻³ of a direct term ≤ 1.2). Blend 0.2 leaves the lit
/// floor mostly volume-like (P ≈ 0.2 at the floor's gradient): 0.3 + 0.7·(0.2·0.71 + 0.8·0.49)
/// ≈ 0.67 against 0.3 in shadow, so at least 1.8× brighter; a shadow in the wrong place, or none,
/// fails. The reference agrees in the shadow to 10⁻⁶.
#[test]
fn opaque_slab_leaves_the_scattering_floor_at_the_ambient_term() {
    let ctx = gpu();
    let f = slab_and_floor();
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = from_above();
    let s = with_scattering(
        with_exact_shadows(lit(LightDirection::Patient([1.0, 0.0, 1.0]))),
        0.3,
        0.2,
    );
    let frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("scattering-slab", &f, &cam, &s);
    let ambient = Shading::default().ambient as f64;
    let (mut in_shadow, mut lit_floor) = (Vec::new(), Vec::new());
    for py in 0..SIZE {
        for px in 0..SIZE {
            let (origin, _) = cam.basis().ray(px, py, SIZE, SIZE);
            let (x, y) = (origin.x, origin.y);
            let i = ((py * SIZE + px) * 4) as usize;
            let pixel = &frame.rgba[i..i + 4];
            let r = &reference.rgba_f64[(py * SIZE + px) as usize];
            if (1.0..=7.0).contains(&x) && (16.0..=24.0).contains(&y) {
                let a = pixel[3] as f64 / 255.0;
                assert!(a > 0.98, "floor pixel ({px}, {py}) not opaque: {pixel:?}");
                for c in 0..3 {
                    let got = pixel[c] as f64 / 255.0;
                    let expected = ambient * OPAQUE_COLOUR[c] * a;
                    assert!(
                        (got - expected).abs() <= 2.0 / 255.0,
                        "shadowed ({px}, {py}) channel {c}: {got} vs ambient {expected}"
                    );
                    assert!(
                        (r[c] - ambient * OPAQUE_COLOUR[c] * r[3]).abs() < 1e-6,
                        "reference shadowed ({px}, {py}): {r:?}"
                    );
                }
                in_shadow.push(pixel[0]);
            }
            if (1.0..=7.0).contains(&x) && ((2.0..=10.0).contains(&y) || (30.0..=38.0).contains(&y))
            {
                lit_floor.push(pixel[0]);
            }
        }
    }
    assert!(in_shadow.len() > 40 && lit_floor.len() > 80);
    let darkest_lit = *lit_floor.iter().min().unwrap_or(&0) as f64;
    let brightest_shadow = *in_shadow.iter().max().unwrap_or(&255) as f64;
    assert!(
        darkest_lit >= 1.8 * brightest_shadow,
        "lit floor {darkest_lit} not 1.8× the shadowed {brightest_shadow}"
    );
    // The whole image: shadows.rs's slab bound and reasons (35 dB; silhouette of the opaque
    // slab's rim and shadow rays grazing its edge, which flip between lit and ambient); 47.2
    // dB measured.
    let c = compare_rgba8(&frame.rgba, &reference.rgba).unwrap();
    save("scattering-slab-gpu", SIZE, SIZE, &frame.rgba);
    save("scattering-slab-ref", SIZE, SIZE, &reference.rgba);
    eprintln!("scattering slab: {c:?}");
    assert!(c.psnr_db >= 35.0, "{c:?}");
}

/// A hollow cube whose walls are one voxel thick (x, y, z in 8..24, opaque TF), seen
/// obliquely, every effect on: the wall's gradient flips across its one voxel, the occlusion
/// rays leave it on both sides and shadow rays cross walls of one voxel. Finite everywhere.
/// The main ray alone is the hard part here: its first sample in a wall whose opacity band is
/// under a voxel thick lands at a depth that varies across the face, and the gradient there
/// (zero at the wall's centre) with it, so even the effect-free image is only 38 dB from its
/// reference at a main step of ⅛ voxel (34 dB at ½: bands across the faces). The test runs at
/// ⅛ with a shadow step of ¼ (so occlusion and shadow rays cannot step over a wall) and asserts
/// that the effects add no error of their own: within 3 dB of the effect-free image's PSNR
/// (40.3 against 38.1 dB measured), and above 35 dB.
#[test]
fn one_voxel_shell_with_every_effect_on() {
    let ctx = gpu();
    let shell = |x: u32, y: u32, z: u32| {
        let inside = |v: u32| (8..24).contains(&v);
        let wall = |v: u32| v == 8 || v == 23;
        inside(x) && inside(y) && inside(z) && (wall(x) || wall(y) || wall(z))
    };
    let f = binary_fixture(32, shell);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = oblique(&f, 30.0, 35.0);
    let plain = RenderSettings {
        quality: 0.125,
        ..lit(LightDirection::Camera([-0.4, 0.8, 0.45]))
    };
    let mut s = with_scattering(
        with_occlusion(with_exact_shadows(plain.clone()), 3.0),
        0.5,
        0.5,
    );
    s.shadows.step = 0.25;
    let frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("shell", &f, &cam, &s);
    let c = compare_rgba8(&frame.rgba, &reference.rgba).unwrap();
    save("shell-gpu", SIZE, SIZE, &frame.rgba);
    save("shell-ref", SIZE, SIZE, &reference.rgba);
    let base = compare_rgba8(
        &g.render(&ctx, &f, &cam, &plain).rgba,
        &timed_reference("shell-plain", &f, &cam, &plain).rgba,
    )
    .unwrap();
    eprintln!("shell: {c:?}; without the effects: {base:?}");
    assert!(
        c.psnr_db >= 35.0 && c.psnr_db >= base.psnr_db - 3.0,
        "{c:?} vs {base:?}"
    );
}

/// The light inside the volume's bounding box: a perspective camera at the centre of the
/// phantom with the headlight, so every shadow ray starts inside the box and runs back
/// towards the eye, and occlusion rays leave through all faces. Finite, and against the
/// reference with the phantom bound (45 dB) and its reasons; the shadow step of 2 voxels makes
/// the midpoint rule's error on the optical depth 4× that at 1, still second order on the
/// phantom's smooth soft tissue (54.5 dB measured).
#[test]
fn light_from_inside_the_box() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = Camera::look_at(
        [15.5, 15.5, 15.5],
        [31.0, 20.0, 10.0],
        [0.0, 0.0, 1.0],
        Projection::Perspective { fov_y_deg: 60.0 },
    );
    let mut s = with_scattering(
        with_occlusion(with_exact_shadows(lit(LightDirection::Headlight)), 2.0),
        0.6,
        0.3,
    );
    // Shadow rays back to the eye cross up to half the volume from every shaded sample: a
    // step of 2 voxels (the reference's ½) keeps the reference to seconds.
    s.shadows.step = 2.0;
    let frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("inside", &f, &cam, &s);
    assert_close("cinematic-inside", &frame, &reference, 45.0, 24);
}

/// Light exactly along +x (zero direction components: shadow rays parallel to four faces) with
/// scattering and occlusion (whose directions include ones nearly parallel to faces too).
/// Against the reference (phantom bound), and continuous: 10⁻⁹ off the axis gives the same
/// image within one step. 61.6 dB measured.
#[test]
fn grazing_light_along_the_faces() {
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
    let at = |v: [f64; 3]| {
        with_scattering(
            with_occlusion(with_exact_shadows(lit(LightDirection::Patient(v))), 2.0),
            0.4,
            0.4,
        )
    };
    let s = at([1.0, 0.0, 0.0]);
    let frame = g.render(&ctx, &f, &cam, &s);
    let reference = timed_reference("cinematic-grazing", &f, &cam, &s);
    assert_close("cinematic-grazing", &frame, &reference, 45.0, 24);
    let other = g.render(&ctx, &f, &cam, &at([1.0, 1e-9, -1e-9]));
    let c = compare_rgba8(&frame.rgba, &other.rgba).unwrap();
    assert!(c.max_abs_error <= 1, "grazing light not continuous: {c:?}");
}

/// Occlusion with a radius within the shadow bias (1 voxel) is no occlusion: every ray is
/// empty, AO = 1 (the same image within one 8-bit step: the pipelines differ, so f32
/// contraction may differ). Just above the bias the image moves by at most a few steps, and a
/// real radius darkens it (so the test fails if the radius were ignored).
#[test]
fn occlusion_radius_to_zero_is_no_occlusion() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = oblique(&f, 35.0, 25.0);
    let plain = lit(LightDirection::Camera([0.6, 0.7, 0.4]));
    let none = g.render(&ctx, &f, &cam, &plain);
    let diff = |g: &mut GpuScene, r: f64| {
        let s = with_occlusion(plain.clone(), r);
        assert!(g.key(&f, &cam, &s).occlusion);
        compare_rgba8(&g.render(&ctx, &f, &cam, &s).rgba, &none.rgba).unwrap()
    };
    for r in [0.0, 0.5, 1.0] {
        let c = diff(&mut g, r);
        assert!(c.max_abs_error <= 1, "radius {r}: {c:?}");
    }
    let near = diff(&mut g, 1.05);
    let far = diff(&mut g, 4.0);
    eprintln!("radius 1.05: {near:?}; radius 4: {far:?}");
    assert!(near.max_abs_error <= 3, "radius 1.05: {near:?}");
    assert!(far.max_abs_error >= 10, "radius 4 changes nothing: {far:?}");
}

/// g = 0 with the volume-like lobe alone (blend 0) is isotropic: the direct term is I·k_d·c
/// whatever the light's direction (phase 1/4π, normalised to 1), so two lights give one image
/// (within one step: f32 rounding of the phase's terms). With g = 0.6 they do not.
#[test]
fn isotropic_scattering_ignores_the_light_direction() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let mut g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = oblique(&f, 20.0, 10.0);
    let image = |g: &mut GpuScene, light: [f64; 3], asym: f64| {
        let s = with_scattering(lit(LightDirection::Camera(light)), asym, 0.0);
        g.render(&ctx, &f, &cam, &s)
    };
    let a = image(&mut g, [0.0, 0.0, 1.0], 0.0);
    let b = image(&mut g, [0.7, -0.3, -0.6], 0.0);
    let c = compare_rgba8(&a.rgba, &b.rgba).unwrap();
    assert!(
        c.max_abs_error <= 1,
        "isotropic phase depends on the light: {c:?}"
    );
    let a = image(&mut g, [0.0, 0.0, 1.0], 0.6);
    let b = image(&mut g, [0.7, -0.3, -0.6], 0.6);
    let c = compare_rgba8(&a.rgba, &b.rgba).unwrap();
    assert!(c.max_abs_error >= 10, "g = 0.6 ignores the light: {c:?}");
}

/// Default settings compile neither effect in; asked for without shading (unlit DVR) or in MIP
/// they compile none either (no ambient or direct term to scale); on, they compile in alone.
#[test]
fn occlusion_and_scattering_are_compiled_in_only_when_they_light_something() {
    let ctx = gpu();
    let f = Fixture::ct(32);
    let g = GpuScene::new(&ctx, &f, CacheConfig::default());
    let cam = oblique(&f, 0.0, 0.0);
    let k = g.key(&f, &cam, &compare_settings(RenderMode::Dvr, SIZE));
    assert!(!k.occlusion && !k.scattering && !k.key_light);
    let on = with_scattering(
        with_occlusion(lit(LightDirection::Headlight), 3.0),
        0.2,
        0.5,
    );
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
        assert!(
            !k.occlusion && !k.scattering && !k.key_light,
            "{:?}",
            s.mode
        );
    }
    let k = g.key(&f, &cam, &on);
    assert!(k.occlusion && k.scattering && k.key_light && !k.shadows);
    let iso = RenderSettings {
        mode: RenderMode::Isosurface,
        shading: None,
        ..with_occlusion(compare_settings(RenderMode::Dvr, SIZE), 2.0)
    };
    let k = g.key(&f, &cam, &iso);
    assert!(k.occlusion && !k.scattering, "isosurfaces are always lit");
}

/// Out-of-range settings are refused with a message that names them.
#[test]
fn out_of_range_settings_are_refused() {
    let base = lit(LightDirection::Headlight);
    for (s, needle) in [
        (with_occlusion(base.clone(), -1.0), "occlusion radius"),
        (with_occlusion(base.clone(), f64::NAN), "occlusion radius"),
        (with_scattering(base.clone(), 1.0, 0.5), "scattering g"),
        (with_scattering(base.clone(), -0.995, 0.5), "scattering g"),
        (with_scattering(base.clone(), 0.2, 1.5), "blend"),
    ] {
        let e = s.validate().unwrap_err().to_string();
        assert!(e.contains(needle), "{e}");
    }
    assert!(with_scattering(with_occlusion(base, 0.0), -0.99, 0.0)
        .validate()
        .is_ok());
}
