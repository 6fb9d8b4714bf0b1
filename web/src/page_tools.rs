//! The page's undo and redo, keyboard shortcuts and help, and screenshot download (wasm32
//! only; issue 47), each the desktop's through strata-viewer-ui:
//! - undo and redo keep the link's [`ViewState`] without its navigation
//!   (strata_viewer_ui::history: the desktop's rules, a drag one step), so whatever the link
//!   learns to hold later is undone too, and the segmentation's edits in the order made
//!   (segment_editor.rs); Ctrl+Z, Ctrl+Shift+Z and Ctrl+Y, and the toolbar's
//!   Undo and Redo, disabled when there is nothing to undo or redo;
//! - the keys are the shared table's (strata_viewer_ui::shortcuts), handled only while no text
//!   field has focus, and the help (F1, H, ?) lists only what the page has;
//! - F12 and the toolbar's Screenshot download the 3D view's frame as PNG at the size it was
//!   drawn, named as the desktop names its screenshots (`strata-3d-MILLIS.png`).
//!
//! The page publishes what the browser tests cannot see otherwise on its canvas:
//! `data-windows` (the open windows: `help`) and `data-readout` (the slice readout under the
//! pointer: `VIEW:I,J,K:VALUE`).

use strata_viewer_ui::history::{edits_of, restore_edits, History, Stepped};
use strata_viewer_ui::shortcuts::{self, Viewer};
use wasm_bindgen::{JsCast, JsValue};

use crate::segment_editor::{PageSegmentation, SegmentStep};
use crate::view_state::{Layout, ViewState};

/// What the toolbar or the keys asked for this frame, done after the views drew.
#[derive(Clone, Copy, Debug, Default)]
struct Asked {
    undo: bool,
    redo: bool,
    screenshot: bool,
}

/// The page's history, help window and the requests of its keys and toolbar.
#[derive(Default)]
pub struct PageTools {
    /// Made on the first frame the view is drawn (what the page opened with is no step); the
    /// segmentation's edits are steps in it too (segment_editor.rs).
    history: Option<History<ViewState, SegmentStep>>,
    help_open: bool,
    asked: Asked,
    /// The object URL of the last download, revoked when the next is made (revoking it at
    /// once may cancel the download).
    last_download_url: Option<String>,
    /// The last download's problem, shown in the toolbar.
    download_error: Option<String>,
    /// An undo or redo of a segmentation edit was done this frame.
    edit_stepped: bool,
}

impl PageTools {
    /// The shared keys the page has, while no text field takes the keys: the help, undo and
    /// redo, the screenshot, the layouts, the mode cycle and the view's reset. Returns true
    /// when the camera moved (the view's reset).
    pub fn keys(&mut self, ctx: &egui::Context, view: &mut ViewState) -> bool {
        if ctx.egui_wants_keyboard_input() {
            return false;
        }
        if ctx.input(shortcuts::help_pressed) {
            self.help_open = !self.help_open;
        }
        let (undo, redo) = ctx.input(shortcuts::undo_redo_pressed);
        self.asked.undo |= undo;
        self.asked.redo |= redo;
        self.asked.screenshot |= ctx.input(shortcuts::screenshot_pressed);
        if let Some(layout) = ctx.input(shortcuts::layout_pressed) {
            view.layout = [Layout::Single, Layout::ThreeDOverSlices, Layout::FourUp][layout];
        }
        if ctx.input(shortcuts::mode_cycle_pressed) {
            view.mode = shortcuts::next_mode(view.mode);
        }
        if ctx.input(shortcuts::reset_view_pressed) {
            let home = ViewState::default();
            view.azimuth_deg = home.azimuth_deg;
            view.elevation_deg = home.elevation_deg;
            view.zoom = home.zoom;
            view.pan = home.pan;
            return true;
        }
        false
    }

    /// The toolbar's Undo, Redo, Screenshot and help buttons.
    pub fn toolbar(&mut self, ui: &mut egui::Ui) {
        let (can_undo, can_redo) = self
            .history
            .as_ref()
            .map_or((false, false), |h| (h.can_undo(), h.can_redo()));
        if ui
            .add_enabled(can_undo, egui::Button::new("Undo"))
            .on_hover_text("Undo the last TF, window, crop, light or segmentation change (Ctrl+Z)")
            .clicked()
        {
            self.asked.undo = true;
        }
        if ui
            .add_enabled(can_redo, egui::Button::new("Redo"))
            .on_hover_text("Redo (Ctrl+Shift+Z, Ctrl+Y)")
            .clicked()
        {
            self.asked.redo = true;
        }
        if ui
            .button("Screenshot")
            .on_hover_text("Download the 3D view as PNG (F12)")
            .clicked()
        {
            self.asked.screenshot = true;
        }
        if ui
            .button("?")
            .on_hover_text("Keyboard and mouse (F1)")
            .clicked()
        {
            self.help_open = !self.help_open;
        }
        if let Some(error) = &self.download_error {
            ui.colored_label(egui::Color32::LIGHT_RED, error);
        }
    }

