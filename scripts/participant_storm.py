#!/usr/bin/env python3
"""A storm of short-lived participants: does the node give back what it kept for them?

Run it with the venv's python after `source scripts/env.sh`. It starts the release node on a
ROS domain of its own (the lock files of the test suites), LOCALHOST discovery, sim output, and
then PARTICIPANTS rclpy processes, CONCURRENCY at a time. Each is a new process (a child of a
fork server that has imported rclpy but never initialised it), so a new DDS participant with a
new GUID prefix; it creates a plain rclpy node (parameter services, /rosout, as `ros2 param get`
has), waits for the node's `get_parameters` service, calls it once and checks the answer, then
leaves: cleanly (its participant announces that it leaves) or, for every KILL_EVERY-th one, by
SIGKILL, so that the node only learns of it when its lease expires.

The lease a participant announces is Fast DDS's default, 20 s, unless --lease-s is given: then
a Fast DDS XML profile (FASTRTPS_DEFAULT_PROFILES_FILE, the default participant profile) makes
every participant of the storm announce that lease, with its announcements every third of it.
The node honours whatever lease a participant announces, so a shorter one only shortens the
wait for the killed ones.

After the last participant has left it waits for their leases to expire (the lease, the node's
2 s check and a margin) and samples the node's memory for a few seconds ("after the leases");
then it waits one more lease, the time the node keeps a lost participant's endpoints in case it
comes back (the attic, vendor/rustdds/README.pwm_actuator.md), and samples again ("end"). It
prints the node's resident memory (VmRSS, and its anonymous part RssAnon: heap and stacks) at
the start (after start-up, before any participant), its peak (VmHWM), after the leases and at
the end (each the median of its samples), its threads and open file descriptors at the start,
their peak and at the end, and the participants' results. It exits 1 if a participant got no
right answer, or the RSS after the leases or at the end is more than --max-growth-mb above the
start, or the node's threads or descriptors did not come back to their start, and 2 when the
node does not start.

Usage: participant_storm.py [--participants N] [--concurrency C] [--kill-every K]
                            [--lease-s S] [--max-growth-mb M] [--wrap CMD] [--json]
"""

from __future__ import annotations

import argparse
import atexit
import json
import multiprocessing
import os
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from multiprocessing.connection import wait as wait_connections
from pathlib import Path
from typing import Any, Optional

import rclpy
from proclib import proc_status, take_domain
from rcl_interfaces.srv import GetParameters
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

REPO = Path(__file__).resolve().parents[1]
NODE = "/pwm_actuator"
#: The parameter each participant asks for, and the value the node was started with.
PARAMETER = ("pw01.period_ms", 1234)
#: What a participant waits for the service, and then for the answer, s.
DISCOVERY_TIMEOUT_S = 60.0
ANSWER_TIMEOUT_S = 20.0
#: How often the node's memory is sampled, s.
SAMPLE_S = 0.5
#: What the node's own lease check adds to a lease: its period (rustdds checks every 2 s) and a
#: margin for a loaded machine, s.
LEASE_CHECK_MARGIN_S = 4.0
#: How long the end figures are sampled after the leases have expired, s.
END_WINDOW_S = 4.0

PROFILE = """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <participant profile_name="participant_storm" is_default_profile="true">
    <rtps>
      <builtin>
        <discovery_config>
          <leaseDuration><sec>{lease_s}</sec><nanosec>{lease_ns}</nanosec></leaseDuration>
          <leaseAnnouncement><sec>{ann_s}</sec><nanosec>{ann_ns}</nanosec></leaseAnnouncement>
        </discovery_config>
      </builtin>
    </rtps>
  </participant>
</profiles>
"""


def lease_profile(lease_s: float) -> str:
    """The XML profile that makes a participant announce `lease_s`, refreshed every third."""
    ann = lease_s / 3.0
    return PROFILE.format(
        lease_s=int(lease_s),
        lease_ns=int(round((lease_s % 1) * 1e9)),
        ann_s=int(ann),
        ann_ns=int(round((ann % 1) * 1e9)),
    )


