"""REP-2016 type hashes, from outside: every endpoint of the node announces, in its DDS
USER_DATA, the RIHS01 hash that rosidl generated for its type, as rclpy's own endpoints do.

rclpy reads the hash of a discovered endpoint from its USER_DATA (`typehash=RIHS01_...;`) and
shows it as `TopicEndpointInfo.topic_type_hash` (`ros2 topic info -v` prints it); without one
it shows INVALID. The reference is rosidl's own output: the `type_hashes` of the `.json` files
the message packages install in `share/<package>/{msg,srv}/` (the Jazzy wheels in `.venv`, and
`pwm_actuator_msgs` built by scripts/setup.sh). A service's request topic (`rq/<name>Request`)
carries the hash of `<pkg>/srv/<Name>_Request` and its reply topic (`rr/<name>Reply`) that of
`<pkg>/srv/<Name>_Response`, as rmw_fastrtps announces them; an rclpy service in the same test
shows the same. An action's endpoints are those of its two services
(`<pkg>/action/<Name>_SendGoal_Request`/`_Response`, `..._GetResult_...`, hashes in
`share/<pkg>/action/<Name>.json`), of `action_msgs/srv/CancelGoal`, its feedback topic
(`<pkg>/action/<Name>_FeedbackMessage`) and its status topic (`action_msgs/msg/GoalStatusArray`);
an rclpy action server of the same type in the same test shows the same hashes.
"""

from __future__ import annotations

import json
import os
from functools import lru_cache
from pathlib import Path

import pytest
from rclpy.action import ActionServer
from rclpy.node import Node
from std_srvs.srv import Trigger

from pwm_actuator_msgs.action import Autotune

from conftest import REPO_ROOT
from helpers_rules import node_args

# Times nothing (pytest.ini, `untimed`): the type hashes each endpoint announces.
pytestmark = pytest.mark.untimed

NAME = "pwm_actuator"
#: Every kind of endpoint the node has: the channels' topics, a split-range pair, a heater's
#: feedback, setpoint and autotune action, a valve, the e-stop, the lifecycle, the parameter
#: services, the rosout and parameter events ros2-client makes for it.
ARGS = ["--managed"] + node_args(
    channels=5,
    split="sp:pw01:pw02",
    valve="mix:pw04:pw05",
    pw03__feedback_topic="/heater/temperature",
    pw03__control="pid",
    pw03__temp_max_c=150.0,
)
#: The DDS name space of the heater channel's autotune action's services and topics.
ACTION = "pwm_actuator/pw03/autotune/_action"
#: Endpoints that must be among those checked (DDS names: topics `rt/...`, service requests
#: `rq/...Request`, replies `rr/...Reply`), by kind.
REQUIRED_PUBLISHERS = {
    f"rt/{ACTION}/feedback",
    f"rt/{ACTION}/status",
    f"rr/{ACTION}/send_goalReply",
    f"rr/{ACTION}/get_resultReply",
    f"rr/{ACTION}/cancel_goalReply",
    "rt/pwm_actuator/pw01/edges",
    "rt/pwm_actuator/pw01/status",
    "rt/pwm_actuator/pw01/e1",
    "rt/diagnostics",
    "rt/pwm_actuator/transition_event",
    "rt/rosout",
    "rt/parameter_events",
    "rr/pwm_actuator/get_parametersReply",
    "rr/pwm_actuator/reset_estopReply",
    "rr/pwm_actuator/change_stateReply",
    "rr/pwm_actuator/pw03/reset_faultReply",
    "rt/pwm_actuator/valve/mix/state",
    "rr/pwm_actuator/valve/mix/resetReply",
}
REQUIRED_SUBSCRIPTIONS = {
    f"rq/{ACTION}/send_goalRequest",
    f"rq/{ACTION}/get_resultRequest",
    f"rq/{ACTION}/cancel_goalRequest",
    "rt/pwm_actuator/pw01/duty",
    "rt/pwm_actuator/pw01/sv",
    "rt/pwm_actuator/pw01/enable",
    "rt/pwm_actuator/pw01/params",
    "rt/pwm_actuator/estop",
    "rt/pwm_actuator/split/sp/command",
    "rt/pwm_actuator/pw03/setpoint",
    "rt/heater/temperature",
    "rq/pwm_actuator/get_parametersRequest",
    "rq/pwm_actuator/set_parametersRequest",
    "rq/pwm_actuator/describe_parametersRequest",
    "rq/pwm_actuator/reset_estopRequest",
    "rq/pwm_actuator/get_stateRequest",
    "rq/pwm_actuator/pw03/reset_faultRequest",
    "rt/pwm_actuator/valve/mix/position",
    "rq/pwm_actuator/valve/mix/resetRequest",
}


