#!/usr/bin/env bash
# Bounded, repeatable fuzz and load run against the release node (not part of scripts/test.sh:
# it takes about a minute and a half and loads the machine). Builds what it needs (the release
# binary; the Python environment through scripts/setup.sh), then runs scripts/stress.py:
# malformed CDR on every input topic, parameter extremes, a command flood with a slow
# subscriber. Prints inputs sent, crashes, RSS at start and end, CPU, edges, early edges and
# phases below the minimum; exits 1 if crashes, early edges or short phases are not 0.
#
# Usage: scripts/stress.sh [--seed N] [--malformed-rounds N] [--flood-seconds S] [--json]
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
cargo build --release --quiet
scripts/setup.sh >/dev/null
# shellcheck source=scripts/env.sh
source scripts/env.sh
exec python scripts/stress.py "$@"
