#!/usr/bin/env python3
"""What a trace costs the node: the same run without a trace, with a CSV trace and with an MCAP
trace, one after the other, each for SECONDS after a warm-up; prints for each the node's CPU in %
of one core, its RSS at the end, and how fast the trace file grew (docs/safety.md#mcap-traces).

The run: the sim output, 4 channels at a 10 ms period and 37 %, status on change only (about 900
edges and 950 status messages a second), LOCALHOST discovery, on a ROS domain of its own (taken as the test suite takes them).
Nothing subscribes: what is measured is what the node spends publishing and writing.

Usage: scripts/trace-cost.sh [--seconds S] [--warmup S]   (the .sh builds the release binary)
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from proclib import cpu_seconds, proc_status, take_domain

REPO = Path(__file__).resolve().parents[1]
CHANNELS = 4


def run(node: str, trace: Path | None, seconds: float, warmup: float, domain: int) -> dict:
    argv = [node, "--channels", str(CHANNELS), "--status-rate", "0"]
    if trace is not None:
        argv += ["--trace", str(trace)]
    argv += ["--ros-args", "--log-level", "warn"]
    for k in range(CHANNELS):
        ch = f"pw{k + 1:02d}"
        argv += ["-p", f"{ch}.period_ms:=10", "-p", f"{ch}.duty:=37.0", "-p", f"{ch}.enable:=true"]
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(warmup)
        if proc.poll() is not None:
            sys.exit(f"trace-cost: the node exited ({proc.returncode}): {' '.join(argv)}")
        c0, t0 = cpu_seconds(proc.pid), time.monotonic()
        s0 = trace.stat().st_size if trace is not None and trace.exists() else 0
        time.sleep(seconds)
        c1, t1 = cpu_seconds(proc.pid), time.monotonic()
        s1 = trace.stat().st_size if trace is not None and trace.exists() else 0
        rss = proc_status(proc.pid, ("VmRSS",))["VmRSS"] / 1024
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=10)
    return {
        "cpu_pct": 100.0 * (c1 - c0) / (t1 - t0),
        "rss_mib": rss,
        "kb_per_s": (s1 - s0) / 1000 / (t1 - t0),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--warmup", type=float, default=5.0)
    ap.add_argument("--node", default=str(REPO / "target/release/pwm_actuator_node"))
    a = ap.parse_args()
    domain, _lock = take_domain("trace-cost")
    rev = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                         capture_output=True, text=True).stdout.strip()
    print(f"trace-cost: {time.strftime('%Y-%m-%d')}, commit {rev}, {os.cpu_count()} CPUs, "
          f"{CHANNELS} channels x 10 ms at 37 %, status on change, {a.seconds:.0f} s each")
    print(f"{'trace':<8} {'CPU % of a core':>16} {'RSS MiB':>9} {'file kB/s':>10}")
    with tempfile.TemporaryDirectory() as d:
        for label, trace in (("none", None), ("csv", Path(d) / "run.csv"),
                             ("mcap", Path(d) / "run.mcap")):
            r = run(a.node, trace, a.seconds, a.warmup, domain)
            size = "-" if trace is None else f"{r['kb_per_s']:.0f}"
            print(f"{label:<8} {r['cpu_pct']:>16.2f} {r['rss_mib']:>9.1f} {size:>10}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
