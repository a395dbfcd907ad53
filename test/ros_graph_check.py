"""The node in an ordinary ROS 2 graph (used by test_interop.py): simulated time from a
`/clock` publisher, an override the node does not declare, compressed PNG and JPEG input, a
reliable image subscription through rclcpp's `qos_overrides` syntax, the standard output
messages (decoded again with the upstream definitions), diagnostics that recover after a
burst of bad frames, and warnings on `/rosout`."""

import io
import math
import threading
import time

from PIL import Image as PilImage

import harness
import ros2_types as t
import standard_types

NODE = "/vernier_detector"
TOPIC = "rt/image/compressed"
SIM_CLOCK = (42, 500_000_000)
# JPEG (quality 95) moves the measured phase a little: allow 20× the raw tolerance.
JPEG_TOLERANCE_FACTOR = 20.0
WARN, OK = 1, 0


def encode(frame, size, codec):
    picture = PilImage.frombytes("L", (size, size), frame)
    out = io.BytesIO()
    if codec == "jpeg":
        picture.save(out, format="JPEG", quality=95)
    else:
        picture.save(out, format="PNG")
    return out.getvalue()


def compressed(data, fmt, sec):
    # An empty frame_id, as some camera drivers send: the node must say so and use `camera`.
    return t.CompressedImage(header=t.Header(stamp=t.Time(sec=sec, nanosec=0), frame_id=""),
                             format=fmt, data=data)


def wait_matched(entity, timeout, publications=False):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        matched = (entity.get_matched_publications() if publications
                   else entity.get_matched_subscriptions())
        if matched:
            return True
        time.sleep(0.1)
    return False


class Readers:
    """What test_interop.wait_for needs of a peer: a backlog and `take_all`."""

    def __init__(self):
        self.backlog = {}

    @staticmethod
    def take_all(reader):
        return harness.take_all(reader)


