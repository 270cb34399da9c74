#!/usr/bin/env bash
# The project's test command: sets up the ROS 2 environment (scripts/setup.sh), then checks
# formatting and lints, builds the release node, runs the Rust tests and the rclpy suite in
# tests/rclpy against the release binary with ROS 2 Jazzy's rclpy, then the suite's smoke subset
# (`pytest -m smoke`) with ROS 2 Kilted's (`scripts/setup.sh --distro kilted`). Exits non-zero if
# any step fails; the last line is a summary of all tests run ("total: N passed, N failed,
# N skipped").
#
# The GPIO tests run on real kernel GPIO lines in a QEMU guest (scripts/gpio-vm.sh, which
# installs QEMU and builds a gpio-sim module on first use). Only where this machine cannot run the
# guest at all (not Debian, or packages missing and not root) are they reported as skipped, with
# the reason; a failed preparation or a guest that hangs fails the run.
#
# What waits on the network or times nothing runs beside the compiles: the Kilted set-up and
# the GPIO guest's preparation from the start; from the release build on, the README's and docs' runnable commands (3b), the two
# long rclpy memory tests (BESIDE_TESTS below)
# and, in two pytest processes of their own, the rclpy tests marked `untimed`, each test on a ROS
# domain of its own. The rclpy tests that time what the node does run one at a time after the
# Rust tests (5), beside nothing but what is left of the untimed ones and, once those have ended,
# the GPIO guest's checks that time nothing (in a guest of one virtual CPU); the GPIO guest's
# timed checks after them, alone. Each step's time is printed, and all of them at the end,
# with when each group that ran beside the steps started and ended.
#
# Usage: scripts/test.sh [--quick] [-- PYTEST_ARGS...]
#   --quick   skip `cargo fmt --check` and `cargo clippy`
#   PYTEST_ARGS are passed to the Jazzy run of pytest (e.g. `-- -k edges -x`).

set -uo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO" || exit 1

quick=0
pytest_extra=()
while (($#)); do
    case "$1" in
        --quick) quick=1 ;;
        --) shift; pytest_extra=("$@"); break ;;
        -h | --help) awk 'NR > 1 && !/^#/ { exit } NR > 1' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "test: unknown argument '$1' (try --help)" >&2; exit 2 ;;
    esac
    shift
done

LOG_DIR="$REPO/target/test-logs"
mkdir -p "$LOG_DIR"
# Tables of figures the rclpy tests show, from both timing groups' processes, printed together at
# the end of the one that ends last (tests/rclpy/conftest.py, `show_figures`); of this run only.
export PWM_TEST_FIGURES_DIR="$LOG_DIR/figures"
rm -rf "$PWM_TEST_FIGURES_DIR"
SECONDS=0
failed_steps=()
skipped_steps=()
step_times=()
passed=0 failed=0 skipped=0

banner() { printf '\n==== %s ====\n' "$*"; }

run_step() {
    # run_step NAME COMMAND...: runs COMMAND, records NAME as failed if it exits non-zero.
    local name=$1 start=$SECONDS rc
    shift
    banner "$name"
    "$@"
    rc=$?
    if ((rc != 0)); then
        failed_steps+=("$name")
        printf -- '---- %s: FAILED (exit %d, %d s)\n' "$name" "$rc" $((SECONDS - start))
    else
        printf -- '---- %s: ok (%d s)\n' "$name" $((SECONDS - start))
    fi
    step_times+=("$(printf '%6d s  %s' $((SECONDS - start)) "$name")")
    return "$rc"
}

# Adds the counts of a pytest junit XML file to the totals; its skips also go to junit_skipped.
# No result file at all (pytest did not start) counts as one failed test, so it never looks clean.
junit_skipped=0
# shellcheck disable=SC2317  # called through beside_done too
add_junit_counts() {
    local p_tests p_fail p_err p_skip
    junit_skipped=0
    if [[ ! -f "$1" ]]; then
        failed=$((failed + 1))
        return
    fi
    read -r p_tests p_fail p_err p_skip < <(python3 - "$1" <<'EOF'
import sys
import xml.etree.ElementTree as ET

root = ET.parse(sys.argv[1]).getroot()
suites = [root] if root.tag == "testsuite" else root.findall("testsuite")
total = [sum(int(s.get(k, 0)) for s in suites) for k in ("tests", "failures", "errors", "skipped")]
print(*total)
EOF
    )
    passed=$((passed + p_tests - p_fail - p_err - p_skip))
    failed=$((failed + p_fail + p_err))
    skipped=$((skipped + p_skip))
    junit_skipped=$p_skip
}

