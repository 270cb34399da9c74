"""Careless and hostile inputs, as any participant on the ROS domain can send them:
parameter values the node cannot use, and strings made to forge or flood its log.

Each test talks to the node only over ROS (and reads its stderr, as an operator would).
"""

from __future__ import annotations

from typing import Sequence

import pytest
from conftest import ManagedProcess, RosClient
from diagnostic_msgs.msg import DiagnosticArray
from pwm_actuator_msgs.msg import ChannelParams, ChannelStatus
from rcl_interfaces.msg import Log
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool

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


@pytest.mark.untimed
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


# Untimed (pytest.ini): what the log holds, and a flood of 1.2 s counted within the limiter's
# 10 s window, waited for up to 30 s.
@pytest.mark.untimed
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

    # The same with 128 KiB more through the parameter topic (the node decodes input up to
    # 256 KiB): echoed as 64 characters and a size.
    pub = matched_publisher(ros, ChannelParams, f"{NODE}/pw01/params")
    huge = FORGED + "A" * (128 << 10)
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


# ---------------------------------------------------------------------------------------------
# Memory: what the node keeps of large input
# ---------------------------------------------------------------------------------------------

#: How far above its steady state the node's RSS may stay after large input, MiB. The bound is
#: generous: the node's own growth while it runs (buffers, rate windows) is a few MiB.
RSS_SLACK_MIB = 32


def rss_mib(pid: int) -> float:
    """Resident set size of process `pid`, MiB (VmRSS in /proc/PID/status)."""
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS in /proc/{pid}/status")


def test_large_channel_params_do_not_stay_in_memory(ros, node_process):
    """Valid ChannelParams with a 16 and 32 MiB string field (12 x 16 MiB left the
    node at 556 MB): after them RSS comes back to within RSS_SLACK_MIB of its steady state, a
    small message from the same publisher is still applied, and /diagnostics counts what was
    dropped."""
    proc = start_node(node_process)
    pub = matched_publisher(ros, ChannelParams, f"{NODE}/pw01/params")
    assert ros.get_parameters(NODE, ["pw01.period_ms"]) == {"pw01.period_ms": 1000}
    ros.spin_for(1.0)
    steady = rss_mib(proc.pid)

    sizes_mib = (16, 16, 16, 16, 32, 32, 32, 32)
    for size_mib in sizes_mib:
        pub.publish(ChannelParams(set=["output_kind"], output_kind="A" * (size_mib << 20)))
        ros.spin_once(0.01)
    # Reliable and in order: this one is taken only after the node is done with those above.
    pub.publish(ChannelParams(set=["period_ms"], period_ms=1500))
    ros.spin_until(
        lambda: ros.get_parameters(NODE, ["pw01.period_ms"]) == {"pw01.period_ms": 1500},
        "the small ChannelParams after the large ones applied",
        timeout=30,
    )
    assert proc.is_running(), proc.output()

    # The node may free what it held a little later (its DDS caches clean up on a timer).
    readings = []

    def back_to_steady() -> bool:
        readings.append(rss_mib(proc.pid))
        return readings[-1] < steady + RSS_SLACK_MIB

    try:
        ros.spin_until(back_to_steady, "RSS back to its steady state", timeout=8)
    except AssertionError as exc:
        raise AssertionError(
            f"RSS {steady:.1f} MiB before the large messages, {readings[0]:.1f} MiB after, "
            f"still {readings[-1]:.1f} MiB {len(readings)} readings later"
        ) from exc

    def too_large(array: DiagnosticArray) -> bool:
        return all(
            kv.value == str(len(sizes_mib))
            for status in array.status
            for kv in status.values
            if kv.key == "samples_too_large"
        ) and any(kv.key == "samples_too_large" for s in array.status for kv in s.values)

    ros.wait_for_message(DiagnosticArray, "/diagnostics", too_large)
    assert "input samples larger than 256 KiB were dropped before decoding" in proc.stderr()


# Untimed (pytest.ini): lines counted; the flood lasts well under a second of the limiter's 10 s
# window, and its count is waited for up to 30 s.
@pytest.mark.untimed
def test_an_enable_flood_gives_a_few_log_lines_and_a_count(node_process, ros):
    """Each enable change is logged at INFO, but a participant toggling it 400 times gets a
    burst of lines and then one count of the rest, not 400 lines."""
    proc = start_node(node_process)
    pub = matched_publisher(ros, Bool, f"{NODE}/pw01/enable")
    for i in range(400):
        pub.publish(Bool(data=i % 2 == 0))
        if i % 20 == 0:
            ros.spin_for(0.01)
    ros.spin_until(
        lambda: "similar messages suppressed" in proc.stderr(),
        "the count of suppressed enable lines",
        timeout=30,
    )
    lines = [l for l in proc.stderr().splitlines() if "pw01: enabled" in l or "pw01: disabled" in l]
    assert len(lines) <= 12, f"{len(lines)} enable lines:\n" + "\n".join(lines[:40])
