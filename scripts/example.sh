#!/usr/bin/env bash
# Builds and installs the `vernier` command (release; the first build takes about 4 minutes on
# 2 cores, later ones seconds), then runs the main job, `vernier detect`, on the bundled
# example and says how far the result is from the true pose.
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
# Wherever cargo builds ($CARGO_TARGET_DIR or ./target): the install reuses that build.
target_dir="$(cargo metadata --format-version 1 --no-deps --locked |
    grep -o '"target_directory":"[^"]*"' | cut -d'"' -f4)"
echo "== building and installing vernier (first build: about 4 minutes on 2 cores)"
cargo install --locked --quiet --path vernier-cli --target-dir "$target_dir"
bin_dir="${CARGO_INSTALL_ROOT:-${CARGO_HOME:-$HOME/.cargo}}/bin"
vernier="$bin_dir/vernier"
case ":$PATH:" in *":$bin_dir:"*) ;; *) echo "(add $bin_dir to PATH to type \`vernier\`)";; esac

truth_x=3.25 truth_y=-1.5 truth_alpha=0.1 pixel_size=1.2
image=examples/periodic_p15_x3.25_y-1.5_a0.1_ps1.2.png
echo "== vernier detect --pattern examples/periodic_p15.json $image"
echo "   (truth: x = $truth_x µm, y = $truth_y µm, alpha = $truth_alpha rad, pixel size $pixel_size µm/px)"
"$vernier" detect --pattern examples/periodic_p15.json "$image"
# The verdict, from the CSV row: error against the truth in µm, px and rad.
"$vernier" detect --pattern examples/periodic_p15.json --format csv "$image" | awk -F, \
    -v tx="$truth_x" -v ty="$truth_y" -v ta="$truth_alpha" -v ps="$pixel_size" '
    NR == 1 { for (i = 1; i <= NF; i++) col[$i] = i; next }
    function abs(v) { return v < 0 ? -v : v }
    {
        if ($col["error"] != "" || $col["x"] == "") { print "verdict: no pose (" $col["error"] ")"; bad = 1; exit }
        dx = $col["x"] - tx; dy = $col["y"] - ty; da = $col["alpha"] - ta
        printf "verdict: error x %.2e µm (%.2e px), y %.2e µm (%.2e px), alpha %.2e rad\n", \
            dx, dx / ps, dy, dy / ps, da
        # 1 % noise, 8 bits: a few 1e-3 px and 1e-4 rad are expected (README, phase engine).
        if (abs(dx / ps) < 0.01 && abs(dy / ps) < 0.01 && abs(da) < 1e-3) {
            print "verdict: as expected (within 0.01 px and 1e-3 rad of the true pose)"
        } else { print "verdict: NOT as expected (more than 0.01 px or 1e-3 rad off)"; bad = 1 }
    }
    END { exit bad }'
