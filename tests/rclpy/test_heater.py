"""The heater loop from outside: the node with pw01 under `pid`, and the simulated
heater (`pwm_actuator_node sim-heater`) as its own process and ROS participant, driven by
pw01's edges and publishing sensor_msgs/Temperature best effort. The test is the user: it sends
the setpoint and the enable, injects faults on the simulated heater's `/sim_heater/fault`, and
reads ~/pw01/status, /diagnostics, the reset service and the node's trace.

- the loop holds its setpoint within ±1 °C once settled;
- each injected fault ends in the right latched check with the line off (and the heartbeat line
  stopped), ERROR on /diagnostics naming the check, and a reset refused while the condition
  lasts; once it is gone the reset is taken and the channel stays disabled.
"""

from __future__ import annotations

import math

import pytest
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Temperature
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

from helpers_rules import MS, NODE, diag_level, diag_values, mono_ns, trace_edges
from test_channel_rules import observe_until, start

# Untimed (pytest.ini): a simulated plant over seconds (±1 °C held over 15 s, a check named
# with the line off after it, readings and planned heartbeat edges counted at half of what
# comes); no figure of how soon the node answers or how its edges fall.
pytestmark = pytest.mark.untimed

ERROR = 2
TOPIC = "/heater/temperature"
#: A quick plant: 5 °C/s at full power from 20 °C, time constant 20 s, dead time 0.5 s.
PLANT = [
    "--heat-rate", "5", "--tau", "20", "--dead-time", "0.5", "--ambient", "20",
    "--noise", "0.05", "--rate-hz", "20", "--topic", TOPIC,
]  # fmt: skip
#: SIMC gains for it (K = 1 °C/%, kp = tau / (K·2L) = 20, TI = 8L = 4 s), a 200 ms period
#: (TCONT_CP: period <= TI/5), the checks sized as docs/heater.md says.
PARAMS = dict(
    pw01__period_ms=200,
    pw01__feedback_topic=TOPIC,
    pw01__control="pid",
    pw01__pid_kp=20.0,
    pw01__pid_ki=5.0,
    pw01__temp_min_c=0.0,
    pw01__temp_max_c=150.0,
    pw01__feedback_timeout_ms=1000,
    pw01__stuck_on_rise_c=5.0,
    pw01__stuck_on_time_s=5.0,
    heartbeat_line=0,
    heartbeat_hz=20.0,
)
SETPOINT = 60.0


def send_setpoint(ros, ch, celsius: float) -> None:
    """Publishes `celsius` on pw01's setpoint topic, confirmed by a status showing it."""
    sp = ros.publisher(Float64, f"{NODE}/pw01/setpoint")
    ros.wait_for_subscribers(sp, 1)
    ch.send(
        sp,
        Float64(data=celsius),
        ch.status,
        lambda s: s.setpoint_c == celsius,
        "status confirming the setpoint",
    )


def run_loop(node_process, process_launcher, node_binary, ros):
    """Starts node and simulated heater, waits for a first reading, sends the setpoint and
    enables pw01; returns (node, channel client, simulated heater, its fault publisher)."""
    proc, ch = start(node_process, ros, **PARAMS)
    sim = process_launcher.launch([node_binary, "sim-heater", *PLANT], name="sim")
    ch.wait_status(
        lambda s: math.isfinite(s.temperature_c), "a first temperature reading", timeout=60
    )
    send_setpoint(ros, ch, SETPOINT)
    ch.enable(True)
    faults = ros.publisher(String, "/sim_heater/fault")
    ros.wait_for_subscribers(faults, 1)
    return proc, ch, sim, faults


