"""Careless and hostile inputs, as any participant on the ROS domain can send them (issue 9):
parameter values the node cannot use, and strings made to forge or flood its log.

Each test talks to the node only over ROS (and reads its stderr, as an operator would).
"""

from __future__ import annotations

from typing import Sequence

from conftest import ManagedProcess, RosClient
from pwm_actuator_msgs.msg import ChannelParams, ChannelStatus
from rcl_interfaces.msg import Log
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

NODE = "/pwm_actuator"


def start_node(node_process, ros_args: Sequence[str] = ()) -> ManagedProcess:
    """Starts the node with `--ros-args *ros_args` and waits until it is running."""
    proc = node_process(["--ros-args", *ros_args] if ros_args else [])
    proc.wait_for_output("running:")
    return proc


def set_rate(ros: RosClient, value: float):
    return ros.set_parameters(NODE, {"status_rate_hz": value})["status_rate_hz"]


# ---------------------------------------------------------------------------------------------
# status_rate_hz
# ---------------------------------------------------------------------------------------------


def test_a_status_rate_the_node_cannot_keep_is_refused_and_a_new_rate_applies_at_once(
    ros, node_process
):
    status = ros.subscribe(ChannelStatus, f"{NODE}/pw01/status")
    proc = start_node(node_process, ["-p", "status_rate_hz:=0.01"])
    status.wait_for_publishers()

    # 1/1e-20 s is no Duration: it used to be accepted and then panic the node (exit 101).
    for bad in (1e-20, 5e-324, 0.001):
        result = set_rate(ros, bad)
        assert not result.successful, bad
        assert "0.01..1000" in result.reason, result.reason
    assert ros.get_parameters(NODE, ["status_rate_hz"]) == {"status_rate_hz": 0.01}
    ros.spin_for(0.5)
    assert proc.is_running(), proc.output()

    # 0.01 Hz sleeps 100 s; the change to 10 Hz must not wait for that sleep to end.
    ros.spin_for(1.0)
    assert set_rate(ros, 10.0).successful
    start = len(status.messages)
    ros.spin_for(1.5)
    got = len(status.messages) - start
    assert got >= 8, f"{got} status messages in the 1.5 s after switching to 10 Hz"
    assert proc.is_running(), proc.output()


def test_a_start_up_status_rate_the_node_cannot_keep_is_a_configuration_error(node_process):
    for i, argv in enumerate(
        (["--status-rate", "5e-324"], ["--ros-args", "-p", "status_rate_hz:=1e-20"])
    ):
        proc = node_process(argv, name=f"bad-rate-{i}")
        code = proc.wait_exit()
        assert code == 2, f"{argv}: exit {code}\n{proc.output()}"
        assert "status_rate_hz" in proc.stderr() and "0.01..1000" in proc.stderr(), proc.output()
        assert "panicked" not in proc.stderr(), proc.output()


# ---------------------------------------------------------------------------------------------
# What the node says about input: escaped, bounded, rate-limited
# ---------------------------------------------------------------------------------------------

#: A parameter name made to forge a log line and clear the terminal.
FORGED = "x\n[ERROR] [0] [pwm_actuator]: forged\x1b[2J"
REFUSED = "parameter change refused"


def matched_publisher(ros: RosClient, msg_type, topic: str):
    publisher = ros.publisher(msg_type, topic)
    ros.wait_for_subscribers(publisher)
    ros.spin_for(0.25)
    return publisher


def test_refusals_do_not_forge_or_flood_the_log(ros, node_process):
    rosout = ros.subscribe(
        Log,
        "/rosout",
        QoSProfile(
            depth=1000,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.VOLATILE,
        ),
    )
    proc = start_node(node_process)

    # A forged name through the parameter services: refused, and echoed escaped.
    result = ros.set_parameters(NODE, {FORGED: 1})[FORGED]
    assert not result.successful
    assert "x\\n[ERROR] [0] [pwm_actuator]: forged\\u{1b}[2J" in result.reason, result.reason
    assert "\n" not in result.reason and "\x1b" not in result.reason, repr(result.reason)

    # The same with 1 MiB more through the parameter topic: echoed as 64 characters and a size.
    pub = matched_publisher(ros, ChannelParams, f"{NODE}/pw01/params")
    huge = FORGED + "A" * (1 << 20)
    ros.publish_until(
        pub,
        ChannelParams(set=[huge]),
        lambda: "bytes)` in `set` is not a ChannelParams field" in proc.stderr(),
        "the bounded refusal of the huge field name in the log",
    )
    stderr = proc.stderr()
    assert "\x1b" not in stderr, "raw ESC in the node's stderr"
    assert not any(l.startswith("[ERROR] [0]") for l in stderr.splitlines()), "a forged line"
    assert len(stderr.encode()) < 64 * 1024, f"{len(stderr.encode())} bytes of log"

    # A flood of refusals: a few lines, then one count of the rest.
    bad = ChannelParams(set=["nope"])
    for _ in range(60):
        pub.publish(bad)
        ros.spin_for(0.02)
    ros.spin_until(
        lambda: "similar messages suppressed" in proc.stderr(),
        "the count of suppressed refusals",
        timeout=30,
    )
    lines = [l for l in proc.stderr().splitlines() if REFUSED in l]
    # One from the services, ten from the topic, and the count (which quotes the last one).
    assert len(lines) <= 12, f"{len(lines)} refusal lines:\n" + "\n".join(lines[:40])

    # /rosout carries the same bounded, escaped text, and the count.
    def ours() -> list[str]:
        return [m.msg for m in rosout.messages if m.name == "pwm_actuator"]

    ros.spin_until(
        lambda: any("similar messages suppressed" in m for m in ours()), "the count on /rosout"
    )
    refusals = [m for m in ours() if REFUSED in m]
    assert refusals, ours()[:20]
    for text in refusals:
        assert "\n" not in text and "\x1b" not in text, repr(text[:200])
        assert len(text.encode()) < 4096, len(text.encode())
