"""A valve that is where it says it is, checked against `pwm_actuator_node sim-valve` as a ROS
user would: the node's state and /diagnostics beside the simulated actuator's true position.

- Unreferenced (`reference_at_start: none`) with the valve truly 63 % open, a 0 % command
  drives the full 150 % of the closing travel time and leaves the true valve at 0 %.
- A stalled motor with a position feedback is `motor_stalled` within the bound the node
  derives (start lag and its tolerance, twice the stall distance and the play at the slowest
  travel, the feedback's delay, one sample): ERROR on /diagnostics with the figures, both
  lines off, and `~/valve/mix/reset` clears it.
- Killed (SIGKILL) mid-move and restarted with `reference_at_start: skip_if_restored`: no
  reference stroke, the true position within the restored uncertainty, and the first rise only
  once the reversal pause from the restart has passed.
"""

from __future__ import annotations

import signal

from diagnostic_msgs.msg import DiagnosticArray
from pwm_actuator_msgs.msg import OutputEdge, ValveState
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from helpers_rules import MS, NODE, diag_level, diag_values, node_args, stamp_ns, trace_edges

WARN, ERROR = 1, 2


def valve_diagnostics(ros, diags, pred=lambda s: True, timeout=10.0):
    """The next `<node>: valve mix` status on /diagnostics for which `pred` holds."""

    def mine(a):
        return [s for s in a.status if s.name.endswith("valve mix") and pred(s)]

    found = diags.wait_for(lambda a: mine(a), start=len(diags.messages), timeout=timeout,
                           what="the valve's diagnostics")
    return mine(found)[0]


def sim_valve(node_process, *args, name="sim"):
    return node_process(
        ["sim-valve", "--rate-hz", "50", *[str(a) for a in args]],
        output=None,
        trace=False,
        name=name,
    )


def standing_truth(ros, truth, timeout=10.0) -> float:
    """The simulated valve's position once two samples in a row agree."""
    n = len(truth.messages)
    truth.wait_for(
        lambda m: truth.messages[-2].data == truth.messages[-1].data,
        start=n + 2,
        timeout=timeout,
        what="the simulated valve standing",
    )
    return truth.messages[-1].data


def test_an_unreferenced_valve_at_63_percent_closes_fully_on_a_0_percent_command(
    node_process, ros
):
    travel_ms = 1000
    node = node_process(
        node_args(
            channels=2,
            valve="mix:pw01:pw02",
            mix__travel_open_ms=travel_ms,
            mix__travel_close_ms=travel_ms,
            mix__reversal_pause_ms=50,
            mix__reference_at_start="none",
        )
    )
    # The true travel 10 % slow: the hardest case for reaching the end.
    sim = sim_valve(node_process, "--travel-open-ms", 1100, "--travel-close-ms", 1100,
                    "--start-pct", 63)
    truth = ros.subscribe(Float64, "/sim_valve/position")
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    diags = ros.subscribe(DiagnosticArray, "/diagnostics")
    pub = ros.publisher(Float64, f"{NODE}/valve/mix/position")
    ros.wait_for_subscribers(pub, 1)
    # Matched both ways before the first wait: a discovery that is slow shows as such, not as
    # /diagnostics missing.
    diags.wait_for_publishers(1)
    first = valve_diagnostics(ros, diags, timeout=20.0)
    values = diag_values(first)
    assert diag_level(first) == WARN and "unreferenced" in first.message, first
    assert values["position_pct"] == "0.00" and values["uncertainty_pct"] == "100.00", values
    assert abs(standing_truth(ros, truth) - 63.0) < 1e-6
    start = len(states.messages)
    pub.publish(Float64(data=0.0))
    done = states.wait_for(
        lambda s: s.motion == "stopped" and s.referenced and s.moves >= 1,
        start=start,
        timeout=20.0,
        what="the valve referenced at the closed end",
    )
    assert done.position_pct == 0.0 and done.uncertainty_pct == 0.0, done
    true_pct = standing_truth(ros, truth)
    assert true_pct == 0.0, f"the valve stayed {true_pct} % open"
    assert node.terminate() == 0, node.output()
    close_edges = trace_edges(node, "pw02")
    drives = [
        (b.t_ns - a.t_ns)
        for a, b in zip(close_edges, close_edges[1:])
        if a.level == 1 and b.level == 0
    ]
    # The whole 150 % (the unreferenced valve could have been fully open), never more.
    assert len(drives) == 1 and 1.5 * travel_ms * MS <= drives[0] < 1.5 * travel_ms * MS + 50 * MS, drives
    assert sim.terminate() == 0, sim.output()


