"""LensProfile: the DESIGN.md API, save/load round trip, version and sidecar validation (no images needed)."""

import json

import numpy as np
import pytest

from fieldcal.errors import ParameterError, SpecError
from fieldcal.fit import ImageGeometry, fit_surfaces
from fieldcal.fit.geometry import GeometryData, fit_geometry
from fieldcal.fit.synthetic import base_lens, synthetic_tiles
from fieldcal.fit.tolerance import fit_tolerance
from fieldcal.profile.lens_profile import LensProfile
from fieldcal.simulate.truth import TruthProfile


@pytest.fixture(scope="module")
def profile_and_truth():
    spec = base_lens()
    from dataclasses import replace
    chans = tuple(replace(c, focus_offset_um=off, curvature_um=(-120.0,))
                  for c, off in zip(spec.channels, (8.0, 0.0, -5.0)))
    spec = replace(spec, channels=chans, exit_pupil_mm=20.0, stage_axis_tilt_mrad=(0.5, -0.2))
    truth = TruthProfile(spec)
    rng = np.random.default_rng(4)
    tiles, geom, _ = synthetic_tiles(spec, rng, fs_cyc_per_mm=40.0)
    surf = fit_surfaces(tiles, geom, effort="quick", quiet=True)
    z = np.linspace(-150, 50, 11)
    rows = {"z_um": [], "channel": [], "magnification": [], "mag_sigma": [], "shift_x_px": [], "shift_y_px": [],
            "shift_sigma_px": []}
    for zz in z:
        dx, dy = truth.shift_px(zz)
        for c in truth.channels:
            rows["z_um"].append(zz); rows["channel"].append(c)
            rows["magnification"].append(float(truth.magnification(zz)) + rng.normal(0, 1e-5))
            rows["mag_sigma"].append(1e-5)
            rows["shift_x_px"].append(float(dx) + rng.normal(0, 0.01))
            rows["shift_y_px"].append(float(dy) + rng.normal(0, 0.01))
            rows["shift_sigma_px"].append(0.01)
    gfit = fit_geometry(GeometryData.from_arrays(**rows), z_ref_um=0.0)
    tol = fit_tolerance(tiles, geom, 40.0, 0.05)
    profile = LensProfile(
        surfaces=surf, geometry_fit=gfit, tolerance_fit=tol,
        image={"width_px": geom.width_px, "height_px": geom.height_px, "pixel_pitch_um": geom.pixel_pitch_um,
               "channels": list(truth.channels), "cfa": None},
        optics={"f_number": spec.f_number, "focal_length_mm": spec.focal_length_mm, "object_distance_mm": None},
        calibration={"fs_cyc_per_mm": 40.0, "q": 0.05, "effort": "quick", "z_range_um": [-150.0, 50.0]},
        z_ref_um=0.0, diagnostics={"note": "synthetic"}, provenance={"stack": "synthetic"},
        tiles={"channel": np.asarray(tiles.channel), "x_px": tiles.x_px, "y_px": tiles.y_px,
               "z_best_um": tiles.z_best_um, "status": np.full(len(tiles), "ok")})
    return profile, truth


def test_design_api_against_truth(profile_and_truth):
    p, truth = profile_and_truth
    assert p.channels == ("R", "G", "B")
    X, Y = np.meshgrid(np.linspace(0, 319, 17), np.linspace(0, 239, 13))
    for c in p.channels:
        z = p.best_focus_um(X, Y, c)
        assert z.shape == X.shape
        assert np.sqrt(np.mean((z - truth.best_focus_um(X, Y, c)) ** 2)) < 1.5
        lo, hi = p.best_focus_interval_um(X, Y, c, level=0.9)
        assert np.all(lo <= z + 1e-9) and np.all(z <= hi + 1e-9) and np.all(hi - lo > 0)
        lo5, hi5 = p.best_focus_interval_um(X, Y, c, level=0.5)
        assert np.all(hi5 - lo5 <= hi - lo + 1e-9)  # a lower level gives a narrower band
    assert p.magnification(p.z_ref_um, "G") == pytest.approx(1.0, abs=1e-9)
    assert p.magnification(-150.0, "G") == pytest.approx(float(truth.magnification(-150.0)), abs=2e-5)
    dx, dy = p.shift_px(-150.0, "G")
    tdx, tdy = truth.shift_px(-150.0)
    assert dx == pytest.approx(float(tdx), abs=0.02) and dy == pytest.approx(float(tdy), abs=0.02)
    t = p.focus_tolerance_um(160.0, 120.0, "G", 40.0, 0.05)
    assert t == pytest.approx(truth.spec.focus_tolerance_um(40.0, 0.05, "G"), rel=0.15)


