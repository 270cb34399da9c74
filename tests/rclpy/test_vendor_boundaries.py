"""The vendor rules at their boundaries, and the minimum times as a promise about the line, proved
from outside: real rclpy clients command the built node over ROS and read its CSV trace.

As in test_channel_rules.py, rule-driven instants are checked on the trace's `scheduled_ns` (the
instants the timing core chose) against the bounds of when the node handled a command; phases
that must respect a minimum are checked on both the scheduled and the written (`t_ns`) times,
since the minimum is a property of the line.
"""

from __future__ import annotations

from typing import Sequence

from std_msgs.msg import Float64

from helpers_rules import (
    MS,
    NODE,
    WRITE_TOL_NS,
    Edge,
    after,
    diag_values,
    mono_ns,
    pulses,
    t_on_ns,
    trace_edges,
    wait_trace,
)
from test_channel_rules import (
    assert_constant,
    assert_pwm,
    close,
    close_all_traces,
    close_trace,
    observe_until,
    start,
    window_after,
)


def phases(edges: Sequence[Edge], written: bool) -> list[tuple[int, int, int]]:
    """(level, start, length) of each complete phase between consecutive edges, ns."""
    t = [e.t_ns if written else e.scheduled_ns for e in edges]
    return [(a.level, t[i], t[i + 1] - t[i]) for i, (a, _b) in enumerate(zip(edges, edges[1:]))]


def assert_no_phase_below(edges: Sequence[Edge], min_on: int, min_off: int, what: str) -> None:
    """No pulse shorter than min_on and no break shorter than min_off, on the scheduled times
    and on the times the edges were really written."""
    for written in (False, True):
        for level, t0, length in phases(edges, written):
            floor = min_on if level else min_off
            kind = "pulse" if level else "break"
            assert length >= floor, (
                f"{what}: a {length / MS:.3f} ms {kind} ({'written' if written else 'scheduled'}"
                f" times) at {t0}, below its {floor / MS:.0f} ms minimum"
            )


# ---------------------------------------------------------------------------------------------
# 003: the previous impulse/break length is the line's real one
# ---------------------------------------------------------------------------------------------


#: The status rate the boundary tests watch the countdown at: a status every 100 ms lands in
#: the first 150 ms of some period; at the default 1 Hz, on a channel without edges, the
#: periodic status keeps one phase against a 1 s period and may never land there.
WATCH_STATUS_HZ = 10.0


def just_after_boundary(ch, remaining: str, period_ms: float = 1000.0) -> None:
    """Waits for a status taken less than 150 ms into a period (its `remaining` field, the
    running step's remaining time, above period - 150 ms). The node must publish its status at
    `WATCH_STATUS_HZ`."""
    ch.wait_status(lambda s: getattr(s, remaining) > period_ms - 150.0,
                   f"{remaining} above {period_ms - 150.0} ms", start=len(ch.status.messages))


def test_immediate_starts_the_impulse_at_once_after_a_long_break(node_process, ros):
    """003 (tcont_cp): "the calculated manipulated value is larger than the previous break
    length: the impulse starts". 5 % of 1 s is suppressed (50 ms < P_B_TM 100 ms), so the line
    has been low for well over a period when 50 % arrives: the impulse starts the instant the
    command is handled, not at the next boundary of a period the output never showed, and lasts
    500 ms."""
    proc, ch = start(node_process, ros, pw01__profile="tcont_cp", pw01__period_ms=1000,
                     pw01__min_on_ms=100, pw01__duty=5.0, pw01__enable=True,
                     status_rate_hz=WATCH_STATUS_HZ)
    ch.wait_status(lambda s: s.enabled and s.rule == "suppressed_pulse", "5 % suppressed")
    observe_until(ch, mono_ns() + 1100 * MS)
    # Just after a period boundary the output did not show (under 150 ms into the period):
    # counted from that boundary the break would be too short for 50 %, counted from the
    # line's last edge it is long over.
    just_after_boundary(ch, "remaining_off_ms")
    sent = ch.duty(50.0)
    edges = wait_trace(proc, lambda es: len(pulses(es)) >= 1, "the 50 % impulse",
                       spin=ch.ros.spin_once)
    (rise, fall) = pulses(edges)[0]
    assert sent.first_publish_ns <= rise.scheduled_ns <= sent.confirmed_ns, (
        "the impulse did not start when 50 % was handled: "
        f"{(rise.scheduled_ns - sent.first_publish_ns) / MS:.1f} ms after the publish, "
        f"confirmed {(sent.confirmed_ns - sent.first_publish_ns) / MS:.1f} ms after it"
    )
    assert fall.scheduled_ns - rise.scheduled_ns == 500 * MS
    close_trace(proc)


