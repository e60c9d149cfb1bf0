"""Hostile input, reading side (issue 12): altered frames and image bombs.

Recorded frame checksums are verified on every read of a stack (``--no-verify`` skips it), and the profile's
provenance hashes the frames' content; every image's declared size is checked from its header before anything
is allocated.
"""

from __future__ import annotations

import json

import pytest

from fieldcal.errors import EXIT_BAD_INPUT, StackError
from fieldcal.formats.stack import Stack

from hostile_safety_util import (FS, LENS, assert_clean_failure, changed, png_bomb, run_cli, set_frame_sha, snapshot,
                                 tiff_bomb)


def alter(path, how):
    data = bytearray(path.read_bytes())
    if how == "flip-pixel":
        data[-100] ^= 0x01
    elif how == "truncate":
        data = data[: len(data) - 3]
    elif how == "append":
        data += b"\0"
    path.write_bytes(bytes(data))


def calibrate_argv(w, out="new.json", *extra):
    return ["calibrate", w / "S", "--out", w / out, "--fs", FS, "--effort", "quick", "-q", *extra]


# ------------------------------------------------------------------------------------------ checksums


@pytest.mark.parametrize("how", ["flip-pixel", "truncate", "append"])
def test_calibrate_refuses_an_altered_frame(w, capsys, how):
    alter(w / "S" / "frames" / "0007.tiff", how)
    before = snapshot(w)
    rc, err = run_cli(calibrate_argv(w), capsys)
    assert_clean_failure(rc, err, EXIT_BAD_INPUT, "0007.tiff")
    assert "--no-verify" in err or "truncated" in err  # a cut uncompressed TIFF is caught from its header
    assert changed(before, snapshot(w)) == set()


def test_library_calibrate_of_a_path_refuses_an_altered_frame_before_measuring(w, monkeypatch):
    """fieldcal.calibrate(path) hashes in the background (Stack.start_verify) and refuses before the frame pass."""
    from fieldcal.calibration import pipeline
    import fieldcal.measure as measure

    alter(w / "S" / "frames" / "0007.tiff", "flip-pixel")

    def no_pass(*a, **k):
        raise AssertionError("measured a stack that failed its checksums")

    monkeypatch.setattr(measure, "measure_stack", no_pass)
    monkeypatch.setattr(measure, "measure_geometry", no_pass)
    with pytest.raises(StackError, match=r"sha256 differs.*0007\.tiff"):
        pipeline.calibrate(w / "S", fs_cyc_per_mm=float(FS), effort="quick", quiet=True)


def test_calibrate_refuses_swapped_frames(w, capsys):
    a, b = w / "S" / "frames" / "0003.tiff", w / "S" / "frames" / "0004.tiff"
    tmp = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(tmp)
    rc, err = run_cli(calibrate_argv(w), capsys)
    assert_clean_failure(rc, err, EXIT_BAD_INPUT, "2 frame file(s)", "0003.tiff", "0004.tiff")


def test_no_verify_calibrates_and_the_provenance_tells_the_stacks_apart(w, capsys):
    clean = json.loads((w / "lens.json").read_text())["provenance"]["inputs_sha256"]
    alter(w / "S" / "frames" / "0007.tiff", "flip-pixel")
    rc, err = run_cli(calibrate_argv(w, "altered.json", "--no-verify"), capsys)
    assert rc == 0, err
    altered = json.loads((w / "altered.json").read_text())["provenance"]
    assert altered["inputs_sha256"] and altered["inputs_sha256"] != clean
    assert "content" in altered["inputs_hash_method"]


def test_same_stack_same_provenance_hash(w, capsys):
    rc, err = run_cli(calibrate_argv(w, "again.json"), capsys)
    assert rc == 0, err
    a = json.loads((w / "lens.json").read_text())["provenance"]["inputs_sha256"]
    b = json.loads((w / "again.json").read_text())["provenance"]["inputs_sha256"]
    assert a == b


@pytest.mark.parametrize("no_verify", [False, True])
def test_composite_verifies_frames_too(w, capsys, no_verify):
    alter(w / "S" / "frames" / "0010.tiff", "flip-pixel")
    argv = ["composite", w / "S", "--profile", w / "lens.json", "--out", w / "c.tiff", "--quiet"]
    if no_verify:
        rc, err = run_cli([*argv, "--no-verify"], capsys)
        assert rc == 0, err
    else:
        before = snapshot(w)
        rc, err = run_cli(argv, capsys)
        assert_clean_failure(rc, err, EXIT_BAD_INPUT, "0010.tiff", "sha256")
        assert changed(before, snapshot(w)) == set()


