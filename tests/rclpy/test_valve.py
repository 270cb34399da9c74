"""A three-point valve from outside: an rclpy client sets `~/valve/mix/position`
(std_msgs/Float64), reads `~/valve/mix/state` (pwm_actuator_msgs/ValveState) and /diagnostics,
and checks the node's CSV trace of the two lines.

- the reference at start closes for 150 % of the closing travel time, then the valve is
  referenced at 0 %;
- each position is reached within one minimum pulse of the target (the trace's drive times over
  the travel times) and the state reports the same estimate;
- on the trace: the two lines are never on together, and a line rises only after both were off
  for the reversal pause;
- a refused `valve` or valve parameter stops the node with exit code 2 and the reason.
"""

from __future__ import annotations

import math

from diagnostic_msgs.msg import DiagnosticArray
from pwm_actuator_msgs.msg import ValveState
from std_msgs.msg import Float64

from helpers_rules import MS, NODE, diag_level, diag_values, node_args, stamp_ns, trace_edges

TRAVEL_OPEN_MS = 2000
TRAVEL_CLOSE_MS = 1600
MIN_PULSE_MS = 50
PAUSE_MS = 100
OK = 0

VALVE = dict(
    channels=2,
    valve="mix:pw01:pw02",
    mix__travel_open_ms=TRAVEL_OPEN_MS,
    mix__travel_close_ms=TRAVEL_CLOSE_MS,
    mix__min_pulse_ms=MIN_PULSE_MS,
    mix__reversal_pause_ms=PAUSE_MS,
    mix__deadband_pct=0.5,
    mix__end_overrun_pct=10.0,
    # 10 % of the run time over the travel time grows past 20 % over this test's strokes.
    mix__max_uncertainty_pct=50.0,
)


def drive_integral(open_edges, close_edges) -> float:
    """The position the lines' real drive times give, clamped to the stroke, percent."""
    spans = []
    for edges, sign, travel_ms in (
        (open_edges, 1.0, TRAVEL_OPEN_MS),
        (close_edges, -1.0, TRAVEL_CLOSE_MS),
    ):
        rose = None
        for e in edges:
            if e.level == 1:
                rose = e.t_ns
            elif rose is not None:
                spans.append((e.t_ns, sign * (e.t_ns - rose) / (travel_ms * MS) * 100.0))
                rose = None
    pos = 0.0
    for _, delta in sorted(spans):
        pos = min(100.0, max(0.0, pos + delta))
    return pos


def test_a_valve_references_follows_positions_and_keeps_its_lines_apart(node_process, ros):
    proc = node_process(node_args(**VALVE))
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    diags = ros.subscribe(DiagnosticArray, "/diagnostics")
    pub = ros.publisher(Float64, f"{NODE}/valve/mix/position")
    ros.wait_for_subscribers(pub, 1)

    # The reference: 150 % of 1.6 s closing.
    states.wait_for(lambda s: s.referenced and s.motion == "stopped", timeout=20.0)

    one_pulse = MIN_PULSE_MS / min(TRAVEL_OPEN_MS, TRAVEL_CLOSE_MS) * 100.0
    last = states.messages[-1]
    for target in (40.0, 70.0, 20.0, 26.0, 0.0, 55.0):
        start = len(states.messages)
        moves = last.moves
        pub.publish(Float64(data=target))
        # Each target needs a move; once it is done the estimate is within the dead band or one
        # minimum pulse of the target.
        last = states.wait_for(
            lambda s, t=target, m=moves: s.target_pct == t
            and s.motion == "stopped"
            and s.moves > m
            and abs(s.position_pct - t) <= max(0.5, one_pulse) + 0.2,
            start=start,
            timeout=20.0,
            what=f"the valve at {target} %",
        )
    assert last.referenced and last.activity == "tracking", last
    # The snapshot sent with the last fall is followed at once by one whose estimate counts the
    # fall's real write time: once the valve has settled, the newest state is the one the
    # diagnostics judge by, and a status stamped after it shows the same figures.
    ros.spin_for(0.5)
    last = states.messages[-1]
    assert last.motion == "stopped" and last.target_pct == 55.0, last
    settled = stamp_ns(last.stamp)
    status = diags.wait_for(
        lambda a: stamp_ns(a.header.stamp) > settled
        and any(s.name.endswith("valve mix") for s in a.status),
        timeout=10.0,
    )
    mine = [s for s in status.status if s.name.endswith("valve mix")][0]
    assert diag_level(mine) == OK, mine
    assert float(diag_values(mine)["uncertainty_pct"]) == round(last.uncertainty_pct, 2), mine

    code = proc.terminate()
    assert code == 0, proc.output()
    open_edges = trace_edges(proc, "pw01")
    close_edges = trace_edges(proc, "pw02")
    rows = sorted(
        [(e.t_ns, "pw01", e.level) for e in open_edges]
        + [(e.t_ns, "pw02", e.level) for e in close_edges]
    )
    high = {"pw01": 0, "pw02": 0}
    fell = None
    rises = 0
    for t, ch, level in rows:
        if level == 1 and high[ch] == 0:
            rises += 1
            other = "pw02" if ch == "pw01" else "pw01"
            assert high[other] == 0, f"{ch} rose at {t} while {other} was on"
            if fell is not None:
                assert t - fell >= PAUSE_MS * MS, f"{ch} rose {(t - fell) / MS:.1f} ms after a fall"
        if level == 0 and high[ch] == 1:
            fell = t
        high[ch] = level
    assert rises >= 7, rows
    # The state's estimate is the trace's drive times over the travel times (the trace records
    # each edge when its write returned, as the output thread reports it to the valve).
    integral = drive_integral(open_edges, close_edges)
    assert math.isclose(last.position_pct, integral, abs_tol=0.2), (last, integral)


def test_a_refused_valve_stops_the_node_with_the_reason(node_process):
    for params, reason in (
        (dict(channels=2, valve="mix:pw01:pw01"), "used twice"),
        (dict(channels=2, valve="mix:pw01:pw03"), "not a channel of this node"),
        (dict(channels=2, valve="mix:pw01:pw02", mix__travel_open_ms=10), "travel_open_ms"),
    ):
        proc = node_process(node_args(**params), name=f"refused-{len(reason)}")
        code = proc.wait_exit()
        assert code == 2, proc.output()
        assert reason in proc.output(), proc.output()
