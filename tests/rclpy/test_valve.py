"""A three-point valve from outside: an rclpy client sets `~/valve/mix/position`
(std_msgs/Float64), reads `~/valve/mix/state` (pwm_actuator_msgs/ValveState) and /diagnostics,
and checks the node's CSV trace of the two lines.

- the reference at start closes for 150 % of the closing travel time, then the valve is
  referenced at 0 %;
- each position is reached within one minimum pulse of the target (the trace's drive times over
  the travel times) and the state reports the same estimate;
- on the trace: the two lines are never on together, and a line rises only after both were off
  for the reversal pause;
- a refused `valve` or valve parameter stops the node with exit code 2 and the reason;
- the e-stop and a lifecycle deactivate stop a moving valve with both lines off at once; after
  the reset it waits for a fresh command, after activation it resumes; at exit both are off;
- the motion settings change while running (set_parameters), the travel times do not;
- the valve's own loop (`control` `pid`): its parameters checked, it follows a process value,
  holds when the readings stop, and `~/valve/mix/state` and /diagnostics say so (`holding`, a
  WARN with the reading's age and the timeout); manual mode shows on both and a bad word is
  counted; with `safe_position_pct` the valve goes there after `safe_after_ms`.
"""

from __future__ import annotations

import math

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.msg import Transition
from pwm_actuator_msgs.msg import ValveState
from std_msgs.msg import Bool, Float64

from helpers_rules import (
    MS,
    NODE,
    diag_level,
    diag_values,
    mono_ns,
    node_args,
    stamp_ns,
    trace_edges,
)
from test_estop import release
from test_lifecycle import change

TRAVEL_OPEN_MS = 2000
TRAVEL_CLOSE_MS = 1600
MIN_PULSE_MS = 50
PAUSE_MS = 100
BACKLASH_PCT = 1.0
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
    mix__backlash_pct=BACKLASH_PCT,
    # 10 % of the run time over the travel time grows past 20 % over this test's strokes.
    mix__max_uncertainty_pct=50.0,
)
#: The valve's loop in the loop tests: integral only, sampled every 100 ms, stale after 1 s,
#: no motor budget.
LOOP = dict(
    mix__pid_kp=0.0,
    mix__pid_ki=2.0,
    mix__pid_sample_ms=100,
    mix__process_timeout_ms=1000,
    mix__max_starts_per_h=0,
)


def assert_lines_apart(open_edges, close_edges) -> int:
    """Asserts on the trace that the two lines are never on together and that a line rises only
    after both were off for the reversal pause; returns the number of rises."""
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
    return rises


def drive_integral(open_edges, close_edges, top: float = 100.0) -> float:
    """The motor position the lines' real drive times give, clamped to 0..`top`, percent."""
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
        pos = min(top, max(0.0, pos + delta))
    return pos


def start_referenced(node_process, ros):
    """The node with the valve `mix`, logs of its state and /diagnostics, a publisher of its
    position; returns once the reference at start has ended."""
    proc = node_process(node_args(**VALVE))
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    diags = ros.subscribe(DiagnosticArray, "/diagnostics")
    pub = ros.publisher(Float64, f"{NODE}/valve/mix/position")
    ros.wait_for_subscribers(pub, 1)
    states.wait_for(lambda s: s.referenced and s.motion == "stopped", timeout=20.0)
    return proc, states, diags, pub