def test_immediate_ends_the_impulse_at_once_after_a_long_pulse(node_process, ros):
    """003, the mirror case: 95 % of 1 s (break 50 ms < 100 ms suppressed) holds the line high;
    50 % ends the impulse the instant it is handled, and the break then lasts 500 ms."""
    proc, ch = start(node_process, ros, pw01__profile="tcont_cp", pw01__period_ms=1000,
                     pw01__min_on_ms=100, pw01__duty=95.0, pw01__enable=True,
                     status_rate_hz=WATCH_STATUS_HZ)
    wait_trace(proc, lambda es: len(es) >= 2 and es[-1].level == 1, "the line high",
               spin=ch.ros.spin_once)
    observe_until(ch, mono_ns() + 1100 * MS)
    just_after_boundary(ch, "remaining_on_ms")
    sent = ch.duty(50.0)
    edges = wait_trace(proc, lambda es: len(es) >= 4, "the fall and the next rise",
                       spin=ch.ros.spin_once)
    rise, fall, again = edges[1], edges[2], edges[3]
    assert (rise.level, fall.level, again.level) == (1, 0, 1), edges
    assert sent.first_publish_ns <= fall.scheduled_ns <= sent.confirmed_ns, (
        "the impulse did not end when 50 % was handled"
    )
    assert again.scheduled_ns - fall.scheduled_ns == 500 * MS
    close_trace(proc)


# ---------------------------------------------------------------------------------------------
# 004: the band at its boundaries
# ---------------------------------------------------------------------------------------------


def test_band_worked_example_and_upper_boundary(node_process, ros):
    """004's worked example: edge 0.5 and input 0.5 give 50 % PWM (500 ms / 500 ms at a 1 s time
    base; 100 / 100 ms here). And an input exactly at 1 - edge is PWM as written, whatever the
    float rounding: 67 % at edge 0.33 pulses 67 % (pw02), as 20 % at edge 0.2 does."""
    period = 200
    proc, a, b = start(node_process, ros, channels=("pw01", "pw02"),
                       pw01__profile="frequency_output", pw01__period_ms=period,
                       pw01__edge_band=0.5, pw01__enable=True,
                       pw02__profile="frequency_output", pw02__period_ms=period,
                       pw02__edge_band=0.33, pw02__enable=True)
    sa = a.duty(50.0, confirm=lambda s: close(s.duty_commanded, 50.0) and s.rule == "exact")
    sb = b.duty(67.0, confirm=lambda s: close(s.duty_commanded, 67.0) and s.rule == "exact")
    wa, wb = window_after(sa, 3, period), window_after(sb, 3, period)
    observe_until(a, max(wa[1], wb[1]) + period * MS)
    traces = close_all_traces(proc, ("pw01", "pw02"))
    assert_pwm(traces["pw01"], *wa, period, 100 * MS, "edge 0.5, input 0.5")
    assert_pwm(traces["pw02"], *wb, period, t_on_ns(0.67, period), "edge 0.33, input 0.67")


# ---------------------------------------------------------------------------------------------
# 000, 002: minima that do not fit in the period are valid vendor settings
# ---------------------------------------------------------------------------------------------


