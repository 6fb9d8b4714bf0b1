//! Stroke latency, issue 52's figure: a 10 mm brush dragged across the axial slice of a 512³
//! grid of 0.7 mm voxels (a CT's), one pointer event per millimetre. Per event it times what the
//! editor does between the event and the slice shown again:
//! - `paint`: the UI thread's work (`Segmentation::stroke_to`: the disc swept from the last
//!   position, the bricks it reaches copied and written);
//! - `slice`: the overlay reader's work, the edited slice read back (512², the labels on the
//!   primary's grid, as the slice view samples them).
//!
//! And per stroke, the merge of its events into one undo step (`end_stroke`, at release).
//!
//! `cargo run --release -p strata-segment --example stroke_latency [-- STROKES EVENTS]`
//! (default 10 strokes of 200 events). One thread: wall time is its CPU time on an idle machine.

use std::time::Instant;

use glam::DVec3;
use strata_segment::history::merge_edits;
use strata_segment::tools::brush::{self, Brush, BrushAction, BrushShape, SlicePlane};
use strata_segment::{LabelLayer, LabelRead};
use strata_types::VolumeGeometry;

const EDGE: u32 = 512;
const SPACING_MM: f64 = 0.7;
const DIAMETER_MM: f64 = 10.0;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let strokes: usize = args.next().map(|a| a.parse()).transpose()?.unwrap_or(10);
    let events: usize = args.next().map(|a| a.parse()).transpose()?.unwrap_or(200);
    let geometry = VolumeGeometry::axis_aligned([EDGE; 3], [SPACING_MM; 3]);
    let mut layer = LabelLayer::new_empty(geometry.clone())?;
    let label = layer.segments_mut().add("stroke")?;
    let brush = Brush {
        shape: BrushShape::Disc(SlicePlane::Axial),
        diameter_mm: DIAMETER_MM,
        value_range: None,
    };
    let k = EDGE / 2;
    let mut slice = vec![0; (EDGE * EDGE) as usize];
    let (mut paint_ms, mut slice_ms, mut event_ms, mut merge_ms) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for s in 0..strokes {
        let mut last: Option<DVec3> = None;
        let mut edits = Vec::new();
        for e in 0..events {
            // Across the slice, 1 mm per event, each stroke on its own row with a gentle wave.
            let index = DVec3::new(
                40.0 + e as f64 / SPACING_MM,
                40.0 + s as f64 * 40.0 + 6.0 * (e as f64 * 0.05).sin(),
                f64::from(k),
            );
            let position = geometry.patient_from_index(index);
            let swept: Vec<DVec3> = last.into_iter().chain([position]).collect();
            let started = Instant::now();
            let edit = brush::stroke(&mut layer, &brush, BrushAction::Paint(label), &swept, None)?;
            let painted = Instant::now();
            layer.read_slice_k(k, &mut slice)?;
            let shown = Instant::now();
            edits.extend(edit);
            last = Some(position);
            paint_ms.push((painted - started).as_secs_f64() * 1e3);
            slice_ms.push((shown - painted).as_secs_f64() * 1e3);
            event_ms.push((shown - started).as_secs_f64() * 1e3);
        }
        let started = Instant::now();
        let merged = merge_edits("Brush", edits);
        merge_ms.push(started.elapsed().as_secs_f64() * 1e3);
        if merged.is_none() {
            return Err("a stroke changed no voxel".into());
        }
    }
    let labelled = slice.iter().filter(|&&v| v == label).count();
    println!(
        "{strokes} strokes x {events} events, {DIAMETER_MM} mm brush, {EDGE}³ at {SPACING_MM} mm; \
         {labelled} voxels labelled on the slice"
    );
    for (name, times) in [
        ("paint (UI thread)", &mut paint_ms),
        ("slice read (overlay thread)", &mut slice_ms),
        ("event to slice", &mut event_ms),
        ("merge at release (per stroke)", &mut merge_ms),
    ] {
        times.sort_by(f64::total_cmp);
        let at = |q: f64| times[((times.len() - 1) as f64 * q).round() as usize];
        println!(
            "{name:>30}: p50 {:.3} ms  p95 {:.3} ms  max {:.3} ms  (n {})",
            at(0.5),
            at(0.95),
            at(1.0),
            times.len()
        );
    }
    Ok(())
}
