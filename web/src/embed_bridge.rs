//! The page inside a notebook (issue 50): a postMessage bridge to the frame's parent, the
//! Jupyter widget `strata.Viewer` (python/strata/widget.js), which embeds the page in an
//! iframe.
//!
//! Off unless the link names the parent's origin (`embed=ORIGIN` in the fragment, which the
//! widget writes), and the server must also let that origin frame the page (its CSP
//! `frame-ancestors`, `strata.serve(frame_ancestors=...)`). Messages are taken only from the
//! parent window *and* from that exact origin, and sent only to it (postMessage's
//! targetOrigin): another page or frame can neither drive the view nor read the view or a
//! screenshot.
//!
//! The protocol (plain objects with a `type`):
//! - parent → page: `{type: "strata:set-view", view: {azimuth, elevation, zoom, preset}}`
//!   (any subset), `{type: "strata:screenshot", id}`;
//! - page → parent: `{type: "strata:view", view: {...}}` once the view rested for
//!   [`VIEW_REPORT_REST_S`] after it changed (an orbit reports where it ends, not each
//!   frame), `{type: "strata:screenshot", id, png}` (an ArrayBuffer, transferred) or
//!   `{type: "strata:screenshot", id, error}`, and `{type: "strata:error", message}` for a
//!   view the page refused.

use std::cell::RefCell;
use std::rc::Rc;

use strata_render::TransferFunction;
use wasm_bindgen::prelude::*;
use wasm_bindgen::JsCast;

use crate::view_state::ViewState;

/// How long the view must stay still before the page reports it (seconds).
pub const VIEW_REPORT_REST_S: f64 = 0.15;

/// How long after the page's first report the notebook's answer may take (seconds): the widget
/// answers that report with the model's view when the two differ (the model leads), and a view
/// the page changed before the answer came would be put back by it.
pub const MODEL_LEAD_WAIT_S: f64 = 2.0;

/// The view the parent sees: the widget's traits.
#[derive(Clone, Debug, PartialEq)]
struct ReportedView {
    azimuth: f64,
    elevation: f64,
    zoom: f64,
    preset: String,
}

impl ReportedView {
    fn of(view: &ViewState) -> Self {
        ReportedView {
            azimuth: view.azimuth_deg,
            elevation: view.elevation_deg,
            zoom: view.zoom,
            preset: view.preset.clone(),
        }
    }
}

/// What the parent asked for, queued by the message listener for the next frame.
enum Request {
    SetView(JsValue),
    Screenshot(JsValue),
}

/// The bridge of an embedded page.
pub struct EmbedBridge {
    /// The parent's origin, from the link.
    origin: String,
    inbox: Rc<RefCell<Vec<Request>>>,
    /// Kept for the page's life: dropping it would leave the listener calling a freed closure.
    _listener: Closure<dyn FnMut(web_sys::MessageEvent)>,
    reported: Option<ReportedView>,
    /// The view last seen and since when (page clock, seconds): reported once it rests.
    seen: Option<(ReportedView, f64)>,
    /// Screenshot requests waiting for a frame (their ids, as the parent sent them).
    screenshots: Vec<JsValue>,
    /// When the page first reported its view (page clock, seconds).
    first_report_at: Option<f64>,
    /// Whether the parent has set a view.
    view_applied: bool,
}

/// `embed=ORIGIN` of a link's fragment (percent-decoded), if any.
pub fn embed_origin(hash: &str) -> Option<String> {
    hash.trim_start_matches('#')
        .split('&')
        .filter_map(|pair| pair.split_once('='))
        .find(|(key, _)| *key == "embed")
        .and_then(|(_, value)| js_sys::decode_uri_component(value).ok())
        .map(String::from)
        .filter(|origin| !origin.is_empty() && origin != "null" && origin != "*")
}

/// Why the bridge to the parent page could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    #[error("no window")]
    NoWindow,
    #[error("the page has no parent window")]
    NoParent,
    /// A JavaScript exception, as its debug text.
    #[error("{0}")]
    Js(String),
}

