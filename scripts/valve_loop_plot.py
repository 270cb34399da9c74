#!/usr/bin/env python3
"""Draw the valve loop's picture for docs/valve.md from a real run of scripts/valve-demo.sh: the
node's valve under control pid holding the mixed water of `pwm_actuator_node sim-valve --mix` at
45 °C, and the hot supply dropping by 10 K at 90 s.

It runs the demo with VALVE_DEMO_RECORD set (the simulator records every reading it publishes,
the true mixed temperature, the valve's true position and the hot supply) and draws, against
time, the readings the node received, the true temperature, the setpoint with its ±1 K band,
and below them the valve's true position and the hot supply.

Usage (after scripts/setup.sh and cargo build --release):
  source scripts/env.sh && .venv/bin/pip install -r scripts/requirements-docs.txt \\
      -c scripts/constraints-ros.txt && python scripts/valve_loop_plot.py [--out docs/valve-loop.png]

Uses ROS_DOMAIN_ID (default 0) with discovery kept on this machine.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SECONDS = 150
SETPOINT_C = 45.0
BAND_C = 1.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO / "docs" / "valve-loop.png")
    a = p.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with tempfile.TemporaryDirectory() as tmp:
        record = Path(tmp) / "mix.csv"
        env = dict(os.environ, VALVE_DEMO_RECORD=str(record))
        subprocess.run(
            [str(REPO / "scripts" / "valve-demo.sh"), str(SECONDS), str(SETPOINT_C)],
            env=env,
            check=True,
        )
        rows = list(csv.reader(record.open()))
    t0 = float(rows[0][0])
    series: dict[str, list[tuple[float, float]]] = {}
    for t, kind, value in rows:
        series.setdefault(kind, []).append((float(t) - t0, float(value)))
    hot = series["hot"] + [(SECONDS, series["hot"][-1][1])]

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True,
                                      gridspec_kw={"height_ratios": [3, 2]})
    top.axhspan(SETPOINT_C - BAND_C, SETPOINT_C + BAND_C, color="tab:green", alpha=0.12,
                label=f"setpoint ±{BAND_C:g} K")
    top.axhline(SETPOINT_C, color="tab:green", lw=1)
    top.plot(*zip(*series["reading"]), ".", ms=2.5, color="tab:gray",
             label="readings the node receives (±0.5 K noise)")
    top.plot(*zip(*series["mixed"]), color="tab:red", lw=1.5, label="mixed water (true)")
    top.set_ylabel("°C")
    top.legend(loc="lower right", fontsize=8)
    top.set_title("The valve's own loop on sim-valve --mix (travel 20 s, tau 20 s, dead time "
                  "3 s; SIMC gains)", fontsize=10)
    bottom.plot(*zip(*series["true"]), color="tab:blue", lw=1.2, label="valve (true), %")
    bottom.set_ylabel("valve %")
    right = bottom.twinx()
    right.step(*zip(*hot), where="post", color="tab:orange", lw=1.2, label="hot supply, °C")
    right.set_ylabel("hot supply °C")
    right.set_ylim(50, 80)
    bottom.set_xlabel("s")
    bottom.set_xlim(0, SECONDS)
    lines = bottom.get_legend_handles_labels()
    more = right.get_legend_handles_labels()
    bottom.legend(lines[0] + more[0], lines[1] + more[1], loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"valve_loop_plot: wrote {a.out}")


if __name__ == "__main__":
    main()
