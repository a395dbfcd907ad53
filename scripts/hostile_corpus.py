#!/usr/bin/env python3
"""Writes the hostile-input corpus of issue 16 into OUT_DIR, with `manifest.json` listing,
for each case, the `vernier` arguments to run and a fragment the one-line error must hold.

    python3 scripts/hostile_corpus.py OUT_DIR [--data DATA_DIR] [--big]

Decompression bombs are headers only (a few hundred bytes with valid CRCs: the dimensions
are refused before any pixel is decoded); `--big` adds a real 60000x60000 PNG (about 3.5 MB,
a minute to compress), for a manual run. Real images for the truncation cases come from
DATA_DIR (default `$VERNIER_DATA_DIR`, else ../shared/data beside the repository).

The test `vernier-cli/tests/hostile_corpus.rs` runs every case under `prlimit --as=4G` and
checks a clean, non-zero exit with that message, no panic and no abort.
Standard library only.
"""

import json
import os
import struct
import sys
import zlib


def chunk(kind, data):
    body = kind + data
    return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)


def png_header_bomb(width, height, depth=8, color=0):
    """A well-formed PNG (valid CRCs, IEND) whose IHDR declares width x height."""
    ihdr = struct.pack(">IIBBBBB", width, height, depth, color, 0, 0, 0)
    idat = zlib.compress(b"\0" * 64)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def real_png_bomb(side):
    """A real, fully valid grey PNG of side x side black pixels (compressed row by row)."""
    compressor = zlib.compressobj(9)
    row = b"\0" * (side + 1)
    parts = []
    for _ in range(side):
        out = compressor.compress(row)
        if out:
            parts.append(out)
    parts.append(compressor.flush())
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", b"".join(parts))
            + chunk(b"IEND", b""))


def jpeg_with_size(data, width, height):
    """The JPEG `data` with its frame header (SOF0/1/2) patched to width x height."""
    out = bytearray(data)
    i = 2
    while i + 9 < len(out):
        if out[i] != 0xFF:
            raise ValueError("not a JPEG marker at %d" % i)
        marker = out[i + 1]
        length = struct.unpack(">H", bytes(out[i + 2:i + 4]))[0]
        if marker in (0xC0, 0xC1, 0xC2):
            out[i + 5:i + 7] = struct.pack(">H", height)
            out[i + 7:i + 9] = struct.pack(">H", width)
            return bytes(out)
        i += 2 + length
    raise ValueError("no frame header")


def yaml_bomb(levels=12, fan=10):
    lines = ["/**:", "  ros__parameters:", "    period: 10.0"]
    lines.append("    lol0: &a0 [" + ", ".join(["lol"] * fan) + "]")
    for i in range(1, levels):
        lines.append("    lol%d: &a%d [" % (i, i) + ", ".join(["*a%d" % (i - 1)] * fan) + "]")
    return "\n".join(lines) + "\n"


