"""A client asking an action server for the results of goals it never had: get_result requests
with random goal ids on `<action>/_action/get_result`, WINDOW of them outstanding at a time.

As a program (one participant of its own): connects, asks WARMUP results, prints `ready`, waits
until the file GO exists, asks COUNT results, prints `done <answered> <unknown> <seconds>`, and
waits until the file GO is gone before it leaves (so that whoever measures the server can do so
while every client is still there). Exits 1 if a request was not answered within TIMEOUT s.

Usage: python result_flood.py ACTION COUNT WARMUP WINDOW GO [TIMEOUT]
"""

from __future__ import annotations

import os
import sys
import time

import rclpy
from action_msgs.msg import GoalStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from pwm_actuator_msgs.action import Autotune

GetResult = Autotune.Impl.GetResultService


#: The client's QoS: reliable, volatile, keep last 256. Every client's reply reader takes in the
#: answers to all clients of the service; with rclpy's default (keep last 10) the answers to a
#: few clients' requests at once push each other out of it.
QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=256,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)


def make_client(node, action: str):
    return node.create_client(GetResult, f"{action}/_action/get_result", qos_profile=QOS)


def flood(executor, client, count: int, window: int, timeout: float) -> tuple[int, int]:
    """Sends `count` requests with random goal ids, `window` at a time; returns (answered,
    answered with STATUS_UNKNOWN). Raises TimeoutError when no answer comes for `timeout` s."""
    pending: list = []
    sent = answered = unknown = 0
    last_answer = time.monotonic()
    while answered < count:
        while sent < count and len(pending) < window:
            req = GetResult.Request()
            req.goal_id.uuid = list(os.urandom(16))
            pending.append(client.call_async(req))
            sent += 1
        executor.spin_once(timeout_sec=0.05)
        still = []
        for f in pending:
            if f.done():
                answered += 1
                unknown += f.result().status == GoalStatus.STATUS_UNKNOWN
            else:
                still.append(f)
        if len(still) < len(pending):
            last_answer = time.monotonic()
        elif time.monotonic() - last_answer > timeout:
            raise TimeoutError(
                f"{len(pending)} requests unanswered for {timeout} s after {answered} answers"
            )
        pending = still
    return answered, unknown


def main(argv: list[str]) -> int:
    action, count, warmup, window, go = argv[1], int(argv[2]), int(argv[3]), int(argv[4]), argv[5]
    timeout = float(argv[6]) if len(argv) > 6 else 20.0
    rclpy.init()
    node = rclpy.create_node(f"result_flood_{os.getpid()}")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    client = make_client(node, action)
    deadline = time.monotonic() + 60
    while not client.service_is_ready():
        if time.monotonic() > deadline:
            print("no get_result service", flush=True)
            return 1
        executor.spin_once(timeout_sec=0.1)
    try:
        flood(executor, client, warmup, window, timeout)
        print("ready", flush=True)
        while not os.path.exists(go):
            executor.spin_once(timeout_sec=0.05)
        t0 = time.monotonic()
        answered, unknown = flood(executor, client, count, window, timeout)
        print(f"done {answered} {unknown} {time.monotonic() - t0:.3f}", flush=True)
    except TimeoutError as e:
        print(f"timeout: {e}", flush=True)
        return 1
    while os.path.exists(go):
        executor.spin_once(timeout_sec=0.05)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
