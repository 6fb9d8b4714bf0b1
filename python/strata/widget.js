// strata.Viewer's front end (widget.py), as anywidget's module contract wants it:
// `export default { render({ model, el }) }`.
//
// The viewer is the page `strata serve` serves at `/`, in an iframe. Its address (with the
// token in its fragment) is no trait, so it is never saved with the notebook: this module
// asks the kernel for it with a custom message when it renders (see widget.py's doc).
// The page and this module talk by postMessage (the page's side: web/src/embed_bridge.rs),
// each taking messages only from the other's window and origin, and sending only to it.
//
// The view traits (azimuth, elevation, zoom, preset) go both ways: a change from Python is
// posted to the page; the page reports its view once it rests after an orbit, and the traits
// follow. Until the page's first report the model leads (it may have changed while the page
// loaded); after it, a value the page reported is not posted back to it.

const VIEW_TRAITS = ["azimuth", "elevation", "zoom", "preset"];

const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));

// The view in the page's link format (viewer-ui/src/view_state.rs), within what it accepts.
function viewFragment(model) {
  const az = Number(model.get("azimuth"));
  const wrapped = ((((az + 180) % 360) + 360) % 360) - 180;
  return (
    `az=${Number.isFinite(wrapped) ? wrapped : 30}` +
    `&el=${clamp(Number(model.get("elevation")) || 0, -89, 89)}` +
    `&zoom=${clamp(Number(model.get("zoom")) || 1, 0.25, 8)}` +
    `&preset=${encodeURIComponent(model.get("preset"))}`
  );
}

function render({ model, el }) {
  const caption = document.createElement("div");
  caption.textContent = "Starting the Strata viewer…";
  caption.style.font = "12px sans-serif";
  caption.style.opacity = "0.7";
  const frame = document.createElement("iframe");
  frame.title = "Strata viewer";
  frame.style.width = "100%";
  frame.style.border = "0";
  frame.style.height = `${model.get("height")}px`;
  el.append(caption, frame);

  let pageOrigin = null; // the page's origin, once its address came
  let live = false; // the page reported its view: it listens
  const reported = {}; // the values the page last reported
  const waitingShots = []; // screenshot ids asked for before the page listened
  let applying = false; // the page's report is being set on the model: nothing to post

  const post = (message) => frame.contentWindow.postMessage(message, pageOrigin);

  const sendView = () => {
    // Before the page listens, its address carries the view it starts with.
    if (!live || applying) return;
    const view = {};
    for (const name of VIEW_TRAITS) {
      const value = model.get(name);
      if (reported[name] !== value) view[name] = value;
    }
    if (Object.keys(view).length > 0) post({ type: "strata:set-view", view });
  };

  const onPageMessage = (event) => {
    if (pageOrigin === null || event.origin !== pageOrigin) return;
    if (event.source !== frame.contentWindow) return;
    const data = event.data;
    if (data === null || typeof data !== "object") return;
    if (data.type === "strata:view") {
      const view = data.view || {};
      for (const name of VIEW_TRAITS) {
        if (name in view) reported[name] = view[name];
      }
      if (!live) {
        // The model leads: what changed while the page loaded goes to it.
        live = true;
        caption.textContent = `Strata · ${model.get("store") || "sample"}`;
        sendView();
        for (const id of waitingShots.splice(0)) post({ type: "strata:screenshot", id });
        return;
      }
      let changed = false;
      applying = true;
      try {
        for (const name of VIEW_TRAITS) {
          if (name in view && model.get(name) !== view[name]) {
            model.set(name, view[name]);
            changed = true;
          }
        }
      } finally {
        applying = false;
      }
      if (changed) model.save_changes();
    } else if (data.type === "strata:screenshot") {
      if (data.png instanceof ArrayBuffer) {
        model.send({ type: "screenshot", id: data.id }, undefined, [data.png]);
      } else {
        model.send({ type: "screenshot", id: data.id, error: String(data.error || "no image") });
      }
    } else if (data.type === "strata:error") {
      console.warn("strata viewer:", data.message);
    }
  };
  window.addEventListener("message", onPageMessage);

  const onKernelMessage = (message) => {
    if (message === null || typeof message !== "object") return;
    if (message.type === "connect" && pageOrigin === null) {
      const address = new URL(message.url);
      pageOrigin = address.origin;
      // The page listens to this window's origin only (`embed=`).
      const extra = `${viewFragment(model)}&embed=${encodeURIComponent(window.location.origin)}`;
      const fragment = address.hash.replace(/^#/, "");
      address.hash = fragment ? `${fragment}&${extra}` : extra;
      frame.src = address.href;
    } else if (message.type === "screenshot") {
      if (live) post({ type: "strata:screenshot", id: message.id });
      else waitingShots.push(message.id);
    }
  };
  model.on("msg:custom", onKernelMessage);
  for (const name of VIEW_TRAITS) model.on(`change:${name}`, sendView);
  const onHeight = () => {
    frame.style.height = `${model.get("height")}px`;
  };
  model.on("change:height", onHeight);
  model.send({ type: "ready" });

  return () => {
    window.removeEventListener("message", onPageMessage);
    model.off("msg:custom", onKernelMessage);
    for (const name of VIEW_TRAITS) model.off(`change:${name}`, sendView);
    model.off("change:height", onHeight);
    frame.remove();
  };
}

export default { render };