def test_a_valve_references_follows_positions_and_keeps_its_lines_apart(node_process, ros):
    # The reference: 150 % of 1.6 s closing.
    proc, states, diags, pub = start_referenced(node_process, ros)

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
    # docs/valve.md, the motor's budget: every rise of a line is a start, counted.
    assert diag_values(mine)["max_starts_per_h"] == "1200", mine
    starts = int(diag_values(mine)["starts"])
    # At rest /diagnostics goes out once a second (and at a change of level): the valve's
    # status counts among the levels compared, so it does not look changed at every wake-up.
    before = len(diags.messages)
    ros.spin_for(4.0)
    published = len(diags.messages) - before
    assert published <= 6, f"{published} /diagnostics messages in 4 s at rest"

    code = proc.terminate()
    assert code == 0, proc.output()
    open_edges = trace_edges(proc, "pw01")
    close_edges = trace_edges(proc, "pw02")
    rises = assert_lines_apart(open_edges, close_edges)
    assert rises >= 7, (open_edges, close_edges)
    assert starts == rises, (starts, rises)
    # The state's estimate is the trace's drive times over the travel times (the trace records
    # each edge when its write returned, as the output thread reports it to the valve), less
    # half the play: the motor's position runs 0..100 + backlash, the stem sits within the play.
    integral = drive_integral(open_edges, close_edges, top=100.0 + BACKLASH_PCT)
    want = integral - BACKLASH_PCT / 2
    assert math.isclose(last.position_pct, want, abs_tol=0.2), (last, integral)


@pytest.mark.untimed
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


def test_the_estop_and_deactivation_stop_a_moving_valve_and_leave_both_lines_off(
    node_process, ros
):
    """docs/valve.md: the e-stop and a managed node's inactive states drive both lines off at
    once and the valve stays where it is; after the e-stop's reset it waits for a fresh position
    command, after activation it resumes its move; at exit both lines are off."""
    proc = node_process(["--managed"] + node_args(**VALVE))
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    pub = ros.publisher(Float64, f"{NODE}/valve/mix/position")
    estop = ros.publisher(Bool, f"{NODE}/estop")
    ros.wait_for_subscribers(pub, 1)
    ros.wait_for_subscribers(estop, 1)
    assert change(ros, Transition.TRANSITION_CONFIGURE)
    assert change(ros, Transition.TRANSITION_ACTIVATE)
    # The reference at start runs once the node is active.
    states.wait_for(lambda s: s.referenced and s.motion == "stopped", timeout=20.0)

    def moving(target: float, motion: str) -> None:
        start = len(states.messages)
        pub.publish(Float64(data=target))
        states.wait_for(
            lambda s: s.target_pct == target and s.motion == motion,
            start=start,
            timeout=10.0,
            what=f"the valve {motion} towards {target} %",
        )
        ros.spin_for(0.3)

    # 1. The e-stop while opening: both lines off, the valve stops where it is.
    moving(100.0, "opening")
    start = len(states.messages)
    pressed = mono_ns()
    estop.publish(Bool(data=True))
    stopped = states.wait_for(lambda s: s.estop and s.motion == "stopped", start=start, timeout=5.0)
    assert 0.0 < stopped.position_pct < 100.0, stopped
    # Latched: a position command is taken, nothing moves.
    pub.publish(Float64(data=0.0))
    ros.spin_for(0.6)
    response = release(ros, estop)
    assert response.success, response
    # Released: nothing moves before a fresh command.
    ros.spin_for(0.6)
    assert all(s.motion == "stopped" for s in states.messages[start:]), states.messages[start:]
    fresh = mono_ns()

    # 2. Deactivation while opening: both lines off; activation resumes the move to the target.
    moving(90.0, "opening")
    start = len(states.messages)
    deactivated = mono_ns()
    assert change(ros, Transition.TRANSITION_DEACTIVATE)
    held = states.wait_for(lambda s: s.motion == "stopped", start=start, timeout=5.0)
    assert held.position_pct < 90.0 - 1.0, held
    ros.spin_for(0.6)
    # Only states sent after the activation count: the valve held short of 90 % is stopped too.
    resumed_from = len(states.messages)
    activated = mono_ns()
    assert change(ros, Transition.TRANSITION_ACTIVATE)
    states.wait_for(lambda s: s.motion == "opening", start=resumed_from, timeout=10.0,
                    what="the move resumed after activation")
    states.wait_for(
        lambda s: s.motion == "stopped" and abs(s.position_pct - 90.0) <= 3.0,
        start=resumed_from,
        timeout=10.0,
        what="the valve at 90 % after activation",
    )

    code = proc.terminate()
    assert code == 0, proc.output()
    open_edges = trace_edges(proc, "pw01")
    close_edges = trace_edges(proc, "pw02")
    assert_lines_apart(open_edges, close_edges)
    edges = sorted(open_edges + close_edges, key=lambda e: e.t_ns)

    def level_at(line_edges, t_ns: int) -> int:
        before = [e for e in line_edges if e.t_ns <= t_ns]
        return before[-1].level if before else 0

    for what, t_off, t_on in (("e-stop", pressed, fresh), ("deactivate", deactivated, activated)):
        # On when it came, off within half a second (milliseconds in practice) ...
        assert level_at(open_edges, t_off) == 1, (what, open_edges)
        falls = [e for e in open_edges if e.level == 0 and e.t_ns > t_off]
        assert falls and falls[0].t_ns <= t_off + 500 * MS, (what, falls[:1], t_off)
        # ... and no line rose until the fresh command or the activation.
        rises = [e for e in edges if e.level == 1 and t_off < e.t_ns < t_on]
        assert not rises, (what, rises)
    # The move resumed after activation, and every exit leaves both lines off.
    assert any(e.level == 1 and e.t_ns > activated for e in open_edges), open_edges
    assert open_edges[-1].level == 0 and close_edges[-1].level == 0


