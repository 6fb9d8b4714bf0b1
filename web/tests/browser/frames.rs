//! A served 4-D store in the page (issue 47, web/src/frames.rs): opened at `frame=2`, the
//! page's axial slice equals, byte for byte, the desktop's assembler on frame 2 read by the
//! desktop's client (`RemoteSource::frame_source`) and differs from frame 0's; Play advances
//! the shown frame (cine, driven by the page's frames: the test only waits for it); Pause, then
//! the frame slider back to frame 0, gives frame 0's slice. And the next frame's bricks are
//! fetched ahead (web/src/frame_ahead.rs): the server's access log lists frame 1's bricks
//! while the page still shows frame 0, paused, and the frame Play then shows is the desktop's.

use std::sync::mpsc;
use std::sync::Arc;

use serde_json::json;

use strata_service::CapturedFrame;
use strata_slices::Window;
use strata_source::VolumeSource;
use strata_storage::import::{import_source, ImportOptions};
use strata_storage::readers::{open_source, ReadOptions};

use crate::input::cdp::Cdp;
use crate::{
    assert_same_slice, desktop_axial_slice, desktop_client, metric, serve_capturing, web_viewer,
    PAGE_DEADLINE, TOKEN,
};

const DIMS: [usize; 3] = [48, 40, 24];
const FRAMES: usize = 3;
/// The link's window: every frame's values lie inside it.
const WINDOW: [f64; 2] = [1000.0, 2400.0];

/// Voxel (i, j, k) of frame t: diagonal bands (many grey levels in an axial slice), shifted by
/// 400 per frame, so every pixel of a frame's slice differs from another frame's.
fn value(i: usize, j: usize, k: usize, t: usize) -> i16 {
    (100 + 50 * ((i + 2 * j + 3 * k) % 20) + 400 * t) as i16
}

/// A 4-D NIfTI-1 (int16, 1 mm voxels) written byte by byte: dim[0] = 4, dim[4] = frames.
fn write_4d_nifti(path: &std::path::Path) {
    let mut bytes = vec![0u8; 352];
    bytes[0..4].copy_from_slice(&348i32.to_le_bytes());
    let dim = [
        4i16,
        DIMS[0] as i16,
        DIMS[1] as i16,
        DIMS[2] as i16,
        FRAMES as i16,
        1,
        1,
        1,
    ];
    for (n, d) in dim.iter().enumerate() {
        bytes[40 + 2 * n..42 + 2 * n].copy_from_slice(&d.to_le_bytes());
    }
    bytes[70..72].copy_from_slice(&4i16.to_le_bytes()); // datatype int16
    bytes[72..74].copy_from_slice(&16i16.to_le_bytes()); // bits per voxel
    for (n, p) in [1f32, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0].iter().enumerate() {
        bytes[76 + 4 * n..80 + 4 * n].copy_from_slice(&p.to_le_bytes());
    }
    bytes[108..112].copy_from_slice(&352f32.to_le_bytes()); // vox_offset
    bytes[252..254].copy_from_slice(&1i16.to_le_bytes()); // qform_code: scanner
    bytes[344..348].copy_from_slice(b"n+1\0");
    for t in 0..FRAMES {
        for k in 0..DIMS[2] {
            for j in 0..DIMS[1] {
                for i in 0..DIMS[0] {
                    bytes.extend_from_slice(&value(i, j, k, t).to_le_bytes());
                }
            }
        }
    }
    std::fs::write(path, bytes).expect("write the 4-D NIfTI");
}

/// The next slice capture the page posts of `frame` (its `frame` metric), skipping others.
fn next_slice_of_frame(
    frames: &mpsc::Receiver<CapturedFrame>,
    page: &Cdp,
    frame: u32,
) -> CapturedFrame {
    let until = std::time::Instant::now() + PAGE_DEADLINE;
    loop {
        let left = until.saturating_duration_since(std::time::Instant::now());
        match frames.recv_timeout(left) {
            Ok(posted) if metric(&posted, "frame") == Some(f64::from(frame)) => return posted,
            Ok(_) => continue,
            Err(_) => panic!(
                "the page posted no slice of frame {frame} within {PAGE_DEADLINE:?}; its console:\n{}",
                page.console()
            ),
        }
    }
}

/// The page's `data-frame` ("2/3 paused").
fn shown_frame(page: &mut Cdp) -> Option<String> {
    page.evaluate("document.getElementById('strata-canvas')?.dataset.frame ?? null")
        .as_str()
        .map(str::to_owned)
}

