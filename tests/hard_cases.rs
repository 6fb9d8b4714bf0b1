//! Hard cases stay numerically stable: each case renders on the GPU (lavapipe in CI) and with
//! the f64 CPU reference, and asserts no NaN anywhere (reference colour, GPU and reference
//! depth), no panic, and the GPU image within a stated bound of the reference.
//!
//! Bounds, and why: the GPU marches f32 samples with 8-bit-weighted hardware trilinear
//! filtering (lavapipe) while the reference integrates the same field in f64 at 1/8 of the
//! step. On smooth data that leaves PSNR far above 40 dB; cases that put a discontinuity under
//! a ray (step transfer functions, grazing rays along cell faces, sub-pixel volumes) may flip
//! single pixels, so they bound PSNR and say so instead of the maximum error.

use glam::DVec3;
use strata_render::reference::{render_reference, ReferenceOptions, ReferenceScene};
use strata_render::{
    compare_rgba8, BrickedVolume, CacheConfig, Camera, ClipPlane, GpuContext, OffscreenRenderer,
    Projection, RenderMode, RenderSettings, Shading, TransferFunction, ValueMapping,
    VolumeGeometry,
};

const SIZE: u32 = 64;

/// A headless device or a failed test carrying the install hint (never a silent pass).
fn gpu() -> GpuContext {
    GpuContext::headless().unwrap_or_else(|e| panic!("{e}"))
}

struct Bound {
    min_psnr_db: f64,
    /// Largest allowed per-channel error (out of 255).
    max_abs: u8,
    /// Largest fraction of pixels allowed to differ by more than the smooth bound (24/255).
    max_fraction_off: f64,
}

/// Smooth data: only f32 positions and 8-bit filter weights differ from the reference.
const SMOOTH: Bound = Bound {
    min_psnr_db: 40.0,
    max_abs: 24,
    max_fraction_off: 1.0,
};
/// A discontinuity under some rays: a step TF, a one-voxel spike, a silhouette. Single pixels
/// may flip fully, but at most 1 % of them may leave the smooth bound, and PSNR bounds the mean.
///
/// Silhouettes of the volume box where the TF is opaque at the boundary are one source: both
/// renderers sample a ray's last, shortened segment for its own length, but the GPU clamps
/// opacity to 0.999999 (finite extinction, no NaN), so a ray that only grazes a corner of
/// opaque air stays partly transparent where the reference's opacity-1 segment does not.
const EDGY: Bound = Bound {
    min_psnr_db: 25.0,
    max_abs: 255,
    max_fraction_off: 0.01,
};

fn settings(mode: RenderMode) -> RenderSettings {
    RenderSettings {
        width: SIZE,
        height: SIZE,
        mode,
        // Jitter off: the reference has none and the noise would eat the tolerance.
        jitter: false,
        shading: (mode == RenderMode::Isosurface).then(Shading::default),
        ..RenderSettings::default()
    }
}

/// Renders `volume` both ways and checks the invariants; returns the GPU image.
fn check(
    name: &str,
    volume: &BrickedVolume,
    tf: &TransferFunction,
    camera: &Camera,
    settings: &RenderSettings,
    bound: Bound,
) -> Vec<u8> {
    check_cut(
        name,
        volume,
        volume.page_table_uniform(0),
        tf,
        camera,
        settings,
        bound,
    )
}

