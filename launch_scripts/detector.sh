#!/usr/bin/env bash
# Starts the vernier_ros detector node without ROS launch, with params/detector.yaml.
#
#   launch_scripts/detector.sh [extra --ros-args arguments...]
#   e.g. launch_scripts/detector.sh -r image:=/camera/image_raw -p period:=8.0
#
# Uses `ros2 run vernier_ros detector` when the package is installed in a sourced ROS 2
# workspace (colcon build), otherwise builds and runs the node with cargo (no ROS needed).
# Environment: PARAMS_FILE (default: params/detector.yaml next to this script's folder),
# ROS_DOMAIN_ID (DDS domain, default 0).
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
params="${PARAMS_FILE:-$here/../params/detector.yaml}"

if command -v ros2 >/dev/null 2>&1 && ros2 pkg prefix vernier_ros >/dev/null 2>&1; then
    exec ros2 run vernier_ros detector --ros-args --params-file "$params" "$@"
fi
cd "$here/.."
exec cargo run --release --bin detector -- --ros-args --params-file "$params" "$@"