def test_the_motion_settings_change_while_running_the_travel_times_do_not(node_process, ros):
    """docs/valve.md: `ros2 param set` on a valve's motion settings acts at once (a wide dead
    band holds the valve, a narrow one moves it to the target in force, a lowered
    `max_uncertainty_pct` warns); a change the core refuses, or one of the travel times, is
    refused with the reason and changes nothing."""
    proc, states, diags, pub = start_referenced(node_process, ros)

    def set_one(name: str, value):
        return ros.set_parameters(NODE, {name: value})[name]

    # A 20 % dead band: a 10 % step does not move the valve.
    r = set_one("mix.deadband_pct", 20.0)
    assert r.successful, r.reason
    moves = states.messages[-1].moves
    start = len(states.messages)
    pub.publish(Float64(data=10.0))
    states.wait_for(lambda s: s.target_pct == 10.0, start=start, timeout=5.0)
    ros.spin_for(1.0)
    assert all(s.motion == "stopped" and s.moves == moves for s in states.messages[start:])
    # Back to 0.5 %: the valve goes to the target in force without a new command.
    start = len(states.messages)
    r = set_one("mix.deadband_pct", 0.5)
    assert r.successful, r.reason
    states.wait_for(
        lambda s: s.motion == "stopped" and s.moves > moves and abs(s.position_pct - 10.0) <= 3.5,
        start=start,
        timeout=10.0,
        what="the valve at 10 % once the dead band narrowed",
    )
    # A lower uncertainty limit than the estimate's: the diagnostics warn.
    r = set_one("mix.max_uncertainty_pct", 0.0)
    assert r.successful, r.reason
    start = len(diags.messages)
    status = diags.wait_for(
        lambda a: any(
            s.name.endswith("valve mix") and "above max_uncertainty_pct 0 %" in s.message
            for s in a.status
        ),
        start=start,
        timeout=10.0,
    )
    mine = [s for s in status.status if s.name.endswith("valve mix")][0]
    assert diag_level(mine) == 1, mine

    # Refused, with the reason, and nothing changes: a minimum pulse above the closing travel
    # time (the core's check of the valve's settings together), and the travel times.
    r = set_one("mix.min_pulse_ms", TRAVEL_CLOSE_MS + 100)
    assert not r.successful and r.reason.startswith("valve mix: min_pulse_ms"), r.reason
    r = set_one("mix.travel_open_ms", 3000)
    assert not r.successful and "restart the node" in r.reason, r.reason
    got = ros.get_parameters(NODE, ["mix.min_pulse_ms", "mix.travel_open_ms"])
    assert got == {"mix.min_pulse_ms": MIN_PULSE_MS, "mix.travel_open_ms": TRAVEL_OPEN_MS}, got
    assert proc.terminate() == 0, proc.output()


