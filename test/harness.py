"""Shared plumbing of the interop test and the benchmark: the node process, a Cyclone DDS
participant speaking ROS 2 type and topic names, and the synthetic frames.

Run inside an isolated network namespace (test/run_interop.sh, test/run_bench.sh): DDS
discovery multicasts, and nothing may leave the machine."""

import json
import os
import subprocess
import time
from pathlib import Path

from cyclonedds._clayer import ddspy_write

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

import ros2_types as t

ROOT = Path(__file__).resolve().parent.parent
# Set by test/run_in_netns.sh after building: cargo's output folder of the profile.
BIN_DIR = Path(os.environ.get("VERNIER_ROS_BIN_DIR", ROOT / "target" / "release"))
# The frame renderer is a cargo example (test/render_test_frames.rs), never installed.
RENDER_BIN = BIN_DIR / "examples" / "render_test_frames"


def installed_package():
    """The prefix of vernier_ros found the way `ros2 run` finds it: the ament index marker
    `share/ament_index/resource_index/packages/vernier_ros` under an AMENT_PREFIX_PATH entry
    (put there by sourcing a colcon workspace's install/setup.sh)."""
    for prefix in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
        if (Path(prefix) / "share/ament_index/resource_index/packages/vernier_ros").is_file():
            return Path(prefix)
    raise SystemExit("vernier_ros is not on AMENT_PREFIX_PATH (source install/setup.sh)")


# VERNIER_ROS_FROM_INSTALL=1 (test/run_colcon.sh, after sourcing install/setup.sh): the node
# and its parameter file from the colcon install tree; otherwise cargo's build and the source.
if os.environ.get("VERNIER_ROS_FROM_INSTALL") == "1":
    _prefix = installed_package()
    NODE_BIN = _prefix / "lib" / "vernier_ros" / "detector"
    PARAMS_FILE = _prefix / "share" / "vernier_ros" / "params" / "detector.yaml"
else:
    NODE_BIN = BIN_DIR / "detector"
    PARAMS_FILE = ROOT / "params" / "detector.yaml"

# ROS 2 speaks XCDR1 (plain CDR); ask Cyclone for it explicitly.
XCDR1 = Policy.DataRepresentation(use_cdrv0_representation=True)
# Sensor-data image writer: best effort, newest sample only.
IMAGE_QOS = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1), XCDR1)
# Reliable readers: a best-effort writer would never match them, the node's are reliable.
RESULT_QOS = Qos(
    Policy.Reliability.Reliable(duration(seconds=1)),
    Policy.History.KeepLast(200),
    XCDR1,
)

# Services, as ROS 2's rmw_qos_profile_services_default: reliable, volatile, keep last 10.
SERVICE_QOS = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(10),
                  XCDR1)


def call_service(writer, reader, request, timeout, accept=lambda reply: True):
    """Writes `request` and returns the first reply on `reader` that `accept`s.

    Matching is asymmetric: our endpoints may be matched before the node's reply writer has
    matched our reader, and a reply written before that is lost. get/set/list/describe are
    idempotent, so the request is re-sent every second until a reply comes."""
    reader.take(N=100)
    deadline = time.monotonic() + timeout
    next_send = 0.0
    while time.monotonic() < deadline:
        if time.monotonic() >= next_send:
            writer.write(request)
            next_send = time.monotonic() + 1.0
        for reply in reader.take(N=10):
            if accept(reply):
                return reply
        time.sleep(0.02)
    raise AssertionError(f"no reply to {type(request).__name__} within {timeout} s")


def services_matched(pairs, timeout):
    """Waits until every (request writer, reply reader) pair is matched with the node's."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if all(w.get_matched_subscriptions() and r.get_matched_publications() for w, r in pairs):
            return True
        time.sleep(0.1)
    return False


def render_frames(out_dir, count, size=1024, period=10.0, pixel_size=0.8, seed=1,
                  kind="periodic", extra=()):
    """Renders `count` frames with the project's renderer (test/render_test_frames.rs;
    `kind` periodic: one grid, ID 0; hpcode: two HP codes, see its header for `extra` flags
    such as `--ids a,b` and `--code-size W`); returns (truth dict, list of bytes)."""
    subprocess.run(
        [str(RENDER_BIN), "--out", str(out_dir), "--kind", kind, "--count", str(count),
         "--size", str(size), "--period", str(period), "--pixel-size", str(pixel_size),
         "--seed", str(seed), *extra],
        check=True,
    )
    truth = json.loads((Path(out_dir) / "truth.json").read_text())
    frames = [(Path(out_dir) / f["file"]).read_bytes() for f in truth["frames"]]
    return truth, frames


def start_node(domain_id, extra_args, log_path, env=None):
    """Starts the detector node with the project's parameter file plus `extra_args`; `env`
    adds to (or, with None values, removes from) the environment."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), **(env or {}))
    env = {k: v for k, v in env.items() if v is not None}
    log = open(log_path, "w")
    return subprocess.Popen(
        [str(NODE_BIN), "--ros-args", "--params-file", str(PARAMS_FILE), *extra_args],
        stdout=log, stderr=subprocess.STDOUT, env=env,
    )


