"""`fieldcal profile diff` and `profile show`: the max-|z| calibration, known changes, two calibrations of one lens."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from scipy.special import ndtri

from fieldcal.cli import main
from fieldcal.formats import documents
from fieldcal.profile import LensProfile
from fieldcal.profile.diff import diff_profiles, max_z_test
from fieldcal.profile.show import format_summary, profile_summary


def test_max_z_critical_value_matches_closed_forms():
    """Independent points: Šidák's value; one fully correlated field: the pointwise value; between: between."""
    level, m = 0.95, 60
    t = max_z_test(np.zeros(m), np.eye(m), level, n_null=40000)
    assert t.critical_z == pytest.approx(float(ndtri(0.5 + 0.5 * level ** (1 / m))), abs=0.04)
    assert t.n_effective == pytest.approx(m, rel=0.15)
    t1 = max_z_test(np.zeros(m), np.ones((m, m)) + 1e-9 * np.eye(m), level, n_null=40000)
    assert t1.critical_z == pytest.approx(float(ndtri(0.5 + 0.5 * level)), abs=0.04)
    x = np.linspace(0, 1, m)
    smooth = np.exp(-np.abs(x[:, None] - x[None, :]) / 0.2)
    t2 = max_z_test(np.zeros(m), smooth, level)
    assert t1.critical_z < t2.critical_z < t.critical_z
    # candidates: the test takes the most demanding one
    assert max_z_test(np.zeros(m), [smooth, np.eye(m)], level).critical_z == pytest.approx(t.critical_z, abs=0.05)


def test_max_z_false_alarm_rate_is_the_level():
    """Fresh draws from the null exceed the critical value at 1 - level (within binomial noise)."""
    m, level = 40, 0.9
    x = np.linspace(0, 1, m)
    cov = np.exp(-np.abs(x[:, None] - x[None, :]) / 0.15) * np.outer(1 + x, 1 + x)
    t = max_z_test(np.zeros(m), cov, level, n_null=40000, seed=3)
    g = np.random.default_rng(99).multivariate_normal(np.zeros(m), cov, size=20000)
    rate = np.mean(np.max(np.abs(g) / np.sqrt(np.diag(cov)), axis=1) > t.critical_z)
    assert rate == pytest.approx(1 - level, abs=0.01)


@pytest.fixture(scope="module")
def prof_path(hostile_world):
    return hostile_world / "lens.json"


def _changed(prof_path, tmp_path, name, piston_um=0.0, breathing=0.0):
    p = LensProfile.load(prof_path)
    p.surfaces = copy.copy(p.surfaces)
    p.surfaces.z_centre_um += piston_um
    if breathing:
        g = copy.deepcopy(p.geometry_fit)
        for ch, f in g.mag.items():
            coef = f.coef.copy()
            coef[0] += breathing
            g.mag[ch] = type(f)(coef, f.cov, f.chi2_dof)
        p.geometry_fit = g
    out = tmp_path / f"{name}.json"
    p.save(out)
    return out


def test_a_profile_against_itself(prof_path):
    a = LensProfile.load(prof_path)
    doc, maps = diff_profiles(a, LensProfile.load(prof_path), nx=8, n_null=2000)
    documents.validate(json.loads(json.dumps(doc)), "profile-diff", "diff.json")
    assert doc["significant"] is False
    for ch in a.channels:
        assert doc["channels"][ch]["max_abs_diff_um"] == 0.0
        assert doc["channels"][ch]["max_z_score"] == 0.0
    assert set(doc["channels"]) == set(a.channels)


def test_known_changes_are_found_where_and_how_big(prof_path, tmp_path):
    """An 8 µm piston of every surface and a breathing change of 0.1 % over the scan: both flagged, sized right.

    The piston is about three times this calibration's real error: the fixture is a quick 256x144 calibration
    whose scan stops short of 42 % of the tiles' peaks, 2.1-2.6 µm RMS off the truth with a 90 % band of
    +-4.6 µm that holds it (0.97-1.00). 4 µm is inside that band, so an honest profile need not flag it in
    every channel (R: max z 4.1 against 4.5); it was flagged only while the renderer's blur-level cusp made
    the fixture's profile 5 µm off with a +-1 µm band (coverage 0.45-0.50, docs/simulator.md "Blur levels").
    """
    piston_um = 8.0
    a = LensProfile.load(prof_path)
    b = LensProfile.load(_changed(prof_path, tmp_path, "piston", piston_um=piston_um))
    doc, _ = diff_profiles(a, b, nx=8, n_null=2000)
    assert doc["significant"]
    for ch in a.channels:
        c = doc["channels"][ch]
        e = next(iter(c["orientations"].values()))
        assert e["mean_diff_um"] == pytest.approx(-piston_um, abs=1e-6)
        assert e["components"]["offset_um"]["diff"] == pytest.approx(-piston_um, abs=0.05)
        assert c["significant"], (ch, c["max_z_score"], c["critical_z"])
    assert not doc["geometry"]["significant"]
    # breathing: m(z) - 1 = b1 t; b1 += 0.001 is 0.1 % more magnification at the scan's ends
    c = LensProfile.load(_changed(prof_path, tmp_path, "breathing", breathing=0.001))
    doc, _ = diff_profiles(a, c, nx=8, n_null=2000)
    assert doc["geometry"]["significant"] and doc["significant"]
    st = doc["geometry"]["channels"][a.channels[0]]["statistics"]["breathing_per_um"]
    assert st["diff"] == pytest.approx(-0.001 / a.geometry_fit.z_scale_um, rel=0.05)
    assert all(not ch["significant"] for ch in doc["channels"].values())


