"""Helpers for test_channel_rules.py: one channel of the node seen from rclpy, and the node's CSV
trace read as edges.

A `ChannelClient` holds the publishers of one channel's inputs (duty, SV, enable) and logs of its
outputs (edges, E1, status) and of `/diagnostics`; it confirms each command by what the node
reports back, and records the monotonic times that bound when the node handled it. `Edge` rows
come from the trace; their `scheduled_ns` are the exact times the timing core chose, so rules are
checked on them to the nanosecond, while written times (`t_ns`) get only a generous tolerance.

This module must not assert the node's behaviour: it only talks to the node and reads its trace.
The rules are asserted in the test module.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence

from conftest import ManagedProcess, MessageLog, RosClient, wait_until
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from pwm_actuator_msgs.msg import ChannelStatus, OutputEdge
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool, Float64, UInt16

#: Nanoseconds per millisecond.
MS = 1_000_000


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time in nanoseconds."""
    return stamp.sec * 1_000_000_000 + stamp.nanosec


#: The most an edge may be written after its scheduled time (trace `t_ns`, an edge's
#: `lateness_ns`), ns: on a shared 2-core VM without real-time priority the output thread was
#: seen waking 39 ms late once. Timing accuracy is the benchmark's business. An edge must also
#: be written before the line's next edge is due (test_channel_rules.assert_written_in_time),
#: so a short phase gets no more than its own length. Only absolute lateness is held to this:
#: two written times are compared by their difference, within CLOCK_TOL_NS.
WRITE_TOL_NS = 60 * MS
#: How far apart two figures of the same instants may be when they come from two clocks read
#: beside each other (the wall clock of a message's stamp, the monotonic clock of the trace), ns:
#: the offset between the clocks changes by far less than this over a test.
CLOCK_TOL_NS = 2 * MS
#: QoS of `~/<ch>/e1`: reliable, transient local, keep last 1 (docs/interface.md), so a late subscriber
#: gets the current state.
E1_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
#: The node's fully qualified name.
NODE = "/pwm_actuator"


def mono_ns() -> int:
    """CLOCK_MONOTONIC in ns, the clock of the node's trace and schedule."""
    return time.monotonic_ns()


def arrival_ns(log: MessageLog, index: int) -> int:
    """When message `index` of `log` was taken by the test (monotonic ns, rounded up)."""
    return math.ceil(log.arrivals[index] * 1e9)


def t_on_ns(fraction: float, period_ms: int) -> int:
    """The on time the core computes for a duty fraction: fraction x period, rounded to the
    nearest ns (half away from zero, as Rust's f64::round)."""
    exact = fraction * (period_ms * MS)
    return min(int(math.floor(exact + 0.5)), period_ms * MS)


def diag_level(status: DiagnosticStatus) -> int:
    """The level of a DiagnosticStatus as an int (rclpy gives a `byte` field as bytes)."""
    level = status.level
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


def diag_values(status: DiagnosticStatus) -> dict[str, str]:
    """The key-values of a DiagnosticStatus as a dict."""
    return {kv.key: kv.value for kv in status.values}


# ---------------------------------------------------------------------------------------------
# Trace
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Edge:
    """One row of the CSV trace: written at `t_ns`, scheduled at `scheduled_ns` (monotonic)."""

    t_ns: int
    level: int
    scheduled_ns: int


def trace_edges(proc: ManagedProcess, channel: str = "pw01") -> list[Edge]:
    """The trace rows of `channel`, the initial row (level 0 at start-up) first.

    Only complete lines are read: the writer may be in the middle of a row.
    """
    text = proc.trace_text()
    lines = text.split("\n")[:-1]  # the last element is '' or an incomplete line
    if not lines:
        return []
    header = lines[0].split(",")
    edges = []
    for line in lines[1:]:
        row = dict(zip(header, line.split(",")))
        if row.get("channel") != channel:
            continue
        edges.append(
            Edge(
                t_ns=int(row["t_ns"]),
                level=int(row["level"]),
                scheduled_ns=int(row["scheduled_ns"]),
            )
        )
    return edges