@pytest.mark.untimed
def test_the_loop_parameters_are_checked_and_pid_refuses_position_commands(node_process, ros):
    """docs/parameters.md: a valve's loop settings are bounded and checked with its others;
    `control` `pid` needs a process topic (read at start-up) and a gain, and under `pid` the
    position commands set nothing."""
    proc = node_process(
        node_args(**VALVE, mix__control="pid", mix__pid_kp=5.0), name="pid-without-process"
    )
    assert proc.wait_exit() == 2, proc.output()
    assert "needs a process_topic" in proc.output(), proc.output()

    proc = node_process(
        node_args(**VALVE, mix__control="pid", mix__process_topic="/supply", mix__pid_kp=5.0)
    )
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    pub = ros.publisher(Float64, f"{NODE}/valve/mix/position")
    ros.wait_for_subscribers(pub, 1)
    states.wait_for(lambda s: s.referenced and s.motion == "stopped", timeout=20.0)

    def set_one(name: str, value):
        return ros.set_parameters(NODE, {name: value})[name]

    start = len(states.messages)
    pub.publish(Float64(data=40.0))
    ros.spin_for(1.5)
    seen = states.messages[start:]
    assert seen and all(math.isnan(s.target_pct) and s.motion == "stopped" for s in seen), seen[-1]
    # Refused with the reason, and nothing changes: no gain left, a sample below 10 ms, another
    # process topic while running.
    r = ros.set_parameters(NODE, {"mix.pid_kp": 0.0})["mix.pid_kp"]
    assert not r.successful and "pid_kp or pid_ki above 0" in r.reason, r.reason
    r = set_one("mix.pid_sample_ms", 5)
    assert not r.successful, r.reason
    r = set_one("mix.process_topic", "/other")
    assert not r.successful and "restart the node" in r.reason, r.reason
    # Back to position: the commands set the target again.
    r = set_one("mix.control", "position")
    assert r.successful, r.reason
    start = len(states.messages)
    pub.publish(Float64(data=40.0))
    states.wait_for(lambda s: s.target_pct == 40.0, start=start, timeout=5.0)
    got = ros.get_parameters(NODE, ["mix.pid_kp", "mix.control"])
    assert got == {"mix.pid_kp": 5.0, "mix.control": "position"}, got
    assert proc.terminate() == 0, proc.output()


def test_the_loop_follows_its_process_value_holds_when_it_goes_stale_and_obeys_manual(
    node_process, ros
):
    """docs/valve.md: under `control` `pid` the valve follows its loop from the process value
    (`std_msgs/Float64` here) and `~/valve/NAME/setpoint`; with no fresh reading for
    `process_timeout_ms` it holds where it is; `~/valve/NAME/manual` (std_msgs/String) opens,
    stops and returns to automatic, and a bad word is refused while the node keeps running."""
    from std_msgs.msg import String

    proc = node_process(
        node_args(
            **VALVE,
            mix__control="pid",
            mix__process_topic="/supply",
            mix__process_type="float64",
            **LOOP,
        )
    )
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    process = ros.publisher(Float64, "/supply")
    setpoint = ros.publisher(Float64, f"{NODE}/valve/mix/setpoint")
    manual = ros.publisher(String, f"{NODE}/valve/mix/manual")
    for p in (process, setpoint, manual):
        ros.wait_for_subscribers(p, 1)
    states.wait_for(lambda s: s.referenced and s.motion == "stopped", timeout=20.0)
    closed = states.messages[-1].position_pct

    # 5 units below the setpoint, integral only (2 %/unit·s): the loop opens the valve.
    setpoint.publish(Float64(data=50.0))
    for _ in range(25):
        process.publish(Float64(data=45.0))
        ros.spin_for(0.1)
    opened = states.messages[-1].position_pct
    assert opened > closed + 5.0, (closed, opened)
    # No more readings: after process_timeout_ms the valve holds where it is.
    ros.spin_for(1.6)
    start = len(states.messages)
    held = states.messages[-1].position_pct
    ros.spin_for(2.0)
    later = states.messages[start:]
    assert later and all(
        s.motion == "stopped" and abs(s.position_pct - held) < 0.01 for s in later
    ), (held, later[-1])
    assert held < 100.0 - 5.0, held

    # Manual: open drives, stop stops, a bad word is refused, auto returns.
    start = len(states.messages)
    manual.publish(String(data="open"))
    states.wait_for(lambda s: s.motion == "opening", start=start, timeout=5.0)
    # From after the "opening" state on: a state published before the command came says
    # "stopped" too, at the held position.
    start = len(states.messages)
    manual.publish(String(data="stop"))
    stopped = states.wait_for(lambda s: s.motion == "stopped", start=start, timeout=5.0)
    assert stopped.position_pct > held, (held, stopped)
    manual.publish(String(data="wide open"))
    ros.spin_for(0.5)
    assert "manual command refused" in proc.output(), proc.output()
    manual.publish(String(data="auto"))
    ros.spin_for(0.5)
    assert proc.terminate() == 0, proc.output()


