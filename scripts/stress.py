#!/usr/bin/env python3
"""Bounded, repeatable fuzz and load run against the release node, from outside, over ROS.

Started by scripts/stress.sh (which builds what it needs); run it with the venv's python after
`source scripts/env.sh`. It starts pwm_actuator_node on a ROS domain of its own (the lock files
of the test suites, so it never shares one), LOCALHOST discovery, sim output traced to CSV, and:

1. malformed CDR on every input topic (raw serialized bytes published with the topic's real
   type: empty, header only, truncated, wrong encapsulation, huge length prefixes, random);
2. semantic extremes on parameters (NaN, +-inf, 1e308, 5e-324, -0.0, int64 limits, negative,
   128 KiB and control-character strings, wrong types) through the standard set_parameters service;
3. a command flood (duty, SV, split command, enable toggles) while a separate, slow subscriber
   (sleeping in its callback) listens to edges, status and diagnostics.

It prints the inputs sent, crashes (the node must stay up and exit 0 on SIGINT), RSS at start and
end (from /proc/PID/status), CPU, edges, early edges and phases below the configured minimum, the
last two from the sim trace (written times). It exits 1 if any of crashes, early edges, phases
below minimum or overlapping split lines is not 0.

Fixed seed (--seed), fixed counts and a fixed flood duration (--flood-seconds) make it repeatable.
"""

from __future__ import annotations

import argparse
import atexit
import csv
import json
import os
import random
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from pwm_actuator_msgs.msg import ChannelParams, ChannelStatus, OutputEdge
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from proclib import cpu_seconds, proc_status, take_domain
from std_msgs.msg import Bool, Float64, UInt16

REPO = Path(__file__).resolve().parents[1]
NODE = "/pwm_actuator"
# pw01: the flood target, never disabled (a falling enable may cut a pulse at once, by design).
# pw02: the parameter-extremes and enable-toggle target (its minima change: not checked).
# pw03/pw04: a split pair driven by ~/split/z/command.
MINIMA_MS = {"pw01": (20, 20), "pw03": (30, 30), "pw04": (30, 30)}
NODE_ARGS = [
    "--channels", "4",
    "--ros-args",
    "-p", "pw01.period_ms:=100", "-p", "pw01.min_on_ms:=20", "-p", "pw01.min_off_ms:=20",
    "-p", "pw01.enable:=true", "-p", "pw01.duty:=50.0",
    "-p", "pw02.period_ms:=50", "-p", "pw02.enable:=true",
    "-p", "pw03.period_ms:=200", "-p", "pw03.min_on_ms:=30", "-p", "pw03.enable:=true",
    "-p", "pw04.period_ms:=200", "-p", "pw04.min_on_ms:=30", "-p", "pw04.enable:=true",
    "-p", "split:=z:pw03:pw04",
]

SLOW_SUBSCRIBER = r"""
import sys, time, rclpy
from rclpy.node import Node
from diagnostic_msgs.msg import DiagnosticArray
from pwm_actuator_msgs.msg import ChannelStatus, OutputEdge
rclpy.init()
n = Node("stress_slow_subscriber")
got = [0]
def slow(_m):
    got[0] += 1
    time.sleep(0.2)
for ch in ("pw01", "pw03"):
    n.create_subscription(OutputEdge, f"/pwm_actuator/{ch}/edges", slow, 10)
    n.create_subscription(ChannelStatus, f"/pwm_actuator/{ch}/status", slow, 10)
n.create_subscription(DiagnosticArray, "/diagnostics", slow, 10)
end = time.monotonic() + float(sys.argv[1])
while time.monotonic() < end:
    rclpy.spin_once(n, timeout_sec=0.1)
print(got[0], flush=True)
"""


# ---------------------------------------------------------------------------------------------
# Malformed CDR
# ---------------------------------------------------------------------------------------------

CDR_LE = b"\x00\x01\x00\x00"


