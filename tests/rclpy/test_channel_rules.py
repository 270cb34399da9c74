"""The channel rules of SPEC §1, proved from outside: real rclpy clients command the built node
over ROS and read what it did on its topics and in its CSV trace.

The trace's `scheduled_ns` are the exact instants the timing core chose, so periods, on times
and the instants of rule-driven edges are checked on them to the nanosecond. When the node acted
on a command, the test knows only bounds: the command was handled after the test published it
and before the test received the status that reflects it; rule-driven edges are checked against
those bounds. A written time (`t_ns`, lateness) is checked to be after its scheduled time, in
its own phase and within WRITE_TOL_NS (timing accuracy is the benchmark's business); figures
of the same instants on two clocks (an edge's stamp and the trace) agree within CLOCK_TOL_NS.

Every test names the vendor rule it checks (seeds 000..004).
"""

from __future__ import annotations

import math
from typing import Sequence

import pytest
from std_msgs.msg import Bool, Float64
from helpers_rules import (
    E1_QOS,
    MS,
    NODE,
    WRITE_TOL_NS,
    CLOCK_TOL_NS,
    ChannelClient,
    Edge,
    Sent,
    after,
    diag_level,
    diag_values,
    mono_ns,
    node_args,
    pulses,
    stamp_ns,
    t_on_ns,
    trace_edges,
    wait_trace,
)

OK, WARN, ERROR = 0, 1, 2


def start(node_process, ros, channels: Sequence[str] = ("pw01",), **params):
    """Starts the node with `params` (see node_args) and connects to `channels`."""
    proc = node_process(node_args(**params))
    clients = [ChannelClient(ros, ch) for ch in channels]
    for c in clients:
        c.wait_connected()
    return (proc, *clients)


def level_at(edges: Sequence[Edge], t_ns: int) -> int:
    """The output level at `t_ns` according to the trace (the last edge scheduled at or before)."""
    before = [e for e in edges if e.scheduled_ns <= t_ns]
    assert before, f"no trace row at or before {t_ns}"
    return before[-1].level


def assert_constant(edges: Sequence[Edge], start_ns: int, end_ns: int, level: int, what: str):
    """The output is `level` throughout [start_ns, end_ns]: at the start and with no edge in
    between."""
    assert level_at(edges, start_ns) == level, f"{what}: output not {level} at the window start"
    inside = [e for e in edges if start_ns < e.scheduled_ns <= end_ns]
    assert not inside, (
        f"{what}: expected a constant {level} for {(end_ns - start_ns) / MS:.0f} ms, got edges "
        f"{[(e.level, (e.scheduled_ns - start_ns) / MS) for e in inside]} (ms after the window "
        "start)"
    )


def assert_written_in_time(edges: Sequence[Edge], what: str) -> None:
    """Each edge was written no earlier than scheduled, within WRITE_TOL_NS after, and before
    the next edge of `edges` (consecutive edges of one line) was due: in its own phase."""
    for e, nxt in zip(edges, list(edges[1:]) + [None]):
        late = e.t_ns - e.scheduled_ns
        assert 0 <= late <= WRITE_TOL_NS, f"{what}: edge {e} written {late / MS:.3f} ms late"
        assert nxt is None or e.t_ns < nxt.scheduled_ns, (
            f"{what}: edge {e} written {late / MS:.3f} ms late, after the next edge was due "
            f"({nxt})"
        )


#: The few µs between the sim output recording a write (trace `t_ns`) and the output thread
#: reading the clock after it, the instant the core counts a real edge from.
REAL_EDGE_SLACK_NS = 1 * MS


def from_real_rise(rise: Edge, fall: Edge, expected_ns: int) -> bool:
    """Whether a pulse the core counts from the instant its rise really reached the line (a
    pulse of exactly the minimum on time, or TCONT_CP's real impulse length) lasts
    `expected_ns` from there: on the schedule it is `expected_ns`, longer by at most the rise's
    write latency. The minimum is a property of the line, so the fall waits for it."""
    pulse = fall.scheduled_ns - rise.scheduled_ns
    latency = rise.t_ns - rise.scheduled_ns
    return expected_ns <= pulse <= expected_ns + latency + REAL_EDGE_SLACK_NS


def assert_pwm(
    edges: Sequence[Edge], start_ns: int, end_ns: int, period_ms: int, on_ns: int, what: str,
    at_minimum: bool = False,
) -> list[tuple[Edge, Edge]]:
    """Between start_ns and end_ns the output pulses with exactly `on_ns` on per `period_ms`:
    every period starts on the grid of the first one and every pulse lasts exactly `on_ns`
    (`at_minimum`: `on_ns` is the minimum on time, so each pulse lasts it from its real rise,
    see from_real_rise). Returns the complete pulses that start in the window (at least two)."""
    period = period_ms * MS
    inside = [e for e in edges if start_ns <= e.scheduled_ns <= end_ns]
    ps = pulses(inside)
    assert len(ps) >= 2, f"{what}: fewer than 2 complete pulses in the window: {inside}"
    r0 = ps[0][0].scheduled_ns
    for r, f in ps:
        exact = f.scheduled_ns - r.scheduled_ns == on_ns
        assert exact or (at_minimum and from_real_rise(r, f, on_ns)), (
            f"{what}: pulse of {(f.scheduled_ns - r.scheduled_ns)} ns, expected {on_ns} ns"
            + (f" from its real rise ({r.t_ns - r.scheduled_ns} ns late)" if at_minimum else "")
        )
        assert (r.scheduled_ns - r0) % period == 0, (
            f"{what}: rise {r.scheduled_ns - r0} ns after the first one, off the {period_ms} ms "
            "grid"
        )
    # No stray edge: the window holds only whole pulses (rise, fall, rise, fall, ...).
    levels = [e.level for e in after(inside, r0)]
    assert all(a != b for a, b in zip(levels, levels[1:])), f"{what}: repeated level {levels}"
    return ps


