#!/usr/bin/env python3
"""What an always-on node costs while nothing much happens: pwm_actuator_node and an rclpy node
doing the same publishing, side by side in one run.

Run it with the venv's python after `source scripts/env.sh` (scripts/idle-cost.sh does both, and
builds the release binary first). Both processes start at once, each on a ROS domain of its own
(the lock files of the test suites) with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, nobody
subscribing to either:

- **pwm_actuator**: `--channels 2`, both channels `period_ms` 1000, `duty` 37 and 50 %,
  enabled, every other parameter at its default, simulated output: 4 edges a second (each an
  `~/pwNN/edges` message), the status messages at the default `status_rate_hz`, `/diagnostics`
  once a second;
- **rclpy reference** (scripts/idle_reference.py): 4 std_msgs/Bool a second, a DiagnosticArray
  with two statuses once a second, two subscriptions, one SingleThreadedExecutor.

After a warm-up (start-up and discovery are not idle) it reads, at the start and at the end of
the measured window, for each thread of each process /proc/PID/task/TID/schedstat (time on a
CPU, ns) and .../status (voluntary context switches, i.e. the times the thread went to sleep and
was woken), and at the end VmRSS. It prints per process the CPU in % of one core (the sum over
its threads; --json also gives `cpu_pct_ticks`, the same from /proc/PID/stat, in 10 ms ticks,
which counts threads that ended too) and RSS, and per thread its name, CPU % and wake-ups per
second (threads that neither ran nor woke in the window are counted, not listed).

Exit status: 0; 1 with --check when the node's CPU is above --max-node-cpu-pct or not below the
reference's; 2 when a process does not start or dies.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from proclib import take_domain

REPO = Path(__file__).resolve().parents[1]
TICK = os.sysconf("SC_CLK_TCK")
#: The node's configuration: per channel (period ms, duty %).
CHANNELS = ((1000, 37.0), (1000, 50.0))


def node_argv(node: str, params: list[str]) -> list[str]:
    argv = [node, "--channels", str(len(CHANNELS)), "--ros-args"]
    for n, (period, duty) in enumerate(CHANNELS, start=1):
        ch = f"pw{n:02d}"
        argv += ["-p", f"{ch}.period_ms:={period}", "-p", f"{ch}.duty:={duty}",
                 "-p", f"{ch}.enable:=true"]
    for p in params:
        argv += ["-p", p]
    return argv


def stat_cpu_ticks(path: Path) -> int:
    """utime + stime of a /proc .../stat file, clock ticks."""
    fields = path.read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


def threads(pid: int) -> dict[int, tuple[str, int, int]]:
    """Per thread id: its name, CPU time so far (ns, from schedstat: the tick counts of stat
    are 10 ms coarse, as long as a whole minute at 0.01 %), voluntary context switches so
    far."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            name = (task / "comm").read_text().strip()
            ticks = int((task / "schedstat").read_text().split()[0])
            switches = 0
            for line in (task / "status").read_text().splitlines():
                if line.startswith("voluntary_ctxt_switches:"):
                    switches = int(line.split()[1])
            out[int(task.name)] = (name, ticks, switches)
        except (FileNotFoundError, ProcessLookupError):
            continue  # the thread ended while read
    return out


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


class Sample:
    def __init__(self, pid: int) -> None:
        self.t = time.monotonic()
        self.threads = threads(pid)
        # Threads that end between two samples count in the process's own (coarse) figure.
        self.cpu_ticks = stat_cpu_ticks(Path(f"/proc/{pid}/stat"))


