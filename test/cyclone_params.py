"""`ros2 param` as a ROS 2 tool on `rmw_cyclonedds_cpp` sends it: the rcl_interfaces service
types with Cyclone's 16-byte request header (`uint64 guid; int64 seq`, the
`cdds_request_header_t` of rmw_cyclonedds) in front of every request and reply payload, on the
usual `rq/<node>/<service>Request` and `rr/<node>/<service>Reply` topics. The server must echo
the header; a client keeps the replies carrying its own guid and sequence number.

Use these types on a participant of their own: they share DDS type names with the headerless
types of ros2_types.py."""

import random
from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float64, int64, sequence, uint8, uint64
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

import ros2_types as t
from harness import SERVICE_QOS, call_service, services_matched



@dataclass
class GetParametersRequest(IdlStruct, typename="rcl_interfaces::srv::dds_::GetParameters_Request_"):
    guid: uint64 = 0
    seq: int64 = 0
    names: sequence[str] = field(default_factory=list)


@dataclass
class GetParametersResponse(IdlStruct,
                            typename="rcl_interfaces::srv::dds_::GetParameters_Response_"):
    guid: uint64 = 0
    seq: int64 = 0
    values: sequence[t.ParameterValue] = field(default_factory=list)


@dataclass
class SetParametersRequest(IdlStruct, typename="rcl_interfaces::srv::dds_::SetParameters_Request_"):
    guid: uint64 = 0
    seq: int64 = 0
    parameters: sequence[t.Parameter] = field(default_factory=list)


@dataclass
class SetParametersResponse(IdlStruct,
                            typename="rcl_interfaces::srv::dds_::SetParameters_Response_"):
    guid: uint64 = 0
    seq: int64 = 0
    results: sequence[t.SetParametersResult] = field(default_factory=list)


@dataclass
class ListParametersRequest(IdlStruct,
                            typename="rcl_interfaces::srv::dds_::ListParameters_Request_"):
    guid: uint64 = 0
    seq: int64 = 0
    prefixes: sequence[str] = field(default_factory=list)
    depth: uint64 = 0


@dataclass
class ListParametersResult(IdlStruct, typename="rcl_interfaces::msg::dds_::ListParametersResult_"):
    names: sequence[str] = field(default_factory=list)
    prefixes: sequence[str] = field(default_factory=list)


@dataclass
class ListParametersResponse(IdlStruct,
                             typename="rcl_interfaces::srv::dds_::ListParameters_Response_"):
    guid: uint64 = 0
    seq: int64 = 0
    result: ListParametersResult = field(default_factory=ListParametersResult)


@dataclass
class FloatingPointRange(IdlStruct, typename="rcl_interfaces::msg::dds_::FloatingPointRange_"):
    from_value: float64 = 0.0
    to_value: float64 = 0.0
    step: float64 = 0.0


@dataclass
class IntegerRange(IdlStruct, typename="rcl_interfaces::msg::dds_::IntegerRange_"):
    from_value: int64 = 0
    to_value: int64 = 0
    step: uint64 = 0


@dataclass
class ParameterDescriptor(IdlStruct, typename="rcl_interfaces::msg::dds_::ParameterDescriptor_"):
    name: str = ""
    type: uint8 = 0
    description: str = ""
    additional_constraints: str = ""
    read_only: bool = False
    dynamic_typing: bool = False
    floating_point_range: sequence[FloatingPointRange] = field(default_factory=list)
    integer_range: sequence[IntegerRange] = field(default_factory=list)


@dataclass
class DescribeParametersRequest(IdlStruct,
                                typename="rcl_interfaces::srv::dds_::DescribeParameters_Request_"):
    guid: uint64 = 0
    seq: int64 = 0
    names: sequence[str] = field(default_factory=list)


@dataclass
class DescribeParametersResponse(
        IdlStruct, typename="rcl_interfaces::srv::dds_::DescribeParameters_Response_"):
    guid: uint64 = 0
    seq: int64 = 0
    descriptors: sequence[ParameterDescriptor] = field(default_factory=list)


SERVICES = {
    "get_parameters": (GetParametersRequest, GetParametersResponse),
    "set_parameters": (SetParametersRequest, SetParametersResponse),
    "list_parameters": (ListParametersRequest, ListParametersResponse),
    "describe_parameters": (DescribeParametersRequest, DescribeParametersResponse),
}


class CycloneParamClient:
    """A `ros2 param` client speaking rmw_cyclonedds's request/reply mapping."""

    def __init__(self, dp, node="/vernier_detector"):
        self.guid = random.getrandbits(63) | 1
        self.seq = 0
        self.pairs = {}
        for service, (req, resp) in SERVICES.items():
            w = DataWriter(dp, Topic(dp, f"rq{node}/{service}Request", req), qos=SERVICE_QOS)
            r = DataReader(dp, Topic(dp, f"rr{node}/{service}Reply", resp), qos=SERVICE_QOS)
            self.pairs[service] = (w, r)

    def wait_ready(self, timeout=20.0):
        return services_matched(self.pairs.values(), timeout)

    def call(self, service, timeout=30.0, **fields):
        """Sends one request (re-sent with the same sequence number until answered) and
        returns the reply whose header carries our guid and that sequence number."""
        writer, reader = self.pairs[service]
        self.seq += 1
        request = SERVICES[service][0](guid=self.guid, seq=self.seq, **fields)
        seq = self.seq
        return call_service(writer, reader, request, timeout,
                            accept=lambda reply: reply.guid == self.guid and reply.seq == seq)
