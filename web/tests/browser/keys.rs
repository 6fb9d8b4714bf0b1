//! The page's shared tools under real keys and pointer moves (issue 47), sent over the
//! DevTools pipe (../cdp): undo and redo of an edit (the link says what is undone), the F1
//! help, the screenshot download (F12), the orientation triad (strata-viewer-ui's geometry,
//! found in a screenshot of the page), the slices' colour map from the link (`cmap=`) and the
//! value readout under the pointer, each against the desktop's code for the same input.

use std::path::Path;
use std::time::{Duration, Instant};

use egui::pos2;
use serde_json::json;
use strata_render::BrickSource;
use strata_slices::{ColourMap, SliceFrame, SliceView, Window};
use strata_types::{OctreeLayout, BRICK_APRON, BRICK_CORE, BRICK_PAYLOAD};
use strata_viewer_ui::history::edits_of;
use strata_viewer_ui::orbit::StandardView;
use strata_viewer_ui::presets::{integer_values, readout_value};
use strata_viewer_ui::slice_canvas::{fraction_at, inner_rect, ZoomPan};
use strata_viewer_ui::triad::{triad, Triad};
use strata_web::view_state::Fragment;

use crate::input::cdp::Cdp;
use crate::input::{close, open_page, open_page_capturing, view_rect, wait_for_link};
use crate::PAGE_DEADLINE;

/// DevTools' modifier bits (Input.dispatchKeyEvent).
pub(crate) const CTRL: u32 = 2;
const SHIFT: u32 = 8;

/// Presses and releases a key with `modifiers`: `key` as KeyboardEvent.key, `code` as its
/// code, `virtual_code` as its Windows virtual key code (F1 is 112, F12 123, Z 90).
pub(crate) fn key_with(page: &mut Cdp, key: &str, code: &str, virtual_code: u32, modifiers: u32) {
    for kind in ["keyDown", "keyUp"] {
        let mut event = json!({
            "type": kind, "key": key, "code": code, "modifiers": modifiers,
            "windowsVirtualKeyCode": virtual_code, "nativeVirtualKeyCode": virtual_code,
        });
        // A letter typed without Ctrl is text too (as a keyboard sends it).
        if kind == "keyDown" && modifiers & CTRL == 0 && key.chars().count() == 1 {
            event["text"] = json!(key);
        }
        page.command("Input.dispatchKeyEvent", event);
    }
    page.next_frames();
}

/// Gives the canvas the keys, as a user's click on the 3D view does.
fn focus_canvas(page: &mut Cdp) {
    let centre = view_rect(page, "3d").center().round();
    page.click(centre.x as f64, centre.y as f64);
    page.evaluate("document.getElementById('strata-canvas').focus()");
}

/// A right-button drag (the slices' windowing) from `from` by `by` CSS pixels.
pub(crate) fn right_drag(page: &mut Cdp, from: egui::Pos2, by: [f64; 2]) {
    let mouse = |page: &mut Cdp, kind: &str, x: f64, y: f64, buttons: u32| {
        page.command(
            "Input.dispatchMouseEvent",
            json!({
                "type": kind, "x": x, "y": y, "button": "right", "buttons": buttons,
                "clickCount": 1,
            }),
        );
        page.next_frames();
    };
    let (x, y) = (from.x as f64, from.y as f64);
    mouse(page, "mouseMoved", x, y, 0);
    mouse(page, "mousePressed", x, y, 2);
    for step in 1..=4 {
        let t = f64::from(step) / 4.0;
        mouse(page, "mouseMoved", x + by[0] * t, y + by[1] * t, 2);
    }
    mouse(page, "mouseReleased", x + by[0], y + by[1], 0);
}

/// The canvas's `data-NAME` attribute (None while absent).
fn canvas_data(page: &mut Cdp, name: &str) -> Option<String> {
    page.evaluate(&format!(
        "document.getElementById('strata-canvas')?.dataset.{name} ?? null"
    ))
    .as_str()
    .map(str::to_owned)
}

