"""`fieldcal batch calibrate` and `fieldcal validate --lenses` on Dask: results identical to the serial run, a
failed unit reported while the others finish, the fleet report, and the errors when Dask or its scheduler is
not there. Small stacks on an in-process LocalCluster (threads) keep each test to a few seconds."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")

from fieldcal.batch.calibrate import profile_without_times, unit_names, without_times  # noqa: E402
from fieldcal.batch.fleet import compare_units, fleet_statistics  # noqa: E402
from fieldcal.cli import main  # noqa: E402
from fieldcal.formats import documents  # noqa: E402

MODELS = Path(__file__).resolve().parents[1] / "models"
CAL = ["--fs", "16", "--effort", "quick"]


@pytest.fixture(scope="module")
def two_stacks(tmp_path_factory):
    """Two units of the triplet: 21 frames of 256x144 px, different noise; the second one tilted."""
    import dataclasses

    from fieldcal.simulate.lens import LensSpec
    from fieldcal.simulate.stackgen import simulate_stack, z_grid

    root = tmp_path_factory.mktemp("fleet")
    spec = LensSpec.load(MODELS / "triplet-uncorrected.json")
    tilted = dataclasses.replace(spec, tilt_um_per_mm=(6.0, 0.0))
    for name, s, seed in (("unit-a", spec, 3), ("unit-b", tilted, 4)):
        simulate_stack(s, root / name, z_grid(-380.0, 60.0, 20.0), scene="chart", seed=seed, size=(256, 144),
                       progress=False)
    return root


def _batch(args):
    return main(["batch", "calibrate", *args, "--scheduler", "threads", "--workers", "2", "-q"])


def test_batch_equals_serial_calibrate_and_writes_the_fleet_report(two_stacks, tmp_path):
    a, b = two_stacks / "unit-a", two_stacks / "unit-b"
    assert _batch([str(a), str(b), "--out", str(tmp_path / "fleet"), *CAL]) == 0
    assert main(["calibrate", str(b), "--out", str(tmp_path / "serial.json"), *CAL, "-q"]) == 0
    batch_file, serial_file = tmp_path / "fleet" / "unit-b.json", tmp_path / "serial.json"
    assert profile_without_times(batch_file) == profile_without_times(serial_file)
    # what was taken out: the time keys only (the sidecar is the same file, named after each profile)
    full = json.loads(batch_file.read_text())
    assert without_times(full) != full and "created_utc" not in without_times(full)
    assert without_times(full)["surfaces"] == without_times(json.loads(serial_file.read_text()))["surfaces"]
    doc = documents.read(tmp_path / "fleet" / "fleet.json", "fleet")
    assert doc["n_units"] == 2 and doc["n_failed"] == 0
    assert [u["name"] for u in doc["units"]] == ["unit-a", "unit-b"]
    assert (tmp_path / "fleet" / "fleet.png").stat().st_size > 1000
    # the tilt of unit b (6 µm/mm along x) shows as the fleet's spread: two units at ±half the difference
    g = doc["fleet"]["channels"]["G"]
    rms = [g["per_unit"][n]["rms_deviation_um"] for n in ("unit-a", "unit-b")]
    assert rms[0] == pytest.approx(rms[1], rel=1e-9)
    sd = np.asarray(g["sd_surface_um"])
    assert sd[:, -1].mean() > sd[:, sd.shape[1] // 2].mean()  # larger at the edges than in the middle


def test_a_broken_stack_is_reported_and_the_others_finish(two_stacks, tmp_path, capsys):
    bad = tmp_path / "broken"
    bad.mkdir()
    (bad / "stack.json").write_text('{"format": "fieldcal-stack/1"}')
    code = _batch([str(two_stacks / "unit-a"), str(bad), "--out", str(tmp_path / "out"), *CAL, "--no-plots"])
    err = capsys.readouterr().err
    assert code == 2  # the failed unit's own exit status (a bad input), docs/batch.md
    assert "1 of 2 unit(s) FAILED" in err and "broken: error (exit 2)" in err and "pixel_pitch_um" in err
    assert (tmp_path / "out" / "unit-a.json").is_file()
    doc = documents.read(tmp_path / "out" / "fleet.json", "fleet")
    failed = [u for u in doc["units"] if not u["ok"]]
    assert [(u["name"], u["exit_code"]) for u in failed] == [("broken", 2)]
    assert "pixel_pitch_um" in failed[0]["error"] and failed[0]["output"] is None
    assert doc["fleet"]["channels"]["G"]["units"] == ["unit-a"]


def test_an_existing_scheduler_over_tcp(two_stacks, tmp_path):
    import logging

    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://",
                      dashboard_address=None, silence_logs=logging.ERROR) as cluster:
        assert cluster.scheduler_address.startswith("tcp://")
        code = main(["batch", "calibrate", str(two_stacks / "unit-a"), "--out", str(tmp_path / "o"), *CAL,
                     "--scheduler", cluster.scheduler_address, "-q", "--no-plots"])
    assert code == 0 and (tmp_path / "o" / "unit-a.json").is_file()


def test_no_dask_is_exit_4_with_the_install_command(two_stacks, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    code = main(["batch", "calibrate", str(two_stacks / "unit-a"), "--out", str(tmp_path / "o"), *CAL])
    assert code == 4
    assert 'pip install -e ".[dask]"' in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("extra, field", [(["--scheduler", "http//nowhere"], "--scheduler"),
                                          (["--scheduler", "tcp://127.0.0.1:8786", "--workers", "2"], "--workers"),
                                          (["--workers", "0"], "--workers"), (["--q", "1.5"], None)])
def test_bad_scheduler_options_are_exit_2(two_stacks, tmp_path, capsys, extra, field):
    code = main(["batch", "calibrate", str(two_stacks / "unit-a"), "--out", str(tmp_path / "o"), *extra])
    assert code == 2
    err = capsys.readouterr().err
    assert "fix:" in err and (field is None or field in err)


def test_an_unreachable_scheduler_is_exit_4(two_stacks, tmp_path, monkeypatch, capsys):
    import fieldcal.batch.engine as engine

    monkeypatch.setattr(engine, "CONNECT_TIMEOUT_S", 1.0)
    code = main(["batch", "calibrate", str(two_stacks / "unit-a"), "--out", str(tmp_path / "o"), *CAL,
                 "--scheduler", "tcp://127.0.0.1:9"])
    assert code == 4 and "dask scheduler" in capsys.readouterr().err


def test_unit_names_are_unique_and_plain():
    assert unit_names(["a/stack", "b/stack", "c/Stack", "d/x y", "e/stack.json"]) == \
        ["stack", "stack-2", "Stack-3", "x_y", "e"]


def test_the_z_score_flags_the_unit_off_by_six_sigma():
    """n units of one surface plus independent noise of their stated sd: z is N(0, 1), so its RMS is ~1 for
    every unit; a unit shifted by 6 sd scores 6 / sqrt(1 + 1/(n-1)) (the mean of the others is uncertain too)
    and is flagged, while the others stay below the limit (the outlier widens the spread that judges them)."""
    rng = np.random.default_rng(1)
    n, sd = 12, 0.5
    base = np.linspace(-20.0, 5.0, 400)
    s = base + sd * rng.standard_normal((n, base.size))
    z_rms, _ = compare_units(s, np.full_like(s, sd))
    assert np.all(np.abs(z_rms - 1.0) < 0.15)
    s[3] += 6 * sd
    z_rms, z_max = compare_units(s, np.full_like(s, sd))
    assert z_rms[3] == pytest.approx(6 / np.sqrt(1 + 1 / (n - 1)), rel=0.1)
    assert np.all(np.delete(z_rms, 3) < 1.2)
    assert np.all(z_max >= z_rms)


def test_fleet_statistics_on_known_surfaces():
    """Two units at ±d around a common surface: mean = the surface, sd = d·√2, RMS deviation d each; with
    stated sds σ the z-score is 2d / sqrt(2σ²)."""
    shape, d, sig = (3, 4), 1.5, 0.5
    base = np.arange(12.0).reshape(shape)
    maps = {n: {"channels": {"G": {"surface_um": base + k * d, "sd_um": np.full(shape, sig),
                                   "tolerance_um": np.full(shape, 10.0 + k)}}}
            for n, k in (("u1", 1), ("u2", -1))}
    st = fleet_statistics(maps, grid=(4, 3), z_limit=3.0)["G"]
    np.testing.assert_allclose(st["mean_surface_um"], base)
    np.testing.assert_allclose(st["sd_surface_um"], d * np.sqrt(2))
    assert st["per_unit"]["u1"]["rms_deviation_um"] == pytest.approx(d)
    assert st["per_unit"]["u1"]["z_rms"] == pytest.approx(2 * d / np.sqrt(2 * sig ** 2))
    assert st["per_unit"]["u1"]["significant"] and st["per_unit"]["u2"]["significant"]
    np.testing.assert_allclose(st["mean_tolerance_um"], 10.0)


def test_validate_lenses_runs_one_task_per_lens(tmp_path, capsys):
    out = tmp_path / "v"
    code = main(["validate", "--lenses", "2", "--size", "96x72", "--profile", "truth", "--out", str(out),
                 "--scheduler", "threads", "--workers", "2", "--no-plots"])
    assert code in (0, 1)  # 1: a check of a random lens failed at this tiny size (the reports say which)
    doc = documents.read(out / "fleet.json", "fleet")
    assert [u["name"] for u in doc["units"]] == ["lens-000", "lens-001"] and doc["n_failed"] == 0
    for u in doc["units"]:
        summary = documents.read(out / u["name"] / "summary.json", "validation")
        assert summary["passed"] == u["passed"]
        assert (out / u["name"] / "lens.json").is_file()
    assert code == (0 if all(u["passed"] for u in doc["units"]) else 1)
    # the same lens validated alone (from the lens.json its unit wrote) gives the same summary but for times
    assert main(["validate", str(out / "lens-001" / "lens.json"), "--size", "96x72", "--profile", "truth",
                 "--out", str(tmp_path / "one"), "--no-plots"]) in (0, 1)
    one, unit = (json.loads((d / "summary.json").read_text()) for d in (tmp_path / "one", out / "lens-001"))
    assert without_times(one) == without_times(unit) and "timings_s" in unit


@pytest.mark.parametrize("argv", [["models/triplet-uncorrected.json", "--lenses", "2"], ["--workers", "2"],
                                  ["--lenses", "0"], ["--lenses", "1", "--profile", "lens.json"], []])
def test_validate_lens_options_are_checked(argv, tmp_path):
    assert main(["validate", *argv, "--out", str(tmp_path / "v")]) == 2


def test_only_the_engine_imports_dask():
    import re

    pkg = Path(__file__).resolve().parents[1] / "fieldcal"
    hits = [p.relative_to(pkg).as_posix() for p in pkg.rglob("*.py")
            if re.search(r"^\s*(import|from)\s+(dask|distributed)\b", p.read_text(encoding="utf-8"), re.M)]
    assert hits == ["batch/engine.py"]


def test_a_unit_error_names_the_flag(two_stacks, tmp_path, capsys):
    """fs above a stack's Nyquist is found per stack (its pixel pitch): the unit fails naming --fs, as
    `fieldcal calibrate` would."""
    code = _batch([str(two_stacks / "unit-a"), "--out", str(tmp_path / "o"), "--fs", "19", "--no-plots"])
    assert code == 2
    assert "unit-a: error (exit 2): field '--fs'" in capsys.readouterr().err
    doc = documents.read(tmp_path / "o" / "fleet.json", "fleet")
    assert doc["units"][0]["error"].startswith("field '--fs'") and doc["fleet"] is None
