"""strata.render: the same frame as `strata render` with the same options, bit for bit, and its
errors as the documented exceptions. The GPU on CI is lavapipe; images are 128².

The `strata` binary is the one CI builds before this stage (cargo's target directory,
$CARGO_TARGET_DIR or the checkout's target/), or $STRATA_BIN.
"""

from __future__ import annotations

import os
import pathlib
import struct
import subprocess
import zlib

import numpy as np
import pytest

import strata

REPO = pathlib.Path(__file__).resolve().parents[2]


def strata_binary() -> pathlib.Path:
    """The `strata` command line to compare with; a missing one fails with how to build it."""
    if os.environ.get("STRATA_BIN"):
        path = pathlib.Path(os.environ["STRATA_BIN"])
        if not path.is_file():
            pytest.fail(f"STRATA_BIN={path} is not a file")
        return path
    target = pathlib.Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target"))
    found = [target / profile / "strata" for profile in ("debug", "release")]
    found = [p for p in found if p.is_file()]
    if not found:
        pytest.fail(
            f"no strata binary in {target}/debug or {target}/release: build it with "
            "`cargo build -p strata-app` (CI builds it before the python stage) or set STRATA_BIN"
        )
    return max(found, key=lambda p: p.stat().st_mtime)


def read_png_rgb(path: pathlib.Path) -> np.ndarray:
    """An 8-bit RGB, non-interlaced PNG (what `strata render` writes) as (h, w, 3) uint8."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    assert header is not None, f"{path}: no IHDR"
    width, height, depth, colour, _, _, interlace = header
    assert (depth, colour, interlace) == (8, 2, 0), f"{path}: not 8-bit RGB non-interlaced"
    raw = zlib.decompress(idat)
    stride, bpp = width * 3, 3
    out = np.zeros((height, stride), dtype=np.uint8)
    prev = np.zeros(stride, dtype=np.int32)
    for y in range(height):
        row = raw[y * (stride + 1) : (y + 1) * (stride + 1)]
        kind, line = row[0], np.frombuffer(row[1:], dtype=np.uint8).astype(np.int32)
        cur = np.zeros(stride, dtype=np.int32)
        for x in range(stride):
            a = cur[x - bpp] if x >= bpp else 0
            b = prev[x]
            c = prev[x - bpp] if x >= bpp else 0
            if kind == 0:
                p = 0
            elif kind == 1:
                p = a
            elif kind == 2:
                p = b
            elif kind == 3:
                p = (a + b) // 2
            elif kind == 4:
                pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                p = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            else:
                raise AssertionError(f"{path}: PNG filter {kind}")
            cur[x] = (line[x] + p) & 0xFF
        out[y] = cur
        prev = cur
    return out.reshape(height, width, 3)


@pytest.fixture(scope="module")
def phantom(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    """A 64³ CT-like phantom's store (closed): a bone shell around soft tissue, a denser
    off-centre blob."""
    z, y, x = np.mgrid[0:64, 0:64, 0:64].astype(np.float64)
    r = np.sqrt((x - 31.5) ** 2 + (y - 31.5) ** 2 + ((z - 31.5) * 1.2) ** 2)
    a = np.full(r.shape, -1000.0)
    a[r < 28] = 40.0 + 3.0 * x[r < 28]
    a[(r >= 22) & (r < 28)] = 1200.0
    blob = (x - 20) ** 2 + (y - 40) ** 2 + (z - 30) ** 2 < 36
    a[blob] = 600.0
    dst = tmp_path_factory.mktemp("render") / "phantom.strata"
    strata.from_numpy(a.astype(np.int16), dst=dst, spacing=(1.2, 1.0, 0.9), modality="CT").close()
    return dst


@pytest.fixture
def ct_store(phantom: pathlib.Path):
    """The phantom, open in this process for the test (closed after: the CLI opens it too)."""
    with strata.open(phantom) as vol:
        yield vol


#: (Python keywords, the same view's `strata render` flags).
VIEWS = [
    pytest.param(
        dict(azimuth=30.0, elevation=20.0, up_front=True),
        ["--azimuth", "30", "--elevation", "20", "--up-front"],
        id="dvr-up-front",
    ),
    pytest.param(
        dict(azimuth=-45.0, mode="mip", up_front=True, orthographic=True),
        ["--azimuth", "-45", "--mode", "mip", "--up-front", "--orthographic"],
        id="mip-orthographic",
    ),
    pytest.param(
        dict(elevation=-30.0, tf="ct-soft-tissue", shading=True, shadows="exact", up_front=True),
        ["--elevation", "-30", "--tf", "ct-soft-tissue", "--shading", "--shadows", "exact", "--up-front"],
        id="shaded-shadows",
    ),
    pytest.param(
        dict(azimuth=60.0, exact_trilinear=True),
        ["--azimuth", "60", "--exact-trilinear"],
        id="streamed-exact-trilinear",
    ),
]


@pytest.mark.parametrize(("keywords", "flags"), VIEWS)
def test_render_equals_the_cli_png_bit_for_bit(
    phantom: pathlib.Path, tmp_path: pathlib.Path, keywords: dict, flags: list[str]
) -> None:
    # Closed before the CLI runs: an open store is locked to this process.
    with strata.open(phantom) as vol:
        image = strata.render(vol, size=128, **keywords)
    assert image.shape == (128, 128, 4) and image.dtype == np.uint8
    assert (image[..., 3] > 0).mean() > 0.05, "the phantom covers part of the frame"
    assert (image[..., 3] == 0).any(), "and not all of it"

    png = tmp_path / "cli.png"
    run = subprocess.run(
        [str(strata_binary()), "render", str(phantom), "--size", "128x128", "--out", str(png), *flags],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr
    cli = read_png_rgb(png)
    # The PNG is the premultiplied RGB over black: the array's first three channels.
    differing = np.argwhere(np.any(cli != image[..., :3], axis=-1))
    assert differing.size == 0, f"{len(differing)} pixels differ, first at {differing[:5].tolist()}"


def test_the_reference_and_the_gpu_agree_within_a_few_steps(ct_store: strata.Volume) -> None:
    """The GPU frame against the f64 CPU reference of the same view (no jitter): within a few
    8-bit steps per channel on nearly every pixel (trilinear sampling in f32 against f64)."""
    common = dict(size=128, azimuth=15.0, up_front=True, jitter=False, exact_trilinear=True)
    gpu = strata.render(ct_store, **common).astype(np.int16)
    cpu = strata.render(ct_store, reference=True, **common).astype(np.int16)
    diff = np.abs(gpu - cpu)
    assert np.percentile(diff, 99.5) <= 4, f"99.5th percentile of |GPU - f64| is {np.percentile(diff, 99.5)}"


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        (dict(mode="volume"), '--mode "volume": expected one of dvr, mip'),
        (dict(size=0), r"--size 0x0 is outside 1\.\.8192"),
        (dict(size="big"), "size='big': expected WIDTHxHEIGHT"),
        (dict(step=0.0), "--step must be a number between"),
        (dict(azimuth=float("nan")), "--azimuth must be a finite number"),
        (dict(mode="mip", shadows="exact"), "not for MIP"),
        (dict(shadows="soft"), '--shadows "soft": expected off, exact or cache'),
        (dict(progressive=4, reference=True), "--progressive averages jittered frames"),
        (dict(light_dir=(0.0, 0.0, 0.0)), "--light-dir .*finite and non-zero"),
        (dict(tf="rainbow"), "unknown transfer function 'rainbow'"),
        (dict(level=300), r"level=300: expected 0\.\.=255"),
    ],
)
def test_bad_options_raise_value_error_naming_the_option(
    ct_store: strata.Volume, keywords: dict, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        strata.render(ct_store, size=keywords.pop("size", 32), **keywords)


def test_no_usable_adapter_raises_render_error(ct_store: strata.Volume, monkeypatch: pytest.MonkeyPatch) -> None:
    # wgpu reads WGPU_BACKEND at each instance: DirectX 12 is not built on Linux, so no adapter.
    monkeypatch.setenv("WGPU_BACKEND", "dx12")
    with pytest.raises(strata.RenderError, match="no wgpu adapter found") as e:
        strata.render(ct_store, size=32, up_front=True)
    assert isinstance(e.value, strata.StrataError)
    # The f64 reference needs no adapter.
    assert strata.render(ct_store, size=32, reference=True).shape == (32, 32, 4)


def test_a_closed_volume_raises_store_error(tmp_path: pathlib.Path) -> None:
    vol = strata.from_numpy(np.zeros((8, 8, 8), dtype=np.uint8), dst=tmp_path / "closed.strata")
    vol.close()
    with pytest.raises(strata.StoreError, match="closed"):
        strata.render(vol, size=32)


def render_threads() -> int:
    """Threads of this process named by strata.render's worker (Linux names are cut to 15)."""
    names = [p.read_text().strip() for p in pathlib.Path("/proc/self/task").glob("*/comm")]
    return sum(1 for n in names if n == "strata-py-rende")


def test_ctrl_c_interrupts_a_render(ct_store: strata.Volume) -> None:
    """A pending Ctrl-C (KeyboardInterrupt) ends `strata.render` while its frame is still being
    drawn: a timer interrupts the main thread during renders of the f64 reference (seconds
    each), and when the exception arrives the render's own thread is still running (an
    interrupt seen only after the call returned would find none). A few tries, since the
    timer may fire between two calls."""
    import _thread
    import threading

    for _ in range(3):
        timer = threading.Timer(0.3, _thread.interrupt_main)
        timer.start()
        try:
            for _ in range(100):
                strata.render(ct_store, size=256, reference=True, step=0.25)
        except KeyboardInterrupt:
            if render_threads() > 0:
                return
        finally:
            timer.cancel()
    pytest.fail("Ctrl-C never ended a render while its frame was being drawn")
