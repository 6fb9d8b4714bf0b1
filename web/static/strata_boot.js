// Starts the viewer, or says plainly why this browser cannot run it (issue 39: limits of the
// browser). The module itself reports what it finds later (no adapter, WebGL only, lost device).
const message = (html) => {
  const box = document.getElementById("strata-message");
  box.innerHTML = html;
  box.hidden = false;
  document.getElementById("strata-canvas").hidden = true;
};
if (!window.isSecureContext) {
  message("<h2>WebGPU needs a secure page</h2><p>This page was opened over plain http from " +
    "another host. Browsers expose WebGPU only on https or on localhost: start the server " +
    "with <code>strata serve --tls-cert CERT.pem --tls-key KEY.pem</code> and open the https " +
    "address, or open it on the server's own machine as http://localhost.</p>");
} else if (!navigator.gpu) {
  message("<h2>This browser has no WebGPU</h2><p>The Strata viewer draws with WebGPU: " +
    "Chrome or Edge 113 or newer, Firefox 141 or newer (Windows; other systems behind a " +
    "setting), Safari 26 or newer. On Linux, Chrome needs " +
    "<code>--enable-unsafe-webgpu</code> on some drivers.</p>");
} else {
  const { default: init } = await import("./strata_web.js");
  try {
    await init({ module_or_path: "./strata_web_bg.wasm" });
  } catch (e) {
    message("<h2>The viewer could not start</h2><pre></pre>");
    document.querySelector("#strata-message pre").textContent = String(e);
  }
}
