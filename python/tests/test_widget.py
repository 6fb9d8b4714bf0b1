"""strata.Viewer, the Jupyter widget, without a browser: its traits, its server, where the
token goes (never into the saved notebook), the screenshot's PNG and its timeout, and the
hint when anywidget is missing. The front end runs in Chromium in web/tests/browser.rs
(`the_notebook_widget_draws_the_volume_and_syncs_its_view_both_ways`)."""

from __future__ import annotations

import json
import os
import pathlib
import struct
import subprocess
import sys
import threading
import urllib.error
import urllib.request
import zlib
from typing import Any

import numpy as np
import pytest

import strata
from strata import widget

try:
    import anywidget  # noqa: F401
except ImportError as e:
    raise ImportError(
        "the widget's tests need anywidget: pip install anywidget (.ci/run installs it)"
    ) from e

#: The browser viewer's files, as `cargo run -p xtask -- web` writes them (.ci/run's web
#: stage runs before the Python one).
WEB_DIST = pathlib.Path(__file__).resolve().parents[2] / "web" / "dist"


@pytest.fixture()
def web_dist() -> pathlib.Path:
    if not (WEB_DIST / "index.html").is_file():
        pytest.fail(
            f"{WEB_DIST}: the browser viewer is not built; run `cargo run -p xtask -- web`"
        )
    return WEB_DIST


@pytest.fixture()
def store(tmp_path: pathlib.Path) -> pathlib.Path:
    a = np.arange(24 * 20 * 16, dtype=np.uint16).reshape(24, 20, 16)
    strata.from_numpy(a, dst=tmp_path / "scan.strata").close()
    return tmp_path / "scan.strata"


def front_end(viewer: strata.Viewer) -> list[dict]:
    """The custom messages the widget sends, with a front end that has just rendered."""
    sent: list[dict] = []
    viewer.send = lambda content, buffers=None: sent.append(content)  # type: ignore[method-assign]
    viewer._on_front_end_message(viewer, {"type": "ready"}, [])
    return sent


def get(url: str, token: str | None = None) -> tuple[int, dict[str, str], bytes]:
    request = urllib.request.Request(url)
    if token is not None:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=10) as answer:
            return answer.status, lower_keys(answer.headers), answer.read()
    except urllib.error.HTTPError as e:
        return e.code, lower_keys(e.headers), e.read()


def lower_keys(headers: Any) -> dict[str, str]:
    return {name.lower(): value for name, value in headers.items()}


def test_the_viewer_serves_its_store_and_keeps_the_token_out_of_the_saved_state(
    store: pathlib.Path, web_dist: pathlib.Path
) -> None:
    viewer = strata.Viewer(store, web_viewer=web_dist, azimuth=45.0)
    try:
        assert (viewer.azimuth, viewer.elevation, viewer.zoom, viewer.preset) == (
            45.0,
            15.0,
            1.0,
            "ct-bone",
        )
        assert viewer.store == "scan"
        state = viewer.get_state()
        for trait in ("azimuth", "elevation", "zoom", "preset"):
            assert trait in state
        with pytest.raises(Exception, match="preset"):
            viewer.preset = "not-a-preset"

        # The front end gets the page's address (with the token) by a custom message...
        (connect,) = front_end(viewer)
        assert connect["type"] == "connect"
        base, fragment = connect["url"].split("#", 1)
        assert base.startswith("http://127.0.0.1:") and base.endswith("/")
        fields = dict(pair.split("=", 1) for pair in fragment.split("&"))
        assert fields["store"] == "scan"
        token = fields["token"]
        assert len(token) >= 16

        # ...and nothing the notebook saves carries it: the synced state, the widget
        # manager's saved state (what "save widget state" writes), the output, the repr.
        from ipywidgets.embed import embed_data

        saved = json.dumps(embed_data(views=[viewer]), default=str)
        assert '"azimuth": 45.0' in saved
        for text in (
            json.dumps(viewer.get_state(), default=str),
            saved,
            json.dumps(viewer._repr_mimebundle_(), default=str),
            repr(viewer),
        ):
            assert token not in text
            assert base not in text

        # The server wants the token for data; the page may be framed by a local notebook.
        status, _, _ = get(f"{base}v1/stores/scan")
        assert status == 401
        status, _, _ = get(f"{base}v1/stores/scan", token)
        assert status == 200
        status, headers, body = get(base)
        assert status == 200 and b"strata_boot.js" in body
        csp = headers["content-security-policy"]
        assert "frame-ancestors http://localhost:* http://127.0.0.1:*" in csp
        assert "x-frame-options" not in headers

        # A screenshot without a live front end ends in a clear error, not a hang.
        with pytest.raises(TimeoutError, match="live notebook front end"):
            viewer.screenshot(timeout=0.3)
    finally:
        viewer.close()
    # Closing stops the server.
    with pytest.raises(OSError):
        urllib.request.urlopen(base, timeout=2)


