//! Timings, not checks (speed targets live in benchmarks, never in the default run): run with
//! `cargo test --release -p strata-segment --test tools -- --ignored --nocapture bench`.

use std::time::Instant;

use glam::DVec3;
use strata_segment::intensity::{DenseIntensity, ValueRange};
use strata_segment::tools::brush::{stroke, Brush, BrushAction, BrushShape, SlicePlane};
use strata_segment::tools::grow::{grow_from_seed, GrowCriterion};
use strata_segment::LabelLayer;
use strata_types::VolumeGeometry;

use super::common::{python, scratch};

/// CPU seconds of this thread (user + system) from /proc, so that a busy machine does not
/// inflate the figure (10 ms ticks: fine for the seconds measured here).
fn thread_cpu_s() -> f64 {
    let stat = std::fs::read_to_string("/proc/thread-self/stat").unwrap_or_default();
    let after = stat.rsplit_once(')').map_or("", |(_, rest)| rest);
    let fields: Vec<&str> = after.split_whitespace().collect();
    // Fields 14 and 15 of stat(5), counted from the state (field 3) here.
    let ticks = |n: usize| {
        fields
            .get(n - 3)
            .and_then(|f| f.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    (ticks(14) + ticks(15)) / 100.0
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

#[test]
#[ignore = "timing: run with --release -- --ignored --nocapture"]
fn bench_a_10_mm_brush_stroke_on_a_512_cubed_grid() {
    let g = VolumeGeometry::axis_aligned([512, 512, 512], [0.7, 0.7, 1.0]);
    let mut layer = LabelLayer::new_empty(g.clone()).unwrap();
    let a = layer.segments_mut().add("a").unwrap();
    let brush = Brush {
        shape: BrushShape::Disc(SlicePlane::Axial),
        diameter_mm: 10.0,
        value_range: None,
    };
    // 400 pointer events 1.2 mm apart along a wavy path in slice 256: each event paints the
    // segment from the previous position (what the view shows at once).
    let path: Vec<DVec3> = (0..=400)
        .map(|n| {
            let t = n as f64 * 1.2;
            DVec3::new(40.0 + t * 0.6, 180.0 + 40.0 * (t * 0.02).sin(), 256.0)
        })
        .collect();
    let mut times = Vec::new();
    for w in path.windows(2) {
        let start = Instant::now();
        stroke(&mut layer, &brush, BrushAction::Paint(a), w, None).unwrap();
        times.push(start.elapsed().as_secs_f64() * 1e3);
    }
    let whole = Instant::now();
    let mut fresh = LabelLayer::new_empty(g).unwrap();
    let b = fresh.segments_mut().add("b").unwrap();
    let edit = stroke(&mut fresh, &brush, BrushAction::Paint(b), &path, None)
        .unwrap()
        .unwrap();
    let whole_ms = whole.elapsed().as_secs_f64() * 1e3;
    let slowest = (0..times.len())
        .max_by(|&x, &y| times[x].total_cmp(&times[y]))
        .unwrap_or(0);
    println!("slowest event: #{slowest}");
    times.sort_by(f64::total_cmp);
    println!(
        "brush 10 mm, 512³ (0.7×0.7×1 mm), {} events: per event p50 {:.3} ms, p95 {:.3} ms, max {:.3} ms; whole 400-event stroke as one edit {:.2} ms ({} bricks)",
        times.len(),
        percentile(&times, 0.5),
        percentile(&times, 0.95),
        times[times.len() - 1],
        whole_ms,
        edit.changes.len()
    );
}

#[test]
#[ignore = "timing: run with --release -- --ignored --nocapture"]
fn bench_region_growing_of_a_512_cubed_volume_against_scipy() {
    let dims = [512u32, 512, 512];
    let [nx, ny, nz] = dims;
    let mut values = Vec::with_capacity((nx * ny * nz) as usize);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let (x, y, z) = (i as f32, j as f32, k as f32);
                let v = (x * 0.05).sin() * (y * 0.04 + 0.3 * (z * 0.03).cos()).cos()
                    + 0.6 * (z * 0.05 + x * 0.01).sin();
                values.push(400.0 * v);
            }
        }
    }
    let dir = scratch("bench-grow");
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(dir.join("volume.f32"), &bytes).unwrap();
    drop(bytes);
    let intensity = DenseIntensity::new(dims, values, "HU").unwrap();
    // A small bright component and one that spans most of the volume.
    for lo in [250.0f32, 100.0] {
        let values = intensity.values();
        let seed = [
            (0..nx)
                .find(|&i| values[(i + nx * (256 + ny * 256)) as usize] >= lo)
                .unwrap(),
            256,
            256,
        ];
        grow_once(&dir, dims, &intensity, lo, seed);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Region growing of bone (HU ≥ 300) on the 512³ CT phantom (`strata sample`'s: a spine of
/// cortical shell around trabecular bone, ribs, contrast-filled vessels at ~300 HU) against scipy
/// on the same machine, in one run.
#[test]
#[ignore = "timing: run with --release -- --ignored --nocapture"]
fn bench_region_growing_of_bone_on_the_512_cubed_ct_phantom_against_scipy() {
    let phantom = strata_storage::phantom::Phantom::cube(512);
    let dims = [512u32, 512, 512];
    let [nx, ny, nz] = dims;
    let mut values = Vec::with_capacity((nx * ny * nz) as usize);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                values.push(f32::from(phantom.hu(
                    u64::from(i),
                    u64::from(j),
                    u64::from(k),
                )));
            }
        }
    }
    let dir = scratch("bench-grow-ct");
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(dir.join("volume.f32"), &bytes).unwrap();
    drop(bytes);
    let intensity = DenseIntensity::new(dims, values, "HU").unwrap();
    // The seed: the bone voxel nearest the middle of the middle slice (the spine).
    let values = intensity.values();
    let (k, lo) = (256u32, 300.0f32);
    let seed = (0..ny)
        .flat_map(|j| (0..nx).map(move |i| [i, j, k]))
        .filter(|&[i, j, k]| values[(i + nx * (j + ny * k)) as usize] >= lo)
        .min_by_key(|&[i, j, _]| (i as i64 - 256).pow(2) + (j as i64 - 256).pow(2))
        .expect("the phantom has bone in its middle slice");
    grow_once(&dir, dims, &intensity, lo, seed);
    let _ = std::fs::remove_dir_all(&dir);
}