def test_cli_diff_show_and_exit_codes(prof_path, tmp_path, capsys):
    b = _changed(prof_path, tmp_path, "b", piston_um=8.0)  # well outside the fixture's band (see above)
    assert main(["profile", "diff", str(prof_path), str(prof_path), "--json", "--grid", "8", "--draws", "2000"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["format"] == "fieldcal-profile-diff/1" and doc["significant"] is False
    plots = tmp_path / "plots"
    assert main(["profile", "diff", str(prof_path), str(b), "--plot", str(plots), "--out",
                 str(tmp_path / "d.json"), "--grid", "8", "--draws", "2000"]) == 0
    out = capsys.readouterr().out
    assert "DIFFERENT" in out and "SIGNIFICANT" in out
    # a mean-difference plot per channel, and a tolerance one where the profiles measured widths (quick effort
    # does since its default measure takes the band-pass too)
    kinds = ["mean"] + (["tolerance"] if LensProfile.load(prof_path).tolerance_fit is not None else [])
    assert sorted(p.name for p in plots.iterdir()) == sorted(f"diff-{c}-{k}.png" for c in "RGB" for k in kinds)
    assert documents.read(tmp_path / "d.json", "profile-diff")["significant"] is True
    assert main(["profile", "diff", str(prof_path), str(b), "--grid", "8", "--draws", "2000", "--fail-if-significant"]) == 1
    assert main(["profile", "diff", str(prof_path), str(prof_path), "--grid", "8", "--draws", "2000", "--fail-if-significant"]) == 0
    capsys.readouterr()
    assert main(["profile", "diff", str(prof_path), str(b), "--level", "1.5"]) == 2
    assert "--level" in capsys.readouterr().err
    assert main(["profile", "diff", str(prof_path), str(tmp_path / "missing.json")]) == 2
    assert main(["profile", "show", str(prof_path)]) == 0
    text = capsys.readouterr().out
    for word in ("triplet-uncorrected", "best focus", "breathing", "self-check", "distortion", "sha256"):
        assert word in text
    assert main(["profile", "show", str(prof_path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert set(s["surfaces"]) == {"R", "G", "B"}


def test_show_numbers_come_from_the_profile(prof_path):
    p = LensProfile.load(prof_path)
    s = profile_summary(p)
    cx, cy = p.optical_centre_px()
    g = s["surfaces"]["G"]
    assert g["best_focus_centre_um"] == pytest.approx(float(p.best_focus_um(cx, cy, "G")))
    w, h = p.image_size_px
    corners = p.best_focus_um(np.array([0, w - 1, 0, w - 1.0]), np.array([0, 0, h - 1, h - 1.0]), "G")
    assert g["sag_centre_to_corner_um"] == pytest.approx(float(np.mean(corners)) - g["best_focus_centre_um"])
    assert "G" in format_summary(s)


def test_two_calibrations_of_one_lens(tmp_path):
    """The benchmark's trials, two of them: the same lens is not flagged; a tilt of 3 µm/mm and 0.1 % of
    breathing are (benchmarks/bench_profile_diff.py runs 20, with a tilt of 3 µm at the corner too)."""
    from bench_util import import_bench
    bench = import_bench("bench_profile_diff")
    for k in (0, 1):
        row = bench.trial(k, tmp_path, changes=("tilt_mm", "breathing"), n_null=2000)
        assert not row["null_significant"], row
        assert row["tilt_mm_significant"] and row["breathing_significant"], row


def test_joint_uncertainty_has_the_profiles_own_bands(prof_path):
    """The joint covariance's diagonal is the band's variance; breathing is d ln m / dz of the fitted m(z)."""
    from fieldcal.profile.uncertainty import geometry_rates, surface_estimate
    p = LensProfile.load(prof_path)
    w, h = p.image_size_px
    x, y = np.meshgrid(np.linspace(0, w - 1, 6), np.linspace(0, h - 1, 4))
    e = surface_estimate(p, x.ravel(), y.ravel(), "G")
    lo, hi = p.best_focus_interval_um(x.ravel(), y.ravel(), "G", 0.9)
    # a Gaussian band: half-width = 1.645 sd, within what the band's own shape allows: it is the quantiles of a
    # model average's samples, a mixture of members whose surfaces differ, so not exactly Gaussian where they
    # disagree (this fixture since session 8: top member at weight 0.72, ratios 0.94-1.09 over these points, the
    # largest at the right edge; on main before it 0.99-1.02)
    np.testing.assert_allclose(0.5 * (hi - lo), 1.6449 * e.sd, rtol=0.12)
    for ell in e.lengths:
        np.testing.assert_allclose(np.sqrt(np.diag(e.cov(ell))), e.sd, rtol=1e-9)
    z = 0.5 * sum(p.z_range_um)
    r = geometry_rates(p, "G", z)["breathing_per_um"]
    dz = 1e-3
    num = (np.log(p.magnification(z + dz, "G")) - np.log(p.magnification(z - dz, "G"))) / (2 * dz)
    assert r.value == pytest.approx(float(num), rel=1e-6)
