"""Helpers for test_fresh_clients.py: one-shot rclpy clients and publishers, each in a process of
its own, as `ros2 service call`, `ros2 param set`, `ros2 lifecycle set` and
`ros2 topic pub --once` are.

A trial runs in a child of a fork server that has imported rclpy but never initialised it
(`multiprocessing`'s "forkserver" start method with this module preloaded), so each trial is a
new process with a new DDS participant, a new GUID prefix and nothing discovered yet, at the
cost of a fork rather than of a Python start. Several contexts in one process do not show the
same timing: the problem these trials look for (a first request or sample lost on a new match,
repaired a heartbeat period later) was seen only with a process per call.

A service trial creates a client, waits for the service (`wait_for_service`), calls once and
waits for the answer; it reports the time from the call to the answer. A topic trial creates a
publisher, waits until it is matched with a subscription (`get_subscription_count() > 0`),
publishes once and reports when; it then stays until the test has seen the command take effect
(or given up), so that a lost first sample could still be repaired as it would be for a
publisher that stays.

This module must not assert the node's behaviour; it only runs trials and reports times.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from dataclasses import dataclass
from typing import Any, Optional

import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from pwm_actuator_msgs.msg import ChannelParams
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Bool, Float64
from std_srvs.srv import Trigger

#: What a trial waits for a service or a subscription to be discovered, s.
DISCOVERY_TIMEOUT_S = 30.0
#: What a service trial waits for the answer, s (well beyond the 3 s a lost request costs).
ANSWER_TIMEOUT_S = 10.0
#: What a topic trial stays at most after publishing, waiting to be released, s.
LINGER_MAX_S = 15.0

SERVICE_KINDS = ("get_parameters", "set_parameters", "reset_estop", "change_state")
TOPIC_KINDS = ("duty", "enable", "params")


@dataclass(frozen=True)
class Trial:
    """One fresh client or publisher. `value` is what it sends: the parameter value, the duty,
    the enable flag, the edge band, or the lifecycle transition id."""

    kind: str
    node: str
    channel: str
    value: Any
    index: int


def _request(trial: Trial) -> tuple[Any, str, Any]:
    """(service type, service name, request) of a service trial."""
    if trial.kind == "get_parameters":
        names = [f"{trial.channel}.edge_band"]
        return GetParameters, f"{trial.node}/get_parameters", GetParameters.Request(names=names)
    if trial.kind == "set_parameters":
        value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=trial.value)
        param = Parameter(name=f"{trial.channel}.expected_command_hz_max", value=value)
        return SetParameters, f"{trial.node}/set_parameters", SetParameters.Request(
            parameters=[param]
        )
    if trial.kind == "reset_estop":
        return Trigger, f"{trial.node}/reset_estop", Trigger.Request()
    if trial.kind == "change_state":
        request = ChangeState.Request(transition=Transition(id=trial.value))
        return ChangeState, f"{trial.node}/change_state", request
    raise ValueError(trial.kind)


def _summary(trial: Trial, response: Any) -> dict[str, Any]:
    """What the test checks of an answer."""
    if trial.kind == "get_parameters":
        return {"values": len(response.values)}
    if trial.kind == "set_parameters":
        return {"successful": [r.successful for r in response.results]}
    if trial.kind in ("reset_estop", "change_state"):
        return {"success": bool(response.success)}
    return {}


def _message(trial: Trial) -> tuple[Any, str, Any]:
    """(message type, topic, message) of a topic trial."""
    topic = f"{trial.node}/{trial.channel}/{trial.kind}"
    if trial.kind == "duty":
        return Float64, topic, Float64(data=float(trial.value))
    if trial.kind == "enable":
        return Bool, topic, Bool(data=bool(trial.value))
    if trial.kind == "params":
        return ChannelParams, topic, ChannelParams(set=["edge_band"], edge_band=trial.value)
    raise ValueError(trial.kind)


def run_trial(conn: Any, domain_id: int, trial: Trial) -> None:
    """The body of one trial's process: sends one dict on `conn` (times are time.monotonic()).

    Service trials: {"ready": bool, "wait_s", "pid", "answered": bool, "latency_s", ...the
    answer}. Topic trials: {"matched": bool, "wait_s", "t_publish", "pid"}; then waits for any message on
    `conn` (or LINGER_MAX_S) before it leaves.
    """
    context = Context()
    rclpy.init(context=context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    node = Node(
        f"fresh_{trial.kind}_{os.getpid()}",
        context=context,
        start_parameter_services=False,
        enable_rosout=False,
    )
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        if trial.kind in SERVICE_KINDS:
            srv_type, service, request = _request(trial)
            client = node.create_client(srv_type, service)
            t0 = time.monotonic()
            ready = client.wait_for_service(timeout_sec=DISCOVERY_TIMEOUT_S)
            result: dict[str, Any] = {
                "ready": ready,
                "wait_s": time.monotonic() - t0,
                "pid": os.getpid(),
            }
            if ready:
                t_call = time.monotonic()
                future = client.call_async(request)
                executor.spin_until_future_complete(future, timeout_sec=ANSWER_TIMEOUT_S)
                t_done = time.monotonic()
                response = future.result() if future.done() else None
                result["answered"] = response is not None
                result["latency_s"] = t_done - t_call
                if response is not None:
                    result.update(_summary(trial, response))
            conn.send(result)
        else:
            msg_type, topic, msg = _message(trial)
            publisher = node.create_publisher(msg_type, topic, 10)
            t0 = time.monotonic()
            while publisher.get_subscription_count() == 0:
                if time.monotonic() - t0 > DISCOVERY_TIMEOUT_S:
                    break
                time.sleep(0.005)
            matched = publisher.get_subscription_count() > 0
            t_publish = time.monotonic()
            if matched:
                publisher.publish(msg)
            conn.send(
                {
                    "matched": matched,
                    "wait_s": t_publish - t0,
                    "t_publish": t_publish,
                    "pid": os.getpid(),
                }
            )
            if matched:
                # The DDS threads repair a lost sample while this process waits here.
                conn.poll(LINGER_MAX_S)
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        context.try_shutdown()
        conn.close()


_MP: Optional[Any] = None


def mp_context() -> Any:
    """The fork server's multiprocessing context (started on first use, this module preloaded)."""
    global _MP
    if _MP is None:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload([__name__])
        _MP = ctx
    return _MP


class TrialProcess:
    """One trial's process; `result()` waits for what it reports, `release()` lets it go."""

    def __init__(self, domain_id: int, trial: Trial) -> None:
        ctx = mp_context()
        self.trial = trial
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=run_trial, args=(child, domain_id, trial), daemon=True)
        self._proc.start()
        child.close()

    def result(self) -> Optional[dict[str, Any]]:
        """The trial's report, or None if it sent none (it died or hung)."""
        limit = DISCOVERY_TIMEOUT_S + ANSWER_TIMEOUT_S + 10.0
        if self._conn.poll(limit):
            try:
                return self._conn.recv()
            except EOFError:
                return None
        return None

    def release(self) -> None:
        """Lets the trial leave and waits for its process to end (killed if it does not)."""
        try:
            self._conn.send("done")
        except (BrokenPipeError, OSError):
            pass
        self._proc.join(10.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()
        self._conn.close()


__all__ = [
    "SERVICE_KINDS",
    "TOPIC_KINDS",
    "Trial",
    "TrialProcess",
    "mp_context",
]
