"""Trace files on disk (docs/safety.md "Trace files"): a trace that cannot be written is WARN on
/diagnostics at once, naming it, and said in the log a bounded number of times in the node's
own words; each trace keeps to `trace_max_mb` by rotation; a trace file deleted while the node
runs is begun again at its path and said.

The file system that fills is a tmpfs mounted for the test (root only: a test run without root
skips these with the reason), filled by a file the test writes until the kernel says ENOSPC.
"""

from __future__ import annotations

import csv as csv_module
import errno
import os
import subprocess
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from mcap.reader import make_reader

from helpers_rules import diag_values

NODE = "pwm_actuator"
#: Files a trace keeps: the one written and three older ones (TRACE_FILES).
TRACE_FILES = 4
WARN = DiagnosticStatus.WARN


def channels_args(n: int, period_ms: int) -> list[str]:
    """`n` channels at `period_ms` and 50 %, enabled."""
    args = ["--channels", str(n), "--ros-args"]
    for k in range(1, n + 1):
        ch = f"pw{k:02d}"
        args += ["-p", f"{ch}.period_ms:={period_ms}", "-p", f"{ch}.duty:=50.0",
                 "-p", f"{ch}.enable:=true"]  # fmt: skip
    return args


@pytest.fixture
def tmpfs(tmp_path: Path) -> Iterator[Callable[[str], Path]]:
    """mount(size) -> a fresh tmpfs of `size` (e.g. "16m"), unmounted after the test."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    mounted: list[Path] = []

    def mount(size: str) -> Path:
        d = tmp_path / f"fs{len(mounted)}"
        d.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(d)],
                       check=True)  # fmt: skip
        mounted.append(d)
        return d

    yield mount
    for d in mounted:
        # Lazy: a node that failed the test may still hold files there.
        subprocess.run(["umount", "-l", str(d)], check=False)


def fill(directory: Path) -> Path:
    """Writes a file in `directory` until the file system has no room left; returns it."""
    filler = directory / "filler"
    with open(filler, "wb", buffering=0) as f:
        for size in (1 << 20, 4096, 1):
            block = b"\xa5" * size
            while True:
                try:
                    f.write(block)
                except OSError as e:
                    if e.errno != errno.ENOSPC:
                        raise
                    break
    return filler


def traces(array: DiagnosticArray) -> dict[str, DiagnosticStatus]:
    """The trace statuses of a /diagnostics message, by path."""
    prefix = f"{NODE}: trace "
    return {s.name[len(prefix):]: s for s in array.status if s.name.startswith(prefix)}


def first_after(
    log: Any, start: int, pred: Callable[[DiagnosticArray], bool]
) -> tuple[int] | None:
    """The index (in a tuple, so 0 is found) of the first message from `start` that `pred`
    holds for."""
    for i in range(start, len(log.messages)):
        if pred(log.messages[i]):
            return (i,)
    return None


def wait_diag(ros: Any, log: Any, start: int, pred: Callable[[DiagnosticArray], bool],
              what: str, timeout: float = 10.0) -> int:  # fmt: skip
    """Spins until a /diagnostics message at index >= `start` satisfies `pred`; its index."""
    return ros.spin_until(lambda: first_after(log, start, pred), what, timeout)[0]


def on_disk(base: Path) -> list[Path]:
    """A trace's files on disk: its path and the older ones (`run.1.csv`, ...)."""
    files = [base] + [base.with_name(f"{base.stem}.{k}{base.suffix}") for k in range(1, 8)]
    return [f for f in files if f.exists()]


def test_a_file_system_that_fills_is_warn_naming_each_trace_within_a_second(ros, node_process, tmpfs):
    fs = tmpfs("16m")
    paths = [fs / "run.csv", fs / "run.vcd", fs / "run.mcap"]
    diag = ros.subscribe(DiagnosticArray, "/diagnostics", 1000)
    trace_args = [a for p in paths for a in ("--trace", str(p))]
    node = node_process([*trace_args, *channels_args(2, 20)], trace=False)
    node.wait_for_output("running:")
    names = [str(p) for p in paths]

    def all_writing(a: DiagnosticArray) -> bool:
        t = traces(a)
        return all(n in t and diag_values(t[n])["state"] == "writing" for n in names)

    wait_diag(ros, diag, 0, all_writing, "three traces writing")
    ros.spin_for(1.0)

    start = len(diag.messages)
    fill(fs)
    full_at = time.monotonic()

    def all_warn(a: DiagnosticArray) -> bool:
        t = traces(a)
        return all(n in t and t[n].level == WARN for n in names)

    i = wait_diag(ros, diag, start, all_warn, "every trace WARN")
    delay = diag.arrivals[i] - full_at
    print(f"every trace WARN on /diagnostics {delay * 1000:.0f} ms after the file system filled")
    for n, s in traces(diag.messages[i]).items():
        print(f"  {s.name}: {s.message}")
    assert delay < 1.0, f"WARN {delay:.2f} s after the file system filled"

    # Their writes fail: each says why in the node's words and counts what it lost.
    def all_failing(a: DiagnosticArray) -> bool:
        t = traces(a)
        return all(
            n in t
            and diag_values(t[n])["state"] == "failing"
            and int(diag_values(t[n]).get("edges_lost", diag_values(t[n]).get("messages_lost", "0")))
            > 0
            for n in names
        )

    i = wait_diag(ros, diag, i, all_failing, "every trace failing, with records lost")
    for n, s in traces(diag.messages[i]).items():
        assert s.level == WARN
        assert "no space left on the file system (os error 28)" in s.message, s.message
    # A while longer: the log says each failure once, in the node's words, not once a write.
    ros.spin_for(3.0)
    out = node.output()
    for n in names:
        lines = [line for line in out.splitlines() if f"trace {n}:" in line]
        warns = [line for line in lines if line.startswith("[WARN]")]
        assert any("no space left on the file system (os error 28)" in line for line in warns), lines
        assert 1 <= len(warns) <= 4, warns
    assert "No space left on device" not in out, "the system's raw text in the log"

    # Room again: each trace goes on in a new file after the one that failed.
    (fs / "filler").unlink()
    start = len(diag.messages)
    wait_diag(ros, diag, start, all_writing, "every trace writing again", timeout=10.0)
    ros.spin_for(1.0)
    assert node.terminate() == 0, node.output()
    out = node.output()
    assert all(f"trace {n}: written again" in out for n in names), out
    assert "No space left on device" not in out, "the system's raw text in the log at the stop"
    for p in paths:
        files = on_disk(p)
        assert len(files) >= 2, f"{p}: the failed file is kept beside the new one: {files}"
    rows = list(csv_module.DictReader(paths[0].read_text().splitlines()))
    assert len(rows) > 2, "the new CSV holds edges after its start rows"
    with open(paths[2], "rb") as f:
        assert make_reader(f).get_summary() is not None, "the new MCAP file is closed whole"


