//! The performance panel: target frame rate (strata_viewer_ui::target_fps) or fixed step,
//! resolution, then the figures the browser viewer shows too (strata_viewer_ui::performance),
//! gathered here from the render thread's status.

use std::time::Instant;

use strata_viewer_ui::performance::{self, FrameClock, PerformanceFigures};
use strata_viewer_ui::target_fps::target_fps_control;

use crate::preferences::Preferences;
use crate::scene::VolumeData;

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
        target_fps_control(ui, &mut prefs.target_fps_enabled, &mut prefs.target_fps);
        if !prefs.target_fps_enabled {
            ui.add(
                egui::Slider::new(&mut prefs.step_voxels, 0.125..=4.0)
                    .logarithmic(true)
                    .text("step (voxels)"),
            );
        }
        ui.add(egui::Slider::new(&mut prefs.render_scale, 0.25..=1.0).text("resolution"));
        // The render thread stamps its frames with Instants; the plot's axis is the clock's.
        let now = Instant::now();
        let t_now = clock.latest_seconds();
        let volume_frame_ms = status
            .volume_frame_ms
            .iter()
            .map(|(at, ms)| {
                [
                    t_now - now.saturating_duration_since(*at).as_secs_f64(),
                    *ms,
                ]
            })
            .collect();
        let working = if status.loading.is_some() || status.refining {
            Some(
                status
                    .loading
                    .clone()
                    .unwrap_or_else(|| status.refining_line()),
            )
        } else {
            None
        };
        let figures = PerformanceFigures {
            adapter: &status.adapter,
            volume_frame_ms,
            gpu_frame_ms: None,
            sampling_rate: status.sampling_rate,
            lod_factor: status.lod_factor,
            loader: status.loader.as_ref(),
            traversal: Some(&status.traversal),
            finest_resident_level: status.finest_resident_level,
            level_count: status.level_count,
            frames_rendered: status.frames_rendered,
            working,
        };
        performance::show(ui, clock, &figures);
    }
}