def test_minima_beyond_half_the_period_are_accepted_and_give_0_or_1(node_process, ros):
    """000's relay table with PD 150 ms and ME 100 ms (min off = min on), Pico GFX ME above
    PD/2, and 002's nMinSwiTi = nPrd are accepted over the parameter services. With the relay
    setting every duty gives a constant output for the period, with E1: 30 % (45 ms < 100 ms)
    gives 0, 80 % (break 30 ms < 100 ms) gives 1."""
    proc, ch = start(node_process, ros, pw01__output_kind="relay", pw01__period_ms=150,
                     pw01__enable=True)
    results = ros.set_parameters(NODE, {"pw01.min_on_ms": 100})
    assert results["pw01.min_on_ms"].successful, results["pw01.min_on_ms"].reason
    results = ros.set_parameters(NODE, {"pw02.period_ms": 1000, "pw02.min_on_ms": 600})
    assert all(r.successful for r in results.values()), results
    result = ros.set_parameters_atomically(
        NODE, {"pw02.profile": "twincat_ba", "pw02.min_on_ms": 1000}
    )
    assert result.successful, result.reason
    values = ros.get_parameters(NODE, ["pw01.min_on_ms", "pw02.min_on_ms", "pw02.profile"])
    assert values == {"pw01.min_on_ms": 100, "pw02.min_on_ms": 1000,
                      "pw02.profile": "twincat_ba"}

    low = ch.duty(30.0, confirm=lambda s: close(s.duty_commanded, 30.0)
                  and s.rule == "suppressed_pulse")
    assert low.reply.e1 and low.reply.period_ms == 150.0
    ch.wait_e1(True, "30 % of 150 ms below ME 100 ms")
    w_low = window_after(low, 4, 150)
    observe_until(ch, w_low[1])
    high = ch.duty(80.0, confirm=lambda s: close(s.duty_commanded, 80.0)
                   and s.rule == "suppressed_break")
    assert high.reply.e1
    w_high = window_after(high, 4, 150)
    observe_until(ch, w_high[1])
    edges = close_trace(proc)
    assert_constant(edges, *w_low, 0, "30 % with ME 100 ms of PD 150 ms")
    assert_constant(edges, *w_high, 1, "80 % with ME 100 ms of PD 150 ms")


# ---------------------------------------------------------------------------------------------
# 004's hold and the watchdog
# ---------------------------------------------------------------------------------------------


def test_the_watchdog_switches_off_a_line_held_on(node_process, ros):
    """004's hold keeps the line high after a disable; the watchdog (command_timeout_ms 600)
    covers every state in which the line is high, so when commands stop the held line goes off
    600 ms after the last command, and the channel reports the trip. (Edge band 0.1: 99 % lies
    above 1 - edge, a constant TRUE.)"""
    proc, ch = start(node_process, ros, pw01__profile="frequency_output", pw01__period_ms=200,
                     pw01__edge_band=0.1, pw01__command_timeout_ms=600)
    ch.duty(100.0)
    ch.enable(True)
    wait_trace(proc, lambda es: len(es) >= 2 and es[-1].level == 1, "the line high",
               spin=ch.ros.spin_once)
    last = ch.duty(99.0)
    off = ch.enable(False)
    after_disable = len(ch.status.messages)
    assert off.reply.output, "hold keeps the line high after the disable"
    edges = wait_trace(proc, lambda es: es[-1].level == 0, "the watchdog's off edge",
                       spin=ch.ros.spin_once, timeout=10.0)
    fall = edges[-1]
    assert last.first_publish_ns + 600 * MS <= fall.scheduled_ns <= last.confirmed_ns + 600 * MS
    ch.wait_status(
        lambda s: s.watchdog_tripped and not s.output, "tripped, output off", start=after_disable
    )
    close_trace(proc)


def test_a_held_line_goes_off_when_on_disable_becomes_off(node_process, ros):
    """A line held on by 004's hold stays on only while the configuration holds it: setting
    on_disable to `off` while disabled switches it off at once."""
    proc, ch = start(node_process, ros, pw01__profile="frequency_output", pw01__period_ms=200)
    ch.duty(100.0)
    ch.enable(True)
    wait_trace(proc, lambda es: len(es) >= 2 and es[-1].level == 1, "the line high",
               spin=ch.ros.spin_once)
    ch.enable(False)
    observe_until(ch, mono_ns() + 300 * MS)
    assert trace_last_level(proc) == 1, "held high"
    before = mono_ns()
    result = ros.set_parameters(NODE, {"pw01.on_disable": "off"})["pw01.on_disable"]
    assert result.successful, result.reason
    done = mono_ns()
    edges = wait_trace(proc, lambda es: es[-1].level == 0, "the line off",
                       spin=ch.ros.spin_once)
    # Applied when the parameter change reaches the output thread, right after the reply.
    assert before <= edges[-1].scheduled_ns <= done + WRITE_TOL_NS
    close_trace(proc)


def trace_last_level(proc) -> int:
    return trace_edges(proc)[-1].level


# ---------------------------------------------------------------------------------------------
# 000, 002: EN toggling never shortens a break
# ---------------------------------------------------------------------------------------------