def stop_node(proc):
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def mono8(width, height, data, sec, nanosec=0, frame_id="camera", encoding="mono8", step=None):
    return t.Image(
        header=t.Header(stamp=t.Time(sec=sec, nanosec=nanosec), frame_id=frame_id),
        height=height, width=width, encoding=encoding, is_bigendian=0,
        step=width if step is None else step, data=data,
    )


class RosPeer:
    """A Cyclone DDS participant with an image writer and readers on the node's outputs:
    `~/markers`, `~/marker_<id>/pose` for each of `marker_ids` (`poses[id]`),
    `~/relative/marker_<a>_<b>/pose` for each `(a, b)` of `relative_pairs`
    (`relative[(a, b)]`), /tf and /diagnostics."""

    def __init__(self, domain_id, node="/vernier_detector", marker_ids=(0,), relative_pairs=()):
        self.dp = DomainParticipant(domain_id)
        self.image_writer = DataWriter(self.dp, Topic(self.dp, "rt/image", t.Image), qos=IMAGE_QOS)

        def reader(name, kind):
            return DataReader(self.dp, Topic(self.dp, name, kind), qos=RESULT_QOS)

        self.markers = reader(f"rt{node}/markers", t.MarkerPoseArray)
        self.poses = {i: reader(f"rt{node}/marker_{i}/pose", t.PoseStamped) for i in marker_ids}
        self.relative = {
            (a, b): reader(f"rt{node}/relative/marker_{a}_{b}/pose", t.PoseStamped)
            for a, b in relative_pairs
        }
        self.tf = reader("rt/tf", t.TFMessage)
        self.diagnostics = reader("rt/diagnostics", t.DiagnosticArray)

    def wait_for_node(self, timeout=30.0):
        """Waits until the node's image reader and output writers are matched."""
        deadline = time.monotonic() + timeout
        readers = [self.markers, *self.poses.values(), *self.relative.values()]
        while time.monotonic() < deadline:
            if self.image_writer.get_matched_subscriptions() and all(
                r.get_matched_publications() for r in readers
            ):
                return True
            time.sleep(0.1)
        return False

    def take_all(self, reader):
        return take_all(reader)


def take_all(reader):
    """Every sample waiting in `reader`."""
    out = []
    while True:
        batch = reader.take(N=100)
        if not batch:
            return out
        out.extend(batch)


class ParamClient:
    """`ros2 param get/set` over the node's rcl_interfaces services, Cyclone DDS side.

    Without RMW_IMPLEMENTATION the node serves the "enhanced" RPC-over-DDS mapping
    (rmw_fastrtps style: no request header in the payload); a request without a related-sample
    identity is answered with its own sample identity, so a plain DDS writer/reader pair can
    call the service. (Cyclone's mapping: test/cyclone_params.py.)"""

    def __init__(self, dp, node="/vernier_detector"):
        def pair(service, req, resp):
            w = DataWriter(dp, Topic(dp, f"rq{node}/{service}Request", req), qos=SERVICE_QOS)
            r = DataReader(dp, Topic(dp, f"rr{node}/{service}Reply", resp), qos=SERVICE_QOS)
            return w, r

        self.set_w, self.set_r = pair("set_parameters", t.SetParametersRequest,
                                      t.SetParametersResponse)
        self.get_w, self.get_r = pair("get_parameters", t.GetParametersRequest,
                                      t.GetParametersResponse)

    def wait_ready(self, timeout=20.0):
        return services_matched([(self.set_w, self.set_r), (self.get_w, self.get_r)], timeout)

    def set(self, name, value, timeout=30.0):
        """Sets one parameter; `value` is a t.ParameterValue. Returns (successful, reason)."""
        request = t.SetParametersRequest(parameters=[t.Parameter(name=name, value=value)])
        reply = call_service(self.set_w, self.set_r, request, timeout)
        result = reply.results[0]
        return result.successful, result.reason

    def get(self, name, timeout=30.0):
        reply = call_service(self.get_w, self.get_r, t.GetParametersRequest(names=[name]), timeout)
        return reply.values[0]


CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid):
    """User + system CPU time of process `pid`, seconds (/proc/<pid>/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    # Fields 14 and 15 of stat (utime, stime); index from after the command name.
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def rss_bytes(pid):
    """Resident set size of process `pid`, bytes (VmRSS of /proc/<pid>/status); None once
    the process is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def percentile(values, q):
    """Nearest-rank percentile `q` in [0, 1] of `values` (nan when empty), as the node's
    /diagnostics computes it."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    rank = max(1, min(len(ordered), int(-(-q * len(ordered) // 1))))
    return ordered[rank - 1]


def image_payload(msg):
    """`msg` (a t.Image) serialised once as Cyclone writes it (XCDR1, padded to 4 bytes), for
    `write_stamped`: a Python publisher keeps up with camera rates only by sending the same
    bytes with a new stamp."""
    ser = msg.serialize(use_version_2=False)
    return bytearray(ser.ljust((len(ser) + 3) & ~3, b"\0"))


def write_stamped(writer, payload, stamp_ns):
    """Writes an `image_payload` with its header stamp set to `stamp_ns` (Cyclone's own C
    writer sends it)."""
    # Stamp: bytes 4..12, after the 4-byte encapsulation header.
    payload[4:8] = (stamp_ns // 1_000_000_000).to_bytes(4, "little", signed=True)
    payload[8:12] = (stamp_ns % 1_000_000_000).to_bytes(4, "little")
    ddspy_write(writer._ref, bytes(payload))
