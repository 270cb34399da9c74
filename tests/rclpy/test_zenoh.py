"""The node on Zenoh (`RMW_IMPLEMENTATION=rmw_zenoh_cpp`; the `zenoh` feature, a default one),
checked by a client that is neither rclpy nor ros2-client nor RustDDS: the `eclipse-zenoh`
Python package, speaking rmw_zenoh's wire format from its design document
(rmw_zenoh/docs/design.md: key expressions, liveliness tokens, the 33-byte attachment, GIDs as
XXH3-128 of the token), with CDR from `ros2msg.py` (the MCAP project's codec over the installed
`.msg` files) and type hashes read from rosidl's `.json` files.

A Zenoh router runs in the pytest process, as `rmw_zenohd` would on the host; the node connects
to it (`ZENOH_CONFIG_OVERRIDE`), and so does the client, as a peer of its own.
"""

from __future__ import annotations

import concurrent.futures
import os
import socket
import struct
import threading
import time
from typing import Any, Callable, Optional

import pytest
import xxhash
import zenoh
import zenoh.ext

import ros2msg
from helpers_rules import node_args
from test_type_hashes import rosidl_hash

pytestmark = pytest.mark.untimed

NODE = "/pwm_actuator"
#: What a test waits at most for the graph, a sample or a reply, s.
WAIT_S = 10.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def mangle(name: str) -> str:
    return name.replace("/", "%")


def zenoh_type(ros_type: str) -> str:
    """`std_msgs/msg/Bool` → `std_msgs::msg::dds_::Bool_` (design.md "Topic and Service name
    mapping")."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def data_key(domain: int, name: str, ros_type: str) -> str:
    """The exact key of a topic's samples or a service's queries: no wildcard."""
    return f"{domain}/{name.lstrip('/')}/{zenoh_type(ros_type)}/{rosidl_hash(ros_type)}"


def gid_of(token: str) -> bytes:
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


def attachment(seq: int, gid: bytes) -> bytes:
    return struct.pack("<qq", seq, time.time_ns()) + b"\x10" + gid


def read_attachment(raw: Optional[zenoh.ZBytes]) -> tuple[int, int, bytes]:
    """(sequence, source timestamp ns, GID) of a 33-byte attachment; asserts its layout."""
    assert raw is not None, "no attachment"
    b = raw.to_bytes()
    assert len(b) == 33 and b[16] == 0x10, f"attachment {b.hex()}"
    seq, ts = struct.unpack_from("<qq", b)
    return seq, ts, bytes(b[17:])


def wait_until(what: str, f: Callable[[], Any], timeout: float = WAIT_S) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        got = f()
        if got:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout} s")
        time.sleep(0.05)


class Router:
    """A Zenoh router in this process and the port it listens on."""

    def __init__(self, session: zenoh.Session, port: int) -> None:
        self.session = session
        self.port = port


@pytest.fixture
def router() -> Any:
    port = free_port()
    conf = zenoh.Config.from_json5(
        '{mode: "router", listen: {endpoints: ["tcp/127.0.0.1:%d"]},'
        " scouting: {multicast: {enabled: false}},"
        " timestamping: {enabled: {router: true, peer: true, client: true}}}" % port
    )
    session = zenoh.open(conf)
    yield Router(session, port)
    session.close()


def client(port: int) -> zenoh.Session:
    """A peer as rmw_zenoh makes one: connected to the router, listening on loopback, so that
    the router's gossip lets it and the node connect to each other."""
    return zenoh.open(
        zenoh.Config.from_json5(
            '{mode: "peer", connect: {endpoints: ["tcp/127.0.0.1:%d"]},'
            ' listen: {endpoints: ["tcp/127.0.0.1:0"]}, scouting: {multicast: {enabled: false}}}'
            % port
        )
    )


def start_node(node_process, router, domain: int, *args: str, **params: Any):
    env = {
        "RMW_IMPLEMENTATION": "rmw_zenoh_cpp",
        "ROS_DOMAIN_ID": str(domain),
        # rmw_zenoh's default session otherwise: it listens on loopback for its peers.
        "ZENOH_CONFIG_OVERRIDE": 'connect/endpoints=["tcp/127.0.0.1:%d"]' % router.port,
    }
    node = node_process([*args, *node_args(**params)], env=env)
    node.wait_for_output("running:", timeout=WAIT_S)
    return node


