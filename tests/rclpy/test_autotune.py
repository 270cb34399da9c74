"""The autotune action from outside: the node with pw01 under `pid` and the simulated heater
(`pwm_actuator_node sim-heater`, the quick plant of test_heater.py) as its own process. The test
is the user: an rclpy ActionClient sends the goal to ~/pw01/autotune.

- with `apply` the run converges, feedback arrives for every cycle, the result carries Ku, Tu,
  the gains and the sizing, the gains are the parameters afterwards, and the loop with them
  takes a step of about 25 °C and settles within ±1 °C (overshoot printed, bounded at 3 °C);
- a cancel mid-run ends the goal CANCELED; an e-stop, a disable and a heater fault
  (`sensor_timeout`, the simulated sensor falling silent) end it ABORTED with the reason; each
  leaves the line off and the old gains in force.
"""

from __future__ import annotations

import math

import pytest
from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Temperature
from std_msgs.msg import Bool, Float64, String

from pwm_actuator_msgs.action import Autotune

from helpers_rules import MS, NODE, diag_values, mono_ns
from test_channel_rules import close_trace, observe_until, start
from test_heater import PARAMS, PLANT, TOPIC

# Untimed (pytest.ini): the relay test of a simulated plant over seconds (Tu between 0.5 and
# 10 s, the step settled within ±1 °C), how a run ends and the line off after it; no figure
# of how soon the node answers or how its edges fall.
pytestmark = pytest.mark.untimed

TARGET = 60.0
#: Gains before the run: deliberately soft, so a change is plain.
OLD = dict(pw01__pid_kp=2.0, pw01__pid_ki=0.05, pw01__pid_kd=0.0)


def run(node_process, process_launcher, node_binary, ros):
    """Node and simulated heater, a first reading, pw01 enabled (at 0 %: no setpoint)."""
    params = {**PARAMS, **OLD}
    proc, ch = start(node_process, ros, **params)
    process_launcher.launch([node_binary, "sim-heater", *PLANT], name="sim")
    ch.wait_status(
        lambda s: math.isfinite(s.temperature_c), "a first temperature reading", timeout=60
    )
    ch.enable(True)
    client = ActionClient(ros.node, Autotune, f"{NODE}/pw01/autotune")
    ros.spin_until(client.server_is_ready, "the autotune action server", timeout=30)
    ros.spin_for(0.25)
    return proc, ch, client


def send(ros, client, apply: bool, feedback: list):
    goal = Autotune.Goal(target_c=TARGET, apply=apply)
    assert goal.noise_band_c == 0.5 and goal.amplitude_pct == 0.0  # the action's defaults
    sent = client.send_goal_async(goal, feedback_callback=lambda m: feedback.append(m.feedback))
    ros.spin_until(sent.done, "the goal's answer", timeout=10)
    handle = sent.result()
    assert handle.accepted
    return handle


