"""The node's parameters and its ROS node-level interface, checked from outside with rclpy.

Parameters through both doors (the standard parameter services and the `~/<ch>/params` topic),
the refusals and their reasons, descriptors and listing, type coercion; `/diagnostics` levels;
`--ros-args` name remapping and parameter files; and what a stop by signal leaves on the outputs.

Each test starts the built node on its own ROS domain with the simulated output and a CSV trace
(`node_process`), talks to it only over ROS (`ros`), and reads the trace for timing. Timing is
checked on the trace's `scheduled_ns` column, the times the node's core planned, which are exact
integers whatever the machine's load; wall-clock measurements only bound things loosely.
"""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Optional, Sequence

import pytest
from conftest import (
    DEFAULT_TIMEOUT,
    ManagedProcess,
    MessageLog,
    RosClient,
    WaitTimeout,
    wait_until,
)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from pwm_actuator_msgs.msg import ChannelParams, OutputEdge
from rcl_interfaces.msg import (
    ListParametersResult,
    ParameterDescriptor,
    ParameterEvent,
    ParameterType,
    ParameterValue,
    SetParametersResult,
)
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.srv import (
    DescribeParameters,
    GetParameters,
    GetParameterTypes,
    ListParameters,
    SetParameters,
    SetParametersAtomically,
)
from rclpy.parameter import parameter_value_to_python
from rclpy.qos import qos_profile_parameter_events
from rclpy.serialization import serialize_message
from std_msgs.msg import Float64

NODE = "/pwm_actuator"
MS = 1_000_000
TRACE_HEADER = "t_ns,channel,level,scheduled_ns"

#: Every per-channel parameter the parameter page (docs/parameters.md) documents.
#: Every per-channel parameter the README and docs/heater.md document.
CHANNEL_PARAMS = (
    "period_ms",
    "min_on_ms",
    "min_off_ms",
    "output_kind",
    "profile",
    "short_pulse",
    "edge_band",
    "apply_at",
    "on_disable",
    "command_timeout_ms",
    "fault_duty_pct",
    "fault_hold_ms",
    "expected_command_hz_min",
    "expected_command_hz_max",
    "max_on_ms",
    "max_duty_pct",
    "min_duty_pct",
    "zero_means_zero",
    "duty_slew_pct_per_s",
    "duty_deadband_pct",
    "extend_max",
    "time_base_ms",
    "avg_duty_limit_pct",
    "avg_window_s",
    "active_low",
    "enable",
    "duty",
    "gpio_chip",
    "gpio_line",
    # The heater loop (docs/heater.md).
    "feedback_topic",
    "control",
    "pid_sample_ms",
    "pid_kp",
    "pid_ki",
    "pid_kd",
    "pid_d_filter_s",
    "temp_min_c",
    "temp_max_c",
    "feedback_timeout_ms",
    "feedback_max_skew_ms",
    "setpoint_margin_c",
    "sensor_stuck_time_s",
    "sensor_stuck_band_c",
    "sensor_stuck_energy_s",
    "no_rise_time_s",
    "sensor_max_rate_c_per_s",
    "runaway_hysteresis_c",
    "runaway_max_error",
    "runaway_gain_time_s",
    "runaway_heating_gain_c",
    "stuck_on_rise_c",
    "stuck_on_time_s",
    "autotune_max_overshoot_c",
    "autotune_timeout_s",
    "autotune_extend_s",
    "autotune_margin_c",
    "model_gain_c_per_pct",
    "model_tau_s",
    "model_dead_time_s",
    "model_ambient_c",
    "model_sensor_tau_s",
    "feedforward_topic",
    "feedforward_timeout_ms",
    "ambient_topic",
    "ambient_timeout_ms",
    "setpoint_ramp_c_per_s",
    "model_tolerance_c",
    "model_time_s",
)


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


def start_node(node_process, ros_args: Sequence[str] = (), name: str = "node") -> ManagedProcess:
    """Starts the node with `--ros-args *ros_args` and waits until it says it is running."""
    args = ["--ros-args", *ros_args] if ros_args else []
    proc = node_process(args, name=name)
    proc.wait_for_output("running:")
    return proc


def params(*assignments: str) -> list[str]:
    """`-p` before each `name:=value`."""
    return [arg for a in assignments for arg in ("-p", a)]


class Services:
    """The parameter services of one node: the `ros` fixture's parameter helpers (which keep one
    client per service for the test) bound to the node's name."""

    #: Pause after a new publisher matches, seconds (not a timing assertion).
    SETTLE_S = 0.25

    def __init__(self, ros: RosClient, node: str = NODE) -> None:
        self.ros = ros
        self.node = node

    def get_parameter_values(self, names: Sequence[str]) -> list[ParameterValue]:
        return self.ros.get_parameter_values(self.node, names)

    def get_parameters(self, names: Sequence[str]) -> dict[str, Any]:
        return self.ros.get_parameters(self.node, names)

    def set_parameters(self, values: Mapping[str, Any]) -> dict[str, SetParametersResult]:
        return self.ros.set_parameters(self.node, values)

    def set_parameters_atomically(self, values: Mapping[str, Any]) -> SetParametersResult:
        return self.ros.set_parameters_atomically(self.node, values)

    def list_parameters(self, prefixes: Sequence[str] = ()) -> ListParametersResult:
        return self.ros.list_parameters(self.node, prefixes)

    def describe_parameters(self, names: Sequence[str]) -> dict[str, ParameterDescriptor]:
        return self.ros.describe_parameters(self.node, names)


