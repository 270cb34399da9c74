"""The last vendor details seen over ROS: 004's fraction input, 002's continuously
calculated times and whole-second countdowns on `~/<ch>/status`."""

from __future__ import annotations

import math

import pytest
from helpers_rules import ChannelClient, node_args
from std_msgs.msg import Float64

# Times nothing (pytest.ini, `untimed`): the figures of a status message checked against each
# other and against the command.
pytestmark = pytest.mark.untimed


def test_fraction_topic_takes_a_0_to_1_input_004(node_process, ros):
    # 004: i_rIput is a fraction 0.0..1.0; ~/<ch>/fraction reaches the core's fraction command.
    node_process(node_args(pw01__profile="frequency_output"))
    ch = ChannelClient(ros, "pw01")
    ch.wait_connected()
    pub = ros.publisher(Float64, "/pwm_actuator/pw01/fraction")
    ros.wait_for_subscribers(pub, 1)
    sent = ch.send(
        pub,
        Float64(data=0.25),
        ch.status,
        lambda s: math.isclose(s.duty_commanded, 25.0, abs_tol=1e-9),
        "status confirming fraction 0.25",
    )
    assert math.isclose(sent.reply.on_time_input_ms, 250.0, abs_tol=1e-6)
    # Out of range: clamped to 1.0 and flagged, as on ~/<ch>/duty.
    sent = ch.send(
        pub, Float64(data=1.5), ch.status, lambda s: s.command_clamped, "clamped fraction"
    )
    assert sent.reply.duty_commanded == 100.0


def test_times_from_the_input_and_countdowns_in_seconds_002(node_process, ros):
    # 002: the running step keeps its latched time; fActTiOn / fActTiOff follow the input;
    # nRemTiOn / nRemTiOff count down in whole seconds.
    node_process(node_args(pw01__profile="twincat_ba", pw01__period_ms=10_000))
    ch = ChannelClient(ros, "pw01")
    ch.wait_connected()
    ch.duty(80.0)
    ch.enable(True)
    first = ch.wait_status(lambda s: s.output and s.remaining_on_s >= 6, "an 8 s on step")
    assert first.remaining_on_s == math.floor(first.remaining_on_ms / 1000)
    sent = ch.duty(30.0)
    s = sent.reply
    assert (s.on_time_ms, s.on_time_input_ms) == (8000.0, 3000.0), s
    assert (s.off_time_ms, s.off_time_input_ms) == (2000.0, 7000.0), s