# Untimed (pytest.ini): readings 5 s old against a 1 s timeout move nothing; fresh ones, with a
# second to spare, open the valve by more than 5 % within 2.5 s where the loop's integral makes
# 25 % of them.
@pytest.mark.untimed
def test_a_temperature_process_value_counts_only_when_fresh(node_process, ros):
    """docs/valve.md: a `sensor_msgs/Temperature` process value is aged by its stamp; readings
    older than `process_timeout_ms` on arrival move nothing, fresh ones drive the loop."""
    from sensor_msgs.msg import Temperature

    proc = node_process(
        node_args(
            **VALVE,
            mix__control="pid",
            mix__process_topic="/supply_c",
            **LOOP,
        )
    )
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    process = ros.publisher(Temperature, "/supply_c")
    setpoint = ros.publisher(Float64, f"{NODE}/valve/mix/setpoint")
    for p in (process, setpoint):
        ros.wait_for_subscribers(p, 1)
    states.wait_for(lambda s: s.referenced and s.motion == "stopped", timeout=20.0)
    closed = states.messages[-1].position_pct
    setpoint.publish(Float64(data=50.0))

    def reading(age_s: float) -> Temperature:
        m = Temperature(temperature=45.0)
        now = ros.node.get_clock().now().nanoseconds - int(age_s * 1e9)
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(now, 1_000_000_000)
        return m

    # Five seconds old on arrival: stale, the valve stays closed.
    for _ in range(20):
        process.publish(reading(5.0))
        ros.spin_for(0.1)
    assert all(abs(s.position_pct - closed) < 0.01 for s in states.messages), states.messages[-1]
    # Fresh: the loop opens the valve.
    for _ in range(25):
        process.publish(reading(0.0))
        ros.spin_for(0.1)
    opened = states.messages[-1].position_pct
    assert opened > closed + 5.0, (closed, opened)
    assert proc.terminate() == 0, proc.output()


WARN = 1


def start_loop(node_process, ros, **extra):
    """The node with a pid valve on the `std_msgs/Float64` process value `/supply` (LOOP's
    settings, and `extra`), referenced and at rest; its state and /diagnostics subscribed."""
    from std_msgs.msg import String

    params = {
        **VALVE,
        "mix__control": "pid",
        "mix__process_topic": "/supply",
        "mix__process_type": "float64",
        **LOOP,
        **extra,
    }
    proc = node_process(node_args(**params))
    states = ros.subscribe(ValveState, f"{NODE}/valve/mix/state")
    diags = ros.subscribe(DiagnosticArray, "/diagnostics")
    process = ros.publisher(Float64, "/supply")
    setpoint = ros.publisher(Float64, f"{NODE}/valve/mix/setpoint")
    manual = ros.publisher(String, f"{NODE}/valve/mix/manual")
    for p in (process, setpoint, manual):
        ros.wait_for_subscribers(p, 1)
    states.wait_for(lambda s: s.referenced and s.motion == "stopped", timeout=20.0)
    return proc, states, diags, process, setpoint, manual


def feed_until(ros, process, value: float, log, predicate, start: int, timeout: float):
    """Publishes `value` on the process topic every 100 ms until a message of `log` (at index
    >= `start`) satisfies `predicate`; returns it."""
    deadline = mono_ns() + int(timeout * 1e9)
    while mono_ns() < deadline:
        process.publish(Float64(data=value))
        ros.spin_for(0.1)
        for m in log.messages[start:]:
            if predicate(m):
                return m
    last = log.messages[-1] if log.messages else None
    if last is not None and hasattr(last, "status"):
        last = mix_diag(last)
    raise AssertionError(f"not seen within {timeout} s while feeding {value}; last: {last}")


