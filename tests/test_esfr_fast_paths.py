"""The e-SFR's fast paths against their plain definitions (brute force on random data).

- ``esfr._row_centroids`` (a batched matrix product against separable Hamming terms, only the window's end
  bands masked) against the per-element Hamming-weighted centroid of the row derivative;
- ``esfr_detect._free_distance`` (bisection in the mask's boundaries) against walking the pixels of every row.
"""

from __future__ import annotations

import numpy as np
import pytest

from fieldcal.measure import esfr as E
from fieldcal.measure import esfr_detect as D


def _centroids_plain(d: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """sum(w d x) / sum(w d) per row, w the Hamming weight 0.54 + 0.46 cos(pi (x - c) / h) inside |x - c| <= h."""
    B, C, R, Wd = d.shape
    out = np.full((B, C, R), np.nan)
    x = np.arange(Wd) + 0.5
    for b in range(B):
        for c in range(C):
            for r in range(R):
                cr = centre[b, c, r]
                if not np.isfinite(cr):
                    continue
                inside = np.abs(x - cr) <= half[b]
                w = (0.54 + 0.46 * np.cos(np.pi * (x - cr) / half[b])) * inside
                s0 = np.sum(w * d[b, c, r])
                out[b, c, r] = np.sum(w * d[b, c, r] * x) / s0 if s0 != 0 else np.nan
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_row_centroids_equal_the_plain_weighted_centroid(seed):
    rng = np.random.default_rng(seed)
    B, C, R, W = 5, 3, 23, 41
    ncols = rng.integers(20, W + 1, B)
    half = rng.uniform(4.0, 14.0, B).round(rng.integers(0, 2))  # integer and fractional half-widths
    slope = rng.uniform(-0.35, 0.35, B)
    rows = np.arange(R)
    # a blurred step along a slanted line per region, noise, zero padding beyond each region's columns
    edge = (ncols[:, None] / 2.0 + slope[:, None] * (rows - R / 2.0))[:, None, :, None]  # B x 1 x R x 1
    cols = np.arange(W)[None, None, None, :]
    a = 0.2 + 0.6 / (1.0 + np.exp(-(cols - edge) / 1.3)) + 0.01 * rng.standard_normal((B, C, R, W))
    a = np.where(cols < ncols[:, None, None, None], a, 0.0)
    d = np.diff(a, axis=3)
    for b in range(B):
        d[b, :, :, ncols[b] - 1:] = 0.0
    d[1] *= -1.0  # a falling edge: the centroid does not depend on the sign
    centre = np.broadcast_to(edge[..., 0] - 0.5, (B, C, R)).copy() + rng.normal(0, 0.7, (B, C, R))
    centre[0, 1, 3] = np.nan  # a row without a centre
    centre[2, :, 5] = 0.5 + 3.0  # window cut by the region's first column
    centre[3, 0, :4] = half[3] + 0.5  # |x - c| == half exactly at x = 0.5 (the window's inclusive end)
    centre[4, 2, 7] = -40.0  # windows off the region on either side: no column, no centroid
    centre[4, 1, 8] = W + 40.0
    got = E._row_centroids(d, centre, half)
    want = _centroids_plain(d, centre, half)
    assert np.array_equal(np.isnan(got), np.isnan(want))
    ok = np.isfinite(want)
    assert ok.sum() > 0.9 * ok.size
    np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-9)
    # the centroid of a clean step's derivative sits on the edge (sanity of the reference itself)
    assert np.nanmedian(np.abs(want[:, :, 4:-4] - (edge[..., 0] - 0.5)[:, :, 4:-4])) < 0.5


def _free_plain(mask_v: np.ndarray, rows: np.ndarray, xs: np.ndarray, reach: int) -> float:
    """Walk each row outward from the edge pixel: the first pixel 2 .. reach px away that differs from the pixel
    2 px away on that side (clamped into the image), smallest over the rows and both sides; reach if none."""
    H, W = mask_v.shape
    best = reach
    for r, x in zip(rows, np.rint(xs).astype(int)):
        for sgn in (-1, 1):
            own = mask_v[r, min(max(x + 2 * sgn, 0), W - 1)]
            for off in range(2, reach + 1):
                col = x + sgn * off
                if 0 <= col < W and mask_v[r, col] != own:
                    best = min(best, off)
                    break
    return float(best)


