"""The protections of the load, proved from outside: rclpy clients command the built
node over ROS, set the protections as parameters, and read what the node did in its CSV trace,
on `~/<ch>/status` and on `/diagnostics`.

As in test_channel_rules.py, instants the core chose are checked on the trace's `scheduled_ns`
to the nanosecond; an instant the core counts from a real edge (the maximum on time runs from
the real rise, the minimum break from the real cut) is checked against that edge's written time
`t_ns`, within the few µs between the write and the clock read after it.
"""

from __future__ import annotations

from typing import Sequence

from helpers_rules import (
    MS,
    NODE,
    ChannelClient,
    Edge,
    after,
    diag_level,
    diag_values,
    mono_ns,
    node_args,
    pulses,
    t_on_ns,
    trace_edges,
    wait_trace,
)
from test_channel_rules import (
    REAL_EDGE_SLACK_NS,
    assert_constant,
    assert_pwm,
    close,
    close_trace,
    close_all_traces,
    observe_until,
    start,
    window_after,
)

OK, WARN = 0, 1


def counted_from(edge: Edge, later: Edge, length_ns: int) -> bool:
    """Whether `later` is scheduled `length_ns` after the instant `edge` really reached the line
    (its written time, up to the slack of the clock read after the write)."""
    gap = later.scheduled_ns - edge.t_ns
    return length_ns <= gap <= length_ns + REAL_EDGE_SLACK_NS


def high_runs(edges: Sequence[Edge]) -> list[tuple[Edge, Edge]]:
    """(rise, fall) of every complete high run, the initial row excluded."""
    return pulses(edges[1:])


# ---------------------------------------------------------------------------------------------
# Maximum on time
# ---------------------------------------------------------------------------------------------


def test_max_on_cuts_a_line_stuck_at_100_percent(node_process, ros):
    """A controller stuck at 100 %: with max_on_ms 500 the line goes off 500 ms after each real
    rise, stays off for its 50 ms minimum break (counted from the real cut), and comes on again;
    no high run on the line is longer than 500 ms. E1 and the limit flag are set, status and
    diagnostics name `max_on`, and diagnostics WARN."""
    proc, ch = start(node_process, ros, pw01__period_ms=200, pw01__min_on_ms=50,
                     pw01__max_on_ms=500)
    ch.duty(100.0)
    on = ch.enable(True)
    assert on.reply.e1 and on.reply.min_time_limited, on.reply
    assert list(on.reply.protections) == ["max_on"], on.reply
    edges = wait_trace(proc, lambda es: len(high_runs(es)) >= 3, "three cuts",
                       spin=ch.ros.spin_once, timeout=10.0)
    ch.wait_e1(True, "max_on_ms acts at 100 %")
    d = ch.wait_diag(lambda d: diag_values(d).get("protections") == "max_on", "max_on acting")
    assert diag_level(d) == WARN and d.message.startswith("E1: max_on_ms"), d
    edges = close_trace(proc)
    # The shutdown ends the last run, if it was high.
    runs = [r for r in high_runs(edges) if r[1] is not edges[-1]]
    assert len(runs) >= 3, edges
    for rise, fall in runs:
        assert counted_from(rise, fall, 500 * MS), (
            f"cut {(fall.scheduled_ns - rise.t_ns) / MS:.3f} ms after the real rise, expected "
            "500 ms"
        )
        assert fall.t_ns - rise.t_ns <= 500 * MS + 20 * MS, "a written high run beyond max_on"
    for (_, fall), (rise, _) in zip(runs, runs[1:]):
        assert counted_from(fall, rise, 50 * MS), (
            f"break of {(rise.scheduled_ns - fall.t_ns) / MS:.3f} ms after the real cut, "
            "expected the 50 ms minimum"
        )