def test_bad_queries_are_clear(profile_and_truth):
    p, _ = profile_and_truth
    with pytest.raises(ParameterError, match="channel"):
        p.best_focus_um(1.0, 1.0, "Y")
    with pytest.raises(ParameterError, match="level"):
        p.best_focus_interval_um(1.0, 1.0, "G", level=1.5)
    with pytest.raises(ParameterError, match="broadcast"):
        p.best_focus_um(np.zeros(3), np.zeros(4), "G")


def test_save_load_round_trip(profile_and_truth, tmp_path):
    p, _ = profile_and_truth
    path = p.save(tmp_path / "lens.json")
    side = json.loads(path.read_text())["sidecar"]
    assert (tmp_path / side["file"]).is_file()
    assert side["file"] == f"lens.{side['sha256'][:16]}.samples.npz"  # content-addressed
    q = LensProfile.load(path)
    x, y = np.array([0.0, 100.0, 319.0]), np.array([0.0, 50.0, 239.0])
    for c in p.channels:
        np.testing.assert_allclose(q.best_focus_um(x, y, c), p.best_focus_um(x, y, c))
        np.testing.assert_allclose(q.best_focus_interval_um(x, y, c), p.best_focus_interval_um(x, y, c))
        np.testing.assert_allclose(q.magnification([-100.0, 40.0], c), p.magnification([-100.0, 40.0], c))
        np.testing.assert_allclose(q.shift_px([-100.0, 40.0], c), p.shift_px([-100.0, 40.0], c))
        np.testing.assert_allclose(q.focus_tolerance_um(x, y, c, 80.0, 0.02), p.focus_tolerance_um(x, y, c, 80.0, 0.02))
    assert q.tiles is not None and len(q.tiles["x_px"]) == len(p.tiles["x_px"])
    d = json.loads(path.read_text())
    assert d["format"] == "fieldcal-profile/1" and d["tool"]["name"] == "fieldcal"
    assert {"surfaces", "geometry", "tolerance", "model_selection", "diagnostics", "provenance"} <= set(d)


def test_load_refuses_newer_unknown_and_mismatched(profile_and_truth, tmp_path):
    p, _ = profile_and_truth
    path = p.save(tmp_path / "lens.json")
    d = json.loads(path.read_text())
    newer = tmp_path / "newer.json"
    newer.write_text(json.dumps({**d, "format": "fieldcal-profile/2"}))
    with pytest.raises(SpecError, match="newer") as e:
        LensProfile.load(newer)
    assert "upgrade" in str(e.value) and "newer.json" in str(e.value)
    other = tmp_path / "other.json"
    other.write_text(json.dumps({**d, "format": "somebody-else/1"}))
    with pytest.raises(SpecError, match="unknown profile format"):
        LensProfile.load(other)
    # tampered sidecar: refused, named
    side = tmp_path / d["sidecar"]["file"]
    side.write_bytes(side.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(SpecError, match="sidecar"):
        LensProfile.load(path)
    side.unlink()
    with pytest.raises(SpecError, match="missing"):
        LensProfile.load(path)
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(SpecError, match="JSON"):
        LensProfile.load(tmp_path / "broken.json")
    with pytest.raises(SpecError, match="not found"):
        LensProfile.load(tmp_path / "nope.json")


def test_save_is_atomic_and_named(profile_and_truth, tmp_path):
    p, _ = profile_and_truth
    with pytest.raises(ParameterError, match=".json"):
        p.save(tmp_path / "lens.txt")
    assert list(tmp_path.iterdir()) == []


def test_report_from_profile(profile_and_truth, tmp_path):
    from fieldcal.report.calibration_report import write_report
    p, _ = profile_and_truth
    html = write_report(p, tmp_path / "rep")
    names = {f.name for f in (tmp_path / "rep").iterdir()}
    assert {"index.html", "surfaces.png", "bands.png", "geometry.png", "tolerance.png", "residuals.png"} <= names
    text = html.read_text()
    assert "Model selection" in text and "chosen" in text
    assert "Uncertainty budget" in text


def test_uncertainty_budget_adds_up(profile_and_truth):
    """The budget's half-widths are those of best_focus_interval_um and contain the systematic terms it lists."""
    from fieldcal.report.calibration_report import uncertainty_budget
    p, _ = profile_and_truth
    rows = uncertainty_budget(p)
    assert [r["channel"] for r in rows] == list(p.channels)
    cx, cy = p.optical_centre_px()
    for r in rows:
        lo, hi = p.best_focus_interval_um(cx, cy, r["channel"])
        assert r["90% half-width at centre (µm)"] == pytest.approx(0.5 * float(hi - lo), abs=1e-3)
        floor = 1.6448536 * np.hypot(r["breathing systematic sd (µm)"], r["common-mode sd (µm)"])
        assert r["90% half-width at centre (µm)"] >= floor - 2e-3
        assert r["90% half-width at corner (µm)"] > 0
