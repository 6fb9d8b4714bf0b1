//! The Performance panel's figures: UI and volume frame times (line and plot), the GPU time of
//! the raycast when the renderer measures it, sampling rate, lod factor, the loader's GPU/CPU
//! cache figures and I/O, and whether the view is still refining. [`FrameClock`] keeps the UI
//! frame-time history it plots and the frame log the desktop writes on exit.
//!
//! The caller gathers the figures ([`PerformanceFigures`]) from its own renderer: the desktop
//! from its render thread's status, the browser from its inline loader. Controls that belong to
//! one build (the desktop's fixed step and resolution) stay with that build's panel.

use std::collections::VecDeque;

use strata_loader::FrameStats;
use web_time::Instant;

use crate::widgets::slow_spinner;

const MIB: f64 = (1u64 << 20) as f64;
/// UI frames kept for the plot.
const SAMPLES_KEPT: usize = 300;

/// One UI frame.
#[derive(Clone, Copy, Debug)]
pub struct FrameSample {
    /// Since the viewer started.
    pub seconds: f64,
    /// Since the previous UI frame (0 for the first).
    pub interval_ms: f64,
    /// CPU time of the app's `ui()`.
    pub ui_cpu_ms: f64,
    /// Volume frames the renderer had published by then.
    pub volume_frames: u64,
}

/// Frame-time history for the performance panel and the frame log.
#[derive(Default)]
pub struct FrameClock {
    last_frame_at: Option<Instant>,
    pub samples: VecDeque<FrameSample>,
    pub log: Vec<FrameSample>,
}

impl FrameClock {
    /// Records a UI frame that started at `ui_started` and ends now; `keep_log` keeps every
    /// sample.
    pub fn record(
        &mut self,
        seconds: f64,
        ui_started: Instant,
        volume_frames: u64,
        keep_log: bool,
    ) {
        self.record_at(Instant::now(), seconds, ui_started, volume_frames, keep_log);
    }

    /// [`FrameClock::record`] with the frame's end given (tests step a clock of their own).
    pub fn record_at(
        &mut self,
        now: Instant,
        seconds: f64,
        ui_started: Instant,
        volume_frames: u64,
        keep_log: bool,
    ) {
        let interval_ms = self.last_frame_at.map_or(0.0, |t| {
            now.saturating_duration_since(t).as_secs_f64() * 1e3
        });
        self.last_frame_at = Some(now);
        let sample = FrameSample {
            seconds,
            interval_ms,
            ui_cpu_ms: now.saturating_duration_since(ui_started).as_secs_f64() * 1e3,
            volume_frames,
        };
        self.samples.push_back(sample);
        while self.samples.len() > SAMPLES_KEPT {
            self.samples.pop_front();
        }
        if keep_log {
            self.log.push(sample);
        }
    }

    /// The newest sample's time (0 before the first): the plot's "now".
    pub fn latest_seconds(&self) -> f64 {
        self.samples.back().map_or(0.0, |s| s.seconds)
    }

    /// The frame log as CSV.
    pub fn log_csv(&self) -> String {
        let mut text = String::from("seconds,ui_interval_ms,ui_cpu_ms,volume_frames\n");
        for s in &self.log {
            text.push_str(&format!(
                "{:.4},{:.3},{:.3},{}\n",
                s.seconds, s.interval_ms, s.ui_cpu_ms, s.volume_frames
            ));
        }
        text
    }
}

/// What the panel shows besides the UI clock, gathered by the caller each frame.
#[derive(Clone, Debug, Default)]
pub struct PerformanceFigures<'a> {
    /// The GPU adapter the volume is drawn on.
    pub adapter: &'a str,
    /// Volume frame times as `[seconds, ms]` on the clock's time axis, newest last.
    pub volume_frame_ms: Vec<[f64; 2]>,
    /// The raycast pass's GPU time of the newest measured frame (timestamp queries), if any.
    pub gpu_frame_ms: Option<f64>,
    /// Samples per finest voxel along a ray.
    pub sampling_rate: f64,
    /// The loader's quality (lod) factor: 1 is the full-quality cut.
    pub lod_factor: f64,
    /// The loader's figures for the last frame (a streamed volume).
    pub loader: Option<&'a FrameStats>,
    /// The traversal the volume renders with (shown with the loader's figures).
    pub traversal: Option<&'a str>,
    /// Finest octree level with a brick on the GPU.
    pub finest_resident_level: Option<u8>,
    pub level_count: usize,
    pub frames_rendered: u64,
    /// Still working (loading or refining): the line shown beside a spinner. `None`: the view
    /// is final ("converged", or why it stopped short: the loader's convergence status).
    pub working: Option<String>,
}

/// The mean of the last `n` plot points' values; None for none.
fn mean_of_last(points: &[[f64; 2]], n: usize) -> Option<f64> {
    let last = &points[points.len().saturating_sub(n)..];
    let mean = last.iter().map(|p| p[1]).sum::<f64>() / last.len() as f64;
    (!last.is_empty() && mean.is_finite()).then_some(mean)
}

/// "12.3 ms", or "—" until there is a time (issue 47: the page showed "volume frame NaN ms"
/// before its first timed frame).
pub fn format_ms(ms: Option<f64>) -> String {
    match ms {
        Some(ms) if ms.is_finite() => format!("{ms:.1} ms"),
        _ => "—".into(),
    }
}

/// The panel's first line: the mean UI and volume frame times (last 30 and 10 frames).
pub fn frame_times_line(ui_ms: &[[f64; 2]], volume_ms: &[[f64; 2]]) -> String {
    format!(
        "UI frame {} · volume frame {}",
        format_ms(mean_of_last(ui_ms, 30)),
        format_ms(mean_of_last(volume_ms, 10)),
    )
}

