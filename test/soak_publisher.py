#!/usr/bin/env python3
"""The soak test's camera (test/soak.py): a Cyclone DDS process publishing the rendered frames
on `rt/image`, which soak.py kills (SIGKILL) and starts again, as a camera driver restart.

    soak_publisher.py FRAMES_DIR

Prints `ready` once the node's image reader is matched, then reads one command per line on
stdin, `<variant> <frame index>`, writes that frame stamped with the current time and prints
the stamp (ns). Variants (`VARIANTS`): the frame as rendered (`good`), its second marker
painted over (`masked`: out of view), no marker at all (`blank`), an empty `frame_id`
(`empty_frame_id`: accepted, published in frame `camera`), and the malformed ones the node
must reject and count (`MALFORMED`): a wrong encoding, a step or a height that disagrees with
the data, truncated data. ROS_DOMAIN_ID names the domain."""

import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import harness  # noqa: E402
import ros2_types as t  # noqa: E402

FRAME_ID = "soak_camera"
# Rejected by the node (counted as bad messages).
MALFORMED = ("wrong_encoding", "wrong_step", "wrong_size", "truncated")
VARIANTS = ("good", "masked", "blank", "empty_frame_id", *MALFORMED)


def background(data):
    """Mean grey level of a frame (what a painted-over marker and a blank frame show)."""
    return sum(data) // len(data)


def masked(data, width, height, frame, truth):
    """`data` with the frame's second marker painted over by a disc of the mean grey level:
    its whole HP code (half-diagonal of `code_size` half periods) plus a margin."""
    out = bytearray(data)
    cx, cy = frame["markers"][1]["origin_px"]
    side_px = truth["code_size"] * truth["period"] / 2 / truth["pixel_size"]
    radius = 0.78 * side_px
    fill = background(data)
    for row in range(max(0, int(cy - radius)), min(height, int(cy + radius) + 1)):
        half = max(0.0, radius * radius - (row - cy) ** 2) ** 0.5
        lo, hi = max(0, int(cx - half)), min(width, int(cx + half) + 1)
        if hi > lo:
            out[row * width + lo:row * width + hi] = bytes([fill]) * (hi - lo)
    return bytes(out)


def message(variant, data, width, height, frame, truth):
    """The image message of `variant` for a rendered frame (`data`, its truth entry)."""
    def image(payload, **kw):
        return harness.mono8(width, height, payload, 0, frame_id=FRAME_ID, **kw)

    if variant == "good":
        return image(data)
    if variant == "masked":
        return image(masked(data, width, height, frame, truth))
    if variant == "blank":
        return image(bytes([background(data)]) * len(data))
    if variant == "empty_frame_id":
        return harness.mono8(width, height, data, 0, frame_id="")
    if variant == "wrong_encoding":
        return image(data, encoding="rgb8")
    if variant == "wrong_step":
        return image(data, step=width + 16)
    if variant == "wrong_size":
        return harness.mono8(width, height + 8, data, 0, frame_id=FRAME_ID)
    if variant == "truncated":
        return image(data[:len(data) // 2])
    raise ValueError(f"unknown variant {variant}")


def main():
    frames_dir = Path(sys.argv[1])
    truth = json.loads((frames_dir / "truth.json").read_text())
    width = truth["size"]
    height = truth.get("height") or width
    frames = [(frames_dir / f["file"]).read_bytes() for f in truth["frames"]]
    dp = harness.DomainParticipant(int(os.environ["ROS_DOMAIN_ID"]))
    writer = harness.DataWriter(dp, harness.Topic(dp, "rt/image", t.Image), qos=harness.IMAGE_QOS)
    deadline = time.monotonic() + 30
    while not writer.get_matched_subscriptions():
        if time.monotonic() > deadline:
            print("not matched", flush=True)
            return 1
        time.sleep(0.05)
    print("ready", flush=True)
    # Serialised once per (variant, frame); malformed ones are rare, built each time.
    cache = {}
    for line in sys.stdin:
        variant, index = line.split()
        key = (variant, int(index))
        payload = cache.get(key)
        if payload is None:
            i = int(index)
            payload = harness.image_payload(
                message(variant, frames[i], width, height, truth["frames"][i], truth))
            if variant not in MALFORMED:
                cache[key] = payload
        stamp = time.time_ns()
        harness.write_stamped(writer, payload, stamp)
        print(stamp, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
