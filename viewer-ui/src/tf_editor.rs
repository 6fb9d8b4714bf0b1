//! Transfer-function editor, in the desktop viewer's TF panel and the browser's side panel: the
//! volume's histogram (log counts) over physical values, an opacity polyline with draggable
//! points (click to add, right-click to remove) and a colour bar with stops (click to add, drag,
//! right-click to remove, pick the colour of the selected stop). Every edit changes the
//! `TransferFunction` at once; the caller's next render carries it.

use egui::{Color32, Pos2, Rect, Sense, Stroke, Vec2};
use strata_render::model::transfer_function::{ColorStop, OpacityStop};
use strata_render::TransferFunction;
use strata_storage::histogram::Histogram;

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Selection {
    #[default]
    None,
    Opacity(usize),
    Color(usize),
}

#[derive(Default)]
pub struct TfEditorState {
    pub selection: Selection,
    dragging: Option<Selection>,
    /// Where the opacity plot was drawn last frame (tests click into it).
    pub plot_rect: Option<Rect>,
}

const POINT_RADIUS: f32 = 5.0;

fn to_rgb8(rgb: [f64; 3]) -> Color32 {
    Color32::from_rgb(
        (rgb[0].clamp(0.0, 1.0) * 255.0) as u8,
        (rgb[1].clamp(0.0, 1.0) * 255.0) as u8,
        (rgb[2].clamp(0.0, 1.0) * 255.0) as u8,
    )
}