def share_dirs() -> list[Path]:
    """Where rosidl's `.json` files are: the venv's ROS share directory and the message
    package's install."""
    venv = Path(os.environ.get("VIRTUAL_ENV", REPO_ROOT / ".venv"))
    return [venv / "share", REPO_ROOT / ".ros-ws" / "install" / "pwm_actuator_msgs" / "share"]


#: The suffixes of the types rosidl derives from a service or an action, which it writes in the
#: `.json` file of the service or action (longest first).
DERIVED_SUFFIXES = {
    "srv": ("_Request", "_Response", "_Event"),
    "action": (
        "_SendGoal_Request", "_SendGoal_Response", "_SendGoal_Event", "_SendGoal",
        "_GetResult_Request", "_GetResult_Response", "_GetResult_Event", "_GetResult",
        "_FeedbackMessage", "_Goal", "_Result", "_Feedback",
    ),
}


def json_file_name(kind: str, name: str) -> str:
    """The name of the `.json` file (without suffix) that holds the hash of `name`."""
    for suffix in DERIVED_SUFFIXES.get(kind, ()):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


@lru_cache(maxsize=None)
def rosidl_hash(type_name: str) -> str:
    """The hash rosidl generated for `type_name` (`std_msgs/msg/Float64`,
    `std_srvs/srv/Trigger_Request`, `pkg/action/Autotune_SendGoal_Request`), from the
    `type_hashes` of its `.json` file."""
    pkg, kind, name = type_name.split("/")
    name = json_file_name(kind, name)
    for share in share_dirs():
        path = share / pkg / kind / f"{name}.json"
        if path.exists():
            hashes = json.loads(path.read_text())["type_hashes"]
            return next(h["hash_string"] for h in hashes if h["type_name"] == type_name)
    raise AssertionError(f"no rosidl .json for {type_name} under {share_dirs()}")


def ros_type(dds_type: str) -> str:
    """`std_msgs::msg::dds_::Float64_` -> `std_msgs/msg/Float64`; a ROS name stays as it is."""
    if "::dds_::" not in dds_type:
        return dds_type
    head, name = dds_type.split("::dds_::")
    return head.replace("::", "/") + "/" + name.rstrip("_")


def endpoints_of(ros, kind: str) -> dict[str, list]:
    """The node's endpoints of `kind` ("publishers" or "subscriptions"), by DDS topic name, as
    rclpy's graph shows them."""
    node: Node = ros.node
    if kind == "publishers":
        names = node.get_publisher_names_and_types_by_node(NAME, "/", no_demangle=True)
        info = node.get_publishers_info_by_topic
    else:
        names = node.get_subscriber_names_and_types_by_node(NAME, "/", no_demangle=True)
        info = node.get_subscriptions_info_by_topic
    return {
        topic: [e for e in info(topic, no_mangle=True) if e.node_name == NAME]
        for topic, _types in names
    }


