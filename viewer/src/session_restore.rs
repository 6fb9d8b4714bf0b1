//! Surviving the loss of eframe's own device (the one that draws the UI).
//!
//! The 3D renderer's device is ours and is rebuilt in place (gpu_recovery.rs). eframe's is
//! not: egui-wgpu 0.37 installs no device-lost callback and has no way to recreate its
//! device, and wgpu reports every later operation on a lost device to the lost callback
//! only, so the window would freeze silently. What this module does instead:
//!
//! - **Autosave.** The session (volume, 3D camera, transfer function, window/level, iso
//!   value, crop, clip plane, crosshair, measurements, preferences) is written to
//!   `last-session.json` beside the data folder at most every [`AUTOSAVE_EVERY`] while it
//!   changes, atomically (temporary file, then rename), so a crash of any kind loses at most
//!   that much.
//! - **Detection.** [`UiDeviceWatch`] is eframe's device-lost callback; when it fires the
//!   viewer writes the session once more and exits with [`UI_DEVICE_LOST_EXIT`].
//! - **Supervision.** `strata view` runs the window in a child process ([`supervise`]); when
//!   the child ends with that code, or crashes (a panic, a signal), the parent starts it
//!   again with [`RESTORE_ENV`] naming the saved session, and the new window opens the same
//!   volume and puts the session back ([`SavedSession::apply`]). A child that keeps failing
//!   is not restarted forever ([`RestartPolicy`]).
//!
//! An overlay is not reopened (it is reopened from its panel); everything else is.

use std::path::{Path, PathBuf};
use std::process::ExitStatus;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use strata_render::{CropBox, TransferFunction};

use glam::DVec3;

use super::oblique::ObliquePlane;
use super::preferences::Preferences;
use super::scene::{Scene, Window};
use super::sync::lock_ignoring_poison;
use super::view3d::OrbitCamera;
use strata_viewer_ui::crop_clip::ClipSettings;
use strata_viewer_ui::measurements::{Measurement, Measurements};

/// The child's exit code after its UI device was lost (EX_TEMPFAIL: "try again").
pub const UI_DEVICE_LOST_EXIT: i32 = 75;
/// Set by the supervisor in its child: where the child autosaves its session.
pub const SESSION_FILE_ENV: &str = "STRATA_SESSION_FILE";
/// Set in a restarted child: put the session of [`SESSION_FILE_ENV`] back.
pub const RESTORE_ENV: &str = "STRATA_RESTORE_SESSION";
/// Set in every supervised child, so it does not supervise itself again.
pub const SUPERVISED_ENV: &str = "STRATA_SUPERVISED";
/// How often, at most, a changing session is written.
pub const AUTOSAVE_EVERY: Duration = Duration::from_secs(2);
const FORMAT_VERSION: u32 = 1;

/// Where the session is autosaved: beside the stores of the data folder.
pub fn session_path(data_folder: &Path) -> PathBuf {
    data_folder
        .parent()
        .unwrap_or(data_folder)
        .join("last-session.json")
}

/// Everything of a session that a restarted viewer puts back.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SavedSession {
    pub version: u32,
    /// The store's folder or URL (what the volume was opened as).
    pub location: String,
    pub preferences: Preferences,
    pub orbit: OrbitCamera,
    pub cursor: [f64; 3],
    pub window: Window,
    pub transfer_function: TransferFunction,
    pub tf_source: TransferFunction,
    pub iso_value: f64,
    pub crop: CropBox,
    pub clip: ClipSettings,
    pub measurements: Vec<Measurement>,
    /// The oblique view's orientation once turned (issue 47: it came back axial). Absent in
    /// sessions saved before it was kept, and while the plane is axial.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub oblique: Option<SavedOblique>,
}

/// An oblique plane's orientation (its centre follows the crosshair).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SavedOblique {
    pub right: [f64; 3],
    pub down: [f64; 3],
    pub extent_mm: f64,
}

impl SavedOblique {
    pub fn of(plane: &ObliquePlane) -> Self {
        SavedOblique {
            right: plane.right.to_array(),
            down: plane.down.to_array(),
            extent_mm: plane.extent_mm,
        }
    }

    /// The plane, centred at `centre` (the crosshair's patient position).
    pub fn plane(&self, centre: DVec3) -> ObliquePlane {
        ObliquePlane {
            centre,
            right: DVec3::from_array(self.right),
            down: DVec3::from_array(self.down),
            extent_mm: self.extent_mm,
        }
    }
}