def test_max_on_leaves_pulses_within_it_alone(node_process, ros):
    """50 % of 200 ms is 100 ms on: max_on_ms 150 never acts, no E1, no protection named."""
    proc, ch = start(node_process, ros, pw01__period_ms=200, pw01__max_on_ms=150,
                     pw01__enable=True)
    sent = ch.duty(50.0)
    assert not sent.reply.e1 and list(sent.reply.protections) == [], sent.reply
    window = window_after(sent, 4, 200)
    observe_until(ch, window[1] + 200 * MS)
    edges = close_trace(proc)
    assert_pwm(edges, *window, 200, 100 * MS, "50 % within max_on_ms")


# ---------------------------------------------------------------------------------------------
# Power limits
# ---------------------------------------------------------------------------------------------


def test_power_limits_and_zero_means_zero(node_process, ros):
    """pw01, max_duty_pct 60: 100 % commanded gives exactly 60 % (120 ms of 200 ms), status
    duty_target 60 with `max_duty`, diagnostics OK naming it. pw02, min_duty_pct 20: 0 % gives
    20 % (40 ms); zero_means_zero set over the parameter services makes 0 % off."""
    period = 200
    proc, a, b = start(node_process, ros, channels=("pw01", "pw02"),
                       pw01__period_ms=period, pw01__max_duty_pct=60.0, pw01__enable=True,
                       pw02__period_ms=period, pw02__min_duty_pct=20.0, pw02__enable=True)
    sa = a.duty(100.0, confirm=lambda s: close(s.duty_commanded, 100.0)
                and close(s.duty_applied, 60.0))
    assert close(sa.reply.duty_target, 60.0) and list(sa.reply.protections) == ["max_duty"]
    assert not sa.reply.e1, sa.reply
    d = a.wait_diag(lambda d: diag_values(d).get("protections") == "max_duty", "max_duty")
    assert diag_level(d) == OK and "protections acting: max_duty" in d.message, d
    assert diag_values(d)["duty_target_pct"] == "60.000", d
    sb = b.duty(0.0, confirm=lambda s: s.enabled and close(s.duty_applied, 20.0))
    assert list(sb.reply.protections) == ["min_duty"], sb.reply
    wa, wb = window_after(sa, 3, period), window_after(sb, 3, period)
    observe_until(a, max(wa[1], wb[1]) + period * MS)
    result = ros.set_parameters(NODE, {"pw02.zero_means_zero": True})["pw02.zero_means_zero"]
    assert result.successful, result.reason
    changed = mono_ns()
    off = b.wait_status(lambda s: close(s.duty_target, 0.0) and close(s.duty_applied, 0.0),
                        "0 % off with zero_means_zero", start=len(b.status.messages))
    assert list(off.protections) == [], off
    quiet = (mono_ns() + period * MS, mono_ns() + 4 * period * MS)
    observe_until(a, quiet[1])
    traces = close_all_traces(proc, ("pw01", "pw02"))
    assert_pwm(traces["pw01"], *wa, period, t_on_ns(0.6, period), "max_duty_pct 60, 100 %")
    assert_pwm(traces["pw02"], *wb, period, t_on_ns(0.2, period), "min_duty_pct 20, 0 %")
    assert wb[1] < changed
    assert_constant(traces["pw02"], *quiet, 0, "0 % with zero_means_zero")


def test_out_of_range_protections_are_refused(node_process, ros):
    """The core judges the protections: max_on_ms below the minimum on time, min_duty_pct above
    max_duty_pct and a negative slew are refused with the reason; the old values stay."""
    proc, ch = start(node_process, ros, pw01__min_on_ms=100)
    r = ros.set_parameters(NODE, {"pw01.max_on_ms": 50})["pw01.max_on_ms"]
    assert not r.successful and "below the minimum on time of 100 ms" in r.reason, r.reason
    r = ros.set_parameters_atomically(NODE, {"pw01.min_duty_pct": 70.0,
                                             "pw01.max_duty_pct": 60.0})
    assert not r.successful and "min_duty_pct 70 is above max_duty_pct 60" in r.reason, r.reason
    r = ros.set_parameters(NODE, {"pw01.duty_slew_pct_per_s": -1.0})["pw01.duty_slew_pct_per_s"]
    assert not r.successful, r.reason
    values = ros.get_parameters(NODE, ["pw01.max_on_ms", "pw01.min_duty_pct",
                                       "pw01.max_duty_pct", "pw01.duty_slew_pct_per_s"])
    assert values == {"pw01.max_on_ms": 0, "pw01.min_duty_pct": 0.0,
                      "pw01.max_duty_pct": 100.0, "pw01.duty_slew_pct_per_s": 0.0}
    close_trace(proc)


