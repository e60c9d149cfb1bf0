"""`fieldcal validate`: metrics against closed forms, a small end-to-end run whose checks a broken stage fails,
and clean CLI errors.

Runs use the paper's triplet rendered at 256x144 px over its real sensor area (24.5 µm pixels, Nyquist 20.4
cycles/mm) at the default fs = 8 cycles/mm (0.4 Nyquist), where the true tolerance is δ = 50.8 µm, the focus
range D = 329.5 µm and the optimum plan has ceil(D / 2δ) = 4 frames.
"""

from __future__ import annotations

import dataclasses as dc
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldcal.errors import ParameterError, SpecError
from fieldcal.simulate.lens import LensSpec
from fieldcal.simulate.truth import TruthProfile
from fieldcal.validation.run import (Check, Thresholds, ValidateConfig, chart_positions_um, geometry_metrics,
                               plan_coverage, psnr_db, relative_mtf, resolve, surface_metrics, validate)
from tests.conftest import MODELS

SIZE = (256, 144)
FS = 8.0


@pytest.fixture(scope="module")
def spec():
    return LensSpec.load(MODELS / "triplet-uncorrected.json").with_sensor_size(*SIZE)


class Biased(TruthProfile):
    """The true lens with a best-focus offset and an extra magnification slope: a miscalibrated profile."""

    def __init__(self, spec, dz_um=0.0, dm_per_um=0.0, band_um=0.0):
        super().__init__(spec)
        self.dz_um, self.dm_per_um, self.band_um = dz_um, dm_per_um, band_um

    def best_focus_um(self, x, y, channel):
        return super().best_focus_um(x, y, channel) + self.dz_um

    def best_focus_interval_um(self, x, y, channel, level=0.9):
        z = self.best_focus_um(x, y, channel)
        return z - self.band_um, z + self.band_um

    def magnification(self, z_um, channel=None):
        return super().magnification(z_um, channel) + self.dm_per_um * (np.asarray(z_um, float) - self.z_ref_um)


# ----------------------------------------------------------------------------------------- metrics
def test_surface_metrics_measure_an_offset_exactly(spec):
    truth = TruthProfile(spec)
    m, maps, _ = surface_metrics(Biased(spec, dz_um=7.0, band_um=5.0), truth)
    for c in spec.channel_names:
        assert m[c]["rms_um"] == pytest.approx(7.0, abs=1e-9)
        assert m[c]["max_um"] == pytest.approx(7.0, abs=1e-9)
        assert m[c]["band_coverage"] == 0.0           # 7 µm off, band ±5 µm: truth never inside
    m2, _, _ = surface_metrics(Biased(spec, dz_um=3.0, band_um=5.0), truth)
    assert all(v["band_coverage"] == 1.0 and v["band_halfwidth_um"] == pytest.approx(5.0) for v in m2.values())


def test_geometry_metrics_registration_error_closed_form(spec):
    truth = TruthProfile(spec)
    dm = 2e-6  # per µm
    g = geometry_metrics(Biased(spec, dm_per_um=dm), truth, -300.0, 0.0)
    cx, cy = truth.optical_centre_px()
    r_corner = math.hypot(cx, cy)     # centred lens: every corner at the half-diagonal
    assert g["registration_error_px"] == pytest.approx(dm * 300.0 * r_corner, rel=1e-6)
    assert g["channels"]["G"]["mag_slope_ppm_per_um"]["error"] == pytest.approx(dm * 1e6, rel=1e-6)
    assert geometry_metrics(truth, truth, -300.0, 0.0)["registration_error_px"] == 0.0


def test_plan_coverage_detects_frames_placed_for_a_wrong_surface(spec):
    from fieldcal.plan import StackRequest, plan_stack
    truth = TruthProfile(spec)
    tols = {c: spec.focus_tolerance_um(FS, 0.05, c) for c in spec.channel_names}
    good = plan_stack(truth, StackRequest(fs_cyc_per_mm=FS, q=0.05))
    cov, _ = plan_coverage(good.frames_um, truth, tols)
    assert all(v["coverage"] == 1.0 and v["min_margin_um"] >= -1e-9 for v in cov.values())
    # a plan made for a surface 1.5 δ too far: the cover is translation invariant, so its first frame sits at
    # z_min + 2.5 δ and the pixels focused at z_min miss their tolerance by 1.5 δ
    d = tols["G"]
    bad = plan_stack(Biased(spec, dz_um=1.5 * d), StackRequest(fs_cyc_per_mm=FS, q=0.05))
    assert np.allclose(bad.frames_um, good.frames_um + 1.5 * d, atol=0.01)
    cov_bad, _ = plan_coverage(bad.frames_um, truth, tols)
    assert cov_bad["G"]["min_margin_um"] == pytest.approx(-1.5 * d, abs=3.0)  # pixel grid vs exact z_min
    assert 0.0 < cov_bad["G"]["coverage"] < 1.0


