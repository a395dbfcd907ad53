#!/usr/bin/env bash
# Shared set-up of the DDS tests (test/run_interop.sh, test/run_bench.sh, test/run_colcon.sh):
# installs the test tools into the ignored `.venv/`, builds the node and the frame renderer (a
# cargo example; only the renderer with VERNIER_ROS_FROM_INSTALL=1, where the node comes from a
# sourced colcon install tree), then runs the given Python script (with its arguments) inside a
# private network namespace (loopback only, multicast routed on it) so that DDS discovery never
# leaves the machine. Needs root (or user namespaces) for `unshare --net`.
#
#   bash test/run_in_netns.sh SCRIPT.py [ARGS...]
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bash scripts/setup_test_tools.sh
# VERNIER_ROS_PROFILE=test reuses what `cargo test` built (CI); default: release.
profile="${VERNIER_ROS_PROFILE:-release}"
node=(--bin detector)
[ "${VERNIER_ROS_FROM_INSTALL:-}" = 1 ] && node=()
cargo build --profile "$profile" -p vernier_ros "${node[@]}" --example render_test_frames
case "$profile" in dev | test) out=debug ;; *) out="$profile" ;; esac
# Wherever cargo builds ($CARGO_TARGET_DIR, a config's build.target-dir, or ./target).
target_dir="$(cargo metadata --format-version 1 --no-deps --locked |
    grep -o '"target_directory":"[^"]*"' | cut -d'"' -f4)"
export VERNIER_ROS_BIN_DIR="$target_dir/$out"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 200) + 1 ))}"
exec unshare --net -- bash -c '
    set -euo pipefail
    ip link set lo up
    ip link set lo multicast on
    ip route add 224.0.0.0/4 dev lo
    exec "$0" "$@"
' "$root/.venv/bin/python" "$@"
