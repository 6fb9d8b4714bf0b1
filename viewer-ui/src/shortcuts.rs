//! The keyboard and mouse of both viewers (issue 47): one table of what each key and gesture
//! does, each entry saying whether the browser page has it, the help window both draw from it
//! (F1, H or ?), and the key tests both viewers' key handling asks, so a key means the same
//! in either and the page's help lists only what the page does.

use egui::{InputState, Key};

/// One line of the help: the keys or gesture, what it does, and whether the page has it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shortcut {
    pub keys: &'static str,
    pub action: &'static str,
    pub in_page: bool,
}

const fn both(keys: &'static str, action: &'static str) -> Shortcut {
    Shortcut {
        keys,
        action,
        in_page: true,
    }
}

const fn desktop(keys: &'static str, action: &'static str) -> Shortcut {
    Shortcut {
        keys,
        action,
        in_page: false,
    }
}

/// Every shortcut, in the help's order.
pub const SHORTCUTS: &[Shortcut] = &[
    both("Left drag (3D)", "orbit"),
    desktop("Middle / Shift+left drag (3D)", "pan"),
    both("Wheel (3D)", "zoom"),
    desktop(
        "Right drag (3D)",
        "shift (sideways) / widen (up-down) the transfer function",
    ),
    desktop("Double-click (3D)", "reset view"),
    both(
        "A P L R S I",
        "standard views: anterior, posterior, left, right, superior, inferior",
    ),
    both("Home, 0", "reset view"),
    both("Left click / drag (slice)", "move the linked crosshair"),
    both("Wheel (slice)", "page slices"),
    desktop(
        "Up/Down, PgUp/PgDn",
        "page the focused slice (axial if none)",
    ),
    both("Right drag (slice)", "window (sideways) / level (up-down)"),
    both(
        "Ctrl+wheel, middle drag (slice)",
        "zoom, pan; double-click resets",
    ),
    desktop("Double-click view title", "focus the view (1×1)"),
    both("1 2 3", "layouts 1×1, 3D + 1×3, 2×2"),
    both("M", "cycle DVR / MIP / isosurface"),
    desktop("T", "target frame rate on/off"),
    both(
        "F12",
        "screenshot of the 3D view (in the page: a PNG download)",
    ),
    both(
        "Ctrl+Z, Ctrl+Shift+Z / Ctrl+Y",
        "undo, redo (TF, window, crop, measurements)",
    ),
    both(
        "Click (3D)",
        "move the crosshair to what is seen there (pick)",
    ),
    both(
        "Ruler / Angle / ROI tools",
        "measure on slices (drag, clicks)",
    ),
    desktop("Ruler / Angle tools (3D)", "measure in 3D (clicks)"),
    desktop("Ctrl+O", "open or import"),
    both("F1, H, ?", "this help"),
];

/// Which viewer's help: the page lists only what it has.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Viewer {
    Desktop,
    Page,
}

/// The shortcuts `viewer` has, in the help's order.
pub fn shortcuts_of(viewer: Viewer) -> impl Iterator<Item = &'static Shortcut> {
    SHORTCUTS
        .iter()
        .filter(move |s| viewer == Viewer::Desktop || s.in_page)
}

/// The title of the help window.
pub const HELP_TITLE: &str = "Keyboard and mouse";

/// The help window (open while `open`; its close button clears it), listing `viewer`'s
/// shortcuts with `footer` under them.
pub fn help_window(ctx: &egui::Context, open: &mut bool, viewer: Viewer, footer: egui::RichText) {
    egui::Window::new(HELP_TITLE)
        .open(open)
        .resizable(false)
        .show(ctx, |ui| {
            egui::Grid::new("help")
                .num_columns(2)
                .striped(true)
                .show(ui, |ui| {
                    for shortcut in shortcuts_of(viewer) {
                        ui.strong(shortcut.keys);
                        ui.label(shortcut.action);
                        ui.end_row();
                    }
                });
            ui.add_space(6.0);
            ui.label(footer);
        });
}

/// `key` pressed without Ctrl or Command (those are other shortcuts').
pub fn plain_key(input: &InputState, key: Key) -> bool {
    input.key_pressed(key) && !input.modifiers.ctrl && !input.modifiers.command
}

/// F1, H or ? pressed: the help opens or closes.
pub fn help_pressed(input: &InputState) -> bool {
    plain_key(input, Key::F1) || plain_key(input, Key::H) || input.key_pressed(Key::Questionmark)
}