def test_feedback_matches_reliable_and_best_effort_publishers_and_inputs_are_checked(
    node_process, ros
):
    """No simulated heater: the test publishes the readings itself, reliable then best effort;
    under open a setpoint is refused with the reason; a NaN reading latches
    temperature_out_of_range."""
    proc, ch = start(
        node_process,
        ros,
        pw01__feedback_topic=TOPIC,
        pw01__temp_min_c=0.0,
        pw01__temp_max_c=150.0,
    )
    reliable = ros.publisher(Temperature, TOPIC, 10)
    best_effort = ros.publisher(Temperature, TOPIC, qos_profile_sensor_data)
    ros.wait_for_subscribers(reliable, 1)
    ros.wait_for_subscribers(best_effort, 1)
    for pub, value in ((reliable, 42.5), (best_effort, 43.5)):
        ch.send(
            pub,
            Temperature(temperature=value),
            ch.status,
            lambda s, v=value: s.temperature_c == v,
            f"status showing the reading {value}",
        )
    s = ch.status.messages[-1]
    assert s.control == "open" and s.heater_fault == "", s
    d = ch.wait_diag(lambda d: diag_values(d).get("temperature_c") == "43.500", "the reading")
    assert diag_level(d) != ERROR, d
    sp = ros.publisher(Float64, f"{NODE}/pw01/setpoint")
    ros.wait_for_subscribers(sp, 1)
    sp.publish(Float64(data=50.0))
    ch.wait_diag(
        lambda d: "setpoint refused: control is open" in diag_values(d).get("last_rejection", ""),
        "the setpoint refused under open",
    )
    r = reset(ros)
    assert not r.success and "no heater fault is latched" in r.message, r.message
    reliable.publish(Temperature(temperature=float("nan")))
    d = ch.wait_diag(lambda d: diag_level(d) == ERROR, "ERROR after a NaN reading")
    assert d.message.startswith("heater fault temperature_out_of_range:"), d.message
    r = reset(ros)
    assert not r.success and "the condition lasts" in r.message, r.message
    ch.send(
        reliable,
        Temperature(temperature=41.0),
        ch.status,
        lambda s: s.temperature_c == 41.0 and not s.heater_fault_lasts,
        "a valid reading again",
    )
    r = reset(ros)
    assert r.success, r.message


def reset(ros) -> Trigger.Response:
    return ros.call(Trigger, f"{NODE}/pw01/reset_fault", Trigger.Request())


def test_the_loop_holds_its_setpoint_within_one_degree(
    node_process, process_launcher, node_binary, ros
):
    proc, ch, sim, _ = run_loop(node_process, process_launcher, node_binary, ros)
    readings = ros.subscribe(Temperature, TOPIC, qos_profile_sensor_data)
    # 40 °C at up to 5 °C/s, then a few integral times to settle.
    observe_until(ch, mono_ns() + 30_000 * MS)
    start_at = len(readings.messages)
    observe_until(ch, mono_ns() + 15_000 * MS)
    seen = [m.temperature for m in readings.messages[start_at:]]
    assert len(seen) > 100, f"only {len(seen)} readings in 15 s"
    low, high = min(seen), max(seen)
    assert SETPOINT - 1.0 <= low and high <= SETPOINT + 1.0, (low, high)
    s = ch.status.messages[-1]
    assert s.control == "pid" and s.heater_fault == "", s
    # At 60 °C the plant needs (60 − 20) / 100 = 40 % on average; the integral carries it.
    assert 25.0 < s.pid_output < 55.0, s
    assert abs(s.temperature_c - SETPOINT) < 1.0 and 0.0 <= s.temperature_age_ms < 1000.0, s
    # Diagnostics sent now, with the loop settled, not the first ones from before it ran.
    d = ch.wait_diag(lambda d: "pid_output_pct" in diag_values(d), "the loop's figures",
                     start=len(ch.diagnostics.messages))
    assert diag_level(d) != ERROR, d
    assert 25.0 < float(diag_values(d)["pid_output_pct"]) < 55.0, d
    # A duty command is refused under pid, with the reason. The reason stays on /diagnostics
    # after any earlier refusal: only a count above the one before the command is this one's.
    refused_from = len(ch.diagnostics.messages)
    before = rejected_commands(ch, ch.diagnostics.messages[:refused_from])
    ch.duty_pub.publish(Float64(data=10.0))
    d = ch.wait_diag(
        lambda d: int(diag_values(d).get("rejected_commands", "0")) > before
        and "control is pid" in diag_values(d).get("last_rejection", ""),
        "the duty command refused",
        start=refused_from,
    )


