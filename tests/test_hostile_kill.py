"""SIGKILL at chosen points of a write (issue 12): the old outputs or the new ones, never a mix.

The command runs in a child process whose ``os.replace`` / ``os.write`` are wrapped to ``SIGKILL`` the process
itself at the N-th call (before or after it), so the kill lands exactly between two renames of a profile,
mid-way through a temporary file, or after the JSON but before the old sidecar is removed.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from fieldcal.cli import main
from fieldcal.profile.lens_profile import LensProfile

from hostile_safety_util import FS

REPO = Path(__file__).resolve().parents[1]

CHILD = r"""
import os, signal, sys
point, n = os.environ["KILL_POINT"], int(os.environ["KILL_N"])
calls = {"replace": 0, "write": 0}
real_replace, real_write = os.replace, os.write

def die():
    os.kill(os.getpid(), signal.SIGKILL)

def replace(src, dst, *a, **k):
    calls["replace"] += 1
    if point == "before-replace" and calls["replace"] == n:
        die()
    r = real_replace(src, dst, *a, **k)
    if point == "after-replace" and calls["replace"] == n:
        die()
    return r

def write(fd, data):
    calls["write"] += 1
    if point == "mid-write" and calls["write"] == n:
        real_write(fd, bytes(data[: max(1, len(data) // 2)]))
        die()
    return real_write(fd, data)

os.replace, os.write = replace, write
from fieldcal.cli import main
sys.exit(main(sys.argv[1:]))
"""


def run_killed(argv, point, n, cwd):
    env = {**os.environ, "PYTHONPATH": str(REPO), "KILL_POINT": point, "KILL_N": str(n),
           "FIELDCAL_PROGRESS": "0", "MPLBACKEND": "Agg"}
    r = subprocess.run([sys.executable, "-c", CHILD, *[str(a) for a in argv]], env=env, cwd=cwd,
                       capture_output=True, text=True, timeout=300)
    return r


def sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


# replace #1 = the new sidecar, #2 = the JSON; write #1 = the sidecar's bytes
@pytest.mark.parametrize("point,n", [("mid-write", 1), ("before-replace", 1), ("after-replace", 1),
                                     ("before-replace", 2), ("after-replace", 2)])
def test_calibrate_overwrite_killed_leaves_old_or_new_profile(w, point, n):
    js = w / "lens.json"
    old_json = js.read_bytes()
    old_side = json.loads(old_json)["sidecar"]["file"]
    r = run_killed(["calibrate", w / "S", "--out", js, "--fs", FS, "--effort", "quick", "-q", "--seed", "7",
                    "--overwrite"], point, n, w)
    assert r.returncode == -signal.SIGKILL, (r.returncode, r.stderr)
    prof = LensProfile.load(js)  # whatever happened, the JSON and the sidecar it names belong together
    now = json.loads(js.read_text())
    became_new = point == "after-replace" and n == 2
    if became_new:
        assert js.read_bytes() != old_json and now["calibration"] and prof.surfaces is not None
    else:
        assert js.read_bytes() == old_json and now["sidecar"]["file"] == old_side
        assert (w / old_side).is_file()
    # nothing was ever written under a final name half-way: every visible .npz is complete or a temp
    for f in w.glob("*.npz"):
        assert f.name.startswith(".") or len(f.read_bytes()) > 0
    if not (point == "after-replace" and n == 1):
        return
    # killed between the renames: an orphan new sidecar; the next run cleans up and gives the new profile
    assert len(list(w.glob("lens*.npz"))) == 2
    r = subprocess.run([sys.executable, "-m", "fieldcal", "calibrate", str(w / "S"), "--out", str(js), "--fs", FS,
                        "--effort", "quick", "-q", "--seed", "7", "--overwrite"],
                       env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, cwd=w)
    assert r.returncode == 0, r.stderr
    LensProfile.load(js)
    visible = sorted(f.name for f in w.glob("lens*.npz"))
    assert visible == [json.loads(js.read_text())["sidecar"]["file"]], visible


@pytest.mark.parametrize("point,n", [("mid-write", 1), ("before-replace", 1)])
def test_plan_overwrite_killed_leaves_the_old_plan(w, point, n):
    plan = w / "plan.json"
    assert main(["plan", "stack", str(w / "lens.json"), "--fs", FS, "--q", "0.05", "--out", str(plan)]) == 0
    old = sha(plan)
    r = run_killed(["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.1", "--out", plan, "--overwrite"],
                   point, n, w)
    assert r.returncode == -signal.SIGKILL, r.stderr
    assert sha(plan) == old
    json.loads(plan.read_text())


@pytest.mark.parametrize("n", [1, 3, 6])
def test_report_killed_leaves_every_file_whole(w, n):
    from PIL import Image

    assert main(["report", str(w / "lens.json"), "--out", str(w / "R")]) == 0
    old = {f.name: sha(f) for f in (w / "R").iterdir()}
    r = run_killed(["report", w / "lens.json", "--out", w / "R", "--fs", "10", "--overwrite"], "before-replace",
                   n, w)
    assert r.returncode == -signal.SIGKILL, r.stderr
    for f in (w / "R").iterdir():
        if f.name.startswith("."):
            continue  # an unfinished temporary, never under a final name
        assert f.name in old
        if f.suffix == ".png":
            with Image.open(f) as im:
                im.load()  # a whole PNG (old or new), never a truncated one
    assert (w / "R" / "index.html").read_text().rstrip().endswith("</html>")


def test_composite_overwrite_killed_leaves_the_old_image(w):
    out = w / "c.tiff"
    out.write_bytes(b"old composite")
    r = run_killed(["composite", w / "S", "--profile", w / "lens.json", "--out", out, "--overwrite", "--quiet"],
                   "mid-write", 1, w)
    assert r.returncode == -signal.SIGKILL, r.stderr
    assert out.read_bytes() == b"old composite"