def test_a_stalled_motor_is_motor_stalled_within_the_derived_bound(node_process, ros):
    travel_ms, lag_ms, backlash, rate_hz = 2000, 150, 1.0, 50
    node = node_process(
        node_args(
            channels=2,
            valve="mix:pw01:pw02",
            mix__travel_open_ms=travel_ms,
            mix__travel_close_ms=travel_ms,
            mix__reversal_pause_ms=50,
            mix__start_lag_ms=lag_ms,
            mix__backlash_pct=backlash,
            mix__reference_at_start="none",
            mix__feedback_topic="/sim_valve/feedback",
            mix__feedback_tolerance_pct=1.0,
        )
    )
    sim = sim_valve(node_process, "--travel-open-ms", travel_ms, "--travel-close-ms", travel_ms,
                    "--start-pct", 40, "--start-lag-ms", lag_ms, "--backlash-pct", backlash,
                    "--feedback-topic", "/sim_valve/feedback", "--feedback-noise-pct", 0.3,
                    "--stalled")
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    diags = ros.subscribe(DiagnosticArray, "/diagnostics")
    edges = ros.subscribe(OutputEdge, f"{NODE}/pw01/edges")
    pub = ros.publisher(Float64, f"{NODE}/valve/mix/position")
    ros.wait_for_subscribers(pub, 1)
    # The feedback references the valve at rest.
    states.wait_for(lambda s: s.referenced and abs(s.position_pct - 40.0) < 1.0, timeout=20.0,
                    what="the valve referenced by its feedback")
    start = len(states.messages)
    pub.publish(Float64(data=90.0))
    stalled = states.wait_for(lambda s: s.fault == "motor_stalled", start=start, timeout=10.0,
                              what="motor_stalled")
    assert stalled.motion == "stopped", stalled
    rise = edges.wait_for(lambda e: e.level, timeout=5.0)
    # The bound: after the rise, the configured lag; then the drive that moves a healthy valve
    # 4 % (twice the 2 % it must see) plus the play at a travel 10 % slow, plus the lag's
    # tolerance (half of it and 20 ms); then the feedback's delay (500 ms) and one sample.
    bound_ms = lag_ms + (4.0 + backlash) / 100 * travel_ms * 1.1 + (0.5 * lag_ms + 20) + 500 + 1000 / rate_hz
    took_ms = (stamp_ns(stalled.stamp) - stamp_ns(rise.stamp)) / MS
    # Transport and a loaded machine: 300 ms on top.
    assert took_ms <= bound_ms + 300, (took_ms, bound_ms)
    print(f"motor_stalled {took_ms:.0f} ms after the rise; derived bound {bound_ms:.0f} ms")
    mine = valve_diagnostics(ros, diags, lambda s: diag_level(s) == ERROR)
    assert mine.message.startswith("motor_stalled: ") and "moved the feedback" in mine.message, mine
    assert "~/valve/mix/reset" in mine.message, mine
    # Latched: a new command drives nothing.
    n = len(edges.messages)
    pub.publish(Float64(data=10.0))
    ros.spin_for(1.0)
    assert not any(e.level for e in edges.messages[n:]), edges.messages[n:]
    before_reset = len(states.messages)
    response = ros.call(Trigger, f"{NODE}/valve/mix/reset", Trigger.Request(), timeout=10.0)
    assert response.success and "motor_stalled cleared" in response.message, response
    cleared = states.wait_for(lambda s: s.fault == "", start=before_reset, timeout=5.0)
    assert cleared.motion == "stopped", cleared
    assert node.terminate() == 0, node.output()
    assert "motor_stalled" in node.output()
    assert sim.terminate() == 0, sim.output()