/// A window edit (a right drag on the axial view) is undone by Ctrl+Z, which gives the link
/// its window before the drag and nothing else changed, and redone by Ctrl+Shift+Z (and
/// Ctrl+Y after another undo). F1 opens the page's help and F1 again closes it (the page
/// publishes its open windows as `data-windows`).
#[test]
fn ctrl_z_undoes_a_window_drag_ctrl_shift_z_redoes_it_and_f1_shows_the_help() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let fragment = "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&layout=conventional";
    let (mut page, _server) = open_page(fragment, scratch.path(), [1200, 800]);
    let before = wait_for_link(&mut page, "the link to carry the slices' window", |v| {
        v.window.is_some()
    });
    focus_canvas(&mut page);
    let axial = view_rect(&mut page, "axial");
    right_drag(&mut page, axial.center().round(), [60.0, 0.0]);
    let edited = wait_for_link(&mut page, "the link to show the dragged window", |v| {
        v.window
            .is_some_and(|w| !close(w[1], before.window.expect("window")[1]))
    });
    let same_window = |a: Option<[f64; 2]>, b: Option<[f64; 2]>| match (a, b) {
        (Some(a), Some(b)) => close(a[0], b[0]) && close(a[1], b[1]),
        _ => false,
    };
    key_with(&mut page, "z", "KeyZ", 90, CTRL);
    let undone = wait_for_link(&mut page, "Ctrl+Z to put the window back", |v| {
        same_window(v.window, before.window)
    });
    assert_eq!(
        edits_of(&undone),
        edits_of(&before),
        "undo restores the link's edits as they were before the drag"
    );
    key_with(&mut page, "Z", "KeyZ", 90, CTRL | SHIFT);
    wait_for_link(&mut page, "Ctrl+Shift+Z to apply the drag again", |v| {
        same_window(v.window, edited.window)
    });
    key_with(&mut page, "z", "KeyZ", 90, CTRL);
    wait_for_link(&mut page, "a second Ctrl+Z", |v| {
        same_window(v.window, before.window)
    });
    key_with(&mut page, "y", "KeyY", 89, CTRL);
    wait_for_link(&mut page, "Ctrl+Y to apply the drag again", |v| {
        same_window(v.window, edited.window)
    });

    assert_eq!(canvas_data(&mut page, "windows").unwrap_or_default(), "");
    key_with(&mut page, "F1", "F1", 112, 0);
    page.wait_for("F1 to open the help", PAGE_DEADLINE, |page| {
        (canvas_data(page, "windows").as_deref() == Some("help")).then_some(())
    });
    key_with(&mut page, "F1", "F1", 112, 0);
    page.wait_for("F1 again to close the help", PAGE_DEADLINE, |page| {
        (canvas_data(page, "windows").as_deref() == Some("")).then_some(())
    });
}