def test_autotune_with_apply_sets_gains_that_settle_the_loop(
    node_process, process_launcher, node_binary, ros
):
    proc, ch, client = run(node_process, process_launcher, node_binary, ros)
    feedback: list = []
    t0 = mono_ns()
    handle = send(ros, client, True, feedback)
    during = len(ch.status.messages)
    got = handle.get_result_async()
    ros.spin_until(got.done, "the autotune's result", timeout=150)
    took = (mono_ns() - t0) / 1e9
    status, r = got.result().status, got.result().result
    print(f"autotune: {took:.1f} s, {r}")
    assert status == GoalStatus.STATUS_SUCCEEDED, (status, r)
    assert r.converged and r.stop == "converged" and r.applied, r
    assert r.rule == "tyreus_luyben", r
    # The quick plant: K = 1 °C/%, tau 20 s, dead time 0.5 s plus the 200 ms period. Wide
    # bounds: Tu of a few seconds, Ku of tens of % per °C.
    assert 0.5 < r.tu_s < 10.0 and 2.0 < r.ku < 500.0, r
    assert math.isclose(r.pid_kp, 0.45 * r.ku, rel_tol=1e-9), r
    assert math.isclose(r.pid_ki, r.pid_kp / (2.2 * r.tu_s), rel_tol=1e-9), r
    # TCONT_CP: a 200 ms period keeps period <= TI/5 for TI = 2.2 Tu.
    assert r.period_ok and r.min_times_ok and r.recommended_period_ms >= 200, r
    assert not r.sizing, r
    # Feedback: the approach, then each cycle counted up to the result's (the last feedback and
    # the result travel on different topics: the feedback may come second).
    ros.spin_until(
        lambda: feedback and feedback[-1].cycles == r.cycles, "the last cycle's feedback", 5.0
    )
    phases = [f.phase for f in feedback]
    assert phases[0] == "approach" and "relay" in phases, phases
    cycles = [f.cycles for f in feedback]
    assert cycles == sorted(cycles) and cycles[-1] == r.cycles >= 5, cycles
    assert all(f.amplitude_c > 0 and f.period_s > 0 for f in feedback if f.cycles > 0), feedback
    # The gains are the parameters now.
    got_params = ros.get_parameters(NODE, ["pw01.pid_kp", "pw01.pid_ki", "pw01.pid_kd"])
    assert got_params == {
        "pw01.pid_kp": r.pid_kp,
        "pw01.pid_ki": r.pid_ki,
        "pw01.pid_kd": r.pid_kd,
    }, got_params
    # The run ends at 0 %: the line off until a setpoint. Only statuses sent once the run is
    # over count: the channel was at 0 % before it, and the relay's off half is 0 % too.
    assert any(m.output for m in ch.status.messages[during:]), "the line never on in the run"
    ch.wait_diag(lambda d: diag_values(d).get("autotune") == "", "no autotune after the run",
                 start=len(ch.diagnostics.messages))
    after = len(ch.status.messages)
    s = ch.wait_status(lambda s: s.duty_commanded == 0.0 and not s.output, "0 % after the run",
                       start=after)
    assert s.setpoint_c != TARGET or math.isnan(s.setpoint_c), s

    # Let the heater cool, then the step to the target with the new gains.
    readings = ros.subscribe(Temperature, TOPIC, qos_profile_sensor_data)
    observe_until(ch, mono_ns() + 12_000 * MS)
    start_temp = readings.messages[-1].temperature
    sp = ros.publisher(Float64, f"{NODE}/pw01/setpoint")
    ros.wait_for_subscribers(sp, 1)
    first = len(readings.messages)
    ch.send(sp, Float64(data=TARGET), ch.status, lambda s: s.setpoint_c == TARGET, "setpoint")
    observe_until(ch, mono_ns() + 30_000 * MS)
    settled_from = len(readings.messages)
    observe_until(ch, mono_ns() + 10_000 * MS)
    step = [m.temperature for m in readings.messages[first:]]
    tail = [m.temperature for m in readings.messages[settled_from:]]
    overshoot = max(step) - TARGET
    print(
        f"step {start_temp:.1f} -> {TARGET} °C: overshoot {overshoot:.2f} °C; after 30 s within "
        f"{min(tail) - TARGET:+.2f}..{max(tail) - TARGET:+.2f} °C"
    )
    assert start_temp < TARGET - 10.0, start_temp
    assert len(tail) > 100, len(tail)
    assert TARGET - 1.0 <= min(tail) and max(tail) <= TARGET + 1.0, (min(tail), max(tail))
    assert overshoot < 3.0, overshoot
    assert ch.status.messages[-1].heater_fault == "", ch.status.messages[-1]


def cancel(ros, handle, ch) -> None:
    canceled = handle.cancel_goal_async()
    ros.spin_until(canceled.done, "the cancel's answer", timeout=10)
    assert len(canceled.result().goals_canceling) == 1, canceled.result()