def test_killed_mid_move_the_restart_restores_without_a_stroke(node_process, ros, tmp_path):
    travel_ms, pause_ms = 8000, 3000
    state_dir = tmp_path / "state"
    state_dir.mkdir()
    params = dict(
        channels=2,
        valve="mix:pw01:pw02",
        state_dir=str(state_dir),
        mix__travel_open_ms=travel_ms,
        mix__travel_close_ms=travel_ms,
        mix__reversal_pause_ms=pause_ms,
        mix__reference_at_start="skip_if_restored",
        # The restored bounds are wide after a kill: no recalibration through an end for them.
        mix__max_uncertainty_pct=60.0,
    )
    sim = sim_valve(node_process, "--travel-open-ms", travel_ms * 1.05,
                    "--travel-close-ms", travel_ms * 0.95, "--start-pct", 20)
    truth = ros.subscribe(Float64, "/sim_valve/position")
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    pub = ros.publisher(Float64, f"{NODE}/valve/mix/position")
    first = node_process(node_args(**params), name="first")
    ros.wait_for_subscribers(pub, 1)
    # No state file yet: the reference at start closes (150 % of 8 s).
    states.wait_for(lambda s: s.referenced and s.motion == "stopped" and not s.restored,
                    timeout=30.0, what="the first reference")
    assert (state_dir / "mix.state").exists()
    start = len(states.messages)
    pub.publish(Float64(data=80.0))
    states.wait_for(lambda s: s.motion == "opening", start=start, timeout=10.0)
    ros.spin_for(2.5)
    first.send_signal(signal.SIGKILL)
    first.wait_exit(timeout=10.0)
    # What safe-off does after a kill (the unit runs it): the lines go off. The simulated output
    # cannot, so the falls are published for the simulated actuator as the node would have.
    stamp = ros.node.get_clock().now().to_msg()
    edge_pub = {ch: ros.publisher(OutputEdge, f"{NODE}/{ch}/edges") for ch in ("pw01", "pw02")}
    for ch, p in edge_pub.items():
        ros.wait_for_subscribers(p, 1)
        p.publish(OutputEdge(stamp=stamp, channel=1 if ch == "pw01" else 2, level=False, seq=0,
                             lateness_ns=0))
    true_pct = standing_truth(ros, truth)
    assert 25.0 < true_pct < 80.0, true_pct
    ros.spin_for(0.5)

    states.messages.clear()
    diags = ros.subscribe(DiagnosticArray, "/diagnostics")
    second = node_process(node_args(**params), name="second")
    restored = valve_diagnostics(ros, diags, timeout=20.0)
    values = {k: float(v) for k, v in diag_values(restored).items()
              if k in ("position_pct", "uncertainty_pct", "position_low_pct", "position_high_pct")}
    # A command at once, before the reversal pause from the restart has passed.
    target = values["position_pct"] - 15.0
    pub.publish(Float64(data=target))
    assert diag_values(restored)["restored"] == "true", restored
    assert abs(true_pct - values["position_pct"]) <= values["uncertainty_pct"], (true_pct, values)
    assert values["position_low_pct"] <= true_pct <= values["position_high_pct"], values
    print(f"true {true_pct:.2f} %, restored {values['position_pct']:.2f} % ± "
          f"{values['uncertainty_pct']:.2f} %")
    moved = states.wait_for(lambda s: s.motion == "stopped" and s.moves >= 1 and
                            s.target_pct == target, timeout=20.0, what="the move to the target")
    assert abs(moved.position_pct - target) < 1.0, moved
    # No reference stroke: never referencing, one closing drive of about 15 % of the travel.
    assert all(s.activity == "tracking" for s in states.messages), states.messages
    assert second.terminate() == 0, second.output()
    edges = sorted(trace_edges(second, "pw01") + trace_edges(second, "pw02"), key=lambda e: e.t_ns)
    started = edges[0].t_ns
    rises = [e for e in edges if e.level == 1]
    falls = [e for e in edges if e.level == 0 and e.t_ns > rises[0].t_ns]
    assert len(rises) == 1, rises
    assert (falls[0].t_ns - rises[0].t_ns) < 0.2 * travel_ms * MS, (rises, falls)
    # The first rise only once the pause from the restart has passed.
    assert rises[0].t_ns >= started + pause_ms * MS, (started, rises[0])
    assert sim.terminate() == 0, sim.output()
