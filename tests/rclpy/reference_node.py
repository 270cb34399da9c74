"""An rclpy node with the shape of pwm_actuator's ROS interface, as far as test_fresh_clients.py
uses it: the yardstick for how fast a fresh rclpy client or publisher is served by a node on
rclpy itself (Fast DDS), on the same machine, in the same run.

It is a managed node named `pwm_actuator` (rclpy's LifecycleNode: `~/change_state` and the other
lifecycle services) with rclpy's parameter services, a `std_srvs/Trigger` service
`~/reset_estop`, and per channel `pwNN`: the parameters `pwNN.edge_band` and
`pwNN.expected_command_hz_max`, the inputs `~/pwNN/duty` (std_msgs/Float64), `~/pwNN/enable`
(std_msgs/Bool) and `~/pwNN/params` (pwm_actuator_msgs/ChannelParams, the fields named in `set`
that are parameters here are set together), and the output `~/pwNN/status`
(pwm_actuator_msgs/ChannelStatus, published on every change of `enabled` or `duty_commanded`).
Accepted parameter changes appear on /parameter_events as rclpy publishes them. It does nothing
else: no output, no timing.

Usage: python reference_node.py CHANNELS  (runs until SIGINT / SIGTERM)
"""

from __future__ import annotations

import sys

import rclpy
from pwm_actuator_msgs.msg import ChannelParams, ChannelStatus
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode
from rclpy.parameter import Parameter
from std_msgs.msg import Bool, Float64
from std_srvs.srv import Trigger


class Channel:
    def __init__(self, node: "ReferenceNode", number: int) -> None:
        self.node = node
        self.number = number
        self.name = f"pw{number:02d}"
        self.enabled = False
        self.duty = 0.0
        node.declare_parameter(f"{self.name}.edge_band", 0.0)
        node.declare_parameter(f"{self.name}.expected_command_hz_max", 0.0)
        self.status = node.create_publisher(ChannelStatus, f"~/{self.name}/status", 10)
        node.create_subscription(Float64, f"~/{self.name}/duty", self.on_duty, 10)
        node.create_subscription(Bool, f"~/{self.name}/enable", self.on_enable, 10)
        node.create_subscription(ChannelParams, f"~/{self.name}/params", self.on_params, 10)

    def publish_status(self) -> None:
        msg = ChannelStatus(channel=self.number, enabled=self.enabled, duty_commanded=self.duty)
        msg.stamp = self.node.get_clock().now().to_msg()
        self.status.publish(msg)

    def on_duty(self, msg: Float64) -> None:
        self.duty = min(max(msg.data, 0.0), 100.0)
        self.publish_status()

    def on_enable(self, msg: Bool) -> None:
        self.enabled = msg.data
        self.publish_status()

    def on_params(self, msg: ChannelParams) -> None:
        params = []
        for field in msg.set:
            name = f"{self.name}.{field}"
            if self.node.has_parameter(name):
                params.append(Parameter(name, value=getattr(msg, field)))
        if params:
            self.node.set_parameters_atomically(params)


class ReferenceNode(LifecycleNode):
    def __init__(self, channels: int) -> None:
        super().__init__("pwm_actuator")
        self.channels = [Channel(self, n) for n in range(1, channels + 1)]
        self.create_service(Trigger, "~/reset_estop", self.on_reset_estop)

    def on_reset_estop(self, request: Trigger.Request, response: Trigger.Response):
        response.success = False
        response.message = "the e-stop is not latched"
        return response


def main() -> int:
    channels = int(sys.argv[1]) if len(sys.argv) > 1 else 2
    # rclpy's own handlers turn SIGINT and SIGTERM into a shutdown that ends spin().
    rclpy.init()
    node = ReferenceNode(channels)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    print("reference node ready", file=sys.stderr, flush=True)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