def run_session(domain, work, truth, frames, check, wait_for, tol_m, size):
    work.mkdir(parents=True, exist_ok=True)
    log_path = work / "node.log"
    node = harness.start_node(
        domain,
        ["-p", "period:=10.0", "-p", "use_sim_time:=true", "-p", "image_transport:=compressed",
         "-p", "qos_overrides./image/compressed.subscription.reliability:=reliable",
         "-p", "not_a_vernier_parameter:=3"],
        log_path,
    )
    dp = harness.DomainParticipant(domain)
    topic = harness.Topic(dp, TOPIC, t.CompressedImage)
    reliable = harness.DataWriter(dp, topic, qos=harness.RESULT_QOS)
    best_effort = harness.DataWriter(dp, topic, qos=harness.IMAGE_QOS)

    def reader(name, kind):
        return harness.DataReader(dp, harness.Topic(dp, name, kind), qos=harness.RESULT_QOS)

    peer = Readers()
    with_covariance = reader(f"rt{NODE}/marker_0/pose_with_covariance",
                             t.PoseWithCovarianceStamped)
    detections = reader(f"rt{NODE}/detections", t.Detection3DArray)
    diagnostics = reader("rt/diagnostics", t.DiagnosticArray)
    rosout = reader("rt/rosout", t.Log)
    clock = harness.DataWriter(dp, harness.Topic(dp, "rt/clock", t.Clock), qos=harness.RESULT_QOS)
    stop = threading.Event()

    def tick():
        while not stop.is_set():
            clock.write(t.Clock(clock=t.Time(sec=SIM_CLOCK[0], nanosec=SIM_CLOCK[1])))
            time.sleep(0.1)

    ticker = threading.Thread(target=tick, daemon=True)
    ticker.start()
    store = standard_types.typestore()
    logs = []
    try:
        def starts_with_foreign_parameters():
            assert wait_matched(reliable, 30.0), "node's image reader not discovered"
            assert node.poll() is None, "node exited"
            text = log_path.read_text()
            assert "not_a_vernier_parameter" in text and "ignored" in text, text[-2000:]

        check("use_sim_time and an undeclared override are accepted (warning)",
              starts_with_foreign_parameters)

        def reliable_through_qos_overrides():
            # A reliable reader never matches a best-effort writer.
            time.sleep(2.0)
            assert reliable.get_matched_subscriptions(), "reliable writer not matched"
            assert not best_effort.get_matched_subscriptions(), \
                "a best-effort writer matched: the subscription is not reliable"

        check("qos_overrides makes the image subscription reliable", reliable_through_qos_overrides)

        for codec, fmt, sec, factor in (("png", "png", 100, 1.0),
                                        ("jpeg", "mono8; jpeg compressed mono8", 101,
                                         JPEG_TOLERANCE_FACTOR)):
            def compressed_frame(codec=codec, fmt=fmt, sec=sec, factor=factor):
                msg = compressed(encode(frames[0], size, codec), fmt, sec)
                pose = wait_for(peer, with_covariance, sec, 0, 30.0,
                                resend=lambda: reliable.write(msg))
                ex, ey, _ = truth["frames"][0]["markers"][0]["position_m"]
                p = pose.pose.pose.position
                err = math.hypot(p.x - ex, p.y - ey)
                print(f"  {codec}: error {err:.3e} m ({err / tol_m * 1e-3:.2e} px)")
                assert err < tol_m * factor, f"{codec}: error {err:.3e} m"
                assert pose.header.frame_id == "camera", pose.header.frame_id
                assert 0.0 < pose.pose.covariance[0] < (tol_m * factor) ** 2 * 100
                array = wait_for(peer, detections, sec, 0, 10.0)
                # Decoded again from the node's CDR with the standard definitions.
                raw = array.serialize(use_version_2=False)
                std = standard_types.decode(store, raw, "vision_msgs/msg/Detection3DArray")
                again = bytes(store.serialize_cdr(std, "vision_msgs/msg/Detection3DArray"))
                assert again == bytes(raw), "Detection3DArray is not byte-exact standard CDR"
                assert len(std.detections) == 1, len(std.detections)
                d = std.detections[0]
                assert d.results[0].hypothesis.class_id == "0", d.results[0].hypothesis
                assert d.id == "vernier_marker_0" and std.header.frame_id == "camera"
                q = d.results[0].pose.pose.position
                assert math.hypot(q.x - p.x, q.y - p.y) < 1e-15
                assert list(d.results[0].pose.covariance) == list(pose.pose.covariance)

            check(f"compressed {codec} frame → pose with covariance and vision_msgs detections",
                  compressed_frame)

        def latest_status(timeout):
            deadline = time.monotonic() + timeout
            last = None
            while time.monotonic() < deadline:
                for d in peer.take_all(diagnostics):
                    last = d
                if last is not None:
                    return last
                time.sleep(0.1)
            return last

        def diagnostics_follow_sim_time_and_recover():
            good = compressed(encode(frames[1], size, "png"), "png", 200)
            for _ in range(5):
                reliable.write(good)
                time.sleep(0.3)
            d = latest_status(5.0)
            assert d is not None, "no /diagnostics"
            stamp = (d.header.stamp.sec, d.header.stamp.nanosec)
            assert stamp == SIM_CLOCK, f"diagnostics stamped {stamp}, /clock says {SIM_CLOCK}"
            for i in range(10):
                reliable.write(compressed(b"\x89PNG\r\n\x1a\n not an image", "png", 300 + i))
            time.sleep(1.5)
            d = latest_status(3.0)
            values = {kv.key: kv.value for kv in d.status[0].values}
            assert d.status[0].level == WARN, (d.status[0].level, d.status[0].message)
            assert int(values["window_bad_messages"]) >= 1, values
            print(f"  after the burst: {d.status[0].message}")
            # Good frames for longer than the window: the level comes back.
            deadline = time.monotonic() + 16.0
            level = None
            while time.monotonic() < deadline:
                reliable.write(good)
                time.sleep(0.5)
                d = latest_status(0.5)
                level = d.status[0].level if d is not None else level
                if level == OK and time.monotonic() > deadline - 4.0:
                    break
            assert level == OK, f"diagnostics still at level {level}: {d.status[0].message}"

        check("diagnostics: /clock stamps, WARN on a burst of bad frames, then OK again",
              diagnostics_follow_sim_time_and_recover)

        def rosout_carries_warnings():
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                logs.extend(peer.take_all(rosout))
                warnings = [m for m in logs if m.level == 30]
                if any("frame_id" in m.msg for m in warnings):
                    break
                time.sleep(0.2)
            texts = [m.msg for m in logs if m.level == 30]
            assert any("frame_id" in m for m in texts), f"/rosout warnings: {texts}"
            print(f"  /rosout: {len(texts)} warnings, e.g. {texts[0][:80]!r}")

        check("/rosout carries the node's warnings", rosout_carries_warnings)
    finally:
        stop.set()
        ticker.join(timeout=2)
        harness.stop_node(node)
        tail = log_path.read_text().splitlines()[-10:]
        print("---- graph node.log (tail) ----")
        print("\n".join(tail))
