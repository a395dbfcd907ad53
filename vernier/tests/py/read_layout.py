"""Independent reader of the GDSII / OASIS exports (used by vernier/tests/export.rs).

Usage: read_layout.py FILE.gds|FILE.oas
Prints one JSON object: library units, top cells, element counts of the top cell before
flattening, every polygon of the flattened top cell as its bounding box with its vertex
count and (layer, datatype), the labels, and for OASIS the CRC validation result.
"""
import json
import sys

import gdstk

path = sys.argv[1]
if path.endswith(".oas"):
    lib = gdstk.read_oas(path)
    validation = gdstk.oas_validate(path)
    valid = None if validation is None else bool(validation[0])
else:
    lib = gdstk.read_gds(path)
    valid = None

tops = lib.top_level()
out = {
    "unit": lib.unit,
    "precision": lib.precision,
    "cells": sorted(c.name for c in lib.cells),
    "top": [c.name for c in tops],
    "valid": valid,
}
if len(tops) == 1:
    top = tops[0]
    out["top_polygons"] = len(top.polygons)
    out["top_references"] = len(top.references)
    out["top_repeated_polygons"] = sum(1 for p in top.polygons if p.repetition.size > 1)
    rects = []
    for p in top.get_polygons(apply_repetitions=True, include_paths=True):
        (x0, y0), (x1, y1) = p.bounding_box()
        rects.append([round(x0, 6), round(y0, 6), round(x1, 6), round(y1, 6),
                      len(p.points), p.layer, p.datatype, round(abs(p.area()), 6)])
    out["polygons"] = rects
    labels = top.get_labels(apply_repetitions=True)
    out["labels"] = [{"text": l.text, "layer": l.layer, "texttype": l.texttype,
                      "x": l.origin[0], "y": l.origin[1]} for l in labels]
json.dump(out, sys.stdout)
