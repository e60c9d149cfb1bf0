"""Through-focus curves of one tile: best focus with sub-step accuracy, its uncertainty, the width, or a reason.

Two curve models, both fitted to the whole peak (never argmax, never a bare three-point rule) by
``scipy.optimize.least_squares`` in normalised coordinates (``u = (z - z_peak) / step``, values / max):

* ``"otf"`` — for the band-pass energy at fs: ``E(z) = a * D(pi * fs * k * (z - z0))**2 + b`` with
  ``D(x) = 2 J1(x) / x`` the geometric-defocus OTF of :mod:`fieldcal.lens` (a blur disc of diameter
  ``k |z - z0|``, ``k ~ 1/N``). Diffraction and residual blur only scale ``a``; ``b`` is the noise power
  in the band. The contrast at fs is ``sqrt(E - b) ~ |D|``, so the half-width where it falls by q is
  ``x_q / (pi * fs * k)`` with ``D(x_q) = 1 - q`` (the lens model's ``focus_tolerance_um`` at the fitted k).
* ``"peak"`` — for broad-band measures (SML): a Pearson-VII / Lorentzian peak
  ``a / (1 + ((z - z0) / w)**2)**p + b`` (``p`` fitted when the window has >= 8 points, else 1).

Uncertainty: the covariance ``(J^T J)^-1`` scaled by the residual variance ``RSS / (n - n_params)``.

A curve is rejected, with the reason in ``status``, when it is flat, has two or more peaks, peaks at or
beyond the ends of the scan (no extrapolation), or the fit fails; see :class:`CurveRules` for thresholds.
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy import optimize, signal, special

STATUS_OK = "ok"
REASONS = ("too_few_frames", "low_texture", "saturated", "out_of_frame", "flat", "multi_peak",
           "peak_outside_range", "peak_at_edge", "fit_failed")


@dataclass(frozen=True)
class CurveRules:
    """Thresholds of the curve tests (see docs/measurement.md for why each value).

    Attributes
    ----------
    min_frames : int
        Fewer frames than this and no curve is analysed.
    flat_ratio : float
        The peak must rise above the curve's floor by at least this fraction of the floor ...
    flat_snr : float
        ... and by this many times the frame-to-frame noise (MAD of second differences).
    multi_peak_prominence : float
        A second local maximum with at least this prominence (fraction of the main peak's height above the
        floor) makes the curve ambiguous.
    edge_flank : float
        Both flanks must fall below this fraction of the peak height (above the floor) inside the scan.
    window_frac : float
        Fit window: the contiguous run around the maximum above this fraction of the height, plus one point
        on each side.
    min_window : int
        The window is widened symmetrically to at least this many points.
    """

    min_frames: int = 5
    flat_ratio: float = 0.25
    flat_snr: float = 8.0
    multi_peak_prominence: float = 0.3
    edge_flank: float = 0.5
    window_frac: float = 0.15
    min_window: int = 6


@dataclass(frozen=True)
class CurveFit:
    """Result of one through-focus curve. ``status`` is "ok" or a reason from :data:`REASONS`."""

    z_best_um: float
    z_sigma_um: float
    width_um: float
    peak: float
    floor: float
    status: str
    n_used: int = 0

    @classmethod
    def rejected(cls, status: str, peak: float = math.nan, floor: float = math.nan) -> "CurveFit":
        return cls(math.nan, math.nan, math.nan, peak, floor, status, 0)


def defocus_d(x):
    """``2 J1(x) / x`` (1 at x = 0), the geometric-defocus OTF."""
    x = np.asarray(x, dtype=np.float64)
    ax = np.abs(x)
    small = ax < 1e-4
    xs = np.where(small, 1.0, x)
    return np.where(small, 1.0 - x * x / 8.0, 2.0 * special.j1(xs) / xs)


def defocus_d_prime(x):
    """Derivative of ``2 J1(x) / x``: ``-2 J2(x) / x``."""
    x = np.asarray(x, dtype=np.float64)
    small = np.abs(x) < 1e-4
    xs = np.where(small, 1.0, x)
    return np.where(small, -x / 4.0, -2.0 * special.jv(2, xs) / xs)


def _x_at_fraction(level: float) -> float:
    """x in (0, 3.83) where D(x) = level (monotonic branch)."""
    return float(optimize.brentq(lambda t: float(defocus_d(t)) - level, 1e-9, 3.8317))


@functools.lru_cache(maxsize=64)
def _x_at_fraction_cached(level: float) -> float:
    return _x_at_fraction(level)


def otf_model(z_um, a, z0_um, k, b, fs_cyc_per_mm):
    """The ``"otf"`` curve model (energy), for tests and plots."""
    x = math.pi * fs_cyc_per_mm * 1e-3 * k * (np.asarray(z_um, dtype=np.float64) - z0_um)
    return a * defocus_d(x) ** 2 + b


def peak_model(z_um, a, z0_um, w_um, p, b):
    """The ``"peak"`` curve model."""
    t = (np.asarray(z_um, dtype=np.float64) - z0_um) / w_um
    return a / (1.0 + t * t) ** p + b


def noise_sigma(v: np.ndarray) -> float:
    """Frame-to-frame noise of a curve: MAD of its second differences / sqrt(6)."""
    if v.size < 3:
        return 0.0
    d2 = v[2:] - 2.0 * v[1:-1] + v[:-2]
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def _window(v: np.ndarray, i_max: int, floor: float, height: float, rules: CurveRules) -> tuple[int, int]:
    n = v.size
    thr = floor + rules.window_frac * height
    lo = i_max
    while lo > 0 and v[lo - 1] >= thr:
        lo -= 1
    hi = i_max
    while hi < n - 1 and v[hi + 1] >= thr:
        hi += 1
    lo, hi = max(lo - 1, 0), min(hi + 1, n - 1)
    while hi - lo + 1 < rules.min_window and (lo > 0 or hi < n - 1):
        if lo > 0:
            lo -= 1
        if hi - lo + 1 < rules.min_window and hi < n - 1:
            hi += 1
    return lo, hi


def analyse_curve(z_um, values, model: str = "peak", fs_cyc_per_mm: float | None = None, q: float = 0.05,
                  rules: CurveRules | None = None) -> CurveFit:
    """Best focus, uncertainty and width of one through-focus curve, or the reason it is rejected.

    Parameters
    ----------
    z_um : array_like
        Stage positions (µm), strictly increasing.
    values : array_like
        Focus measure at each position (any positive scale).
    model : {"peak", "otf"}
        Curve model (module docstring). ``"otf"`` needs ``fs_cyc_per_mm`` and gives ``width_um``.
    q : float
        Contrast loss defining the width (half-width where contrast at fs falls by q).

    Returns
    -------
    CurveFit
        ``peak`` is the fitted height above the floor, in the units of ``values``.
    """
    rules = rules or CurveRules()
    z = np.asarray(z_um, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if z.size < rules.min_frames:
        return CurveFit.rejected("too_few_frames")
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(v))):
        return CurveFit.rejected("fit_failed")
    n = z.size
    floor = float(np.percentile(v, 10.0))
    i_max = int(np.argmax(v))
    height = float(v[i_max] - floor)
    sigma_n = noise_sigma(v)
    if not (height > rules.flat_ratio * abs(floor) and height > rules.flat_snr * sigma_n and height > 0.0):
        return CurveFit.rejected("flat", height, floor)
    # Peaks, counting a rise at either end as one (pad with the floor so find_peaks sees it).
    padded = np.concatenate([[min(floor, v[0]) - height], v, [min(floor, v[-1]) - height]])
    peaks, _ = signal.find_peaks(padded, prominence=rules.multi_peak_prominence * height)
    if len(peaks) >= 2:
        return CurveFit.rejected("multi_peak", height, floor)
    if i_max == 0 or i_max == n - 1:
        return CurveFit.rejected("peak_outside_range", height, floor)
    flank = floor + rules.edge_flank * height
    if not (np.any(v[:i_max] < flank) and np.any(v[i_max + 1:] < flank)):
        return CurveFit.rejected("peak_at_edge", height, floor)
    lo, hi = _window(v, i_max, floor, height, rules)
    zw, vw = z[lo:hi + 1], v[lo:hi + 1]
    step = float(np.median(np.diff(z)))
    if not step > 0.0:
        return CurveFit.rejected("fit_failed", height, floor)
    scale = float(v[i_max])
    u = (zw - z[i_max]) / step
    y = vw / scale
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            if model == "otf":
                if fs_cyc_per_mm is None or not fs_cyc_per_mm > 0:
                    raise ValueError("the otf model needs fs_cyc_per_mm > 0")
                res = _fit_otf(u, y, height / scale, floor / scale, v, i_max, floor, height, z, step)
            elif model == "peak":
                res = _fit_peak(u, y, height / scale, floor / scale, v, i_max, floor, height, z, step)
            else:
                raise ValueError(f"unknown curve model {model!r}")
    except (RuntimeWarning, np.linalg.LinAlgError, FloatingPointError):
        return CurveFit.rejected("fit_failed", height, floor)
    if res is None:
        return CurveFit.rejected("fit_failed", height, floor)
    params, cov, iz = res
    u0 = params[1]
    z0 = z[i_max] + u0 * step
    var = cov[iz, iz]
    if not (math.isfinite(var) and var > 0.0):
        return CurveFit.rejected("fit_failed", height, floor)
    z_sigma = math.sqrt(var) * step
    # Never extrapolate: the fitted peak must lie between the first and last sampled points of the window
    # and inside the scan with a sample beyond it on each side.
    if not (z[1] <= z0 <= z[-2]) or not (zw[0] < z0 < zw[-1]):
        return CurveFit.rejected("peak_at_edge", height, floor)
    width = math.nan
    if model == "otf":
        kappa = params[2]  # pi * fs * k * step, per unit of u
        x_q = _x_at_fraction_cached(round(1.0 - q, 12))
        width = x_q / kappa * step
    return CurveFit(float(z0), float(z_sigma), float(width), float(params[0] * scale), float(params[3] * scale
                    if model == "otf" else params[4] * scale), STATUS_OK, int(zw.size))


def _half_width_units(v, i_max, floor, height, step_units_z, z):
    """Data half-width at half height (in units of the step), by linear interpolation on each flank."""
    half = floor + 0.5 * height
    widths = []
    for direction in (-1, 1):
        i = i_max
        while 0 <= i + direction < v.size and v[i + direction] >= half:
            i += direction
        j = i + direction
        if 0 <= j < v.size and v[i] != v[j]:
            frac = (v[i] - half) / (v[i] - v[j])
            widths.append(abs((z[i] + frac * (z[j] - z[i])) - z[i_max]))
    return max(np.mean(widths) / step_units_z, 0.5) if widths else 1.0


def _covariance(jac: np.ndarray, resid: np.ndarray) -> np.ndarray | None:
    n, m = jac.shape
    dof = n - m
    if dof <= 0:
        return None
    s2 = float(resid @ resid) / dof
    jtj = jac.T @ jac
    if not np.all(np.isfinite(jtj)) or np.linalg.cond(jtj) > 1e14:
        return None
    cov = np.linalg.inv(jtj) * max(s2, 1e-300)
    return cov


def _fit_otf(u, y, a0, b0, v, i_max, floor, height, z, step):
    # Initial kappa from the half-height half-width: D(x)^2 = 1/2 at x_half.
    hw = _half_width_units(v, i_max, floor, height, step, z)
    kappa0 = _X_HALF_ENERGY / hw

    def fun(p):
        a, u0, kappa, b = p
        d = defocus_d(kappa * (u - u0))
        return a * d * d + b - y

    def jac(p):
        a, u0, kappa, b = p
        x = kappa * (u - u0)
        d = defocus_d(x)
        dd = defocus_d_prime(x)
        return np.stack([d * d, -2.0 * a * d * dd * kappa, 2.0 * a * d * dd * (u - u0), np.ones_like(u)], axis=1)

    p0 = np.array([max(a0, 1e-6), 0.0, kappa0, max(b0, 0.0)])
    x = _lm(fun, jac, p0)
    if x is None:
        return None
    x[2] = abs(x[2])  # D is even: the sign of kappa is meaningless
    if not (x[0] > 0.0 and x[2] > 1e-6):
        return None
    cov = _covariance(jac(x), fun(x))
    if cov is None:
        return None
    return x, cov, 1


def _fit_peak(u, y, a0, b0, v, i_max, floor, height, z, step):
    hw = _half_width_units(v, i_max, floor, height, step, z)
    free_p = u.size >= 8

    def unpack(p):
        return (p[0], p[1], p[2], p[3], p[4]) if free_p else (p[0], p[1], p[2], 1.0, p[3])

    def fun(p):
        a, u0, w, pw, b = unpack(p)
        t = (u - u0) / w
        return a / (1.0 + t * t) ** pw + b - y

    def jac(p):
        a, u0, w, pw, b = unpack(p)
        t = (u - u0) / w
        L = 1.0 + t * t
        lp = L ** -pw
        common = 2.0 * a * pw * t * lp / L / w
        cols = [lp, common, common * t]
        if free_p:
            cols.append(-a * lp * np.log(L))
        cols.append(np.ones_like(u))
        return np.stack(cols, axis=1)

    if free_p:
        p0 = np.array([max(a0, 1e-6), 0.0, hw, 1.0, max(b0, 0.0)])
    else:
        p0 = np.array([max(a0, 1e-6), 0.0, hw, max(b0, 0.0)])
    x = _lm(fun, jac, p0)
    if x is None:
        return None
    x[2] = abs(x[2])  # the model is even in w
    pw = x[3] if free_p else 1.0
    if not (x[0] > 0.0 and x[2] > 1e-3 and 0.1 <= pw <= 20.0):
        return None
    cov = _covariance(jac(x), fun(x))
    if cov is None:
        return None
    if not free_p:
        x = np.array([x[0], x[1], x[2], 1.0, x[3]])
    return x, cov, 1


def _lm(fun, jac, p0) -> np.ndarray | None:
    """Levenberg-Marquardt (MINPACK via scipy); None when it does not converge to finite values."""
    r = optimize.least_squares(fun, p0, jac=jac, method="lm", x_scale="jac", max_nfev=400)
    if not (r.success and np.all(np.isfinite(r.x))):
        return None
    return np.array(r.x, dtype=np.float64)


# x where D(x)^2 = 1/2, for the initial guess of the blur scale.
_X_HALF_ENERGY = _x_at_fraction(math.sqrt(0.5))