def wait_trace(
    proc: ManagedProcess,
    predicate: Callable[[list[Edge]], Any],
    what: str,
    channel: str = "pw01",
    timeout: Optional[float] = None,
    spin: Optional[Callable[[float], None]] = None,
) -> list[Edge]:
    """Polls the trace until `predicate(edges of channel)` holds; returns those edges.

    Fails at once if the node exits. `spin` (a RosClient's spin_once) keeps ROS moving while
    waiting."""
    found: list[list[Edge]] = []

    def check() -> bool:
        if not proc.is_running():
            raise AssertionError(
                f"node exited ({proc.returncode}) while waiting for {what}\n" + proc.output()
            )
        edges = trace_edges(proc, channel)
        if predicate(edges):
            found.append(edges)
            return True
        return False

    wait_until(check, f"{what} in the {channel} trace", timeout, spin=spin)
    return found[0]


def after(edges: Sequence[Edge], t_ns: int) -> list[Edge]:
    """The edges scheduled at or after `t_ns`."""
    return [e for e in edges if e.scheduled_ns >= t_ns]


def pulses(edges: Sequence[Edge]) -> list[tuple[Edge, Edge]]:
    """(rising, falling) pairs of complete pulses, in order."""
    out = []
    for a, b in zip(edges, edges[1:]):
        if a.level == 1 and b.level == 0:
            out.append((a, b))
    return out


# ---------------------------------------------------------------------------------------------
# One channel over ROS
# ---------------------------------------------------------------------------------------------


@dataclass
class Sent:
    """A command as the test sent it: the node handled it at some instant in
    [first_publish_ns, confirmed_ns] (monotonic ns), and `reply` is the message that confirmed
    it."""

    first_publish_ns: int
    confirmed_ns: int
    reply: Any
    #: Index of `reply` in the log it came from.
    index: int


