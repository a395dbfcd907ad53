"""Reads the poses written by `vernier bag` with PyPI rosbags (vernier-cli/tests/bag_cli.rs).

Usage: read_bag.py OUT.mcap
Prints one JSON object per message: topic, message type, log time, header and poses.
"""
import json
import sys
from pathlib import Path

from rosbags.highlevel import AnyReader


def pose(p):
    return {'position': [p.position.x, p.position.y, p.position.z],
            'orientation': [p.orientation.x, p.orientation.y, p.orientation.z,
                            p.orientation.w]}


with AnyReader([Path(sys.argv[1])]) as reader:
    for connection, timestamp, raw in reader.messages():
        msg = reader.deserialize(raw, connection.msgtype)
        out = {'topic': connection.topic, 'type': connection.msgtype, 'time': timestamp,
               'sec': msg.header.stamp.sec, 'nanosec': msg.header.stamp.nanosec,
               'frame_id': msg.header.frame_id}
        if connection.msgtype == 'geometry_msgs/msg/PoseStamped':
            out['pose'] = pose(msg.pose)
        else:
            out['markers'] = [{'id': int(m.id), 'pose': pose(m.pose),
                               'pixel_size': m.pixel_size, 'quality': m.quality,
                               'covariance': [float(v) for v in m.covariance],
                               'duplicate_id': bool(m.duplicate_id),
                               'decode_confidence': m.decode_confidence} for m in msg.markers]
        print(json.dumps(out))
