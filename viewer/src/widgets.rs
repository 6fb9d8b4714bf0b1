//! Small pieces every view and dialog shares: the not-for-diagnosis wording and colour, view
//! titles, wheel input in lines, and what a view reports after drawing itself. (The widgets the
//! browser viewer shares, such as the slow spinner, are in strata_viewer_ui::widgets.)

use egui::{Color32, Rect, Sense, Vec2};

pub const NOT_FOR_DIAGNOSIS: &str = "NOT FOR DIAGNOSTIC USE";
pub const WARNING_COLOUR: Color32 = Color32::from_rgb(255, 170, 40);

/// `text` shortened to at most `max_chars` characters by cutting its middle ("…"): a path
/// keeps its start and its file name (issue 47: the status bar's save path ran under
/// "NOT FOR DIAGNOSTIC USE").
pub fn elide_middle(text: &str, max_chars: usize) -> String {
    let chars: Vec<char> = text.chars().collect();
    if chars.len() <= max_chars {
        return text.to_string();
    }
    if max_chars <= 1 {
        return "…".chars().take(max_chars).collect();
    }
    let kept = max_chars - 1;
    // The end (the file name) matters most: two thirds of what is kept.
    let tail = (kept * 2).div_ceil(3);
    let head = kept - tail;
    let mut out: String = chars[..head].iter().collect();
    out.push('…');
    out.extend(&chars[chars.len() - tail..]);
    out
}

/// `text` elided in the middle so that it fits `max_width` points in `font` (a line painted
/// over a view: issue 47's export line ran off the 3D view). Whole when it fits.
pub fn fit_line(
    painter: &egui::Painter,
    text: &str,
    font: &egui::FontId,
    max_width: f32,
) -> String {
    let width = |t: &str| {
        painter
            .layout_no_wrap(t.to_owned(), font.clone(), Color32::WHITE)
            .size()
            .x
    };
    if width(text) <= max_width {
        return text.to_owned();
    }
    // The longest middle-elided version that fits (width grows with the characters kept).
    let (mut fits, mut too_long) = (0, text.chars().count());
    while too_long - fits > 1 {
        let mid = (fits + too_long) / 2;
        if width(&elide_middle(text, mid)) <= max_width {
            fits = mid;
        } else {
            too_long = mid;
        }
    }
    elide_middle(text, fits)
}

/// What a view reports after drawing itself.
#[derive(Clone, Copy, Debug, Default)]
pub struct ViewResponse {
    /// Its title was double-clicked: focus (1×1) or unfocus it.
    pub toggle_focus: bool,
    /// It was clicked or dragged: it becomes the focused view (keys page it).
    pub focused: bool,
    /// The level-0 continuous index under the pointer (slices: on the slice; 3D: at the pick
    /// depth), for the readout.
    pub hover: Option<[f64; 3]>,
}

/// Wheel movement this frame in lines (up positive), whatever unit the platform reports it in.
pub fn wheel_lines(ui: &egui::Ui) -> f64 {
    ui.input(|i| {
        i.events
            .iter()
            .map(|e| match e {
                egui::Event::MouseWheel { unit, delta, .. } => match unit {
                    // egui-winit reports a wheel click as 40 points on most platforms.
                    egui::MouseWheelUnit::Point => delta.y as f64 / 40.0,
                    egui::MouseWheelUnit::Line => delta.y as f64,
                    egui::MouseWheelUnit::Page => delta.y as f64 * 10.0,
                },
                _ => 0.0,
            })
            .sum::<f64>()
    })
}

/// Paints a view's title; returns true when it was double-clicked (focus toggle).
pub fn view_title(ui: &mut egui::Ui, rect: Rect, id: &str, title: &str, colour: Color32) -> bool {
    let galley_rect = Rect::from_min_size(
        rect.min + Vec2::new(6.0, 4.0),
        Vec2::new(title.len() as f32 * 7.5 + 8.0, 16.0),
    );
    let response = ui.interact(
        galley_rect,
        ui.scope_id().with(("title", id)),
        Sense::click(),
    );
    ui.painter_at(rect).text(
        rect.min + Vec2::new(8.0, 4.0),
        egui::Align2::LEFT_TOP,
        title,
        egui::FontId::proportional(13.0),
        colour,
    );
    response
        .on_hover_text("Double-click to focus / unfocus this view")
        .double_clicked()
}

#[cfg(test)]
mod elide_tests {
    use super::elide_middle;

    #[test]
    fn a_long_path_is_cut_in_the_middle_and_keeps_its_file_name() {
        let path = "/home/someone/strata/screenshots/2026-12-06/shot-0001.png";
        assert_eq!(elide_middle(path, 100), path);
        let short = elide_middle(path, 30);
        assert_eq!(short.chars().count(), 30);
        assert!(
            short.starts_with("/home/") && short.ends_with("shot-0001.png"),
            "{short}"
        );
        assert!(short.contains('…'));
        assert_eq!(elide_middle(path, 1), "…");
        assert_eq!(elide_middle(path, 0), "");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_too_wide_for_its_room_is_elided_to_fit_and_one_that_fits_is_whole() {
        let ctx = egui::Context::default();
        let mut output = ctx.run_ui(Default::default(), |ui| {
            let painter = ui.painter();
            let font = egui::FontId::proportional(12.0);
            let long = "2× screenshot of the 3D view to /home/user/Pictures/strata-3d-2x-1765000000000.png: frame 1 of 1";
            let width = |t: &str| {
                painter
                    .layout_no_wrap(t.to_owned(), font.clone(), Color32::WHITE)
                    .size()
                    .x
            };
            assert!(width(long) > 150.0, "the test line fits already");
            let fitted = fit_line(painter, long, &font, 150.0);
            assert!(fitted.contains('…'), "{fitted}");
            assert!(width(&fitted) <= 150.0, "{fitted} is {} wide", width(&fitted));
            // As long as fits: one more character kept would not.
            let kept = fitted.chars().count();
            assert!(width(&elide_middle(long, kept + 1)) > 150.0);
            assert!(fitted.ends_with("frame 1 of 1"), "{fitted}");
            assert_eq!(fit_line(painter, "finest level 0", &font, 150.0), "finest level 0");
        });
        // No renderer takes the frame's font texture here.
        output.textures_delta.clear();
    }
}
