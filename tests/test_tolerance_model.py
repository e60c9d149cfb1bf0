"""The width (tolerance) model about the sensor centre with decentring as linear terms, and its covariance
(fit/tolerance.py, profile/uncertainty._tolerance_coef_cov), against closed-form width fields."""

from types import SimpleNamespace

import numpy as np
import pytest

from fieldcal.fit.data import ImageGeometry, TileData
from fieldcal.fit.tolerance import ToleranceFit, fit_tolerance
from fieldcal.optics import MTFCriterion
from fieldcal.profile.uncertainty import _tolerance_coef_cov

GEOM = ImageGeometry(320, 180, 19.6)
CRIT = MTFCriterion(16.0, 0.05)
GX, GY = np.meshgrid(np.linspace(16, 304, 10), np.linspace(16, 164, 6))
X, Y = GX.ravel(), GY.ravel()
R = GEOM.half_diagonal_px
CX, CY = GEOM.centre_px


def tiles_with(width_um):
    n = X.size
    return TileData.from_arrays(np.full(n, "G"), X, Y, np.zeros(n), np.ones(n), width_um=width_um)


def field(d_px=(0.0, 0.0), c0=25.0, c1=3.0):
    return c0 + c1 * ((X - CX - d_px[0]) ** 2 + (Y - CY - d_px[1]) ** 2) / R ** 2


def profile_of(fit, tiles):
    return SimpleNamespace(tolerance_fit=fit, tiles={"channel": tiles.channel, "x_px": tiles.x_px,
                                                      "y_px": tiles.y_px, "width_um": tiles.width_um})


def test_a_decentred_width_field_is_recovered_exactly_about_the_sensor_centre():
    d = (40.0, -25.0)
    t = fit_tolerance(tiles_with(field(d)), GEOM, CRIT)
    assert len(t.coef_um["G"]) == 4 and t.centre_px == GEOM.centre_px
    # everywhere on the frame, corners included (beyond the tiles)
    px, py = np.meshgrid(np.linspace(0, 319, 7), np.linspace(0, 179, 5))
    truth = 25.0 + 3.0 * ((px - CX - d[0]) ** 2 + (py - CY - d[1]) ** 2) / R ** 2
    np.testing.assert_allclose(t.width_cal_um(px, py, "G"), truth, rtol=1e-5)
    # the decentring is -2 c1 d / R in the linear terms
    np.testing.assert_allclose(t.coef_um["G"][2:], [-2 * 3.0 * d[0] / R, -2 * 3.0 * d[1] / R], rtol=1e-4)


def test_a_centred_field_keeps_the_radial_model():
    rng = np.random.default_rng(0)
    t = fit_tolerance(tiles_with(field() + 0.05 * rng.standard_normal(X.size)), GEOM, CRIT)
    assert len(t.coef_um["G"]) == 2
    assert t.diagnostics["G"]["model"] == "w0 + w1 rho^2"
    assert ToleranceFit.from_dict(t.to_dict()).width_cal_um(10.0, 20.0, "G") == pytest.approx(
        t.width_cal_um(10.0, 20.0, "G"))


def _z_scores(cov_fn, n_draws=300):
    """z of the fitted width at the frame's corner and centre over noisy draws whose scatter grows with rho."""
    rng = np.random.default_rng(7)
    rho2 = ((X - CX) ** 2 + (Y - CY) ** 2) / R ** 2
    sd = 0.15 + 0.9 * rho2          # the corners' widths scatter 4-6x the centre's (measured fields: 1.5x)
    pts = (np.array([0.0, CX]), np.array([0.0, CY]))
    truth = 25.0 + 3.0 * ((pts[0] - CX) ** 2 + (pts[1] - CY) ** 2) / R ** 2
    z = []
    for _ in range(n_draws):
        tiles = tiles_with(field() + sd * rng.standard_normal(X.size))
        t = fit_tolerance(tiles, GEOM, CRIT)
        n = len(t.coef_um["G"])
        J = t.design(*pts, n)
        cov = cov_fn(profile_of(t, tiles), t, n)
        z.append((t.width_cal_um(*pts, "G") - truth) / np.sqrt(np.einsum("ij,jk,ik->i", J, cov, J)))
    return np.std(np.array(z), axis=0)


def test_width_uncertainty_is_honest_when_the_scatter_grows_over_the_field():
    zsd = _z_scores(lambda p, t, n: _tolerance_coef_cov(p, "G", n))
    assert np.all((zsd > 0.85) & (zsd < 1.2)), zsd


def test_one_pooled_residual_sd_would_understate_the_corner():
    # the form before: sd^2 (A^T A)^-1 with one pooled sd; the same check fails at the corner
    def pooled(p, t, n):
        A = t.design(X, Y, n)
        s2 = t.residual_sd_um["G"] ** 2 * X.size / (X.size - n)
        return s2 * np.linalg.pinv(A.T @ A)
    zsd = _z_scores(pooled)
    assert zsd[0] > 1.2, zsd


def _three_channels(widths_um, sd_um, seed):
    rng = np.random.default_rng(seed)
    n = X.size
    ch = np.repeat(np.array(["R", "G", "B"]), n)
    w = np.concatenate([np.full(n, wc) + sd_um * rng.standard_normal(n) for wc in widths_um])
    return TileData.from_arrays(ch, np.tile(X, 3), np.tile(Y, 3), np.zeros(3 * n), np.ones(3 * n), width_um=w)


