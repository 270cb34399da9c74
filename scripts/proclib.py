"""What scripts/soak.py and scripts/stress.py share: a ROS domain id of their own, and the
node process's memory and CPU as /proc shows them.

The domain ids are taken with the same lock files as the rclpy suite's (tests/rclpy/conftest.py),
so a run of either script never shares a domain with a test run on the same machine.
"""

from __future__ import annotations

import fcntl
import os
import sys
import tempfile
from pathlib import Path

#: The lock files of the ROS domain ids in use, one per id (shared with tests/rclpy/conftest.py).
DOMAIN_LOCK_DIR = Path(tempfile.gettempdir()) / "pwm_actuator-ros-domains"


def take_domain(tool: str) -> tuple[int, int]:
    """A ROS domain id no other run holds, from 48 down, and the descriptor whose lock holds
    it (released when the process exits). Exits with `tool` named when every id is held."""
    DOMAIN_LOCK_DIR.mkdir(parents=True, exist_ok=True)
    for d in range(48, 0, -1):
        fd = os.open(DOMAIN_LOCK_DIR / f"{d}.lock", os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return d, fd
        except BlockingIOError:
            os.close(fd)
    sys.exit(f"{tool}: every ROS domain id 1..48 is held by a test run")


def proc_status(pid: int, keys: tuple[str, ...]) -> dict[str, int]:
    """The fields `keys` of /proc/<pid>/status (VmRSS, VmHWM, RssAnon, RssFile, ...), kB."""
    got = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in keys:
            got[key] = int(value.split()[0])
    missing = set(keys) - set(got)
    if missing:
        raise RuntimeError(f"no {', '.join(sorted(missing))} for pid {pid}")
    return got


def cpu_seconds(pid: int) -> float:
    """User plus system CPU time of process `pid` so far, s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
