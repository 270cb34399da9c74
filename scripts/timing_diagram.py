#!/usr/bin/env python3
"""Render a timing diagram (PNG, SVG or PDF) from a CSV edge trace of pwm_actuator_node.

The trace is the one the node writes with `--trace FILE.csv` (sim output): header
`t_ns,channel,level,scheduled_ns`, one row at level 0 per channel when the output starts, then
one row per edge, times in CLOCK_MONOTONIC nanoseconds. Each channel is drawn as a 0/1 step
waveform against milliseconds since the first row. The first full pulse of each channel (a
rising edge, its falling edge and the next rising edge) is measured from the trace and
annotated with its on time, its period and the duty they make.

Usage:
  scripts/timing_diagram.py --run docs/timing-diagram.png    run the node, then render
  scripts/timing_diagram.py --run --scenario stagger docs/timing-stagger.png
  scripts/timing_diagram.py --csv trace.csv out.png          render an existing trace

`--run` starts target/release/pwm_actuator_node (build it first with
`cargo build --release --bins`) with the sim output, a trace in a temporary directory and the
channels of a scenario (`--scenario`, see SCENARIOS) enabled at start-up. The default,
`minimum`: pw01 at 37 % of 200 ms, and pw02 at 10 % of 200 ms with a 30 ms minimum on time
under the twincat_ba profile, which stretches the 20 ms pulse to 30 ms and sets E1. `sync` and
`stagger`: three channels at 15, 25 and 30 % of 200 ms with `phase` sync or stagger. `extend`:
10 % of 100 ms with a 30 ms minimum on time, extended (pw01) and stretched (pw02). `timebase`:
37.1 % of 100 ms with a 60 Hz half-cycle time base (pw01) and without (pw02), drawn over the
tick grid, with the mean duty of each channel's full periods. `--seconds` after the first edge
it sends SIGTERM (the node drives every output inactive and must exit 0), then renders the
trace with the command in the title.

Dependency: matplotlib (pinned in scripts/requirements-docs.txt; install it into the repository's
virtualenv with `.venv/bin/pip install -r scripts/requirements-docs.txt -c
scripts/constraints-ros.txt`). Started with an interpreter that lacks it, the script re-executes
itself with .venv/bin/python when that exists.
"""

from __future__ import annotations

import argparse
import csv
import os
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
VENV_PYTHON = REPO / ".venv" / "bin" / "python"
DEFAULT_BINARY = REPO / "target" / "release" / "pwm_actuator_node"
REEXEC_MARKER = "PWM_TIMING_DIAGRAM_REEXEC"
CSV_HEADER = ["t_ns", "channel", "level", "scheduled_ns"]
# How long --run waits for the first edge in the trace (DDS set-up comes first).
STARTUP_TIMEOUT_S = 30
# --run's default time from the first edge to SIGTERM. Both channels' periods start together at
# that edge, so 1.95 s falls 150 ms into a 200 ms period: after pw01's 74 ms pulse and pw02's
# 30 ms pulse, 50 ms before the next ones. The SIGTERM line lands in an off phase and no pulse
# is cut short in the picture.
DEFAULT_SECONDS = 1.95
NS_PER_MS = 1_000_000

