"""The rclpy reference of scripts/idle-cost.py: a node that publishes what pwm_actuator publishes
in the idle-cost configuration (2 channels of 1 s at 37 % and 50 %), at the same rates, and
does nothing else.

- per channel a std_msgs/Bool publisher `~/pwNN/edge`, twice a second (the two edges of a 1 s
  period): 4 messages a second in all;
- `/diagnostics`, a diagnostic_msgs/DiagnosticArray with two statuses (one per channel, four
  key-values each), once a second;
- per channel a subscription to `~/pwNN/duty` (std_msgs/Float64), which nobody publishes.

One SingleThreadedExecutor, as a small rclpy node is usually written.

Usage: python idle_reference.py  (runs until SIGINT / SIGTERM)
"""

from __future__ import annotations

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import Bool, Float64

DUTIES = (37.0, 50.0)


class IdleReference(Node):
    def __init__(self) -> None:
        super().__init__("idle_reference")
        self.levels = [False] * len(DUTIES)
        self.edges = []
        for n, _ in enumerate(DUTIES, start=1):
            self.edges.append(self.create_publisher(Bool, f"~/pw{n:02d}/edge", 10))
            self.create_subscription(Float64, f"~/pw{n:02d}/duty", lambda _m: None, 10)
        self.diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        for ch in range(len(DUTIES)):
            self.create_timer(0.5, lambda ch=ch: self.edge(ch))
        self.create_timer(1.0, self.publish_diagnostics)

    def edge(self, ch: int) -> None:
        self.levels[ch] = not self.levels[ch]
        self.edges[ch].publish(Bool(data=self.levels[ch]))

    def publish_diagnostics(self) -> None:
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        for n, duty in enumerate(DUTIES, start=1):
            arr.status.append(DiagnosticStatus(
                level=DiagnosticStatus.OK,
                name=f"idle_reference: pw{n:02d}",
                message="running",
                hardware_id=f"pw{n:02d}",
                values=[
                    KeyValue(key="duty_commanded", value=f"{duty:.1f}"),
                    KeyValue(key="level", value=str(self.levels[n - 1]).lower()),
                    KeyValue(key="period_ms", value="1000"),
                    KeyValue(key="enabled", value="true"),
                ],
            ))
        self.diagnostics.publish(arr)


def main() -> int:
    rclpy.init()
    node = IdleReference()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
