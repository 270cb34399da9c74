"""Model-predictive control from outside: the node with pw01 and the simulated heater
(`pwm_actuator_node sim-heater`, the quick plant of test_heater.py with a sensor lagging its
block by 0.5 s) as its own process. The test is the user: a model autotune with `apply` (the
action), then in one run the same setpoint and the same fan (30 % of the heater's power, on
`/sim_heater/fan`, not announced to the node) under `pid` with the autotune's gains and under
`control:=mpc` on the autotune's model.

- under `mpc` the heater holds its setpoint within ±0.5 °C once settled;
- the fan's step is rejected faster under `mpc` than under `pid` (both printed): the integrated
  absolute error over the 20 s after the step is smaller, and the reading is back within
  0.5 °C of the setpoint sooner;
- `feedforward_topic`: a value published is the one in force on /diagnostics; with none fresh
  the channel is WARN, saying the feed-forward is stale.
- `ambient_topic`: the same for the ambient (a stamped `sensor_msgs/Temperature`); a reading
  that is not a temperature is refused and leaves the ambient in force as it was; stale, the
  model's ambient is in force again.
- `setpoint_ramp_c_per_s`: the ramped target on the status moves from the reading at the
  enable toward the setpoint at that rate, never beyond it.
"""

from __future__ import annotations

import math

import pytest
from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Temperature
from std_msgs.msg import Float64

from pwm_actuator_msgs.action import Autotune

from helpers_rules import MS, NODE, diag_level, diag_values, mono_ns
from test_channel_rules import observe_until, start
from test_heater import PARAMS, PLANT, TOPIC, send_setpoint

SETPOINT = 60.0
FAN = 0.3
#: The quick plant's sensor lags its block by 0.5 s.
LAGGING = [*PLANT, "--sensor-tau", "0.5"]
#: `mpc` on the quick plant's model (with the lagging sensor), set as parameters.
MPC_MODEL = dict(
    pw01__control="mpc",
    pw01__model_gain_c_per_pct=1.0,
    pw01__model_tau_s=20.0,
    pw01__model_dead_time_s=0.5,
    pw01__model_sensor_tau_s=0.5,
    pw01__model_ambient_c=20.0,
    pw01__model_tolerance_c=45.0,
)
#: The fan's response is measured over this long, s.
WATCH_S = 20.0


def fan_step(ch, ros, fan, readings, share: float) -> tuple[float, float, float]:
    """Switches the fan to `share` and watches WATCH_S: the integrated absolute error of the
    readings (°C·s), the largest excursion (°C) and when the reading was back within 0.5 °C of
    the setpoint for good (s after the step)."""
    first = len(readings.messages)
    t0 = mono_ns()
    fan.publish(Float64(data=share))
    observe_until(ch, t0 + int(WATCH_S * 1000) * MS)
    got = readings.messages[first:]
    assert len(got) > 10 * WATCH_S, len(got)
    dt = WATCH_S / len(got)
    errors = [m.temperature - SETPOINT for m in got]
    iae = sum(abs(e) for e in errors) * dt
    worst = max(abs(e) for e in errors)
    last_out = max((i for i, e in enumerate(errors) if abs(e) > 0.5), default=-1)
    # Never back within the watch: counted as the whole watch.
    back = (last_out + 1) * dt
    return iae, worst, back