# The node's start-up settings for --run, per scenario (--scenario): node-level settings as
# ("name", value), channel settings as ("pwNN.name", value).
SCENARIOS: dict[str, list[tuple[str, str]]] = {
    # pw02's 10 % of 200 ms is 20 ms, below its 30 ms minimum on time: twincat_ba stretches the
    # pulse to the minimum (002: nMinSwiTi) and E1 is set.
    "minimum": [
        ("pw01.period_ms", "200"),
        ("pw01.duty", "37.0"),
        ("pw01.enable", "true"),
        ("pw02.period_ms", "200"),
        ("pw02.min_on_ms", "30"),
        ("pw02.profile", "twincat_ba"),
        ("pw02.duty", "10.0"),
        ("pw02.enable", "true"),
    ],
    # Three heaters on one supply, 15 + 25 + 30 % of 200 ms: in sync all switch on together at
    # each period start; staggered, their pulses lie end to end on the grid and never overlap.
    **{
        phase: [
            ("channels", "3"),
            ("phase", phase),
            *[
                (f"{ch}.{name}", value)
                for ch, duty in (("pw01", "15.0"), ("pw02", "25.0"), ("pw03", "30.0"))
                for name, value in (("period_ms", "200"), ("duty", duty), ("enable", "true"))
            ],
        ]
        for phase in ("sync", "stagger")
    },
    # 10 % of 100 ms is a 10 ms pulse, below the 30 ms minimum on time. extend (pw01) keeps the
    # duty by growing the period to 30 ms / 10 % = 300 ms; stretch (pw02) raises the pulse to
    # 30 ms in the 100 ms period, 30 % delivered, E1.
    "extend": [
        *[
            (f"{ch}.{name}", value)
            for ch, policy in (("pw01", "extend"), ("pw02", "stretch"))
            for name, value in (
                ("period_ms", "100"),
                ("min_on_ms", "30"),
                ("short_pulse", policy),
                ("duty", "10.0"),
                ("enable", "true"),
            )
        ],
    ],
    # A zero-cross SSR on 60 Hz mains switches only at the half-cycle zero crossings (drawn as
    # the grid). 37.1 % of 100 ms is 4.452 half cycles: with the time base (pw01) the pulses are
    # 4 or 5 whole half cycles on the grid, the remainder carried so the mean is 37.1 %; without
    # (pw02) every pulse is 37.1 ms and ends between two crossings, which the SSR rounds itself.
    "timebase": [
        *[
            (f"{ch}.{name}", value)
            for ch, extra in (("pw01", [("time_base_ms", "8.333333")]), ("pw02", []))
            for name, value in (
                ("period_ms", "100"),
                *extra,
                ("duty", "37.1"),
                ("enable", "true"),
            )
        ],
    ],
}
# --run's default scenario.
DEFAULT_SCENARIO = "minimum"
# Scenarios drawn over a tick grid: its period, ns (the instants k * tick of CLOCK_MONOTONIC).
SCENARIO_GRID: dict[str, int] = {"timebase": 8_333_333}


def _import_pyplot():
    """Returns matplotlib.pyplot with the file-only Agg backend, re-executing the script with the
    repository's virtualenv when this interpreter lacks matplotlib."""
    try:
        import matplotlib
    except ImportError:
        in_venv = Path(sys.prefix).resolve() == VENV_PYTHON.parent.parent.resolve()
        # The marker stops a second re-execution when the virtualenv lacks matplotlib too.
        if VENV_PYTHON.exists() and not in_venv and REEXEC_MARKER not in os.environ:
            os.environ[REEXEC_MARKER] = "1"
            script = str(Path(__file__).resolve())
            os.execv(str(VENV_PYTHON), [str(VENV_PYTHON), script, *sys.argv[1:]])
        sys.exit(
            "timing_diagram: matplotlib is not installed for "
            f"{sys.executable}; install it with\n"
            "  .venv/bin/pip install -r scripts/requirements-docs.txt -c scripts/constraints-ros.txt"
        )
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


class TraceError(Exception):
    """A trace file that is not a pwm_actuator CSV trace; the message says where and why."""


@dataclass
class Channel:
    """One channel's rows: (t_ns, level, scheduled_ns) in file order."""

    name: str
    rows: list[tuple[int, int, int]] = field(default_factory=list)


@dataclass
class Pulse:
    """The first full pulse of a channel, times in ns."""

    rise: int
    fall: int
    next_rise: int

    @property
    def on_ns(self) -> int:
        return self.fall - self.rise

    @property
    def period_ns(self) -> int:
        return self.next_rise - self.rise


def read_trace(path: Path) -> list[Channel]:
    """Reads a CSV trace; channels in order of first appearance."""
    channels: dict[str, Channel] = {}
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header != CSV_HEADER:
                raise TraceError(
                    f"{path}: header is {header!r}, expected {','.join(CSV_HEADER)!r}"
                )
            for lineno, row in enumerate(reader, start=2):
                if not row:
                    continue
                if len(row) != 4:
                    raise TraceError(f"{path}:{lineno}: expected 4 fields, got {len(row)}")
                t, name, level, sched = row
                try:
                    t_ns, lvl, sched_ns = int(t), int(level), int(sched)
                except ValueError:
                    raise TraceError(
                        f"{path}:{lineno}: t_ns, level and scheduled_ns must be integers: {row!r}"
                    ) from None
                if lvl not in (0, 1):
                    raise TraceError(f"{path}:{lineno}: level must be 0 or 1, got {lvl}")
                ch = channels.setdefault(name, Channel(name))
                if ch.rows and t_ns < ch.rows[-1][0]:
                    raise TraceError(
                        f"{path}:{lineno}: {name}: time goes backwards ({t_ns} < {ch.rows[-1][0]})"
                    )
                ch.rows.append((t_ns, lvl, sched_ns))
    except OSError as e:
        raise TraceError(f"cannot read {path}: {e.strerror}") from None
    if not channels:
        raise TraceError(f"{path}: no rows after the header")
    return list(channels.values())