def malformed(rng: random.Random, kind: str) -> list[bytes]:
    """Payloads that do not decode as the topic's type, or decode to nonsense."""
    p = [
        b"",
        CDR_LE,
        CDR_LE + b"\x01",
        CDR_LE + b"\x01\x02\x03",
        b"\x00\x07\x00\x00" + bytes(8),  # an unknown encapsulation
        b"\xff\xff\xff\xff" + bytes(8),
        b"\x00\x00\x00\x00" + bytes(3),  # big-endian CDR, truncated
        CDR_LE + struct.pack("<I", 0xFFFFFFF0),  # a huge string/sequence length
        CDR_LE + struct.pack("<I", 0x7FFFFFFF) + b"A" * 16,
    ]
    if kind == "params":
        # set = [huge count], then garbage; and a valid count naming a field with a huge length.
        p.append(CDR_LE + struct.pack("<I", 0x10000000) + b"x" * 64)
        p.append(CDR_LE + struct.pack("<II", 1, 0xFFFFFF00) + b"period_ms\x00")
    for _ in range(8):
        p.append(CDR_LE + rng.randbytes(rng.randint(0, 64)))
    p.append(rng.randbytes(rng.randint(1, 4096)))
    return p


# ---------------------------------------------------------------------------------------------
# Parameter extremes
# ---------------------------------------------------------------------------------------------

# Under the node's 256 KiB input bound, so that it is decoded and refused, not dropped unseen.
HUGE = "A" * (128 << 10)
NASTY = "pw02\n[ERROR] [0.0] [pwm_actuator]: forged\x1b[2J\u202e"


def extremes() -> list[ParameterValue]:
    d = lambda v: ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=v)  # noqa: E731
    i = lambda v: ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=v)  # noqa: E731
    s = lambda v: ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=v)  # noqa: E731
    return [
        d(float("nan")), d(float("inf")), d(float("-inf")), d(1e308), d(-1e308), d(5e-324),
        d(-0.0), d(-1.0), d(1e-20),
        i(2**63 - 1), i(-(2**63)), i(-1), i(10**15),
        s(HUGE), s(NASTY), s(""),
        ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=True),
        ParameterValue(type=ParameterType.PARAMETER_BYTE_ARRAY, byte_array_value=[b"\x00"] * 4096),
    ]


PARAM_NAMES = [
    "status_rate_hz", "edge_log_rate", "rt_priority", "channels", "output", "trace", "split",
    *[
        f"pw02.{p}"
        for p in (
            "period_ms", "min_on_ms", "min_off_ms", "edge_band", "command_timeout_ms", "duty",
            "gpio_line", "output_kind", "profile", "short_pulse", "apply_at", "on_disable",
            "gpio_chip", "active_low", "enable",
        )
    ],
    "pw02." + "x" * 4096,
    NASTY,
]


# ---------------------------------------------------------------------------------------------
# Trace checks
# ---------------------------------------------------------------------------------------------


def check_trace(path: Path, since_ns: int, until_ns: int) -> dict[str, int]:
    """Edges, early edges, split overlaps over the whole run; phases below the minimum for the
    phases that start at or after `since_ns` and end before `until_ns` (CLOCK_MONOTONIC, as the
    trace). Before `since_ns`, fuzz bytes that decode as a valid `Bool false` disable channels,
    and a falling enable switches off at once by design (a safety off); from `until_ns` on, the
    node is stopping and drives every line off at once, also by design."""
    rows: dict[str, list[tuple[int, int, int]]] = {}
    with path.open() as f:
        for r in csv.DictReader(f):
            rows.setdefault(r["channel"], []).append(
                (int(r["t_ns"]), int(r["level"]), int(r["scheduled_ns"]))
            )
    edges = early = short = 0
    worst_short_ms = None
    for ch, rs in rows.items():
        rs.sort()
        changes = rs[1:]  # the first row is the initial level
        edges += len(changes)
        early += sum(1 for t, _, sched in changes if t < sched)
        if ch in MINIMA_MS:
            min_on, min_off = MINIMA_MS[ch]
            for (t0, lvl, _), (t1, _, _) in zip(rs[1:], rs[2:]):
                if t0 < since_ns or t1 >= until_ns:
                    continue
                need = (min_on if lvl else min_off) * 1_000_000
                if t1 - t0 < need:
                    short += 1
                    ms = (t1 - t0) / 1e6
                    worst_short_ms = ms if worst_short_ms is None else min(worst_short_ms, ms)
    # Split pair: never high together (each line's level over time).
    overlap = 0
    if "pw03" in rows and "pw04" in rows:
        ev = sorted([(t, "pw03", l) for t, l, _ in rows["pw03"]] + [(t, "pw04", l) for t, l, _ in rows["pw04"]])
        lvl = {"pw03": 0, "pw04": 0}
        for i, (t, ch, l) in enumerate(ev):
            lvl[ch] = l
            nxt = ev[i + 1][0] if i + 1 < len(ev) else None
            if lvl["pw03"] and lvl["pw04"] and nxt != t:
                overlap += 1
    return {
        "edges": edges,
        "early_edges": early,
        "phases_below_minimum": short,
        "shortest_violating_phase_ms": worst_short_ms,
        "split_overlaps": overlap,
    }


