"""The optical model against closed forms and the paper's / reconstruction's numbers."""

import math

import numpy as np
import pytest
from hypothesis import given, strategies as st

from fieldcal.errors import SpecError
from fieldcal.lens import LensSpec, defocus_otf, diffraction_mtf, focus_tolerance_um
from fieldcal.truth import TruthProfile


def test_triplet_matches_reconstruction_table(triplet_path):
    lens = LensSpec.load(triplet_path)
    table = {"R": [10.8, -63.8, -301.5], "G": [-5.8, -80.6, -319.6], "B": [-6.9, -81.8, -321.8]}
    for ch, zs in table.items():
        got = lens.best_focus_um(np.array([0.0, 1.8, 3.6]), np.zeros(3), ch)
        np.testing.assert_allclose(got, zs, atol=0.05)
    lo, hi = lens.focus_range_um()
    assert abs((hi - lo) - 332.0) < 2.0  # the paper's D


def test_tolerance_matches_traced_depth_of_focus():
    # Ray-traced triplet: MTF at 80 cy/mm within 5% of peak from -5.4 to +6.1 um on axis.
    tol = focus_tolerance_um(80.0, 0.05, 2.0)
    assert 4.5 < tol < 6.1
    # 2J1(x)/x = 1 - q exactly at the tolerance
    assert defocus_otf(80.0, tol, 2.0) == pytest.approx(0.95, abs=1e-9)


@given(st.floats(5, 300), st.floats(1e-3, 0.9), st.floats(1.0, 16.0))
def test_tolerance_scales_as_f_number_over_frequency(fs, q, n):
    t = focus_tolerance_um(fs, q, n)
    assert t > 0 and math.isfinite(t)
    assert focus_tolerance_um(fs, q, 2 * n) == pytest.approx(2 * t, rel=1e-6)
    assert focus_tolerance_um(2 * fs, q, n) == pytest.approx(t / 2, rel=1e-6)


def test_diffraction_mtf_closed_form():
    assert diffraction_mtf(0.0, 550, 2.0) == pytest.approx(1.0)
    fc = 1 / (550e-6 * 2.0)
    assert diffraction_mtf(fc, 550, 2.0) == pytest.approx(0.0, abs=1e-12)
    assert diffraction_mtf(fc / 2, 550, 2.0) == pytest.approx(0.3910, abs=1e-3)


def test_bad_spec_names_field(tmp_path):
    p = tmp_path / "bad.json"
    p.write_text('{"format": "fieldcal-lens/1", "focal_length_mm": 10, "f_number": -2, "image_height_max_mm": 3,'
                 ' "channels": [{"name": "Y"}], "sensor": {"width_px": 64, "height_px": 48, "pixel_pitch_um": 5}}')
    with pytest.raises(SpecError) as e:
        LensSpec.load(p)
    assert "f_number" in str(e.value) and str(p) in str(e.value)
    p.write_text('{"format": "fieldcal-lens/9"}')
    with pytest.raises(SpecError, match="format"):
        LensSpec.load(p)


def test_geometry_and_truth_profile(triplet_path):
    lens = LensSpec.load(triplet_path)
    tp = TruthProfile(lens, 384, 216)
    assert tp.magnification(lens.z_ref_um, "G") == pytest.approx(1.0)
    assert tp.magnification(190.31, "G") == pytest.approx(1.01, rel=1e-4)
    dx, dy = tp.shift_px(100.0)
    assert dx == pytest.approx(100 * math.tan(0.5e-3) / tp.pixel_pitch_um)
    cx, cy = tp.optical_centre_px()
    assert tp.best_focus_um(cx, cy, "R") == pytest.approx(10.8)


def test_spec_round_trips_without_json(models_dir):
    for path in models_dir.glob("*.json"):
        if ".prescription" in path.name:
            continue
        lens = LensSpec.load(path)
        again = LensSpec.from_dict(lens.to_dict())
        assert again == lens
