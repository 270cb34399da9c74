"""What /diagnostics says beyond each channel's own status, read by an rclpy client as an
aggregator or an operator would (docs/interface.md, "Diagnostics"):

- `<node>: <ch> command frequency`: diagnostic_updater's FrequencyStatus on the channel's duty
  commands; with commands at 10 Hz and `expected_command_hz_min` 5 it is OK, and when they stop
  it goes WARN "Frequency too low." and then ERROR "No events recorded.", in that order, within
  the window; its settings change while running;
- `<node>: node`: the lifecycle state (`unmanaged`, or a managed node's state as it moves),
  the e-stop, the output thread's lateness and the lost reports;
- `launch-notes/diagnostic_analyzers.yaml`: its analyzer takes exactly the statuses the node
  publishes, and names them as docs/interface.md says.
"""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any, Callable, Optional

import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from std_msgs.msg import Bool, Float64

from helpers_rules import NODE, ChannelClient, diag_level, diag_values, node_args
from test_channel_rules import start
from test_estop import release

OK, WARN, ERROR = 0, 1, 2
NODE_NAME = NODE.rsplit("/", 1)[-1]
ANALYZERS = Path(__file__).resolve().parents[2] / "launch-notes" / "diagnostic_analyzers.yaml"


def freq_name(channel: str) -> str:
    return f"{NODE_NAME}: {channel} command frequency"


NODE_STATUS = f"{NODE_NAME}: node"


def find(array: DiagnosticArray, name: str) -> Optional[DiagnosticStatus]:
    return next((s for s in array.status if s.name == name), None)


def wait_status(
    ch: ChannelClient,
    name: str,
    predicate: Callable[[DiagnosticStatus], bool],
    what: str,
    start: int = 0,
    timeout: Optional[float] = None,
    spin: Optional[Callable[[], None]] = None,
) -> tuple[int, DiagnosticArray, DiagnosticStatus]:
    """The first /diagnostics array (from message `start` on) whose status `name` satisfies
    `predicate`: (its index, the array, the status). `spin` runs between looks."""
    log = ch.diagnostics

    def look() -> Any:
        if spin is not None:
            spin()
        for i in range(start, len(log.messages)):
            s = find(log.messages[i], name)
            if s is not None and predicate(s):
                return (i, log.messages[i], s)
        return None

    return ch.ros.spin_until(look, f"/diagnostics {name!r}: {what}", timeout)


class Commander:
    """Publishes duty commands on one channel at a fixed rate while the test waits."""

    def __init__(self, ch: ChannelClient, hz: float) -> None:
        self.ch = ch
        self.period = 1.0 / hz
        self.next = time.monotonic()
        self.sent = 0

    def __call__(self) -> None:
        now = time.monotonic()
        if now >= self.next:
            self.ch.duty_pub.publish(Float64(data=20.0))
            self.sent += 1
            # After a stall, carry on at the rate rather than in a burst.
            self.next = max(self.next + self.period, now)


