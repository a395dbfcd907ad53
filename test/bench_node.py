#!/usr/bin/env python3
"""Benchmark of the detector node through DDS (not run in CI): a Cyclone DDS publisher sends
1024×1024 mono8 frames (rendered by the project: a periodic grid, or two HP code markers with
IDs 37 and 300) at 30 Hz and 60 Hz for 30 s each; a Cyclone reader on `~/markers` timestamps
every result. Reports, per marker kind:
  * end-to-end latency = receipt time − image stamp (stamp = send time), p50 / p99;
  * frames sent, processed (results received), of those with every marker found, dropped by
    the node while busy (its /diagnostics `frames_dropped`), lost otherwise
    (sent − processed − dropped);
  * node CPU time per processed frame (user + system, /proc/<pid>/stat).

    test/run_bench.sh [--kind periodic|hpcode|hpcode_5mp|megarena|both] [--duration 30]
                      [--rates 30,60] [--tracking on|off|both] [--field-fit on|off]

`--kind hpcode` runs the node with `pattern_type:=hpcode code_size:=33 marker_ids:=[37, 300]
relative_pairs:=['37:300']` (both poses, the relative pose and /tf published per frame);
`--kind hpcode_5mp` is the same on 2456×2054 frames (a 5 MP microscope camera) forming a smooth
sequence (each marker drifts 0.4 px and turns 1 mrad per frame; the cycle's jump back to the
first frame is a loss, found again by the full search), so that tracking can follow them.
`--kind megarena` renders 1024² frames of a 12-bit Megarena at random absolute positions
(`pattern_type:=megarena code_depth:=12`). `both` runs a fresh node per kind (periodic, hpcode)
and prints both tables. `--tracking`
runs the node with `tracking:=true`, `false`, or a fresh node for each; `--field-fit off` sets
`field_fit:=false` (the analysis window's planes: the speed setting for servo loops).

Frames are serialised once and only their stamp is patched before each write, so the Python
publisher keeps up at 60 Hz (Cyclone's own C writer sends them)."""

import argparse
import os
import random
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet  # noqa: E402
from cyclonedds.util import duration  # noqa: E402

import harness  # noqa: E402

SIZE = 1024
cpu_seconds = harness.cpu_seconds
percentile = harness.percentile


class Receiver(threading.Thread):
    """Collects (stamp_ns, receipt_ns, marker count) for every MarkerPoseArray."""

    def __init__(self, peer):
        super().__init__(daemon=True)
        self.peer = peer
        self.results = []
        self.diagnostics = {}
        self.running = True
        self.waitset = WaitSet(peer.dp)
        any_state = SampleState.Any | ViewState.Any | InstanceState.Any
        self.waitset.attach(ReadCondition(peer.markers, any_state))
        self.waitset.attach(ReadCondition(peer.diagnostics, any_state))

    def run(self):
        while self.running:
            self.waitset.wait(duration(milliseconds=50))
            now = time.time_ns()
            for s in self.peer.take_all(self.peer.markers):
                stamp = s.header.stamp.sec * 1_000_000_000 + s.header.stamp.nanosec
                self.results.append((stamp, now, len(s.markers)))
            for d in self.peer.take_all(self.peer.diagnostics):
                self.diagnostics = {kv.key: kv.value for kv in d.status[0].values}


def run_rate(peer, receiver, node, frames, rate, seconds, expected_markers=1, shape=(SIZE, SIZE)):
    payloads = []
    for data in frames:
        payloads.append(harness.image_payload(harness.mono8(shape[0], shape[1], data, 0)))
    receiver.results.clear()
    cpu0 = cpu_seconds(node.pid)
    dropped0 = int(receiver.diagnostics.get("frames_dropped", 0))
    sent = set()
    period_ns = int(1e9 / rate)
    start = time.time_ns() + 200_000_000
    k = 0
    while True:
        due = start + k * period_ns
        if due > start + int(seconds * 1e9):
            break
        pause = (due - time.time_ns()) / 1e9
        if pause > 0:
            time.sleep(pause)
        now = time.time_ns()
        # Stamp = send time.
        harness.write_stamped(peer.image_writer, payloads[k % len(payloads)], now)
        sent.add(now)
        k += 1
    time.sleep(2.5)  # let the last frames and a diagnostics report arrive
    cpu = cpu_seconds(node.pid) - cpu0
    results = [r for r in receiver.results if r[0] in sent]
    latencies = [(recv - stamp) / 1e6 for stamp, recv, _ in results]
    all_found = sum(1 for r in results if r[2] >= expected_markers)
    dropped = int(receiver.diagnostics.get("frames_dropped", 0)) - dropped0
    processed = len(results)
    return {
        "rate": rate,
        "sent": len(sent),
        "processed": processed,
        "all_found": all_found,
        "dropped_busy": dropped,
        "lost_other": len(sent) - processed - dropped,
        "p50": percentile(latencies, 0.5),
        "p99": percentile(latencies, 0.99),
        "mean": statistics.fmean(latencies) if latencies else float("nan"),
        "cpu_ms_per_frame": 1e3 * cpu / processed if processed else float("nan"),
    }


