#!/usr/bin/env python3
"""Interoperability test of the detector node against an independent DDS implementation
(Cyclone DDS, PyPI `cyclonedds`), no ROS installation involved.

A Cyclone publisher sends synthetic 1024×1024 mono8 images rendered by the project at known
poses on `rt/image` (`sensor_msgs::msg::dds_::Image_`, best effort); Cyclone readers check:
  * every PoseStamped (`~/marker_0/pose`) and MarkerPoseArray entry against the true pose,
    within 1e-3 px converted to metres, with the image stamp and the configured frame;
  * /tf carries the same transform;
  * a blank frame gives an empty MarkerPoseArray (loss detection);
  * bad messages (wrong length, unknown encoding, zero size, undecodable CDR) are survived
    and counted in /diagnostics;
  * the parameter services (what `ros2 param get/set` calls): invalid values are rejected
    with a reason, a new period applies from the next frame.
Relative poses need two markers with distinct IDs in one image: the periodic detector reports
one (ID 0), so they are covered by the unit tests of src/processing.rs until a multi-marker
detector (HP code) is available through `vernier::Detector`.

Run it with test/run_interop.sh (builds, isolates the network, installs cyclonedds).
Prints `N passed, N failed` and exits non-zero on any failure."""

import math
import os
import random
import sys
import tempfile
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import harness  # noqa: E402
import ros2_types as t  # noqa: E402

SIZE = 1024
PERIOD_UM = 10.0
PIXEL_UM = 0.8
TOL_PX = 1e-3
TOL_M = TOL_PX * PIXEL_UM * 1e-6
FRAMES = 4
CAMERA_FRAME = "test_camera"

results = []


def check(name, fn):
    try:
        fn()
        results.append((name, None))
        print(f"PASS {name}", flush=True)
    except Exception as e:  # noqa: BLE001 - report every failure, keep going
        results.append((name, e))
        print(f"FAIL {name}: {e}", flush=True)
        traceback.print_exc()


def wait_for(peer, reader, sec, nanosec, timeout, resend=None):
    """Waits for a sample stamped (sec, nanosec) on `reader`, calling `resend` every 2 s
    (best-effort images may lose a fragment). Other samples are kept in `peer.backlog`."""
    deadline = time.monotonic() + timeout
    next_send = 0.0
    while time.monotonic() < deadline:
        if resend and time.monotonic() >= next_send:
            resend()
            next_send = time.monotonic() + 2.0
        for s in peer.take_all(reader):
            peer.backlog.setdefault(id(reader), []).append(s)
        for s in peer.backlog.get(id(reader), []):
            if s.header.stamp.sec == sec and s.header.stamp.nanosec == nanosec:
                return s
        time.sleep(0.02)
    raise AssertionError(f"no sample stamped {sec}.{nanosec:09d} within {timeout} s")


def yaw_of(q):
    return 2.0 * math.atan2(q.z, q.w)


def main():
    domain = int(os.environ.get("ROS_DOMAIN_ID", random.randint(1, 200)))
    work = Path(tempfile.mkdtemp(prefix="vernier_interop_"))
    truth, frames = harness.render_frames(work, FRAMES, SIZE, PERIOD_UM, PIXEL_UM, seed=7)
    node = harness.start_node(
        domain,
        ["-p", f"period:={PERIOD_UM}", "-p", f"camera_frame:={CAMERA_FRAME}",
         "-p", "marker_ids:=[0]", "-p", "publish_tf:=true"],
        work / "node.log",
    )
    peer = harness.RosPeer(domain)
    peer.domain = domain
    peer.backlog = {}
    try:
        if not peer.wait_for_node():
            raise SystemExit(f"node not discovered; log:\n{(work / 'node.log').read_text()}")
        run_checks(peer, truth, frames, node)
    finally:
        harness.stop_node(node)
        log = (work / "node.log").read_text()
        print("---- node log (tail) ----")
        print("\n".join(log.splitlines()[-20:]))
    failed = sum(1 for _, e in results if e is not None)
    print(f"{len(results) - failed} passed, {failed} failed")
    return 1 if failed else 0


