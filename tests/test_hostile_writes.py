"""Hostile input, writes side (issue 12): links, inputs as outputs, overwrites, profile+sidecar, faults.

Every case asserts: the documented exit status, a what/where/fix message, no traceback, no byte changed
outside the command's outputs (the whole tree is hashed before and after), no input modified, and no partial
output under a final name.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from fieldcal.cli import main
from fieldcal.errors import (EXIT_BAD_INPUT, EXIT_ENVIRONMENT, EXIT_INTERNAL, EXIT_INTERRUPTED, FieldcalError,
                             OutputError)
from fieldcal.formats import atomic
from fieldcal.profile.lens_profile import LensProfile

from hostile_safety_util import (FS, LENS, assert_clean_failure, changed, no_temp_files, only_under, run_cli,
                                 snapshot)


def sidecar_of(profile: Path) -> Path:
    return profile.with_name(json.loads(profile.read_text())["sidecar"]["file"])


def refused(w: Path, argv, capsys, *needles, code=EXIT_BAD_INPUT):
    """The command fails cleanly and changes nothing at all."""
    before = snapshot(w)
    rc, err = run_cli(argv, capsys)
    assert_clean_failure(rc, err, code, *needles)
    assert changed(before, snapshot(w)) == set(), "a refused command changed files"
    return err


# --------------------------------------------------------------------------------- symbolic links


@pytest.mark.parametrize("name", ["surfaces.png", "index.html", "tolerance.png"])
@pytest.mark.parametrize("overwrite", [False, True])
def test_report_refuses_a_link_at_an_output_name(w, capsys, name, overwrite):
    victim = w / "victim.txt"
    victim.write_text("precious")
    (w / "R").mkdir()
    (w / "R" / name).symlink_to(victim)
    refused(w, ["report", w / "lens.json", "--out", w / "R", *(["--overwrite"] if overwrite else [])], capsys,
            "symbolic link", name)
    assert victim.read_text() == "precious"


def test_report_ignores_planted_predictable_temp_names(w, capsys):
    victim = w / "victim.txt"
    victim.write_text("precious")
    (w / "R").mkdir()
    for name in ("surfaces", "bands", "residuals", "geometry", "tolerance"):  # the old fixed temporary names
        (w / "R" / f".{name}.png.tmp.png").symlink_to(victim)
    before = snapshot(w)
    rc, err = run_cli(["report", w / "lens.json", "--out", w / "R"], capsys)
    assert rc == 0, err
    assert victim.read_text() == "precious"
    assert only_under(changed(before, snapshot(w)), ["R"])
    assert all(p.is_symlink() and p.name.endswith(".tmp.png") for p in no_temp_files(w / "R"))  # the planted
    assert (w / "R" / "index.html").is_file() and not (w / "R" / "index.html").is_symlink()


@pytest.mark.parametrize("argv_out", [
    ("calibrate", "lens2.json"), ("plan-stack", "plan.json"), ("plan-sweep", "sweep.json"),
    ("composite", "c.tiff")])
def test_every_writer_refuses_a_link_at_out(w, capsys, argv_out):
    cmd, name = argv_out
    victim = w / "victim.txt"
    victim.write_text("precious")
    (w / name).symlink_to(victim)
    argv = {"calibrate": ["calibrate", w / "S", "--out", w / name, "--fs", FS, "--effort", "quick", "-q"],
            "plan-stack": ["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.05", "--out", w / name],
            "plan-sweep": ["plan", "sweep", LENS, "--alpha-um", "20", "--pixel-exposure-ms", "16", "--size",
                           "96x54", "--out", w / name],
            "composite": ["composite", w / "S", "--profile", w / "lens.json", "--out", w / name]}[cmd]
    refused(w, [*argv, "--overwrite"], capsys, "symbolic link")
    assert victim.read_text() == "precious"


@pytest.mark.parametrize("name", ["summary.json", "compare.png"])
def test_demo_refuses_links_at_its_own_files(w, capsys, name):
    victim = w / "victim.txt"
    victim.write_text("precious")
    (w / "D").mkdir()
    (w / "D" / name).symlink_to(victim)
    refused(w, ["demo", "--out", w / "D", "--overwrite"], capsys, "symbolic link", name)
    assert victim.read_text() == "precious"


def test_demo_refuses_a_folder_holding_its_lens(w, capsys):
    (w / "D").mkdir()
    shutil.copy(LENS, w / "D" / "lens-spec.json")
    (w / "D" / "summary.json").symlink_to(w / "D" / "lens-spec.json")
    refused(w, ["demo", "--out", w / "D", "--lens", w / "D" / "lens-spec.json", "--overwrite"], capsys,
            "input")


# ----------------------------------------------------------------------------- inputs as outputs


@pytest.mark.parametrize("overwrite", [False, True])
@pytest.mark.parametrize("kind", ["stack", "sweep"])
def test_plan_never_writes_over_its_profile(w, capsys, overwrite, kind):
    extra = ["--fs", FS, "--q", "0.05"] if kind == "stack" else ["--alpha-um", "20", "--pixel-exposure-ms", "16"]
    refused(w, ["plan", kind, w / "lens.json", *extra, "--out", w / "lens.json",
                *(["--overwrite"] if overwrite else [])], capsys, "input", "lens.json")
    LensProfile.load(w / "lens.json")


def test_plan_never_writes_over_the_profile_sidecar(w, capsys):
    side = sidecar_of(w / "lens.json")
    refused(w, ["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.05", "--out", side, "--overwrite"],
            capsys, "input")


def test_plan_refuses_an_existing_stack_json_without_overwrite(w, capsys):
    refused(w, ["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.05", "--out", w / "S" / "stack.json"],
            capsys, "exists", "--overwrite")


def test_plan_refuses_an_existing_plan_then_replaces_it_with_overwrite(w, capsys):
    argv = ["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.05", "--out", w / "plan.json"]
    assert run_cli(argv, capsys)[0] == 0
    old = (w / "plan.json").read_bytes()
    os.chmod(w / "plan.json", 0o640)
    refused(w, argv, capsys, "exists")
    before = snapshot(w)
    rc, err = run_cli([*argv, "--q", "0.1", "--overwrite"], capsys)
    assert rc == 0, err
    assert (w / "plan.json").read_bytes() != old
    assert (w / "plan.json").stat().st_mode & 0o777 == 0o640  # the mode of what it replaced
    assert changed(before, snapshot(w)) == {"plan.json"}


@pytest.mark.parametrize("overwrite", [False, True])
def test_composite_never_replaces_a_frame_of_its_stack(w, capsys, overwrite):
    refused(w, ["composite", w / "S", "--profile", w / "lens.json", "--out", w / "S" / "frames" / "0002.tiff",
                *(["--overwrite"] if overwrite else [])], capsys, "input")


@pytest.mark.parametrize("target", ["S", "lens.json"])
def test_composite_never_writes_over_stack_or_profile(w, capsys, target):
    out = w / target
    refused(w, ["composite", w / "S", "--profile", w / "lens.json", "--out", out, "--overwrite"], capsys)


def test_composite_onto_an_existing_file_needs_overwrite(w, capsys):
    (w / "c.tiff").write_bytes(b"an older composite")
    refused(w, ["composite", w / "S", "--profile", w / "lens.json", "--out", w / "c.tiff"], capsys, "exists",
            "--overwrite")
    before = snapshot(w)
    rc, err = run_cli(["composite", w / "S", "--profile", w / "lens.json", "--out", w / "c.tiff", "--overwrite",
                       "--quiet"], capsys)
    assert rc == 0, err
    assert changed(before, snapshot(w)) == {"c.tiff"}
    assert not no_temp_files(w)


def test_composite_sweep_image_is_an_input(w, capsys):
    img = w / "sweep.tiff"
    shutil.copy(w / "S" / "frames" / "0003.tiff", img)
    refused(w, ["composite", img, "--profile", w / "lens.json", "--sweep-alpha-um", "20", "--out", img,
                "--overwrite"], capsys, "input")


@pytest.mark.parametrize("out", ["S/lens.json", "S/frames/x.json", "S/stack.json"])
def test_calibrate_never_writes_into_its_stack(w, capsys, out):
    refused(w, ["calibrate", w / "S", "--out", w / out, "--fs", FS, "--effort", "quick", "-q", "--overwrite"],
            capsys, "input")


def test_calibrate_report_inside_the_stack_is_refused_before_any_work(w, capsys):
    refused(w, ["calibrate", w / "S", "--out", w / "new.json", "--fs", FS, "--effort", "quick", "-q",
                "--report", w / "S" / "report"], capsys, "input")
    assert not (w / "new.json").exists()


def test_calibrate_refuses_an_existing_profile(w, capsys):
    refused(w, ["calibrate", w / "S", "--out", w / "lens.json", "--fs", FS, "--effort", "quick", "-q"], capsys,
            "exists", "--overwrite")


def test_report_refuses_existing_report_files_without_overwrite(w, capsys):
    (w / "R").mkdir()
    (w / "R" / "index.html").write_text("<p>my notes</p>")
    refused(w, ["report", w / "lens.json", "--out", w / "R"], capsys, "exists", "--overwrite")


def test_report_into_the_profile_folder_leaves_the_profile(w, capsys):
    before = snapshot(w)
    rc, err = run_cli(["report", w / "lens.json", "--out", w], capsys)
    assert rc == 0, err
    diff = changed(before, snapshot(w))
    assert diff and all(Path(p).name in ("surfaces.png", "bands.png", "residuals.png", "geometry.png",
                                         "tolerance.png", "index.html") for p in diff)
    LensProfile.load(w / "lens.json")


def test_simulate_overwrite_never_deletes_its_lens_spec(w, capsys):
    spec = w / "S" / "my-lens.json"
    shutil.copy(LENS, spec)
    refused(w, ["simulate", spec, w / "S", "--z", "-100", "100", "50", "--size", "64x36", "--overwrite"],
            capsys, "input")
    assert spec.is_file()


def test_lens_from_prescription_never_overwrites_its_table(w, capsys):
    table = w / "rx.csv"
    shutil.copy(LENS.with_name("triplet-uncorrected.prescription.csv"), table)
    refused(w, ["lens", "from-prescription", table, "--out", table, "--overwrite"], capsys, "input")


def test_a_write_inside_a_protected_input_is_refused(tmp_path):
    """The guard is in the write helper too, so a writer that forgets check_output still cannot do harm."""
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "a.txt").write_text("x")
    with atomic.command_scope():
        atomic.protect(tmp_path / "in")
        with pytest.raises(OutputError, match="input"):
            atomic.write_text(tmp_path / "in" / "a.txt", "y")
        with pytest.raises(OutputError, match="input"):
            atomic.write_text(tmp_path / "in" / "new.txt", "y")
        atomic.write_text(tmp_path / "out.txt", "y")
    atomic.write_text(tmp_path / "in" / "new.txt", "y")  # outside the command, nothing is protected
    assert (tmp_path / "in" / "a.txt").read_text() == "x"


# ------------------------------------------------------------------------- profile and sidecar


def test_case_only_collision_is_refused(w, capsys):
    (w / "d").mkdir()
    for f in ("lens.json", sidecar_of(w / "lens.json").name):
        shutil.copy(w / f, w / "d" / f.replace("lens", "a"))
    d = json.loads((w / "d" / "a.json").read_text())
    d["sidecar"]["file"] = d["sidecar"]["file"].replace("lens", "a")
    (w / "d" / "a.json").write_text(json.dumps(d))
    LensProfile.load(w / "d" / "a.json")
    for ow in ([], ["--overwrite"]):
        refused(w, ["calibrate", w / "S", "--out", w / "d" / "a.JSON", "--fs", FS, "--effort", "quick", "-q",
                    *ow], capsys, "differs only in case", "a.json")
    LensProfile.load(w / "d" / "a.json")


def test_sidecar_names_are_content_addressed_and_never_shared(w):
    p = LensProfile.load(w / "lens.json")
    a = p.save(w / "x" / "a.json")
    p.surfaces.samples = p.surfaces.samples + 0.25  # other content -> other sidecar name
    b = p.save(w / "x" / "a.JSON")
    assert sidecar_of(a) != sidecar_of(b)
    LensProfile.load(a)
    LensProfile.load(b)


def test_resave_removes_the_old_sidecar_and_orphans_but_not_a_shared_one(w):
    p = LensProfile.load(w / "lens.json")
    out = w / "x" / "a.json"
    p.save(out)
    first = sidecar_of(out)
    shutil.copy(out, w / "x" / "copy.json")  # another profile naming the same sidecar
    orphan = w / "x" / "a.0123456789abcdef.samples.npz"  # what a killed save leaves
    orphan.write_bytes(b"orphan")
    foreign = w / "x" / "notes.samples.npz"
    foreign.write_bytes(b"not ours")
    p.surfaces.samples = p.surfaces.samples + 1.0
    p.save(out)
    assert sidecar_of(out) != first
    assert first.is_file(), "a sidecar another profile names was removed"
    assert not orphan.exists() and foreign.exists()
    LensProfile.load(w / "x" / "copy.json")
    LensProfile.load(out)
    (w / "x" / "copy.json").unlink()
    p.surfaces.samples = p.surfaces.samples + 1.0
    p.save(out)
    assert not first.exists()  # no longer named by anyone: removed after the new JSON is in place
    assert sorted(f.name for f in (w / "x").iterdir()) == sorted(["a.json", sidecar_of(out).name,
                                                                  "notes.samples.npz"])


@pytest.mark.parametrize("tamper", ["no-sha", "bad-sha", "short-sha", "no-sidecar", "null-sidecar",
                                    "samples-edited", "sidecar-deleted", "file-traversal", "file-empty"])
def test_profile_sidecar_tampering_is_refused(w, capsys, tamper):
    js = w / "lens.json"
    d = json.loads(js.read_text())
    side = js.with_name(d["sidecar"]["file"])
    if tamper == "no-sha":
        del d["sidecar"]["sha256"]
    elif tamper == "bad-sha":
        d["sidecar"]["sha256"] = "0" * 64
    elif tamper == "short-sha":
        d["sidecar"]["sha256"] = "abc"
    elif tamper == "no-sidecar":
        del d["sidecar"]
    elif tamper == "null-sidecar":
        d["sidecar"] = None
    elif tamper == "samples-edited":
        side.write_bytes(side.read_bytes()[:-8] + b"\0" * 8)
    elif tamper == "sidecar-deleted":
        side.unlink()
    elif tamper == "file-traversal":
        d["sidecar"]["file"] = "../../etc/passwd"
    elif tamper == "file-empty":
        d["sidecar"]["file"] = ""
    js.write_text(json.dumps(d))
    refused(w, ["report", js, "--out", w / "R"], capsys, "sidecar")


def test_no_sha_case_would_have_used_tampered_samples(w):
    """Closed form of the issue's case: with the hash deleted and the samples edited, load refuses."""
    js = w / "lens.json"
    d = json.loads(js.read_text())
    del d["sidecar"]["sha256"]
    js.write_text(json.dumps(d))
    side = js.with_name(d["sidecar"]["file"])
    side.write_bytes(side.read_bytes()[:-8] + b"\0" * 8)
    with pytest.raises(Exception, match="sha256"):
        LensProfile.load(js)


