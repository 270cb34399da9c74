#!/usr/bin/env python3
"""Long-running load against the release node: does its memory stay flat once it is warm?

Run it with the venv's python after `source scripts/env.sh` (scripts/soak.sh does both, and
builds the release binary first). It starts pwm_actuator_node on a ROS domain of its own (the
lock files of the test suites, so it never shares one), LOCALHOST discovery, sim output traced
to CSV, with four channels:

  pw01  heater:  1 s,   transistor, pico_gfx,   min on/off 50 ms
  pw02  relay:   2 s,   relay,      tcont_cp,   min on/off 100 ms
  pw03  fast:    20 ms, transistor, twincat_ba, min on 2 ms, min off 1 ms
  pw04  valve:   500 ms, transistor, pico_gfx with on_disable hold, min on/off 20 ms,
                 watchdog (command_timeout_ms) 2 s

(`--period-ms P` gives every channel the period P instead, and scales the minima with it, a
relay's staying at least 50 ms: the heater case is 100.) An rclpy
controller in this process sends random duties at 10 Hz (pw01, pw03, pw04) and 2 Hz (pw02),
toggles pw04's enable every 5 s, changes parameters every 30 s (status_rate_hz, edge_log_rate,
pw01.max_duty_pct, pw02.duty_deadband_pct, pw03.expected_command_hz_min) and subscribes to every
channel's edges and status, and to /diagnostics.

Every 10 s it samples the node's RSS (/proc/PID/status) and CPU time (/proc/PID/stat); once a
minute it prints the figures so far. At the end it stops the node with SIGTERM and prints:

- RSS at start, at the end of the warm-up, at the end, and its slope after the warm-up
  (least-squares line through the samples, kB per minute), and the slopes of its two parts,
  RssAnon (heap, stacks) and RssFile (pages of the binary and libraries);
- CPU, % of one core;
- edges per channel from the trace, and from ROS: messages received, the highest `seq`, the
  gaps in `seq` after the first one received, and how many messages disagree with the trace
  (the n-th edge message of a channel must carry the level of the n-th edge in the trace);
- early edges (written before their scheduled time) and phases below their channel's minimum,
  from the trace, up to the SIGTERM (on every exit the node drives every line off at once, by
  design).

It exits 1 when the slope is above --max-slope-kb-per-min, or any of early edges, phases below
the minimum, missing edge messages, disagreeing messages and reports the node says on
/diagnostics it dropped (`reports_dropped`) is not 0, or the node exits other than with 0; and 2
when the node does not start.
"""

from __future__ import annotations

import argparse
import atexit
import csv
import json
import os
import random
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from pwm_actuator_msgs.msg import ChannelStatus, OutputEdge
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from proclib import cpu_seconds, proc_status, take_domain
from std_msgs.msg import Bool, Float64

REPO = Path(__file__).resolve().parents[1]
NODE = "/pwm_actuator"
CHANNELS = ("pw01", "pw02", "pw03", "pw04")
#: Per channel: period ms, minimum on ms, minimum off ms, the other parameters.
LOAD = {
    "pw01": (1000, 50, 50, {"profile": "pico_gfx"}),
    "pw02": (2000, 100, 100, {"profile": "tcont_cp", "output_kind": "relay"}),
    "pw03": (20, 2, 1, {"profile": "twincat_ba"}),
    "pw04": (500, 20, 20, {"profile": "pico_gfx", "on_disable": "hold",
                           "command_timeout_ms": 2000}),
}
#: Duty command rate per channel, Hz.
RATE_HZ = {"pw01": 10.0, "pw02": 2.0, "pw03": 10.0, "pw04": 10.0}
SAMPLE_S = 10.0
# The edge readers' history (messages) and how many waiting callbacks one turn of the loop runs.
EDGE_READER_DEPTH = 5000
SPIN_BATCH = 500
TOGGLE_S = 5.0
PARAMS_S = 30.0


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


