#!/bin/bash
# The GPU session's checks, run there from the repository root with .gpu/ carried (benchmarks/gpu/bundle.py made
# .gpu/prefix.txz; add .gpu/gsplat_build.tgz once a first run has returned it in $OUT):
#   1. set-up (benchmarks/gpu/env.sh) and gsplat's kernels, built and saved to $OUT when not carried;
#   2. the tracking node live on the synthetic loop (360 frames, 12 s at 30 Hz), its threads' stacks sampled
#      (benchmarks/stack_sampler.py). RUNS lists MODE:SIZE:SWITCH_INTERVAL:DEVICE[:off] runs (off: without the
#      measures for skipped frames, OFF_SETTINGS; they are the defaults; SETTINGS: more node parameters for every
#      run; RATE: the player's speed, default 1). MODE apart: the node in its
#      own process and the player in another, as on a robot (processed frames, their gaps and ATE from the node's
#      trajectory); inproc: `gausem-ros` on a bag of the sequence, all in one process (its report: frames processed
#      and dropped, latency, ATE);
#   3. the CUDA-marked tests (TESTS=0 leaves them out).
set -u
source benchmarks/gpu/env.sh || exit 1
SEQUENCE=synthetic:loop
PARAMS=params/synthetic.yaml
OFF_SETTINGS="-p tracking.feature_start.mode:=never -p mapping.coverage_keyframes:=never"
T0=$SECONDS
stage() { echo "== $((SECONDS - T0)) s: $*"; }
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
git log --oneline -1
python3 -c "import rclpy.executors, sensor_msgs.msg, gtsam, rosbags, gsplat" || exit 1
if [ ! -f .gpu/gsplat_build.tgz ]; then
  python3 -c "from gsplat.cuda._backend import _C" && tar -czf "$OUT/gsplat_build.tgz" -C "$TORCH_EXTENSIONS_DIR" .
fi
stage "set up"

sampled() {  # sampled SWITCH_INTERVAL MODULE ARGS...: the module with its stacks sampled, in this process
  local switch=$1
  shift
  exec python3 benchmarks/stack_sampler.py --switch-interval "$switch" -m "$@"
}

apart() {  # apart DIR SIZE SWITCH DEVICE [SETTINGS...]
  local d=$1 size=$2 switch=$3 device=$4
  shift 4
  (sampled "$switch" gausem_ros.nodes.tracking_mapping --ros-args --params-file $PARAMS -p device:="$device" "$@" \
    -p save_on_exit:=true -p output_dir:="$d" > "$d/log" 2>&1) &
  local node=$!
  timeout 150 python3 -m gausem_ros.player $SEQUENCE --size "$size" --rate ${RATE:-1} --wait-subscribers 120 \
    --gt-out "$d/gt.txt" --ros-args --params-file $PARAMS > "$d/player.log" 2>&1
  tail -2 "$d/player.log"
  sleep 5
  kill -TERM $node
  for _ in $(seq 60); do kill -0 $node 2>/dev/null || break; sleep 1; done
  kill -KILL $node 2>/dev/null && echo "node killed 60 s after SIGTERM"
  python3 - "$d" <<'EOF'
import sys
from pathlib import Path
import numpy as np
from gausem_core.eval.trajectory import absolute_trajectory_error, associate_trajectories
from gausem_core.io.trajectory import read_tum_trajectory
d = Path(sys.argv[1])
if not (d / "trajectory.txt").exists():
    sys.exit("no trajectory written")
estimate, truth = read_tum_trajectory(d / "trajectory.txt"), read_tum_trajectory(d / "gt.txt")
gaps = np.diff(np.searchsorted(truth.stamps, estimate.stamps))
line = f"processed {len(estimate)} of {len(truth)} frames; gaps median {np.median(gaps) if len(gaps) else '-'}"
if len(estimate) >= 3:
    line += f"; ATE {100 * absolute_trajectory_error(*associate_trajectories(estimate, truth)).rmse:.2f} cm"
print(line)
EOF
}

inproc() {  # inproc DIR SIZE SWITCH DEVICE [SETTINGS...]
  local d=$1 size=$2 switch=$3 device=$4 bag=/tmp/bag_$2
  shift 4
  [ -d "$bag" ] || python3 -m gausem_ros.convert $SEQUENCE "$bag" --size "$size" > /dev/null || return
  (sampled "$switch" gausem_ros.run_all "$bag" --rate ${RATE:-1} --quiet --report "$d/report" --reference $SEQUENCE \
    --ros-args --params-file $PARAMS -p device:="$device" "$@" > "$d/log" 2>&1) &
  local all=$!
  for _ in $(seq 200); do kill -0 $all 2>/dev/null || break; sleep 1; done
  kill -TERM $all 2>/dev/null && echo "gausem-ros stopped after 200 s" && sleep 10
  grep "frames in" "$d/log"
  grep -E "^(ate_rmse_cm|fps) " "$d/log"
}

for run in ${RUNS:-apart:160x120:0.005:cuda apart:160x120:0.0001:cuda apart:160x120:0.005:cuda:off \
                   inproc:160x120:0.005:cuda apart:640x480:0.005:cuda}; do
  IFS=: read -r mode size switch device settings <<< "$run"
  d=/tmp/live_${mode}_${size}_${switch}_${device}_${settings:-defaults}
  rm -rf "$d" && mkdir -p "$d"
  stage "$run"
  if [ "$settings" = off ]; then extra=($OFF_SETTINGS); else extra=(); fi
  extra+=(${SETTINGS:-})
  $mode "$d" "$size" "$switch" "$device" "${extra[@]}"
  grep -E "ERROR|lost|relocalis" "$d/log" | head -4
  sed -n '/\[stack-sampler\]/,$p' "$d/log" | head -50
done

if [ "${TESTS:-1}" != 0 ]; then
  stage "cuda tests"
  timeout 240 python3 -m pytest -m cuda -q -p no:cacheprovider 2>&1 | tail -5
fi
stage end