def window_after(sent: Sent, periods: int, period_ms: int) -> tuple[int, int]:
    """An observation window that starts one period after the command was confirmed (so the
    period running when it arrived has ended) and lasts `periods` periods."""
    start_ns = sent.confirmed_ns + period_ms * MS
    return start_ns, start_ns + periods * period_ms * MS


def observe_until(ch: ChannelClient, t_ns: int) -> None:
    """Keeps ROS spinning until the monotonic clock passes `t_ns`."""
    while (left := t_ns - mono_ns()) > 0:
        ch.ros.spin_once(min(0.05, left / 1e9))


def close_trace(proc) -> list[Edge]:
    """Stops the node (SIGTERM, exit 0) so its trace is complete, and returns pw01's edges."""
    assert proc.is_running(), "the node stopped during the test\n" + proc.output()
    code = proc.terminate()
    assert code == 0, f"node exit status {code} on SIGTERM\n" + proc.output()
    return trace_edges(proc)


def close_all_traces(proc, channels: Sequence[str]) -> dict[str, list[Edge]]:
    assert proc.is_running(), "the node stopped during the test\n" + proc.output()
    code = proc.terminate()
    assert code == 0, f"node exit status {code} on SIGTERM\n" + proc.output()
    return {ch: trace_edges(proc, ch) for ch in channels}


def close(a: float, b: float, tol: float = 1e-6) -> bool:
    return math.isclose(a, b, rel_tol=0.0, abs_tol=tol)


# ---------------------------------------------------------------------------------------------
# Period and on time
# ---------------------------------------------------------------------------------------------


@pytest.mark.smoke
def test_period_and_on_time_of_edges(node_process, ros):
    """000: "the on time is proportional to SV, the period duration is unchanged": at 37 % of
    200 ms every period is exactly 200 ms and every pulse exactly 74 ms (scheduled times); the
    edges topic and the trace agree edge for edge, and written times are within tolerance."""
    proc, ch = start(node_process, ros, pw01__period_ms=200, pw01__duty=37.0)
    ch.enable(True)
    n_edges = 12
    ch.edges.wait_for_count(n_edges)
    edges = wait_trace(proc, lambda es: len(es) > n_edges, f"{n_edges} edges",
                       spin=ch.ros.spin_once)
    run = edges[1:]  # after the initial row
    assert [e.level for e in run] == [1, 0] * (len(run) // 2) + [1] * (len(run) % 2), run
    assert_pwm(run, run[0].scheduled_ns, run[-1].scheduled_ns, 200, 74 * MS, "37 % of 200 ms")
    assert_written_in_time(run, "37 % of 200 ms")

    # The edges topic, message by message: seq without gap, level and lateness as in the trace,
    # where row k of the channel is edge seq k (seq counts from 1).
    msgs = ch.edges.messages[:n_edges]
    assert [m.seq for m in msgs] == list(range(msgs[0].seq, msgs[0].seq + n_edges)), msgs
    for m in msgs:
        row = edges[m.seq]
        assert m.channel == 1
        assert m.level == bool(row.level), (m, row)
        assert 0 <= m.lateness_ns <= WRITE_TOL_NS, m
        # The message's lateness is read on the output thread's clock just after the write the
        # trace recorded: the same figure, a few µs later.
        assert 0 <= m.lateness_ns - (row.t_ns - row.scheduled_ns) <= REAL_EDGE_SLACK_NS, (m, row)
    # Wall-clock stamps: the scheduled instants (stamp - lateness) keep the trace's 74 ms on
    # and 200 ms period, to within the drift between the two clocks.
    sched = [stamp_ns(m.stamp) - m.lateness_ns for m in msgs]
    first_rise = 0 if msgs[0].level else 1  # the first message may precede matching
    for k in range(first_rise, n_edges - 2, 2):
        assert msgs[k].level and not msgs[k + 1].level
        assert abs(sched[k + 1] - sched[k] - 74 * MS) <= CLOCK_TOL_NS, k
        assert abs(sched[k + 2] - sched[k] - 200 * MS) <= CLOCK_TOL_NS, k

    s = ch.status.messages[-1]
    assert (s.period_ms, s.on_time_ms, s.off_time_ms, s.rule) == (200.0, 74.0, 126.0, "exact")
    assert close(s.duty_applied, 37.0) and not s.e1 and not s.min_time_limited
    close_trace(proc)


# ---------------------------------------------------------------------------------------------
# Commands: SV, percent, 0 % and 100 %
# ---------------------------------------------------------------------------------------------


def test_sv_full_scale_is_4095(node_process, ros):
    """000: "the value range from 0 to 4095 of SV corresponds to 0 to 100 % of the period":
    SV 2048 gives 2048/4095 of 200 ms to the ns, SV 4095 a constant 1 and SV 0 a constant 0."""
    period = 200
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__enable=True)
    sv_2048 = ch.sv(2048, lambda s: close(s.duty_commanded, 2048 / 4095 * 100, 1e-9))
    on_2048 = 100_024_420  # 2048/4095 x 200 ms = 100.024420024... ms, to the nearest ns
    ch.wait_status(lambda s: close(s.on_time_ms, on_2048 / MS, 1e-6), "on time of SV 2048",
                   start=sv_2048.index)
    w_2048 = window_after(sv_2048, 3, period)
    wait_trace(
        proc,
        lambda es: len(pulses(after(es, w_2048[0]))) >= 2,
        "two pulses after SV 2048",
        spin=ch.ros.spin_once,
    )

    full = ch.sv(4095, lambda s: s.duty_commanded == 100.0)
    st = ch.wait_status(lambda s: s.rule == "exact" and s.output and s.duty_applied == 100.0,
                        "SV 4095 applied", start=full.index)
    assert not st.e1 and not st.command_clamped, st
    w_full = window_after(full, 3, period)
    observe_until(ch, w_full[1])

    zero = ch.sv(0, lambda s: s.duty_commanded == 0.0)
    st = ch.wait_status(lambda s: s.duty_applied == 0.0 and not s.output, "SV 0 applied",
                        start=zero.index)
    assert not st.e1 and not st.command_clamped, st
    w_zero = window_after(zero, 3, period)
    observe_until(ch, w_zero[1])

    edges = close_trace(proc)
    ps = assert_pwm(edges, w_2048[0], w_2048[1], period, on_2048, "SV 2048")
    assert_written_in_time([e for p in ps for e in p], "SV 2048")
    assert_constant(edges, *w_full, 1, "SV 4095")
    assert_constant(edges, *w_zero, 0, "SV 0")