/// [`check`] on a cut of mixed levels.
fn check_cut(
    name: &str,
    volume: &BrickedVolume,
    cut: strata_render::PageTable,
    tf: &TransferFunction,
    camera: &Camera,
    settings: &RenderSettings,
    bound: Bound,
) -> Vec<u8> {
    let ctx = gpu();
    let mut renderer = OffscreenRenderer::with_cut(&ctx, volume, tf, cut, CacheConfig::default())
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    let frame = renderer
        .render(&ctx, volume, camera, settings)
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    let (lo, hi) = volume.physical_range();
    let reference = render_reference(
        &ReferenceScene {
            source: volume,
            page_table: &renderer.page_table,
            geometry: &volume.geometry,
            mapping: volume.mapping,
            transfer_function: tf,
            tf_range: (lo, hi),
        },
        camera,
        settings,
        ReferenceOptions::default(),
    )
    .unwrap_or_else(|e| panic!("{name}: reference: {e}"));
    assert!(
        reference.rgba_f64.iter().flatten().all(|c| c.is_finite()),
        "{name}: reference produced a non-finite colour"
    );
    for (what, depth) in [("GPU", &frame.depth), ("reference", &reference.depth)] {
        assert!(
            depth.iter().all(|d| !d.is_nan() && *d >= 0.0),
            "{name}: {what} depth has NaN or negative values"
        );
    }
    let c = compare_rgba8(&frame.rgba, &reference.rgba).unwrap();
    eprintln!("{name}: {c:?}");
    let off = frame
        .rgba
        .chunks_exact(4)
        .zip(reference.rgba.chunks_exact(4))
        .filter(|(a, b)| {
            a.iter()
                .zip(b.iter())
                .any(|(x, y)| x.abs_diff(*y) > SMOOTH.max_abs)
        })
        .count();
    let fraction_off = off as f64 / (frame.rgba.len() / 4) as f64;
    assert!(
        c.psnr_db >= bound.min_psnr_db
            && c.max_abs_error <= bound.max_abs
            && fraction_off <= bound.max_fraction_off,
        "{name}: {c:?}, {off} pixels off by > 24: outside PSNR >= {} dB, max abs <= {}, <= {} % of pixels off",
        bound.min_psnr_db,
        bound.max_abs,
        bound.max_fraction_off * 100.0
    );
    frame.rgba
}

fn opaque_pixels(rgba: &[u8]) -> usize {
    rgba.chunks_exact(4).filter(|p| p[3] > 0).count()
}

/// A soft ball (stored 0..4000) centred in the volume: smooth, with interior structure.
fn ball(dims: [u32; 3], spacing_mm: [f64; 3]) -> BrickedVolume {
    let geometry = VolumeGeometry::axis_aligned(dims, spacing_mm);
    let extent = [0, 1, 2].map(|a| dims[a] as f64 * spacing_mm[a]);
    let centre = geometry.centre_patient();
    BrickedVolume::from_fn(geometry.clone(), ValueMapping::default(), move |x, y, z| {
        let p = DVec3::new(
            x as f64 * spacing_mm[0],
            y as f64 * spacing_mm[1],
            z as f64 * spacing_mm[2],
        );
        // Distance relative to the smallest extent, so thin axes still hold a "ball" slab.
        let q = (p - centre) / DVec3::from(extent.map(|e| e.max(1e-9)));
        let t = (1.0 - q.length() / 0.5).clamp(0.0, 1.0);
        (4000.0 * t * t) as u16
    })
    .unwrap()
}

fn ramp_tf(hi: f64) -> TransferFunction {
    TransferFunction::new(
        "ramp",
        &[(0.0, 0.0), (0.2 * hi, 0.0), (hi, 0.6)],
        &[(0.0, [1.0, 0.3, 0.2]), (hi, [1.0, 1.0, 0.9])],
    )
}

fn orbit(volume: &BrickedVolume, az: f64, el: f64, zoom: f64) -> Camera {
    Camera::orbit(
        &volume.geometry,
        az,
        el,
        zoom,
        Projection::Perspective { fov_y_deg: 30.0 },
    )
}

