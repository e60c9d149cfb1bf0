"""The model focus tolerance δ(fs, q) with diffraction (fieldcal.optics.pupil_tolerance_um / model_tolerance_um)
against an independent quadrature of Hopkins' defocus OTF, its geometric limit, and where fieldcal uses it."""

import math

import numpy as np
import pytest
from scipy import optimize

from hopkins_util import hopkins_otf
from fieldcal.errors import ParameterError
from fieldcal.optics import (DEFAULT_WAVELENGTH_NM, TOLERANCE_WAVELENGTH_NM, MTFCriterion, focus_tolerance_um,
                             model_tolerance_um, pupil_tolerance_um, tolerance_wavelength_nm)

from scipy import special as _special

# the disc's δ in closed form: 2 J1(x)/x = 1 - q (q = 0.05) at x = pi fs δ / N, solved here independently
N_DISC = optimize.brentq(lambda x: 2.0 * _special.j1(x) / x - 0.95, 0.1, 3.0)



def hopkins_delta_um(fs: float, q: float, f_number: float, wavelength_nm: float) -> float:
    """δ by root-finding on the 1-D Hopkins OTF, bracketed from 0 to 3x the geometric δ."""
    lam_um = wavelength_nm * 1e-3
    nu = fs * 1e-3 * lam_um * f_number
    peak = hopkins_otf(nu, 0.0)

    def g(dz):
        return hopkins_otf(nu, dz / (8.0 * f_number ** 2 * lam_um)) / peak - (1.0 - q)

    geo = focus_tolerance_um(MTFCriterion(fs, q), f_number)
    return optimize.brentq(g, 1e-6, 3.0 * geo, xtol=1e-10)


@pytest.mark.parametrize("f_number", [2.0, 5.6, 8.0])
@pytest.mark.parametrize("wavelength_nm", [470.0, 540.0, 610.0])
def test_model_delta_is_the_hopkins_half_width(f_number, wavelength_nm):
    crit = MTFCriterion(80.0, 0.05)
    want = hopkins_delta_um(80.0, 0.05, f_number, wavelength_nm)
    assert pupil_tolerance_um(crit, f_number, wavelength_nm) == pytest.approx(want, rel=5e-3)


def test_model_delta_at_f8_is_the_clean_room_figure():
    # docs/benchmarks.md bench_cleanroom: the true δ at F/8, 80 cycles/mm, 540 nm is 31.7 µm, the disc's 20.3
    crit = MTFCriterion(80.0, 0.05)
    assert pupil_tolerance_um(crit, 8.0, 540.0) == pytest.approx(31.6, abs=0.2)
    assert focus_tolerance_um(crit, 8.0) == pytest.approx(20.3, abs=0.05)


def test_model_delta_tends_to_the_geometric_disc_where_defocus_dominates():
    # nu = fs lambda N -> 0 (low F-number, low fs): the defocus at δ is many waves and the ray picture holds
    ratios = []
    for fs in (80.0, 20.0, 5.0, 1.0):
        crit = MTFCriterion(fs, 0.05)
        ratios.append(pupil_tolerance_um(crit, 1.4, 500.0) / focus_tolerance_um(crit, 1.4))
    assert all(r > 1.0 for r in ratios)  # diffraction only widens the aberration-free curve
    assert ratios == sorted(ratios, reverse=True)
    assert ratios[-1] - 1.0 < 2e-3 and ratios[0] - 1.0 > 0.04
    # and at fixed fs with the F-number
    crit = MTFCriterion(80.0, 0.05)
    by_n = [pupil_tolerance_um(crit, n, 540.0) / focus_tolerance_um(crit, n) for n in (1.0, 2.0, 4.0, 8.0)]
    assert by_n == sorted(by_n) and by_n[0] < 1.06 and by_n[-1] > 1.5


@pytest.mark.parametrize("q", [0.02, 0.05, 0.3])
def test_model_delta_grows_with_wavelength_so_the_short_end_is_the_bound(q):
    crit = MTFCriterion(80.0, q)
    d = [pupil_tolerance_um(crit, 5.6, lam) for lam in (440.0, 500.0, 580.0, 650.0)]
    assert d == sorted(d)
    for ch in ("R", "G", "B", "Y"):
        assert TOLERANCE_WAVELENGTH_NM[ch] < DEFAULT_WAVELENGTH_NM[ch]


