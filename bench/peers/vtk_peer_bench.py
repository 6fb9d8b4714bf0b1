#!/usr/bin/env python3
# Peer measurement for strata-render: VTK's GPU raycaster (vtkGPUVolumeRayCastMapper) offscreen
# on Mesa llvmpipe, on the same volume, transfer function, view and step as
# render/benches/raycast.rs. Adapted from /work/shared/tools/vtk_peer_bench.py.
#
# Setup (Debian): apt-get install -y libegl1 libgl1 libosmesa6 && pip install vtk numpy
# Run:            python3 bench/peers/vtk_peer_bench.py [--size 512] [--frames 5] [--n 256]
# Compare with:   cargo bench -p strata-render --bench raycast (bench/peers/compare_with_vtk.sh runs both)
# Run both in one session: these machines are shared and noisy, only ratios mean much.
#
# Phantom: identical formula to strata_render::phantom::vtk_peer_phantom. The original script's
# float32 -> uint8 cast is undefined for negative values in C; on x86 it truncates and wraps, so
# here the cast is spelled out (truncate toward zero, wrap mod 256) and both sides see the same
# bytes on any platform.
import argparse, time, statistics
import numpy as np
import vtk
from vtk.util import numpy_support

ap = argparse.ArgumentParser()
ap.add_argument("--n", type=int, default=256)
ap.add_argument("--size", type=int, default=512)
ap.add_argument("--frames", type=int, default=5)
ap.add_argument("--save", help="write a PNG of the first DVR frame at sd 0.5 to this path")
ap.add_argument("--reference-dir", help="folder with strata-bench-{dvr,mip}-ref.ppm written by the "
                "Rust bench (STRATA_BENCH_SAVE=DIR): VTK's frame at the same view is compared with "
                "that f64 reference and its PSNR printed")
ap.add_argument("--ref-size", type=int, default=128, help="image edge of the reference PPMs")
args = ap.parse_args()

n = args.n
z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(np.float32) / n - 0.5
r = np.sqrt(x * x + y * y * 1.3 + z * z * 0.8)
v = np.clip(1 - r * 2, 0, 1) * 200 + (r < 0.2) * 50 + 20 * np.sin(x * 40) * np.cos(y * 30)
vol = (v.astype(np.int32) % 256).astype(np.uint8)
img = vtk.vtkImageData()
img.SetDimensions(n, n, n)
img.GetPointData().SetScalars(numpy_support.numpy_to_vtk(vol.ravel(), deep=True, array_type=vtk.VTK_UNSIGNED_CHAR))



def make_pipeline(mode, sd, size):
    m = vtk.vtkGPUVolumeRayCastMapper()
    m.SetInputData(img)
    m.SetSampleDistance(sd)
    m.SetAutoAdjustSampleDistances(False)
    if mode == "mip":
        m.SetBlendModeToMaximumIntensity()
    ctf = vtk.vtkColorTransferFunction()
    ctf.AddRGBPoint(0, 0, 0, 0); ctf.AddRGBPoint(100, 1, 0.5, 0.3); ctf.AddRGBPoint(255, 1, 1, 1)
    otf = vtk.vtkPiecewiseFunction()
    otf.AddPoint(0, 0); otf.AddPoint(60, 0); otf.AddPoint(120, 0.05); otf.AddPoint(255, 0.4)
    p = vtk.vtkVolumeProperty()
    p.SetColor(ctf); p.SetScalarOpacity(otf); p.SetInterpolationTypeToLinear()
    vol_actor = vtk.vtkVolume(); vol_actor.SetMapper(m); vol_actor.SetProperty(p)
    ren = vtk.vtkRenderer(); ren.AddVolume(vol_actor)
    rw = vtk.vtkRenderWindow(); rw.SetOffScreenRendering(1); rw.AddRenderer(ren); rw.SetSize(size, size)
    ren.ResetCamera()
    return ren, rw


def read_ppm(path):
    with open(path, "rb") as f:
        data = f.read()
    parts = data.split(maxsplit=4)
    if parts[0] != b"P6":
        raise SystemExit(f"{path}: not a binary PPM")
    w, h = int(parts[1]), int(parts[2])
    return np.frombuffer(parts[4][: w * h * 3], dtype=np.uint8).reshape(h, w, 3)