#[test]
fn rays_parallel_to_axes_along_brick_faces_and_through_brick_corners() {
    // 64³, 1 mm voxels at the origin: brick faces at index (= mm) 31.5. An orthographic view
    // 65 mm high on 65 px puts pixel centres on every half-integer x and y, so rays run exactly
    // along voxel cell faces, along the brick faces x = 31.5 and y = 31.5, and down the brick
    // edge where both meet.
    let volume = ball([64; 3], [1.0; 3]);
    let tf = ramp_tf(4000.0);
    let centre = volume.geometry.centre_patient();
    let s = RenderSettings {
        width: 65,
        height: 65,
        ..settings(RenderMode::Dvr)
    };
    for (axis, up) in [
        (DVec3::Z, DVec3::Y),
        (DVec3::X, DVec3::Z),
        (DVec3::Y, DVec3::Z),
    ] {
        let camera = Camera::look_at(
            (centre - axis * 200.0).into(),
            centre.into(),
            up.into(),
            Projection::Orthographic { height_mm: 65.0 },
        );
        check(&format!("axis {axis}"), &volume, &tf, &camera, &s, SMOOTH);
        check(
            &format!("axis {axis} mip"),
            &volume,
            &tf,
            &camera,
            &RenderSettings {
                width: 65,
                height: 65,
                ..settings(RenderMode::Mip)
            },
            SMOOTH,
        );
    }
}

#[test]
fn smooth_transitions_with_rays_exactly_on_level_faces_edges_and_corners() {
    // 128³ in a 3D checkerboard of level-1 and level-0 octants: every level face, edge and
    // corner of the 2×2×2 level-1 grid lies on x, y or z = 63.5, the volume's centre. An
    // orthographic view 129 mm high on 129 px puts pixel centres on every half-integer, so
    // rays run exactly along those faces and down the edges where the blend weight is 1 on one
    // side and the distance to two coarser regions is equal (the analogue of the paper's
    // singular v = 0.5 case), and through the band's inner edge half a voxel in.
    let volume = ball([128; 3], [1.0; 3]);
    let cut = volume
        .page_table_with_levels(|p| (((p[0] >> 1) + (p[1] >> 1) + (p[2] >> 1)) % 2 == 0) as u8);
    let tf = ramp_tf(4000.0);
    let centre = volume.geometry.centre_patient();
    for (axis, up) in [(DVec3::Z, DVec3::Y), (DVec3::X, DVec3::Z)] {
        let camera = Camera::look_at(
            (centre - axis * 300.0).into(),
            centre.into(),
            up.into(),
            Projection::Orthographic { height_mm: 129.0 },
        );
        for (mode, shading) in [
            (RenderMode::Dvr, None),
            (RenderMode::Dvr, Some(Shading::default())),
            (RenderMode::Mip, None),
        ] {
            let s = RenderSettings {
                width: 129,
                height: 129,
                shading,
                ..settings(mode)
            };
            assert!(s.smooth_transitions);
            let name = format!("level faces {axis} {mode:?} shaded {}", shading.is_some());
            check_cut(&name, &volume, cut.clone(), &tf, &camera, &s, SMOOTH);
        }
    }
}

#[test]
fn camera_inside_and_exactly_on_the_boundary() {
    let volume = ball([48; 3], [1.0; 3]);
    let tf = ramp_tf(4000.0);
    let centre = volume.geometry.centre_patient();
    // The box spans index -0.5 .. 47.5 = patient -0.5 .. 47.5 mm.
    for (name, eye) in [
        ("inside", centre + DVec3::new(3.0, -2.0, -9.0)),
        ("on the -z face", DVec3::new(centre.x, centre.y, -0.5)),
        ("on a corner", DVec3::new(-0.5, -0.5, -0.5)),
    ] {
        let camera = Camera::look_at(
            eye.into(),
            (centre + DVec3::new(0.0, 0.0, 5.0)).into(),
            [0.0, 1.0, 0.0],
            Projection::Perspective { fov_y_deg: 60.0 },
        );
        let rgba = check(
            name,
            &volume,
            &tf,
            &camera,
            &settings(RenderMode::Dvr),
            SMOOTH,
        );
        assert!(opaque_pixels(&rgba) > 0, "{name}: nothing drawn");
    }
}

