"""Checks of the ROS 2 test environment itself: rclpy on the test's domain, the generated
pwm_actuator_msgs bindings against the .msg files in msg/, and real message exchange between
DDS participants, parameter services and a launched process.

These run without the node binary. They fail on a broken or stale build of the messages, a
missing or mismatched wheel, or fixtures that do not isolate or clean up. They must not test
the node's behaviour (that is the other modules' job).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
import re
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
from ament_index_python.packages import get_package_share_directory
from conftest import MSG_DIR, DomainAllocator, RosClient
from pwm_actuator_msgs.msg import OutputEdge
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterType
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.utilities import get_rmw_implementation_identifier
from std_msgs.msg import Bool

# Times nothing (pytest.ini, `untimed`): bindings, serialisation, exchange between
# participants and the parameter helpers, each checked by what arrives.
pytestmark = pytest.mark.untimed

MSG_FILES = sorted(MSG_DIR.glob("*.msg"))
MSG_PACKAGE = "pwm_actuator_msgs"

# .msg primitive type -> the name rosidl_generator_py uses in get_fields_and_field_types().
PRIMITIVES = {
    "bool": "boolean",
    "byte": "octet",
    "char": "uint8",
    "float32": "float",
    "float64": "double",
    "int8": "int8",
    "uint8": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "string": "string",
    "wstring": "wstring",
}


def idl_type(msg_type: str) -> str:
    """The generated binding's type string for a .msg field type (ROS 2 .msg grammar)."""
    array = re.fullmatch(r"(.+)\[(<=)?(\d*)\]", msg_type)
    if array:
        element, bounded, size = array.groups()
        inner = idl_type(element)
        if not size:
            return f"sequence<{inner}>"
        if bounded:
            return f"sequence<{inner}, {size}>"
        return f"{inner}[{size}]"
    bounded_string = re.fullmatch(r"(w?string)<=(\d+)", msg_type)
    if bounded_string:
        return f"{bounded_string.group(1)}<{bounded_string.group(2)}>"
    if msg_type in PRIMITIVES:
        return PRIMITIVES[msg_type]
    if "/" in msg_type:
        return msg_type
    return f"{MSG_PACKAGE}/{msg_type}"


def parse_msg_fields(path: Path) -> list[tuple[str, str]]:
    """(name, .msg type) of each field of a .msg file, in order; constants are not fields."""
    fields = []
    for raw in path.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split(None, 2)
        assert len(parts) >= 2, f"{path.name}: cannot parse line {raw!r}"
        msg_type, rest = parts[0], line[len(parts[0]) :].strip()
        if re.match(r"^[A-Z][A-Z0-9_]*\s*=", rest):
            continue  # a constant
        fields.append((rest.split()[0], msg_type))
    return fields


def message_class(type_name: str) -> Any:
    """The Python class of "pkg/Type"."""
    package, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), name)


INT_SAMPLES = {
    "octet": b"\x07",
    "int8": -7,
    "uint8": 200,
    "int16": -30000,
    "uint16": 4095,
    "int32": -2_000_000_000,
    "uint32": 4_000_000_000,
    "int64": -(2**62),
    "uint64": 2**63 + 5,
}


def sample(type_string: str, salt: int = 0) -> Any:
    """A value of the given binding type string, far from the default, for round trips."""
    if type_string.startswith("sequence<"):
        inner = type_string[len("sequence<") : -1].split(",")[0].strip()
        return [sample(inner, salt), sample(inner, salt + 1)]
    fixed = re.fullmatch(r"(.+)\[(\d+)\]", type_string)
    if fixed:
        return [sample(fixed.group(1), salt + i) for i in range(int(fixed.group(2)))]
    if type_string == "boolean":
        return True
    if type_string in ("float", "double"):
        return 1.5 + salt
    if type_string.startswith("string") or type_string.startswith("wstring"):
        return f"value-{salt}"
    if type_string in INT_SAMPLES:
        value = INT_SAMPLES[type_string]
        return value if isinstance(value, bytes) or salt == 0 else abs(value) // (salt + 1)
    if "/" in type_string:
        return filled(message_class(type_string), salt)
    raise AssertionError(f"no sample value for type {type_string!r}: extend sample()")


def filled(cls: Any, salt: int = 0) -> Any:
    """An instance of message class `cls` with every field set to a non-default sample."""
    msg = cls()
    for i, (name, type_string) in enumerate(cls.get_fields_and_field_types().items()):
        setattr(msg, name, sample(type_string, salt + i))
    return msg