@pytest.fixture
def svc(ros: RosClient) -> Services:
    """The parameter services of /pwm_actuator."""
    return Services(ros)


def matched_publisher(ros: RosClient, msg_type: Any, topic: str) -> Any:
    """A publisher on `topic` once the node's subscription has matched it, given a moment more
    (Services.SETTLE_S) for the node's side to match it too: a message sent before that is
    delivered only after Fast DDS's next heartbeat, 3 s later."""
    publisher = ros.publisher(msg_type, topic)
    ros.wait_for_subscribers(publisher)
    ros.spin_for(Services.SETTLE_S)
    return publisher


@dataclass(frozen=True)
class Edge:
    """One row of the CSV trace."""

    t_ns: int
    level: int
    scheduled_ns: int


def trace_edges(proc: ManagedProcess, channel: str) -> list[Edge]:
    """The trace rows of `channel` after its initial row, complete lines only (the node writes
    the file while it runs, so the last line may be half written)."""
    text = proc.trace_text()
    if not text:
        return []
    lines = text.split("\n")
    assert lines[0] == TRACE_HEADER, f"unexpected trace header {lines[0]!r}"
    rows = []
    for line in lines[1:-1]:
        t_ns, ch, level, scheduled = line.split(",")
        if ch == channel:
            rows.append(Edge(int(t_ns), int(level), int(scheduled)))
    # The first row of each channel is its initial level, not an edge.
    return rows[1:]


def last_levels(proc: ManagedProcess) -> dict[str, int]:
    """Each channel's last level in the trace, initial rows included."""
    text = proc.trace_text()
    lines = text.split("\n")
    assert lines[0] == TRACE_HEADER, f"unexpected trace header {lines[0]!r}"
    last: dict[str, int] = {}
    for line in lines[1:]:
        if line:
            _, ch, level, _ = line.split(",")
            last[ch] = int(level)
    return last


def wait_edges(
    ros: RosClient,
    proc: ManagedProcess,
    channel: str,
    predicate: Callable[[list[Edge]], bool],
    what: str,
    timeout: Optional[float] = None,
) -> list[Edge]:
    """Spins `ros` until `predicate(trace_edges(channel))` holds; returns those edges."""

    def check() -> Optional[list[Edge]]:
        edges = trace_edges(proc, channel)
        return edges if predicate(edges) else None

    try:
        return ros.spin_until(check, what, timeout)
    except WaitTimeout as exc:
        raise AssertionError(f"{exc}\ntrace of {channel}: {trace_edges(proc, channel)}") from None


def rises(edges: Iterable[Edge]) -> list[int]:
    """Scheduled times of the rising edges, ns."""
    return [e.scheduled_ns for e in edges if e.level == 1]


def intervals_ms(times: Sequence[int]) -> list[float]:
    return [(b - a) / MS for a, b in zip(times, times[1:])]


def on_times(edges: Sequence[Edge]) -> list[tuple[int, int]]:
    """(rise, fall - rise) for every rise followed by a fall, scheduled ns."""
    out = []
    for a, b in zip(edges, edges[1:]):
        if a.level == 1 and b.level == 0:
            out.append((a.scheduled_ns, b.scheduled_ns - a.scheduled_ns))
    return out


def level_of(status: DiagnosticStatus) -> int:
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


OK = level_of(DiagnosticStatus(level=DiagnosticStatus.OK))
WARN = level_of(DiagnosticStatus(level=DiagnosticStatus.WARN))
ERROR = level_of(DiagnosticStatus(level=DiagnosticStatus.ERROR))


def key_values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def wait_diag(
    ros: RosClient,
    log: MessageLog,
    name: str,
    predicate: Callable[[DiagnosticStatus], bool] = lambda s: True,
    what: str = "",
    start: int = 0,
    timeout: Optional[float] = None,
) -> DiagnosticStatus:
    """The first status named `name` (in messages from index `start`) satisfying `predicate`."""

    def find() -> Optional[DiagnosticStatus]:
        for array in log.messages[start:]:
            for status in array.status:
                if status.name == name and predicate(status):
                    return status
        return None

    try:
        return ros.spin_until(find, f"diagnostics {name!r}: {what}", timeout)
    except WaitTimeout as exc:
        seen = [
            (s.name, level_of(s), s.message)
            for a in log.messages[-5:]
            for s in a.status
            if s.name == name
        ]
        raise AssertionError(f"{exc}\nlast statuses seen: {seen}") from None


def wait_refusal(ros: RosClient, log: MessageLog, what: str, start: int = 0) -> DiagnosticStatus:
    """pw01's first status (in messages from index `start`) that reports a last refusal."""
    return wait_diag(
        ros, log, "pwm_actuator: pw01", lambda s: key_values(s).get("last_refusal", ""), what, start
    )


def subscribe_events(ros: RosClient) -> MessageLog:
    return ros.subscribe(ParameterEvent, "/parameter_events", qos_profile_parameter_events)


#: The parameter `sync_parameter_events` changes (it only sets how many edges the console shows).
SYNC_PARAM = "edge_log_rate"