def test_zero_and_full_percent_are_constant_without_e1(node_process, ros):
    """002: "the minimum switching time is deactivated for these two cases" (0 % and 100 %);
    000: E1 only when a time is below its minimum. With a 30 ms minimum on and off time, 100 %
    and 0 % are constant outputs with E1 false, while 5 % and 97 % (below the minima) set E1."""
    period = 100
    proc, ch = start(
        node_process, ros, pw01__period_ms=period, pw01__min_on_ms=30, pw01__duty=100.0,
        pw01__enable=True,
    )
    st = ch.wait_status(lambda s: s.output and s.duty_applied == 100.0, "100 % applied")
    assert (st.e1, st.min_time_limited, st.rule) == (False, False, "exact"), st
    assert ch.e1_state() is False
    observe_until(ch, mono_ns() + 5 * period * MS)

    windows, suppressed = [], []
    for below, rule, side, exact, label in [
        # 5 %: a 5 ms pulse, below the minimum on time: E1 (suppress, 000); then 0 %: exact,
        # constant 0, E1 false again.
        (5.0, "suppressed_pulse", "on", 0.0, "0 %"),
        # 97 %: a 3 ms break, below the minimum off time: E1 (suppress, 000); then 100 %: exact,
        # constant 1, E1 false again.
        (97.0, "suppressed_break", "off", 100.0, "100 % again"),
    ]:
        sent = ch.duty(below)
        suppressed.append(sent)
        st = ch.wait_status(lambda s, r=rule: s.rule == r, f"{below:g} % suppressed", sent.index)
        assert st.e1, st
        ch.wait_e1(True, f"{below:g} % below the minimum {side} time")

        sent = ch.duty(exact)
        st = ch.wait_status(lambda s, d=exact: s.rule == "exact" and s.duty_commanded == d,
                            f"{label} applied", sent.index)
        on = exact == 100.0
        assert (st.e1, st.min_time_limited, st.output, st.duty_applied) == (False, False, on, exact)
        ch.wait_e1(False, f"{exact:g} % is exact")
        w = window_after(sent, 5, period)
        observe_until(ch, w[1])
        windows.append((label, *w, int(on)))

    diag = ch.wait_diag(lambda d: True, "any", start=len(ch.diagnostics.messages))
    assert diag_level(diag) == OK and diag_values(diag)["e1"] == "false", diag

    edges = close_trace(proc)
    # 100 % from start-up: one rising edge, then on until 5 % was sent.
    assert edges[1].level == 1, edges[:3]
    assert_constant(edges, edges[1].scheduled_ns, suppressed[0].first_publish_ns, 1,
                    "100 % at start-up")
    for what, a, b, level in windows:
        assert_constant(edges, a, b, level, what)


# ---------------------------------------------------------------------------------------------
# Minimum on and off times
# ---------------------------------------------------------------------------------------------


