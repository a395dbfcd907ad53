"""Reads the poses written by `vernier bag` with PyPI rosbags (vernier-cli/tests/bag_cli.rs).

Usage: read_bag.py OUT.mcap
Prints one JSON object per message: topic, message type, log time, header and poses.
"""
import json
import sys
from pathlib import Path

from rosbags.highlevel import AnyReader

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / 'test'))
from standard_types import decode, typestore  # noqa: E402

STANDARD = typestore()


def pose(p):
    return {'position': [p.position.x, p.position.y, p.position.z],
            'orientation': [p.orientation.x, p.orientation.y, p.orientation.z,
                            p.orientation.w]}


with AnyReader([Path(sys.argv[1])]) as reader:
    for connection, timestamp, raw in reader.messages():
        if connection.msgtype.startswith('vernier_ros/'):
            # The project's own type: decoded with the schema the file carries.
            msg = reader.deserialize(raw, connection.msgtype)
        else:
            # Standard types: decoded with the upstream definitions, not the file's schema,
            # and encoded again by rosbags: byte for byte what vernier wrote.
            msg = decode(STANDARD, raw, connection.msgtype)
            again = bytes(STANDARD.serialize_cdr(msg, connection.msgtype))
            if again != bytes(raw):
                sys.exit(f'{connection.topic}: {connection.msgtype} is not byte-exact CDR '
                         f'({len(again)} bytes from rosbags, {len(raw)} written)')
        out = {'topic': connection.topic, 'type': connection.msgtype, 'time': timestamp,
               'sec': msg.header.stamp.sec, 'nanosec': msg.header.stamp.nanosec,
               'frame_id': msg.header.frame_id}
        if connection.msgtype == 'geometry_msgs/msg/PoseStamped':
            out['pose'] = pose(msg.pose)
        elif connection.msgtype == 'geometry_msgs/msg/PoseWithCovarianceStamped':
            out['pose'] = pose(msg.pose.pose)
            out['covariance'] = [float(v) for v in msg.pose.covariance]
        elif connection.msgtype == 'vision_msgs/msg/Detection3DArray':
            out['detections'] = [{'id': d.id, 'class_id': d.results[0].hypothesis.class_id,
                                  'score': d.results[0].hypothesis.score,
                                  'pose': pose(d.results[0].pose.pose),
                                  'covariance': [float(v) for v in d.results[0].pose.covariance],
                                  'size': [d.bbox.size.x, d.bbox.size.y, d.bbox.size.z]}
                                 for d in msg.detections]
        else:
            out['markers'] = [{'id': int(m.id), 'pose': pose(m.pose),
                               'pixel_size': m.pixel_size, 'quality': m.quality,
                               'covariance': [float(v) for v in m.covariance],
                               'duplicate_id': bool(m.duplicate_id),
                               'decode_confidence': m.decode_confidence} for m in msg.markers]
        print(json.dumps(out))
