"""The MCAP trace (`--trace run.mcap`, docs/output.md "Traces"), read back by an independent
reader, the Python `mcap` library with `mcap-ros2-support`, and compared with the CSV trace of
the same run:

- after SIGTERM the file is complete (summary, footer, end magic); every message decodes with the
  schema the file carries, which is the installed packages' `.msg` files joined as rosbag2 joins
  them; each channel's edges are the CSV's, edge for edge (level, order, `seq` from 1, and the
  write and scheduled times, on the wall clock in the MCAP and the monotonic clock in the CSV, a
  constant offset apart); status changes and /diagnostics are there;
- after SIGKILL, a reader that reads up to the damage still gets every edge the node had
  published more than a flush period (1 s) before the kill.
"""

from __future__ import annotations

import csv as csv_module
import os
import signal
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

from ament_index_python.packages import get_package_share_directory
from mcap.reader import NonSeekingReader, make_reader
from mcap_ros2.decoder import DecoderFactory
from pwm_actuator_msgs.msg import ChannelStatus, OutputEdge
from std_msgs.msg import Float64

from helpers_rules import stamp_ns

NODE = "/pwm_actuator"
CHANNELS = ("pw01", "pw02")
MCAP_MAGIC = b"\x89MCAP0\r\n"
SEPARATOR = "=" * 80
#: The writer closes a chunk at least this often while messages come (FLUSH_PERIOD).
FLUSH_PERIOD_S = 1.0
#: Fast enough for many edges in a few seconds: 100 ms periods on both channels.
ARGS = [
    "--ros-args",
    "-p", "pw01.period_ms:=100", "-p", "pw01.enable:=true",
    "-p", "pw02.period_ms:=100", "-p", "pw02.enable:=true",
    "-p", "status_rate_hz:=0.0",
]  # fmt: skip


def ros2msg_definition(package: str, name: str, uses: dict[str, list[str]]) -> str:
    """The `ros2msg` schema text rosbag2 writes for `package/name`, built from the installed
    packages' `.msg` files: the type's file, then each type it uses, depth first, each once,
    in name order, after a separator line and `MSG: pkg/Type`."""

    def text(full: str) -> str:
        pkg, typ = full.split("/")
        return (Path(get_package_share_directory(pkg)) / "msg" / f"{typ}.msg").read_text()

    root = f"{package}/{name}"
    out = text(root)
    seen: set[str] = set()

    def walk(full: str) -> None:
        nonlocal out
        for dep in sorted(uses.get(full, [])):
            if dep in seen:
                continue
            seen.add(dep)
            out += f"\n{SEPARATOR}\nMSG: {dep}\n" + text(dep)
            walk(dep)

    walk(root)
    return out


def definition_lines(text: str) -> list[str]:
    """A definition's fields, constants and separators, without comments and blank lines."""
    lines = (line.split("#", 1)[0].strip() for line in text.splitlines())
    return [line for line in lines if line]


USES = {
    "pwm_actuator_msgs/OutputEdge": ["builtin_interfaces/Time"],
    "pwm_actuator_msgs/ChannelStatus": ["builtin_interfaces/Time"],
    "diagnostic_msgs/DiagnosticArray": ["diagnostic_msgs/DiagnosticStatus", "std_msgs/Header"],
    "diagnostic_msgs/DiagnosticStatus": ["diagnostic_msgs/KeyValue"],
    "std_msgs/Header": ["builtin_interfaces/Time"],
}


def _rows(path: Path) -> list[dict[str, str]]:
    """The CSV trace's rows keyed by its header."""
    return list(csv_module.DictReader(path.read_text().splitlines()))


def csv_edges(rows: list[dict[str, str]]) -> dict[str, list[tuple[int, int, int]]]:
    """Per channel, the CSV's edges as (level, t_ns, scheduled_ns), without the start rows."""
    start = rows[0]["t_ns"]
    edges: dict[str, list[tuple[int, int, int]]] = defaultdict(list)
    for r in rows:
        if r["t_ns"] == start and r["level"] == "0" and r["scheduled_ns"] == start:
            continue
        edges[r["channel"]].append((int(r["level"]), int(r["t_ns"]), int(r["scheduled_ns"])))
    return edges


