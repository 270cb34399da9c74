"""The latched emergency stop, from outside: an rclpy client publishes on `~/estop`
(std_msgs/Bool), calls `~/reset_estop` (std_srvs/Trigger) and reads the node's CSV trace and
/diagnostics.

- `true` drives the line inactive at once (not at the end of the running pulse) and latches;
- while latched, commands and enables are taken and reported, but the line stays inactive;
- the reset is refused while the last input is `true`, and after it nothing switches on by
  itself: a fresh `enable=true` runs the channel again;
- with `estop_timeout_ms` (a heartbeat e-stop), silence on `~/estop` latches it too.
"""

from __future__ import annotations

from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from helpers_rules import MS, NODE, diag_level, diag_values, mono_ns, pulses
from test_channel_rules import close_trace, observe_until, start

ERROR = 2


def estop_publisher(ros):
    pub = ros.publisher(Bool, f"{NODE}/estop")
    ros.wait_for_subscribers(pub, 1)
    return pub


def reset(ros) -> Trigger.Response:
    return ros.call(Trigger, f"{NODE}/reset_estop", Trigger.Request())


def release(ros, estop) -> Trigger.Response:
    """Publishes `false` on ~/estop and resets: the reset is asked again while the node answers
    that the e-stop is still asserted (the `false` travels on a topic, the reset on a service:
    nothing orders the two), up to 5 s. Returns the last answer."""
    estop.publish(Bool(data=False))
    deadline = mono_ns() + 5_000 * MS
    while True:
        ros.spin_for(0.1)
        response = reset(ros)
        if response.success or "still asserted" not in response.message or mono_ns() > deadline:
            return response


def latched(d) -> bool:
    return diag_values(d).get("estop_latched") == "true"


def test_the_estop_latches_off_at_once_and_nothing_runs_again_before_a_fresh_enable(
    node_process, ros
):
    # 90 % of 4 s: a 3.6 s pulse that the e-stop must cut, not wait for.
    proc, ch = start(node_process, ros, pw01__period_ms=4000)
    estop = estop_publisher(ros)
    ch.duty(90.0)
    on = ch.enable(True)
    observe_until(ch, on.confirmed_ns + 300 * MS)
    pressed = mono_ns()
    estop.publish(Bool(data=True))
    d = ch.wait_diag(latched, "e-stop latched")
    assert diag_level(d) == ERROR, d
    assert "e-stop latched" in d.message, d

    # Latched: an enable toggle and a new duty are taken (status shows them), the line stays off.
    ch.enable(False)
    ch.enable(True)
    ch.duty(100.0)
    response = reset(ros)
    assert not response.success and "still asserted" in response.message, response
    observe_until(ch, mono_ns() + 600 * MS)

    before_reset = len(ch.status.messages)
    response = release(ros, estop)
    assert response.success, response
    released = mono_ns()
    ch.wait_status(lambda s: not s.enabled, "disabled by the reset", start=before_reset)
    observe_until(ch, released + 800 * MS)
    again = ch.enable(True)
    observe_until(ch, again.confirmed_ns + 500 * MS)

    edges = close_trace(proc)
    ps = pulses(edges)
    assert len(ps) >= 2, edges
    first_rise, first_fall = ps[0]
    # The fall came within half a second of the press, far before the 3.6 s pulse's end.
    assert pressed <= first_fall.t_ns <= pressed + 500 * MS, (pressed, first_fall)
    assert first_fall.scheduled_ns - first_rise.scheduled_ns < 3000 * MS
    # No rise from the press until the fresh enable after the reset.
    between = [e for e in edges if e.level == 1 and pressed < e.scheduled_ns < again.first_publish_ns]
    assert not between, f"rises while latched or before the fresh enable: {between}"
    # The fresh enable runs the channel: a rise after it.
    assert any(e.level == 1 and e.scheduled_ns >= again.first_publish_ns for e in edges), edges


def test_silence_on_the_estop_topic_latches_it_when_a_timeout_is_set(node_process, ros):
    proc, ch = start(node_process, ros, estop_timeout_ms=1000)
    estop = estop_publisher(ros)
    ch.duty(100.0)

    # A false every 100 ms keeps it released; the channel runs.
    def keep_alive(seconds: float) -> None:
        end = mono_ns() + int(seconds * 1e9)
        while mono_ns() < end:
            estop.publish(Bool(data=False))
            ros.spin_for(0.1)

    keep_alive(0.3)
    # The first call makes the service client (a quarter second without publishing); the
    # node may also have latched before the first false arrived: reset until released.
    reset(ros)
    keep_alive(0.3)
    response = reset(ros)
    assert response.success, response
    on = ch.enable(True)
    # Kept alive, the diagnostics sent from now on say released: at least one must come.
    seen = len(ch.diagnostics.messages)
    keep_alive(0.8)
    end = mono_ns() + 3000 * MS
    while len(ch.diagnostics.messages) <= seen:
        assert mono_ns() < end, "no diagnostics while the e-stop was kept alive"
        keep_alive(0.1)
    released = ch.diagnostics.messages[seen:]
    assert not any(latched(s) for d in released for s in d.status), released

    # Silence: latched within the timeout (plus the check's period and delivery).
    silent = mono_ns()
    d = ch.wait_diag(latched, "e-stop latched by the timeout", start=len(ch.diagnostics.messages))
    assert diag_level(d) == ERROR
    response = reset(ros)
    assert not response.success and "estop_timeout_ms" in response.message, response
    keep_alive(0.3)
    assert reset(ros).success
    edges = close_trace(proc)
    falls = [e for e in edges if e.level == 0 and e.scheduled_ns > on.first_publish_ns]
    assert falls, edges
    assert silent + 800 * MS <= falls[0].t_ns <= silent + 2500 * MS, (silent, falls[0])
