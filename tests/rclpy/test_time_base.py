"""The time base from outside: a zero-cross SSR on 60 Hz mains switches only at the
half-cycle zero crossings, so it turns every pulse into whole half cycles. Two channels run the
same command side by side, one with `time_base_ms` = 8.333333 (a 60 Hz half cycle, 8 333 333 ns
on the monotonic clock) and one without; the CSV trace's scheduled instants are checked to the
nanosecond, and the energy a zero-cross SSR would deliver is computed from them for an arbitrary
mains phase.
"""

from __future__ import annotations

import math
from typing import Sequence

from helpers_rules import MS, ChannelClient, Edge, diag_values, node_args, pulses, wait_trace

#: A 60 Hz half cycle, ms, and the tick the node makes of it (rounded to the ns).
HALF_CYCLE_MS = 8.333333
TICK_NS = 8_333_333
#: 200 ms is 24.000001 half cycles: the period in force is 24 ticks.
PERIOD_MS = 200
PERIOD_TICKS = 24
#: 37.1 % of 24 ticks is 8.904 ticks: not a whole number of them.
DUTY_PCT = 37.1
PERIODS = 50


def ssr_conduction(edges: Sequence[Edge], phase_ns: int) -> int:
    """The time a zero-cross SSR conducts for the pulses of `edges`, ns: it turns on at the
    first zero crossing at or after a rise and off at the first one at or after a fall, the
    zero crossings lying at `phase_ns + k * TICK_NS`."""

    def crossing(t: int) -> int:
        return phase_ns + math.ceil((t - phase_ns) / TICK_NS) * TICK_NS

    return sum(crossing(f.scheduled_ns) - crossing(r.scheduled_ns) for r, f in pulses(edges))


def on_in(edges: Sequence[Edge], start: int, end: int) -> int:
    """The scheduled on time within [start, end), ns."""
    return sum(
        max(0, min(f.scheduled_ns, end) - max(r.scheduled_ns, start)) for r, f in pulses(edges)
    )


def test_sixty_hz_half_cycles_deliver_the_commanded_duty_over_50_periods(node_process, ros):
    proc = node_process(
        node_args(
            pw01__period_ms=PERIOD_MS,
            pw01__time_base_ms=HALF_CYCLE_MS,
            pw02__period_ms=PERIOD_MS,
        )
    )
    ticked, plain = ChannelClient(ros, "pw01"), ChannelClient(ros, "pw02")
    for c in (ticked, plain):
        c.wait_connected()
    status = ticked.wait_status(lambda s: s.time_base_ms > 0, "the time base reported")
    assert math.isclose(status.time_base_ms, TICK_NS / MS, abs_tol=1e-9)
    # The period in force is 24 whole ticks (199.999992 ms).
    assert math.isclose(status.period_ms, PERIOD_TICKS * TICK_NS / MS, abs_tol=1e-9)
    assert plain.wait_status(lambda s: True, "pw02 status").time_base_ms == 0.0
    diag = ticked.wait_diag(lambda s: "time_base_ms" in diag_values(s), "time base shown")
    assert diag_values(diag)["time_base_ms"] == f"{TICK_NS / MS:.6f}"

    for c in (ticked, plain):
        c.duty(DUTY_PCT)
    for c in (ticked, plain):
        c.enable(True)
    period_ns = PERIOD_TICKS * TICK_NS
    runs = {}
    for c, period in ((ticked, period_ns), (plain, PERIOD_MS * MS)):
        edges = wait_trace(
            proc,
            lambda es: len([e for e in es if e.level == 1]) >= PERIODS + 1,
            f"{PERIODS + 1} rises",
            channel=c.channel,
            timeout=PERIODS * PERIOD_MS / 1000 + 30,
            spin=ros.spin_once,
        )
        first = next(e for e in edges if e.level == 1).scheduled_ns
        runs[c.channel] = (edges, first, period)

    # With the time base: every edge on the grid of the monotonic clock, every pulse 8 or 9
    # ticks, and over any run of consecutive periods the on time within a tick of the command.
    edges, first, period = runs["pw01"]
    live = [e for e in edges if e.scheduled_ns >= first]
    assert all(e.scheduled_ns % TICK_NS == 0 for e in live), "an edge off the tick grid"
    lengths = [f.scheduled_ns - r.scheduled_ns for r, f in pulses(live)][:PERIODS]
    assert set(lengths) <= {8 * TICK_NS, 9 * TICK_NS}, lengths
    per_period = [on_in(live, first + k * period, first + (k + 1) * period) for k in range(PERIODS)]
    for i in range(PERIODS):
        for j in range(i + 1, PERIODS + 1):
            want = DUTY_PCT / 100 * (j - i) * period
            got = sum(per_period[i:j])
            assert abs(got - want) <= TICK_NS, f"periods {i}..{j}: {got} ns, {want:.0f} ns commanded"
    window = (first, first + PERIODS * period)
    ticked_on = on_in(live, *window)
    # The same run without a time base: exact to the ns on the line, 74.2 ms every pulse.
    edges2, first2, period2 = runs["pw02"]
    live2 = [e for e in edges2 if e.scheduled_ns >= first2]
    window2 = (first2, first2 + PERIODS * period2)
    plain_on = on_in(live2, *window2)
    assert plain_on == PERIODS * round(DUTY_PCT / 100 * PERIOD_MS * MS)

    # What a zero-cross SSR makes of them, for a few mains phases: whole ticks pass unchanged;
    # 74.2 ms pulses become 75 ms (or 66.7 ms) of mains, a drift of several half cycles.
    inside = lambda es, w: [e for e in es if w[0] <= e.scheduled_ns <= w[1]]  # noqa: E731
    for phase in (0, 1_234_567, 4_166_666, 7_000_001):
        ssr_ticked = ssr_conduction(inside(live, window), phase)
        ssr_plain = ssr_conduction(inside(live2, window2), phase)
        want = DUTY_PCT / 100 * PERIODS * period
        print(
            f"phase {phase / MS:.3f} ms: commanded {DUTY_PCT} %; time base: "
            f"{100 * ticked_on / (PERIODS * period):.4f} % on the line, "
            f"{100 * ssr_ticked / (PERIODS * period):.4f} % through the SSR; without: "
            f"{100 * plain_on / (PERIODS * period2):.4f} % on the line, "
            f"{100 * ssr_plain / (PERIODS * period2):.4f} % through the SSR"
        )
        assert ssr_ticked == ticked_on
        assert abs(ssr_ticked - want) <= TICK_NS
        assert abs(ssr_plain - DUTY_PCT / 100 * PERIODS * period2) > 2 * TICK_NS
