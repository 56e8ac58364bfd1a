#!/usr/bin/env bash
# Build and install the roigsf_interfaces ament_cmake package into the venv with pip-installed ROS tools,
# and vendor/tf2_msgs (the standard TFMessage: not on PyPI) when no tf2_msgs is installed.
# Usage: build_interfaces.sh VENV. Works around the PyPI wheels' quirks (../shared/notes/ros2-on-pypi.md):
# exported CMake files carry the wheel build machine's include paths, and the prefix paths must point at the venv.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$1"
PYBIN="$VENV/bin/python"

# 1. Rewrite the wheel build machine's include dirs in exported CMake files to this venv's.
"$PYBIN" - "$VENV" <<'PY'
import pathlib, sys, sysconfig
import numpy
venv = pathlib.Path(sys.argv[1])
py_inc, np_inc = sysconfig.get_paths()["include"], numpy.get_include()
for f in (venv / "share").glob("*/cmake/export_*__rosidl_generator_pyExport.cmake"):
    text = f.read_text()
    new = text.replace("/opt/python/cp311-cp311/include/python3.11", py_inc)
    # The wheel's numpy include dir lives in the build machine's site-packages.
    import re
    new = re.sub(r"/[^;\"]*?/site-packages/numpy/(_core|core)/include", np_inc, new)
    if new != text:
        f.write_text(new)
PY

# 2. Configure, build and install each package with plain CMake (about 10 s each).
export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
BUILD="$(mktemp -d)"
trap 'rm -rf "$BUILD"' EXIT
build_package() {  # build_package SOURCE_DIR
    local src="$1" dir="$BUILD/$(basename "$1")"
    cmake -S "$src" -B "$dir" -DCMAKE_INSTALL_PREFIX="$VENV" -DBUILD_TESTING=OFF \
        -DPython3_EXECUTABLE="$PYBIN" -DCMAKE_BUILD_TYPE=Release >"$BUILD/cmake.log" 2>&1 \
        || { cat "$BUILD/cmake.log" >&2; exit 1; }
    cmake --build "$dir" -j2 >"$BUILD/build.log" 2>&1 || { tail -50 "$BUILD/build.log" >&2; exit 1; }
    cmake --install "$dir" >/dev/null
}
# tf2_msgs: a full ROS install has it; the PyPI wheels do not (the nodes read the camera pose from /tf).
if ! "$PYBIN" -c "import tf2_msgs.msg" 2>/dev/null || [ -f "$VENV/share/tf2_msgs/.roigsf-vendored" ]; then
    build_package "$REPO/vendor/tf2_msgs"
    touch "$VENV/share/tf2_msgs/.roigsf-vendored"
fi
build_package "$REPO/roigsf_interfaces"
"$PYBIN" -c "from roigsf_interfaces.srv import GetNextBestView; GetNextBestView.Request()"
"$PYBIN" -c "from tf2_msgs.msg import TFMessage; TFMessage()"
