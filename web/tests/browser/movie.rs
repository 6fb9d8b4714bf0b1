//! The orbit movie in the page (issue 47, web/src/orbit_movie.rs): the side panel's Orbit
//! movie, clicked with the fewest frames its slider offers, downloads one animated PNG
//! (`strata-orbit-MILLIS.png`) whose frames are the native renderer's frames of the link's
//! view at strata-viewer-ui's shared `orbit_azimuth`s, at the shared rate, looping; then the
//! view is back where the movie started. Cancel ends a movie without a download and puts the
//! view back.

use std::path::Path;
use std::time::{Duration, Instant};

use egui::{pos2, Rect};
use serde_json::json;
use strata_render::{compare_rgba8, CacheConfig, GpuContext, OffscreenRenderer};
use strata_viewer_ui::orbit_movie::{orbit_azimuth, OFFERED_ORBIT_FRAMES, ORBIT_FRAMES_PER_SECOND};
use strata_web::view_state::{Fragment, ViewState};

use crate::input::cdp::Cdp;
use crate::input::{close, open_page_capturing, wait_for_link};
use crate::PAGE_DEADLINE;

/// MIP, so that no frame refines (each frame is one drawn frame, as the native one), on the
/// page's sample at a small size; off-axis, so that no two of the movie's frames are alike.
const FRAGMENT: &str = "#mode=mip&preset=ct-soft-tissue&az=-60&el=10&zoom=1.1&volume=40\
     &size=48x48&layout=single&capture=1";

/// The lowest PSNR of a movie frame against the native frame at its azimuth: the bound of
/// `the_served_page_draws_the_view_its_link_names_as_the_native_renderer_does` for the same
/// sample and mode (same WGSL on SwiftShader and lavapipe: every movie frame measured identical,
/// 2026-12-07, rmse 0; drivers may round f32 trilinear weights differently, moving single 8-bit
/// steps). The next azimuth's frame is far below it (24-28 dB, checked below).
const MIN_PSNR_DB: f64 = 40.0;

/// The movie control `name` (`frames`, `start`, `cancel`) in page CSS pixels.
fn control(page: &mut Cdp, name: &str) -> Rect {
    page.wait_for(
        &format!("the side panel to place the movie's {name} control"),
        PAGE_DEADLINE,
        |page| {
            let v = page.evaluate(
                "(() => { const c = document.getElementById('strata-canvas'); \
                 const r = c.getBoundingClientRect(); \
                 return [r.left, r.top, c.dataset.movieControls ?? ''] })()",
            );
            let (left, top) = (v[0].as_f64()? as f32, v[1].as_f64()? as f32);
            let numbers: Vec<f32> = v[2]
                .as_str()?
                .split(';')
                .find_map(|entry| entry.strip_prefix(&format!("{name}:")))?
                .split(',')
                .filter_map(|n| n.parse().ok())
                .collect();
            let [x, y, w, h] = numbers[..] else {
                return None;
            };
            Some(Rect::from_min_size(
                pos2(x + left, y + top),
                egui::vec2(w, h),
            ))
        },
    )
}

/// A click at `at` with the press and the release back to back: egui takes a press held
/// longer than its click time (0.8 s) as a drag's start, and one SwiftShader frame between them
/// may exceed it (as segment.rs's clicks).
fn click(page: &mut Cdp, at: egui::Pos2) {
    let (x, y) = (at.x.round() as f64, at.y.round() as f64);
    page.mouse_move(x, y, false);
    for (kind, buttons) in [("mousePressed", 1), ("mouseReleased", 0)] {
        page.command(
            "Input.dispatchMouseEvent",
            json!({ "type": kind, "x": x, "y": y, "button": "left", "buttons": buttons, "clickCount": 1 }),
        );
    }
    page.next_frames();
}

/// The page's `data-movie`: `run=R;frames=K/N;state=…`.
fn movie_state(page: &mut Cdp) -> Option<String> {
    page.evaluate("document.getElementById('strata-canvas')?.dataset.movie ?? null")
        .as_str()
        .map(str::to_owned)
}