# ---------------------------------------------------------------------------- file-system faults


FAULTS = [(errno.ENOSPC, "space"), (errno.EDQUOT, "quota"), (errno.EROFS, "writable"),
          (errno.EACCES, "permission"), (errno.EIO, "disk")]


@pytest.mark.parametrize("err_no,needle", FAULTS)
@pytest.mark.parametrize("cmd", ["calibrate", "plan", "report"])
def test_disk_faults_exit_4_and_leave_the_old_outputs(w, capsys, monkeypatch, err_no, needle, cmd):
    argv = {"calibrate": ["calibrate", w / "S", "--out", w / "lens.json", "--fs", FS, "--effort", "quick", "-q",
                          "--seed", "3", "--overwrite"],
            "plan": ["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.05", "--out", w / "lens-plan.json"],
            "report": ["report", w / "lens.json", "--out", w / "R"]}[cmd]
    before = snapshot(w)

    def fail(fd):
        raise OSError(err_no, os.strerror(err_no))

    monkeypatch.setattr(os, "fsync", fail)
    rc, err = run_cli(argv, capsys)
    assert_clean_failure(rc, err, EXIT_ENVIRONMENT, needle)
    monkeypatch.undo()
    after = snapshot(w)
    diff = changed(before, after)
    # nothing changed except, for report, the folder it created; never a temp file, never a half output
    assert only_under(diff, ["R"]) and not no_temp_files(w)
    assert all(after[p][0] == "dir" for p in diff)
    LensProfile.load(w / "lens.json")


