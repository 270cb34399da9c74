#!/usr/bin/env python3
"""Draw the heater loop's pictures for docs/heater.md from real runs of the node and the
simulated heater (`pwm_actuator_node sim-heater`, its own process and ROS participant).

Each scenario starts the simulated heater (it records every reading and every edge of pw01's
line as CSV, and sends the setpoint), then the node with pw01 under pid on a simulated output,
lets them run, stops both, and draws from the record: the temperature (what the sensor sent and
the plant's true one), the setpoint, the duty (the line's on time in each period) and the line.

  settle        80 °C setpoint from 20 °C: the loop settling          -> docs/heater-settle.png
  fallen_off    settled, then the sensor falls off its block: no_rise trips -> docs/heater-fallen-off.png
  pid_mpc       the same plant (its sensor lagging 1 s) and the same 80 °C step and unannounced fan
                (30 % of the power at 150 s) under pid and under mpc, side by side
                                                                      -> docs/heater-pid-mpc.png

Usage:
  scripts/heater_plots.py                     every scenario, into docs/
  scripts/heater_plots.py --scenario settle --out /tmp/a.png

Needs the release build (cargo build --release) and matplotlib (scripts/requirements-docs.txt,
installed into .venv: `.venv/bin/pip install -r scripts/requirements-docs.txt -c
scripts/constraints-ros.txt`); run with an interpreter lacking it, it re-executes itself with
.venv/bin/python. Uses ROS_DOMAIN_ID (default 0) with discovery kept on this machine.
"""

from __future__ import annotations

import argparse
import csv
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NODE = Path(os.environ.get("PWM_ACTUATOR_NODE", REPO / "target" / "release" / "pwm_actuator_node"))
PERIOD_S = 1.0
SETPOINT = 80.0
#: The demo plant of scripts/heater-demo.sh and its SIMC gains.
PLANT = ["--heat-rate", "2", "--tau", "60", "--dead-time", "2", "--ambient", "20", "--noise", "0.05"]
PARAMS = [
    "pw01.period_ms:=1000", "pw01.feedback_topic:=/heater/temperature", "pw01.control:=pid",
    "pw01.pid_kp:=12.5", "pw01.pid_ki:=0.78", "pw01.temp_min_c:=0.0", "pw01.temp_max_c:=250.0",
    "pw01.feedback_timeout_ms:=5000", "pw01.stuck_on_rise_c:=8.0", "pw01.enable:=true",
]  # fmt: skip
SCENARIOS = {
    "settle": dict(seconds=200.0, sim=[], out="docs/heater-settle.png",
                   title="pw01 under pid: 80 °C setpoint from 20 °C"),
    "fallen_off": dict(seconds=150.0, sim=["--fault", "sensor_fallen_off", "--fault-after", "110"],
                       out="docs/heater-fallen-off.png",
                       title="settled at 80 °C, the sensor falls off its block at 110 s: no_rise"),
}  # fmt: skip
#: pid_mpc: the loops compared, each a run of its own (on its own ROS domain, at once). mpc on
#: the plant's model (gain 2 °C/s × 60 s / 100 %), the tolerance of model_deviation above
#: what the unannounced fan moves its residual by (docs/heater.md).
COMPARE = dict(seconds=300.0, plant=["--sensor-tau", "1"], sim=["--fan", "0.3", "--fan-after", "150"],
               out="docs/heater-pid-mpc.png",
               title="80 °C from 20 °C, then a fan taking 30 % of the power at 150 s (unannounced)")
MPC_PARAMS = [
    "pw01.control:=mpc", "pw01.model_gain_c_per_pct:=1.2", "pw01.model_tau_s:=60.0",
    "pw01.model_dead_time_s:=2.0", "pw01.model_sensor_tau_s:=1.0", "pw01.model_ambient_c:=20.0",
    "pw01.model_tolerance_c:=46.0",
]  # fmt: skip


def ensure_matplotlib() -> None:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        venv = REPO / ".venv" / "bin" / "python"
        if venv.exists() and Path(sys.executable).resolve() != venv.resolve():
            os.execv(str(venv), [str(venv), *sys.argv])
        sys.exit("heater_plots: matplotlib is missing (see scripts/requirements-docs.txt)")


