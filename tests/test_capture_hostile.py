"""`fieldcal capture` against hostile folders, journals and numbers (issue #12): every case ends in one clear
message and a documented exit code (2 bad input, 3 device, 4 environment), with no traceback, no byte changed
outside --out and nothing deleted that capture did not create."""

import fcntl
import hashlib
import json
import os
import stat
from pathlib import Path

import pytest

from fieldcal import Stack
from fieldcal.capture import JOURNAL, CapturePlan
from fieldcal.cli import main

SIZE = "32x20"
Z = ["--z", "0", "30", "10"]


def _cam(triplet_path):
    return f"sim:{triplet_path},size={SIZE}"


def _tree(root: Path) -> dict:
    """Every entry under root (links not followed): kind, and the bytes of regular files."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = os.lstat(p)
            rel = str(p.relative_to(root))
            if stat.S_ISLNK(st.st_mode):
                out[rel] = ("link", os.readlink(p))
            elif stat.S_ISDIR(st.st_mode):
                out[rel] = ("dir",)
            else:
                out[rel] = ("file", p.read_bytes())
    return out


def _run(argv, capsys):
    rc = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err


@pytest.fixture
def done(tmp_path, triplet_path, capsys):
    """A complete capture folder S (4 frames) and its argv."""
    argv = ["capture", *Z, "--camera", _cam(triplet_path), "--out", str(tmp_path / "S"), "--quiet"]
    assert main(argv) == 0
    capsys.readouterr()
    return tmp_path / "S", argv


# ---------------------------------------------------------------------------------------------- data loss (#12)
def test_a_folder_capture_did_not_make_is_never_deleted(tmp_path, triplet_path, capsys):
    """#12.1: an empty-frames stack.json beside the user's files used to be rmtree'd with exit 0."""
    x = tmp_path / "X"
    (x / "raw").mkdir(parents=True)
    (x / "stack.json").write_text('{"format":"fieldcal-stack/1","pixel_pitch_um":3.45,"channels":["Y"],"frames":[]}')
    (x / "NOTES.txt").write_text("notes\n")
    before = _tree(tmp_path)
    rc, err = _run(["capture", "--z", "-100", "100", "50", "--camera", _cam(triplet_path), "--out", str(x)], capsys)
    assert rc == 2 and "not a capture folder" in err and "fix:" in err
    assert _tree(tmp_path) == before


def test_frames_symlinked_elsewhere_loses_nothing(done, tmp_path, capsys):
    """#12.2: resume used to delete 'uncommitted' files through a frames/ link into another folder."""
    out, argv = done
    other = tmp_path / "other"
    other.mkdir()
    (other / "0001.tiff").write_bytes(b"someone else's frame")
    (other / "precious.txt").write_text("keep me")
    os.rename(out / "frames", tmp_path / "moved-frames")
    os.symlink(other, out / "frames")
    before = _tree(tmp_path)
    rc, err = _run(argv, capsys)
    assert rc == 2 and "frames/ is not a real folder" in err
    assert _tree(tmp_path) == before


