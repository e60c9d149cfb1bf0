"""Stack plans under the profile's uncertainty (surface band and δ's sd) against known truth: the stated expected
fraction is what true surfaces and tolerances drawn from the profile's own posterior deliver, the coverage target
adds frames until it is reached, and exact models are planned as before."""

import math

import numpy as np
import pytest
from scipy.special import ndtri

from fieldcal.errors import ParameterError
from fieldcal.optics import MTFCriterion
from fieldcal.plan import StackRequest, plan_stack
from fieldcal.plan.cover import nearest_index
from fieldcal.plan.scene import full_grid
from fieldcal.plan.synthetic import SyntheticProfile
from fieldcal.plan.tolerance import (ESFR_WIDTH, TEXTURE_WIDTH, coverage_probability, tolerance_sd_um,
                                     tolerance_um)


def delivered_fraction(prof, plan, sigma, tol, tol_sd=0.0, n=24):
    """Fraction of full-grid pixels within the true δ, averaged (Gauss-Hermite) over a field-wide true shift
    ~ N(0, sigma) and a true δ ~ N(tol, tol_sd): one lens drawn from the profile's posterior at a time."""
    x, y = full_grid(plan.field.roi)
    frames = np.sort(plan.frames_um)
    z = prof.best_focus_um(x, y, "G")
    zf = frames[nearest_index(frames, z)]
    nodes, w = np.polynomial.hermite_e.hermegauss(n)
    w = w / w.sum()
    out = 0.0
    for a, wa in zip(nodes, w):
        for b, wb in zip(nodes, w):
            out += wa * wb * np.mean(np.abs(zf - (z + sigma * a)) <= tol + tol_sd * b)
    return out


def test_coverage_target_adds_frames_until_the_delivered_fraction_reaches_it():
    band, tol, sd = 1.0, 4.0, 0.1
    prof = SyntheticProfile(97, 65, a_um=-120.0, tolerance_um=tol, band_um=band, tolerance_sd_um=sd)
    sigma = band / float(ndtri(0.95))  # the band is the 90 % interval
    fewest = plan_stack(prof, StackRequest(grid_step_px=4, coverage=None))
    plan = plan_stack(prof, StackRequest(grid_step_px=4, coverage=0.99))
    assert fewest.n_frames == 15  # ceil(120 / 8): the MAP cover ignores the uncertainty
    got_fewest = delivered_fraction(prof, fewest, sigma, tol, sd)
    got = delivered_fraction(prof, plan, sigma, tol, sd)
    assert got_fewest < 0.97  # frames 2δ apart: every surface error at a band's edge costs pixels
    assert plan.n_frames > fewest.n_frames and plan.stats["fewest_frames"] == fewest.n_frames
    assert plan.stats["expected_fraction"] >= 0.99
    assert got >= 0.985
    # the stated fraction (on the plan's sample grid) is what is delivered on the full grid, within issue 13's
    # 2 points
    for p, g in ((fewest, got_fewest), (plan, got)):
        assert abs(p.stats["expected_fraction"] - g) <= 0.02, (p.n_frames, p.stats["expected_fraction"], g)
    assert plan.to_dict()["parameters"]["coverage"] == 0.99


def test_exact_models_are_planned_as_before():
    prof = SyntheticProfile(97, 65, a_um=-332.0, tolerance_um=4.0)
    a = plan_stack(prof, StackRequest(coverage=0.999))
    b = plan_stack(prof, StackRequest(coverage=None))
    np.testing.assert_array_equal(a.frames_um, b.frames_um)
    assert a.n_frames == 42 and a.stats["expected_fraction"] == 1.0 and a.stats["probability"] == 1.0


def test_confidence_uses_the_lower_credible_bound_of_the_tolerance():
    tol, sd, band = 4.0, 0.3, 0.5
    prof = SyntheticProfile(97, 65, a_um=-120.0, tolerance_um=tol, band_um=band, tolerance_sd_um=sd)
    plan = plan_stack(prof, StackRequest(confidence=0.9, coverage=None, grid_step_px=4))
    low = tol - float(ndtri(0.95)) * sd - band
    assert plan.n_frames == math.ceil(120.0 / (2.0 * low))
    assert plan.stats["probability"] >= 0.9