def main():
    args = sys.argv[1:]
    if not args or args[0].startswith("-"):
        sys.exit(__doc__)
    out = args[0]
    big = "--big" in args
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    data = os.environ.get("VERNIER_DATA_DIR") or os.path.join(repo, "..", "shared", "data")
    if "--data" in args:
        data = args[args.index("--data") + 1]
    os.makedirs(out, exist_ok=True)
    cases = []

    def write(name, content):
        path = os.path.join(out, name)
        with open(path, "wb" if isinstance(content, bytes) else "w") as f:
            f.write(content)
        return path

    def case(name, argv, expect):
        cases.append({"name": name, "args": argv, "expect": expect})

    detect = ["detect", "--period", "10"]
    # Decompression bombs: header dimensions above --max-pixels (100 MP).
    for name, w, h, depth, color in [
        ("png_2g_square.png", 2**31 - 1, 2**31 - 1, 8, 0),
        ("png_100000.png", 100000, 100000, 8, 0),
        ("png_60000_rgba16.png", 60000, 60000, 16, 6),
        ("png_16x2e9.png", 16, 2000000000, 8, 0),
    ]:
        path = write(name, png_header_bomb(w, h, depth, color))
        case(name, detect + [path], "--max-pixels")
    bomb = os.path.join(out, "png_100000.png")
    small = write("small.png", png_header_bomb(64, 64))
    case("bitmap_bomb", ["detect", "--stamp", "--period", "15", "--bitmap", bomb, small],
         "--max-pixels")
    if big:
        path = write("png_real_60000.png", real_png_bomb(60000))
        case("png_real_60000.png", detect + [path], "--max-pixels")

    jpeg = os.path.join(data, "hpcode", "code18.jpg")
    with open(jpeg, "rb") as f:
        jpeg_bytes = f.read()
    case("jpeg_65000.jpg", detect + [write("jpeg_65000.jpg", jpeg_with_size(jpeg_bytes, 65000, 65000))],
         "--max-pixels")
    # Integrity: partial files are errors, not partial images.
    case("jpeg_truncated_25.jpg",
         detect + [write("jpeg_truncated_25.jpg", jpeg_bytes[:len(jpeg_bytes) // 4])],
         "truncated JPEG")
    png_path = os.path.join(data, "hpcode", "code19.png")
    with open(png_path, "rb") as f:
        png_bytes = f.read()
    case("png_no_iend.png", detect + [write("png_no_iend.png", png_bytes[:-12])], "IEND")
    case("png_truncated_25.png",
         detect + [write("png_truncated_25.png", png_bytes[:len(png_bytes) // 4])], "PNG")
    flipped = bytearray(png_bytes)
    flipped[len(flipped) // 2] ^= 0x55
    case("png_bad_crc.png", detect + [write("png_bad_crc.png", bytes(flipped))], "CRC")

    # Settings out of range: errors naming the setting, on every detector.
    real = os.path.join(data, "hpcode", "code19.png")
    hp = ["detect", "--hpcode", "--period", "15.5", "--code-size", "33"]
    case("window_4294967295", hp + ["--window-size", "4294967295", real], "window_size")
    case("window_1000000",
         ["detect", "--stamp", "--period", "15", "--bitmap",
          os.path.join(data, "layouts", "stamp69x69.png"), "--window-size", "1000000", real],
         "window_size")
    case("window_larger_than_image", hp + ["--window-size", "30000", real], "window_size")
    case("code_size_1000001", ["detect", "--hpcode", "--period", "15.5", "--code-size", "1000001",
                               real], "code_size")
    case("period_denormal", ["detect", "--period", "5e-324", real], "period")
    case("period_denormal_hp", ["detect", "--hpcode", "--period", "5e-324", "--code-size", "33",
                                real], "period")

    # Render bounds.
    pattern = os.path.join(repo, "examples", "periodic_p15.json")
    render = ["render", "--pattern", pattern, "--pose", "0,0,0", "--pixel-size", "1"]
    target = os.path.join(out, "render.png")
    case("render_65536", render + ["--size", "65536x65536", target], "size")
    case("render_blur_1e9", render + ["--size", "64x64", "--blur", "1e9", target], "blur")
    tiny = write("megarena_tiny_period.json",
                 '{"MegarenaPattern": {"period": 1e-9, "codeDepth": 12}}')
    case("megarena_period_1e-9",
         ["render", "--pattern", tiny, "--pose", "0,0,0", "--pixel-size", "1", "--size", "64x64",
          target], "period")
    fine = write("megarena_fine.json", '{"MegarenaPattern": {"period": 1e-6, "codeDepth": 12}}')
    case("render_sub_pixel_period",
         ["render", "--pattern", fine, "--pose", "0,0,0", "--pixel-size", "1", "--size", "64x64",
          target], "pixels per period")
    if os.path.exists("/dev/full"):
        case("render_enospc", render + ["--size", "64x64", "/dev/full"], "No space left")

    # Export: the size is estimated first; huge regions need --force.
    megarena = os.path.join(data, "patterns", "megarenaPattern.json")
    for roi in ["0,0,1e5,1e5", "0,0,1e6,1e6"]:
        case("export_svg_" + roi, ["export", "--pattern", megarena, "--roi", roi,
                                    os.path.join(out, "big.svg")], "--force")

    # Pattern files.
    deep = write("pattern_deep.json", '{"PeriodicPattern": ' + "[" * 100000 + "]" * 100000 + "}")
    case("pattern_deep", ["detect", "--pattern", deep, real], "JSON")

    # Parameter files (vernier bag --params, same reader limits as the node).
    params = write("yaml_bomb.yaml", yaml_bomb())
    mcap = write("empty.mcap", b"")
    csv = os.path.join(out, "out.csv")
    case("yaml_bomb", ["bag", "--input", mcap, "--params", params, "--output", csv], "nodes")
    for name, text, expect in [
        # A name the node does not declare is ignored with a warning (as rclcpp does); a
        # declared one of the wrong type is an error.
        ("yaml_wrong_type.yaml", "/**:\n  ros__parameters:\n    not_a_param: 1\n    code_size: x\n",
         "code_size"),
        ("yaml_min_quality.yaml", "/**:\n  ros__parameters:\n    min_quality: 2\n", "min_quality"),
        ("yaml_max_rate.yaml", "/**:\n  ros__parameters:\n    max_rate: -5\n", "max_rate"),
        ("yaml_pairs.yaml", "/**:\n  ros__parameters:\n    relative_pairs: ['1-2']\n",
         "relative_pairs"),
        ("yaml_deep.yaml", "/**:\n  ros__parameters:\n    period: " + "[" * 1000 + "]" * 1000 + "\n",
         "YAML"),
    ]:
        path = write(name, text)
        case(name, ["bag", "--input", mcap, "--params", path, "--output", csv], expect)

    with open(os.path.join(out, "manifest.json"), "w") as f:
        json.dump(cases, f, indent=1)
    print("%d cases in %s" % (len(cases), out))


if __name__ == "__main__":
    main()