def test_en_toggling_never_puts_a_short_break_on_the_line(node_process, ros):
    """000/002: EN's falling edge acts at once; a rising edge starts the on phase only once the
    break since the last real fall has lasted the minimum off time. A relay with a 400 ms
    minimum (on and off), toggled off and on a few ms apart several times: every break on the
    line, scheduled and as written, lasts at least 400 ms, and the re-enabled period starts
    exactly 400 ms after the fall the disable wrote."""
    proc, ch = start(node_process, ros, pw01__output_kind="relay", pw01__period_ms=2000,
                     pw01__min_on_ms=400, pw01__duty=50.0)
    ch.enable(True)
    wait_trace(proc, lambda es: len(es) >= 2, "the first rise", spin=ch.ros.spin_once)
    for _ in range(4):
        ch.enable(False)
        ch.enable(True)
    edges = wait_trace(proc, lambda es: len(es) >= 4, "a rise after the toggling",
                       spin=ch.ros.spin_once, timeout=10.0)
    observe_until(ch, mono_ns() + 500 * MS)
    edges = close_trace(proc)
    # After the initial row. Pulses are not checked: a falling EN ends one at once (000, 002),
    # and so does the shutdown.
    run = edges[1:]
    assert_no_phase_below(run, 0, 400 * MS, "EN toggling")
    falls = [e for e in run if e.level == 0]
    rises = after([e for e in run if e.level == 1], falls[0].scheduled_ns)
    assert rises, run
    assert rises[0].scheduled_ns - falls[0].scheduled_ns >= 400 * MS
    assert rises[0].t_ns - falls[0].t_ns >= 400 * MS


# ---------------------------------------------------------------------------------------------
# 001: split range
# ---------------------------------------------------------------------------------------------


def overlaps(a: Sequence[Edge], b: Sequence[Edge], written: bool) -> list[int]:
    """Instants at which both traces are high (merged in time order; at equal instants a fall
    counts before a rise, as the node writes them)."""
    tagged = sorted(
        [((e.t_ns if written else e.scheduled_ns), e.level, i) for i, es in ((0, a), (1, b))
         for e in es]
    )
    high, out = [0, 0], []
    for t, level, i in tagged:
        high[i] = level
        if high[0] and high[1]:
            out.append(t)
    return out


def test_split_range_drives_one_side_and_never_overlaps(node_process, ros):
    """001's "Hot/Cold or Split Range case": one signed command on ~/split/zone/command drives
    pw01 (hot) when positive and pw02 (cold) when negative, the other held at 0, with a 2 %
    dead band around 0. On every sign change the two lines never overlap (trace, scheduled and
    written times), and the one starting waits out its own minimum break: cold's breaks are never
    below its 150 ms minimum."""
    proc, hot, cold = start(node_process, ros, channels=("pw01", "pw02"), split="zone:pw01:pw02:2",
                            pw01__period_ms=300, pw01__enable=True,
                            pw02__period_ms=500, pw02__min_on_ms=150,
                            pw02__apply_at="immediate", pw02__enable=True)
    command = ros.publisher(Float64, f"{NODE}/split/zone/command")
    ros.wait_for_subscribers(command, 1)

    def signed(value: float, hot_pct: float, cold_pct: float):
        command.publish(Float64(data=value))
        hot.wait_status(lambda s: close(s.duty_commanded, hot_pct), f"hot {hot_pct} %",
                        start=len(hot.status.messages) - 1)
        cold.wait_status(lambda s: close(s.duty_commanded, cold_pct), f"cold {cold_pct} %",
                         start=len(cold.status.messages) - 1)

    signed(1.5, 0.0, 0.0)  # inside the dead band: both off
    for k in range(6):
        if k % 2 == 0:
            signed(80.0, 80.0, 0.0)
        else:
            signed(-70.0, 0.0, 70.0)
        observe_until(hot, mono_ns() + 400 * MS)
    traces = close_all_traces(proc, ("pw01", "pw02"))
    h, c = traces["pw01"][1:], traces["pw02"][1:]
    assert len(pulses(h)) >= 3 and len(pulses(c)) >= 3, (h, c)
    for written in (False, True):
        both = overlaps(h, c, written)
        assert not both, f"hot and cold both high ({'written' if written else 'scheduled'}) at {both}"
    assert_no_phase_below(c, 0, 150 * MS, "cold")


# ---------------------------------------------------------------------------------------------
# The minimum is a property of the line: a stalled process
# ---------------------------------------------------------------------------------------------


