#!/usr/bin/env python3
"""End-to-end latency of a duty command, as an rclpy controller sees it.

Starts the node (sim output, pw01 under `apply_at: immediate`, so a command changes the line at
once), enables pw01 and publishes duty 100 % and 0 % in turn from one rclpy publisher that stays,
as a controller does. For each command it records, on the wall clock of this machine:

- publish -> line written: the edge's `stamp` (when the output thread's write returned) minus
  the time just before `publish()`;
- publish -> edge received: when the edge message reached this rclpy subscriber, minus the same.

and prints p50, p90, p99 and max of both, in ms. Run it with the venv's rclpy:

    source scripts/env.sh
    python3 scripts/e2e.py --node target/release/pwm_actuator_node --trials 200

`--node` may be given more than once: the binaries are measured one after the other in the same
run, so their figures compare on the same machine load. Each run uses its own ROS_DOMAIN_ID.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy
from pwm_actuator_msgs.msg import OutputEdge
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import Bool, Float64

#: The largest number of trials one run takes.
MAX_TRIALS = 10_000
#: What a trial waits for its edge, s.
EDGE_TIMEOUT_S = 5.0


def percentile(values: list[float], q: float) -> float:
    """The q-th percentile (0..100) by the nearest-rank method."""
    ordered = sorted(values)
    rank = max(1, min(len(ordered), round(q / 100 * len(ordered) + 0.5)))
    return ordered[rank - 1]


def measure(node_bin: Path, trials: int, gap_s: float, domain: int) -> dict[str, list[float]]:
    """Runs `trials` commands against a fresh node from `node_bin`; the delays in ms."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    log = tempfile.TemporaryFile()
    proc = subprocess.Popen(
        [
            str(node_bin),
            "--output",
            "sim",
            "--ros-args",
            "-p",
            "pw01.apply_at:=immediate",
            "-p",
            "pw01.period_ms:=1000",
        ],
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("e2e_probe", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    edges: list[tuple[OutputEdge, int]] = []
    node.create_subscription(
        OutputEdge, "/pwm_actuator/pw01/edges", lambda m: edges.append((m, time.time_ns())), 100
    )
    duty = node.create_publisher(Float64, "/pwm_actuator/pw01/duty", 10)
    enable = node.create_publisher(Bool, "/pwm_actuator/pw01/enable", 10)
    out: dict[str, list[float]] = {"written": [], "received": []}
    try:
        deadline = time.monotonic() + 30
        while duty.get_subscription_count() == 0 or enable.get_subscription_count() == 0:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError(f"{node_bin}: the node's inputs were not discovered")
            executor.spin_once(timeout_sec=0.05)
        duty.publish(Float64(data=0.0))
        enable.publish(Bool(data=True))
        end = time.monotonic() + 2
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        level = False
        for _ in range(trials):
            level = not level
            edges.clear()
            t_pub = time.time_ns()
            duty.publish(Float64(data=100.0 if level else 0.0))
            end = time.monotonic() + EDGE_TIMEOUT_S
            hit = None
            while hit is None and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.01)
                hit = next(((m, t) for m, t in edges if m.level == level), None)
            if hit is None:
                raise RuntimeError(f"{node_bin}: no edge within {EDGE_TIMEOUT_S} s of a command")
            msg, t_recv = hit
            stamp_ns = msg.stamp.sec * 1_000_000_000 + msg.stamp.nanosec
            out["written"].append((stamp_ns - t_pub) / 1e6)
            out["received"].append((t_recv - t_pub) / 1e6)
            end = time.monotonic() + gap_s
            while time.monotonic() < end:
                executor.spin_once(timeout_sec=0.005)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--node", action="append", type=Path, required=True, help="node binary")
    ap.add_argument("--trials", type=int, default=200, help="commands per binary (default 200)")
    ap.add_argument("--gap-ms", type=float, default=50.0, help="pause between commands, ms")
    ap.add_argument("--domain", type=int, default=77, help="first ROS_DOMAIN_ID to use")
    a = ap.parse_args()
    if not 1 <= a.trials <= MAX_TRIALS:
        ap.error(f"--trials must be within 1..{MAX_TRIALS}")
    if not 0 <= a.gap_ms <= 10_000:
        ap.error("--gap-ms must be within 0..10000")
    if not 0 <= a.domain <= 232 - len(a.node):
        ap.error("--domain must leave room for one domain per binary within 0..232")
    print(f"e2e: {a.trials} commands per binary, {a.gap_ms:g} ms apart; delays in ms")
    print(f"{'binary':<48} {'delay':<24} {'p50':>7} {'p90':>7} {'p99':>7} {'max':>7}")
    for i, node_bin in enumerate(a.node):
        figures = measure(node_bin, a.trials, a.gap_ms / 1000, a.domain + i)
        for what, label in (("written", "publish -> line written"), ("received", "publish -> edge received")):
            v = figures[what]
            print(
                f"{str(node_bin)[-48:]:<48} {label:<24} {statistics.median(v):7.3f} "
                f"{percentile(v, 90):7.3f} {percentile(v, 99):7.3f} {max(v):7.3f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