def mix_diag(array):
    """The valve's status in a DiagnosticArray, or None."""
    return next((s for s in array.status if s.name.endswith("valve mix")), None)


def feed_until_diag(ros, process, value: float, diags, predicate, timeout: float = 5.0):
    """`feed_until` on /diagnostics: the valve's status of the first array published from now
    on whose valve status satisfies `predicate`."""
    array = feed_until(
        ros,
        process,
        value,
        diags,
        lambda a: (d := mix_diag(a)) is not None and predicate(d),
        len(diags.messages),
        timeout,
    )
    return mix_diag(array)


def test_a_stale_process_value_shows_as_holding_and_warns_with_its_age_and_timeout(
    node_process, ros
):
    """docs/valve.md, the loop's state and diagnostics: the readings stop, and within
    `process_timeout_ms` and a sample `~/valve/mix/state` says `holding` (published at the
    loop's sample, not at a move) and /diagnostics WARNs with the reading's age and the timeout;
    fresh readings again: `running`, and the WARN is gone."""
    proc, states, diags, process, setpoint, _ = start_loop(node_process, ros)
    setpoint.publish(Float64(data=50.0))
    feed_until(
        ros,
        process,
        45.0,
        states,
        lambda s: s.loop_state == "running" and s.process_value == 45.0,
        start=0,
        timeout=5.0,
    )
    running = feed_until_diag(
        ros, process, 45.0, diags, lambda d: diag_values(d)["loop_state"] == "running"
    )
    assert diag_values(running)["setpoint"] == "50" and diag_values(running)["control"] == "pid"
    assert "process value stale" not in running.message, running
    # At the setpoint the integral stands still and so does the valve.
    feed_until(ros, process, 50.0, states, lambda s: s.motion == "stopped", len(states.messages), 5.0)
    for _ in range(5):
        process.publish(Float64(data=50.0))
        ros.spin_for(0.1)
    at_rest = states.messages[-1]
    assert at_rest.motion == "stopped" and at_rest.loop_state == "running", at_rest

    # The readings stop: the hold is published at the loop's sample, with nothing moving.
    stopped_at = mono_ns()
    start = len(states.messages)
    held = states.wait_for(lambda s: s.loop_state == "holding", start=start, timeout=5.0)
    after_s = (mono_ns() - stopped_at) / 1e9
    # process_timeout_ms 1000, a sample of 100 ms, and ROS on a loaded machine.
    assert 0.9 <= after_s <= 2.5, after_s
    assert held.motion == "stopped" and held.moves == at_rest.moves, (at_rest, held)
    assert held.process_age_s >= 1.0 and held.process_value == 50.0, held
    assert held.control == "pid" and held.setpoint == 50.0 and held.manual == "", held
    d = diags.wait_for(
        lambda a: (d := mix_diag(a)) is not None and "process value stale" in d.message,
        start=len(diags.messages),
        timeout=3.0,
    )
    warn = mix_diag(d)
    assert diag_level(warn) == WARN, warn
    assert "(process_timeout_ms 1000)" in warn.message, warn.message
    age = float(warn.message.split("the last fresh reading is ")[1].split(" s old")[0])
    assert age >= 1.0, warn.message
    assert diag_values(warn)["loop_state"] == "holding", warn
    assert float(diag_values(warn)["process_age_s"]) >= 1.0, warn

    # Readings again: running, and the WARN is gone.
    start = len(states.messages)
    feed_until(ros, process, 45.0, states, lambda s: s.loop_state == "running", start, 5.0)
    back = feed_until_diag(
        ros, process, 45.0, diags, lambda d: diag_values(d)["loop_state"] == "running"
    )
    assert diag_level(back) == OK and "process value stale" not in back.message, back
    assert proc.terminate() == 0, proc.output()


