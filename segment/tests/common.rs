//! Helpers of the segment tests: label layers with known voxels, and Python peers.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

use strata_segment::{Code, Label, LabelLayer, LabelRead, Segment, SegmentCategory};
use strata_types::VolumeGeometry;

/// A rotated (about an oblique axis), shifted, anisotropic right-handed grid.
pub fn oblique_geometry(dims: [u32; 3]) -> VolumeGeometry {
    let (c, s) = (0.8_f64, 0.6_f64);
    VolumeGeometry {
        dims,
        spacing_mm: [0.7, 0.9, 2.5],
        origin_lps_mm: [-120.5, 33.25, 410.0],
        // Rotation about z by atan(0.6/0.8), then about x by 90° (a coronal-ish stack).
        direction: [[c, s, 0.0], [0.0, 0.0, -1.0], [-s, c, 0.0]],
    }
}

/// A layer with spheres of a few segments (values 1, 2, 300 and 65 535), one named with a
/// category, so every writer sees several segments, a wide value and gaps between values.
pub fn sample_layer(geometry: VolumeGeometry) -> LabelLayer {
    let mut layer = LabelLayer::new_empty(geometry).expect("grid");
    let [nx, ny, nz] = layer.grid().dims();
    let named = [
        (1, "liver", [220, 120, 60]),
        (2, "left kidney", [30, 200, 90]),
        (300, "tumour", [250, 20, 200]),
        (65535, "last", [10, 10, 250]),
    ];
    for (value, name, rgb) in named {
        layer
            .segments_mut()
            .insert(Segment {
                value,
                name: name.into(),
                rgb,
                visible: true,
                locked: false,
                category: (value == 2).then(|| SegmentCategory {
                    category: Code {
                        value: "123037004".into(),
                        scheme: "SCT".into(),
                        meaning: "Anatomical Structure".into(),
                    },
                    kind: Code {
                        value: "64033007".into(),
                        scheme: "SCT".into(),
                        meaning: "Kidney".into(),
                    },
                }),
            })
            .expect("segment");
    }
    let centres: [([f64; 3], f64, Label); 4] = [
        ([0.3, 0.4, 0.5], 0.25, 1),
        ([0.7, 0.6, 0.4], 0.2, 2),
        ([0.45, 0.5, 0.45], 0.12, 300),
        ([0.8, 0.2, 0.75], 0.1, 65535),
    ];
    layer
        .edit("spheres", |w| {
            for k in 0..nz {
                for j in 0..ny {
                    for i in 0..nx {
                        let p = [
                            f64::from(i) / f64::from(nx),
                            f64::from(j) / f64::from(ny),
                            f64::from(k) / f64::from(nz),
                        ];
                        for (c, r, v) in centres {
                            let d2: f64 = (0..3).map(|a| (p[a] - c[a]).powi(2)).sum();
                            if d2 < r * r {
                                w.set([i, j, k], v)?;
                            }
                        }
                    }
                }
            }
            Ok(())
        })
        .expect("edit");
    layer
}

/// Every voxel of a label grid, i fastest.
pub fn all_voxels(labels: &dyn LabelRead) -> Vec<Label> {
    let [nx, ny, nz] = labels.geometry().dims;
    let plane = (nx * ny) as usize;
    let mut out = vec![0; plane * nz as usize];
    for (k, slice) in out.chunks_mut(plane).enumerate() {
        labels.read_slice_k(k as u32, slice).expect("slice");
    }
    out
}

/// Writes voxels as raw little-endian u16 (i fastest) for a Python peer to compare with.
pub fn write_raw(path: &Path, voxels: &[Label]) {
    let bytes: Vec<u8> = voxels.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(path, bytes).expect("write raw");
}

/// `python3` with the given modules, or a panic with the install hint: the independent
/// reader is part of what these tests check, so a missing one fails rather than skips.
pub fn python_with(modules: &[&str], pip: &str) -> PathBuf {
    let python = PathBuf::from(std::env::var("PYTHON").unwrap_or_else(|_| "python3".into()));
    let ok = Command::new(&python)
        .args(["-c", &format!("import {}", modules.join(", "))])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        ok,
        "python3 with {} is needed for this test: pip install {pip}",
        modules.join(", ")
    );
    python
}

/// Runs a Python script with arguments; panics with its output unless it prints `OK` last.
pub fn run_python(python: &Path, script: &str, args: &[&Path]) -> String {
    let out = Command::new(python)
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("run python3");
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success() && stdout.trim_end().ends_with("OK"),
        "python peer failed:\nstdout:\n{stdout}\nstderr:\n{stderr}"
    );
    stdout
}