@pytest.mark.parametrize("seed", range(4))
def test_free_distance_equals_walking_the_pixels(seed):
    rng = np.random.default_rng(seed)
    H, W = 60, 90
    # blocks of random width along each row (boundaries a few to tens of px apart), some rows uniform
    mask = np.zeros((H, W), np.uint8)
    for r in range(H):
        x, v = 0, int(rng.integers(0, 2))
        while x < W:
            n = int(rng.integers(1, 30))
            mask[r, x:x + n] = v
            x, v = x + n, 1 - v
    mask[7] = 1
    for transposed in (False, True):
        mask_v = mask.T if transposed else mask
        Hv, Wv = mask_v.shape
        changes = D._row_changes(mask, transposed=transposed)
        for _ in range(60):
            r0 = int(rng.integers(0, Hv - 5))
            rows = np.arange(r0, min(Hv, r0 + int(rng.integers(4, 30))))
            xs = rng.uniform(-6, Wv + 6) + rng.uniform(-0.4, 0.4) * (rows - rows[0])  # also off the image
            reach = int(rng.integers(4, 70))
            assert D._free_distance(changes, Wv, rows, xs, reach) == _free_plain(mask_v, rows, xs, reach)


def test_row_changes_are_the_boundaries():
    mask = np.array([[0, 0, 1, 1, 0], [1, 1, 1, 1, 1], [0, 1, 0, 1, 0]], np.uint8)
    assert D._row_changes(mask).tolist() == [2, 4, 5 * 2 + 1, 5 * 2 + 2, 5 * 2 + 3, 5 * 2 + 4]
    # columns of mask as rows (length 3): column 0 = 0,1,0; 1 = 0,1,1; 2 = 1,1,0; 3 = 1,1,1; 4 = 0,1,0
    assert D._row_changes(mask, transposed=True).tolist() == [1, 2, 3 + 1, 6 + 2, 12 + 1, 12 + 2]


def test_median_in_place_equals_np_median():
    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 10, 11, 500, 501):
        x = rng.standard_normal(n)
        want = float(np.median(x))
        y = x.copy()
        assert E._median_1d(y, in_place=True) == want
        assert sorted(y.tolist()) == sorted(x.tolist())  # reordered, not changed
        # the noise estimate's MAD, in place, equals the plain one
        r = x.copy()
        r -= E._median_1d(r, in_place=True)
        assert E._median_1d(np.abs(r, out=r), in_place=True) == float(np.median(np.abs(x - np.median(x))))


def test_kept_esf_is_the_blurred_step_on_the_regions_own_bins():
    """keep_esf=True (the binned ESF is put back on the region's bins only then): a Gaussian-blurred edge's ESF,
    bin j at (j - nb_half + 1/2) / oversample px along the normal, is 0.2 + 0.6 Phi(s / sigma), sigma^2 the blur's
    plus the pixel box's 1/12 px^2."""
    from math import erf, sqrt

    from fieldcal.measure.esfr_synth import render_edge
    sigma_px, hw, over = 0.8, 20, 4
    r = E.esfr_roi(render_edge(96, 64, normal_deg=5.0, sigma_px=sigma_px), half_width_px=hw, keep_esf=True)
    assert r.quality[0].ok
    nb_half = int(np.ceil(hw * over)) + 2
    assert r.esf.shape == (1, 2 * nb_half)
    j = np.arange(2 * nb_half)
    s = (j - nb_half + 0.5) / over
    want = 0.2 + 0.6 * 0.5 * (1 + np.vectorize(erf)(s / sqrt(2 * (sigma_px ** 2 + 1 / 12))))
    esf = r.esf[0]
    ok = np.isfinite(esf)
    assert ok[nb_half - 40:nb_half + 40].all()  # +-10 px about the edge binned
    assert np.max(np.abs(esf[ok] - want[ok])) < 0.01
    assert E.esfr_roi(render_edge(96, 64, normal_deg=5.0, sigma_px=sigma_px), half_width_px=hw).esf is None