# ---------------------------------------------------------------------------------------------
# Rolling-average cap
# ---------------------------------------------------------------------------------------------


def most_on_in_a_window(runs: Sequence[tuple[int, int]], window_ns: int) -> tuple[int, int]:
    """The most on time any window of `window_ns` holds over the high runs `(rise, fall)`, ns,
    and where that window ends: it holds the most when it ends at a fall or begins at a rise."""

    def on_within(a: int, z: int) -> int:
        return sum(max(0, min(z, f) - max(a, r)) for r, f in runs)

    ends = [f for _, f in runs] + [r + window_ns for r, _ in runs]
    return max(((on_within(e - window_ns, e), e) for e in ends), default=(0, 0))


def test_avg_duty_caps_the_on_time_of_every_window(node_process, ros):
    """avg_duty_limit_pct 25 over avg_window_s 2 at a 200 ms period, 100 % commanded: on the
    trace no 2 s window holds more than 500 ms on. The core counts from the real writes, so on
    the written times (`t_ns`) that is exact up to a few µs per pulse; on the core's schedule
    (`scheduled_ns`) a rise written late moves its fall by as much, so the schedule's window
    may hold that rise lateness more, and no other. The line comes on
    again as the window slides, so the average stays near the limit. Status and diagnostics
    name `avg_duty` at OK (no E1: a configured limit), diagnostics give the average; a window
    of 0 s is refused with the reason."""
    period, window = 200, 2 * 1000 * MS
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__avg_duty_limit_pct=25.0,
                     pw01__avg_window_s=2, pw01__enable=True)
    sent = ch.duty(100.0)
    capped = ch.wait_status(lambda s: list(s.protections) == ["avg_duty"], "the cap holding",
                            start=sent.index)
    assert not capped.e1 and close(capped.duty_target, 100.0), capped
    d = ch.wait_diag(lambda d: diag_values(d).get("protections") == "avg_duty", "avg_duty")
    assert diag_level(d) == OK and "protections acting: avg_duty" in d.message, d
    # A fall later than every one before it may exceed the cap by that extra lateness once
    # (docs/protections.md); it is at most the largest lateness seen, which diagnostics give.
    # The figure is rounded to 0.001 %.
    over_pct = 100 * float(diag_values(d)["max_lateness_us"]) * 1000 / window
    avg = float(diag_values(d)["avg_duty_pct"])
    assert 20.0 <= avg <= 25.0 + over_pct + 0.0005, (avg, over_pct, d)
    observe_until(ch, sent.confirmed_ns + 4 * window + 300 * MS)
    r = ros.set_parameters(NODE, {"pw01.avg_window_s": 0})["pw01.avg_window_s"]
    assert not r.successful and "avg_window_s 0 is outside 1..86400 s" in r.reason, r.reason
    edges = close_trace(proc)
    runs = high_runs(edges)
    # Four windows' worth of pulses (a wake-up late past a whole short pulse merges it, as the
    # log then says: one fewer).
    assert len(runs) >= 6, edges
    scheduled = [(r.scheduled_ns, f.scheduled_ns) for r, f in runs]
    written = [(r.t_ns, f.t_ns) for r, f in runs]
    slack = 3 * REAL_EDGE_SLACK_NS  # at most three pulses begin in a 2 s window here
    for name, spans in (("scheduled", scheduled), ("written", written)):
        most, end = most_on_in_a_window(spans, window)
        # The core ends a capped pulse early by the lateness it has seen on earlier falls; a
        # fall written later than the one before it (a preempted wake-up) could not be
        # foreseen, and that jump is the written window's allowance. A steady lateness the
        # core should have counted gets none.
        jumps = 0
        if name == "scheduled":
            # The fall is scheduled from the rise's real write: the rise's lateness.
            jumps = sum(
                r.t_ns - r.scheduled_ns
                for r, f in runs
                if f.scheduled_ns > end - window and r.scheduled_ns < end
            )
        if name == "written":
            late = [f.t_ns - f.scheduled_ns for _, f in runs]
            jumps = sum(
                max(0, late[k] - late[k - 1])
                for k in range(1, len(runs))
                if end - window < runs[k][1].t_ns <= end
            )
        print(
            f"{name}: at most {most / MS:.3f} ms on in a 2 s window (ends {end}); "
            f"allowed lateness {jumps / MS:.3f} ms"
        )
        assert most <= 500 * MS + slack + jumps, (
            f"{most / MS:.3f} ms on in the 2 s window ending at {end} ({name})"
        )
    # Four whole windows of the line from the first rise: at most 4 x 500 ms, and not much less.
    first = written[0][0]
    on = sum(max(0, min(f, first + 4 * window) - r) for r, f in written)
    average = on / (4 * window)
    print(f"average over four windows: {100 * average:.2f} %")
    assert 0.18 <= average <= 0.25 + slack / (4 * window), f"average {average:.4f}, cap 25 %"