def test_the_command_frequency_goes_warn_then_error_when_commands_stop(node_process, ros):
    proc, ch = start(node_process, ros, pw01__expected_command_hz_min=5.0)
    commander = Commander(ch, 10.0)

    # Commands at 10 Hz: the rate is met over a whole window (5 runs, one a second).
    _, _, met = wait_status(
        ch,
        freq_name("pw01"),
        lambda s: s.message == "Desired frequency met"
        and float(diag_values(s)["Duration of window (s)"]) >= 4.5,
        "met at 10 Hz over a whole window",
        spin=commander,
    )
    assert diag_level(met) == OK, met
    kv = diag_values(met)
    assert kv["Minimum acceptable frequency (Hz)"] == "4.500000", kv
    assert "Maximum acceptable frequency (Hz)" not in kv, kv
    # What the test sent, give or take the commands at the window's ends.
    assert 5.0 <= float(kv["Actual frequency (Hz)"]) <= 12.0, kv
    assert int(kv["Events in window"]) > 0 and int(kv["Events since startup"]) > 0, kv
    assert kv["Window (diagnostics runs)"] == "5" and kv["Tolerance"] == "0.1", kv
    assert met.hardware_id == "sim"
    # pw02 has no expected rate: measured, not judged.
    array = ch.diagnostics.messages[-1]
    other = find(array, freq_name("pw02"))
    assert other is not None and diag_level(other) == OK, other
    assert other.message.startswith("Not checked"), other.message

    # Stop. The window (5 one-second runs) empties: WARN "Frequency too low." first, then
    # ERROR "No events recorded.", within the window and a generous margin.
    stopped = time.monotonic()
    start_index = len(ch.diagnostics.messages)
    low_index, _, low = wait_status(
        ch,
        freq_name("pw01"),
        lambda s: diag_level(s) != OK,
        "not OK after the commands stopped",
        start=start_index,
        timeout=15,
    )
    assert (diag_level(low), low.message) == (WARN, "Frequency too low."), low
    kv = diag_values(low)
    assert 0 < float(kv["Actual frequency (Hz)"]) < 4.5, kv
    err_index, err_array, err = wait_status(
        ch,
        freq_name("pw01"),
        lambda s: diag_level(s) == ERROR,
        "ERROR once no command is left in the window",
        start=low_index,
        timeout=15,
    )
    assert err.message == "No events recorded.", err
    assert diag_values(err)["Events in window"] == "0"
    assert err_index > low_index
    took = ch.diagnostics.arrivals[err_index] - stopped
    assert 3.0 <= took <= 12.0, f"ERROR {took:.1f} s after the last command"
    # The channel's own status is unaffected: a slow controller is not an output problem.
    own = find(err_array, f"{NODE_NAME}: pw01")
    assert own is not None and diag_level(own) == OK, own

    # The bounds change while running: a maximum below the minimum is refused, a minimum of 0
    # turns the check off.
    result = ros.set_parameters(NODE, {"pw01.expected_command_hz_max": 2.0})
    bad = result["pw01.expected_command_hz_max"]
    assert not bad.successful and "expected_command_hz_min 5" in bad.reason, bad.reason
    result = ros.set_parameters(NODE, {"pw01.expected_command_hz_min": 0.0})
    assert result["pw01.expected_command_hz_min"].successful
    _, _, off = wait_status(
        ch,
        freq_name("pw01"),
        lambda s: s.message.startswith("Not checked"),
        "not checked after the minimum went to 0",
        start=len(ch.diagnostics.messages),
    )
    assert diag_level(off) == OK, off
    assert "Minimum acceptable frequency (Hz)" not in diag_values(off)


def test_the_node_status_shows_lateness_lifecycle_and_the_estop(node_process, ros):
    # pw01 pulses at 50 % of 100 ms: 20 edges a second for the lateness window.
    proc, ch = start(
        node_process, ros, pw01__period_ms=100, pw01__duty=50.0, pw01__enable=True
    )
    _, _, node = wait_status(
        ch,
        NODE_STATUS,
        lambda s: int(diag_values(s).get("lateness_window_edges", "0")) >= 5,
        "a lateness window with edges",
    )
    assert diag_level(node) == OK, node
    assert node.hardware_id == NODE_NAME
    assert node.message.startswith("lifecycle unmanaged, e-stop released"), node.message
    kv = diag_values(node)
    assert kv["lifecycle_state"] == "unmanaged", kv
    assert (kv["estop_latched"], kv["estop_latches"]) == ("false", "0"), kv
    assert (kv["reports_dropped"], kv["samples_too_large"]) == ("0", "0"), kv
    p99, worst = float(kv["lateness_p99_us"]), float(kv["lateness_max_us"])
    # Lateness is the business of the benchmark; here only its shape: the p99 is at most the
    # maximum, and on a loaded 2-core machine still far below a period.
    assert 0 <= p99 <= worst < 100_000, kv
    assert 0.5 <= float(kv["lateness_window_s"]) <= 3.0, kv
    # 20 edges a second over a window of about one second.
    assert 5 <= int(kv["lateness_window_edges"]) <= 60, kv

    estop = ros.publisher(Bool, f"{NODE}/estop")
    ros.wait_for_subscribers(estop, 1)
    estop.publish(Bool(data=True))
    _, _, latched = wait_status(
        ch, NODE_STATUS, lambda s: diag_values(s)["estop_latched"] == "true", "e-stop latched"
    )
    assert diag_level(latched) == ERROR, latched
    assert latched.message.startswith("e-stop latched"), latched.message
    assert diag_values(latched)["estop_latches"] == "1"

    response = release(ros, estop)
    assert response.success, response
    _, _, released = wait_status(
        ch,
        NODE_STATUS,
        lambda s: diag_values(s)["estop_latched"] == "false",
        "e-stop released",
        start=len(ch.diagnostics.messages),
    )
    assert diag_level(released) == OK, released
    assert diag_values(released)["estop_latches"] == "1"