def slope_per_minute(samples: list[tuple[float, int]]) -> float | None:
    """Least-squares slope of (seconds, kB) samples, in kB per minute."""
    if len(samples) < 2:
        return None
    n = len(samples)
    mx = sum(t for t, _ in samples) / n
    my = sum(v for _, v in samples) / n
    sxx = sum((t - mx) ** 2 for t, _ in samples)
    if sxx == 0:
        return None
    sxy = sum((t - mx) * (v - my) for t, v in samples)
    return 60.0 * sxy / sxx


def minima(period_ms: int | None) -> dict[str, tuple[int, int]]:
    """Each channel's minimum on and off times, ms. With `period_ms` they are scaled with the
    period (a 100 ms heater keeps the 5 % minimum of a 1 s one), whole ms, at least 1 ms, and a
    relay's at least its 50 ms floor."""
    out = {}
    for ch, (period, min_on, min_off, extra) in LOAD.items():
        if period_ms is not None:
            floor = 50 if extra.get("output_kind") == "relay" else 1
            min_on = max(floor, min_on * period_ms // period)
            min_off = max(floor, min_off * period_ms // period)
        out[ch] = (min_on, min_off)
    return out


def node_args(period_ms: int | None, rt_priority: int | None) -> list[str]:
    args = ["--channels", str(len(CHANNELS))]
    if rt_priority is not None:
        args += ["--rt-priority", str(rt_priority)]
    args.append("--ros-args")
    mins = minima(period_ms)
    for ch in CHANNELS:
        period, _, _, extra = LOAD[ch]
        min_on, min_off = mins[ch]
        if period_ms is not None:
            period = period_ms
        values = {
            "period_ms": period,
            "min_on_ms": min_on,
            "min_off_ms": min_off,
            "enable": "true",
            "duty": "50.0",
            **extra,
        }
        for k, v in values.items():
            args += ["-p", f"{ch}.{k}:={v}"]
    args += ["-p", "status_rate_hz:=2.0", "-p", "edge_log_rate:=1"]
    return args


def check_trace(
    path: Path, stop_ns: int, minima: dict[str, tuple[int, int]]
) -> tuple[dict[str, list[tuple[int, int, int]]], dict]:
    """The trace's edges per channel (t_ns, level, scheduled_ns; the first row of a channel is
    its initial level, not an edge), early edges, phases below the minimum before `stop_ns`."""
    rows: dict[str, list[tuple[int, int, int]]] = {}
    with path.open() as f:
        for r in csv.DictReader(f):
            rows.setdefault(r["channel"], []).append(
                (int(r["t_ns"]), int(r["level"]), int(r["scheduled_ns"]))
            )
    edges: dict[str, list[tuple[int, int, int]]] = {}
    early = short = 0
    shortest = None
    for ch, rs in rows.items():
        rs.sort()
        changes = rs[1:]
        edges[ch] = changes
        early += sum(1 for t, _, sched in changes if t < sched)
        min_on, min_off = minima[ch]
        for (t0, lvl, _), (t1, _, _) in zip(changes, changes[1:]):
            if t1 >= stop_ns:
                break
            if t1 - t0 < (min_on if lvl else min_off) * 1_000_000:
                short += 1
                ms = (t1 - t0) / 1e6
                shortest = ms if shortest is None else min(shortest, ms)
    return edges, {
        "early_edges": early,
        "phases_below_minimum": short,
        "shortest_violating_phase_ms": shortest,
    }


class Controller:
    """The rclpy side: publishers of commands, subscribers of what the node reports."""

    def __init__(self, rng: random.Random) -> None:
        self.rng = rng
        self.node = Node("soak_controller")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        n = self.node
        self.duty = {ch: n.create_publisher(Float64, f"{NODE}/{ch}/duty", 10) for ch in CHANNELS}
        self.enable = {ch: n.create_publisher(Bool, f"{NODE}/{ch}/enable", 10) for ch in CHANNELS}
        # Per channel: seq -> (level, lateness_ns) of every edge message received.
        self.edges: dict[str, dict[int, tuple[int, int]]] = {ch: {} for ch in CHANNELS}
        self.received = {"status": 0, "diagnostics": 0}
        # The highest `reports_dropped` the node reported on /diagnostics: reports its output
        # thread could not hand to the ROS side, lost before any message was published.
        self.reports_dropped = 0
        for ch in CHANNELS:
            # The node's edges writer keeps the last 100 samples (reliable); the history of
            # this reader is deeper, so that this process falling behind for a while (it shares
            # the machine with compiles in the test command) does not lose what its DDS layer
            # has already received: pw03 sends 100 edges a second.
            n.create_subscription(
                OutputEdge, f"{NODE}/{ch}/edges", lambda m, ch=ch: self._edge(ch, m),
                EDGE_READER_DEPTH,
            )
            n.create_subscription(ChannelStatus, f"{NODE}/{ch}/status", self._status, 10)
        n.create_subscription(DiagnosticArray, "/diagnostics", self._diagnostics, 10)
        self.params = n.create_client(SetParameters, f"{NODE}/set_parameters")
        self.pending: list = []
        self.sent = {"duty": 0, "enable": 0, "parameter_calls": 0}
        self.refused_params = 0
        self.unanswered_params = 0
        self.enabled_pw04 = True
        self.param_round = 0

    def _edge(self, ch: str, m: OutputEdge) -> None:
        self.edges[ch][m.seq] = (1 if m.level else 0, m.lateness_ns)

    def _status(self, _m: ChannelStatus) -> None:
        self.received["status"] += 1

    def _diagnostics(self, m: DiagnosticArray) -> None:
        self.received["diagnostics"] += 1
        for st in m.status:
            for kv in st.values:
                if kv.key == "reports_dropped" and kv.value.isdigit():
                    self.reports_dropped = max(self.reports_dropped, int(kv.value))

    def spin(self, seconds: float) -> None:
        """Waits up to `seconds` for a callback, then runs those already waiting (at most
        SPIN_BATCH): one `spin_once` takes a single callback, fewer than pw03's edges come."""
        self.executor.spin_once(timeout_sec=max(0.0, seconds))
        for _ in range(SPIN_BATCH):
            before = self.taken()
            self.executor.spin_once(timeout_sec=0.0)
            if self.taken() == before:
                break

    def taken(self) -> int:
        return sum(len(e) for e in self.edges.values()) + sum(self.received.values())

    def wait_matched(self, timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        pubs = [*self.duty.values(), *self.enable.values()]
        while time.monotonic() < end:
            if all(p.get_subscription_count() > 0 for p in pubs) and self.params.service_is_ready():
                return True
            self.spin(0.05)
        return False

    def send_duty(self, ch: str) -> None:
        self.duty[ch].publish(Float64(data=round(self.rng.uniform(0.0, 100.0), 3)))
        self.sent["duty"] += 1

    def toggle_pw04(self) -> None:
        self.enabled_pw04 = not self.enabled_pw04
        self.enable["pw04"].publish(Bool(data=self.enabled_pw04))
        self.sent["enable"] += 1

    def change_parameters(self) -> None:
        """Alternates between two sets of values, none of which changes a minimum time."""
        self._collect()
        k = self.param_round % 2
        self.param_round += 1
        d = lambda v: ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=v)  # noqa: E731
        i = lambda v: ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=v)  # noqa: E731
        values = {
            "status_rate_hz": d((2.0, 5.0)[k]),
            "edge_log_rate": i((1, 5)[k]),
            "pw01.max_duty_pct": d((100.0, 90.0)[k]),
            "pw02.duty_deadband_pct": d((0.0, 1.0)[k]),
            "pw03.expected_command_hz_min": d((0.0, 5.0)[k]),
        }
        req = SetParameters.Request(
            parameters=[Parameter(name=name, value=v) for name, v in values.items()]
        )
        self.pending.append((time.monotonic(), self.params.call_async(req)))
        self.sent["parameter_calls"] += 1

    def _collect(self, final: bool = False) -> None:
        keep = []
        for t, fut in self.pending:
            if fut.done():
                res = fut.result()
                if res is None or not all(r.successful for r in res.results):
                    self.refused_params += 1
            elif final or time.monotonic() - t > 10.0:
                self.unanswered_params += 1
                self.params.remove_pending_request(fut)
            else:
                keep.append((t, fut))
        self.pending = keep

    def close(self) -> None:
        self._collect(final=True)
        self.executor.remove_node(self.node)
        self.node.destroy_node()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--node", default=str(REPO / "target" / "release" / "pwm_actuator_node"))
    ap.add_argument("--minutes", type=float, default=60.0, help="length of the run")
    ap.add_argument(
        "--warmup-minutes", type=float, default=None,
        help="samples before this are left out of the slope (default: 5, or a third of a run "
        "shorter than 15 minutes)",
    )
    ap.add_argument("--period-ms", type=int, default=None,
                    help="every channel's period, ms, minima scaled with it "
                    "(default: 1000, 2000, 20, 500)")
    ap.add_argument("--rt-priority", type=int, default=None,
                    help="pass --rt-priority N to the node (SCHED_FIFO output thread, mlockall)")
    ap.add_argument("--max-slope-kb-per-min", type=float, default=5.0,
                    help="fail above this RSS slope after the warm-up (default 5)")
    ap.add_argument("--seed", type=int, default=26)
    ap.add_argument("--work-dir", default=None, help="where the trace, log and samples go "
                    "(default: a new directory under the system's temporary directory)")
    ap.add_argument("--wrap", default="", help="a command line put before the node's, e.g. "
                    "'heaptrack -o /tmp/node' (the node is found among its descendants)")
    ap.add_argument("--json", action="store_true", help="also print the figures as JSON")
    a = ap.parse_args()
    warmup_min = a.warmup_minutes
    if warmup_min is None:
        warmup_min = 5.0 if a.minutes >= 15 else a.minutes / 3
    rng = random.Random(a.seed)

    domain, lock = take_domain("soak")
    env = dict(os.environ)
    env.update(
        ROS_DOMAIN_ID=str(domain),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        RMW_IMPLEMENTATION="rmw_fastrtps_cpp",
    )
    os.environ.update(env)
    work = Path(a.work_dir) if a.work_dir else Path(tempfile.mkdtemp(prefix="pwm_soak_"))
    work.mkdir(parents=True, exist_ok=True)
    # rclpy's log files go with the run's unless the caller chose a place.
    if "ROS_LOG_DIR" not in os.environ and "ROS_HOME" not in os.environ:
        os.environ["ROS_LOG_DIR"] = str(work / "ros_log")
    trace = work / "trace.csv"
    log_path = work / "node.log"
    argv = [*shlex.split(a.wrap), a.node, "--trace", str(trace),
            *node_args(a.period_ms, a.rt_priority)]
    mins = minima(a.period_ms)
    with log_path.open("w") as log:
        proc = subprocess.Popen(argv, env=env, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)
    # Never leave the node running on a domain whose lock this process releases when it exits
    # (SIGTERM to this process included).
    atexit.register(lambda: proc.poll() is None and proc.kill())
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    print(f"soak: {a.minutes:g} min, warm-up {warmup_min:g} min, domain {domain}, "
          f"work dir {work}", flush=True)
    print(f"soak: {shlex.join(argv)}", flush=True)

    end = time.monotonic() + 30
    while "running:" not in log_path.read_text():
        if proc.poll() is not None or time.monotonic() > end:
            print(log_path.read_text())
            print("soak: the node did not start", flush=True)
            return 2
        time.sleep(0.05)
    pid = find_node_pid(proc.pid, a.node)

    rclpy.init()
    ctl = Controller(rng)
    if not ctl.wait_matched(30.0):
        print("soak: the node's topics and parameter service were not matched in 30 s")
        proc.kill()
        return 2

    t0 = time.monotonic()
    cpu0 = cpu_seconds(pid)
    # (s since t0, RSS kB, CPU s since t0, RssAnon kB, RssFile kB)
    samples: list[tuple[float, int, float, int, int]] = []
    sample_file = (work / "samples.csv").open("w")
    sample_file.write("t_s,rss_kib,cpu_s,rss_anon_kib,rss_file_kib\n")
    due = {ch: t0 for ch in CHANNELS}
    next_sample = t0
    next_toggle = t0 + TOGGLE_S
    next_params = t0 + PARAMS_S
    next_print = t0 + 60.0
    stop_at = t0 + 60.0 * a.minutes
    alive = True
    while True:
        now = time.monotonic()
        if proc.poll() is not None:
            alive = False
            break
        if now >= next_sample:
            try:
                st = proc_status(pid, ("VmRSS", "RssAnon", "RssFile"))
                rss, anon, file_ = st["VmRSS"], st["RssAnon"], st["RssFile"]
                s = (now - t0, rss, cpu_seconds(pid) - cpu0, anon, file_)
            except (OSError, RuntimeError):  # it exited since the poll
                alive = False
                break
            samples.append(s)
            sample_file.write(f"{s[0]:.1f},{s[1]},{s[2]:.2f},{s[3]},{s[4]}\n")
            sample_file.flush()
            next_sample += SAMPLE_S
        if now >= stop_at:
            break
        for ch in CHANNELS:
            if now >= due[ch]:
                ctl.send_duty(ch)
                due[ch] += 1.0 / RATE_HZ[ch]
                if due[ch] < now:  # this process was held up: no burst to catch up
                    due[ch] = now + 1.0 / RATE_HZ[ch]
        if now >= next_toggle:
            ctl.toggle_pw04()
            next_toggle += TOGGLE_S
        if now >= next_params:
            ctl.change_parameters()
            next_params += PARAMS_S
        if now >= next_print:
            warm = [(s[0], s[1]) for s in samples if s[0] >= 60 * warmup_min]
            sl = slope_per_minute(warm)
            print(f"soak: {(now - t0) / 60:5.1f} min  RSS {samples[-1][1]} kB  "
                  f"slope after warm-up {'-' if sl is None else f'{sl:+.2f}'} kB/min  "
                  f"CPU {100 * samples[-1][2] / max(samples[-1][0], 1e-9):.1f} %  "
                  f"edge messages {sum(len(e) for e in ctl.edges.values())}", flush=True)
            next_print += 60.0
        wake = min(*due.values(), next_sample, next_toggle, next_params, stop_at)
        ctl.spin(min(0.05, wake - time.monotonic()))
    sample_file.close()

    # Stop: SIGTERM, then the node must exit 0 by itself.
    stop_ns = time.monotonic_ns()
    t_end = time.monotonic()
    code = None
    if alive:
        os.kill(pid, signal.SIGTERM)
    try:
        code = proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        code = proc.wait()
        print("soak: the node did not exit within 30 s of SIGTERM; killed")
        code = code if code != 0 else -9
    # Messages still in flight when the node stopped.
    for _ in range(20):
        ctl.spin(0.05)
    ctl.close()
    rclpy.shutdown()
    os.close(lock)

    edges, tr = check_trace(trace, stop_ns, mins)
    with (work / "edge_messages.csv").open("w") as f:
        f.write("channel,seq,level,lateness_ns\n")
        for ch in CHANNELS:
            for seq, (level, late) in sorted(ctl.edges[ch].items()):
                f.write(f"{ch},{seq},{level},{late}\n")
    per_channel = {}
    lost = disagree = 0
    for ch in CHANNELS:
        got = ctl.edges[ch]
        top = max(got) if got else 0
        tr_edges = edges.get(ch, [])
        bad = 0
        for seq, (level, late) in got.items():
            if seq > len(tr_edges):
                bad += 1
                continue
            if tr_edges[seq - 1][1] != level:
                bad += 1
        # Edges before this subscription was matched are not lost: count the gaps after it.
        lost += (top - min(got) + 1 - len(got)) if got else 0
        disagree += bad
        per_channel[ch] = {
            "trace_edges": len(tr_edges),
            "edge_messages": len(got),
            "highest_seq": top,
            "disagreeing": bad,
        }
    warm = [(s[0], s[1]) for s in samples if s[0] >= 60 * warmup_min]
    slope = slope_per_minute(warm)

    def part_slope(i: int) -> float | None:
        sl = slope_per_minute([(s[0], s[i]) for s in samples if s[0] >= 60 * warmup_min])
        return None if sl is None else round(sl, 3)

    first_warm = warm[0][1] if warm else None
    wall = t_end - t0
    cpu = samples[-1][2] if samples else 0.0
    figures = {
        "minutes": round(wall / 60, 2),
        "warmup_minutes": warmup_min,
        "period_ms": a.period_ms,
        "rt_priority": a.rt_priority,
        "rss_start_kib": samples[0][1] if samples else None,
        "rss_after_warmup_kib": first_warm,
        "rss_end_kib": samples[-1][1] if samples else None,
        "rss_max_kib": max(s[1] for s in samples) if samples else None,
        "rss_slope_after_warmup_kb_per_min": None if slope is None else round(slope, 3),
        "rss_samples_in_fit": len(warm),
        # The same fit from minute 5 on, whatever the warm-up, for comparison between runs.
        "rss_slope_from_minute_5_kb_per_min": None
        if (s5 := slope_per_minute([(s[0], s[1]) for s in samples if s[0] >= 300])) is None
        else round(s5, 3),
        # RSS in two parts: anonymous memory (heap, stacks) and pages of the binary and
        # libraries, which grow as code runs for the first time and shrink under page-cache
        # pressure.
        "rss_anon_slope_after_warmup_kb_per_min": part_slope(3),
        "rss_file_slope_after_warmup_kb_per_min": part_slope(4),
        "rss_anon_start_end_kib": [samples[0][3], samples[-1][3]] if samples else None,
        "rss_file_start_end_kib": [samples[0][4], samples[-1][4]] if samples else None,
        "cpu_percent_of_one_core": round(100 * cpu / max(samples[-1][0], 1e-9), 2)
        if samples else None,
        "commands_sent": ctl.sent,
        "parameter_calls_refused": ctl.refused_params,
        "parameter_calls_unanswered": ctl.unanswered_params,
        "status_messages": ctl.received["status"],
        "diagnostics_messages": ctl.received["diagnostics"],
        "edges": per_channel,
        "edges_total": sum(c["trace_edges"] for c in per_channel.values()),
        "edge_messages_missing": lost,
        "edge_messages_disagreeing": disagree,
        "reports_dropped_by_the_node": ctl.reports_dropped,
        **tr,
        "node_alive_until_sigterm": alive,
        "exit_code": code,
        "work_dir": str(work),
    }
    for k, v in figures.items():
        print(f"{k}: {v}")
    if a.json:
        print(json.dumps(figures))
    failures = []
    if slope is None:
        failures.append("too few RSS samples after the warm-up for a slope")
    elif slope > a.max_slope_kb_per_min:
        failures.append(f"RSS slope {slope:.2f} kB/min above {a.max_slope_kb_per_min:g}")
    for k in ("early_edges", "phases_below_minimum", "edge_messages_missing",
              "edge_messages_disagreeing", "reports_dropped_by_the_node"):
        if figures[k]:
            failures.append(f"{k}: {figures[k]}")
    if not alive:
        failures.append("the node exited before the SIGTERM")
    if code != 0:
        failures.append(f"exit code {code} after SIGTERM")
    for f in failures:
        print(f"soak: FAIL: {f}")
    print("soak: FAIL" if failures else "soak: ok", flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
