//! DICOM SEG import against highdicom: `support/make_dicom_seg.py` writes BINARY and FRACTIONAL
//! SEGs (1-bit frames that do not end on byte boundaries, frames unordered and sparse, three
//! segments with names, colours and an overlap) and highdicom's decode of each. The store's
//! level-0 voxels must equal highdicom's label at the same patient position, the segment names
//! and colours must match highdicom's CIELab → sRGB. Without highdicom this FAILS with the
//! install command (CI installs it: .ci/run).

use std::path::Path;

use strata_storage::import::{import_source, ImportOptions};
use strata_storage::readers::{open_source, ReadOptions};
use strata_storage::Store;
use strata_types::BrickId;
use strata_types::{BRICK_APRON, BRICK_PAYLOAD};

fn generate(dir: &Path) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/support/make_dicom_seg.py");
    let out = std::process::Command::new("python3")
        .arg(&script)
        .arg(dir)
        .output()
        .expect("python3 needed");
    assert!(
        out.status.success(),
        "make_dicom_seg.py failed (needs highdicom: pip install highdicom; CI: .ci/run)\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Solves the 3×3 system `m · x = b` (Cramer's rule; the test's affines are well conditioned).
fn solve3(m: [[f64; 3]; 3], b: [f64; 3]) -> [f64; 3] {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(m);
    let mut x = [0.0; 3];
    for (c, xc) in x.iter_mut().enumerate() {
        let mut mc = m;
        for r in 0..3 {
            mc[r][c] = b[r];
        }
        *xc = det(mc) / d;
    }
    x
}

#[test]
fn dicom_seg_imports_as_a_label_store_equal_to_highdicoms_decode() {
    let dir = tempfile::tempdir().unwrap();
    generate(dir.path());
    for case in ["binary", "fractional"] {
        let expected: serde_json::Value = serde_json::from_slice(
            &std::fs::read(dir.path().join(format!("{case}.json"))).unwrap(),
        )
        .unwrap();
        let opened = open_source(
            &dir.path().join(format!("{case}.dcm")),
            &ReadOptions::default(),
        )
        .unwrap_or_else(|e| panic!("{case}: {e}"));
        assert_eq!(opened.info.modality, "SEG");

        // Segment names and colours (±1 per channel: both sides round a float conversion).
        let segments = expected["segments"].as_array().unwrap();
        assert_eq!(opened.info.labels.len(), segments.len(), "{case}");
        for (label, want) in opened.info.labels.iter().zip(segments) {
            assert_eq!(u64::from(label.value), want["number"].as_u64().unwrap());
            assert_eq!(label.name, want["name"].as_str().unwrap());
            let rgb = label.rgb.expect("a recommended colour");
            for c in 0..3 {
                let w = want["rgb"][c].as_i64().unwrap();
                assert!(
                    (i64::from(rgb[c]) - w).abs() <= 1,
                    "{case} {}: {rgb:?} vs {}",
                    label.name,
                    want["rgb"]
                );
            }
        }

        let store_path = dir.path().join(format!("{case}.strata"));
        import_source(opened, &store_path, &ImportOptions::default()).unwrap();
        let store = Store::open(&store_path).unwrap();
        let header = store.header().clone();
        assert_eq!(
            header.labels.len(),
            segments.len(),
            "labels reach the header"
        );
        let g = &header.geometry;
        let shape: Vec<usize> = expected["shape_krc"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect();
        let affine: Vec<Vec<f64>> = expected["affine"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| {
                r.as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_f64().unwrap())
                    .collect()
            })
            .collect();
        let labels: Vec<i64> = expected["labels_krc"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_i64().unwrap())
            .collect();
        // The same number of voxels on the same physical grid (maybe with axes reversed).
        let mut ours = g.dims.map(|d| d as usize);
        let mut theirs = [shape[2], shape[1], shape[0]];
        ours.sort_unstable();
        theirs.sort_unstable();
        assert_eq!(ours, theirs, "{case}: grid sizes");
        assert!(
            g.dims[0] == 5 && g.dims[1] == 7,
            "{case}: 5 columns, 7 rows"
        );

        assert!(
            store.layout().bricks_in_level(0) == [1, 1, 1],
            "the test volume fits one brick"
        );
        let brick = store.read_brick(BrickId::new(0, [0, 0, 0])).unwrap();
        let m = [
            [affine[0][0], affine[0][1], affine[0][2]],
            [affine[1][0], affine[1][1], affine[1][2]],
            [affine[2][0], affine[2][1], affine[2][2]],
        ];
        let mut labelled = 0;
        let mut overlapping = 0;
        for k in 0..g.dims[2] {
            for j in 0..g.dims[1] {
                for i in 0..g.dims[0] {
                    // Our voxel's patient position, then highdicom's index there.
                    let p: [f64; 3] = std::array::from_fn(|a| {
                        g.origin_lps_mm[a]
                            + g.direction[0][a] * g.spacing_mm[0] * i as f64
                            + g.direction[1][a] * g.spacing_mm[1] * j as f64
                            + g.direction[2][a] * g.spacing_mm[2] * k as f64
                    });
                    let krc = solve3(
                        m,
                        [
                            p[0] - affine[0][3],
                            p[1] - affine[1][3],
                            p[2] - affine[2][3],
                        ],
                    );
                    for x in krc {
                        assert!(
                            (x - x.round()).abs() < 1e-6,
                            "{case}: voxel ({i},{j},{k}) at {p:?} is off highdicom's grid: {krc:?}"
                        );
                    }
                    let [kk, r, c] = krc.map(|x| x.round() as usize);
                    let want = labels[(kk * shape[1] + r) * shape[2] + c];
                    let payload = BRICK_PAYLOAD as usize;
                    let a = BRICK_APRON as usize;
                    let stored = brick[(i as usize + a)
                        + payload * ((j as usize + a) + payload * (k as usize + a))];
                    let got = header.value_mapping.physical(stored);
                    assert_eq!(got, want as f64, "{case}: voxel ({i},{j},{k})");
                    labelled += usize::from(want != 0);
                    overlapping += usize::from(want == 3);
                }
            }
        }
        assert!(labelled > 20, "{case}: only {labelled} labelled voxels");
        assert!(overlapping > 0, "{case}: the top segment shows somewhere");
        // The empty slice (1) of the source still exists in the grid: frames were sparse.
        assert_eq!(g.dims[2], 6, "{case}: 6 slices, one of them without frames");
    }
}
