"""Per-frame stage errors fitted with the surface (fieldcal.fit.stage): sensitivities from the curves, the joint
fit's closed forms, and recovery of frame errors where the tiles make them identifiable."""

import math

import numpy as np
import pytest

from fieldcal.fit.discrepancy import COEF_PRIOR_SD, Discrepancy
from fieldcal.fit.stage import _slope_weights, stage_sensitivity
from fieldcal.fit.surface import SurfaceModel


def _disc(model, x, y, target, noise_var, stage_c=None, prior_sd=0.0):
    n = target.size
    X = model.design(x, y, np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(2))
    iid = np.linalg.inv((X.T / noise_var) @ X + np.eye(X.shape[1]) / COEF_PRIOR_SD ** 2)
    return Discrepancy(model, np.zeros(2), x, y, np.zeros(n, np.int64), target, noise_var, np.array([0.0]),
                       1.0, 1.0, iid, stage_c=stage_c, stage_prior_sd=prior_sd)


def _shared_frame_case(n=50, sig=0.2):
    """Tiles that all read frame 0 only (c = -1): a stage error there is a piston of the whole surface."""
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-0.6, 0.6, n), rng.uniform(-0.4, 0.4, n)
    model = SurfaceModel(("G",), 0, False, False, False, False, None)
    target = rng.normal(0.0, sig, n)
    C = np.zeros((n, 3))
    C[:, 0] = -1.0
    return model, x, y, target, C


def test_slope_weights_of_a_gaussian_curve_are_its_shift_sensitivity():
    z = np.arange(-30.0, 31.0, 1.0)
    s = 6.0
    v = 1.0 + 5.0 * np.exp(-0.5 * (z / s) ** 2)
    w = _slope_weights(v, z)
    # analytic least-squares shift sensitivity J^2 / sum J^2, J = dv/dz (broad curve: the smoothing is ~1 %)
    J = -5.0 * z / s ** 2 * np.exp(-0.5 * (z / s) ** 2)
    ref = np.where(v - 1.0 > 0.5, J * J, 0.0)
    ref /= ref.sum()
    assert w.sum() == pytest.approx(1.0)
    assert np.allclose(w, w[::-1], atol=1e-12)                       # symmetric curve, symmetric weights
    assert np.abs(w - ref).max() < 0.03 * ref.max()
    assert w[np.argmin(np.abs(z))] < 1e-3 * w.max()                  # the top of the peak does not move it
    assert _slope_weights(np.ones(9), np.arange(9.0)) is None        # a flat curve has no slope


def test_stage_sensitivity_takes_the_estimators_gain():
    z = np.arange(0.0, 40.0, 2.0)
    curves = np.array([np.exp(-0.5 * ((z - c) / 5.0) ** 2) for c in (12.0, 20.0, 28.0)])
    table = type("T", (), {"curves": {"sml": curves}, "z_um": z, "ok": np.array([True, False, True]),
                           "stage_gain": np.array([0.4, 0.5, np.nan])})()
    C = stage_sensitivity(table)
    assert C.shape == (2, z.size)
    assert np.linalg.norm(C[0]) == pytest.approx(0.4)                 # the measure's own gain
    assert C[1].sum() == pytest.approx(-1.0)                         # no gain: the LS shift, sum c = -1
    assert np.all(C <= 0)
    assert stage_sensitivity(type("T", (), {"curves": {}, "z_um": z, "ok": np.ones(3, bool)})()) is None


def test_a_fully_shared_frame_error_adds_its_prior_to_the_band():
    """Every tile reads one frame only (c = -1 on frame 0): the stage error is a piston the data cannot tell
    from the surface's, so the posterior variance of the surface is r^2 + sigma^2 / n (flat coefficient prior)."""
    n, r, sig = 50, 0.3, 0.2
    model, x, y, target, C = _shared_frame_case(n, sig)
    d = _disc(model, x, y, target, np.full(n, sig ** 2), C, r)
    _, extra = d.predict(np.array([0.0]), np.array([0.0]), 0)
    bare = _disc(model, x, y, target, np.full(n, sig ** 2))
    _, extra0 = bare.predict(np.array([0.0]), np.array([0.0]), 0)
    iid = sig ** 2 / n
    assert extra0[0] == pytest.approx(0.0, abs=1e-9)
    assert extra[0] + iid == pytest.approx(r ** 2 + iid, rel=0.02)
    est, sd = d.stage_errors
    assert sd[1] == pytest.approx(r) and sd[2] == pytest.approx(r)   # frames no tile reads keep their prior