# -- rclpy and domains --------------------------------------------------------------------------


def test_rclpy_initialises_on_the_test_domain(ros, ros_domain_id):
    assert 1 <= ros_domain_id <= 101
    assert ros.context.ok()
    assert ros.context.get_domain_id() == ros_domain_id
    assert get_rmw_implementation_identifier() == "rmw_fastrtps_cpp"
    # The node is visible in its own graph, which needs the RMW to be working.
    ros.wait_for_node(ros.node.get_name())


@pytest.mark.smoke
def test_rclpy_and_the_messages_are_of_the_distribution_set_up():
    """ROS_DISTRO (scripts/env.sh, from PWM_DISTRO) names the distribution whose rclpy this
    interpreter imports and whose tools built pwm_actuator_msgs, so that a run reported as Kilted
    really ran Kilted's rclpy against the node."""
    import rclpy

    distro = os.environ.get("ROS_DISTRO", "")
    assert distro in ("jazzy", "kilted"), f"ROS_DISTRO={distro!r}: source scripts/env.sh"
    importlib.metadata.version(f"ros-{distro}-rclpy")  # raises if that wheel is not installed
    venv = Path(sys.prefix).resolve()
    assert Path(rclpy.__file__).resolve().is_relative_to(venv), (rclpy.__file__, venv)
    suffix = "" if distro == "jazzy" else f"-{distro}"
    workspace = (Path(__file__).resolve().parents[2] / f".ros-ws{suffix}").resolve()
    msgs = Path(importlib.import_module(MSG_PACKAGE).__file__).resolve()
    assert msgs.is_relative_to(workspace), (msgs, workspace)


def test_domain_ids_are_exclusive_while_held(tmp_path):
    allocator = DomainAllocator(tmp_path / "locks")
    held = [allocator.acquire() for _ in range(5)]
    ids = [domain_id for domain_id, _ in held]
    assert len(set(ids)) == len(ids), ids
    # A second allocator (another test run) skips every id the first one holds.
    other = DomainAllocator(tmp_path / "locks")
    other_held = [other.acquire() for _ in range(3)]
    assert not set(ids) & {domain_id for domain_id, _ in other_held}
    for _, fd in held + other_held:
        DomainAllocator.release(fd)


# -- generated messages -------------------------------------------------------------------------


def test_msg_folder_has_the_interface_files():
    assert {p.stem for p in MSG_FILES} >= {"OutputEdge", "ChannelStatus", "ChannelParams"}


@pytest.mark.parametrize("msg_file", MSG_FILES, ids=lambda p: p.stem)
def test_generated_message_matches_its_msg_file(msg_file):
    cls = message_class(f"{MSG_PACKAGE}/{msg_file.stem}")
    expected = [(name, idl_type(msg_type)) for name, msg_type in parse_msg_fields(msg_file)]
    assert expected, f"{msg_file.name} has no fields"
    assert list(cls.get_fields_and_field_types().items()) == expected


@pytest.mark.parametrize("msg_file", MSG_FILES, ids=lambda p: p.stem)
def test_installed_interface_file_is_current(msg_file):
    # The build installs a copy of each .msg; a difference means the build is stale.
    installed = Path(get_package_share_directory(MSG_PACKAGE)) / "msg" / msg_file.name
    assert installed.read_text() == msg_file.read_text()


def test_package_has_no_messages_without_a_msg_file():
    module = importlib.import_module(f"{MSG_PACKAGE}.msg")
    generated = {
        name
        for name in dir(module)
        if isinstance(getattr(module, name), type)
        and hasattr(getattr(module, name), "get_fields_and_field_types")
    }
    assert generated == {p.stem for p in MSG_FILES}


ROUND_TRIP_TYPES = [f"{MSG_PACKAGE}/{p.stem}" for p in MSG_FILES] + [
    # The standard types the node speaks, from the wheels.
    "std_msgs/Float64",
    "std_msgs/UInt16",
    "std_msgs/Bool",
    "diagnostic_msgs/DiagnosticArray",
]


@pytest.mark.parametrize("type_name", ROUND_TRIP_TYPES)
def test_serialisation_round_trip(type_name):
    cls = message_class(type_name)
    msg = filled(cls)
    assert msg != cls(), "the sample must differ from the default to mean anything"
    data = serialize_message(msg)
    assert deserialize_message(data, cls) == msg