# ---------------------------------------------------------------------------------------------
# Slew limit and dead band
# ---------------------------------------------------------------------------------------------


def test_slew_ramps_the_duty_from_the_enable(node_process, ros):
    """Soft start: 50 %/s at a 200 ms period is 10 % a period. After the enable the first period
    has no pulse, then the pulses grow by exactly 20 ms a period on the grid (20, 40, 60, 80 ms)
    up to the 45 % commanded (90 ms); status shows `slew` while it ramps."""
    period = 200
    proc, ch = start(node_process, ros, pw01__period_ms=period,
                     pw01__duty_slew_pct_per_s=50.0)
    ch.duty(45.0)
    start_from = len(ch.status.messages)
    on = ch.enable(True)
    ramping = ch.wait_status(lambda s: "slew" in s.protections and s.duty_applied > 0.0,
                             "ramping", start=start_from)
    assert close(ramping.duty_target, 45.0) and ramping.duty_applied < 45.0, ramping
    ch.wait_status(lambda s: close(s.duty_applied, 45.0) and list(s.protections) == [],
                   "45 % reached", start=start_from)
    observe_until(ch, mono_ns() + 3 * period * MS)
    edges = close_trace(proc)
    runs = [p for p in high_runs(edges) if p[0].scheduled_ns >= on.first_publish_ns]
    expected, duty = [], 0.0
    for _ in range(6):
        duty = min(duty + 50.0 / 100.0 * (period * MS) / 1e9, 0.45)
        expected.append(t_on_ns(duty, period))
    got = [f.scheduled_ns - r.scheduled_ns for r, f in runs[:6]]
    assert got == expected, f"pulses {[g / MS for g in got]} ms, expected ramp " \
        f"{[e / MS for e in expected]} ms"
    r0 = runs[0][0].scheduled_ns
    assert all((r.scheduled_ns - r0) % (period * MS) == 0 for r, _ in runs), "off the grid"
    # The first period after the enable had no pulse: the ramp starts at 0.
    assert on.first_publish_ns + period * MS <= r0 <= on.confirmed_ns + period * MS, (
        (r0 - on.first_publish_ns) / MS
    )