def test_fitted_frames_replace_the_common_mode_term():
    """The common mode stood for frame-level errors shared by the tiles; once the frames are fitted it would count
    them twice: attaching the frames sets it to 0 (the old value kept in the diagnostics), and the band at a point
    is then the bare band plus the frames' own share, r^2 for a fully shared frame."""
    n, r, sig, cm = 50, 0.3, 0.2, 0.1
    model, x, y, target, C = _shared_frame_case(n, sig)
    d = _disc(model, x, y, target, np.full(n, sig ** 2))
    d.common_sd = np.array([cm])
    at = (np.array([0.0]), np.array([0.0]))
    _, with_common = d.predict(*at, 0)
    assert with_common[0] == pytest.approx(cm ** 2, rel=1e-6)
    d.attach_stage(C, r)
    _, extra = d.predict(*at, 0)
    assert d.has_stage and d.common_sd[0] == 0.0
    assert d.diagnostics["common_mode_sd_replaced"] == [cm]
    assert extra[0] + sig ** 2 / n == pytest.approx(r ** 2 + sig ** 2 / n, rel=0.02)
    assert d.band_terms_um(1.0)["common_mode"].startswith("replaced")
    # no stated repeatability: nothing is fitted and the common mode stays
    d0 = _disc(model, x, y, target, np.full(n, sig ** 2))
    d0.common_sd = np.array([cm])
    d0.attach_stage(C, 0.0)
    assert not d0.has_stage and d0.common_sd[0] == cm


def test_a_shared_frame_error_is_not_hidden_by_the_block_jackknife():
    """The same fully shared frame error with a block-jackknife covariance larger than the kriging one (errors
    shared by regions of tiles): the jackknife cannot see a shift of every tile, so the frame's prior still adds
    r^2 on top of it. (It used to enter inside the maximum of the two and vanish: 0.00-0.02 µm stated where the
    frames moved the benchmark lenses' surfaces by 0.05-0.1 µm.)"""
    from dataclasses import replace

    n, r, sig, jk = 50, 0.3, 0.2, 0.25
    model, x, y, target, C = _shared_frame_case(n, sig)
    d = replace(_disc(model, x, y, target, np.full(n, sig ** 2), C, r), jk_cov=np.array([[jk ** 2]]))
    bare = replace(_disc(model, x, y, target, np.full(n, sig ** 2)), jk_cov=np.array([[jk ** 2]]))
    at = (np.array([0.0]), np.array([0.0]))
    iid = sig ** 2 / n
    _, extra0 = bare.predict(*at, 0)
    _, extra = d.predict(*at, 0)
    assert extra0[0] + iid == pytest.approx(jk ** 2, rel=1e-6)       # the jackknife's variance, nothing else
    assert extra[0] - extra0[0] == pytest.approx(r ** 2, rel=0.02)   # the frame adds its own on top
    # a held-out tile shares the frame with the kept ones: the check leaves it out
    _, extra_check = d.predict(*at, 0, nuisance=False)
    assert extra_check[0] == pytest.approx(extra0[0], rel=1e-9)


def test_frame_errors_that_tiles_share_by_height_are_recovered():
    """A plane sampled by tiles whose best foci fall on different frames (each tile reading two neighbouring
    frames): the joint fit recovers the frame errors up to their mean and trend (degenerate with the plane's
    piston and tilt: the stage's own zero and scale)."""
    rng = np.random.default_rng(3)
    nf, n, r, sig = 12, 400, 0.5, 0.05
    e = rng.normal(0.0, r, nf)
    x, y = rng.uniform(-0.7, 0.7, n), rng.uniform(-0.5, 0.5, n)
    height = (x + 0.7) / 1.4 * (nf - 1.001)                          # best focus rises across x through the frames
    k = np.floor(height).astype(int)
    f = height - k
    C = np.zeros((n, nf))
    C[np.arange(n), k] = -(1.0 - f)
    C[np.arange(n), k + 1] = -f
    model = SurfaceModel(("G",), 0, True, False, False, False, None)  # piston + tilt
    truth = 0.2 + 0.8 * x - 0.3 * y
    target = truth + C @ e + rng.normal(0.0, sig, n)
    d = _disc(model, x, y, target, np.full(n, sig ** 2), C, r)
    est, sd = d.stage_errors
    # piston and tilt in x absorb the frames' mean and linear trend: compare what remains
    A = np.c_[np.ones(nf), np.arange(nf)]
    res = lambda v: v - A @ np.linalg.lstsq(A, v, rcond=None)[0]  # noqa: E731
    assert np.std(res(est) - res(e)) < 0.25 * np.std(res(e))
    # what the tiles identify is known better than the prior says, what they cannot keeps it
    P = np.eye(nf) - A @ np.linalg.pinv(A)
    assert np.sqrt(np.mean(np.diag(P @ np.diag(sd ** 2) @ P))) < r


