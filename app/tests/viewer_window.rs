//! Real-window smoke test: the `strata` binary opens its eframe window on an X server (Xvfb,
//! started here), draws the 3D view of a small phantom, and keeps running. The screen is read
//! back over the X protocol (x11rb, no screenshot tool needed) and must show the volume.
//!
//! Without Xvfb this test fails with the install hint; it never passes silently.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use x11rb::connection::Connection;
use x11rb::protocol::xproto::{ConnectionExt, ImageFormat};

const SCREEN: (u16, u16) = (1000, 680);

/// Kills what it holds when the test ends, pass or fail.
struct KillOnDrop(Child);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start_xvfb() -> (KillOnDrop, String) {
    // A display number unlikely to collide with a parallel run.
    let base = 60 + (std::process::id() % 200);
    for n in base..base + 20 {
        if Path::new(&format!("/tmp/.X11-unix/X{n}")).exists() || Path::new(&format!("/tmp/.X{n}-lock")).exists() {
            continue;
        }
        let display = format!(":{n}");
        let child = match Command::new("Xvfb")
            .args([display.as_str(), "-screen", "0", &format!("{}x{}x24", SCREEN.0, SCREEN.1), "-nolisten", "tcp"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
        {
            Ok(c) => c,
            Err(e) => panic!("cannot start Xvfb ({e}): install it with `apt-get install -y xvfb` (.ci/run does)"),
        };
        let guard = KillOnDrop(child);
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(15) {
            if x11rb::connect(Some(&display)).is_ok() {
                return (guard, display);
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
    panic!("Xvfb did not come up on any display from :{base}");
}

/// The root window as RGB rows.
fn screenshot(display: &str) -> Option<(usize, usize, Vec<[u8; 3]>)> {
    let (conn, screen_num) = x11rb::connect(Some(display)).ok()?;
    let screen = &conn.setup().roots[screen_num];
    let (w, h) = (screen.width_in_pixels, screen.height_in_pixels);
    let reply = conn.get_image(ImageFormat::Z_PIXMAP, screen.root, 0, 0, w, h, !0).ok()?.reply().ok()?;
    // Depth 24 in a 32-bit little-endian pixel: B, G, R, unused.
    let pixels = reply.data.chunks_exact(4).map(|p| [p[2], p[1], p[0]]).collect::<Vec<_>>();
    (pixels.len() == w as usize * h as usize).then_some((w as usize, h as usize, pixels))
}

fn save_png(path: &Path, w: usize, h: usize, pixels: &[[u8; 3]]) {
    let flat: Vec<u8> = pixels.iter().flatten().copied().collect();
    let _ = image::save_buffer(path, &flat, w as u32, h as u32, image::ExtendedColorType::Rgb8);
}

/// Lit pixels inside the 3D view of the default layout (3D over three slices, side panel on
/// the right): left of the side panel, above the slice row, clear of the title, orientation
/// marker and the warning text in its corners.
fn lit_fraction_in_3d_view(w: usize, h: usize, pixels: &[[u8; 3]]) -> f64 {
    let (x0, x1) = (w * 15 / 100, w * 55 / 100);
    let (y0, y1) = (h * 10 / 100, h * 50 / 100);
    let mut lit = 0usize;
    for y in y0..y1 {
        for x in x0..x1 {
            let [r, g, b] = pixels[y * w + x];
            if r.max(g).max(b) > 40 {
                lit += 1;
            }
        }
    }
    lit as f64 / ((x1 - x0) * (y1 - y0)) as f64
}

#[test]
fn the_viewer_window_shows_the_volume_and_keeps_running() {
    let dir = tempfile::tempdir().expect("temp dir");
    let store = dir.path().join("phantom.strata");
    strata_storage::phantom::Phantom::cube(64).write_store(&store, &Default::default()).expect("phantom store");
    let runtime_dir = dir.path().join("runtime");
    std::fs::create_dir_all(&runtime_dir).expect("runtime dir");

    let (_xvfb, display) = start_xvfb();
    let child = Command::new(env!("CARGO_BIN_EXE_strata"))
        .args(["view", &store.display().to_string(), "--fresh", "--exit-after", "150", "--layout", "conventional"])
        .arg("--window")
        .arg(format!("{}x{}", SCREEN.0, SCREEN.1))
        .env("DISPLAY", &display)
        .env_remove("WAYLAND_DISPLAY")
        .env("XDG_RUNTIME_DIR", &runtime_dir)
        .env("XDG_DATA_HOME", dir.path().join("data"))
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("launching strata");
    let mut viewer = KillOnDrop(child);

    let shot_path: PathBuf = std::env::temp_dir().join("strata-viewer-window.png");
    let start = Instant::now();
    let mut last_lit = 0.0;
    loop {
        if let Ok(Some(status)) = viewer.0.try_wait() {
            let mut stderr = String::new();
            if let Some(mut e) = viewer.0.stderr.take() {
                let _ = std::io::Read::read_to_string(&mut e, &mut stderr);
            }
            panic!("strata exited before showing the volume ({status}):\n{stderr}");
        }
        if let Some((w, h, pixels)) = screenshot(&display) {
            last_lit = lit_fraction_in_3d_view(w, h, &pixels);
            // The 64³ phantom's bone shell covers well over 5% of this region once drawn; the
            // empty (black) view or a window not yet mapped is ~0.
            if last_lit > 0.05 {
                save_png(&shot_path, w, h, &pixels);
                let distinct: std::collections::HashSet<[u8; 3]> = pixels.iter().copied().collect();
                assert!(distinct.len() > 50, "screen has only {} colours", distinct.len());
                break;
            }
            if start.elapsed() > Duration::from_secs(120) {
                save_png(&shot_path, w, h, &pixels);
            }
        }
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "no volume on screen after 120 s (lit fraction {last_lit:.3}); last screen in {}",
            shot_path.display()
        );
        std::thread::sleep(Duration::from_millis(500));
    }
    // Still alive after drawing: no crash on the first frames.
    std::thread::sleep(Duration::from_secs(1));
    assert!(matches!(viewer.0.try_wait(), Ok(None)), "strata died right after its first frames");
    eprintln!("viewer window screenshot: {} ({:.0}% of the 3D region lit)", shot_path.display(), last_lit * 100.0);
}
