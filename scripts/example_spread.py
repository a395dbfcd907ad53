#!/usr/bin/env python3
"""How far the bundled HP code example's poses scatter with the render's noise alone.

Renders examples/two_hpcodes.json as examples/README.md says, for noise seeds 1..N, detects
both markers and prints the RMS error of each marker's image position (px) and angle (rad),
and of the relative pose of marker 300 in marker 5's frame, against the true poses. The
verdict of scripts/example.sh allows five times these figures.

    python3 scripts/example_spread.py [N] [VERNIER]     (default 40 draws, target/release/vernier)
"""
import json
import math
import os
import subprocess
import sys
import tempfile

N = int(sys.argv[1]) if len(sys.argv) > 1 else 40
VERNIER = sys.argv[2] if len(sys.argv) > 2 else "target/release/vernier"
X, Y, A, S, W, H = 12.5, -7.25, 0.12, 0.8, 640, 400  # the render's pose, pixel size and size
MARKERS = {5: ((-130.0, -30.0), 0.0), 300: ((130.0, 30.0), math.pi / 2)}  # centre (µm), turn


def rz(a, u, v):
    return u * math.cos(a) - v * math.sin(a), u * math.sin(a) + v * math.cos(a)


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def rms(values):
    return math.sqrt(sum(v * v for v in values) / len(values))


def main():
    truth = {}
    for mid, ((dx, dy), turn) in MARKERS.items():
        cx, cy = rz(A, dx + X, dy + Y)
        truth[mid] = (W // 2 + cx / S, H // 2 + cy / S, A + turn)
    pos, ang, rel_pos, rel_ang = [], [], [], []
    with tempfile.TemporaryDirectory() as work:
        image = os.path.join(work, "render.png")
        for seed in range(1, N + 1):
            subprocess.run(
                [VERNIER, "render", "--pattern", "examples/two_hpcodes.json",
                 "--pose", f"{X},{Y},{A}", "--pixel-size", str(S), "--size", f"{W}x{H}",
                 "--bits", "8", "--noise", "0.02", "--blur", "0.8", "--seed", str(seed), image],
                check=True, capture_output=True)
            found = json.loads(subprocess.run(
                [VERNIER, "detect", "--hpcode", "--period", "10", "--code-size", "33", image],
                check=True, capture_output=True, text=True).stdout)
            m = {k["id"]: k for k in found["markers"]}
            if set(m) != set(MARKERS):
                sys.exit(f"seed {seed}: found markers {sorted(m)}, not {sorted(MARKERS)}")
            for mid, (tx, ty, ta) in truth.items():
                pos.append(math.hypot(m[mid]["x_px"] - tx, m[mid]["y_px"] - ty))
                ang.append(wrap(m[mid]["alpha"] - ta))
            a, b = m[5], m[300]
            ta_, tb_ = rz(a["alpha"], a["x"], a["y"]), rz(b["alpha"], b["x"], b["y"])
            rx, ry = rz(-a["alpha"], tb_[0] - ta_[0], tb_[1] - ta_[1])
            rel_pos.append(math.hypot(rx - 260.0, ry - 60.0) / S)
            rel_ang.append(wrap(b["alpha"] - a["alpha"] - math.pi / 2))
    print(f"{N} noise draws: per marker RMS {rms(pos):.2e} px, {rms(ang):.2e} rad; "
          f"relative pose RMS {rms(rel_pos):.2e} px, {rms(rel_ang):.2e} rad")


if __name__ == "__main__":
    main()