def participant(conn: Any, domain_id: int, index: int, kill: bool) -> None:
    """One participant's process: discover the node, call get_parameters once, report, leave
    (SIGKILL when `kill`)."""
    report: dict[str, Any] = {"index": index, "pid": os.getpid(), "ready": False,
                              "answered": False, "value": None}
    context = Context()
    rclpy.init(context=context, domain_id=domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    node = Node(f"storm_{index}", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        client = node.create_client(GetParameters, f"{NODE}/get_parameters")
        t0 = time.monotonic()
        report["ready"] = client.wait_for_service(timeout_sec=DISCOVERY_TIMEOUT_S)
        report["wait_s"] = time.monotonic() - t0
        if report["ready"]:
            future = client.call_async(GetParameters.Request(names=[PARAMETER[0]]))
            executor.spin_until_future_complete(future, timeout_sec=ANSWER_TIMEOUT_S)
            response = future.result() if future.done() else None
            if response is not None:
                report["answered"] = True
                report["value"] = [v.integer_value for v in response.values]
        conn.send(report)
        conn.close()
        if kill:
            os.kill(os.getpid(), signal.SIGKILL)
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        context.try_shutdown()


def node_figures(pid: int) -> dict[str, int]:
    """RSS, its anonymous part and its peak (kB), threads and open file descriptors."""
    st = proc_status(pid, ("VmRSS", "RssAnon", "VmHWM", "Threads"))
    return {
        "rss_kib": st["VmRSS"],
        "anon_kib": st["RssAnon"],
        "hwm_kib": st["VmHWM"],
        "threads": st["Threads"],
        "fds": len(os.listdir(f"/proc/{pid}/fd")),
    }


def find_node_pid(root: int, exe: str, timeout_s: float = 20.0) -> int:
    """The pid of `exe` among `root` and its descendants (it is `root` unless a wrapper such
    as a heap profiler started it)."""
    want = os.path.realpath(exe)
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        todo = [root]
        while todo:
            pid = todo.pop()
            try:
                if os.path.realpath(f"/proc/{pid}/exe") == want:
                    return pid
                for task in os.listdir(f"/proc/{pid}/task"):
                    kids = Path(f"/proc/{pid}/task/{task}/children").read_text().split()
                    todo.extend(int(k) for k in kids)
            except (FileNotFoundError, ProcessLookupError, PermissionError):
                continue
        time.sleep(0.05)
    raise RuntimeError(f"no process running {exe} under pid {root}")


class Sampler:
    """The node's figures every SAMPLE_S, kept with their time since the start."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.samples: list[tuple[float, dict[str, int]]] = []
        self.t0 = time.monotonic()
        self._next = self.t0

    def poll(self) -> None:
        now = time.monotonic()
        if now >= self._next:
            self.samples.append((now - self.t0, node_figures(self.pid)))
            self._next = now + SAMPLE_S


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--node", default=str(REPO / "target" / "release" / "pwm_actuator_node"))
    ap.add_argument("--participants", type=int, default=1000, help="per round (default 1000)")
    ap.add_argument("--rounds", type=int, default=1,
                    help="storms one after the other, each followed by its leases (default 1)")
    ap.add_argument("--concurrency", type=int, default=8,
                    help="participants alive at once (default 8)")
    ap.add_argument("--kill-every", type=int, default=10,
                    help="every K-th participant leaves by SIGKILL (default 10; 0: none)")
    ap.add_argument("--lease-s", type=float, default=None,
                    help="the lease every participant announces, s (default: Fast DDS's, 20)")
    ap.add_argument("--max-growth-mb", type=float, default=5.0,
                    help="fail if the end RSS is more than this above the start, MB (1e6 bytes)")
    ap.add_argument("--settle-s", type=float, default=3.0,
                    help="the node runs this long after start-up before the start figures")
    ap.add_argument("--work-dir", default=None)
    ap.add_argument("--wrap", default="", help="a command line put before the node's, e.g. "
                    "'heaptrack -o /tmp/node' (the node is found among its descendants)")
    ap.add_argument("--json", action="store_true", help="also print the figures as JSON")
    a = ap.parse_args()

    domain, lock = take_domain("participant_storm")
    work = Path(a.work_dir) if a.work_dir else Path(tempfile.mkdtemp(prefix="pwm_storm_"))
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               RMW_IMPLEMENTATION="rmw_fastrtps_cpp")
    if "ROS_LOG_DIR" not in env and "ROS_HOME" not in env:
        env["ROS_LOG_DIR"] = str(work / "ros_log")
    lease_s = 20.0 if a.lease_s is None else a.lease_s
    if a.lease_s is not None:
        profile = work / "lease.xml"
        profile.write_text(lease_profile(a.lease_s))
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile)
    # The participants inherit this environment through the fork server.
    os.environ.update(env)

    log_path = work / "node.log"
    argv = [*shlex.split(a.wrap), a.node, "--output", "sim", "--ros-args",
            "-p", f"{PARAMETER[0]}:={PARAMETER[1]}"]
    with log_path.open("w") as log:
        proc = subprocess.Popen(argv, env=env, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)
    atexit.register(lambda: proc.poll() is None and proc.kill())
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    print(f"storm: {a.participants} participants, {a.concurrency} at a time, every "
          f"{a.kill_every or 'no'}-th killed, lease {lease_s:g} s, domain {domain}, "
          f"work dir {work}", flush=True)
    print(f"storm: {shlex.join(argv)}", flush=True)
    end = time.monotonic() + 30
    while "running:" not in log_path.read_text():
        if proc.poll() is not None or time.monotonic() > end:
            print(log_path.read_text())
            print("storm: the node did not start", flush=True)
            return 2
        time.sleep(0.05)
    pid = find_node_pid(proc.pid, a.node)
    time.sleep(a.settle_s)
    start = node_figures(pid)
    sampler = Sampler(pid)

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["rclpy", "rcl_interfaces.srv", "rclpy.executors"])
    reports: list[dict[str, Any]] = []
    no_report: list[int] = []

    def storm(first: int) -> float:
        """Runs participants `first` .. `first + a.participants - 1`; returns how long it took."""
        live: dict[Any, tuple[Any, int]] = {}  # connection -> (process, index)
        started = 0
        t_storm = time.monotonic()
        next_print = t_storm + 10.0
        while started < a.participants or live:
            while started < a.participants and len(live) < a.concurrency:
                index = first + started
                kill = a.kill_every > 0 and (index + 1) % a.kill_every == 0
                parent, child = ctx.Pipe(duplex=False)
                p = ctx.Process(target=participant, args=(child, domain, index, kill),
                                daemon=True)
                p.start()
                child.close()
                live[parent] = (p, index)
                started += 1
            for conn in wait_connections(list(live), timeout=SAMPLE_S):
                p, index = live.pop(conn)
                try:
                    reports.append(conn.recv())
                except EOFError:
                    no_report.append(index)
                conn.close()
                p.join(15.0)
                if p.is_alive():
                    p.kill()
                    p.join()
            sampler.poll()
            if proc.poll() is not None:
                raise RuntimeError("the node exited during the storm")
            if time.monotonic() >= next_print:
                print(f"storm: {time.monotonic() - t_storm:5.0f} s  {len(reports)} answered of "
                      f"{first + started} started  RSS {sampler.samples[-1][1]['rss_kib']} kB",
                      flush=True)
                next_print += 10.0
        return time.monotonic() - t_storm

    def settled(wait_s: float) -> dict[str, int]:
        """Waits `wait_s`, then the median of the node's figures over END_WINDOW_S."""
        until = time.monotonic() + wait_s
        while time.monotonic() < until:
            sampler.poll()
            time.sleep(0.1)
        window_start = time.monotonic() - sampler.t0
        while time.monotonic() - sampler.t0 < window_start + END_WINDOW_S:
            sampler.poll()
            time.sleep(0.1)
        window = [f for t, f in sampler.samples if t >= window_start]
        return {k: int(statistics.median(f[k] for f in window)) for k in window[0]}

    rounds: list[dict[str, Any]] = []
    for r in range(a.rounds):
        try:
            storm_s = storm(r * a.participants)
        except RuntimeError as e:
            print(log_path.read_text()[-4000:])
            print(f"storm: FAIL: {e}", flush=True)
            return 1
        after_storm = node_figures(pid)
        # The killed ones are dropped when their lease has expired, on the node's next check;
        # the node keeps their endpoints one more lease in case they come back.
        after_leases = settled(lease_s + LEASE_CHECK_MARGIN_S)
        end = settled(lease_s)
        rounds.append({"storm_s": round(storm_s, 1), "after_storm": after_storm,
                       "after_leases": after_leases, "end": end})
        print(f"storm: round {r + 1}: {storm_s:.0f} s, RSS {after_storm['rss_kib']} kB after "
              f"it, {after_leases['rss_kib']} kB after the leases, {end['rss_kib']} kB at the "
              f"end (start {start['rss_kib']} kB)", flush=True)
    end = rounds[-1]["end"]
    end_rss = end["rss_kib"]

    peak_kib = node_figures(pid)["hwm_kib"]
    os.kill(pid, signal.SIGTERM)
    try:
        code = proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        code = None
    os.close(lock)

    answered = [r for r in reports if r["answered"] and r["value"] == [PARAMETER[1]]]
    wrong = [r for r in reports if r["answered"] and r["value"] != [PARAMETER[1]]]
    waits = sorted(r["wait_s"] for r in reports if r["ready"])
    figures = {
        "participants": a.participants * a.rounds,
        "killed": sum(1 for i in range(a.participants * a.rounds)
                      if a.kill_every > 0 and (i + 1) % a.kill_every == 0),
        "answered": len(answered),
        "wrong_answers": len(wrong),
        "not_discovered": sum(1 for r in reports if not r["ready"]),
        "unanswered": sum(1 for r in reports if r["ready"] and not r["answered"]),
        "no_report": len(no_report),
        "discovery_wait_p50_s": round(waits[len(waits) // 2], 3) if waits else None,
        "discovery_wait_max_s": round(waits[-1], 3) if waits else None,
        "rounds": a.rounds,
        "storm_s": [x["storm_s"] for x in rounds],
        "lease_s": lease_s,
        "rss_start_kib": start["rss_kib"],
        "rss_peak_kib": peak_kib,
        "rss_after_storm_kib": [x["after_storm"]["rss_kib"] for x in rounds],
        "rss_after_leases_kib": [x["after_leases"]["rss_kib"] for x in rounds],
        "rss_end_kib": [x["end"]["rss_kib"] for x in rounds],
        "rss_growth_kib": end_rss - start["rss_kib"],
        "rss_anon_start_kib": start["anon_kib"],
        "rss_anon_after_leases_end_kib": [[x["after_leases"]["anon_kib"], x["end"]["anon_kib"]]
                                          for x in rounds],
        "threads_start_peak_end": [start["threads"],
                                   max(f["threads"] for _, f in sampler.samples),
                                   end["threads"]],
        "fds_start_peak_end": [start["fds"], max(f["fds"] for _, f in sampler.samples),
                               end["fds"]],
        "exit_code": code,
        "work_dir": str(work),
    }
    for k, v in figures.items():
        print(f"{k}: {v}")
    if a.json:
        print(json.dumps(figures))
    failures = []
    if len(answered) != a.participants * a.rounds:
        failures.append(f"{a.participants * a.rounds - len(answered)} participants got no right "
                        "answer")
    for r, x in enumerate(rounds):
        for when, rss in (("after the leases", x["after_leases"]["rss_kib"]),
                          ("at the end", x["end"]["rss_kib"])):
            if rss - start["rss_kib"] > a.max_growth_mb * 1e6 / 1024:
                failures.append(f"RSS {start['rss_kib']} kB at the start, {rss} kB {when} of "
                                f"round {r + 1}: more than {a.max_growth_mb:g} MB above")
    if end["threads"] != start["threads"]:
        failures.append(f"threads {start['threads']} at the start, {end['threads']} at the end")
    if end["fds"] != start["fds"]:
        failures.append(f"file descriptors {start['fds']} at the start, {end['fds']} at the end")
    if code != 0:
        failures.append(f"exit code {code} after SIGTERM")
    for f in failures:
        print(f"storm: FAIL: {f}")
    print("storm: FAIL" if failures else "storm: ok", flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
