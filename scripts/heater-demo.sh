#!/usr/bin/env bash
# The heater loop without hardware: starts pwm_actuator_node with pw01 under pid on a simulated
# output, and the simulated heater (`pwm_actuator_node sim-heater`, its own process and ROS
# participant) driven by pw01's edges; the simulated heater also sends the setpoint. Prints the
# temperature and the line's share of on time every 10 s while the loop settles, then stops both.
#
# Usage: scripts/heater-demo.sh [SECONDS] [SETPOINT_C]      (defaults: 200 s, 80 °C)
# Needs the release build (cargo build --release). Uses ROS_DOMAIN_ID (default 0) and keeps
# discovery on this machine unless ROS_AUTOMATIC_DISCOVERY_RANGE says otherwise.

set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
NODE="${PWM_ACTUATOR_NODE:-$REPO/target/release/pwm_actuator_node}"
SECONDS_TO_RUN="${1:-200}"
SETPOINT="${2:-80}"
[ -x "$NODE" ] || { echo "heater-demo: $NODE not found: run cargo build --release" >&2; exit 2; }
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
LOG="$(mktemp -d)"
# The plant: 2 °C/s at full power, 60 s time constant, 2 s dead time (docs/heater.md);
# the gains: SIMC for it, kp = tau / (K * 2 L) = 12.5 %/°C, TI = 8 L = 16 s.
"$NODE" --output sim --ros-args \
    -p pw01.feedback_topic:=/heater/temperature -p pw01.control:=pid \
    -p pw01.pid_kp:=12.5 -p pw01.pid_ki:=0.78 -p pw01.temp_min_c:=0.0 -p pw01.temp_max_c:=250.0 \
    -p pw01.feedback_timeout_ms:=5000 -p pw01.stuck_on_rise_c:=8.0 -p pw01.enable:=true \
    >"$LOG/node.log" 2>&1 &
node_pid=$!
trap 'kill "$node_pid" 2>/dev/null; wait "$node_pid" 2>/dev/null || true' EXIT
echo "heater-demo: node started (log $LOG/node.log); simulated heater, setpoint $SETPOINT °C, $SECONDS_TO_RUN s"
"$NODE" sim-heater --setpoint "$SETPOINT" --print-every 10 --duration "$SECONDS_TO_RUN" 2>"$LOG/sim.log"
grep -E "heater fault|refused" "$LOG/node.log" || true
