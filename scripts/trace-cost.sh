#!/usr/bin/env bash
# What a CSV and an MCAP trace cost the node, beside the same run without a trace
# (scripts/trace-cost.py; docs/safety.md#mcap-traces). Builds the release binary first.
#
# Usage: scripts/trace-cost.sh [--seconds S] [--warmup S]
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
cargo build --release --quiet
exec python3 scripts/trace-cost.py "$@"