@pytest.mark.untimed
def test_manual_mode_shows_on_the_state_and_on_diagnostics_and_bad_words_are_counted(
    node_process, ros
):
    """docs/valve.md, manual mode: `open` puts the valve in manual mode, and
    `~/valve/mix/state` says `manual` with the command `open` while /diagnostics WARNs that
    the loop is set aside; a word that is no command is refused and counted; `auto` returns
    to the loop, and the manual WARN is gone."""
    from std_msgs.msg import String

    proc, states, diags, process, setpoint, manual = start_loop(node_process, ros)
    setpoint.publish(Float64(data=50.0))
    feed_until(ros, process, 45.0, states, lambda s: s.loop_state == "running", 0, 5.0)

    start = len(states.messages)
    manual.publish(String(data="open"))
    m = feed_until(ros, process, 45.0, states, lambda s: s.manual == "open", start, 5.0)
    assert m.loop_state == "manual", m
    d = feed_until_diag(
        ros, process, 45.0, diags, lambda d: "manual mode: open" in d.message
    )
    assert diag_level(d) == WARN, d
    assert "until auto on ~/valve/mix/manual" in d.message, d.message
    assert diag_values(d)["manual"] == "open" and diag_values(d)["loop_state"] == "manual", d

    before = states.messages[-1].manual_refused
    start = len(states.messages)
    manual.publish(String(data="wide open"))
    counted = feed_until(
        ros, process, 45.0, states, lambda s: s.manual_refused == before + 1, start, 5.0
    )
    assert counted.manual == "open", counted
    assert "manual command refused" in proc.output(), proc.output()

    start = len(states.messages)
    manual.publish(String(data="auto"))
    back = feed_until(ros, process, 45.0, states, lambda s: s.manual == "", start, 5.0)
    assert back.loop_state == "running", back
    d = feed_until_diag(
        ros, process, 45.0, diags, lambda d: diag_values(d)["manual"] == ""
    )
    assert "manual mode" not in d.message and diag_values(d)["loop_state"] == "running", d
    assert proc.terminate() == 0, proc.output()


SAFE_PCT = 80.0


def test_a_stale_process_value_drives_the_valve_to_its_safe_position_after_safe_after_ms(
    node_process, ros
):
    """docs/valve.md, freshness: with `safe_position_pct`, once the loop has held for
    `safe_after_ms` the valve goes to the safe position: `~/valve/mix/state` says `safe` and
    its estimate reaches it; /diagnostics WARNs with the figures."""
    proc, states, diags, process, setpoint, _ = start_loop(
        node_process, ros, mix__safe_position_pct=SAFE_PCT, mix__safe_after_ms=500
    )
    setpoint.publish(Float64(data=50.0))
    feed_until(ros, process, 45.0, states, lambda s: s.loop_state == "running", 0, 5.0)
    for _ in range(10):
        process.publish(Float64(data=45.0))
        ros.spin_for(0.1)
    opened = states.messages[-1].position_pct
    assert opened < SAFE_PCT - 20.0, opened

    # The readings stop: holding after process_timeout_ms, safe after safe_after_ms more.
    start = len(states.messages)
    states.wait_for(lambda s: s.loop_state == "holding", start=start, timeout=5.0)
    safe = states.wait_for(lambda s: s.loop_state == "safe", start=start, timeout=5.0)
    assert safe.target_pct == SAFE_PCT, safe
    there = states.wait_for(
        lambda s: s.loop_state == "safe"
        and s.motion == "stopped"
        and abs(s.position_pct - SAFE_PCT) <= 2.0,
        start=start,
        timeout=10.0,
    )
    d = diags.wait_for(
        lambda a: (d := mix_diag(a)) is not None and diag_values(d)["loop_state"] == "safe",
        start=len(diags.messages),
        timeout=3.0,
    )
    warn = mix_diag(d)
    assert diag_level(warn) == WARN, warn
    assert f"driven to safe_position_pct {SAFE_PCT:g} %" in warn.message, warn.message
    assert "process_timeout_ms 1000, then safe_after_ms 500" in warn.message, warn.message
    assert there.position_pct > opened + 20.0, (opened, there)
    assert proc.terminate() == 0, proc.output()