@pytest.mark.untimed
def test_the_node_status_follows_a_managed_node_s_lifecycle(node_process, ros):
    node_process(["--managed"])
    ch = ChannelClient(ros, "pw01")
    ch.wait_connected()
    _, _, node = wait_status(
        ch, NODE_STATUS, lambda s: "lifecycle_state" in diag_values(s), "a node status"
    )
    assert diag_values(node)["lifecycle_state"] == "unconfigured", diag_values(node)
    assert node.message.startswith("lifecycle unconfigured"), node.message
    for transition, label in (
        (Transition.TRANSITION_CONFIGURE, "inactive"),
        (Transition.TRANSITION_ACTIVATE, "active"),
    ):
        req = ChangeState.Request(transition=Transition(id=transition))
        assert ros.call(ChangeState, f"{NODE}/change_state", req).success
        _, _, node = wait_status(
            ch,
            NODE_STATUS,
            lambda s: diag_values(s)["lifecycle_state"] == label,
            f"lifecycle_state {label}",
            start=len(ch.diagnostics.messages),
        )
        assert diag_level(node) == OK, node


# ---------------------------------------------------------------------------------------------
# diagnostic_aggregator's GenericAnalyzer (Jazzy), as far as its matching and naming go
# ---------------------------------------------------------------------------------------------


def as_list(value: Any) -> list[str]:
    """A string or a list of strings, as the analyzer's parameters accept them."""
    if value is None:
        return []
    return [value] if isinstance(value, str) else list(value)


def analyzer_matches(cfg: dict[str, Any], name: str) -> bool:
    """GenericAnalyzer::match: a regex (whole name), a name start or a name part."""
    starts = as_list(cfg.get("startswith")) + as_list(cfg.get("find_and_remove_prefix"))
    return (
        any(re.fullmatch(r, name) for r in as_list(cfg.get("regex")))
        or any(name.startswith(p) for p in starts)
        or any(c in name for c in as_list(cfg.get("contains")))
    )


def remove_leading_chaff(name: str, chaff: str) -> str:
    """diagnostic_aggregator's removeLeadingNameChaff: the chaff after the last '/', then a
    ':' and the spaces that follow it."""
    last = name.rfind("/")
    head, tail = name[: last + 1], name[last + 1 :]
    if tail.startswith(chaff):
        tail = tail[len(chaff) :]
    if tail.startswith(":"):
        tail = tail[1:]
    return head + tail.lstrip(" ")


def aggregated_name(cfg: dict[str, Any], name: str) -> str:
    """The item's name on /diagnostics_agg: the analyzer's path, '/', the name with '/' made
    ' ', each chaff removed."""
    out = f"/{cfg['path']}/{name.replace('/', ' ')}"
    chaff = as_list(cfg.get("find_and_remove_prefix")) + as_list(cfg.get("remove_prefix"))
    for c in chaff:
        out = remove_leading_chaff(out, c.replace("/", " "))
    return out


@pytest.mark.untimed
def test_the_aggregator_analyzers_take_every_status_the_node_publishes(node_process, ros):
    doc = yaml.safe_load(ANALYZERS.read_text())
    params = doc["analyzers"]["ros__parameters"]
    cfg = params["pwm_actuator"]
    assert cfg["type"] == "diagnostic_aggregator/GenericAnalyzer", cfg
    assert isinstance(cfg["path"], str) and cfg["path"], cfg
    # The analyzer reads these as a double and as string arrays (rclcpp parameters: a wrong
    # type is an exception, not a conversion).
    assert isinstance(cfg.get("timeout", 5.0), float), cfg
    for key in ("find_and_remove_prefix", "expected"):
        assert isinstance(cfg.get(key, []), list), (key, cfg)

    proc = node_process(node_args(channels=3))
    ch = ChannelClient(ros, "pw01")
    ch.wait_connected()
    array = ch.diagnostics.wait_for(
        lambda a: any(s.name == NODE_STATUS for s in a.status), what="a full /diagnostics"
    )
    names = [s.name for s in array.status]
    channels = ("pw01", "pw02", "pw03")
    assert names == [
        *(f"{NODE_NAME}: {c}" for c in channels),
        *(freq_name(c) for c in channels),
        NODE_STATUS,
        f"{NODE_NAME}: trace {proc.trace_path}",
    ], names

    # Every status the node publishes is taken, each under the path with the prefix gone;
    # a status of another node is not.
    for n in names:
        assert analyzer_matches(cfg, n), f"{n!r} not taken by the analyzer"
    short = [aggregated_name(cfg, n) for n in names]
    base = f"/{cfg['path']}/"
    assert short == [
        *(base + c for c in channels),
        *(f"{base}{c} command frequency" for c in channels),
        base + "node",
        # The aggregator makes each '/' of a name a space.
        f"{base}trace {str(proc.trace_path).replace('/', ' ')}",
    ], short
    for other in ("pwm_actuator_2: pw01", "camera: pwm_actuator: x", "heater: pw01"):
        assert not analyzer_matches(cfg, other), other
    # What it expects is what the node publishes.
    for n in as_list(cfg.get("expected")):
        assert n in names, f"expected {n!r} is not published: {names}"
