//! `strata-viewer`: the interactive viewer as a library (issue 47; `strata` and `strata view`
//! open it through `run`): eframe window, layouts of the 3D view and three slice views, side
//! panels (transfer function, rendering, performance, screenshot, information). Not for
//! diagnostic use.
//!
//! Besides the viewer, what the `strata` command line and the benchmarks (`strata-bench`) share
//! with it: writing frames and orbit movies and the command line's size and transfer-function
//! options (`export`), the flythrough's camera path (`camera_path`), the demo volume
//! (`sample`), where a volume comes from (`volume_location`), a PACS server and its retrieval
//! (`pacs_client`) and how an error is told (`error_report`). The command line's modules
//! (`app/src/cmd_*.rs`) use these; the viewer never uses a command module.
//!
//! Structure, as egui's demo app: a thin shell (`app.rs`: toolbar, status bar, layout,
//! shortcuts), views that own their state and draw themselves (`view3d.rs`, `slice_view.rs`),
//! panels likewise (`panels/`), dialogs (`dialogs.rs`), and the state they share
//! (`scene.rs`: the volume's data handles and the scene the user adjusts). The editable label
//! layer, its tools and journal are `segmentation.rs` (issue 52).
//!
//! Threads: the UI thread only draws and turns input into requests. The render thread
//! (`volume_session`), the slice reader (`slices`) and store preparation (`jobs`) do all GPU
//! work, disk reads and imports, and wake the UI when they have something new.

pub mod adaptive_view;
pub mod app;
pub mod camera_path;
// Orientation and colour maps live in strata-slices, shared with the browser viewer.
pub use strata_slices::colour_maps;
pub mod dialogs;
pub mod error_report;
pub mod export;
pub mod exports;
pub mod file_chooser;
pub mod frames;
pub mod gpu_recovery;
pub mod history;
pub mod jobs;
pub mod links;
pub mod oblique;
pub mod oblique_view;
pub use strata_slices::orientation;
pub mod overlay;
pub mod overlay_3d;
pub mod pacs_client;
pub mod pacs_dialog;
pub mod pacs_thumbnail;
pub mod panels;
pub mod preferences;
pub mod sample;
pub mod scene;
pub mod screenshots;
pub mod segmentation;
pub mod session_restore;
pub mod slice_view;
pub mod slices;
pub(crate) mod sync;
pub mod view3d;
pub mod volume_location;
pub mod volume_session;
pub mod widgets;

/// The UI tests (egui_kittest): kept under tests/ui/, compiled here for private access.
#[cfg(test)]
#[path = "../tests/ui/mod.rs"]
mod ui_tests;

/// The real PACS fixture (Orthanc on loopback) of the integration tests, shared by path so that
/// the viewer's tests use the same one (pacs_dialog.rs, tests/ui/opening.rs).
#[cfg(test)]
#[path = "../../app/tests/common/orthanc.rs"]
#[allow(dead_code)]
pub(crate) mod orthanc_fixture;

use std::path::PathBuf;

use anyhow::Result;

pub use app::{Preferences, StrataApp, ViewerOptions};
pub use jobs::VolumeToOpen;

/// Opens the viewer window and runs until it is closed. Unless this process is already the
/// supervised child (or `STRATA_NO_SUPERVISOR=1`), the window runs in a child process that is
/// restarted with its saved session when its UI device is lost or it crashes
/// (session_restore.rs); this process then only waits, and exits with the child's code.
pub fn run(options: ViewerOptions) -> Result<()> {
    use session_restore::{SESSION_FILE_ENV, SUPERVISED_ENV};
    let supervised = std::env::var_os(SUPERVISED_ENV).is_some();
    if !supervised && std::env::var("STRATA_NO_SUPERVISOR").map_or(true, |v| v != "1") {
        let session_file = if options.persist_settings {
            session_restore::session_path(&options.import_folder)
        } else {
            std::env::temp_dir().join(format!("strata-session-{}.json", std::process::id()))
        };
        let exe = std::env::current_exe().map_err(|e| {
            anyhow::anyhow!("cannot find the strata executable to start the viewer: {e}")
        })?;
        let code = session_restore::supervise(
            session_restore::RestartPolicy::default(),
            |restore| {
                let mut child = std::process::Command::new(&exe);
                child
                    .args(std::env::args_os().skip(1))
                    .env(SUPERVISED_ENV, "1")
                    .env(SESSION_FILE_ENV, &session_file);
                if restore {
                    child.env(session_restore::RESTORE_ENV, "1");
                }
                session_restore::end_with_parent(&mut child);
                child.status()
            },
            |line| eprintln!("{line}"),
        )
        .map_err(|e| anyhow::anyhow!("cannot start the viewer process: {e}"))?;
        if !options.persist_settings {
            let _ = std::fs::remove_file(&session_file);
        }
        std::process::exit(code);
    }
    let session_file = std::env::var_os(SESSION_FILE_ENV)
        .map(PathBuf::from)
        .or_else(|| {
            options
                .persist_settings
                .then(|| session_restore::session_path(&options.import_folder))
        });
    let restore = std::env::var_os(session_restore::RESTORE_ENV).is_some();
    let native = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default()
            .with_title("Strata — not for diagnostic use")
            .with_inner_size([options.window_size[0], options.window_size[1]])
            .with_min_inner_size([640.0, 420.0]),
        // --fresh: eframe restores window geometry from its store whatever `persist_window`
        // says, so a fresh run gets a store of its own that starts empty.
        persist_window: options.persist_settings,
        persistence_path: (!options.persist_settings)
            .then(|| std::env::temp_dir().join(format!("strata-fresh-{}", std::process::id()))),
        // The volume renders on its own device (see volume_session.rs); eframe's only draws the UI.
        ..Default::default()
    };
    let persist = options.persist_settings;
    eframe::run_native(
        "strata",
        native,
        Box::new(move |cc| {
            let preferences: Preferences = if persist {
                cc.storage.and_then(|s| eframe::get_value(s, eframe::APP_KEY)).unwrap_or_default()
            } else {
                Preferences::default()
            };
            // The saved session of a restarted child: its preferences now, its scene once the
            // volume has opened.
            let saved = restore.then_some(session_file.as_deref()).flatten().and_then(|path| {
                session_restore::SavedSession::read(path)
                    .map_err(|e| eprintln!("strata: {e}; starting without it"))
                    .ok()
            });
            let preferences = saved.as_ref().map_or(preferences, |s| s.preferences.clone());
            let ui_device = cc.wgpu_render_state.as_ref().map(|rs| session_restore::UiDeviceWatch::install(&rs.device));
            let mut app = StrataApp::new(cc.egui_ctx.clone(), preferences, options);
            app.pending_restore = saved;
            Ok(Box::new(app::EframeApp {
                app,
                persist,
                autosave: session_file.map(session_restore::Autosave::new),
                ui_device,
            }))
        }),
    )
    .map_err(|e| anyhow::anyhow!("the viewer window could not start: {e} (is a display available? `strata render` works headless)"))
}

/// The demo volume the viewer opens with no arguments.
pub fn demo_source() -> VolumeToOpen {
    VolumeToOpen::Demo {
        path: sample::demo_store_path(),
        size: sample::DEMO_SIZE,
    }
}

/// A path given on the command line.
pub fn path_source(path: PathBuf) -> VolumeToOpen {
    VolumeToOpen::Path(path)
}

/// A store served by `strata serve`, streamed (with the bearer token in `token_file`).
pub fn url_source(url: String, token_file: Option<PathBuf>) -> VolumeToOpen {
    VolumeToOpen::Url {
        url,
        token_file,
        token: None,
    }
}
