#!/bin/bash
# Where the core's time goes on the GPU: `gausem run` on the synthetic loop, every frame and every n-th (STRIDES),
# loop closure on, refinement off; under cProfile (the gausem_core functions by cumulative time; PROFILE=0: without
# it, for the run's own fps; SETS: more --set overrides, e.g. "tracking.gauss_newton.fused=false" for the torch step
# beside the fused kernel). Run there from the repository root with .gpu carried (live.sh).
set -u
source benchmarks/gpu/env.sh || exit 1
for stride in ${STRIDES:-1 4}; do
  d=/tmp/phases_$stride
  echo "== stride $stride, ${FRAMES:-60} frames, ${SIZE:-160x120}, $(git log --oneline -1 | cut -c1-7)"
  profile=(); [ "${PROFILE:-1}" = 0 ] || profile=(-m cProfile -o $d.pstats)
  python3 "${profile[@]}" -m gausem_core.cli run --dataset synthetic:loop --size ${SIZE:-160x120} --stride $stride \
    --frames ${FRAMES:-60} --set device=cuda --set refinement.enabled=false \
    $(for s in ${SETS:-}; do echo --set $s; done) --quiet --out $d \
    | grep -E "^(ate_rmse_cm|fps|seconds_per_frame|num_keyframes|num_submaps|tracking_status|loops.seconds) "
  [ "${PROFILE:-1}" = 0 ] || python3 -c "import pstats, sys
pstats.Stats(sys.argv[1]).sort_stats('cumulative').print_stats('gausem_core', 28)" $d.pstats | grep gausem_core
done