# The autotune, then 75 s under each loop.
@pytest.mark.timeout(420)
@pytest.mark.untimed
def test_mpc_after_a_model_autotune_holds_and_rejects_a_fan_faster_than_pid(
    node_process, process_launcher, node_binary, ros
):
    # An unannounced fan of 30 % moves model_deviation's residual by up to gain × 30 °C
    # (docs/heater.md): the tolerance above it.
    proc, ch = start(node_process, ros, **PARAMS, pw01__model_tolerance_c=45.0)
    process_launcher.launch([node_binary, "sim-heater", *LAGGING], name="sim")
    ch.wait_status(
        lambda s: math.isfinite(s.temperature_c), "a first temperature reading", timeout=60
    )
    ch.enable(True)
    client = ActionClient(ros.node, Autotune, f"{NODE}/pw01/autotune")
    ros.spin_until(client.server_is_ready, "the autotune action server", timeout=30)
    ros.spin_for(0.25)
    sent = client.send_goal_async(Autotune.Goal(target_c=SETPOINT, apply=True))
    ros.spin_until(sent.done, "the goal's answer", timeout=10)
    handle = sent.result()
    assert handle.accepted
    got = handle.get_result_async()
    ros.spin_until(got.done, "the autotune's result", timeout=150)
    status, r = got.result().status, got.result().result
    assert status == GoalStatus.STATUS_SUCCEEDED and r.applied, (status, r)
    print(
        f"model: gain {r.model_gain_c_per_pct:.3f} °C/%, tau {r.model_tau_s:.1f} s, dead time "
        f"{r.model_dead_time_s:.2f} s, sensor {r.model_sensor_tau_s:.2f} s, ambient "
        f"{r.model_ambient_c:.1f} °C (plant: 1, 20, 0.5, 0.5, 20)"
    )
    assert r.model_gain_c_per_pct > 0.0, r
    # The message gives the model in words with the dead time's standard error.
    print(r.message)
    assert f"dead time {r.model_dead_time_s:.2f} ± " in r.message, r.message

    readings = ros.subscribe(Temperature, TOPIC, qos_profile_sensor_data)
    fan = ros.publisher(Float64, "/sim_heater/fan")
    ros.wait_for_subscribers(fan, 1)
    sp = ros.publisher(Float64, f"{NODE}/pw01/setpoint")
    ros.wait_for_subscribers(sp, 1)
    figures = {}
    for control in ("pid", "mpc"):
        res = ros.set_parameters(NODE, {"pw01.control": control})
        assert res["pw01.control"].successful, res
        ch.send(
            sp, Float64(data=SETPOINT), ch.status, lambda s: s.setpoint_c == SETPOINT, "setpoint"
        )
        ch.wait_status(lambda s, c=control: s.control == c, f"control {control}")
        # Settle, then hold: 10 s of readings.
        observe_until(ch, mono_ns() + 25_000 * MS)
        first = len(readings.messages)
        observe_until(ch, mono_ns() + 10_000 * MS)
        held = [m.temperature - SETPOINT for m in readings.messages[first:]]
        assert len(held) > 100, len(held)
        iae, worst, back = fan_step(ch, ros, fan, readings, FAN)
        figures[control] = (min(held), max(held), iae, worst, back)
        never = " (not within the watch)" if back >= WATCH_S - 0.1 else ""
        print(
            f"{control}: held {min(held):+.2f}..{max(held):+.2f} °C; fan {FAN:.0%} unannounced: "
            f"IAE {iae:.1f} °C·s over {WATCH_S:.0f} s, worst {worst:.2f} °C, back within "
            f"0.5 °C for good after {back:.1f} s{never}"
        )
        # The fan off again, and the heater back at the setpoint before the next loop.
        fan.publish(Float64(data=0.0))
        observe_until(ch, mono_ns() + 20_000 * MS)
        assert ch.status.messages[-1].heater_fault == "", ch.status.messages[-1]
    lo, hi = figures["mpc"][0], figures["mpc"][1]
    assert -0.5 <= lo and hi <= 0.5, (lo, hi)
    assert figures["mpc"][2] < figures["pid"][2], figures
    assert figures["mpc"][4] <= figures["pid"][4], figures
    d = ch.wait_diag(lambda d: diag_values(d).get("control") == "mpc", "mpc on /diagnostics")
    v = diag_values(d)
    assert v["model"].startswith("gain "), v
    assert math.isfinite(float(v["mpc_predicted_c"])), v


@pytest.mark.untimed
def test_the_feedforward_topic_is_used_while_fresh_and_warns_when_stale(
    node_process, process_launcher, node_binary, ros
):
    model = dict(
        **MPC_MODEL,
        pw01__feedforward_topic="/heater/fan_ff",
        pw01__feedforward_timeout_ms=1000,
    )
    proc, ch = start(node_process, ros, **{**PARAMS, **model})
    process_launcher.launch([node_binary, "sim-heater", *LAGGING], name="sim")
    ch.wait_status(
        lambda s: math.isfinite(s.temperature_c), "a first temperature reading", timeout=60
    )
    # None yet: stale, WARN.
    d = ch.wait_diag(lambda d: diag_values(d).get("feedforward_stale") == "true", "stale")
    assert diag_level(d) == 1 and d.message.startswith("feed-forward input stale"), d
    ff = ros.publisher(Float64, "/heater/fan_ff")
    ros.wait_for_subscribers(ff, 1)
    fresh = None
    t_end = mono_ns() + 5_000 * MS
    while mono_ns() < t_end:
        ff.publish(Float64(data=30.0))
        ros.spin_for(0.2)
        mine = [m for m in map(ch.my_diag, ch.diagnostics.messages[-3:]) if m is not None]
        if mine and diag_values(mine[-1]).get("feedforward_pct") == "30.000":
            fresh = mine[-1]
            break
    assert fresh is not None, "the feed-forward never in force"
    assert diag_values(fresh)["feedforward_stale"] == "false", diag_values(fresh)
    # Publishing stops: stale again after feedforward_timeout_ms, the value no longer used.
    start_at = len(ch.diagnostics.messages)
    d = ch.wait_diag(
        lambda d: diag_values(d).get("feedforward_stale") == "true",
        "stale after the timeout",
        start=start_at,
        timeout=10,
    )
    assert diag_values(d)["feedforward_pct"] == "0.000", diag_values(d)
    assert diag_level(d) == 1, d


