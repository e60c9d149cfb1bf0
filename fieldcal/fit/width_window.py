"""Tile widths corrected for the spread of best focus inside each tile (the width's window bias).

A tile's band-pass curve is the sum of its pixels' curves, and on a curved field those pixels focus at
different z: with a surface gradient g (µm/px) a tile of side s spans about |g| s of best focus. The sum of
shifted through-focus peaks is wider than any one of them, so the defocus-law fit reads a δ wider than every
pixel's own, and more so towards the corners where the field is steepest. On a random lens with 230 µm of field
curvature (F/1.9, δ = 9.6 µm, 40 px tiles at 640 px) the tile widths read 1.01 of δ on axis, 1.10 at ρ = 0.7
and 1.12 at ρ = 0.93 while δ is the same everywhere; the tolerance model's ρ² term took the rise and the plans
spaced the frames serving the corners too wide (issue 13: 98.55 % of pixels within the true δ).

The correction is the estimator applied to a model of its own input: for each tile the fitted surface on an
``n x n`` grid over the tile gives its pixels' best foci z_p; the curve ``mean_p D(x_q (z_k - z_p) / w)^2`` on
the stack's own z positions (``D(x) = 2 J1(x)/x``, ``D(x_q) = 1 - q``, the band-pass curve model of
:mod:`fieldcal.measure.throughfocus`) is fitted by the same batched curve fit, and so is the same curve with
every z_p at the tile's centre. The ratio of the two fitted widths is the window bias ``b(w)`` alone (the
sampling of the scan, which both share, cancels); the corrected width solves ``w_measured = b(w) w`` by
bisection in log w (model widths grow with w; a fixed-point iteration diverges once the spread exceeds a few
widths). Only the geometric defocus law enters, which the measured widths already assume; tiles whose model
curve cannot be fitted keep their width if their spread is under one width, and tiles that cannot tell their
pixels' width are left out of the
tolerance fit: those whose spread alone makes a curve wider than the one measured, and those whose modelled width
responds to the pixels' width at less than half the rate (d ln w_read / d ln w < 0.5: the curve is mostly the
spread, so any error of its model becomes a large error of δ). At 1920 x 1080 with 88 px tiles the triplet's
corners span 30-60 µm of best focus against δ = 4.4 µm at 0.3 cycles/px: most corner tiles are left out there.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..optics.defocus import disc_otf, disc_x_at_contrast

SUB_GRID = 12         # pixels' best foci sampled on SUB_GRID x SUB_GRID points per tile (the surface is smooth)
BISECTION_STEPS = 7   # in log w over at most a factor SPREAD_MAX: the width to 0.5 %
SPREAD_MAX = 4.0      # a tile whose measured width is more than this many times its pixels' is not solved for
QUANTILES = 16        # the tile's best foci as this many equal-weight groups (SUB_GRID**2 must divide by it)
SMALL_WIDENING = 0.01  # below this widening b(wm) is the tile's factor (no bisection; second-order error)
MIN_RESPONSE = 0.8    # d ln(width read) / d ln(pixels' width) below which a tile measures its spread, not δ


def _fitted_widths(z_um, z_pix, w_um, q: float, fs_cyc_per_mm: float) -> np.ndarray:
    """Widths the band-pass curve fit reads from ``mean_p D(x_q (z - z_pix[t, p]) / w[t])^2`` (NaN if rejected)."""
    from ..measure.throughfocus import CurveRules, analyse_curves

    xq = disc_x_at_contrast(1.0 - q)
    x = xq * (z_um[None, None, :] - z_pix[:, :, None]) / w_um[:, None, None]
    curves = np.mean(disc_otf(x) ** 2, axis=1)
    # the model curves are symmetric: the skew search (most of the fit's cost) has nothing to find. The main
    # fit's width, not the tapered refit's: both curves of the ratio b (the tile's and one pixel's) are sampled
    # at the same z with nearly the same width, so the estimator's sampling-phase error cancels in it, and the
    # refit made the correction 3-4x dearer (7 s of a 1080p standard calibration)
    fits = analyse_curves(z_um, curves, "otf", fs_cyc_per_mm, q, CurveRules(skew=False, tapered_width=False))
    return np.array([f.width_um if f.status == "ok" else np.nan for f in fits])


def _trend_um(surface, x_px, y_px, channel: str) -> np.ndarray:
    """The fitted surface's smooth part (µm): the polynomial trend without the kriged discrepancy, whose
    variation inside one tile is small and whose solve would cost more than the rest of the correction."""
    disc = getattr(surface, "discrepancy", None)
    if disc is None or not hasattr(surface, "geometry"):
        return np.asarray(surface.predict(x_px, y_px, channel), dtype=np.float64)
    xh, yh = surface.geometry.normalise(np.ravel(x_px), np.ravel(y_px))
    t = surface.z_centre_um + surface.z_scale_um * disc.trend(xh, yh, surface._ch(channel))
    return np.asarray(t, dtype=np.float64).reshape(np.shape(x_px))


def window_bias(surface, tiles, z_um, tile_px: float, fs_cyc_per_mm: float, q: float,
                sub_grid: int = SUB_GRID, steps: int = BISECTION_STEPS) -> np.ndarray:
    """Per tile row: the factor b >= 1 by which the tile's measured width exceeds its pixels' own (1 where the
    width is missing or the model curve is rejected; NaN where the spread alone makes a curve wider than the
    one measured, so the tile cannot tell its pixels' width).

    Parameters
    ----------
    surface : SurfaceFit, or any object with ``predict(x_px, y_px, channel)``
        The fitted best-focus surface (µm, stage coordinates); its polynomial trend is used.
    tiles : TileData
        Accepted tiles (centres, best foci, widths at the calibration's fs and q).
    z_um : array
        The stack's frame positions (µm).
    tile_px : float
        Tile side (px).
    fs_cyc_per_mm, q : float
        The calibration's MTF criterion (the widths' definition).
    """
    z = np.sort(np.asarray(z_um, dtype=np.float64))
    w_meas = np.asarray(tiles.width_um, dtype=np.float64)
    out = np.ones(w_meas.size)
    ok = np.isfinite(w_meas) & (w_meas > 0) & np.isfinite(np.asarray(tiles.z_best_um, dtype=np.float64))
    if not ok.any() or z.size < 5 or tile_px <= 0:
        return out
    off = (np.arange(sub_grid) + 0.5) / sub_grid * tile_px - 0.5 * tile_px
    ox, oy = (a.ravel() for a in np.meshgrid(off, off))
    ch = np.asarray(tiles.channel)
    x = np.asarray(tiles.x_px, dtype=np.float64)
    y = np.asarray(tiles.y_px, dtype=np.float64)
    zb = np.asarray(tiles.z_best_um, dtype=np.float64)
    for c in dict.fromkeys(ch[ok].tolist()):
        rows = np.flatnonzero(ok & (ch == c))
        px, py = x[rows, None] + ox[None, :], y[rows, None] + oy[None, :]
        zs = _trend_um(surface, px, py, c)
        zc = _trend_um(surface, x[rows], y[rows], c)
        # the pixels' best foci about the tile's measured one (its peak sits where the data put it), reduced to
        # QUANTILES equal-weight groups of the sorted values: the curve is a sum over the distribution of z, so
        # the order of the pixels does not matter, and 16 groups cost a ninth of 144 points
        z_pix = zs - zc[:, None] + zb[rows, None]
        z_pix = np.sort(z_pix, axis=1).reshape(rows.size, QUANTILES, -1).mean(axis=2)
        wm = w_meas[rows]
        # the scan's own sampling, common to the tile and to one pixel: what the fit reads from a single
        # pixel's curve of width wm, per µm of width (it changes little over the bracket below)
        sampling = _fitted_widths(z, zb[rows, None], wm, q, fs_cyc_per_mm) / wm
        sampling = np.where(np.isfinite(sampling) & (sampling > 0), sampling, 1.0)

        def model(w, sel=slice(None)):  # the width the fit would read from tiles sel if their pixels' width were w
            return _fitted_widths(z, z_pix[sel], w, q, fs_cyc_per_mm) / sampling[sel]

        # solve model(w) = wm for w in [wm / SPREAD_MAX, wm] by bisection in log w: the spread only widens,
        # and model(w) grows with w (a fixed-point iteration w = wm / b(w) diverges once the spread exceeds
        # a few widths, where b rises fast as w falls)
        # the model curve is a sum of QUANTILES shifted peaks along the gradient: smooth only for widths above
        # twice their spacing, so the bracket starts there (a tile needing less is lost: spread >> width)
        w_min = np.maximum(wm / SPREAD_MAX, 2.0 * np.ptp(z_pix, axis=1) / (QUANTILES - 1))
        unresolved = w_min >= wm
        w_min = np.minimum(w_min, wm)
        m_hi = model(wm)
        spread = np.ptp(z_pix, axis=1)
        # no widening; or the model curve rejected while the spread is under one width (it barely matters there)
        keep = (np.isfinite(m_hi) & (m_hi <= wm * (1.0 + 1e-6))) | (~np.isfinite(m_hi) & (spread < wm))
        b = np.ones(rows.size)
        lost = np.zeros(rows.size, dtype=bool)
        # a tile widened by under SMALL_WIDENING needs no solve: b(w) = 1 + O(spread^2 / w^2) changes over the
        # bracket [wm / b, wm] only at second order in (b - 1), so b(wm) itself is its factor to 2e-4. Only the
        # others are solved for (at 1920x1080 the bisection of every tile was 7 of the 12 s of a standard run)
        small = ~keep & np.isfinite(m_hi) & (m_hi < wm * (1.0 + SMALL_WIDENING)) & ~unresolved
        b[small] = m_hi[small] / wm[small]
        need = np.flatnonzero(~keep & ~small)
        if need.size:
            wn, w_min_n = wm[need], w_min[need]
            m_lo = model(w_min_n, need)
            m_hi_n = m_hi[need]
            # the spread alone is wider than the measured curve, too wide for the model to resolve the width,
            # or so wide that the model curve cannot be fitted
            lost_n = unresolved[need] | ~np.isfinite(m_hi_n) | (np.isfinite(m_lo) & (m_lo > wn))
            lo, hi = np.log(w_min_n), np.log(wn)
            # a tighter bracket where the widening is small (b(w) rises as w falls, so w > wm / b(wm)^3 there):
            # the same bisection steps then give the width to a fraction of the widening
            b0 = np.where(~np.isfinite(m_hi_n), 1.0, m_hi_n / wn)
            w_try = np.maximum(wn / b0 ** 3, w_min_n)
            m_try = model(w_try, need)
            lo = np.where(np.isfinite(m_try) & (m_try <= wn), np.log(w_try), lo)
            for _ in range(steps):
                mid = 0.5 * (lo + hi)
                mm = model(np.exp(mid), need)
                above = ~np.isfinite(mm) | (mm > wn)
                hi = np.where(above, mid, hi)
                lo = np.where(above, lo, mid)
            w_true = np.exp(0.5 * (lo + hi))
            # how much of the measured width is the pixels' own: d ln(model) / d ln(w) at the solution. Below
            # MIN_RESPONSE the tile's curve is mostly its spread, and a small error of the model (of the
            # surface, of the blur's shape) becomes a large error of w: such a tile cannot tell its pixels'
            # width either
            up, down = model(w_true * np.exp(0.05), need), model(w_true * np.exp(-0.05), need)
            response = (np.log(up) - np.log(down)) / 0.1
            lost[need] = lost_n | (response < MIN_RESPONSE)
            b[need] = wn / w_true
        out[rows] = np.where(lost, np.nan, b)
    return out


def correct_widths(surface, tiles, z_um, tile_px: float, fs_cyc_per_mm: float, q: float):
    """``tiles`` with each width divided by its window bias (:func:`window_bias`), and a summary for the
    tolerance fit's diagnostics (median and largest factor)."""
    b = window_bias(surface, tiles, z_um, tile_px, fs_cyc_per_mm, q)
    w = np.asarray(tiles.width_um, dtype=np.float64)
    lost = np.isfinite(w) & ~np.isfinite(b)
    has = np.isfinite(w) & np.isfinite(b)
    summary = {"rule": "tile width / window bias b (fit/width_window.py): the defocus-law fit of the mean "
                       "curve of the tile's pixels (fitted surface) over that of its centre",
               "tile_px": float(tile_px),
               "median_factor": float(np.median(b[has])) if has.any() else 1.0,
               "max_factor": float(np.max(b[has])) if has.any() else 1.0,
               # tiles whose curve the spread of best focus alone explains: they cannot tell δ and are left out
               "tiles_dropped": int(lost.sum())}
    return replace(tiles, width_um=w / b), summary
