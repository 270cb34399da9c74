"""Fresh clients and one-shot publishers, as the ROS 2 command line makes them, are served at once.

Every `ros2 param get/set`, `ros2 service call` and `ros2 lifecycle set` is a new process with a
new client that waits for the service, calls once and waits for the answer; `ros2 topic pub
--once` is a new publisher that waits until it is matched and publishes once. Each trial here is
such a process (helpers_fresh.py): TRIALS each of `get_parameters`, `set_parameters`,
`reset_estop` and `change_state` (the node started with `--managed`; configure and cleanup in
turn), and of one-shot `duty`, `enable` and `params` commands, each confirmed by what the node
reports (`~/<ch>/status`, `/parameter_events`) to a subscriber that stays. Every call must be
answered and every command applied. How many did so within LIMIT_S (200 ms), and p50, p99 and
max, are printed for both nodes; the test fails on a trial slower than ASSERT_S (1 s): a lost
first request or sample costs a Fast DDS heartbeat period (3 s), while the delays of a loaded
2-core machine (p99 up to ~0.7 s for the rclpy reference at a load average of 15) stay below
it.

The same trials run against an rclpy node of the same shape (reference_node.py), the yardstick,
in a test of their own: that node must answer every call and apply every command within
CONFIRM_TIMEOUT_S (6 s), but its times are only shown, since a Python node on a loaded 2-core
machine is itself sometimes late. The yardstick runs on rmw_fastrtps as shipped, which drops a
response when the fresh client's response reader is not matched within the response writer's
`max_blocking_time` (100 ms by default) and says so on stderr ("client will not receive
response": rmw_fastrtps_shared_cpp's rmw_response.cpp, ros2/ros2#1253): such a drop is counted
and shown, not failed, as long as each unanswered call has its warning and they stay below 1 in
100 calls; anything else the reference misses fails the test. Its trials take under a second even then, so the 6 s bound has
far more than a factor of two to spare: that test is `untimed` (pytest.ini) and scripts/test.sh
runs it beside the others, while the node's trials, timed, run one test at a time. Both tables (p50, p99, max per kind) are printed together
at the end of the run (conftest.py's `show_figures`), also when the two tests ran in different
pytest processes. Before the vendored rustdds's third change (vendor/rustdds/README.pwm_actuator.md)
about half of the node's trials took 3 s, a Fast DDS heartbeat period.

Trials run in LANES concurrent lanes (one channel each, so the enable flags alternate per lane;
every change_state in lane 0, so each transition is valid), a lane's next trial starting once
the previous one was confirmed or given up.

Environment: PWM_FRESH_TRIALS (default 100), PWM_FRESH_LANES (default 6). `-k reference` or
`-k node` runs one of the two tests.
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import pytest
import rclpy
from conftest import wait_until
from helpers_fresh import SERVICE_KINDS, TOPIC_KINDS, Trial, TrialProcess
from helpers_rules import NODE, node_args
from pwm_actuator_msgs.msg import ChannelStatus
from rcl_interfaces.msg import ParameterEvent
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import qos_profile_parameter_events
from rclpy.signals import SignalHandlerOptions

#: Trials of each kind, per node.
TRIALS = int(os.environ.get("PWM_FRESH_TRIALS", "100"))
#: Concurrent lanes (and channels of the node).
LANES = int(os.environ.get("PWM_FRESH_LANES", "6"))
#: The target for every call and command, s (printed: how many met it).
LIMIT_S = 0.200
#: What fails the test, s: well below the 3 s of a lost first sample, well above load delays.
ASSERT_S = 1.0
#: What a lane waits for a command to take effect before it counts it as not applied, s.
CONFIRM_TIMEOUT_S = 6.0
REFERENCE_NODE = Path(__file__).with_name("reference_node.py")
#: What rmw_fastrtps writes when it drops a response to a client whose reader it has not matched.
RMW_DROPPED_RESPONSE = "client will not receive response"
KINDS = SERVICE_KINDS + TOPIC_KINDS


def channel_of(lane: int) -> str:
    return f"pw{lane + 1:02d}"


def plan(trials: int) -> list[list[Trial]]:
    """The trials of each lane, interleaved by index, change_state all in lane 0."""
    lanes: list[list[Trial]] = [[] for _ in range(LANES)]
    enables = [False] * LANES
    for i in range(trials):
        # configure, cleanup, configure, ...: each valid in the state the previous one left.
        lanes[0].append(Trial("change_state", NODE, channel_of(0), 1 if i % 2 == 0 else 2, i))
        for kind in ("get_parameters", "set_parameters", "reset_estop") + TOPIC_KINDS:
            lane = min(range(LANES), key=lambda n: (len(lanes[n]), n))
            channel = channel_of(lane)
            if kind == "enable":
                enables[lane] = not enables[lane]
                value: Any = enables[lane]
            elif kind == "duty":
                value = 1.0 + 0.25 * i
            elif kind == "params":
                value = round(0.001 * (i + 1), 6)
            elif kind == "set_parameters":
                value = 1.0 + i
            else:
                value = None
            lanes[lane].append(Trial(kind, NODE, channel, value, i))
    return lanes


class Observer:
    """A subscriber that stays: each lane channel's status and /parameter_events, with arrival
    times (time.monotonic()), spun in a thread of its own."""

    def __init__(self, domain_id: int) -> None:
        self.context = Context()
        rclpy.init(
            context=self.context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO
        )
        self.node = rclpy.create_node("fresh_observer", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._cond = threading.Condition()
        self.status: dict[str, list[tuple[float, ChannelStatus]]] = {}
        self.status_subs = {}
        for lane in range(LANES):
            ch = channel_of(lane)
            self.status[ch] = []
            self.status_subs[ch] = self.node.create_subscription(
                ChannelStatus, f"{NODE}/{ch}/status", self._on(self.status[ch]), 100
            )
        self.events: list[tuple[float, ParameterEvent]] = []
        self.events_sub = self.node.create_subscription(
            ParameterEvent, "/parameter_events", self._on(self.events), qos_profile_parameter_events
        )
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _on(self, log: list) -> Callable[[Any], None]:
        def record(msg: Any) -> None:
            now = time.monotonic()
            with self._cond:
                log.append((now, msg))
                self._cond.notify_all()

        return record

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def wait_connected(self) -> None:
        for ch, sub in self.status_subs.items():
            wait_until(lambda: sub.get_publisher_count() > 0, f"a publisher of {ch}/status")
        wait_until(
            lambda: self.events_sub.get_publisher_count() > 0, "a publisher of /parameter_events"
        )

    def arrival(self, trial: Trial, after: float, timeout: float) -> Optional[float]:
        """When what `trial` commanded was first reported after `after`, or None."""

        def find() -> Optional[float]:
            if trial.kind == "params":
                name = f"{trial.channel}.edge_band"
                for t, event in self.events:
                    if t < after or event.node != trial.node:
                        continue
                    for p in event.changed_parameters:
                        if p.name == name and p.value.double_value == trial.value:
                            return t
                return None
            for t, status in self.status[trial.channel]:
                if t < after:
                    continue
                if trial.kind == "duty" and abs(status.duty_commanded - trial.value) < 1e-9:
                    return t
                if trial.kind == "enable" and status.enabled == trial.value:
                    return t
            return None

        deadline = time.monotonic() + timeout
        with self._cond:
            while (found := find()) is None:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return found

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.executor.shutdown(timeout_sec=5.0)
        self.node.destroy_node()
        self.context.try_shutdown()


@dataclass
class Outcome:
    trial: Trial
    latency_s: float  # math.inf: never answered or applied
    wait_s: float = math.nan  # from creating the client or publisher until it was matched
    pid: int = 0  # the trial's process (Fast DDS puts it in the participant's GUID prefix)
    problem: str = ""  # why it failed, beyond being late


def check_answer(trial: Trial, result: dict[str, Any]) -> str:
    if trial.kind == "get_parameters" and result.get("values") != 1:
        return f"{result.get('values')} values for 1 name"
    if trial.kind == "set_parameters" and result.get("successful") != [True]:
        return f"refused: {result.get('successful')}"
    if trial.kind == "change_state" and result.get("success") is not True:
        return f"transition {trial.value} failed"
    return ""


def run_lane(domain_id: int, observer: Observer, trials: list[Trial]) -> list[Outcome]:
    outcomes = []
    for trial in trials:
        proc = TrialProcess(domain_id, trial)
        try:
            result = proc.result()
            if result is None:
                outcomes.append(Outcome(trial, math.inf, problem="the trial process reported nothing"))
            elif trial.kind in SERVICE_KINDS:
                if not result["ready"]:
                    outcomes.append(Outcome(trial, math.inf, problem="service never ready"))
                elif not result["answered"]:
                    outcomes.append(Outcome(trial, math.inf, problem="no answer"))
                else:
                    problem = check_answer(trial, result)
                    outcomes.append(
                        Outcome(trial, result["latency_s"], result["wait_s"], result["pid"], problem)
                    )
            elif not result["matched"]:
                outcomes.append(Outcome(trial, math.inf, problem="publisher never matched"))
            else:
                t_publish = result["t_publish"]
                seen = observer.arrival(trial, t_publish, CONFIRM_TIMEOUT_S)
                if seen is None:
                    outcomes.append(Outcome(trial, math.inf, problem="never applied"))
                else:
                    outcomes.append(Outcome(trial, seen - t_publish, result["wait_s"], result["pid"]))
        finally:
            proc.release()
    return outcomes


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[max(0, math.ceil(q * len(ordered)) - 1)]


def table(label: str, outcomes: list[Outcome]) -> str:
    def ms(x: float) -> str:
        return "never" if math.isinf(x) else f"{x * 1000:.1f}"

    lines = [f"{label}: fresh process per trial, limit {LIMIT_S * 1000:.0f} ms"]
    lines.append(
        f"  {'kind':<15}{'n':>5}{'in time':>9}{'p50 ms':>10}{'p99 ms':>10}{'max ms':>10}"
        f"{'match p50 ms':>14}"
    )
    for kind in KINDS:
        lat = [o.latency_s for o in outcomes if o.trial.kind == kind]
        waits = [o.wait_s for o in outcomes if o.trial.kind == kind and not math.isnan(o.wait_s)]
        waits = waits or [math.inf]
        ok = sum(1 for o in outcomes if o.trial.kind == kind and o.latency_s <= LIMIT_S)
        lines.append(
            f"  {kind:<15}{len(lat):>5}{ok:>9}{ms(percentile(lat, 0.5)):>10}"
            f"{ms(percentile(lat, 0.99)):>10}{ms(max(lat)):>10}{ms(percentile(waits, 0.5)):>14}"
        )
    return "\n".join(lines)


def run_all(domain_id: int) -> list[Outcome]:
    observer = Observer(domain_id)
    try:
        observer.wait_connected()
        lanes = plan(TRIALS)
        with ThreadPoolExecutor(max_workers=LANES) as pool:
            results = list(pool.map(lambda trials: run_lane(domain_id, observer, trials), lanes))
        return [o for lane in results for o in lane]
    finally:
        observer.close()


def failures(label: str, outcomes: list[Outcome], limit_s: float) -> list[str]:
    bad = [o for o in outcomes if o.problem or o.latency_s > limit_s]
    return [
        f"{label} {o.trial.kind} #{o.trial.index} on {o.trial.channel} (pid {o.pid}): "
        + (o.problem or f"took {o.latency_s * 1000:.0f} ms")
        for o in bad
    ]


def measure(
    domain_id: int, show_figures: Callable[[str, str, str], None], key: str, label: str
) -> list[Outcome]:
    """All trials against the node on `domain_id`; their table shown (`show_figures`) with
    when they started, so that the two tables printed together are seen to be of one run."""
    when = time.strftime("%H:%M:%S")
    started = time.monotonic()
    outcomes = run_all(domain_id)
    label = f"{label} ({time.monotonic() - started:.0f} s from {when})"
    show_figures("fresh clients", key, table(label, outcomes))
    return outcomes


# 700 processes: about 3 min for the reference on a loaded 2-core machine, beyond pytest.ini's
# 180 s per test.
@pytest.mark.untimed
@pytest.mark.timeout(600)
def test_the_rclpy_reference_node_answers_every_fresh_client_and_one_shot_publisher(
    process_launcher, ros_domain_id: int, show_figures
):
    """The yardstick: every call answered (but for rmw_fastrtps's own, rare, drops) and every
    command applied within 6 s; times shown."""
    reference = process_launcher.launch(
        [sys.executable, str(REFERENCE_NODE), str(LANES)], name="reference"
    )
    reference.wait_for_output("reference node ready")
    outcomes = measure(ros_domain_id, show_figures, "1-reference", "rclpy reference node")
    reference.terminate()
    dropped_by_rmw = reference.stderr().count(RMW_DROPPED_RESPONSE)
    unanswered = [o for o in outcomes if o.trial.kind in SERVICE_KINDS and o.problem == "no answer"]
    service_calls = sum(1 for o in outcomes if o.trial.kind in SERVICE_KINDS)
    show_figures(
        "fresh clients",
        "1-reference-rmw",
        f"  rmw_fastrtps dropped {dropped_by_rmw} of the reference's {service_calls} responses "
        f"({RMW_DROPPED_RESPONSE!r}); {len(unanswered)} calls unanswered",
    )
    # Each unanswered call has rmw_fastrtps's own warning, and they are rare.
    assert len(unanswered) <= dropped_by_rmw, (
        f"{len(unanswered)} calls unanswered, {dropped_by_rmw} dropped by rmw_fastrtps:\n"
        + "\n".join(failures("rclpy reference node", unanswered, CONFIRM_TIMEOUT_S))
    )
    assert len(unanswered) * 100 < service_calls, f"{len(unanswered)} of {service_calls} unanswered"
    problems = failures(
        "rclpy reference node", [o for o in outcomes if o not in unanswered], CONFIRM_TIMEOUT_S
    )
    assert not problems, f"{len(problems)} trials failed:\n" + "\n".join(problems[:40])


# 700 processes: about 1.5-2 min on a loaded 2-core machine, beyond pytest.ini's 180 s at worst.
@pytest.mark.timeout(600)
def test_fresh_clients_and_one_shot_publishers_are_served_at_once(
    node_process, ros_domain_id: int, show_figures
):
    node_process(["--managed"] + node_args(channels=LANES))
    outcomes = measure(ros_domain_id, show_figures, "2-node", "pwm_actuator")
    problems = failures("pwm_actuator", outcomes, ASSERT_S)
    assert not problems, f"{len(problems)} trials failed:\n" + "\n".join(problems[:40])
