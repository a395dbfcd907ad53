"""The node's discovery settings (src/discovery.rs), part of test/test_interop.py.

A second network namespace joined to the test's one by a veth pair stands for another host:
the node and a Cyclone peer pinned to the loopback interface run in the test's namespace
(10.231.0.1 on the veth), a Cyclone peer pinned to the veth runs in the other one (10.231.0.2).
  * default settings: both peers match the node's writer (the control: the other namespace is
    reachable, so the next checks' "unmatched" means something);
  * ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, and ROS_LOCALHOST_ONLY=1: the loopback peer
    matches, the other namespace's does not, and the node logs the setting;
  * ROS_AUTOMATIC_DISCOVERY_RANGE=OFF: the node refuses to start, saying why;
  * ROS_STATIC_PEERS: the node logs that it ignores them."""

import os
import subprocess
import sys
import time
from pathlib import Path

import harness

HERE = Path(__file__).resolve().parent
LOCAL_IP, REMOTE_IP = "10.231.0.1", "10.231.0.2"
MATCH_TIMEOUT = 20.0
CYCLONE_URI = ('<CycloneDDS><Domain Id="any"><General><Interfaces>'
               '<NetworkInterface name="{}" multicast="true"/>'
               '</Interfaces></General></Domain></CycloneDDS>')
# Environment variables of the settings; each scenario sets its own.
SETTINGS = ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS")


def sh(*cmd):
    subprocess.run(cmd, check=True)


class OtherHost:
    """A network namespace on a veth pair with the current one."""

    def __enter__(self):
        sh("ip", "link", "add", "vd0", "type", "veth", "peer", "name", "vd1")
        sh("ip", "addr", "add", f"{LOCAL_IP}/24", "dev", "vd0")
        sh("ip", "link", "set", "vd0", "up", "multicast", "on")
        own = os.readlink("/proc/self/ns/net")
        self.holder = subprocess.Popen(["unshare", "--net", "--", "sleep", "3600"])
        deadline = time.monotonic() + 5
        while os.readlink(f"/proc/{self.holder.pid}/ns/net") == own:
            if time.monotonic() > deadline:
                raise AssertionError("second network namespace not created")
            time.sleep(0.02)
        sh("ip", "link", "set", "vd1", "netns", str(self.holder.pid))
        self.run("ip", "link", "set", "lo", "up")
        self.run("ip", "addr", "add", f"{REMOTE_IP}/24", "dev", "vd1")
        self.run("ip", "link", "set", "vd1", "up", "multicast", "on")
        return self

    def run(self, *cmd):
        sh("nsenter", "-t", str(self.holder.pid), "-n", *cmd)

    def __exit__(self, *exc):
        subprocess.run(["ip", "link", "del", "vd0"], check=False)
        self.holder.kill()
        self.holder.wait()


def peer(domain, interface, netns_pid=None):
    cmd = [sys.executable, str(HERE / "discovery_peer.py"), str(domain), str(MATCH_TIMEOUT)]
    if netns_pid is not None:
        cmd = ["nsenter", "-t", str(netns_pid), "-n", *cmd]
    env = dict(os.environ, CYCLONEDDS_URI=CYCLONE_URI.format(interface))
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, env=env)


def scenario(domain, other, log_path, settings):
    """Starts the node with `settings`; returns (loopback peer's, other host's verdict, log)."""
    env = {name: settings.get(name) for name in SETTINGS}
    node = harness.start_node(domain, [], log_path, env=env)
    try:
        local = peer(domain, "lo")
        remote = peer(domain, "vd1", other.holder.pid)
        verdicts = (local.communicate(timeout=MATCH_TIMEOUT + 30)[0].strip(),
                    remote.communicate(timeout=MATCH_TIMEOUT + 30)[0].strip())
    finally:
        harness.stop_node(node)
    return (*verdicts, log_path.read_text())


def run(domain, work, check):
    """Registers the discovery checks with `check(name, fn)`."""
    work.mkdir(parents=True, exist_ok=True)
    with OtherHost() as other:
        def control():
            local, remote, log = scenario(domain, other, work / "default.log", {})
            assert (local, remote) == ("matched", "matched"), (local, remote, log[-2000:])

        check("discovery, default range: a peer in another namespace finds the node", control)

        for name, settings in (
            ("ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST",
             {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}),
            ("ROS_LOCALHOST_ONLY=1", {"ROS_LOCALHOST_ONLY": "1"}),
        ):
            def localhost(name=name, settings=settings):
                log_path = work / f"{name.split('=')[0].lower()}.log"
                local, remote, log = scenario(domain, other, log_path, settings)
                assert local == "matched", f"loopback peer {local}; log:\n{log[-2000:]}"
                assert remote == "unmatched", f"other namespace's peer {remote}"
                assert "loopback interface only" in log, log[-2000:]

            check(f"discovery, {name}: the loopback peer only", localhost)

    def off_refused():
        log_path = work / "off.log"
        node = harness.start_node(domain, [], log_path,
                                  env={"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"})
        try:
            code = node.wait(timeout=20)
        finally:
            harness.stop_node(node)
        log = log_path.read_text()
        assert code != 0, f"exit status {code}"
        assert "ROS_AUTOMATIC_DISCOVERY_RANGE=OFF is not supported" in log, log

    check("discovery, ROS_AUTOMATIC_DISCOVERY_RANGE=OFF: refused with a reason", off_refused)

    def static_peers_noted():
        log_path = work / "static_peers.log"
        node = harness.start_node(domain, [], log_path,
                                  env={"ROS_STATIC_PEERS": "192.0.2.7;robot.local"})
        try:
            deadline = time.monotonic() + 20
            while "ROS_STATIC_PEERS" not in log_path.read_text():
                assert node.poll() is None, log_path.read_text()
                assert time.monotonic() < deadline, log_path.read_text()
                time.sleep(0.1)
        finally:
            harness.stop_node(node)
        assert "`192.0.2.7;robot.local` ignored" in log_path.read_text()

    check("discovery, ROS_STATIC_PEERS: the node says it ignores them", static_peers_noted)
