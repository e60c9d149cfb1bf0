"""Hostile input, session 16 audit: gaps found by attacking every command with tiny inputs.

Each test is the regression test of one defect the audit found (it failed before the fix). Inputs are tiny
(64x48 images, a 96x64 simulated stack of 5 frames) so the file runs in seconds. Every case asserts the
documented exit status, a what/where/fix message without a traceback, and that no input byte changed.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from fieldcal.errors import EXIT_BAD_INPUT

from hostile_safety_util import (LENS, assert_clean_failure, changed, no_temp_files, only_under, run_cli,
                                 snapshot)


@pytest.fixture(scope="module")
def tiny_world(tmp_path_factory):
    """J/img0-3.png and .jpg (64x48 RGB noise) and S, a 96x64 simulated stack of 5 frames."""
    from fieldcal.cli import main

    root = tmp_path_factory.mktemp("audit-world")
    (root / "J").mkdir()
    rng = np.random.default_rng(0)
    for k in range(4):
        im = (rng.random((48, 64, 3)) * 255).astype(np.uint8)
        cv2.imwrite(str(root / "J" / f"img{k}.png"), im)
        cv2.imwrite(str(root / "J" / f"img{k}.jpg"), im)
    assert main(["simulate", str(LENS), str(root / "S"), "--z", "-100", "100", "50", "--size", "96x64",
                 "--quiet"]) == 0
    return root


@pytest.fixture
def t(tiny_world, tmp_path):
    from conftest import private_copy

    return private_copy(tiny_world, tmp_path, "t")


def refused(root: Path, argv, capsys, *needles, code=EXIT_BAD_INPUT) -> str:
    before = snapshot(root)
    rc, err = run_cli(argv, capsys)
    assert_clean_failure(rc, err, code, *needles)
    assert changed(before, snapshot(root)) == set(), "a refused command changed files"
    return err


# ------------------------------------------------------------------------------------ fieldcal mtf


def test_mtf_refuses_out_over_its_input_image(t, capsys):
    """Before: `mtf img.png --out img.png` replaced the measured image with the JSON (the input was lost)."""
    refused(t, ["mtf", t / "J" / "img0.png", "--out", t / "J" / "img0.png"], capsys, "--out", "input", "img0.png")


@pytest.mark.parametrize("flag,target", [("--out", "S/m.json"), ("--plots", "S/frames")])
def test_mtf_refuses_outputs_inside_the_stack(t, capsys, flag, target):
    """Before: the JSON and the plots were written into the stack folder measured."""
    argv = ["mtf", t / "S", "--out", t / "m.json", "--quiet"]
    if flag == "--out":
        argv[3] = t / target
    else:
        argv += ["--plots", t / target]
    refused(t, argv, capsys, flag, "inside the input")


def test_mtf_needs_overwrite_to_replace_an_output(t, capsys):
    """Before: an existing --out (and --plots pictures) were replaced silently; mtf had no --overwrite."""
    img, out, plots = t / "J" / "img0.png", t / "m.json", t / "plots"
    rc, err = run_cli(["mtf", img, "--out", out, "--plots", plots, "--quiet"], capsys)
    assert rc == 0, err
    refused(t, ["mtf", img, "--out", out, "--quiet"], capsys, "exists", "--overwrite")
    refused(t, ["mtf", img, "--out", t / "m2.json", "--plots", plots, "--quiet"], capsys, "--plots", "exists")
    rc, err = run_cli(["mtf", img, "--out", out, "--plots", plots, "--overwrite", "--quiet"], capsys)
    assert rc == 0, err


def test_mtf_plots_never_write_through_a_planted_temporary_name(t, capsys):
    """Before: the plots went through the fixed temporary name .mtf50_field.png.tmp.png, following a link
    planted there (a file outside the output folder was overwritten)."""
    victim = t / "victim.txt"
    victim.write_text("precious")
    plots = t / "plots"
    plots.mkdir()
    (plots / ".mtf50_field.png.tmp.png").symlink_to(victim)
    rc, err = run_cli(["mtf", t / "J" / "img0.png", "--out", t / "m.json", "--plots", plots, "--quiet"], capsys)
    assert rc == 0, err
    assert victim.read_text() == "precious"
    assert (plots / "mtf50_field.png").is_file() and not (plots / "mtf50_field.png").is_symlink()
    assert cv2.imread(str(plots / "mtf50_field.png")) is not None


@pytest.mark.parametrize("centre", ["nan,nan", "inf,3", "1e400,2"])
def test_mtf_refuses_a_non_finite_centre(t, capsys, centre):
    """Before: --centre nan,nan was taken, and every edge's tangential/sagittal split was silently wrong."""
    refused(t, ["mtf", t / "J" / "img0.png", "--out", t / "m.json", "--centre", centre], capsys, "--centre",
            "finite")


# ----------------------------------------------------------------- outputs over a linked stack's frames


@pytest.mark.parametrize("link", ["symlink", "hard"])
@pytest.mark.parametrize("command", ["composite", "mtf"])
def test_no_output_over_the_camera_file_a_linked_frame_is(t, capsys, link, command):
    """Before: after `import --link symlink`, `composite STACK --out <a camera file> --overwrite` replaced the
    camera file the stack's frame links to (the stack folder was protected, the data it points to was not)."""
    jpgs = sorted((t / "J").glob("*.jpg"))
    rc, err = run_cli(["import", *jpgs, "--out", t / "I", "--z", "0", "20", "--pixel-pitch-um", "5", "--link", link,
                       "--quiet"], capsys)
    assert rc == 0, err
    victim = jpgs[1]
    argv = [command, t / "I", "--out", victim, "--overwrite", "--quiet"]
    refused(t, argv, capsys, "--out", victim.name, "input")
    # a fresh output beside them is still fine
    out = t / ("c.jpg" if command == "composite" else "m.json")
    rc, err = run_cli([command, t / "I", "--out", out, "--quiet"], capsys)
    assert rc == 0, err


# --------------------------------------------------------------------------------- fieldcal import


def _import(t, images, *extra):
    return ["import", *images, "--out", t / "I", "--z", "0", "20", "--pixel-pitch-um", "5", *extra]


