"""Where edge messages are lost, and what the node counts of it: a subscriber that
stops taking messages for 2 s, as an rclpy callback that blocks would, seen over ROS.

docs/interface.md says: a gap in `seq` is edges this subscriber lost; a subscriber's own reader
keeps as many unread messages as its History depth and acknowledges each one as it arrives, so what
it overwrites is lost where no publisher can see it; the node's writer never drops an edge
silently (a full send window is a failed publish, counted in `publish_failures`).
"""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray
from pwm_actuator_msgs.msg import OutputEdge

from helpers_rules import diag_values

NODE = "/pwm_actuator"
#: 50 % of 10 ms: 200 edges a second on pw01.
FAST = ["-p", "pw01.period_ms:=10", "-p", "pw01.duty:=50.0", "-p", "pw01.enable:=true"]
STALL_S = 2.0


def gaps(seqs: list[int]) -> int:
    """Edges missing between the first and the last `seq` received."""
    s = sorted(seqs)
    return sum(b - a - 1 for a, b in zip(s, s[1:]))


def test_a_stalled_subscriber_loses_edges_in_its_own_history_not_the_nodes(ros, node_process):
    shallow = ros.subscribe(OutputEdge, f"{NODE}/pw01/edges", 10)
    deep = ros.subscribe(OutputEdge, f"{NODE}/pw01/edges", 1000)
    node_process(["--ros-args", *FAST]).wait_for_output("running:")
    shallow.wait_for_count(20)
    deep.wait_for_count(20)

    # Neither subscription is served for STALL_S: 400 edges arrive meanwhile.
    time.sleep(STALL_S)
    before = max(m.seq for m in deep.messages)
    ros.spin_until(
        lambda: max(m.seq for m in deep.messages) > before + 50,
        "edges after the stall",
    )
    shallow_seqs = [m.seq for m in shallow.messages]
    deep_seqs = [m.seq for m in deep.messages]

    # Depth 10: all but about 10 of the stall's edges are gone, and seq shows how many.
    assert gaps(shallow_seqs) >= 300, f"{gaps(shallow_seqs)} edges missing at depth 10"
    # Depth 1000, stalled as long, on the same node and writer: nothing lost.
    assert gaps(deep_seqs) == 0, f"{gaps(deep_seqs)} edges missing at depth 1000"
    assert deep_seqs == sorted(deep_seqs) and len(set(deep_seqs)) == len(deep_seqs)

    # The node handed every edge to DDS and saw no loss: what depth 10 lost was acknowledged by
    # the subscriber's reader on arrival, and no publisher can count it.
    array = ros.wait_for_message(
        DiagnosticArray,
        "/diagnostics",
        lambda a: any(s.name.endswith(": pw01") for s in a.status),
    )
    pw01 = diag_values(next(s for s in array.status if s.name.endswith(": pw01")))
    assert pw01["publish_failures"] == "0", pw01
    assert pw01["reports_dropped"] == "0", pw01
    assert int(pw01["edges"]) >= max(deep_seqs), pw01