def test_suppress_short_pulse_and_short_break(node_process, ros):
    """000: "if the value specified via SV is shorter than the minimum on duration, the output is
    0"; "if the off duration is less than the minimum off duration, Q1 or Q2 are permanently on";
    "E1 is set if the duration is below the set minimum on or off duration". 200 ms, minimum
    30 ms: 10 % -> constant 0 with E1, 90 % -> constant 1 with E1, 15 % (exactly the minimum)
    -> 30 ms pulses, E1 false."""
    period = 200
    proc, ch = start(
        node_process, ros, pw01__period_ms=period, pw01__min_on_ms=30, pw01__duty=10.0,
        pw01__enable=True,
    )
    # The subscriber joined after E1 was set: transient local gives it the current state.
    ch.wait_e1(True, "10 % is a 20 ms pulse < 30 ms")
    st = ch.wait_status(lambda s: s.rule == "suppressed_pulse", "10 % suppressed")
    assert (st.e1, st.min_time_limited, st.output, st.duty_applied) == (True, False, False, 0.0)
    assert close(st.duty_commanded, 10.0), st
    diag = ch.wait_diag(lambda d: diag_level(d) == WARN and diag_values(d)["e1"] == "true",
                        "WARN for E1")
    assert "E1" in diag.message and diag_values(diag)["e1"] == "true", diag
    # A subscriber that joins now, long after E1 was set, gets the current state at once.
    late = ros.subscribe(Bool, f"{NODE}/pw01/e1", E1_QOS)
    assert late.wait_for(timeout=10.0, what="the latched E1 on a late subscription").data is True
    observe_until(ch, mono_ns() + 5 * period * MS)

    e1_from = len(ch.e1.messages)
    high = ch.duty(90.0)
    st = ch.wait_status(lambda s: s.rule == "suppressed_break", "90 % suppressed", high.index)
    assert (st.e1, st.min_time_limited, st.duty_applied) == (True, False, 100.0), st
    w = window_after(high, 5, period)
    observe_until(ch, w[1])
    # E1 stays set: the latest E1 may be the one from 10 %, so no E1 sent since 90 % may be
    # false (E1 is sent on a change only).
    assert ch.e1_state() is True
    assert all(m.data for m in ch.e1.messages[e1_from:]), ch.e1.messages[e1_from:]
    windows = [("90 % suppressed", *w, 1)]

    exact = ch.duty(15.0)
    ch.wait_e1(False, "15 % is exactly the 30 ms minimum")
    st = ch.wait_status(lambda s: s.rule == "exact" and close(s.duty_commanded, 15.0), "15 %",
                        exact.index)
    assert (st.e1, st.on_time_ms, st.off_time_ms) == (False, 30.0, 170.0), st
    w15 = window_after(exact, 3, period)
    wait_trace(proc, lambda es: len(pulses(after(es, w15[0]))) >= 2, "15 % pulses",
               spin=ch.ros.spin_once)

    edges = close_trace(proc)
    # 10 % from start-up until 90 % was sent: no pulse at all.
    assert_constant(edges, edges[0].scheduled_ns, high.first_publish_ns, 0, "10 % suppressed")
    for what, a, b, level in windows:
        assert_constant(edges, a, b, level, what)
    assert_pwm(edges, w15[0], w15[1], period, 30 * MS, "15 % = minimum on time", at_minimum=True)


def test_stretch_raises_pulse_to_min_on(node_process, ros):
    """002: nMinSwiTi limits the switch-on time downwards and bLmtSwiTi says so (profile
    twincat_ba, short_pulse stretch): 5 % of 200 ms (10 ms) becomes a 30 ms pulse in an
    unchanged 200 ms period, with the limit flag and E1 set; 50 % clears both."""
    period = 200
    proc, ch = start(
        node_process, ros, pw01__profile="twincat_ba", pw01__period_ms=period,
        pw01__min_on_ms=30, pw01__duty=5.0, pw01__enable=True,
    )
    st = ch.wait_status(lambda s: s.rule == "stretched_pulse", "5 % stretched")
    assert (st.e1, st.min_time_limited, st.on_time_ms, st.off_time_ms) == (True, True, 30.0, 170.0)
    assert close(st.duty_applied, 15.0) and close(st.duty_commanded, 5.0), st
    ch.wait_e1(True, "5 % stretched")
    diag = ch.wait_diag(
        lambda d: diag_level(d) == WARN and diag_values(d)["min_time_limited"] == "true",
        "WARN for the limit",
    )
    assert diag_values(diag)["min_time_limited"] == "true", diag
    t0 = mono_ns()
    edges = wait_trace(proc, lambda es: len(pulses(after(es, t0))) >= 3, "3 stretched pulses",
                       spin=ch.ros.spin_once)
    ps = assert_pwm(edges, t0, edges[-1].scheduled_ns, period, 30 * MS, "5 % stretched",
                    at_minimum=True)
    assert_written_in_time([e for p in ps for e in p], "5 % stretched")

    half = ch.duty(50.0)
    st = ch.wait_status(lambda s: s.rule == "exact", "50 % exact", half.index)
    assert (st.e1, st.min_time_limited, st.on_time_ms) == (False, False, 100.0), st
    ch.wait_e1(False, "50 % is reproduced")
    close_trace(proc)


# Frequency_Output's truth table (004), as (edge band, duty %, expected output: 0, 1 or "pwm").
BAND_CASES = {
    "pw01": (
        0.2,
        [(10.0, 0), (20.0, "pwm"), (50.0, "pwm"), (80.0, "pwm"), (90.0, 1), (19.0, 0)],
    ),
    "pw02": (0.7, [(50.0, 0), (70.0, 1), (20.0, 0), (95.0, 1), (69.0, 0)]),
}


def test_band_follows_frequency_output_truth_table(node_process, ros):
    """004's truth table (profile frequency_output, short_pulse band): with i_rEdge < 0.5, d < e
    -> FALSE, e <= d <= 1-e -> PWM with duty d, d > 1-e -> TRUE; with i_rEdge >= 0.5, d < e ->
    FALSE, d >= e -> TRUE. pw01 has e = 0.2, pw02 e = 0.7; the output is read from the trace."""
    period = 100
    params = {}
    for name, (edge, _cases) in BAND_CASES.items():
        params.update({
            f"{name}__profile": "frequency_output",
            f"{name}__period_ms": period,
            f"{name}__edge_band": edge,
            f"{name}__enable": True,
        })
    proc, *clients = start(node_process, ros, channels=tuple(BAND_CASES), **params)
    windows = []
    for ch in clients:
        edge, cases = BAND_CASES[ch.channel]
        for duty, expected in cases:
            rule = {0: "band_low", 1: "band_high", "pwm": "exact"}[expected]
            sent = ch.duty(duty)
            expected_applied = {0: 0.0, 1: 100.0, "pwm": duty}[expected]
            st = ch.wait_status(
                lambda s, d=duty, r=rule, a=expected_applied: close(s.duty_commanded, d)
                and s.rule == r
                and close(s.duty_applied, a),
                f"e={edge} d={duty} % -> {rule}, {expected_applied} % applied",
                sent.index,
            )
            # The band is a policy, not a minimum time: E1 and the limit flag stay false.
            assert not st.e1 and not st.min_time_limited, st
            w = window_after(sent, 3, period)
            if expected == "pwm":
                wait_trace(proc, lambda es, a=w[0]: len(pulses(after(es, a))) >= 2,
                           f"pulses at {duty} %", channel=ch.channel, spin=ch.ros.spin_once)
            observe_until(ch, w[1])
            windows.append((ch.channel, edge, duty, expected, w))

    traces = close_all_traces(proc, tuple(BAND_CASES))
    for channel, edge, duty, expected, (a, b) in windows:
        what = f"{channel}: e={edge}, d={duty} %"
        if expected == "pwm":
            assert_pwm(traces[channel], a, b, period, t_on_ns(duty / 100, period), what)
        else:
            assert_constant(traces[channel], a, b, expected, what)