def test_read_only_folder_at_create_time(w, capsys, monkeypatch):
    real_open = os.open

    def ro(path, flags, *a, **k):
        if flags & os.O_CREAT:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_open(path, flags, *a, **k)

    monkeypatch.setattr(os, "open", ro)
    before = snapshot(w)
    rc, err = run_cli(["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.05", "--out", w / "p.json"], capsys)
    monkeypatch.undo()
    assert_clean_failure(rc, err, EXIT_ENVIRONMENT, "read-only", "p.json")
    assert changed(before, snapshot(w)) == set()


@pytest.mark.parametrize("cmd", ["calibrate", "plan", "composite"])
def test_out_that_is_a_folder(w, capsys, cmd):
    (w / "o.json").mkdir()
    (w / "o.tiff").mkdir()
    argv = {"calibrate": ["calibrate", w / "S", "--out", w / "o.json", "--fs", FS, "--overwrite"],
            "plan": ["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.05", "--out", w / "o.json",
                     "--overwrite"],
            "composite": ["composite", w / "S", "--out", w / "o.tiff", "--overwrite"]}[cmd]
    refused(w, argv, capsys, "folder")


@pytest.mark.parametrize("cmd", ["calibrate", "calibrate-report", "plan", "plan-plots", "composite", "report"])
def test_out_whose_parent_is_a_file(w, capsys, cmd):
    f = w / "afile"
    f.write_text("x")
    argv = {"calibrate": ["calibrate", w / "S", "--out", f / "l.json", "--fs", FS],
            "calibrate-report": ["calibrate", w / "S", "--out", w / "new.json", "--fs", FS, "--effort", "quick",
                                 "-q", "--report", f / "rep"],
            "plan": ["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.05", "--out", f / "p.json"],
            "plan-plots": ["plan", "stack", w / "lens.json", "--fs", FS, "--q", "0.05", "--out", w / "p.json",
                           "--plots", f / "pl"],
            "composite": ["composite", w / "S", "--out", f / "c.tiff"],
            "report": ["report", w / "lens.json", "--out", f / "R"]}[cmd]
    refused(w, argv, capsys, "afile")
    assert not (w / "new.json").exists() and not (w / "p.json").exists()


