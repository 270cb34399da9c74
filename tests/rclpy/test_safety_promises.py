"""The promises about the lines hold in every combination, and safety inputs always arrive, seen
from outside on the node's CSV trace:

- the two lines of a split-range pair are never high together, also when a pulse starts on a
  slot handed over under `max_simultaneous_on`, and when a managed node is activated with both
  channels of a pair running;
- with the output thread stopped (ptrace, as a stuck write or CPU starvation would stop it) while
  thousands of duty commands fill its request queue, an e-stop, a lowered
  `max_simultaneous_on` and a lifecycle shutdown still act on the lines, and nothing reports
  them done before they are;
- a parameter request as large as the input bound allows does not hold up the e-stop: with 99
  channels, the e-stop reaches the line within 100 ms while such a request is served.
"""

from __future__ import annotations

import ctypes
import os
import time
from pathlib import Path
from typing import Sequence

from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.srv import GetParameters, ListParameters
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool, Float64

from helpers_rules import (
    MS,
    NODE,
    ChannelClient,
    Edge,
    diag_level,
    diag_values,
    mono_ns,
    node_args,
    trace_edges,
)
from test_channel_rules import close_all_traces, observe_until, start
from test_estop import estop_publisher, release, reset

PAIR = ("pw01", "pw02")
#: The bound within which the output thread must take a safety input once the node has it, else
#: the outputs are switched off by the emergency handle (output_thread::SAFETY_TAKE_BOUND; the 250 ms
#: of docs/safety.md).
TAKE_BOUND_NS = 250 * MS
#: What the test allows on top of it for the input's way to the node: DDS delivery behind the
#: thousands of duty commands just published, on a loaded machine (docs/safety.md says so).
DELIVERY_NS = 100 * MS


def high_spans(edges: Sequence[Edge]) -> list[tuple[int, int]]:
    """[rise, fall) of every high run, by written time; a run still high at the end ends at
    the last row."""
    spans, rose = [], None
    for e in edges:
        if e.level == 1 and rose is None:
            rose = e.t_ns
        elif e.level == 0 and rose is not None:
            spans.append((rose, e.t_ns))
            rose = None
    if rose is not None:
        spans.append((rose, edges[-1].t_ns + 1))
    return spans


def overlaps(a: Sequence[Edge], b: Sequence[Edge]) -> list[tuple[int, int]]:
    """Intervals where both lines were high (a fall and a rise in one write do not overlap)."""
    found = []
    for r1, f1 in high_spans(a):
        for r2, f2 in high_spans(b):
            lo, hi = max(r1, r2), min(f1, f2)
            if lo < hi:
                found.append((lo, hi - lo))
    return found


def most_high_at_a_rise(traces: dict[str, list[Edge]], after_ns: int = 0) -> int:
    """The most lines high right after any rise written at or after `after_ns`."""
    rows = sorted(
        (e.t_ns, e.level, ch) for ch, edges in traces.items() for e in edges[1:]
    )
    high: dict[str, int] = {}
    most = 0
    i = 0
    while i < len(rows):
        # One write: every row with the same written time.
        j = i
        rose = False
        while j < len(rows) and rows[j][0] == rows[i][0]:
            _, level, ch = rows[j]
            rose |= level == 1 and not high.get(ch)
            high[ch] = level
            j += 1
        if rose and rows[i][0] >= after_ns:
            most = max(most, sum(high.values()))
        i = j
    return most


# ---------------------------------------------------------------------------------------------
# The output thread stopped from outside
# ---------------------------------------------------------------------------------------------

_libc = ctypes.CDLL(None, use_errno=True)
_libc.ptrace.argtypes = [ctypes.c_long, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p]
PTRACE_DETACH, PTRACE_SEIZE, PTRACE_INTERRUPT = 17, 0x4206, 0x4207
WALL = 0x40000000


def output_thread(pid: int) -> int:
    for tid in os.listdir(f"/proc/{pid}/task"):
        if Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip() == "pwm-output":
            return int(tid)
    raise AssertionError("no pwm-output thread")


