#!/usr/bin/env bash
# What the node costs while nothing much happens, against an rclpy node doing the same
# publishing, in one run (see docs/benchmark.md#idle-cost). Builds what it needs (the release
# binary; the Python environment through scripts/setup.sh), then runs scripts/idle-cost.py:
# pwm_actuator_node with 2 channels of 1 s at 37 % and 50 % (defaults otherwise) and
# scripts/idle_reference.py side by side, LOCALHOST discovery; prints each one's CPU in % of one
# core, RSS, and per thread its CPU and wake-ups per second.
#
# Usage: scripts/idle-cost.sh [--seconds S] [--warmup S] [--json] [--check] ...
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
cargo build --release --quiet
scripts/setup.sh >/dev/null
# shellcheck source=scripts/env.sh
source scripts/env.sh
exec python scripts/idle-cost.py "$@"