fn grow_once(
    dir: &std::path::Path,
    dims: [u32; 3],
    intensity: &DenseIntensity,
    lo: f32,
    seed: [u32; 3],
) {
    let [nx, ny, nz] = dims;
    let script = format!(
        r#"
import time, numpy as np, scipy.ndimage as ndi
v = np.fromfile("volume.f32", dtype="<f4").reshape(({nz}, {ny}, {nx}))
t = time.perf_counter(); c = time.process_time()
mask = v >= np.float32({lo})
labels, n = ndi.label(mask)
comp = labels == labels[{sk}, {sj}, {si}]
s = time.perf_counter() - t; c = time.process_time() - c
print(s, c, int(comp.sum()))
"#,
        si = seed[0],
        sj = seed[1],
        sk = seed[2],
    );
    let printed = python(&script, dir);
    let mut words = printed.split_whitespace();
    let scipy_s: f64 = words.next().unwrap().parse().unwrap();
    let scipy_cpu_s: f64 = words.next().unwrap().parse().unwrap();
    let scipy_voxels: u64 = words.next().unwrap().parse().unwrap();
    let g = VolumeGeometry::axis_aligned(dims, [0.7, 0.7, 1.0]);
    let mut layer = LabelLayer::new_empty(g).unwrap();
    let bone = layer.segments_mut().add("bone").unwrap();
    let start = Instant::now();
    let cpu = thread_cpu_s();
    let (out, _) = grow_from_seed(
        &mut layer,
        intensity,
        seed,
        bone,
        GrowCriterion::Range(ValueRange::new(f64::from(lo), f64::INFINITY).unwrap()),
        u64::MAX,
        &mut |_| {},
        None,
    )
    .unwrap();
    let ours_s = start.elapsed().as_secs_f64();
    let ours_cpu_s = thread_cpu_s() - cpu;
    assert_eq!(out.voxels, scipy_voxels, "the same component");
    println!(
        "region growing, 512³, value ≥ {lo}, component of {} voxels: strata {:.3} s wall / {:.2} s CPU, scipy threshold+label+select {:.3} s wall / {:.2} s CPU; ratio scipy/strata wall {:.2}, CPU {:.2}",
        out.voxels,
        ours_s,
        ours_cpu_s,
        scipy_s,
        scipy_cpu_s,
        scipy_s / ours_s,
        scipy_cpu_s / ours_cpu_s.max(0.01)
    );
}