def estop(ros, handle, ch) -> None:
    pub = ros.publisher(Bool, f"{NODE}/estop")
    ros.wait_for_subscribers(pub, 1)
    pub.publish(Bool(data=True))


def disable(ros, handle, ch) -> None:
    ch.enable(False)


def sensor_silent(ros, handle, ch) -> None:
    # The simulated heater stops publishing: sensor_timeout latches after feedback_timeout_ms.
    pub = ros.publisher(String, "/sim_heater/fault")
    ros.wait_for_subscribers(pub, 1)
    pub.publish(String(data="sensor_silent"))


#: Each way a run ends early: what ends it, the goal's status, the result's `stop`, and what
#: the channel's status shows afterwards besides 0 % and the line off.
ENDS = {
    "cancel": (cancel, GoalStatus.STATUS_CANCELED, "canceled", lambda s: s.enabled),
    "estop": (estop, GoalStatus.STATUS_ABORTED, "estop", lambda s: not s.enabled),
    "disable": (disable, GoalStatus.STATUS_ABORTED, "disabled", lambda s: not s.enabled),
    "heater_fault": (
        sensor_silent,
        GoalStatus.STATUS_ABORTED,
        "heater_fault",
        lambda s: s.heater_fault == "sensor_timeout",
    ),
}


@pytest.mark.parametrize("how", list(ENDS))
def test_a_run_ended_mid_way_leaves_the_line_off_and_the_old_gains(
    how, node_process, process_launcher, node_binary, ros
):
    end, want_status, want_stop, after = ENDS[how]
    proc, ch, client = run(node_process, process_launcher, node_binary, ros)
    feedback: list = []
    handle = send(ros, client, True, feedback)
    ros.spin_until(
        lambda: any(f.phase == "relay" for f in feedback), "the relay cycling", timeout=60
    )
    # The channel's diagnostics say that the relay, not the loop, sets the duty.
    d = ch.wait_diag(
        lambda d: diag_values(d).get("autotune", "").startswith("relay"), "autotune running"
    )
    assert d.message.startswith("autotune running (relay, "), d
    end(ros, handle, ch)
    got = handle.get_result_async()
    ros.spin_until(got.done, "the ended goal's result", timeout=10)
    ended = mono_ns()
    after_end = len(ch.status.messages)
    status, r = got.result().status, got.result().result
    assert status == want_status, (status, r)
    assert r.stop == want_stop and not r.converged and not r.applied, r
    assert r.pid_kp == 0.0 and r.ku == 0.0, r
    # Every end leaves 0 % commanded (nothing switches on again by itself) and the line off;
    # only statuses sent after the result count (the relay's off half is 0 % too).
    s = ch.wait_status(
        lambda s: s.duty_commanded == 0.0 and not s.output and after(s),
        f"0 % and the line off after {how}",
        start=after_end,
    )
    assert s.heater_fault == ("sensor_timeout" if how == "heater_fault" else ""), s
    start = len(ch.diagnostics.messages)
    ch.wait_diag(lambda d: diag_values(d)["autotune"] == "", "no autotune after it", start=start)
    got_params = ros.get_parameters(NODE, ["pw01.pid_kp", "pw01.pid_ki", "pw01.pid_kd"])
    assert got_params == {"pw01.pid_kp": 2.0, "pw01.pid_ki": 0.05, "pw01.pid_kd": 0.0}, got_params
    # The line stays off: no rise on the trace after the end (the last pulse finishes within
    # one 200 ms period, the relay's 100 % being cut at once).
    observe_until(ch, mono_ns() + 3_000 * MS)
    edges = close_trace(proc)
    rises = [e for e in edges if e.level == 1 and e.scheduled_ns > ended]
    assert not rises, [(e.scheduled_ns - ended) / MS for e in rises]
    assert edges[-1].level == 0, edges[-1]
