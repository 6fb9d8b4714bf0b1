//! The page's canvas attributes the browser tests read (`data-views`, `data-pick`,
//! `data-measurements`, `data-segmentation`, …): what the page shows, published where a test
//! driving a real Chromium can read it. One setter, written only when a value changes.

/// Sets the page canvas's attribute `name` to `value` when it differs.
pub(crate) fn set(name: &str, value: &str) {
    let Some(canvas) = web_sys::window()
        .and_then(|w| w.document())
        .and_then(|d| d.get_element_by_id("strata-canvas"))
    else {
        return;
    };
    if canvas.get_attribute(name).as_deref() != Some(value) {
        let _ = canvas.set_attribute(name, value);
    }
}