def test_psnr_closed_form():
    rng = np.random.default_rng(0)
    t = rng.uniform(100, 3000, (40, 50, 3))
    assert psnr_db(t + 4.0, t, black=64, white=4095) == pytest.approx(20 * math.log10(4031 / 4.0))
    assert psnr_db(t, t, 0, 1) == math.inf
    # the border is excluded: errors only there do not count
    e = t.copy()
    e[:3] += 100
    assert psnr_db(e, t, 0, 4095, border_px=3) == math.inf


def test_relative_mtf_of_a_gaussian_blur_matches_its_transfer_function():
    from scipy import ndimage
    rng = np.random.default_rng(1)
    t = rng.normal(0.0, 1.0, (128, 128))
    sigma_px, pitch_um, fs = 1.2, 10.0, 20.0                 # fs = 0.2 cycles/px
    b = ndimage.gaussian_filter(t, sigma_px, mode="wrap")
    f_px = fs * pitch_um / 1000.0
    expect = math.exp(-2 * (math.pi * sigma_px * f_px) ** 2)   # 0.567
    assert relative_mtf(b, t, fs, pitch_um, rel_bandwidth=0.1) == pytest.approx(expect, abs=0.03)
    # uncorrelated noise does not bias it (cross-spectrum)
    noisy = b + rng.normal(0.0, 0.5, b.shape)
    assert relative_mtf(noisy, t, fs, pitch_um, rel_bandwidth=0.1) == pytest.approx(expect, abs=0.05)


@settings(max_examples=25, deadline=None)
@given(a=st.floats(0.05, 20.0), b=st.floats(-1e3, 1e3))
def test_relative_mtf_is_the_gain_of_a_linear_map(a, b):
    t = np.random.default_rng(2).uniform(0, 1, (32, 48, 2))
    assert relative_mtf(a * t + b, t, 10.0, 25.0) == pytest.approx(a, rel=1e-6)


@settings(max_examples=40, deadline=None)
@given(step=st.floats(0.1, 2.0), margin=st.floats(0.0, 5.0), tol=st.floats(1.0, 200.0))
def test_chart_positions_span_the_focus_range_on_a_grid_through_z_ref(spec, step, margin, tol):
    z = chart_positions_um(spec, tol, step, margin)
    lo, hi = spec.focus_range_um()
    assert z[0] <= lo - margin * tol + 1e-6 and z[-1] >= hi + margin * tol - 1e-6
    assert np.allclose(np.diff(z), step * tol)
    assert np.min(np.abs(z - spec.z_ref_um)) < 1e-6 * max(1.0, abs(z).max())   # z_ref is a frame
    assert z[0] > lo - margin * tol - step * tol - 1e-6                           # no wasted frames


def test_check_pass_fail_and_nan():
    assert Check("a", 1.0, 1.0, "<=", "").passed and not Check("a", 1.01, 1.0, "<=", "").passed
    assert Check("b", 0.9, 0.9, ">=", "").passed and not Check("b", 0.5, 0.9, ">=", "").passed
    assert not Check("c", math.nan, 1.0, "<=", "").passed


@pytest.mark.parametrize("kw, field", [({"fs_cyc_per_mm": 30.0}, "fs_cyc_per_mm"),
                                       ({"fs_cyc_per_mm": -1.0}, "fs_cyc_per_mm"),
                                       ({"q": 1.5}, "q"), ({"effort": "fast"}, "effort"),
                                       ({"size_px": (8, 8)}, "size_px"), ({"profile": "magic"}, "profile"),
                                       ({"confidence": 1.0}, "confidence"), ({"seed": -1}, "seed"),
                                       ({"scene": "nowhere.png"}, "scene")])
def test_bad_parameters_name_the_field(kw, field):
    """The library names its own parameters (the CLI shows the flags: test_cli_names_the_flags)."""
    base = LensSpec.load(MODELS / "triplet-uncorrected.json")
    with pytest.raises(ParameterError) as e:
        resolve(base, ValidateConfig(**{"size_px": SIZE, **kw}))
    assert e.value.field == field and e.value.fix


