#!/usr/bin/env python3
"""The README's quick start, step by step, from rclpy.

Start the node first (in another terminal):

    cargo run --release -- --trace /tmp/pw.vcd --ros-args -p pw01.period_ms:=2000

then, from the repository root:

    source scripts/env.sh && python3 docs/quickstart.py

Each step prints the ROS 2 command line that does the same. The script commands pw01 to 25 %,
enables it, watches its edges and diagnostics, sets its period to 1000 ms through the
parameter service, watches again, then disables the channel. It exits 0 when edges came and
the parameter was accepted, 1 otherwise.
"""

import argparse
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from std_msgs.msg import Bool, Float64

from pwm_actuator_msgs.msg import OutputEdge


def step(text, cli):
    print(f"\n== {text}\n   ros2 CLI: {cli}", flush=True)


def spin_for(node, seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--node", default="/pwm_actuator", help="the node's full name")
    ap.add_argument("--watch", type=float, default=4.0, help="seconds to watch after each step")
    args = ap.parse_args()
    ns = args.node

    rclpy.init()
    node = Node("quickstart")
    edges, levels = [], {}

    def on_edge(e):
        edges.append(e)
        state = "on " if e.level else "off"
        print(f"   edge #{e.seq}: pw01 {state} at {e.stamp.sec}.{e.stamp.nanosec:09d}, "
              f"{e.lateness_ns / 1000:.0f} us late", flush=True)

    def on_diagnostics(d):
        for s in d.status:
            if s.name.endswith(": pw01") and levels.get(s.name) != (s.level, s.message):
                levels[s.name] = (s.level, s.message)
                print(f"   diagnostics: {s.name}: level {ord(s.level)} {s.message}", flush=True)

    step("1. Publishers for duty and enable, subscriptions to edges and diagnostics",
         f"ros2 topic echo {ns}/pw01/edges   (and: ros2 topic echo /diagnostics)")
    duty = node.create_publisher(Float64, f"{ns}/pw01/duty", 10)
    enable = node.create_publisher(Bool, f"{ns}/pw01/enable", 10)
    node.create_subscription(OutputEdge, f"{ns}/pw01/edges", on_edge, 10)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
    deadline = time.monotonic() + 10.0
    while (duty.get_subscription_count() == 0 or enable.get_subscription_count() == 0) \
            and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    if duty.get_subscription_count() == 0:
        print(f"   no node subscribes to {ns}/pw01/duty: is it running, on this ROS_DOMAIN_ID?")
        return 1
    print("   matched the node's subscriptions")

    step("2. Command 25 %: 500 ms on, 1500 ms off at the 2000 ms period",
         f'ros2 topic pub --once {ns}/pw01/duty std_msgs/msg/Float64 "{{data: 25.0}}"')
    duty.publish(Float64(data=25.0))

    step("3. Enable the channel: a new period starts with its on phase",
         f'ros2 topic pub --once {ns}/pw01/enable std_msgs/msg/Bool "{{data: true}}"')
    enable.publish(Bool(data=True))
    spin_for(node, args.watch)
    seen_before = len(edges)

    step("4. Set the period to 1000 ms while running (from the next period on)",
         f"ros2 param set {ns} pw01.period_ms 1000")
    client = node.create_client(SetParameters, f"{ns}/set_parameters")
    if not client.wait_for_service(timeout_sec=5.0):
        print("   the parameter service did not appear")
        return 1
    request = SetParameters.Request(parameters=[Parameter(
        name="pw01.period_ms",
        value=ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=1000))])
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=5.0)
    result = future.result()
    accepted = result is not None and result.results[0].successful
    print(f"   successful={accepted}" + ("" if accepted or result is None
                                          else f", reason: {result.results[0].reason}"))
    spin_for(node, args.watch)

    step("5. Disable the channel: the output goes off at once",
         f'ros2 topic pub --once {ns}/pw01/enable std_msgs/msg/Bool "{{data: false}}"')
    enable.publish(Bool(data=False))
    spin_for(node, 1.0)

    print(f"\n{len(edges)} edges seen ({seen_before} at 2000 ms, "
          f"{len(edges) - seen_before} after the change); period change accepted: {accepted}")
    node.destroy_node()
    rclpy.shutdown()
    return 0 if seen_before > 0 and accepted else 1


if __name__ == "__main__":
    sys.exit(main())
