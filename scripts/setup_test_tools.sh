#!/usr/bin/env bash
# Installs the independent readers used by the test-suite into an ignored virtual environment
# `.venv/` at the repository root:
#   - gdstk   : reads the GDSII and OASIS layout exports (vernier/tests/export.rs);
#   - rosbags : writes and reads rosbag2 MCAP files for the `vernier bag` round trip;
#   - pillow  : encodes the PNG and JPEG frames of the compressed-input interop check;
#   - cyclonedds : an independent DDS implementation (Eclipse Cyclone DDS, bundled C library)
#               talking to the ROS 2 node in test/test_interop.py and test/bench_node.py;
#   - colcon-core, colcon-package-selection, colcon-ros, colcon-ros-cargo (with colcon-cargo):
#               `colcon build --packages-select` of the node without a ROS installation
#               (test/run_colcon.sh);
# and, from crates.io into the same `.venv/bin`, not ~/.cargo:
#   - cargo-ament-build: the `cargo ament-build` that colcon-ros-cargo calls.
# Versions are pinned so that CI and developers validate against the same readers.
# Idempotent: re-running only installs what is missing. Run it before `cargo test`.
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
python="${PYTHON:-python3}"

if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv"
fi
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check \
    "gdstk==1.0.2" \
    "rosbags==0.11.9" \
    "cyclonedds==11.0.1" \
    "pillow==11.0.0" \
    "colcon-core==0.21.3" \
    "colcon-ros==0.5.0" \
    "colcon-cargo==0.2.0" \
    "colcon-ros-cargo==0.2.0" \
    "colcon-package-selection==0.2.10"
cargo_ament_build=0.1.11
if ! grep -qs "cargo-ament-build $cargo_ament_build " "$venv/.crates.toml"; then
    # --force: a binary left by an interrupted install (no record in .crates.toml) is replaced.
    cargo install --quiet --locked --force --root "$venv" --version "$cargo_ament_build" \
        cargo-ament-build
fi
"$venv/bin/python" -c "import gdstk, rosbags, cyclonedds.domain; print('test tools ready: gdstk', gdstk.__version__)"