def test_coverage_probability_with_an_uncertain_tolerance_matches_monte_carlo():
    rng = np.random.default_rng(3)
    d = np.array([0.0, 2.0, 3.5, 4.2])
    tol, sigma, tol_sd = 4.0, np.array([0.0, 0.5, 0.7, 0.3]), 0.4
    p = coverage_probability(d, 0.0, tol, sigma, tol_sd)
    n = 400_000
    z = rng.normal(0.0, 1.0, (n, 1)) * sigma
    t = np.maximum(tol + tol_sd * rng.normal(0.0, 1.0, (n, 1)), 0.0)
    mc = np.mean(np.abs(d - z) <= t, axis=0)
    np.testing.assert_allclose(p, mc, atol=0.004)


class _Widths:
    """A calibrated profile (5 µm pixels, calibrated at 40 cycles/mm = 0.2 cycles/px) with a measured width of
    20 µm everywhere and a fit standard error of 0.3 µm."""

    f_number = 4.0  # the defocus model's δ (~40 µm at 20 cycles/mm) above the widths: no cap binds
    has_measured_tolerance = True
    pixel_pitch_um = 5.0

    def __init__(self, measurement):
        self.calibration = {"measurement": measurement, "fs_cyc_per_mm": 40.0}

    def focus_tolerance_um(self, x, y, channel, fs, q):
        return np.full(np.broadcast(np.asarray(x), np.asarray(y)).shape, 20.0)

    def focus_tolerance_sd_um(self, x, y, channel, fs, q):
        return np.full(np.broadcast(np.asarray(x), np.asarray(y)).shape, 0.3)


@pytest.mark.parametrize("measurement, bias", [("esfr", ESFR_WIDTH), ("focus-measure", TEXTURE_WIDTH)])
def test_tolerance_sd_is_the_fit_error_and_the_measurements_systematic(measurement, bias):
    prof = _Widths(measurement)
    crit = MTFCriterion(20.0, 0.05)
    x, y = np.arange(3.0), np.zeros(3)
    tol, src = tolerance_um(prof, x, y, "G", crit)
    sd = tolerance_sd_um(prof, x, y, "G", crit, tol)
    k = max(a + b * 0.2 for a, b in bias.lines)  # the bias at the calibration's 0.2 cycles/px
    np.testing.assert_allclose(tol, 20.0 / k)
    np.testing.assert_allclose(sd, np.hypot(0.3 / k, bias.rel_sd * 20.0 / k))
    assert ("texture" in src) == (bias is TEXTURE_WIDTH)


def test_texture_width_bias_grows_with_fs_in_cycles_per_pixel_and_is_clipped_to_the_measured_range():
    lo, hi = TEXTURE_WIDTH.fs_px_range
    f = [TEXTURE_WIDTH.factor(v) for v in (0.0, lo, 0.2, 0.3, hi, 0.5, None)]
    assert f[0] == f[1] < f[2] < f[3] < f[4] == f[5] == f[6]  # None (fs unknown): the narrowest δ
    assert 0.9 < f[1] < 0.96 and 1.08 < f[4] < 1.15  # docs/planning.md "Measured tolerance"
    # the upper envelope of the two simulator paths' lines: never below either
    for v in (0.1, 0.25, 0.4):
        assert TEXTURE_WIDTH.factor(v) == max(a + b * v for a, b in TEXTURE_WIDTH.lines)


@pytest.mark.parametrize("bad", [0.0, 1.0, 1.5, -0.2, "x"])
def test_invalid_coverage_target_is_refused(bad):
    with pytest.raises(ParameterError) as e:
        plan_stack(SyntheticProfile(33, 33, a_um=-50.0), StackRequest(coverage=bad))
    assert e.value.field == "coverage" and e.value.fix


class _TextureWide(SyntheticProfile):
    """A texture-calibrated profile (20 µm pixels, fs = 15 cycles/mm = 0.3 cycles/px, F/2) whose widths read
    the texture bias at the centre and ``1 + rise rho^2`` times it towards the corners, as the 1920x1080 triplet's
    do (astigmatism and the spread of best focus inside its tiles widen the band-pass curve there); the true δ
    is the aberration-free pupil's everywhere (G at the band's short end)."""

    def __init__(self, rise, measurement="focus-measure", **kw):
        crit = MTFCriterion(15.0, 0.05)
        from fieldcal.optics import model_tolerance_um
        self.model_um = model_tolerance_um(crit, 2.0, "G")
        k = TEXTURE_WIDTH.factor(0.3)
        super().__init__(97, 65, a_um=-600.0, f_number=2.0, tolerance_sd_um=0.0,
                         tolerance_fn=lambda r, fs, q: self.model_um * k * (1.0 + rise * r ** 2), **kw)
        self.calibration = {"measurement": measurement, "fs_cyc_per_mm": 15.0}