/// F12 pressed: a screenshot of the 3D view.
pub fn screenshot_pressed(input: &InputState) -> bool {
    plain_key(input, Key::F12)
}

/// Undo (Ctrl+Z) and redo (Ctrl+Shift+Z or Ctrl+Y; Command on a Mac) pressed.
pub fn undo_redo_pressed(input: &InputState) -> (bool, bool) {
    let command = input.modifiers.command || input.modifiers.ctrl;
    let shift = input.modifiers.shift;
    (
        command && !shift && input.key_pressed(Key::Z),
        command && (shift && input.key_pressed(Key::Z) || input.key_pressed(Key::Y)),
    )
}

/// 1, 2 or 3 pressed: the layout it names (0: 1×1, 1: 3D + 1×3, 2: 2×2).
pub fn layout_pressed(input: &InputState) -> Option<usize> {
    [Key::Num1, Key::Num2, Key::Num3]
        .iter()
        .position(|key| plain_key(input, *key))
}

/// M pressed: the next render mode.
pub fn mode_cycle_pressed(input: &InputState) -> bool {
    plain_key(input, Key::M)
}

/// Home or 0 pressed: the view resets.
pub fn reset_view_pressed(input: &InputState) -> bool {
    plain_key(input, Key::Home) || plain_key(input, Key::Num0)
}

/// The render mode after `mode` in the M key's cycle.
pub fn next_mode(mode: strata_render::RenderMode) -> strata_render::RenderMode {
    use strata_render::RenderMode;
    match mode {
        RenderMode::Dvr => RenderMode::Mip,
        RenderMode::Mip => RenderMode::Isosurface,
        RenderMode::Isosurface => RenderMode::Dvr,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn input_with(key: Key, modifiers: egui::Modifiers) -> InputState {
        let raw = egui::RawInput {
            events: vec![
                egui::Event::ModifiersChanged(modifiers),
                egui::Event::Key {
                    key,
                    physical_key: None,
                    pressed: true,
                    repeat: false,
                    modifiers,
                },
            ],
            ..Default::default()
        };
        InputState::default().begin_pass(raw, false, 1.0, egui::InputOptions::default())
    }

    #[test]
    fn undo_and_redo_keys_are_told_apart_by_shift() {
        let ctrl = egui::Modifiers::CTRL;
        let ctrl_shift = egui::Modifiers::CTRL | egui::Modifiers::SHIFT;
        assert_eq!(undo_redo_pressed(&input_with(Key::Z, ctrl)), (true, false));
        assert_eq!(
            undo_redo_pressed(&input_with(Key::Z, ctrl_shift)),
            (false, true)
        );
        assert_eq!(undo_redo_pressed(&input_with(Key::Y, ctrl)), (false, true));
        let plain = egui::Modifiers::NONE;
        assert_eq!(
            undo_redo_pressed(&input_with(Key::Z, plain)),
            (false, false)
        );
        // A plain letter is a view's key, not with Ctrl held.
        assert!(help_pressed(&input_with(Key::H, plain)));
        assert!(!help_pressed(&input_with(Key::H, ctrl)));
        assert!(help_pressed(&input_with(Key::F1, plain)));
        assert!(screenshot_pressed(&input_with(Key::F12, plain)));
        assert_eq!(layout_pressed(&input_with(Key::Num2, plain)), Some(1));
        assert_eq!(layout_pressed(&input_with(Key::Num2, ctrl)), None);
    }

    #[test]
    fn the_pages_help_lists_only_what_the_page_has() {
        let page: Vec<_> = shortcuts_of(Viewer::Page).collect();
        let desktop: Vec<_> = shortcuts_of(Viewer::Desktop).collect();
        assert_eq!(desktop.len(), SHORTCUTS.len());
        assert!(page.len() < desktop.len());
        assert!(page.iter().all(|s| s.in_page));
        for keys in [
            "F1, H, ?",
            "Ctrl+Z, Ctrl+Shift+Z / Ctrl+Y",
            "F12",
            "A P L R S I",
        ] {
            assert!(page.iter().any(|s| s.keys == keys), "{keys}");
        }
        assert!(!page.iter().any(|s| s.keys == "Ctrl+O"));
        assert!(!page.iter().any(|s| s.keys == "Ruler / Angle tools (3D)"));
        let mut mode = strata_render::RenderMode::Dvr;
        for _ in 0..3 {
            mode = next_mode(mode);
        }
        assert_eq!(mode, strata_render::RenderMode::Dvr);
    }
}
