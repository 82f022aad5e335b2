#!/usr/bin/env bash
# Build the ROS 2 interface packages the package registry lacks (tf2_msgs,
# control_msgs) with rosidl from the registry's wheels, and install them into
# a virtualenv beside those wheels (its lib/ and site-packages).
#
#   usage: build.sh VENV
set -euo pipefail
if [[ $# -ne 1 || ! -x "$1/bin/python" ]]; then
  echo "usage: $0 VENV   (a virtualenv with ros-jazzy-rclpy and the rosidl generators)" >&2
  exit 2
fi
venv=$(realpath "$1")
here=$(dirname "$(realpath "$0")")
export PATH="$venv/bin:$PATH" AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv"
for pkg in tf2_msgs control_msgs; do
  build="$venv/.ros_interfaces_build/$pkg"
  log="$build.log"
  mkdir -p "$build"
  echo "building $pkg with rosidl (log: $log)"
  if ! { cmake -S "$here/$pkg" -B "$build" -DCMAKE_INSTALL_PREFIX="$venv" -DCMAKE_BUILD_TYPE=Release \
           -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$venv/bin/python" &&
         cmake --build "$build" -j "$(nproc)" &&
         cmake --install "$build"; } > "$log" 2>&1; then
    tail -n 40 "$log" >&2
    echo "building $pkg failed; the whole log is $log" >&2
    exit 1
  fi
done