#[test]
fn extreme_zoom_in_and_out() {
    let volume = ball([48; 3], [1.0; 3]);
    let tf = ramp_tf(4000.0);
    // 1000× in: one voxel fills the view; the field is smooth there, so tight bounds hold.
    check(
        "zoom 1000",
        &volume,
        &tf,
        &orbit(&volume, 20.0, 10.0, 1000.0),
        &settings(RenderMode::Dvr),
        SMOOTH,
    );
    // 1/1000: the volume is far below one pixel. Whether the one ray near it hits is a
    // discontinuity, so only PSNR is bounded (the image is almost all background).
    let rgba = check(
        "zoom 0.001",
        &volume,
        &tf,
        &orbit(&volume, 20.0, 10.0, 0.001),
        &settings(RenderMode::Dvr),
        EDGY,
    );
    assert!(
        opaque_pixels(&rgba) <= 4,
        "a sub-pixel volume covers at most a few pixels"
    );
}

#[test]
fn degenerate_and_odd_volume_shapes() {
    for (name, dims, spacing) in [
        ("1 slice", [40, 36, 1], [1.0, 1.0, 1.0]),
        ("2 slices", [40, 36, 2], [1.0, 1.0, 1.0]),
        ("1x1xN", [1, 1, 50], [1.0, 1.0, 1.0]),
        ("33x47x65", [33, 47, 65], [1.0, 1.0, 1.0]),
        ("spacing 1:100", [40, 40, 40], [0.1, 0.1, 10.0]),
    ] {
        let volume = ball(dims, spacing);
        let tf = ramp_tf(4000.0);
        for (mode, bound) in [
            (RenderMode::Dvr, SMOOTH),
            (RenderMode::Mip, SMOOTH),
            // A 1- or 2-voxel-thick shape turns the isosurface into a silhouette everywhere.
            (RenderMode::Isosurface, EDGY),
        ] {
            let s = RenderSettings {
                iso_value: 1500.0,
                ..settings(mode)
            };
            check(
                &format!("{name} {mode:?}"),
                &volume,
                &tf,
                &orbit(&volume, 30.0, 25.0, 1.0),
                &s,
                bound,
            );
        }
    }
}

#[test]
fn constant_volume_with_shading_has_no_nan() {
    let geometry = VolumeGeometry::axis_aligned([40; 3], [1.0; 3]);
    let volume = BrickedVolume::from_fn(geometry, ValueMapping::default(), |_, _, _| 2000).unwrap();
    let tf = ramp_tf(4000.0);
    let s = RenderSettings {
        shading: Some(Shading::default()),
        ..settings(RenderMode::Dvr)
    };
    let rgba = check(
        "constant shaded",
        &volume,
        &tf,
        &orbit(&volume, 30.0, 20.0, 1.0),
        &s,
        SMOOTH,
    );
    assert!(opaque_pixels(&rgba) > 0);
    // Pre-integration on a constant field: every segment has s_front = s_back, the table's
    // diagonal, which must equal the classic sample.
    let pre = RenderSettings {
        preintegrated: true,
        shading: Some(Shading::default()),
        ..settings(RenderMode::Dvr)
    };
    check(
        "constant pre-integrated",
        &volume,
        &tf,
        &orbit(&volume, 30.0, 20.0, 1.0),
        &pre,
        SMOOTH,
    );
    // Isosurface exactly at the constant value: every sample is ">= iso", gradient zero.
    let s = RenderSettings {
        iso_value: 2000.0,
        ..settings(RenderMode::Isosurface)
    };
    check(
        "constant iso at its value",
        &volume,
        &tf,
        &orbit(&volume, 30.0, 20.0, 1.0),
        &s,
        EDGY,
    );
}

