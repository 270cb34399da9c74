#!/usr/bin/env bash
# `cargo test ARGS...` as scripts/test.sh builds and runs the Rust tests (and
# scripts/gpio-vm-tests.sh the integration test binary it runs in the QEMU guest): with the
# `bench` profile of Cargo.toml, which is the release profile for every dependency and, for
# this crate, opt-level 0 with debug assertions and overflow checks. The dependencies are then
# those `cargo build --release` built (the same profile, features and intermediate directory)
# and are not compiled a second time; a plain `cargo test` compiles all of them again
# unoptimized, with debug info.
#
# The intermediate files go where the release build's go (the target directory, or
# CARGO_BUILD_BUILD_DIR if set), the final ones (this build's node binary and examples) to
# target/tests/release/, never over the release binary in target/release/. Everything else as
# `cargo test` (RUSTC_WORKSPACE_WRAPPER and CLIPPY_ARGS as set, which scripts/test.sh sets to
# build the tests with clippy's lints: see its step 2c).
#
# Usage: scripts/cargo-test.sh [CARGO_TEST_ARGS...]   e.g. --all-targets, --lib NAME, -- --ignored
#   (run from anywhere; CARGO_TARGET_DIR is honoured; PWM_FEATURES, e.g. `dds-security`, adds
#   `--features PWM_FEATURES`).

set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
target_dir="${CARGO_TARGET_DIR:-$REPO/target}"
CARGO_BUILD_BUILD_DIR="${CARGO_BUILD_BUILD_DIR:-$target_dir}" exec cargo test --profile bench \
    --target-dir "$target_dir/tests" ${PWM_FEATURES:+--features "$PWM_FEATURES"} "$@"