# ---------------------------------------------------------------------------------------------


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--node", default=str(REPO / "target" / "release" / "pwm_actuator_node"))
    ap.add_argument("--seed", type=int, default=9)
    ap.add_argument("--malformed-rounds", type=int, default=100, help="rounds per input topic")
    ap.add_argument("--flood-seconds", type=float, default=20.0)
    ap.add_argument("--json", action="store_true", help="also print the figures as JSON")
    a = ap.parse_args()
    rng = random.Random(a.seed)

    domain, lock = take_domain("stress")
    env = dict(os.environ)
    env.update(
        ROS_DOMAIN_ID=str(domain),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        RMW_IMPLEMENTATION="rmw_fastrtps_cpp",
    )
    os.environ.update(env)
    work = Path(tempfile.mkdtemp(prefix="pwm_stress_"))
    trace = work / "trace.csv"
    log = (work / "node.log").open("w")
    node = subprocess.Popen(
        [a.node, "--trace", str(trace), *NODE_ARGS], env=env, stdout=log, stderr=subprocess.STDOUT
    )
    # Never leave the node running on a domain whose lock this process releases when it exits.
    atexit.register(lambda: node.poll() is None and node.kill())
    print(f"stress: node pid {node.pid}, domain {domain}, work dir {work}", flush=True)
    crashes = 0

    def alive() -> bool:
        return node.poll() is None

    end = time.monotonic() + 20
    while "running:" not in (work / "node.log").read_text():
        if not alive() or time.monotonic() > end:
            print((work / "node.log").read_text())
            sys.exit("stress: the node did not start")
        time.sleep(0.05)

    rclpy.init()
    n = Node("stress_driver")
    time.sleep(2.0)
    rss_start = proc_status(node.pid, ("VmRSS", "VmHWM"))["VmRSS"]
    cpu0, t0 = cpu_seconds(node.pid), time.monotonic()
    sent = {"malformed": 0, "parameters": 0, "flood": 0}
    refused_by_rmw = 0
    rss_phase: dict[str, int] = {}

    # 1. Malformed CDR on every input topic.
    types = {"duty": Float64, "sv": UInt16, "enable": Bool, "params": ChannelParams}
    pubs = []
    by_topic = {}
    for ch in ("pw01", "pw02", "pw03", "pw04"):
        for name, ty in types.items():
            by_topic[(ch, name)] = n.create_publisher(ty, f"{NODE}/{ch}/{name}", 10)
            pubs.append((name, by_topic[(ch, name)]))
    pubs.append(("command", n.create_publisher(Float64, f"{NODE}/split/z/command", 10)))
    deadline = time.monotonic() + 20
    while any(p.get_subscription_count() == 0 for _, p in pubs) and time.monotonic() < deadline:
        rclpy.spin_once(n, timeout_sec=0.05)
    for r in range(a.malformed_rounds):
        for kind, p in pubs:
            for payload in malformed(rng, kind):
                try:
                    p.publish(payload)
                    sent["malformed"] += 1
                except Exception:  # rmw refuses some payloads (e.g. empty) before the wire
                    refused_by_rmw += 1
        rclpy.spin_once(n, timeout_sec=0)
    crashes += 0 if alive() else 1
    rss_phase["after_malformed"] = proc_status(node.pid, ("VmRSS", "VmHWM"))["VmRSS"] if alive() else -1

    # 2. Parameter extremes.
    cli = n.create_client(SetParameters, f"{NODE}/set_parameters")
    cli.wait_for_service(timeout_sec=20)
    unanswered = 0
    for name in PARAM_NAMES:
        for v in extremes():
            fut = cli.call_async(SetParameters.Request(parameters=[Parameter(name=name, value=v)]))
            rclpy.spin_until_future_complete(n, fut, timeout_sec=5)
            sent["parameters"] += 1
            if not fut.done():
                unanswered += 1
                cli.remove_pending_request(fut)
        if not alive():
            break
    # Back to sane rates for the flood.
    for name, v in (("status_rate_hz", 10.0), ("edge_log_rate", 10)):
        pv = (
            ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=v)
            if isinstance(v, float)
            else ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=v)
        )
        fut = cli.call_async(SetParameters.Request(parameters=[Parameter(name=name, value=pv)]))
        rclpy.spin_until_future_complete(n, fut, timeout_sec=5)
    crashes += 0 if alive() else 1

    # 3. Command flood with a slow subscriber.
    slow = subprocess.Popen(
        [sys.executable, "-c", SLOW_SUBSCRIBER, str(a.flood_seconds + 5)],
        env=env, stdout=subprocess.PIPE, text=True,
    )
    # Undo what fuzz bytes decoded as valid commands did (enable false on pw01, say).
    # (With the publishers matched during phase 1: a new one's first messages could be lost.)
    reenable = [by_topic[(ch, "enable")] for ch in ("pw01", "pw03", "pw04")]
    for _ in range(10):
        for p in reenable:
            p.publish(Bool(data=True))
        rclpy.spin_once(n, timeout_sec=0.1)
    rss_phase["after_parameters"] = proc_status(node.pid, ("VmRSS", "VmHWM"))["VmRSS"]
    time.sleep(2)
    flood_start_ns = time.monotonic_ns()
    duty = {ch: by_topic[(ch, "duty")] for ch in ("pw01", "pw02")}
    sv = by_topic[("pw01", "sv")]
    en2 = by_topic[("pw02", "enable")]
    split = pubs[-1][1]
    flood_end = time.monotonic() + a.flood_seconds
    extremes_f = [float("nan"), float("inf"), -float("inf"), 1e308, -1e308, -0.0, 100.0, 0.0]
    i = 0
    while time.monotonic() < flood_end and alive():
        i += 1
        v = rng.choice(extremes_f) if i % 7 == 0 else rng.uniform(-20, 120)
        duty["pw01"].publish(Float64(data=v))
        duty["pw02"].publish(Float64(data=rng.uniform(0, 100)))
        sv.publish(UInt16(data=rng.randint(0, 65535)))
        split.publish(Float64(data=rng.choice(extremes_f) if i % 11 == 0 else rng.uniform(-150, 150)))
        en2.publish(Bool(data=bool(i % 2)))
        sent["flood"] += 5
        if i % 50 == 0:
            rclpy.spin_once(n, timeout_sec=0)
    slow_got = slow.communicate(timeout=60)[0].strip()
    crashes += 0 if alive() else 1
    rss_phase["after_flood"] = proc_status(node.pid, ("VmRSS", "VmHWM"))["VmRSS"] if alive() else -1

    # Idle, then the end figures.
    time.sleep(3)
    cpu1, t1 = cpu_seconds(node.pid), time.monotonic()
    st = proc_status(node.pid, ("VmRSS", "VmHWM")) if alive() else {"VmRSS": -1, "VmHWM": -1}
    stop_ns = time.monotonic_ns()
    node.send_signal(signal.SIGINT)
    try:
        code = node.wait(timeout=20)
    except subprocess.TimeoutExpired:
        node.kill()
        code = node.wait()
    if code != 0:
        crashes += 1
    n.destroy_node()
    rclpy.shutdown()
    os.close(lock)

    tr = check_trace(trace, flood_start_ns, stop_ns)
    figures = {
        "inputs_sent": sent,
        "inputs_total": sum(sent.values()),
        "malformed_refused_by_sender_rmw": refused_by_rmw,
        "parameter_calls_unanswered": unanswered,
        "slow_subscriber_received": int(slow_got or 0),
        "crashes": crashes,
        "exit_code": code,
        "rss_start_kib": rss_start,
        "rss_end_kib": st["VmRSS"],
        "rss_peak_kib": st.get("VmHWM"),
        "rss_by_phase_kib": rss_phase,
        "cpu_percent_of_one_core": round(100 * (cpu1 - cpu0) / (t1 - t0), 1),
        "seconds": round(t1 - t0, 1),
        **tr,
        "log_lines": sum(1 for _ in (work / "node.log").open()),
        # Another node with this name on the domain would share the flood: the run is void.
        "other_nodes_with_the_same_name": (work / "node.log").read_text().count("nodes with the name"),
    }
    for k, v in figures.items():
        print(f"{k}: {v}")
    if a.json:
        print(json.dumps(figures))
    bad = (
        crashes
        or tr["early_edges"]
        or tr["phases_below_minimum"]
        or tr["split_overlaps"]
        or figures["other_nodes_with_the_same_name"]
    )
    print("stress: FAIL" if bad else "stress: ok")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
