#!/bin/bash
# The GPU session's checks, run there from the repository root with .gpu/ carried (benchmarks/gpu/bundle.py made
# .gpu/prefix.txz; add .gpu/gsplat_build.tgz once a first run has returned it in $OUT):
#   1. set-up (benchmarks/gpu/env.sh) and gsplat's kernels, built and saved to $OUT when not carried;
#   2. the tracking node live, as on a robot: its own process (stacks sampled, benchmarks/stack_sampler.py) and the
#      player in another at the camera's rate, the synthetic walk at each of $SIZES; then the processed frames, the
#      gaps between them and their ATE against the player's ground truth;
#   3. the CUDA-marked tests.
# Environment: SIZES (default "160x120 640x480"), SWITCH (the node's sys.setswitchinterval), TESTS=0 to skip 3.
set -u
source benchmarks/gpu/env.sh || exit 1
T0=$SECONDS
stage() { echo "== $((SECONDS - T0)) s: $*"; }
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
git log --oneline -1
python3 -c "import rclpy.executors, sensor_msgs.msg, gtsam, rosbags, gsplat" || exit 1
if [ ! -f .gpu/gsplat_build.tgz ]; then
  python3 -c "from gsplat.cuda._backend import _C" && tar -czf "$OUT/gsplat_build.tgz" -C "$TORCH_EXTENSIONS_DIR" .
fi
stage "set up"

for size in ${SIZES:-160x120 640x480}; do
  d=/tmp/live_$size
  rm -rf "$d" && mkdir -p "$d"
  python3 benchmarks/stack_sampler.py ${SWITCH:+--switch-interval $SWITCH} -m gausem_ros.nodes.tracking_mapping \
    --ros-args --params-file params/synthetic.yaml -p save_on_exit:=true -p output_dir:="$d" > "$d/node.log" 2>&1 &
  node=$!
  timeout 150 python3 -m gausem_ros.player synthetic --size "$size" --rate 1 --wait-subscribers 120 \
    --gt-out "$d/gt.txt" --ros-args --params-file params/synthetic.yaml > "$d/player.log" 2>&1
  sleep 5
  kill -TERM $node
  for _ in $(seq 60); do kill -0 $node 2>/dev/null || break; sleep 1; done
  kill -KILL $node 2>/dev/null && echo "node killed 60 s after SIGTERM"
  stage "live $size"
  tail -2 "$d/player.log"
  grep -E "ERROR|lost|relocalis" "$d/node.log" | head -5
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
  sed -n '/\[stack-sampler\]/,$p' "$d/node.log" | grep -v "^\s*[0-9]*\s*$" | head -60
done

if [ "${TESTS:-1}" != 0 ]; then
  stage "cuda tests"
  timeout 240 python3 -m pytest -m cuda -q -p no:cacheprovider 2>&1 | tail -5
fi
stage end
