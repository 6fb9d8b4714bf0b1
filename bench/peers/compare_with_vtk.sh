#!/usr/bin/env bash
# Strata's raycaster and VTK's vtkGPUVolumeRayCastMapper on the same machine in one session:
# same 256³ u8 phantom, transfer function, 512² view and 0.5-voxel step. Prints both tables,
# VTK's PSNR against Strata's f64 CPU reference of the same view, and the time ratios.
# These machines are shared and noisy: only ratios from one run mean much.
#
# Needs (Debian): apt-get install -y mesa-vulkan-drivers libvulkan1 libegl1 libgl1 libosmesa6
#                 pip install vtk numpy
# Run:            bench/peers/compare_with_vtk.sh        (from the workspace root)
set -euo pipefail
cd "$(dirname "$0")/../.."

out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

echo "== strata (cargo bench -p strata-render --bench raycast) =="
STRATA_BENCH_SAVE="$out" cargo bench -q -p strata-render --bench raycast | tee "$out/strata.txt"

echo
echo "== VTK $(python3 -c 'import vtk; print(vtk.vtkVersion.GetVTKVersion())') (bench/peers/vtk_peer_bench.py) =="
python3 bench/peers/vtk_peer_bench.py | tee "$out/vtk.txt"
python3 bench/peers/vtk_peer_bench.py --reference-dir "$out" | tee "$out/vtk_psnr.txt"

echo
echo "== ratios (strata ms / VTK ms at step 0.5; goal <= 0.6 at the same step) =="
python3 - "$out" <<'EOF'
import re, sys
d = sys.argv[1]
text = open(f"{d}/strata.txt").read()
# "dvr step 0.5   328.3 ..." rows of the timing table (skip-enabled configs only).
strata_ms = {(m, float(s)): float(ms) for m, s, ms in re.findall(r"^(dvr|mip) step ([\d.]+)\s+([\d.]+)\s", text, re.M)}
psnr_text = open(f"{d}/vtk_psnr.txt").read()
# Both PSNRs from the peer script, RGB only (VTK has no alpha), against the same f64 reference.
strata_psnr = {(m, float(s)): float(p) for m, s, p in re.findall(r"^strata-(dvr|mip)-step([\d.]+)\t([\d.]+)", psnr_text, re.M)}
# Each renderer against its own converged image (step / sample distance 1/16): column 5.
strata_own = {(m, float(s)): float(p) for m, s, p in re.findall(r"^strata-(dvr|mip)-step([\d.]+)\t[\d.]+\t[\d.]+\t\d+\t([\d.]+)", psnr_text, re.M)}
vtk_own = {m: float(p) for m, p in re.findall(r"^vtk-(dvr|mip)\t[\d.]+\t[\d.]+\t\d+\t([\d.]+)", psnr_text, re.M)}
vtk_ms = {}
for line in open(f"{d}/vtk.txt"):
    f = line.strip().split("\t")
    if len(f) == 4 and f[0] == "vtk-gpu-raycast":
        vtk_ms[(f[1], float(f[2]))] = float(f[3])
vtk_psnr = {m: float(p) for m, p in re.findall(r"^vtk-(dvr|mip)\t([\d.]+)", psnr_text, re.M)}
for mode in ["dvr", "mip"]:
    vtk = vtk_ms.get((mode, 0.5))
    same = strata_ms.get((mode, 0.5))
    if vtk is None or same is None:
        print(f"{mode}: missing figures"); continue
    print(f"{mode} at step 0.5: strata {same:.1f} ms ({strata_psnr.get((mode, 0.5), float('nan')):.1f} dB), "
          f"VTK {vtk:.0f} ms ({vtk_psnr.get(mode, float('nan')):.1f} dB): ratio {same / vtk:.3f}")
    print(f"{mode} at step 0.5 against each renderer's own step 1/16: strata "
          f"{strata_own.get((mode, 0.5), float('nan')):.1f} dB, VTK {vtk_own.get(mode, float('nan')):.1f} dB")
    # The goal is "1/3 of VTK's time at equal or better PSNR": Strata's fastest step that is
    # still at least as accurate as VTK at its 0.5-voxel step.
    ok = [(ms, s) for (m, s), ms in strata_ms.items()
          if m == mode and strata_psnr.get((m, s), -1) >= vtk_psnr.get(mode, 1e9)]
    if ok:
        ms, s = min(ok)
        print(f"{mode} at equal or better PSNR: strata step {s} {ms:.1f} ms ({strata_psnr[(mode, s)]:.1f} dB) "
              f"vs VTK {vtk:.0f} ms: ratio {ms / vtk:.3f}")
EOF
