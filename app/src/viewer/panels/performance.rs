//! The performance panel: target frame rate or fixed step, resolution, UI and volume frame
//! times (plot), sampling rate, lod factor, GPU/CPU cache figures, I/O. [`FrameClock`] keeps the
//! UI frame-time history it plots and the frame log written on exit.

use std::collections::VecDeque;
use std::time::Instant;

use crate::viewer::preferences::Preferences;
use crate::viewer::scene::VolumeData;

const MIB: f64 = (1u64 << 20) as f64;

/// One UI frame.
#[derive(Clone, Copy, Debug)]
pub struct FrameSample {
    /// Since the viewer started.
    pub seconds: f64,
    /// Since the previous UI frame (0 for the first).
    pub interval_ms: f64,
    /// CPU time of the app's `ui()`.
    pub ui_cpu_ms: f64,
    /// Volume frames the render thread had published by then.
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
    /// Records a UI frame that started at `ui_started`; `keep_log` keeps every sample.
    pub fn record(
        &mut self,
        seconds: f64,
        ui_started: Instant,
        volume_frames: u64,
        keep_log: bool,
    ) {
        let now = Instant::now();
        let interval_ms = self
            .last_frame_at
            .map_or(0.0, |t| (now - t).as_secs_f64() * 1e3);
        self.last_frame_at = Some(now);
        let sample = FrameSample {
            seconds,
            interval_ms,
            ui_cpu_ms: (now - ui_started).as_secs_f64() * 1e3,
            volume_frames,
        };
        self.samples.push_back(sample);
        while self.samples.len() > 300 {
            self.samples.pop_front();
        }
        if keep_log {
            self.log.push(sample);
        }
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

#[derive(Default)]
pub struct PerformancePanel;

impl PerformancePanel {
    pub fn ui(
        &mut self,
        ui: &mut egui::Ui,
        prefs: &mut Preferences,
        data: &VolumeData,
        clock: &FrameClock,
    ) {
        let status = data.session.status();
        ui.horizontal(|ui| {
            let enabled = ui.checkbox(&mut prefs.target_fps_enabled, "Target frame rate");
            ui.add_enabled(
                prefs.target_fps_enabled,
                egui::Slider::new(&mut prefs.target_fps, 2.0..=60.0)
                    .suffix(" fps")
                    .logarithmic(true),
            )
            .labelled_by(enabled.id);
        });
        if !prefs.target_fps_enabled {
            ui.add(
                egui::Slider::new(&mut prefs.step_voxels, 0.125..=4.0)
                    .logarithmic(true)
                    .text("step (voxels)"),
            );
        }
        ui.add(egui::Slider::new(&mut prefs.render_scale, 0.25..=1.0).text("resolution"));
        let now = Instant::now();
        let ui_ms: Vec<[f64; 2]> = clock
            .samples
            .iter()
            .filter(|s| s.interval_ms > 0.0)
            .map(|s| [s.seconds, s.interval_ms])
            .collect();
        let t_now = clock.samples.back().map_or(0.0, |s| s.seconds);
        let volume_ms: Vec<[f64; 2]> = status
            .volume_frame_ms
            .iter()
            .map(|(at, ms)| {
                [
                    t_now - now.saturating_duration_since(*at).as_secs_f64(),
                    *ms,
                ]
            })
            .collect();
        let mean = |xs: &[[f64; 2]]| {
            if xs.is_empty() {
                f64::NAN
            } else {
                xs.iter().map(|p| p[1]).sum::<f64>() / xs.len() as f64
            }
        };
        ui.label(format!(
            "UI frame {:.1} ms · volume frame {:.1} ms",
            mean(&ui_ms[ui_ms.len().saturating_sub(30)..]),
            mean(&volume_ms[volume_ms.len().saturating_sub(10)..]),
        ));
        ui.weak(format!("volume on {}", status.adapter));
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
                    egui_plot::PlotPoints::from(volume_ms),
                ));
            });
        egui::Grid::new("perf figures")
            .num_columns(2)
            .show(ui, |ui| {
                ui.label("Sampling rate");
                ui.label(format!("{:.2} samples/voxel", status.sampling_rate));
                ui.end_row();
                ui.label("Quality (lod) factor");
                ui.label(format!("{:.1}", status.lod_factor));
                ui.end_row();
                if let Some(l) = &status.loader {
                    ui.label("GPU bricks per level");
                    let per_level: Vec<String> = l
                        .gpu_resident_per_level
                        .iter()
                        .enumerate()
                        .filter(|(_, n)| **n > 0)
                        .map(|(level, n)| format!("L{level}: {n}"))
                        .collect();
                    ui.label(per_level.join("  "));
                    ui.end_row();
                    ui.label("GPU cache");
                    ui.label(format!(
                        "{} / {} slots · {:.0} / {:.0} MiB",
                        l.gpu_slots_used,
                        l.gpu_slots_capacity,
                        l.gpu_bytes as f64 / MIB,
                        l.gpu_budget_bytes as f64 / MIB
                    ));
                    ui.end_row();
                    ui.label("Traversal");
                    ui.label(&status.traversal);
                    ui.end_row();
                    ui.label("CPU cache");
                    ui.label(format!(
                        "{:.0} / {:.0} MiB · hit {:.0}%",
                        l.cpu_bytes as f64 / MIB,
                        l.cpu_budget_bytes as f64 / MIB,
                        l.cpu_hit_rate * 100.0
                    ));
                    ui.end_row();
                    ui.label("Pending loads");
                    ui.label(format!("{} ({} reading)", l.pending, l.in_flight));
                    ui.end_row();
                    ui.label("I/O");
                    ui.label(format!(
                        "{:.1} MB/s · {} bricks read",
                        l.bytes_read_per_second / 1e6,
                        l.bricks_read_total
                    ));
                    ui.end_row();
                    // LOD flicker: cut changes while the view stood still (0 when still is
                    // still; issue 35).
                    ui.label("Cut changes while still");
                    ui.label(l.cut_changes_while_still_total.to_string());
                    ui.end_row();
                }
                ui.label("Finest level on GPU");
                ui.label(status.finest_resident_level.map_or("—".into(), |l| {
                    format!(
                        "{l} (0 = full resolution; root {})",
                        status.level_count.saturating_sub(1)
                    )
                }));
                ui.end_row();
                ui.label("Volume frames");
                ui.label(status.frames_rendered.to_string());
                ui.end_row();
            });
        if status.loading.is_some() || status.refining {
            ui.horizontal(|ui| {
                crate::viewer::widgets::slow_spinner(ui);
                ui.label(
                    status
                        .loading
                        .clone()
                        .unwrap_or_else(|| status.refining_line()),
                );
            });
        } else {
            // "converged at budget (N nodes left coarser than wanted)" when the GPU budget
            // bound: a bigger budget would refine further.
            ui.weak(match &status.loader {
                Some(stats) if stats.converged_at_budget => stats.convergence_status(),
                _ => "converged".into(),
            });
        }
    }
}
