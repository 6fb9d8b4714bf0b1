//! `strata seg`: statistics of a label map over its scan, and export to DICOM SEG, NIfTI and
//! OME-Zarr labels, each loaded back equal.

use std::path::Path;

use strata_segment::io::{load_label_file, load_omezarr_labels, write_nifti};
use strata_segment::{Label, LabelLayer, LabelRead};
use strata_storage::readers::{open_source, ReadOptions};

use crate::common::strata;

fn text(o: &std::process::Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn all_voxels(labels: &dyn LabelRead) -> Vec<Label> {
    let [nx, ny, nz] = labels.geometry().dims;
    let plane = (nx * ny) as usize;
    let mut out = vec![0; plane * nz as usize];
    for (k, slice) in out.chunks_mut(plane).enumerate() {
        labels.read_slice_k(k as u32, slice).expect("slice");
    }
    out
}

/// Two boxes of labels 1 and 7 on the phantom's grid, saved as NIfTI.
fn labels_on(primary: &Path, out: &Path) -> LabelLayer {
    let source = open_source(primary, &ReadOptions::default()).expect("phantom opens");
    let mut layer = LabelLayer::new_empty(source.info.geometry.clone()).expect("grid");
    layer.segments_mut().add("bone").expect("segment");
    layer
        .edit("boxes", |w| {
            for k in 5..15 {
                for j in 10..30 {
                    for i in 8..20 {
                        w.set([i, j, k], 1)?;
                    }
                }
            }
            for k in 20..36 {
                for j in 2..9 {
                    for i in 25..39 {
                        w.set([i, j, k], 7)?;
                    }
                }
            }
            Ok(())
        })
        .expect("edit");
    write_nifti(&layer, out).expect("labels saved");
    layer
}

#[test]
fn seg_stats_and_exports_match_the_labels_and_load_back_equal() {
    let dir = tempfile::tempdir().expect("tempdir");
    let primary = dir.path().join("p.nrrd");
    let o = strata(&["sample", "--size", "40", "--out", primary.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let labels = dir.path().join("labels.nii.gz");
    let layer = labels_on(&primary, &labels);
    let voxels = all_voxels(&layer);

    // Expected statistics, computed here from the phantom's values.
    let source = open_source(&primary, &ReadOptions::default()).expect("phantom");
    let (mut n, mut sum) = ([0u64; 2], [0f64; 2]);
    let mut values = Vec::new();
    let plane = 40 * 40;
    for k in 0..40u64 {
        source.data.read_slice_f64(k, &mut values);
        for (p, v) in values.iter().enumerate() {
            let slot = match voxels[k as usize * plane + p] {
                1 => 0,
                7 => 1,
                _ => continue,
            };
            n[slot] += 1;
            sum[slot] += v * source.info.slope + source.info.intercept;
        }
    }
    assert_eq!(n, [10 * 20 * 12, 16 * 7 * 14]);
    let o = strata(&[
        "seg",
        "stats",
        labels.to_str().unwrap(),
        "--on",
        primary.to_str().unwrap(),
    ]);
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    let ml = source.info.geometry.spacing_mm.iter().product::<f64>() / 1000.0;
    for (slot, (value, name)) in [(1, "segment 1"), (7, "segment 7")].into_iter().enumerate() {
        let line = out
            .lines()
            .find(|l| l.starts_with(&format!("{value}\t")))
            .unwrap_or_else(|| panic!("no line for label {value}: {out}"));
        let fields: Vec<&str> = line.split('\t').collect();
        assert_eq!(fields[1], name, "{line}");
        assert_eq!(fields[2], n[slot].to_string(), "{line}");
        let volume: f64 = fields[3].parse().expect("mL");
        assert!((volume - n[slot] as f64 * ml).abs() < 1e-3, "{line}");
        let mean: f64 = fields[4].parse().expect("mean");
        let want = sum[slot] / n[slot] as f64;
        assert!(
            (mean - want).abs() < 1e-3 * want.abs().max(1.0),
            "{line}: mean {want}"
        );
    }

    for (format, name) in [
        ("seg", "out.dcm"),
        ("nifti", "out.nii"),
        ("ome-zarr", "out.zarr"),
        ("store", "out.strata"),
    ] {
        let target = dir.path().join(name);
        let o = strata(&[
            "seg",
            "export",
            labels.to_str().unwrap(),
            "--format",
            format,
            "-o",
            target.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{format}: {}", text(&o));
        let back = if format == "ome-zarr" {
            load_omezarr_labels(&target.join("labels/segmentation")).expect("load back")
        } else {
            load_label_file(&target).expect("load back")
        };
        assert_eq!(back.geometry().dims, [40, 40, 40], "{format}");
        assert!(
            all_voxels(&back) == voxels,
            "{format}: voxels differ after export"
        );
    }

    // The primary on another grid (the same phantom at 56³: 400 mm across either way): the
    // labels keep their voxels, each takes the value of the primary's nearest voxel, said so.
    let finer = dir.path().join("p56.nrrd");
    let o = strata(&["sample", "--size", "56", "--out", finer.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let fine = open_source(&finer, &ReadOptions::default()).expect("phantom 56");
    let fine_g = fine.info.geometry.clone();
    let label_g = source.info.geometry.clone();
    let nearest = |g: &strata_types::VolumeGeometry, p: glam::DVec3| -> Option<[u32; 3]> {
        let s = g.index_from_patient(p);
        let s = [s.x, s.y, s.z].map(|c| (c + 0.5).floor() as i64);
        (0..3)
            .all(|a| s[a] >= 0 && s[a] < i64::from(g.dims[a]))
            .then(|| s.map(|c| c as u32))
    };
    let mut fine_slices = Vec::new();
    for k in 0..56u64 {
        let mut v = Vec::new();
        fine.data.read_slice_f64(k, &mut v);
        fine_slices.push(v);
    }
    let mut sum_fine = [0f64; 2];
    for (n, &l) in voxels.iter().enumerate() {
        let slot = match l {
            1 => 0,
            7 => 1,
            _ => continue,
        };
        let n = n as u32;
        let at = glam::DVec3::new(
            f64::from(n % 40),
            f64::from((n / 40) % 40),
            f64::from(n / 1600),
        );
        let s = nearest(&fine_g, label_g.patient_from_index(at)).expect("inside");
        sum_fine[slot] += fine_slices[s[2] as usize][(s[0] + 56 * s[1]) as usize] * fine.info.slope
            + fine.info.intercept;
    }
    let o = strata(&[
        "seg",
        "stats",
        labels.to_str().unwrap(),
        "--on",
        finer.to_str().unwrap(),
    ]);
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    assert!(
        out.contains("on another grid") && out.contains("nearest"),
        "{out}"
    );
    for (slot, value) in [1, 7].into_iter().enumerate() {
        let line = out
            .lines()
            .find(|l| l.starts_with(&format!("{value}\t")))
            .unwrap_or_else(|| panic!("no line for label {value}: {out}"));
        let fields: Vec<&str> = line.split('\t').collect();
        assert_eq!(fields[2], n[slot].to_string(), "{line}");
        let mean: f64 = fields[4].parse().expect("mean");
        let want = sum_fine[slot] / n[slot] as f64;
        assert!(
            (mean - want).abs() < 1e-3 * want.abs().max(1.0),
            "{line}: mean {want} from the nearest voxels of the 56³ primary"
        );
    }

    // Export onto the finer grid: every voxel of it holds the label of the nearest label voxel.
    let onto = dir.path().join("onto.nii");
    let o = strata(&[
        "seg",
        "export",
        labels.to_str().unwrap(),
        "--format",
        "nifti",
        "-o",
        onto.to_str().unwrap(),
        "--onto",
        finer.to_str().unwrap(),
    ]);
    let out = text(&o);
    assert!(o.status.success(), "{out}");
    assert!(
        out.contains("resampled") && out.contains("nearest"),
        "{out}"
    );
    let moved = load_label_file(&onto).expect("load back");
    assert_eq!(moved.geometry().dims, [56, 56, 56]);
    let got = all_voxels(&moved);
    let mut differing = 0;
    for (n, &l) in got.iter().enumerate() {
        let n = n as u32;
        let at = glam::DVec3::new(
            f64::from(n % 56),
            f64::from((n / 56) % 56),
            f64::from(n / 3136),
        );
        let want = nearest(&label_g, fine_g.patient_from_index(at))
            .map_or(0, |s| voxels[(s[0] + 40 * (s[1] + 40 * s[2])) as usize]);
        differing += usize::from(want != l);
    }
    assert_eq!(
        differing, 0,
        "voxels of the resampled export differing from nearest neighbour"
    );
    assert!(got.contains(&7));

    let missing = dir.path().join("missing.nii");
    let o = strata(&["seg", "stats", missing.to_str().unwrap()]);
    assert!(!o.status.success());
    let err = text(&o);
    assert!(
        err.contains("missing.nii") && err.contains("does not exist"),
        "{err}"
    );
}