# -- exchange over DDS --------------------------------------------------------------------------


@pytest.mark.parametrize("type_name", ROUND_TRIP_TYPES)
def test_pub_sub_between_two_participants(ros, ros_peer, type_name):
    cls = message_class(type_name)
    topic = "/env_check/" + type_name.replace("/", "_").lower()
    sent = filled(cls, salt=3)
    log = ros.subscribe(cls, topic)
    publisher = ros_peer.node.create_publisher(cls, topic, 10)
    log.wait_for_publishers()
    ros.publish_until(publisher, sent, lambda: log.messages, f"a {type_name} on {topic}")
    assert log.messages[0] == sent


def test_other_domain_sees_nothing(ros, ros_peer, domain_allocator):
    topic = "/env_check/isolation"
    ros_peer.node.create_publisher(Bool, topic, 10)
    # Positive control: the same domain discovers the publisher.
    ros.wait_for_topic(topic, publishers=1)
    other_id, fd = domain_allocator.acquire()
    try:
        other = RosClient(other_id, "pwm_test_other_domain")
        try:
            other.spin_for(2.0)
            assert other.node.count_publishers(topic) == 0
        finally:
            other.close()
    finally:
        DomainAllocator.release(fd)


def test_parameter_helpers_against_an_rclpy_node(ros, ros_peer):
    peer = ros_peer.node
    peer.declare_parameter(
        "pw01.period_ms",
        1000,
        ParameterDescriptor(description="period", type=ParameterType.PARAMETER_INTEGER),
    )
    peer.declare_parameter(
        "pw01.edge_band",
        0.0,
        ParameterDescriptor(
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1.0, step=0.0)]
        ),
    )
    peer.declare_parameter("pw02.profile", "pico_gfx")
    target = peer.get_fully_qualified_name()

    listed = ros.list_parameters(target, prefixes=["pw01"])
    assert set(listed.names) == {"pw01.period_ms", "pw01.edge_band"}

    assert ros.get_parameters(target, ["pw01.period_ms", "pw02.profile"]) == {
        "pw01.period_ms": 1000,
        "pw02.profile": "pico_gfx",
    }
    raw = ros.get_parameter_values(target, ["pw01.period_ms"])
    assert raw[0].type == ParameterType.PARAMETER_INTEGER

    results = ros.set_parameters(target, {"pw01.period_ms": 500, "pw01.edge_band": 2.0})
    assert results["pw01.period_ms"].successful
    assert not results["pw01.edge_band"].successful  # outside its range
    assert results["pw01.edge_band"].reason

    atomic = ros.set_parameters_atomically(
        target, {"pw01.period_ms": 700, "pw01.edge_band": 5.0}
    )
    assert not atomic.successful
    assert ros.get_parameters(target, ["pw01.period_ms", "pw01.edge_band"]) == {
        "pw01.period_ms": 500,
        "pw01.edge_band": 0.0,
    }

    described = ros.describe_parameters(target, ["pw01.edge_band"])
    assert described["pw01.edge_band"].floating_point_range[0].to_value == 1.0


CHILD_PUBLISHER = textwrap.dedent(
    """
    import itertools, signal, sys
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from pwm_actuator_msgs.msg import OutputEdge

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("env_check_child")
    print("domain", node.context.get_domain_id(), flush=True)
    pub = node.create_publisher(OutputEdge, "/env_check/child_edges", 10)
    seq = itertools.count(1)
    node.create_timer(0.2, lambda: pub.publish(OutputEdge(channel=2, level=True, seq=next(seq))))
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.1)
    node.destroy_node()
    rclpy.shutdown()
    print("stopped cleanly", flush=True)
    """
)


def test_launched_process_joins_the_test_domain(ros, ros_domain_id, process_launcher, tmp_path):
    script = tmp_path / "child.py"
    script.write_text(CHILD_PUBLISHER)
    log = ros.subscribe(OutputEdge, "/env_check/child_edges")
    child = process_launcher.launch([sys.executable, script], name="child")
    ros.wait_for_node("env_check_child")
    edge = log.wait_for(lambda m: m.seq >= 1)
    assert (edge.channel, edge.level) == (2, True)
    assert child.terminate() == 0, child.output()
    assert f"domain {ros_domain_id}" in child.stdout()
    assert "stopped cleanly" in child.stdout()
