"""An rclpy client on "another host" for test_static_peers.py: run inside a network namespace,
it looks for the node for a bounded time and prints one JSON line saying what it got.

    python static_peers_client.py SECONDS [--full]

Without `--full` it only watches: whether the node is in the ROS graph and whether any
`/diagnostics` array of the node arrived. With `--full` it also asks the node for a parameter
(`get_parameters`), and enables channel pw01 and commands it 37 % until the node's status shows
both, then counts the rising edges the node reports after that. It stops as soon as everything it
looks for has arrived, or after SECONDS.

This script only talks to the node and reports; the test asserts on what it printed. The
environment (ROS_DOMAIN_ID, ROS_STATIC_PEERS, ROS_AUTOMATIC_DISCOVERY_RANGE) is the caller's.
"""

from __future__ import annotations

import json
import math
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from pwm_actuator_msgs.msg import ChannelStatus, OutputEdge
from rcl_interfaces.srv import GetParameters
from rclpy.parameter import parameter_value_to_python
from std_msgs.msg import Bool, Float64

NODE = "/pwm_actuator"
CHANNEL = f"{NODE}/pw01"
DUTY = 37.0
#: Rising edges reported after the command that count as "the node acts on it".
RISES = 3


def main() -> int:
    seconds = float(sys.argv[1])
    full = "--full" in sys.argv[2:]
    rclpy.init()
    node = rclpy.create_node("static_peers_client")
    start = time.monotonic()
    got: dict = {
        "rmw": rclpy.utilities.get_rmw_implementation_identifier(),
        "seen_s": None,
        "diagnostics": 0,
        "parameter": None,
        "commanded_s": None,
        "rises_after_command": 0,
    }

    def on_diag(msg: DiagnosticArray) -> None:
        if any(s.name.startswith("pwm_actuator") for s in msg.status):
            got["diagnostics"] += 1

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    duty_pub = node.create_publisher(Float64, f"{CHANNEL}/duty", 10)
    enable_pub = node.create_publisher(Bool, f"{CHANNEL}/enable", 10)
    commanded = [False]

    def on_status(s: ChannelStatus) -> None:
        if s.enabled and math.isclose(s.duty_commanded, DUTY) and not commanded[0]:
            commanded[0] = True
            got["commanded_s"] = round(time.monotonic() - start, 2)

    def on_edge(e: OutputEdge) -> None:
        if commanded[0] and e.level:
            got["rises_after_command"] += 1

    node.create_subscription(ChannelStatus, f"{CHANNEL}/status", on_status, 10)
    node.create_subscription(OutputEdge, f"{CHANNEL}/edges", on_edge, 100)
    params = node.create_client(GetParameters, f"{NODE}/get_parameters")
    pending = None
    next_send = 0.0

    def done() -> bool:
        if not full:
            return got["seen_s"] is not None and got["diagnostics"] > 0
        return (
            got["diagnostics"] > 0
            and got["parameter"] is not None
            and got["rises_after_command"] >= RISES
        )

    while time.monotonic() - start < seconds and not done():
        rclpy.spin_once(node, timeout_sec=0.1)
        if got["seen_s"] is None and "pwm_actuator" in node.get_node_names():
            got["seen_s"] = round(time.monotonic() - start, 2)
        if not full:
            continue
        if pending is None and got["parameter"] is None and params.service_is_ready():
            pending = params.call_async(GetParameters.Request(names=["pw01.period_ms"]))
        if pending is not None and pending.done():
            values = pending.result().values
            if values:
                got["parameter"] = parameter_value_to_python(values[0])
            pending = None
        # Commands are idempotent: repeated until the status shows them.
        if not commanded[0] and time.monotonic() >= next_send:
            if duty_pub.get_subscription_count() and enable_pub.get_subscription_count():
                enable_pub.publish(Bool(data=True))
                duty_pub.publish(Float64(data=DUTY))
            next_send = time.monotonic() + 1.0
    got["elapsed_s"] = round(time.monotonic() - start, 2)
    print(json.dumps(got), flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