def test_stack_open_api_verifies_by_default(w):
    alter(w / "S" / "frames" / "0001.tiff", "flip-pixel")
    with pytest.raises(StackError, match="0001.tiff"):
        Stack.open(w / "S")
    s = Stack.open(w / "S", verify=False)
    assert [f.index for f in s.verify_checksums()] == [1]


def test_frames_without_recorded_sha_are_not_refused(w):
    d = json.loads((w / "S" / "stack.json").read_text())
    for f in d["frames"]:
        f.pop("sha256")
    (w / "S" / "stack.json").write_text(json.dumps(d))
    alter(w / "S" / "frames" / "0001.tiff", "flip-pixel")
    assert len(Stack.open(w / "S")) == len(d["frames"])


# --------------------------------------------------------------------------------------- image bombs


BOMBS = {
    "png-200k": ("png", lambda: png_bomb(200_000, 200_000)),
    "png-200k-gray16": ("png", lambda: png_bomb(200_000, 200_000, colour_type=0, bit_depth=16)),
    "png-ratio": ("png", lambda: png_bomb(12_000, 12_000)),  # under the pixel cap, beyond deflate's ratio
    "tiff-200k-raw": ("tiff", lambda: tiff_bomb(200_000, 200_000)),
    "tiff-200k-deflate": ("tiff", lambda: tiff_bomb(200_000, 200_000, compression=8)),
    "tiff-raw-beyond-eof": ("tiff", lambda: tiff_bomb(4000, 3000)),  # under the cap, data not in the file
}


@pytest.mark.parametrize("name", sorted(BOMBS))
def test_calibrate_refuses_an_image_bomb_frame(w, capsys, name):
    kind, make = BOMBS[name]
    d = json.loads((w / "S" / "stack.json").read_text())
    frame = w / "S" / "frames" / f"0005.{kind}"
    (w / "S" / "frames" / "0005.tiff").unlink()
    frame.write_bytes(make())
    d["frames"][5]["file"] = f"frames/0005.{kind}"
    (w / "S" / "stack.json").write_text(json.dumps(d))
    set_frame_sha(w / "S", 5)  # a consistent, crafted stack: only the declared size is hostile
    assert frame.stat().st_size < 400
    before = snapshot(w)
    rc, err = run_cli(calibrate_argv(w), capsys)
    assert_clean_failure(rc, err, EXIT_BAD_INPUT, f"0005.{kind}")
    assert any(k in err for k in ("declares", "truncated")), err
    assert changed(before, snapshot(w)) == set()


@pytest.mark.parametrize("name", ["png-200k", "tiff-200k-deflate"])
def test_composite_refuses_a_bomb_sweep_image(w, capsys, name):
    kind, make = BOMBS[name]
    img = w / f"sweep.{kind}"
    img.write_bytes(make())
    before = snapshot(w)
    rc, err = run_cli(["composite", img, "--profile", w / "lens.json", "--sweep-alpha-um", "20", "--out",
                       w / "r.tiff"], capsys)
    assert_clean_failure(rc, err, EXIT_BAD_INPUT, "declares")
    assert changed(before, snapshot(w)) == set()


@pytest.mark.parametrize("name", ["png-200k", "tiff-200k-deflate", "png-ratio"])
def test_simulate_refuses_a_bomb_scene(w, capsys, name):
    kind, make = BOMBS[name]
    img = w / f"scene.{kind}"
    img.write_bytes(make())
    before = snapshot(w)
    rc, err = run_cli(["simulate", LENS, w / "T", "--z", "-50", "50", "50", "--size", "64x36", "--scene", img,
                       "--quiet"], capsys)
    assert_clean_failure(rc, err, EXIT_BAD_INPUT, "declares")
    assert changed(before, snapshot(w)) == set()


def test_the_pixel_limit_is_configurable(w, capsys, monkeypatch):
    monkeypatch.setenv("FIELDCAL_MAX_PIXELS", "1000")
    rc, err = run_cli(calibrate_argv(w), capsys)
    assert_clean_failure(rc, err, EXIT_BAD_INPUT, "FIELDCAL_MAX_PIXELS", "256 x 144")
    monkeypatch.setenv("FIELDCAL_MAX_PIXELS", str(256 * 144))
    assert len(Stack.open(w / "S")) == 21