@pytest.mark.untimed
def test_the_ambient_topic_is_used_while_fresh_and_warns_when_stale(
    node_process, process_launcher, node_binary, ros
):
    model = dict(
        **MPC_MODEL,
        pw01__ambient_topic="/heater/ambient",
        pw01__ambient_timeout_ms=3000,
    )
    proc, ch = start(node_process, ros, **{**PARAMS, **model})
    process_launcher.launch([node_binary, "sim-heater", *LAGGING], name="sim")
    ch.wait_status(
        lambda s: math.isfinite(s.temperature_c), "a first temperature reading", timeout=60
    )
    # None yet: stale, WARN, the model's ambient in force.
    d = ch.wait_diag(lambda d: diag_values(d).get("ambient_stale") == "true", "stale")
    assert diag_level(d) == 1 and d.message.startswith("ambient input stale"), d
    assert diag_values(d)["ambient_c"] == "20.000", diag_values(d)
    amb = ros.publisher(Temperature, "/heater/ambient")
    ros.wait_for_subscribers(amb, 1)

    def publish_until(celsius: float, want: str, what: str):
        t_end = mono_ns() + 5_000 * MS
        while mono_ns() < t_end:
            m = Temperature(temperature=celsius)
            m.header.stamp = ros.node.get_clock().now().to_msg()
            amb.publish(m)
            ros.spin_for(0.2)
            mine = [m for m in map(ch.my_diag, ch.diagnostics.messages[-3:]) if m is not None]
            if mine and diag_values(mine[-1]).get("ambient_c") == want:
                return mine[-1]
        raise AssertionError(f"{what}: ambient_c never {want}")

    fresh = publish_until(26.5, "26.500", "a fresh ambient")
    assert diag_values(fresh)["ambient_stale"] == "false", diag_values(fresh)
    # Not a temperature: refused, the ambient in force stays 26.5 °C while it is published
    # (for half the timeout: a refused reading does not keep the last good one fresh).
    start_at = len(ch.diagnostics.messages)
    t_end = mono_ns() + 1_500 * MS
    while mono_ns() < t_end:
        m = Temperature(temperature=5000.0)
        m.header.stamp = ros.node.get_clock().now().to_msg()
        amb.publish(m)
        ros.spin_for(0.2)
    mine = [v for v in map(ch.my_diag, ch.diagnostics.messages[start_at:]) if v is not None]
    assert mine, "no diagnostics while the refused ambient was published"
    assert {diag_values(v)["ambient_c"] for v in mine} == {"26.500"}, [
        diag_values(v)["ambient_c"] for v in mine
    ]
    # Publishing stops: stale after ambient_timeout_ms (counted from the last good reading's
    # stamp), the model's ambient in force again.
    start_at = len(ch.diagnostics.messages)
    d = ch.wait_diag(
        lambda d: diag_values(d).get("ambient_stale") == "true",
        "stale after the timeout",
        start=start_at,
        timeout=10,
    )
    assert diag_values(d)["ambient_c"] == "20.000", diag_values(d)
    assert diag_level(d) == 1, d


def test_a_ramped_setpoint_moves_the_status_target_at_its_rate(
    node_process, process_launcher, node_binary, ros
):
    rate = 2.0
    proc, ch = start(node_process, ros, **PARAMS, pw01__setpoint_ramp_c_per_s=rate)
    process_launcher.launch([node_binary, "sim-heater", *PLANT], name="sim")
    first = ch.wait_status(
        lambda s: math.isfinite(s.temperature_c), "a first temperature reading", timeout=60
    )
    send_setpoint(ros, ch, SETPOINT)
    start_at = len(ch.status.messages)
    ch.enable(True)
    ros.spin_for(4.0)
    ramping = [s for s in ch.status.messages[start_at:] if s.enabled]
    assert len(ramping) > 20, len(ramping)
    stamp = [s.stamp.sec + s.stamp.nanosec * 1e-9 for s in ramping]
    target = [s.target_c for s in ramping]
    assert all(math.isfinite(t) and t <= SETPOINT for t in target), target
    # From where the heater was at the enable (about ambient; the reading moves little in the
    # ramp's first status period).
    assert abs(target[0] - first.temperature_c) < 3.0, (target[0], first.temperature_c)
    slope = (target[-1] - target[0]) / (stamp[-1] - stamp[0])
    print(f"ramp: target {target[0]:.2f} -> {target[-1]:.2f} °C over "
          f"{stamp[-1] - stamp[0]:.2f} s: {slope:.3f} °C/s (rate {rate})")
    assert abs(slope - rate) < 0.2, slope
    assert all(b >= a for a, b in zip(target, target[1:])), target