def test_a_served_store_is_shown_as_it_is_and_a_bad_source_is_refused() -> None:
    viewer = strata.Viewer("http://127.0.0.1:9/v1/stores/ct%20head", token="t" * 20)
    try:
        (connect,) = front_end(viewer)
        assert connect["url"] == f"http://127.0.0.1:9/#store=ct%20head&token={'t' * 20}"
        assert viewer.store == "ct head"
    finally:
        viewer.close()
    with pytest.raises(ValueError, match="served store's URL"):
        strata.Viewer("http://127.0.0.1:9/elsewhere")
    with pytest.raises(TypeError, match="strata.Viewer takes"):
        strata.Viewer(42)


def test_the_viewer_needs_the_page_files_and_says_how_to_build_them(
    store: pathlib.Path, tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(widget.WEB_VIEWER_ENV, raising=False)
    with pytest.raises(FileNotFoundError, match="cargo run -p xtask -- web"):
        strata.Viewer(store)
    with pytest.raises(FileNotFoundError, match="index.html"):
        strata.Viewer(store, web_viewer=tmp_path)


def png_bytes(rgba: np.ndarray, filters: list[int]) -> bytes:
    """An RGBA PNG whose rows use the given filter types (0 to 4), as an encoder writes."""
    height, width, _ = rgba.shape
    stride = width * 4
    rows = rgba.reshape(height, stride).astype(np.int32)
    raw = bytearray()
    for y in range(height):
        kind = filters[y % len(filters)]
        line, up = rows[y], rows[y - 1] if y else np.zeros(stride, np.int32)
        out = np.zeros(stride, np.int32)
        for x in range(stride):
            left = line[x - 4] if x >= 4 else 0
            up_left = up[x - 4] if x >= 4 and y else 0
            p = left + up[x] - up_left
            pa, pb, pc = abs(p - left), abs(p - up[x]), abs(p - up_left)
            paeth = left if pa <= pb and pa <= pc else (up[x] if pb <= pc else up_left)
            predictor = [0, left, up[x], (left + up[x]) // 2, paeth][kind]
            out[x] = (line[x] - predictor) & 0xFF
        raw.append(kind)
        raw.extend(out.astype(np.uint8).tobytes())

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body)
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", width, height, 8, 6, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(bytes(raw)))
        + chunk(b"IEND", b"")
    )


def test_a_screenshot_is_the_front_ends_png_as_rgba(store: pathlib.Path, web_dist: pathlib.Path) -> None:
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, size=(7, 5, 4), dtype=np.uint8)
    # Every row filter, so the decoder's each branch is checked against the encoder's.
    png = png_bytes(image, [0, 1, 2, 3, 4])
    assert np.array_equal(widget.decode_png(png), image)
    with pytest.raises(ValueError, match="not a PNG"):
        widget.decode_png(b"GIF89a")

    viewer = strata.Viewer(store, web_viewer=web_dist)
    try:
        requests: list[dict] = []

        def answer(content: dict, buffers: list | None = None) -> None:
            # The front end answers on another thread, as the kernel's comm would.
            requests.append(content)
            reply = {"type": "screenshot", "id": content["id"]}
            threading.Timer(
                0.05, viewer._on_front_end_message, (viewer, reply, [memoryview(png)])
            ).start()

        viewer.send = answer  # type: ignore[method-assign]
        shot = viewer.screenshot(timeout=10)
        assert shot.dtype == np.uint8 and shot.shape == (7, 5, 4)
        assert np.array_equal(shot, image)
        assert requests == [{"type": "screenshot", "id": 1}]

        def refuse(content: dict, buffers: list | None = None) -> None:
            reply = {"type": "screenshot", "id": content["id"], "error": "GPU lost"}
            threading.Timer(0.05, viewer._on_front_end_message, (viewer, reply, [])).start()

        viewer.send = refuse  # type: ignore[method-assign]
        with pytest.raises(RuntimeError, match="GPU lost"):
            viewer.screenshot(timeout=10)
    finally:
        viewer.close()


def test_strata_imports_without_anywidget_and_viewer_says_how_to_get_it(tmp_path: pathlib.Path) -> None:
    # A Python where `import anywidget` fails, as where it is not installed.
    script = (
        "import sys; sys.modules['anywidget'] = None\n"
        "import strata\n"
        "assert strata.open and strata.serve\n"
        "try:\n"
        "    strata.Viewer('scan.strata')\n"
        "except ImportError as e:\n"
        "    print('HINT:', e)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env={**os.environ},
    )
    assert done.returncode == 0, done.stderr
    assert "HINT: strata.Viewer needs anywidget" in done.stdout
    assert "pip install anywidget" in done.stdout
