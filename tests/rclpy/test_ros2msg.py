"""The CDR codec of tests/rclpy/ros2msg.py (mcap_ros2 on definitions put together from the
installed `.msg`, `.srv` and `.action` files) against rclpy's own serialization: for every type a
client of the node exchanges with it — its topics, the parameter and lifecycle services, the
autotune action's parts, the log — a message with a value other than the default in every
field (strings with non-ASCII text, sequences of two, nested messages) is read by rclpy from the
codec's payload, and by the codec from rclpy's, as the same message."""

from __future__ import annotations

import importlib
import re

import pytest
from rclpy.serialization import deserialize_message, serialize_message

import ros2msg

# Times nothing (pytest.ini, `untimed`).
pytestmark = pytest.mark.untimed

#: Every type the node publishes, takes or answers with, by rosidl's name.
TYPES = [
    "std_msgs/msg/Bool",
    "std_msgs/msg/Float64",
    "sensor_msgs/msg/Temperature",
    "pwm_actuator_msgs/msg/OutputEdge",
    "pwm_actuator_msgs/msg/ChannelStatus",
    "pwm_actuator_msgs/msg/ChannelParams",
    "pwm_actuator_msgs/msg/ValveState",
    "diagnostic_msgs/msg/DiagnosticArray",
    "rcl_interfaces/msg/Log",
    "rcl_interfaces/msg/ParameterEvent",
    "lifecycle_msgs/msg/TransitionEvent",
    "action_msgs/msg/GoalStatusArray",
    "rcl_interfaces/srv/GetParameters_Request",
    "rcl_interfaces/srv/GetParameters_Response",
    "rcl_interfaces/srv/SetParameters_Request",
    "rcl_interfaces/srv/SetParameters_Response",
    "rcl_interfaces/srv/SetParametersAtomically_Response",
    "rcl_interfaces/srv/DescribeParameters_Response",
    "rcl_interfaces/srv/GetParameterTypes_Response",
    "rcl_interfaces/srv/ListParameters_Request",
    "rcl_interfaces/srv/ListParameters_Response",
    "lifecycle_msgs/srv/ChangeState_Request",
    "lifecycle_msgs/srv/ChangeState_Response",
    "lifecycle_msgs/srv/GetState_Response",
    "lifecycle_msgs/srv/GetAvailableStates_Response",
    "lifecycle_msgs/srv/GetAvailableTransitions_Response",
    "std_srvs/srv/Trigger_Response",
    "action_msgs/srv/CancelGoal_Request",
    "action_msgs/srv/CancelGoal_Response",
    "pwm_actuator_msgs/action/Autotune_SendGoal_Request",
    "pwm_actuator_msgs/action/Autotune_SendGoal_Response",
    "pwm_actuator_msgs/action/Autotune_GetResult_Request",
    "pwm_actuator_msgs/action/Autotune_GetResult_Response",
    "pwm_actuator_msgs/action/Autotune_FeedbackMessage",
]

#: A value other than the default for each primitive, in rclpy's type names.
VALUES = {
    "boolean": True,
    "char": 65,
    "float": 1.5,
    "double": -2.25,
    "int8": -7,
    "uint8": 200,
    "int16": -3000,
    "uint16": 60000,
    "int32": -100000,
    "uint32": 4_000_000_000,
    "int64": -5_000_000_000_000,
    "uint64": 10_000_000_000_000_000_000,
    "string": "pw01 °C/é",
    "wstring": "wide °C",
}


def rclpy_class(type_name: str):
    pkg, kind, name = type_name.split("/")
    module = importlib.import_module(f"{pkg}.{kind}")
    if kind == "msg":
        return getattr(module, name)
    if kind == "srv":
        base, half = name.rsplit("_", 1)
        return getattr(getattr(module, base), half)
    for section in ("Goal", "Result", "Feedback"):
        if name.endswith("_" + section):
            return getattr(getattr(module, name[: -len(section) - 1]), section)
    for part, path in (
        ("_SendGoal_Request", ("SendGoalService", "Request")),
        ("_SendGoal_Response", ("SendGoalService", "Response")),
        ("_GetResult_Request", ("GetResultService", "Request")),
        ("_GetResult_Response", ("GetResultService", "Response")),
        ("_FeedbackMessage", ("FeedbackMessage",)),
    ):
        if name.endswith(part):
            cls = getattr(module, name[: -len(part)]).Impl
            for attr in path:
                cls = getattr(cls, attr)
            return cls
    raise ValueError(type_name)


def value(ftype: str, seed: int):
    """A value of rclpy field type `ftype` other than its default, in rclpy's form; the same in
    the codec's form (nested messages as dicts); `seed` varies numbers between fields."""
    m = re.fullmatch(r"sequence<(.+?)(?:, (\d+))?>", ftype)
    array = re.fullmatch(r"(.+)\[(\d+)\]", ftype)
    if m or array:
        inner = m.group(1) if m else array.group(1)
        n = min(2, int(m.group(2) or 2)) if m else int(array.group(2))
        pairs = [value(inner, seed + i) for i in range(n)]
        return [p[0] for p in pairs], [p[1] for p in pairs]
    base = re.sub(r"<=\d+$", "", ftype)
    if base == "octet":
        return bytes([7 + seed % 5]), 7 + seed % 5
    if base in VALUES:
        v = VALUES[base]
        if base.startswith("uint"):
            v += seed % 5
        if base == "string" and "<=" in ftype:
            v = v[: int(ftype.split("<=")[1])]
        return v, v
    return message(ros2msg.field_type_name(base, ""), seed)


def message(type_name: str, seed: int = 0):
    """An rclpy message of `type_name` with every field set; the same as the codec's dict."""
    cls = rclpy_class(type_name)
    msg, fields = cls(), {}
    for i, (name, ftype) in enumerate(cls.get_fields_and_field_types().items()):
        ours, plain = value(ftype, seed + i)
        setattr(msg, name, ours)
        fields[name] = plain
    return msg, fields


def plain(obj):
    """A decoded message (or value) in the codec's dict form."""
    if hasattr(obj, "__slots__"):
        return {k: plain(getattr(obj, k)) for k in obj.__slots__}
    if isinstance(obj, list):
        return [plain(x) for x in obj]
    if isinstance(obj, bytes):  # uint8 and byte arrays and sequences
        return list(obj)
    return obj


@pytest.mark.parametrize("type_name", TYPES)
def test_the_codec_agrees_with_rclpy(type_name):
    msg, fields = message(type_name)
    theirs = serialize_message(msg)
    ours = ros2msg.encode(type_name, fields)
    # The same layout: rclpy reads ours as the message, ours reads rclpy's as the fields, and
    # the lengths agree but for rclpy's padding to a multiple of 4 bytes. (The padding inside
    # and at the end of rclpy's payload is whatever was in memory: bytes are not compared.)
    assert deserialize_message(ours, type(msg)) == msg, f"{type_name}: {ours.hex()}"
    assert plain(ros2msg.decode(type_name, theirs)) == fields, f"{type_name}: {theirs.hex()}"
    assert 0 <= len(theirs) - len(ours) < 4, (len(theirs), len(ours))


def test_the_codec_refuses_a_payload_that_is_not_little_endian_cdr():
    with pytest.raises(ValueError, match="not little-endian plain CDR"):
        ros2msg.decode("std_msgs/msg/Bool", b"\x00\x00\x00\x00\x01")
