#!/usr/bin/env bash
# Benchmark of the detector node through DDS (not part of CI): builds the release binaries,
# installs the test tools into `.venv/`, and runs test/bench_node.py in a private network
# namespace (loopback only). Arguments go to bench_node.py (--kind periodic|hpcode|both,
# --duration, --rates, --frames).
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bash scripts/setup_test_tools.sh
# VERNIER_ROS_PROFILE=test reuses what `cargo test` built (CI); default: release.
profile="${VERNIER_ROS_PROFILE:-release}"
cargo build --profile "$profile" -p vernier_ros --bins
case "$profile" in dev | test) out=debug ;; *) out="$profile" ;; esac
export VERNIER_ROS_BIN_DIR="${CARGO_TARGET_DIR:-$root/target}/$out"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 200) + 1 ))}"
exec unshare --net -- bash -c '
    set -euo pipefail
    ip link set lo up
    ip link set lo multicast on
    ip route add 224.0.0.0/4 dev lo
    exec "$0" "$@"
' "$root/.venv/bin/python" "$root/test/bench_node.py" "$@"
