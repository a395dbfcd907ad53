#!/usr/bin/env bash
# Builds the project (release) and runs the main job, `vernier detect`, on the bundled example.
# Needs a Rust toolchain (cargo ≥ 1.85) and a C compiler; installs the compiler on Debian.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
if ! command -v cc >/dev/null 2>&1; then
    sudo_cmd=""; [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
    $sudo_cmd apt-get update -qq && $sudo_cmd apt-get install -y -qq build-essential
fi
if ! command -v cargo >/dev/null 2>&1; then
    echo "cargo not found: install Rust ≥ 1.85 (https://rustup.rs), then re-run $0" >&2
    exit 1
fi
cargo build --release --locked -p vernier-cli
echo "== vernier detect on examples/ (truth: x=3.25 um, y=-1.5 um, alpha=0.1 rad, pixel size 1.2 um/px)"
./target/release/vernier detect --pattern examples/periodic_p15.json examples/*.png