def test_import_names_out_when_its_parent_is_a_file(t, capsys):
    """Before: 'fieldcal import ... --out notes.txt/I' said '<abs path>/notes.txt: File exists' with the fix
    'choose another name (or add --overwrite)', which does not help, and named no option."""
    (t / "notes.txt").write_text("mine")
    jpgs = sorted((t / "J").glob("*.jpg"))
    argv = ["import", *jpgs, "--out", t / "notes.txt" / "I", "--z", "0", "20", "--pixel-pitch-um", "5"]
    err = refused(t, argv, capsys, "--out", "notes.txt", "is a file")
    assert "--overwrite" not in err.split("fix:")[1]


def test_import_refuses_out_equal_to_its_z_csv(t, capsys):
    """The --z-csv file is an input too: an --out over it is refused like an --out over an image."""
    jpgs = sorted((t / "J").glob("*.jpg"))
    csv = t / "z.csv"
    csv.write_text("".join(f"{p.name},{10 * k}\n" for k, p in enumerate(jpgs)))
    refused(t, ["import", *jpgs, "--out", csv, "--z-csv", csv, "--pixel-pitch-um", "5", "--overwrite"], capsys,
            "--out", "input")


def _truncate_jpeg_data(p: Path) -> None:
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])  # header whole, entropy-coded data cut


def _damage_deflate_tiff(p: Path) -> None:
    import tifffile

    rng = np.random.default_rng(2)
    tifffile.imwrite(p, (rng.random((48, 64, 3)) * 65535).astype(np.uint16), photometric="rgb",
                     compression="zlib")
    data = bytearray(p.read_bytes())
    data[300:340] = b"\0" * 40  # inside the deflate stream; the header still declares a whole image
    p.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", ["jpeg", "tiff"])
def test_import_decodes_frames_and_refuses_damaged_data(t, capsys, damage):
    """Before: import probed only the headers, so a JPEG cut in its data (or a TIFF with a damaged deflate
    stream) became a 'valid' stack that failed later in calibrate or composite."""
    import tifffile

    if damage == "jpeg":
        frames = sorted((t / "J").glob("*.jpg"))
        _truncate_jpeg_data(frames[2])
    else:
        rng = np.random.default_rng(1)
        frames = [t / f"f{k}.tiff" for k in range(3)]
        for p in frames:
            tifffile.imwrite(p, (rng.random((48, 64, 3)) * 65535).astype(np.uint16), photometric="rgb",
                             compression="zlib")
        _damage_deflate_tiff(frames[2])
    refused(t, _import(t, frames), capsys, frames[2].name, "decoded", "IMAGE")
    assert not (t / "I").exists()
    assert not [p for p in t.iterdir() if p.name.startswith(".I.")]  # no staging folder left beside it


# ------------------------------------------------------------------------------ fieldcal composite


@pytest.mark.parametrize("z", ["inf", "nan", "-inf"])
def test_composite_refuses_a_non_finite_z_ref(t, capsys, z):
    """Before: --z-ref-um inf ran the whole registration and failed at the end with 'c.tiff: cannot be stored
    as JSON', naming the output instead of the option."""
    refused(t, ["composite", t / "S", "--out", t / "c.tiff", f"--z-ref-um={z}", "--quiet"], capsys, "--z-ref-um",
            "finite")


# ---------------------------------------------------------------------------------- fieldcal plan


@pytest.fixture(scope="module")
def tiny_profile(tmp_path_factory):
    """lens.json from a 256x144 chart stack (quick effort): enough for planning."""
    from fieldcal.cli import main

    root = tmp_path_factory.mktemp("audit-profile")
    assert main(["simulate", str(LENS), str(root / "S"), "--z", "-360", "50", "20", "--size", "256x144",
                 "--quiet"]) == 0
    assert main(["calibrate", str(root / "S"), "--out", str(root / "lens.json"), "--fs", "16", "--effort", "quick",
                 "-q"]) == 0
    return root


def test_a_refused_sweep_plan_leaves_no_masks_file(tiny_profile, tmp_path, capsys, monkeypatch):
    """Before: the masks sidecar was written before the plan document was validated, so a plan the schema
    refused (here --alpha-um 1e9: stop_um beyond 1e9 µm) left an orphan out.masks.npz behind."""
    from fieldcal.plan import sweep_plan

    monkeypatch.setattr(sweep_plan, "_check", lambda r: None)  # reach the writer with the bound lifted
    out = tmp_path / "sw.json"
    rc, err = run_cli(["plan", "sweep", tiny_profile / "lens.json", "--alpha-um", "1e9", "--pixel-exposure-ms", "16",
                       "--out", out], capsys)
    assert rc == EXIT_BAD_INPUT and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "a refused plan left files"


def test_sweep_plan_refuses_an_alpha_beyond_any_stage(tiny_profile, tmp_path, capsys):
    """Before: --alpha-um 1e9 failed as 'sw.json: field stop_um' with the fix 'make the plan again'."""
    refused(tmp_path, ["plan", "sweep", tiny_profile / "lens.json", "--alpha-um", "1e9", "--pixel-exposure-ms", "16",
                       "--out", tmp_path / "sw.json"], capsys, "--alpha-um")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------ fieldcal simulate


def test_simulate_refuses_a_scene_image_cut_short(t, capsys):
    """Before: a JPEG scene cut in its data was decoded by OpenCV as a half-grey picture (libjpeg printed
    'Premature end of JPEG file') and a stack of that was written with exit 0."""
    scene = t / "J" / "img2.jpg"
    _truncate_jpeg_data(scene)
    refused(t, ["simulate", LENS, t / "SX", "--z", "-100", "100", "50", "--size", "64x48", "--scene", scene,
                "--quiet"], capsys, "--scene", "img2.jpg", "decoded")
    assert "Premature end" not in capsys.readouterr().err