def window_rgb(rw):
    w2i = vtk.vtkWindowToImageFilter(); w2i.SetInput(rw); w2i.SetInputBufferTypeToRGB(); w2i.Update()
    out = w2i.GetOutput()
    w, h, _ = out.GetDimensions()
    rgb = numpy_support.vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, 3)
    return rgb[::-1]  # VTK's row 0 is the bottom


if args.reference_dir:
    # Same view as the Rust bench's camera_at(1): ResetCamera, then one Azimuth(30). VTK
    # composites over a black background, which equals the reference's premultiplied RGB.
    # Strata's own frames (saved by the bench) are scored here too, with this same RGB metric,
    # so both PSNRs mean the same thing (the Rust bench's figure also counts alpha).
    import glob, os, re
    def score(got, ref):
        err = got - ref
        rmse = np.sqrt(np.mean(err ** 2))
        return 20 * np.log10(255.0 / max(rmse, 1e-12)), rmse, np.abs(err).max()
    # The f64 reference shares Strata's optical model, which VTK does not (its opacity
    # correction, colour interpolation and ray setup differ), so each renderer is also scored
    # against its own converged image: VTK at sample distance 1/16, Strata's GPU at step 1/16
    # (strata-bench-{mode}-gpu-converged.ppm). Column 5 is that "own" PSNR.
    def vtk_frame(mode, sd):
        ren, rw = make_pipeline(mode, sd, args.ref_size)
        ren.GetActiveCamera().Azimuth(30)
        rw.Render()
        return window_rgb(rw).astype(np.float64)
    print("image", "PSNR_dB(RGB vs f64 ref)", "RMSE", "max_abs", "PSNR_dB(vs own step 1/16)", sep="\t")
    for mode in ["dvr", "mip"]:
        ref = read_ppm(f"{args.reference_dir}/strata-bench-{mode}-ref.ppm").astype(np.float64)
        vtk_converged = vtk_frame(mode, 1.0 / 16.0)
        got = vtk_frame(mode, 0.5)
        psnr, rmse, mx = score(got, ref)
        own, _, _ = score(got, vtk_converged)
        print(f"vtk-{mode}", "%.1f" % psnr, "%.3f" % rmse, "%d" % mx, "%.1f" % own, sep="\t", flush=True)
        converged_path = f"{args.reference_dir}/strata-bench-{mode}-gpu-converged.ppm"
        strata_converged = read_ppm(converged_path).astype(np.float64) if os.path.exists(converged_path) else None
        for path in sorted(glob.glob(f"{args.reference_dir}/strata-bench-{mode}-gpu-step*.ppm")):
            step = re.search(r"step([\d.]+)\.ppm$", path).group(1)
            frame = read_ppm(path).astype(np.float64)
            psnr, rmse, mx = score(frame, ref)
            own = score(frame, strata_converged)[0] if strata_converged is not None else float("nan")
            print(f"strata-{mode}-step{step}", "%.1f" % psnr, "%.3f" % rmse, "%d" % mx, "%.1f" % own, sep="\t", flush=True)
    raise SystemExit(0)

print("renderer", "mode", "sample_distance", "ms/frame(median)", sep="\t")
for mode in ["dvr", "mip"]:
    for sd in [1.0, 0.5, 0.25]:
        ren, rw = make_pipeline(mode, sd, args.size)
        rw.Render(); rw.Render()
        times = []
        for i in range(args.frames):
            ren.GetActiveCamera().Azimuth(30)
            t = time.time(); rw.Render(); times.append((time.time() - t) * 1000)
        print("vtk-gpu-raycast", mode, sd, "%.0f" % statistics.median(times), sep="\t", flush=True)
        if args.save and mode == "dvr" and sd == 0.5:
            w2i = vtk.vtkWindowToImageFilter(); w2i.SetInput(rw); w2i.Update()
            wr = vtk.vtkPNGWriter(); wr.SetFileName(args.save); wr.SetInputConnection(w2i.GetOutputPort()); wr.Write()