def mcap_messages(path: Path) -> list[Any]:
    """Every message of a complete file, decoded: (topic, schema, message record, ROS msg)."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [
            (channel.topic, schema, message, ros_msg)
            for schema, channel, message, ros_msg in reader.iter_decoded_messages(
                log_time_order=False
            )
        ]


def recover_messages(path: Path) -> tuple[list[Any], str]:
    """Reads a damaged file from the start up to the first record that cannot be read, as a
    recovering reader does: the messages decoded so far and why reading stopped."""
    got: list[Any] = []
    why = "end of file"
    with open(path, "rb") as f:
        reader = NonSeekingReader(f, decoder_factories=[DecoderFactory()])
        try:
            for schema, channel, message, ros_msg in reader.iter_decoded_messages(
                log_time_order=False
            ):
                got.append((channel.topic, schema, message, ros_msg))
        except Exception as exc:  # the damage: a truncated record or chunk
            why = f"{type(exc).__name__}: {exc}"
    return got, why


def edges_by_channel(messages: list[Any]) -> dict[str, list[tuple[Any, Any]]]:
    out: dict[str, list[tuple[Any, Any]]] = defaultdict(list)
    for topic, _schema, message, msg in messages:
        for ch in CHANNELS:
            if topic == f"{NODE}/{ch}/edges":
                out[ch].append((message, msg))
    return out


def compare_edges(
    mcap_edges: list[tuple[Any, Any]], csv: list[tuple[int, int, int]], channel: int
) -> None:
    """The MCAP's edges of one channel against the CSV's first len(mcap_edges) edges."""
    assert len(mcap_edges) <= len(csv)
    sched_offsets = []
    write_offsets = []
    for k, ((record, msg), (level, t_ns, sched_ns)) in enumerate(zip(mcap_edges, csv)):
        assert msg.seq == k + 1, f"edge {k}: seq {msg.seq}"
        assert record.sequence == k + 1
        assert msg.channel == channel
        assert int(msg.level) == level, f"edge {k} (seq {msg.seq}): level differs"
        stamp = stamp_ns(msg.stamp)
        assert record.log_time == stamp and record.publish_time == stamp
        # The MCAP says when (wall clock) and how late; the CSV when it was scheduled and
        # written (monotonic): scheduled = stamp - lateness is the CSV's, a clock offset away.
        sched_offsets.append(stamp - msg.lateness_ns - sched_ns)
        write_offsets.append(stamp - t_ns)
    # Wall minus monotonic, read beside each write: the same to well within 2 ms over the run.
    assert max(sched_offsets) - min(sched_offsets) < 2_000_000, (
        min(sched_offsets),
        max(sched_offsets),
    )
    assert max(write_offsets) - min(write_offsets) < 2_000_000


def drive(ros, duty_pubs, edges_seen) -> None:
    """Duty 30 %, then 70 % on pw01, 50 % on pw02."""
    for duties in ((30.0, 50.0), (70.0, 50.0)):
        for pub, d in zip(duty_pubs, duties):
            pub.publish(Float64(data=d))
        before = [len(e.messages) for e in edges_seen]
        ros.spin_until(
            lambda: all(len(e.messages) >= b + 8 for e, b in zip(edges_seen, before)),
            f"edges at {duties}",
        )


def test_mcap_after_sigterm_matches_the_csv_edge_for_edge(ros, node_process, tmp_path):
    csv_path, mcap_path = tmp_path / "x.csv", tmp_path / "x.mcap"
    edges_seen = [ros.subscribe(OutputEdge, f"{NODE}/{ch}/edges", 1000) for ch in CHANNELS]
    status = ros.subscribe(ChannelStatus, f"{NODE}/pw01/status", 100)
    duty_pubs = [ros.publisher(Float64, f"{NODE}/{ch}/duty") for ch in CHANNELS]
    node = node_process(
        ["--trace", str(csv_path), "--trace", str(mcap_path), *ARGS], trace=False
    )
    node.wait_for_output("running:")
    ros.wait_for_subscribers(duty_pubs[0], 1)
    ros.wait_for_subscribers(duty_pubs[1], 1)
    ros.publish_until(
        duty_pubs[0], Float64(data=30.0), lambda: len(edges_seen[0].messages) >= 2, "edges"
    )
    drive(ros, duty_pubs, edges_seen)
    seen = len(status.messages)
    for pub in duty_pubs:
        pub.publish(Float64(data=0.0))
    ros.spin_until(
        lambda: any(
            m.duty_commanded == 0.0 and not m.output for m in status.messages[seen:]
        ),
        "pw01 at 0 % and off",
    )
    # Running again, stopped mid-period: the edges of the stop's hold are traced too.
    before = [len(e.messages) for e in edges_seen]
    for pub in duty_pubs:
        pub.publish(Float64(data=60.0))
    ros.spin_until(
        lambda: all(len(e.messages) >= b + 6 for e, b in zip(edges_seen, before)),
        "edges at 60 %",
    )
    assert node.terminate() == 0, node.output()

    data = mcap_path.read_bytes()
    assert data.startswith(MCAP_MAGIC) and data.endswith(MCAP_MAGIC), "incomplete file"
    with open(mcap_path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
    assert header.profile == "ros2"
    assert summary is not None and summary.statistics is not None

    # Schemas: rosbag2's ros2msg text of each type, from the installed .msg files.
    topics = {c.topic: c for c in summary.channels.values()}
    expected_types = {f"{NODE}/{ch}/{kind}": t for ch in CHANNELS for kind, t in
                      (("edges", "pwm_actuator_msgs/OutputEdge"),
                       ("status", "pwm_actuator_msgs/ChannelStatus"))}  # fmt: skip
    expected_types["/diagnostics"] = "diagnostic_msgs/DiagnosticArray"
    assert set(topics) == set(expected_types)
    for topic, full in expected_types.items():
        channel = topics[topic]
        schema = summary.schemas[channel.schema_id]
        pkg, name = full.split("/")
        assert channel.message_encoding == "cdr"
        assert schema.name == f"{pkg}/msg/{name}" and schema.encoding == "ros2msg"
        expected = ros2msg_definition(pkg, name, USES)
        if os.environ.get("ROS_DISTRO", "jazzy") == "jazzy":
            assert schema.data.decode() == expected, topic
        else:
            # The node carries Jazzy's definitions; another distribution's files may differ in
            # their comments only.
            assert definition_lines(schema.data.decode()) == definition_lines(expected), topic

    messages = mcap_messages(mcap_path)
    assert len(messages) == summary.statistics.message_count
    csv = csv_edges(_rows(csv_path))
    mcap_edges = edges_by_channel(messages)
    for i, ch in enumerate(CHANNELS):
        assert len(mcap_edges[ch]) == len(csv[ch]), (ch, len(mcap_edges[ch]), len(csv[ch]))
        assert len(csv[ch]) >= 16, f"{ch}: only {len(csv[ch])} edges"
        compare_edges(mcap_edges[ch], csv[ch], i + 1)
        assert mcap_edges[ch][-1][1].level is False, f"{ch}: the trace does not end off"

    statuses = [m for t, _s, _r, m in messages if t == f"{NODE}/pw01/status"]
    duties = {round(s.duty_commanded, 6) for s in statuses}
    assert {30.0, 70.0, 0.0, 60.0} <= duties, duties
    diagnostics = [m for t, _s, _r, m in messages if t == "/diagnostics"]
    assert diagnostics, "no /diagnostics in the trace"
    names = {s.name for a in diagnostics for s in a.status}
    assert {"pwm_actuator: pw01", "pwm_actuator: pw02"} <= names, names
    # Nothing was lost on the way to the writer, as the node's own status says.
    node_kv = {kv.key: kv.value for s in diagnostics[-1].status if s.name == "pwm_actuator: node"
               for kv in s.values}  # fmt: skip
    assert node_kv.get("trace_messages_dropped") == "0", node_kv
    size = len(data)
    print(
        f"MCAP: {size} bytes, {len(messages)} messages "
        f"({sum(len(v) for v in mcap_edges.values())} edges, {len(statuses)} pw01 statuses, "
        f"{len(diagnostics)} diagnostics)"
    )


def test_mcap_after_sigkill_keeps_what_was_flushed(ros, node_process, tmp_path):
    csv_path, mcap_path = tmp_path / "k.csv", tmp_path / "k.mcap"
    edges_seen = ros.subscribe(OutputEdge, f"{NODE}/pw01/edges", 1000)
    duty = ros.publisher(Float64, f"{NODE}/pw01/duty")
    node = node_process(
        ["--trace", str(csv_path), "--trace", str(mcap_path), *ARGS], trace=False
    )
    node.wait_for_output("running:")
    ros.wait_for_subscribers(duty, 1)
    ros.publish_until(
        duty, Float64(data=40.0), lambda: len(edges_seen.messages) >= 20, "20 edges"
    )
    published = max(m.seq for m in edges_seen.messages)
    # Longer than a flush period (and a margin): those edges are in a closed chunk on disk.
    deadline = time.monotonic() + 2.5 * FLUSH_PERIOD_S
    while time.monotonic() < deadline:
        ros.spin_once(0.05)
    node.send_signal(signal.SIGKILL)
    assert node.wait_exit() == -signal.SIGKILL

    data = mcap_path.read_bytes()
    assert data.startswith(MCAP_MAGIC)
    messages, why = recover_messages(mcap_path)
    edges = edges_by_channel(messages)["pw01"]
    seqs = [m.seq for _r, m in edges]
    assert seqs == list(range(1, len(seqs) + 1)), "recovered edges are not contiguous from 1"
    assert len(seqs) >= published, (
        f"recovered {len(seqs)} pw01 edges, {published} were published "
        f"{2.5 * FLUSH_PERIOD_S} s before the kill (reading stopped at: {why})"
    )
    compare_edges(edges, csv_edges(_rows(csv_path))["pw01"], 1)
    print(f"recovered {len(messages)} messages, {len(seqs)} pw01 edges; stopped at: {why}")
