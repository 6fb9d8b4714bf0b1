#!/usr/bin/env bash
# One prepared pass of Strata's render and streaming figures on a machine with a real GPU, sized
# to finish in about 5 minutes there (issue 35 item 7). It builds nothing: it takes stripped
# release binaries from a git-ignored .gpu folder of the checkout. Adapted from
# ../shared/tools/gpu-run.sh.
#
# Here (no GPU), from the checkout's root:
#   cargo build --release -p strata-app --bin strata -p strata-bench --bin strata-bench
#   cargo bench --no-run -p strata-render --bench raycast --bench traversal
#   cargo test --release --no-run -p strata-render --test integration  # features::cache_first_upload_cost
#   mkdir -p .gpu && grep -qx /.gpu/ .git/info/exclude || echo /.gpu/ >> .git/info/exclude
#   for b in target/release/strata target/release/strata-bench target/release/deps/raycast-* target/release/deps/traversal-* \
#            $(ls -t target/release/deps/integration-* | grep -v '\.d$' | head -1); do
#     case $b in *.d) continue;; esac; n=$(basename $b | sed 's/-[0-9a-f]*$//; s/^integration$/features/')
#     strip -o .gpu/$n $b; xz -f -T0 .gpu/$n; done
#   (render's integration-test binary, newest after the command above, goes as `features`.)
#   and, for a bare GPU machine without a Vulkan loader, its Debian packages into .gl (git-ignored):
#   mkdir -p .gl && (cd .gl && apt-get download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
# There: with .gl and .gpu carried along (git worktrees: `carry: [".gpu", ".gl"]`):
#   bash bench/gpu/run.sh          (OUT=... for the summary's folder; default /tmp/gpu-out)
# Rehearse here first at small sizes on lavapipe: SMALL=1 bash bench/gpu/run.sh
# Each step has its own timeout; step logs are tarred into $OUT/logs.tgz after each step, and
# $OUT/summary.txt holds each step's tail. CSVs of the flythroughs go into the logs.
set -u
OUT=${OUT:-/tmp/gpu-out}; mkdir -p "$OUT"
L=/tmp/gpu-logs; rm -rf $L; mkdir -p $L
BIN=${BIN:-.gpu}
if [ -d .gl ] && [ -z "${SMALL:-}" ]; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
  [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ] && export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
fi
B=/tmp/sbin; mkdir -p $B
for n in strata strata-bench raycast traversal features; do
  rm -f $B/$n
  if [ -f $BIN/$n.xz ]; then xz -dc $BIN/$n.xz > $B/$n; elif [ -f $BIN/$n ]; then cp $BIN/$n $B/$n; fi
  [ -f $B/$n ] && chmod +x $B/$n
done
[ -x $B/strata ] || { echo "no strata binary in $BIN (see the header)"; exit 2; }
[ -x $B/strata-bench ] || { echo "no strata-bench binary in $BIN (see the header)"; exit 2; }
export XDG_RUNTIME_DIR=/tmp/xdg; mkdir -p $XDG_RUNTIME_DIR; chmod 700 $XDG_RUNTIME_DIR
W=/tmp/gw; mkdir -p $W
S=$B/strata
SB=$B/strata-bench
: > "$OUT/summary.txt"
log() { echo "=== $(date +%T) $*" | tee -a "$OUT/summary.txt"; }
step() { # step NAME TIMEOUT CMD...
  local name=$1 t=$2; shift 2
  log "$name"; local t0=$(date +%s.%N)
  timeout "$t" "$@" >"$L/$name.log" 2>&1; local rc=$?
  local t1=$(date +%s.%N)
  echo "    rc=$rc wall=$(python3 -c "print(round($t1-$t0,2))")s" | tee -a "$OUT/summary.txt"
  [ $rc -eq 124 ] && echo "    TIMED OUT after ${t} s: killed, not failed (what it printed after 'interrupted' is teardown)" | tee -a "$OUT/summary.txt"
  grep -vE 'XDG_RUNTIME' "$L/$name.log" | tail -n "${TAILN:-14}" | sed 's/^/    /' >> "$OUT/summary.txt"
  tar czf "$OUT/logs.tgz" -C $L . 2>/dev/null
}
if [ -n "${SMALL:-}" ]; then
  MID=128; BIG=128; IMG=128; BIGIMG=128; FR=3; HUGE=2048; TCF=30; SET=100; GMIB=1024; SECS=20
  FLYT=600; STEPT=300
