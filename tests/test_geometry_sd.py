"""Honest uncertainties of the geometry maps and the absolute distortion, on synthetic board correspondences
with known truth (closed form, no rendering): error / sd must be ~1, so a too-small and a too-large sd fail.

* The absolute distortion is fitted to reference corners averaged through the maps; the maps' own error moves
  every corner at once (``reference_points_map_cov``), which the board fit's residuals cannot show.
* Errors shared by all points of a frame that the maps' polynomial in z does not follow (a scale error per
  frame) are found by the lack of fit and carried in ``warp_sd_px`` as a random effect per frame.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from fieldcal.fit.distortion import (brown_basis, fit_absolute_distortion, reference_points,
                                     reference_points_map_cov)
from fieldcal.fit.geometry_map import Correspondences, fit_geometry_map

SIZE = (320, 240)
CENTRE = np.array([(SIZE[0] - 1) / 2.0, (SIZE[1] - 1) / 2.0])
R = 0.5 * math.hypot(SIZE[0] - 1, SIZE[1] - 1)
TERMS = ("k1", "k2", "p1", "p2")
COEF = np.array([-0.04, 0.008, 5e-4, -3e-4])
Z = np.linspace(-120.0, 40.0, 9)
CHANNELS = ("R", "G", "B")


def _distort(p_px):
    w = (p_px - CENTRE) / R
    d = w.copy()
    for t, a in zip(TERMS, COEF):
        bx, by = brown_basis(t, w[:, 0], w[:, 1])
        d[:, 0] += a * bx
        d[:, 1] += a * by
    return CENTRE + R * d


def _warp(p_px, z_um, channel, frame_scale=None):
    """The true maps: breathing (linear and quadratic in z), a shift, lateral colour."""
    t = z_um / 160.0
    lc = {"R": 4e-4, "G": 0.0, "B": -3e-4}[channel]
    s = 2e-3 * t + 5e-4 * t * t + lc
    if frame_scale is not None:
        s = s + frame_scale.get(float(z_um), 0.0)
    return p_px + s * (p_px - CENTRE) + np.array([0.05 * t, -0.03 * t])


def _board():
    gx, gy = np.meshgrid(np.arange(13), np.arange(9))
    return np.column_stack([gx.ravel(), gy.ravel()]).astype(float)


def _correspondences(rng, sigma_px=0.02, frame_scale=None):
    board = _board()
    # the board's ideal image: a mild homography, then the lens's distortion (the z_ref geometry)
    H = np.array([[20.0, 0.4, 35.0], [-0.3, 20.0, 38.0], [1e-4, -2e-4, 1.0]])
    hb = np.column_stack([board, np.ones(len(board))]) @ H.T
    p_true = _distort(hb[:, :2] / hb[:, 2:])
    ids = np.arange(len(board))
    P, Q, Zs, C, I = [], [], [], [], []
    p_meas = None
    for z in Z:
        for c in CHANNELS:
            q = _warp(p_true, z, c, frame_scale) + rng.normal(0.0, sigma_px, p_true.shape)
            if z == 0.0 and c == "G":
                p_meas = q.copy()   # the reference plane's own corners: as noisy as any other
            Q.append(q)
            Zs.append(np.full(len(ids), z))
            C.append(np.full(len(ids), c))
            I.append(ids)
    assert p_meas is not None
    P = [p_meas] * len(Q)
    n = len(ids) * len(Q)
    corr = Correspondences(np.concatenate(P), np.concatenate(Q), np.concatenate(Zs), np.concatenate(C),
                           np.full(n, sigma_px), np.concatenate(I))
    return board, p_true, corr


def _coverage_band(s: float, lo: float, hi: float) -> None:
    """``s`` (mean of chi^2 / dof) inside [lo, hi], while an sd 0.7x or 1.4x as large would leave it."""
    assert lo < s < hi, s
    assert not lo < s / 0.7 ** 2 < hi and not lo < s / 1.4 ** 2 < hi, "the band does not tell a wrong sd"


def test_absolute_distortion_sd_holds_the_maps_shared_error():
    rng = np.random.default_rng(7)
    chi, chi_own, n = 0.0, 0.0, 0
    for _ in range(16):
        board, p_true, corr = _correspondences(rng)
        gmap = fit_geometry_map(corr, 0.0, SIZE)
        ids, p_ref, sd = reference_points(corr, gmap)
        shared = reference_points_map_cov(corr, gmap, ids, p_ref)
        d = fit_absolute_distortion(board[ids], p_ref, SIZE, sigma_px=sd, shared_cov_px2=shared)
        d_own = fit_absolute_distortion(board[ids], p_ref, SIZE, sigma_px=sd)
        if d.terms != TERMS:
            continue      # BIC chose another term set: its coefficients are not the truth's
        e = d.coef - COEF
        chi += float(e @ np.linalg.solve(d.cov, e))
        chi_own += float(e @ np.linalg.solve(d_own.cov, e))
        n += len(e)
    assert n >= 40
    _coverage_band(chi / n, 0.6, 1.55)
    # the shared part is no rounding: it widens the coefficients' sd
    assert chi_own / n > 1.15 * chi / n


def test_shared_covariance_must_match_the_points():
    from fieldcal.fit.data import FitError
    board = _board()
    with pytest.raises(FitError, match="shared covariance"):
        fit_absolute_distortion(board, board * 10 + 40, SIZE, shared_cov_px2=np.eye(3))


def _warp_chi2(gmap, frame_scale):
    xs, ys = np.meshgrid(np.linspace(40, SIZE[0] - 41, 7), np.linspace(40, SIZE[1] - 41, 5))
    p = np.column_stack([xs.ravel(), ys.ravel()])
    chi, n = 0.0, 0
    for z in Z:
        for c in CHANNELS:
            if c == "G" and z == 0.0:
                continue
            tx, ty = _warp(p, z, c, frame_scale).T
            fx, fy = gmap.warp_px(p[:, 0], p[:, 1], z, c)
            sx, sy = gmap.warp_sd_px(p[:, 0], p[:, 1], z, c)
            chi += float(np.sum(((fx - tx) / sx) ** 2) + np.sum(((fy - ty) / sy) ** 2))
            n += 2 * fx.size
    return chi / n


def test_frame_errors_are_found_and_carried_in_warp_sd():
    """Clean correspondences: lack-of-fit F ~1 and warp error/sd ~1. Every frame but z_ref magnified by its own
    error (sd 3e-5, the same for all its points: a radial bias of 0.0045 px at r = 150 px; rendered boards show
    up to 0.015 px): F above 1, and warp_sd carries much of the error that ignoring the frame errors leaves."""
    rng = np.random.default_rng(3)
    f_clean, f_frame, chi_clean, chi_frame, chi_plain = [], [], [], [], []
    for _ in range(8):
        _, _, corr = _correspondences(rng)
        g = fit_geometry_map(corr, 0.0, SIZE)
        f_clean += list(g.diagnostics["lack_of_fit_F"].values())
        chi_clean.append(_warp_chi2(g, None))
        # (not the z_ref frame: it defines the geometry the maps start from)
        frame = {float(z): float(rng.normal(0.0, 3e-5)) for z in Z if z != 0.0}
        _, _, corr = _correspondences(rng, frame_scale=frame)
        g = fit_geometry_map(corr, 0.0, SIZE)
        f_frame += list(g.diagnostics["lack_of_fit_F"].values())
        chi_frame.append(_warp_chi2(g, frame))
        g.channels = {c: dataclasses.replace(cm, cov=cm.cov - np.asarray(g.diagnostics["frame_cov"][c]))
                      for c, cm in g.channels.items()}
        chi_plain.append(_warp_chi2(g, frame))
    assert 0.7 < np.mean(f_clean) < 1.3, f_clean
    assert np.mean(f_frame) > 1.25, f_frame
    _coverage_band(float(np.mean(chi_clean)), 0.55, 1.6)
    # partly carried: (error/sd)^2 ~1.9 against ~2.8 without (the frames' effects on the reference positions
    # are not modelled; docs/geometry.md)
    assert np.mean(chi_frame) < 0.8 * np.mean(chi_plain) and np.mean(chi_frame) < 2.5, (chi_frame, chi_plain)