def test_a_change_inside_the_dead_band_is_ignored(node_process, ros):
    """duty_deadband_pct 5: after 50 %, 53 % changes nothing (the pulses stay 100 ms of 200 ms;
    status says `deadband`, diagnostics count one ignored command); 56 % is taken (112 ms)."""
    period = 200
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__duty_deadband_pct=5.0,
                     pw01__enable=True)
    ch.duty(50.0)
    ignored = ch.duty(53.0)
    assert close(ignored.reply.duty_target, 50.0), ignored.reply
    assert list(ignored.reply.protections) == ["deadband"], ignored.reply
    d = ch.wait_diag(lambda d: diag_values(d).get("ignored_commands") == "1", "one ignored")
    assert diag_level(d) == OK and diag_values(d)["protections"] == "deadband", d
    w_ignored = window_after(ignored, 3, period)
    observe_until(ch, w_ignored[1])
    taken = ch.duty(56.0, confirm=lambda s: close(s.duty_target, 56.0))
    assert list(taken.reply.protections) == [], taken.reply
    w_taken = window_after(taken, 3, period)
    observe_until(ch, w_taken[1] + period * MS)
    edges = close_trace(proc)
    assert_pwm(edges, *w_ignored, period, 100 * MS, "53 % inside the band after 50 %")
    assert_pwm(edges, *w_taken, period, t_on_ns(0.56, period), "56 % outside the band")


# ---------------------------------------------------------------------------------------------
# Cycle extension
# ---------------------------------------------------------------------------------------------


def test_extend_grows_the_period_and_keeps_the_duty(node_process, ros):
    """short_pulse extend (PLC PWM output modules' "extend cycle"), 200 ms period, 30 ms minimum
    on and off time. 5 % (a 10 ms pulse) is neither dropped nor stretched: the period grows to
    30 ms / 0.05 = 600 ms with a pulse of exactly 30 ms, so the duty is 5 %; 95 % likewise
    gives 600 ms with a break of exactly 30 ms. No E1, the limit flag, diagnostics OK naming the
    extension. extend_max 2 (400 ms) is too short for it: suppressed, E1, WARN."""
    period, extended = 200, 600
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__min_on_ms=30,
                     pw01__short_pulse="extend", pw01__duty=5.0, pw01__enable=True)
    st = ch.wait_status(lambda s: s.rule == "extended_pulse", "5 % extended")
    assert (st.e1, st.min_time_limited) == (False, True), st
    assert (st.period_ms, st.on_time_ms, st.off_time_ms) == (600.0, 30.0, 570.0), st
    assert close(st.duty_applied, 5.0) and close(st.duty_commanded, 5.0), st
    assert ch.e1_state() is False
    d = ch.wait_diag(lambda d: diag_values(d).get("cycle_extended") == "true", "extended")
    assert diag_level(d) == OK, d
    assert "cycle extended to 600.0 ms to keep the duty (extended_pulse)" in d.message, d
    assert diag_values(d)["period_ms"] == "600.000", d
    t0 = mono_ns()
    edges = wait_trace(proc, lambda es: len(pulses(after(es, t0))) >= 4, "4 extended pulses",
                       spin=ch.ros.spin_once, timeout=15.0)

    high = ch.duty(95.0)
    st = ch.wait_status(lambda s: s.rule == "extended_break", "95 % extended", high.index)
    assert (st.e1, st.min_time_limited) == (False, True), st
    assert (st.period_ms, st.on_time_ms, st.off_time_ms) == (600.0, 570.0, 30.0), st
    w95 = window_after(high, 4, extended)
    observe_until(ch, w95[1] + extended * MS)

    result = ros.set_parameters(NODE, {"pw01.extend_max": 0.5})["pw01.extend_max"]
    assert not result.successful and "extend_max" in result.reason, result
    result = ros.set_parameters(NODE, {"pw01.extend_max": 2.0})["pw01.extend_max"]
    assert result.successful, result.reason
    changed = mono_ns()
    st = ch.wait_status(lambda s: s.rule == "suppressed_break", "95 % beyond extend_max",
                        start=len(ch.status.messages))
    assert (st.e1, st.min_time_limited, st.period_ms) == (True, False, 200.0), st
    ch.wait_e1(True, "600 ms is beyond 2 x 200 ms")
    d = ch.wait_diag(lambda d: diag_values(d).get("rule") == "suppressed_break", "suppressed")
    assert diag_level(d) == WARN and diag_values(d)["cycle_extended"] == "false", d
    # The extended period running at the change ends within 600 ms: constant 1 from then.
    quiet = (changed + extended * MS, changed + (extended + 3 * period) * MS)
    observe_until(ch, quiet[1])
    edges = close_trace(proc)

    # 5 %: rises on the 600 ms grid, each pulse exactly the 30 ms minimum (from its real rise).
    ps = assert_pwm(edges, t0, high.first_publish_ns, extended, 30 * MS, "5 % extended",
                    at_minimum=True)
    n = len(ps)
    assert n >= 3, ps
    # The duty over the N whole extended periods: 5 % within the rises' write latencies.
    on = sum(f.scheduled_ns - r.scheduled_ns for r, f in ps)
    span = n * extended * MS
    assert abs(on - 0.05 * span) <= n * REAL_EDGE_SLACK_NS, (on, span)
    # 95 %: falls on the 600 ms grid, each break exactly 30 ms (from its real fall), so each
    # rise follows its fall by the minimum.
    inside = [e for e in edges if w95[0] <= e.scheduled_ns <= w95[1]]
    falls = [e for e in inside if e.level == 0]
    assert len(falls) >= 3, inside
    for f in falls:
        assert (f.scheduled_ns - falls[0].scheduled_ns) % (extended * MS) == 0, (
            f"fall {(f.scheduled_ns - falls[0].scheduled_ns) / MS} ms after the first, off the "
            "600 ms grid"
        )
    for f, r in zip(inside, inside[1:]):
        if f.level == 0:
            assert r.scheduled_ns - f.scheduled_ns == 30 * MS or counted_from(f, r, 30 * MS), (
                f"break of {(r.scheduled_ns - f.scheduled_ns) / MS} ms, expected 30 ms"
            )
    assert_constant(edges, *quiet, 1, "95 % suppressed beyond extend_max")