def test_a_damaged_tiff_prints_only_fieldcals_message(t):
    """Before: tifffile's own warning ('<tifffile.TiffPages @N> invalid offset to first page N') was printed on
    stderr by Python's last-resort log handler before fieldcal's what/where/fix message."""
    frames = [t / "a.tiff", t / "b.tiff"]
    rng = np.random.default_rng(1)
    for p in frames:
        cv2.imwrite(str(p), (rng.random((48, 64, 3)) * 65535).astype(np.uint16))  # OpenCV puts the IFD last
    data = frames[1].read_bytes()
    frames[1].write_bytes(data[: len(data) // 2])
    import subprocess
    import sys

    # in a process of its own: pytest's log capture would swallow the warning the last-resort handler prints
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    r = subprocess.run([sys.executable, "-m", "fieldcal", *map(str, _import(t, frames))], capture_output=True,
                       text=True, env=env, timeout=120)
    assert_clean_failure(r.returncode, r.stderr, EXIT_BAD_INPUT, "b.tiff", "TIFF")
    assert r.stderr.strip().startswith("fieldcal import: error:"), r.stderr
    assert "tifffile" not in r.stderr, r.stderr


@pytest.mark.parametrize("command", ["import", "mtf"])
def test_a_float_frame_with_nan_is_refused_where_it_enters(t, capsys, command):
    """Before: `import` built a stack of float TIFFs one of which was all NaN (calibrate and composite refused
    it later), and `mtf nan.tiff` wrote an empty result with exit 0."""
    import tifffile

    rng = np.random.default_rng(3)
    frames = [t / f"f{k}.tiff" for k in range(3)]
    for p in frames:
        tifffile.imwrite(p, rng.random((48, 64, 3)).astype(np.float32), photometric="rgb")
    bad = frames[1]
    img = rng.random((48, 64, 3)).astype(np.float32)
    img[5, 7, 1] = np.nan
    img[9, 9, 0] = np.inf
    tifffile.imwrite(bad, img, photometric="rgb")
    argv = _import(t, frames) if command == "import" else ["mtf", bad, "--out", t / "m.json", "--quiet"]
    refused(t, argv, capsys, bad.name, "2 NaN/Inf")


# --------------------------------------------------------------------------------- fieldcal batch


@pytest.mark.parametrize("second", ["S", "S/stack.json", "J/../S", "Slink"])
def test_batch_refuses_one_stack_given_twice(t, capsys, second):
    """Before: `batch calibrate S S` (or S and a link to it) calibrated it twice as units S and S-2, and the
    fleet's statistics counted one unit as two (its spread shrank towards that unit)."""
    pytest.importorskip("dask.distributed")
    (t / "Slink").symlink_to(t / "S")
    refused(t, ["batch", "calibrate", t / "S", f"{t}/{second}", "--out", t / "B", "--scheduler", "threads",
                "--workers", "1", "--fs", "4", "--effort", "quick", "-q"], capsys, "STACK", "twice")


# ------------------------------------------------------------------ a replaced stack folder, killed


_KILL_AT_RENAME = r"""
import os, signal, sys
real_rename = os.rename
def rename(src, dst, *a, **k):
    r = real_rename(src, dst, *a, **k)
    os.kill(os.getpid(), signal.SIGKILL)  # right after the first rename of the folder swap
    return r
os.rename = rename
from fieldcal.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.skipif(not os.uname().sysname == "Linux", reason="the one-step swap is Linux's renameat2")
def test_import_overwrite_killed_mid_swap_leaves_a_stack_under_the_name(t):
    """Before: `import --overwrite` moved the old stack aside (rename 1) and then the new one into place
    (rename 2); killed between them, the folder the user named was gone (the old stack hidden as
    .NAME.old-*). Now the two folders are swapped in one step where the OS can."""
    import json
    import signal
    import subprocess
    import sys

    jpgs = sorted((t / "J").glob("*.jpg"))
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "FIELDCAL_PROGRESS": "0"}
    base = [sys.executable, "-c", _KILL_AT_RENAME, "import", *map(str, jpgs), "--out", str(t / "I"),
            "--pixel-pitch-um", "5", "--quiet"]
    subprocess.run([sys.executable, "-m", "fieldcal", *base[3:], "--z", "0", "20"], env=env, check=True,
                   timeout=120)
    r = subprocess.run([*base, "--z", "0", "30", "--overwrite"], env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode in (0, -signal.SIGKILL), r.stderr
    meta = json.loads((t / "I" / "stack.json").read_text())  # a whole stack under the name, old or new
    assert [f["z_um"] for f in meta["frames"]] in ([0, 20, 40, 60], [0, 30, 60, 90])


# ---------------------------------------------------------------------------- loops of symbolic links


def _stack_with_a_looped_frame(t: Path) -> Path:
    import json

    meta = json.loads((t / "S" / "stack.json").read_text())
    meta["links"] = "symlink"
    (t / "S" / "stack.json").write_text(json.dumps(meta))
    frame = t / "S" / "frames" / "0001.tiff"
    frame.unlink()
    frame.symlink_to("0001.tiff")  # a link to itself
    return t / "S"


@pytest.mark.parametrize("case", ["out", "stack-folder", "frame-in-stack", "import-image", "mtf-image"])
def test_a_loop_of_symbolic_links_is_bad_input_not_a_bug(t, capsys, case):
    """Before: Path.resolve() raised RuntimeError('Symlink loop from ...') and every command exited 5 ('a bug in
    fieldcal') for an output, input folder, frame or image that is a loop of links."""
    loop = t / "loop.tiff"
    loop.symlink_to("loop.tiff")
    loopd = t / "loopd"
    loopd.symlink_to("loopd")
    argv = {"out": ["composite", t / "S", "--out", loop, "--overwrite", "--quiet"],
            "stack-folder": ["composite", loopd, "--out", t / "c.tiff", "--quiet"],
            "frame-in-stack": ["composite", t / "S", "--out", t / "c.tiff", "--quiet"],
            "import-image": _import(t, [loop, t / "J" / "img0.png"]),
            "mtf-image": ["mtf", loop, "--out", t / "m.json", "--quiet"]}[case]
    if case == "frame-in-stack":
        _stack_with_a_looped_frame(t)
    refused(t, argv, capsys, "loop of symbolic links")


# ------------------------------------------------------------------------ pipes where a file is wanted


def _fifo(t: Path, name: str) -> Path:
    p = t / name
    os.mkfifo(p)
    return p


@pytest.mark.parametrize("case", ["mtf-image", "import-z-csv", "lens-check", "frame-in-stack"])
def test_a_named_pipe_given_as_a_file_is_refused_not_read(t, capsys, case):
    """Before: `mtf PIPE`, `import --z-csv PIPE` and `lens check PIPE` opened the pipe and blocked forever (no
    writer); a frame that is a pipe was reported as 'does not exist'."""
    import json
    import threading

    if case == "frame-in-stack":
        frame = t / "S" / "frames" / "0001.tiff"
        frame.unlink()
        os.mkfifo(frame)
        argv, needles = ["composite", t / "S", "--out", t / "c.tiff", "--quiet"], ("not a regular file", "frames[1]")
    else:
        pipe = _fifo(t, {"mtf-image": "p.png", "import-z-csv": "z.csv", "lens-check": "lens.csv"}[case])
        jpgs = sorted((t / "J").glob("*.jpg"))
        argv = {"mtf-image": ["mtf", pipe, "--out", t / "m.json", "--quiet"],
                "import-z-csv": ["import", *jpgs, "--out", t / "I", "--z-csv", pipe, "--pixel-pitch-um", "5"],
                "lens-check": ["lens", "check", pipe]}[case]
        needles = ("not a regular file", pipe.name)
    done = threading.Event()

    def unblock():  # were the command to block on the pipe, open its write end so that the test ends (and fails)
        if not done.wait(20):
            for p in t.rglob("*"):
                if p.is_fifo():
                    with open(p, "wb"):
                        pass

    threading.Thread(target=unblock, daemon=True).start()
    before = {p: p.read_bytes() for p in t.rglob("*") if p.is_file() and not p.is_fifo()}
    try:
        rc, err = run_cli(argv, capsys)  # (snapshot() would itself block reading the pipe)
    finally:
        done.set()
    assert_clean_failure(rc, err, EXIT_BAD_INPUT, *needles)
    assert {p: p.read_bytes() for p in t.rglob("*") if p.is_file() and not p.is_fifo()} == before
    assert json.loads((t / "S" / "stack.json").read_text())["frames"]


# ------------------------------------------------------------------------------- fieldcal capture


@pytest.mark.parametrize("out,needles", [("notes.txt/CAP", ("--out", "notes.txt is a file")),
                                         ("", ("--out", "empty"))])
def test_capture_names_out_for_a_bad_folder_path(t, capsys, out, needles):
    """Before: '--out notes.txt/CAP' said 'notes.txt/CAP: Not a directory' naming no option, and '--out ""' was
    taken as the current folder ('.: exists and is not a capture folder')."""
    (t / "notes.txt").write_text("mine")
    out_arg = str(t / out) if out else ""
    refused(t, ["capture", "--z", "-100", "100", "50", "--stage", "sim", "--camera", f"sim:{LENS},size=64x48",
                "--out", out_arg, "--quiet"], capsys, *needles)


def test_simulate_names_its_fs_flag(t, capsys):
    """Before: 'simulate --optics wave --fs nan' said field 'fs_cyc_per_mm' (the library's name), not '--fs'."""
    refused(t, ["simulate", LENS, t / "SX", "--z", "-100", "100", "50", "--size", "64x48", "--optics", "wave",
                "--fs", "nan", "--quiet"], capsys, "field '--fs'")


# ------------------------------------------------------- --overwrite of a folder holding the user's files


@pytest.mark.parametrize("command", ["simulate", "import"])
def test_overwrite_never_deletes_files_put_into_a_stack_folder(t, capsys, command):
    """Before: `simulate S --overwrite` and `import --out S --overwrite` replaced the whole folder because it held
    a stack.json, deleting what the user had put beside the stack (notes, a report, a profile)."""
    (t / "S" / "notes.txt").write_text("mine")
    (t / "S" / "report").mkdir()
    (t / "S" / "report" / "index.html").write_text("<html>")
    jpgs = sorted((t / "J").glob("*.jpg"))
    argv = (["simulate", LENS, t / "S", "--z", "-100", "100", "50", "--size", "64x48", "--overwrite", "--quiet"]
            if command == "simulate" else
            ["import", *jpgs, "--out", t / "S", "--z", "0", "20", "--pixel-pitch-um", "5", "--overwrite"])
    refused(t, argv, capsys, "notes.txt", "report/index.html", "never deletes")
    # with them moved out, the stack is replaced (its own frames, truth and stack.json are fieldcal's)
    (t / "S" / "notes.txt").unlink()
    import shutil
    shutil.rmtree(t / "S" / "report")
    rc, err = run_cli(argv, capsys)
    assert rc == 0, err


# --------------------------------------------------------------------------- profile export, report


@pytest.mark.parametrize("z", ["nan", "inf"])
def test_profile_export_refuses_a_non_finite_z(tiny_profile, tmp_path, capsys, z):
    """Before: 'profile export --z nan' failed inside the Lensfun fit: exit 5, 'internal error (ValueError:
    Residuals are not finite in the initial point.)'."""
    refused(tmp_path, ["profile", "export", tiny_profile / "lens.json", "--format", "lensfun", "--out",
                       tmp_path / "x.xml", "--allow-no-distortion", "--z", z], capsys, "field '--z'", "finite")


def test_profile_export_says_when_z_is_outside_the_scan(tiny_profile, tmp_path, capsys):
    """A --z outside the calibrated scan is the fit's extrapolation: the export says so (the default, the
    calibrated focus, is already clipped to the scan)."""
    rc, err = run_cli(["profile", "export", tiny_profile / "lens.json", "--format", "lensfun", "--out",
                       tmp_path / "x.xml", "--allow-no-distortion", "--z", "1e5"], capsys)
    assert rc == 0, err
    assert "outside the scan" in err and "extrapolation" in err


def test_report_names_its_fs_flag(tiny_profile, tmp_path, capsys):
    """Before: 'report --fs nan' named field 'fs_cyc_per_mm' (the library's name), not '--fs'."""
    refused(tmp_path, ["report", tiny_profile / "lens.json", "--out", tmp_path / "R", "--fs", "nan"], capsys,
            "field '--fs'")


@pytest.mark.parametrize("flag,value", [("--fs", "-3"), ("--q", "1.5"), ("--q", "nan")])
def test_report_checks_fs_and_q_before_writing_any_picture(tiny_profile, tmp_path, capsys, flag, value):
    """Before: 'report --fs nan' (or a bad --q) wrote surfaces.png and bands.png, then failed at the tolerance
    map: a half-written report."""
    refused(tmp_path, ["report", tiny_profile / "lens.json", "--out", tmp_path / "R", f"{flag}={value}"], capsys,
            flag)
    assert not (tmp_path / "R").exists()


# ------------------------------------------------------------------------------------ raw (DNG) levels


@pytest.mark.parametrize("case", ["mixed-black", "black-above-white"])
def test_import_refuses_raw_frames_whose_levels_disagree_or_are_impossible(t, capsys, case):
    """Before: DNG frames with black levels 64 and 5000 became one stack recording only the first frame's
    levels (the second's black read as signal); a DNG whose black level lies above its white level failed on
    the hidden staging folder's stack.json ('.I.import-*/stack.json: field white_level')."""
    pytest.importorskip("pidng")
    pytest.importorskip("rawpy")
    from test_import import _write_dng

    rng = np.random.default_rng(0)
    levels = {"mixed-black": [(64, 4095), (5000, 65535)], "black-above-white": [(5000, 4095), (5000, 4095)]}[case]
    frames = []
    for k, (black, white) in enumerate(levels):
        p = t / f"d{k}.dng"
        _write_dng(p, (rng.random((48, 64)) * 3000 + 100).astype(np.uint16), black=black, white=white)
        frames.append(p)
    err = refused(t, _import(t, frames), capsys, "IMAGE", "level")
    assert ".import-" not in err


# ------------------------------------------------------------------------------------ over-long names


def test_calibrate_refuses_a_profile_name_its_sidecar_cannot_have_before_the_work(tiny_profile, tmp_path, capsys):
    """Before: a 235-byte --out name fits the file system, its NAME.<16 hex>.samples.npz sidecar (260 bytes) does
    not: calibrate ran the whole fit and then failed writing the sidecar."""
    out = tmp_path / ("b" * 230 + ".json")
    refused(tmp_path, ["calibrate", tiny_profile / "S", "--out", out, "--fs", "16", "--effort", "quick", "-q"],
            capsys, "--out", "shorter name", "beside it")



@pytest.mark.parametrize("target", ["colour-image", "stack"])
def test_mtf_never_ignores_or_misapplies_cfa(t, capsys, target):
    """Before: `mtf RGB.png --cfa RGGB` measured the red channel as if it were a Bayer mosaic (a silently wrong
    MTF), and `mtf STACK --cfa RGGB` ignored the flag."""
    src = t / "J" / "img0.png" if target == "colour-image" else t / "S"
    refused(t, ["mtf", src, "--out", t / "m.json", "--cfa", "RGGB", "--quiet"], capsys, "field '--cfa'")


def test_composite_refuses_a_captured_sweep_image_with_nan(tiny_profile, tmp_path, capsys):
    """Before: a float sweep image holding one NaN pixel was deconvolved (numpy printed a RuntimeWarning) and the
    command failed at the end naming the output: 'c.tiff: cannot be stored as JSON'."""
    import tifffile

    img = np.random.default_rng(0).random((144, 256, 3)).astype(np.float32)
    img[3, 3, 0] = np.nan
    tifffile.imwrite(tmp_path / "sweep.tiff", img, photometric="rgb")
    err = refused(tmp_path, ["composite", tmp_path / "sweep.tiff", "--out", tmp_path / "c.tiff", "--profile",
                             tiny_profile / "lens.json", "--sweep-alpha-um", "20", "--quiet"], capsys, "sweep.tiff",
                  "1 NaN/Inf")
    assert "RuntimeWarning" not in err


# ------------------------------------------------------------------------------------ fieldcal targets


def test_targets_checks_every_chart_name_before_drawing_any(t, capsys):
    """Before: a symbolic link at the slanted-edge chart's name was refused only when that chart was written,
    after the texture and ChArUco charts: a half-written set without targets.json."""
    victim = t / "victim.txt"
    victim.write_text("precious")
    (t / "TG").mkdir()
    (t / "TG" / "slanted-edge_210x148mm_50dpi.png").symlink_to(victim)
    refused(t, ["targets", "--out", t / "TG", "--dpi", "50", "--size-mm", "A5"], capsys, "symbolic link",
            "slanted-edge_210x148mm_50dpi.png")
    assert sorted(p.name for p in (t / "TG").iterdir()) == ["slanted-edge_210x148mm_50dpi.png"]
    assert victim.read_text() == "precious"


def test_only_capture_named_frames_of_a_journalled_folder_count_as_fieldcals(tmp_path):
    """--overwrite may replace a folder whose unlisted files fieldcal wrote: a killed capture's uncommitted
    frames/NNNN.tiff (capture's own name, beside its journal). A photo the user dropped into frames/, or a
    capture-named file in a folder no capture wrote, is the user's and blocks the replacement."""
    from fieldcal.formats.atomic import foreign_files

    out = tmp_path / "S"
    (out / "frames").mkdir(parents=True)
    (out / "stack.json").write_text("{}")
    for name in ("frames/0007.tiff", "frames/holiday.jpg", "frames/0008.png"):
        (out / name).write_bytes(b"x")
    assert foreign_files(out, "stack.json") == ["frames/0007.tiff", "frames/0008.png", "frames/holiday.jpg"]
    (out / "capture.journal").write_text("")
    assert foreign_files(out, "stack.json") == ["frames/0008.png", "frames/holiday.jpg"]
    (out / "frames" / "0009.tiff").symlink_to(tmp_path / "elsewhere.tiff")
    assert "frames/0009.tiff" in foreign_files(out, "stack.json")


# ------------------------------------------------------------------------- session 16 leftovers (s16-leftovers)


@pytest.mark.parametrize("rows,needles", [
    # a decimal comma: "12,5" (12.5 µm) splits into two columns, and was read as z = 12 without a word
    (["img0.jpg,0", "img1.jpg,12,5", "img2.jpg,25", "img3.jpg,37,5"], ["line 2", "3 columns", "decimal point"]),
    # the same under a header naming two columns (the header is line 1, so the bad row is line 3)
    (["file,z_um", "img0.jpg,0", "img1.jpg,12,5", "img2.jpg,25", "img3.jpg,37"], ["line 3", "decimal point"]),
    # quoted, the decimal comma is one field: still not a number, said as such
    (["img0.jpg,0", 'img1.jpg,"12,5"', "img2.jpg,25", "img3.jpg,37"], ["line 2", "not a number", "decimal point"]),
])
def test_import_refuses_a_z_csv_row_with_a_decimal_comma(t, capsys, rows, needles):
    """Before: `import --z-csv` read 'img1.jpg,12,5' (12.5 µm with a decimal comma) as z = 12 and imported the
    stack; every row must have the header's column count (two without a header), and z a decimal point."""
    jpgs = sorted((t / "J").glob("*.jpg"))
    csv = t / "z.csv"
    csv.write_text("\n".join(rows) + "\n")
    refused(t, ["import", *jpgs, "--out", t / "I", "--z-csv", csv, "--pixel-pitch-um", "5"], capsys,
            "z.csv", *needles)
    assert not (t / "I").exists()


@pytest.mark.parametrize("z", ["5000", "-101", "1e8"])
def test_composite_refuses_a_z_ref_outside_the_stack(t, capsys, z):
    """Before: --z-ref-um far outside the frames' z range (S: -100 to 100 µm) was taken silently; the chained
    per-frame maps then used the nearest frame while the linear model extrapolated to z_ref. The output is in a
    frame's geometry, so a reference outside the frames is refused, naming the flag and the range."""
    err = refused(t, ["composite", t / "S", "--out", t / "c.tiff", "--z-ref-um", z, "--quiet"], capsys,
                  "--z-ref-um", "outside", "-100 to 100")
    assert not (t / "c.tiff").exists() and "S" in err


def test_composite_takes_a_z_ref_at_the_ends_of_the_stack(t, capsys):
    """The end frames are frames of the stack: a reference there is used, and recorded."""
    import tifffile

    rc, err = run_cli(["composite", t / "S", "--out", t / "c.tiff", "--z-ref-um", "100", "--quiet"], capsys)
    assert rc == 0, err
    assert '"z_ref_um": 100.0' in tifffile.TiffFile(t / "c.tiff").pages[0].description


@pytest.mark.parametrize("extra", [["--profile", "lens.json"], ["--no-register"]])
def test_composite_refuses_a_z_ref_it_would_ignore(w, capsys, extra):
    """Never ignore a flag: with a profile the output is in the profile's z_ref geometry and with --no-register
    in the frames' own, so --z-ref-um there was silently dropped (the composite's metadata even recorded the
    profile's z_ref). Refused before any work, naming the flag."""
    argv = ["composite", w / "S", "--out", w / "c.tiff", "--z-ref-um", "0", "--quiet",
            *[w / a if a.endswith(".json") else a for a in extra]]
    refused(w, argv, capsys, "--z-ref-um", extra[0].lstrip("-").replace("-", " ").split()[0])
    assert not (w / "c.tiff").exists()


def _killed_import(t: Path, out: Path) -> Path:
    """Run `fieldcal import` in a child process killed (os._exit, as SIGKILL: no cleanup runs) just before
    its finished staging folder takes the output's name; returns the staging folder it left."""
    import subprocess
    import sys

    jpgs = sorted((t / "J").glob("*.jpg"))
    code = ("import os, sys\nimport fieldcal.formats.importer as imp\n"
            "imp.replace_folder = lambda *a, **k: os._exit(9)\n"
            "from fieldcal.cli import main\nsys.exit(main(sys.argv[1:]))\n")
    argv = ["import", *map(str, jpgs), "--out", str(out), "--z", "0", "20", "--pixel-pitch-um", "5", "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    r = subprocess.run([sys.executable, "-c", code, *argv], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 9, r.stderr
    left = [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.fieldcal-import-")]
    assert len(left) == 1 and (left[0] / "stack.json").is_file() and not out.exists()
    return left[0]


@pytest.mark.parametrize("command", ["import", "simulate"])
def test_the_next_run_removes_what_a_killed_run_left(t, capsys, command):
    """Before: an import or simulate killed mid-way left its hidden staging folder (.I.fieldcal-import-*,
    .I.fieldcal-partial-*) beside the output, a full copy of the frames, and no later run removed it. Now the
    next run on the same output removes the folders fieldcal provably made (its exact name for that output, a
    folder, only what fieldcal writes there) and says so; the output is made as usual. The old output that
    replace_folder's two-rename fallback moved aside may be the only copy after a crash: never removed, named."""
    out = t / "I"
    left = _killed_import(t, out)
    partial = t / ".I.fieldcal-partial-abcd_123"  # a simulate killed after its first frame (StackWriter's layout)
    (partial / "frames").mkdir(parents=True)
    (partial / "frames" / "0000.tiff").write_bytes((t / "S" / "frames").iterdir().__next__().read_bytes())
    (partial / "stack.json").write_text('{"format": "fieldcal-stack/1", "frames": []}')
    (t / ".I.fieldcal-old-zz99zz99").mkdir()  # replace_folder's fallback, killed between its renames
    if command == "import":
        argv = _import(t, sorted((t / "J").glob("*.jpg")))
    else:
        argv = ["simulate", LENS, out, "--z", "-100", "100", "50", "--size", "96x64", "--quiet"]
    rc, err = run_cli(argv, capsys)
    assert rc == 0, err
    assert not left.exists() and not partial.exists() and (t / ".I.fieldcal-old-zz99zz99").is_dir()
    assert err.count("removed") == 2 and str(left) in err and "rename it back" in err
    assert (out / "stack.json").is_file()
    assert [p.name for p in t.iterdir() if p.name.startswith(".I.")] == [".I.fieldcal-old-zz99zz99"]


def test_the_next_run_leaves_what_fieldcal_cannot_prove_it_made(t, capsys):
    """Only fieldcal's own staging folders for THIS output, holding only what fieldcal writes, are removed:
    a user's file inside one, a link, a folder in use by a running command, another output's folder and a
    name that is not fieldcal's pattern are all left as they were (the first three named in a warning)."""
    import fcntl

    mine = t / ".I.fieldcal-import-abcd1234"
    (mine / "frames").mkdir(parents=True)
    (mine / "frames" / "0000_img0.jpg").write_bytes(b"frame")
    (mine / "notes.txt").write_text("the user's notes")
    sub = t / ".I.fieldcal-partial-abcd1234"
    (sub / "frames" / "raw").mkdir(parents=True)  # a folder fieldcal never makes inside a staging folder
    (t / "target").mkdir()
    link = t / ".I.fieldcal-import-link0000"
    link.symlink_to(t / "target", target_is_directory=True)
    backup = t / ".I.old-20261125"  # the user's own dated backup of a stack: not fieldcal's name
    (backup / "frames").mkdir(parents=True)
    (backup / "stack.json").write_text('{"format": "fieldcal-stack/1", "frames": []}')
    busy = t / ".I.fieldcal-import-busy0000"  # a run still building: its folder is locked
    busy.mkdir()
    other = t / ".J.fieldcal-import-abcd1234"  # another output's
    other.mkdir()
    odd = t / ".I.fieldcal-import-abcd12345"  # not mkdtemp's 8 characters
    odd.mkdir()
    before = snapshot(t)
    fd = os.open(busy, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        rc, err = run_cli(_import(t, sorted((t / "J").glob("*.jpg"))), capsys)
    finally:
        os.close(fd)
    assert rc == 0, err
    assert changed(before, snapshot(t)) and only_under(changed(before, snapshot(t)), ["I"])
    for p, why in ((mine, "notes.txt"), (sub, "frames/raw"), (link, "not a folder"),
                   (busy, "in use")):
        assert f"left {p} alone" in err and why in err, err
    assert str(other) not in err and str(odd) not in err and str(backup) not in err and backup.is_dir()


@pytest.mark.parametrize("kind", ["sweep", "stack"])
def test_plan_names_its_size_flag_for_a_profile(tiny_profile, tmp_path, capsys, kind):
    """Before: `plan stack lens.json --size 96x64` (a calibrated profile) said "lens.json: field 'size': ...",
    as if the profile file had a bad field; the size is the --size argument, and the CLI names it."""
    argv = ["plan", kind, tiny_profile / "lens.json", "--size", "96x64", "--out", tmp_path / "p.json"]
    argv += ["--fs", "16", "--q", "0.05"] if kind == "stack" else ["--alpha-um", "100", "--pixel-exposure-ms", "16"]
    err = refused(tmp_path, argv, capsys, "field '--size'", "lens specs only", "lens.json")
    assert "field 'size'" not in err and list(tmp_path.iterdir()) == []


def test_plan_bounds_the_size_of_a_lens_spec_as_simulate_does(tmp_path, capsys):
    """Before: `plan stack LENS --size 100000x100000` (10 Gpx) was accepted and planned for minutes; the size
    a spec is planned at has simulate's bounds (8 px to 100 Mpx), refused at once naming --size."""
    refused(tmp_path, ["plan", "stack", LENS, "--size", "100000x100000", "--out", tmp_path / "p.json", "--fs", "16",
                       "--q", "0.05"], capsys, "field '--size'", "100 Mpx")
    assert list(tmp_path.iterdir()) == []


def test_stale_mask_export_folders_are_told_apart_by_their_files(tmp_path):
    """plan export-masks builds in .NAME.fieldcal-partial-*: a killed export's folder (mask files, a temporary file) is
    fieldcal's, one that also holds another file is not, and a stack layout is not a mask export's."""
    from fieldcal.formats.atomic import clean_stale_staging

    ours = tmp_path / ".M.fieldcal-partial-abcd1234"
    ours.mkdir()
    (ours / "CFA-RGGB-slot-0000.png").write_bytes(b"png")
    (ours / ".CFA-RGGB-slot-0001.png.0123456789abcdef.tmp").write_bytes(b"half")
    theirs = tmp_path / ".M.fieldcal-partial-efgh5678"
    theirs.mkdir()
    (theirs / "Y-start.tif").write_bytes(b"tif")
    (theirs / "README").write_text("mine")
    stack = tmp_path / ".M.fieldcal-partial-stack000"
    (stack / "frames").mkdir(parents=True)
    removed, kept = clean_stale_staging(tmp_path / "M", "masks.json")
    assert removed == [ours] and not ours.exists()
    assert {p for p, _ in kept} == {theirs, stack} and (theirs / "README").is_file() and stack.is_dir()


def _stack_folder(path: Path, extra: str | None = None) -> Path:
    (path / "frames").mkdir(parents=True)
    (path / "stack.json").write_text('{"format": "fieldcal-stack/1", "frames": []}')
    if extra:
        (path / extra).write_text("the user's")
    return path


def test_replace_folder_checks_the_output_again_before_the_swap(tmp_path):
    """Review finding: the output was checked only when the command started; a folder made (or a file added to an
    old stack) while a long import ran was swapped out and deleted at the end, even without --overwrite. With
    the marker given, replace_folder checks again just before the swap and refuses, the new build untouched."""
    from fieldcal.errors import OutputError
    from fieldcal.formats.atomic import replace_folder

    new = _stack_folder(tmp_path / ".S.fieldcal-import-abcd1234")
    out = tmp_path / "S"
    out.mkdir()
    (out / "my_notes.txt").write_text("made while the import ran")
    with pytest.raises(OutputError, match="not empty"):
        replace_folder(new, out, marker="stack.json", overwrite=False, what="a stack")
    old = _stack_folder(tmp_path / "T", extra="report.pdf")  # --overwrite of a stack the user added a file to
    with pytest.raises(OutputError, match="report.pdf"):
        replace_folder(new, old, marker="stack.json", overwrite=True, what="a stack")
    assert (out / "my_notes.txt").is_file() and (old / "report.pdf").is_file() and (new / "stack.json").is_file()
    replace_folder(new, tmp_path / "U", marker="stack.json", overwrite=False, what="a stack")  # a new name: fine
    assert (tmp_path / "U" / "stack.json").is_file() and not new.exists()


def test_overwrite_refuses_a_folder_a_running_capture_holds(tmp_path):
    """Review finding: --overwrite of a stack folder that `fieldcal capture` is still writing (it holds flock on
    the folder for its whole run) swapped it out and deleted it under the capture. Refused while locked."""
    import fcntl

    from fieldcal.errors import OutputError
    from fieldcal.formats.atomic import check_replaceable_folder

    out = _stack_folder(tmp_path / "CAP")
    fd = os.open(out, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with pytest.raises(OutputError, match="in use by a running fieldcal command"):
            check_replaceable_folder(out, "stack.json", True, "a stack")
    finally:
        os.close(fd)
    check_replaceable_folder(out, "stack.json", True, "a stack")  # the capture ended: replaceable


def test_the_fallback_puts_the_old_folder_back_when_the_second_rename_fails(tmp_path, monkeypatch):
    """Review finding: without RENAME_EXCHANGE (macOS, NFS, FUSE) the old output is moved aside first; if the new
    folder then could not take its name, the old one stayed hidden and the user's name held nothing."""
    import fieldcal.formats.atomic as atomic

    new = _stack_folder(tmp_path / ".S.fieldcal-import-abcd1234")
    out = _stack_folder(tmp_path / "S")
    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    real_rename = os.rename

    def rename(a, b):
        if Path(a) == new:
            raise OSError(5, "I/O error", str(b))
        return real_rename(a, b)

    monkeypatch.setattr(atomic.os, "rename", rename)
    with pytest.raises(OSError):
        atomic.replace_folder(new, out)
    assert (out / "stack.json").is_file() and not [p for p in tmp_path.iterdir() if "fieldcal-old" in p.name]


def test_only_fieldcals_own_temporary_names_are_not_foreign(tmp_path):
    """Review finding: any hidden *.tmp in a stack folder counted as fieldcal's, so --overwrite deleted a user's
    `.measurements.tmp`; only write_bytes' own names (.NAME.<16 hex>.tmp) are fieldcal's."""
    from fieldcal.formats.atomic import foreign_files

    out = _stack_folder(tmp_path / "S")
    (out / ".measurements.tmp").write_text("the user's")
    (out / ".stack.json.0123456789abcdef.tmp").write_text("fieldcal's, interrupted")
    assert foreign_files(out, "stack.json") == [".measurements.tmp"]


def test_a_link_to_a_folder_inside_an_input_does_not_make_its_target_an_input(tmp_path):
    """Review finding: a stack holding a link `up -> ..` made its whole parent an input, so every output beside
    the stack was refused. Only files that links lead to are inputs (import --link symlink's frames)."""
    from fieldcal.errors import OutputError
    from fieldcal.formats.atomic import check_output

    s = _stack_folder(tmp_path / "S")
    (s / "up").symlink_to(tmp_path, target_is_directory=True)
    camera = tmp_path / "cam" / "IMG_0001.JPG"
    camera.parent.mkdir()
    camera.write_bytes(b"jpeg")
    (s / "frames" / "0000.jpg").symlink_to(camera)
    check_output(tmp_path / "m.json", inputs=[s], overwrite=False)
    with pytest.raises(OutputError):
        check_output(camera, inputs=[s], overwrite=True)


def test_overlapping_reads_leave_tifffile_logging_as_it_was():
    """Review finding: the quiet reader saved and restored tifffile's log level per call; two reads overlapping
    on the compositor's threads (A in, B in, A out, B out) restored the quieted level last and left tifffile
    silenced for good. The first read in saves the level, the last out restores it."""
    import logging

    from fieldcal.formats.imageio import _tifffile_quiet

    log = logging.getLogger("tifffile")
    log.setLevel(logging.WARNING)
    a, b = _tifffile_quiet(), _tifffile_quiet()
    a.__enter__()
    b.__enter__()
    a.__exit__(None, None, None)
    assert log.level > logging.ERROR  # B still reading: still quiet
    b.__exit__(None, None, None)
    assert log.level == logging.WARNING


@pytest.mark.parametrize("command", ["simulate", "import"])
def test_overwrite_of_the_current_folder_given_as_dot(t, capsys, monkeypatch, command):
    """Review finding: `--out .` (the stack folder one stands in) has no name, so the staging folder was made
    INSIDE the output ("..fieldcal-partial-*") and the swap failed ("Device or resource busy", exit 4, or the
    build refused as foreign files of its own output). The output is taken by its absolute path."""
    monkeypatch.chdir(t / "S")
    if command == "simulate":
        argv = ["simulate", LENS, ".", "--z", "-100", "100", "25", "--size", "96x64", "--quiet", "--overwrite"]
    else:
        argv = ["import", *sorted((t / "J").glob("*.jpg")), "--out", ".", "--z", "0", "20", "--pixel-pitch-um", "5",
                "--quiet", "--overwrite"]
    rc, err = run_cli(argv, capsys)
    assert rc == 0, err
    assert (t / "S" / "stack.json").is_file() and not [p for p in t.iterdir() if p.name.startswith(".")]
    assert not [p for p in (t / "S").iterdir() if p.name.startswith(".")]


def test_composite_refuses_a_z_ref_away_from_a_single_frame(t, capsys):
    """Before: a one-frame stack skipped registration and with it the range check, so `--z-ref-um 50` on a frame
    at 0 µm was dropped without a word. One frame is its own reference: any other position is refused."""
    from fieldcal.cli import main

    assert main(["simulate", str(LENS), str(t / "one"), "--z", "0", "0", "50", "--size", "96x64", "--quiet"]) == 0
    refused(t, ["composite", t / "one", "--out", t / "c.tiff", "--z-ref-um", "50", "--quiet"], capsys,
            "--z-ref-um", "outside", "0 to 0")
    assert not (t / "c.tiff").exists()


def test_overlapping_decodes_leave_opencv_logging_as_it_was():
    """The same pattern as tifffile's, written three times for OpenCV (PNG and JPEG frames, scene images):
    JPEG frames decode on several threads, and a save/restore per call (A in, B in, A out, B out) left OpenCV
    silenced for good. One context: the first in saves the level, the last out restores it."""
    import cv2

    from fieldcal.formats.imageio import cv2_quiet

    before = cv2.utils.logging.getLogLevel()
    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_WARNING)
        a, b = cv2_quiet(), cv2_quiet()
        a.__enter__()
        b.__enter__()
        a.__exit__(None, None, None)
        assert cv2.utils.logging.getLogLevel() == cv2.utils.logging.LOG_LEVEL_SILENT  # B still decoding
        b.__exit__(None, None, None)
        assert cv2.utils.logging.getLogLevel() == cv2.utils.logging.LOG_LEVEL_WARNING
    finally:
        cv2.utils.logging.setLogLevel(before)


@pytest.mark.parametrize("damage", ["truncated", "crc"])
def test_a_damaged_png_is_refused_without_libpng_s_own_line(t, capfd, damage):
    """Before: a PNG with a damaged chunk made libpng print "libpng error: IDAT: CRC error" on stderr (its default
    handler, beyond OpenCV's log level) before fieldcal's message. The chunks' CRCs are checked first (ISO/IEC
    15948 §5.3): only fieldcal's message, naming the chunk."""
    from fieldcal.cli import main

    data = bytearray((t / "J" / "img0.png").read_bytes())
    if damage == "truncated":
        data = data[:len(data) // 2]
    else:
        data[60] ^= 0xFF  # inside the first IDAT of a 64 x 48 noise image
    bad = t / "bad.png"
    bad.write_bytes(bytes(data))
    assert main(["mtf", str(bad), "--out", str(t / "m.json")]) == EXIT_BAD_INPUT
    err = capfd.readouterr().err
    assert "libpng" not in err and "bad.png" in err and "IDAT" in err and "Traceback" not in err
    assert not (t / "m.json").exists()


def test_png_chunk_check_accepts_what_opencv_and_numpy_write(tmp_path):
    """The CRC walk must not refuse a valid PNG: 8- and 16-bit, grey and colour, as OpenCV encodes them."""
    from fieldcal.formats.imageio import check_png_chunks

    rng = np.random.default_rng(1)
    for img in ((rng.random((31, 17)) * 255).astype(np.uint8), (rng.random((9, 40, 3)) * 65535).astype(np.uint16)):
        ok, enc = cv2.imencode(".png", img)
        assert ok
        check_png_chunks(enc)
