"""Through-focus MTF(fs) of slanted edges: edge tracks across frames, best focus (sub-step) and tolerance.

* :func:`link_tracks` — the same physical edge in successive frames (z order), matched by position and
  direction (Hungarian assignment, so two nearby edges never swap).
* :func:`through_focus_peak` — best focus as the maximum of MTF(fs) over z, to a fraction of the scan step:
  a least-squares cubic (quadratic when fewer samples) over the samples around the sampled maximum, in
  normalised ``u = (z - z_k) / step``; a cubic allows a skewed peak, so no symmetry is assumed. Its
  uncertainty is the delta-method standard deviation of the root of p'(u) from the fit's covariance (the
  residual scatter, or the given per-sample sigma when that is larger).
* :func:`tolerance_half_widths` — the measured depth of field: the distances from best focus to where
  MTF(fs) crosses ``(1 - q) * peak`` on each side, from a cubic spline through the samples (root by Brent's
  method in the bracketing interval); each side separately, so an asymmetric curve keeps its asymmetry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError


def link_tracks(frame: np.ndarray, x_px: np.ndarray, y_px: np.ndarray, angle_deg: np.ndarray, z_um: np.ndarray,
                *, max_shift_px: float = 6.0, max_turn_deg: float = 4.0) -> np.ndarray:
    """Track id of each detection: detections of consecutive frames (in z order) within ``max_shift_px`` and
    ``max_turn_deg`` are the same edge (optimal one-to-one assignment). A track may skip frames where the edge
    was not found (it is matched against its last position)."""
    from scipy.optimize import linear_sum_assignment

    frame = np.asarray(frame)
    x, y, ang, z = (np.asarray(v, dtype=np.float64) for v in (x_px, y_px, angle_deg, z_um))
    track = np.full(frame.size, -1, dtype=np.int64)
    frames = sorted(set(frame.tolist()), key=lambda f: (float(np.mean(z[frame == f])), f))
    last: list[int] = []  # detection index of each track's latest member
    for f in frames:
        idx = np.flatnonzero(frame == f)
        if last:
            L = np.asarray(last)
            dist = np.hypot(x[idx, None] - x[None, L], y[idx, None] - y[None, L])
            turn = np.abs((ang[idx, None] - ang[None, L] + 90.0) % 180.0 - 90.0)
            cost = np.where((dist <= max_shift_px) & (turn <= max_turn_deg), dist, 1e9)
            ri, ci = linear_sum_assignment(cost)
            for r, c in zip(ri, ci):
                if cost[r, c] < 1e9:
                    track[idx[r]] = c
                    last[c] = int(idx[r])
        for i in idx[track[idx] < 0]:
            track[i] = len(last)
            last.append(int(i))
    return track


@dataclass(frozen=True)
class FocusPeak:
    """Best focus of one through-focus curve."""

    z_um: float
    sigma_um: float  # 1-sigma uncertainty of z_um
    peak: float  # the curve's value at z_um (the fitted maximum)
    n_used: int  # samples in the local fit
    ok: bool
    reason: str


def through_focus_peak(z_um, values, *, half_window: int = 3, sigma=None) -> FocusPeak:
    """Sub-step maximum of a sampled through-focus curve (no symmetry assumed).

    Parameters
    ----------
    z_um, values : 1-D arrays (any order; NaN samples ignored).
    half_window : samples on each side of the sampled maximum used in the local fit (3 -> up to 7 samples).
    sigma : float or array, optional
        1-sigma noise of the values; the uncertainty uses the larger of it and the fit's residual scatter.
    """
    z = np.asarray(z_um, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if z.shape != v.shape or z.ndim != 1:
        raise ParameterError("z and values must be 1-D arrays of the same length", field="values",
                             fix="give one MTF(fs) value per z position")
    good = np.isfinite(z) & np.isfinite(v)
    o = np.argsort(z[good])
    z, v = z[good][o], v[good][o]
    sig = None if sigma is None else np.broadcast_to(np.asarray(sigma, dtype=np.float64), good.shape)[good][o]
    if z.size < 3:
        return FocusPeak(math.nan, math.nan, math.nan, int(z.size), False, "fewer than 3 samples")
    k = int(np.argmax(v))
    if k == 0 or k == z.size - 1:
        return FocusPeak(float(z[k]), math.nan, float(v[k]), 1, False, "maximum at the end of the scan")
    lo, hi = max(0, k - half_window), min(z.size, k + half_window + 1)
    zz, vv = z[lo:hi], v[lo:hi]
    step = float(np.median(np.diff(z)))
    u = (zz - z[k]) / step
    n = u.size
    deg = 3 if n >= 5 else 2
    A = np.vander(u, deg + 1)  # columns u^deg ... u^0
    coef, *_ = np.linalg.lstsq(A, vv, rcond=None)
    dof = n - (deg + 1)
    res = vv - A @ coef
    s2 = float(res @ res / dof) if dof > 0 else 0.0
    if sig is not None:
        s2 = max(s2, float(np.mean(sig[lo:hi] ** 2)))
    # maximum of the polynomial between the neighbours of the sampled maximum
    ul, ur = (z[k - 1] - z[k]) / step, (z[k + 1] - z[k]) / step
    d1 = np.polyder(coef)
    cands = [r.real for r in np.roots(d1) if abs(r.imag) < 1e-12 and ul <= r.real <= ur] if d1.size > 1 else []
    cands += [ul, 0.0, ur]
    ustar = max(cands, key=lambda t: np.polyval(coef, t))
    d2 = np.polyval(np.polyder(d1), ustar)
    if not d2 < 0:
        return FocusPeak(float(z[k]), math.nan, float(v[k]), n, False, "no interior maximum in the local fit")
    # delta method: g = d u* / d coef = -(d p'(u*) / d coef) / p''(u*)
    dpd = np.array([(deg - j) * ustar ** (deg - j - 1) if deg - j >= 1 else 0.0 for j in range(deg + 1)])
    g = -dpd / d2
    try:
        cov = s2 * np.linalg.inv(A.T @ A)
        su = float(math.sqrt(max(g @ cov @ g, 0.0)))
    except np.linalg.LinAlgError:
        su = math.nan
    return FocusPeak(float(z[k] + ustar * step), su * abs(step), float(np.polyval(coef, ustar)), n, True, "ok")


def tolerance_half_widths(z_um, values, q: float, peak: FocusPeak) -> tuple[float, float]:
    """(left, right) distances (µm) from ``peak.z_um`` to where the curve falls to ``(1 - q) * peak.peak``.

    NaN on a side where the scan ends before the curve falls that far.
    """
    from scipy.interpolate import CubicSpline
    from scipy.optimize import brentq

    if not 0.0 < q < 1.0:
        raise ParameterError(f"q = {q} outside (0, 1)", field="q", fix="give the MTF loss as a fraction, e.g. 0.05")
    z = np.asarray(z_um, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    good = np.isfinite(z) & np.isfinite(v)
    o = np.argsort(z[good])
    z, v = z[good][o], v[good][o]
    if not peak.ok or z.size < 4 or not math.isfinite(peak.peak):
        return math.nan, math.nan
    thr = (1.0 - q) * peak.peak
    spl = CubicSpline(z, v, bc_type="not-a-knot")
    zp = peak.z_um
    out = []
    for direction in (-1, 1):
        side = np.flatnonzero(z < zp)[::-1] if direction < 0 else np.flatnonzero(z > zp)
        prev, found = zp, math.nan
        for j in side:
            if v[j] < thr:
                a, b = (prev, z[j])
                fa, fb = spl(a) - thr, spl(b) - thr
                if fa > 0 > fb or fa < 0 < fb:
                    found = brentq(lambda t: float(spl(t) - thr), min(a, b), max(a, b))
                else:  # the spline does not bracket (noise at the peak): linear between the samples
                    found = float(b)
                break
            prev = z[j]
        out.append(abs(found - zp) if math.isfinite(found) else math.nan)
    return out[0], out[1]


@dataclass(frozen=True)
class TrackFocus:
    """Best focus and measured tolerance of one edge track at one frequency."""

    z_best_um: float
    z_sigma_um: float
    peak_mtf: float
    tol_left_um: float  # best focus minus the near end of the tolerance
    tol_right_um: float
    ok: bool
    reason: str

    @property
    def depth_um(self) -> float:
        """Total depth of the tolerance interval, left + right."""
        return self.tol_left_um + self.tol_right_um


def analyse_track(z_um, mtf_fs, q: float = 0.05, *, half_window: int = 3, sigma=None) -> TrackFocus:
    """Best focus (sub-step peak of MTF(fs)) and the tolerance half-widths of one edge track."""
    pk = through_focus_peak(z_um, mtf_fs, half_window=half_window, sigma=sigma)
    left, right = tolerance_half_widths(z_um, mtf_fs, q, pk)
    reason = pk.reason
    if pk.ok and not (math.isfinite(left) and math.isfinite(right)):
        reason = "the scan ends before MTF(fs) falls by q on one side"
    return TrackFocus(pk.z_um, pk.sigma_um, pk.peak, left, right, pk.ok and reason == "ok", reason)