# ---------------------------------------------------------------------------------------------
# Enable
# ---------------------------------------------------------------------------------------------


def test_enable_rising_edge_starts_a_period_with_its_on_phase(node_process, ros):
    """000, 004: "the output signal starts with TRUE" on enable: the first rising edge is
    scheduled at the instant the enable was handled, and the period grid runs from there; a
    later re-enable starts a new grid at its own instant."""
    period = 200
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__duty=30.0)
    assert len(trace_edges(proc)) <= 1, "edges before enable"
    first = ch.enable(True)
    edges = wait_trace(proc, lambda es: len(pulses(es)) >= 3, "3 pulses after enable",
                       spin=ch.ros.spin_once)
    r1 = edges[1]
    assert r1.level == 1, "the first edge after enable is not a rising edge"
    assert first.first_publish_ns <= r1.scheduled_ns <= first.confirmed_ns, (
        "first rising edge not scheduled while the enable was handled"
    )
    ps = assert_pwm(edges, r1.scheduled_ns, edges[-1].scheduled_ns, period, 60 * MS, "30 %")
    assert ps[0][0] == r1
    assert_written_in_time(edges[1:], "after enable")

    off = ch.enable(False)
    ch.spin_for(0.13)  # re-enable at some instant off the old grid
    again = ch.enable(True)
    edges = wait_trace(proc, lambda es: len(pulses(after(es, again.first_publish_ns))) >= 3,
                       "3 pulses after re-enable", spin=ch.ros.spin_once)
    r2 = after(edges, again.first_publish_ns)[0]
    assert r2.level == 1, "the first edge after re-enable is not a rising edge"
    assert again.first_publish_ns <= r2.scheduled_ns <= again.confirmed_ns
    assert (r2.scheduled_ns - r1.scheduled_ns) % (period * MS) != 0, "re-enable kept the old grid"
    assert_pwm(edges, r2.scheduled_ns, edges[-1].scheduled_ns, period, 60 * MS, "re-enabled")
    # While disabled (off, 000) the output stayed off.
    assert_constant(edges, off.confirmed_ns, again.first_publish_ns, 0, "disabled")
    close_trace(proc)


def test_disable_off_switches_output_off_at_once(node_process, ros):
    """000: "a falling edge from 1 to 0 will deactivate the entire function block and set output
    Q1 or Q2 to 0" (on_disable off): at 100 % the output is on; disabling it writes a falling
    edge scheduled at the instant the disable was handled, and it stays off. 002: while
    disabled the channel still computes its on and off times."""
    period = 500
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__duty=100.0)
    on = ch.enable(True)
    edges = wait_trace(proc, lambda es: len(es) >= 2, "the rising edge", spin=ch.ros.spin_once)
    assert on.reply.output, on.reply
    # 002: on enable at 100 % the output goes straight on.
    assert edges[1].level == 1 and on.first_publish_ns <= edges[1].scheduled_ns <= on.confirmed_ns
    ch.spin_for(0.2)

    off = ch.enable(False)
    st = off.reply
    assert (st.enabled, st.output, st.active) == (False, False, False), st
    # A disabled channel still computes t_on / t_off for a new command (002).
    ch.duty(40.0, confirm=lambda s: close(s.duty_commanded, 40.0) and s.on_time_ms == 200.0)
    st = ch.status.messages[-1]
    assert (st.enabled, st.output, st.on_time_ms, st.off_time_ms) == (False, False, 200.0, 300.0)
    t_end = mono_ns() + 3 * period * MS // 2
    observe_until(ch, t_end)

    edges = close_trace(proc)
    run = [e for e in edges[1:] if e.scheduled_ns <= t_end]
    assert [e.level for e in run] == [1, 0], f"expected one pulse ended by the disable: {run}"
    fall = run[1]
    assert off.first_publish_ns <= fall.scheduled_ns <= off.confirmed_ns, (
        "the falling edge was not scheduled at the disable"
    )
    assert_written_in_time(run, "disable")


def test_disable_hold_keeps_the_output_level(node_process, ros):
    """004: "if the signal at i_xEn is removed, the output signal remains at its current value"
    (profile frequency_output, on_disable hold): at 100 % the output stays on after the disable,
    with no edge while disabled; 000's off would have switched it off."""
    period = 200
    proc, ch = start(
        node_process, ros, pw01__profile="frequency_output", pw01__period_ms=period,
        pw01__duty=100.0,
    )
    on = ch.enable(True)
    assert on.reply.output, on.reply
    ch.spin_for(0.1)
    off = ch.enable(False)
    st = off.reply
    assert not st.enabled and st.output, f"hold: the output went off on disable: {st}"
    t_end = off.confirmed_ns + 5 * period * MS
    observe_until(ch, t_end)
    st = ch.status.messages[-1]
    assert (st.enabled, st.output) == (False, True), st

    edges = close_trace(proc)
    assert_constant(edges, off.first_publish_ns, t_end, 1, "held after disable")


