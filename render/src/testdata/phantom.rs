//! Synthetic volumes for tests, benchmarks and demos. Defined in patient space where geometry
//! matters, so differently sampled volumes of the same object can be compared.

use glam::DVec3;

use crate::error::RenderError;
use crate::gpu::bricked_volume::BrickedVolume;
use crate::model::transfer_function::TransferFunction;
use strata_types::{ValueMapping, VolumeGeometry};

/// CT stored values are HU + 1024 (slope 1, intercept -1024), as in most DICOM CT.
pub const CT_MAPPING: ValueMapping = ValueMapping {
    slope: 1.0,
    intercept: -1024.0,
};

fn smooth_inside(signed_distance_mm: f64, edge_mm: f64) -> f64 {
    // Partial-volume edge about two voxels wide: real CT edges are never steps, and steps would
    // make every GPU/CPU comparison a test of edge aliasing instead of the renderer.
    let t = ((edge_mm - signed_distance_mm) / (2.0 * edge_mm)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// CT-like object in HU around `centre` (mm) with overall radius `r` (mm): air, soft-tissue
/// body, a lung, a bone shell, a contrast vessel and a calcification.
pub fn ct_phantom_hu(p: DVec3, centre: DVec3, r: f64, edge_mm: f64) -> f64 {
    let q = p - centre;
    let ellipsoid = |q: DVec3, axes: DVec3| ((q / axes).length() - 1.0) * axes.min_element();
    let mut hu = -1000.0;
    let mix = |hu: f64, target: f64, w: f64| hu + (target - hu) * w;
    hu = mix(
        hu,
        40.0,
        smooth_inside(ellipsoid(q, DVec3::new(0.9, 0.72, 0.95) * r), edge_mm),
    );
    hu = mix(
        hu,
        -820.0,
        smooth_inside(
            ellipsoid(
                q - DVec3::new(-0.42, 0.0, 0.05) * r,
                DVec3::new(0.3, 0.4, 0.5) * r,
            ),
            edge_mm,
        ),
    );
    let shell_centre = DVec3::new(0.3, -0.05, 0.0) * r;
    let shell = ((q - shell_centre).length() - 0.38 * r).abs() - 0.06 * r;
    hu = mix(hu, 800.0, smooth_inside(shell, edge_mm));
    let vessel = (DVec3::new(q.x, q.y, 0.0) - DVec3::new(0.0, 0.38 * r, 0.0)).length() - 0.08 * r;
    hu = mix(
        hu,
        300.0,
        smooth_inside(vessel.max(q.z.abs() - 0.8 * r), edge_mm),
    );
    hu = mix(
        hu,
        1400.0,
        smooth_inside((q - shell_centre).length() - 0.07 * r, edge_mm),
    );
    hu
}

/// A CT phantom sampled on `geometry`; the object's centre and size follow the geometry's
/// bounding box unless given.
pub fn ct_phantom(
    geometry: VolumeGeometry,
    centre: Option<DVec3>,
    radius_mm: Option<f64>,
) -> Result<BrickedVolume, RenderError> {
    geometry.validate()?;
    let centre = centre.unwrap_or_else(|| geometry.centre_patient());
    let extent = [0, 1, 2].map(|a| geometry.dims[a] as f64 * geometry.spacing_mm[a]);
    let r = radius_mm.unwrap_or(0.5 * extent.iter().cloned().fold(f64::INFINITY, f64::min));
    let edge = geometry.spacing_mm.iter().cloned().fold(0.0, f64::max);
    let g = geometry.clone();
    BrickedVolume::from_fn(geometry, CT_MAPPING, move |x, y, z| {
        let p = g.patient_from_index(DVec3::new(x as f64, y as f64, z as f64));
        (ct_phantom_hu(p, centre, r, edge) + 1024.0)
            .round()
            .clamp(0.0, 4095.0) as u16
    })
}

/// The 256³ u8 phantom of bench/peers/vtk_peer_bench.py (same formula), for comparable timings:
/// `r = sqrt(x² + 1.3 y² + 0.8 z²)` with x, y, z = index/n - 0.5, and
/// `value = uint8(clip(1-2r, 0, 1)·200 + 50·[r < 0.2] + 20·sin(40x)·cos(30y))`. numpy's
/// float→uint8 cast truncates and wraps negative values (x86), which we reproduce so both
/// renderers see the same bytes.
pub fn vtk_peer_phantom(n: u32) -> Result<BrickedVolume, RenderError> {
    let geometry = VolumeGeometry::axis_aligned([n; 3], [1.0; 3]);
    BrickedVolume::from_fn(geometry, ValueMapping::default(), move |xi, yi, zi| {
        let f = |i: u32| (i as f32) / n as f32 - 0.5;
        let (x, y, z) = (f(xi), f(yi), f(zi));
        let r = (x * x + y * y * 1.3 + z * z * 0.8).sqrt();
        let v = (1.0 - r * 2.0).clamp(0.0, 1.0) * 200.0
            + if r < 0.2 { 50.0 } else { 0.0 }
            + 20.0 * (x * 40.0).sin() * (y * 30.0).cos();
        ((v as i32).rem_euclid(256)) as u16
    })
}

/// The peer benchmark's transfer function (vtkColorTransferFunction + vtkPiecewiseFunction).
pub fn vtk_peer_transfer_function() -> TransferFunction {
    TransferFunction::new(
        "vtk-peer",
        &[(0.0, 0.0), (60.0, 0.0), (120.0, 0.05), (255.0, 0.4)],
        &[
            (0.0, [0.0, 0.0, 0.0]),
            (100.0, [1.0, 0.5, 0.3]),
            (255.0, [1.0, 1.0, 1.0]),
        ],
    )
}