else
  MID=512; BIG=1024; IMG=1024; BIGIMG=2048; FR=15; HUGE=16384; TCF=360; SET=3000; GMIB=8192; SECS=4
  # A flythrough holds each of its 3 viewpoints 3000 frames after converging (or 4 s
  # without): 75 s killed the 256 MiB runs on the H200 before they ended.
  FLYT=150; STEPT=60
fi
(nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem --format=csv 2>&1; nproc) | tee -a "$OUT/summary.txt"
step adapter $STEPT $S sample --size 64 --out $W/p64.strata
step adapter-render $STEPT $S render $W/p64.strata --out $W/p64.png --size 64x64
if [ -z "${SMALL:-}" ] && grep -qi llvmpipe "$L/adapter-render.log"; then log "llvmpipe, not the GPU: stop"; exit 3; fi
# The cache's first-upload cost with the texture allocated for the whole budget and growing.
[ -x $B/features ] && TAILN=8 step cache-first-upload $STEPT env STRATA_CACHE_BUDGETS_MIB=256,$GMIB $B/features cache_first_upload_cost --ignored --nocapture --test-threads 1
[ -x $B/raycast ] && TAILN=24 step raycast $STEPT env STRATA_BENCH_SIZE=$IMG STRATA_BENCH_FRAMES=$FR STRATA_BENCH_STEPS=0.5,1 STRATA_BENCH_REF_SIZE=128 $B/raycast
[ -x $B/traversal ] && TAILN=30 step traversal $STEPT env STRATA_BENCH_SIZE=$IMG STRATA_BENCH_FRAMES=$FR $B/traversal
step sample-$BIG $STEPT $S sample --size $BIG --out $W/p$BIG.strata
# Hold and wall-clock settle only where this build has them (issue 35 item 4).
HELP=$($S flythrough --help 2>&1)
HOLD=""
echo "$HELP" | grep -q -- --hold-frames && HOLD="$HOLD --hold-frames $SET"
echo "$HELP" | grep -q -- --settle-seconds && HOLD="$HOLD --settle-seconds $SECS"
log "flythrough extras:${HOLD:- none}"
fly() { # fly NAME GPU_MIB CPU_MIB EXTRA...
  local name=$1 g=$2 c=$3; shift 3
  TAILN=18 step fly-$name $FLYT $S flythrough $W/p$BIG.strata --frames 12000 --size ${IMG}x$IMG --gpu-mib $g --cpu-mib $c --stops 3 --glide-frames 10 --settle-frames $SET --fetch-threads 12 --no-in-core $HOLD "$@" --csv "$L/fly-$name.csv"
}
fly generous-flat-vis $GMIB 16384
fly generous-flat-novis $GMIB 16384 --no-visibility
fly generous-octree-vis $GMIB 16384 --traversal octree
fly tight-flat-vis 256 512
fly tight-octree-vis 256 512 --traversal octree
step sample-$MID $STEPT $S sample --size $MID --out $W/p$MID.strata
TAILN=10 step timecritical 90 $SB timecritical $W/p$MID.strata --target 120 --frames $TCF --size ${BIGIMG}x$BIGIMG --csv "$L/timecritical.csv"
# A level over the budget: refused before it is read, bricks × bytes against the budget.
TAILN=4 step timecritical-over-budget 30 $SB timecritical $W/p$BIG.strata --target 120 --frames 4 --size 64x64 --gpu-mib 256
TAILN=24 step adaptive 100 $SB adaptive phantom --phantom-size 256 --size ${IMG}x$IMG --frames 5 --epsilons 0.001,0.01,0.05 --out-dir $W/adaptive
step sparse-gen 150 $S sample --sparse --size $HUGE --out $W/big.strata
step sparse-info 30 $S info $W/big.strata
TAILN=8 step sparse-render 150 $S render $W/big.strata --out "$OUT/big.png" --size ${IMG}x$IMG --mode mip --traversal octree --max-frames 400
log done
cat "$OUT/summary.txt"