def test_report_out_that_is_a_file(w, capsys):
    (w / "R").write_text("not a folder")
    refused(w, ["report", w / "lens.json", "--out", w / "R"], capsys, "not a folder")


# ----------------------------------------------------------------------------- the top-level handler


def test_unexpected_exception_is_exit_5_with_a_short_message(w, capsys, monkeypatch):

    def bug(*a, **k):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr("fieldcal.profile.lens_profile.load_profile_or_truth", bug)
    before = snapshot(w)
    rc, err = run_cli(["report", w / "lens.json", "--out", w / "R"], capsys)
    assert rc == EXIT_INTERNAL
    assert "Traceback" not in err and "fieldcal report" in err and "--debug" in err and "ZeroDivisionError" in err
    assert changed(before, snapshot(w)) == set()
    with pytest.raises(ZeroDivisionError):  # --debug: the traceback, anywhere on the line
        main(["report", str(w / "lens.json"), "--out", str(w / "R"), "--debug"])


@pytest.mark.parametrize("exc,code", [(MemoryError(), EXIT_ENVIRONMENT), (KeyboardInterrupt(), EXIT_INTERRUPTED),
                                      (RecursionError("deep"), EXIT_BAD_INPUT),
                                      (OSError(errno.ENOSPC, "No space left on device"), EXIT_ENVIRONMENT),
                                      (OSError(errno.ENOENT, "No such file or directory", "x"), EXIT_BAD_INPUT),
                                      (PermissionError(errno.EACCES, "Permission denied", "y"), EXIT_ENVIRONMENT)])
