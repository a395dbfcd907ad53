#!/usr/bin/env bash
# Soak test of the detector node (docs/robustness.md): test/soak.py in a private network
# namespace (set-up, build and isolation: test/run_in_netns.sh; needs root or user
# namespaces). Frames of two moving HP codes at camera rate, faults on a seeded schedule,
# memory, recovery, diagnostics and latency drift checked; exits non-zero when a check fails.
#
#   test/run_soak.sh [--duration SECONDS (120)] [--rate HZ (60)] [--size 1mp|5mp] [--seed N]
set -euo pipefail
exec bash "$(dirname "${BASH_SOURCE[0]}")/run_in_netns.sh" \
    "$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)/soak.py" "$@"
