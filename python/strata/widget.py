"""``strata.Viewer``: the browser viewer in a Jupyter notebook cell (an anywidget).

>>> viewer = strata.Viewer("scan.strata")   # starts a loopback strata.serve for the store
>>> viewer                                   # the cell shows the viewer; orbit it there
>>> viewer.azimuth = 30                      # moves the view; orbiting updates the traits
>>> viewer.preset = "ct-bone"
>>> image = viewer.screenshot()              # (H, W, 4) uint8, the frame on screen

The widget's front end (widget.js) embeds the page that ``strata serve`` serves at ``/`` in an
iframe and talks to it with postMessage (the page's side: web/src/embed_bridge.rs).

Where the token goes, and why it never reaches the saved notebook: a notebook saves the
widget's *state*, the traits tagged ``sync=True`` (with "save widget state"), and the cell's
output, which for a widget is only its model id. The page's address carries the token in its
fragment, so it is no trait: the front end asks for it with a custom message when it renders
(``{"type": "ready"}``) and gets it in the answer (``{"type": "connect", "url": ...}``).
Custom messages travel over the widget's comm and are not stored anywhere; the iframe's
``src`` lives in the browser's page only.
"""

from __future__ import annotations

import itertools
import os
import pathlib
import secrets
import threading
import time
import urllib.parse
import weakref
import zlib
from typing import Any

import numpy as np

#: The page's transfer-function presets (strata-render's TransferFunction::PRESETS).
PRESETS = ("ct-bone", "ct-soft-tissue", "ct-lung", "ct-vessels", "mr-default")

#: Who may frame the page a Viewer starts: a notebook served from this machine (JupyterLab,
#: Notebook, Voilà) and VS Code's notebook webviews. ``Viewer(frame_ancestors=...)`` says
#: otherwise (a JupyterHub's origin, say).
DEFAULT_FRAME_ANCESTORS = (
    "http://localhost:* http://127.0.0.1:* https://localhost:* https://127.0.0.1:* "
    "vscode-webview:"
)

#: Where the browser viewer's files are looked for when ``web_viewer`` is not given.
WEB_VIEWER_ENV = "STRATA_WEB_VIEWER_DIR"

INSTALL_HINT = (
    "strata.Viewer needs anywidget (the Jupyter widget framework): pip install anywidget"
)

try:
    import anywidget
    import traitlets
except ImportError as _missing:  # the rest of strata works without it
    _MISSING: ImportError | None = _missing
else:
    _MISSING = None


def _web_viewer_dir(web_viewer: str | os.PathLike[str] | None) -> pathlib.Path:
    """The folder with the page's files: ``web_viewer``, else $STRATA_WEB_VIEWER_DIR."""
    chosen = web_viewer if web_viewer is not None else os.environ.get(WEB_VIEWER_ENV)
    if chosen is None:
        raise FileNotFoundError(
            "strata.Viewer serves the browser viewer, whose files are not in this package: "
            "build them with `cargo run -p xtask -- web` (they go to web/dist/ of the "
            f"checkout) and pass web_viewer=PATH or set {WEB_VIEWER_ENV}=PATH"
        )
    folder = pathlib.Path(chosen)
    if not (folder / "index.html").is_file():
        raise FileNotFoundError(
            f"{folder}: no browser viewer here (index.html is missing); build it with "
            "`cargo run -p xtask -- web`, which writes web/dist/"
        )
    return folder


def _served_page(url: str, token: str | None) -> str:
    """The page's address for a store URL ``BASE/v1/stores/NAME`` (token in the fragment)."""
    parts = urllib.parse.urlsplit(url)
    prefix, _, name = parts.path.rstrip("/").rpartition("/v1/stores/")
    if parts.scheme not in ("http", "https") or not name or "/" in name:
        raise ValueError(
            f"'{url}' is not a served store's URL (http://HOST:PORT/v1/stores/NAME)"
        )
    fragment = "store=" + urllib.parse.quote(urllib.parse.unquote(name), safe="")
    if token is not None:
        fragment += "&token=" + urllib.parse.quote(token, safe="")
    return urllib.parse.urlunsplit((parts.scheme, parts.netloc, prefix + "/", "", fragment))


