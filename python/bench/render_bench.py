"""strata.render's overhead against the `strata render` command line, same store, same views.

A synthetic CT phantom (the read benchmark's: nested ellipsoids in HU-like values, noise) is
imported once with ``strata.from_numpy``; then, for each view, alternately (so both see the
same machine load), ``--repeats`` times each:

- ``cli``: ``strata render STORE --size WxH --out frame.png FLAGS`` as a subprocess, wall time
  (process start, store open, GPU device, render, PNG written);
- ``python``: ``strata.open(STORE)``, ``strata.render(vol, ...)``, ``vol.close()`` in this
  process (store open, GPU device, render, the array): what a notebook cell does;
- ``python-open``: ``strata.render`` alone on a volume already open.

Medians are reported with the ratio python / cli (goal: ≤ 1.1). Every Python frame's RGB is
checked equal to the CLI's PNG first (the same code renders both).

    python python/bench/render_bench.py --size 128 --image 256 --repeats 5 \\
        --strata target/debug/strata --workdir /tmp/strata-render-bench
"""

from __future__ import annotations

import argparse
import os
import pathlib
import platform
import shutil
import statistics
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))

import strata  # noqa: E402
from read_bench import phantom  # noqa: E402
from test_render import read_png_rgb  # noqa: E402

#: (name, Python keywords, the same view's flags).
VIEWS = [
    ("dvr up-front", dict(azimuth=30.0, elevation=20.0, up_front=True), ["--azimuth", "30", "--elevation", "20", "--up-front"]),
    ("mip up-front", dict(azimuth=-45.0, mode="mip", up_front=True), ["--azimuth", "-45", "--mode", "mip", "--up-front"]),
    ("dvr streamed", dict(azimuth=60.0, exact_trilinear=True), ["--azimuth", "60", "--exact-trilinear"]),
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=128, help="phantom edge, voxels")
    parser.add_argument("--image", type=int, default=256, help="image edge, pixels")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--strata", type=pathlib.Path, required=True, help="the strata binary")
    parser.add_argument("--workdir", type=pathlib.Path, default=pathlib.Path("/tmp/strata-render-bench"))
    args = parser.parse_args()

    shutil.rmtree(args.workdir, ignore_errors=True)
    args.workdir.mkdir(parents=True)
    store = args.workdir / "phantom.strata"
    strata.from_numpy(phantom(args.size), dst=store, spacing=0.8, modality="CT").close()
    png = args.workdir / "frame.png"
    size = f"{args.image}x{args.image}"
    print(f"# {platform.node()} {platform.machine()} python {platform.python_version()}, "
          f"{os.cpu_count()} CPUs, strata {strata.__version__}; phantom {args.size}³, image {size}, "
          f"{args.repeats} repeats (medians, seconds)")
    print(f"# cli: {args.strata}")
    print("| view | cli | python (open + render) | python (render) | python / cli |")
    print("|---|---|---|---|---|")
    for name, keywords, flags in VIEWS:
        command = [str(args.strata), "render", str(store), "--size", size, "--out", str(png), *flags]
        cli, py, py_open = [], [], []
        for i in range(args.repeats + 1):  # the first round warms caches and is not counted
            t0 = time.perf_counter()
            with strata.open(store) as vol:
                image = strata.render(vol, size=args.image, **keywords)
            t_py = time.perf_counter() - t0
            t0 = time.perf_counter()
            subprocess.run(command, check=True, capture_output=True)
            t_cli = time.perf_counter() - t0
            if i == 0:
                assert np.array_equal(read_png_rgb(png), image[..., :3]), f"{name}: python and cli frames differ"
                continue
            py.append(t_py)
            cli.append(t_cli)
        with strata.open(store) as vol:
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                strata.render(vol, size=args.image, **keywords)
                py_open.append(time.perf_counter() - t0)
        c, p, po = statistics.median(cli), statistics.median(py), statistics.median(py_open)
        print(f"| {name} | {c:.3f} | {p:.3f} | {po:.3f} | {p / c:.2f}× |")


if __name__ == "__main__":
    main()