def test_a_band_is_at_least_as_wide_as_its_shortest_wavelength():
    # the δ of a summed MTF over a band (the wave simulator's 3-point quadrature about 540 nm) is between its
    # wavelengths' δ: the short end bounds it from below
    fs, q, n = 80.0, 0.05, 8.0
    band = ((515.0, 0.25), (540.0, 0.5), (565.0, 0.25))

    def mtf(dz):
        return sum(w * hopkins_otf(fs * 1e-3 * lam * 1e-3 * n, dz / (8 * n * n * lam * 1e-3)) for lam, w in band)

    d_band = optimize.brentq(lambda dz: mtf(dz) / mtf(0.0) - (1 - q), 1e-3, 60.0)
    crit = MTFCriterion(fs, q)
    assert pupil_tolerance_um(crit, n, 515.0) < d_band < pupil_tolerance_um(crit, n, 565.0)


def test_recorded_wavelengths_win_over_the_nominal_short_end():
    assert tolerance_wavelength_nm("G") == TOLERANCE_WAVELENGTH_NM["G"]
    assert tolerance_wavelength_nm("G", {"G": 532.0}) == 532.0
    assert tolerance_wavelength_nm("G", {"R": 600.0}) == TOLERANCE_WAVELENGTH_NM["G"]
    assert tolerance_wavelength_nm("G", {"G": "x"}) == TOLERANCE_WAVELENGTH_NM["G"]
    assert tolerance_wavelength_nm("NIR") == 450.0
    crit = MTFCriterion(80.0, 0.05)
    assert model_tolerance_um(crit, 4.0, "G", {"G": 532.0}) == pytest.approx(pupil_tolerance_um(crit, 4.0, 532.0))


def test_beyond_the_cutoff_is_refused_naming_fs():
    with pytest.raises(ParameterError) as e:
        pupil_tolerance_um(MTFCriterion(500.0, 0.05), 8.0, 600.0)  # cut-off 208 cycles/mm
    assert e.value.field == "fs_cyc_per_mm" and e.value.fix
    with pytest.raises(ParameterError) as e:
        pupil_tolerance_um(MTFCriterion(80.0, 0.05), math.nan, 600.0)
    assert e.value.field == "f_number"


def test_a_profile_without_widths_answers_with_the_geometric_lower_bound(tmp_path):
    """With nothing measured the plan takes the geometric disc's δ, the least any lens of that F-number has
    (the pupil with diffraction is wider: at F/8, 80 cycles/mm, 1.5x); the pupil is only the measured widths' cap."""
    from fieldcal.optics import focus_tolerance_um
    from fieldcal.plan.tolerance import MODEL_SOURCE, tolerance_um
    from fieldcal.plan.synthetic import SyntheticProfile

    class _NoWidths(SyntheticProfile):
        has_measured_tolerance = False
        optics = {"wavelength_nm": None}

        def focus_tolerance_um(self, x, y, channel, fs, q):
            return np.full(np.broadcast(np.asarray(x), np.asarray(y)).shape, np.nan)

    prof = _NoWidths(33, 33, a_um=-50.0, f_number=8.0)
    crit = MTFCriterion(80.0, 0.05)
    tol, src = tolerance_um(prof, np.arange(3.0), np.zeros(3), "G", crit)
    disc = N_DISC * 8.0 / (math.pi * 80.0e-3)
    np.testing.assert_allclose(tol, disc, rtol=1e-9)
    np.testing.assert_allclose(focus_tolerance_um(crit, 8.0), disc, rtol=1e-9)
    assert disc < pupil_tolerance_um(crit, 8.0, TOLERANCE_WAVELENGTH_NM["G"]) / 1.3
    assert src == MODEL_SOURCE


def test_lens_profile_without_widths_answers_with_the_geometric_lower_bound(hostile_world):
    import dataclasses

    from fieldcal import LensProfile

    base = LensProfile.load(hostile_world / "lens.json")
    prof = dataclasses.replace(base, tolerance_fit=None, optics={**base.optics, "f_number": 8.0,
                                                                  "wavelength_nm": None})
    want = N_DISC * 8.0 / (math.pi * 16.0e-3)
    np.testing.assert_allclose(prof.focus_tolerance_um(np.arange(3.0), np.zeros(3), "G", 16.0, 0.05), want,
                               rtol=1e-9)
