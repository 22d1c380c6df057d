#!/bin/bash
# The GPU acceptance checks of the fast-steps work, run there from the repository root with .gpu carried (see
# live.sh); benchmarks/gpu/acceptance.py turns what lands in $OUT into a results record. STAGES picks and orders them
# (default: all, most telling first, each under a timeout):
#   sync      `gausem run` on the synthetic loop (360 frames) in sync mode with the defaults (the fused step on CUDA):
#             tracking ms a frame, mapping ms a keyframe, fps;
#   realtime  the same at the recorded pace (--realtime 1, the mapping worker beside the tracker);
#   torch     the first TORCH_FRAMES (90) in sync mode with the torch tracking step (fused=false): the "before";
#   tests     the CUDA-marked tests;
#   live      the tracking node fed at 30 Hz by the player in another process (live.sh's `apart` run);
#   tum       sync and --realtime 1 on TUM fr1/rpy, when TUM is at $TUM (benchmarks/gpu/pack_tum.py; carry it in a
#             call of its own: it does not fit beside the prefix).
# A call runs at most 600 s: e.g. STAGES="sync realtime torch" in the first (with gsplat's build), STAGES="tests live"
# in the next, STAGES=tum with .gpu/tum_fr1_rpy carried in a third; acceptance.py reads their files copied into one
# folder.
# SIZE (640x480), FRAMES (all), DEVICE (cuda) allow a dry run on a CPU without the bundle:
#   SIZE=80x60 FRAMES=12 DEVICE=cpu STAGES="sync realtime torch tum" OUT=/tmp/acc bash benchmarks/gpu/acceptance.sh
set -u
DEVICE=${DEVICE:-cuda} SIZE=${SIZE:-640x480} TUM=${TUM:-.gpu/tum_fr1_rpy}
if [ "$DEVICE" = cuda ]; then
  source benchmarks/gpu/env.sh || exit 1
  if [ ! -f .gpu/gsplat_build.tgz ] && [ ! -f "$OUT/gsplat_build.tgz" ]; then
    python3 -c "from gsplat.cuda._backend import _C" && tar -czf "$OUT/gsplat_build.tgz" -C "$TORCH_EXTENSIONS_DIR" .
  fi
fi
python3 - "$OUT" <<'EOF' || exit 1
import sys
from pathlib import Path
import torch  # noqa: F401 -- current_machine names the GPU torch sees
sys.path.insert(0, "benchmarks")
from gausem_bench.results import current_commit, current_machine, now
for name, value in (("machine", current_machine()), ("commit", current_commit()), ("date", now())):
    (Path(sys.argv[1]) / f"{name}.txt").write_text(value + "\n")
EOF
T0=$SECONDS
stage() { echo "== $((SECONDS - T0)) s: $*"; }

run() {  # run NAME TIMEOUT FRAMES DATASET [ARGS...]: `gausem run` into $OUT/NAME (metrics.json and the log)
  local name=$1 limit=$2 frames=$3 dataset=$4
  shift 4
  mkdir -p "$OUT/$name"
  stage "$name"
  timeout "$limit" python3 -m gausem_core.cli run --dataset "$dataset" --size "$SIZE" \
    ${frames:+--frames $frames} --set device="$DEVICE" "$@" --quiet --out "/tmp/acceptance_$name" \
    > "$OUT/$name/log" 2>&1
  echo "exit $?" >> "$OUT/$name/log"
  cp "/tmp/acceptance_$name/metrics.json" "$OUT/$name/" 2>/dev/null
  grep -E "^(ate_rmse_cm|fps|tracking_ms_median|mapping_ms_median|num_gaussians|live\.frames_processed) |^exit" \
    "$OUT/$name/log"
}

FRAMES=${FRAMES:-}
for s in ${STAGES:-sync realtime torch tests live tum}; do
  case $s in
    sync) run sync 240 "$FRAMES" synthetic:loop --set worker.mode=sync ;;
    realtime) run realtime 120 "$FRAMES" synthetic:loop --realtime 1 ;;
    torch) run torch 150 "${FRAMES:-${TORCH_FRAMES:-90}}" synthetic:loop --set worker.mode=sync \
             --set tracking.gauss_newton.fused=false ;;
    tests) stage tests; timeout 240 python3 -m pytest -m cuda -q -p no:cacheprovider > "$OUT/tests.txt" 2>&1
           tail -3 "$OUT/tests.txt" ;;
    tum) if [ -d "$TUM" ]; then
           run tum_sync 150 "$FRAMES" "tum:$TUM" --set worker.mode=sync
           run tum_realtime 90 "$FRAMES" "tum:$TUM" --realtime 1
         else stage "tum: no $TUM, skipped"; fi ;;
    live) stage live; RUNS=apart:$SIZE:0.005:$DEVICE TESTS=0 bash benchmarks/gpu/live.sh > "$OUT/live.txt" 2>&1
          grep -E "^processed|ERROR" "$OUT/live.txt" ;;
    *) echo "unknown stage $s"; exit 2 ;;
  esac
done
stage end