def start(scenario: dict, workdir: Path, params=(), domain=None):
    """Starts simulated heater and node; returns both processes and the record's path."""
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if domain is not None:
        env["ROS_DOMAIN_ID"] = str(domain)
    record = workdir / "record.csv"
    sim = subprocess.Popen(
        [NODE, "sim-heater", *PLANT, *scenario.get("plant", []), "--setpoint", str(SETPOINT),
         "--record", record, "--duration", str(scenario["seconds"]), *scenario["sim"]],
        env=env, stdout=subprocess.DEVNULL, stderr=open(workdir / "sim.log", "wb"),
    )  # fmt: skip
    node = subprocess.Popen(
        [NODE, "--output", "sim", "--ros-args",
         *[a for p in [*PARAMS, *params] for a in ("-p", p)]],
        env=env, stdout=subprocess.DEVNULL, stderr=open(workdir / "node.log", "wb"),
    )  # fmt: skip
    return sim, node, record


def finish(scenario: dict, workdir: Path, sim, node, record) -> tuple[Path, str]:
    """Waits for the simulated heater's end, stops the node; the record and the node's log."""
    try:
        sim.wait(timeout=scenario["seconds"] + 60)
    finally:
        node.send_signal(signal.SIGTERM)
        node.wait(timeout=20)
        if sim.poll() is None:
            sim.send_signal(signal.SIGTERM)
            sim.wait(timeout=10)
    return record, (workdir / "node.log").read_text(errors="replace")


def run(scenario: dict, workdir: Path) -> tuple[Path, str]:
    """Runs node and simulated heater; returns the record and the node's log."""
    return finish(scenario, workdir, *start(scenario, workdir))


def load(record: Path):
    """The readings, the true temperatures, the line's edges and the duty of each period."""
    readings, true_c, edges = [], [], []
    with open(record) as f:
        for t, kind, value, true in csv.reader(f):
            if kind == "reading":
                readings.append((float(t), float(value)))
                true_c.append((float(t), float(true)))
            elif kind == "line":
                edges.append((float(t), int(float(value))))
    end = readings[-1][0] if readings else 1.0
    duty = []
    k = int(edges[0][0] / PERIOD_S) if edges else 0
    while (k + 1) * PERIOD_S <= end:
        a, b = k * PERIOD_S, (k + 1) * PERIOD_S
        on, level, since = 0.0, 0, 0.0
        for t, v in edges:
            if level:
                on += max(0.0, min(t, b) - max(since, a))
            level, since = v, t
        if level:
            on += max(0.0, b - max(since, a))
        duty.append((a, 100.0 * on / PERIOD_S))
        k += 1
    return readings, true_c, edges, duty