def node_events(
    log: MessageLog, node: str, start: int, sync: bool = False
) -> list[ParameterEvent]:
    """Events from `node` with changed parameters, from index `start`; those changing only
    SYNC_PARAM are left out unless `sync`."""
    return [
        m
        for m in log.messages[start:]
        if m.node == node
        and m.changed_parameters
        and (sync or any(p.name != SYNC_PARAM for p in m.changed_parameters))
    ]


def sync_parameter_events(svc: Services, log: MessageLog) -> int:
    """Makes sure the node's `/parameter_events` reach `log` before a test relies on them.

    Changes SYNC_PARAM until the node's event about it arrives, so discovery has matched both
    ways. Returns the index from which later events are new.
    """
    deadline = time.monotonic() + DEFAULT_TIMEOUT
    rate = 11
    while True:
        start = len(log.messages)
        result = svc.set_parameters({SYNC_PARAM: rate})[SYNC_PARAM]
        assert result.successful, f"{SYNC_PARAM} {rate} refused: {result.reason}"
        try:
            svc.ros.spin_until(
                lambda: node_events(log, svc.node, start, sync=True),
                "the node's event",
                timeout=1.0,
            )
            return len(log.messages)
        except WaitTimeout:
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"no /parameter_events message from {svc.node} after changing {SYNC_PARAM}"
                ) from None
        rate += 1


def changed(event: ParameterEvent) -> dict[str, Any]:
    return {p.name: parameter_value_to_python(p.value) for p in event.changed_parameters}


def assert_no_events(log: MessageLog, start: int, node: str = NODE) -> None:
    announced = node_events(log, node, start)
    assert not announced, f"unexpected changes announced: {[changed(e) for e in announced]}"


def wait_for_stderr(ros: RosClient, proc: ManagedProcess, needle: str, what: str) -> str:
    """Spins until `needle` is in the node's stderr; returns the stderr."""
    try:
        ros.spin_until(lambda: needle in proc.stderr(), what)
    except WaitTimeout as exc:
        raise AssertionError(f"{exc}\n{proc.output()}") from None
    return proc.stderr()


# ---------------------------------------------------------------------------------------------
# Parameter services
# ---------------------------------------------------------------------------------------------


@pytest.mark.smoke
def test_period_change_through_set_parameters_applies_at_a_period_boundary(ros, node_process, svc):
    events = subscribe_events(ros)
    proc = start_node(
        node_process, params("pw01.enable:=true", "pw01.duty:=50.0", "pw01.period_ms:=200")
    )
    start = sync_parameter_events(svc, events)
    wait_edges(ros, proc, "pw01", lambda e: len(rises(e)) >= 3, "3 periods of 200 ms")

    t_request = time.monotonic_ns()
    result = svc.set_parameters({"pw01.period_ms": 100})["pw01.period_ms"]
    t_response = time.monotonic_ns()
    assert result.successful, result.reason

    [value] = svc.get_parameter_values(["pw01.period_ms"])
    assert (value.type, value.integer_value) == (ParameterType.PARAMETER_INTEGER, 100)

    [event] = ros.spin_until(
        lambda: node_events(events, NODE, start), "the node's /parameter_events message"
    )
    assert changed(event) == {"pw01.period_ms": 100}
    assert event.changed_parameters[0].value.type == ParameterType.PARAMETER_INTEGER
    assert not event.new_parameters and not event.deleted_parameters

    edges = wait_edges(
        ros,
        proc,
        "pw01",
        lambda e: len([r for r in rises(e) if r > t_response + 300 * MS]) >= 4,
        "4 rises after the change",
    )
    starts = rises(edges)
    periods = intervals_ms(starts)
    # Old periods, then new ones: no period of another length (the grid changes at a boundary).
    assert set(periods) <= {200.0, 100.0}, periods
    first_new = periods.index(100.0)
    assert first_new >= 2 and set(periods[:first_new]) == {200.0}, periods
    assert set(periods[first_new:]) == {100.0} and len(periods) - first_new >= 3, periods
    # Every period's pulse is half of that period's length.
    pulse = dict(on_times(edges))
    for begin, length in zip(starts, periods):
        assert pulse.get(begin) == length * MS / 2, (begin, length, on_times(edges))
    # The first new period starts at a boundary after the request (less the output thread's
    # lateness, bounded at 100 ms: a change applied to an earlier period would be 200 ms off),
    # and soon after the answer (within a period and a generous second).
    switch = starts[first_new]
    assert t_request - 100 * MS < switch, (t_request, switch)
    assert switch < t_response + 200 * MS + 1_000 * MS, (t_response, switch)


# ---------------------------------------------------------------------------------------------
# The parameter topic
# ---------------------------------------------------------------------------------------------