def test_failure_classes_map_to_documented_codes(w, capsys, monkeypatch, exc, code):

    def boom(*a, **k):
        raise exc

    monkeypatch.setattr("fieldcal.profile.lens_profile.load_profile_or_truth", boom)
    rc, err = run_cli(["report", w / "lens.json", "--out", w / "R"], capsys)
    assert rc == code, err
    assert "Traceback" not in err and "fieldcal report" in err


def test_docs_list_every_exit_code():
    from fieldcal import errors
    text = (Path(__file__).resolve().parents[1] / "docs" / "safety.md").read_text()
    for name in ("EXIT_OK", "EXIT_CHECK_FAILED", "EXIT_BAD_INPUT", "EXIT_DEVICE", "EXIT_ENVIRONMENT",
                 "EXIT_INTERNAL", "EXIT_INTERRUPTED"):
        assert f"| {getattr(errors, name)} |" in text, name


def test_real_process_exit_codes_and_no_traceback(w):
    import subprocess
    import sys
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    r = subprocess.run([sys.executable, "-m", "fieldcal", "plan", "stack", str(w / "lens.json"), "--fs", FS,
                        "--q", "0.05", "--out", str(w / "lens.json"), "--overwrite"], capture_output=True, text=True,
                       env=env)
    assert r.returncode == EXIT_BAD_INPUT and "Traceback" not in r.stderr and "fix:" in r.stderr


