"""The commands the docs show work as written.

Every command block of docs/cli.md's guide (the part above the generated reference) runs in order, as written,
in a temporary folder that holds the repository's ``models/`` (the guide says to run from the repository
folder), through ``python -m fieldcal``; each must exit 0. A block preceded by a ``<!-- docs-test: not run
(...) -->`` comment says why it is not run (hardware, minutes) and is skipped. The README's ``fieldcal``
commands must be among the commands run. The generated reference must match the parsers.
"""

from __future__ import annotations

import io
import os
import re
import shlex
import subprocess
import sys
import time
from contextlib import redirect_stdout
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CLI_MD = ROOT / "docs" / "cli.md"
README = ROOT / "README.md"
REFERENCE = "## Reference (generated)"
SKIP = re.compile(r"<!--\s*docs-test:\s*not run")


def command_blocks(text: str) -> list[tuple[bool, list[str]]]:
    """``(run, lines)`` for each fenced block; ``run`` is False after a docs-test skip comment."""
    out = []
    for m in re.finditer(r"```[^\n]*\n(.*?)```", text, flags=re.S):
        before = text[:m.start()].rstrip().splitlines()
        skip = bool(before) and bool(SKIP.search(before[-1]))
        out.append((not skip, m.group(1).splitlines()))
    return out


def fieldcal_commands(lines: list[str]) -> list[list[str]]:
    """The ``fieldcal ...`` commands of a block (also after ``&&``), as argv without comments."""
    cmds = []
    for line in lines:
        for part in line.split("&&"):
            argv = shlex.split(part, comments=True)
            if argv and argv[0] == "fieldcal":
                cmds.append(argv[1:])
    return cmds


def guide_commands() -> list[list[str]]:
    guide = CLI_MD.read_text().split(REFERENCE)[0]
    cmds = [c for run, lines in command_blocks(guide) if run for c in fieldcal_commands(lines)]
    assert len(cmds) >= 8, "docs/cli.md lost its command guide"
    return cmds


def test_the_guide_marks_every_block_it_does_not_run():
    guide = CLI_MD.read_text().split(REFERENCE)[0]
    for run, lines in command_blocks(guide):
        assert fieldcal_commands(lines), f"a block without fieldcal commands in the guide: {lines[:2]}"


def test_readme_commands_are_in_the_guide():
    ran = {tuple(c) for c in guide_commands()}
    readme = [c for _, lines in command_blocks(README.read_text()) for c in fieldcal_commands(lines)]
    assert readme, "README.md shows no fieldcal command"
    for argv in readme:
        assert tuple(argv) in ran, f"README's `fieldcal {' '.join(argv)}` is not run by the guide test"


def test_reference_matches_the_parsers(monkeypatch):
    from fieldcal.commands import _clidoc
    monkeypatch.setenv("COLUMNS", "110")
    buf = io.StringIO()
    with redirect_stdout(buf):
        _clidoc.main()
    assert buf.getvalue() == CLI_MD.read_text(), \
        "docs/cli.md is stale: python -m fieldcal.commands._clidoc > docs/cli.md"


def test_every_guide_command_runs_as_written(tmp_path):
    (tmp_path / "models").symlink_to(ROOT / "models", target_is_directory=True)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "FIELDCAL_PROGRESS": "0", "MPLBACKEND": "Agg"}
    times = []
    for argv in guide_commands():
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "fieldcal", *argv], cwd=tmp_path, env=env,
                           capture_output=True, text=True, timeout=300)
        times.append((time.perf_counter() - t0, argv[0]))
        assert r.returncode == 0, f"`fieldcal {shlex.join(argv)}` exited {r.returncode}:\n{r.stderr[-2000:]}"
    print("timings (s):", [(round(t, 1), c) for t, c in times])
