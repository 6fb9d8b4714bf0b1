//! Choosing a file or folder as a desktop does: the system dialog through rfd's desktop portal
//! first (on its own thread: it blocks whoever calls it), and when no portal answers an
//! egui-drawn dialog (egui_file: pure Rust, no system package) in the window itself.
//!
//! Issue 36: without a portal there was no chooser at all and paths had to be typed. rfd says
//! nothing about why it returned no path; a portal that is missing (no session bus, or no
//! service on it) answers at once, while a person cancelling takes longer, so an empty answer
//! within [`NO_PORTAL_WITHIN`] counts as "no portal" and opens the egui dialog instead.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::sync::lock_ignoring_poison;

/// What is chosen.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ChooserKind {
    OpenFile,
    OpenFolder,
    SaveFile,
}

/// An empty answer from the portal sooner than this is taken as "no portal answered".
pub const NO_PORTAL_WITHIN: Duration = Duration::from_millis(400);

/// How a chooser ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Chosen {
    Path(PathBuf),
    /// The user closed it without a choice.
    Nothing,
}

/// Whether an empty answer of the system dialog after `elapsed` means no portal answered (the
/// egui dialog opens) rather than a person's cancel.
pub fn no_portal_answered(elapsed: Duration) -> bool {
    elapsed < NO_PORTAL_WITHIN
}

/// Whether a portal can answer at all: xdg-desktop-portal is reached over the session bus, so
/// without one rfd cannot show anything and the egui dialog opens at once.
pub fn session_bus_present() -> bool {
    std::env::var_os("DBUS_SESSION_BUS_ADDRESS").is_some_and(|v| !v.is_empty())
        || std::env::var_os("XDG_RUNTIME_DIR").is_some_and(|d| Path::new(&d).join("bus").exists())
}

/// What the system dialog's thread hands back: the path chosen, and how long it was open.
type PortalAnswer = Arc<Mutex<Option<(Option<PathBuf>, Duration)>>>;

/// One file or folder being chosen.
pub struct FileChooser {
    kind: ChooserKind,
    title: String,
    start: PathBuf,
    default_name: Option<String>,
    /// The system dialog's thread fills this when it closes: the path, and how long it took.
    portal: Option<PortalAnswer>,
    fallback: Option<egui_file::FileDialog>,
}

impl FileChooser {
    /// Starts a chooser: the system dialog when a session bus is there, else the egui one.
    /// `start` is the folder it opens in (or a file in it); `default_name` the file name a
    /// save dialog suggests.
    pub fn start(
        ctx: &egui::Context,
        kind: ChooserKind,
        title: &str,
        start: &Path,
        default_name: Option<&str>,
    ) -> Self {
        let mut chooser = FileChooser {
            kind,
            title: title.to_string(),
            start: start_folder(start),
            default_name: default_name.map(str::to_string),
            portal: None,
            fallback: None,
        };
        if !session_bus_present() || !chooser.start_portal(ctx) {
            chooser.open_fallback();
        }
        chooser
    }

    /// True while the egui dialog is drawn (tests).
    #[cfg(test)]
    pub fn shows_egui_dialog(&self) -> bool {
        self.fallback.as_ref().is_some_and(|d| d.visible())
    }

    fn start_portal(&mut self, ctx: &egui::Context) -> bool {
        let slot = Arc::new(Mutex::new(None));
        let thread_slot = slot.clone();
        let (kind, title, start, name) = (
            self.kind,
            self.title.clone(),
            self.start.clone(),
            self.default_name.clone(),
        );
        let ctx = ctx.clone();
        let spawned = std::thread::Builder::new()
            .name("strata-file-dialog".into())
            .spawn(move || {
                let began = Instant::now();
                let mut dialog = rfd::FileDialog::new().set_title(&title);
                if start.is_dir() {
                    dialog = dialog.set_directory(&start);
                }
                if let Some(name) = &name {
                    dialog = dialog.set_file_name(name);
                }
                let chosen = match kind {
                    ChooserKind::OpenFile => dialog.pick_file(),
                    ChooserKind::OpenFolder => dialog.pick_folder(),
                    ChooserKind::SaveFile => dialog.save_file(),
                };
                *lock_ignoring_poison(&thread_slot) = Some((chosen, began.elapsed()));
                ctx.request_repaint();
            });
        if spawned.is_err() {
            return false;
        }
        self.portal = Some(slot);
        true
    }

    fn open_fallback(&mut self) {
        let dialog = match self.kind {
            ChooserKind::OpenFile => egui_file::FileDialog::open_file(),
            ChooserKind::OpenFolder => egui_file::FileDialog::select_folder(),
            ChooserKind::SaveFile => egui_file::FileDialog::save_file(),
        };
        let mut dialog = dialog
            .title(&self.title)
            .initial_path(self.start.clone())
            .id(egui::Id::unique((
                "strata file chooser",
                self.title.as_str(),
            )));
        if let Some(name) = &self.default_name {
            dialog = dialog.default_filename(name.clone());
        }
        dialog.open();
        self.fallback = Some(dialog);
    }