/// Returns true when the function changed.
pub fn show(
    ui: &mut egui::Ui,
    state: &mut TfEditorState,
    tf: &mut TransferFunction,
    histogram: &Histogram,
    range: (f64, f64),
    unit: &str,
) -> bool {
    let mut changed = false;
    let width = ui.available_width().max(120.0);
    let (lo, hi) = if range.1 > range.0 {
        range
    } else {
        (range.0, range.0 + 1.0)
    };
    let (plot_response, painter) =
        ui.allocate_painter(Vec2::new(width, 130.0), Sense::click_and_drag());
    let plot = plot_response
        .rect
        .shrink2(Vec2::new(POINT_RADIUS, POINT_RADIUS));
    state.plot_rect = Some(plot);
    let x_of = |v: f64| plot.left() + ((v - lo) / (hi - lo)) as f32 * plot.width();
    let v_of = |x: f32| lo + ((x - plot.left()) / plot.width()).clamp(0.0, 1.0) as f64 * (hi - lo);
    let y_of = |o: f64| plot.bottom() - o.clamp(0.0, 1.0) as f32 * plot.height();
    let o_of = |y: f32| ((plot.bottom() - y) / plot.height()).clamp(0.0, 1.0) as f64;

    painter.rect_filled(plot_response.rect, 2.0, Color32::from_gray(18));
    // Histogram, log counts, in the volume's own bins mapped onto the plot.
    let max_log = histogram
        .counts
        .iter()
        .map(|&c| ((c as f64) + 1.0).ln())
        .fold(0.0, f64::max)
        .max(1e-9);
    let bins = histogram.counts.len().max(1);
    let bin_width = (histogram.physical_max - histogram.physical_min) / bins as f64;
    for (i, &count) in histogram.counts.iter().enumerate() {
        if count == 0 {
            continue;
        }
        let v0 = histogram.physical_min + i as f64 * bin_width;
        let x0 = x_of(v0);
        let x1 = x_of(v0 + bin_width).max(x0 + 1.0);
        let h = (((count as f64) + 1.0).ln() / max_log) as f32 * plot.height();
        painter.rect_filled(
            Rect::from_min_max(
                Pos2::new(x0, plot.bottom() - h),
                Pos2::new(x1, plot.bottom()),
            ),
            0.0,
            Color32::from_gray(70),
        );
    }
    // Opacity polyline filled with the colour the function gives each value.
    let samples = 96;
    for s in 0..samples {
        let va = lo + (hi - lo) * s as f64 / samples as f64;
        let vb = lo + (hi - lo) * (s + 1) as f64 / samples as f64;
        let colour = to_rgb8(tf.color_at(0.5 * (va + vb))).gamma_multiply(0.45);
        let quad = vec![
            Pos2::new(x_of(va), plot.bottom()),
            Pos2::new(x_of(va), y_of(tf.opacity_at(va))),
            Pos2::new(x_of(vb), y_of(tf.opacity_at(vb))),
            Pos2::new(x_of(vb), plot.bottom()),
        ];
        painter.add(egui::Shape::convex_polygon(quad, colour, Stroke::NONE));
    }
    let line: Vec<Pos2> = tf
        .opacity
        .iter()
        .map(|p| Pos2::new(x_of(p.value), y_of(p.opacity)))
        .collect();
    painter.add(egui::Shape::line(
        line.clone(),
        Stroke::new(1.5, Color32::from_rgb(255, 200, 80)),
    ));
    for (i, p) in line.iter().enumerate() {
        let selected = state.selection == Selection::Opacity(i);
        painter.circle(
            *p,
            POINT_RADIUS,
            if selected {
                Color32::WHITE
            } else {
                Color32::from_rgb(255, 200, 80)
            },
            Stroke::new(1.0, Color32::BLACK),
        );
    }

    let nearest_point = |pos: Pos2| {
        line.iter()
            .enumerate()
            .map(|(i, p)| (i, p.distance(pos)))
            .filter(|(_, d)| *d <= POINT_RADIUS * 2.0)
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(i, _)| i)
    };
    if plot_response.drag_started_by(egui::PointerButton::Primary) {
        if let Some(pos) = plot_response.interact_pointer_pos() {
            state.dragging = nearest_point(pos).map(Selection::Opacity);
            if let Some(s) = state.dragging {
                state.selection = s;
            }
        }
    }
    if let (Some(Selection::Opacity(i)), true, Some(pos)) = (
        state.dragging,
        plot_response.dragged_by(egui::PointerButton::Primary),
        plot_response.interact_pointer_pos(),
    ) {
        if i < tf.opacity.len() {
            // Points keep their order: a point cannot pass its neighbours.
            let min = if i == 0 {
                lo.min(tf.opacity[0].value)
            } else {
                tf.opacity[i - 1].value
            };
            let max = if i + 1 == tf.opacity.len() {
                hi.max(tf.opacity[i].value)
            } else {
                tf.opacity[i + 1].value
            };
            let value = if i == 0 || i + 1 == tf.opacity.len() {
                tf.opacity[i].value
            } else {
                v_of(pos.x).clamp(min, max)
            };
            tf.opacity[i] = OpacityStop {
                value,
                opacity: o_of(pos.y),
            };
            changed = true;
        }
    }
    if plot_response.drag_stopped() {
        state.dragging = None;
    }
    if plot_response.clicked() {
        if let Some(pos) = plot_response.interact_pointer_pos() {
            match nearest_point(pos) {
                Some(i) => state.selection = Selection::Opacity(i),
                None => {
                    let value = v_of(pos.x);
                    let at = tf
                        .opacity
                        .iter()
                        .position(|p| p.value > value)
                        .unwrap_or(tf.opacity.len());
                    tf.opacity.insert(
                        at,
                        OpacityStop {
                            value,
                            opacity: o_of(pos.y),
                        },
                    );
                    state.selection = Selection::Opacity(at);
                    changed = true;
                }
            }
        }
    }
    if plot_response.secondary_clicked() {
        if let Some(i) = plot_response.interact_pointer_pos().and_then(nearest_point) {
            if tf.opacity.len() > 2 {
                tf.opacity.remove(i);
                state.selection = Selection::None;
                changed = true;
            }
        }
    }

    // Colour bar with stops.
    let (bar_response, bar_painter) =
        ui.allocate_painter(Vec2::new(width, 22.0), Sense::click_and_drag());
    let bar = Rect::from_min_max(
        Pos2::new(plot.left(), bar_response.rect.top() + 3.0),
        Pos2::new(plot.right(), bar_response.rect.bottom() - 7.0),
    );
    let steps = 128;
    for s in 0..steps {
        let v = lo + (hi - lo) * (s as f64 + 0.5) / steps as f64;
        let x0 = bar.left() + bar.width() * s as f32 / steps as f32;
        let x1 = bar.left() + bar.width() * (s + 1) as f32 / steps as f32 + 0.5;
        bar_painter.rect_filled(
            Rect::from_min_max(Pos2::new(x0, bar.top()), Pos2::new(x1, bar.bottom())),
            0.0,
            to_rgb8(tf.color_at(v)),
        );
    }
    let stop_positions: Vec<Pos2> = tf
        .color
        .iter()
        .map(|c| Pos2::new(x_of(c.value), bar.bottom() + 3.0))
        .collect();
    for (i, p) in stop_positions.iter().enumerate() {
        let selected = state.selection == Selection::Color(i);
        let tri = vec![
            *p + Vec2::new(0.0, -5.0),
            *p + Vec2::new(5.0, 4.0),
            *p + Vec2::new(-5.0, 4.0),
        ];
        bar_painter.add(egui::Shape::convex_polygon(
            tri,
            to_rgb8(tf.color[i].rgb),
            Stroke::new(
                1.0,
                if selected {
                    Color32::WHITE
                } else {
                    Color32::GRAY
                },
            ),
        ));
    }
    let nearest_stop = |pos: Pos2| {
        stop_positions
            .iter()
            .enumerate()
            .map(|(i, p)| (i, (p.x - pos.x).abs()))
            .filter(|(_, d)| *d <= 7.0)
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(i, _)| i)
    };
    if bar_response.drag_started_by(egui::PointerButton::Primary) {
        if let Some(pos) = bar_response.interact_pointer_pos() {
            state.dragging = nearest_stop(pos).map(Selection::Color);
            if let Some(s) = state.dragging {
                state.selection = s;
            }
        }
    }
    if let (Some(Selection::Color(i)), true, Some(pos)) = (
        state.dragging,
        bar_response.dragged_by(egui::PointerButton::Primary),
        bar_response.interact_pointer_pos(),
    ) {
        if i < tf.color.len() && i > 0 && i + 1 < tf.color.len() {
            let value = v_of(pos.x).clamp(tf.color[i - 1].value, tf.color[i + 1].value);
            tf.color[i].value = value;
            changed = true;
        }
    }
    if bar_response.drag_stopped() {
        state.dragging = None;
    }
    if bar_response.clicked() {
        if let Some(pos) = bar_response.interact_pointer_pos() {
            match nearest_stop(pos) {
                Some(i) => state.selection = Selection::Color(i),
                None => {
                    let value = v_of(pos.x);
                    let rgb = tf.color_at(value);
                    let at = tf
                        .color
                        .iter()
                        .position(|c| c.value > value)
                        .unwrap_or(tf.color.len());
                    tf.color.insert(at, ColorStop { value, rgb });
                    state.selection = Selection::Color(at);
                    changed = true;
                }
            }
        }
    }
    if bar_response.secondary_clicked() {
        if let Some(i) = bar_response.interact_pointer_pos().and_then(nearest_stop) {
            if tf.color.len() > 2 {
                tf.color.remove(i);
                state.selection = Selection::None;
                changed = true;
            }
        }
    }

    ui.horizontal(|ui| {
        ui.label(format!("{lo:.0}"));
        ui.with_layout(egui::Layout::right_to_left(egui::Align::Center), |ui| {
            ui.label(format!("{hi:.0} {unit}"));
        });
    });
    match state.selection {
        Selection::Opacity(i) if i < tf.opacity.len() => {
            ui.horizontal(|ui| {
                let p = &mut tf.opacity[i];
                let label = ui.label("Point");
                changed |= ui
                    .add(
                        egui::DragValue::new(&mut p.value)
                            .speed((hi - lo) / 500.0)
                            .suffix(format!(" {unit}")),
                    )
                    .labelled_by(label.id)
                    .changed();
                let label = ui.label("opacity");
                changed |= ui
                    .add(
                        egui::DragValue::new(&mut p.opacity)
                            .speed(0.005)
                            .range(0.0..=1.0),
                    )
                    .labelled_by(label.id)
                    .changed();
                if ui.button("Delete").clicked() && tf.opacity.len() > 2 {
                    tf.opacity.remove(i);
                    state.selection = Selection::None;
                    changed = true;
                }
            });
        }
        Selection::Color(i) if i < tf.color.len() => {
            ui.horizontal(|ui| {
                let label = ui.label("Colour stop");
                let stop = &mut tf.color[i];
                changed |= ui
                    .add(
                        egui::DragValue::new(&mut stop.value)
                            .speed((hi - lo) / 500.0)
                            .suffix(format!(" {unit}")),
                    )
                    .labelled_by(label.id)
                    .changed();
                let mut rgb = stop.rgb.map(|c| c as f32);
                if egui::color_picker::color_edit_button_rgb(ui, &mut rgb).changed() {
                    stop.rgb = rgb.map(|c| c as f64);
                    changed = true;
                }
                if ui.button("Delete").clicked() && tf.color.len() > 2 {
                    tf.color.remove(i);
                    state.selection = Selection::None;
                    changed = true;
                }
            });
        }
        _ => {
            ui.weak("Click: add point · drag: move · right-click: remove");
        }
    }
    if changed {
        sort_stops(tf);
    }
    changed
}

