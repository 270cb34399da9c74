#!/usr/bin/env python3
"""Runs the shell blocks of README.md and docs/*.md that are marked runnable here, and lists the
others with the reason they cannot run here.

Every ```sh or ```bash block is marked on the line before it, an HTML comment that Markdown
does not show:

    <!-- runnable -->                 run here: `bash -eo pipefail` from the repository root,
                                      must exit 0 within 300 s
    <!-- not runnable: REASON -->     not run; REASON is printed (hardware, the ros2 command
                                      line, a run of minutes, ...)

A block without a marker fails the check, so a new command cannot go unchecked unseen.
Usage: scripts/check-doc-commands.py [--list] [FILE.md...]
  --list    list the blocks, run nothing
  FILE.md   only these pages (default: README.md and docs/*.md)
Exit status 0 when every runnable block passed and every block is marked.
"""

import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
TIMEOUT_S = 300
FENCE = re.compile(r"^```(sh|bash)\s*$")
RUNNABLE = re.compile(r"^<!-- runnable -->$")
NOT_RUNNABLE = re.compile(r"^<!-- not runnable: (.+?) -->$")


def blocks(pages):
    """(file, line, marker line, block text) of every shell block of `pages`."""
    for path in pages:
        lines = path.read_text().split("\n")
        i = 0
        while i < len(lines):
            if FENCE.match(lines[i]):
                j = i + 1
                while j < len(lines) and not lines[j].startswith("```"):
                    j += 1
                marker = lines[i - 1].strip() if i > 0 else ""
                yield path.relative_to(REPO), i + 1, marker, "\n".join(lines[i + 1:j])
                i = j
            i += 1


def main() -> int:
    args = sys.argv[1:]
    list_only = "--list" in args
    pages = [(Path.cwd() / a).resolve() for a in args if a != "--list"]
    pages = pages or [REPO / "README.md"] + sorted((REPO / "docs").glob("*.md"))
    passed, failed, skipped = [], [], []
    for path, line, marker, text in blocks(pages):
        where = f"{path}:{line}"
        if m := NOT_RUNNABLE.match(marker):
            skipped.append(where)
            print(f"not runnable here: {where}: {m.group(1)}")
        elif RUNNABLE.match(marker):
            if list_only:
                print(f"runnable: {where}")
                continue
            start = time.monotonic()
            try:
                r = subprocess.run(["bash", "-eo", "pipefail", "-c", text], cwd=REPO,
                                   stdin=subprocess.DEVNULL, capture_output=True, text=True,
                                   timeout=TIMEOUT_S)
                ok, why = r.returncode == 0, f"exit {r.returncode}"
                out = (r.stdout + r.stderr)[-2000:]
            except subprocess.TimeoutExpired:
                ok, why, out = False, f"still running after {TIMEOUT_S} s", ""
            took = time.monotonic() - start
            if ok:
                passed.append(where)
                print(f"PASS {where} ({took:.1f} s)")
            else:
                failed.append(where)
                print(f"FAIL {where} ({why}, {took:.1f} s):\n{text}\n--- output:\n{out}")
        else:
            failed.append(where)
            print(f"FAIL {where}: no marker (<!-- runnable --> or <!-- not runnable: REASON -->) "
                  f"on the line before the block")
    print(f"doc commands: {len(passed)} passed, {len(failed)} failed, {len(skipped)} not runnable "
          "here")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