/// The page as the screenshot shows it: RGBA8 rows of the viewport, with its width. The PNG
/// is kept as `$TMPDIR/strata-browser-tests/NAME.png` for a failure's reader.
pub(crate) fn page_screenshot(page: &mut Cdp, name: &str) -> (u32, Vec<u8>) {
    let shot = page.command("Page.captureScreenshot", json!({ "format": "png" }));
    let data = shot["data"].as_str().expect("screenshot data");
    let png = base64_decode(data);
    let kept = std::env::temp_dir().join("strata-browser-tests");
    if std::fs::create_dir_all(&kept).is_ok() {
        let _ = std::fs::write(kept.join(format!("{name}.png")), &png);
    }
    let mut reader = png::Decoder::new(std::io::Cursor::new(png))
        .read_info()
        .expect("the screenshot is a PNG");
    let mut pixels = vec![0; reader.output_buffer_size().expect("size")];
    let info = reader.next_frame(&mut pixels).expect("PNG pixels");
    pixels.truncate(info.buffer_size());
    let rgba = match info.color_type {
        png::ColorType::Rgba => pixels,
        png::ColorType::Rgb => pixels
            .chunks(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect(),
        other => panic!("the screenshot is {other:?}, not RGB or RGBA"),
    };
    (info.width, rgba)
}

/// Standard base64 (the screenshot's encoding), no line breaks.
fn base64_decode(text: &str) -> Vec<u8> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {:?}", c as char),
    };
    let digits: Vec<u8> = text.bytes().filter(|c| *c != b'=').map(value).collect();
    digits
        .chunks(4)
        .flat_map(|chunk| {
            let bits = chunk
                .iter()
                .enumerate()
                .fold(0u32, |acc, (i, d)| acc | u32::from(*d) << (18 - 6 * i));
            let bytes = [(bits >> 16) as u8, (bits >> 8) as u8, bits as u8];
            bytes.into_iter().take(chunk.len().saturating_sub(1))
        })
        .collect()
}

/// The pixel nearest `colour` within a pixel of `at` and its largest channel difference.
fn nearest_colour(width: u32, rgba: &[u8], at: egui::Pos2, colour: egui::Color32) -> u8 {
    let mut best = u8::MAX;
    for dy in -1..=1 {
        for dx in -1..=1 {
            let (x, y) = (at.x.round() as i64 + dx, at.y.round() as i64 + dy);
            let i = ((y * i64::from(width) + x) * 4) as usize;
            let Some(p) = rgba.get(i..i + 3) else {
                continue;
            };
            let off = (0..3)
                .map(|c| p[c].abs_diff([colour.r(), colour.g(), colour.b()][c]))
                .max()
                .unwrap_or(u8::MAX);
            best = best.min(off);
        }
    }
    best
}

/// The largest channel difference an axis' pixel may have from its colour: egui's
/// anti-aliasing feathers the 3-point line's edges, its middle is the colour.
const TRIAD_COLOUR_TOLERANCE: u8 = 24;

/// Checks the screenshot shows every axis of `triad` that is not end-on, in its colour,
/// halfway along its positive half; returns the points checked.
fn assert_triad_drawn(what: &str, width: u32, rgba: &[u8], triad: &Triad) -> Vec<egui::Pos2> {
    let mut checked = Vec::new();
    for axis in triad
        .axes
        .iter()
        .filter(|a| a.tip.length() > 0.6 * triad.radius)
    {
        let at = triad.centre + axis.tip * 0.6;
        let off = nearest_colour(width, rgba, at, axis.colour);
        assert!(
            off <= TRIAD_COLOUR_TOLERANCE,
            "{what}: the triad's {} axis is not drawn at {at:?} (nearest colour {off} off {:?})",
            axis.positive,
            axis.colour
        );
        checked.push(at);
    }
    assert!(!checked.is_empty(), "{what}: no axis to check");
    checked
}