@pytest.mark.untimed
def test_params_topic_applies_all_named_fields_at_once(ros, node_process, svc):
    events = subscribe_events(ros)
    start_node(node_process)
    start = sync_parameter_events(svc, events)
    pub = matched_publisher(ros, ChannelParams, f"{NODE}/pw01/params")

    msg = ChannelParams(
        set=["period_ms", "min_on_ms", "min_off_ms", "apply_at", "edge_band"],
        period_ms=400,
        min_on_ms=20,
        min_off_ms=30,
        apply_at="immediate",
        edge_band=0.25,
        # Not named in `set`: must be ignored (an empty profile would be refused).
        profile="",
        output_kind="",
    )
    expected = {
        "pw01.period_ms": 400,
        "pw01.min_on_ms": 20,
        "pw01.min_off_ms": 30,
        "pw01.apply_at": "immediate",
        "pw01.edge_band": 0.25,
    }
    # Repeats until applied; a repeat changes nothing, so it announces nothing.
    ros.publish_until(pub, msg, lambda: node_events(events, NODE, start), "the change's event")
    values = svc.get_parameters([*expected, "pw01.profile", "pw01.output_kind"])
    assert values == {**expected, "pw01.profile": "pico_gfx", "pw01.output_kind": "transistor"}

    ros.spin_for(1.0)
    announced = node_events(events, NODE, start)
    assert len(announced) == 1, [changed(e) for e in announced]
    assert changed(announced[0]) == expected


@pytest.mark.untimed
def test_params_topic_refuses_the_whole_message_when_one_field_is_bad(ros, node_process, svc):
    events = subscribe_events(ros)
    diagnostics = ros.subscribe(DiagnosticArray, "/diagnostics")
    proc = start_node(node_process)
    start = sync_parameter_events(svc, events)
    pub = matched_publisher(ros, ChannelParams, f"{NODE}/pw01/params")

    bad = ChannelParams(
        set=["period_ms", "min_on_ms", "edge_band"], period_ms=300, min_on_ms=20, edge_band=1.5
    )
    refusal = "parameter change refused (via ~/pw01/params)"
    ros.publish_until(pub, bad, lambda: refusal in proc.stderr(), "the refusal in the log")
    line = next(l for l in proc.stderr().splitlines() if refusal in l)
    assert "edge_band" in line and "1.5" in line, line

    values = svc.get_parameters(["pw01.period_ms", "pw01.min_on_ms", "pw01.edge_band"])
    assert values == {"pw01.period_ms": 1000, "pw01.min_on_ms": 0, "pw01.edge_band": 0.0}

    status = wait_refusal(ros, diagnostics, "a last_refusal")
    reason = key_values(status)["last_refusal"]
    assert "edge_band" in reason and "1.5" in reason, reason

    ros.spin_for(1.0)
    assert_no_events(events, start)


def test_refused_parameter_puts_the_channel_at_warn(ros, node_process, svc):
    # docs/interface.md: "WARN when E1 or the limit flag acts, when the command in force was clamped, or
    # for 5 s after a refused command or parameter".
    diagnostics = ros.subscribe(DiagnosticArray, "/diagnostics")
    start_node(node_process)
    wait_diag(ros, diagnostics, "pwm_actuator: pw01", lambda s: level_of(s) == OK, "OK at first")
    result = svc.set_parameters({"pw01.period_ms": 4})["pw01.period_ms"]
    assert not result.successful
    start = len(diagnostics.messages)
    status = wait_refusal(ros, diagnostics, "the refusal", start=start)
    assert level_of(status) == WARN, (level_of(status), status.message, key_values(status))


# ---------------------------------------------------------------------------------------------
# Refusals through the services
# ---------------------------------------------------------------------------------------------


@pytest.mark.untimed
def test_invalid_values_are_refused_with_a_reason_and_the_old_values_stay(ros, node_process, svc):
    events = subscribe_events(ros)
    start_node(
        node_process,
        params("pw01.min_off_ms:=100", "pw02.output_kind:=relay", "pw02.period_ms:=1000"),
    )
    start = sync_parameter_events(svc, events)
    watched = [
        "pw01.period_ms",
        "pw01.min_on_ms",
        "pw01.min_off_ms",
        "pw01.edge_band",
        "pw01.profile",
        "pw01.output_kind",
        "pw02.min_on_ms",
    ]
    before = svc.get_parameters(watched)
    assert before == {
        "pw01.period_ms": 1000,
        "pw01.min_on_ms": 0,
        "pw01.min_off_ms": 100,
        "pw01.edge_band": 0.0,
        "pw01.profile": "pico_gfx",
        "pw01.output_kind": "transistor",
        "pw02.min_on_ms": 0,
    }

    # (what, values, atomically, words the reason must contain)
    cases = [
        (
            "period below the transistor minimum",
            {"pw01.period_ms": 4},
            False,
            ["period_ms 4", "transistor", "5 ms"],
        ),
        ("relay min_on below 50 ms", {"pw02.min_on_ms": 20}, False, ["min", "20", "relay", "50"]),
        ("min_on_ms above one hour", {"pw01.min_on_ms": 3_600_001}, False, ["3600001"]),
        ("edge_band 1.5", {"pw01.edge_band": 1.5}, False, ["edge_band", "1.5"]),
        ("unknown profile", {"pw01.profile": "bad_vendor"}, False, ["bad_vendor", "pico_gfx"]),
        (
            "a relay with a 20 ms minimum, atomically",
            {"pw01.output_kind": "relay", "pw01.min_on_ms": 20},
            True,
            ["min_on_ms 20", "relay", "50 ms"],
        ),
    ]
    problems = []
    for what, values, atomically, words in cases:
        if atomically:
            result = svc.set_parameters_atomically(values)
        else:
            [result] = svc.set_parameters(values).values()
        if result.successful:
            problems.append(f"{what}: accepted")
        elif not all(w in result.reason for w in words):
            problems.append(f"{what}: reason {result.reason!r} does not name {words}")
        now = svc.get_parameters(watched)
        if now != before:
            problems.append(f"{what}: values changed to {now}")
    assert not problems, "\n".join(problems)
    ros.spin_for(0.5)
    assert_no_events(events, start)

    # Each value of the refused combination passes on its own; the check is across parameters.
    result = svc.set_parameters_atomically({"pw01.min_on_ms": 20})
    assert result.successful, result.reason
    result = svc.set_parameters_atomically({"pw01.min_on_ms": 0, "pw01.output_kind": "relay"})
    assert result.successful, result.reason
    [result] = svc.set_parameters({"pw01.min_on_ms": 20}).values()
    assert not result.successful and "relay" in result.reason, result.reason
    assert svc.get_parameters(["pw01.min_on_ms", "pw01.output_kind"]) == {
        "pw01.min_on_ms": 0,
        "pw01.output_kind": "relay",
    }
    # Minima that do not both fit in the period are valid vendor settings (000: ME up to
    # 65 535 ms whatever PD): accepted.
    result = svc.set_parameters_atomically({"pw01.min_on_ms": 600, "pw01.min_off_ms": 500})
    assert result.successful, result.reason


