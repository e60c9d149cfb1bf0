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
fixed-point iteration (b changes slowly with w). Only the geometric defocus law enters, which the measured
widths already assume; tiles whose model curve cannot be fitted keep their width.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..optics.defocus import disc_otf, disc_x_at_contrast

SUB_GRID = 8          # pixels' best foci sampled on SUB_GRID x SUB_GRID points per tile (the surface is smooth)
ITERATIONS = 2        # fixed-point steps of w = w_measured / b(w)


def _fitted_widths(z_um, z_pix, w_um, q: float, fs_cyc_per_mm: float) -> np.ndarray:
    """Widths the band-pass curve fit reads from ``mean_p D(x_q (z - z_pix[t, p]) / w[t])^2`` (NaN if rejected)."""
    from ..measure.throughfocus import CurveRules, analyse_curves

    xq = disc_x_at_contrast(1.0 - q)
    x = xq * (z_um[None, None, :] - z_pix[:, :, None]) / w_um[:, None, None]
    curves = np.mean(disc_otf(x) ** 2, axis=1)
    # the model curves are symmetric: the skew search (most of the fit's cost) has nothing to find
    fits = analyse_curves(z_um, curves, "otf", fs_cyc_per_mm, q, CurveRules(skew=False))
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
                sub_grid: int = SUB_GRID, iterations: int = ITERATIONS) -> np.ndarray:
    """Per tile row: the factor b >= 0 by which the tile's measured width exceeds its pixels' own (1 where the
    width is missing or the model curve is rejected).

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
        # the pixels' best foci about the tile's measured one (its peak sits where the data put it)
        z_pix = zs - zc[:, None] + zb[rows, None]
        z_one = zb[rows, None]
        w = w_meas[rows].copy()
        b = np.ones(rows.size)
        for _ in range(iterations):
            spread = _fitted_widths(z, z_pix, w, q, fs_cyc_per_mm)
            single = _fitted_widths(z, z_one, w, q, fs_cyc_per_mm)
            bb = spread / single
            good = np.isfinite(bb) & (bb > 0)
            b = np.where(good, bb, 1.0)
            w = w_meas[rows] / b
        out[rows] = b
    return out


def correct_widths(surface, tiles, z_um, tile_px: float, fs_cyc_per_mm: float, q: float):
    """``tiles`` with each width divided by its window bias (:func:`window_bias`), and a summary for the
    tolerance fit's diagnostics (median and largest factor)."""
    b = window_bias(surface, tiles, z_um, tile_px, fs_cyc_per_mm, q)
    has = np.isfinite(np.asarray(tiles.width_um, dtype=np.float64))
    summary = {"rule": "tile width / window bias b (fit/width_window.py): the defocus-law fit of the mean "
                       "curve of the tile's pixels (fitted surface) over that of its centre",
               "tile_px": float(tile_px),
               "median_factor": float(np.median(b[has])) if has.any() else 1.0,
               "max_factor": float(np.max(b[has])) if has.any() else 1.0}
    return replace(tiles, width_um=np.asarray(tiles.width_um, dtype=np.float64) / b), summary
