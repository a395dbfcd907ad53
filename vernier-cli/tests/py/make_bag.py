"""Writes a rosbag2 MCAP recording of sensor_msgs/Image frames (vernier-cli/tests/bag_cli.rs).

Usage: make_bag.py MANIFEST.json OUT_DIR
MANIFEST: {"topic", "frame_id", "width", "height", "encoding", "step",
           "frames": [{"file": raw pixel file, "sec", "nanosec"}]}
The bag is written by PyPI rosbags (independent of the project), MCAP storage.
"""
import json
import sys
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

manifest = json.loads(Path(sys.argv[1]).read_text())
out = Path(sys.argv[2])
store = get_typestore(Stores.ROS2_HUMBLE)
Image = store.types['sensor_msgs/msg/Image']
Header = store.types['std_msgs/msg/Header']
Time = store.types['builtin_interfaces/msg/Time']

with Writer(out, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
    images = writer.add_connection(manifest['topic'], Image.__msgtype__, typestore=store)
    # An unrelated topic that the replay must skip.
    String = store.types['std_msgs/msg/String']
    chatter = writer.add_connection('/chatter', String.__msgtype__, typestore=store)
    for frame in manifest['frames']:
        data = np.frombuffer(Path(frame['file']).read_bytes(), dtype=np.uint8)
        msg = Image(
            header=Header(stamp=Time(sec=frame['sec'], nanosec=frame['nanosec']),
                          frame_id=manifest['frame_id']),
            height=manifest['height'],
            width=manifest['width'],
            encoding=manifest['encoding'],
            is_bigendian=0,
            step=manifest['step'],
            data=data,
        )
        t = frame['sec'] * 1_000_000_000 + frame['nanosec']
        writer.write(images, t, store.serialize_cdr(msg, Image.__msgtype__))
        writer.write(chatter, t, store.serialize_cdr(String(data='hello'), String.__msgtype__))
