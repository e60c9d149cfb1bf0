"""A T/S pair's focus tolerance from its two e-SFR tracks (measure/edge_tiles.py): the along-edge spread of
foci is removed by a forward model of the measurement, and the pair's width is the mean of its two tracks, not
the smaller one (which reads low by the tracks' scatter). Synthetic tracks with known δ: the through-focus
MTF(fs) of a defocus disc, ``|2 J1(x)/x|`` with ``x = x_q dz / δ``, averaged over the foci along the edge."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fieldcal.measure.edge_tiles import (along_edge_spread_um, astigmatic_floor_um, pair_width_um,
                                         track_width_model)
from fieldcal.measure.esfr_focus import analyse_track
from fieldcal.optics.defocus import disc_otf, disc_x_at_contrast

Q = 0.05
DELTA_UM = 10.0
STEP_UM = 6.0


def _track(z, z0, spread_um, rng=None, noise=0.0, floor_um=0.0):
    """MTF(fs) of an edge whose foci are spread uniformly over ``spread_um`` about z0 along its length, with a
    blur floor ``floor_um`` across it (an astigmatic disc seen off its axes)."""
    xq = disc_x_at_contrast(1.0 - Q)
    u = (np.arange(64) + 0.5) / 64 - 0.5
    e = np.hypot(z[:, None] - z0 - spread_um * u[None, :], floor_um)
    v = 0.6 * np.mean(np.abs(disc_otf(xq * e / DELTA_UM)), axis=1)
    if rng is not None:
        v = v + rng.normal(0.0, noise, v.shape)
    return v


def _width(z, v):
    tk = analyse_track(z, v, Q)
    return 0.5 * (tk.tol_left_um + tk.tol_right_um) if tk.ok else math.nan


def test_along_edge_spread_closed_form():
    # a radial gradient g at 45 degrees: an edge along the radius sees |g| L, one across it nothing, one at
    # 45 degrees from the radius |g| L cos 45
    g = 0.3  # µm/px
    gx, gy = g * math.cos(math.radians(45)), g * math.sin(math.radians(45))
    got = along_edge_spread_um(gx, gy, np.array([45.0, 135.0, 90.0]), 50.0)
    np.testing.assert_allclose(got, [g * 50.0, 0.0, g * 50.0 * math.cos(math.radians(45))], atol=1e-12)


def test_spread_model_recovers_delta_from_a_spread_track():
    model = track_width_model(STEP_UM, DELTA_UM, Q)
    assert model.spread_ratio[0] == pytest.approx(1.0) and model.floor_ratio[0] == pytest.approx(1.0)
    assert np.all(np.diff(model.spread_ratio) >= -1e-6)  # a wider spread never reads narrower
    assert np.all(np.diff(model.floor_ratio) <= 1e-6)  # a higher floor never reads wider
    z = np.arange(-80.0, 80.0 + STEP_UM, STEP_UM)
    for s in (2.0, 4.0):  # spread / δ: the 1080p triplet's sagittal corners reach ~5
        w = _width(z, _track(z, 1.3, s * DELTA_UM))
        w0 = _width(z, _track(z, 1.3, 0.0))
        assert w / w0 > 1.005  # the spread widens the track measurably (0.7 % at 2 δ, 2 % at 4 δ)
        # the correction takes it back to the spread-free reading
        assert float(model.correct(w, s * DELTA_UM)) == pytest.approx(w0, rel=0.006)


@pytest.mark.parametrize("spread_over_delta", [0.0, 5.0])
def test_pair_width_mean_is_unbiased_where_the_min_is_not(spread_over_delta):
    rng = np.random.default_rng(7)
    z = np.arange(-80.0, 80.0 + STEP_UM, STEP_UM)
    model = track_width_model(STEP_UM, DELTA_UM, Q)
    # the sagittal edge lies along a radial focus gradient, the tangential one across it
    spread_s = spread_over_delta * DELTA_UM
    ref = _width(z, _track(z, 0.0, 0.0))  # the estimator's own reading of δ without noise or spread
    wts, wss = [], []
    for _ in range(30):
        z0 = rng.uniform(-3.0, 3.0)
        wts.append(_width(z, _track(z, z0, 0.0, rng, 0.012)))
        wss.append(_width(z, _track(z, z0, spread_s, rng, 0.012)))
    wt, ws = np.array(wts) / ref, np.array(wss) / ref
    scatter = float(np.std(wt, ddof=1))  # one track's relative scatter
    assert scatter > 0.015  # noise large enough for the min's bias to show
    pairs = np.array([pair_width_um(a, b) for a, b in zip(wt, model.correct(ws, spread_s / ref))])
    se = float(np.std(pairs, ddof=1)) / math.sqrt(pairs.size)
    # the mean of the spread-corrected pair is unbiased within its standard error
    assert abs(np.mean(pairs) - 1.0) < max(3.0 * se, 0.004)
    if spread_over_delta == 0.0:
        # the min of two noisy estimates of one δ reads low by ~0.56 of a track's scatter
        assert np.mean(np.minimum(wt, ws)) < 1.0 - 0.3 * scatter
    else:
        # uncorrected, the sagittal track reads wide (3 % at 5 δ of spread), and so would the plain mean
        assert np.mean(ws) > 1.0 + 2.0 * float(np.std(ws, ddof=1)) / math.sqrt(ws.size)
        wc = model.correct(ws, spread_s / ref)
        assert np.mean(wc) == pytest.approx(1.0, abs=3.0 * float(np.std(wc, ddof=1)) / math.sqrt(wc.size))


def test_astigmatic_floor_closed_form_and_correction():
    # an elliptical disc with semi-axes k|z - zT| (radial) and k|z - zS| (tangential) projected on a normal at
    # phi from the radius: its extent^2 is minimal at z* and the minimum is (cos phi sin phi (zT - zS))^2
    zt, zs, phi = 3.0, -9.0, math.radians(25.0)
    z = np.linspace(-30.0, 30.0, 20001)
    ext2 = (math.cos(phi) * (z - zt)) ** 2 + (math.sin(phi) * (z - zs)) ** 2
    assert math.sqrt(ext2.min()) == pytest.approx(float(astigmatic_floor_um(math.cos(2 * phi), zt - zs)), rel=1e-6)
    assert float(astigmatic_floor_um(1.0, 12.0)) == 0.0  # a pure T edge sees T defocus alone
    # a floor narrows the track (the disc's curve falls faster off a blurred peak); the model takes it back
    model = track_width_model(STEP_UM, DELTA_UM, Q)
    zz = np.arange(-80.0, 80.0 + STEP_UM, STEP_UM)
    w0 = _width(zz, _track(zz, 0.7, 0.0))
    w = _width(zz, _track(zz, 0.7, 0.0, floor_um=1.4 * DELTA_UM))
    assert w / w0 < 0.985
    assert float(model.correct(w, 0.0, 1.4 * DELTA_UM)) == pytest.approx(w0, rel=0.006)


def test_pair_width_one_track():
    assert pair_width_um(4.0, math.nan) == 4.0
    assert math.isnan(pair_width_um(math.nan, math.nan))
    # averaged in the defocus law's curvature 1 / w^2, where a width's error is symmetric
    assert pair_width_um(4.0, 5.0) == pytest.approx((0.5 * (4.0 ** -2 + 5.0 ** -2)) ** -0.5)
    assert pair_width_um(4.0, 4.0) == pytest.approx(4.0)


def test_short_scan_widths_are_combined_and_fitted_in_curvature():
    """Tracks of 9 frames at a step near δ (random-7 of bench_edge_calibration: δ 22.4 µm, step 20 µm): the
    defocus law's width x_q / (pi fs k) is skewed (a flat, noisy track reads 2-5x wide, none as far narrow);
    its error is symmetric in 1 / w^2. The pair (pair_width_um) and the width model (fit_tolerance with
    residuals="curvature") both average there; the mean in µm and a fit in µm read δ wide."""
    from fieldcal.fit.data import ImageGeometry, TileData
    from fieldcal.fit.tolerance import fit_tolerance
    from fieldcal.optics import MTFCriterion

    delta, step, n = 22.0, 20.0, 60
    xq = disc_x_at_contrast(1.0 - Q)
    z = np.arange(-80.0, 80.0 + step, step)

    def width(v):
        tk = analyse_track(z, v, Q)
        return 0.5 * (tk.tol_left_um + tk.tol_right_um) if tk.ok else math.nan

    def curve(z0, rng=None):
        v = 0.75 * np.abs(disc_otf(xq * (z - z0) / delta))
        return v if rng is None else v + rng.normal(0.0, 0.015, z.size)

    ref = width(curve(0.0))  # the estimator's own noise-free reading
    assert ref == pytest.approx(delta, rel=0.01)
    rng = np.random.default_rng(0)
    tracks = []
    for _ in range(n):
        z0 = rng.uniform(-10.0, 10.0)
        tracks.append((width(curve(z0, rng)), width(curve(z0, rng))))
    wt = np.array(tracks)
    q10, q50, q90 = np.nanquantile(wt, [0.1, 0.5, 0.9])
    assert q90 - q50 > 1.5 * (q50 - q10)  # skewed wide
    x, y = rng.uniform(10.0, 310.0, n), rng.uniform(10.0, 170.0, n)
    geom = ImageGeometry(320, 180, 19.6)

    def fitted(w, residuals):
        m = np.isfinite(w)
        tiles = TileData.from_arrays(np.full(int(m.sum()), "G"), x[m], y[m], np.zeros(int(m.sum())),
                                     np.ones(int(m.sum())), width_um=w[m])
        fit = fit_tolerance(tiles, geom, MTFCriterion(16.0, Q), residuals=residuals)
        return float(fit.width_cal_um(160.0, 90.0, "G")) / ref

    pairs = np.array([pair_width_um(a, b) for a, b in wt])
    assert fitted(pairs, "curvature") == pytest.approx(1.0, abs=0.03)
    # the µm mean of the pair and a fit in µm (session 8's rules) read wide by the skewed tail
    assert fitted(np.nanmean(wt, axis=1), "width") > 1.06
