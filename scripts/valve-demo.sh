#!/usr/bin/env bash
# The valve's own loop without hardware: starts pwm_actuator_node with a three-point valve `mix`
# (pw01 opens, pw02 closes) under control pid on a simulated output, and the simulated valve
# with its mixing plant (`pwm_actuator_node sim-valve --mix`, its own process and ROS
# participant) driven by the two lines' edges; the simulator also sends the setpoint and drops
# the hot supply by 10 K halfway. Prints the mixed water's temperature, the valve's true
# position and the hot supply every 5 s, then stops both.
#
# Usage: scripts/valve-demo.sh [SECONDS] [SETPOINT_C]      (defaults: 150 s, 45 °C)
# With VALVE_DEMO_RECORD=FILE.csv the simulator records its run there (scripts/valve_loop_plot.py
# draws docs/valve-loop.png from it).
# Needs the release build (cargo build --release). Uses ROS_DOMAIN_ID (default 0) and keeps
# discovery on this machine unless ROS_AUTOMATIC_DISCOVERY_RANGE says otherwise.

set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
NODE="${PWM_ACTUATOR_NODE:-$REPO/target/release/pwm_actuator_node}"
SECONDS_TO_RUN="${1:-150}"
SETPOINT="${2:-45}"
[ -x "$NODE" ] || { echo "valve-demo: $NODE not found: run cargo build --release" >&2; exit 2; }
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
LOG="$(mktemp -d)"
# The plant, scaled to show in minutes: supplies 70 and 15 °C (gain 0.55 K per % of the stroke),
# 20 s time constant, 3 s dead time, ±0.5 K noise; the actuator travels in 20 s. The gains: SIMC
# with the closed-loop time constant of one dead time (docs/valve.md), kp = tau / (K * 2 L) =
# 6.06 %/K, TI = min(tau, 8 L) = 20 s, ki = kp / TI = 0.303 %/(K·s). No position feedback: the
# loop runs in step mode, so the valve needs no reference stroke.
"$NODE" --output sim --ros-args -p channels:=2 -p valve:=mix:pw01:pw02 \
    -p mix.travel_open_ms:=20000 -p mix.travel_close_ms:=20000 -p mix.reference_at_start:=none \
    -p mix.recalibrate_after_s:=0 -p mix.max_uncertainty_pct:=100.0 \
    -p mix.control:=pid -p mix.process_topic:=/mixing/temperature \
    -p mix.pid_kp:=6.06 -p mix.pid_ki:=0.303 -p mix.pid_sample_ms:=500 \
    >"$LOG/node.log" 2>&1 &
node_pid=$!
trap 'kill "$node_pid" 2>/dev/null; wait "$node_pid" 2>/dev/null || true' EXIT
echo "valve-demo: node started (log $LOG/node.log); mixing plant, setpoint $SETPOINT °C, hot supply 70 → 60 °C at $((SECONDS_TO_RUN * 3 / 5)) s, $SECONDS_TO_RUN s"
"$NODE" sim-valve --travel-open-ms 20000 --travel-close-ms 20000 --start-pct 30 \
    --mix --tau 20 --dead-time 3 --noise 0.5 --hot 70 --cold 15 \
    --hot-step-to 60 --hot-step-after $((SECONDS_TO_RUN * 3 / 5)) \
    --setpoint "$SETPOINT" --print-every 5 --duration "$SECONDS_TO_RUN" \
    ${VALVE_DEMO_RECORD:+--record "$VALVE_DEMO_RECORD"} 2>"$LOG/sim.log"
grep -E "refused|fault|ERROR" "$LOG/node.log" || true
