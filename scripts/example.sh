#!/usr/bin/env bash
# Builds and installs the `vernier` command (release; the first build takes about 4 minutes on
# 2 cores, later ones seconds), then runs the main job on the bundled example: two HP code
# markers in one image (examples/two_hpcodes.png, rendered by the project at a known pose),
# found with their IDs, and the pose of one in the other's frame. Ends with a verdict: the
# errors against the true poses, and whether they are within what the render's noise allows.
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

# The render (examples/README.md): pattern examples/two_hpcodes.json at pose x = 12.5 µm,
# y = −7.25 µm, alpha = 0.12 rad, 0.8 µm per pixel, 640×400 px, blur 0.8 px, 2 % noise, 8 bits.
# Marker 5 is the pattern's left code; marker 300 sits 260 µm right of it and 60 µm below,
# turned a quarter turn: its pose in marker 5's frame is (260 µm, 60 µm, π/2).
image=examples/two_hpcodes.png
echo "== vernier detect --hpcode --period 10 --code-size 33 $image"
"$vernier" detect --hpcode --period 10 --code-size 33 "$image"
# The verdict, from the CSV rows. Tolerances: five times the RMS error over 40 noise draws of
# this render (python3 scripts/example_spread.py): 1.2e-3 px and 9.7e-6 rad per marker, 4.0e-3 px
# and 1.4e-5 rad for the relative pose.
"$vernier" detect --hpcode --period 10 --code-size 33 --format csv "$image" | awk -F, '
    function abs(v) { return v < 0 ? -v : v }
    function wrap(a) { while (a >= PI) a -= 2 * PI; while (a < -PI) a += 2 * PI; return a }
    BEGIN {
        PI = atan2(0, -1); X = 12.5; Y = -7.25; A = 0.12; S = 0.8; CX = 320; CY = 200
        # Each marker: its centre in the pattern frame (µm) and its turn in it.
        dx[5] = -130; dy[5] = -30; turn[5] = 0
        dx[300] = 130; dy[300] = 30; turn[300] = PI / 2
        POS_TOL = 0.006; ALPHA_TOL = 5e-5; REL_POS_TOL = 0.02; REL_ALPHA_TOL = 7e-5
    }
    NR == 1 { for (i = 1; i <= NF; i++) col[$i] = i; next }
    $col["error"] != "" { print "verdict: no pose (" $col["error"] ")"; bad = 1; exit }
    $col["id"] == 5 || $col["id"] == 300 {
        id = $col["id"]; seen[id] = 1
        x[id] = $col["x"]; y[id] = $col["y"]; alpha[id] = $col["alpha"]
        # Where the marker centre must appear: centre pixel + Rz(A)·(d + (X, Y))/S.
        u = dx[id] + X; v = dy[id] + Y
        tx = CX + (u * cos(A) - v * sin(A)) / S; ty = CY + (u * sin(A) + v * cos(A)) / S
        ex = $col["x_px"] - tx; ey = $col["y_px"] - ty; ea = wrap($col["alpha"] - A - turn[id])
        printf "verdict: marker %d found, image position error (%.1e, %.1e) px, alpha error %.1e rad\n", id, ex, ey, ea
        if (sqrt(ex * ex + ey * ey) > POS_TOL || abs(ea) > ALPHA_TOL) bad = 1
    }
    END {
        if (!seen[5] || !seen[300]) { print "verdict: NOT as expected (markers 5 and 300 not both found)"; exit 1 }
        # Pose of 300 in 5'"'"'s frame: Rz(−alpha5)·(t300 − t5), t = Rz(alpha)·(x, y).
        t5x = x[5] * cos(alpha[5]) - y[5] * sin(alpha[5]); t5y = x[5] * sin(alpha[5]) + y[5] * cos(alpha[5])
        t3x = x[300] * cos(alpha[300]) - y[300] * sin(alpha[300]); t3y = x[300] * sin(alpha[300]) + y[300] * cos(alpha[300])
        rx = (t3x - t5x) * cos(alpha[5]) + (t3y - t5y) * sin(alpha[5])
        ry = -(t3x - t5x) * sin(alpha[5]) + (t3y - t5y) * cos(alpha[5])
        ra = wrap(alpha[300] - alpha[5])
        printf "verdict: marker 300 in marker 5'"'"'s frame: x %.4f µm, y %.4f µm, alpha %.6f rad (truth 260, 60, %.6f)\n", rx, ry, ra, PI / 2
        erx = (rx - 260) / S; ery = (ry - 60) / S; era = ra - PI / 2
        printf "verdict: relative pose error (%.1e, %.1e) px, alpha %.1e rad\n", erx, ery, era
        if (sqrt(erx * erx + ery * ery) > REL_POS_TOL || abs(era) > REL_ALPHA_TOL) bad = 1
        if (bad) {
            printf "verdict: NOT as expected (allowed: %.3f px and %.0e rad per marker, %.2f px and %.0e rad relative)\n", POS_TOL, ALPHA_TOL, REL_POS_TOL, REL_ALPHA_TOL
            exit 1
        }
        printf "verdict: as expected (within %.3f px and %.0e rad per marker, %.2f px and %.0e rad relative: five times the render noise'"'"'s RMS)\n", POS_TOL, ALPHA_TOL, REL_POS_TOL, REL_ALPHA_TOL
    }'
