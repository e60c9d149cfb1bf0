"""Through-focus width of a band-pass curve that does not depend on where the scan's samples fall.

Why a second fit: the ``"otf"`` model ``a D(kappa u)^2 + b`` is only an approximation of a measured band energy
(the band-pass ring averages D^2 over a range of frequencies, the chart's spectrum weights them, the pixel
and the noise floor add their own shapes). A least-squares fit of an approximate model is a weighted average
of its misfit over the samples it uses, and the main fit uses a hard window (the run above a fraction of the
height plus one point each side, :func:`fieldcal.measure.throughfocus._window`): as the scan's start moves by a
fraction ``phi`` of a step, whole samples enter and leave the window with full weight, so the fitted blur
scale jumps with ``phi``. On the simulated triplet at 20 µm steps the half-width moved by ±0.07 µm
(``cos 2 pi phi``, 2700 tiles), and two scans of one lens started half a step apart disagreed on the
tolerance of every channel at once.

The fix: refit with weights that are a smooth function of the model's own argument ``x = kappa (u - u0)`` — 1
on the central part of the main lobe, a raised-cosine roll-off to 0 before the first zero of ``D`` — iterated
from the main fit. The objective is then a sum of samples of a smooth function of z; by the Poisson summation
formula such a sum differs from the integral (which has no phase) only by the function's Fourier components at
multiples of 1 / step, which for a roll-off several samples long are negligible; a hard window, a
discontinuous function, has components that fall only as 1 / frequency. The best focus keeps the main fit
(the skew correction and its uncertainty are built on it); only the width changes.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: |x| (the argument of D) up to which a sample has full weight (D^2 = 0.15 at x = 2.5, about where the main
#: fit's window ends), and where the roll-off reaches 0 (past D's first zero at 3.83, into the first side lobe:
#: the samples there pin the floor b, which is otherwise traded against the blur scale). On band-averaged D^2
#: curves (the log-Gabor ring's band) sampled at 16 phases the half-width moved by 0.15-0.25 µm peak to peak
#: with the hard window and by <= 0.05 µm with this taper, with a smaller scatter under noise (tests).
X_FLAT = 2.5
X_EDGE = 4.5
N_PASSES = 3
#: samples over which the weights ramp up from 0 at each end of the scan
END_RAMP = 2


def taper(x: np.ndarray) -> np.ndarray:
    """Weight of a sample at model argument ``x``: 1 for |x| <= X_FLAT, raised cosine to 0 at X_EDGE."""
    a = np.abs(np.asarray(x, dtype=np.float64))
    t = np.clip((a - X_FLAT) / (X_EDGE - X_FLAT), 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * t))


def end_weights(n: int) -> np.ndarray:
    """Weights of the scan's samples by their index: a raised-cosine ramp over the END_RAMP samples at each end.

    Why: where the scan cuts a curve's lobe, the last sample would otherwise enter or leave the fit with full
    weight as the scan moves, the same jump the taper removes in the middle of the scan.
    """
    j = np.arange(n, dtype=np.float64)
    d = np.minimum(j, n - 1 - j) / END_RAMP
    return 0.5 * (1.0 - np.cos(np.pi * np.clip(d, 0.0, 1.0)))


def tapered_widths(z, V, pres, fits, step: float, x_q: float, out: list) -> list:
    """``out`` (CurveFits by curve) with the width of every accepted band-pass curve from the tapered refit.

    ``pres``: (curve index, window) pairs of the main fit and ``fits`` its results (normalised coordinates: u in
    steps from the sampled maximum, values / the maximum). A curve whose refit fails keeps the main fit's width.
    ``z``, ``V`` and ``step`` as :func:`fieldcal.measure.throughfocus._fit_batch` takes them (one grid, or per curve).
    """
    from .throughfocus import STATUS_OK, _fit_batch, _st, _zt

    idx = [j for j, ((t, _), f) in enumerate(zip(pres, fits))
           if f is not None and out[t].status == STATUS_OK and np.isfinite(out[t].width_um)]
    if not idx:
        return out
    # one z grid, or each curve its own (throughfocus.analyse_curve_list): rows padded to the longest, the
    # padding weighted 0 (end weights) and cut off again before the fit
    ns = np.array([_zt(z, pres[j][0]).size for j in idx])
    n = int(ns.max())
    full = [(pres[j][0], dataclasses.replace(pres[j][1], lo=0, hi=int(m) - 1)) for j, m in zip(idx, ns)]
    if isinstance(z, np.ndarray):
        u = np.stack([(z - z[pre.i_max]) / step for _, pre in full])
        ends = end_weights(n)
    else:
        u = np.stack([np.pad((z[t] - z[t][pre.i_max]) / _st(step, t), (0, n - m), mode="edge")
                      for (t, pre), m in zip(full, ns)])
        ends = np.stack([np.pad(end_weights(int(m)), (0, n - m)) for m in ns])
    p = np.array([fits[j].params for j in idx], dtype=np.float64)
    for _ in range(N_PASSES):
        w = taper(p[:, 2:3] * (u - p[:, 1:2])) * ends
        new = _fit_batch(z, V, full, step, "otf", p_init=list(p), weights=[w[r, :m] for r, m in enumerate(ns)])
        for r, f in enumerate(new):
            if f is not None and np.sum(w[r] > 0) >= 6:
                p[r] = f.params
    res = list(out)
    for r, (t, _) in enumerate(full):
        kappa = abs(p[r, 2])
        if kappa > 0 and np.isfinite(kappa):
            res[t] = dataclasses.replace(out[t], width_um=float(x_q / kappa * _st(step, t)))
    return res