# ---------------------------------------------------------------------------------------------
# Descriptors, listing, types
# ---------------------------------------------------------------------------------------------


@pytest.mark.untimed
@pytest.mark.smoke
def test_descriptors_ranges_and_listing(ros, node_process, svc):
    start_node(node_process)
    d = svc.describe_parameters(["pw01.period_ms", "pw01.edge_band", "pw01.active_low"])

    period = d["pw01.period_ms"]
    assert period.name == "pw01.period_ms"
    assert period.type == ParameterType.PARAMETER_INTEGER
    assert period.description.strip()
    assert [(r.from_value, r.to_value) for r in period.integer_range] == [(0, 3_600_000)]
    assert not period.floating_point_range and not period.read_only

    band = d["pw01.edge_band"]
    assert band.type == ParameterType.PARAMETER_DOUBLE
    assert band.description.strip()
    assert [(r.from_value, r.to_value) for r in band.floating_point_range] == [(0.0, 1.0)]
    assert not band.integer_range and not band.read_only

    assert d["pw01.active_low"].read_only, "docs/parameters.md: active_low is read-only once running"

    listed = svc.list_parameters()
    names = set(listed.names)
    for ch in ("pw01", "pw02"):
        missing = {f"{ch}.{p}" for p in CHANNEL_PARAMS} - names
        assert not missing, f"not listed: {sorted(missing)}"
    assert {"channels", "output", "status_rate_hz"} <= names
    assert not [n for n in names if n.startswith("pw03.")], sorted(names)
    assert {"pw01", "pw02"} <= set(listed.prefixes)

    only = svc.list_parameters(["pw02"])
    assert set(only.names) == {f"pw02.{p}" for p in CHANNEL_PARAMS}, sorted(only.names)


#: A reply this large is sent in fragments (rustdds fragments a sample above about 1,400 bytes;
#: 1,440 bytes arrived in one piece, 1,728 did not before its DATA_FRAG fix).
FRAGMENTED_REPLY_BYTES = 2048
#: Channels of the node in the large-reply test: 19 parameters each, so that even the list of
#: names (about 20 bytes a name) is larger than FRAGMENTED_REPLY_BYTES.
MANY_CHANNELS = 8