/// Saving a 512³ segmentation in each format (the issue's "saving a 512³ SEG"), and loading it
/// back, timed in one run so the formats compare on the same machine and load.
#[test]
#[ignore = "timing: run with --release -- --ignored --nocapture"]
fn bench_saving_a_512_cubed_segmentation_in_each_format() {
    use strata_segment::grid::BrickKey;
    use strata_segment::io::dicom_seg::{write_dicom_seg, SegOptions};
    use strata_segment::io::load::load_label_file;
    use strata_segment::io::nifti::write_nifti;
    use strata_segment::io::omezarr_labels::{load_omezarr_labels, write_omezarr_labels};
    use strata_segment::LABEL_BRICK;

    let dims = [512u32, 512, 512];
    let g = VolumeGeometry::axis_aligned(dims, [0.7, 0.7, 1.0]);
    let mut layer = LabelLayer::new_empty(g).unwrap();
    // Three organs' worth of labels: a large ball (a liver's size, ~1.7 L), a smaller one inside
    // another, and a slab: 12 % of the voxels labelled, as a body CT's main segments are.
    let a = layer.segments_mut().add("liver").unwrap();
    let b = layer.segments_mut().add("lesion").unwrap();
    let c = layer.segments_mut().add("table").unwrap();
    let label_at = |v: [u32; 3]| -> u16 {
        let d = |c: [f64; 3]| {
            (0..3)
                .map(|n| (f64::from(v[n]) - c[n]).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        if d([300.0, 260.0, 250.0]) < 40.0 {
            b
        } else if d([280.0, 250.0, 256.0]) < 150.0 {
            a
        } else if (440..452).contains(&v[1]) {
            c
        } else {
            0
        }
    };
    layer
        .edit("fill", |w| {
            for bk in 0..dims[2] / LABEL_BRICK {
                for bj in 0..dims[1] / LABEL_BRICK {
                    for bi in 0..dims[0] / LABEL_BRICK {
                        let key = BrickKey([bi, bj, bk]);
                        let o = key.0.map(|x| x * LABEL_BRICK);
                        let brick = w.brick_mut(key)?;
                        let n = LABEL_BRICK as usize;
                        for (at, voxel) in brick.iter_mut().enumerate() {
                            let l = [at % n, (at / n) % n, at / (n * n)].map(|x| x as u32);
                            *voxel = label_at([o[0] + l[0], o[1] + l[1], o[2] + l[2]]);
                        }
                    }
                }
            }
            Ok(())
        })
        .unwrap();
    let dir = scratch("bench-save");
    let size_mb = |p: &std::path::Path| -> f64 {
        fn walk(p: &std::path::Path) -> u64 {
            if p.is_dir() {
                std::fs::read_dir(p)
                    .unwrap()
                    .map(|e| walk(&e.unwrap().path()))
                    .sum()
            } else {
                std::fs::metadata(p).map(|m| m.len()).unwrap_or(0)
            }
        }
        walk(p) as f64 / 1e6
    };
    let timed = |f: &mut dyn FnMut()| {
        let wall = Instant::now();
        let cpu = thread_cpu_s();
        f();
        (wall.elapsed().as_secs_f64(), thread_cpu_s() - cpu)
    };
    let seg = dir.join("labels.seg.dcm");
    let nii = dir.join("labels.nii.gz");
    let zarr = dir.join("image.zarr");
    let mut label_dir = std::path::PathBuf::new();
    let saves = [
        (
            "DICOM SEG",
            timed(&mut || {
                write_dicom_seg(&layer, &seg, &SegOptions::default()).unwrap();
            }),
            size_mb(&seg),
        ),
        (
            "NIfTI (.nii.gz)",
            timed(&mut || write_nifti(&layer, &nii).unwrap()),
            size_mb(&nii),
        ),
        (
            "OME-Zarr labels",
            timed(&mut || label_dir = write_omezarr_labels(&layer, &zarr, "seg").unwrap()),
            size_mb(&zarr),
        ),
    ];
    let loads = [
        timed(&mut || drop(load_label_file(&seg).unwrap())),
        timed(&mut || drop(load_label_file(&nii).unwrap())),
        timed(&mut || drop(load_omezarr_labels(&label_dir).unwrap())),
    ];
    for ((name, (wall, cpu), mb), (load_wall, load_cpu)) in saves.iter().zip(loads) {
        println!(
            "512³, 3 segments: save {name}: {wall:.2} s wall / {cpu:.2} s CPU, {mb:.1} MB; load back {load_wall:.2} s wall / {load_cpu:.2} s CPU"
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