def test_coverage_given_shared_matches_closed_forms_and_monte_carlo():
    from fieldcal.fit.selfcheck import coverage_given_shared

    f = np.full(200, 0.04)
    none = coverage_given_shared(f, 0.0)
    assert none["expected"] == pytest.approx(0.9, abs=1e-6)
    assert none["p05"] == pytest.approx(0.9, abs=1e-6) and none["p95"] == pytest.approx(0.9, abs=1e-6)
    assert none["field_wide_share"] == 0.0
    # all of the variance one draw: the band holds everything or nothing
    allc = coverage_given_shared(np.full(50, 1e-12), 1.0)
    assert allc["expected"] == pytest.approx(0.9, abs=0.01)
    assert allc["p05"] < 0.01 and allc["p95"] > 0.99
    # half and half, against draws
    rng = np.random.default_rng(0)
    fv = rng.uniform(0.02, 0.08, 300)
    s = 0.05
    half = coverage_given_shared(fv, s)
    zq = 1.6448536269514722
    draws = []
    for _ in range(4000):
        d = rng.normal(0.0, math.sqrt(s))
        e = rng.normal(0.0, np.sqrt(fv))
        draws.append(np.mean(np.abs(d + e) <= zq * np.sqrt(fv + s)))
    draws = np.array(draws)
    assert half["expected"] == pytest.approx(draws.mean(), abs=0.01)
    assert half["p05"] == pytest.approx(np.quantile(draws, 0.05), abs=0.03)
    assert half["p95"] == pytest.approx(np.quantile(draws, 0.95), abs=0.01)



def test_frames_field_mean_share_is_the_piston_not_the_pointwise_mean():
    """Two cases with closed forms. (a) Every tile reads frame 0 (c = -1): the frames' error is one piston, so
    the field mean's share equals the pointwise share, r^2. (b) Each tile reads two frames with weights that
    change over the field (c = -(1/2 + x), -(1/2 - x): tiles that peak at different frames), on a piston + tilt
    surface: the tiles move by -(e0 + e1) / 2 - x (e0 - e1), which the fit cannot tell from its piston and tilt,
    so the pointwise share is r^2 / 2 + 2 r^2 x^2 while the field mean over symmetric points has r^2 / 2 only:
    the mean of the pointwise shares (what the benchmark's decomposition used to charge to the piston) is larger
    by 2 r^2 mean(x^2)."""
    n, r, sig = 60, 0.3, 0.02
    model, x, y, target, C = _shared_frame_case(n, sig)
    d = _disc(model, x, y, target, np.full(n, sig ** 2), C, r)
    px, py = np.linspace(-0.5, 0.5, 11), np.zeros(11)
    _, extra = d.predict(px, py, 0)
    assert d.frames_mean_var(px, py, 0) == pytest.approx(r ** 2, rel=0.02)
    assert d.frames_mean_var(px, py, 0) == pytest.approx(float(np.mean(extra)), rel=0.02)

    rng = np.random.default_rng(3)
    x, y = rng.uniform(-0.6, 0.6, n), rng.uniform(-0.4, 0.4, n)
    model1 = SurfaceModel(("G",), 0, True, False, False, False, None)
    C = np.column_stack([-(0.5 + x), -(0.5 - x)])
    d = _disc(model1, x, y, rng.normal(0.0, sig, n), np.full(n, sig ** 2), C, r)
    px, py = np.linspace(-0.6, 0.6, 13), np.zeros(13)
    _, extra = d.predict(px, py, 0)
    _, bare = d.without_nuisances().predict(px, py, 0)
    assert np.allclose(extra - bare, r ** 2 / 2 + 2 * r ** 2 * px ** 2, rtol=0.03)
    assert d.frames_mean_var(px, py, 0) == pytest.approx(r ** 2 / 2, rel=0.03)
    assert float(np.mean(extra - bare)) > 1.4 * d.frames_mean_var(px, py, 0)
    assert _disc(model1, x, y, rng.normal(0.0, sig, n), np.full(n, sig ** 2)).frames_mean_var(px, py, 0) == 0.0