# run_pytest_paths DISTRO JUNIT PATH... -- ARGS...: pytest over the PATHs with DISTRO's venv and
# messages (scripts/env.sh) against the release binary, results in JUNIT (counted by
# add_junit_counts). Returns pytest's status: 0 all passed, 1 some failed, 5 no test collected
# (a failure here too).
# shellcheck disable=SC2317  # called through beside_start too
run_pytest_paths() {
    local distro="$1" junit="$2" ws rc
    shift 2
    local paths=()
    while (($#)) && [[ "$1" != "--" ]]; do
        paths+=("$1")
        shift
    done
    (($#)) && shift
    ws="$REPO/.ros-ws"
    [[ "$distro" == jazzy ]] || ws="$REPO/.ros-ws-$distro"
    rm -f "$junit"
    (
        # shellcheck source=scripts/env.sh
        PWM_DISTRO="$distro" source "$REPO/scripts/env.sh"
        # ROS logs of the run stay in the checkout (git-ignored), not in ~/.ros.
        export ROS_HOME="$ws/ros_home"
        # shellcheck disable=SC2030  # the copy of 3, or the release build
        export PWM_ACTUATOR_NODE="${PWM_ACTUATOR_NODE:-$REPO/target/release/pwm_actuator_node}"
        exec python -m pytest "${paths[@]}" -v -ra --junitxml="$junit" "$@"
    ) </dev/null
    rc=$?
    if ((rc == 5)); then
        echo "test: pytest ($distro) collected no tests" >&2
    fi
    return "$rc"
}

# run_pytest DISTRO JUNIT ARGS...: run_pytest_paths over tests/rclpy less BESIDE_TESTS (3a), the
# results added to the totals.
# shellcheck disable=SC2317  # called through run_step
run_pytest() {
    local distro="$1" junit="$2" rc=0 t
    shift 2
    local ignore=()
    for t in "${BESIDE_TESTS[@]}"; do
        ignore+=("--ignore=$t")
    done
    run_pytest_paths "$distro" "$junit" tests/rclpy -- "${ignore[@]}" "$@" || rc=$?
    add_junit_counts "$junit"
    return "$rc"
}

# beside_start NAME_IN_LOGS COMMAND...: runs COMMAND beside the steps, its output in
# $LOG_DIR/NAME_IN_LOGS.log; it writes the second of the run it ended in
# $LOG_DIR/NAME_IN_LOGS.ended. Its process in beside_started_pid, for beside_done.
beside_started_pid=""
beside_start() {
    local name="$1"
    shift
    rm -f "$LOG_DIR/$name.ended"
    ("$@" >"$LOG_DIR/$name.log" 2>&1
        rc=$?
        echo "$SECONDS" >"$LOG_DIR/$name.ended"
        exit "$rc") &
    beside_started_pid=$!
}

# beside_span STARTED ENDED_FILE: "from S s to E s of the run", E the second a group beside the
# steps wrote when it ended (now, if it wrote none).
beside_span() {
    local ended
    ended=$(cat "$2" 2>/dev/null || echo "$SECONDS")
    printf 'from %d s to %d s of the run' "$1" "$ended"
}

# beside_done [--exit] [--none-selected] NAME PID STARTED NAME_IN_LOGS BANNER COUNT...: the end
# of a group that ran beside the steps, as process PID since STARTED s of the run (or the second
# it wrote in $LOG_DIR/NAME_IN_LOGS.started, when it waited before it began), its output in
# $LOG_DIR/NAME_IN_LOGS.log and the second it ended in $LOG_DIR/NAME_IN_LOGS.ended: waits for
# it, prints BANNER and its output, runs COUNT (which adds its results to the totals), then
# prints its status, its time and its span and adds them to the step times. Its exit status is
# left in beside_rc. A non-zero status fails the step NAME; with --exit the status line gives
# the exit status instead and the caller judges it. With --none-selected, a group that
# PYTEST_ARGS select nothing of (pytest exit 5) is said so, neither counted nor timed.
beside_rc=0
beside_done() {
    local exit_line=0 none_selected=0
    while [[ "$1" == --* ]]; do
        case "$1" in
            --exit) exit_line=1 ;;
            --none-selected) none_selected=1 ;;
        esac
        shift
    done
    local name="$1" pid="$2" started="$3" log="$LOG_DIR/$4.log" ended_file="$LOG_DIR/$4.ended"
    local started_file="$LOG_DIR/$4.started" banner_text="$5" ended when
    shift 5
    banner "$banner_text"
    beside_rc=0
    wait "$pid" || beside_rc=$?
    started=$(cat "$started_file" 2>/dev/null || echo "$started")
    cat "$log"
    if ((none_selected && beside_rc == 5 && ${#pytest_extra[@]})); then
        printf -- '---- %s: none selected by the pytest arguments\n' "$name"
        return
    fi
    "$@"
    ended=$(cat "$ended_file" 2>/dev/null || echo "$SECONDS")
    when="$(beside_span "$started" "$ended_file")"
    if ((exit_line)); then
        printf -- '---- %s, beside the steps: exit %d (%d s, %s)\n' "$name" "$beside_rc" \
            $((ended - started)) "$when"
    elif ((beside_rc != 0)); then
        failed_steps+=("$name")
        printf -- '---- %s: FAILED (exit %d, %d s, %s)\n' "$name" "$beside_rc" \
            $((ended - started)) "$when"
    else
        printf -- '---- %s: ok (%d s, %s)\n' "$name" $((ended - started)) "$when"
    fi
    step_times+=("$(printf '%6d s  %s (beside the steps, %s)' $((ended - started)) "$name" "$when")")
}

# 1. The ROS 2 environment. Nothing else can run without it.
if ! run_step "setup" scripts/setup.sh; then
    echo "test: setup failed; nothing was tested" >&2
    echo "total: 0 passed, 0 failed"
    exit 1
fi

# 1b. The Kilted venv waits on the package registry: it is made beside everything below and
# waited for (its output printed then) before the Kilted smoke subset.
kilted_setup_log="$LOG_DIR/setup-kilted.log"
kilted_setup_started=$SECONDS
scripts/setup.sh --distro kilted >"$kilted_setup_log" 2>&1 </dev/null &
kilted_setup_pid=$!

# 1c. Beside everything below too: the QEMU guest's preparation (the kernel package, the
# gpio-sim module, the initramfs; scripts/gpio-vm.sh --prepare), which waits on the package
# registry, so that the GPIO step (5a) finds it made. Its outcome is not counted here: that
# step prepares again (at once from what this one made) and reports any failure with its reason.
gpio_prepare_log="$LOG_DIR/gpio-vm-prepare.log"
scripts/gpio-vm.sh --prepare >"$gpio_prepare_log" 2>&1 </dev/null &
gpio_prepare_pid=$!

# 2. Static checks.
if ((quick)); then
    skipped_steps+=("cargo fmt" "cargo clippy")
else
    run_step "cargo fmt" cargo fmt --all --check
fi

# 2b. The layers: no import cycle among the files of src/, no layer of the ROS shell importing
# one after it (scripts/check-layers.py). One check.
if run_step "layers" python3 scripts/check-layers.py; then
    passed=$((passed + 1))
else
    failed=$((failed + 1))
fi

# 3. The release binary the rclpy suite runs.
release_ok=1
# The default features: one binary that runs on DDS or, with RMW_IMPLEMENTATION=rmw_zenoh_cpp,
# on Zenoh (the `zenoh` feature; tests/rclpy/test_zenoh.py).
run_step "cargo build --release" cargo build --release --bins --locked || release_ok=0
# Every test below runs this build's binary from a copy: the docs' commands (3b), run beside
# the tests, build target/release/ again as the docs say.
if ((release_ok)); then
    mkdir -p "$REPO/target/test-bin"
    cp "$REPO/target/release/pwm_actuator_node" "$REPO/target/test-bin/pwm_actuator_node"
    # shellcheck disable=SC2031  # run_pytest_paths's subshell only reads it
    export PWM_ACTUATOR_NODE="$REPO/target/test-bin/pwm_actuator_node"
fi

# 3a. The two long rclpy tests that time no edge — memory under a 3-minute soak and after a
# storm of 1,000 short-lived participants (they check that no edge is early and no phase short,
# which load cannot excuse) — run from here beside clippy and the Rust tests, with PYTEST_ARGS;
# the rest of the suite runs without them. Their results are added when waited for (4a'').
# Beside them from here, in two more pytest processes: the rest of the suite's tests marked
# `untimed`, which time nothing the node does and bound only seconds with a second or a factor
# of two to spare, so that no load beside them can change their result (tests/rclpy/pytest.ini),
# with PYTEST_ARGS; waited for, their results added, after the timed ones (5). Part 2 runs the
# untimed tests of UNTIMED_PART2 (the longest ones, most of their time spent waiting on simulated
# plants and fresh processes: about half of the group's time), part 1 those of the rest of the
# suite. All three need setup's venv and messages (1) and the release binary (3), and all end
# before the GPIO guest starts (5-).
BESIDE_TESTS=(tests/rclpy/test_soak.py tests/rclpy/test_participant_storm.py)
UNTIMED_PART2=(tests/rclpy/test_fresh_clients.py tests/rclpy/test_trace_files.py
    tests/rclpy/test_heater_mpc.py tests/rclpy/test_valve_loop.py)
beside_ignore=()
for t in "${BESIDE_TESTS[@]}"; do
    beside_ignore+=("--ignore=$t")
done
part2_ignore=()
for t in "${UNTIMED_PART2[@]}"; do
    part2_ignore+=("--ignore=$t")
done
beside_pid="" untimed_pids=()
if ((release_ok)); then
    beside_started=$SECONDS
    beside_start rclpy-beside run_pytest_paths jazzy "$LOG_DIR/rclpy-beside-junit.xml" \
        "${BESIDE_TESTS[@]}" -- "${pytest_extra[@]}"
    beside_pid=$beside_started_pid
    untimed_started=$SECONDS
    for part in 1 2; do
        if ((part == 1)); then
            part_paths=(tests/rclpy -- "${beside_ignore[@]}" "${part2_ignore[@]}")
        else
            part_paths=("${UNTIMED_PART2[@]}" --)
        fi
        beside_start "rclpy-untimed-$part" run_pytest_paths jazzy \
            "$LOG_DIR/rclpy-untimed-$part-junit.xml" "${part_paths[@]}" --timing-group=untimed \
            "${pytest_extra[@]}"
        untimed_pids+=("$beside_started_pid")
    done
fi

# 3b. The shell blocks of README.md and docs/*.md marked runnable here
# (scripts/check-doc-commands.py): each must exit 0; the others are listed with the reason they
# cannot run here (hardware, the ros2 command line, runs of minutes) and counted as skipped.
# Only their exit status counts, and they spend most of their time asleep (one is a benchmark
# run of a minute whose figures nobody reads here), so they run beside clippy and the Rust
# tests from the release build on; waited for, their output printed, after the Rust tests.
doc_pid=""
if ((release_ok)); then
    doc_started=$SECONDS
    beside_start doc-commands python3 scripts/check-doc-commands.py
    doc_pid=$beside_started_pid
else
    failed=$((failed + 1))
    failed_steps+=("doc commands (no release build)")
fi

# 2c. Clippy's lints, `cargo clippy --all-targets -- -D warnings`, not in a build of their own:
# clippy's driver, as `cargo clippy` sets it (RUSTC_WORKSPACE_WRAPPER, CLIPPY_ARGS), compiles
# this crate's targets in the build of the Rust tests (4), so that every target `--all-targets`
# names is linted as it is compiled. `cargo clippy` checks every dependency once more in a mode
# of its own that no other step can use (110 CPU-s on the VM, nearly all of it the
# dependencies); here the dependencies are the release build's (scripts/cargo-test.sh), and the
# lints add 4 CPU-s to the tests' build (55 CPU-s with them). A warning fails this step as it
# fails `cargo clippy`; the tests are then built again without the lints (lint_env emptied), so
# that they all still run. lint_env is the environment of every build of the Rust tests below
# (4, 4a', 5a): the same for all, so that none compiles this crate again. The driver's builds
# differ from rustc's only in the lints and in running no MIR optimizations (nor the alignment
# and null checks of raw pointers that debug assertions add) on this crate's code.
lint_env=()
if ((!quick)); then
    lint_env=(RUSTC_WORKSPACE_WRAPPER="$(rustc --print sysroot)/bin/clippy-driver"
        CLIPPY_ARGS="-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__")
    run_step "cargo clippy" env "${lint_env[@]}" scripts/cargo-test.sh --all-targets --locked \
        --no-run || lint_env=()
fi

# 4. Rust tests, every test binary even after a failure, built by scripts/cargo-test.sh (the
# release build's dependencies; this crate with debug assertions and overflow checks); at 2c
# already, unless clippy failed or was skipped. The full output goes to the console and to a
# log; the per-binary result lines are counted afterwards.
# shellcheck disable=SC2317  # called through run_step
cargo_tests() {
    env "${lint_env[@]}" scripts/cargo-test.sh --all-targets --no-fail-fast --locked 2>&1 |
        tee "$LOG_DIR/cargo-test.log"
}
run_step "cargo test" cargo_tests
cargo_counts="$(awk '
    /^test result: / {
        for (i = 1; i <= NF; i++) {
            if ($(i + 1) ~ /^passed;?$/) p += $i
            if ($(i + 1) ~ /^failed;?$/) f += $i
            if ($(i + 1) ~ /^ignored;?$/) s += $i
        }
        n++
    }
    END { printf "%d %d %d %d", p, f, s, n }' "$LOG_DIR/cargo-test.log")"
read -r c_pass c_fail c_skip c_bins <<<"$cargo_counts"
printf 'cargo test: %d passed, %d failed, %d ignored in %d test binaries\n' \
    "$c_pass" "$c_fail" "$c_skip" "$c_bins"
grep '^test result: ' "$LOG_DIR/cargo-test.log" | sed 's/^/  /'
passed=$((passed + c_pass)) failed=$((failed + c_fail)) skipped=$((skipped + c_skip))

# 3b'. The doc commands started at 3b: their output, their time and their results.
# shellcheck disable=SC2317  # called through beside_done
doc_counts() {
    local d_pass d_fail d_skip
    read -r d_pass d_fail d_skip < <(sed -n 's/^doc commands: \([0-9]*\) passed, \([0-9]*\) failed, \([0-9]*\) not runnable here$/\1 \2 \3/p' \
        "$LOG_DIR/doc-commands.log" | tail -n1 | grep . || echo "0 1 0")
    passed=$((passed + d_pass)) failed=$((failed + d_fail)) skipped=$((skipped + d_skip))
}
if [[ -n "$doc_pid" ]]; then
    beside_done "doc commands" "$doc_pid" "$doc_started" doc-commands \
        "doc commands (beside the steps since 3b)" doc_counts
fi

# 4a. The vendored rustdds's patch (vendor/rustdds/README.pwm_actuator.md): the unit tests of
# its changes. The crate is a path dependency, not a member of this package, so `cargo test`
# above does not run them; its own other tests are upstream's and are not counted here.
# A target directory of its own, because it shares little with the node's test build anyway:
# its dev-dependencies and the node's dependencies enable different features of the crates both
# use (proc-macro2, syn, log, futures-core, nix, rustix, ...), so that build's artifacts do not
# fit it. Even as a workspace member, with one Cargo.lock and in the same target directory, it
# compiled 118 of its 175 crates again (47 of them crates the node's build has, with other
# features) and took 62 s instead of 71 s; a member would also be formatted by `cargo fmt
# --all`, which would rewrite the upstream files. Not beside the steps either: run from the
# start beside the release build, its compile took cores that build needed (252 s instead of
# 145 s), and the timed rclpy tests started 89 s later. Without debug info and incremental
# files, which only a debugger would use: 86 CPU-s to compile instead of 100.
# shellcheck disable=SC2317  # called through run_step
# The vendored tests bind the well-known ports of the domains they use and take none of the
# lock files the other suites share (1..48, tests/rclpy/conftest.py), so they get domains of
# their own: 49..101 (RUSTDDS_TEST_DOMAIN_ID is the base, their largest offset 52). With their
# default, 0..52, one of them found its port taken by an rclpy test's participant.
vendor_tests() {
    RUSTDDS_TEST_DOMAIN_ID=49 CARGO_PROFILE_TEST_DEBUG=false CARGO_INCREMENTAL=0 \
        cargo test --lib --locked --manifest-path vendor/rustdds/Cargo.toml \
        --target-dir "$REPO/target/vendor-rustdds" -- \
        data_frag::tests::inline_qos_ reader_asks_for_samples_sent_before_the_writer_was_matched \
        reply_written_before_its_reader_matched_goes_to_it_on_match cache_cleaning_ acknowledged_samples_beyond_depth_go_on_insert \
        reply_outlives_the_history_depth_until_its_reader_matches held_reply_ \
        unanswered_nack_is_repeated_until_the_samples_come \
        endpoints_announce_their_user_data_in_sedp gone_participants_and_endpoints_leave_nothing_behind \
        a_participant_back_within_its_attic_time_gets_its_endpoints_back \
        samples_of_a_lost_participant_leave_built_in_topic_caches \
        gone_writers_and_forgotten_instances_leave_the_read_state \
        spdp_announcements_go_to_static_peers \
        without_multicast_discovery_no_multicast_locator_is_announced \
        events_set_on_the_grid_at_different_times_fall_due_together \
        a_reader_behind_that_cannot_be_reached_gets_no_fast_heartbeat \
        the_loops_periodic_events_fall_due_on_the_heartbeat_grid \
        periodic_discovery_tasks_fall_due_together_on_the_grid \
        rings_under_a_hold_wake_the_loop_once_when_it_ends a_hold_delivers_after_its_bounds \
        a_sample_nobody_is_matched_to_does_not_wake_the_event_loop \
        signals_to_the_event_loops_leave_them_running 2>&1 |
        tee "$LOG_DIR/vendor-test.log"
    return "${PIPESTATUS[0]}"
}
run_step "rustdds patch tests" vendor_tests
read -r v_pass v_fail < <(awk '/^test result: /{for(i=1;i<=NF;i++){if($(i+1)~/^passed;?$/)p+=$i; if($(i+1)~/^failed;?$/)f+=$i}} END{print p+0, f+0}' "$LOG_DIR/vendor-test.log")
printf 'rustdds patch tests: %d passed, %d failed\n' "$v_pass" "$v_fail"
passed=$((passed + v_pass)) failed=$((failed + v_fail))

# 4a'. The type hashes the node computes against the .json files rosidl wrote
# (tests/integration/type_hashes.rs): ignored by `cargo test` above, which must not need the venv,
# and counted as skipped there; run here, after setup made the venv.
# shellcheck disable=SC2317  # called through run_step
type_hash_tests() {
    env "${lint_env[@]}" scripts/cargo-test.sh --locked --test integration -- --ignored \
        type_hashes:: 2>&1 | tee "$LOG_DIR/type-hashes.log"
    return "${PIPESTATUS[0]}"
}
run_step "type hashes against rosidl" type_hash_tests
read -r t_pass t_fail < <(awk '/^test result: /{for(i=1;i<=NF;i++){if($(i+1)~/^passed;?$/)p+=$i; if($(i+1)~/^failed;?$/)f+=$i}} END{print p+0, f+0}' "$LOG_DIR/type-hashes.log")
((t_pass + t_fail == 0)) && t_fail=1 # it did not run: count it as failed
printf 'type hashes against rosidl: %d passed, %d failed\n' "$t_pass" "$t_fail"
passed=$((passed + t_pass)) failed=$((failed + t_fail))
skipped=$((skipped - 1)) # the ignored type_hashes test, counted above

# 4b. The DDS-only build (`--no-default-features`, documented in docs/deployment.md): every
# target compiled with clippy's lints, none run (their DDS behaviour is the default build's,
# tested above). It compiles again the dependencies whose features differ without Zenoh (tokio
# without `test-util` and what is built on it, the TLS and RSA crates of the tests): about 80 s
# on the critical path, 140 CPU-s. The intermediate files are the release build's as in 4; the
# final ones go to target/dds-only/, never over the test binaries the GPIO guest runs (5a).
# shellcheck disable=SC2317  # called through run_step
dds_only_build() {
    local target="${CARGO_TARGET_DIR:-$REPO/target}"
    CARGO_BUILD_BUILD_DIR="${CARGO_BUILD_BUILD_DIR:-$target}" CARGO_TARGET_DIR="$target/dds-only" \
        env "${lint_env[@]}" \
        scripts/cargo-test.sh --no-default-features --all-targets --locked --no-run
}
if ((quick)); then
    skipped_steps+=("cargo clippy, DDS only")
else
    run_step "cargo clippy, DDS only" dds_only_build
fi

# 4a''. The rclpy memory tests started at 3a, waited for before the timed rclpy tests (5) and the
# GPIO guest (5a), whose sampler is timed: their output, their time and their results. With
# PYTEST_ARGS that select none of them (pytest exit 5) nothing is counted.
if [[ -n "$beside_pid" ]]; then
    beside_done --none-selected "rclpy memory tests" "$beside_pid" "$beside_started" rclpy-beside \
        "rclpy memory tests (beside the compiles since 3a)" \
        add_junit_counts "$LOG_DIR/rclpy-beside-junit.xml"
fi

# 4c. The systemd unit in launch-notes/: `systemd-analyze verify` with the binary paths pointed
# at the release build (/usr/local/bin is not installed here). One check; skipped, with the
# reason, where systemd-analyze is missing.
# shellcheck disable=SC2317  # called through run_step
verify_unit() {
    local dir rc
    dir="$(mktemp -d)"
    sed "s#/usr/local/bin/pwm_actuator_node#$REPO/target/release/pwm_actuator_node#g" \
        launch-notes/pwm_actuator.service >"$dir/pwm_actuator.service"
    systemd-analyze verify "$dir/pwm_actuator.service" 2>&1 | tee "$LOG_DIR/unit-verify.log"
    rc=${PIPESTATUS[0]}
    # verify prints warnings without failing; any output is a finding.
    if ((rc == 0)) && [[ -s "$LOG_DIR/unit-verify.log" ]]; then
        rc=1
    fi
    rm -rf "$dir"
    return "$rc"
}
if ! command -v systemd-analyze >/dev/null; then
    echo "unit verify: SKIPPED (no systemd-analyze)"
    skipped=$((skipped + 1))
    skipped_steps+=("unit verify (no systemd-analyze)")
elif ((!release_ok)); then
    skipped=$((skipped + 1))
    skipped_steps+=("unit verify (no release build)")
elif run_step "unit verify" verify_unit; then
    passed=$((passed + 1))
else
    failed=$((failed + 1))
fi

# 5. The rest of the rclpy suite (less BESIDE_TESTS and the untimed tests, which run beside the
# steps since 3a), with the venv's python and the built messages: the tests that time what the
# node does, one at a time as ever (`--timing-group timed`), beside nothing but what is left of
# the untimed ones; then the two parts of the untimed ones are waited for, their output printed.
# Each pytest process has its own results file, and all are counted; the step fails if any of
# them fails or leaves no results file. A process that PYTEST_ARGS select nothing of (pytest
# exit 5) is not a failure while another one ran tests; all selecting nothing is.
# shellcheck disable=SC2317  # called through run_step
rclpy_suite() {
    local start=$SECONDS timed_end part any_ran=0 ok=1 rc
    local rcs=()
    if ((${#untimed_pids[@]})); then
        echo "rclpy tests: the untimed ones run beside these since $untimed_started s, in two parts (output in rclpy-untimed-1.log and -2.log, printed below)"
    fi
    rc=0
    run_pytest_paths jazzy "$LOG_DIR/rclpy-junit.xml" tests/rclpy -- "${beside_ignore[@]}" \
        --timing-group=timed "${pytest_extra[@]}" || rc=$?
    timed_end=$SECONDS
    rcs+=("$rc")
    add_junit_counts "$LOG_DIR/rclpy-junit.xml"
    printf -- '---- rclpy tests, timed, one at a time: exit %d (%d s, from %d s to %d s of the run)\n' \
        "$rc" $((timed_end - start)) "$start" "$timed_end"
    step_times+=("$(printf '%6d s  %s' $((timed_end - start)) \
        "rclpy tests, timed (one at a time, from $start s to $timed_end s of the run)")")
    for part in 1 2; do
        beside_done --exit "rclpy tests, untimed, part $part" "${untimed_pids[part - 1]}" \
            "$untimed_started" "rclpy-untimed-$part" \
            "rclpy tests: the untimed ones, part $part (beside the steps since the release build)" \
            add_junit_counts "$LOG_DIR/rclpy-untimed-$part-junit.xml"
        rcs+=("$beside_rc")
    done
    for rc in "${rcs[@]}"; do
        ((rc != 5)) && any_ran=1
    done
    for rc in "${rcs[@]}"; do
        # With PYTEST_ARGS, a process they select nothing of is no failure while another ran.
        if ((rc == 5 && ${#pytest_extra[@]} && any_ran)); then
            continue
        fi
        ((rc == 0)) || ok=0
    done
    ((ok))
}
# 5-. Beside what is left of the timed rclpy tests once both untimed parts have ended: the GPIO
# guest's checks that time nothing (scripts/gpio-vm-tests.sh --group untimed: levels, exit
# statuses, log lines; node_checks.py's UNTIMED), in a guest of one virtual CPU, so that it
# takes at most one core, the load of one untimed part. Waited for, its output printed and its
# results counted, in 5a, before the guest's timed checks.
# shellcheck disable=SC2317  # called through beside_start
gpio_untimed_after_the_untimed_rclpy() {
    local part
    for part in 1 2; do
        while [[ ! -e "$LOG_DIR/rclpy-untimed-$part.ended" ]]; do
            kill -0 "$$" 2>/dev/null || return 1 # the run was stopped
            sleep 1
        done
    done
    # The preparation started at 1c (its apt-get must not meet another one).
    while kill -0 "$gpio_prepare_pid" 2>/dev/null; do
        sleep 1
    done
    echo "$SECONDS" >"$LOG_DIR/gpio-vm-tests-untimed.started"
    env "${lint_env[@]}" scripts/gpio-vm-tests.sh --group untimed
}
gpio_untimed_pid=""
if ((release_ok)); then
    rm -f "$LOG_DIR/gpio-vm-tests-untimed.started"
    beside_start gpio-vm-tests-untimed gpio_untimed_after_the_untimed_rclpy
    gpio_untimed_pid=$beside_started_pid
    run_step "rclpy tests" rclpy_suite
else
    skipped_steps+=("rclpy tests (no release build)")
    failed_steps+=("rclpy tests")
fi

# 5a. Real kernel GPIO lines, in a QEMU guest with a gpio-sim chip: the GPIO backend's
# integration test (ignored by `cargo test` above, counted as skipped there) and the node-level
# checks of the release binary in tests/gpio_vm/, by scripts/gpio-vm-tests.sh, in two groups:
# the untimed ones, started at 5- beside the timed rclpy tests, waited for here; then the timed
# ones (the line's duty, period and on times, heartbeats, how soon a switch stops a drive),
# after everything else, so that nothing runs beside the guest's timed sampler. Counted as
# passed only when they ran and passed. They count as skipped only where this machine cannot
# run the guest at all (not Debian, or packages missing and not root to install them), with the
# reason; a preparation that fails, a guest that hangs (killed after GPIO_VM_TIMEOUT seconds,
# default 900) or one that ends without a result fails them, with the reason.
# gpio_vm_count NAME LOG STATUS TOTAL: adds the counts of scripts/gpio-vm-tests.sh's last line
# in LOG (TOTAL failed if it printed none) to the totals, and NAME to the failed or skipped
# steps by its exit STATUS.
gpio_vm_count() {
    local name="$1" log="$2" rc="$3" total="$4" p f k
    read -r p f k < <(sed -n 's/^gpio-vm tests: \([0-9]*\) passed, \([0-9]*\) failed, \([0-9]*\) skipped$/\1 \2 \3/p' \
        "$log" | tail -n1 | grep . || echo "0 $total 0")
    case $rc in
        0) ;;
        120) skipped_steps+=("$name (this machine cannot run the guest: see above)") ;;
        *) failed_steps+=("$name") ;;
    esac
    # A run that failed without saying what counts one failure at least.
    ((rc != 0 && rc != 120 && f == 0)) && f=1
    passed=$((passed + p)) failed=$((failed + f)) skipped=$((skipped + k))
}
# gpio_untimed_count: gpio_vm_count of the untimed group, by beside_done's status.
# shellcheck disable=SC2317  # called through beside_done
gpio_untimed_count() {
    gpio_vm_count "gpio-vm tests, untimed" "$LOG_DIR/gpio-vm-tests-untimed.log" "$beside_rc" \
        "$vm_untimed_total"
}
vm_total=$(($(python3 tests/gpio_vm/node_checks.py --list | wc -l) + 1))
vm_untimed_total=$(($(python3 tests/gpio_vm/node_checks.py --list --group untimed | wc -l) + 1))
if ((!release_ok)); then
    echo "gpio-vm tests: FAILED (no release build): $vm_total tests did not run"
    failed=$((failed + vm_total))
    failed_steps+=("gpio-vm tests (no release build)")
else
    beside_done --exit "gpio-vm tests, untimed (one virtual CPU)" "$gpio_untimed_pid" \
        "$SECONDS" gpio-vm-tests-untimed "gpio-vm tests, untimed (beside the timed rclpy tests)" \
        gpio_untimed_count

    wait "$gpio_prepare_pid" 2>/dev/null || true
    banner "gpio-vm tests, timed"
    echo "gpio-vm: prepared beside the steps since 1c (output in gpio-vm-prepare.log):"
    tail -n 3 "$gpio_prepare_log"
    vm_start=$SECONDS
    env "${lint_env[@]}" scripts/gpio-vm-tests.sh --group timed 2>&1 |
        tee "$LOG_DIR/gpio-vm-tests-timed.log"
    vm_rc=${PIPESTATUS[0]}
    printf -- '---- gpio-vm tests, timed: exit %d (%d s)\n' "$vm_rc" $((SECONDS - vm_start))
    step_times+=("$(printf '%6d s  %s' $((SECONDS - vm_start)) "gpio-vm tests, timed (alone)")")
    gpio_vm_count "gpio-vm tests, timed" "$LOG_DIR/gpio-vm-tests-timed.log" "$vm_rc" \
        $((vm_total - vm_untimed_total))
fi
skipped=$((skipped - 1)) # the ignored output_gpio_sim test, counted above

# 5b. ROS 2 Kilted: the smoke subset of the rclpy suite (`pytest -m smoke`: a duty command's
# edges, the parameter services and /parameter_events, diagnostics, the lifecycle, the node in
# the graph) with Kilted's rclpy from .venv-kilted/ (scripts/setup.sh --distro kilted) against
# the same release binary. PYTEST_ARGS are not passed: the subset always runs whole. A setup
# that fails counts as a failed step and a failed test, never as skipped; so does a smoke test
# that skips, since none of them has a reason to.
# The Kilted set-up started at 1b: waited for, its output printed, its status returned.
# shellcheck disable=SC2317  # called through run_step
kilted_setup_wait() {
    local rc=0
    wait "$kilted_setup_pid" || rc=$?
    cat "$kilted_setup_log"
    echo "setup (kilted): started at 1b, $((SECONDS - kilted_setup_started)) s ago"
    return "$rc"
}
# shellcheck disable=SC2317  # called through run_step
kilted_smoke() {
    local rc=0
    run_pytest kilted "$LOG_DIR/rclpy-kilted-junit.xml" -m smoke || rc=$?
    if ((junit_skipped && rc == 0)); then
        echo "test: $junit_skipped Kilted smoke test(s) skipped; they must run" >&2
        rc=1
    fi
    return "$rc"
}
if ((!release_ok)); then
    skipped_steps+=("rclpy smoke (kilted) (no release build)")
    failed_steps+=("rclpy smoke (kilted)")
elif ! run_step "setup (kilted)" kilted_setup_wait; then
    echo "test: setup --distro kilted failed; the Kilted smoke subset did not run" >&2
    failed=$((failed + 1))
else
    run_step "rclpy smoke (kilted)" kilted_smoke
fi

# The Kilted set-up, if no step above waited for it (no release build): not left running.
wait "$kilted_setup_pid" 2>/dev/null || true

banner "summary"
printf 'step times:\n'
printf '  %s\n' "${step_times[@]}"
printf 'time: %d s\n' "$SECONDS"
((${#skipped_steps[@]})) && printf 'skipped: %s\n' "${skipped_steps[*]}"
status=0
if ((${#failed_steps[@]})); then
    joined="$(printf '%s, ' "${failed_steps[@]}")"
    printf 'FAILED steps: %s\n' "${joined%, }"
    status=1
fi
if ((passed == 0)); then
    echo "no test passed"
    status=1
fi
printf 'total: %d passed, %d failed, %d skipped\n' "$passed" "$failed" "$skipped"
exit "$status"
