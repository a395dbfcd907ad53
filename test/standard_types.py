"""The standard ROS 2 message definitions, for decoding the node's and `vernier bag`'s CDR
independently of the project's own type descriptions: PyPI rosbags' Jazzy type store, plus
vision_msgs (not shipped by rosbags) registered from its upstream layouts in test/msg_defs/.
"""
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

MSG_DEFS = Path(__file__).resolve().parent / 'msg_defs'
VISION_MSGS = ['ObjectHypothesis', 'BoundingBox3D', 'ObjectHypothesisWithPose', 'Detection3D',
               'Detection3DArray']


def typestore():
    """Jazzy's standard types with vision_msgs registered."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name in VISION_MSGS:
        text = (MSG_DEFS / f'{name}.msg').read_text()
        types.update(get_types_from_msg(text, f'vision_msgs/msg/{name}'))
    store.register(types)
    return store


def decode(store, raw, msgtype):
    """A CDR payload (with its 4-byte encapsulation header) decoded as `msgtype`."""
    return store.deserialize_cdr(raw, msgtype)