def first_full_pulse(ch: Channel, scheduled: bool = False) -> Pulse | None:
    """The first rising edge that has a falling edge and a next rising edge after it, at the
    times the edges were written (`scheduled`: at the instants the core scheduled them)."""
    edges = []
    prev = None
    for written, lvl, sched in ch.rows:
        t = sched if scheduled else written
        if prev is not None and lvl != prev:
            edges.append((t, lvl))
        prev = lvl
    for i in range(len(edges) - 2):
        (t0, l0), (t1, l1), (t2, l2) = edges[i : i + 3]
        if (l0, l1, l2) == (1, 0, 1):
            return Pulse(t0, t1, t2)
    return None


def lateness_us(ch: Channel) -> list[float]:
    """Each edge's lateness against its schedule, µs (the initial row is not an edge)."""
    return [(t - s) / 1000.0 for t, _, s in ch.rows[1:]]


def mean_duty(ch: Channel) -> float:
    """The on time between the first and the last rising edge over that time, % (scheduled
    instants)."""
    edges = []
    prev = None
    for _, lvl, sched in ch.rows:
        if prev is not None and lvl != prev:
            edges.append((sched, lvl))
        prev = lvl
    rises = [t for t, lvl in edges if lvl == 1]
    if len(rises) < 2:
        return float("nan")
    start, end = rises[0], rises[-1]
    on = 0
    for (t, lvl), (t2, _) in zip(edges, edges[1:]):
        if lvl == 1 and start <= t and t2 <= end:
            on += t2 - t
    return 100.0 * on / (end - start)


def fmt_ms(ns: int) -> str:
    return f"{ns / NS_PER_MS:.1f} ms"