class ChannelClient:
    """The topics of one channel (`pw01`, ...) of the node, from an rclpy node."""

    def __init__(self, ros: RosClient, channel: str = "pw01", node: str = NODE) -> None:
        self.ros = ros
        self.channel = channel
        self.number = int(channel[2:])
        base = f"{node}/{channel}"
        self.duty_pub = ros.publisher(Float64, f"{base}/duty")
        self.sv_pub = ros.publisher(UInt16, f"{base}/sv")
        self.enable_pub = ros.publisher(Bool, f"{base}/enable")
        self.edges = ros.subscribe(OutputEdge, f"{base}/edges", 100)
        self.status = ros.subscribe(ChannelStatus, f"{base}/status", 100)
        self.e1 = ros.subscribe(Bool, f"{base}/e1", E1_QOS)
        self.diagnostics = ros.subscribe(DiagnosticArray, "/diagnostics", 100)
        self.diag_name = f"{node.rsplit('/', 1)[-1]}: {channel}"

    def wait_connected(self, timeout: Optional[float] = None) -> None:
        """Waits until every input is matched with the node's subscription and every output
        log with the node's publisher, and a first status has arrived."""
        for pub in (self.duty_pub, self.sv_pub, self.enable_pub):
            self.ros.wait_for_subscribers(pub, 1, timeout)
        for log in (self.edges, self.status, self.e1, self.diagnostics):
            log.wait_for_publishers(1, timeout)
        self.status.wait_for(timeout=timeout, what=f"a first {self.channel} status")

    # -- inputs ----------------------------------------------------------------------------

    def send(
        self,
        publisher: Any,
        msg: Any,
        log: MessageLog,
        confirm: Callable[[Any], bool],
        what: str,
        resend_s: float = 2.0,
        timeout: Optional[float] = None,
    ) -> Sent:
        """Publishes `msg` and waits for a message on `log`, received after the publish, that
        satisfies `confirm`. Publishes again every `resend_s` in case the first one preceded
        matching on the node's side (commands are idempotent)."""
        start = len(log.messages)
        first = mono_ns()
        publisher.publish(msg)
        next_send = [time.monotonic() + resend_s]

        def step() -> Optional[int]:
            for i in range(start, len(log.messages)):
                if confirm(log.messages[i]):
                    return i + 1  # truthy even for index 0
            if time.monotonic() >= next_send[0]:
                publisher.publish(msg)
                next_send[0] = time.monotonic() + resend_s
            return None

        index = self.ros.spin_until(step, what, timeout) - 1
        return Sent(first, arrival_ns(log, index), log.messages[index], index)

    def duty(self, percent: float, confirm: Optional[Callable[[Any], bool]] = None) -> Sent:
        """Commands `percent` on `~/<ch>/duty`; confirmed by a status showing it commanded
        (or by `confirm` on the status)."""
        if confirm is None:

            def confirm(s: ChannelStatus) -> bool:
                return math.isclose(s.duty_commanded, percent, abs_tol=1e-9)

        return self.send(
            self.duty_pub,
            Float64(data=float(percent)),
            self.status,
            confirm,
            f"{self.channel} status confirming duty {percent} %",
        )

    def sv(self, value: int, confirm: Callable[[Any], bool]) -> Sent:
        """Commands raw SV `value` on `~/<ch>/sv`; confirmed by `confirm` on the status."""
        return self.send(
            self.sv_pub,
            UInt16(data=value),
            self.status,
            confirm,
            f"{self.channel} status confirming SV {value}",
        )

    def enable(self, on: bool) -> Sent:
        """Sets EN on `~/<ch>/enable`; confirmed by a status showing it."""
        return self.send(
            self.enable_pub,
            Bool(data=on),
            self.status,
            lambda s: s.enabled == on,
            f"{self.channel} status confirming enabled={on}",
        )

    # -- outputs ---------------------------------------------------------------------------

    def wait_status(
        self,
        predicate: Callable[[ChannelStatus], bool],
        what: str,
        start: int = 0,
        timeout: Optional[float] = None,
    ) -> ChannelStatus:
        return self.status.wait_for(predicate, timeout, start, f"{self.channel} status: {what}")

    def my_diag(self, array: DiagnosticArray) -> Optional[DiagnosticStatus]:
        """This channel's status in a DiagnosticArray, if present."""
        for s in array.status:
            if s.name == self.diag_name:
                return s
        return None

    def wait_diag(
        self,
        predicate: Callable[[DiagnosticStatus], bool],
        what: str,
        start: int = 0,
        timeout: Optional[float] = None,
    ) -> DiagnosticStatus:
        """The first diagnostics status of this channel (from message `start` on) satisfying
        `predicate`."""

        def matches(array: DiagnosticArray) -> bool:
            s = self.my_diag(array)
            return s is not None and predicate(s)

        array = self.diagnostics.wait_for(
            matches, timeout, start, f"/diagnostics for {self.diag_name}: {what}"
        )
        found = self.my_diag(array)
        assert found is not None
        return found

    def e1_state(self, timeout: Optional[float] = None) -> bool:
        """The latest E1 received (waits for a first one)."""
        self.e1.wait_for(timeout=timeout, what=f"a {self.channel}/e1 message")
        return bool(self.e1.messages[-1].data)

    def wait_e1(self, value: bool, what: str, timeout: Optional[float] = None) -> None:
        """Waits until the latest E1 received is `value`."""
        self.ros.spin_until(
            lambda: self.e1.messages and bool(self.e1.messages[-1].data) == value,
            f"{self.channel}/e1 = {value} ({what})",
            timeout,
        )

    def spin_for(self, seconds: float) -> None:
        self.ros.spin_for(seconds)


def node_args(**params: Any) -> list[str]:
    """`--ros-args -p pw01.period_ms:=200 ...` from keyword arguments named `pw01__period_ms`
    (a double underscore stands for the dot)."""
    args = ["--ros-args"]
    for key, value in params.items():
        name = key.replace("__", ".")
        if isinstance(value, bool):
            text = "true" if value else "false"
        else:
            text = str(value)
        args += ["-p", f"{name}:={text}"]
    return args


__all__ = [
    "E1_QOS",
    "MS",
    "NODE",
    "WRITE_TOL_NS",
    "CLOCK_TOL_NS",
    "ChannelClient",
    "Edge",
    "Sent",
    "after",
    "arrival_ns",
    "diag_level",
    "diag_values",
    "mono_ns",
    "node_args",
    "pulses",
    "t_on_ns",
    "trace_edges",
    "wait_trace",
]
