#!/usr/bin/env python3
"""Draw the valve's timing picture for docs/valve.md from a real run of the node and the
simulated actuator (`pwm_actuator_node sim-valve`, its own process and ROS participant).

It starts the simulated actuator (true travel times 10 % off the configured ones, recording the
two lines' edges as the node stamped them and its true position) and the node with a valve on
pw01/pw02, sends a few positions on ~/valve/mix/position, records ~/valve/mix/state, and draws
the target, the node's estimate, the true position, and the open and close lines: the reference
at start, a move, small steps accumulated into one minimum pulse, a reversal with its pause, and
an end move with its overrun.

Usage (after scripts/setup.sh and cargo build --release):
  source scripts/env.sh && .venv/bin/pip install -r scripts/requirements-docs.txt \\
      -c scripts/constraints-ros.txt && python scripts/valve_plot.py [--out docs/valve-timing.png]

Uses ROS_DOMAIN_ID (default 0) with discovery kept on this machine.
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
TRAVEL_MS = 4000
PARAMS = [
    # Managed: the lines are held until the activation, sent once the simulated actuator follows
    # the edges, so it sees the reference at start.
    "managed:=true", "channels:=2", "valve:=mix:pw01:pw02", f"mix.travel_open_ms:={TRAVEL_MS}",
    f"mix.travel_close_ms:={TRAVEL_MS}", "mix.min_pulse_ms:=200", "mix.reversal_pause_ms:=400",
    "mix.deadband_pct:=0.5", "mix.end_overrun_pct:=10.0", "mix.max_uncertainty_pct:=30.0",
]  # fmt: skip
#: (seconds after the reference ended, target %): a move, four 1.5 % steps (60 ms each, below
#: the 200 ms minimum pulse) that wait until the fourth sends all 6 % in one move, a reversal,
#: an end move.
SCRIPT = [(0.5, 50.0), (3.5, 51.5), (4.0, 53.0), (4.5, 54.5), (5.0, 56.0), (5.3, 30.0), (7.5, 0.0)]
TAIL_S = 6.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO / "docs" / "valve-timing.png")
    a = p.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import rclpy
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    from pwm_actuator_msgs.msg import ValveState
    from std_msgs.msg import Float64

    if not os.access(NODE, os.X_OK):
        sys.exit(f"valve_plot: {NODE} not found: run cargo build --release")
    env = dict(os.environ)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with tempfile.TemporaryDirectory() as d:
        record = Path(d) / "record.csv"
        sim = subprocess.Popen(
            [NODE, "sim-valve", "--travel-open-ms", str(TRAVEL_MS * 1.1),
             "--travel-close-ms", str(TRAVEL_MS * 0.9), "--start-pct", "35", "--rate-hz", "100",
             "--record", record],
            env=env, stdout=subprocess.DEVNULL, stderr=open(Path(d) / "sim.log", "wb"),
        )  # fmt: skip
        rclpy.init()
        ros = rclpy.create_node("valve_plot")
        states: list[tuple[float, float, float, bool, float, float]] = []
        ros.create_subscription(
            ValveState,
            "/pwm_actuator/valve/mix/state",
            lambda m: states.append(
                (
                    m.stamp.sec + m.stamp.nanosec * 1e-9,
                    m.position_pct,
                    m.target_pct,
                    m.referenced and m.motion == "stopped",
                    m.position_low_pct,
                    m.position_high_pct,
                )
            ),
            100,
        )
        pub = ros.create_publisher(Float64, "/pwm_actuator/valve/mix/position", 10)
        node = subprocess.Popen(
            [NODE, "--output", "sim", "--ros-args", *[x for q in PARAMS for x in ("-p", q)]],
            env=env, stdout=subprocess.DEVNULL, stderr=open(Path(d) / "node.log", "wb"),
        )  # fmt: skip
        try:
            deadline = time.monotonic() + 30
            # The edges topic matched with sim-valve, then configure and activate.
            edges = "/pwm_actuator/pw02/edges"
            while ros.count_subscribers(edges) < 1 or ros.count_publishers(edges) < 1:
                rclpy.spin_once(ros, timeout_sec=0.05)
                if time.monotonic() > deadline:
                    sys.exit("valve_plot: sim-valve does not follow the edges")
            # Discovery seen from here; give the two of them a moment to match as well.
            settle = time.monotonic() + 1.0
            while time.monotonic() < settle:
                rclpy.spin_once(ros, timeout_sec=0.05)
            client = ros.create_client(ChangeState, "/pwm_actuator/change_state")
            client.wait_for_service(timeout_sec=20)
            for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
                future = client.call_async(ChangeState.Request(transition=Transition(id=transition)))
                rclpy.spin_until_future_complete(ros, future, timeout_sec=20)
                if not (future.result() and future.result().success):
                    sys.exit(f"valve_plot: lifecycle transition {transition} failed")
            # Until the reference at start is done.
            while pub.get_subscription_count() < 1 or not (states and states[-1][3]):
                rclpy.spin_once(ros, timeout_sec=0.05)
                if time.monotonic() > deadline:
                    sys.exit("valve_plot: the reference did not finish\n" + (Path(d) / "node.log").read_text())
            t0 = time.monotonic()
            for at, target in SCRIPT + [(SCRIPT[-1][0] + TAIL_S, None)]:
                while time.monotonic() - t0 < at:
                    rclpy.spin_once(ros, timeout_sec=0.02)
                if target is not None:
                    pub.publish(Float64(data=target))
        finally:
            node.send_signal(signal.SIGTERM)
            node.wait(timeout=20)
            sim.send_signal(signal.SIGTERM)
            sim.wait(timeout=10)
            ros.destroy_node()
            rclpy.shutdown()
        rows = list(csv.reader(open(record)))
    lines = {"open": [], "close": []}
    true = []
    for t, kind, value in rows:
        if kind in lines:
            lines[kind].append((float(t), int(float(value))))
        elif kind == "true":
            true.append((float(t), float(value)))
    t_start = true[0][0]
    end = true[-1][0] - t_start
    rel = lambda xs: [x - t_start for x in xs]  # noqa: E731

    fig, (ax_p, ax_o, ax_c) = plt.subplots(
        3, 1, figsize=(10, 6), sharex=True, gridspec_kw={"height_ratios": [3, 0.6, 0.6]}
    )
    # The estimate between two snapshots moves linearly while a line drives (as the node
    # computes it); the snapshots themselves are drawn as dots.
    st = [s for s in states if s[0] >= t_start]
    ax_p.plot(rel([t for t, _ in true]), [v for _, v in true], lw=1.0, label="true position (sim-valve)")
    ax_p.plot(rel([s[0] for s in st]), [s[1] for s in st], "o-", ms=3, lw=0.8, label="estimate (~/valve/mix/state)")
    ax_p.fill_between(rel([s[0] for s in st]), [s[4] for s in st], [s[5] for s in st], step="post",
                      alpha=0.2, label="bounds of the true position")  # fmt: skip
    tg = [(s[0], s[2]) for s in st if s[2] == s[2]]
    ax_p.step(rel([t for t, _ in tg]), [v for _, v in tg], where="post", color="k", lw=0.8, ls=":", label="target")
    ax_p.set_ylabel("position %")
    ax_p.set_ylim(-5, 105)
    ax_p.legend(loc="upper right", fontsize=8)
    for ax, kind, name in ((ax_o, "open", "pw01 open"), (ax_c, "close", "pw02 close")):
        xs, ys = [0.0], [0]
        for t, v in lines[kind]:
            xs += [t - t_start, t - t_start]
            ys += [ys[-1], v]
        xs.append(end)
        ys.append(ys[-1])
        ax.plot(xs, ys, lw=0.8)
        ax.set_ylabel(name)
        ax.set_yticks([0, 1])
    ax_c.set_xlabel("s since sim-valve started (true travel 10 % off: opening slower, closing faster)")
    fig.suptitle(
        f"valve mix: travel {TRAVEL_MS / 1000:g} s, minimum pulse 200 ms, reversal pause 400 ms, "
        "overrun 10 %"
    )
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=90)
    print(f"valve_plot: {a.out}")


if __name__ == "__main__":
    main()