def test_texture_tolerance_is_capped_at_the_defocus_model_at_the_f_number():
    from fieldcal.optics import TOLERANCE_WAVELENGTH_NM, pupil_tolerance_um
    from fieldcal.optics.defocus import disc_x_at_contrast

    prof = _TextureWide(0.25)
    crit = MTFCriterion(15.0, 0.05)
    # the cap: the aberration-free pupil's δ at G's short wavelength, just above the geometric disc's at this
    # low F-number and fs (2 J1(x)/x = 1 - q at x = pi fs δ / N; tests/test_optics_tolerance_model.py has both)
    want = pupil_tolerance_um(crit, 2.0, TOLERANCE_WAVELENGTH_NM["G"])
    geometric = disc_x_at_contrast(0.95) * 2.0 / (math.pi * 15.0e-3)
    assert geometric < want < 1.03 * geometric
    x = np.linspace(0.0, 96.0, 25)
    y = np.full_like(x, 32.0)
    tol, src = tolerance_um(prof, x, y, "G", crit)
    read = prof.focus_tolerance_um(x, y, "G", 15.0, 0.05) / TEXTURE_WIDTH.factor(0.3)
    np.testing.assert_allclose(tol, np.minimum(read, want), rtol=1e-12)
    assert tol.max() == pytest.approx(want) and read.max() > 1.05 * want  # the cap binds at the edges only
    assert tol[12] == pytest.approx(read[12])  # the centre keeps its measured (corrected) width
    assert "texture" in src and "capped" in src
    # e-SFR widths measure MTF(fs) itself: never capped
    tol_e, src_e = tolerance_um(_TextureWide(0.25, "esfr"), x, y, "G", crit)
    np.testing.assert_allclose(tol_e, prof.focus_tolerance_um(x, y, "G", 15.0, 0.05))


def test_a_plan_from_over_wide_texture_widths_keeps_its_stated_coverage():
    """Widths reading 25 % wide at the corners (the 1920x1080 triplet) against the true δ (the model): the capped
    texture plan keeps >= 99 % of pixels within the true δ with N <= optimum + 1, and its stated fraction is
    within 2 points of the delivered one; the same widths taken at face value (no cap) lose pixels."""
    crit_fs, q = 15.0, 0.05
    prof = _TextureWide(0.25)
    req = StackRequest(fs_cyc_per_mm=crit_fs, q=q, grid_step_px=4, coverage=0.99)
    plan = plan_stack(prof, req)
    truth = SyntheticProfile(97, 65, a_um=-600.0, f_number=2.0, tolerance_um=prof.model_um)
    opt = plan_stack(truth, StackRequest(fs_cyc_per_mm=crit_fs, q=q, grid_step_px=4, coverage=None))
    got = delivered_fraction(prof, plan, 0.0, prof.model_um)
    assert got >= 0.99 and plan.n_frames <= opt.n_frames + 1, (got, plan.n_frames, opt.n_frames)
    assert abs(plan.stats["expected_fraction"] - got) <= 0.02
    naive = plan_stack(_TextureWide(0.25, "esfr"), req)  # the same widths, used as they are
    assert delivered_fraction(prof, naive, 0.0, prof.model_um) < 0.99


@pytest.mark.parametrize("conf, band, tol_sd", [(0.5, 1.0, 0.0), (0.5, 2.0, 0.6), (0.7, 1.5, 0.3), (0.9, 1.0, 0.0)])
def test_confidence_plan_states_what_it_delivers_where_pixels_are_lost(conf, band, tol_sd):
    """--confidence plans at their fewest frames (no coverage target), with a band and δ's sd large enough that
    they lose pixels (stated fraction well under 1, unlike the 320 px benchmark, where every plan keeps every
    pixel): the stated expected fraction (sample grid) is what a true field drawn from the profile's posterior
    (a field-wide shift ~ N(0, sigma) with sigma from the band at the --confidence level, and δ ~ N(δ̂, sd))
    delivers on the full pixel grid, within issue 14's 2 points."""
    tol = 4.0
    prof = SyntheticProfile(97, 65, a_um=-150.0, tolerance_um=tol, band_um=band, tolerance_sd_um=tol_sd)
    plan = plan_stack(prof, StackRequest(confidence=conf, grid_step_px=4, coverage=None))
    sigma = band / float(ndtri(0.5 + 0.5 * conf))
    got = delivered_fraction(prof, plan, sigma, tol, tol_sd)
    stated = plan.stats["expected_fraction"]
    assert stated < 0.995  # a regime where the statement can be wrong (0.79-0.99 here)
    assert abs(stated - got) <= 0.02, (plan.n_frames, stated, got)