def test_channels_share_one_width_when_the_data_do_not_tell_them_apart():
    # one δ for every channel (the defocus law's blur rate 1/N) and 10 % tile noise: one model, whose error is
    # the pooled mean's (about sd / sqrt(3 n)), not one channel's
    errs = []
    for seed in range(8):
        t = fit_tolerance(_three_channels((20.0, 20.0, 20.0), 2.0, seed), GEOM, CRIT, shared_channels=True)
        assert t.diagnostics["channels"]["shared"]
        assert t.coef_um["R"] == t.coef_um["G"] == t.coef_um["B"]
        errs.append(t.coef_um["G"][0] - 20.0)
    assert np.sqrt(np.mean(np.square(errs))) < 2.5 * 2.0 / np.sqrt(3 * X.size)
    # without the option every channel keeps its own model (the texture path's default)
    t = fit_tolerance(_three_channels((20.0, 20.0, 20.0), 2.0, 0), GEOM, CRIT)
    assert "channels" not in t.diagnostics and t.coef_um["R"] != t.coef_um["G"]


def test_channels_keep_their_own_width_when_they_differ():
    # an aberration that makes R's δ 15 % wider: well beyond the noise, so the per-channel models stay
    t = fit_tolerance(_three_channels((23.0, 20.0, 20.0), 1.0, 3), GEOM, CRIT, shared_channels=True)
    assert not t.diagnostics["channels"]["shared"]
    assert t.coef_um["R"][0] == pytest.approx(23.0, abs=0.5) and t.coef_um["G"][0] == pytest.approx(20.0, abs=0.5)


def test_widths_from_one_strip_of_tiles_fit_no_tilt_across_it():
    """Quick effort's widths come from one row of tiles through the middle (measure/fs_strip.py): a y tilt is
    not measured there, so the fit keeps to the constant and rho^2 terms, which the strip does span; the same
    field on the whole grid takes its decentring."""
    d = (40.0, -25.0)
    row = np.abs(Y - CY) < 20.0
    n = int(row.sum())
    strip = TileData.from_arrays(np.full(n, "G"), X[row], Y[row], np.zeros(n), np.ones(n),
                                 width_um=field(d)[row])
    t = fit_tolerance(strip, GEOM, CRIT)
    assert len(t.coef_um["G"]) <= 2
    assert 4 not in t.diagnostics["G"]["bic"]
    assert len(fit_tolerance(tiles_with(field(d)), GEOM, CRIT).coef_um["G"]) == 4


def test_widths_convert_to_another_fs_with_diffraction_when_the_f_number_is_known():
    """At F/8 (fs_cal 80 cycles/mm) the 1/fs law would double δ at 40 cycles/mm; the pupil's ratio (computed
    here from the model δ at each band end, the smaller kept) gives ~1.5; the calibration's own (fs, q) keeps
    the measured width; a fit without an F-number (old profiles) keeps the geometric law; to_dict round-trips."""
    from fieldcal.optics import TOLERANCE_BAND_NM, pupil_tolerance_um

    cal = MTFCriterion(80.0, 0.05)
    base = fit_tolerance(tiles_with(field(c1=0.0)), GEOM, cal)
    phys = fit_tolerance(tiles_with(field(c1=0.0)), GEOM, cal, f_number=8.0)
    w = float(base.width_cal_um(CX, CY, "G"))
    assert float(phys.tolerance_um(CX, CY, "G", 80.0, 0.05)) == pytest.approx(w)
    assert float(base.tolerance_um(CX, CY, "G", 40.0, 0.05)) == pytest.approx(2.0 * w)
    want = min(pupil_tolerance_um(MTFCriterion(40.0, 0.05), 8.0, lam) / pupil_tolerance_um(cal, 8.0, lam)
               for lam in TOLERANCE_BAND_NM["G"])
    got = float(phys.tolerance_um(CX, CY, "G", 40.0, 0.05)) / w
    assert got == pytest.approx(want, rel=1e-9) and 1.4 < got < 1.6
    back = ToleranceFit.from_dict(phys.to_dict())
    assert back.f_number == 8.0 and float(back.tolerance_um(CX, CY, "G", 40.0, 0.05)) == pytest.approx(got * w)


def test_a_quick_strip_with_few_widths_leaves_the_model_to_answer():
    """Fewer than MIN_QUICK_WIDTHS widths in a channel (quick's strip on a large frame): no width model, so the
    calibration records why and the profile answers with the defocus model (calibration/pipeline.py)."""
    from fieldcal.fit.data import FitError
    from fieldcal.fit.tolerance import MIN_QUICK_WIDTHS

    few = np.abs(Y - CY) < 20.0
    keep = np.flatnonzero(few)[:MIN_QUICK_WIDTHS - 1]
    n = keep.size
    tiles = TileData.from_arrays(np.full(n, "G"), X[keep], Y[keep], np.zeros(n), np.ones(n),
                                 width_um=field()[keep])
    with pytest.raises(FitError) as e:
        fit_tolerance(tiles, GEOM, CRIT, min_tiles=MIN_QUICK_WIDTHS)
    assert e.value.field == "width_um"
    assert fit_tolerance(tiles, GEOM, CRIT).coef_um["G"]  # the default minimum (4) fits them
