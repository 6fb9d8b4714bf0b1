//! What the tool tests share: grids, a python3 with numpy/scipy that fails loudly when absent.

use std::path::PathBuf;
use std::process::Command;

use glam::{DMat3, DVec3};
use strata_segment::{Label, LabelLayer};
use strata_types::VolumeGeometry;

/// A grid rotated about an oblique axis, with anisotropic spacing and an offset origin: what
/// catches a tool that measures in index space instead of patient space.
pub fn rotated_anisotropic(dims: [u32; 3]) -> VolumeGeometry {
    let axis = DVec3::new(1.0, 2.0, 3.0).normalize_or_zero();
    let rotation = DMat3::from_axis_angle(axis, 0.6);
    VolumeGeometry {
        dims,
        spacing_mm: [0.7, 0.9, 1.6],
        origin_lps_mm: [-12.5, 30.25, 7.0],
        direction: [
            rotation.x_axis.to_array(),
            rotation.y_axis.to_array(),
            rotation.z_axis.to_array(),
        ],
    }
}

/// Every voxel of the layer, i fastest.
pub fn all_labels(layer: &LabelLayer) -> Vec<Label> {
    let [nx, ny, nz] = layer.grid().dims();
    let mut out = Vec::with_capacity((nx * ny * nz) as usize);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                out.push(layer.get([i, j, k]).unwrap());
            }
        }
    }
    out
}

/// Voxels (i, j, k) holding `label`, sorted by k, j, i.
pub fn voxels_of(layer: &LabelLayer, label: Label) -> Vec<[u32; 3]> {
    let [nx, ny, _] = layer.grid().dims();
    all_labels(layer)
        .iter()
        .enumerate()
        .filter(|(_, &l)| l == label)
        .map(|(n, _)| {
            let n = n as u32;
            [n % nx, (n / nx) % ny, n / (nx * ny)]
        })
        .collect()
}

/// A fresh scratch folder for one test.
pub fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir()
        .join("strata-segment-tests")
        .join(format!("{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create scratch folder under the temp dir");
    dir
}

/// Runs a Python script with numpy and scipy; a missing python3, numpy or scipy fails the test
/// with the command that installs them (a reference that is absent checks nothing).
pub fn python(script: &str, dir: &std::path::Path) -> String {
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .current_dir(dir)
        .output()
        .unwrap_or_else(|e| {
            panic!("python3 is needed as the reference ({e}): apt-get install -y python3 python3-numpy, then pip3 install scipy")
        });
    let stderr = String::from_utf8_lossy(&out.stderr);
    if stderr.contains("ModuleNotFoundError") {
        panic!("the reference needs numpy and scipy: pip3 install numpy scipy\n{stderr}");
    }
    assert!(out.status.success(), "python reference failed:\n{stderr}");
    String::from_utf8_lossy(&out.stdout).into_owned()
}