/// Keeps stops ordered by value (typed values may cross neighbours).
pub fn sort_stops(tf: &mut TransferFunction) {
    tf.opacity.sort_by(|a, b| a.value.total_cmp(&b.value));
    tf.color.sort_by(|a, b| a.value.total_cmp(&b.value));
}

/// Right-drag in the 3D view: shift every stop by `shift` and stretch about the centre of the
/// opacity ramp by `scale` (Slicer's volume-rendering "shift", plus width).
pub fn shift_and_scale(tf: &mut TransferFunction, shift: f64, scale: f64) {
    let (first, last) = match (tf.opacity.first(), tf.opacity.last()) {
        (Some(a), Some(b)) => (a.value, b.value),
        _ => return,
    };
    // The ramp centre: between the first and last points with non-zero opacity.
    let visible: Vec<f64> = tf
        .opacity
        .iter()
        .filter(|p| p.opacity > 0.0)
        .map(|p| p.value)
        .collect();
    let centre = match (visible.first(), visible.last()) {
        (Some(a), Some(b)) => 0.5 * (a + b),
        _ => 0.5 * (first + last),
    };
    let scale = scale.clamp(0.2, 5.0);
    let map = |v: f64| centre + (v - centre) * scale + shift;
    for p in &mut tf.opacity {
        p.value = map(p.value);
    }
    for c in &mut tf.color {
        c.value = map(c.value);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shift_moves_every_stop_and_keeps_order() {
        let mut tf = TransferFunction::preset("ct-bone").expect("preset");
        let before: Vec<f64> = tf.opacity.iter().map(|p| p.value).collect();
        shift_and_scale(&mut tf, 100.0, 1.0);
        for (b, a) in before.iter().zip(tf.opacity.iter()) {
            assert!((a.value - (b + 100.0)).abs() < 1e-9);
        }
        shift_and_scale(&mut tf, 0.0, 0.5);
        assert!(tf.opacity.windows(2).all(|w| w[0].value <= w[1].value));
        assert!(tf.validate().is_ok());
    }
}