# ---------------------------------------------------------------------------------------------
# When a command takes effect
# ---------------------------------------------------------------------------------------------


def wait_rise(ch: ChannelClient, start: int, min_seq: int = 0) -> int:
    """Waits for a rising edge on the edges topic (message index >= start, seq >= min_seq);
    returns its seq."""
    m = ch.edges.wait_for(lambda e: e.level and e.seq >= min_seq, start=start,
                          what="a rising edge")
    return m.seq


def trace_rows(proc, ch: ChannelClient, seq_to: int) -> list[Edge]:
    """The trace rows of the channel up to edge seq `seq_to` (row k is edge seq k)."""
    return wait_trace(proc, lambda es: len(es) > seq_to, f"edge {seq_to} in the trace",
                      channel=ch.channel, spin=ch.ros.spin_once)


IMMEDIATE = dict(pw01__profile="tcont_cp", pw01__period_ms=500, pw01__min_on_ms=100,
                 pw01__enable=True)
ATTEMPTS = 4


def test_immediate_extends_a_running_pulse(node_process, ros):
    """003: "the calculated manipulated value is larger than the previous impulse length /
    PER_TM: then the impulse is extended" (profile tcont_cp, apply_at immediate): a pulse of
    30 % of 500 ms, raised to 70 % while it runs, ends exactly 350 ms after its rise; the break
    is then the new 150 ms, so the period stays 500 ms."""
    proc, ch = start(node_process, ros, pw01__duty=30.0, **IMMEDIATE)
    outcomes = []
    for attempt in range(ATTEMPTS):
        ch.duty(30.0, confirm=lambda s: close(s.duty_commanded, 30.0) and s.on_time_ms == 150.0)
        k = wait_rise(ch, len(ch.edges.messages))
        sent = ch.duty(70.0)
        rows = trace_rows(proc, ch, k + 2)
        rise, fall, next_rise = rows[k], rows[k + 1], rows[k + 2]
        assert rise.level == 1 and fall.level == 0 and next_rise.level == 1, rows[k:]
        if sent.confirmed_ns < rise.scheduled_ns + 150 * MS:
            # Handled inside the 150 ms pulse: it must have been extended.
            # 003: the impulse is extended to 350 ms of real length, from its real rise.
            assert from_real_rise(rise, fall, 350 * MS), (
                f"pulse of {(fall.scheduled_ns - rise.scheduled_ns) / MS} ms, expected 350"
            )
            assert next_rise.scheduled_ns - fall.scheduled_ns == 150 * MS
            assert_written_in_time(rows[k:k + 3], "extended pulse")
            break
        if from_real_rise(rise, fall, 350 * MS):
            break  # extended, though the confirmation came late
        outcomes.append(f"attempt {attempt}: handled after the 150 ms pulse ended")
    else:
        pytest.fail("no 70 % command was handled inside a running 150 ms pulse in "
                    f"{ATTEMPTS} attempts: {outcomes}")
    st = ch.status.messages[-1]
    assert (st.on_time_ms, st.off_time_ms) == (350.0, 150.0), st
    close_trace(proc)


def test_immediate_ends_a_pulse_at_once_but_not_below_min_on(node_process, ros):
    """003: "the calculated manipulated value is less than or equal to the previous impulse
    length / PER_TM: then no impulse signal will be emitted" (profile tcont_cp): a 70 % pulse
    (350 ms of 500) that has run 170 ms or more ends the instant 25 % (125 ms) is handled, and
    the break is the new 375 ms; SPEC 1.3 / 003's P_B_TM: a command that would end a pulse
    before min_on (100 ms) ends it exactly at min_on."""
    proc, ch = start(node_process, ros, pw01__duty=70.0, **IMMEDIATE)
    period = 500

    # Ended at once: the command lowers t_on below the time already on.
    for attempt in range(ATTEMPTS):
        ch.duty(70.0, confirm=lambda s: close(s.duty_commanded, 70.0) and s.on_time_ms == 350.0)
        start_idx = len(ch.edges.messages)
        k = wait_rise(ch, start_idx)
        rise_seen = mono_ns()
        observe_until(ch, rise_seen + 170 * MS)
        sent = ch.duty(25.0)
        rows = trace_rows(proc, ch, k + 2)
        rise, fall, next_rise = rows[k], rows[k + 1], rows[k + 2]
        if sent.first_publish_ns >= rise.scheduled_ns + 350 * MS:
            continue  # the pulse had ended by itself before the command was sent
        assert fall.scheduled_ns - rise.scheduled_ns >= 170 * MS, (rise, fall)
        if fall.scheduled_ns == rise.scheduled_ns + 350 * MS and (
            sent.confirmed_ns > rise.scheduled_ns + 350 * MS
        ):
            continue  # handled only after the pulse ended by itself
        assert sent.first_publish_ns <= fall.scheduled_ns <= sent.confirmed_ns, (
            "the pulse did not end when 25 % was handled: "
            f"ended {(fall.scheduled_ns - rise.scheduled_ns) / MS} ms after its rise, command "
            f"handled {(sent.first_publish_ns - rise.scheduled_ns) / MS}.."
            f"{(sent.confirmed_ns - rise.scheduled_ns) / MS} ms after it"
        )
        assert fall.scheduled_ns < rise.scheduled_ns + 350 * MS
        assert next_rise.scheduled_ns - fall.scheduled_ns == t_on_ns(0.75, period)
        break
    else:
        pytest.fail(f"no 25 % command landed inside a running 350 ms pulse in {ATTEMPTS} tries")

    # Never below min_on: 5 % (25 ms, itself below min_on: suppressed) just after a rise.
    exact_min = False
    for attempt in range(ATTEMPTS):
        ch.duty(70.0, confirm=lambda s: close(s.duty_commanded, 70.0) and s.on_time_ms == 350.0)
        k = wait_rise(ch, len(ch.edges.messages))
        sent = ch.duty(5.0)
        rows = trace_rows(proc, ch, k + 1)
        rise, fall = rows[k], rows[k + 1]
        on = fall.scheduled_ns - rise.scheduled_ns
        assert on >= 100 * MS, f"a {on / MS} ms pulse, below min_on 100 ms"
        if sent.confirmed_ns < rise.scheduled_ns + 100 * MS:
            assert from_real_rise(rise, fall, 100 * MS), (
                f"pulse cut at {on / MS} ms, expected exactly min_on 100 ms from its real rise"
            )
            exact_min = True
            break
    if not exact_min:
        pytest.fail(f"no 5 % command was handled within 100 ms of a rise in {ATTEMPTS} tries")
    ch.wait_status(lambda s: s.rule == "suppressed_pulse" and s.e1, "5 % suppressed", sent.index)
    ch.wait_e1(True, "5 % below min_on")
    close_trace(proc)