def run_checks(peer, truth, frames, node):
    def send(frame_bytes, sec, **kw):
        return lambda: peer.image_writer.write(harness.mono8(SIZE, SIZE, frame_bytes, sec, **kw))

    for i, (frame, expected) in enumerate(zip(frames, truth["frames"])):
        sec = 1000 + i

        def poses_match(frame=frame, expected=expected, sec=sec):
            array = wait_for(peer, peer.markers, sec, 0, 30.0, resend=send(frame, sec))
            pose = wait_for(peer, peer.poses[0], sec, 0, 5.0)
            assert array.header.frame_id == CAMERA_FRAME, array.header.frame_id
            assert pose.header.frame_id == CAMERA_FRAME, pose.header.frame_id
            assert len(array.markers) == 1, f"{len(array.markers)} markers"
            m = array.markers[0]
            true_marker = expected["markers"][0]
            ex, ey, _ = true_marker["position_m"]
            for label, p in (("PoseStamped", pose.pose), ("MarkerPoseArray", m.pose)):
                err = math.hypot(p.position.x - ex, p.position.y - ey)
                print(f"  frame {i} {label}: error {err:.3e} m = {err / (PIXEL_UM * 1e-6):.2e} px")
                assert err < TOL_M, f"{label} position error {err:.3e} m > {TOL_M:.1e} m"
                assert abs(p.position.z) < 1e-15
                dyaw = math.remainder(yaw_of(p.orientation) - true_marker["alpha"], 2 * math.pi)
                # 1e-3 px over the half image gives ~2e-6 rad; allow 1e-5 rad.
                assert abs(dyaw) < 1e-5, f"{label} yaw error {dyaw:.3e} rad"
            # The scale is measured over the whole image: ~1e-3 px / 512 px relative.
            assert abs(m.pixel_size / (PIXEL_UM * 1e-6) - 1.0) < 1e-5, m.pixel_size
            assert m.id == 0 and 0.0 < m.quality <= 1.0
            assert 0.0 < m.covariance[0] < (TOL_M ** 2) * 100, m.covariance[0]
            assert m.covariance[14] >= 1e5  # z unobserved

        check(f"pose of frame {i} within {TOL_PX} px", poses_match)

    def tf_matches():
        # The last frame's transform camera → vernier_marker_0.
        sec = 1000 + FRAMES - 1
        tf = wait_for_tf(peer, sec)
        tr = tf.transform.translation
        ex, ey, _ = truth["frames"][-1]["markers"][0]["position_m"]
        assert tf.header.frame_id == CAMERA_FRAME and tf.child_frame_id == "vernier_marker_0"
        assert math.hypot(tr.x - ex, tr.y - ey) < TOL_M

    check("/tf carries camera → marker transforms", tf_matches)

    blank = bytes(SIZE * SIZE)

    def empty_on_loss():
        array = wait_for(peer, peer.markers, 2000, 0, 30.0, resend=send(blank, 2000))
        assert array.markers == [], f"{len(array.markers)} markers in a blank frame"
        assert array.header.frame_id == CAMERA_FRAME

    check("empty MarkerPoseArray when the marker is lost", empty_on_loss)

    def bad_count(timeout):
        """The latest `bad_messages` of /diagnostics within `timeout` s (None if none)."""
        deadline = time.monotonic() + timeout
        count = None
        while time.monotonic() < deadline:
            for d in peer.take_all(peer.diagnostics):
                values = {kv.key: kv.value for kv in d.status[0].values}
                count = int(values["bad_messages"])
            if count is not None:
                return count
            time.sleep(0.1)
        return count

    def survives_bad_messages():
        bad = {
            "wrong length": harness.mono8(SIZE, SIZE, frames[0][:-1], 3000),
            "unknown encoding": harness.mono8(SIZE, SIZE, frames[0], 3001, encoding="yuv422"),
            "zero size": harness.mono8(0, 0, b"", 3002),
        }
        # A payload that is not an Image at all (same topic and type name, truncated
        # layout), from a second participant since a participant has one type per topic.
        rogue_dp = harness.DomainParticipant(peer.domain)
        rogue = harness.DataWriter(rogue_dp, harness.Topic(rogue_dp, "rt/image", t.TruncatedImage),
                                   qos=harness.IMAGE_QOS)
        deadline = time.monotonic() + 20
        while not rogue.get_matched_subscriptions():
            assert time.monotonic() < deadline, "rogue writer not matched"
            time.sleep(0.1)
        writers = {kind: peer.image_writer for kind in bad}
        bad["undecodable CDR"] = t.TruncatedImage(stamp_sec=3003)
        writers["undecodable CDR"] = rogue
        before = bad_count(5.0)
        assert before is not None, "no /diagnostics"
        for kind, msg in bad.items():
            # Best effort may lose a sample: resend until the counter moves (1 Hz reports).
            counted = None
            for _ in range(4):
                writers[kind].write(msg)
                time.sleep(1.2)
                counted = bad_count(2.0)
                if counted is not None and counted > before:
                    break
            assert counted is not None and counted > before, f"{kind}: not counted ({counted})"
            print(f"  {kind}: bad_messages {before} -> {counted}")
            before = counted
            assert node.poll() is None, f"node exited after a {kind} message"
        # Still alive and measuring, and nothing was published for the bad frames.
        array = wait_for(peer, peer.markers, 3100, 0, 30.0, resend=send(frames[1], 3100))
        assert len(array.markers) == 1
        for sec in (3000, 3001, 3002, 3003):
            assert not any(s.header.stamp.sec == sec for s in peer.backlog.get(id(peer.markers), []))

    check("bad messages are survived and counted", survives_bad_messages)

    def parameter_services():
        client = harness.ParamClient(peer.dp)
        assert client.wait_ready(), "parameter services not discovered"
        period = client.get("period")
        assert period.type == t.PARAMETER_DOUBLE and period.double_value == PERIOD_UM, period
        ok, reason = client.set("period", t.ParameterValue(type=t.PARAMETER_DOUBLE, double_value=-1.0))
        assert not ok and "period" in reason, (ok, reason)
        print(f"  set period -1 rejected: {reason}")
        ok, reason = client.set("relative_pairs", t.ParameterValue(
            type=t.PARAMETER_STRING_ARRAY, string_array_value=["0:0"]))
        assert not ok and "itself" in reason, (ok, reason)
        # A doubled period doubles the measured scale from the next frame on.
        ok, reason = client.set("period", t.ParameterValue(
            type=t.PARAMETER_DOUBLE, double_value=2 * PERIOD_UM))
        assert ok, reason
        assert client.get("period").double_value == 2 * PERIOD_UM
        array = wait_for(peer, peer.markers, 4000, 0, 30.0, resend=send(frames[0], 4000))
        ratio = array.markers[0].pixel_size / (PIXEL_UM * 1e-6)
        assert abs(ratio - 2.0) < 1e-4, f"pixel size ratio {ratio} after doubling the period"
        ok, reason = client.set("period", t.ParameterValue(
            type=t.PARAMETER_DOUBLE, double_value=PERIOD_UM))
        assert ok, reason

    check("ros2 param get/set through the parameter services", parameter_services)

    def debug_image_on_demand():
        reader = harness.DataReader(
            peer.dp, harness.Topic(peer.dp, "rt/vernier_detector/debug_image", t.Image),
            qos=harness.RESULT_QOS)
        deadline = time.monotonic() + 20
        while not reader.get_matched_publications():
            assert time.monotonic() < deadline, "debug image publisher not discovered"
            time.sleep(0.1)
        time.sleep(2.5)  # the node checks for debug subscribers once a second
        wait_for(peer, peer.markers, 5000, 0, 30.0, resend=send(frames[2], 5000))
        deadline = time.monotonic() + 10
        while True:
            images = [i for i in peer.take_all(reader) if i.header.stamp.sec == 5000]
            if images:
                break
            assert time.monotonic() < deadline, "no debug image for the frame"
            time.sleep(0.1)
        image = images[0]
        assert (image.encoding, image.width, image.height) == ("rgb8", SIZE, SIZE)
        data = bytes(image.data)
        assert len(data) == 3 * SIZE * SIZE
        red = sum(1 for i in range(0, len(data), 3) if data[i:i + 3] == b"\xff\x00\x00")
        assert red > 10, f"{red} red annotation pixels"

    check("annotated debug image while subscribed", debug_image_on_demand)


def wait_for_tf(peer, sec):
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        for msg in peer.take_all(peer.tf):
            for tf in msg.transforms:
                if tf.header.stamp.sec == sec:
                    return tf
        time.sleep(0.05)
    raise AssertionError(f"no /tf transform stamped {sec}")


if __name__ == "__main__":
    sys.exit(main())
