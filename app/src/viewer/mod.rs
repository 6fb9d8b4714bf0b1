//! The interactive viewer (`strata`, `strata view`): eframe window, layouts of the 3D view and
//! three slice views, side panels (transfer function, rendering, performance, screenshot,
//! information). Not for diagnostic use.
//!
//! Structure, as egui's demo app: a thin shell (`app.rs`: toolbar, status bar, layout,
//! shortcuts), views that own their state and draw themselves (`view3d.rs`, `slice_view.rs`),
//! panels likewise (`panels/`), dialogs (`dialogs.rs`), and the state they share
//! (`scene.rs`: the volume's data handles and the scene the user adjusts).
//!
//! Threads: the UI thread only draws and turns input into requests. The render thread
//! (`volume_session`), the slice reader (`slices`) and store preparation (`jobs`) do all GPU
//! work, disk reads and imports, and wake the UI when they have something new.

pub mod app;
pub mod colour_maps;
pub mod dialogs;
pub mod frames;
pub mod gpu_recovery;
pub mod history;
pub mod jobs;
pub mod measurements;
pub mod oblique;
pub mod oblique_view;
pub mod orientation;
pub mod overlay;
pub mod panels;
pub mod preferences;
pub mod scene;
pub mod screenshots;
pub mod slice_view;
pub mod slices;
pub(crate) mod sync;
pub mod tf_editor;
pub mod view3d;
pub mod volume_session;
pub mod widgets;

#[cfg(test)]
mod ui_tests;

use std::path::PathBuf;

use anyhow::Result;

pub use app::{Preferences, StrataApp, ViewerOptions};
pub use jobs::VolumeSource;

/// Opens the viewer window and runs until it is closed.
pub fn run(options: ViewerOptions) -> Result<()> {
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
            Ok(Box::new(app::EframeApp { app: StrataApp::new(cc.egui_ctx.clone(), preferences, options), persist }))
        }),
    )
    .map_err(|e| anyhow::anyhow!("the viewer window could not start: {e} (is a display available? `strata render` works headless)"))
}

/// The demo volume the viewer opens with no arguments.
pub fn demo_source() -> VolumeSource {
    VolumeSource::Demo {
        path: crate::cmd_sample::demo_store_path(),
        size: crate::cmd_sample::DEMO_SIZE,
    }
}

/// A path given on the command line.
pub fn path_source(path: PathBuf) -> VolumeSource {
    VolumeSource::Path(path)
}

/// A store served by `strata serve`, streamed (with the bearer token in `token_file`).
pub fn url_source(url: String, token_file: Option<PathBuf>) -> VolumeSource {
    VolumeSource::Url { url, token_file }
}
