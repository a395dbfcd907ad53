#!/usr/bin/env python3
"""Writes examples/two_hpcodes.json: two HP codes on one pattern, as a BitmapPattern.

Marker A (ID 5) and marker B (ID 300) are the project's own HP code layouts (size 17, code
size 33, period 10 µm), exported cell by cell with `vernier export` (one pixel per half-period
cell). B is turned a quarter turn clockwise on screen (alpha +π/2 in the image's y-down frame)
and placed 52 cells (260 µm) right of A and 12 cells (60 µm) below it, so the relative pose of
B in A's frame is exactly x = 260 µm, y = 60 µm, alpha = π/2.

    python3 scripts/make_example_pattern.py A.png B.png examples/two_hpcodes.json

where A.png and B.png come from
    vernier export --pattern HP.json --id 5 A.png
    vernier export --pattern HP.json --id 300 B.png
with HP.json = {"HPCodePattern": {"unit": "um", "period": 10.0, "size": 17}}.
scripts/example.sh documents the commands; examples/README.md the true poses.
Needs Pillow (the test tools' .venv has it).
"""
import sys

from PIL import Image

ROWS, COLS = 45, 85  # both ≡ 1 (mod 4): the centre cell (22, 42) is a dot position
A_AT, B_AT = (0, 0), (12, 52)  # top-left cell of each 33 × 33 marker (even: dots on dots


def cells(path):
    image = Image.open(path).convert("L")
    width, height = image.size
    pixels = list(image.getdata())
    return [[1 if pixels[r * width + c] > 127 else 0 for c in range(width)] for r in range(height)]


def turned_clockwise(grid):
    n = len(grid)
    return [[grid[n - 1 - c][r] for c in range(n)] for r in range(n)]


def main():
    a_png, b_png, out = sys.argv[1:4]
    a, b = cells(a_png), turned_clockwise(cells(b_png))
    bitmap = [[0] * COLS for _ in range(ROWS)]
    for grid, (top, left) in ((a, A_AT), (b, B_AT)):
        for r, row in enumerate(grid):
            for c, v in enumerate(row):
                bitmap[top + r][left + c] = v
    rows = ",\n".join("            [" + ", ".join(map(str, row)) + "]" for row in bitmap)
    with open(out, "w", encoding="utf-8") as f:
        f.write(
            "{\n"
            '    "BitmapPattern": {\n'
            '        "description": "Two HP codes (size 17, code size 33): ID 5, and ID 300 turned'
            ' a quarter turn, 260 um right and 60 um below it",\n'
            '        "unit": "um",\n'
            '        "period": 10.000000000000000,\n'
            '        "bitmap": [\n' + rows + "\n        ]\n"
            "    }\n"
            "}\n"
        )


if __name__ == "__main__":
    main()
