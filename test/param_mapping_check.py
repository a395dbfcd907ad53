"""`ros2 param` over rmw_cyclonedds: a node started with RMW_IMPLEMENTATION=rmw_cyclonedds_cpp
must answer requests in Cyclone's request/reply mapping (test/cyclone_params.py), as the ROS 2
CLI on that middleware sends them. Used by test_interop.py."""

import os
import subprocess
import time

import cyclone_params as cp
import harness
import ros2_types as t

NODE = "vernier_cyclone_params"
PARAMETER_NOT_SET = 0


def check_cyclone_mapping(domain, log_path, period_um):
    """Starts a second node (own name, Cyclone mapping) and drives get/set/list/describe."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), RMW_IMPLEMENTATION="rmw_cyclonedds_cpp")
    with open(log_path, "w") as log:
        node = subprocess.Popen(
            [str(harness.NODE_BIN), "--ros-args", "--params-file", str(harness.PARAMS_FILE),
             "-r", f"__node:={NODE}", "-p", f"period:={period_um}"],
            stdout=log, stderr=subprocess.STDOUT, env=env,
        )
    # Its own participant: these types share DDS names with the headerless ones.
    dp = harness.DomainParticipant(domain)
    try:
        client = cp.CycloneParamClient(dp, node=f"/{NODE}")
        assert client.wait_ready(), "Cyclone-mapped parameter services not discovered"

        got = client.call("get_parameters", names=["period", "no_such_parameter"])
        assert got.values[0].type == t.PARAMETER_DOUBLE, got
        assert got.values[0].double_value == period_um, got
        assert got.values[1].type == PARAMETER_NOT_SET, got

        bad = client.call("set_parameters", parameters=[t.Parameter(
            name="period", value=t.ParameterValue(type=t.PARAMETER_DOUBLE, double_value=-1.0))])
        assert not bad.results[0].successful and "period" in bad.results[0].reason, bad
        print(f"  cyclone mapping: set period -1 rejected: {bad.results[0].reason}")

        good = client.call("set_parameters", parameters=[t.Parameter(
            name="period",
            value=t.ParameterValue(type=t.PARAMETER_DOUBLE, double_value=2 * period_um))])
        assert good.results[0].successful, good
        got = client.call("get_parameters", names=["period"])
        assert got.values[0].double_value == 2 * period_um, got

        listed = client.call("list_parameters", prefixes=[], depth=0)
        assert "period" in listed.result.names and "relative_pairs" in listed.result.names, listed

        described = client.call("describe_parameters", names=["period"])
        d = described.descriptors[0]
        assert d.name == "period" and d.type == t.PARAMETER_DOUBLE, d
        assert "period" in d.description and not d.read_only, d
        print(f"  cyclone mapping: describe period: {d.description!r}")
        assert node.poll() is None, "node exited"
    finally:
        harness.stop_node(node)
        del dp
    log_text = open(log_path).read()
    assert "cyclone" in log_text, "the node did not log the Cyclone mapping"
