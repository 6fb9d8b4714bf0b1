#!/usr/bin/env python3
# Cinematic peer for strata-render (issue 37): VTK's vtkGPUVolumeRayCastMapper with its volumetric
# shadows and scattering (GlobalIlluminationReach, VolumetricScatteringBlending, the volume
# property's ScatteringAnisotropy; VTK >= 9.1), offscreen on Mesa llvmpipe, on the same phantom,
# transfer function, view and step as bench/peers/vtk_peer_bench.py and render/benches/raycast.rs.
#
# For each configuration (plain DVR, shadows, shadows+scattering) it prints the median frame time
# at --sd and the PSNR of that frame against VTK's own converged image of the same configuration
# (sample distance --sd / --refine). bench/peers/compare_cinematic.sh runs this and Strata.
#
# Setup (Debian): apt-get install -y libegl1 libgl1 libosmesa6 && pip install vtk numpy
# Run:            python3 bench/peers/vtk_cine_bench.py --n 128 --size 256 --out /tmp/cine
#
# What VTK's options do (vtkVolumeShaderComposer.h, VTK 9.1+): with ShadeOn and
# VolumetricScatteringBlending b > 0, each shaded sample also marches a secondary ray towards every
# light (its length set by GlobalIlluminationReach: 0 = about one sample, 1 = the volume's
# diagonal) and lights the sample by that ray's transmittance times a Henyey-Greenstein phase
# (anisotropy from the volume property; phase 1 when |g| < 0.01). The result is mixed with
# ordinary gradient (Blinn-Phong) shading by vol_coef = 2b exp(-2b |grad| alpha) for b < 1 and
# vol_coef = 1 everywhere at b = 1. So VTK has no "shadowed surface shading": shadows only darken
# the volumetric part, and b = 1 is "shadows everywhere, no gradient shading".
import argparse
import os
import statistics
import time

import numpy as np
import vtk
from vtk.util import numpy_support

ap = argparse.ArgumentParser()
ap.add_argument("--n", type=int, default=128, help="phantom edge in voxels")
ap.add_argument("--size", type=int, default=256, help="image edge in pixels")
ap.add_argument("--frames", type=int, default=5, help="timed frames per configuration")
ap.add_argument("--sd", type=float, default=0.5, help="sample distance in voxels (timed frame)")
ap.add_argument("--refine", type=float, default=8.0,
                help="the converged image is rendered at sample distance sd / refine")
ap.add_argument("--reach", type=float, default=1.0, help="GlobalIlluminationReach, 0..1")
ap.add_argument("--g", type=float, default=0.5, help="scattering anisotropy of the scattering row")
ap.add_argument("--blend", type=float, default=0.5,
                help="VolumetricScatteringBlending of the shadows+scattering row (the shadows row uses 1)")
ap.add_argument("--configs", default="dvr,shadows,shadows+scattering")
ap.add_argument("--out", help="folder for the PNGs (vtk-<config>.png and vtk-<config>-converged.png)")
ap.add_argument("--nrrd", help="also write the phantom here as NRRD for `strata import`, its axes "
                "turned so that strata render --azimuth 30 shows VTK's view (see below)")
args = ap.parse_args()

# The phantom: the formula of strata_render::phantom::vtk_peer_phantom, the float -> u8 cast spelled
# out as there (truncate toward zero, wrap mod 256). numpy index order is [z, y, x], so ravel()
# gives x fastest, which is VTK's (and NRRD's) point order.
n = args.n
z, y, x = np.mgrid[0:n, 0:n, 0:n].astype(np.float32) / n - 0.5
r = np.sqrt(x * x + y * y * 1.3 + z * z * 0.8)
v = np.clip(1 - r * 2, 0, 1) * 200 + (r < 0.2) * 50 + 20 * np.sin(x * 40) * np.cos(y * 30)
voxels = (v.astype(np.int32) % 256).astype(np.uint8)
image = vtk.vtkImageData()
image.SetDimensions(n, n, n)
image.GetPointData().SetScalars(
    numpy_support.numpy_to_vtk(voxels.ravel(), deep=True, array_type=vtk.VTK_UNSIGNED_CHAR))

if args.nrrd:
    # VTK's view is ResetCamera (looking down -z, +y up) then Azimuth(30) about +y. Strata's CLI
    # orbits about the patient's superior axis and looks from anterior at azimuth 0. Voxel axis x
    # goes to patient left (+x LPS), y to superior (+z), z to anterior (-y): a proper rotation, so
    # `strata render --azimuth 30` puts its eye where VTK's is, with the same up vector.
    with open(args.nrrd, "wb") as f:
        f.write(("NRRD0004\ntype: uint8\ndimension: 3\nspace: left-posterior-superior\n"
                 f"sizes: {n} {n} {n}\n"
                 "space directions: (1,0,0) (0,0,1) (0,-1,0)\n"
                 "kinds: domain domain domain\nencoding: raw\n"
                 "space origin: (0,0,0)\n\n").encode())
        f.write(voxels.tobytes())


