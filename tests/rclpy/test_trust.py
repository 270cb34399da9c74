"""The discovery range as an outsider on the same machine sees it: with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST (the suite's default, set for rclpy and the node alike)
every UDP socket of the node is bound to the loopback device, and an rclpy (Fast DDS) client
with the same setting still discovers and commands it.

Interop of DDS security with rclpy cannot be tested here: the Fast DDS in the registry's rclpy
wheels is built without its security plugins (see docs/security.md).
"""

from __future__ import annotations

import shutil
import subprocess

import pytest
from pwm_actuator_msgs.msg import OutputEdge
from std_msgs.msg import Bool, Float64

# Times nothing (pytest.ini, `untimed`): which addresses the node's sockets are bound to, and that
# rclpy's commands arrive.
pytestmark = pytest.mark.untimed

NODE = "/pwm_actuator"


def udp_sockets(pid: int) -> list[str]:
    """Local addresses of the UDP sockets of process `pid`, as `ss` shows them."""
    out = subprocess.run(["ss", "-H", "-uanp"], capture_output=True, text=True, check=True).stdout
    return [
        line.split()[3] for line in out.splitlines() if f"pid={pid}," in line and len(line.split()) > 3
    ]


@pytest.mark.skipif(shutil.which("ss") is None, reason="needs `ss` (iproute2) to list sockets")
def test_localhost_range_binds_the_node_to_loopback_and_rclpy_still_commands_it(
    ros, node_process, ros_env
):
    assert ros_env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST", "the suite's default changed"
    proc = node_process(["--ros-args", "-p", "pw01.period_ms:=100"])
    proc.wait_for_output("running:")
    socks = udp_sockets(proc.pid)
    assert len(socks) >= 4, socks
    reachable = [s for s in socks if "%lo:" not in s and not s.startswith("127.")]
    assert not reachable, f"sockets reachable from other interfaces: {reachable}"
    assert "discovery range LOCALHOST" in proc.stderr()

    edges = ros.subscribe(OutputEdge, f"{NODE}/pw01/edges")
    duty = ros.publisher(Float64, f"{NODE}/pw01/duty")
    enable = ros.publisher(Bool, f"{NODE}/pw01/enable")
    ros.wait_for_subscribers(duty)
    ros.wait_for_subscribers(enable)

    def rose() -> bool:
        duty.publish(Float64(data=50.0))
        return any(e.level for e in edges.messages)

    ros.publish_until(enable, Bool(data=True), rose, "a rising edge from the node on loopback")
