#!/usr/bin/env bash
# Benchmark of the detector node through DDS (not part of CI): test/bench_node.py in a private
# network namespace (set-up, release build and isolation: test/run_in_netns.sh). Arguments go
# to bench_node.py (--kind periodic|hpcode|hpcode_5mp|megarena|both, --duration, --rates, --frames,
# --tracking on|off|both).
set -euo pipefail
exec bash "$(dirname "${BASH_SOURCE[0]}")/run_in_netns.sh" \
    "$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)/bench_node.py" "$@"