def tokens(session: zenoh.Session, domain: int) -> list[str]:
    return [str(r.ok.key_expr) for r in session.liveliness().get(f"@ros2_lv/{domain}/**") if r.ok]


class Call:
    """A service client as rmw_zenoh's: a GID of its own, sequence numbers from 1."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.gid = os.urandom(16)
        self.seq = 0
        self.last: Any = None

    def __call__(self, domain: int, service: str, srv_type: str, fields: dict) -> Any:
        self.seq += 1
        key = data_key(domain, service, srv_type)
        payload = ros2msg.encode(f"{srv_type}_Request", fields)
        replies = list(
            self.session.get(
                key,
                payload=payload,
                attachment=attachment(self.seq, self.gid),
                target=zenoh.QueryTarget.ALL_COMPLETE,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=WAIT_S,
            )
        )
        assert len(replies) == 1, f"{service}: {len(replies)} replies"
        assert replies[0].ok is not None, f"{service}: error {replies[0].err}"
        sample = replies[0].ok
        seq, ts, gid = read_attachment(sample.attachment)
        assert (seq, gid) == (self.seq, self.gid), f"{service}: reply attachment {seq}, {gid.hex()}"
        assert abs(time.time_ns() - ts) < 5e9
        self.last = ros2msg.decode(f"{srv_type}_Response", sample.payload.to_bytes())
        return self.last


def test_the_graph_has_the_node_and_every_endpoint_with_rosidls_hash(
    node_process, router, ros_domain_id: int
):
    d = ros_domain_id
    start_node(node_process, router, d, "--managed", channels=1)
    c = client(router.port)
    try:
        want = {
            ("MP", "/pwm_actuator/pw01/edges", "pwm_actuator_msgs/msg/OutputEdge"),
            ("MP", "/pwm_actuator/pw01/e1", "std_msgs/msg/Bool"),
            ("MP", "/pwm_actuator/pw01/status", "pwm_actuator_msgs/msg/ChannelStatus"),
            ("MP", "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
            ("MP", "/parameter_events", "rcl_interfaces/msg/ParameterEvent"),
            ("MP", "/pwm_actuator/transition_event", "lifecycle_msgs/msg/TransitionEvent"),
            ("MP", "/rosout", "rcl_interfaces/msg/Log"),
            ("MS", "/pwm_actuator/pw01/duty", "std_msgs/msg/Float64"),
            ("MS", "/pwm_actuator/pw01/enable", "std_msgs/msg/Bool"),
            ("MS", "/pwm_actuator/estop", "std_msgs/msg/Bool"),
            ("SS", "/pwm_actuator/get_parameters", "rcl_interfaces/srv/GetParameters"),
            ("SS", "/pwm_actuator/set_parameters", "rcl_interfaces/srv/SetParameters"),
            ("SS", "/pwm_actuator/list_parameters", "rcl_interfaces/srv/ListParameters"),
            ("SS", "/pwm_actuator/describe_parameters", "rcl_interfaces/srv/DescribeParameters"),
            ("SS", "/pwm_actuator/reset_estop", "std_srvs/srv/Trigger"),
            ("SS", "/pwm_actuator/change_state", "lifecycle_msgs/srv/ChangeState"),
            ("SS", "/pwm_actuator/get_state", "lifecycle_msgs/srv/GetState"),
        }

        def seen() -> Optional[dict]:
            found: dict = {}
            for t in tokens(c, d):
                chunks = t.split("/")
                if chunks[5] == "NN":
                    found["NN"] = chunks
                elif len(chunks) >= 13:
                    found[(chunks[5], chunks[9].replace("%", "/"))] = chunks
            return found if all((k, n) in found for k, n, _ in want) and "NN" in found else None

        found = wait_until("every token", seen)
        nn = found["NN"]
        assert nn[:2] == ["@ros2_lv", str(d)] and nn[6:] == ["%", "%", "pwm_actuator"], nn
        zid = nn[2]
        for kind, name, ros_type in want:
            chunks = found[(kind, name)]
            assert chunks[2] == zid and chunks[6:9] == ["%", "%", "pwm_actuator"], chunks
            assert chunks[10] == zenoh_type(ros_type), chunks
            assert chunks[11] == rosidl_hash(ros_type), (name, chunks[11])
        # The QoS the design document writes: e1 transient local, keep last 1; edges keep
        # last 100; commands the defaults but depth 10.
        assert found[("MP", "/pwm_actuator/pw01/e1")][12] == ":1:,1:,:,:,,"
        assert found[("MP", "/pwm_actuator/pw01/edges")][12] == "::,100:,:,:,,"
        assert found[("MS", "/pwm_actuator/pw01/duty")][12] == "::,10:,:,:,,"
        assert found[("MP", "/rosout")][12] == ":1:,1:,:,:,,"
    finally:
        c.close()


def test_a_duty_put_on_its_exact_key_moves_the_edges_and_every_attachment_is_rmw_zenohs(
    node_process, router, ros_domain_id: int
):
    d = ros_domain_id
    start_node(node_process, router, d, channels=1, pw01__period_ms=200, pw01__enable=True)
    c = client(router.port)
    try:
        edges: list = []
        edge_key = data_key(d, "/pwm_actuator/pw01/edges", "pwm_actuator_msgs/msg/OutputEdge")
        sub = c.declare_subscriber(
            edge_key, lambda s: edges.append((s.payload.to_bytes(), s.attachment, str(s.key_expr)))
        )
        duty_key = data_key(d, "/pwm_actuator/pw01/duty", "std_msgs/msg/Float64")
        gid = os.urandom(16)
        seq = 0

        def put_duty() -> bool:
            nonlocal seq
            seq += 1
            c.put(duty_key, ros2msg.encode("std_msgs/msg/Float64", {"data": 30.0}),
                  attachment=attachment(seq, gid))
            time.sleep(0.3)
            return len(edges) >= 4

        wait_until("edges after a duty", put_duty)
        time.sleep(1.0)
        token = next(
            t for t in tokens(c, d) if "/MP/" in t and "%pwm_actuator%pw01%edges/" in t
        )
        seqs = []
        for payload, att, key in list(edges):
            assert key == edge_key
            s, ts, g = read_attachment(att)
            assert g == gid_of(token)
            assert abs(time.time_ns() - ts) < 5e9
            seqs.append(s)
            e = ros2msg.decode("pwm_actuator_msgs/msg/OutputEdge", payload)
            assert e.channel == 1  # channels count from 1 (pw01)
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), seqs
        levels = [ros2msg.decode("pwm_actuator_msgs/msg/OutputEdge", p).level for p, _, _ in edges]
        assert True in levels and False in levels
        sub.undeclare()
    finally:
        c.close()


def test_parameters_are_got_and_set_through_the_parameter_services(
    node_process, router, ros_domain_id: int
):
    d = ros_domain_id
    start_node(node_process, router, d, channels=1, pw01__period_ms=200)
    c = client(router.port)
    try:
        logs: list = []
        log_key = data_key(d, "/rosout", "rcl_interfaces/msg/Log")
        log_sub = c.declare_subscriber(
            log_key, lambda s: logs.append(ros2msg.decode("rcl_interfaces/msg/Log",
                                                          s.payload.to_bytes())))
        call = Call(c)
        get = lambda: call(d, f"{NODE}/get_parameters", "rcl_interfaces/srv/GetParameters",
                           {"names": ["pw01.period_ms"]})
        first = wait_until("the get_parameters service", lambda: _or_none(get))
        assert [v.double_value or v.integer_value for v in first.values] == [200]
        r = call(d, f"{NODE}/set_parameters", "rcl_interfaces/srv/SetParameters", {
            "parameters": [{"name": "pw01.period_ms",
                            "value": {"type": first.values[0].type,
                                      "integer_value": 100, "double_value": 100.0}}]})
        assert [x.successful for x in r.results] == [True], r.results
        again = get()
        assert [v.double_value or v.integer_value for v in again.values] == [100]
        # The change is logged, and the record reaches /rosout on its exact key.
        line = wait_until("the change on /rosout", lambda: next(
            (m for m in logs if m.msg.startswith("parameter pw01.period_ms = 100")), None))
        assert (line.level, line.name) == (20, "pwm_actuator"), line
        assert abs(line.stamp.sec - time.time()) < 60, line.stamp
        log_sub.undeclare()
    finally:
        c.close()


def _or_none(f: Callable[[], Any]) -> Any:
    try:
        return f()
    except AssertionError:
        return None


def test_the_lifecycle_walks_through_change_state_and_get_state(
    node_process, router, ros_domain_id: int
):
    d = ros_domain_id
    start_node(node_process, router, d, "--managed", channels=1)
    c = client(router.port)
    try:
        call = Call(c)
        state = lambda: call(d, f"{NODE}/get_state", "lifecycle_msgs/srv/GetState", {}).current_state.label
        assert wait_until("get_state", lambda: _or_none(state)) == "unconfigured"
        for transition, label in [(1, "inactive"), (3, "active"), (4, "inactive"), (2, "unconfigured")]:
            r = call(d, f"{NODE}/change_state", "lifecycle_msgs/srv/ChangeState",
                     {"transition": {"id": transition}})
            assert r.success, transition
            assert state() == label
    finally:
        c.close()


def test_a_late_joiner_gets_e1s_last_sample(node_process, router, ros_domain_id: int):
    d = ros_domain_id
    # No minimum time: e1 (the duty could not be reproduced) is false, published once at the
    # start and never changed, before anyone listens; what the late joiner gets can only be
    # that sample from the publisher's cache.
    start_node(node_process, router, d, channels=1, pw01__period_ms=200, pw01__enable=True,
               pw01__duty=50.0)
    time.sleep(2.0)
    c = client(router.port)
    try:
        got: list = []
        key = data_key(d, "/pwm_actuator/pw01/e1", "std_msgs/msg/Bool")
        declared_ns = time.time_ns()
        sub = zenoh.ext.declare_advanced_subscriber(
            c, key,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            handler=lambda s: got.append((s.payload.to_bytes(), s.attachment)),
        )
        wait_until("e1's cached sample", lambda: got)
        time.sleep(1.0)  # nothing live follows
        assert len(got) == 1, got
        payload, att = got[0]
        assert ros2msg.decode("std_msgs/msg/Bool", payload).data is False
        seq, stamp_ns, _ = read_attachment(att)
        assert seq >= 1, seq
        assert stamp_ns < declared_ns - 1_000_000_000, (stamp_ns, declared_ns)
        sub.undeclare()
    finally:
        c.close()


ACTION = f"{NODE}/pw01/autotune"
AUTOTUNE = "pwm_actuator_msgs/action/Autotune"


def test_the_autotune_action_takes_a_goal_reports_it_and_cancels_it(
    node_process, router, ros_domain_id: int
):
    d = ros_domain_id
    feedback_topic = "/heater/temperature"
    start_node(node_process, router, d, channels=1, pw01__enable=True, pw01__period_ms=200,
               pw01__feedback_topic=feedback_topic, pw01__control="pid", pw01__pid_kp=20.0,
               pw01__pid_ki=5.0, pw01__temp_min_c=0.0, pw01__temp_max_c=150.0,
               pw01__feedback_timeout_ms=1000)
    c = client(router.port)
    stop = threading.Event()
    try:
        # The action's five endpoints, each with rosidl's hash.
        want = {
            ("SS", f"{ACTION}/_action/send_goal", f"{AUTOTUNE}_SendGoal"),
            ("SS", f"{ACTION}/_action/cancel_goal", "action_msgs/srv/CancelGoal"),
            ("SS", f"{ACTION}/_action/get_result", f"{AUTOTUNE}_GetResult"),
            ("MP", f"{ACTION}/_action/feedback", f"{AUTOTUNE}_FeedbackMessage"),
            ("MP", f"{ACTION}/_action/status", "action_msgs/msg/GoalStatusArray"),
        }

        def seen() -> Optional[dict]:
            found = {(t.split("/")[5], t.split("/")[9].replace("%", "/")): t.split("/")
                     for t in tokens(c, d) if len(t.split("/")) >= 13}
            return found if all((k, n) in found for k, n, _ in want) else None

        found = wait_until("the action's tokens", seen)
        for kind, name, ros_type in want:
            chunks = found[(kind, name)]
            assert chunks[10] == zenoh_type(ros_type), chunks
            assert chunks[11] == rosidl_hash(ros_type), (name, chunks[11])

        # A heater reading ten times a second, as a sensor node would publish it.
        temp_key = data_key(d, feedback_topic, "sensor_msgs/msg/Temperature")
        feed_gid = os.urandom(16)

        def feed() -> None:
            n = 0
            while not stop.is_set():
                n += 1
                now = time.time_ns()
                c.put(temp_key, ros2msg.encode("sensor_msgs/msg/Temperature", {
                    "header": {"stamp": {"sec": now // 10**9, "nanosec": now % 10**9},
                               "frame_id": ""},
                    "temperature": 25.0, "variance": 0.0}), attachment=attachment(n, feed_gid))
                time.sleep(0.1)

        threading.Thread(target=feed, daemon=True).start()
        statuses: list = []
        c.declare_subscriber(
            data_key(d, f"{ACTION}/_action/status", "action_msgs/msg/GoalStatusArray"),
            lambda s: statuses.append(ros2msg.decode("action_msgs/msg/GoalStatusArray",
                                                     s.payload.to_bytes())))
        feedback: list = []
        c.declare_subscriber(
            data_key(d, f"{ACTION}/_action/feedback", f"{AUTOTUNE}_FeedbackMessage"),
            lambda s: feedback.append(ros2msg.decode(f"{AUTOTUNE}_FeedbackMessage",
                                                     s.payload.to_bytes())))
        goal_id = list(os.urandom(16))
        call = Call(c)
        send = lambda: call(d, f"{ACTION}/_action/send_goal", f"{AUTOTUNE}_SendGoal", {
            "goal_id": {"uuid": goal_id},
            "goal": {"target_c": 60.0, "amplitude_pct": 0.0, "noise_band_c": 0.5,
                     "apply": False}})
        # Refused until the first reading is in; a refused goal leaves nothing behind.
        wait_until("the goal accepted", lambda: getattr(_or_none(send), "accepted", False))

        def status_of(uuid: list) -> Optional[int]:
            """The goal's status in the newest status array."""
            if not statuses:
                return None
            return next((s.status for s in statuses[-1].status_list
                         if list(s.goal_info.goal_id.uuid) == uuid), None)

        wait_until("the goal executing on the status topic", lambda: status_of(goal_id) == 2)
        wait_until("the goal's feedback", lambda: any(
            list(f.goal_id.uuid) == goal_id for f in feedback))
        # get_result waits for the end: its reply comes after the cancel.
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            result = pool.submit(Call(c), d, f"{ACTION}/_action/get_result",
                                 f"{AUTOTUNE}_GetResult", {"goal_id": {"uuid": goal_id}})
            time.sleep(0.5)
            assert not result.done()
            r = call(d, f"{ACTION}/_action/cancel_goal", "action_msgs/srv/CancelGoal", {
                "goal_info": {"goal_id": {"uuid": goal_id}, "stamp": {"sec": 0, "nanosec": 0}}})
            assert r.return_code == 0, r
            assert [list(g.goal_id.uuid) for g in r.goals_canceling] == [goal_id], r
            got = result.result(timeout=WAIT_S + 5)
        assert got.status == 5, got  # STATUS_CANCELED
        assert got.result.stop == "canceled", got.result
        wait_until("the goal canceled on the status topic", lambda: status_of(goal_id) == 5)
        # A goal the server does not know: answered at once, STATUS_UNKNOWN.
        t0 = time.monotonic()
        unknown = call(d, f"{ACTION}/_action/get_result", f"{AUTOTUNE}_GetResult",
                       {"goal_id": {"uuid": list(os.urandom(16))}})
        assert unknown.status == 0 and time.monotonic() - t0 < 2.0, unknown
    finally:
        stop.set()
        c.close()
