//! Statistics equal numpy's on the same mask and values: counts exact, means within 1e-9
//! relative; the LPS box against a brute-force pass over the voxel centres.

use glam::DVec3;
use strata_segment::intensity::DenseIntensity;
use strata_segment::stats::{segment_statistics, to_csv};
use strata_segment::LabelLayer;

use super::common::{all_labels, python, rotated_anisotropic, scratch};

#[test]
fn segment_statistics_equal_numpy_on_the_same_mask() {
    let dims = [70u32, 60, 40];
    let g = rotated_anisotropic(dims);
    let [nx, ny, nz] = dims;
    let n = (nx * ny * nz) as usize;
    let mut layer = LabelLayer::new_empty(g.clone()).unwrap();
    for name in ["liver", "spleen", "kidney"] {
        layer.segments_mut().add(name).unwrap();
    }
    // Label 3 is left empty in the data; label 9 is in the data without a table entry.
    layer
        .edit("setup", |w| {
            for k in 0..nz {
                for j in 0..ny {
                    for i in 0..nx {
                        let h = (i * 31 + j * 17 + k * 7) % 23;
                        let label = if (i as i64 - 30).pow(2) + (j as i64 - 25).pow(2) < 300 {
                            1
                        } else if h < 3 && k > 10 {
                            2
                        } else if h == 5 && i > 60 {
                            9
                        } else {
                            0
                        };
                        if label != 0 {
                            w.set([i, j, k], label)?;
                        }
                    }
                }
            }
            Ok(())
        })
        .unwrap();
    let values: Vec<f32> = (0..n)
        .map(|x| {
            let x = x as f32;
            1000.0 * (x * 0.001).sin() + 40.0 * (x * 0.37).cos() - 300.0
        })
        .collect();
    let labels = all_labels(&layer);
    let dir = scratch("stats-numpy");
    let label_bytes: Vec<u8> = labels.iter().flat_map(|l| l.to_le_bytes()).collect();
    std::fs::write(dir.join("labels.u16"), label_bytes).unwrap();
    let value_bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    std::fs::write(dir.join("values.f32"), value_bytes).unwrap();
    let script = r#"
import json, numpy as np
l = np.fromfile("labels.u16", dtype="<u2")
v = np.fromfile("values.f32", dtype="<f4").astype(np.float64)
out = {}
for label in (1, 2, 3, 9):
    m = l == label
    x = v[m]
    out[label] = dict(count=int(m.sum()), mean=float(x.mean()) if x.size else None,
        sd=float(x.std()) if x.size else None, min=float(x.min()) if x.size else None,
        max=float(x.max()) if x.size else None, median=float(np.median(x)) if x.size else None)
print(json.dumps(out))
"#;
    let reference: serde_json::Value = serde_json::from_str(&python(script, &dir)).unwrap();
    let intensity = DenseIntensity::new(dims, values, "HU").unwrap();
    let stats = segment_statistics(&layer, Some(&intensity), None, &mut |_, _| {}).unwrap();
    let labels_seen: Vec<u16> = stats.segments.iter().map(|s| s.label).collect();
    assert_eq!(labels_seen, [1, 2, 3, 9]);
    let close = |a: f64, b: f64, what: &str| {
        assert!(
            (a - b).abs() <= 1e-9 * b.abs().max(1e-300),
            "{what}: {a} vs numpy {b}"
        );
    };
    for s in &stats.segments {
        let r = &reference[s.label.to_string()];
        let count = r["count"].as_u64().unwrap();
        assert_eq!(s.voxels, count, "label {}", s.label);
        let voxel_ml = g.spacing_mm.iter().product::<f64>() / 1000.0;
        close(s.volume_ml, count as f64 * voxel_ml, "volume");
        if count == 0 {
            assert!(s.mean.is_none() && s.median.is_none() && s.lps_box_mm.is_none());
            continue;
        }
        assert!(count > 100, "label {} has too few voxels to test", s.label);
        close(s.mean.unwrap(), r["mean"].as_f64().unwrap(), "mean");
        close(s.sd.unwrap(), r["sd"].as_f64().unwrap(), "sd");
        assert_eq!(s.min.unwrap(), r["min"].as_f64().unwrap());
        assert_eq!(s.max.unwrap(), r["max"].as_f64().unwrap());
        assert_eq!(s.median.unwrap(), r["median"].as_f64().unwrap(), "median");
        // The LPS box by brute force over the segment's voxel centres.
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for (x, _) in labels.iter().enumerate().filter(|(_, &l)| l == s.label) {
            let x = x as u32;
            let p = g.patient_from_index(DVec3::new(
                (x % nx) as f64,
                ((x / nx) % ny) as f64,
                (x / (nx * ny)) as f64,
            ));
            lo = lo.min(p);
            hi = hi.max(p);
        }
        let (got_lo, got_hi) = s.lps_box_mm.unwrap();
        for a in 0..3 {
            close(got_lo[a], lo[a], "box min");
            close(got_hi[a], hi[a], "box max");
        }
    }
    assert_eq!(stats.segments[3].name, "");
    let csv = to_csv(&stats);
    assert_eq!(csv.lines().count(), 5);
    assert!(csv.lines().nth(1).unwrap().starts_with("1,liver,"));
}

/// The page's statistics, one labelled brick a step (`StatisticsPass`, issue 52 item 4): many
/// steps, and exactly the table of the pass in one go (every figure bit for bit: the same sums
/// in the same order).
#[test]
fn statistics_read_one_brick_a_step_equal_the_statistics_in_one_pass() {
    use strata_segment::stats::StatisticsPass;
    let dims = [70u32, 60, 40];
    let mut layer = LabelLayer::new_empty(rotated_anisotropic(dims)).unwrap();
    for name in ["a", "b"] {
        layer.segments_mut().add(name).unwrap();
    }
    layer
        .edit("setup", |w| {
            for k in 0..dims[2] {
                for j in 0..dims[1] {
                    for i in 0..dims[0] {
                        let label = match (i * 31 + j * 17 + k * 7) % 13 {
                            0 => 1,
                            1 if i > 35 => 2,
                            _ => continue,
                        };
                        w.set([i, j, k], label)?;
                    }
                }
            }
            Ok(())
        })
        .unwrap();
    let n = dims.iter().product::<u32>() as usize;
    let values: Vec<f32> = (0..n)
        .map(|x| 800.0 * (x as f32 * 0.003).sin() - 100.0)
        .collect();
    let intensity = DenseIntensity::new(dims, values, "HU").unwrap();
    let at_once = segment_statistics(&layer, Some(&intensity), None, &mut |_, _| {}).unwrap();
    let mut pass = StatisticsPass::new(&layer);
    let mut steps = 0;
    while !pass
        .step(&layer, Some(&intensity), Some(1), None, &mut |_, _| {})
        .unwrap()
    {
        steps += 1;
    }
    assert!(
        steps >= 7,
        "only {steps} steps over {:?} bricks",
        layer.grid().bricks()
    );
    let stepped = pass.finish(&layer, "HU");
    assert_eq!(stepped, at_once);
    assert!(at_once.segments.iter().all(|s| s.voxels > 0));
}