    /// Once a frame after the views: an asked undo or redo gives the view to show (its
    /// navigation as it is); otherwise a change with no gesture in progress becomes a step.
    /// `drawn`: the page shows its volume (before, the volume's own choices are no steps).
    /// The segmentation's edits since the last frame become steps, and its section's Undo and
    /// Redo are these.
    pub fn step_history(
        &mut self,
        view: &ViewState,
        drawn: bool,
        gesture: bool,
        mut segmentation: Option<&mut PageSegmentation>,
    ) -> Option<ViewState> {
        if let Some(seg) = segmentation.as_deref_mut() {
            let (undo, redo) = seg.take_asked();
            self.asked.undo |= undo;
            self.asked.redo |= redo;
        }
        let (undo, redo) = (self.asked.undo, self.asked.redo);
        (self.asked.undo, self.asked.redo) = (false, false);
        if !drawn {
            return None;
        }
        let now = edits_of(view);
        let history = self
            .history
            .get_or_insert_with(|| History::new(now.clone()));
        // A link without a window gets the slice views' once they show (a layout with slices
        // chosen later): that is no edit to undo.
        let first_window = ViewState {
            window: None,
            ..now.clone()
        };
        if history.committed().window.is_none()
            && now.window.is_some()
            && *history.committed() == first_window
        {
            history.rebase(now.clone());
        }
        if let Some(seg) = segmentation.as_deref_mut() {
            for step in seg.take_new_steps() {
                // A view change made before the edit is a step before it.
                history.observe(&now, gesture);
                history.push_edit(step);
            }
        }
        let stepped = if undo {
            history.undo(&now, |step| {
                segmentation
                    .as_deref_mut()
                    .is_some_and(|seg| seg.undo_step(step))
            })
        } else if redo {
            history.redo(|step| {
                segmentation
                    .as_deref_mut()
                    .is_some_and(|seg| seg.redo_step(step))
            })
        } else {
            history.observe(&now, gesture);
            Stepped::Nothing
        };
        if let Some(seg) = segmentation {
            if !history.can_redo() {
                // Every page step of the layer's redo is gone (a new step clears them all).
                seg.forget_redo();
            }
            seg.set_page_history(history.can_undo(), history.can_redo());
        }
        match stepped {
            Stepped::State(snapshot) => Some(restore_edits(view, &snapshot)),
            Stepped::Edit => {
                // The labels changed after the panel drew this frame: draw another.
                self.edit_stepped = true;
                None
            }
            Stepped::Nothing => None,
        }
    }

    /// True once after an undo or redo of a segmentation edit (the frame must be drawn again).
    pub fn take_edit_stepped(&mut self) -> bool {
        std::mem::take(&mut self.edit_stepped)
    }

    /// Another volume: its history starts again.
    pub fn forget_history(&mut self) {
        self.history = None;
    }

    /// True once when a screenshot was asked for.
    pub fn take_screenshot_request(&mut self) -> bool {
        std::mem::take(&mut self.asked.screenshot)
    }

    /// The help window (the page's shortcuts only), and the open windows published.
    pub fn help(&mut self, ctx: &egui::Context) {
        let footer = egui::RichText::new("Not for diagnostic use: research and education only.")
            .color(egui::Color32::from_rgb(255, 170, 60));
        shortcuts::help_window(ctx, &mut self.help_open, Viewer::Page, footer);
        crate::canvas_attributes::set("data-windows", if self.help_open { "help" } else { "" });
    }

    /// Downloads `png` as `name` (a Blob behind an anchor with `download=`).
    pub fn download(&mut self, png: &[u8], name: &str) {
        self.download_error = match download_blob(png, name) {
            Ok(url) => {
                if let Some(old) = self.last_download_url.replace(url) {
                    let _ = web_sys::Url::revoke_object_url(&old);
                }
                None
            }
            Err(e) => Some(format!("the screenshot could not be downloaded: {e:?}")),
        };
    }

    /// A screenshot that could not be made (shown in the toolbar).
    pub fn download_failed(&mut self, problem: String) {
        self.download_error = Some(problem);
    }
}

/// The 3D view's screenshot file name, as the desktop names its screenshots
/// (viewer/src/screenshots.rs: `strata-WHAT-MILLIS.png`).
pub fn screenshot_name() -> String {
    format!("strata-3d-{}.png", js_sys::Date::now() as u64)
}

/// Hands `bytes` to the browser as a PNG download named `name`; the object URL made.
fn download_blob(bytes: &[u8], name: &str) -> Result<String, JsValue> {
    let document = web_sys::window()
        .and_then(|w| w.document())
        .ok_or_else(|| JsValue::from_str("no document"))?;
    let parts = js_sys::Array::of1(&js_sys::Uint8Array::from(bytes));
    let options = web_sys::BlobPropertyBag::new();
    options.set_type("image/png");
    let blob = web_sys::Blob::new_with_u8_array_sequence_and_options(&parts, &options)?;
    let url = web_sys::Url::create_object_url_with_blob(&blob)?;
    let anchor: web_sys::HtmlAnchorElement = document.create_element("a")?.dyn_into()?;
    anchor.set_href(&url);
    anchor.set_download(name);
    anchor.click();
    Ok(url)
}

/// Publishes the slice readout under the pointer (`VIEW:I,J,K:VALUE`) for the browser tests.
pub fn publish_readout(view: &str, index: [u32; 3], value: &str) {
    let [i, j, k] = index;
    crate::canvas_attributes::set("data-readout", &format!("{view}:{i},{j},{k}:{value}"));
}