impl SavedSession {
    pub fn capture(
        location: &Path,
        preferences: &Preferences,
        scene: &Scene,
        orbit: &OrbitCamera,
    ) -> Self {
        SavedSession {
            version: FORMAT_VERSION,
            location: location.display().to_string(),
            preferences: preferences.clone(),
            orbit: *orbit,
            cursor: scene.cursor,
            window: scene.window,
            transfer_function: scene.transfer_function.clone(),
            tf_source: scene.tf_source.clone(),
            iso_value: scene.iso_value,
            crop: scene.crop,
            clip: scene.clip,
            measurements: scene.measurements.items.clone(),
            oblique: None,
        }
    }

    /// With the oblique view's plane (None: never turned, axial).
    pub fn with_oblique(mut self, plane: Option<&ObliquePlane>) -> Self {
        self.oblique = plane.map(SavedOblique::of);
        self
    }

    /// What [`SavedSession::apply`] does not reach, put back after it: the preset the panel
    /// highlights, named by the restored function's own preset (issue 47: it named MR, the
    /// preference of a fresh open, while the function was ct-soft-tissue), and the oblique
    /// view's plane.
    pub fn apply_view(&self, preset: &mut String, oblique: &mut Option<ObliquePlane>) {
        *preset = if TransferFunction::PRESETS.contains(&self.tf_source.name.as_str()) {
            self.tf_source.name.clone()
        } else {
            self.preferences.preset.clone()
        };
        *oblique = self.oblique.map(|o| o.plane(DVec3::ZERO));
    }

    /// Puts the session back into a freshly opened volume's scene and camera. Only for the
    /// same volume: false (and nothing changed) for another one.
    pub fn apply(&self, location: &Path, scene: &mut Scene, orbit: &mut OrbitCamera) -> bool {
        if self.location != location.display().to_string() {
            return false;
        }
        *orbit = self.orbit;
        scene.cursor = self.cursor;
        scene.window = self.window;
        scene.transfer_function = self.transfer_function.clone();
        scene.tf_source = self.tf_source.clone();
        scene.iso_value = self.iso_value;
        scene.crop = self.crop;
        scene.clip = self.clip;
        scene.measurements = Measurements::with_items(self.measurements.clone());
        true
    }

    pub fn to_json(&self) -> String {
        // Plain data (no maps with non-string keys): serialising cannot fail.
        serde_json::to_string_pretty(self).unwrap_or_default()
    }

    /// Writes atomically: a crash mid-write leaves the previous file.
    pub fn write(json: &str, path: &Path) -> std::io::Result<()> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        let partial = path.with_extension(format!("json.{}.partial", std::process::id()));
        std::fs::write(&partial, json)?;
        std::fs::rename(&partial, path)
    }

    pub fn read(path: &Path) -> Result<Self, SavedSessionError> {
        let text = std::fs::read_to_string(path).map_err(|source| SavedSessionError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let saved: SavedSession =
            serde_json::from_str(&text).map_err(|source| SavedSessionError::Damaged {
                path: path.to_path_buf(),
                source,
            })?;
        if saved.version != FORMAT_VERSION {
            return Err(SavedSessionError::Version {
                path: path.to_path_buf(),
                version: saved.version,
            });
        }
        Ok(saved)
    }
}

/// Why a saved session was not restored (the viewer then starts without it).
#[derive(Debug, thiserror::Error)]
pub enum SavedSessionError {
    #[error("cannot read the saved session {}: {source}", .path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("the saved session {} is damaged: {source}", .path.display())]
    Damaged {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("the saved session {} has format {version}, this viewer reads {reads}", .path.display(), reads = FORMAT_VERSION)]
    Version { path: PathBuf, version: u32 },
}

/// Writes the session when it changed, at most every [`AUTOSAVE_EVERY`].
pub struct Autosave {
    pub path: PathBuf,
    last_json: String,
    last_write: Option<Instant>,
}

impl Autosave {
    pub fn new(path: PathBuf) -> Self {
        Autosave {
            path,
            last_json: String::new(),
            last_write: None,
        }
    }

