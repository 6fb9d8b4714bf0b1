#!/usr/bin/env bash
# Cinematic rendering against VTK (issue 37), both sides in one session: plain DVR, shadows and
# shadows+scattering on the peer phantom, transfer function, view (ResetCamera + Azimuth 30) and
# 0.5-voxel step. Prints per configuration: ms/frame of VTK and Strata and their ratio, and each
# renderer's PSNR against its OWN converged image (VTK at sample distance 0.5/REFINE, Strata at
# step 0.5/REFINE with shadow step 1/REFINE). Keeps the PNGs and a side-by-side per configuration
# in OUT (default: a new folder under /tmp). Only ratios mean much: both are CPU renderers here.
#
# Needs (Debian): apt-get install -y mesa-vulkan-drivers libvulkan1 libegl1 libgl1 libosmesa6
#                 pip install vtk numpy pillow
# Run:            bench/peers/compare_cinematic.sh      (from anywhere; env N, SIZE, FRAMES,
#                 REFINE, OUT override the defaults below)
set -euo pipefail
cd "$(dirname "$0")/../.."

N=${N:-128}            # phantom edge, voxels
SIZE=${SIZE:-256}      # image edge, pixels
FRAMES=${FRAMES:-3}    # timed frames per configuration
REFINE=${REFINE:-4}    # converged image: step / REFINE (and shadow step 1 / REFINE for Strata)
OUT=${OUT:-$(mktemp -d /tmp/strata-cine.XXXXXX)}
mkdir -p "$OUT"
echo "images and logs in $OUT"

cargo build -q --release -p strata-app
strata=${CARGO_TARGET_DIR:-target}/release/strata

echo "== VTK (bench/peers/vtk_cine_bench.py) =="
python3 bench/peers/vtk_cine_bench.py --n "$N" --size "$SIZE" --frames "$FRAMES" --refine "$REFINE" \
    --out "$OUT" --nrrd "$OUT/phantom.nrrd" 2> >(grep -v "bad X server" >&2) | tee "$OUT/vtk.txt"

echo
echo "== Strata timing (cargo bench -p strata-render --bench raycast) =="
# Plain DVR: the timing table at step 0.5 (empty skipping, early termination, jitter: a normal
# frame, orbiting 30° per frame). Lit rows: the effect table's "on" column, the same view every
# round, key light from camera-relative (0.5, 0.5, 0.7), exact shadow rays at step 1 voxel.
export STRATA_BENCH_VOLUME=$N STRATA_BENCH_SIZE=$SIZE STRATA_BENCH_FRAMES=$FRAMES
STRATA_BENCH_QUICK=1 STRATA_BENCH_STEPS=0.5 cargo bench -q -p strata-render --bench raycast | tee "$OUT/strata-dvr.txt"
STRATA_BENCH_EFFECTS="shadows (exact),shadows+scattering" cargo bench -q -p strata-render --bench raycast \
    | tee "$OUT/strata-effects.txt"

echo
echo "== Strata images (strata render, the same phantom imported from NRRD) =="
"$strata" import "$OUT/phantom.nrrd" "$OUT/phantom.strata" >/dev/null
# strata_render::phantom::vtk_peer_transfer_function as JSON.
cat > "$OUT/tf.json" <<'EOF'
{"name": "vtk-peer",
 "opacity": [{"value": 0, "opacity": 0}, {"value": 60, "opacity": 0},
             {"value": 120, "opacity": 0.05}, {"value": 255, "opacity": 0.4}],
 "color": [{"value": 0, "rgb": [0, 0, 0]}, {"value": 100, "rgb": [1, 0.5, 0.3]},
           {"value": 255, "rgb": [1, 1, 1]}]}
EOF
fine=$(python3 -c "print(0.5 / $REFINE)")
shadow_fine=$(python3 -c "print(1.0 / $REFINE)")
lit="--light-dir 0.5,0.5,0.7 --shadows exact"
declare -A flags=([dvr]="" [shadows]="$lit" [shadows+scattering]="$lit --scattering 0.5 --scattering-blend 0.5")
for config in dvr shadows shadows+scattering; do
    common=("$OUT/phantom.strata" --up-front --no-jitter --size "${SIZE}x${SIZE}" --azimuth 30
            --tf "$OUT/tf.json")
    # shellcheck disable=SC2086
    "$strata" render "${common[@]}" ${flags[$config]} --step 0.5 --out "$OUT/strata-$config.png" 2>/dev/null
    # shellcheck disable=SC2086
    "$strata" render "${common[@]}" ${flags[$config]} --step "$fine" --shadow-step "$shadow_fine" \
        --out "$OUT/strata-$config-converged.png" 2>/dev/null
done

echo
echo "== side by side (N=$N, ${SIZE}², step 0.5; PSNR against each renderer's own step 0.5/$REFINE) =="
python3 - "$OUT" <<'EOF'
import re, sys
import numpy as np
from PIL import Image
d = sys.argv[1]
load = lambda name: np.asarray(Image.open(f"{d}/{name}.png").convert("RGB"), dtype=np.float64)
def psnr(a, b):
    return 20 * np.log10(255.0 / max(np.sqrt(np.mean((a - b) ** 2)), 1e-12))
vtk_ms, vtk_db = {}, {}
for line in open(f"{d}/vtk.txt"):
    f = line.rstrip("\n").split("\t")
    if len(f) == 5 and f[0] == "vtk":
        vtk_ms[f[1]], vtk_db[f[1]] = float(f[2]), float(f[3])
strata_ms = {}
m = re.search(r"^dvr step 0\.5\s+([\d.]+)", open(f"{d}/strata-dvr.txt").read(), re.M)
if m:
    strata_ms["dvr"] = float(m.group(1))
# Effect rows: name, off, never built, never/off, on, on/off; "on" is the frame with the effect.
for name, on in re.findall(r"^(shadows \(exact\)|shadows\+scattering)\s+[\d.]+\s+[\d.]+\s+[\d.]+\s+([\d.]+)",
                           open(f"{d}/strata-effects.txt").read(), re.M):
    strata_ms["shadows" if name.startswith("shadows (") else name] = float(on)
print(f"{'config':<20} {'VTK ms':>9} {'Strata ms':>10} {'Strata/VTK':>11} {'VTK dB':>8} {'Strata dB':>10}")
rows = []
for c in ["dvr", "shadows", "shadows+scattering"]:
    s_db = psnr(load(f"strata-{c}"), load(f"strata-{c}-converged"))
    v, s = vtk_ms.get(c, float("nan")), strata_ms.get(c, float("nan"))
    print(f"{c:<20} {v:>9.1f} {s:>10.1f} {s / v:>11.3f} {vtk_db.get(c, float('nan')):>8.1f} {s_db:>10.1f}")
    # Top: VTK | Strata at step 0.5; bottom: their converged images.
    tiles = [[f"vtk-{c}", f"strata-{c}"], [f"vtk-{c}-converged", f"strata-{c}-converged"]]
    ims = [[Image.open(f"{d}/{t}.png").convert("RGB") for t in row] for row in tiles]
    w, h = ims[0][0].size
    sheet = Image.new("RGB", (2 * w, 2 * h))
    for j, row in enumerate(ims):
        for i, im in enumerate(row):
            sheet.paste(im, (i * w, j * h))
    sheet.save(f"{d}/side-by-side-{c}.png")
print(f"side-by-side PNGs (top: VTK | Strata at step 0.5, bottom: converged): {d}/side-by-side-*.png")
EOF