/// Draws the panel's figures.
pub fn show(ui: &mut egui::Ui, clock: &FrameClock, figures: &PerformanceFigures<'_>) {
    let ui_ms: Vec<[f64; 2]> = clock
        .samples
        .iter()
        .filter(|s| s.interval_ms > 0.0)
        .map(|s| [s.seconds, s.interval_ms])
        .collect();
    let volume_ms = &figures.volume_frame_ms;
    ui.label(frame_times_line(&ui_ms, volume_ms));
    ui.weak(format!("volume on {}", figures.adapter));
    egui_plot::Plot::new("frame times")
        .height(110.0)
        .allow_drag(false)
        .allow_zoom(false)
        .allow_scroll(false)
        .include_y(0.0)
        .legend(egui_plot::Legend::default())
        .x_axis_label("s")
        .y_axis_label("ms")
        .show(ui, |plot| {
            plot.line(egui_plot::Line::new(
                "UI frame",
                egui_plot::PlotPoints::from(ui_ms),
            ));
            plot.line(egui_plot::Line::new(
                "volume frame",
                egui_plot::PlotPoints::from(volume_ms.clone()),
            ));
        });
    egui::Grid::new("perf figures")
        .num_columns(2)
        .show(ui, |ui| {
            if let Some(ms) = figures.gpu_frame_ms {
                name_cell(ui, "GPU time (raycast)");
                ui.label(format!("{ms:.2} ms"));
                ui.end_row();
            }
            name_cell(ui, "Sampling rate");
            ui.label(format!("{:.2} samples/voxel", figures.sampling_rate));
            ui.end_row();
            name_cell(ui, "Quality (lod) factor");
            ui.label(format!("{:.1}", figures.lod_factor));
            ui.end_row();
            if let Some(l) = figures.loader {
                loader_rows(ui, l, figures.traversal);
            }
            name_cell(ui, "Finest level on GPU");
            ui.label(figures.finest_resident_level.map_or("—".into(), |l| {
                format!(
                    "{l} (0 = full resolution; root {})",
                    figures.level_count.saturating_sub(1)
                )
            }));
            ui.end_row();
            name_cell(ui, "Volume frames");
            ui.label(figures.frames_rendered.to_string());
            ui.end_row();
        });
    match &figures.working {
        Some(line) => {
            ui.horizontal(|ui| {
                slow_spinner(ui);
                ui.label(line);
            });
        }
        None => {
            // "converged at budget (N nodes left coarser than wanted)" when the GPU budget
            // bound: a bigger budget would refine further.
            ui.weak(match figures.loader {
                Some(stats) if stats.converged_at_budget => stats.convergence_status(),
                _ => "converged".into(),
            });
        }
    }
}

/// A figure's name in the grid's first column: on one line, never wrapped. In a narrow side
/// panel the value column took the width and the names wrapped letter by letter (issue 47);
/// the values wrap at their spaces instead.
fn name_cell(ui: &mut egui::Ui, name: &str) {
    ui.add(egui::Label::new(name).extend());
}

/// The loader's rows of the figures grid.
fn loader_rows(ui: &mut egui::Ui, l: &FrameStats, traversal: Option<&str>) {
    name_cell(ui, "GPU bricks per level");
    let per_level: Vec<String> = l
        .gpu_resident_per_level
        .iter()
        .enumerate()
        .filter(|(_, n)| **n > 0)
        .map(|(level, n)| format!("L{level}: {n}"))
        .collect();
    ui.label(per_level.join("  "));
    ui.end_row();
    name_cell(ui, "GPU cache");
    ui.label(format!(
        "{} / {} slots · {:.0} / {:.0} MiB",
        l.gpu_slots_used,
        l.gpu_slots_capacity,
        l.gpu_bytes as f64 / MIB,
        l.gpu_budget_bytes as f64 / MIB
    ));
    ui.end_row();
    if let Some(traversal) = traversal {
        name_cell(ui, "Traversal");
        ui.label(traversal);
        ui.end_row();
    }
    name_cell(ui, "CPU cache");
    ui.label(format!(
        "{:.0} / {:.0} MiB · hit {:.0}%",
        l.cpu_bytes as f64 / MIB,
        l.cpu_budget_bytes as f64 / MIB,
        l.cpu_hit_rate * 100.0
    ));
    ui.end_row();
    name_cell(ui, "Pending loads");
    ui.label(format!("{} ({} reading)", l.pending, l.in_flight));
    ui.end_row();
    name_cell(ui, "I/O");
    ui.label(format!(
        "{:.1} MB/s · {} bricks read",
        l.bytes_read_per_second / 1e6,
        l.bricks_read_total
    ));
    ui.end_row();
    // LOD flicker: cut changes while the view stood still (0 when still is still; issue 35).
    name_cell(ui, "Cut changes while still");
    ui.label(l.cut_changes_while_still_total.to_string());
    ui.end_row();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_times_show_a_dash_until_a_frame_is_timed_never_nan() {
        assert_eq!(frame_times_line(&[], &[]), "UI frame — · volume frame —");
        let line = frame_times_line(&[[0.0, 16.0], [0.1, 18.0]], &[]);
        assert_eq!(line, "UI frame 17.0 ms · volume frame —");
        let line = frame_times_line(&[[0.0, 16.0]], &[[0.0, 40.0], [0.2, f64::NAN]]);
        assert_eq!(line, "UI frame 16.0 ms · volume frame —");
        let line = frame_times_line(&[[0.0, 16.0]], &[[0.0, 40.0], [0.2, 60.0]]);
        assert_eq!(line, "UI frame 16.0 ms · volume frame 50.0 ms");
        assert!(!line.contains("NaN"));
    }
}