def test_default_fs_is_below_nyquist_of_the_render_size():
    base = LensSpec.load(MODELS / "triplet-uncorrected.json")
    for w, h in ((64, 36), (256, 144), (1024, 576)):
        sized, fs = resolve(base, ValidateConfig(size_px=(w, h)))
        assert 0 < fs < 0.9 * 500.0 / sized.sensor.pixel_pitch_um


# ---------------------------------------------------------------------------------------- pipeline
@pytest.fixture(scope="module")
def truth_run(spec):
    cfg = ValidateConfig(size_px=SIZE, fs_cyc_per_mm=FS, profile="truth", seed=3)
    return validate(MODELS / "triplet-uncorrected.json", cfg, quiet=True)


def test_truth_pipeline_plan_and_composite(truth_run):
    r = truth_run
    assert r.passed, [c.to_dict() for c in r.failed]
    assert r.plan["coverage_min"] == 1.0 and r.plan["n_frames"] == r.plan["n_optimal_true"] == 4
    cm = r.composite
    # compositing at the planned frames beats one frame focused on axis, most of all in the corners
    assert cm["gain_over_one_shot_db"] > 3.0
    assert cm["composite"]["psnr_corners_db"] - cm["one_shot"]["psnr_corners_db"] > 4.0
    # every corner within the tolerance keeps MTF(fs) within about q of the in-focus truth; the one shot does not
    assert cm["composite"]["mtf_rel_corners_min"] > 0.9
    assert cm["one_shot"]["mtf_rel_corners_mean"] < 0.85
    assert abs(cm["gap_to_oracle_db"]) < 1e-9          # the oracle *is* this profile here
    json.dumps(r.to_dict(), allow_nan=False)          # the summary is strict JSON


def test_a_miscalibrated_profile_fails_the_right_checks(spec):
    tol = spec.focus_tolerance_um(FS, 0.05, "G")
    bad = Biased(spec, dz_um=1.5 * tol, dm_per_um=3e-5, band_um=2.0)   # 3e-5/µm: ~2.4 px at the corner
    cfg = ValidateConfig(size_px=SIZE, fs_cyc_per_mm=FS, seed=3, confidence=None)
    r = validate(MODELS / "triplet-uncorrected.json", cfg, profile=bad, quiet=True)
    failed = {c.name for c in r.failed}
    assert {"surface_rms_G", "surface_max_G", "band_coverage_G", "registration_px", "plan_coverage",
            "psnr_gap_to_oracle_db"} <= failed
    assert r.composite["gap_to_oracle_db"] > 1.0


def test_given_profile_of_another_size_is_refused(spec):
    with pytest.raises(ParameterError) as e:
        validate(MODELS / "triplet-uncorrected.json", ValidateConfig(size_px=(96, 54), fs_cyc_per_mm=5.0),
                 profile=TruthProfile(spec), quiet=True)
    assert e.value.field == "size_px" and "256x144" in e.value.fix


@pytest.mark.parametrize("argv, flag", [(["--fs", "1000"], "--fs"), (["--size", "8x8"], "--size"),
                                        (["--q", "2"], "--q"), (["--scene", "nowhere.png"], "--scene"),
                                        (["--confidence", "x"], "--confidence")])
def test_cli_names_the_flags(tmp_path, capsys, argv, flag):
    from fieldcal.cli import main
    code = main(["validate", str(MODELS / "triplet-uncorrected.json"), "--out", str(tmp_path / "v"), *argv])
    assert code == 2 and f"field '{flag}'" in capsys.readouterr().err


def test_report_files(truth_run, tmp_path):
    from fieldcal.validation.report import write_report
    files = write_report(truth_run, tmp_path)
    names = {f.name for f in files}
    assert {"surfaces.png", "geometry.png", "plan.png", "composite.png", "index.html", "report.md",
            "summary.json"} <= names
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["passed"] is True and s["plan"]["n_frames"] == 4
    assert "PASS" in (tmp_path / "index.html").read_text()
    assert not list(tmp_path.glob(".*tmp*"))


@pytest.fixture(scope="module")
def calibrated_run():
    # 384 px: at 256 px the outermost tiles stop far from the corners and a quick fit extrapolates there
    return validate(MODELS / "triplet-uncorrected.json", ValidateConfig(size_px=(384, 216), seed=0, effort="quick"),
                    quiet=True)


