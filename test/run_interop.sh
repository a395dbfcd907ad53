#!/usr/bin/env bash
# Interoperability test of the detector node against Cyclone DDS (PyPI `cyclonedds`), no ROS
# installation needed: test/test_interop.py in a private network namespace (set-up, build
# and isolation: test/run_in_netns.sh; needs root or user namespaces).
set -euo pipefail
exec bash "$(dirname "${BASH_SOURCE[0]}")/run_in_netns.sh" \
    "$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)/test_interop.py"