@pytest.mark.untimed
def test_every_parameter_service_answers_for_all_parameters_at_once(ros, node_process):
    # docs/parameters.md: the parameter services answer requests of any size, e.g. for every parameter at
    # once as `ros2 param dump` asks. Replies above one datagram are fragmented; each must reach
    # the rclpy client, and the same client's later calls must still be answered.
    proc = node_process(["--channels", str(MANY_CHANNELS)])
    proc.wait_for_output("running:")
    sizes: dict[str, int] = {}

    def call(service: str, srv_type: Any, request: Any, what: str) -> Any:
        response = ros.call(srv_type, f"{NODE}/{service}", request)
        sizes[what] = len(serialize_message(response))
        return response

    def small_calls_still_answered(duty: ParameterValue) -> None:
        # One small request to each service, on the same clients as the large ones; the set
        # requests give pw01.duty the value `duty` it has.
        req = GetParameters.Request(names=["pw01.period_ms"])
        [value] = call("get_parameters", GetParameters, req, "small get").values
        assert (value.type, value.integer_value) == (ParameterType.PARAMETER_INTEGER, 1000)
        req = GetParameterTypes.Request(names=["pw01.duty"])
        types = call("get_parameter_types", GetParameterTypes, req, "small types").types
        assert list(types) == [ParameterType.PARAMETER_DOUBLE]
        req = DescribeParameters.Request(names=["pw02.edge_band"])
        [d] = call("describe_parameters", DescribeParameters, req, "small describe").descriptors
        assert d.name == "pw02.edge_band"
        req = ListParameters.Request(prefixes=["pw03"], depth=0)
        listed = call("list_parameters", ListParameters, req, "small list").result
        assert set(listed.names) == {f"pw03.{p}" for p in CHANNEL_PARAMS}
        req = SetParameters.Request(parameters=[ParameterMsg(name="pw01.duty", value=duty)])
        [result] = call("set_parameters", SetParameters, req, "small set").results
        assert result.successful, result.reason
        req = SetParametersAtomically.Request(parameters=list(req.parameters))
        result = call("set_parameters_atomically", SetParametersAtomically, req, "small atomic")
        assert result.result.successful, result.result.reason

    # Every name at once.
    listed = call("list_parameters", ListParameters, ListParameters.Request(), "list all").result
    names = list(listed.names)
    expected = {f"pw{c:02}.{p}" for c in range(1, MANY_CHANNELS + 1) for p in CHANNEL_PARAMS}
    assert not expected - set(names), sorted(expected - set(names))

    req = GetParameters.Request(names=names)
    values = list(call("get_parameters", GetParameters, req, "get all").values)
    assert len(values) == len(names)
    unset = [n for n, v in zip(names, values) if v.type == ParameterType.PARAMETER_NOT_SET]
    assert not unset, f"no value for {unset}"

    req = GetParameterTypes.Request(names=names)
    # One byte a name: this reply stays small whatever the node.
    types = list(call("get_parameter_types", GetParameterTypes, req, "types all").types)
    assert types == [v.type for v in values]

    req = DescribeParameters.Request(names=names)
    descriptors = call("describe_parameters", DescribeParameters, req, "describe all").descriptors
    assert [d.name for d in descriptors] == names
    assert [d.type for d in descriptors] == types

    # Every parameter set to the value it has: all accepted, in one request either way.
    same = [ParameterMsg(name=n, value=v) for n, v in zip(names, values)]
    req = SetParameters.Request(parameters=same)
    results = call("set_parameters", SetParameters, req, "set all, same values").results
    refused = {n: r.reason for n, r in zip(names, results) if not r.successful}
    assert len(results) == len(names) and not refused, refused
    req = SetParametersAtomically.Request(parameters=same)
    result = call("set_parameters_atomically", SetParametersAtomically, req, "atomic all").result
    assert result.successful, result.reason
    small_calls_still_answered(values[names.index("pw01.duty")])

    # Every parameter refused, each with a reason naming it: a large set_parameters reply.
    wrong = ParameterValue(type=ParameterType.PARAMETER_BYTE_ARRAY, byte_array_value=[b"\x01"])
    req = SetParameters.Request(parameters=[ParameterMsg(name=n, value=wrong) for n in names])
    results = call("set_parameters", SetParameters, req, "set all refused").results
    assert len(results) == len(names)
    not_named = [n for n, r in zip(names, results) if r.successful or n not in r.reason]
    assert not not_named, f"accepted, or refused without naming the parameter: {not_named}"

    # A refusal echoing a long name, alone and after every parameter of an atomic request.
    long_name = "pw01." + "x" * 3000
    unknown = ParameterMsg(
        name=long_name, value=ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=1)
    )
    req = SetParameters.Request(parameters=[unknown])
    [result] = call("set_parameters", SetParameters, req, "set long name").results
    assert not result.successful and "pw01.xxxx" in result.reason, result.reason[:200]
    req = SetParametersAtomically.Request(parameters=[*same, unknown])
    result = call("set_parameters_atomically", SetParametersAtomically, req, "atomic long").result
    assert not result.successful and "pw01.xxxx" in result.reason, result.reason[:200]

    small_calls_still_answered(values[names.index("pw01.duty")])
    assert ros.get_parameter_values(NODE, names) == values, "values changed"
    # The test is about replies sent in fragments: check that the large ones were.
    large = ("list all", "get all", "describe all", "set all refused")
    small = {what: sizes[what] for what in large if sizes[what] <= FRAGMENTED_REPLY_BYTES}
    assert not small, f"replies expected above {FRAGMENTED_REPLY_BYTES} bytes: {small}"
    print("reply sizes (bytes):", sizes)


@pytest.mark.untimed
def test_whole_doubles_are_taken_for_integers_and_fractions_refused(ros, node_process, svc):
    proc = start_node(node_process)
    [result] = svc.set_parameters({"pw01.period_ms": 500.0}).values()
    assert result.successful, result.reason
    [value] = svc.get_parameter_values(["pw01.period_ms"])
    assert (value.type, value.integer_value) == (ParameterType.PARAMETER_INTEGER, 500)
    # docs/parameters.md: "the log says so".
    wait_for_stderr(ros, proc, "500.0 taken as integer 500", "the coercion note")

    [result] = svc.set_parameters({"pw01.period_ms": 500.5}).values()
    assert not result.successful
    assert "500.5" in result.reason and "whole number" in result.reason, result.reason
    [result] = svc.set_parameters({"pw01.period_ms": "600"}).values()
    assert not result.successful and "integer" in result.reason, result.reason
    assert svc.get_parameters(["pw01.period_ms"]) == {"pw01.period_ms": 500}

    # And an integer for a double parameter.
    [result] = svc.set_parameters({"pw01.edge_band": 1}).values()
    assert result.successful, result.reason
    [value] = svc.get_parameter_values(["pw01.edge_band"])
    assert (value.type, value.double_value) == (ParameterType.PARAMETER_DOUBLE, 1.0)


# ---------------------------------------------------------------------------------------------
# Diagnostics
# ---------------------------------------------------------------------------------------------