/// Why the parent's view update was refused (it is answered with a `strata:error`).
#[derive(Debug, thiserror::Error)]
enum ViewUpdateError {
    #[error("view `{0}` must be a finite number")]
    NotANumber(&'static str),
    #[error("view `preset` '{0}' is not one of {presets}", presets = TransferFunction::PRESETS.join(", "))]
    UnknownPreset(String),
    #[error("view `preset` must be a name")]
    PresetNotAName,
}

fn field(object: &JsValue, name: &str) -> JsValue {
    js_sys::Reflect::get(object, &JsValue::from_str(name)).unwrap_or(JsValue::UNDEFINED)
}

impl EmbedBridge {
    /// Listens to the parent at `origin`; a message wakes the UI (`ctx`).
    pub fn new(origin: String, ctx: egui::Context) -> Result<Self, BridgeError> {
        let window = web_sys::window().ok_or(BridgeError::NoWindow)?;
        let parent = window
            .parent()
            .map_err(|e| BridgeError::Js(format!("{e:?}")))?
            .ok_or(BridgeError::NoParent)?;
        let inbox: Rc<RefCell<Vec<Request>>> = Rc::default();
        let (queue, expected) = (inbox.clone(), origin.clone());
        let listener = Closure::<dyn FnMut(web_sys::MessageEvent)>::new(
            move |event: web_sys::MessageEvent| {
                // Both checks: the origin alone would let another frame of the same origin
                // speak, the source alone a parent that navigated elsewhere.
                // Compared as objects: a cross-origin window is no `instanceof Window` here.
                let from_parent = event
                    .source()
                    .is_some_and(|s| JsValue::from(s) == JsValue::from(parent.clone()));
                if event.origin() != expected || !from_parent {
                    return;
                }
                let data = event.data();
                let request = match field(&data, "type").as_string().as_deref() {
                    Some("strata:set-view") => Request::SetView(field(&data, "view")),
                    Some("strata:screenshot") => Request::Screenshot(field(&data, "id")),
                    _ => return,
                };
                queue.borrow_mut().push(request);
                ctx.request_repaint();
            },
        );
        window
            .add_event_listener_with_callback("message", listener.as_ref().unchecked_ref())
            .map_err(|e| BridgeError::Js(format!("{e:?}")))?;
        Ok(EmbedBridge {
            origin,
            inbox,
            _listener: listener,
            reported: None,
            seen: None,
            screenshots: Vec::new(),
            first_report_at: None,
            view_applied: false,
        })
    }

    /// Applies the parent's requests to `view` (a view it refuses is answered with an
    /// error and leaves `view` as it was) and keeps the screenshot requests for
    /// [`take_screenshot_requests`](Self::take_screenshot_requests).
    pub fn apply(&mut self, view: &mut ViewState) {
        let requests = std::mem::take(&mut *self.inbox.borrow_mut());
        for request in requests {
            match request {
                Request::SetView(update) => {
                    self.view_applied = true;
                    if let Err(problem) = apply_view(view, &update) {
                        let message = problem.to_string();
                        self.post(&[("type", "strata:error".into()), ("message", message.into())]);
                    }
                }
                Request::Screenshot(id) => self.screenshots.push(id),
            }
        }
    }

    /// The screenshot requests waiting; the caller answers them
    /// ([`answer_screenshot`](Self::answer_screenshot)).
    pub fn take_screenshot_requests(&mut self) -> Vec<JsValue> {
        std::mem::take(&mut self.screenshots)
    }

    /// Whether screenshots were asked for.
    pub fn screenshots_wanted(&self) -> bool {
        !self.screenshots.is_empty()
    }

    /// Reports the view once it rested after a change; returns when to look again (seconds
    /// from now) while a report is due.
    pub fn report(&mut self, view: &ViewState, now: f64, dragging: bool) -> Option<f64> {
        let current = ReportedView::of(view);
        if self.reported.as_ref() == Some(&current) {
            self.seen = None;
            return None;
        }
        let since = match &self.seen {
            Some((seen, since)) if *seen == current => *since,
            _ => {
                self.seen = Some((current.clone(), now));
                now
            }
        };
        let rested = now - since;
        if dragging || rested < VIEW_REPORT_REST_S {
            return Some((VIEW_REPORT_REST_S - rested).max(0.0) + 0.01);
        }
        let object = js_sys::Object::new();
        for (name, value) in [
            ("azimuth", JsValue::from_f64(current.azimuth)),
            ("elevation", JsValue::from_f64(current.elevation)),
            ("zoom", JsValue::from_f64(current.zoom)),
            ("preset", JsValue::from_str(&current.preset)),
        ] {
            let _ = js_sys::Reflect::set(&object, &name.into(), &value);
        }
        self.post(&[("type", "strata:view".into()), ("view", object.into())]);
        self.first_report_at.get_or_insert(now);
        self.reported = Some(current);
        self.seen = None;
        None
    }

