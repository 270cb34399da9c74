#!/usr/bin/env bash
# Long-running load against the release node, for memory growth (not part of scripts/test.sh,
# which runs a 3-minute version as tests/rclpy/test_soak.py). Builds what it needs (the release
# binary; the Python environment through scripts/setup.sh), then runs scripts/soak.py: four
# channels (1 s heater, 2 s tcont_cp relay, 20 ms twincat_ba, 500 ms hold with a watchdog), an
# rclpy controller with random duties at 10 Hz and 2 Hz, enable toggles and parameter changes,
# CSV trace on. Prints the RSS slope after the warm-up (linear fit), CPU, edge counts, early
# edges and phases below the minimum; exits 1 when a bound is exceeded. See docs/memory-soak.md.
#
# Usage: scripts/soak.sh [--minutes M] [--period-ms P] [--rt-priority N]
#                        [--max-slope-kb-per-min K] [--work-dir DIR] [--json] ...
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
cargo build --release --quiet
scripts/setup.sh >/dev/null
# shellcheck source=scripts/env.sh
source scripts/env.sh
exec python scripts/soak.py "$@"