@pytest.mark.untimed
@pytest.mark.smoke
def test_diagnostics_ok_for_a_normal_channel(ros, node_process):
    diagnostics = ros.subscribe(DiagnosticArray, "/diagnostics")
    proc = start_node(
        node_process, params("pw01.enable:=true", "pw01.duty:=50.0", "pw01.period_ms:=200")
    )
    status = wait_diag(
        ros,
        diagnostics,
        "pwm_actuator: pw01",
        lambda s: key_values(s).get("duty_applied_pct") == "50.000",
        "50 % applied",
    )
    assert level_of(status) == OK, (status.message, key_values(status))
    assert status.hardware_id == "sim"
    kv = key_values(status)
    for key in (
        "duty_commanded_pct",
        "duty_applied_pct",
        "on_time_ms",
        "off_time_ms",
        "e1",
        "rule",
        "last_rejection",
        "last_refusal",
        "rejected_commands",
        "reports_dropped",
    ):
        assert key in kv, f"key {key} missing from {sorted(kv)}"
    assert kv["duty_commanded_pct"] == "50.000"
    assert float(kv["on_time_ms"]) == 100.0 and float(kv["off_time_ms"]) == 100.0, kv
    assert kv["e1"] == "false" and kv["rule"] == "exact", kv
    assert kv["enabled"] == "true", kv
    # One status per channel, one per channel's command rate, one for the node, one for the
    # trace the test's node writes.
    [array] = [a for a in diagnostics.messages if any(s is status for s in a.status)]
    names = [s.name for s in array.status]
    assert names == [
        "pwm_actuator: pw01",
        "pwm_actuator: pw02",
        "pwm_actuator: pw01 command frequency",
        "pwm_actuator: pw02 command frequency",
        "pwm_actuator: node",
        f"pwm_actuator: trace {proc.trace_path}",
    ], names


@pytest.mark.untimed
def test_diagnostics_warn_while_e1_acts(ros, node_process):
    diagnostics = ros.subscribe(DiagnosticArray, "/diagnostics")
    # 5 % of 1000 ms is a 50 ms pulse, below the 100 ms minimum: pico_gfx suppresses it (E1).
    proc = start_node(
        node_process,
        params("pw01.enable:=true", "pw01.duty:=5.0", "pw01.min_on_ms:=100"),
    )
    status = wait_diag(
        ros, diagnostics, "pwm_actuator: pw01", lambda s: key_values(s).get("e1") == "true", "E1"
    )
    assert level_of(status) == WARN, (status.message, key_values(status))
    kv = key_values(status)
    assert kv["rule"] == "suppressed_pulse" and kv["duty_applied_pct"] == "0.000", kv
    assert "E1" in status.message, status.message
    # The other channel is unaffected.
    other = wait_diag(ros, diagnostics, "pwm_actuator: pw02", what="pw02")
    assert level_of(other) == OK, other.message
    # A status published more than a whole period later: still E1, and not one pulse written.
    ros.spin_for(1.5)
    start = len(diagnostics.messages)
    later = wait_diag(
        ros, diagnostics, "pwm_actuator: pw01", what="a status 1.5 s later", start=start
    )
    assert level_of(later) == WARN and key_values(later)["e1"] == "true", later.message
    assert key_values(later)["edges"] == "0", key_values(later)
    assert not rises(trace_edges(proc, "pw01")), trace_edges(proc, "pw01")


def test_diagnostics_error_when_the_watchdog_trips_and_ok_after_a_command(ros, node_process):
    diagnostics = ros.subscribe(DiagnosticArray, "/diagnostics")
    proc = start_node(
        node_process,
        params(
            "pw01.enable:=true",
            "pw01.duty:=50.0",
            "pw01.period_ms:=200",
            "pw01.command_timeout_ms:=1000",
        ),
    )
    status = wait_diag(
        ros, diagnostics, "pwm_actuator: pw01", lambda s: level_of(s) == ERROR, "ERROR"
    )
    kv = key_values(status)
    assert kv["watchdog_tripped"] == "true", kv
    assert "watchdog" in status.message, status.message
    assert status.hardware_id == "sim"
    # Forced off: the trace ends low, after having pulsed, and stays low for several periods.
    edges = wait_edges(
        ros, proc, "pw01", lambda e: e and e[-1].level == 0, "pw01 off after the trip"
    )
    assert rises(edges), "pw01 never pulsed before the watchdog tripped"
    ros.spin_for(0.8)
    assert trace_edges(proc, "pw01") == edges, "pw01 pulsed while the watchdog was tripped"
    tripped_rows = len(edges)

    # The next command recovers (commands keep coming, faster than the timeout).
    duty = matched_publisher(ros, Float64, f"{NODE}/pw01/duty")
    start = len(diagnostics.messages)
    ros.publish_until(
        duty,
        Float64(data=50.0),
        lambda: any(
            s.name == "pwm_actuator: pw01" and level_of(s) == OK
            for a in diagnostics.messages[start:]
            for s in a.status
        ),
        "OK after a command",
        period_s=0.2,
    )
    ros.publish_until(
        duty,
        Float64(data=50.0),
        lambda: rises(trace_edges(proc, "pw01")[tripped_rows:]),
        "pulses again after the command",
        period_s=0.2,
    )


# ---------------------------------------------------------------------------------------------
# --ros-args
# ---------------------------------------------------------------------------------------------