fn wait_for_movie(folder: &Path) -> Vec<u8> {
    let until = Instant::now() + PAGE_DEADLINE;
    loop {
        let done = std::fs::read_dir(folder)
            .expect("download folder")
            .filter_map(Result::ok)
            .map(|e| e.path())
            .find(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("strata-orbit-") && n.ends_with(".png"))
            });
        if let Some(path) = done {
            return std::fs::read(&path).expect("reading the download");
        }
        assert!(
            Instant::now() < until,
            "no movie was downloaded into {} within {PAGE_DEADLINE:?}",
            folder.display()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A downloaded movie, decoded.
struct Movie {
    size: [u32; 2],
    /// 0: it loops.
    plays: u32,
    /// Each frame's delay (numerator, denominator in seconds) and RGBA (opaque: the movie is
    /// RGB over black).
    frames: Vec<((u16, u16), Vec<u8>)>,
}

fn decode_movie(bytes: &[u8]) -> Movie {
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes))
        .read_info()
        .expect("the movie is a PNG");
    let animation = reader
        .info()
        .animation_control
        .expect("the movie is an animated PNG");
    let size = [reader.info().width, reader.info().height];
    let mut frames = Vec::new();
    for _ in 0..animation.num_frames {
        let mut rgb = vec![0; reader.output_buffer_size().expect("size")];
        let info = reader.next_frame(&mut rgb).expect("a frame's pixels");
        assert_eq!(info.color_type, png::ColorType::Rgb, "RGB over black");
        rgb.truncate(info.buffer_size());
        let control = *reader.info().frame_control().expect("a frame control");
        let rgba = rgb
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect();
        frames.push(((control.delay_num, control.delay_den), rgba));
    }
    Movie {
        size,
        plays: animation.num_plays,
        frames,
    }
}

/// Premultiplied RGBA over black, as the movie stores it.
fn over_black(rgba: &[u8]) -> Vec<u8> {
    rgba.chunks_exact(4)
        .flat_map(|p| [p[0], p[1], p[2], 255])
        .collect()
}

