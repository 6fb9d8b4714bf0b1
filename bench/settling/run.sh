#!/usr/bin/env bash
# Issue 35's settling benchmark on any adapter (lavapipe included): the 1024³ phantom at 128²,
# flythroughs with generous (1900 MiB: about what lavapipe allows) and 256 MiB budgets, flat
# and octree traversals, visibility feedback on and off, at a fast GPU's cadence
# (--frames-per-selection 8: an H200 draws ~7.5 frames per selection) and once at the
# adapter's own; then an occluded view (everything denser than air opaque) with and without
# visibility, for the working set visibility saves. Per viewpoint: time and frames to converge,
# cut changes while still, working set; per run: time to the first frame. Selection rounds to
# converge = frames / 8 at the fixed cadence.
#
#   cargo build --release -p strata-app --bin strata
#   S=target/release/strata bash bench/settling/run.sh        (W=... for the work folder)
set -u
here=$(cd "$(dirname "$0")" && pwd)
S=${S:-target/release/strata}
W=${W:-/tmp/strata-settling}
mkdir -p "$W"
[ -d "$W/p1024.strata" ] || "$S" sample --size 1024 --out "$W/p1024.strata" || exit 1
run() { # name gpu_mib extra...
  local name=$1 g=$2; shift 2
  echo "=== $name"
  timeout 900 "$S" flythrough "$W/p1024.strata" --frames 6000 --size 128x128 \
    --gpu-mib "$g" --cpu-mib 2048 --stops 3 --glide-frames 10 --settle-frames 1500 \
    --settle-seconds 240 --hold-frames 200 --fetch-threads 2 --no-in-core "$@" \
    --csv "$W/fly-$name.csv" 2>&1 | tail -40
}
for g in ${BUDGETS:-1900 256}; do
  for t in flat octree; do
    run "g$g-$t-vis-fast" "$g" --traversal $t --frames-per-selection 8
    run "g$g-$t-novis-fast" "$g" --traversal $t --frames-per-selection 8 --no-visibility
  done
done
run g1900-flat-vis-own-cadence 1900 --traversal flat
run occluded-vis-fast 1900 --traversal flat --frames-per-selection 8 --tf "$here/opaque-tf.json"
run occluded-novis-fast 1900 --traversal flat --frames-per-selection 8 --tf "$here/opaque-tf.json" --no-visibility