@pytest.mark.untimed
@pytest.mark.smoke
def test_node_and_namespace_remapping(ros, node_process):
    diagnostics = ros.subscribe(DiagnosticArray, "/diagnostics")
    edges = ros.subscribe(OutputEdge, "/plant/heater/pw01/edges", 100)
    start_node(
        node_process,
        [
            *("-r", "__node:=heater", "-r", "__ns:=/plant"),
            *params("pw01.enable:=true", "pw01.duty:=50.0", "pw01.period_ms:=100"),
        ],
    )
    heater = Services(ros, "/plant/heater")
    assert heater.get_parameters(["pw01.period_ms"]) == {"pw01.period_ms": 100}
    result = heater.set_parameters({"pw01.period_ms": 120})["pw01.period_ms"]
    assert result.successful, result.reason

    edge = edges.wait_for(lambda e: e.channel == 1, what="an edge on /plant/heater/pw01/edges")
    assert edge.seq >= 1
    status = wait_diag(ros, diagnostics, "heater: pw01", what="a status named after the node")
    assert status.hardware_id == "sim"
    ros.wait_for_node("heater", "/plant")

    expected = {
        "/plant/heater/pw01/duty",
        "/plant/heater/pw01/edges",
        "/plant/heater/pw02/params",
        "/plant/heater/set_parameters",
        "/plant/heater/describe_parameters",
    }

    def names() -> set[str]:
        topics = {t for t, _ in ros.node.get_topic_names_and_types()}
        return topics | {s for s, _ in ros.node.get_service_names_and_types()}

    ros.spin_until(lambda: expected <= names(), f"{sorted(expected)} in the graph")
    assert not [n for n in names() if n.startswith("/pwm_actuator")], sorted(names())
    assert ("pwm_actuator", "/") not in ros.node.get_node_names_and_namespaces()
    assert not [
        s.name for a in diagnostics.messages for s in a.status if s.name.startswith("pwm_actuator")
    ]


def test_topic_remapping_feeds_a_channel_from_another_topic(ros, node_process):
    # The private topic ~/pw01/duty, remapped for this node only (rcl's `node:from:=to`).
    proc = start_node(
        node_process,
        [
            *("-r", "__node:=heater", "-r", "__ns:=/plant"),
            *("-r", "heater:~/pw01/duty:=/pid/output"),
            *params("pw01.enable:=true", "pw01.period_ms:=100"),
        ],
    )
    pid = matched_publisher(ros, Float64, "/pid/output")
    assert not rises(trace_edges(proc, "pw01")), "pulses before any duty"
    ros.publish_until(
        pid,
        Float64(data=50.0),
        lambda: len(rises(trace_edges(proc, "pw01"))) >= 2,
        "pw01 pulsing from /pid/output",
    )
    edges = trace_edges(proc, "pw01")
    assert {length for _, length in on_times(edges)} == {50 * MS}, on_times(edges)
    # Remapped, not duplicated: the default name is no longer subscribed.
    ros.wait_for_topic("/plant/heater/pw01/sv", subscribers=1)
    assert ros.node.count_subscribers("/plant/heater/pw01/duty") == 0


def test_params_file_then_command_line_overrides(ros, node_process, svc, tmp_path: Path):
    params_file = tmp_path / "pwm.params.yaml"
    params_file.write_text(
        "/**:\n"
        "  ros__parameters:\n"
        "    pw01:\n"
        "      period_ms: 300\n"
        "      enable: true\n"
        "      duty: 50.0\n"
        "    pw02:\n"
        "      period_ms: 400\n"
        "      min_on_ms: 20\n"
        "      enable: true\n"
        "      duty: 25.0\n"
    )
    # Later wins: the file over the -p before it, the -p after it over the file.
    proc = start_node(
        node_process,
        [
            *params("pw01.period_ms:=999"),
            *("--params-file", str(params_file)),
            *params("pw02.period_ms:=200"),
        ],
    )
    values = svc.get_parameters(
        ["pw01.period_ms", "pw01.duty", "pw02.period_ms", "pw02.min_on_ms", "pw02.enable"]
    )
    assert values == {
        "pw01.period_ms": 300,
        "pw01.duty": 50.0,
        "pw02.period_ms": 200,
        "pw02.min_on_ms": 20,
        "pw02.enable": True,
    }

    for ch, period, on in (("pw01", 300, 150), ("pw02", 200, 50)):
        edges = wait_edges(ros, proc, ch, lambda e: len(rises(e)) >= 3, f"3 periods of {ch}")
        assert set(intervals_ms(rises(edges))) == {float(period)}, (ch, intervals_ms(rises(edges)))
        assert {length for _, length in on_times(edges)} == {on * MS}, (ch, on_times(edges))


# ---------------------------------------------------------------------------------------------
# Stopping
# ---------------------------------------------------------------------------------------------


@pytest.mark.untimed
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_stop_leaves_every_output_off(node_process, sig):
    proc = start_node(
        node_process,
        params("pw01.enable:=true", "pw01.duty:=100.0", "pw02.enable:=true", "pw02.duty:=100.0"),
    )
    wait_until(
        lambda: last_levels(proc) == {"pw01": 1, "pw02": 1}, "both outputs on in the trace"
    )
    proc.send_signal(sig)
    code = proc.wait_exit()
    assert code == 0, proc.output()
    assert last_levels(proc) == {"pw01": 0, "pw02": 0}, proc.trace_text()
    assert f"{sig.name}: stopping" in proc.stderr(), proc.stderr()
