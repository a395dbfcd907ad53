#!/usr/bin/env bash
# Longer run of every fuzz harness (issue 16): image decoding, pattern files, detectors on
# small images (vernier/tests/fuzz.rs), parameter files, ROS arguments and CDR messages
# (src/fuzz_tests.rs). `cargo test` runs the same harnesses with few cases and a fixed seed.
#
#   bash scripts/fuzz_long.sh [CASES] [SEED]     # default 100000 cases, seed 7
#
# A failure prints the shrunk input: add it as a regression test (vernier/tests/hostile_inputs.rs
# or the module's tests) with the fix.
set -euo pipefail
cd "$(dirname "$0")/.."
export VERNIER_FUZZ_CASES="${1:-100000}"
export VERNIER_FUZZ_SEED="${2:-7}"
cargo test --release -p vernier --test fuzz
cargo test --release -p vernier_ros --lib fuzz