# ------------------------------------------------------------------------------- the write helper


def test_write_keeps_the_mode_and_refuses_links_and_folders(tmp_path):
    p = tmp_path / "a.txt"
    atomic.write_text(p, "one")
    assert p.stat().st_mode & 0o777 == 0o666 & ~atomic._umask()
    os.chmod(p, 0o604)
    atomic.write_text(p, "two")
    assert p.read_text() == "two" and p.stat().st_mode & 0o777 == 0o604
    (tmp_path / "link").symlink_to(p)
    with pytest.raises(OutputError, match="symbolic link"):
        atomic.write_text(tmp_path / "link", "three")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    with pytest.raises(OutputError, match="symbolic link"):
        atomic.write_text(tmp_path / "dangling", "three")
    assert not (tmp_path / "nowhere").exists() and p.read_text() == "two"
    (tmp_path / "d").mkdir()
    with pytest.raises(OutputError, match="folder"):
        atomic.write_text(tmp_path / "d", "x")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.txt", "d", "dangling", "link"]


def test_temp_names_are_unpredictable_and_exclusive(tmp_path, monkeypatch):
    names = []
    real = os.open

    def spy(path, flags, *a, **k):
        if flags & os.O_CREAT:
            names.append(Path(path).name)
            assert flags & os.O_EXCL and flags & os.O_NOFOLLOW
        return real(path, flags, *a, **k)

    monkeypatch.setattr(os, "open", spy)
    for _ in range(3):
        atomic.write_bytes(tmp_path / "x.bin", b"1")
    assert len(set(names)) == 3 and all(n.startswith(".x.bin.") and n.endswith(".tmp") for n in names)


def test_check_output_is_the_composite_helper(w):
    from fieldcal.composite.io import check_composite_output
    with pytest.raises(OutputError, match="input"):
        check_composite_output(w / "S" / "frames" / "0000.tiff", stack=w / "S", overwrite=True)
    with pytest.raises(FieldcalError, match=r"\.tiff, \.png or \.jpg"):
        check_composite_output(w / "c.bmp", stack=w / "S")
    assert check_composite_output(w / "c.tiff", stack=w / "S", profile=w / "lens.json") == w / "c.tiff"


def test_sha_helper_round_trip(w):
    """The provenance hash is stack.json plus every frame's content (closed form, recomputed here)."""
    d = json.loads((w / "lens.json").read_text())
    h = hashlib.sha256((w / "S" / "stack.json").read_bytes())
    for f in json.loads((w / "S" / "stack.json").read_text())["frames"]:
        h.update(hashlib.sha256((w / "S" / f["file"]).read_bytes()).digest())
    assert d["provenance"]["inputs_sha256"] == h.hexdigest()


# ------------------------------------------------------------------------- the other commands' folders


@pytest.mark.parametrize("cmd", ["targets", "validate", "demo", "simulate"])
def test_folder_outputs_that_are_files(w, capsys, cmd):
    f = w / "afile"
    f.write_text("x")
    argv = {"targets": ["targets", "--out", f, "--kind", "texture", "--size-mm", "A5", "--dpi", "50"],
            "validate": ["validate", LENS, "--out", f, "--effort", "quick"],
            "demo": ["demo", "--out", f],
            "simulate": ["simulate", LENS, f, "--z", "-50", "50", "50", "--size", "64x36"]}[cmd]
    refused(w, argv, capsys, "afile")


def test_validate_refuses_a_link_at_its_report_before_any_work(w, capsys):
    victim = w / "victim.txt"
    victim.write_text("precious")
    (w / "V").mkdir()
    (w / "V" / "summary.json").symlink_to(victim)
    refused(w, ["validate", LENS, "--out", w / "V", "--effort", "quick"], capsys, "symbolic link")


def test_composite_case_twin_is_refused(w, capsys):
    (w / "c.tiff").write_bytes(b"older")
    refused(w, ["composite", w / "S", "--profile", w / "lens.json", "--out", w / "C.TIFF"], capsys,
            "differs only in case")


def test_usage_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as e:
        main(["calibrate", "--no-such-option"])
    assert e.value.code == EXIT_BAD_INPUT
