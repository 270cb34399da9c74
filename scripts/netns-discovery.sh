#!/usr/bin/env bash
# Shows what ROS_AUTOMATIC_DISCOVERY_RANGE does from the point of view of another machine: two
# network namespaces made for the run ("host A" runs the node, "host B" an rclpy listener with
# the default range), joined by a veth pair on 10.231.0.0/24. For each range the node runs with,
# it prints whether an rclpy listener on host B and one on host A itself hear the node's
# /diagnostics, and the node's UDP sockets. Expected: SUBNET heard from both; LOCALHOST from A
# only, sockets on `%lo`; OFF from neither.
#
# Needs root (network namespaces) and a built release binary and scripts/setup.sh's venv; not
# part of scripts/test.sh. Everything it creates is removed on exit. Usage: scripts/netns-discovery.sh
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
NODE="$REPO/target/release/pwm_actuator_node"
if [ "$(id -u)" != 0 ]; then
    echo "netns-discovery: needs root to create network namespaces; skipped"
    exit 0
fi
[ -x "$NODE" ] || { echo "netns-discovery: build the release binary first (cargo build --release)" >&2; exit 1; }
# shellcheck source=scripts/env.sh
source "$REPO/scripts/env.sh"

A="pwmdisc-a-$$"
B="pwmdisc-b-$$"
VA="pwva$$"
VB="pwvb$$"
node_pid=""
cleanup() {
    [ -n "$node_pid" ] && kill -INT "$node_pid" 2>/dev/null && wait "$node_pid" 2>/dev/null || true
    ip netns del "$A" 2>/dev/null || true
    ip netns del "$B" 2>/dev/null || true
}
trap cleanup EXIT

ip netns add "$A"
ip netns add "$B"
ip link add "$VA" type veth peer name "$VB"
ip link set "$VA" netns "$A"
ip link set "$VB" netns "$B"
ip -n "$A" addr add 10.231.0.1/24 dev "$VA"
ip -n "$B" addr add 10.231.0.2/24 dev "$VB"
for ns_if in "$A:$VA" "$B:$VB"; do
    ns="${ns_if%%:*}"
    ifc="${ns_if##*:}"
    ip -n "$ns" link set lo up
    ip -n "$ns" link set "$ifc" up
    ip -n "$ns" route add 224.0.0.0/4 dev "$ifc"
done

LISTENER='
import sys, time, rclpy
from rclpy.node import Node
from diagnostic_msgs.msg import DiagnosticArray
rclpy.init()
n = Node("netns_listener")
got = []
n.create_subscription(DiagnosticArray, "/diagnostics", got.append, 10)
end = time.monotonic() + float(sys.argv[1])
while not got and time.monotonic() < end:
    rclpy.spin_once(n, timeout_sec=0.1)
print("heard" if got else "not heard")
'

listen() { # listen NS RANGE SECONDS
    ip netns exec "$1" env ROS_DOMAIN_ID=7 ROS_AUTOMATIC_DISCOVERY_RANGE="$2" \
        ROS_LOG_DIR="$(mktemp -d)" python -c "$LISTENER" "$3" 2>/dev/null || echo "listener failed"
}

printf '%-10s | %-26s | %-24s | %s\n' "node range" "listener on B (SUBNET)" "listener on A (same)" "node's UDP sockets"
status=0
for range in SUBNET LOCALHOST OFF; do
    log="$(mktemp)"
    ip netns exec "$A" env ROS_DOMAIN_ID=7 ROS_AUTOMATIC_DISCOVERY_RANGE="$range" "$NODE" >"$log" 2>&1 &
    node_pid=$!
    for _ in $(seq 100); do grep -q " running: " "$log" && break; sleep 0.1; done
    socks="$(ip netns exec "$A" ss -H -uanp | grep "pid=$node_pid," | awk '{print $4}' | sort | tr '\n' ' ')"
    from_b="$(listen "$B" SUBNET 10)"
    on_a="$(listen "$A" "$range" 10)"
    printf '%-10s | %-26s | %-24s | %s\n' "$range" "$from_b" "$on_a" "$socks"
    case "$range:$from_b:$on_a" in
        SUBNET:heard:heard | LOCALHOST:"not heard":heard | OFF:"not heard":"not heard") ;;
        *) status=1 ;;
    esac
    kill -INT "$node_pid"
    wait "$node_pid" || true
    node_pid=""
    rm -f "$log"
done
[ "$status" = 0 ] && echo "netns-discovery: ok" || echo "netns-discovery: UNEXPECTED"
exit "$status"
