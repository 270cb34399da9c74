"""CDR payloads of ROS 2 messages without rclpy, rustdds or ros2-client: the `ros2msg`
definitions are put together from the `.msg`, `.srv` and `.action` files the message packages
install, and `mcap_ros2` (the MCAP project's own CDR codec) encodes and decodes by them: the codec
of a client that speaks to the node other than through a ROS library.

Types are named as rosidl names them: `pkg/msg/Name`, a service's halves `pkg/srv/Name_Request`
and `pkg/srv/Name_Response`, an action's parts `pkg/action/Name_SendGoal_Request`,
`..._SendGoal_Response`, `..._GetResult_Request`, `..._GetResult_Response` and
`..._FeedbackMessage` (as rosidl generates them: the goal id and the goal, accepted and its
stamp, the goal id, the status and the result, the goal id and the feedback).
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

#: The little-endian plain CDR encapsulation every ROS 2 payload starts with.
CDR_LE = b"\x00\x01\x00\x00"

#: Field types that are not messages.
PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
}

#: rosidl's action parts: (suffix, fields before the action file's section, section index).
ACTION_PARTS = {
    "SendGoal_Request": ("unique_identifier_msgs/UUID goal_id\n", "Goal"),
    "SendGoal_Response": ("bool accepted\nbuiltin_interfaces/Time stamp\n", None),
    "GetResult_Request": ("unique_identifier_msgs/UUID goal_id\n", None),
    "GetResult_Response": ("int8 status\n", "Result"),
    "FeedbackMessage": ("unique_identifier_msgs/UUID goal_id\n", "Feedback"),
}
SECTIONS = {"Goal": 0, "Result": 1, "Feedback": 2, "Request": 0, "Response": 1}


def _file(pkg: str, kind: str, name: str) -> str:
    path = Path(get_package_share_directory(pkg)) / kind / f"{name}.{kind}"
    return path.read_text()


def _sections(text: str) -> list[str]:
    return re.split(r"^---\s*$", text, flags=re.MULTILINE)


@lru_cache(maxsize=None)
def own_text(type_name: str) -> str:
    """The fields of `type_name` alone, as a `.msg` file would give them."""
    pkg, kind, name = type_name.split("/")
    if kind == "msg":
        return _file(pkg, "msg", name)
    if kind == "srv":
        base, half = name.rsplit("_", 1)
        return _sections(_file(pkg, "srv", base))[SECTIONS[half]]
    if kind == "action":
        for suffix, (head, section) in ACTION_PARTS.items():
            if name.endswith("_" + suffix):
                base = name[: -len(suffix) - 1]
                if section is None:
                    return head
                return head + f"{pkg}/{base}_{section} {section.lower()}\n"
        for section in ("Goal", "Result", "Feedback"):
            if name.endswith("_" + section):
                base = name[: -len(section) - 1]
                return _sections(_file(pkg, "action", base))[SECTIONS[section]]
    raise ValueError(f"not a message type: {type_name}")


def field_type_name(ftype: str, pkg: str) -> str:
    """rosidl's name of the message type a field of package `pkg` names as `Name` or
    `other_pkg/Name` (an action's own parts, `Name_Goal` and the like, live in `pkg/action`)."""
    if "/" not in ftype:
        ftype = f"{pkg}/{ftype}"
    dep_pkg, dep = ftype.split("/")
    kind = "action" if dep.endswith(("_Goal", "_Result", "_Feedback")) else "msg"
    return f"{dep_pkg}/{kind}/{dep}"


def _field_types(text: str, pkg: str) -> list[str]:
    """The message types `text`'s fields name, as rosidl names them."""
    out = []
    for line in text.splitlines():
        words = line.split("#", 1)[0].split()
        if not words or (len(words) > 1 and "=" in words[1]):
            continue  # nothing, or a constant
        base = re.sub(r"<=\d+$", "", re.sub(r"\[.*\]$", "", words[0]))
        if base not in PRIMITIVES:
            out.append(field_type_name(base, pkg))
    return out


def _plain_name(name: str) -> str:
    """`name` as mcap_ros2's parser takes a message name: rosidl's generated names of service
    halves and action parts (`Autotune_SendGoal_Request`) without their underscores. The
    names stay inside the definition: CDR carries none."""
    return name.replace("_", "")


def _renamed(text: str) -> str:
    """`text` with every `pkg/Name` field type named as [`_plain_name`] names it."""
    out = []
    for line in text.splitlines():
        m = re.match(r"^(\s*)([A-Za-z0-9_]+)/([A-Za-z0-9_]+)(.*)$", line)
        if m and not line.lstrip().startswith("#"):
            line = f"{m.group(1)}{m.group(2)}/{_plain_name(m.group(3))}{m.group(4)}"
        out.append(line)
    return "\n".join(out) + "\n"


@lru_cache(maxsize=None)
def definition(type_name: str) -> str:
    """The concatenated `ros2msg` definition of `type_name`: its fields, then each message
    type it uses, once, after a line of `=` and `MSG: pkg/Name`."""
    pkg = type_name.split("/")[0]
    parts = [_renamed(own_text(type_name))]
    seen = {type_name}
    todo = _field_types(own_text(type_name), pkg)
    while todo:
        dep = todo.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        dep_pkg, _, dep_name = dep.split("/")
        parts.append(
            "=" * 80 + f"\nMSG: {dep_pkg}/{_plain_name(dep_name)}\n" + _renamed(own_text(dep))
        )
        todo.extend(_field_types(own_text(dep), dep_pkg))
    return "\n".join(parts)


def _schema_name(type_name: str) -> str:
    pkg, _, name = type_name.split("/")
    return f"{pkg}/{_plain_name(name)}"


def decode(type_name: str, payload: bytes):
    """The message of type `type_name` in the CDR `payload` (with its 4-byte header), as an
    object whose attributes are the fields."""
    if payload[:4] != CDR_LE:
        raise ValueError(f"not little-endian plain CDR: header {payload[:4].hex()}")
    name = _schema_name(type_name)
    return generate_dynamic(name, definition(type_name))[name](payload)


def encode(type_name: str, fields) -> bytes:
    """The CDR payload (with its 4-byte header) of a `type_name` message; `fields` is a dict of
    field values (nested messages as dicts too; fields left out take their defaults)."""
    name = _schema_name(type_name)
    return bytes(serialize_dynamic(name, definition(type_name))[name](fields))
