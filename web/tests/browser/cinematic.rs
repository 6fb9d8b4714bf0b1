//! The cinematic preset buttons in the page's side panel (issue 47), clicked with real pointer
//! events (the DevTools pipe, ../cdp): each click must leave the page's view, as its link
//! writes it, with what the desktop's click on the same shared button (strata-viewer-ui's
//! `cinematic_buttons`) sets: the preset's transfer function unedited (the link names the
//! preset and carries no `tf=`, so the function is the preset fitted to the scan, the
//! desktop's `preset_for`) and the lighting `CinematicPreset::light_view` gives, the function
//! the desktop's `Preferences::apply_cinematic` calls: the preset's light, shading on, DVR for
//! MIP. The link is read back by the desktop's own parser (strata-viewer-ui's view_state).

use egui::{pos2, vec2, Rect};
use strata_render::RenderMode;
use strata_viewer_ui::lighting::CinematicPreset;
use strata_web::view_state::{Fragment, ViewState};

use crate::input::cdp::Cdp;
use crate::input::{open_page, wait_for_link};
use crate::PAGE_DEADLINE;

/// The page's sample in MIP, unshaded, with a brighter light than the presets' and another
/// transfer function: every field a cinematic click sets starts elsewhere, so a click that
/// set only some of them fails.
const FRAGMENT: &str =
    "#mode=mip&preset=ct-lung&shade=off&intensity=1.5&ambient=0.4&volume=40&size=48x48&layout=single";
/// Tall enough that the side panel's "Light and shadows" section is in sight below the
/// sections above it.
const WINDOW: [u32; 2] = [1100, 1500];

/// A rectangle the page publishes in the canvas attribute `attribute` (`x,y,w,h`, or entries
/// `LABEL:x,y,w,h;…` where `label` is given), in page CSS pixels.
fn published_rect(page: &mut Cdp, attribute: &str, label: Option<&str>) -> Option<Rect> {
    let found = page.evaluate(&format!(
        "(() => {{ const c = document.getElementById('strata-canvas'); const r = c.getBoundingClientRect(); \
         return [r.left, r.top, c.getAttribute('{attribute}')]; }})()"
    ));
    let (left, top) = (found[0].as_f64()? as f32, found[1].as_f64()? as f32);
    let text = found[2].as_str()?;
    let numbers = match label {
        Some(label) => text
            .split(';')
            .find_map(|entry| entry.strip_prefix(&format!("{label}:")))?,
        None => text,
    };
    let numbers: Vec<f32> = numbers
        .split(',')
        .map(|n| n.parse().ok())
        .collect::<Option<_>>()?;
    let [x, y, w, h] = numbers[..] else {
        return None;
    };
    Some(Rect::from_min_size(pos2(left + x, top + y), vec2(w, h)))
}

/// [`published_rect`] once it stays put over two page frames (egui lays the side panel out
/// over its first frames, and a section opening above moves what is below it).
fn settled_rect(page: &mut Cdp, what: &str, attribute: &str, label: Option<&str>) -> Rect {
    page.wait_for(what, PAGE_DEADLINE, |page| {
        let before = published_rect(page, attribute, label)?;
        page.next_frames();
        (published_rect(page, attribute, label) == Some(before)).then_some(before)
    })
}

/// Clicks the centre of `rect` until `taken` says the page took the click. Each click's press
/// and release go out back to back ([`Cdp::quick_click`]): with frames between them, as
/// `Cdp::click` sends them, this tall window's SwiftShader frames held the press past egui's
/// click time (0.8 s) and the page took every click on the light section's header as a
/// drag's start. A click the page did take is never repeated.
fn click_until(page: &mut Cdp, rect: Rect, what: &str, taken: impl Fn(&mut Cdp) -> bool) {
    let c = rect.center().round();
    let (x, y) = (c.x as f64, c.y as f64);
    for _attempt in 0..5 {
        page.quick_click(x, y);
        let until = std::time::Instant::now() + std::time::Duration::from_secs(20);
        while std::time::Instant::now() < until {
            if taken(page) {
                // Two clicks closer than a double-click's delay would read as one.
                std::thread::sleep(std::time::Duration::from_millis(600));
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    }
    panic!(
        "the page did not take five clicks at ({x}, {y}) for {what}; its console:\n{}",
        page.console()
    );
}

/// What the desktop's click on `preset` makes of `before`: the shared `light_view` on its
/// light, shading and mode, and the preset's transfer function, unedited.
fn desktop_click(before: &ViewState, preset: &CinematicPreset) -> ViewState {
    let mut after = before.clone();
    preset.light_view(&mut after.light, &mut after.shading, &mut after.mode);
    after.preset = preset.tf_preset.into();
    after.tf = None;
    after
}

#[test]
fn clicking_the_pages_cinematic_presets_sets_the_transfer_function_and_lighting_the_desktops_set() {
    let scratch = tempfile::tempdir().expect("scratch folder");
    let (mut page, _server) = open_page(FRAGMENT, scratch.path(), WINDOW);
    let start = Fragment::parse(FRAGMENT).expect("fragment").view;
    assert_eq!(start.mode, RenderMode::Mip);

    // Open the "Light and shadows" section: its buttons are published once it is open.
    let header = settled_rect(
        &mut page,
        "the light section's header to stay put",
        "data-light-header",
        None,
    );
    println!("cinematic: the light section's header at {header:?}");
    assert!(
        header.bottom() < WINDOW[1] as f32,
        "the light section's header {header:?} is below the window"
    );
    click_until(&mut page, header, "the light section's header", |page| {
        published_rect(
            page,
            "data-cinematic-buttons",
            Some(CinematicPreset::ALL[0].label),
        )
        .is_some()
    });

    let mut before = wait_for_link(&mut page, "the page's first link", |_| true);
    // Soft tissue first, then bone: the second click starts from the first's look.
    for preset in [CinematicPreset::ALL[1], CinematicPreset::ALL[0]] {
        let button = settled_rect(
            &mut page,
            &format!("the {} button to stay put", preset.label),
            "data-cinematic-buttons",
            Some(preset.label),
        );
        assert!(
            button.bottom() < WINDOW[1] as f32,
            "the {} button {button:?} is below the window",
            preset.label
        );
        let expected = desktop_click(&before, &preset);
        assert_ne!(
            (before.light, before.preset.as_str()),
            (expected.light, expected.preset.as_str()),
            "the click on {} would change nothing: the test could not fail",
            preset.label
        );
        click_until(&mut page, button, preset.label, |page| {
            let hash = page.evaluate("location.hash");
            hash.as_str()
                .and_then(|h| Fragment::parse(h).ok())
                .is_some_and(|f| f.view.preset == preset.tf_preset)
        });
        let after = wait_for_link(
            &mut page,
            &format!("the link after {}", preset.label),
            |v| v.preset == preset.tf_preset && v.light == preset.light(),
        );
        assert_eq!(
            (after.light, after.shading, after.mode),
            (expected.light, expected.shading, expected.mode),
            "after {}: the page's light, shading and mode against the desktop's",
            preset.label
        );
        assert_eq!(
            (after.preset.as_str(), after.tf.is_none()),
            (expected.preset.as_str(), true),
            "after {}: the page's transfer function is not the preset's, unedited",
            preset.label
        );
        assert_eq!(
            (after.mode, after.shading),
            (RenderMode::Dvr, true),
            "a cinematic look is lit DVR"
        );
        before = after;
    }
}