    /// Whether the notebook has led: its answer to the page's first report (the model's view,
    /// which wins over what the page did meanwhile) came, or [`MODEL_LEAD_WAIT_S`] passed
    /// after that report without one (the views were equal). Until then a change the page
    /// makes of its own (the `bench=` orbit) could be put back.
    pub fn model_has_led(&self, now: f64) -> bool {
        self.view_applied
            || self
                .first_report_at
                .is_some_and(|at| now - at >= MODEL_LEAD_WAIT_S)
    }

    /// Answers screenshot `id` with `png` (or the reason there is none).
    pub fn answer_screenshot(&self, id: &JsValue, png: Result<Vec<u8>, String>) {
        match png {
            Ok(png) => {
                let buffer = js_sys::Uint8Array::from(png.as_slice()).buffer();
                let message = object(&[
                    ("type", "strata:screenshot".into()),
                    ("id", id.clone()),
                    ("png", buffer.clone().into()),
                ]);
                self.post_with_transfer(&message, &js_sys::Array::of1(&buffer));
            }
            Err(error) => self.post(&[
                ("type", "strata:screenshot".into()),
                ("id", id.clone()),
                ("error", error.into()),
            ]),
        }
    }

    fn post(&self, fields: &[(&str, JsValue)]) {
        self.post_with_transfer(&object(fields), &js_sys::Array::new());
    }

    fn post_with_transfer(&self, message: &JsValue, transfer: &js_sys::Array) {
        let Some(parent) = web_sys::window().and_then(|w| w.parent().ok().flatten()) else {
            return;
        };
        // The parent's own postMessage, looked up on it: a cross-origin window is reachable
        // only through the properties it exposes, not through this realm's Window prototype.
        let post = js_sys::Reflect::get(&parent, &JsValue::from_str("postMessage"))
            .ok()
            .and_then(|f| f.dyn_into::<js_sys::Function>().ok());
        let Some(post) = post else {
            return;
        };
        // targetOrigin: a parent that navigated to another origin receives nothing.
        if let Err(e) = post.call3(
            &parent,
            message,
            &JsValue::from_str(&self.origin),
            transfer.as_ref(),
        ) {
            web_sys::console::error_1(&format!("strata: postMessage: {e:?}").into());
        }
    }
}

fn object(fields: &[(&str, JsValue)]) -> JsValue {
    let object = js_sys::Object::new();
    for (name, value) in fields {
        let _ = js_sys::Reflect::set(&object, &JsValue::from_str(name), value);
    }
    object.into()
}

/// Sets what `update` names on `view`, all or nothing, within the page's own bounds.
fn apply_view(view: &mut ViewState, update: &JsValue) -> Result<(), ViewUpdateError> {
    let number = |name: &'static str| -> Result<Option<f64>, ViewUpdateError> {
        let value = field(update, name);
        if value.is_undefined() || value.is_null() {
            return Ok(None);
        }
        match value.as_f64().filter(|v| v.is_finite()) {
            Some(v) => Ok(Some(v)),
            None => Err(ViewUpdateError::NotANumber(name)),
        }
    };
    let azimuth = number("azimuth")?;
    let elevation = number("elevation")?;
    let zoom = number("zoom")?;
    let preset = field(update, "preset");
    let preset = match preset.as_string() {
        Some(name) if TransferFunction::PRESETS.contains(&name.as_str()) => Some(name),
        Some(name) => return Err(ViewUpdateError::UnknownPreset(name)),
        None if preset.is_undefined() || preset.is_null() => None,
        None => return Err(ViewUpdateError::PresetNotAName),
    };
    if let Some(azimuth) = azimuth {
        view.azimuth_deg = azimuth;
    }
    // The page's own limits (the orbit's and the zoom slider's): the report then tells the
    // parent the value it got.
    if let Some(elevation) = elevation {
        view.elevation_deg = elevation.clamp(-89.0, 89.0);
    }
    if let Some(zoom) = zoom {
        view.zoom = zoom.clamp(0.25, 8.0);
    }
    if let Some(preset) = preset {
        if view.preset != preset {
            view.preset = preset;
            // The named preset itself, not an edit of the previous one (the side panel's
            // editor follows the view's preset).
            view.tf = None;
        }
    }
    Ok(())
}
