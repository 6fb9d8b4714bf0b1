//! Helpers of the OME-Zarr tests: level voxels out of a store, Python (zarr-python 3) runs.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use strata_source::VolumeSource;
use strata_types::{BrickId, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};

/// Level `level` of a source, apron stripped, x fastest (the order of a z, y, x array).
pub fn level_voxels(source: &dyn VolumeSource, level: usize) -> (Vec<u16>, [u64; 3]) {
    let layout = source.layout().clone();
    let d = layout.level_dims[level].map(u64::from);
    let mut out = vec![0u16; (d[0] * d[1] * d[2]) as usize];
    let n = layout.bricks_in_level(level);
    let (core, apron, payload) = (
        u64::from(BRICK_CORE),
        u64::from(BRICK_APRON),
        u64::from(BRICK_PAYLOAD),
    );
    for bz in 0..n[2] {
        for by in 0..n[1] {
            for bx in 0..n[0] {
                let id = BrickId::new(level as u8, [bx, by, bz]);
                let brick = source.read_brick(id).unwrap();
                let o = [bx, by, bz].map(|b| u64::from(b) * core);
                for z in 0..core.min(d[2] - o[2]) {
                    for y in 0..core.min(d[1] - o[1]) {
                        for x in 0..core.min(d[0] - o[0]) {
                            let src = ((z + apron) * payload + y + apron) * payload + x + apron;
                            let dst = ((o[2] + z) * d[1] + o[1] + y) * d[0] + o[0] + x;
                            out[dst as usize] = brick[src as usize];
                        }
                    }
                }
            }
        }
    }
    (out, d)
}

/// Every brick of every level of `a` equals `b`'s (payload with apron), and the layouts agree.
pub fn assert_same_bricks(a: &dyn VolumeSource, b: &dyn VolumeSource) {
    assert_eq!(a.layout(), b.layout());
    let layout = a.layout().clone();
    for level in 0..layout.level_count() {
        let n = layout.bricks_in_level(level);
        for bz in 0..n[2] {
            for by in 0..n[1] {
                for bx in 0..n[0] {
                    let id = BrickId::new(level as u8, [bx, by, bz]);
                    let (va, vb) = (a.read_brick(id).unwrap(), b.read_brick(id).unwrap());
                    assert!(
                        va == vb,
                        "brick level {level} at {:?} differs between {} and {}",
                        id.coords,
                        a.location(),
                        b.location()
                    );
                }
            }
        }
    }
}

/// `python3` with zarr-python 3 (and numpy), or a panic with the install hint: the independent
/// reader is part of what these tests check, so a missing one fails rather than skips.
pub fn python_with_zarr() -> PathBuf {
    let python = PathBuf::from(std::env::var("PYTHON").unwrap_or_else(|_| "python3".into()));
    let ok = std::process::Command::new(&python)
        .args([
            "-c",
            "import zarr, numpy; assert int(zarr.__version__.split('.')[0]) >= 3",
        ])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        ok,
        "zarr-python 3 is needed for this test: pip install 'zarr>=3' ome-zarr-models (as .ci/run does)"
    );
    python
}

/// Runs a Python script; panics with its output when it fails. Returns stdout.
pub fn run_python(script: &str, args: &[&Path]) -> String {
    let python = python_with_zarr();
    let out = std::process::Command::new(python)
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "python failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

pub fn shared_data(test: &str) -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if dir.is_dir() {
        Some(dir)
    } else {
        println!(
            "SKIP {test}: {} is absent; real-scan checks not run",
            dir.display()
        );
        None
    }
}

pub fn write_u16(path: &Path, values: &[u16]) {
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(path, bytes).unwrap();
}
