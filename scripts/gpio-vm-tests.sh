#!/usr/bin/env bash
# The tests on real kernel GPIO lines, as scripts/test.sh runs them: prepares the QEMU guest
# (scripts/gpio-vm.sh --prepare), then runs in it the GPIO backend's integration test
# (tests/integration/output_gpio_sim.rs, ignored by `cargo test`) and the node-level checks of
# the release binary (tests/gpio_vm/node_checks.py). Needs the release build (`cargo build
# --release`).
#
# The last line counts them: "gpio-vm tests: P passed, F failed, S skipped". Exit status:
#   0    all ran and passed
#   1    the preparation failed, the guest hung (killed after GPIO_VM_TIMEOUT seconds, default
#        900), it ended without a result, or a test failed or gave no result: each test that
#        did not pass is counted failed, and the reason is printed
#   120  this machine cannot run the guest at all (not Debian, or packages missing and not root
#        to install them): all counted skipped, and the reason is printed
#
# Usage: scripts/gpio-vm-tests.sh [--group untimed|timed]
#   --group untimed  the integration test and the node checks that time nothing
#                    (node_checks.py's UNTIMED), in a guest of one virtual CPU, so that it takes
#                    at most one core of this machine from whatever runs beside it
#   --group timed    the node checks that time the line, in a guest of two virtual CPUs; run
#                    with nothing beside it
#   (no group)       all of them, in one guest of two virtual CPUs
#   GPIO_VM_TIMEOUT  seconds the guest may run before it is killed as hung (default 900)
#   PWM_ACTUATOR_NODE  the node binary (default target/release/pwm_actuator_node)

set -uo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO" || exit 1
group="" cpus=2
case "${1:-}" in
    -h | --help) sed -n '2,25p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; exit 0 ;;
    "") ;;
    --group)
        group=${2:-}
        case "$group" in
            untimed) cpus=1 ;;
            timed) ;;
            *) echo "gpio-vm tests: unknown group '$group' (untimed or timed)" >&2; exit 2 ;;
        esac
        ;;
    *) echo "gpio-vm tests: unknown argument '$1' (try --help)" >&2; exit 2 ;;
esac

timeout_s=${GPIO_VM_TIMEOUT:-900}
checks=$(python3 tests/gpio_vm/node_checks.py --list ${group:+--group "$group"} | wc -l)
# The node checks, and tests/integration/output_gpio_sim.rs but in the timed group.
rust_tests=1
[[ "$group" == timed ]] && rust_tests=0
total=$((checks + rust_tests))
LOG_DIR="$REPO/target/test-logs"
mkdir -p "$LOG_DIR"
log="$LOG_DIR/gpio-vm${group:+-$group}.log"

# count PASSED FAILED SKIPPED EXIT: the last line, and the exit status.
count() {
    echo "gpio-vm tests: $1 passed, $2 failed, $3 skipped"
    exit "$4"
}

echo "---- gpio-vm prepare"
scripts/gpio-vm.sh --prepare
case $? in
    0) ;;
    120)
        echo "gpio-vm tests: SKIPPED: this machine cannot run the guest (the reason is above)"
        count 0 0 "$total" 120
        ;;
    *)
        echo "gpio-vm tests: FAILED: scripts/gpio-vm.sh --prepare failed (the reason is above)"
        count 0 "$total" 0 1
        ;;
esac

# The integration test binary (tests/integration/), of which the guest runs the module
# output_gpio_sim alone: built as scripts/test.sh builds the Rust tests (scripts/cargo-test.sh),
# so that under it this finds the binary built already.
test_bin="$(scripts/cargo-test.sh --locked --no-run --test integration --message-format=json 2>/dev/null \
    | sed -n 's/.*"executable":"\([^"]*\/deps\/integration-[^"]*\)".*/\1/p' | tail -n1)"
if [[ -z "$test_bin" ]]; then
    echo "gpio-vm tests: FAILED: cannot build or find the integration test binary"
    count 0 "$total" 0 1
fi

echo "---- gpio-vm run${group:+, $group checks} ($cpus virtual CPUs, time limit $timeout_s s)"
start=$SECONDS
scripts/gpio-vm.sh --timeout "$timeout_s" --cpus "$cpus" -- tests/gpio_vm/guest.sh "$test_bin" \
    "${PWM_ACTUATOR_NODE:-$REPO/target/release/pwm_actuator_node}" output_gpio_sim:: "$group" 2>&1 | tee "$log"
rc=${PIPESTATUS[0]}
echo "---- gpio-vm run: exit $rc ($((SECONDS - start)) s)"
# The Rust test: its libtest summary; the node checks: one PASS or FAIL line each, so those
# that ended before a hang are counted too.
read -r g_pass g_fail < <(awk '/^test result: /{for(i=1;i<=NF;i++){if($(i+1)~/^passed;?$/)p+=$i; if($(i+1)~/^failed;?$/)f+=$i}} END{print p+0, f+0}' "$log")
read -r n_pass n_fail < <(awk '/^PASS /{p++} /^FAIL /{f++} END{print p+0, f+0}' "$log")
# What reported no result counts as failed: the guest stopped under it, or it never ran.
g_missing=$((rust_tests - g_pass - g_fail)) n_missing=$((checks - n_pass - n_fail))
((g_missing < 0)) && g_missing=0
((n_missing < 0)) && n_missing=0
echo "gpio-vm: output_gpio_sim $g_pass passed, $g_fail failed; node checks $n_pass passed, $n_fail failed; $((g_missing + n_missing)) without a result"
passed=$((g_pass + n_pass))
failed=$((g_fail + g_missing + n_fail + n_missing))
case $rc in
    0) ;;
    124) echo "gpio-vm tests: FAILED: the guest hung and was killed after $timeout_s s" ;;
    125) echo "gpio-vm tests: FAILED: the guest did not run or ended without a status (the reason is above)" ;;
    *) echo "gpio-vm tests: FAILED: the guest's command exited $rc" ;;
esac
# A non-zero exit with every test passed still fails the run (one failure: the guest's).
if ((rc != 0 && failed == 0)); then
    failed=1
fi
((failed == 0)) || count "$passed" "$failed" 0 1
count "$passed" 0 0 0