def figures(pid: int, a: Sample, b: Sample) -> dict:
    span = b.t - a.t
    rows = []
    quiet = 0
    total_ns = 0
    for tid, (name, ticks, switches) in b.threads.items():
        _, ticks0, switches0 = a.threads.get(tid, (name, 0, 0))
        total_ns += ticks - ticks0
        cpu = 100.0 * (ticks - ticks0) / 1e9 / span
        wakes = (switches - switches0) / span
        if ticks == ticks0 and switches == switches0:
            quiet += 1
            continue
        rows.append({"tid": tid, "name": name, "cpu_pct": round(cpu, 4),
                     "wakeups_per_s": round(wakes, 2)})
    rows.sort(key=lambda r: (-r["wakeups_per_s"], -r["cpu_pct"]))
    return {
        "cpu_pct": round(100.0 * total_ns / 1e9 / span, 4),
        "cpu_pct_ticks": round(100.0 * (b.cpu_ticks - a.cpu_ticks) / TICK / span, 3),
        "wakeups_per_s": round(sum(r["wakeups_per_s"] for r in rows), 2),
        "rss_kib": rss_kib(pid),
        "threads": len(b.threads),
        "quiet_threads": quiet,
        "busy_threads": rows,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--node", default=str(REPO / "target/release/pwm_actuator_node"))
    ap.add_argument("--seconds", type=float, default=75.0, help="measured window, s (75)")
    ap.add_argument("--warmup", type=float, default=15.0,
                    help="time from the start to the window, s (15)")
    ap.add_argument("--json", action="store_true", help="print one JSON object instead")
    ap.add_argument("--check", action="store_true",
                    help="exit 1 unless the node's CPU is at most --max-node-cpu-pct and below "
                    "the reference's")
    ap.add_argument("--max-node-cpu-pct", type=float, default=0.1)
    ap.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                    help="one more parameter for the node (e.g. status_rate_hz:=1.0); repeatable")
    a = ap.parse_args()

    d_node, _lock1 = take_domain("idle-cost")
    d_ref, _lock2 = take_domain("idle-cost")
    work = Path(tempfile.mkdtemp(prefix="pwm_idle_"))
    base = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                RMW_IMPLEMENTATION="rmw_fastrtps_cpp", ROS_LOG_DIR=str(work / "ros_log"))
    base.pop("RUST_LOG", None)
    procs = {}
    for label, argv, domain in (
        ("pwm_actuator", node_argv(a.node, a.param), d_node),
        ("rclpy reference", [sys.executable, str(REPO / "scripts/idle_reference.py")], d_ref),
    ):
        log = (work / f"{label.split()[0]}.log").open("w")
        procs[label] = subprocess.Popen(argv, env=dict(base, ROS_DOMAIN_ID=str(domain)),
                                        stdout=log, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL)
    atexit.register(lambda: [p.kill() for p in procs.values() if p.poll() is None])
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    if not a.json:
        print(f"idle-cost: warm-up {a.warmup:g} s, window {a.seconds:g} s, logs in {work}",
              flush=True)
        print(f"idle-cost: {' '.join(node_argv(a.node, a.param))}", flush=True)

    def alive() -> bool:
        for label, p in procs.items():
            if p.poll() is not None:
                print(f"idle-cost: {label} exited with {p.returncode}; see {work}",
                      file=sys.stderr)
                return False
        return True

    time.sleep(a.warmup)
    if not alive():
        return 2
    first = {label: Sample(p.pid) for label, p in procs.items()}
    time.sleep(a.seconds)
    if not alive():
        return 2
    last = {label: Sample(p.pid) for label, p in procs.items()}
    result = {
        "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.release()}",
        "loadavg": os.getloadavg(),
        "seconds": round(last["pwm_actuator"].t - first["pwm_actuator"].t, 1),
    }
    for label, p in procs.items():
        result[label] = figures(p.pid, first[label], last[label])
    for p in procs.values():
        p.send_signal(signal.SIGINT)
    for p in procs.values():
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()

    ours, ref = result["pwm_actuator"]["cpu_pct"], result["rclpy reference"]["cpu_pct"]
    if a.json:
        print(json.dumps(result))
    else:
        print(f"\n{result['date_utc']} UTC, {result['machine']}, load average "
              f"{' '.join(f'{x:.2f}' for x in result['loadavg'])}, window {result['seconds']} s")
        print(f"\n{'process':<16} {'CPU % of a core':>15} {'wake-ups/s':>10} {'RSS MiB':>8}"
              f" {'threads':>8}")
        for label in procs:
            r = result[label]
            print(f"{label:<16} {r['cpu_pct']:>15.4f} {r['wakeups_per_s']:>10.2f}"
                  f" {r['rss_kib'] / 1024:>8.1f} {r['threads']:>8}")
        for label in procs:
            r = result[label]
            print(f"\n{label}: threads that ran or woke ({r['quiet_threads']} more did neither)")
            print(f"  {'thread':<18} {'CPU %':>7} {'wake-ups/s':>10}")
            for t in r["busy_threads"]:
                print(f"  {t['name']:<18} {t['cpu_pct']:>7.4f} {t['wakeups_per_s']:>10.2f}")
    if a.check and not (ours <= a.max_node_cpu_pct and ours < ref):
        print(f"idle-cost: node CPU {ours:.3f} % (limit {a.max_node_cpu_pct} %, reference "
              f"{ref:.3f} %)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