class Stopped:
    """Stops one thread of another process (and only it) with ptrace until the block ends."""

    def __init__(self, pid: int) -> None:
        self.tid = output_thread(pid)

    def _ptrace(self, request: int) -> None:
        if _libc.ptrace(request, self.tid, None, None) != 0:
            raise OSError(ctypes.get_errno(), f"ptrace {request:#x} on {self.tid}")

    def __enter__(self) -> "Stopped":
        self._ptrace(PTRACE_SEIZE)
        self._ptrace(PTRACE_INTERRUPT)
        os.waitpid(self.tid, WALL)
        state = Path(f"/proc/{self.tid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        assert state == "t", f"output thread not stopped: state {state}"
        return self

    def __exit__(self, *exc: object) -> None:
        self._ptrace(PTRACE_DETACH)


def flood(ros, channel: str, count: int = 8000) -> None:
    """Publishes `count` duty commands in quick bursts (the node's reader keeps the last 10
    of a burst it has not taken yet), reliable with room for all on this side."""
    qos = QoSProfile(depth=count, reliability=ReliabilityPolicy.RELIABLE)
    pub = ros.publisher(Float64, f"{NODE}/{channel}/duty", qos)
    ros.wait_for_subscribers(pub, 1)
    ros.spin_for(0.25)
    for k in range(count):
        pub.publish(Float64(data=float(40 + k % 50)))
        if k % 8 == 7:
            time.sleep(0.0003)
    ros.spin_for(0.2)


def launch(node_process, ros, names: Sequence[str], count: int, **params):
    """Starts the node with `count` channels and `params`; connects to the channels `names`."""
    proc = node_process(node_args(**{"channels": count}, **params))
    clients = [ChannelClient(ros, ch) for ch in names]
    for c in clients:
        c.wait_connected()
    return (proc, *clients)


def rises_after(edges: Sequence[Edge], t_ns: int) -> list[Edge]:
    return [e for e in edges if e.level == 1 and e.t_ns > t_ns]


# ---------------------------------------------------------------------------------------------
# 1, 2: a split pair is never high together
# ---------------------------------------------------------------------------------------------


def test_a_pulse_started_on_a_slot_hand_over_never_overlaps_its_split_partner(node_process, ros):
    names = ("pw01", "pw02", "pw03", "pw04")
    periods = {f"{ch}__period_ms": 200 for ch in names}
    proc, a, b, c, d = launch(node_process, ros, names, 4, split="z:pw01:pw02",
                              max_simultaneous_on=2, **periods)
    for ch, duty in zip((a, b, c, d), (50.0, 20.0, 30.0, 40.0)):
        ch.duty(duty)
    c.enable(True)
    d.enable(True)
    ros.spin_for(0.02)
    a.enable(True)
    ros.spin_for(0.08)
    b.enable(True)
    observe_until(a, mono_ns() + 3000 * MS)
    traces = close_all_traces(proc, names)
    # pw03 and pw04 run; of the pair, a pulse lying wholly within its partner's is held by the
    # interlock until it has passed (reported missed).
    assert all(len(high_spans(traces[ch])) >= 10 for ch in ("pw03", "pw04")), traces
    assert len(high_spans(traces["pw01"])) + len(high_spans(traces["pw02"])) >= 10, traces
    assert overlaps(traces["pw01"], traces["pw02"]) == []
    assert most_high_at_a_rise(traces) <= 2


def test_activating_a_managed_node_never_raises_both_lines_of_a_pair(node_process, ros):
    params = {}
    for ch in PAIR:
        params |= {f"{ch}__period_ms": 200, f"{ch}__duty": 95.0, f"{ch}__enable": True}
    proc = node_process(["--managed"] + node_args(channels=2, split="z:pw01:pw02", **params))
    ch = ChannelClient(ros, "pw01")
    ch.wait_connected()

    def change(transition: int) -> None:
        req = ChangeState.Request(transition=Transition(id=transition))
        assert ros.call(ChangeState, f"{NODE}/change_state", req).success

    change(Transition.TRANSITION_CONFIGURE)
    split = ros.publisher(Float64, f"{NODE}/split/z/command")
    ros.wait_for_subscribers(split, 1)
    for k in range(6):
        # A sign flip of the split command while inactive, then the activation.
        split.publish(Float64(data=95.0 if k % 2 else -95.0))
        ros.spin_for(0.05 + 0.037 * k)
        change(Transition.TRANSITION_ACTIVATE)
        observe_until(ch, mono_ns() + 300 * MS)
        change(Transition.TRANSITION_DEACTIVATE)
    traces = close_all_traces(proc, PAIR)
    assert sum(len(high_spans(t)) for t in traces.values()) >= 6, traces
    assert overlaps(traces["pw01"], traces["pw02"]) == []


# ---------------------------------------------------------------------------------------------
# 3: safety inputs behind a full queue, the output thread stopped
# ---------------------------------------------------------------------------------------------


def high_at(edges: Sequence[Edge], t_ns: int) -> list[tuple[int, int]]:
    """The high span (by written time) that the line was in at `t_ns`: one, or none."""
    return [s for s in high_spans(edges) if s[0] <= t_ns < s[1]]


def test_an_estop_acts_while_the_output_thread_is_stopped_behind_a_full_queue(node_process, ros):
    # At 100 % the line is high when the e-stop comes: its fall is the e-stop's.
    proc, ch = start(node_process, ros, pw01__period_ms=100, pw01__duty=100.0)
    estop = estop_publisher(ros)
    ch.enable(True)
    observe_until(ch, mono_ns() + 300 * MS)
    with Stopped(proc.pid):
        flood(ros, "pw01")
        pressed = mono_ns()
        estop.publish(Bool(data=True))
        ros.spin_for(1.5)
    observe_until(ch, mono_ns() + 1500 * MS)
    out = proc.output()
    d = ch.wait_diag(lambda d: diag_values(d).get("estop_latched") == "true", "latched",
                     timeout=5.0)
    traces = close_all_traces(proc, ["pw01"])
    edges = traces["pw01"]
    assert "queue full" in out, "the queue did not fill:\n" + out[-2000:]
    # High at the press, off within the bound (the emergency handle), and no rise after it.
    assert rises_after(edges, pressed) == [], edges[-10:]
    assert edges[-1].level == 0
    span = high_at(edges, pressed)
    assert len(span) == 1, f"the line was not high at the press: {edges[-10:]}"
    off_ms = (span[0][1] - pressed) / MS
    print(f"e-stop with the output thread stopped: line off {off_ms:.1f} ms after the press")
    assert span[0][1] <= pressed + TAKE_BOUND_NS + DELIVERY_NS, off_ms
    assert "emergency handle" in out, out[-2000:]
    assert diag_level(d) == 2, d


def test_a_lowered_limit_acts_while_the_output_thread_is_stopped_behind_a_full_queue(
    node_process, ros
):
    names = ("pw01", "pw02")
    # At 100 % both lines are high when the limit is lowered: their falls are the limit's.
    proc, a, b = launch(node_process, ros, names, 2, pw01__period_ms=100,
                        pw02__period_ms=100, pw01__duty=100.0, pw02__duty=100.0)
    a.enable(True)
    b.enable(True)
    # The parameter client made before the stop (the first call makes it).
    assert ros.set_parameters(NODE, {"max_simultaneous_on": 0})["max_simultaneous_on"].successful
    observe_until(a, mono_ns() + 300 * MS)
    with Stopped(proc.pid):
        flood(ros, "pw01")
        lowered = mono_ns()
        response = ros.set_parameters(NODE, {"max_simultaneous_on": 1})["max_simultaneous_on"]
        answered = mono_ns()
    observe_until(a, mono_ns() + 1500 * MS)
    traces = close_all_traces(proc, names)
    assert response.successful, response
    # Not answered before the bound: the thread was stopped, and the answer waited for it.
    assert answered - lowered >= TAKE_BOUND_NS - 10 * MS, (answered - lowered) / MS
    # Both high when it was lowered, both off within the bound (the emergency handle, which
    # latches the output: nothing rises after it).
    for name, edges in traces.items():
        span = high_at(edges, lowered)
        assert len(span) == 1, f"{name} was not high when the limit was lowered: {edges[-10:]}"
        off_ms = (span[0][1] - lowered) / MS
        assert span[0][1] <= lowered + TAKE_BOUND_NS + DELIVERY_NS, (name, off_ms)
        assert rises_after(edges, lowered) == [], (name, edges[-10:])
        assert edges[-1].level == 0, (name, edges[-10:])
    assert "emergency handle" in proc.output(), "the emergency handle did not act"


def test_a_lifecycle_shutdown_acts_while_the_output_thread_is_stopped(node_process, ros):
    # At 100 % the line is high when the shutdown is asked for: its fall is the shutdown's.
    proc = node_process(
        ["--managed"] + node_args(pw01__period_ms=100, pw01__duty=100.0, pw01__enable=True)
    )
    ch = ChannelClient(ros, "pw01")
    ch.wait_connected()
    for t in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
        req = ChangeState.Request(transition=Transition(id=t))
        assert ros.call(ChangeState, f"{NODE}/change_state", req).success
    observe_until(ch, mono_ns() + 400 * MS)
    with Stopped(proc.pid):
        flood(ros, "pw01")
        asked = mono_ns()
        req = ChangeState.Request(transition=Transition(id=Transition.TRANSITION_ACTIVE_SHUTDOWN))
        done = ros.call(ChangeState, f"{NODE}/change_state", req)
    observe_until(ch, mono_ns() + 1000 * MS)
    edges = close_all_traces(proc, ["pw01"])["pw01"]
    assert done.success, done
    assert rises_after(edges, asked) == [], edges[-10:]
    assert edges[-1].level == 0
    span = high_at(edges, asked)
    assert len(span) == 1, f"the line was not high when the shutdown was asked: {edges[-10:]}"
    assert span[0][1] <= asked + TAKE_BOUND_NS + DELIVERY_NS, (span[0][1] - asked) / MS


# ---------------------------------------------------------------------------------------------
# 4: no parameter request holds up the e-stop
# ---------------------------------------------------------------------------------------------


def test_the_estop_reaches_the_line_at_once_while_a_huge_parameter_request_is_served(
    node_process, ros
):
    proc, ch = launch(node_process, ros, ["pw01"], 99, pw01__period_ms=1000, pw01__duty=100.0)
    estop = estop_publisher(ros)
    lister = ros.node.create_client(ListParameters, f"{NODE}/list_parameters")
    getter = ros.node.create_client(GetParameters, f"{NODE}/get_parameters")
    ros.spin_until(lambda: lister.service_is_ready() and getter.service_is_ready(), "services")
    ros.spin_for(0.25)
    assert reset(ros).success
    delays = []
    for _ in range(3):
        ch.enable(True)
        observe_until(ch, mono_ns() + 300 * MS)
        # 32,000 empty prefixes: about 256 KB, inside the input bound.
        listed = lister.call_async(ListParameters.Request(prefixes=[""] * 32_000, depth=0))
        got = getter.call_async(GetParameters.Request(names=["pw01.period_ms"] * 2_000))
        ros.spin_for(0.5)
        pressed = mono_ns()
        estop.publish(Bool(data=True))
        ch.wait_status(lambda s: not s.enabled, "disabled by the e-stop",
                       start=len(ch.status.messages))
        ros.spin_until(lambda: listed.done() and got.done(), "parameter answers", 10.0)
        assert release(ros, estop).success
        falls = [e for e in trace_edges(proc) if e.level == 0 and e.t_ns >= pressed]
        assert falls, trace_edges(proc)[-5:]
        delays.append((falls[0].t_ns - pressed) / MS)
    close_all_traces(proc, ["pw01"])
    print(f"e-stop to line with a 32,000-prefix list_parameters in flight: {delays} ms")
    assert max(delays) < 100, delays


def test_services_waiting_for_a_stopped_output_thread_hold_up_no_other_endpoint(node_process, ros):
    """Three `reset_fault` calls wait for the output thread's verdict (up to 1 s each) while the
    thread is stopped: more waiting handlers than the node has async workers (2). The node's
    other endpoints are served meanwhile: `get_parameters` answers at once, not after them."""
    from std_srvs.srv import Trigger

    names = ("pw01", "pw02", "pw03")
    # Heaters (the reset is theirs), reading nothing: each latches its sensor timeout.
    heaters = {f"{ch}__feedback_topic": f"/heater_{ch}/temperature" for ch in names}
    proc, *_ = launch(node_process, ros, names, 3, **heaters)
    clients = [ros.node.create_client(Trigger, f"{NODE}/{ch}/reset_fault") for ch in names]
    for c in clients:
        ros.spin_until(c.service_is_ready, "reset_fault", 10.0)
    # Every client made and matched before the stop (the first call makes the parameter one).
    ros.get_parameters(NODE, ["status_rate_hz"])
    ros.spin_for(0.25)
    with Stopped(proc.pid):
        resets = [c.call_async(Trigger.Request()) for c in clients]
        # The three handlers are now waiting for the stopped thread.
        ros.spin_for(0.2)
        asked = time.monotonic()
        ros.get_parameters(NODE, ["status_rate_hz"], timeout=5.0)
        took = time.monotonic() - asked
        ros.spin_until(lambda: all(f.done() for f in resets), "the resets' answers", 10.0)
    answers = [f.result() for f in resets]
    print(f"get_parameters beside three waiting resets: {took * 1000:.0f} ms")
    for a in answers:
        assert not a.success and "no answer from the output thread" in a.message, a
    assert took < 0.5, f"get_parameters waited {took:.2f} s behind the resets"
