"""The command line as a whole: help with examples everywhere, clean errors, docs/cli.md in sync."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from fieldcal.cli import COMMANDS, main

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", [{"import_stack": "import"}.get(c, c) for c in COMMANDS])
def test_every_command_has_help_with_an_example(name, capsys):
    with pytest.raises(SystemExit) as e:
        main([name, "--help"])
    assert e.value.code == 0
    assert "example:" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [
    ["calibrate", "no-such-stack", "--out", "x.json"],
    ["report", "no-such-profile.json", "--out", "rep"],
    ["composite", "no-such-stack", "--out", "x.tiff"],
    ["plan", "stack", "no-such-profile.json", "--fs", "80", "--q", "0.05", "--out", "p.json"],
    ["simulate", "no-such-lens.json", "s", "--z", "0", "10", "5"],
    ["validate", "no-such-lens.json"],
    ["calibrate", "no-such-stack", "--out", "x.txt"],
    ["plan", "stack", "models/triplet-uncorrected.json", "--fs", "80", "--q", "1.5", "--out", "p.json"],
])
def test_user_mistakes_are_one_clean_message(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    if "models/triplet-uncorrected.json" in argv:
        argv = [str(REPO / a) if a.startswith("models/") else a for a in argv]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err and "fix:" in err
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_no_command_prints_help():
    r = subprocess.run([sys.executable, "-m", "fieldcal"], capture_output=True, text=True)
    assert r.returncode == 2 and "COMMAND" in r.stdout


def test_the_program_ends_with_the_commands_status_and_its_whole_output(tmp_path):
    """``python -m fieldcal`` ends the process itself once the command returns (no interpreter teardown): the
    status is the command's, and what it wrote to both streams arrives whole, also through pipes."""
    r = subprocess.run([sys.executable, "-m", "fieldcal", "composite", "no-such-stack", "--out", "x.tiff"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and "fix:" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert list(tmp_path.iterdir()) == []
    code = ("import sys; from fieldcal import cli\n"
            "cli.main = lambda: (sys.stdout.write('x' * 200000), sys.stderr.write('y' * 100000), 3)[-1]\n"
            "cli.entry()\nraise SystemExit('entry returned')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 3 and r.stdout == "x" * 200000 and r.stderr == "y" * 100000, r.stderr[-300:]


def test_docs_cli_reference_is_generated_from_the_parsers():
    env = {**os.environ, "COLUMNS": "110"}
    r = subprocess.run([sys.executable, "-m", "fieldcal.commands._clidoc"], capture_output=True, text=True,
                       env=env, cwd=REPO, check=True)
    assert r.stdout == (REPO / "docs" / "cli.md").read_text(), \
        "docs/cli.md is stale: python -m fieldcal.commands._clidoc > docs/cli.md"