def make_pipeline(config, sd):
    """Renderer and offscreen window for one configuration at sample distance sd."""
    mapper = vtk.vtkGPUVolumeRayCastMapper()
    mapper.SetInputData(image)
    mapper.SetSampleDistance(sd)
    mapper.SetAutoAdjustSampleDistances(False)
    # The transfer function of vtk_peer_bench.py (strata_render::phantom::vtk_peer_transfer_function).
    colour = vtk.vtkColorTransferFunction()
    colour.AddRGBPoint(0, 0, 0, 0)
    colour.AddRGBPoint(100, 1, 0.5, 0.3)
    colour.AddRGBPoint(255, 1, 1, 1)
    opacity = vtk.vtkPiecewiseFunction()
    opacity.AddPoint(0, 0)
    opacity.AddPoint(60, 0)
    opacity.AddPoint(120, 0.05)
    opacity.AddPoint(255, 0.4)
    prop = vtk.vtkVolumeProperty()
    prop.SetColor(colour)
    prop.SetScalarOpacity(opacity)
    prop.SetInterpolationTypeToLinear()
    renderer = vtk.vtkRenderer()
    if config != "dvr":
        # Blinn-Phong with Strata's Shading::default() coefficients.
        prop.ShadeOn()
        prop.SetAmbient(0.3)
        prop.SetDiffuse(0.7)
        prop.SetSpecular(0.2)
        prop.SetSpecularPower(32)
        # The key light of the Rust bench's effect rows: directional, from the upper right,
        # fixed to the camera (camera-light coordinates: the camera sits at (0, 0, 1)).
        light = vtk.vtkLight()
        light.SetLightTypeToCameraLight()
        light.SetPositional(False)
        light.SetPosition(0.5, 0.5, 0.7)
        light.SetFocalPoint(0, 0, 0)
        renderer.AddLight(light)  # a light of our own: VTK adds no headlight
        mapper.SetGlobalIlluminationReach(args.reach)
        if config == "shadows":
            # Fully volumetric: every sample lit by its shadow ray, isotropic phase.
            mapper.SetVolumetricScatteringBlending(1.0)
            prop.SetScatteringAnisotropy(0.0)
        elif config == "shadows+scattering":
            mapper.SetVolumetricScatteringBlending(args.blend)
            prop.SetScatteringAnisotropy(args.g)
        else:
            raise SystemExit(f"unknown config {config}")
    actor = vtk.vtkVolume()
    actor.SetMapper(mapper)
    actor.SetProperty(prop)
    renderer.AddVolume(actor)
    window = vtk.vtkRenderWindow()
    window.SetOffScreenRendering(1)
    window.AddRenderer(renderer)
    window.SetSize(args.size, args.size)
    renderer.ResetCamera()
    renderer.GetActiveCamera().Azimuth(30)
    renderer.ResetCameraClippingRange()
    return renderer, window


def render(window):
    window.Render()
    # Render() may return before the driver has drawn; wait so the time is the frame's.
    if hasattr(window, "WaitForCompletion"):
        window.WaitForCompletion()


def window_rgb(window):
    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(window)
    grab.SetInputBufferTypeToRGB()
    grab.ReadFrontBufferOff()
    grab.Update()
    out = grab.GetOutput()
    w, h, _ = out.GetDimensions()
    rgb = numpy_support.vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, 3)
    return rgb[::-1].copy()  # VTK's row 0 is the bottom


def psnr(a, b):
    err = a.astype(np.float64) - b.astype(np.float64)
    rmse = np.sqrt(np.mean(err ** 2))
    return 20 * np.log10(255.0 / max(rmse, 1e-12))


def write_png(path, rgb):
    h, w, _ = rgb.shape
    data = vtk.vtkImageData()
    data.SetDimensions(w, h, 1)
    data.GetPointData().SetScalars(
        numpy_support.numpy_to_vtk(rgb[::-1].reshape(-1, 3), deep=True, array_type=vtk.VTK_UNSIGNED_CHAR))
    writer = vtk.vtkPNGWriter()
    writer.SetFileName(path)
    writer.SetInputData(data)
    writer.Write()


print(f"VTK {vtk.vtkVersion.GetVTKVersion()}, phantom {n}^3, {args.size}^2, sd {args.sd}, "
      f"converged at sd {args.sd / args.refine:g}, reach {args.reach}", flush=True)
print("renderer", "config", "ms/frame(median)", "PSNR_dB(vs own converged)", "converged_s", sep="\t")
for config in args.configs.split(","):
    renderer, window = make_pipeline(config, args.sd)
    render(window)  # compiles the shader, uploads the volume
    times = []
    for _ in range(args.frames):
        t = time.perf_counter()
        render(window)
        times.append((time.perf_counter() - t) * 1e3)
    frame = window_rgb(window)
    del renderer, window
    renderer, window = make_pipeline(config, args.sd / args.refine)
    t = time.perf_counter()
    render(window)
    converged_s = time.perf_counter() - t
    converged = window_rgb(window)
    del renderer, window
    print("vtk", config, "%.1f" % statistics.median(times), "%.1f" % psnr(frame, converged),
          "%.1f" % converged_s, sep="\t", flush=True)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        write_png(os.path.join(args.out, f"vtk-{config}.png"), frame)
        write_png(os.path.join(args.out, f"vtk-{config}-converged.png"), converged)
