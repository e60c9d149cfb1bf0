"""A sweep capture killed (SIGKILL) mid-exposure or mid-commit leaves no partial image under the final name, and
the same command re-run completes it (as tests/test_capture_hostile.py does for stack captures)."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import tifffile

from fieldcal import Stack
from fieldcal.capture import JOURNAL
from fieldcal.cli import main
from test_capture_hostile import KILLER

REPO = Path(__file__).resolve().parents[1]
TRIPLET = REPO / "models" / "triplet-uncorrected.json"

# "mid-exposure": killed while the camera integrates over the sweep (the stage moving, nothing written yet);
# the other points are test_capture_hostile's (frame temp file half-written, frame renamed but unlisted, ...).
MID_EXPOSURE = r'''
import os, signal, sys
if sys.argv[1] == "mid-exposure":
    import fieldcal.hardware.sim as H
    def close_exposure(self):
        os.kill(os.getpid(), signal.SIGKILL)
    H.SimCamera.close_exposure = close_exposure
    sys.argv[1] = "none"
'''


@pytest.fixture(scope="module")
def plan(tmp_path_factory):
    d = tmp_path_factory.mktemp("sweepkill")
    p = d / "sweep.json"
    assert main(["plan", "sweep", str(TRIPLET), "--size", "48x27", "--alpha-um", "20", "--pixel-exposure-ms", "10",
                 "--device", "pixel", "--out", str(p)]) == 0
    assert main(["plan", "export-masks", str(p), "--out", str(d / "masks")]) == 0
    return p, d / "masks"


def _argv(plan, out):
    p, masks = plan
    return ["capture", "--plan", str(p), "--stage", "sim", "--camera", f"sim:{TRIPLET},size=48x27,sub_step_um=8",
            "--exposure-device", f"sim:{masks}", "--out", str(out), "--quiet"]


def _kill_at(point, argv, tmp_path) -> int:
    script = tmp_path / "killer.py"
    script.write_text(MID_EXPOSURE + KILLER)
    env = {**os.environ, "FIELDCAL_PROGRESS": "0", "PYTHONPATH": str(REPO)}
    r = subprocess.run([sys.executable, str(script), point, "1", *argv], env=env, capture_output=True, text=True,
                       timeout=120)
    return r.returncode


@pytest.mark.parametrize("point", ["mid-exposure", "frame-temp", "frame-renamed", "journal-half"])
def test_a_killed_sweep_leaves_no_partial_image_and_reruns_cleanly(plan, tmp_path, point):
    out = tmp_path / "swept"
    argv = _argv(plan, out)
    assert _kill_at(point, argv, tmp_path) == -9
    final = out / "frames" / "0000.tiff"
    if final.exists():  # a frame under its final name is always whole (renamed into place after fsync)
        assert tifffile.imread(final).shape[:2] == (27, 48)
    listed = json.loads((out / "stack.json").read_text())["frames"]
    assert all((out / e["file"]).is_file() for e in listed)
    assert main(argv) == 0
    s = Stack.open(out)
    assert len(s.frames) == 1 and s.verify_checksums() == []
    (line,) = (out / JOURNAL).read_text().splitlines()[1:]
    entry = json.loads(line)["entry"]
    assert entry["sha256"] == hashlib.sha256(final.read_bytes()).hexdigest() and "sweep" in entry
    assert not [n for n in os.listdir(out) if n.endswith(".tmp")]
    assert sorted(os.listdir(out / "frames")) == ["0000.tiff"]
    before = final.read_bytes()
    assert main(argv) == 0 and final.read_bytes() == before  # complete: a re-run changes nothing
