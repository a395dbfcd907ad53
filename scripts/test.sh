#!/usr/bin/env bash
# The whole test suite: formatting, lints, every workspace test (unit, synthetic round trips,
# real images from $VERNIER_DATA_DIR, default ../shared/data, independent readers and DDS peer
# from the ignored .venv/), the docs' commands, links and API docs (scripts/check_docs.sh), the
# ROS 2 node's interoperability test against Cyclone DDS, its colcon build and its 2-minute
# soak test.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
export VERNIER_DATA_DIR="${VERNIER_DATA_DIR:-$root/../shared/data}"
# One build from scratch: incremental caches would only fill the disk.
export CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"
if [ ! -d "$VERNIER_DATA_DIR" ]; then
    echo "test data not found at $VERNIER_DATA_DIR (set VERNIER_DATA_DIR)" >&2
    exit 1
fi

# System packages the tests need (Debian): a C compiler and Python's venv module.
need=()
command -v cc >/dev/null 2>&1 || need+=(build-essential)
python3 -c "import ensurepip, venv" >/dev/null 2>&1 || need+=(python3-venv)
command -v ip >/dev/null 2>&1 || need+=(iproute2)
command -v unshare >/dev/null 2>&1 || need+=(util-linux)
if [ "${#need[@]}" -gt 0 ]; then
    sudo_cmd=""; [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
    $sudo_cmd apt-get update -qq && $sudo_cmd apt-get install -y -qq "${need[@]}"
fi
rustup component add rustfmt clippy >/dev/null 2>&1 || true

bash scripts/setup_test_tools.sh

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy -D warnings"
cargo clippy --workspace --all-targets --locked -- -D warnings
echo "== cargo test"
cargo test --workspace --locked
echo "== docs: commands, links, rustdoc"
bash scripts/check_docs.sh
echo "== ROS 2 node against an independent DDS (Cyclone DDS)"
VERNIER_ROS_PROFILE=test bash test/run_interop.sh
# colcon build of the node as a ROS user does it (colcon and cargo-ament-build from .venv/),
# its install tree, and the installed node against Cyclone DDS; reuses the test build's
# dependencies.
echo "== colcon build, install tree, installed node (test/run_colcon.sh)"
VERNIER_ROS_PROFILE=test bash test/run_colcon.sh
echo "== soak: the node for 2 minutes at 60 Hz with faults (test/run_soak.sh)"
VERNIER_ROS_PROFILE=test bash test/run_soak.sh
# The optional rerun feature is never in the default build (a large SDK); it must still
# compile and pass the lints.
echo "== cargo check/clippy --features rerun (vernier-cli)"
cargo check -p vernier-cli --features rerun --all-targets --locked
cargo clippy -p vernier-cli --features rerun --all-targets --locked -- -D warnings
# The optional `vernier live` (cargo feature `opencv`, never in the default build): the system's
# OpenCV 4 and libclang (the bindings are generated at build time), GStreamer's base plugins
# for the tests' pipelines; then the lints and its tests (videos written by OpenCV's
# VideoWriter read back through `vernier live`, 16-bit GStreamer frames, error paths, Ctrl-C).
echo "== cargo clippy/test --features opencv (vernier-cli)"
need=()
for package in libopencv-dev clang libclang-dev gstreamer1.0-plugins-base; do
    dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "ok installed" ||
        need+=("$package")
done
if [ "${#need[@]}" -gt 0 ]; then
    sudo_cmd=""; [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
    $sudo_cmd apt-get update -qq && $sudo_cmd apt-get install -y -qq "${need[@]}"
fi
cargo clippy -p vernier-cli --features opencv --all-targets --locked -- -D warnings
cargo test -p vernier-cli --features opencv --locked --bins --test live_cli
