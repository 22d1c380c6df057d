#!/usr/bin/env bash
set -e
source /opt/ros/jazzy/setup.bash
source /ws/install/setup.bash
# ament_python installs console scripts under lib/<package> (for `ros2 run`); put them on PATH too.
export PATH=/ws/install/gausem/lib/gausem:$PATH
exec "$@"