    /// Called every UI pass while choosing: draws the egui dialog if it is the one open, and
    /// returns how the choice ended once it has.
    pub fn poll(&mut self, ctx: &egui::Context) -> Option<Chosen> {
        if let Some(slot) = &self.portal {
            let answer = lock_ignoring_poison(slot).take()?;
            self.portal = None;
            return match answer {
                (Some(path), _) => Some(Chosen::Path(path)),
                (None, elapsed) if no_portal_answered(elapsed) => {
                    self.open_fallback();
                    None
                }
                (None, _) => Some(Chosen::Nothing),
            };
        }
        let dialog = self.fallback.as_mut()?;
        dialog.show(ctx);
        match dialog.state() {
            egui_file::State::Selected => Some(
                dialog
                    .path()
                    .map_or(Chosen::Nothing, |p| Chosen::Path(p.to_path_buf())),
            ),
            egui_file::State::Open => None,
            egui_file::State::Cancelled | egui_file::State::Closed => Some(Chosen::Nothing),
        }
    }
}

/// The folder a chooser opens in: `start` if it is one, else its parent if that is one, else
/// the current folder.
fn start_folder(start: &Path) -> PathBuf {
    // A store is a folder, but its inside (packs, index) is nothing to choose from: start
    // beside it, where the user's scans and stores are (issue 47: Open… opened inside the
    // store shown).
    if start.is_dir() && !super::jobs::is_store(start) {
        return start.to_path_buf();
    }
    match start.parent() {
        Some(parent) if parent.is_dir() => parent.to_path_buf(),
        _ => std::env::current_dir().unwrap_or_default(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The egui dialog's icons (egui_file draws folders as U+1F5C0 and files as U+1F5CB) are
    /// glyphs of the viewer's fonts, not empty boxes.
    #[test]
    fn the_egui_dialogs_folder_and_file_icons_are_in_the_fonts() {
        let ctx = egui::Context::default();
        // A frame loads the fonts; its texture upload is not needed here.
        ctx.run_ui(Default::default(), |_| {})
            .textures_delta
            .clear();
        let font = egui::FontId::proportional(14.0);
        for icon in ['🗀', '🗋', '📁'] {
            assert!(
                ctx.fonts_mut(|f| f.has_glyph(&font, icon)),
                "no glyph for {icon} (U+{:04X})",
                icon as u32
            );
        }
    }

    #[test]
    fn a_chooser_starts_beside_a_store_not_inside_it() {
        let dir = tempfile::tempdir().expect("temp dir");
        let store = dir.path().join("scan.strata");
        std::fs::create_dir_all(&store).expect("store folder");
        std::fs::write(store.join("STRATA-STORE"), b"").expect("marker");
        let folder = dir.path().join("scans");
        std::fs::create_dir_all(&folder).expect("folder");
        assert_eq!(start_folder(&store), dir.path());
        assert_eq!(start_folder(&folder), folder);
        assert_eq!(start_folder(&folder.join("ct.nii.gz")), folder);
    }

    #[test]
    fn an_instant_empty_answer_means_no_portal_and_a_slow_one_a_cancel() {
        assert!(no_portal_answered(Duration::from_millis(20)));
        assert!(!no_portal_answered(Duration::from_secs(3)));
    }

    /// A chooser whose system dialog has already answered nothing after `elapsed`.
    fn answered(elapsed: Duration) -> FileChooser {
        FileChooser {
            kind: ChooserKind::SaveFile,
            title: "Save".into(),
            start: std::env::temp_dir(),
            default_name: Some("tf.json".into()),
            portal: Some(Arc::new(Mutex::new(Some((None, elapsed))))),
            fallback: None,
        }
    }

    fn pass(ctx: &egui::Context, chooser: &mut FileChooser, escape: bool) -> Option<Chosen> {
        let mut input = egui::RawInput::default();
        if escape {
            input.events.push(egui::Event::Key {
                key: egui::Key::Escape,
                physical_key: None,
                pressed: true,
                repeat: false,
                modifiers: egui::Modifiers::NONE,
            });
        }
        let mut outcome = None;
        let mut output = ctx.run_ui(input, |ui| outcome = chooser.poll(ui.ctx()));
        // Nothing draws here: the font atlas's upload is dropped on purpose.
        output.textures_delta.clear();
        outcome
    }

    /// Issue 36: where no portal answers, the egui dialog opens in the window (and Escape
    /// closes it with nothing chosen); a person's slow cancel of the system dialog is final.
    #[test]
    fn no_portal_opens_the_egui_dialog_and_a_cancel_of_the_system_one_is_final() {
        let ctx = egui::Context::default();
        let mut chooser = answered(Duration::from_millis(5));
        assert_eq!(pass(&ctx, &mut chooser, false), None);
        assert!(
            chooser.shows_egui_dialog(),
            "no dialog after the portal's silence"
        );
        assert_eq!(pass(&ctx, &mut chooser, false), None, "it stays open");
        assert_eq!(pass(&ctx, &mut chooser, true), Some(Chosen::Nothing));

        let mut cancelled = answered(Duration::from_secs(4));
        assert_eq!(pass(&ctx, &mut cancelled, false), Some(Chosen::Nothing));
        assert!(!cancelled.shows_egui_dialog());
    }

    #[test]
    fn the_chooser_opens_in_the_files_folder_or_the_folder_itself() {
        let dir = tempfile::tempdir().expect("temp dir");
        assert_eq!(start_folder(dir.path()), dir.path());
        assert_eq!(start_folder(&dir.path().join("tf.json")), dir.path());
        let nowhere = start_folder(Path::new("/no/such/folder/tf.json"));
        assert!(nowhere.is_dir() || nowhere.as_os_str().is_empty());
    }
}