#[test]
fn sixteen_bit_full_range_and_negative_hounsfield() {
    // Full u16 range in a smooth diagonal ramp.
    let geometry = VolumeGeometry::axis_aligned([48; 3], [1.0; 3]);
    let volume = BrickedVolume::from_fn(geometry.clone(), ValueMapping::default(), |x, y, z| {
        ((x + y + z) as f64 / 141.0 * 65535.0).round() as u16
    })
    .unwrap();
    assert_eq!(volume.physical_range(), (0.0, 65535.0));
    let tf = TransferFunction::new(
        "full range",
        &[(0.0, 0.0), (65535.0, 0.3)],
        &[(0.0, [0.2, 0.4, 1.0]), (65535.0, [1.0, 0.8, 0.2])],
    );
    // The ramp is non-zero on the box faces: silhouette rays end in a short last segment,
    // which both renderers sample for its own length, so the smooth bound holds.
    for mode in [RenderMode::Dvr, RenderMode::Mip] {
        check(
            &format!("u16 full range {mode:?}"),
            &volume,
            &tf,
            &orbit(&volume, 40.0, 30.0, 1.0),
            &settings(mode),
            SMOOTH,
        );
    }

    // CT mapping (stored = HU + 1024) with everything of interest below 0 HU: lung-like
    // values between -1000 and -400 HU, a TF defined only on negative values.
    let mapping = ValueMapping {
        slope: 1.0,
        intercept: -1024.0,
    };
    let lung = BrickedVolume::from_fn(geometry, mapping, |x, y, z| {
        let d = ((x as f64 - 23.5).powi(2) + (y as f64 - 23.5).powi(2) + (z as f64 - 23.5).powi(2))
            .sqrt();
        let hu = -1000.0 + 600.0 * (1.0 - d / 24.0).clamp(0.0, 1.0);
        (hu + 1024.0).round() as u16
    })
    .unwrap();
    let (lo, hi) = lung.physical_range();
    assert!(lo < -990.0 && hi < 0.0, "range {lo}..{hi}");
    let tf = TransferFunction::preset("ct-lung").expect("lung preset");
    check(
        "negative HU lung",
        &lung,
        &tf,
        &orbit(&lung, 10.0, 5.0, 1.0),
        &settings(RenderMode::Dvr),
        SMOOTH,
    );
    check(
        "negative HU iso",
        &lung,
        &tf,
        &orbit(&lung, 10.0, 5.0, 1.0),
        &RenderSettings {
            iso_value: -700.0,
            ..settings(RenderMode::Isosurface)
        },
        EDGY,
    );
}

#[test]
fn step_and_binary_transfer_functions() {
    let volume = ball([48; 3], [1.0; 3]);
    let camera = orbit(&volume, 25.0, 15.0, 1.0);
    // Infinite frequency: opacity jumps 0 -> 0.8 at 2000 (two points at the same value).
    let step = TransferFunction::new(
        "step",
        &[(0.0, 0.0), (2000.0, 0.0), (2000.0, 0.8), (4000.0, 0.8)],
        &[(0.0, [1.0, 1.0, 1.0]), (4000.0, [1.0, 1.0, 1.0])],
    );
    check(
        "step TF",
        &volume,
        &step,
        &camera,
        &settings(RenderMode::Dvr),
        EDGY,
    );

    // Opacity exactly 0 everywhere: nothing at all, on both sides, and every page is skipped.
    let zero = TransferFunction::new(
        "zero",
        &[(0.0, 0.0), (4000.0, 0.0)],
        &[(0.0, [1.0, 1.0, 1.0]), (4000.0, [1.0, 1.0, 1.0])],
    );
    let rgba = check(
        "zero TF",
        &volume,
        &zero,
        &camera,
        &settings(RenderMode::Dvr),
        SMOOTH,
    );
    assert!(rgba.iter().all(|&b| b == 0), "opacity 0 must draw nothing");

    // Opacity exactly 1 everywhere (the air included): the first sample saturates; the image
    // is the TF colour over the whole footprint, whatever the step.
    let one = TransferFunction::new(
        "one",
        &[(0.0, 1.0), (4000.0, 1.0)],
        &[(0.0, [0.2, 0.6, 1.0]), (4000.0, [0.2, 0.6, 1.0])],
    );
    // Opaque air makes the box silhouette an edge (see EDGY).
    let rgba = check(
        "opaque TF",
        &volume,
        &one,
        &camera,
        &settings(RenderMode::Dvr),
        EDGY,
    );
    for p in rgba.chunks_exact(4).filter(|p| p[3] > 0) {
        if p[3] == 255 {
            assert!(
                p[0].abs_diff(51) <= 1 && p[1].abs_diff(153) <= 1 && p[2] == 255,
                "{p:?}"
            );
        }
    }
}

