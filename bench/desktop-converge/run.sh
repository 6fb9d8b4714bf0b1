#!/usr/bin/env bash
# Issue 47's desktop figure: time to converge and volume frame time on the adapter at hand
# (lavapipe here), for two `strata` binaries alternated in one run, so that both meet the same
# machine. Each binary writes its own 256³ phantom (`strata sample`: a binary opens the store
# format it writes), then opens it in the single 3D layout at 1360x860 under Xvfb, --fresh:
# still for 75 s (converged = no new volume frame in the last 5 s; the time of the last new
# one), then orbiting at 30°/s for 40 s (seconds per volume frame after the first).
#
#   BEFORE=path/to/old/strata AFTER=target/debug/strata bash bench/desktop-converge/run.sh
#   (W=... for the work folder, ROUNDS=... for more rounds)
set -u
here=$(cd "$(dirname "$0")" && pwd)
W=${W:-/tmp/strata-desktop-converge}
ROUNDS=${ROUNDS:-2}
mkdir -p "$W"
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-$W/xdg}; mkdir -p "$XDG_RUNTIME_DIR"; chmod 700 "$XDG_RUNTIME_DIR"
export STRATA_NO_SUPERVISOR=1
for b in before after; do
  bin=${BEFORE:?name the old binary in BEFORE}; [ $b = after ] && bin=${AFTER:?name the new binary in AFTER}
  [ -d "$W/phantom-$b.strata" ] || "$bin" sample --size 256 --out "$W/phantom-$b.strata" || exit 1
done
for rep in $(seq 1 "$ROUNDS"); do
  for b in before after; do
    bin=$BEFORE; [ $b = after ] && bin=$AFTER
    timeout 200 xvfb-run -a -s "-screen 0 1600x1000x24" "$bin" view "$W/phantom-$b.strata" --fresh \
      --layout single --exit-after 75 --frame-log "$W/still-$b-$rep.csv" > "$W/still-$b-$rep.out" 2>&1
    timeout 200 xvfb-run -a -s "-screen 0 1600x1000x24" "$bin" view "$W/phantom-$b.strata" --fresh \
      --layout single --orbit 30 --exit-after 40 --frame-log "$W/orbit-$b-$rep.csv" > "$W/orbit-$b-$rep.out" 2>&1
  done
done
python3 "$here/summarize.py" "$W"
