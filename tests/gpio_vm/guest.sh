#!/bin/sh
# The guest side of scripts/test.sh's gpio-vm step, run inside scripts/gpio-vm.sh: the GPIO
# backend's integration test (tests/output_gpio_sim.rs, built by cargo on the host) and the
# node-level checks of the release binary, both on the guest's gpio-sim chip.
#
# Usage: tests/gpio_vm/guest.sh GPIO_SIM_TEST_BINARY NODE_BINARY
# Exit status 0 when both passed.
set -u
test_bin=$1 node=$2
here=$(dirname "$0")
rc=0
echo "== tests/output_gpio_sim.rs on $GPIO_SIM_CHIP"
"$test_bin" --ignored --test-threads=1 || rc=1
echo "== node checks ($node)"
/usr/bin/python3 "$here/node_checks.py" "$node" || rc=1
exit $rc