/// Waits for a file named `strata-3d-*.png` (complete: no `.crdownload`) in `folder`.
fn wait_for_download(folder: &Path) -> Vec<u8> {
    let until = Instant::now() + PAGE_DEADLINE;
    loop {
        let done = std::fs::read_dir(folder)
            .expect("download folder")
            .filter_map(Result::ok)
            .map(|e| e.path())
            .find(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("strata-3d-") && n.ends_with(".png"))
            });
        if let Some(path) = done {
            return std::fs::read(&path).expect("reading the download");
        }
        assert!(
            Instant::now() < until,
            "no screenshot was downloaded into {} within {PAGE_DEADLINE:?}",
            folder.display()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// F12 downloads the 3D view as PNG (`strata-3d-MILLIS.png`, the desktop's naming) whose
/// pixels are the frame the page posted through its capture hook, at the size it was drawn.
/// Then the orientation triad: at the anterior view (key A) and the left view (key L) every
/// axis that is not end-on shows its colour where strata-viewer-ui's triad geometry puts it
/// for the view's camera, and the left view no longer shows the L axis where the anterior
/// view had it.
#[test]
fn f12_downloads_the_drawn_frame_and_the_triad_turns_with_the_standard_views() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let downloads = tempfile::tempdir().expect("download folder");
    let fragment = "#mode=mip&preset=ct-soft-tissue&volume=40&size=96x96&layout=single&capture=1";
    let (mut page, _server, frames) = open_page_capturing(fragment, scratch.path(), [640, 480]);
    let posted = frames
        .recv_timeout(PAGE_DEADLINE)
        .expect("the page posts its drawn frame");
    page.browser_command(
        "Browser.setDownloadBehavior",
        json!({ "behavior": "allow", "downloadPath": downloads.path().to_str().expect("utf-8") }),
    );
    focus_canvas(&mut page);
    key_with(&mut page, "F12", "F12", 123, 0);
    let png = wait_for_download(downloads.path());
    let (width, height, rgba) = crate::decode_png(&png);
    assert_eq!((width, height), (posted.width, posted.height));
    let lit = rgba.chunks(4).filter(|p| p[..3] != [0, 0, 0]).count();
    assert!(
        lit > 100,
        "the downloaded frame is nearly empty ({lit} pixels lit)"
    );
    assert!(
        rgba == posted.rgba,
        "the downloaded PNG differs from the frame the page drew ({} of {} bytes differ)",
        rgba.iter()
            .zip(&posted.rgba)
            .filter(|(a, b)| a != b)
            .count(),
        rgba.len()
    );

    let geometry = Fragment::parse(fragment).expect("fragment").view.geometry();
    let mut anterior_l = None;
    for (key, code, standard) in [
        ("a", "KeyA", StandardView::Anterior),
        ("l", "KeyL", StandardView::Left),
    ] {
        key_with(
            &mut page,
            key,
            code,
            u32::from(key.as_bytes()[0].to_ascii_uppercase()),
            0,
        );
        let (az, el) = standard.angles_deg();
        let view = wait_for_link(&mut page, &format!("the {standard:?} view"), |v| {
            close(v.azimuth_deg, az) && close(v.elevation_deg, el)
        });
        // The view's place as the screenshot shows it: the same before and after it (a
        // headless window may still settle its size while the page starts).
        let (rect, (width, shot)) = page.wait_for(
            "the 3D view to stay put over a screenshot",
            PAGE_DEADLINE,
            |page| {
                page.next_frames();
                let before = view_rect(page, "3d");
                let shot = page_screenshot(page, &format!("triad-{standard:?}"));
                (view_rect(page, "3d") == before).then_some((before, shot))
            },
        );
        let shown = triad(rect, &view.camera(&geometry));
        let what = format!(
            "{standard:?} view (3D view at {rect:?}, the page's views: {:?})",
            canvas_data(&mut page, "views")
        );
        assert_triad_drawn(&what, width, &shot, &shown);
        let l_axis = shown.axes.iter().find(|a| a.positive == "L").expect("L");
        match anterior_l {
            None => anterior_l = Some((shown.centre + l_axis.tip * 0.6, l_axis.colour)),
            Some((at, colour)) => assert!(
                nearest_colour(width, &shot, at, colour) > TRIAD_COLOUR_TOLERANCE,
                "the left view still shows the L axis where the anterior view drew it: the \
                 check could not tell the views apart"
            ),
        }
    }
}

