#!/usr/bin/env bash
# Installs the independent readers used by the test-suite into an ignored virtual environment
# `.venv/` at the repository root:
#   - gdstk   : reads the GDSII and OASIS layout exports (vernier/tests/export.rs);
#   - rosbags : writes and reads rosbag2 MCAP files for the `vernier bag` round trip;
#   - pillow  : encodes the PNG and JPEG frames of the compressed-input interop check;
#   - cyclonedds : an independent DDS implementation (Eclipse Cyclone DDS, bundled C library)
#               talking to the ROS 2 node in test/test_interop.py and test/bench_node.py.
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
    "pillow==11.0.0"
"$venv/bin/python" -c "import gdstk, rosbags, cyclonedds.domain; print('test tools ready: gdstk', gdstk.__version__)"