    /// Called every UI frame; `force` writes now (before an exit). Returns whether it wrote.
    pub fn tick(&mut self, session: Option<&SavedSession>, force: bool) -> bool {
        let Some(session) = session else {
            return false;
        };
        if !force
            && self
                .last_write
                .is_some_and(|t| t.elapsed() < AUTOSAVE_EVERY)
        {
            return false;
        }
        let json = session.to_json();
        if json == self.last_json {
            return false;
        }
        self.last_write = Some(Instant::now());
        match SavedSession::write(&json, &self.path) {
            Ok(()) => {
                self.last_json = json;
                true
            }
            Err(e) => {
                // Not fatal: the session goes on, only a restart could not restore it.
                eprintln!(
                    "strata: cannot autosave the session to {}: {e}",
                    self.path.display()
                );
                false
            }
        }
    }
}

/// eframe's device-lost callback: the reason, once the UI's device is gone.
#[derive(Clone, Default)]
pub struct UiDeviceWatch {
    lost: Arc<Mutex<Option<String>>>,
}

impl UiDeviceWatch {
    pub fn install(device: &wgpu::Device) -> Self {
        let watch = UiDeviceWatch::default();
        let on_lost = watch.clone();
        device.set_device_lost_callback(move |reason, message| {
            on_lost.record_lost(format!("{reason:?}: {message}"));
        });
        watch
    }

    pub fn record_lost(&self, detail: String) {
        lock_ignoring_poison(&self.lost).get_or_insert(detail);
    }

    pub fn lost(&self) -> Option<String> {
        lock_ignoring_poison(&self.lost).clone()
    }
}

/// The window must not outlive its supervisor (killed, or ended by Ctrl-C or SIGTERM): on
/// Linux the kernel sends the child SIGTERM when the supervisor ends, and the child's own
/// handler ends it as Ctrl-C would.
pub fn end_with_parent(child: &mut std::process::Command) {
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::process::CommandExt;
        // SAFETY: the closure runs in the forked child before exec and only calls prctl,
        // which is async-signal-safe and touches no memory of ours.
        unsafe {
            child.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                Ok(())
            });
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = child;
}

/// How a supervised child ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ChildOutcome {
    /// Closed by the user (or any exit of its own): the supervisor ends with its code.
    Finished(i32),
    /// Its UI device was lost; it saved the session.
    UiDeviceLost,
    /// A panic or a signal: the autosave is at most [`AUTOSAVE_EVERY`] old.
    Crashed(String),
}

/// Rust's exit code of a panicking main thread.
const PANIC_EXIT: i32 = 101;

pub fn classify_exit(status: ExitStatus) -> ChildOutcome {
    match status.code() {
        Some(UI_DEVICE_LOST_EXIT) => ChildOutcome::UiDeviceLost,
        Some(PANIC_EXIT) => ChildOutcome::Crashed("it panicked".into()),
        Some(code) => ChildOutcome::Finished(code),
        None => ChildOutcome::Crashed(signal_text(status)),
    }
}

#[cfg(unix)]
fn signal_text(status: ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match status.signal() {
        Some(signal) => format!("it was killed by signal {signal}"),
        None => "it ended without an exit code".into(),
    }
}

#[cfg(not(unix))]
fn signal_text(_status: ExitStatus) -> String {
    "it ended without an exit code".into()
}

/// At most `max_restarts` restarts within `window`: a child that fails faster than that
/// (a crash at start-up, a driver that loses every device) is not restarted forever.
#[derive(Clone, Copy, Debug)]
pub struct RestartPolicy {
    pub max_restarts: usize,
    pub window: Duration,
}

impl Default for RestartPolicy {
    fn default() -> Self {
        RestartPolicy {
            max_restarts: 3,
            window: Duration::from_secs(120),
        }
    }
}

