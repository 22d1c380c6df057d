#!/usr/bin/env bash
# Build tf2_msgs/TFMessage (tools/tf2_msgs) into a venv with the ROS interface generator wheels, so that the nodes
# publish /tf and /tf_static on the pip set-up (gausem_ros/tf.py). Usage: tools/build_tf2_msgs.sh VENV
# Nothing to do where `import tf2_msgs` works (a ROS install, or built before). Without cmake or a C/C++ compiler it
# says so and exits 0: the set-up goes on and the nodes warn that TF is unavailable (odometry and path carry the
# poses). Any other failure (pip, configure, compile) exits non-zero.
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
V=$(realpath "$1")
PY=$V/bin/python
if "$PY" -c "import tf2_msgs.msg" 2>/dev/null; then
  echo "tf2_msgs: importable, nothing to build"
  exit 0
fi
for tool in cmake cc c++; do
  if ! command -v "$tool" >/dev/null; then
    echo "tf2_msgs: NOT built: '$tool' is missing (Debian: apt-get install cmake g++); without it the nodes publish" \
         "no /tf (odometry and path only). Install it and run: $0 $1" >&2
    exit 0
  fi
done
start=$SECONDS
"$PY" -m pip install -q --disable-pip-version-check -r "$HERE/../requirements-tf.txt" -c "$HERE/../constraints.txt"
# The wheels' CMake exports carry the include dirs of the interpreter that built them (/opt/python/cp3XX-cp3XX/...):
# point them at this venv's Python and numpy headers.
PYINC=$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
NPINC=$("$PY" -c "import numpy; print(numpy.get_include())")
{ grep -rlE "/opt/python/cp3[0-9]+-cp3[0-9]+" "$V/share" --include="*.cmake" || true; } | xargs -r sed -i \
  -e "s#/opt/python/cp3[0-9]*-cp3[0-9]*/include/python3\.[0-9]*#$PYINC#g" \
  -e "s#/opt/python/cp3[0-9]*-cp3[0-9]*/lib/python3\.[0-9]*/site-packages/numpy/_core/include#$NPINC#g"
BUILD=$(mktemp -d)
trap 'rm -rf "$BUILD"' EXIT
export AMENT_PREFIX_PATH=$V  # the generators find the type supports through the ament index
cmake -S "$HERE/tf2_msgs" -B "$BUILD" -DCMAKE_PREFIX_PATH="$V" -DCMAKE_INSTALL_PREFIX="$V" \
  -DPython3_EXECUTABLE="$PY" -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release >"$BUILD/configure.log" \
  || { cat "$BUILD/configure.log" >&2; exit 1; }
cmake --build "$BUILD" -j"$(nproc)" >"$BUILD/build.log" || { cat "$BUILD/build.log" >&2; exit 1; }
cmake --install "$BUILD" >/dev/null
"$PY" -c "from tf2_msgs.msg import TFMessage; TFMessage()"
echo "tf2_msgs: built into $V in $((SECONDS - start)) s"