def decode_png(data: bytes) -> np.ndarray:
    """An 8-bit RGBA or RGB PNG (not interlaced) as an (H, W, 4) uint8 array."""
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("the screenshot is not a PNG")
    pos, header, idat = 8, None, []
    while pos + 8 <= len(data):
        length = int.from_bytes(data[pos : pos + 4], "big")
        kind = data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        if len(body) != length:
            raise ValueError("the screenshot's PNG is cut short")
        if kind == b"IHDR":
            header = body
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        pos += 12 + length
    if header is None or len(header) != 13:
        raise ValueError("the screenshot's PNG has no header")
    width = int.from_bytes(header[0:4], "big")
    height = int.from_bytes(header[4:8], "big")
    depth, colour, interlace = header[8], header[9], header[12]
    channels = {6: 4, 2: 3}.get(colour)
    if depth != 8 or channels is None or interlace != 0:
        raise ValueError(
            f"the screenshot's PNG is {depth}-bit colour type {colour}, interlace {interlace}; "
            "8-bit RGB(A), not interlaced, expected"
        )
    stride = width * channels
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8)
    if raw.size != height * (stride + 1):
        raise ValueError("the screenshot's PNG data does not match its size")
    rows = raw.reshape(height, stride + 1)
    out = np.zeros((height, stride), np.uint8)
    previous = np.zeros(stride, np.int32)
    for y in range(height):
        kind, line = rows[y, 0], rows[y, 1:].astype(np.int32)
        if kind == 0:
            recon = line
        elif kind == 1:  # Sub: a running sum along the row, per channel
            recon = np.cumsum(line.reshape(width, channels), axis=0).reshape(-1)
        elif kind == 2:  # Up
            recon = line + previous
        elif kind in (3, 4):  # Average, Paeth: each byte needs its left neighbour's result
            recon = np.zeros(stride, np.int32)
            for x in range(stride):
                left = recon[x - channels] if x >= channels else 0
                up = previous[x]
                if kind == 3:
                    recon[x] = (line[x] + (left + up) // 2) & 0xFF
                    continue
                up_left = previous[x - channels] if x >= channels else 0
                p = left + up - up_left
                pa, pb, pc = abs(p - left), abs(p - up), abs(p - up_left)
                pred = left if pa <= pb and pa <= pc else (up if pb <= pc else up_left)
                recon[x] = (line[x] + pred) & 0xFF
        else:
            raise ValueError(f"the screenshot's PNG has an unknown row filter {kind}")
        recon = recon & 0xFF
        out[y] = recon
        previous = recon
    image = out.reshape(height, width, channels)
    if channels == 3:
        image = np.concatenate([image, np.full((height, width, 1), 255, np.uint8)], axis=2)
    return image


if _MISSING is not None:

    class Viewer:  # noqa: D101 - stands in for the widget when anywidget is missing
        """The browser viewer as a notebook widget; needs ``pip install anywidget``."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            raise ImportError(INSTALL_HINT) from _MISSING

else:

    class Viewer(anywidget.AnyWidget):  # type: ignore[no-redef]
        """The Strata browser viewer in a notebook cell, streaming one store.

        ``source`` is a store's folder (or a :class:`strata.Volume` opened from one): the
        widget serves it on loopback (:func:`strata.serve`, a random token) until
        :meth:`close`, or until the widget is garbage-collected. A served store's URL
        (``http://HOST:PORT/v1/stores/NAME``, with ``token``) is shown as it is; its server
        must let the notebook frame the page (``frame_ancestors``).

        The view is a set of traits synced both ways: ``azimuth`` and ``elevation``
        (degrees), ``zoom`` (1 frames the volume) and ``preset``. Setting one moves the view;
        orbiting, zooming or choosing a preset in the cell updates them once the view rests.

        ``web_viewer``: the folder of the browser viewer's files (``cargo run -p xtask --
        web`` writes web/dist/); default ``$STRATA_WEB_VIEWER_DIR``.
        """

        _esm = pathlib.Path(__file__).with_name("widget.js")

        azimuth = traitlets.Float(30.0, help="Orbit azimuth, degrees").tag(sync=True)
        elevation = traitlets.Float(15.0, help="Orbit elevation, degrees (±89)").tag(sync=True)
        zoom = traitlets.Float(1.0, help="Zoom; 1 frames the volume (0.25 to 8)").tag(sync=True)
        preset = traitlets.Enum(PRESETS, "ct-bone", help="Transfer-function preset").tag(
            sync=True
        )
        height = traitlets.Int(480, help="The cell's height, CSS pixels").tag(sync=True)
        # The store's name, for the cell's caption: no secret in it.
        store = traitlets.Unicode("", read_only=True).tag(sync=True)

        def __init__(
            self,
            source: Any,
            *,
            token: str | None = None,
            web_viewer: str | os.PathLike[str] | None = None,
            frame_ancestors: str = DEFAULT_FRAME_ANCESTORS,
            **traits: Any,
        ) -> None:
            from ._serve import serve

            server = None
            if isinstance(source, (str, os.PathLike)):
                text = os.fspath(source)
                remote = text.startswith(("http://", "https://"))
                url, path = (text, None) if remote else (None, text)
            else:  # a strata.Volume: a folder's path, or the URL it was opened from
                url, path = getattr(source, "url", None), getattr(source, "path", None)
            if url is not None:
                page = _served_page(url, token)
            elif path is not None:
                # A token although the server listens on loopback only: other users of this
                # machine can reach loopback too.
                secret = secrets.token_urlsafe(24)
                server = serve(
                    path,
                    token=secret,
                    web_viewer=_web_viewer_dir(web_viewer),
                    frame_ancestors=frame_ancestors,
                )
                urls = server.urls
                if len(urls) != 1:
                    server.stop()
                    raise ValueError(f"{path}: one store expected, found {len(urls)}")
                page = _served_page(urls[0], secret)
            else:
                raise TypeError(
                    "strata.Viewer takes a store's path, a served store's URL or a "
                    f"strata.Volume, not {type(source).__name__}"
                )
            super().__init__(**traits)
            name = page.split("store=", 1)[1].split("&", 1)[0]
            self.set_trait("store", urllib.parse.unquote(name))
            # Private, not a trait (see the module doc): sent to a front end that asks.
            self._page = page
            self._server = server
            self._shots: dict[int, list[Any]] = {}
            self._shot_ids = itertools.count(1)
            self._lock = threading.Lock()
            # The server stops with the widget, closed or collected (the finalizer holds the
            # server, not the widget, so it does not keep the widget alive).
            self._stop_server = weakref.finalize(self, server.stop) if server else None
            self.on_msg(self._on_front_end_message)

        def close(self) -> None:
            """Closes the widget and stops its server (idempotent)."""
            # getattr: a Viewer whose __init__ failed is closed too (ipywidgets' __del__).
            stop_server = getattr(self, "_stop_server", None)
            if stop_server is not None:
                stop_server()
            super().close()

        def _on_front_end_message(self, _widget: Any, content: Any, buffers: list[Any]) -> None:
            if not isinstance(content, dict):
                return
            kind = content.get("type")
            if kind == "ready":
                self.send({"type": "connect", "url": self._page})
            elif kind == "screenshot":
                with self._lock:
                    waiting = self._shots.get(content.get("id"))
                if waiting is None:
                    return
                if content.get("error"):
                    waiting[1] = RuntimeError(f"the viewer could not take it: {content['error']}")
                elif buffers:
                    waiting[1] = bytes(buffers[0])
                else:
                    waiting[1] = RuntimeError("the viewer's answer carried no image")
                waiting[0].set()

        def screenshot(self, timeout: float = 30.0) -> np.ndarray:
            """The frame on screen as an (H, W, 4) uint8 RGBA array.

            Needs the widget shown in a live front end; raises :class:`TimeoutError` when no
            answer comes within ``timeout`` seconds. In a notebook cell the answer can only
            arrive while the kernel reads messages: with ``jupyter-ui-poll`` installed this
            call reads them while it waits; without it, call it in a later cell than the one
            that shows the widget and it still times out, so install it.
            """
            request = next(self._shot_ids)
            done = threading.Event()
            with self._lock:
                self._shots[request] = [done, None]
            try:
                self.send({"type": "screenshot", "id": request})
                _wait(done, timeout)
                with self._lock:
                    answer = self._shots[request][1]
            finally:
                with self._lock:
                    self._shots.pop(request, None)
            if answer is None:
                raise TimeoutError(
                    f"the viewer did not answer the screenshot within {timeout:g} s: it takes "
                    "the widget shown in a live notebook front end (display it first); in "
                    "Jupyter, pip install jupyter-ui-poll lets this call read the answer "
                    "while it waits"
                )
            if isinstance(answer, Exception):
                raise answer
            return decode_png(answer)

        def __repr__(self) -> str:
            # The page's address (and its token) stays out of reprs too.
            return (
                f"<strata.Viewer {self.store}: azimuth={self.azimuth:g} "
                f"elevation={self.elevation:g} zoom={self.zoom:g} preset={self.preset}>"
            )


def _wait(done: threading.Event, timeout: float) -> None:
    """Waits for ``done``, letting a Jupyter kernel read the front end's answer meanwhile."""
    deadline = time.monotonic() + timeout
    try:
        from IPython import get_ipython
        from jupyter_ui_poll import ui_events  # type: ignore[import-not-found]
    except ImportError:
        done.wait(timeout)
        return
    if getattr(get_ipython(), "kernel", None) is None:  # no kernel: nothing to read
        done.wait(timeout)
        return
    with ui_events() as poll:
        while not done.is_set() and time.monotonic() < deadline:
            poll(10)
            done.wait(0.02)