/// Runs the child until it finishes on its own, restarting it (with `restore` true) after a
/// lost UI device or a crash, within `policy`. `spawn` starts one child and waits for it.
/// Returns the exit code for the supervisor.
pub fn supervise(
    policy: RestartPolicy,
    mut spawn: impl FnMut(bool) -> std::io::Result<ExitStatus>,
    mut report: impl FnMut(&str),
) -> std::io::Result<i32> {
    let mut restarts: Vec<Instant> = Vec::new();
    let mut restore = false;
    loop {
        let status = spawn(restore)?;
        let why = match classify_exit(status) {
            ChildOutcome::Finished(code) => return Ok(code),
            ChildOutcome::UiDeviceLost => "the window's GPU device was lost".to_string(),
            ChildOutcome::Crashed(how) => format!("the viewer stopped ({how})"),
        };
        restarts.retain(|t| t.elapsed() < policy.window);
        if restarts.len() >= policy.max_restarts {
            report(&format!(
                "strata: {why}; not restarting: {} restarts within {} s",
                restarts.len(),
                policy.window.as_secs()
            ));
            return Ok(status.code().unwrap_or(1));
        }
        restarts.push(Instant::now());
        report(&format!(
            "strata: {why}; restarting the viewer with the saved session"
        ));
        restore = true;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::process::Command;

    fn scene() -> Scene {
        let tf = TransferFunction::preset("ct-bone").expect("preset");
        Scene {
            cursor: [10.0, 20.0, 30.0],
            window: Window::new(40.0, 400.0),
            colour_map: Default::default(),
            transfer_function: tf.clone(),
            tf_source: tf,
            iso_value: 300.0,
            crop: CropBox::default(),
            clip: ClipSettings::default(),
            measurements: Measurements::default(),
        }
    }

    /// Issue 47: after a crash restore the preset highlight named MR while the function was
    /// ct-soft-tissue, and the oblique tilt came back axial.
    #[test]
    fn a_restored_session_names_its_preset_and_keeps_the_oblique_tilt() {
        let dir = tempfile::tempdir().expect("tempdir");
        let location = dir.path().join("mr.strata");
        let mut soft = scene();
        soft.transfer_function = TransferFunction::preset("ct-soft-tissue").expect("preset");
        soft.tf_source = soft.transfer_function.clone();
        let preferences = Preferences {
            preset: "ct-soft-tissue".into(),
            ..Preferences::default()
        };
        let tilted = ObliquePlane::axial(DVec3::ZERO, 120.0).rotated(0.3, 0.7);
        let saved = SavedSession::capture(&location, &preferences, &soft, &OrbitCamera::default())
            .with_oblique(Some(&tilted));
        let path = session_path(&dir.path().join("stores"));
        SavedSession::write(&saved.to_json(), &path).expect("write");
        let read = SavedSession::read(&path).expect("read");
        assert_eq!(read, saved);

        // The reopened volume first chose its own preset (an MR's) and an axial plane.
        let mut fresh = scene();
        let mut orbit = OrbitCamera::default();
        let mut preset = "mr-default".to_string();
        let mut oblique = None;
        assert!(read.apply(&location, &mut fresh, &mut orbit));
        read.apply_view(&mut preset, &mut oblique);
        assert_eq!(
            preset, "ct-soft-tissue",
            "the highlight names the restored function"
        );
        assert_eq!(fresh.transfer_function.name, "ct-soft-tissue");
        let oblique = oblique.expect("the tilted plane");
        assert_eq!(oblique.right, tilted.right);
        assert_eq!(oblique.down, tilted.down);
        assert_eq!(oblique.extent_mm, 120.0);
        assert_ne!(oblique.down, DVec3::Y, "not axial");

        // A session saved before the plane was kept reads, with no plane.
        let old = saved.to_json().replace("\"oblique\"", "\"ignored\"");
        let old: SavedSession = serde_json::from_str(&old).expect("reads");
        assert_eq!(old.oblique, None);
    }

    #[test]
    fn a_saved_session_comes_back_exactly_through_its_file_and_only_for_its_volume() {
        let dir = tempfile::tempdir().expect("tempdir");
        let location = dir.path().join("ct.strata");
        let mut edited = scene();
        edited.window = Window::new(-600.0, 1500.0);
        edited.iso_value = 123.25;
        edited.cursor = [1.5, 2.5, 3.5];
        edited.crop.max[2] = 0.75;
        edited.clip = ClipSettings {
            enabled: true,
            axis: 2,
            flip: true,
            fraction: 0.3,
        };
        edited.transfer_function = TransferFunction::preset("ct-lung").expect("preset");
        let orbit = OrbitCamera {
            azimuth_deg: 211.0,
            elevation_deg: -12.5,
            zoom: 2.25,
            pan: [0.1, -0.2],
            orthographic: true,
        };
        let preferences = Preferences {
            preset: "ct-lung".into(),
            adaptive_sampling: true,
            adaptive_epsilon: 0.02,
            ..Preferences::default()
        };
        let saved = SavedSession::capture(&location, &preferences, &edited, &orbit);
        let path = session_path(&dir.path().join("stores"));
        SavedSession::write(&saved.to_json(), &path).expect("write");
        let read = SavedSession::read(&path).expect("read");
        assert_eq!(read, saved);
        // The restarted window takes its preferences from here (viewer/mod.rs).
        assert!(read.preferences.adaptive_sampling);
        assert_eq!(read.preferences.adaptive_epsilon, 0.02);

        let mut fresh = scene();
        let mut fresh_orbit = OrbitCamera::default();
        assert!(!read.apply(
            &dir.path().join("other.strata"),
            &mut fresh,
            &mut fresh_orbit
        ));
        assert_eq!(fresh, scene(), "another volume's session changes nothing");
        assert!(read.apply(&location, &mut fresh, &mut fresh_orbit));
        assert_eq!(fresh_orbit, orbit);
        assert_eq!(fresh, edited);
    }

    #[test]
    fn the_light_comes_back_with_the_session_and_an_older_session_has_the_headlight() {
        use super::super::preferences::render_lighting;
        use strata_render::{LightDirection, ShadowMode};
        use strata_viewer_ui::lighting::LightPrefs;

        let dir = tempfile::tempdir().expect("tempdir");
        let location = dir.path().join("ct.strata");
        let preferences = Preferences {
            light: LightPrefs {
                headlight: false,
                azimuth_deg: 75.5,
                elevation_deg: -20.25,
                intensity: 1.5,
                ambient: 0.125,
                shadows: ShadowMode::Cache,
                shadow_step: 0.75,
                occlusion: true,
                occlusion_radius_mm: 7.5,
                scattering: true,
                scattering_g: -0.25,
                scattering_blend: 0.625,
            },
            ..Preferences::default()
        };
        let saved = SavedSession::capture(&location, &preferences, &scene(), &Default::default());
        let path = session_path(&dir.path().join("stores"));
        SavedSession::write(&saved.to_json(), &path).expect("write");
        let read = SavedSession::read(&path).expect("read");
        assert_eq!(read.preferences.light, preferences.light);
        assert_eq!(
            render_lighting(&read.preferences),
            render_lighting(&preferences),
            "the restored session renders with the same light"
        );

        // A session written before the light controls: its preferences have no "light".
        let mut json: serde_json::Value = serde_json::from_str(&saved.to_json()).expect("json");
        json["preferences"]
            .as_object_mut()
            .expect("preferences object")
            .remove("light")
            .expect("the light is saved under preferences.light");
        std::fs::write(&path, json.to_string()).expect("write old");
        let old = SavedSession::read(&path).expect("an old session still loads");
        assert_eq!(old.preferences.light, LightPrefs::default());
        let lit = render_lighting(&old.preferences);
        assert_eq!(lit.light.direction, LightDirection::Headlight);
        assert!(lit.light.is_default(), "today's look: {:?}", lit.light);
        assert_eq!(lit.shadows.mode, ShadowMode::Off);
        assert_eq!(lit.shading, Some(strata_render::Shading::default()));
        assert_eq!((lit.occlusion, lit.scattering), (None, None));

        // A session written with the first light controls (shadows off/exact), before
        // occlusion and scattering: its light loads as saved, the new effects off.
        let mut json: serde_json::Value = serde_json::from_str(&saved.to_json()).expect("json");
        let light = json["preferences"]["light"]
            .as_object_mut()
            .expect("light object");
        for new in [
            "occlusion",
            "occlusion_radius_mm",
            "scattering",
            "scattering_g",
            "scattering_blend",
        ] {
            light.remove(new).expect("each new field is saved");
        }
        light.insert("shadows".into(), "Exact".into());
        std::fs::write(&path, json.to_string()).expect("write old");
        let old = SavedSession::read(&path).expect("a first-light-controls session loads");
        assert_eq!(
            old.preferences.light,
            LightPrefs {
                shadows: ShadowMode::Exact,
                occlusion: false,
                occlusion_radius_mm: LightPrefs::default().occlusion_radius_mm,
                scattering: false,
                scattering_g: LightPrefs::default().scattering_g,
                scattering_blend: LightPrefs::default().scattering_blend,
                ..preferences.light
            }
        );
        let lit = render_lighting(&old.preferences);
        assert_eq!(lit.shadows.mode, ShadowMode::Exact);
        assert_eq!((lit.occlusion, lit.scattering), (None, None));
    }

    #[test]
    fn a_damaged_or_foreign_session_file_is_an_error_naming_it() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("last-session.json");
        std::fs::write(&path, "{\"version\": 1, \"location\": ").expect("write");
        let e = SavedSession::read(&path).expect_err("damaged").to_string();
        assert!(
            e.contains("damaged") && e.contains("last-session.json"),
            "{e}"
        );
        let saved = SavedSession::capture(
            &path,
            &Preferences::default(),
            &scene(),
            &Default::default(),
        );
        let mut json: serde_json::Value = serde_json::from_str(&saved.to_json()).expect("json");
        json["version"] = 99.into();
        std::fs::write(&path, json.to_string()).expect("write");
        let e = SavedSession::read(&path).expect_err("version").to_string();
        assert!(e.contains("format 99"), "{e}");
    }

    #[test]
    fn autosave_writes_changes_only_and_not_more_often_than_its_interval() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("last-session.json");
        let mut autosave = Autosave::new(path.clone());
        let mut s = scene();
        let take = |s: &Scene| {
            SavedSession::capture(&path, &Preferences::default(), s, &Default::default())
        };
        assert!(!autosave.tick(None, false), "no volume: nothing to save");
        assert!(autosave.tick(Some(&take(&s)), false));
        assert!(
            !autosave.tick(Some(&take(&s)), true),
            "unchanged: not written"
        );
        s.iso_value = 5.0;
        assert!(
            !autosave.tick(Some(&take(&s)), false),
            "changed within the interval: later"
        );
        assert!(autosave.tick(Some(&take(&s)), true), "forced (before exit)");
        assert_eq!(
            SavedSession::read(&path).expect("read").iso_value,
            5.0,
            "the file holds the newest session"
        );
    }

    #[test]
    fn the_lost_callback_of_a_real_device_is_seen_by_the_watch() {
        let ctx = strata_render::GpuContext::headless().unwrap_or_else(|e| panic!("{e}"));
        let watch = UiDeviceWatch::install(&ctx.device);
        assert_eq!(watch.lost(), None);
        ctx.device.destroy();
        // wgpu calls the callback once the destruction is processed.
        let _ = ctx.device.poll(wgpu::PollType::wait_indefinitely());
        assert!(watch.lost().is_some_and(|d| d.contains("Destroyed")));
    }

    /// Real child processes (`sh -c 'exit N'`): what each exit means to the supervisor.
    fn exit_with(code: &str) -> std::io::Result<ExitStatus> {
        Command::new("sh").args(["-c", code]).status()
    }

    #[test]
    fn the_supervisor_restarts_after_a_lost_device_or_a_crash_with_the_session_and_stops_on_exit() {
        // Device lost, then a panic, then the user closes the window (exit 0).
        let script = [
            format!("exit {UI_DEVICE_LOST_EXIT}"),
            "exit 101".into(),
            "exit 0".into(),
        ];
        let mut started = Vec::new();
        let mut lines = Vec::new();
        let code = supervise(
            RestartPolicy::default(),
            |restore| {
                started.push(restore);
                exit_with(&script[started.len() - 1])
            },
            |line| lines.push(line.to_string()),
        )
        .expect("children run");
        assert_eq!(code, 0);
        assert_eq!(
            started,
            vec![false, true, true],
            "restarts restore the session"
        );
        assert!(lines[0].contains("GPU device was lost"), "{lines:?}");
        assert!(lines[1].contains("panicked"), "{lines:?}");
        // A plain error exit of the viewer (a bad file: exit 1) is its answer, not a crash.
        let code = supervise(RestartPolicy::default(), |_| exit_with("exit 1"), |_| {})
            .expect("children run");
        assert_eq!(code, 1);
    }

    #[test]
    fn a_child_that_keeps_crashing_is_restarted_a_bounded_number_of_times() {
        let mut runs = 0;
        let mut lines = Vec::new();
        let code = supervise(
            RestartPolicy {
                max_restarts: 2,
                window: Duration::from_secs(60),
            },
            |_| {
                runs += 1;
                // Killed by a signal, as a segfaulting driver would be.
                exit_with("kill -9 $$")
            },
            |line| lines.push(line.to_string()),
        )
        .expect("children run");
        assert_eq!(runs, 3, "the first run and two restarts");
        assert_eq!(code, 1);
        assert!(lines
            .last()
            .is_some_and(|l| l.contains("not restarting") && l.contains("signal 9")));
    }
}