@pytest.mark.slow
def test_calibrated_pipeline_downstream_checks(calibrated_run):
    """The full pipeline: geometry, plan coverage and composite quality from the calibrated profile."""
    r = calibrated_run
    assert r.setup["chart"]["n_frames"] >= 20
    ok = {c.name for c in r.checks if c.passed}
    assert {"registration_px", "plan_coverage", "plan_frames", "psnr_gain_over_one_shot_db",
            "psnr_gap_to_oracle_db"} <= ok, [c.to_dict() for c in r.failed]
    assert r.geometry["channels"]["G"]["mag_slope_ppm_per_um"]["error"] == pytest.approx(0.0, abs=1.0)
    assert r.surface["G"]["rms_um"] < 0.25 * r.setup["true_tolerance_um"]["G"]


@pytest.mark.slow
def test_calibrated_surfaces_and_bands_meet_the_thresholds(calibrated_run):
    assert calibrated_run.passed, [c.to_dict() for c in calibrated_run.failed]


# --------------------------------------------------------------------------------------------- CLI
def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "fieldcal", "validate", *args], capture_output=True, text=True,
                          cwd=cwd, env={**__import__("os").environ, "FIELDCAL_PROGRESS": "0"})


def test_cli_help_has_an_example():
    p = _cli("--help")
    assert p.returncode == 0 and "example:" in p.stdout and "fieldcal validate" in p.stdout


@pytest.mark.parametrize("args, needle", [(["missing.json"], "lens spec not found"),
                                          (["{lens}", "--fs", "500", "--size", "64x36"], "--fs"),
                                          (["{lens}", "--size", "abc"], "--size"),
                                          (["{lens}", "--scene", "nothing.png"], "--scene"),
                                          (["{lens}", "--profile", "nope.json"], "--profile"),
                                          (["{lens}", "--confidence", "x"], "--confidence")])
def test_cli_errors_are_clean_and_write_nothing(tmp_path, args, needle):
    lens = str(MODELS / "triplet-uncorrected.json")
    out = tmp_path / "rep"
    p = _cli(*[a.format(lens=lens) for a in args], "--out", str(out))
    assert p.returncode == 2
    assert needle in p.stderr and "fix:" in p.stderr and "Traceback" not in p.stderr
    assert not out.exists()


def test_cli_exit_status_follows_the_checks(tmp_path, monkeypatch):
    import fieldcal.validation.run as fv
    from fieldcal.cli import main
    monkeypatch.setenv("FIELDCAL_PROGRESS", "0")
    lens = str(MODELS / "triplet-uncorrected.json")
    args = [lens, "--size", "192x108", "--profile", "truth", "--no-plots"]
    assert main(["validate", *args, "--out", str(tmp_path / "ok")]) == 0
    real = fv.validate

    def strict(lens, cfg, **kw):  # an unreachable PSNR gain: the run must report a failure
        return real(lens, dc.replace(cfg, thresholds=Thresholds(psnr_gain_db_min=100.0)), **kw)

    monkeypatch.setattr(fv, "validate", strict)
    assert main(["validate", *args, "--out", str(tmp_path / "bad")]) == 1
    s = json.loads((tmp_path / "bad" / "summary.json").read_text())
    assert s["passed"] is False and any(c["name"] == "psnr_gain_over_one_shot_db" and not c["passed"]
                                        for c in s["checks"])


def test_lens_file_errors_are_spec_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    with pytest.raises(SpecError):
        validate(bad, ValidateConfig(size_px=SIZE), quiet=True)


def test_demo_settings_follow_the_lens():
    """The demo's choices (fieldcal.validation.demo): fs resolvable at the size, a z grid through z_ref that
    covers the best-focus range with four steps of margin, steps about half the tolerance."""
    from fieldcal.validation.demo import demo_settings
    base = LensSpec.load(MODELS / "triplet-uncorrected.json")
    for w, h in ((160, 90), (640, 360), (3840, 2160)):
        spec = base.with_sensor_size(w, h)
        d = demo_settings(spec, 0.05)
        nyq = 500.0 / spec.sensor.pixel_pitch_um
        assert d.fs_cyc_per_mm == min(80.0, round(0.4 * nyq)) and d.fs_cyc_per_mm < 0.9 * nyq
        assert d.tolerance_um == pytest.approx(min(spec.focus_tolerance_um(d.fs_cyc_per_mm, 0.05, c)
                                                   for c in spec.channel_names))
        assert d.step_um == max(1.0, round(d.tolerance_um / 2, 1))
        k = (spec.z_ref_um - d.z_start_um) / d.step_um
        assert abs(k - round(k)) < 1e-9                                    # z_ref is on the grid
        assert d.z_start_um <= d.focus_lo_um - 4 * d.step_um < d.z_start_um + d.step_um
        assert d.z_stop_um >= d.focus_hi_um + 4 * d.step_um > d.z_stop_um - d.step_um
