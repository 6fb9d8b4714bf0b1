#!/usr/bin/env bash
# Renders the benches' scenes with two `strata` binaries and reports whether every image is
# byte-identical (issue 12: a refactor must not change a pixel). Usage:
#   bench/house/same_images.sh OLD_STRATA NEW_STRATA [WORK_DIR]
# Both binaries render the same phantom store (made by OLD); GPU frames, the f64 reference, and
# the error columns of `strata-bench accuracy` / `strata-bench transitions` are compared.
set -euo pipefail
old=$1 new=$2 work=${3:-$(mktemp -d)}
mkdir -p "$work"
store="$work/phantom96.strata"
[ -d "$store" ] || "$old" sample --size 96 --out "$store" >/dev/null
scenes=(
  "--mode dvr"
  "--mode dvr --shading"
  "--mode mip"
  "--mode iso --iso 300"
  "--mode iso --iso 300 --shading --orthographic"
  "--mode dvr --tf ct-bone --azimuth 70 --elevation -20"
  "--mode dvr --level 1 --up-front"
  "--mode dvr --quality 4 --no-smooth"
  "--mode dvr --quality 4"
  "--mode dvr --step 2 --no-jitter"
  "--mode dvr --reference"
  "--mode iso --iso 300 --shading --reference"
)
differ=0
for i in "${!scenes[@]}"; do
  for side in old new; do
    bin=$old; [ $side = new ] && bin=$new
    # shellcheck disable=SC2086
    "$bin" render "$store" --out "$work/$side-$i.png" --size 160x128 ${scenes[$i]} >/dev/null 2>&1
  done
  if cmp -s "$work/old-$i.png" "$work/new-$i.png"; then
    echo "same    ${scenes[$i]}"
  else
    echo "DIFFER  ${scenes[$i]}"; differ=1
  fi
done
for bench in accuracy transitions; do
  for side in old new; do
    bin=$old; [ $side = new ] && bin=$new
    mkdir -p "$work/$side-$bench"
    if [ $bench = accuracy ]; then out=(--out-dir "$work/$side-$bench"); else out=(--out "$work/$side-$bench/table.md"); fi
    "$bin" bench $bench phantom --phantom-size 64 --size 128x128 --frames 1 "${out[@]}" >/dev/null 2>&1
  done
  # Timing columns differ run to run; every error column must not.
  for side in old new; do
    python3 - "$work/$side-$bench" > "$work/$side-$bench.errors" <<'PY'
import csv, glob, sys
for path in sorted(glob.glob(sys.argv[1] + "/*.csv")):
    rows = list(csv.DictReader(open(path)))
    for r in rows:
        # The time-critical rows pick their step from measured frame times, and the Pareto
        # flag compares times: both move with the machine's load, not with the image.
        if r.get("family", "").startswith("time-critical"):
            continue
        print({k: v for k, v in r.items() if not (k.endswith("_ms") or k == "pareto")})
PY
  done
  if cmp -s "$work/old-$bench.errors" "$work/new-$bench.errors" && [ -s "$work/old-$bench.errors" ]; then
    echo "same    bench $bench ($(wc -l < "$work/old-$bench.errors") rows of error figures)"
  else
    echo "DIFFER  bench $bench"; differ=1
  fi
done
exit $differ