# ---------------------------------------------------------------------------------------------
# Across channels: phase staggering and the simultaneous-on limit
# ---------------------------------------------------------------------------------------------


def overlaps(a: Sequence[tuple[Edge, Edge]], b: Sequence[tuple[Edge, Edge]]) -> list:
    """The pairs of pulses of `a` and `b` that were on together (scheduled instants)."""
    return [(p, q) for p in a for q in b
            if p[0].scheduled_ns < q[1].scheduled_ns and q[0].scheduled_ns < p[1].scheduled_ns]


def whole_runs(edges: Sequence[Edge]) -> list[tuple[Edge, Edge]]:
    """The high runs the schedule ended: a run the shutdown cut short is left out."""
    return [r for r in high_runs(edges) if r[1] is not edges[-1]]


def test_stagger_lays_the_pulses_end_to_end_on_the_grid(node_process, ros):
    """phase stagger (set while running), three channels of 200 ms at 20, 30 and 40 %: every
    pw01 pulse starts on the grid of whole periods of the monotonic clock, pw02's starts exactly
    where pw01's ends, pw03's where pw02's ends; pulses keep their exact lengths and no two
    overlap. Status names `stagger`."""
    period, duties = 200, (20.0, 30.0, 40.0)
    names = ("pw01", "pw02", "pw03")
    settings = {f"{c}__period_ms": period for c in names}
    proc = node_process(node_args(channels=3, **settings))
    chans = [ChannelClient(ros, c) for c in names]
    for c in chans:
        c.wait_connected()
    r = ros.set_parameters(NODE, {"phase": "stagger"})["phase"]
    assert r.successful, r
    for c, d in zip(chans, duties):
        c.duty(d)
    for c in chans:
        c.enable(True)
    s = chans[2].wait_status(lambda s: "stagger" in s.protections, "stagger reported")
    assert close(s.duty_applied, 40.0), s
    observe_until(chans[0], mono_ns() + 6 * period * MS)
    edges = close_all_traces(proc, names)
    runs = {c: whole_runs(edges[c]) for c in names}
    assert all(len(r) >= 4 for r in runs.values()), runs
    for c, d in zip(names, duties):
        for rise, fall in runs[c]:
            assert fall.scheduled_ns - rise.scheduled_ns == t_on_ns(d / 100, period), (c, rise)
    for rise, _ in runs["pw01"]:
        assert rise.scheduled_ns % (period * MS) == 0, f"pw01 off the grid: {rise}"
    for first, second in (("pw01", "pw02"), ("pw02", "pw03")):
        ends = {f.scheduled_ns for _, f in runs[first]}
        for rise, _ in runs[second]:
            assert rise.scheduled_ns in ends, f"{second} rise {rise} not at a {first} fall"
    for a, b in (("pw01", "pw02"), ("pw01", "pw03"), ("pw02", "pw03")):
        assert not overlaps(runs[a], runs[b]), (a, b)


