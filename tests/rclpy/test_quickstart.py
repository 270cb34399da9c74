"""The README's quick start, run as a new user runs it.

Terminal 1 of the quick start is the node with the README's options (`--trace /tmp/pw.vcd
--ros-args -p pw01.period_ms:=2000`, the trace here in the test's directory); terminal 2 is
`python3 docs/quickstart.py` with the venv's python. The script must exit 0 (edges came, the
period change was accepted), and what it printed must show what the README says it shows: the
25 % pulse at the 2000 ms period (500 ms on), then a shorter one after the change; the VCD file
must hold pw01's edges.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
QUICKSTART = REPO / "docs" / "quickstart.py"


def on_times_ms(text: str) -> list[float]:
    """The on phases the script printed, in ms, from its edge lines (stamps in s.ns)."""
    edges = re.findall(r"edge #\d+: pw01 (on |off) at (\d+)\.(\d{9})", text)
    times = [(level.strip(), int(s) + int(ns) / 1e9) for level, s, ns in edges]
    return [
        (t_off - t_on) * 1000
        for (l_on, t_on), (l_off, t_off) in zip(times, times[1:])
        if l_on == "on" and l_off == "off"
    ]


@pytest.mark.timeout(90)
def test_the_readme_quick_start_works_as_written(node_process, ros_env, tmp_path: Path):
    vcd = tmp_path / "pw.vcd"
    node = node_process(
        ["--trace", str(vcd), "--ros-args", "-p", "pw01.period_ms:=2000"],
        output=None,
        trace=False,
    )
    node.wait_for_output("running")
    run = subprocess.run(
        [sys.executable, str(QUICKSTART)],
        env=ros_env,
        cwd=REPO,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=60,
    )
    out = run.stdout
    assert run.returncode == 0, f"quickstart.py exited {run.returncode}:\n{out}\n{run.stderr}"
    assert "period change accepted: True" in out, out
    on = on_times_ms(out)
    assert on, f"no complete pulse printed:\n{out}"
    # 25 % of 2000 ms, then 25 % of 1000 ms: wide bounds, the stamps are the write times.
    assert any(480 <= t <= 520 for t in on), f"no 500 ms pulse in {on}"
    assert any(230 <= t <= 270 for t in on), f"no 250 ms pulse after the change in {on}"
    node.terminate()
    text = vcd.read_text()
    assert "$var" in text and "pw01" in text, text[:400]
    assert re.search(r"^#\d+", text, re.M), "the VCD holds no timestamped change"
