#!/usr/bin/env python3
"""A Cyclone DDS participant that waits for the node's `~/markers` writer to match its reader
and prints `matched` or `unmatched` (test/discovery_check.py runs it, pinned to one network
interface by CYCLONEDDS_URI, in the node's network namespace or in another one).

    discovery_peer.py DOMAIN TIMEOUT_S"""

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cyclonedds.domain import DomainParticipant  # noqa: E402
from cyclonedds.sub import DataReader  # noqa: E402
from cyclonedds.topic import Topic  # noqa: E402

import harness  # noqa: E402
import ros2_types as t  # noqa: E402


def main():
    domain, timeout = int(sys.argv[1]), float(sys.argv[2])
    dp = DomainParticipant(domain)
    reader = DataReader(dp, Topic(dp, "rt/vernier_detector/markers", t.MarkerPoseArray),
                        qos=harness.RESULT_QOS)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if reader.get_matched_publications():
            print("matched", flush=True)
            return
        time.sleep(0.1)
    print("unmatched", flush=True)


if __name__ == "__main__":
    main()