#[test]
fn tiny_and_huge_steps_with_opacity_correction() {
    let volume = ball([48; 3], [1.0; 3]);
    let tf = ramp_tf(4000.0);
    let camera = orbit(&volume, 25.0, 15.0, 1.0);
    // 1/50 voxel: 50 × more samples, each with α' ≈ α/50; f32 rounding of 1-(1-α)^(1/50)
    // must not accumulate into visible error.
    let tiny = RenderSettings {
        quality: 0.02,
        ..settings(RenderMode::Dvr)
    };
    check("step 0.02", &volume, &tf, &camera, &tiny, SMOOTH);
    // Pre-integration with d -> 0: table entries shrink continuously to zero, no 0/0.
    let tiny_pre = RenderSettings {
        preintegrated: true,
        ..tiny.clone()
    };
    check(
        "step 0.02 pre-integrated",
        &volume,
        &tf,
        &camera,
        &tiny_pre,
        SMOOTH,
    );
    // 8 voxels per step: a coarse but finite integral. The reference integrates the true
    // field (at 1 voxel here), so the bound is loose and stated: the opacity correction keeps
    // the overall opacity right (PSNR >= 20 dB), no sample can blow up.
    let huge = RenderSettings {
        quality: 8.0,
        ..settings(RenderMode::Dvr)
    };
    let ctx = gpu();
    let mut renderer =
        OffscreenRenderer::new(&ctx, &volume, &tf, 0, CacheConfig::default()).unwrap();
    let gpu_frame = renderer.render(&ctx, &volume, &camera, &huge).unwrap();
    let reference = render_reference(
        &ReferenceScene {
            source: &volume,
            page_table: &renderer.page_table,
            geometry: &volume.geometry,
            mapping: volume.mapping,
            transfer_function: &tf,
            tf_range: volume.physical_range(),
        },
        &camera,
        &settings(RenderMode::Dvr),
        ReferenceOptions::default(),
    )
    .unwrap();
    assert!(gpu_frame.depth.iter().all(|d| !d.is_nan()));
    let c = compare_rgba8(&gpu_frame.rgba, &reference.rgba).unwrap();
    eprintln!("step 8 vs fine reference: {c:?}");
    assert!(c.psnr_db >= 20.0, "{c:?}");
}

#[test]
fn clip_plane_through_the_eye_and_grazing_a_face() {
    let volume = ball([48; 3], [1.0; 3]);
    let tf = ramp_tf(4000.0);
    let camera = orbit(&volume, 0.0, 0.0, 1.0);
    let centre = volume.geometry.centre_patient();
    // A plane containing the view direction: every ray is parallel to it (n·d = 0), the
    // degenerate branch of the clip test.
    let basis = camera.basis();
    let n = basis.right;
    for (name, plane) in [
        (
            "plane parallel to rays",
            ClipPlane {
                normal: n.into(),
                offset_mm: n.dot(centre),
            },
        ),
        (
            "plane on the -x face",
            ClipPlane {
                normal: [1.0, 0.0, 0.0],
                offset_mm: -0.5,
            },
        ),
    ] {
        let s = RenderSettings {
            clip_plane: Some(plane),
            ..settings(RenderMode::Dvr)
        };
        check(name, &volume, &tf, &camera, &s, EDGY);
    }
}