def render(
    channels: list[Channel],
    out: Path,
    title: str,
    notes: dict[str, str] | None = None,
    marker: tuple[int, str] | None = None,
    grid_ns: int | None = None,
) -> None:
    """Draws the diagram to `out`. `notes` adds a line under a channel's name; `marker` is an
    (absolute t_ns, label) drawn as a vertical line across every channel; `grid_ns` draws the
    tick grid (the instants k * grid_ns of the trace's clock) behind every channel and adds each
    channel's mean duty over its full periods."""
    plt = _import_pyplot()
    notes = notes or {}
    t0 = min(ch.rows[0][0] for ch in channels)
    t_end = max(ch.rows[-1][0] for ch in channels)
    if marker is not None:
        t_end = max(t_end, marker[0])
    span_ms = max((t_end - t0) / NS_PER_MS, 1.0)
    x_end = span_ms * 1.03
    ms = lambda t: (t - t0) / NS_PER_MS  # noqa: E731

    n = len(channels)
    fig, axes = plt.subplots(
        n, 1, sharex=True, figsize=(13, 1.9 * n + 1.5), dpi=110, squeeze=False
    )
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (ax, ch) in enumerate(zip(axes[:, 0], channels)):
        color = colors[i % len(colors)]
        xs = [ms(t) for t, _, _ in ch.rows] + [x_end]
        ys = [lvl for _, lvl, _ in ch.rows] + [ch.rows[-1][1]]
        if grid_ns:
            k = -(-t0 // grid_ns)
            while k * grid_ns <= t0 + x_end * NS_PER_MS:
                ax.axvline(ms(k * grid_ns), color="0.8", linewidth=0.5, zorder=0)
                k += 1
        ax.step(xs, ys, where="post", color=color, linewidth=1.6)
        ax.fill_between(xs, ys, step="post", color=color, alpha=0.15, linewidth=0)
        ax.set_ylim(-0.75, 1.75)
        ax.set_yticks([0, 1])
        ax.set_xlim(0, x_end)
        ax.grid(axis="x", color="0.88", linewidth=0.6)
        ax.spines[["top", "right"]].set_visible(False)
        # Name and settings left of the tick labels, offset in points so they never overlap them.
        left = dict(xy=(0, 0.5), xycoords="axes fraction", textcoords="offset points", ha="right")
        ax.annotate(ch.name, xytext=(-28, 4), va="bottom", fontsize=11, fontweight="bold", **left)
        if ch.name in notes:
            ax.annotate(notes[ch.name], xytext=(-28, -2), va="top", fontsize=8.5, **left)

        late = lateness_us(ch)
        edges = len(late)
        summary = f"{edges} edges"
        if late:
            summary += f", lateness median {statistics.median(late):.0f} µs, max {max(late):.0f} µs"
        # Over a tick grid the pulse is measured where the core put it, on the grid.
        pulse = first_full_pulse(ch, scheduled=bool(grid_ns))
        if pulse is None:
            if edges == 0:
                summary = f"no edge: constant {ch.rows[0][1]}"
            else:
                summary = "no full pulse (rise, fall, rise) in the trace; " + summary
            ax.set_title(summary, loc="right", fontsize=9)
            continue
        r, f, r2 = ms(pulse.rise), ms(pulse.fall), ms(pulse.next_rise)
        for x in (r, f, r2):
            ax.axvline(x, color="0.45", linestyle=":", linewidth=0.8)
        box = dict(facecolor="white", edgecolor="none", pad=1.0)
        arrow = dict(
            arrowstyle="<|-|>", color="0.15", linewidth=1.0, shrinkA=0, shrinkB=0, mutation_scale=9
        )
        # On time above the pulse, left-aligned at the rising edge so it never leaves the axes;
        # period below it, centred on the period.
        ax.annotate("", xy=(f, 1.22), xytext=(r, 1.22), arrowprops=arrow)
        ax.text(r, 1.33, f"on {fmt_ms(pulse.on_ns)}", ha="left", va="bottom", fontsize=9, bbox=box)
        ax.annotate("", xy=(r2, -0.3), xytext=(r, -0.3), arrowprops=arrow)
        ax.text(
            (r + r2) / 2, -0.4, f"period {fmt_ms(pulse.period_ns)}",
            ha="center", va="top", fontsize=9, bbox=box,
        )
        duty = 100.0 * pulse.on_ns / pulse.period_ns
        summary = f"first full pulse: duty {duty:.1f} %; " + summary
        if grid_ns:
            summary = f"{mean_duty(ch):.2f} % over its full periods; " + summary
        ax.set_title(summary, loc="right", fontsize=9)

    if marker is not None:
        mx = ms(marker[0])
        for ax in axes[:, 0]:
            ax.axvline(mx, color="tab:red", linestyle="--", linewidth=1.2)
        axes[-1, 0].annotate(
            marker[1], xy=(mx, 0.5), xytext=(-3, 0), textcoords="offset points",
            color="tab:red", rotation=90, ha="right", va="center", fontsize=9,
        )

    axes[-1, 0].set_xlabel("time since the first trace row, ms (CLOCK_MONOTONIC)")
    fig.suptitle(title, fontsize=9.5, family="monospace", x=0.01, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)


def wrap_title(text: str, width: int = 118) -> str:
    return "\n".join(textwrap.wrap(text, width=width, break_long_words=False, break_on_hyphens=False))


def _setting(name: str, value: str) -> str:
    """A start-up setting as shown beside its channel ('' for enable, which every channel has)."""
    if name == "enable":
        return ""
    if name.endswith("_ms"):
        return f"{name[:-3]} {value} ms"
    if name == "duty":
        return f"duty {float(value):g} %"
    return f"{name} {value}"


def _first_rise_ns(trace: Path) -> int | None:
    """t_ns of the trace's first rising edge, once the node has written it (None before)."""
    try:
        with open(trace) as f:
            lines = f.readlines()
    except OSError:
        return None
    for line in lines[1:]:
        parts = line.split(",")
        if line.endswith("\n") and len(parts) == 4 and parts[2] == "1":
            try:
                return int(parts[0])
            except ValueError:
                return None
    return None


def run_node(
    binary: Path, seconds: float, workdir: Path, domain: int, params: list[tuple[str, str]]
) -> tuple[Path, list[str], int, dict[str, str]]:
    """Runs the node with `params` and a CSV trace, sends SIGTERM after `seconds`. Returns the
    trace path, the command, the monotonic ns at which SIGTERM was sent and per-channel notes."""
    if not binary.exists():
        sys.exit(
            f"timing_diagram: {binary} does not exist; build it with `cargo build --release --bins`"
        )
    trace = workdir / "trace.csv"
    log_path = workdir / "node.log"
    cmd = [str(binary), "--trace", str(trace), "--ros-args"]
    for name, value in params:
        cmd += ["-p", f"{name}:={value}"]
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=workdir)
        # SIGTERM is timed from the first edge in the trace rather than from the process start,
        # so where it falls in the pulse pattern does not depend on how long the start took.
        # time.monotonic_ns() reads CLOCK_MONOTONIC, the trace's clock.
        t0 = None
        give_up = time.monotonic() + STARTUP_TIMEOUT_S
        while proc.poll() is None:
            if t0 is None:
                t0 = _first_rise_ns(trace)
                if t0 is None and time.monotonic() > give_up:
                    break
            if t0 is not None and time.monotonic_ns() >= t0 + int(seconds * 1e9):
                break
            time.sleep(0.005)
        if proc.poll() is not None or t0 is None:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            sys.stderr.write(log_path.read_text(errors="replace"))
            if t0 is None:
                sys.exit(f"timing_diagram: no edge in the trace within {STARTUP_TIMEOUT_S} s of start")
            sys.exit(f"timing_diagram: the node exited early with code {proc.returncode}")
        term_ns = time.monotonic_ns()
        proc.send_signal(signal.SIGTERM)
        try:
            code = proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            sys.exit("timing_diagram: the node did not stop within 15 s of SIGTERM; killed it")
    text = log_path.read_text(errors="replace")
    if code != 0:
        sys.stderr.write(text)
        sys.exit(f"timing_diagram: the node exited with code {code} after SIGTERM (expected 0)")
    notes = {}
    node_wide = [_setting(n, v) for n, v in params if "." not in n and n != "channels"]
    for ch in sorted({n.split(".", 1)[0] for n, _ in params if "." in n}):
        settings = node_wide + [
            _setting(n.split(".", 1)[1], v) for n, v in params if n.startswith(ch + ".")
        ]
        note = "\n".join(x for x in settings if x)
        if f"{ch}: E1 set" in text:
            note += "\nE1 set (node log)"
        notes[ch] = note
    shown = ["pwm_actuator_node", "--trace", "trace.csv"] + cmd[3:]
    return trace, shown, term_ns, notes


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(
        description="Render a timing diagram from a pwm_actuator CSV trace.",
        epilog="Example: scripts/timing_diagram.py --run docs/timing-diagram.png",
    )
    p.add_argument("output", type=Path, help="picture to write (.png, .svg or .pdf)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--run", action="store_true", help="run the node (sim output) and render its trace"
    )
    src.add_argument(
        "--csv", type=Path, metavar="FILE", help="render an existing trace instead of running"
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=DEFAULT_SECONDS,
        help=f"--run: time from the first edge to SIGTERM, s (default {DEFAULT_SECONDS})",
    )
    p.add_argument(
        "--binary",
        type=Path,
        default=DEFAULT_BINARY,
        help=f"--run: the node binary (default {DEFAULT_BINARY.relative_to(REPO)})",
    )
    p.add_argument(
        "--domain",
        type=int,
        default=None,
        help="--run: ROS_DOMAIN_ID for the node (default 200 + pid %% 30, away from the "
        "domain of a live system)",
    )
    p.add_argument(
        "--scenario",
        choices=sorted(SCENARIOS),
        default=DEFAULT_SCENARIO,
        help=f"--run: the settings to run (default {DEFAULT_SCENARIO}; see SCENARIOS)",
    )
    p.add_argument("--save-csv", type=Path, metavar="FILE", help="--run: keep a copy of the trace")
    p.add_argument("--title", help="title (default: the command, or the trace path with --csv)")
    a = p.parse_args(argv)
    if a.seconds <= 0 or a.seconds > 600:
        p.error(f"--seconds {a.seconds}: expected more than 0 and at most 600")
    _import_pyplot()  # fail (or re-execute) before running anything

    try:
        if a.csv is not None:
            channels = read_trace(a.csv)
            render(channels, a.output, a.title or f"trace {a.csv}")
        else:
            domain = a.domain if a.domain is not None else 200 + os.getpid() % 30
            if not 0 <= domain <= 232:
                p.error(f"--domain {domain}: expected 0..232")
            with tempfile.TemporaryDirectory(prefix="pwm_timing_") as tmp:
                trace, shown, term_ns, notes = run_node(
                    a.binary.resolve(), a.seconds, Path(tmp), domain, SCENARIOS[a.scenario]
                )
                channels = read_trace(trace)
                if a.save_csv is not None:
                    a.save_csv.write_bytes(trace.read_bytes())
            # The node must leave every output at 0 after SIGTERM; the label only says so when
            # the trace shows it.
            still_on = [ch.name for ch in channels if ch.rows[-1][1] != 0]
            label = "SIGTERM: outputs off, exit 0"
            if still_on:
                label = "SIGTERM, exit 0"
                print(
                    f"timing_diagram: warning: {', '.join(still_on)} not at 0 at the end of the trace",
                    file=sys.stderr,
                )
            command = " ".join(shlex.quote(s) for s in shown)
            title = a.title or wrap_title(f"{command}   (SIGTERM {a.seconds:g} s after the first edge)")
            render(
                channels, a.output, title, notes=notes, marker=(term_ns, label),
                grid_ns=SCENARIO_GRID.get(a.scenario),
            )
    except TraceError as e:
        print(f"timing_diagram: {e}", file=sys.stderr)
        return 2
    print(f"wrote {a.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