def test_max_simultaneous_on_delays_a_pulse_then_skips_what_cannot_fit(node_process, ros):
    """max_simultaneous_on 1, two channels of 200 ms at 40 % enabled at start-up: one channel's
    pulse waits for the other's to end and keeps its 80 ms, each period keeps 200 ms; never both
    on; no E1. At 60 % each, the waiting channel's pulse can no longer fit its period: it is
    skipped, E1 is set, diagnostics say so and count `skipped_pulses`."""
    period = 200
    proc, a, b = start(node_process, ros, ("pw01", "pw02"), max_simultaneous_on=1,
                       pw01__period_ms=period, pw02__period_ms=period, pw01__duty=40.0,
                       pw02__duty=40.0, pw01__enable=True, pw02__enable=True)
    observe_until(a, mono_ns() + 5 * period * MS)
    edges = trace_edges(proc, "pw01"), trace_edges(proc, "pw02")
    ra, rb = whole_runs(edges[0]), whole_runs(edges[1])
    assert len(ra) >= 3 and len(rb) >= 3, (ra, rb)
    falls = [{f.scheduled_ns for _, f in r} for r in (ra, rb)]
    # Which one waits: its rises lie at the other's falls.
    waiting = 1 if all(r.scheduled_ns in falls[0] for r, _ in rb) else 0
    assert all(r.scheduled_ns in falls[1 - waiting] for r, _ in (ra, rb)[waiting]), (ra, rb)
    for rise, fall in ra + rb:
        assert fall.scheduled_ns - rise.scheduled_ns == t_on_ns(0.4, period), (rise, fall)
    late = (a, b)[waiting]
    late.wait_status(lambda s: "delayed" in s.protections, "the slot limit acting")
    assert not late.e1_state(), "delayed, not lost: no E1"
    diag_from = len(late.diagnostics.messages)
    # The count only grows: only a count above the last one sent before the commands is theirs.
    counts = [int(diag_values(s).get("skipped_pulses", "0"))
              for s in map(late.my_diag, late.diagnostics.messages[:diag_from]) if s is not None]
    skipped_before = counts[-1] if counts else 0
    sent = (a.duty(60.0), b.duty(60.0))
    # Both commands in force from the later confirmation on.
    switch_ns = max(s.confirmed_ns for s in sent)
    late.wait_e1(True, "a skipped pulse")
    d = late.wait_diag(
        lambda d: int(diag_values(d).get("skipped_pulses", "0")) > skipped_before,
        "skips counted after the commands",
        start=diag_from,
    )
    assert diag_level(d) == WARN and "max_simultaneous_on" in d.message, d
    assert "delayed" in diag_values(d)["protections"], d
    edges = close_all_traces(proc, ("pw01", "pw02"))
    ra, rb = high_runs(edges["pw01"]), high_runs(edges["pw02"])
    assert not overlaps(ra, rb), overlaps(ra, rb)[:3]
    skipped = [p for p in (ra, rb)[waiting] if p[0].scheduled_ns > switch_ns + 2 * period * MS]
    assert not skipped, f"the waiting channel pulsed at 60 % beside the other's 60 %: {skipped}"