def test_next_period_applies_a_command_from_the_next_period(node_process, ros):
    """000 (profile pico_gfx, apply_at next_period): the running period completes with the
    times computed at its start and the new duty applies from the next period; the grid never
    shifts. 30 % <-> 70 % of 400 ms, commanded just after a rise."""
    period = 400
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__duty=30.0,
                     pw01__enable=True)
    old, new = 30.0, 70.0
    checked_inside = 0
    records = []
    min_seq = 0
    for attempt in range(ATTEMPTS):
        k = wait_rise(ch, len(ch.edges.messages), min_seq)
        min_seq = k + 6
        sent = ch.duty(new)
        records.append((k, old, new, sent))
        rows = trace_rows(proc, ch, k + 5)
        rise = rows[k]
        if sent.confirmed_ns < rise.scheduled_ns + t_on_ns(old / 100, period):
            checked_inside += 1
        old, new = new, old
        if checked_inside >= 1 and attempt >= 1:
            break
    edges = close_trace(proc)
    grid0 = edges[records[0][0]].scheduled_ns
    for k, old_pct, new_pct, sent in records:
        rise = edges[k]
        assert (rise.scheduled_ns - grid0) % (period * MS) == 0, "the period grid shifted"
        ps = pulses(edges[k:k + 6])
        assert len(ps) >= 3, edges[k:k + 6]
        # The period running when the command arrived completes with the old on time.
        assert ps[0][1].scheduled_ns - ps[0][0].scheduled_ns == t_on_ns(old_pct / 100, period), (
            f"{old_pct} -> {new_pct} %: the running period did not keep its on time"
        )
        new_seen = 0
        for r, f in ps[1:]:
            assert (r.scheduled_ns - rise.scheduled_ns) % (period * MS) == 0
            if r.scheduled_ns > sent.confirmed_ns:  # a period started after the command
                new_seen += 1
                assert f.scheduled_ns - r.scheduled_ns == t_on_ns(new_pct / 100, period), (
                    f"{old_pct} -> {new_pct} %: a later period did not take the new on time"
                )
        assert new_seen >= 1, f"{old_pct} -> {new_pct} %: no period after the command"
    assert checked_inside >= 1, "no command landed inside a running pulse"


# ---------------------------------------------------------------------------------------------
# Bad commands
# ---------------------------------------------------------------------------------------------


def test_non_finite_commands_are_refused_and_the_last_good_one_kept(node_process, ros):
    """001: on an error "the loop output is frozen": NaN, +inf and -inf on ~/pw01/duty are
    refused, the last good command (40 %) stays in force (status and the output pattern
    unchanged), and /diagnostics says WARN with the reason; the node keeps running."""
    period = 200
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__duty=40.0,
                     pw01__enable=True)
    ch.wait_status(lambda s: close(s.duty_commanded, 40.0) and s.enabled, "40 % enabled")
    first_bad = mono_ns()
    status_from = len(ch.status.messages)
    for n, (value, reason) in enumerate(
        [(math.nan, "nan"), (math.inf, "infinite"), (-math.inf, "infinite")], start=1
    ):
        sent = ch.send(
            ch.duty_pub,
            Float64(data=value),
            ch.diagnostics,
            lambda a, n=n: (d := ch.my_diag(a)) is not None
            and int(diag_values(d)["rejected_commands"]) >= n,
            f"diagnostics counting {n} refused commands",
        )
        d = ch.my_diag(sent.reply)
        assert diag_level(d) == WARN, d
        assert reason in diag_values(d)["last_rejection"].lower(), d
        assert "refused" in d.message and reason in d.message.lower(), d
        assert diag_values(d)["duty_commanded_pct"] == "40.000", d
    ch.spin_for(0.5)
    last_bad = mono_ns()
    for s in ch.status.messages[status_from:]:
        assert close(s.duty_commanded, 40.0) and not s.command_clamped, s
        assert s.enabled and s.on_time_ms == 80.0 and s.rule == "exact", s
    assert proc.is_running()
    edges = wait_trace(proc, lambda es: len(pulses(after(es, last_bad))) >= 2,
                       "pulses after the refused commands", spin=ch.ros.spin_once)
    ps = assert_pwm(edges, edges[1].scheduled_ns, edges[-1].scheduled_ns, period, 80 * MS,
                    "40 % across the refused commands")
    assert ps[0][0].scheduled_ns < first_bad and ps[-1][0].scheduled_ns > last_bad
    close_trace(proc)


