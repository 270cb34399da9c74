"""The managed node (`--managed`), from outside: an rclpy client walks it through the lifecycle
with lifecycle_msgs' services and checks, in the node's CSV trace, what the line does in each
state: held inactive while unconfigured and inactive, following its channel while active,
inactive at once on deactivate, released on cleanup and shutdown. A configure that cannot
open its GPIO line fails and leaves the node unconfigured.
"""

from __future__ import annotations

import pytest
from lifecycle_msgs.msg import Transition, TransitionEvent
from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState
from rcl_interfaces.srv import GetParameters

from helpers_rules import MS, NODE, ChannelClient, mono_ns, node_args, pulses
from test_channel_rules import close_trace, observe_until

UNCONFIGURED, INACTIVE, ACTIVE, FINALIZED = 1, 2, 3, 4


def state(ros) -> int:
    return ros.call(GetState, f"{NODE}/get_state", GetState.Request()).current_state.id


def change(ros, transition_id: int) -> bool:
    req = ChangeState.Request(transition=Transition(id=transition_id))
    return ros.call(ChangeState, f"{NODE}/change_state", req).success


def available(ros, service: str = "get_available_transitions") -> list[tuple[int, str]]:
    resp = ros.call(GetAvailableTransitions, f"{NODE}/{service}", GetAvailableTransitions.Request())
    return [(t.transition.id, t.transition.label) for t in resp.available_transitions]


def rises_between(edges, start_ns: int, end_ns: int):
    return [e for e in edges if e.level == 1 and start_ns < e.scheduled_ns <= end_ns]


@pytest.mark.smoke
def test_the_lifecycle_walk_keeps_the_line_inactive_except_while_active(node_process, ros):
    proc = node_process(
        ["--managed"] + node_args(pw01__period_ms=200, pw01__duty=50.0, pw01__enable=True)
    )
    ch = ChannelClient(ros, "pw01")
    ch.wait_connected()
    events = ros.subscribe(TransitionEvent, f"{NODE}/transition_event", 10)
    events.wait_for_publishers(1)

    assert state(ros) == UNCONFIGURED
    assert available(ros) == [(1, "configure"), (5, "shutdown")]
    assert len(available(ros, "get_transition_graph")) == 25
    # The parameter services answer in every state.
    got = ros.call(GetParameters, f"{NODE}/get_parameters", GetParameters.Request(names=["managed"]))
    assert got.values[0].bool_value is True
    t_unconfigured = mono_ns()
    observe_until(ch, t_unconfigured + 500 * MS)

    t_configure = mono_ns()
    assert change(ros, Transition.TRANSITION_CONFIGURE)
    assert state(ros) == INACTIVE
    events.wait_for_count(2)
    first, second = events.messages[0], events.messages[1]
    assert (first.transition.id, first.start_state.id, first.goal_state.id) == (1, 1, 10)
    assert (second.transition.id, second.goal_state.id) == (10, INACTIVE)
    observe_until(ch, mono_ns() + 500 * MS)

    t_activate = mono_ns()
    assert change(ros, Transition.TRANSITION_ACTIVATE)
    assert state(ros) == ACTIVE
    observe_until(ch, t_activate + 900 * MS)
    # 100 %: the line is on when the node is deactivated.
    t_full = ch.duty(100.0).first_publish_ns
    observe_until(ch, t_full + 500 * MS)

    t_deactivate = mono_ns()
    assert change(ros, Transition.TRANSITION_DEACTIVATE)
    t_deactivated = mono_ns()
    assert state(ros) == INACTIVE
    observe_until(ch, t_deactivated + 600 * MS)

    assert change(ros, Transition.TRANSITION_CLEANUP)
    assert state(ros) == UNCONFIGURED
    assert not change(ros, Transition.TRANSITION_ACTIVATE), "activate is not available here"
    assert change(ros, Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
    assert state(ros) == FINALIZED
    got = ros.call(GetParameters, f"{NODE}/get_parameters", GetParameters.Request(names=["managed"]))
    assert got.values[0].bool_value is True

    edges = close_trace(proc)
    assert not rises_between(edges, 0, t_activate), "a rise before activate"
    active = rises_between(edges, t_activate, t_deactivate)
    assert len(active) >= 3, f"the line did not follow its channel while active: {edges}"
    # The channel's period grid ran on while the line was held: the first pulse may be the rest
    # of an on step that was running at activation; the whole periods after it are exact.
    for rise, fall in pulses([e for e in edges if t_activate < e.scheduled_ns <= t_full])[1:]:
        assert fall.scheduled_ns - rise.scheduled_ns == 100 * MS, (rise, fall)
    assert not rises_between(edges, t_deactivated, 1 << 62), "a rise after deactivate"
    # On at 100 % when deactivated: off at once.
    last_before = [e for e in edges if e.scheduled_ns < t_deactivate][-1]
    assert last_before.level == 1, edges
    falls = [e for e in edges if e.level == 0 and e.scheduled_ns >= t_deactivate]
    assert falls and falls[0].t_ns <= t_deactivated + 50 * MS, (falls[:1], t_deactivated)
    assert edges[-1].level == 0


@pytest.mark.untimed
def test_a_configure_that_cannot_open_its_line_fails_and_stays_unconfigured(node_process, ros):
    proc = node_process(
        ["--managed", "--output", "gpio", "--line", "pw01=/dev/gpiochip-missing:3",
         "--channels", "1"] + node_args()
    )
    ch = ChannelClient(ros, "pw01")
    ch.wait_connected()
    assert state(ros) == UNCONFIGURED
    assert not change(ros, Transition.TRANSITION_CONFIGURE)
    assert state(ros) == UNCONFIGURED
    proc.wait_for_output("cannot open the GPIO output", timeout=10)
    assert "/dev/gpiochip-missing" in proc.output()
    assert change(ros, Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
    assert state(ros) == FINALIZED
    assert proc.terminate() == 0, proc.output()
