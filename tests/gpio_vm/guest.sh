#!/bin/sh
# The guest side of scripts/test.sh's gpio-vm step, run inside scripts/gpio-vm.sh: the GPIO
# backend's integration test (tests/integration/output_gpio_sim.rs, built by cargo on the host)
# and the node-level checks of the release binary, both on the guest's gpio-sim chip.
#
# Usage: tests/gpio_vm/guest.sh GPIO_SIM_TEST_BINARY NODE_BINARY [TEST_FILTER [GROUP]]
#   TEST_FILTER  libtest's name filter for the binary (e.g. `output_gpio_sim::`), when the
#                binary holds other tests too ('' for none)
#   GROUP        `untimed`: the integration test and the node checks that time nothing;
#                `timed`: the node checks that time the line, alone; default both parts whole
# Exit status 0 when both passed. Each part has a time limit of its own (PART_TIMEOUT_S): a part
# that hangs is killed, said to have hung, and counted failed, and the other part still runs.
set -u
test_bin=$1 node=$2 filter=${3:-} group=${4:-}
here=$(dirname "$0")
# Each part takes under 2 minutes on an idle machine; this leaves room for a loaded one.
PART_TIMEOUT_S=420
rc=0

# part NAME COMMAND...: runs COMMAND under the time limit; says so if it hung.
part() {
    name=$1
    shift
    timeout -k 5 "$PART_TIMEOUT_S" "$@"
    status=$?
    if [ "$status" -eq 124 ] || [ "$status" -eq 137 ]; then
        echo "== $name: HUNG: killed after $PART_TIMEOUT_S s"
    fi
    [ "$status" -eq 0 ] || rc=1
}

case "$group" in
    "" | untimed | timed) ;;
    *) echo "guest.sh: unknown group '$group' (untimed or timed)"; exit 2 ;;
esac
# The integration test writes levels and reads them back: it times nothing.
if [ "$group" != timed ]; then
    echo "== tests/integration/output_gpio_sim.rs on $GPIO_SIM_CHIP"
    if [ -n "$filter" ]; then
        part output_gpio_sim "$test_bin" --ignored --test-threads=1 "$filter"
    else
        part output_gpio_sim "$test_bin" --ignored --test-threads=1
    fi
fi
echo "== node checks ($node${group:+, $group})"
if [ -n "$group" ]; then
    part "node checks" /usr/bin/python3 "$here/node_checks.py" --group "$group" "$node"
else
    part "node checks" /usr/bin/python3 "$here/node_checks.py" "$node"
fi
exit $rc
