"""`ROS_STATIC_PEERS` across a router that does not pass multicast, against rclpy.

Three network namespaces made for each test and removed after it: host A runs the node, host B
an rclpy client (static_peers_client.py, in its own process inside B), and R routes unicast
between A's subnet and B's. Linux does not forward multicast without a multicast routing daemon,
so SPDP's multicast from either host stops at R, as at a site router or a switch that drops
multicast. Each test first checks that on the wire: a datagram to 239.255.0.1 from A reaches R
but not B, one to B's address does.

- Without static peers the client on B does not see the node (not in the graph, no
  `/diagnostics`) within the wait in which, with them, it gets everything.
- With `ROS_STATIC_PEERS` naming B on the node only (the client has none), the client sees the
  node: the node's own unicast announcements are what makes it found.
- With `ROS_STATIC_PEERS` on both sides, as rcl users set it, the client receives the node's
  `/diagnostics`, gets a `get_parameters` answer, and commands channel pw01, which the node
  shows by its status and its edges, and writes in its trace: with the node's range `SUBNET`
  and with `LOCALHOST` (this host and the static peers, no multicast).

Needs root (network namespaces) and `ip`; skipped with that reason where they are missing.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional

import pytest

CLIENT = Path(__file__).with_name("static_peers_client.py")
#: How long the client on B looks for the node, seconds. With static peers everything arrives
#: within a few seconds on a loaded machine; without, this is how long nothing must arrive.
LOOK_S = 25.0
#: The node's logged line once its ROS entities exist.
RUNNING = " running: "

# Untimed (pytest.ini): each test on network namespaces of its own, what the client on B gets
# within a 25 s look (seconds where everything arrives), no figure of how soon the node answers
# or how its edges fall.
pytestmark = [
    pytest.mark.untimed,
    pytest.mark.skipif(
        os.geteuid() != 0 or shutil.which("ip") is None,
        reason="needs root and iproute2's `ip` to create network namespaces",
    ),
]


def sh(*argv: str) -> None:
    subprocess.run(argv, check=True, capture_output=True, timeout=20)


@dataclass
class RoutedHosts:
    """Host A (the node), host B (the client), and the router R between their subnets."""

    a: str
    b: str
    r: str
    a_addr: str = "10.213.1.2"
    b_addr: str = "10.213.2.2"

    def run(self, ns: str, argv: list[str], env: dict, timeout: float) -> str:
        """Runs `argv` inside namespace `ns`; its stdout (the test fails if it fails)."""
        done = subprocess.run(
            ["ip", "netns", "exec", ns, *argv],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        assert done.returncode == 0, f"{argv[:3]} in {ns}: exit {done.returncode}\n{done.stderr}"
        return done.stdout


@pytest.fixture
def hosts() -> Iterable[RoutedHosts]:
    tag = f"{os.getpid()}"
    h = RoutedHosts(a=f"pwmsp-a-{tag}", b=f"pwmsp-b-{tag}", r=f"pwmsp-r-{tag}")
    try:
        for ns in (h.a, h.b, h.r):
            sh("ip", "netns", "add", ns)
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        # A <-> R on 10.213.1.0/24, R <-> B on 10.213.2.0/24.
        for host, addr, gw, side, net in (
            (h.a, h.a_addr, "10.213.1.1", "a", "1"),
            (h.b, h.b_addr, "10.213.2.1", "b", "2"),
        ):
            here, there = f"sp{side}{tag}"[-15:], f"sp{side}r{tag}"[-15:]
            sh("ip", "link", "add", here, "netns", host, "type", "veth", "peer", "name", there,
               "netns", h.r)
            sh("ip", "-n", host, "addr", "add", f"{addr}/24", "dev", here)
            sh("ip", "-n", h.r, "addr", "add", f"10.213.{net}.1/24", "dev", there)
            sh("ip", "-n", host, "link", "set", here, "up")
            sh("ip", "-n", h.r, "link", "set", there, "up")
            sh("ip", "-n", host, "route", "add", "default", "via", gw)
            # Multicast leaves by this interface, as on a host of a LAN.
            sh("ip", "-n", host, "route", "add", "224.0.0.0/4", "dev", here)
            if side == "a":
                # The router listens for groups on A's side (the check of the wire).
                sh("ip", "-n", h.r, "route", "add", "224.0.0.0/4", "dev", there)
        sh("ip", "netns", "exec", h.r, "sysctl", "-qw", "net.ipv4.ip_forward=1")
        yield h
    finally:
        for ns in (h.a, h.b, h.r):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)


PROBE = textwrap.dedent(
    """
    import socket, struct, sys, time
    port = 47999
    if sys.argv[1] == "listen":
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("0.0.0.0", port))
        mreq = struct.pack("4s4s", socket.inet_aton("239.255.0.1"), socket.inet_aton("0.0.0.0"))
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
        s.settimeout(3)
        got = set()
        try:
            while len(got) < 2:
                got.add(s.recvfrom(64)[0].decode())
        except socket.timeout:
            pass
        print(" ".join(sorted(got)))
    elif sys.argv[1] == "count":
        # Datagrams to the domain's SPDP multicast group and port until stdin closes.
        import select
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("0.0.0.0", int(sys.argv[2])))
        mreq = struct.pack("4s4s", socket.inet_aton("239.255.0.1"), socket.inet_aton("0.0.0.0"))
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
        print("joined", flush=True)
        n = 0
        while True:
            ready = select.select([s, sys.stdin], [], [], 1.0)[0]
            if s in ready:
                s.recv(65536)
                n += 1
            if sys.stdin in ready:
                break
        print(n)
    else:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for _ in range(10):
            s.sendto(b"multicast", ("239.255.0.1", port))
            s.sendto(b"unicast", (sys.argv[2], port))
            time.sleep(0.1)
    """
)


def check_the_wire(h: RoutedHosts, env: dict) -> None:
    """Multicast from A reaches the router, not B; unicast from A reaches B."""
    heard = {}
    for ns, unicast_to in ((h.r, "10.213.1.1"), (h.b, h.b_addr)):
        listener = subprocess.Popen(
            ["ip", "netns", "exec", ns, sys.executable, "-c", PROBE, "listen"],
            stdout=subprocess.PIPE, text=True, env=env,
        )
        try:
            # The listener has joined the group well before the sender's last datagram.
            h.run(h.a, [sys.executable, "-c", PROBE, "send", unicast_to], env, 20)
            heard[ns] = listener.communicate(timeout=20)[0].split()
        finally:
            if listener.poll() is None:
                listener.kill()
    assert heard[h.r] == ["multicast", "unicast"], f"on the router's side of A: {heard[h.r]}"
    assert heard[h.b] == ["unicast"], f"on host B: {heard[h.b]} (multicast must not pass)"


def start_node(h, process_launcher, node_binary, tmp_path, peers: Optional[str],
               node_range: str = "SUBNET"):
    trace = tmp_path / "node-trace.csv"
    argv = ["ip", "netns", "exec", h.a, str(node_binary), "--output", "sim", "--trace",
            str(trace), "--ros-args", "-p", "pw01.period_ms:=200"]
    proc = process_launcher.launch(
        argv,
        name="node",
        env={"ROS_AUTOMATIC_DISCOVERY_RANGE": node_range, "ROS_STATIC_PEERS": peers},
        trace_path=trace,
    )
    proc.wait_for_output(RUNNING)
    return proc


def look(h: RoutedHosts, ros_env: dict, peers: Optional[str], full: bool) -> dict:
    """What the client on B got; it looks for LOOK_S at most."""
    env = dict(ros_env)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SUBNET"
    env.pop("ROS_STATIC_PEERS", None)
    if peers is not None:
        env["ROS_STATIC_PEERS"] = peers
    argv = [sys.executable, str(CLIENT), str(LOOK_S)] + (["--full"] if full else [])
    out = h.run(h.b, argv, env, LOOK_S + 60)
    got = json.loads(out.strip().splitlines()[-1])
    print(f"client on B (ROS_STATIC_PEERS={peers!r}): {got}")
    assert got["rmw"] == "rmw_fastrtps_cpp", got
    return got


def rises_in_trace(proc) -> int:
    lines = proc.trace_text().split("\n")[:-1]
    if not lines:
        return 0
    header = lines[0].split(",")
    rows = [dict(zip(header, line.split(","))) for line in lines[1:]]
    return sum(1 for r in rows if r.get("channel") == "pw01" and r.get("level") == "1")


def test_without_static_peers_the_node_is_not_seen_across_the_router(
    hosts, ros_env, process_launcher, node_binary, tmp_path
):
    check_the_wire(hosts, ros_env)
    proc = start_node(hosts, process_launcher, node_binary, tmp_path, peers=None)
    got = look(hosts, ros_env, peers=None, full=False)
    assert got["seen_s"] is None and got["diagnostics"] == 0, got
    assert got["elapsed_s"] >= LOOK_S, got
    assert "static peers" not in proc.stderr()


def test_the_node_s_own_static_peers_make_it_seen(
    hosts, ros_env, process_launcher, node_binary, tmp_path
):
    check_the_wire(hosts, ros_env)
    proc = start_node(hosts, process_launcher, node_binary, tmp_path, peers=hosts.b_addr)
    assert f"discovery announcements also sent to {hosts.b_addr}" in proc.stderr()
    got = look(hosts, ros_env, peers=None, full=False)
    assert got["seen_s"] is not None and got["diagnostics"] > 0, got


@pytest.mark.parametrize("node_range", ["SUBNET", "LOCALHOST"])
def test_with_static_peers_on_both_sides_rclpy_gets_diagnostics_parameters_and_commands(
    hosts, ros_env, ros_domain_id, process_launcher, node_binary, tmp_path, node_range
):
    """SUBNET: the peers beside multicast; LOCALHOST: this host and the peers only (rcl's
    meaning), no multicast, the node's sockets reachable from the peers."""
    check_the_wire(hosts, ros_env)
    # What the node sends to the SPDP multicast group, as the router sees it.
    spdp_port = 7400 + 250 * ros_domain_id
    counter = subprocess.Popen(
        ["ip", "netns", "exec", hosts.r, sys.executable, "-c", PROBE, "count", str(spdp_port)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=ros_env,
    )
    try:
        assert counter.stdout.readline().strip() == "joined"
        proc = start_node(hosts, process_launcher, node_binary, tmp_path, peers=hosts.b_addr,
                          node_range=node_range)
        assert f"discovery announcements also sent to {hosts.b_addr}" in proc.stderr()
        got = look(hosts, ros_env, peers=hosts.a_addr, full=True)
        multicast = int(counter.communicate(input="", timeout=20)[0].strip())
    finally:
        if counter.poll() is None:
            counter.kill()
    print(f"SPDP multicast datagrams from host A seen by the router: {multicast}")
    if node_range == "LOCALHOST":
        assert multicast == 0, "LOCALHOST with static peers sent discovery by multicast"
    else:
        assert multicast > 0, "SUBNET sent no discovery by multicast"
    assert got["seen_s"] is not None, got
    assert got["diagnostics"] > 0, got
    assert got["parameter"] == 200, got
    assert got["commanded_s"] is not None and got["rises_after_command"] >= 3, got
    # The node wrote the pulses it reported.
    assert rises_in_trace(proc) >= 3, proc.trace_text()[-2000:]
