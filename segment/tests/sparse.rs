//! Painting out of core (issue 52, "Out of core"): on a sparse grid far larger than memory, a
//! layer and its history cost memory in proportion to the bricks edited, nothing per brick of
//! the grid. Its own test binary, one test in it, so the process's resident memory is this
//! test's alone (libtest runs the tests of one binary on parallel threads).

use std::collections::BTreeSet;
use std::time::Instant;

use glam::DVec3;
use strata_segment::grid::BrickKey;
use strata_segment::history::History;
use strata_segment::tools::brush::{stroke, stroke_voxels, Brush, BrushAction, BrushShape};
use strata_segment::{LabelLayer, LABEL_BRICK, LABEL_BRICK_VOXELS};
use strata_types::VolumeGeometry;

/// Resident memory of this process in bytes (`VmRSS` of `/proc/self/status`, in kB).
fn resident_bytes() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("read /proc/self/status");
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .expect("/proc/self/status has VmRSS in kB");
    kb * 1024
}

/// A deterministic scatter of positions (a linear congruential generator: no dependency, the
/// same strokes on every run).
struct Scatter(u64);

impl Scatter {
    fn next_unit(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// `strokes` brush strokes of 12 pointer positions each, 1.5 mm apart, at scattered places of
/// the grid, each pushed to a history as the viewer does. Returns the layer, the history and
/// the distinct bricks the strokes cover (from the brush's own voxel list).
fn paint(
    geometry: &VolumeGeometry,
    strokes: usize,
    seed: u64,
) -> (LabelLayer, History, BTreeSet<BrickKey>, Vec<f64>) {
    let mut layer = LabelLayer::new_empty(geometry.clone()).expect("a valid grid");
    let label = layer
        .segments_mut()
        .add("painted")
        .expect("room for a segment");
    let brush = Brush {
        shape: BrushShape::Sphere,
        diameter_mm: 10.0,
        value_range: None,
    };
    let mut history = History::new(usize::MAX);
    let mut covered = BTreeSet::new();
    let mut scatter = Scatter(seed);
    let extent = geometry.dims.map(|d| f64::from(d) - 40.0);
    let mut per_stroke_ms = Vec::with_capacity(strokes);
    for _ in 0..strokes {
        let start = [0, 1, 2].map(|a| 20.0 + scatter.next_unit() * extent[a]);
        let path: Vec<DVec3> = (0..12)
            .map(|n| {
                let index = DVec3::new(start[0] + 3.0 * n as f64, start[1], start[2]);
                geometry.patient_from_index(index)
            })
            .collect();
        for v in stroke_voxels(layer.grid(), &brush, &path).expect("stroke inside the grid") {
            covered.insert(BrickKey(v.map(|c| c / LABEL_BRICK)));
        }
        let began = Instant::now();
        let edit = stroke(&mut layer, &brush, BrushAction::Paint(label), &path, None)
            .expect("the stroke applies")
            .expect("the stroke changes voxels");
        per_stroke_ms.push(began.elapsed().as_secs_f64() * 1e3);
        history.push(edit);
    }
    (layer, history, covered, per_stroke_ms)
}

#[test]
fn painting_a_4096_cubed_sparse_grid_costs_memory_for_the_edited_bricks_only() {
    // 4096³ at 0.5 mm: 128 GiB of u16 labels if held whole, 2 097 152 bricks.
    let geometry = VolumeGeometry::axis_aligned([4096; 3], [0.5, 0.5, 0.5]);
    let before = resident_bytes();
    let (layer, history, covered, _) = paint(&geometry, 150, 52);
    let grown = resident_bytes().saturating_sub(before);

    // Exactly the bricks the strokes reach are held: none for the rest of the grid.
    let edited: BTreeSet<BrickKey> = layer.edited_bricks().map(|(k, _)| k).collect();
    assert_eq!(
        edited, covered,
        "the layer holds the bricks the strokes cover, no others"
    );

    // What the layer and its history hold: the edited bricks' images, and each edit's before and
    // after image of the bricks it changed (a 10 mm sphere at 0.5 mm crosses 2-8 bricks).
    let brick_bytes = (LABEL_BRICK_VOXELS * size_of::<u16>()) as u64;
    let held = edited.len() as u64 * brick_bytes + history.bytes() as u64;
    let dense = 4096u64.pow(3) * 2;
    println!(
        "4096³ sparse: {} edited bricks of {}, layer + history {:.1} MiB, resident memory grew {:.1} MiB (dense labels: {} GiB)",
        edited.len(),
        geometry.dims.map(|d| u64::from(d.div_ceil(LABEL_BRICK))).iter().product::<u64>(),
        held as f64 / 1048576.0,
        grown as f64 / 1048576.0,
        dense >> 30,
    );
    // What is held is per edited brick: its image in the layer and, per edit that changed it,
    // a before and an after image (the after shared with the layer, counted twice here).
    assert!(
        held <= 3 * edited.len() as u64 * brick_bytes,
        "layer and history hold {held} bytes for {} edited bricks",
        edited.len()
    );
    // Resident memory: what is held, plus 48 MiB for the harness and a stroke's scratch. A
    // structure per brick of the grid (2 M bricks) or per voxel, or a dense plane of the grid
    // (4096² u16: 32 MiB per plane touched), would exceed it.
    let bound = held + (48 << 20);
    assert!(
        grown <= bound,
        "resident memory grew {grown} bytes for {held} bytes of edited bricks and history (bound {bound})"
    );
}

/// Memory and time of 1 000 strokes on a 16384³ sparse grid (the benchmark): run with
/// `cargo test --release -p strata-segment --test sparse -- --ignored --nocapture`.
#[test]
#[ignore = "benchmark: run with --release -- --ignored --nocapture"]
fn bench_1000_strokes_on_a_16384_cubed_sparse_grid() {
    let geometry = VolumeGeometry::axis_aligned([16384; 3], [0.25, 0.25, 0.25]);
    let before = resident_bytes();
    let (layer, history, covered, mut per_stroke_ms) = paint(&geometry, 1000, 16384);
    let grown = resident_bytes().saturating_sub(before);
    assert_eq!(layer.edited_brick_count(), covered.len());
    per_stroke_ms.sort_by(f64::total_cmp);
    let p = |q: f64| per_stroke_ms[((per_stroke_ms.len() - 1) as f64 * q).round() as usize];
    println!(
        "16384³ sparse (0.25 mm), 1000 strokes of a 10 mm sphere, 12 events each: {} edited bricks, layer {:.1} MiB + history {:.1} MiB; resident memory grew {:.1} MiB; per stroke p50 {:.2} ms, p95 {:.2} ms",
        layer.edited_brick_count(),
        (layer.edited_brick_count() * LABEL_BRICK_VOXELS * 2) as f64 / 1048576.0,
        history.bytes() as f64 / 1048576.0,
        grown as f64 / 1048576.0,
        p(0.5),
        p(0.95),
    );
}