def test_stalls_of_the_process_never_shorten_a_phase_below_its_minimum(node_process, ros):
    """A relay at 200 ms / 50 %, minimum 50 ms on and off; the whole node is stopped (SIGSTOP)
    for 80 ms at a time, at random phases, twenty times. An edge written late moves the next one:
    no pulse and no break on the line (written times) is below 50 ms, and every edge was
    written no earlier than scheduled."""
    import random
    import signal

    proc, ch = start(node_process, ros, pw01__output_kind="relay", pw01__period_ms=200,
                     pw01__duty=50.0, pw01__enable=True)
    wait_trace(proc, lambda es: len(es) >= 3, "pulsing", spin=ch.ros.spin_once)
    rng = random.Random(8)
    for _ in range(20):
        observe_until(ch, mono_ns() + rng.randrange(20, 150) * MS)
        proc.send_signal(signal.SIGSTOP)
        stopped = mono_ns()
        while mono_ns() - stopped < 80 * MS:
            pass
        proc.send_signal(signal.SIGCONT)
    observe_until(ch, mono_ns() + 500 * MS)
    edges = close_trace(proc)[1:]
    assert len(edges) > 20, edges
    late = [e for e in edges if e.t_ns < e.scheduled_ns]
    assert not late, f"written before their schedule: {late}"
    # The shutdown edge may cut the last pulse: leave it out.
    for level, t0, length in phases(edges[:-1], written=True):
        assert length >= 50 * MS, (
            f"a {length / MS:.3f} ms {'pulse' if level else 'break'} on the line at {t0}"
        )


def test_a_stopped_and_continued_node_keeps_its_ros_side(node_process, ros):
    """A node stopped and continued (SIGSTOP or Ctrl-Z, then SIGCONT; a debugger attaching)
    keeps talking ROS: the DDS threads' waits return EINTR at the continue (signal(7)), which
    ended both threads before the vendored rustdds's twelfth change and left the node running
    its lines with no ROS at all. After five stops, the node still answers get_parameters,
    takes a duty command and reports it on its status."""
    import signal
    import time

    proc, ch = start(node_process, ros, pw01__period_ms=200, pw01__enable=True)
    ch.duty(20.0)
    for _ in range(5):
        proc.send_signal(signal.SIGSTOP)
        time.sleep(0.1)
        proc.send_signal(signal.SIGCONT)
        time.sleep(0.1)
    values = ros.get_parameters(NODE, ["pw01.period_ms"], timeout=10.0)
    assert values == {"pw01.period_ms": 200}, values
    sent = ch.duty(60.0)
    assert sent.reply.duty_commanded == 60.0, sent.reply
    assert proc.popen.poll() is None, "the node ended"


# ---------------------------------------------------------------------------------------------
# Fault value after a watchdog trip (fault mode of PLC output modules)
# ---------------------------------------------------------------------------------------------


def test_the_watchdog_runs_the_fault_value_then_off(node_process, ros):
    """No command for command_timeout_ms (500) trips the watchdog; with fault_duty_pct 25 the
    channel then runs 25 % of its 200 ms period (50 ms pulses) for fault_hold_ms (1000), then
    switches off until the next command. Status and /diagnostics say the fault value runs."""
    proc, ch = start(node_process, ros, pw01__period_ms=200, pw01__command_timeout_ms=500,
                     pw01__fault_duty_pct=25.0, pw01__fault_hold_ms=1000)
    ch.duty(80.0)
    ch.enable(True)
    last = ch.duty(79.0)
    trip_lo = last.first_publish_ns + 500 * MS
    trip_hi = last.confirmed_ns + 500 * MS
    st = ch.wait_status(lambda s: s.watchdog_tripped, "watchdog tripped", start=last.index)
    ch.wait_diag(lambda d: diag_values(d).get("fault_value_active") == "true",
                 "fault value running")
    observe_until(ch, trip_hi + 2500 * MS)
    edges = close_trace(proc)
    during = [p for p in pulses(edges)
              if trip_hi + 200 * MS <= p[0].scheduled_ns <= trip_lo + 800 * MS]
    assert len(during) >= 2, (st, edges)
    for rise, fall in during:
        assert fall.scheduled_ns - rise.scheduled_ns == 50 * MS, (rise, fall)
    late_rises = [e for e in edges if e.level == 1 and e.scheduled_ns > trip_hi + 1000 * MS]
    assert not late_rises, f"pulses after the hold time: {late_rises}"
    assert edges[-1].level == 0