/// f32 sources with NaN and ±Inf: the import policy (quantize.rs) maps NaN and −Inf to the
/// lowest stored value and +Inf to the highest, counts them in the header, and the stored
/// volume renders without NaN.
#[test]
fn float_source_with_nan_and_infinities_imports_by_policy_and_renders() {
    use strata_storage::import::{import_source, ImportOptions};
    use strata_storage::readers::{open_source, RawSpec, ReadOptions};
    use strata_storage::{ByteOrder, SampleType, Store};

    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("with-nan.raw");
    let n = 24usize;
    let mut values = vec![0f32; n * n * n];
    for (i, v) in values.iter_mut().enumerate() {
        let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
        let d = ((x as f32 - 11.5).powi(2) + (y as f32 - 11.5).powi(2) + (z as f32 - 11.5).powi(2))
            .sqrt();
        *v = 100.0 * (1.0 - d / 12.0).max(0.0) + 0.25;
    }
    let nan_at = 5 + n * (6 + n * 7);
    let inf_at = 12 + n * (12 + n * 12);
    let neg_inf_at = 20 + n * (3 + n * 9);
    values[nan_at] = f32::NAN;
    values[inf_at] = f32::INFINITY;
    values[neg_inf_at] = f32::NEG_INFINITY;
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(&raw, bytes).unwrap();

    let options = ReadOptions {
        raw: Some(RawSpec {
            dims: [n as u64; 3],
            sample_type: SampleType::F32,
            spacing_mm: [1.0; 3],
            byte_order: ByteOrder::Little,
            header_bytes: 0,
        }),
        ..Default::default()
    };
    let store_path = dir.path().join("with-nan.strata");
    let opened = open_source(&raw, &options).unwrap();
    let report = import_source(opened, &store_path, &ImportOptions::default()).unwrap();
    assert_eq!(report.header.non_finite_samples, 3);
    let store = Store::open(&store_path).unwrap();
    let mut voxels = strata_e2e::VoxelReader::new(&store);
    let index = |i: usize| [(i % n) as u64, ((i / n) % n) as u64, (i / (n * n)) as u64];
    let [lo, hi] = store.header().stored_range;
    assert_eq!(
        voxels.stored(index(nan_at)),
        lo,
        "NaN reads as the lowest value"
    );
    assert_eq!(
        voxels.stored(index(neg_inf_at)),
        lo,
        "-Inf reads as the lowest value"
    );
    assert_eq!(
        voxels.stored(index(inf_at)),
        hi,
        "+Inf reads as the highest value"
    );
    // Finite samples keep their value within the stated quantisation error.
    let q = store.header().quantization_error;
    let finite_at = 11 + n * (11 + n * 11);
    assert!((voxels.physical(index(finite_at)) - values[finite_at] as f64).abs() <= q + 1e-9);

    let ctx = gpu();
    let tf = TransferFunction::new(
        "float",
        &[(0.0, 0.0), (20.0, 0.0), (100.0, 0.5)],
        &[(0.0, [1.0, 0.5, 0.2]), (100.0, [1.0, 1.0, 1.0])],
    );
    let pair = strata_e2e::render_pair::render(
        &ctx,
        &store,
        0,
        &tf,
        |g| {
            Camera::orbit(
                g,
                30.0,
                20.0,
                1.0,
                Projection::Perspective { fov_y_deg: 30.0 },
            )
        },
        &settings(RenderMode::Dvr),
        None,
    );
    let c = compare_rgba8(&pair.gpu, &pair.reference).unwrap();
    eprintln!("float with NaN/Inf: {c:?}");
    // +Inf became one voxel at the top of the range: a one-voxel spike is an edge for the
    // rays through it, hence the PSNR-only bound.
    assert!(c.psnr_db >= EDGY.min_psnr_db, "{c:?}");
}