/// The Frames panel's control `name` (`play`, `slider`) in page coordinates (CSS pixels).
fn control_rect(page: &mut Cdp, name: &str) -> egui::Rect {
    let found = page.evaluate(
        "(() => { const c = document.getElementById('strata-canvas'); const r = c.getBoundingClientRect(); \
         return [r.left, r.top, c.dataset.frameControls ?? null]; })()",
    );
    let (left, top) = (
        found[0].as_f64().expect("canvas left") as f32,
        found[1].as_f64().expect("canvas top") as f32,
    );
    let controls = found[2]
        .as_str()
        .unwrap_or_else(|| panic!("the page published no frame controls"))
        .to_owned();
    let numbers: Vec<f32> = controls
        .split(';')
        .find_map(|entry| entry.strip_prefix(&format!("{name}:")))
        .unwrap_or_else(|| panic!("no {name} in the frame controls: {controls}"))
        .split(',')
        .map(|n| n.parse().unwrap_or_else(|e| panic!("{controls}: {e}")))
        .collect();
    let [x, y, w, h] = numbers[..] else {
        panic!("{controls}: not x,y,w,h");
    };
    egui::Rect::from_min_size(egui::pos2(x + left, y + top), egui::vec2(w, h))
}

/// A left click at `at` with press and release in one page frame: egui takes a press held
/// past its click time for a drag, and a page frame on a loaded machine can take that long.
fn click_at(page: &mut Cdp, at: egui::Pos2) {
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

/// The control `name` once it stays put over two frames (the side panel settles).
fn settled_control(page: &mut Cdp, name: &str) -> egui::Rect {
    page.wait_for(
        &format!("the frame control {name} to stay put"),
        PAGE_DEADLINE,
        |page| {
            let before = control_rect(page, name);
            page.next_frames();
            (control_rect(page, name) == before).then_some(before)
        },
    )
}

/// Waits for the page's `data-frame` to satisfy `done`; at the deadline, keeps a screenshot
/// (`$TMPDIR/strata-browser-tests/frames-WHAT.png`) and says what the page showed.
fn wait_for_frame(page: &mut Cdp, what: &str, done: impl Fn(&str) -> bool) -> String {
    let until = std::time::Instant::now() + PAGE_DEADLINE;
    loop {
        let shown = shown_frame(page);
        if let Some(text) = shown.as_ref().filter(|text| done(text)) {
            return text.clone();
        }
        if std::time::Instant::now() > until {
            let name = format!("frames-{}", what.replace(' ', "-"));
            crate::keys::page_screenshot(page, &name);
            let controls = page.evaluate(
                "document.getElementById('strata-canvas')?.dataset.frameControls ?? null",
            );
            panic!(
                "waited {PAGE_DEADLINE:?} for {what}: the page shows frame {shown:?}, its \
                 controls {controls}, screenshot {name}.png in $TMPDIR/strata-browser-tests; \
                 console:\n{}",
                page.console()
            );
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
}

/// The 4-D NIfTI imported as the store `cine` in `scratch`.
fn import_cine(scratch: &std::path::Path) -> std::path::PathBuf {
    let nifti = scratch.join("cine.nii");
    write_4d_nifti(&nifti);
    let path = scratch.join("cine.strata");
    let opened = open_source(&nifti, &ReadOptions::default()).expect("read the 4-D NIfTI");
    import_source(opened, &path, &ImportOptions::default()).expect("import the 4-D NIfTI");
    path
}

#[test]
fn the_page_shows_a_served_4d_stores_frames_and_plays_them() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let path = import_cine(scratch.path());
    let (server, frames) = serve_capturing(&path);
    let fragment = format!(
        "#store=cine&mode=mip&preset=ct-soft-tissue&size=64x64&capture=1&window={},{}&frame=2",
        WINDOW[0], WINDOW[1]
    );
    let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
    let mut page = Cdp::open(&url, scratch.path(), [1100, 800]);

    // The desktop's path: its client on the same server, each frame its own source.
    let client = Arc::new(desktop_client(&server, "cine"));
    assert_eq!(client.frame_count(), FRAMES as u32);
    let header = client.header().clone();
    let desktop_slice = |frame: u32, posted: &CapturedFrame, console: &str| {
        let source = client
            .clone()
            .frame_source(frame)
            .unwrap_or_else(|| panic!("the desktop's client opens frame {frame}"));
        desktop_axial_slice(
            &header.layout,
            &header.geometry,
            Window::new(WINDOW[0], WINDOW[1]),
            header.value_mapping.mapping,
            (posted, console),
            |id| source.read_brick(id).expect("brick"),
        )
    };
    let differing =
        |a: &[u8], b: &[u8]| a.chunks(4).zip(b.chunks(4)).filter(|(a, b)| a != b).count();

    // Opened at frame=2: frame 2's slice, not frame 0's.
    let second = next_slice_of_frame(&frames, &page, 2);
    let console = page.console();
    let (level, of_frame_2) = desktop_slice(2, &second, &console);
    assert_same_slice("frame 2", level, &second, &of_frame_2, &console);
    let (_, of_frame_0) = desktop_slice(0, &second, &console);
    let pixels = of_frame_0.len() / 4;
    assert!(
        differing(&second.rgba, &of_frame_0) > pixels / 2,
        "the page's frame 2 looks like frame 0: the frames would not tell a wrong frame"
    );
    assert_eq!(
        shown_frame(&mut page).as_deref(),
        Some("2/3 paused"),
        "the page shows frame 2 of 3"
    );

    // Play: cine moves off frame 2 (the page's clock, frames drawn; nothing is timed here).
    let play = settled_control(&mut page, "play");
    click_at(&mut page, play.center());
    wait_for_frame(&mut page, "cine to move off frame 2", |text| {
        text.ends_with("playing") && !text.starts_with("2/")
    });
    // Pause (the same button), then the slider: its right end (frame 2) first, should cine
    // have stopped on frame 0, then its left end, frame 0.
    click_at(&mut page, play.center());
    let paused = wait_for_frame(&mut page, "cine to pause", |text| text.ends_with("paused"));
    let slider = settled_control(&mut page, "slider");
    // The rail is the slider's first `slider_width` (egui's 100 points) of the row.
    let y = slider.center().y;
    let (rail_left, rail_right) = (
        egui::pos2(slider.min.x + 2.0, y),
        egui::pos2(slider.min.x + 98.0, y),
    );
    if paused.starts_with("0/") {
        click_at(&mut page, rail_right);
        wait_for_frame(&mut page, "the slider to show frame 2", |t| {
            t == "2/3 paused"
        });
    }
    while frames.try_recv().is_ok() {}
    click_at(&mut page, rail_left);
    wait_for_frame(&mut page, "the slider to show frame 0", |t| {
        t == "0/3 paused"
    });
    let first = next_slice_of_frame(&frames, &page, 0);
    let console = page.console();
    let (level, of_frame_0) = desktop_slice(0, &first, &console);
    assert_same_slice(
        "frame 0 from the slider",
        level,
        &first,
        &of_frame_0,
        &console,
    );
    assert!(
        differing(&first.rgba, &of_frame_2) > pixels / 2,
        "the slider's frame 0 looks like frame 2"
    );
}

/// [`serve_capturing`] with the server's access log (one line per answered request, its path
/// included) written to `log`.
fn serve_logged(
    path: &std::path::Path,
    log: &std::path::Path,
) -> (
    strata_service::server::RunningServer,
    mpsc::Receiver<CapturedFrame>,
) {
    let (frames_in, frames) = mpsc::channel::<CapturedFrame>();
    let frames_in = std::sync::Mutex::new(frames_in);
    let server = strata_service::server::start(
        strata_service::server::find_stores(&[path.to_path_buf()]).expect("store found"),
        strata_service::ServeOptions {
            web_viewer: Some(Arc::new(web_viewer())),
            test_frame_sink: Some(strata_service::FrameSink(Arc::new(move |frame| {
                if let Ok(sender) = frames_in.lock() {
                    let _ = sender.send(frame);
                }
            }))),
            token: Some(TOKEN.into()),
            access_log: Some(log.to_path_buf()),
            ..strata_service::ServeOptions::default()
        },
    )
    .expect("server starts");
    (server, frames)
}

/// The bricks of frame `frame` below the root level (`root_level`) the server answered, as its
/// access log lists them (`…/f/FRAME/bricks/LEVEL/Z/Y/X`). The root brick comes with the
/// frame's store when it is opened, ahead or not: not counted.
fn answered_bricks_of_frame(log: &std::path::Path, frame: u32, root_level: usize) -> Vec<String> {
    let marker = format!("/f/{frame}/bricks/");
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter_map(|line| {
            let path = line.split(' ').nth(3)?;
            let status = line.split(' ').nth(4)?;
            let rest = path.split_once(&marker)?.1;
            let level: usize = rest.split('/').next()?.parse().ok()?;
            (status == "200" && level < root_level).then(|| path.to_owned())
        })
        .collect()
}

/// The page's `data-frame-ahead`: records its frames' fetchers took from what was fetched
/// ahead, over the page's life (`…; used=N`).
fn records_used_ahead(page: &mut Cdp) -> Option<u64> {
    let text =
        page.evaluate("document.getElementById('strata-canvas')?.dataset.frameAhead ?? null");
    text.as_str()?.split("used=").nth(1)?.trim().parse().ok()
}

/// The page opened at frame 0 of a served 4-D store, paused: once its 3D view has converged,
/// frame 1's bricks below the root are requested (the server's access log answers them) while
/// the page still shows frame 0 (`data-frame` says "0/3 paused" before and after): streamed
/// ahead. Without it, nothing asks for a frame's bricks before it is shown. Play then moves
/// cine on; paused again, the frame shown is, byte for byte, the desktop's slice of that frame
/// (its client's `frame_source`), and the frames shown took records fetched ahead instead of
/// asking the server.
#[test]
fn the_next_frames_bricks_are_requested_before_it_is_shown_and_play_shows_the_desktops_frame() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let path = import_cine(scratch.path());
    let log = scratch.path().join("access.log");
    let (server, frames) = serve_logged(&path, &log);
    let fragment = format!(
        "#store=cine&mode=mip&preset=ct-soft-tissue&size=96x96&capture=1&window={},{}",
        WINDOW[0], WINDOW[1]
    );
    let url = format!("{}/{fragment}&token={TOKEN}", server.base_url());
    let mut page = Cdp::open(&url, scratch.path(), [1100, 800]);
    let client = Arc::new(desktop_client(&server, "cine"));
    let header = client.header().clone();
    let root_level = header.layout.level_count() - 1;
    assert!(
        root_level > 0,
        "a store of one level has no bricks but its root"
    );

    // Frame 0 shown; frame 1 is not, and nothing but its fetching ahead asks for its bricks.
    next_slice_of_frame(&frames, &page, 0);
    let ahead = page.wait_for(
        "frame 1's bricks to be requested while frame 0 is shown",
        PAGE_DEADLINE,
        |page| {
            assert_eq!(
                shown_frame(page).as_deref(),
                Some("0/3 paused"),
                "the page left frame 0 by itself"
            );
            let answered = answered_bricks_of_frame(&log, 1, root_level);
            (!answered.is_empty()).then_some(answered)
        },
    );
    assert_eq!(
        shown_frame(&mut page).as_deref(),
        Some("0/3 paused"),
        "frame 1's bricks were answered while frame 0 was shown"
    );
    println!(
        "frames: {} of frame 1's bricks requested ahead while frame 0 was shown: {ahead:?}",
        ahead.len()
    );

    // Play: cine moves on (frame 1 first); pause again and compare the frame shown.
    let play = settled_control(&mut page, "play");
    click_at(&mut page, play.center());
    wait_for_frame(&mut page, "cine to move off frame 0", |text| {
        text.ends_with("playing") && !text.starts_with("0/")
    });
    click_at(&mut page, play.center());
    let paused = wait_for_frame(&mut page, "cine to pause", |text| text.ends_with("paused"));
    let shown: u32 = paused
        .split('/')
        .next()
        .and_then(|f| f.parse().ok())
        .unwrap_or_else(|| panic!("data-frame {paused:?}"));
    let posted = next_slice_of_frame(&frames, &page, shown);
    let console = page.console();
    let source = client
        .clone()
        .frame_source(shown)
        .unwrap_or_else(|| panic!("the desktop's client opens frame {shown}"));
    let (level, desktop) = desktop_axial_slice(
        &header.layout,
        &header.geometry,
        Window::new(WINDOW[0], WINDOW[1]),
        header.value_mapping.mapping,
        (&posted, &console),
        |id| source.read_brick(id).expect("brick"),
    );
    assert_same_slice(
        &format!("frame {shown} after Play"),
        level,
        &posted,
        &desktop,
        &console,
    );
    // Waited for, not read once: the count the page published last may be from before the
    // shown frame's fetchers took the records (it read 0 there, last session's failure).
    let used = page.wait_for(
        &format!("the frames cine showed ({paused}) to take records fetched ahead"),
        PAGE_DEADLINE,
        |page| records_used_ahead(page).filter(|used| *used > 0),
    );
    println!("frames: the frames cine showed took {used} records fetched ahead");
}