#[test]
fn the_orbit_movie_downloads_the_native_frames_at_the_shared_azimuths_as_one_animated_png() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let downloads = tempfile::tempdir().expect("download folder");
    // Tall enough for the side panel's sections above the movie's controls.
    let (mut page, _server, frames) = open_page_capturing(FRAGMENT, scratch.path(), [900, 1000]);
    frames
        .recv_timeout(PAGE_DEADLINE)
        .expect("the page posts its drawn frame");
    page.browser_command(
        "Browser.setDownloadBehavior",
        json!({ "behavior": "allow", "downloadPath": downloads.path().to_str().expect("utf-8") }),
    );
    // The fewest frames the slider offers: a click at its left end.
    let slider = control(&mut page, "frames");
    click(&mut page, pos2(slider.left() + 1.0, slider.center().y));
    let frames_wanted = *OFFERED_ORBIT_FRAMES.start();
    // The slider's number is narrower now: the button's place once the page drew it.
    let start = control(&mut page, "start");
    println!("movie: frames slider {slider:?}, start button {start:?}");
    click(&mut page, start.center());
    let making = page.wait_for("the movie to start", PAGE_DEADLINE, |page| {
        movie_state(page).filter(|s| !s.contains("state=idle"))
    });
    println!("movie: {making}");
    let movie = wait_for_movie(downloads.path());
    let ended = movie_state(&mut page).expect("the movie's state");
    assert!(ended.ends_with("state=downloaded"), "{ended}");

    let view = Fragment::parse(FRAGMENT).expect("fragment").view;
    // The view is put back where the movie started.
    wait_for_link(&mut page, "the view back at the movie's start", |v| {
        close(v.azimuth_deg, view.azimuth_deg)
    });

    // Cancel: a movie of many frames (a click near the right end of the slider's rail, egui's
    // default 100 points wide), cancelled as soon as it shows its progress, ends without a
    // download and puts the view back.
    let slider = control(&mut page, "frames");
    click(&mut page, pos2(slider.left() + 95.0, slider.center().y));
    let start = control(&mut page, "start");
    click(&mut page, start.center());
    let cancel = control(&mut page, "cancel");
    let making = movie_state(&mut page).expect("the movie's state");
    let total: u32 = making
        .split(';')
        .find_map(|part| part.strip_prefix("frames="))
        .and_then(|frames| frames.split_once('/')?.1.parse().ok())
        .unwrap_or_else(|| panic!("no frame count in {making}"));
    assert!(making.ends_with("state=making") && total >= 100, "{making}");
    click(&mut page, cancel.center());
    let cancelled = page.wait_for("the movie to be cancelled", PAGE_DEADLINE, |page| {
        movie_state(page).filter(|s| s.ends_with("state=cancelled"))
    });
    println!("movie: {cancelled}");
    wait_for_link(&mut page, "the view back after Cancel", |v| {
        close(v.azimuth_deg, view.azimuth_deg)
    });
    let downloaded = std::fs::read_dir(downloads.path())
        .expect("download folder")
        .count();
    assert_eq!(downloaded, 1, "a cancelled movie downloads nothing");
    let console = page.console();
    drop(page);

    let Movie {
        size,
        plays,
        frames: decoded,
    } = decode_movie(&movie);
    let [width, height] = view.image_size.expect("the link fixes the size");
    assert_eq!(size, [width, height]);
    assert_eq!(plays, 0, "an orbit loops");
    assert_eq!(decoded.len() as u32, frames_wanted, "{console}");

    // Each frame against the native renderer's frame of the same view at the shared azimuth.
    let gpu = GpuContext::headless().expect("a Vulkan adapter (lavapipe)");
    let volume = view.sample_volume().expect("sample volume");
    let mut renderer = OffscreenRenderer::new(
        &gpu,
        &volume,
        &view.transfer_function(),
        0,
        CacheConfig {
            // The f32 brick format the browser has to use (no 16-bit normalised on WebGPU).
            force_fallback_format: true,
            ..CacheConfig::default()
        },
    )
    .expect("native renderer");
    let settings = view.settings(&volume.geometry, width, height);
    let native: Vec<Vec<u8>> = (0..frames_wanted)
        .map(|i| {
            let turned = ViewState {
                azimuth_deg: orbit_azimuth(view.azimuth_deg, i, frames_wanted),
                ..view.clone()
            };
            let frame = renderer
                .render(&gpu, &volume, &turned.camera(&volume.geometry), &settings)
                .expect("native frame");
            over_black(&frame.rgba)
        })
        .collect();
    for (i, ((delay, rgba), expected)) in decoded.iter().zip(&native).enumerate() {
        assert_eq!(*delay, (1, ORBIT_FRAMES_PER_SECOND as u16), "frame {i}");
        let lit = rgba.chunks(4).filter(|p| p[..3] != [0, 0, 0]).count();
        assert!(
            lit > (width * height / 10) as usize,
            "frame {i} is nearly empty ({lit} lit)"
        );
        let comparison = compare_rgba8(rgba, expected).expect("same size");
        println!("movie frame {i}: page (SwiftShader) vs native (lavapipe): {comparison:?}");
        assert!(
            comparison.psnr_db >= MIN_PSNR_DB,
            "movie frame {i} differs from the native frame at its azimuth: {comparison:?}"
        );
        // The comparison can fail: the next azimuth's frame is far from this one.
        let next = &native[(i + 1) % native.len()];
        let apart = compare_rgba8(rgba, next).expect("same size");
        println!("movie frame {i} vs the next azimuth's native frame: {apart:?}");
        assert!(apart.psnr_db < MIN_PSNR_DB, "frame {i}: {apart:?}");
    }
}
