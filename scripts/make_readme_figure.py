#!/usr/bin/env python3
"""Draws the README's figure: the bundled render of two HP codes with what `vernier detect`
found on it (each marker's origin, its pattern x axis in red and y axis in green, its ID) and
the relative pose of marker 300 in marker 5's frame.

    .venv/bin/python scripts/make_readme_figure.py [VERNIER]   (default target/release/vernier)

Writes docs/images/two_hpcodes_detected.png. Needs Pillow (bash scripts/setup_test_tools.sh
installs it into .venv/).
"""
import json
import math
import subprocess
import sys

from PIL import Image, ImageDraw, ImageFont

VERNIER = sys.argv[1] if len(sys.argv) > 1 else "target/release/vernier"
IMAGE = "examples/two_hpcodes.png"
OUT = "docs/images/two_hpcodes_detected.png"
PERIOD = 10.0  # µm


def font(size):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: the bitmap font has one size
        return ImageFont.load_default()


def arrow(draw, start, end, colour):
    angle = math.atan2(end[1] - start[1], end[0] - start[0])
    head = [end] + [(end[0] + 16 * math.cos(angle + math.pi + side * 0.4),
                     end[1] + 16 * math.sin(angle + math.pi + side * 0.4)) for side in (-1, 1)]
    for width, fill in ((9, (0, 0, 0)), (5, colour)):
        draw.line([start, end], fill=fill, width=width)
    draw.polygon(head, fill=colour, outline=(0, 0, 0))


def main():
    found = json.loads(subprocess.run(
        [VERNIER, "detect", "--hpcode", "--period", "10", "--code-size", "33", IMAGE],
        check=True, capture_output=True, text=True).stdout)
    markers = {m["id"]: m for m in found["markers"]}
    image = Image.open(IMAGE).convert("RGB")
    draw = ImageDraw.Draw(image)
    label, caption = font(20), font(16)
    for m in markers.values():
        ox, oy, a = m["x_px"], m["y_px"], m["alpha"]
        length = 6 * PERIOD / m["pixel_size"]  # six periods
        x_end = (ox + length * math.cos(a), oy + length * math.sin(a))
        y_end = (ox - length * math.sin(a), oy + length * math.cos(a))
        arrow(draw, (ox, oy), x_end, (230, 40, 40))
        arrow(draw, (ox, oy), y_end, (40, 200, 60))
        for end, name in ((x_end, "x"), (y_end, "y")):
            draw.text((end[0] + 6, end[1] + 2), name, fill=(255, 255, 255), font=label,
                      stroke_width=2, stroke_fill=(0, 0, 0))
        draw.ellipse([ox - 6, oy - 6, ox + 6, oy + 6], outline=(255, 210, 0), width=3)
        text = f"ID {m['id']}"
        box = draw.textbbox((ox + 12, oy - 34), text, font=label)
        draw.rectangle([box[0] - 4, box[1] - 3, box[2] + 4, box[3] + 3], fill=(255, 210, 0))
        draw.text((ox + 12, oy - 34), text, fill=(0, 0, 0), font=label)
    if 5 in markers and 300 in markers:
        a, b = markers[5], markers[300]

        def camera(m):
            return (m["x"] * math.cos(m["alpha"]) - m["y"] * math.sin(m["alpha"]),
                    m["x"] * math.sin(m["alpha"]) + m["y"] * math.cos(m["alpha"]))

        (ax, ay), (bx, by) = camera(a), camera(b)
        c, s = math.cos(a["alpha"]), math.sin(a["alpha"])
        rx, ry = c * (bx - ax) + s * (by - ay), -s * (bx - ax) + c * (by - ay)
        text = (f"ID 300 in ID 5's frame: ({rx:.3f}, {ry:.3f}) um, {b['alpha'] - a['alpha']:.5f} rad"
                "   (truth: (260, 60) um, pi/2)")
        box = draw.textbbox((10, image.height - 28), text, font=caption)
        draw.rectangle([0, box[1] - 6, image.width, image.height], fill=(255, 255, 255))
        draw.text((10, image.height - 28), text, fill=(0, 0, 0), font=caption)
    # A palette of 96 colours keeps the file small (the render's grey levels and the marks).
    image.quantize(96, dither=Image.Dither.NONE).save(OUT, optimize=True)
    print(OUT)


if __name__ == "__main__":
    main()
