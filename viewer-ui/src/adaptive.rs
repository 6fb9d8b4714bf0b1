//! Adaptive sampling of the still view as both viewers decide and report it (render's
//! `passes::adaptive`, the adaptive-sampling paper): which views the adaptive pass draws, the
//! key an oracle is valid for, the ε knob's default and range, and the status line. The desktop
//! builds its oracle on a thread of its own (viewer/src/adaptive_view.rs), the page a bounded
//! number of slots per animation frame (web/src/adaptive.rs, render's `BlockOracleBuild`);
//! both apply an oracle only to the cut and transfer function it was built from
//! ([`OracleKey`]).

use strata_render::passes::adaptive::OracleTarget;
use strata_render::{RenderMode, RenderSettings, TransferFunction};

/// The ε of a new viewer: the render command's default (`strata render --oracle-epsilon`).
pub const DEFAULT_EPSILON: f64 = 0.001;
/// The ε slider's range. Below 1e-4 nearly every block near structure samples every slice (no
/// gain); above 0.1 thin features are stepped over.
pub const EPSILON_RANGE: (f64, f64) = (1e-4, 0.1);

/// What an oracle was built from; equal keys mean it is valid for the cut drawn now.
#[derive(Clone, Debug, PartialEq)]
pub struct OracleKey {
    /// Which streaming volume (a traversal switch, a GPU recovery or another 4-D frame makes a
    /// new one whose residency generations start again).
    pub volume: u64,
    /// `StreamingVolume::residency_generation`: the same bricks in the same slots.
    pub residency: u64,
    pub transfer_function: TransferFunction,
    pub epsilon: f64,
    /// Slice spacing in finest voxels (`RenderSettings::quality` of the frame).
    pub quality: f64,
    /// What the distances bound: the lit colour where the frame is lit (issue 37 item 4), so
    /// turning the light on or off builds again.
    pub target: OracleTarget,
}

impl OracleKey {
    /// The key of `volume`'s cut at `residency` drawn with `settings` and `transfer_function`.
    pub fn new(
        volume: u64,
        residency: u64,
        transfer_function: &TransferFunction,
        epsilon: f64,
        settings: &RenderSettings,
    ) -> Self {
        OracleKey {
            volume,
            residency,
            transfer_function: transfer_function.clone(),
            epsilon,
            quality: settings.quality,
            target: OracleTarget::for_settings(settings),
        }
    }
}

/// Why a view in `mode` is drawn by the raycaster alone although adaptive sampling is on
/// (`overlay`: a 3D overlay is drawn, which only the raycaster composites).
pub fn not_applicable(mode: RenderMode, overlay: bool) -> Option<&'static str> {
    if !matches!(mode, RenderMode::Dvr | RenderMode::Mip) {
        return Some("adaptive sampling draws DVR and MIP; the isosurface is the raycaster's");
    }
    if overlay {
        return Some("adaptive sampling off: the 3D overlay is drawn by the raycaster only");
    }
    None
}

/// "adaptive: 0.65 M samples (2.9× fewer than the raycaster), ε 0.001"; without the
/// raycaster's count (the page does not read its frame back) the comparison is left out.
pub fn status_line(samples: u64, raycaster_samples: Option<u64>, epsilon: f64) -> String {
    let millions = samples as f64 / 1e6;
    let ratio = match raycaster_samples {
        Some(r) if samples > 0 => {
            format!(
                " ({:.1}× fewer than the raycaster)",
                r as f64 / samples as f64
            )
        }
        _ => String::new(),
    };
    format!(
        "adaptive: {millions:.2} M samples{ratio}, ε {}",
        format_epsilon(epsilon)
    )
}

/// ε as the slider shows it (0.001, 0.0005, 0.02).
pub fn format_epsilon(epsilon: f64) -> String {
    let text = format!("{epsilon:.6}");
    text.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// The checkbox label (the UI tests find it by this text).
pub const ADAPTIVE_LABEL: &str = "Adaptive sampling (still view)";
/// The ε slider's accessible name.
pub const EPSILON_LABEL: &str = "Adaptive ε";

/// The Rendering panel's switch for adaptive sampling of the still view and its oracle's ε
/// (a logarithmic slider over [`EPSILON_RANGE`]), disabled for the isosurface. Both viewers
/// draw it: the desktop over its preferences, the page over its link's `adaptive=`.
pub fn controls(ui: &mut egui::Ui, mode: RenderMode, on: &mut bool, epsilon: &mut f64) {
    let iso = mode == RenderMode::Isosurface;
    ui.add_enabled_ui(!iso, |ui| {
        ui.checkbox(on, ADAPTIVE_LABEL)
            .on_hover_text(
                "When the view is still and loaded, draw the final frame by adaptive sampling \
                 (samples on view-aligned slices, skipped where the data are smooth and \
                 synthesised from coarser ones): far fewer samples for nearly the same image. \
                 Moving the camera draws with the raycaster as usual.",
            )
            .on_disabled_hover_text(
                "Adaptive sampling draws DVR and MIP; the isosurface's hit search is the \
                 raycaster's own.",
            );
        if *on {
            let (lo, hi) = EPSILON_RANGE;
            if !epsilon.is_finite() {
                *epsilon = DEFAULT_EPSILON;
            }
            ui.add(
                egui::Slider::new(epsilon, lo..=hi)
                    .logarithmic(true)
                    .custom_formatter(|v, _| format_epsilon(v))
                    .text("ε"),
            )
            .on_hover_text(
                "The oracle's ε: the opacity change per slice a 2³ block may have before it is \
                 sampled at every slice. Smaller is closer to the raycaster and slower; larger \
                 skips more and may step over thin features.",
            )
            .accessible_name(EPSILON_LABEL);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn epsilon_is_written_as_the_slider_shows_it() {
        assert_eq!(format_epsilon(0.001), "0.001");
        assert_eq!(format_epsilon(0.0005), "0.0005");
        assert_eq!(format_epsilon(0.02), "0.02");
    }

    #[test]
    fn the_status_line_compares_with_the_raycaster_where_it_counted() {
        assert_eq!(
            status_line(650_000, Some(1_885_000), 0.001),
            "adaptive: 0.65 M samples (2.9× fewer than the raycaster), ε 0.001"
        );
        assert_eq!(
            status_line(650_000, None, 0.02),
            "adaptive: 0.65 M samples, ε 0.02"
        );
    }

    #[test]
    fn the_isosurface_and_a_3d_overlay_stay_the_raycasters() {
        assert_eq!(not_applicable(RenderMode::Dvr, false), None);
        assert_eq!(not_applicable(RenderMode::Mip, false), None);
        assert!(not_applicable(RenderMode::Isosurface, false).is_some());
        assert!(not_applicable(RenderMode::Dvr, true).is_some());
    }
}
