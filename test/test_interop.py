#!/usr/bin/env python3
"""Interoperability test of the detector node against an independent DDS implementation
(Cyclone DDS, PyPI `cyclonedds`), no ROS installation involved.

A Cyclone publisher sends synthetic 1024×1024 mono8 images rendered by the project at known
poses on `rt/image` (`sensor_msgs::msg::dds_::Image_`, best effort); Cyclone readers check,
first with the node detecting a periodic grid (ID 0):
  * every PoseStamped (`~/marker_0/pose`) and MarkerPoseArray entry against the true pose,
    within 1e-3 px converted to metres, with the image stamp and the configured frame;
  * /tf carries the same transform;
  * a blank frame gives an empty MarkerPoseArray (loss detection);
  * bad messages (wrong length, unknown encoding, zero size, undecodable CDR) are survived
    and counted in /diagnostics;
  * the parameter services (what `ros2 param get/set` calls): invalid values are rejected
    with a reason, a new period applies from the next frame;
  * the annotated debug image while someone subscribes;
then with a second node process (own DDS domain) detecting HP codes (`pattern_type:=hpcode`)
on frames holding two markers with distinct IDs `a`, `b` at random poses anywhere in the image,
and `relative_pairs:=['a:b']`:
  * the MarkerPoseArray has exactly both IDs; each `~/marker_<id>/pose` equals its array entry
    and matches the truth: the image position it implies (position / measured pixel size)
    within 1e-3 px, the pixel size within 1e-5 (relative), hence the position in metres
    within (1e-3 px + 1e-5 × the marker's distance from the image centre) × pixel size (a
    marker 500 px off-centre turns a 1e-5 scale error into 5e-3 px), yaw within 2e-5 rad;
  * /tf carries both camera → marker transforms;
  * `~/relative/marker_<a>_<b>/pose` (frame `vernier_marker_<a>`) is the pose of b in a's
    frame composed from the two published poses (to 1e-12 m) and matches the truth within
    2e-3 px plus what the scale and yaw tolerances allow over the markers' distances;
then with a third node in an ordinary ROS 2 graph (`ros_graph_session`): `use_sim_time:=true`
with a Python `/clock` publisher, an undeclared override, `image_transport:=compressed`, and a
reliable subscription through `qos_overrides./image/compressed.subscription.reliability`:
  * a best-effort image writer does not match the node's reliable reader, a reliable one does;
  * PNG and JPEG `sensor_msgs/CompressedImage` frames with an empty frame_id give the truth
    on `~/marker_0/pose_with_covariance` and `~/detections`, in frame `camera`; the
    `vision_msgs/Detection3DArray` is re-decoded with the standard definitions (PyPI
    rosbags' Jazzy store plus vision_msgs' upstream layouts, test/standard_types.py);
  * /diagnostics is stamped with /clock time, turns WARN on a burst of bad frames and
    recovers to OK once the burst has left its 10 s window;
  * /rosout carries the node's warnings (the ignored override, the empty frame_id);
then with a fourth node started with RMW_IMPLEMENTATION=rmw_cyclonedds_cpp, called the way
`ros2 param` on that middleware calls it (Cyclone's request header, test/cyclone_params.py):
get, a rejected and an accepted set, list and describe;
and last the discovery settings (ROS_AUTOMATIC_DISCOVERY_RANGE, ROS_LOCALHOST_ONLY,
ROS_STATIC_PEERS) with a peer in a second network namespace (test/discovery_check.py).

`--installed` (test/run_colcon.sh, after sourcing a colcon workspace's install/setup.sh): only
the first node's pose checks, with the node and parameter file of the install tree
(`lib/vernier_ros/detector --ros-args --params-file share/vernier_ros/params/detector.yaml`).

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

import discovery_check  # noqa: E402
import harness  # noqa: E402
import param_mapping_check  # noqa: E402
import ros2_types as t  # noqa: E402
import ros_graph_check  # noqa: E402

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
    installed = "--installed" in sys.argv[1:]
    print(f"node: {harness.NODE_BIN} --ros-args --params-file {harness.PARAMS_FILE}")
    try:
        if not peer.wait_for_node():
            raise SystemExit(f"node not discovered; log:\n{(work / 'node.log').read_text()}")
        run_checks(peer, truth, frames, node, poses_only=installed)
    finally:
        harness.stop_node(node)
        print_log_tail(work / "node.log")
    if installed:
        return summary()
    # The HP code node on its own domain: nothing of the first node's discovery lingers.
    run_hpcode_session(domain % 200 + 1, work / "hpcode")
    # Sim time, compressed input, QoS overrides, standard messages, /rosout.
    ros_graph_check.run_session((domain + 2) % 200 + 1, work / "graph", truth, frames, check,
                                wait_for, TOL_M, SIZE)
    # `ros2 param` from a ROS 2 install on rmw_cyclonedds, again on a domain of its own.
    cyclone_log = work / "cyclone_params.log"
    check("ros2 param get/set/list/describe in rmw_cyclonedds's service mapping",
          lambda: param_mapping_check.check_cyclone_mapping(
              (domain + 3) % 200 + 1, cyclone_log, PERIOD_UM))
    if cyclone_log.exists():
        print_log_tail(cyclone_log, lines=5)
    discovery_check.run((domain + 4) % 200 + 1, work / "discovery", check)
    return summary()


def summary():
    failed = sum(1 for _, e in results if e is not None)
    print(f"{len(results) - failed} passed, {failed} failed")
    return 1 if failed else 0


def print_log_tail(path, lines=20):
    log = path.read_text()
    print(f"---- {path.name} (tail) ----")
    print("\n".join(log.splitlines()[-lines:]))


def run_checks(peer, truth, frames, node, poses_only=False):
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
    if poses_only:
        return

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


# HP code session: marker IDs a, b (several ID bits set), width in half periods, frames.
HP_IDS = (37, 300)
HP_CODE_SIZE = 33
HP_FRAMES = 4
# Image position (px), pixel size (relative) and yaw (rad) tolerances of each marker. The
# analysis window of a 33-cell marker at 12.5 px per period is ~130 px: 1e-3 px over its half
# gives 1.5e-5 rad. (Measured on 300 such markers: image position ≤ 6.6e-4 px, scale ≤ 8.7e-6,
# yaw ≤ 1.0e-5 rad.)
HP_TOL_PX = 1e-3
HP_SCALE_TOL = 1e-5
HP_YAW_TOL = 2e-5
# Relative pose: both markers' image positions.
HP_REL_TOL_PX = 2e-3


def run_hpcode_session(domain, work):
    a, b = HP_IDS
    truth, frames = harness.render_frames(
        work, HP_FRAMES, SIZE, PERIOD_UM, PIXEL_UM, seed=7, kind="hpcode",
        extra=["--ids", f"{a},{b}", "--code-size", str(HP_CODE_SIZE)],
    )
    log = work / "node.log"
    node = harness.start_node(
        domain,
        ["-p", "pattern_type:=hpcode", "-p", f"period:={PERIOD_UM}",
         "-p", f"code_size:={HP_CODE_SIZE}", "-p", f"camera_frame:={CAMERA_FRAME}",
         "-p", f"marker_ids:=[{a}, {b}]", "-p", f"relative_pairs:=['{a}:{b}']",
         "-p", "publish_tf:=true"],
        log,
    )
    peer = harness.RosPeer(domain, marker_ids=HP_IDS, relative_pairs=[HP_IDS])
    peer.domain = domain
    peer.backlog = {}
    try:
        def discovered():
            assert peer.wait_for_node(), f"HP code node not discovered; log:\n{log.read_text()}"

        check("HP code node discovered (markers, both poses, relative pose)", discovered)
        if results[-1][1] is None:
            run_hpcode_checks(peer, truth, frames)
    finally:
        harness.stop_node(node)
        print_log_tail(log)


def run_hpcode_checks(peer, truth, frames):
    a, b = HP_IDS
    pixel_m = PIXEL_UM * 1e-6
    published = {}

    def send(frame_bytes, sec):
        return lambda: peer.image_writer.write(harness.mono8(SIZE, SIZE, frame_bytes, sec))

    for i, (frame, expected) in enumerate(zip(frames, truth["frames"])):
        sec = 6000 + i

        def markers_match(frame=frame, expected=expected, sec=sec, i=i):
            array = wait_for(peer, peer.markers, sec, 0, 30.0, resend=send(frame, sec))
            assert array.header.frame_id == CAMERA_FRAME, array.header.frame_id
            ids = sorted(m.id for m in array.markers)
            assert ids == sorted(HP_IDS), f"marker ids {ids}, expected {sorted(HP_IDS)}"
            by_id = {m.id: m for m in array.markers}
            for true_marker in expected["markers"]:
                mid = true_marker["id"]
                m = by_id[mid]
                assert not m.duplicate_id and 0.0 < m.quality <= 1.0, (m.duplicate_id, m.quality)
                assert 0.2 <= m.decode_confidence <= 1.0, m.decode_confidence
                assert 0.0 < m.covariance[0] and m.covariance[14] >= 1e5, m.covariance
                stamped = wait_for(peer, peer.poses[mid], sec, 0, 5.0)
                assert stamped.header.frame_id == CAMERA_FRAME, stamped.header.frame_id
                p = stamped.pose
                assert (p.position.x, p.position.y, p.position.z) == (
                    m.pose.position.x, m.pose.position.y, m.pose.position.z)
                assert abs(p.position.z) < 1e-15
                assert abs(p.orientation.x) < 1e-12 and abs(p.orientation.y) < 1e-12
                ex, ey, _ = true_marker["position_m"]
                scale_err = m.pixel_size / pixel_m - 1.0
                # Image position implied by the message (the node publishes position_px ×
                # its measured pixel size) against the rendered one.
                image_err = math.hypot(p.position.x / m.pixel_size - ex / pixel_m,
                                       p.position.y / m.pixel_size - ey / pixel_m)
                err_m = math.hypot(p.position.x - ex, p.position.y - ey)
                radius_px = math.hypot(ex, ey) / pixel_m
                tol_m = (HP_TOL_PX + HP_SCALE_TOL * radius_px) * pixel_m
                dyaw = math.remainder(yaw_of(p.orientation) - true_marker["alpha"], 2 * math.pi)
                print(f"  frame {i} marker {mid} ({radius_px:.0f} px off-centre): image "
                      f"{image_err:.2e} px, scale {scale_err:+.1e}, metres {err_m:.3e} m = "
                      f"{err_m / pixel_m:.2e} px (tol {tol_m / pixel_m:.2e}), yaw {dyaw:+.1e} rad")
                assert image_err < HP_TOL_PX, f"marker {mid}: image error {image_err:.2e} px"
                assert abs(scale_err) < HP_SCALE_TOL, f"marker {mid}: scale error {scale_err:.1e}"
                assert err_m < tol_m, f"marker {mid}: position error {err_m:.3e} m > {tol_m:.3e} m"
                assert abs(dyaw) < HP_YAW_TOL, f"marker {mid}: yaw error {dyaw:.2e} rad"
                published[(sec, mid)] = p

        check(f"HP code frame {i}: both markers, poses within {HP_TOL_PX} px", markers_match)

        def relative_matches(expected=expected, sec=sec, i=i):
            rel = wait_for(peer, peer.relative[(a, b)], sec, 0, 10.0)
            assert rel.header.frame_id == f"vernier_marker_{a}", rel.header.frame_id
            r = rel.pose
            pa, pb = published[(sec, a)], published[(sec, b)]
            # b in a's frame from the two published poses: R(−yaw_a)·(p_b − p_a), yaw_b − yaw_a.
            ya, yb = yaw_of(pa.orientation), yaw_of(pb.orientation)
            dx, dy = pb.position.x - pa.position.x, pb.position.y - pa.position.y
            cx = math.cos(ya) * dx + math.sin(ya) * dy
            cy = -math.sin(ya) * dx + math.cos(ya) * dy
            composed = math.hypot(r.position.x - cx, r.position.y - cy)
            assert composed < 1e-12, f"relative pose is not b in a's frame ({composed:.1e} m)"
            assert abs(math.remainder(yaw_of(r.orientation) - (yb - ya), 2 * math.pi)) < 1e-9
            assert abs(r.position.z) < 1e-15
            tx, ty, _ = expected["relative"]["position_m"]
            radii = [math.hypot(*m["position_m"][:2]) / pixel_m for m in expected["markers"]]
            separation_px = math.hypot(tx, ty) / pixel_m
            tol_px = HP_REL_TOL_PX + HP_SCALE_TOL * sum(radii) + HP_YAW_TOL * separation_px
            err_m = math.hypot(r.position.x - tx, r.position.y - ty)
            dyaw = math.remainder(yaw_of(r.orientation) - expected["relative"]["yaw"], 2 * math.pi)
            print(f"  frame {i} {b} in {a}'s frame ({separation_px:.0f} px apart): "
                  f"{err_m:.3e} m = {err_m / pixel_m:.2e} px (tol {tol_px:.2e}), "
                  f"yaw {dyaw:+.1e} rad")
            assert err_m < tol_px * pixel_m, f"relative position error {err_m / pixel_m:.2e} px"
            assert abs(dyaw) < 2 * HP_YAW_TOL, f"relative yaw error {dyaw:.2e} rad"

        check(f"HP code frame {i}: relative pose of {b} in {a}'s frame", relative_matches)

    def tf_has_both():
        sec = 6000 + HP_FRAMES - 1
        transforms = {tf.child_frame_id: tf for tf in wait_for_tf_all(peer, sec)}
        for mid in HP_IDS:
            tf = transforms.get(f"vernier_marker_{mid}")
            assert tf is not None, f"no /tf for marker {mid}: {sorted(transforms)}"
            assert tf.header.frame_id == CAMERA_FRAME
            p = published[(sec, mid)]
            tr = tf.transform.translation
            assert (tr.x, tr.y, tr.z) == (p.position.x, p.position.y, p.position.z)

    check("HP code: /tf carries both camera → marker transforms", tf_has_both)


def wait_for_tf_all(peer, sec, timeout=10.0):
    """Every /tf transform stamped `sec` (those of one message)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for msg in peer.take_all(peer.tf):
            found = [tf for tf in msg.transforms if tf.header.stamp.sec == sec]
            if found:
                return found
        time.sleep(0.05)
    raise AssertionError(f"no /tf transform stamped {sec}")


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
