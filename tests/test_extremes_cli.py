"""Extremes through the command line: every case ends in a one-paragraph message with a fix and a non-zero exit,
never a traceback, and leaves no half-written output. Runs ``fieldcal.cli.main`` in-process (fast)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from fieldcal.cli import main

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    return code, out, err


def test_simulate_at_one_metre_defocus_is_a_clear_error_and_writes_nothing(tmp_path, capsys, triplet_path):
    code, _, err = run(["simulate", triplet_path, tmp_path / "s", "--z", -1e6, 1e6, 1e6, "--size", "32x18",
                        "--quiet"], capsys)
    assert code == 2 and "field '--z'" in err and "fix:" in err
    assert not (tmp_path / "s").exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("q,field", [("1e-12", "--q"), ("1", "--q"), ("0", "--q"), ("nan", "--q")])
def test_plan_stack_with_extreme_q_is_a_clear_error(tmp_path, capsys, triplet_path, q, field):
    out = tmp_path / "plan.json"
    code, _, err = run(["plan", "stack", triplet_path, "--fs", 80, "--q", q, "--size", "96x54", "--out", out],
                       capsys)
    assert code == 2 and f"'{field}'" in err and "fix:" in err
    assert not out.exists()


def test_plan_stack_q_near_one_works(tmp_path, capsys, triplet_path):
    out = tmp_path / "plan.json"
    code, _, _ = run(["plan", "stack", triplet_path, "--fs", 80, "--q", "0.999999999", "--size", "96x54",
                      "--out", out], capsys)
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["n_frames"] >= 1 and all(np.isfinite(f["z_um"]) for f in doc["frames"])


def test_plan_sweep_alpha_to_zero_is_a_clear_error(tmp_path, capsys, triplet_path):
    out = tmp_path / "sweep.json"
    code, _, err = run(["plan", "sweep", triplet_path, "--alpha-um", "1e-9", "--pixel-exposure-ms", 16,
                        "--device", "lcos", "--channels", "G", "--size", "96x54", "--out", out], capsys)
    assert code == 2 and "field '--alpha-um'" in err  # the library's alpha_um, named as the flag
    assert not out.exists() and not (tmp_path / "sweep.masks.npz").exists()


def _stack(root, frames, z, channels=("Y",)):
    (root / "frames").mkdir(parents=True)
    entries = []
    for i, (f, zi) in enumerate(zip(frames, z)):
        name = f"frames/{i:04d}.tiff"
        tifffile.imwrite(root / name, f)
        entries.append({"file": name, "z_um": zi})
    (root / "stack.json").write_text(json.dumps({"format": "fieldcal-stack/1", "pixel_pitch_um": 4.0,
                                                 "channels": list(channels), "frames": entries}))
    return root


def test_calibrate_one_frame_is_a_clear_error(tmp_path, capsys):
    st = _stack(tmp_path / "s", [np.zeros((64, 64), np.uint16)], [0.0])
    out = tmp_path / "lens.json"
    code, _, err = run(["calibrate", st, "--out", out, "--fs", 40], capsys)
    assert code != 0 and "too few frames" in err and "fix:" in err
    assert not out.exists()


def test_composite_of_a_nan_frame_is_a_clear_error(tmp_path, capsys):
    f = [np.full((32, 32), 0.5, np.float32) for _ in range(3)]
    f[1][4, 4] = np.nan
    st = _stack(tmp_path / "s", f, [-10.0, 0.0, 10.0])
    out = tmp_path / "out.tiff"
    code, _, err = run(["composite", st, "--method", "dff", "--out", out, "--quiet"], capsys)
    assert code != 0 and "NaN" in err and "0001.tiff" in err
    assert not out.exists()