def test_out_of_range_commands_are_clamped_and_flagged(node_process, ros):
    """001, 002: the input is "internally limited to 0..100 %"; 000: SV 0..4095. -5 % runs as
    0 %, 150 % as 100 %, SV 5000 as 100 %, each with command_clamped true and WARN on
    /diagnostics; a valid command clears the flag; the node keeps running."""
    period = 200
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__duty=40.0,
                     pw01__enable=True)
    windows = []

    def clamped(sent: Sent, pct_expected: float, level: int, text: str, diag_from: int) -> None:
        st = sent.reply
        assert st.command_clamped and st.duty_commanded == pct_expected, st
        d = ch.wait_diag(lambda d: text in diag_values(d)["last_clamp"], f"clamp of {text}",
                         start=diag_from)
        assert diag_level(d) == WARN and diag_values(d)["command_clamped"] == "true", d
        assert "out of range" in d.message, d
        w = window_after(sent, 3, period)
        observe_until(ch, w[1])
        windows.append((text, *w, level))

    diag_from = len(ch.diagnostics.messages)
    low = ch.duty(-5.0, confirm=lambda s: s.duty_commanded == 0.0 and s.command_clamped)
    clamped(low, 0.0, 0, "-5", diag_from)
    diag_from = len(ch.diagnostics.messages)
    high = ch.duty(150.0, confirm=lambda s: s.duty_commanded == 100.0 and s.command_clamped)
    clamped(high, 100.0, 1, "150", diag_from)
    good = ch.duty(50.0, confirm=lambda s: close(s.duty_commanded, 50.0))
    assert not good.reply.command_clamped, good.reply
    diag_from = len(ch.diagnostics.messages)
    sv = ch.sv(5000, lambda s: s.duty_commanded == 100.0 and s.command_clamped)
    clamped(sv, 100.0, 1, "SV 5000", diag_from)
    good = ch.sv(2000, lambda s: close(s.duty_commanded, 2000 / 4095 * 100, 1e-9))
    assert not good.reply.command_clamped, good.reply
    d = ch.wait_diag(lambda d: diag_values(d)["command_clamped"] == "false", "clamp cleared",
                     start=len(ch.diagnostics.messages))
    assert int(diag_values(d)["clamped_commands"]) >= 3, d
    edges = close_trace(proc)
    for what, a, b, level in windows:
        assert_constant(edges, a, b, level, what)


# ---------------------------------------------------------------------------------------------
# Watchdog
# ---------------------------------------------------------------------------------------------


def test_watchdog_switches_off_at_the_deadline_and_recovers(node_process, ros):
    """SPEC 1 (command_timeout_ms): no command for the timeout puts the channel in its safe
    state, off: at 100 % the output falls exactly one timeout after the last command was
    handled, status watchdog_tripped and diagnostics ERROR; the next command recovers."""
    period, timeout = 200, 1000
    proc, ch = start(node_process, ros, pw01__period_ms=period, pw01__enable=True,
                     pw01__command_timeout_ms=timeout)
    # The channel was enabled at start-up with no command: on a slow start the watchdog trips
    # before the command, at 0 % commanded. Only an ERROR at 100 % commanded, after the command,
    # is the trip it causes.
    diag_from = len(ch.diagnostics.messages)
    first = ch.duty(100.0, confirm=lambda s: s.duty_commanded == 100.0 and not s.watchdog_tripped)
    tripped = ch.wait_status(lambda s: s.watchdog_tripped, "watchdog tripped",
                             start=len(ch.status.messages))
    assert not tripped.output and not tripped.active, tripped
    assert tripped.duty_commanded == 100.0, tripped
    d = ch.wait_diag(
        lambda d: diag_level(d) == ERROR and diag_values(d)["duty_commanded_pct"] == "100.000",
        "ERROR for the watchdog after the command",
        start=diag_from,
    )
    assert diag_values(d)["watchdog_tripped"] == "true" and "watchdog" in d.message, d
    t_quiet = mono_ns()
    observe_until(ch, t_quiet + 3 * period * MS)

    # The OK may be published with the status that shows the output on again: look from the
    # command on.
    diag_from = len(ch.diagnostics.messages)
    second = ch.duty(100.0, confirm=lambda s: s.duty_commanded == 100.0 and not s.watchdog_tripped)
    ch.wait_status(lambda s: s.output, "output on again", start=second.index)
    d = ch.wait_diag(lambda d: diag_level(d) == OK, "OK after recovery", start=diag_from)
    assert diag_values(d)["watchdog_tripped"] == "false", d
    ch.wait_status(lambda s: s.watchdog_tripped, "watchdog tripped again",
                   start=len(ch.status.messages))

    edges = close_trace(proc)
    for sent, what in ((first, "first"), (second, "second")):
        run = after(edges, sent.first_publish_ns)
        assert len(run) >= 2 and run[0].level == 1 and run[1].level == 0, (what, run)
        # The rise comes at a period start after the command, the fall at the deadline.
        assert run[0].scheduled_ns <= sent.confirmed_ns + period * MS, (what, run[0])
        lo = sent.first_publish_ns + timeout * MS
        hi = sent.confirmed_ns + timeout * MS
        assert lo <= run[1].scheduled_ns <= hi, (
            f"{what} trip {(run[1].scheduled_ns - sent.first_publish_ns) / MS} ms after the "
            f"command was sent, expected {timeout} ms after it was handled (handled within "
            f"{(sent.confirmed_ns - sent.first_publish_ns) / MS} ms of sending)"
        )
        assert_written_in_time(run[:2], f"{what} trip")
    # Off while tripped: nothing between the first trip and the recovery command.
    assert_constant(edges, t_quiet, second.first_publish_ns, 0, "tripped")