/// A page opened with `cmap=hot` colours its slices as the desktop's window/level step does
/// with the hot map: its axial image equals, byte for byte, the desktop's assembler and
/// colouring of the same sample. Moving the pointer over the axial view then reads the voxel
/// the desktop's slice mapping gives for that point, with the value the desktop's readout
/// prints for it (the page publishes its readout as `data-readout`).
#[test]
fn the_link_colours_the_slices_as_the_desktop_and_the_readout_reads_its_voxel() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let fragment =
        "#mode=mip&preset=ct-soft-tissue&volume=40&size=64x64&layout=conventional&cmap=hot&capture=1";
    let (mut page, _server, frames) = open_page_capturing(fragment, scratch.path(), [1200, 800]);
    let view = Fragment::parse(fragment).expect("fragment").view;
    assert_eq!(view.colour_map, ColourMap::Hot);
    let three_d = frames.recv_timeout(PAGE_DEADLINE).expect("the 3D frame");
    assert_eq!((three_d.width, three_d.height), (64, 64));
    let slice = frames.recv_timeout(PAGE_DEADLINE).expect("the axial slice");
    let console = page.console();
    let volume = view.sample_volume().expect("sample volume");
    let (level, desktop) = crate::desktop_axial_slice_coloured(
        &OctreeLayout::new(volume.geometry.dims),
        &volume.geometry,
        (Window::new(40.0, 400.0), ColourMap::Hot),
        volume.mapping,
        (&slice, &console),
        |id| {
            volume
                .brick(id.level, id.coords)
                .expect("in-memory brick")
                .to_vec()
        },
    );
    crate::assert_same_slice("hot slices", level, &slice, &desktop, &console);
    let (_, grey) = crate::desktop_axial_slice(
        &OctreeLayout::new(volume.geometry.dims),
        &volume.geometry,
        Window::new(40.0, 400.0),
        volume.mapping,
        (&slice, &console),
        |id| {
            volume
                .brick(id.level, id.coords)
                .expect("in-memory brick")
                .to_vec()
        },
    );
    assert_ne!(
        grey, desktop,
        "the grey slice equals the hot one: the comparison could not tell the maps apart"
    );
    assert!(
        wait_for_link(&mut page, "the link to keep its colour map", |v| v
            .window
            .is_some())
        .colour_map
            == ColourMap::Hot
    );

    // The readout under the pointer.
    let geometry = &volume.geometry;
    let axial = view_rect(&mut page, "axial");
    let frame = SliceFrame::for_view(SliceView::Axial, geometry);
    let image = ZoomPan::default().image_rect(inner_rect(axial), frame.extent_mm(geometry));
    let at = pos2(
        image.left() + image.width() * 0.35,
        image.top() + image.height() * 0.6,
    )
    .round();
    let dims = geometry.dims;
    let (u, v) = fraction_at(image, at);
    let (a, d) = frame.index_at(dims, u, v);
    let mut index = dims.map(|n| ((n as f64 - 1.0) * 0.5).floor().max(0.0) as u32);
    index[frame.across_axis] = (a.round().max(0.0) as u32).min(dims[frame.across_axis] - 1);
    index[frame.down_axis] = (d.round().max(0.0) as u32).min(dims[frame.down_axis] - 1);
    let node = index.map(|i| i / BRICK_CORE);
    let [x, y, z] = index.map(|i| (i % BRICK_CORE + BRICK_APRON) as usize);
    let edge = BRICK_PAYLOAD as usize;
    let stored = volume.brick(0, node).expect("level-0 brick")[(z * edge + y) * edge + x];
    let physical = volume.mapping.physical(f64::from(stored));
    // The sample is the CT phantom in HU: the desktop's readout of its voxel (scene.rs's
    // Readout prints its value with the same function).
    let value = readout_value(physical, "HU", integer_values(&volume.mapping));
    let expected = format!("axial:{},{},{}:{value}", index[0], index[1], index[2]);
    page.mouse_move(at.x as f64, at.y as f64, false);
    let readout = page.wait_for("the readout under the pointer", PAGE_DEADLINE, |page| {
        page.mouse_move(at.x as f64, at.y as f64, false);
        canvas_data(page, "readout").filter(|r| !r.ends_with('…'))
    });
    assert_eq!(
        readout, expected,
        "the pointer at {at:?} on the axial view {axial:?}"
    );
}