def test_every_endpoint_announces_rosidls_type_hash(node_process, ros):
    proc = node_process(ARGS)
    ros.wait_for_node(NAME)

    # The references: an rclpy service and an rclpy action server of types the node serves too.
    ref = ros.node.create_service(Trigger, "/reference/trigger", lambda req, resp: resp)
    ref_action = ActionServer(ros.node, Autotune, "/reference/autotune",
                              lambda goal: Autotune.Result())
    try:
        def complete():
            pubs = endpoints_of(ros, "publishers")
            subs = endpoints_of(ros, "subscriptions")
            return (
                REQUIRED_PUBLISHERS <= {t for t, es in pubs.items() if es}
                and REQUIRED_SUBSCRIPTIONS <= {t for t, es in subs.items() if es}
                and (pubs, subs)
            )

        pubs, subs = ros.spin_until(complete, "every endpoint of the node in rclpy's graph")
        # Discovery data of one endpoint comes in one SEDP sample: a listed endpoint already
        # has its USER_DATA, so one look is enough.
        checked: dict[str, int] = {}
        wrong = []
        for kind, endpoints in (("publishers", pubs), ("subscriptions", subs)):
            for topic, es in sorted(endpoints.items()):
                for e in es:
                    t = ros_type(e.topic_type)
                    expected = rosidl_hash(t)
                    got = str(e.topic_type_hash)
                    if got != expected:
                        wrong.append(f"{kind} {topic} ({t}): {got}, rosidl: {expected}")
                    checked[kind] = checked.get(kind, 0) + 1
        types = {ros_type(e.topic_type) for d in (pubs, subs) for es in d.values() for e in es}
        print(f"endpoints checked: {checked}, types: {len(types)}")
        assert not wrong, "\n".join(wrong)
        # Every required endpoint was among those compared (an endpoint without a hash shows
        # INVALID, which is no rosidl hash).
        for kind, required, endpoints in (("publishers", REQUIRED_PUBLISHERS, pubs),
                                          ("subscriptions", REQUIRED_SUBSCRIPTIONS, subs)):
            for topic in required:
                assert endpoints[topic], f"{kind} {topic}"
                for e in endpoints[topic]:
                    assert str(e.topic_type_hash).startswith("RIHS01_"), (topic, e)
        assert checked["publishers"] >= len(REQUIRED_PUBLISHERS), checked
        assert checked["subscriptions"] >= len(REQUIRED_SUBSCRIPTIONS), checked

        # The same hashes as rclpy's own service of the same type: the request type's on the
        # request topic, the response type's on the reply topic.
        def ref_endpoint(topic: str, publishers: bool):
            info = (ros.node.get_publishers_info_by_topic if publishers
                    else ros.node.get_subscriptions_info_by_topic)
            es = [e for e in info(topic, no_mangle=True) if e.node_name == ros.node.get_name()]
            return es[0] if es else None

        ref_rq = ros.spin_until(lambda: ref_endpoint("rq/reference/triggerRequest", False),
                                "the reference service's request reader")
        ref_rr = ros.spin_until(lambda: ref_endpoint("rr/reference/triggerReply", True),
                                "the reference service's reply writer")
        ours_rq = subs["rq/pwm_actuator/reset_estopRequest"][0]
        ours_rr = pubs["rr/pwm_actuator/reset_estopReply"][0]
        assert str(ours_rq.topic_type_hash) == str(ref_rq.topic_type_hash) == rosidl_hash(
            "std_srvs/srv/Trigger_Request")
        assert str(ours_rr.topic_type_hash) == str(ref_rr.topic_type_hash) == rosidl_hash(
            "std_srvs/srv/Trigger_Response")

        # The action's: each topic of the node's action shows the hash of rclpy's same topic.
        action_topics = (
            ("send_goalRequest", "rq", False,
             "pwm_actuator_msgs/action/Autotune_SendGoal_Request"),
            ("send_goalReply", "rr", True,
             "pwm_actuator_msgs/action/Autotune_SendGoal_Response"),
            ("get_resultRequest", "rq", False,
             "pwm_actuator_msgs/action/Autotune_GetResult_Request"),
            ("get_resultReply", "rr", True,
             "pwm_actuator_msgs/action/Autotune_GetResult_Response"),
            ("cancel_goalRequest", "rq", False, "action_msgs/srv/CancelGoal_Request"),
            ("cancel_goalReply", "rr", True, "action_msgs/srv/CancelGoal_Response"),
            ("feedback", "rt", True, "pwm_actuator_msgs/action/Autotune_FeedbackMessage"),
            ("status", "rt", True, "action_msgs/msg/GoalStatusArray"),
        )
        for suffix, prefix, publisher, type_name in action_topics:
            theirs = ros.spin_until(
                lambda p=prefix, s=suffix, pub=publisher: ref_endpoint(
                    f"{p}/reference/autotune/_action/{s}", pub),
                f"the reference action's {suffix}")
            mine = (pubs if publisher else subs)[f"{prefix}/{ACTION}/{suffix}"][0]
            assert ros_type(mine.topic_type) == ros_type(theirs.topic_type) == type_name
            assert str(mine.topic_type_hash) == str(theirs.topic_type_hash) == rosidl_hash(
                type_name), suffix
    finally:
        ref_action.destroy()
        ros.node.destroy_service(ref)
    assert proc.is_running(), proc.output()


def test_endpoints_outside_the_node_announce_their_hash_too(node_process, ros):
    """The endpoints ros2-client makes for the participant rather than the node: the
    `ros_discovery_info` writer and reader (rmw_dds_common/msg/ParticipantEntitiesInfo), and
    the `/clock` reader (ros2-client subscribes to it as builtin_interfaces/msg/Time)."""
    node_process()
    ros.wait_for_node(NAME)
    expected_clock = rosidl_hash("builtin_interfaces/msg/Time")
    expected_info = rosidl_hash("rmw_dds_common/msg/ParticipantEntitiesInfo")

    def clock_readers():
        return ros.node.get_subscriptions_info_by_topic("/clock")

    clock = ros.spin_until(clock_readers, "the node's /clock reader")
    assert [str(e.topic_type_hash) for e in clock] == [expected_clock] * len(clock)
    # rclpy's own participant has one writer and one reader of ros_discovery_info; the node's
    # participant the other ones.
    info_w = ros.spin_until(
        lambda: (lambda es: len(es) >= 2 and es)(
            ros.node.get_publishers_info_by_topic("ros_discovery_info", no_mangle=True)),
        "two ros_discovery_info writers")
    info_r = ros.spin_until(
        lambda: (lambda es: len(es) >= 2 and es)(
            ros.node.get_subscriptions_info_by_topic("ros_discovery_info", no_mangle=True)),
        "two ros_discovery_info readers")
    got = [str(e.topic_type_hash) for e in info_w + info_r]
    print(f"/clock readers: {len(clock)}, ros_discovery_info endpoints: {len(got)}")
    assert got == [expected_info] * len(got)

