//! Slice window/level presets, shared by the desktop's Slices panel and the browser's slice
//! views (issue 47 item 3: the page gets them by sharing this code, not by a copy): CT's named
//! windows, the scan's own (DICOM's WindowCenter/Width, NRRD's and NIfTI's cal_min/max), and
//! Auto (the histogram's 1st to 99th percentile, for MR, whose values have no absolute scale);
//! and [`initial_window`], the window a scan opens with in either viewer.
//!
//! Tested here (the choice of the opening window, the percentile window), by the desktop's
//! `ui_tests` (a preset button sets the window) and in Chromium by web/tests/browser.rs
//! (`the_page_opens_a_scan_at_the_window_the_desktop_opens_it_with`).

use strata_slices::Window;
use strata_storage::histogram::Histogram;
use strata_storage::source::WindowPreset as ScanWindow;

/// A named slice window.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowPreset {
    pub name: &'static str,
    pub window: Window,
}

const fn preset(name: &'static str, centre: f64, width: f64) -> WindowPreset {
    WindowPreset {
        name,
        window: Window { centre, width },
    }
}

/// The usual CT windows (HU), as radiology departments and Slicer name them.
pub const CT_WINDOWS: [WindowPreset; 8] = [
    preset("Brain", 40.0, 80.0),
    preset("Subdural", 75.0, 215.0),
    preset("Stroke", 40.0, 40.0),
    preset("Bone", 400.0, 1800.0),
    preset("Lung", -600.0, 1500.0),
    preset("Abdomen", 40.0, 400.0),
    preset("Liver", 60.0, 160.0),
    preset("Mediastinum", 50.0, 350.0),
];

/// A window from the `low`..`high` quantiles of the histogram (MR's "auto": MR has no
/// absolute scale, so the window follows the scan's own distribution).
pub fn quantile_window(h: &Histogram, low: f64, high: f64) -> Window {
    let total = h.total().max(1) as f64;
    let bin = (h.physical_max - h.physical_min) / h.counts.len().max(1) as f64;
    let mut seen = 0.0;
    let (mut lo, mut hi) = (h.physical_min, h.physical_max);
    let mut lo_set = false;
    for (i, &c) in h.counts.iter().enumerate() {
        seen += c as f64;
        if !lo_set && seen >= low * total {
            lo = h.physical_min + i as f64 * bin;
            lo_set = true;
        }
        if seen >= high * total {
            hi = h.physical_min + (i + 1) as f64 * bin;
            break;
        }
    }
    Window::new((lo + hi) * 0.5, (hi - lo).max(1e-6))
}

/// A window from the histogram's 1st to 99th percentile, for scans without presets (Auto).
pub fn percentile_window(h: &Histogram) -> Window {
    quantile_window(h, 0.01, 0.99)
}

/// The scan's own first window (DICOM's), if it names one; a zero width is widened so the
/// window/level step never divides by zero.
pub fn header_window(scan_windows: &[ScanWindow]) -> Option<Window> {
    scan_windows
        .first()
        .map(|w| Window::new(w.center, w.width.max(1e-6)))
}

/// The window a volume opens with: the header's first (DICOM's), else for a CT (by
/// [`crate::presets::looks_like_ct`]: a NRRD or NIfTI in HU has no window in its header) the
/// abdomen window W400/L40 as a CT reader expects (issue 36: a CT NRRD opened at a percentile
/// W1256/L−372), else the percentile window, which suits MR's arbitrary scale.
pub fn initial_window(header_window: Option<Window>, is_ct: bool, h: &Histogram) -> Window {
    header_window.unwrap_or_else(|| {
        if is_ct {
            CT_WINDOWS
                .iter()
                .find(|p| p.name == "Abdomen")
                .map_or(Window::new(40.0, 400.0), |p| p.window)
        } else {
            percentile_window(h)
        }
    })
}

/// The preset buttons, one wrapped row: CT's windows when `is_ct`, the scan's own windows
/// (those CT's do not already name), then Auto. A click sets `window`; returns whether one did.
pub fn preset_buttons(
    ui: &mut egui::Ui,
    is_ct: bool,
    scan_windows: &[ScanWindow],
    histogram: &Histogram,
    window: &mut Window,
) -> bool {
    let before = *window;
    ui.horizontal_wrapped(|ui| {
        if is_ct {
            for preset in CT_WINDOWS {
                if ui
                    .selectable_label(*window == preset.window, preset.name)
                    .on_hover_text(format!(
                        "W {:.0} / L {:.0} HU",
                        preset.window.width, preset.window.centre
                    ))
                    .clicked()
                {
                    *window = preset.window;
                }
            }
        }
        // The scan's own windows (DICOM window presets), then the histogram's.
        for w in scan_windows {
            let own = Window::new(w.center, w.width.max(1e-6));
            if !CT_WINDOWS.iter().any(|p| p.window == own)
                && ui
                    .selectable_label(*window == own, format!("{} (scan)", w.name))
                    .clicked()
            {
                *window = own;
            }
        }
        let auto = percentile_window(histogram);
        if ui
            .selectable_label(*window == auto, "Auto")
            .on_hover_text("1st to 99th percentile of the scan's values (MR, anything unscaled)")
            .clicked()
        {
            *window = auto;
        }
    });
    *window != before
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::presets::looks_like_ct;

    #[test]
    fn a_ct_without_a_header_window_opens_at_a_ct_window_and_an_mr_at_its_percentiles() {
        // A CT NRRD in HU: air, soft tissue, bone; no modality tag, no window in the header.
        let mut counts = vec![0u64; 300];
        counts[0] = 5_000; // air at -1024
        for c in counts.iter_mut().take(120).skip(100) {
            *c = 2_000; // soft tissue around 0 HU
        }
        counts[250] = 300; // bone
        let ct = Histogram {
            physical_min: -1024.0,
            physical_max: 2000.0,
            counts: counts.clone(),
        };
        let is_ct = looks_like_ct("", "", (ct.physical_min, ct.physical_max));
        assert!(is_ct);
        assert_eq!(initial_window(None, is_ct, &ct), Window::new(40.0, 400.0));
        // The header's window wins where there is one.
        let dicom = Window::new(-600.0, 1500.0);
        assert_eq!(initial_window(Some(dicom), is_ct, &ct), dicom);
        let named = [ScanWindow {
            name: "lung".into(),
            center: -600.0,
            width: 1500.0,
        }];
        assert_eq!(header_window(&named), Some(dicom));
        assert_eq!(header_window(&[]), None);
        // An MR (non-negative, no unit): the percentile window, as before.
        let mr = Histogram {
            physical_min: 0.0,
            physical_max: 3000.0,
            counts,
        };
        let is_ct = looks_like_ct("MR", "", (mr.physical_min, mr.physical_max));
        assert!(!is_ct);
        assert_eq!(initial_window(None, is_ct, &mr), percentile_window(&mr));
    }

    #[test]
    fn percentile_window_spans_the_bulk_of_the_histogram() {
        let mut counts = vec![0u64; 100];
        counts[10] = 1; // an outlier below
        for c in counts.iter_mut().take(80).skip(20) {
            *c = 100;
        }
        counts[99] = 1; // an outlier above
        let h = Histogram {
            physical_min: 0.0,
            physical_max: 100.0,
            counts,
        };
        let w = percentile_window(&h);
        assert!(
            (w.centre - 50.0).abs() < 2.0 && (w.width - 60.0).abs() < 3.0,
            "window {w:?}"
        );
    }
}