def test_a_second_capture_into_the_same_folder_is_refused(done, capsys):
    """#12.7: the folder's flock is held by a running capture (here: by the test) -> exit 4, nothing written."""
    out, argv = done
    (out / "frames" / "0003.tiff").unlink()  # so the second run would have work to do
    before = _tree(out)
    fd = os.open(out, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        rc, err = _run(argv, capsys)
    finally:
        os.close(fd)
    assert rc == 4 and "another capture is writing into this folder" in err
    assert _tree(out) == before
    assert main(argv) == 0  # once the lock is free the capture resumes
    lines = (out / JOURNAL).read_text().splitlines()[1:]
    assert sorted(json.loads(l)["i"] for l in lines) == [0, 1, 2, 3, 3]  # frame 3 re-taken once, nothing doubled


def _journal_with(out: Path, mutate) -> None:
    lines = (out / JOURNAL).read_text().splitlines()
    lines = mutate(lines)
    (out / JOURNAL).write_text("".join(l + "\n" for l in lines))


def _entry(lines, k=1):
    return json.loads(lines[k])


def _set_file(path):
    def mutate(lines):
        e = _entry(lines)
        e["entry"]["file"] = path
        return [lines[0], json.dumps(e)] + lines[2:]
    return mutate


JOURNAL_CASES = {
    "outside the folder (#12.8)": (_set_file("../../outside.tiff"), "directly inside the capture's frames/ folder"),
    "absolute path": (_set_file("/etc/passwd"), "directly inside the capture's frames/ folder"),
    "another frame's file": (_set_file("frames/0001.tiff"), "must be 'frames/0000.tiff'"),
    "header []": (lambda lines: ["[]"] + lines[1:], "'line 1': must hold a JSON object"),
    "header of another format": (lambda lines: ['{"journal": "x/1"}'] + lines[1:], "unknown capture-journal format"),
    "entry without file": (lambda lines: [lines[0], json.dumps({"i": 0, "entry": {
        k: v for k, v in _entry(lines)["entry"].items() if k != "file"}})] + lines[2:], "'line 2.entry.file': is missing"),
    "entry without entry": (lambda lines: [lines[0], '{"i": 0}'] + lines[2:], "'line 2.entry': is missing"),
    "index out of range": (lambda lines: lines + [json.dumps({**_entry(lines), "i": 99})], "not a frame record"),
    "bool index": (lambda lines: lines + [json.dumps({**_entry(lines), "i": True})], "must be an integer, got true"),
    "z not the plan's": (lambda lines: [lines[0], json.dumps({"i": 0, "entry": {**_entry(lines)["entry"],
                                                                                "z_um": 5.0}})] + lines[2:],
                         "is not the plan's"),
    "sha256 not hex": (lambda lines: [lines[0], json.dumps({"i": 0, "entry": {**_entry(lines)["entry"],
                                                                              "sha256": "../x"}})] + lines[2:],
                       "'line 2.entry.sha256': must be 64 hex digits"),
    "an unknown field": (lambda lines: [lines[0], json.dumps({"i": 0, "entry": {**_entry(lines)["entry"],
                                                                                "cfa": "RGGB"}})] + lines[2:],
                         "field 'cfa' is unknown"),
    "a non-finite exposure": (lambda lines: [lines[0], json.dumps({"i": 0, "entry": {**_entry(lines)["entry"],
                                                                                     "exposure_ms": "abc"}})]
                              + lines[2:], "'line 2.entry.exposure_ms': must be a number"),
    "another frame's plan_index": (lambda lines: [lines[0], json.dumps({"i": 0, "entry": {
        **_entry(lines)["entry"], "plan_index": 2}})] + lines[2:], "plan_index 2 is not 0"),
    "not JSON in the middle": (lambda lines: [lines[0], "{not json"] + lines[1:], "'line 2': is not valid JSON"),
    "deeply nested": (lambda lines: lines[:1] + ["[" * 100000 + "]" * 100000] + lines[1:], "levels deep"),
}


@pytest.mark.parametrize("case", list(JOURNAL_CASES))
def test_crafted_journal_lines_are_refused(done, tmp_path, capsys, case):
    out, argv = done
    (out / "frames" / "0003.tiff").unlink()  # a resume with work to do
    (tmp_path / "outside.tiff").write_bytes(b"not yours")
    mutate, msg = JOURNAL_CASES[case]
    _journal_with(out, mutate)
    before = _tree(tmp_path)
    rc, err = _run(argv, capsys)
    assert rc == 2 and msg in err and "capture.journal" in err and "fix:" in err, err
    assert _tree(tmp_path) == before  # nothing in or out of --out changed


def _subfolder(out, tmp_path):
    (out / "frames" / "sub").mkdir()
    (out / "frames" / "sub" / "x.txt").write_text("x")


def _file_link_in_frames(out, tmp_path):
    (tmp_path / "target.tiff").write_bytes(b"elsewhere")
    os.symlink(tmp_path / "target.tiff", out / "frames" / "0004.tiff")


def _foreign_file_in_frames(out, tmp_path):
    (out / "frames" / "README.txt").write_text("mine")


def _journal_link(out, tmp_path):
    os.rename(out / JOURNAL, tmp_path / "j")
    os.symlink(tmp_path / "j", out / JOURNAL)


def _stack_json_link(out, tmp_path):
    os.rename(out / "stack.json", tmp_path / "s.json")
    os.symlink(tmp_path / "s.json", out / "stack.json")


def _frames_is_a_file(out, tmp_path):
    os.rename(out / "frames", tmp_path / "f")
    (out / "frames").write_text("x")


LAYOUT_CASES = {
    "a subfolder in frames/": (_subfolder, "frames/sub is a folder"),
    "a link in frames/": (_file_link_in_frames, "frames/0004.tiff is a symbolic link"),
    "a foreign file in frames/": (_foreign_file_in_frames, "frames/README.txt was not written by this capture"),
    "the journal is a link": (_journal_link, "capture.journal is not a regular file"),
    "stack.json is a link": (_stack_json_link, "stack.json is missing or not a regular file"),
    "frames is a file": (_frames_is_a_file, "frames/ is not a real folder"),
}


@pytest.mark.parametrize("case", list(LAYOUT_CASES))
def test_unexpected_entries_are_refused_before_anything_changes(done, tmp_path, capsys, case):
    out, argv = done
    (out / "frames" / "0002.tiff").unlink()
    make, msg = LAYOUT_CASES[case]
    make(out, tmp_path)
    before = _tree(tmp_path)
    rc, err = _run(argv, capsys)
    assert rc == 2 and msg in err and "nothing was changed" in err, err
    assert _tree(tmp_path) == before


def test_out_a_symlink_when_resuming_is_refused(done, tmp_path, capsys):
    out, argv = done
    (out / "frames" / "0001.tiff").unlink()
    link = tmp_path / "L"
    os.symlink(out, link)
    before = _tree(tmp_path)
    rc, err = _run([a if a != str(out) else str(link) for a in argv], capsys)
    assert rc == 2 and "symbolic link" in err
    assert _tree(tmp_path) == before


def test_out_a_file_is_refused(tmp_path, triplet_path, capsys):
    (tmp_path / "F").write_text("x")
    rc, err = _run(["capture", *Z, "--camera", _cam(triplet_path), "--out", str(tmp_path / "F")], capsys)
    assert rc == 2 and "not a folder" in err and (tmp_path / "F").read_text() == "x"


def test_read_only_parent_is_an_environment_error(tmp_path, triplet_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root ignores directory permissions")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        rc, err = _run(["capture", *Z, "--camera", _cam(triplet_path), "--out", str(ro / "S")], capsys)
    finally:
        ro.chmod(0o700)
    assert rc == 4 and "cannot create" in err


# ---------------------------------------------------------------------------------------------- numbers
NUMBER_CASES = {
    "--z +1e308": (["--z", "0", "1e308", "1"], "--z"),
    "--z -1e308": (["--z", "-1e308", "0", "1"], "--z"),
    "--z nan": (["--z", "nan", "10", "1"], "--z"),
    "--z step 0": (["--z", "0", "10", "0"], "--z"),
    "--z step inf": (["--z", "0", "10", "inf"], "--z"),
    "--z too many frames": (["--z", "-1000", "1000", "0.001"], "--z"),
    "--z wrong way": (["--z", "0", "10", "-1"], "--z"),
    "--settle-ms inf": ([*Z, "--settle-ms", "inf"], "--settle-ms"),
    "--settle-ms -1": ([*Z, "--settle-ms", "-1"], "--settle-ms"),
    "--on-target-timeout-ms nan": ([*Z, "--on-target-timeout-ms", "nan"], "--on-target-timeout-ms"),
    "--on-target-timeout-ms 0": ([*Z, "--on-target-timeout-ms", "0"], "--on-target-timeout-ms"),
    "--exposure-ms 0": ([*Z, "--exposure-ms", "0"], "--exposure-ms"),
    "--exposure-ms nan": ([*Z, "--exposure-ms", "nan"], "--exposure-ms"),
    "--exposure-ms -5": ([*Z, "--exposure-ms", "-5"], "--exposure-ms"),
    "--overshoot-um inf": ([*Z, "--overshoot-um", "inf"], "--overshoot-um"),
    "--overshoot-um -1": ([*Z, "--overshoot-um", "-1"], "--overshoot-um"),
    "--retries -1": ([*Z, "--retries", "-1"], "--retries"),
}


@pytest.mark.parametrize("case", list(NUMBER_CASES))
def test_bad_numbers_are_refused_naming_the_flag(tmp_path, triplet_path, capsys, case):
    args, flag = NUMBER_CASES[case]
    rc, err = _run(["capture", *args, "--camera", _cam(triplet_path), "--out", str(tmp_path / "S")], capsys)
    assert rc == 2 and f"field '{flag}'" in err and "fix:" in err, err
    assert not (tmp_path / "S").exists()


@pytest.mark.parametrize("value", ["1e400", "10" + "0" * 400, "NaN"])
def test_plan_file_numbers_floats_cannot_hold(tmp_path, triplet_path, capsys, value):
    p = tmp_path / "plan.json"
    p.write_text('{"format": "fieldcal-plan/1", "kind": "stack", "parameters": {}, "direction": "+z", '
                 f'"frames": [{{"z_um": 0}}, {{"z_um": {value}}}]}}')
    rc, err = _run(["capture", "--plan", str(p), "--camera", _cam(triplet_path), "--out", str(tmp_path / "S")],
                   capsys)
    assert rc == 2 and "plan.json" in err and "fix:" in err, err
    assert not (tmp_path / "S").exists()


@pytest.mark.parametrize("doc", ["[]", "{", "[" * 100000 + "]" * 100000, ""])
def test_malformed_plan_files(tmp_path, triplet_path, capsys, doc):
    p = tmp_path / "plan.json"
    p.write_text(doc)
    rc, err = _run(["capture", "--plan", str(p), "--camera", _cam(triplet_path), "--out", str(tmp_path / "S")],
                   capsys)
    assert rc == 2 and "plan.json" in err


def test_plan_that_is_a_folder(tmp_path, triplet_path, capsys):
    rc, err = _run(["capture", "--plan", str(tmp_path), "--camera", _cam(triplet_path), "--out",
                    str(tmp_path / "S")], capsys)
    assert rc == 2 and "plan" in err


@pytest.mark.parametrize("slot", ["-5", "0", "nan", "inf"])
def test_a_negative_slot_is_not_reported_as_exceeding_the_hold_limit(slot):
    from fieldcal.errors import ParameterError
    from fieldcal.plan.masks import make_device
    with pytest.raises(ParameterError) as e:
        make_device("lcos", 16.0, slot_ms=float(slot), max_hold_ms=20.0)
    assert "exceeds" not in str(e.value) and "must be a finite time > 0" in str(e.value)
    with pytest.raises(ParameterError, match="exceeds"):
        make_device("lcos", 40.0, slot_ms=40.0, max_hold_ms=20.0)


# ---------------------------------------------------------------------------------------------- SIGKILL
KILLER = r'''
import os, signal, sys
point, n, argv = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
import fieldcal.formats.stack as S
from fieldcal.capture import folder as F
from fieldcal.cli import main
calls = {"n": 0}
def due():
    calls["n"] += 1
    return calls["n"] == n
def die():
    os.kill(os.getpid(), signal.SIGKILL)
if point == "frame-temp":          # the frame's temporary file is written, not yet renamed
    real = S.atomic_write_bytes
    def f(path, data):
        if due():
            tmp = os.path.join(os.path.dirname(path), "." + os.path.basename(path) + ".k1ll3d.tmp")
            open(tmp, "wb").write(data[: len(data) // 2])
            die()
        real(path, data)
    S.atomic_write_bytes = f
elif point == "frame-renamed":     # the frame file is in place, stack.json does not list it yet
    real = S.atomic_write_text
    def f(path, text):
        if str(path).endswith("stack.json") and '"frames": []' not in text and due():
            die()
        real(path, text)
    S.atomic_write_text = f
elif point == "stack-written":     # stack.json lists the frame, the journal does not (before the commit point)
    real = F.CaptureFolder._append_journal
    def f(self, line):
        if due():
            die()
        real(self, line)
    F.CaptureFolder._append_journal = f
elif point == "journal-half":      # half a journal line is on disk
    real = F.CaptureFolder._append_journal
    def f(self, line):
        if due():
            with open(self.journal_path, "ab") as fh:
                fh.write(line.encode()[: len(line) // 2]); fh.flush(); os.fsync(fh.fileno())
            die()
        real(self, line)
    F.CaptureFolder._append_journal = f
elif point == "committed":         # right after the commit point
    real = F.CaptureFolder._append_journal
    def f(self, line):
        real(self, line)
        if due():
            die()
    F.CaptureFolder._append_journal = f
elif point == "resume-rewrite":    # a resume dies right after it rewrote stack.json
    real = F.atomic_write_text
    def f(path, text):
        real(path, text)
        if str(path).endswith("stack.json") and due():
            die()
    F.atomic_write_text = f
elif point == "pause":             # hold the run (and its lock) mid-capture until the test says go
    import time
    real = F.CaptureFolder._append_journal
    def f(self, line):
        if due():
            open(os.environ["FIELDCAL_TEST_READY"], "w").close()
            while not os.path.exists(os.environ["FIELDCAL_TEST_GO"]):
                time.sleep(0.01)
        real(self, line)
    F.CaptureFolder._append_journal = f
sys.exit(main(argv))
'''


def _start(point, n, argv, tmp_path, **env_extra):
    import subprocess
    import sys
    script = tmp_path / "killer.py"
    script.write_text(KILLER)
    env = {**os.environ, "FIELDCAL_PROGRESS": "0", "PYTHONPATH": str(Path(__file__).resolve().parents[1]),
           **env_extra}
    return subprocess.Popen([sys.executable, str(script), point, str(n), *argv], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _kill_at(point, n, argv, tmp_path):
    p = _start(point, n, argv, tmp_path)
    p.communicate(timeout=120)
    return p.returncode


def test_a_second_process_is_refused_while_the_first_runs(tmp_path, triplet_path, capsys):
    """#12.7 with two real processes: the first is held mid-capture (by a file, not by a clock)."""
    import time
    out = tmp_path / "S"
    argv = ["capture", *Z, "--camera", _cam(triplet_path), "--out", str(out), "--quiet"]
    ready, go = tmp_path / "ready", tmp_path / "go"
    first = _start("pause", 2, argv, tmp_path, FIELDCAL_TEST_READY=str(ready), FIELDCAL_TEST_GO=str(go))
    try:
        deadline = time.monotonic() + 120
        while not ready.exists():
            assert first.poll() is None, first.stderr.read()
            assert time.monotonic() < deadline
            time.sleep(0.01)
        before = _tree(out)
        rc, err = _run(argv, capsys)
        assert rc == 4 and "another capture is writing into this folder" in err
        assert _tree(out) == before
    finally:
        go.touch()
        first.communicate(timeout=120)
    assert first.returncode == 0
    lines = [json.loads(l)["i"] for l in (out / JOURNAL).read_text().splitlines()[1:]]
    assert lines == [0, 1, 2, 3]  # one line per frame: no duplicate from a second run
    _assert_complete_once(out, CapturePlan.from_range(0, 30, 10))


def _assert_complete_once(out: Path, plan: CapturePlan):
    s = Stack.open(out)
    assert sorted(f.z_um for f in s.frames) == sorted(plan.z_um.tolist())  # every frame, once
    assert s.verify_checksums() == []
    idx = [f.meta["plan_index"] for f in s.frames]
    assert sorted(idx) == list(range(len(plan.frames)))
    lines = [json.loads(l) for l in (out / JOURNAL).read_text().splitlines()[1:]]
    latest = {e["i"]: e["entry"] for e in lines}
    assert sorted(latest) == list(range(len(plan.frames)))
    for f in s.frames:  # stack.json and journal agree on every frame, and the bytes are the journal's
        assert latest[f.meta["plan_index"]]["sha256"] == f.meta["sha256"] == \
            hashlib.sha256(f.path.read_bytes()).hexdigest()
    assert sorted(os.listdir(out / "frames")) == [f"{i:04d}.tiff" for i in range(len(plan.frames))]
    assert not [n for n in os.listdir(out) if n.endswith(".tmp")]


@pytest.mark.parametrize("point,n", [("frame-temp", 2), ("frame-renamed", 3), ("stack-written", 2),
                                     ("journal-half", 3), ("committed", 1), ("resume-rewrite", 1)])
def test_a_killed_capture_resumes_with_no_frame_lost_or_doubled(tmp_path, triplet_path, point, n):
    out = tmp_path / "S"
    argv = ["capture", *Z, "--camera", _cam(triplet_path), "--out", str(out), "--quiet"]
    plan = CapturePlan.from_range(0, 30, 10)
    if point == "resume-rewrite":  # first a crash that leaves stack.json listing an uncommitted frame
        assert _kill_at("stack-written", 2, argv, tmp_path) == -9
    rc = _kill_at(point, n, argv, tmp_path)
    assert rc == -9  # SIGKILL
    listed = json.loads((out / "stack.json").read_text())["frames"]  # stack.json parses at every moment
    assert all((out / e["file"]).is_file() for e in listed)              # and lists only complete files
    assert main(argv) == 0
    _assert_complete_once(out, plan)
    before = _tree(out)
    assert main(argv) == 0  # complete: a re-run changes nothing
    assert _tree(out) == before


def test_a_full_disk_is_an_environment_error_and_the_folder_resumes(tmp_path, triplet_path, capsys, monkeypatch):
    import errno

    import fieldcal.formats.stack as S
    real, calls = S.atomic_write_bytes, {"n": 0}

    def full(path, data):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, data)

    monkeypatch.setattr(S, "atomic_write_bytes", full)
    argv = ["capture", *Z, "--camera", _cam(triplet_path), "--out", str(tmp_path / "S"), "--quiet"]
    rc, err = _run(argv, capsys)
    assert rc == 4 and "No space left on device" in err and "re-run the same command" in err
    monkeypatch.setattr(S, "atomic_write_bytes", real)
    assert main(argv) == 0
    _assert_complete_once(tmp_path / "S", CapturePlan.from_range(0, 30, 10))


def test_permission_denied_creating_out_is_an_environment_error(tmp_path, triplet_path, capsys, monkeypatch):
    """The same case as the read-only parent, simulated (the test suite may run as root)."""
    import errno

    def denied(self, *a, **k):
        raise PermissionError(errno.EACCES, "Permission denied", str(self))

    monkeypatch.setattr(Path, "mkdir", denied)
    before = _tree(tmp_path)
    rc, err = _run(["capture", *Z, "--camera", _cam(triplet_path), "--out", str(tmp_path / "S")], capsys)
    assert rc == 4 and "Permission denied" in err and "permissions" in err
    assert _tree(tmp_path) == before