# Untimed (pytest.ini): sizes and counts of files on the disk, looked at until each trace has
# rotated; the 40 s given for that are twice what it takes.
@pytest.mark.untimed
def test_rotation_keeps_each_trace_within_its_limit(ros, node_process, tmpfs):
    fs = tmpfs("64m")
    paths = [fs / "run.csv", fs / "run.vcd", fs / "run.mcap"]
    limit = 1_000_000  # --trace-max-mb 1
    diag = ros.subscribe(DiagnosticArray, "/diagnostics", 1000)
    trace_args = [a for p in paths for a in ("--trace", str(p))]
    node = node_process([*trace_args, "--trace-max-mb", "1", *channels_args(6, 5)], trace=False)
    node.wait_for_output("running:")
    totals: dict[Path, int] = {p: 0 for p in paths}
    most: dict[Path, int] = {p: 0 for p in paths}
    deadline = time.monotonic() + 40.0

    def dropped(p: Path) -> int:
        for a in reversed(diag.messages):
            t = traces(a)
            if str(p) in t:
                return int(diag_values(t[str(p)])["files_deleted"])
        return 0

    # Until the CSV and the MCAP trace have each deleted an older file (and the VCD has
    # rotated), every look at the disk finds each trace's files within the limit.
    while time.monotonic() < deadline:
        ros.spin_for(0.1)
        for p in paths:
            files = on_disk(p)
            assert len(files) <= TRACE_FILES, files
            total = sum(f.stat().st_size for f in files if f.exists())
            totals[p] = total
            most[p] = max(most[p], total)
            assert total <= limit, f"{p}: {total} bytes in {files}"
        if dropped(paths[0]) >= 1 and dropped(paths[2]) >= 1 and len(on_disk(paths[1])) >= 2:
            break
    print({p.name: (most[p], len(on_disk(p)), dropped(p)) for p in paths})
    assert dropped(paths[0]) >= 1 and dropped(paths[2]) >= 1, "no file deleted in 40 s"
    assert len(on_disk(paths[1])) >= 2, "the VCD trace did not rotate in 40 s"
    last = traces(diag.messages[-1])
    for p in paths:
        v = diag_values(last[str(p)])
        assert last[str(p)].level == DiagnosticStatus.OK, last[str(p)]
        assert int(v["bytes"]) <= limit and v["limit_bytes"] == str(limit), v
    assert node.terminate() == 0, node.output()
    # Every file is whole: the CSV's and VCD's with their header, the MCAP's closed with its
    # summary; none beyond the four.
    for p in paths:
        files = on_disk(p)
        assert len(files) <= TRACE_FILES
        for f in files:
            data = f.read_bytes()
            assert len(data) <= limit // TRACE_FILES, (f, len(data))
            if p.suffix == ".csv":
                assert data.startswith(b"t_ns,channel,level,scheduled_ns\n"), f
            elif p.suffix == ".vcd":
                assert data.startswith(b"$version pwm_actuator"), f
            else:
                with open(f, "rb") as h:
                    assert make_reader(h).get_summary() is not None, f


def test_a_trace_deleted_while_the_node_runs_is_begun_again_and_said(ros, node_process, tmp_path):
    path = tmp_path / "run.csv"
    diag = ros.subscribe(DiagnosticArray, "/diagnostics", 1000)
    node = node_process(["--trace", str(path), *channels_args(1, 20)], trace=False)
    node.wait_for_output("running:")
    ros.spin_until(lambda: path.exists() and path.stat().st_size > 200, "rows in the trace")
    start = len(diag.messages)
    path.unlink()
    deleted_at = time.monotonic()

    def reopened(a: DiagnosticArray) -> bool:
        s = traces(a).get(str(path))
        return s is not None and s.level == WARN and diag_values(s)["reopened"] == "1"

    i = wait_diag(ros, diag, start, reopened, "the deleted trace said")
    s = traces(diag.messages[i])[str(path)]
    assert "deleted" in diag_values(s)["last_problem"], s
    assert diag.arrivals[i] - deleted_at < 1.0
    ros.spin_until(lambda: path.exists() and path.stat().st_size > 100, "the trace begun again")
    assert path.read_text().startswith("t_ns,channel,level,scheduled_ns\n")
    assert node.terminate() == 0
    assert "was deleted or replaced while written; begun again" in node.output()