def rejected_commands(ch, arrays) -> int:
    """The channel's `rejected_commands` in the latest of `arrays` (the count only grows)."""
    counts = [int(diag_values(s).get("rejected_commands", "0"))
              for s in map(ch.my_diag, arrays) if s is not None]
    return counts[-1] if counts else 0


@pytest.mark.parametrize(
    "fault, check",
    [
        # At full power the reading falls: the heater does not heat.
        ("heater_disconnected", "no_rise"),
        # 60 °C to ambient in one reading: no heater moves that fast.
        ("sensor_shorted", "sensor_jump"),
        # Frozen near the setpoint: the loop's integral ramps the power, the reading does
        # not follow it (or, at full power, does not rise).
        ("sensor_stuck", ("sensor_stuck", "no_rise")),
        # Cools toward ambient at full power.
        ("sensor_fallen_off", "no_rise"),
        ("heater_stuck_on", "stuck_on"),
        ("sensor_silent", "sensor_timeout"),
    ],
)
def test_each_fault_latches_its_check_with_the_line_off(
    node_process, process_launcher, node_binary, ros, fault, check
):
    proc, ch, sim, faults = run_loop(node_process, process_launcher, node_binary, ros)
    observe_until(ch, mono_ns() + 3_000 * MS)
    faults.publish(String(data=fault))
    injected = mono_ns()
    # not_heating needs the approach to run out (runaway_gain_time_s 20) and the error to add up.
    d = ch.wait_diag(lambda d: diag_level(d) == ERROR, f"ERROR after {fault}", timeout=90)
    latched = mono_ns()
    checks = check if isinstance(check, tuple) else (check,)
    check = diag_values(d)["heater_fault"]
    assert check in checks, d
    assert d.message.startswith(f"heater fault {check}:"), d.message
    s = ch.wait_status(lambda s: s.heater_fault == check, f"{check} latched in the status")
    assert not s.output and not s.enabled, s
    assert s.heater_fault_message.startswith(check), s

    # While the condition lasts the reset is refused with the reason.
    r = reset(ros)
    assert not r.success and "the condition lasts" in r.message, r.message
    observe_until(ch, mono_ns() + 1_500 * MS)

    if fault == "sensor_silent":
        # The sensor comes back: the condition is gone, the reset is taken, the channel stays
        # disabled until a fresh enable.
        faults.publish(String(data="none"))
        ch.wait_status(
            lambda s: 0.0 <= s.temperature_age_ms < 500.0, "fresh readings", start=len(ch.status.messages)
        )
        before_reset = len(ch.status.messages)
        r = reset(ros)
        assert r.success, r.message
        s = ch.wait_status(lambda s: s.heater_fault == "", "the fault cleared", start=before_reset)
        assert not s.enabled, s
        observe_until(ch, mono_ns() + 1_000 * MS)

    code = proc.terminate()
    assert code == 0, proc.output()
    edges = trace_edges(proc)
    # The line went off when the check latched and never rose again.
    assert edges[-1].level == 0, edges[-5:]
    rises = [e for e in edges if e.level == 1 and e.scheduled_ns > latched]
    assert not rises, f"the line rose after {check} latched: {rises[:3]}"
    # The heartbeat line stopped while the fault was latched.
    beats = trace_edges(proc, "heartbeat")
    before = [e for e in beats if injected - 2_000 * MS < e.scheduled_ns < injected]
    assert len(before) > 20, "the heartbeat ran before the fault"
    after = [e for e in beats if latched + 200 * MS < e.scheduled_ns < latched + 1_500 * MS]
    assert not after, f"the heartbeat toggled while {check} was latched"
