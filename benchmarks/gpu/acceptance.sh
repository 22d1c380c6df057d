#!/bin/bash
# The GPU acceptance checks of the fast-steps work in one call, run there from the repository root with .gpu carried
# (see live.sh); benchmarks/gpu/acceptance.py turns what lands in $OUT into a results record. STAGES picks and orders
# them (default: all, cheapest first, each under a timeout):
#   tests     the CUDA-marked tests;
#   torch     `gausem run` on the synthetic loop in sync mode with the torch tracking step (fused=false): the "before";
#   sync      the same with the defaults (the fused step on CUDA): tracking ms a frame, mapping ms a keyframe, fps;
#   realtime  the same at the recorded pace (--realtime 1, the mapping worker beside the tracker);
#   tum       sync and --realtime 1 on TUM fr1/rpy, when TUM is at $TUM (carry it: too large beside the prefix);
#   live      the tracking node fed at 30 Hz by the player in another process (live.sh's `apart` run).
# SIZE (640x480), FRAMES (all), DEVICE (cuda) allow a dry run on a CPU without the bundle:
#   SIZE=80x60 FRAMES=12 DEVICE=cpu STAGES="torch sync realtime" OUT=/tmp/acc bash benchmarks/gpu/acceptance.sh
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

run() {  # run NAME TIMEOUT DATASET [ARGS...]: `gausem run` into $OUT/NAME (metrics.json and the log)
  local name=$1 limit=$2 dataset=$3
  shift 3
  mkdir -p "$OUT/$name"
  stage "$name"
  timeout "$limit" python3 -m gausem_core.cli run --dataset "$dataset" --size "$SIZE" \
    ${FRAMES:+--frames $FRAMES} --set device="$DEVICE" "$@" --quiet --out "/tmp/acceptance_$name" \
    > "$OUT/$name/log" 2>&1
  echo "exit $?" >> "$OUT/$name/log"
  cp "/tmp/acceptance_$name/metrics.json" "$OUT/$name/" 2>/dev/null
  grep -E "^(ate_rmse_cm|fps|tracking_ms_median|mapping_ms_median|num_gaussians|live\.frames_processed) |^exit" \
    "$OUT/$name/log"
}

for s in ${STAGES:-tests torch sync realtime tum live}; do
  case $s in
    tests) stage tests; timeout 240 python3 -m pytest -m cuda -q -p no:cacheprovider > "$OUT/tests.txt" 2>&1
           tail -3 "$OUT/tests.txt" ;;
    torch) run torch 200 synthetic:loop --set worker.mode=sync --set tracking.gauss_newton.fused=false ;;
    sync) run sync 150 synthetic:loop --set worker.mode=sync ;;
    realtime) run realtime 90 synthetic:loop --realtime 1 ;;
    tum) if [ -d "$TUM" ]; then
           run tum_sync 120 "tum:$TUM" --set worker.mode=sync
           run tum_realtime 90 "tum:$TUM" --realtime 1
         else stage "tum: no $TUM, skipped"; fi ;;
    live) stage live; RUNS=apart:$SIZE:0.005:$DEVICE TESTS=0 bash benchmarks/gpu/live.sh > "$OUT/live.txt" 2>&1
          grep -E "^processed|ERROR" "$OUT/live.txt" ;;
    *) echo "unknown stage $s"; exit 2 ;;
  esac
done
stage end