def compare(out: Path) -> None:
    """pid_mpc: both loops at once on their own domains, drawn on one figure, with the
    integrated absolute error of the plant's true temperature after the step and the fan."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = COMPARE
    base = int(os.environ.get("ROS_DOMAIN_ID", "0"))
    with tempfile.TemporaryDirectory() as d:
        runs = {}
        for i, (name, params) in enumerate((("pid", []), ("mpc", MPC_PARAMS))):
            w = Path(d) / name
            w.mkdir()
            runs[name] = (w, start(s, w, params, domain=base + 1 + i))
        got = {name: load(finish(s, w, *procs)[0]) for name, (w, procs) in runs.items()}
        logs = {name: (w / "node.log").read_text(errors="replace") for name, (w, _) in runs.items()}
    fan_at = float(s["sim"][s["sim"].index("--fan-after") + 1])
    fig, (ax_t, ax_d) = plt.subplots(
        2, 1, figsize=(10, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1.5]}
    )
    for name, (readings, true_c, _, duty) in got.items():
        dt = [b[0] - a[0] for a, b in zip(true_c, true_c[1:])]
        step = sum(abs(v - SETPOINT) * h for (t, v), h in zip(true_c, dt) if t < fan_at)
        fan = sum(abs(v - SETPOINT) * h for (t, v), h in zip(true_c, dt) if t >= fan_at)
        dip = max((SETPOINT - v for t, v in true_c if t >= fan_at), default=0.0)
        over = max((v - SETPOINT for t, v in true_c if t < fan_at), default=0.0)
        label = (f"{name}: IAE step {step:.0f}, fan {fan:.0f} °C·s; overshoot {over:.2f} °C, "
                 f"fan dip {dip:.2f} °C")  # fmt: skip
        print(f"heater_plots: {label}")
        ax_t.plot([t for t, _ in true_c], [v for _, v in true_c], lw=0.9, label=label)
        ax_d.step([t for t, _ in duty], [v for _, v in duty], where="post", lw=0.8, label=name)
        if "heater fault latched" in logs[name]:
            print(f"heater_plots: {name}: a heater fault latched")
    ax_t.axhline(SETPOINT, color="k", lw=0.8, ls=":", label=f"setpoint {SETPOINT:g} °C")
    for ax in (ax_t, ax_d):
        ax.axvline(fan_at, color="grey", lw=0.8, ls="--")
    ax_t.set_ylabel("°C (plant, true)")
    ax_t.set_ylim(SETPOINT - 15, SETPOINT + 5)
    ax_t.legend(loc="lower right", fontsize=8)
    ax_d.set_ylabel("duty %")
    ax_d.set_ylim(-5, 105)
    ax_d.legend(loc="lower right", fontsize=8)
    ax_d.set_xlabel("s since the simulated heater started")
    fig.suptitle(s["title"])
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    print(f"heater_plots: {out}")


def draw(record: Path, log: str, title: str, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # Time from the simulated heater's start (the node enables pw01 a moment later); the
    # duty: the line's on time in each period after the enable.
    readings, true_c, edges, duty = load(record)
    end = readings[-1][0] if readings else 1.0
    fault = next((ln for ln in log.splitlines() if "heater fault latched" in ln), None)
    last_fall = next((t for t, v in reversed(edges) if v == 0), None)

    fig, (ax_t, ax_d, ax_l) = plt.subplots(
        3, 1, figsize=(10, 7), sharex=True, gridspec_kw={"height_ratios": [3, 1.5, 0.7]}
    )
    ax_t.plot([t for t, _ in readings], [v for _, v in readings], lw=0.8, label="reading (sensor_msgs/Temperature)")
    ax_t.plot([t for t, _ in true_c], [v for _, v in true_c], lw=0.8, ls="--", label="plant (true)")
    ax_t.axhline(SETPOINT, color="k", lw=0.8, ls=":", label=f"setpoint {SETPOINT:g} °C")
    ax_t.set_ylabel("°C")
    ax_t.legend(loc="lower right", fontsize=8)
    ax_d.step([t for t, _ in duty], [v for _, v in duty], where="post", lw=0.8)
    ax_d.set_ylabel("duty %")
    ax_d.set_ylim(-5, 105)
    xs, ys = [0.0], [0]
    for t, v in edges:
        xs += [t, t]
        ys += [ys[-1], v]
    xs.append(end)
    ys.append(ys[-1])
    ax_l.plot(xs, ys, lw=0.5)
    ax_l.set_ylabel("line")
    ax_l.set_yticks([0, 1])
    ax_l.set_xlabel("s since the simulated heater started")
    if fault and last_fall is not None:
        for ax in (ax_t, ax_d, ax_l):
            ax.axvline(last_fall, color="r", lw=0.8)
        check = fault.split("heater fault latched: ", 1)[-1].split(":", 1)[0]
        ax_t.annotate(f"{check} latched: line off", (last_fall, 40.0), xytext=(5, 0),
                      textcoords="offset points", color="r", fontsize=9)  # fmt: skip
    fig.suptitle(title)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    print(f"heater_plots: {out}" + (f" ({fault.split(']: ', 1)[-1]})" if fault else ""))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", choices=sorted([*SCENARIOS, "pid_mpc"]), action="append")
    p.add_argument("--out", type=Path, help="output file (with one --scenario)")
    a = p.parse_args()
    ensure_matplotlib()
    if not os.access(NODE, os.X_OK):
        sys.exit(f"heater_plots: {NODE} not found: run cargo build --release")
    names = a.scenario or sorted([*SCENARIOS, "pid_mpc"])
    for name in names:
        if name == "pid_mpc":
            started = time.monotonic()
            compare(a.out if (a.out and len(names) == 1) else REPO / COMPARE["out"])
            print(f"heater_plots: {name} ran {time.monotonic() - started:.0f} s")
            continue
        s = SCENARIOS[name]
        out = a.out if (a.out and len(names) == 1) else REPO / s["out"]
        with tempfile.TemporaryDirectory() as d:
            started = time.monotonic()
            record, log = run(s, Path(d))
            draw(record, log, s["title"], out)
            print(f"heater_plots: {name} ran {time.monotonic() - started:.0f} s")


if __name__ == "__main__":
    main()