# Per kind: renderer flags, node parameters, marker IDs per frame, relative pairs.
KINDS = {
    "periodic": {
        "render": [],
        "params": ["-p", "period:=10.0", "-p", "marker_ids:=[0]"],
        "ids": (0,),
        "pairs": [],
        "label": "periodic grid",
    },
    "hpcode": {
        "render": ["--ids", "37,300", "--code-size", "33"],
        "params": ["-p", "pattern_type:=hpcode", "-p", "period:=10.0", "-p", "code_size:=33",
                   "-p", "marker_ids:=[37, 300]", "-p", "relative_pairs:=['37:300']"],
        "ids": (37, 300),
        "pairs": [(37, 300)],
        "label": "2 HP codes (W 33) + relative pose",
    },
    "megarena": {
        "render": [],
        "params": ["-p", "pattern_type:=megarena", "-p", "period:=10.0", "-p", "code_depth:=12",
                   "-p", "marker_ids:=[0]"],
        "ids": (0,),
        "pairs": [],
        "label": "12-bit Megarena (absolute position), 1 % noise",
    },
    "hpcode_5mp": {
        "render": ["--ids", "37,300", "--code-size", "33", "--size", "2456", "--height", "2054",
                   "--motion", "0.4"],
        "params": ["-p", "pattern_type:=hpcode", "-p", "period:=10.0", "-p", "code_size:=33",
                   "-p", "marker_ids:=[37, 300]", "-p", "relative_pairs:=['37:300']"],
        "ids": (37, 300),
        "pairs": [(37, 300)],
        "label": "2 HP codes (W 33) + relative pose, smooth motion",
        "shape": (2456, 2054),
    },
}


def bench_kind(kind, domain, work, args, tracking):
    """Starts a node for `kind`, runs every rate, stops it; returns the table rows."""
    spec = KINDS[kind]
    shape = spec.get("shape", (SIZE, SIZE))
    frames_dir = work / kind
    if not (frames_dir / "truth.json").exists():
        harness.render_frames(frames_dir, args.frames, SIZE, 10.0, 0.8, seed=3,
                              kind=kind.split("_")[0], extra=spec["render"])
    truth = __import__("json").loads((frames_dir / "truth.json").read_text())
    frames = [(frames_dir / f["file"]).read_bytes() for f in truth["frames"]]
    log = work / f"node_{kind}_{tracking}.log"
    node = harness.start_node(
        domain, [*spec["params"], "-p", f"tracking:={tracking}",
                 "-p", f"field_fit:={'true' if args.field_fit == 'on' else 'false'}",
                 "--log-level", "error"], log)
    peer = harness.RosPeer(domain, marker_ids=spec["ids"], relative_pairs=spec["pairs"])
    try:
        if not peer.wait_for_node():
            raise SystemExit(f"node not discovered:\n{log.read_text()}")
        receiver = Receiver(peer)
        receiver.start()
        # Warm-up: FFT plans, discovery of the per-marker topics.
        markers = len(spec["ids"])
        run_rate(peer, receiver, node, frames, 10, 2.0, markers, shape)
        rows = [run_rate(peer, receiver, node, frames, float(r), args.duration, markers, shape)
                for r in args.rates.split(",")]
        receiver.running = False
        receiver.join(timeout=2.0)
    finally:
        harness.stop_node(node)
    return rows


def print_table(kind, tracking, field_fit, rows, duration):
    w, h = KINDS[kind].get("shape", (SIZE, SIZE))
    print(f"detector node, {w}x{h} mono8, {KINDS[kind]['label']}, tracking {tracking}, "
          f"field fit {field_fit}, "
          f"{duration:.0f} s per rate, {os.cpu_count()} CPUs")
    print(f"{'rate Hz':>8} {'sent':>6} {'processed':>9} {'all found':>9} {'dropped':>8} "
          f"{'lost':>5} {'p50 ms':>8} {'p99 ms':>8} {'mean ms':>8} {'CPU ms/frame':>13}")
    for r in rows:
        print(f"{r['rate']:8.0f} {r['sent']:6d} {r['processed']:9d} {r['all_found']:9d} "
              f"{r['dropped_busy']:8d} {r['lost_other']:5d} {r['p50']:8.2f} {r['p99']:8.2f} "
              f"{r['mean']:8.2f} {r['cpu_ms_per_frame']:13.2f}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kind", choices=[*KINDS, "both"], default="periodic",
                        help="marker kind of the frames (both: one node and table per kind)")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds per rate")
    parser.add_argument("--rates", default="30,60", help="comma-separated Hz")
    parser.add_argument("--frames", type=int, default=8, help="distinct frames cycled")
    parser.add_argument("--tracking", choices=["on", "off", "both"], default="on",
                        help="the node's tracking parameter (both: a node for each)")
    parser.add_argument("--field-fit", choices=["on", "off"], default="on",
                        help="the node's field_fit parameter (whole-field fit of HP codes, stamps)")
    args = parser.parse_args()
    domain = int(os.environ.get("ROS_DOMAIN_ID", random.randint(1, 200)))
    work = Path(tempfile.mkdtemp(prefix="vernier_bench_"))
    kinds = ["periodic", "hpcode"] if args.kind == "both" else [args.kind]
    modes = {"on": ["true"], "off": ["false"], "both": ["true", "false"]}[args.tracking]
    tables = []
    runs = [(kind, mode) for kind in kinds for mode in modes]
    for n, (kind, mode) in enumerate(runs):
        # A domain per node: nothing of the previous node's discovery lingers.
        domain_n = (domain + n - 1) % 200 + 1
        tables.append((kind, mode, bench_kind(kind, domain_n, work, args, mode)))
    for kind, mode, rows in tables:
        print_table(kind, mode, args.field_fit, rows, args.duration)
    return 0


if __name__ == "__main__":
    sys.exit(main())
