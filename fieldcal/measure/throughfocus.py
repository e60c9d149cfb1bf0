"""Through-focus curves of one tile: best focus with sub-step accuracy, its uncertainty, the width, or a reason.

Two curve models, both fitted to the whole peak (never argmax, never a bare three-point rule) by
``scipy.optimize.least_squares`` in normalised coordinates (``u = (z - z_peak) / step``, values / max):

* ``"otf"`` — for the band-pass energy at fs: ``E(z) = a * D(pi * fs * k * (z - z0))**2 + b`` with
  ``D(x) = 2 J1(x) / x`` the geometric-defocus OTF of :mod:`fieldcal.simulate.lens` (a blur disc of diameter
  ``k |z - z0|``, ``k ~ 1/N``). Diffraction and residual blur only scale ``a``; ``b`` is the noise power
  in the band. The contrast at fs is ``sqrt(E - b) ~ |D|``, so the half-width where it falls by q is
  ``x_q / (pi * fs * k)`` with ``D(x_q) = 1 - q`` (the lens model's ``focus_tolerance_um`` at the fitted k).
* ``"peak"`` — for broad-band measures (SML): a Pearson-VII peak ``a / (1 + t**2 / p)**p + b`` with
  ``t = (z - z0) / w``: a Lorentzian at p = 1, a Gaussian as p grows (``p`` fitted when the window has >= 8
  points, else 1).

Uncertainty: the covariance ``(J^T J)^-1`` scaled by the residual variance ``RSS / (n - n_params)``.

A curve is rejected, with the reason in ``status``, when it is flat, has two or more peaks, peaks at or
beyond the ends of the scan (no extrapolation), or the fit fails; see :class:`CurveRules` for thresholds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import spherical
from ..optics.defocus import disc_otf as defocus_d, disc_otf_derivative as defocus_d_prime, disc_x_at_contrast

STATUS_OK = "ok"
# Prior odds symmetric : skewed curve in the skew correction's evidence weight. At 1 (BIC alone) a curve with
# no evidence either way still took 1/(1 + sqrt(n)) ~ 0.27 of the noisier local estimate: tile scatter on
# simulated lenses at coarse steps doubled (0.48 -> 0.90 µm). See docs/measurement.md "Asymmetric curves".
SKEW_PRIOR_ODDS = 10.0
# Wavelength (nm) of the skew model's diffraction term when the caller gives none (mid-visible); it only sets
# nu = fs lambda N, whose effect on the peak is second order (module spherical, WAVE_MIN_NU).
WAVELENGTH_NM = 550.0
# Skew evidence (chi2 of s != 0) above which a curve may take the diffraction-included skew model: the skew
# weight 1 / (1 + O sqrt(n) exp(-chi2 / 2)) passes 1/2 at chi2 = 2 ln(O sqrt(n)) ~ 10.4 for n = 16.
WAVE_MIN_CHI2 = 2.0 * math.log(SKEW_PRIOR_ODDS * 4.0)
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
    skew : bool
        Also locate the maximum of a local skewed peak (a cubic in log height over the curve's core) and
        average it with the symmetric model by the evidence for skew, so an asymmetric curve (spherical
        aberration) gives its sharpest position, not its centre (docs/measurement.md "Asymmetric curves").
        False: the symmetric model alone (the behaviour before).
    tapered_width : bool
        The ``"otf"`` width from the smoothly weighted refit (:mod:`.otf_width`, independent of the scan's
        sampling phase). False: the main fit's width (3-4x cheaper; for noise-free model curves whose sampling
        error cancels in a ratio, as in :mod:`fieldcal.fit.width_window`).
    core_frac : float
        The local peak uses the contiguous run of points above this fraction of the height (above the floor).
    """

    min_frames: int = 5
    flat_ratio: float = 0.25
    flat_snr: float = 8.0
    multi_peak_prominence: float = 0.3
    edge_flank: float = 0.5
    window_frac: float = 0.15
    min_window: int = 6
    skew: bool = True
    tapered_width: bool = True
    core_frac: float = 0.3


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
    skew_weight: float = math.nan   # evidence weight of the skew correction (0: symmetric curve)
    stage_gain: float = math.nan    # best-focus sd per unit of independent per-frame stage-position noise
    z_centre_um: float = math.nan   # the symmetric model's centre and its sd (NaN when it did not fit)
    z_centre_sd_um: float = math.nan
    skew_shift_um: float = math.nan  # sharpest position minus the centre (local skewed peak) and its sd
    skew_shift_sd_um: float = math.nan
    # the same shift by the other estimator (the local skewed peak where the shift came from the spherical-aberration
    # model): their pooled difference is the skew shift's model error (:func:`pooled_skew_shift`)
    skew_alt_um: float = math.nan
    # Frame responses (per frame of the curve's z grid, µm per µm; None where not known): how the symmetric
    # centre, the skew shift and the best focus move when frame k was taken e_k away from where it is recorded.
    # Every tile's curve is sampled at the same frames, so a pooled value's frame error is the coherent sum of
    # its tiles' responses (:func:`frames_var_um2`), which pooling over tiles does not average.
    centre_resp: np.ndarray | None = field(default=None, compare=False, repr=False)
    skew_resp: np.ndarray | None = field(default=None, compare=False, repr=False)
    best_resp: np.ndarray | None = field(default=None, compare=False, repr=False)

    @classmethod
    def rejected(cls, status: str, peak: float = math.nan, floor: float = math.nan) -> "CurveFit":
        return cls(math.nan, math.nan, math.nan, peak, floor, status, 0)


def otf_model(z_um, a, z0_um, k, b, fs_cyc_per_mm):
    """The ``"otf"`` curve model (energy), for tests and plots."""
    x = math.pi * fs_cyc_per_mm * 1e-3 * k * (np.asarray(z_um, dtype=np.float64) - z0_um)
    return a * defocus_d(x) ** 2 + b


def peak_model(z_um, a, z0_um, w_um, p, b):
    """The ``"peak"`` curve model: Pearson VII, Lorentzian at p = 1, Gaussian ``exp(-t^2)`` as p grows."""
    t = (np.asarray(z_um, dtype=np.float64) - z0_um) / w_um
    return a / (1.0 + t * t / p) ** p + b


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
    v = np.asarray(values, dtype=np.float64)
    return analyse_curves(z_um, v.reshape(1, -1), model, fs_cyc_per_mm, q, rules)[0]


def second_peak_depth(v: np.ndarray) -> float:
    """Deepest dip below the lower of the highest points on its two sides: the prominence of a second peak.

    A 1-D curve has two peaks of prominence >= P (``scipy.signal.find_peaks(v, prominence=P)`` finds two)
    exactly when some point lies >= P below both the highest point on its left and on its right (checked on
    30 000 random curves without exact ties). Written out because importing scipy.signal (and the
    scipy.stats it pulls in) costs ~1 s, a fifth of a quick calibration.
    """
    v = np.asarray(v, dtype=np.float64)
    if v.size < 3:
        return -math.inf
    left = np.maximum.accumulate(v)
    right = np.maximum.accumulate(v[::-1])[::-1]
    return float(np.max(np.minimum(left[:-2], right[2:]) - v[1:-1]))


@dataclass
class _Pre:
    i_max: int
    lo: int
    hi: int
    floor: float
    height: float


def _precheck(z: np.ndarray, v: np.ndarray, rules: CurveRules) -> _Pre | CurveFit:
    """The tests that need no fit; returns a rejection or the fit window."""
    n = z.size
    if not np.all(np.isfinite(v)):
        return CurveFit.rejected("fit_failed")
    floor = float(np.partition(v, n // 10)[n // 10])  # ~10th percentile: robust to the peak
    i_max = int(np.argmax(v))
    height = float(v[i_max] - floor)
    sigma_n = noise_sigma(v)
    if not (height > rules.flat_ratio * abs(floor) and height > rules.flat_snr * sigma_n and height > 0.0):
        return CurveFit.rejected("flat", height, floor)
    # Peaks, counting a rise at either end as one (pad below the floor so an end counts as a peak).
    padded = np.concatenate([[min(floor, v[0]) - height], v, [min(floor, v[-1]) - height]])
    if second_peak_depth(padded) >= rules.multi_peak_prominence * height:
        return CurveFit.rejected("multi_peak", height, floor)
    if i_max == 0 or i_max == n - 1:
        return CurveFit.rejected("peak_outside_range", height, floor)
    flank = floor + rules.edge_flank * height
    if not (np.any(v[:i_max] < flank) and np.any(v[i_max + 1:] < flank)):
        return CurveFit.rejected("peak_at_edge", height, floor)
    lo, hi = _window(v, i_max, floor, height, rules)
    return _Pre(i_max, lo, hi, floor, height)


def _precheck_many(z: np.ndarray, V: np.ndarray, rules: CurveRules) -> list[_Pre | CurveFit]:
    """:func:`_precheck` of every row of ``V``, its arithmetic done for all rows at once (the same numbers: the
    same operations on the same values); only the fit window is found row by row. The per-row version cost
    ~60 µs a curve, most of the width-window correction's 11 000 model curves at 1080p standard."""
    T, n = V.shape
    finite = np.all(np.isfinite(V), axis=1)
    Vf = np.where(finite[:, None], V, 0.0)
    rows = np.arange(T)
    floor = np.partition(Vf, n // 10, axis=1)[:, n // 10]
    i_max = np.argmax(Vf, axis=1)
    height = Vf[rows, i_max] - floor
    if n >= 3:  # noise_sigma, row-wise
        d2 = Vf[:, 2:] - 2.0 * Vf[:, 1:-1] + Vf[:, :-2]
        sigma_n = 1.4826 * np.median(np.abs(d2 - np.median(d2, axis=1)[:, None]), axis=1) / math.sqrt(6.0)
    else:
        sigma_n = np.zeros(T)
    flat = ~((height > rules.flat_ratio * np.abs(floor)) & (height > rules.flat_snr * sigma_n) & (height > 0.0))
    # second_peak_depth of the curve padded below the floor at both ends, row-wise
    P = np.concatenate([(np.minimum(floor, Vf[:, 0]) - height)[:, None], Vf,
                        (np.minimum(floor, Vf[:, -1]) - height)[:, None]], axis=1)
    left = np.maximum.accumulate(P, axis=1)
    right = np.maximum.accumulate(P[:, ::-1], axis=1)[:, ::-1]
    multi = np.max(np.minimum(left[:, :-2], right[:, 2:]) - P[:, 1:-1], axis=1) >= rules.multi_peak_prominence * height
    at_end = (i_max == 0) | (i_max == n - 1)
    below = Vf < (floor + rules.edge_flank * height)[:, None]
    idx = np.arange(n)[None, :]
    flanked = np.any(below & (idx < i_max[:, None]), axis=1) & np.any(below & (idx > i_max[:, None]), axis=1)
    out: list[_Pre | CurveFit] = []
    for t in range(T):
        h, f = float(height[t]), float(floor[t])
        if not finite[t]:
            out.append(CurveFit.rejected("fit_failed"))
        elif flat[t]:
            out.append(CurveFit.rejected("flat", h, f))
        elif multi[t]:
            out.append(CurveFit.rejected("multi_peak", h, f))
        elif at_end[t]:
            out.append(CurveFit.rejected("peak_outside_range", h, f))
        elif not flanked[t]:
            out.append(CurveFit.rejected("peak_at_edge", h, f))
        else:
            lo, hi = _window(V[t], int(i_max[t]), f, h, rules)
            out.append(_Pre(int(i_max[t]), lo, hi, f, h))
    return out


def analyse_curves(z_um, values, model: str = "peak", fs_cyc_per_mm: float | None = None, q: float = 0.05,
                   rules: CurveRules | None = None, wavelength_nm: float = WAVELENGTH_NM) -> list[CurveFit]:
    """:func:`analyse_curve` for many curves on the same z grid (rows of ``values``), fitted together.

    All accepted curves are fitted at once by a batched Levenberg-Marquardt (one small normal-equation
    solve per curve per iteration, vectorised with numpy): thousands of tiles take a fraction of a second,
    where one ``scipy.optimize.least_squares`` call per curve costs milliseconds of overhead each.
    ``wavelength_nm``: the channel's, for the diffraction term of the ``"otf"`` skew model (strongly aberrated
    curves at high ``fs lambda N`` only, :data:`fieldcal.measure.spherical.WAVE_MIN_NU`).
    """
    rules = rules or CurveRules()
    if model not in ("peak", "otf"):
        raise ValueError(f"unknown curve model {model!r}")
    if model == "otf" and not (fs_cyc_per_mm is not None and fs_cyc_per_mm > 0):
        raise ValueError("the otf model needs fs_cyc_per_mm > 0")
    z = np.asarray(z_um, dtype=np.float64)
    V = np.atleast_2d(np.asarray(values, dtype=np.float64))
    T, n = V.shape
    if n != z.size:
        raise ValueError(f"{n} values per curve but {z.size} z positions")
    if n < rules.min_frames:
        return [CurveFit.rejected("too_few_frames") for _ in range(T)]
    if not (np.all(np.isfinite(z)) and np.all(np.diff(z) > 0)):
        raise ValueError("z positions must be finite and strictly increasing")
    out: list[CurveFit | None] = [None] * T
    step = float(np.median(np.diff(z)))
    pres: list[tuple[int, _Pre]] = []
    for t, r in enumerate(_precheck_many(z, V, rules)):
        if isinstance(r, CurveFit):
            out[t] = r
        else:
            pres.append((t, r))
    return _fit_curves(z, V, step, pres, out, model, fs_cyc_per_mm, q, rules, wavelength_nm)


def analyse_curve_list(curves, model: str = "peak", fs_cyc_per_mm: float | None = None, q: float = 0.05,
                       rules: CurveRules | None = None, wavelength_nm: float = WAVELENGTH_NM) -> list[CurveFit]:
    """:func:`analyse_curve` of each ``(z_um, values)`` pair of ``curves``, fitted together although the curves
    do not share a z grid (slanted-edge tracks: each has the frames where its edge was measured).

    Each curve keeps its own z, median step and window; the batched fits (:func:`_fit_batch`) pad the windows
    with zero weight, so each result equals :func:`analyse_curve` of that curve alone to round-off (the
    padding changes only the order of floating-point sums). One call per curve cost ~4 ms of per-call
    overhead at 1080p (1950 tracks: a quarter of the e-SFR calibration's CPU time)."""
    rules = rules or CurveRules()
    if model not in ("peak", "otf"):
        raise ValueError(f"unknown curve model {model!r}")
    if model == "otf" and not (fs_cyc_per_mm is not None and fs_cyc_per_mm > 0):
        raise ValueError("the otf model needs fs_cyc_per_mm > 0")
    zs, vs, steps = [], [], []
    out: list[CurveFit | None] = [None] * len(curves)
    pres: list[tuple[int, _Pre]] = []
    for t, (z_um, values) in enumerate(curves):
        z = np.asarray(z_um, dtype=np.float64)
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.size != z.size:
            raise ValueError(f"{v.size} values per curve but {z.size} z positions")
        zs.append(z)
        vs.append(v)
        steps.append(math.nan)
        if v.size < rules.min_frames:
            out[t] = CurveFit.rejected("too_few_frames")
            continue
        if not (np.all(np.isfinite(z)) and np.all(np.diff(z) > 0)):
            raise ValueError("z positions must be finite and strictly increasing")
        steps[t] = float(np.median(np.diff(z)))
        r = _precheck_many(z, v[None, :], rules)[0]
        if isinstance(r, CurveFit):
            out[t] = r
        else:
            pres.append((t, r))
    return _fit_curves(zs, vs, np.array(steps), pres, out, model, fs_cyc_per_mm, q, rules, wavelength_nm)


def _zt(z, t: int) -> np.ndarray:
    """Curve ``t``'s z positions: ``z`` itself (one grid) or its ``t``-th array (:func:`analyse_curve_list`)."""
    return z[t] if isinstance(z, list) else z


def _st(step, t: int) -> float:
    """Curve ``t``'s step: ``step`` itself (one grid) or its ``t``-th entry (:func:`analyse_curve_list`)."""
    return float(step[t]) if np.ndim(step) else step


def _fit_curves(z, V, step, pres, out, model, fs_cyc_per_mm, q, rules, wavelength_nm) -> list[CurveFit]:
    """The fits of :func:`analyse_curves` after the precheck: the windows ``pres`` fitted together, moved by
    their skew corrections (:func:`_finish`) and given their tapered widths. ``z``, ``V`` and ``step`` are one
    grid, a (T x n) array and a float, or one entry per curve (:func:`analyse_curve_list`)."""
    if pres:
        fits = _fit_batch(z, V, pres, step, model)
        x_q = disc_x_at_contrast(round(1.0 - q, 12)) if model == "otf" else math.nan
        sa = (_sa_corrections(z, V, pres, fits, step, fs_cyc_per_mm * 1e-3, wavelength_nm * 1e-3)
              if model == "otf" and rules.skew
              else [_LOCAL] * len(pres))
        # the second estimate of the skew shift (skew_model_sd_um) only where the pooled shift will apply: a set of
        # curves without evidence of skew (pooled weight < 1/2) gives it ~no weight, and saves the local fits
        shifts = [(c[0] * _st(step, t), math.sqrt(c[1]) * _st(step, t))
                  for (t, _), c in zip(pres, sa) if isinstance(c, tuple)]
        # one grid = one channel's tiles, pooled later; curves on their own grids (edge tracks,
        # analyse_curve_list) are each fitted as if alone
        check = not isinstance(z, list) and len(shifts) >= 2 and pooled_mean(*zip(*shifts))[2] >= 0.5
        for (t, pre), fit, corr in zip(pres, fits, sa):
            out[t] = _finish(_zt(z, t), V[t], pre, fit, _st(step, t), model, x_q, rules, corr, check)
        if model == "otf" and rules.tapered_width:  # the width from a fit that does not depend on where the samples fall
            from .otf_width import tapered_widths
            out = tapered_widths(z, V, pres, fits, step, x_q, out)
    return out  # type: ignore[return-value]


@dataclass
class _Local:
    u0: float        # maximum of the local skewed peak (steps from the sampled maximum)
    var_u0: float
    c3: float        # skew (cubic) coefficient and its variance
    var_c3: float


def _core(v: np.ndarray, pre: _Pre, rules: CurveRules) -> tuple[int, int] | None:
    """The contiguous run above ``core_frac`` of the height around the maximum, widened to >= 6 points."""
    thr = pre.floor + rules.core_frac * pre.height
    lo = hi = pre.i_max
    while lo > pre.lo and v[lo - 1] >= thr:
        lo -= 1
    while hi < pre.hi and v[hi + 1] >= thr:
        hi += 1
    while hi - lo + 1 < 6 and (lo > pre.lo or hi < pre.hi):  # >= 6 points: 2 dof for the cubic
        if lo > pre.lo:
            lo -= 1
        if hi - lo + 1 < 6 and hi < pre.hi:
            hi += 1
    return (lo, hi) if hi - lo + 1 >= 6 else None


def _local_peak(u: np.ndarray, e: np.ndarray, want_cov: bool = True) -> _Local | None:
    """Maximum of a skewed local peak: ``ln e`` (e = height above the floor, > 0) fitted with a cubic in u.

    Why this form: the sharpest position depends only on the curve near its top; ``ln`` of a Gaussian-like
    peak is a parabola and the cubic term is the lowest-order skew. Weighted by ``e`` (the sd of ``ln e`` under
    additive noise is ``noise / e``). The variance is the delta method through the root of the cubic's
    derivative with the coefficients' residual-scaled covariance, so it carries the skew's own uncertainty.
    """
    y, wt = np.log(e), e
    X = np.vander(u, 4, increasing=True) * wt[:, None]
    coef, *_ = np.linalg.lstsq(X, y * wt, rcond=None)
    c0, c1, c2, c3 = coef
    # maxima of the cubic: roots of c1 + 2 c2 u + 3 c3 u^2 with a negative second derivative
    if abs(c3) < 1e-12 * max(abs(c2), 1e-300):
        roots = np.array([-c1 / (2.0 * c2)]) if c2 != 0 else np.array([])
    else:
        disc = 4.0 * c2 * c2 - 12.0 * c3 * c1
        if disc < 0:
            return None
        sq = math.sqrt(disc)
        roots = np.array([(-2.0 * c2 + sq) / (6.0 * c3), (-2.0 * c2 - sq) / (6.0 * c3)])
    roots = roots[(2.0 * c2 + 6.0 * c3 * roots < 0) & (roots > u[0]) & (roots < u[-1])]
    if roots.size == 0:
        return None
    u0 = float(roots[np.argmin(np.abs(roots))])
    if not want_cov:
        return _Local(u0, math.nan, float(c3), math.nan)
    r = X @ coef - y * wt
    cov = np.linalg.pinv(X.T @ X) * max(float(r @ r), 1e-24) / (u.size - 4)
    grad = -np.array([0.0, 1.0, 2.0 * u0, 3.0 * u0 * u0]) / (2.0 * c2 + 6.0 * c3 * u0)
    var = float(grad @ cov @ grad)
    if not (math.isfinite(var) and var > 0.0):
        return None
    return _Local(u0, var, float(c3), float(cov[3, 3]))


def _skew_correction(z, v, pre: _Pre, fit, step, model, rules: CurveRules):
    """(du, var_du, w_skew): how far the curve's sharpest position lies from the symmetric fit's centre.

    The local skewed peak (:func:`_local_peak`) is fitted twice on the curve's core: to the data and to the
    symmetric fit's own values at the same points. The difference of the two maxima is the skew correction:
    the local fit's bias on a symmetric shape (``ln`` of a Pearson or an Airy-like curve is not exactly a
    cubic) is the same in both and cancels, so a curve the symmetric model describes gets exactly its centre.
    ``w_skew`` is the BIC weight of the extra skew parameter: the data's cubic coefficient against the
    symmetric fit's, ``w = 1 / (1 + O sqrt(n) exp(-chi2 / 2))``, ``chi2 = (c3 - c3_sym)^2 / var(c3)``, with
    prior odds ``O = SKEW_PRIOR_ODDS`` for a symmetric curve.
    """
    core = _core(v, pre, rules)
    if core is None:
        return None
    lo, hi = core
    u = (z[lo:hi + 1] - z[pre.i_max]) / step
    e = (v[lo:hi + 1] - pre.floor) / pre.height
    if fit is not None:
        free = np.ones(1)
        f_sym, _ = _model_eval(model, u[None, :], fit.params[None, :], free)
        e_sym = (f_sym[0] * fit.scale - pre.floor) / pre.height
        if np.any(e_sym <= 0):
            return None
    e = np.maximum(e, 1e-3)
    loc = _local_peak(u, e)
    if loc is None:
        return None
    if fit is None:
        return loc.u0, loc.var_u0, 1.0
    ref = _local_peak(u, e_sym, want_cov=False)
    if ref is None:
        return None
    chi2 = (loc.c3 - ref.c3) ** 2 / max(loc.var_c3, 1e-300)
    w_skew = 1.0 / (1.0 + SKEW_PRIOR_ODDS * math.sqrt(u.size) * math.exp(-0.5 * min(chi2, 1400.0)))
    return loc.u0 - ref.u0, loc.var_u0, w_skew


_LOCAL = "local"  # _finish: the skew correction from the local skewed peak (_skew_correction)


def _sa_corrections(z, V, pres, fits, step, fs_cyc_per_um: float = math.nan, wavelength_um: float = 0.55) -> list:
    """Skew corrections of band-pass curves from the spherical-aberration model (:mod:`.spherical`).

    Each curve whose symmetric ``"otf"`` fit succeeded is refitted on the same window with the skewed model
    ``a O(kappa (u - u0), s)^2 + b`` (started from the symmetric fit, s = 0). Per curve: ``(du, var_du, w)``
    with ``du`` = the skewed model's peak minus the symmetric centre, ``var_du`` the peak's variance (delta
    method through :func:`spherical.peak_u` with the residual-scaled covariance, so the uncertainty of s is in
    it), ``w = 1 / (1 + O sqrt(n) exp(-chi2 / 2))`` with ``chi2`` the drop in the residual sum of squares over
    the skewed fit's residual variance (the evidence for s != 0; prior odds O = SKEW_PRIOR_ODDS). None where
    the skewed fit fails or has < 2 degrees of freedom; ``_LOCAL`` (the local skewed peak) where the symmetric
    fit failed. Curves whose ray-model fit says they are strongly aberrated at a high ``nu = fs lambda N``
    (:data:`spherical.WAVE_MIN_NU`, :data:`spherical.WAVE_MIN_W040_WAVES`) are refitted from it with the exact
    (diffraction-included) model, whose peak they then use.
    """
    out: list = [_LOCAL if f is None else None for f in fits]
    idx = [j for j, f in enumerate(fits) if f is not None and f.n - 5 >= 2]
    if not idx:
        return out
    sub = [pres[j] for j in idx]
    p_init = [[fits[j].params[0], fits[j].params[1], fits[j].params[2], 0.0, fits[j].params[3]] for j in idx]
    sa = _fit_batch(z, V, sub, step, "otf_sa", p_init=p_init)
    ok = [k for k, f in enumerate(sa) if f is not None]
    if not ok:
        return out
    P = np.array([sa[k].params for k in ok])
    zk = [_zt(z, sub[k][0]) for k in ok]
    sk = np.array([_st(step, sub[k][0]) for k in ok])
    lo = np.array([(zr[sub[k][1].lo] - zr[sub[k][1].i_max]) / s for k, zr, s in zip(ok, zk, sk)])
    hi = np.array([(zr[sub[k][1].hi] - zr[sub[k][1].i_max]) / s for k, zr, s in zip(ok, zk, sk)])
    nu = spherical.wave_nu(P[:, 2], fs_cyc_per_um, sk if np.ndim(step) else step, wavelength_um)
    c_nu = nu * np.abs(P[:, 2])  # = pi fs^2 lambda step: nu moves with the fitted kappa (1/N)
    # evidence for the skew (chi2 of s != 0, as the weight below): a symmetric curve's noise-fitted s is no reason
    chi2 = np.array([max(fits[idx[k]].rss - sa[k].rss, 0.0) / max(sa[k].rss / (sa[k].n - 5), 1e-30) for k in ok])
    wave = (np.isfinite(nu) & (nu >= spherical.WAVE_MIN_NU) & (nu < 0.95) & (chi2 > WAVE_MIN_CHI2)
            & (np.abs(spherical.w040_waves(P[:, 3], nu)) >= spherical.WAVE_MIN_W040_WAVES))
    # the exact model's quadrature is chosen for the largest x of its batch: curves on their own z grids
    # (analyse_curve_list) are each their own batch there, as when analysed one by one
    wave_sets = [np.flatnonzero(wave)] if not isinstance(z, list) else [[i] for i in np.flatnonzero(wave)]
    for r in wave_sets if wave.any() else []:  # the ray model's fit is the exact model's start (rare: strongly
        wf = _fit_batch(z, V, [sub[ok[i]] for i in r], step, "otf_sa_wave",  # aberrated, high fs lambda N)
                        p_init=list(P[r]), nu=c_nu[r])
        for i, f in zip(r, wf):
            if f is None:
                wave[i] = False
            else:
                sa[ok[i]], P[i] = f, f.params
    sels = [(~wave, None)] + ([(wave, c_nu[wave])] if not isinstance(z, list) else
                              [(np.arange(wave.size) == i, c_nu[i:i + 1]) for i in np.flatnonzero(wave)])
    u_pk = np.empty(len(ok))
    grad = np.zeros((len(ok), 5))
    grad[:, 1] = 1.0  # d u_pk / d params: 0 for a and b, 1 for u0; kappa and s by central differences
    for sel, cn in sels:
        if not sel.any():
            continue
        fn = spherical.peak_u if cn is None else (
            lambda *q, u_start=None, cn=cn: spherical.wave_peak_u(*q, cn, u_start=u_start))
        Ps, ls, hs = P[sel], lo[sel], hi[sel]
        u_pk[sel] = fn(Ps[:, 0], Ps[:, 1], Ps[:, 2], Ps[:, 3], ls, hs)
        near = {} if cn is None else {"u_start": u_pk[sel]}  # the exact model: no grid again
        for i in (2, 3):
            h = 1e-4 * np.maximum(np.abs(Ps[:, i]), 1e-2)
            q = [Ps[:, c] for c in range(4)]
            q[i] = Ps[:, i] + h
            up = fn(*q, ls, hs, **near)
            q[i] = Ps[:, i] - h
            um = fn(*q, ls, hs, **near)
            grad[sel, i] = (up - um) / (2.0 * h)
    for r, k in enumerate(ok):
        j, f = idx[k], sa[k]
        var = float(grad[r] @ f.cov @ grad[r])
        if not (math.isfinite(u_pk[r]) and math.isfinite(var) and var > 0.0):
            continue
        s2 = max(f.rss / (f.n - 5), 1e-30)
        chi2 = max(fits[j].rss - f.rss, 0.0) / s2
        w = 1.0 / (1.0 + SKEW_PRIOR_ODDS * math.sqrt(f.n) * math.exp(-0.5 * min(chi2, 1400.0)))
        # the shift's frame response over the window: the skewed model's peak's (its gradient through the fit's
        # d params / d e) less the centre's; a common offset of every frame moves both alike (sum 0)
        k_win = sub[k][1].hi - sub[k][1].lo + 1
        resp = (grad[r] @ f.sens[:, :k_win] - fits[j].sens[1, :k_win]
                if f.sens is not None and fits[j].sens is not None else None)
        out[j] = (float(u_pk[r] - fits[j].params[1]), var, w, resp)
    return out


def _finish(z, v, pre: _Pre, fit, step, model, x_q, rules: CurveRules, corr=_LOCAL, check: bool = False) -> CurveFit:
    """The symmetric fit's centre, moved by the evidence-weighted skew correction to the sharpest position.

    Variance: the weighted mix of "no skew" (the symmetric fit's variance) and "skew" (the local peak's
    variance), plus the spread between the two positions: when the data cannot tell whether the curve is
    skewed, the difference between the centre and the sharpest position is part of the uncertainty (shape
    uncertainty), not hidden by picking one. A curve the symmetric models cannot fit at all uses the local
    peak alone.
    """
    if fit is not None and not (math.isfinite(fit.var_u0) and fit.var_u0 > 0.0):
        fit = None
    alt = math.nan
    if corr == _LOCAL or fit is None:
        corr = _skew_correction(z, v, pre, fit, step, model, rules) if rules.skew else None
    elif corr is not None and check:
        # the spherical-aberration model's shift: the local skewed peak's too, as a check of its model
        # (skew_model_sd_um)
        loc = _skew_correction(z, v, pre, fit, step, model, rules)
        alt = loc[0] * step if loc is not None else math.nan
    if fit is None and corr is None:
        return CurveFit.rejected("fit_failed", pre.height, pre.floor)
    # frame responses on the full grid (zeros outside the window): the centre's from the fit, the shift's from
    # the spherical-aberration model's (_sa_corrections; the local skewed peak's is not derived: None)
    k_win = pre.hi - pre.lo + 1
    c_resp = s_resp = None
    if fit is not None and fit.sens is not None:
        c_resp = np.zeros(z.size)
        c_resp[pre.lo:pre.hi + 1] = fit.sens[1, :k_win]
    if corr is not None and len(corr) > 3 and corr[3] is not None:
        s_resp = np.zeros(z.size)
        s_resp[pre.lo:pre.hi + 1] = corr[3]
    if fit is None:
        u_mean, var_u, w_skew = corr[0], corr[1], 1.0
    elif corr is None:
        u_mean, var_u, w_skew = float(fit.params[1]), fit.var_u0, (0.0 if rules.skew else math.nan)
    else:
        du, var_du, w_skew = corr[:3]
        u_s = float(fit.params[1])
        u_mean = u_s + w_skew * du
        var_u = (w_skew * (var_du + (u_s + du - u_mean) ** 2) + (1.0 - w_skew) * (fit.var_u0 + (u_s - u_mean) ** 2))
    z0 = z[pre.i_max] + u_mean * step
    # Never extrapolate: the fitted peak must lie inside the window with a sample beyond it on each side.
    if not (z[1] <= z0 <= z[-2]) or not (z[pre.lo] < z0 < z[pre.hi]):
        return CurveFit.rejected("peak_at_edge", pre.height, pre.floor)
    shift = (corr[0] * step, math.sqrt(corr[1]) * step, alt) if corr is not None else (math.nan, math.nan, alt)
    if fit is None:
        return CurveFit(float(z0), float(math.sqrt(var_u) * step), math.nan, float(pre.height), float(pre.floor),
                        STATUS_OK, int(pre.hi - pre.lo + 1), w_skew, math.nan, math.nan, math.nan, *shift)
    width = x_q / fit.params[2] * step if model == "otf" else math.nan
    best = (c_resp if corr is None or not w_skew > 0 else
            (c_resp + w_skew * s_resp if c_resp is not None and s_resp is not None else None))
    return CurveFit(float(z0), float(math.sqrt(var_u) * step), float(width), float(fit.params[0] * fit.scale),
                    float(fit.params[-1] * fit.scale), STATUS_OK, int(pre.hi - pre.lo + 1), w_skew,
                    fit.stage_gain, float(z[pre.i_max] + fit.params[1] * step), float(math.sqrt(fit.var_u0) * step),
                    *shift, c_resp, s_resp, best)


def pooled_skew_shift(fits: list[CurveFit], repeatability_um: float = 0.0) -> tuple[float, float, float]:
    """(shift, sd, weight): the skew correction shared by a set of curves (the tiles of one channel).

    Why pool: a lens's spherical aberration skews every tile's curve the same way, while a tile that spans a
    steep field-curvature gradient holds a *mixture* of peaks whose mode is not the average of its local foci
    (what a tile should report) — a per-tile skew correction followed those mixtures and doubled the tile
    scatter on simulated lenses at coarse steps. The inverse-variance mean of the per-tile shifts (its sd
    Birge-inflated by their scatter) is applied to every tile, with the evidence weight
    ``1 / (1 + O sqrt(N) exp(-chi2 / 2))``, ``chi2 = (mean / sd)^2``: a lens whose curves are skewed the same
    way everywhere gets its sharpest positions; scattered, sign-changing shifts average out.

    ``repeatability_um``: the stage's; the sd (and so the evidence) takes the frames' share of the pooled shift
    (:func:`pooled_skew`), one draw for every curve that pooling over tiles does not average.
    """
    return pooled_skew(fits, repeatability_um)[:3]


def pooled_skew(fits: list[CurveFit], repeatability_um: float = 0.0):
    """(shift, sd, weight, frame response, frames' sd): :func:`pooled_skew_shift` with the pooled shift's
    response to the frames' position errors (per frame, µm per µm: the tiles' skew-shift responses
    :attr:`CurveFit.skew_resp` summed with the pooling's own weights, :func:`pooled_coefficients`) and the sd
    that puts in it at the stage's repeatability (:func:`frames_var_um2`), which is in ``sd``.

    Why frame by frame: every tile's curve is sampled at the same frames, so one pattern of position errors
    makes every tile's curve look skewed the same way, which the pooled shift keeps in full and its evidence,
    which takes the tiles as independent, read as a real skew (random lens 14 of the band benchmark, symmetric
    curves, repeatability 0.48 µm: -0.44 µm at weight 1; with the true frame positions -0.06 µm at 0.02). A
    bound on that share (each tile's whole stage gain, session 13's trial) also swamped real small skews;
    the coherent sum is the share itself: a real skew that the frames cannot make reads as evidence, a
    frame pattern does not.
    """
    ok = [f for f in fits if f.status == STATUS_OK]
    d = np.array([f.skew_shift_um for f in ok], dtype=np.float64)
    sd = np.array([f.skew_shift_sd_um for f in ok], dtype=np.float64)
    mean, se, weight, a = _pooled(d, sd)
    resp = frames_response(a, [f.skew_resp for f in ok])
    v = frames_var_um2(resp, repeatability_um)
    if v > 0 and se > 0:
        se = math.sqrt(se * se + v)
        weight = evidence_weight(mean, se, int(np.count_nonzero(a)))
    return mean, se, weight, resp, math.sqrt(v)


def frames_response(a, resps) -> np.ndarray | None:
    """``sum_i a_i resp_i``: a pooled value's response to the frames' position errors (per frame, µm per µm),
    from its values' responses ``resps`` (arrays on one z grid; None: not known, counted as 0) and the pooling's
    linear weights ``a`` (:func:`pooled_coefficients`). None when no value has one, or when the values' curves
    are not on one z grid (curves on their own grids, :func:`analyse_curve_list`, share no frames by index)."""
    out = None
    for ai, r in zip(a, resps):
        if r is None or not ai:
            continue
        if out is not None and r.shape != out.shape:
            return None
        out = ai * r if out is None else out + ai * r
    return out


def frames_var_um2(resp, repeatability_um: float) -> float:
    """Variance (µm²) of a value whose frame response is ``resp`` (:func:`frames_response`) when each frame's
    position has an independent error of sd ``repeatability_um``: ``r^2 |resp|^2``. (A common offset or a
    scale error of every frame is the stage's own zero and scale, which the profile is relative to: fit/stage.py.)"""
    r = float(repeatability_um or 0.0)
    if resp is None or not (r > 0 and math.isfinite(r)):
        return 0.0
    v = r * r * float(np.sum(np.square(resp)))
    return v if math.isfinite(v) else 0.0


def skew_model_sd_um(fits: list[CurveFit]) -> float:
    """Model error (µm) of a set of curves' pooled skew shift, shared by all of them: how far the two estimators of
    the sharpest position disagree, pooled over the curves that have both.

    The shift comes from the spherical-aberration model fitted over the curve's window (:func:`_sa_corrections`);
    the local skewed peak (a cubic in ln height over the core, :func:`_local_peak`) assumes another shape and
    uses other points. Each would be unbiased on a curve its model describes; a real pupil is neither, and their
    disagreement is the size of the model error that no scatter over tiles can show (every tile has the same
    curve shape, so the error is the same in every tile). ``sqrt(max(D^2 - se^2, 0))`` with D the pooled mean of
    the per-curve differences and se its sd (the part of D that is noise). 0 where no curve has both.
    """
    d = np.array([f.skew_shift_um - f.skew_alt_um for f in fits if f.status == STATUS_OK], dtype=np.float64)
    sd = np.array([f.skew_shift_sd_um for f in fits if f.status == STATUS_OK], dtype=np.float64)
    mean, se, _ = pooled_mean(d, sd)
    return math.sqrt(max(mean * mean - se * se, 0.0))


# Huber's tuning constant (95 % efficiency on normal data) and the least count for the robust pooled mean; below
# it the MAD scale is too coarse and :func:`pooled_mean` is the plain inverse-variance mean.
HUBER_C = 1.345
ROBUST_MIN_N = 6


def pooled_mean(d, sd, robust: bool = True) -> tuple[float, float, float]:
    """(mean, sd, weight) of per-tile values ``d`` with sds ``sd`` that share one value over a channel: the
    inverse-variance Huber M-estimate of the mean, its sd from the same fit with the standardised residuals'
    robust scale (never below the stated sds: Birge-style), and the evidence weight for a non-zero mean
    ``1 / (1 + O sqrt(N) exp(-chi2 / 2))``, ``chi2 = (mean / sd)^2``, prior odds O = SKEW_PRIOR_ODDS.

    Why robust: a tile's sd is a delta-method or curve-fit sd, and on a few tiles it is far too small (a skewed
    fit whose peak barely moves with its parameters). With plain inverse-variance weights such a tile outweighs
    the rest: on an F/6.9 lens (W040 0.8 waves) one band-pass tile at +2.7 ± 0.5 µm among 58 at -1.1 ± 1.9 µm
    pulled the pooled skew shift to -0.3 µm (its evidence weight to 0.02), so the curves kept their centres
    1.4 µm above the sharpest position; and outlying tiles inflated the Birge ratio of the sml@fs offset. The
    Huber weights ``min(1, c / |r / s|)`` (r = (d - mean) / sd, s = max(1, 1.4826 MAD(r)), c = :data:`HUBER_C`)
    leave normal data as they are (95 % efficiency) and bound any one tile's pull. The sd is the M-estimator's
    sandwich ``s^2 sum(w psi^2) / (sum(w psi'))^2 x n / (n - 1)`` (``psi`` Huber's, of r / s), at least
    ``1 / sum(w)``: it takes the spread from the values themselves, as the Birge ratio does, but tile by tile, so
    a heavy tile whose sd is too small widens it (the premise: the stated sds are not all right); on normal data
    with right sds it is the Birge-inflated sd within its noise. ``robust=False``: the plain
    inverse-variance mean, Birge-inflated.
    """
    return _pooled(d, sd, robust)[:3]


def pooled_coefficients(d, sd, robust: bool = True) -> np.ndarray:
    """The linear weights ``a`` (summing to 1, one per value of ``d``; 0 for values left out) with which
    :func:`pooled_mean`'s mean is ``sum a_i d_i`` at its solution (the Huber weights held fixed): what a common
    change of every value's estimator moves the pooled mean by (:func:`frames_var_um2`)."""
    return _pooled(d, sd, robust)[3]


def _pooled(d, sd, robust: bool = True) -> tuple[float, float, float, np.ndarray]:
    """:func:`pooled_mean` and :func:`pooled_coefficients` together."""
    d, sd = np.asarray(d, dtype=np.float64), np.asarray(sd, dtype=np.float64)
    ok = np.isfinite(d) & np.isfinite(sd) & (sd > 0)
    a = np.zeros(d.shape)
    if ok.sum() < 2:
        return 0.0, 0.0, 0.0, a
    d, sd = d[ok], sd[ok]
    w = 1.0 / sd ** 2
    mean = float(np.sum(w * d) / np.sum(w))
    n = d.size
    if n < ROBUST_MIN_N or not robust:
        birge = max(1.0, float(np.sum(w * (d - mean) ** 2)) / (n - 1))
        se = math.sqrt(birge / float(np.sum(w)))
        a[ok] = w / np.sum(w)
        return mean, se, evidence_weight(mean, se, n), a
    scale = max(1.0, 1.4826 * float(np.median(np.abs(d - np.median(d)) / sd)))
    for _ in range(50):
        u = (d - mean) / (sd * scale)
        h = np.minimum(1.0, HUBER_C / np.maximum(np.abs(u), 1e-12))
        new = float(np.sum(h * w * d) / np.sum(h * w))
        if abs(new - mean) <= 1e-10 * (1.0 + abs(mean)):
            mean = new
            break
        mean = new
    u = (d - mean) / (sd * scale)
    h = np.minimum(1.0, HUBER_C / np.maximum(np.abs(u), 1e-12))
    a[ok] = h * w / np.sum(h * w)
    psi = np.clip(u, -HUBER_C, HUBER_C)
    inside = max(float(np.sum(w * (np.abs(u) < HUBER_C))), float(np.min(w)))
    sandwich = scale ** 2 * float(np.sum(w * psi ** 2)) / inside ** 2 * n / (n - 1)
    se = math.sqrt(max(sandwich, 1.0 / float(np.sum(w))))
    return mean, se, evidence_weight(mean, se, n), a


def evidence_weight(mean: float, se: float, n: int) -> float:
    """Posterior weight of "non-zero" for a pooled value ``mean`` ± ``se`` over ``n`` values:
    ``1 / (1 + O sqrt(n) exp(-chi2 / 2))``, ``chi2 = (mean / se)^2``, prior odds O = SKEW_PRIOR_ODDS."""
    chi2 = (mean / se) ** 2 if se > 0 else (math.inf if mean else 0.0)
    return 1.0 / (1.0 + SKEW_PRIOR_ODDS * math.sqrt(max(n, 1)) * math.exp(-0.5 * min(chi2, 1400.0)))


def apply_pooled_skew(fits: list[CurveFit], apply: bool = True, weight: float | None = None,
                      repeatability_um: float = 0.0) -> tuple[list[CurveFit], dict]:
    """Every accepted curve's best focus = its symmetric centre + the pooled skew shift (evidence-weighted);
    its variance adds the pooled shift's. Curves without a symmetric centre keep their own estimate.

    ``apply=False``: the centre alone (the shift is still measured and returned, for the record). ``weight``: the
    evidence weight to use instead of these curves' own (the side bands of :func:`band_frequency_terms` take
    the largest of the three bands': one pupil's spherical aberration skews them all). ``repeatability_um``: the
    stage's, whose frame errors move every curve's skew at once (:func:`pooled_skew`: in the shift's sd and
    evidence; ``frames_sd_um`` in the record).
    """
    from dataclasses import replace as _replace
    mean, se, own, resp, frames_sd = pooled_skew(fits, repeatability_um)
    model = skew_model_sd_um(fits)
    weight = own if weight is None else float(weight)
    info = {"shift_um": mean, "sd_um": se, "model_sd_um": model, "weight": weight, "applied": bool(apply),
            "frames_sd_um": frames_sd, "_frame_resp": resp}
    if not apply:
        weight = 0.0
    out = []
    for f in fits:
        if f.status != STATUS_OK or not math.isfinite(f.z_centre_um):
            out.append(f)
            continue
        var = (f.z_centre_sd_um ** 2 + weight * (se * se + model * model)
               + weight * (1.0 - weight) * mean * mean)
        best = f.centre_resp
        if best is not None and weight and resp is not None:
            best = best + weight * resp
        out.append(_replace(f, z_best_um=f.z_centre_um + weight * mean, z_sigma_um=math.sqrt(var),
                            skew_weight=weight, best_resp=best))
    return out, info


# Zones of field radius the sml@fs offset's tiles are split into for its delete-a-zone jackknife (equal counts).
OFFSET_ZONES = 5


def zone_jackknife_sd(d, sd, zone_key) -> float:
    """sd of :func:`pooled_mean` of ``d`` by a delete-a-group jackknife over :data:`OFFSET_ZONES` groups of
    equal count along ``zone_key`` (e.g. the tiles' field radius); 0 with too few values.

    Why: the pooled mean's own sd takes the per-tile values' scatter as independent noise (1/sqrt(n)). The SML's
    offset from the band-pass at fs changes smoothly over the field (the other aberrations change the curves'
    shapes with field height), so neighbouring tiles share their deviations and the mean of a field with another
    balance of radii (the surface's, where the offset is applied) differs by more: leaving out a whole zone at a
    time measures that.
    """
    d, sd, key = (np.asarray(a, dtype=np.float64) for a in (d, sd, zone_key))
    ok = np.isfinite(d) & np.isfinite(sd) & (sd > 0) & np.isfinite(key)
    d, sd, key = d[ok], sd[ok], key[ok]
    k = OFFSET_ZONES
    if d.size < 2 * k:
        return 0.0
    zone = np.minimum((np.argsort(np.argsort(key)) * k) // d.size, k - 1)
    # the plain mean: the jackknife measures how the field's zones move it (structure), not outlying tiles
    loo = np.array([pooled_mean(d[zone != j], sd[zone != j], robust=False)[0] for j in range(k)])
    return float(math.sqrt((k - 1) / k * np.sum((loo - loo.mean()) ** 2)))


def pooled_skew_var_um2(info: dict, frames: bool = True) -> float:
    """Variance (µm²) an :func:`apply_pooled_skew` record adds to every one of its curves' best foci:
    ``w (sd^2 + model^2) + w (1 - w) shift^2`` (the pooled shift's own sd, its model error
    :func:`skew_model_sd_um`, and whether it applies at all). It is one draw shared by all those curves, not
    noise of each. ``frames=False``: without the frames' share of the sd (``frames_sd_um``), for a caller that
    carries the frames' response itself (:func:`apply_measure_offset`)."""
    w, m, se, mod = (float(info.get(k, 0.0) or 0.0) for k in ("weight", "shift_um", "sd_um", "model_sd_um"))
    fr = float(info.get("frames_sd_um", 0.0) or 0.0)
    if not all(math.isfinite(v) for v in (w, m, se, mod, fr)):
        return 0.0
    if not frames:
        se = math.sqrt(max(se * se - fr * fr, 0.0))
    return max(w * (se * se + mod * mod) + w * (1.0 - w) * m * m, 0.0)


def apply_measure_offset(main: list[CurveFit], ref: list[CurveFit], radius=None,
                         ref_skew: dict | None = None, repeatability_um: float = 0.0) -> tuple[list[CurveFit], dict]:
    """``main``'s best foci moved by the channel's pooled offset to ``ref`` (same tiles, in order).

    For the SML moved to the band-pass at fs (``measure="auto"``): the SML's broad band gives the lower tile
    noise, the band-pass at fs the paper's definition of best focus. Where the through-focus curves are
    symmetric the two peak together and the offset's evidence weight is ~0; spherical aberration skews the
    curves and moves them apart by the same amount over a channel (docs/measurement.md "Asymmetric curves").
    The offset is :func:`pooled_mean` of the per-tile differences (sd from both fits' sds); its error
    (:func:`offset_sd_um`) is shared by the channel's tiles and is not added to theirs (:func:`shift_by_offset`).
    With the tiles' field ``radius`` (same order), its sd is at least the delete-a-zone jackknife's
    (:func:`zone_jackknife_sd`): the offset changes over the field, so its tiles are not independent draws.

    ``ref_skew``: the :func:`apply_pooled_skew` record of ``ref`` (the band-pass curves' pooled skew shift).
    Two things follow from it, both because one pupil's spherical aberration skews every tile the same way:

    * its variance (:func:`pooled_skew_var_um2`) is one error shared by every ``ref`` best focus, so it is taken
      out of the tiles' sds before pooling (where 1/sqrt(n) would average it away: lens 13 of the band
      benchmark, F/6.9, B's shift applied at weight 0.1 left +1.9 µm on 27 tiles while the offset stated 0.35)
      and added to the pooled offset's sd after;
    * its evidence weight is evidence for the offset too: the SML (broad band) and the band-pass at fs peak
      together only on symmetric curves, so curves measured skewed say the offset is real even where its own
      chi2 is weak. The offset applies with the larger of the two weights (the skew's only where it is >= 1/2:
      the evidence favours skew). (Before, an offset of -0.3 to -0.45
      µm at 2-3 sd was applied at weight 0.09-0.5 on F/1.6-1.9 lenses whose band-pass curves were skewed at
      weight 1, and the unapplied part, 0.15-0.37 µm, was 1.5-3x the sd stated for it.)
    * the converse (:func:`_skew_from_offset`): an offset between the SML and the band-pass curves' centres is
      evidence that those curves are skewed, so the band-pass skew shift applies with that evidence where it is
      the larger (>= 1/2), before the offset is pooled.

    ``repeatability_um``: the stage's. The two measures weigh the frames differently (other bands, windows and
    shapes), so one pattern of frame errors moves them apart in every tile at once; the pooled offset's frame
    response (the tiles' best-focus responses :attr:`CurveFit.best_resp`, the band-pass skew shift's included,
    summed with the pooling's weights) puts ``r^2 |resp|^2`` in its sd and evidence (``offset_frames_sd_um``;
    :func:`pooled_skew`), in place of the skew shift's own frames' share, which it contains.
    """
    keep = [i for i, (a, b) in enumerate(zip(main, ref)) if a.status == STATUS_OK and b.status == STATUS_OK]
    lifted = None
    if ref_skew and len(keep) >= 2:
        ref, ref_skew, lifted = _skew_from_offset(main, ref, ref_skew, keep, repeatability_um)
    shared2 = pooled_skew_var_um2(ref_skew or {})
    d = np.array([ref[i].z_best_um - main[i].z_best_um for i in keep])
    sd = np.array([math.sqrt(main[i].z_sigma_um ** 2 + max(ref[i].z_sigma_um ** 2 - shared2, 0.0)) for i in keep])
    mean, se, weight, a = _pooled(d, sd)
    resp = frames_response(a, [_diff_resp(ref[i].best_resp, main[i].best_resp) for i in keep])
    frames2 = frames_var_um2(resp, repeatability_um)
    info = {"offset_um": mean, "offset_sd_um": se, "offset_weight": weight, "n_tiles": len(keep)}
    if radius is not None and len(keep):
        # the offset varies over the field: its error as the zones of field radius tell it, when larger
        jk = zone_jackknife_sd(d, sd, np.asarray(radius, dtype=np.float64)[keep])
        info.update(offset_zone_sd_um=jk, offset_sd_um=max(se, jk))
    if frames2 > 0 and len(keep) >= 2:
        # one pattern of frame errors moves the two measures apart in every tile at once (pooled_skew)
        info.update(offset_frames_sd_um=math.sqrt(frames2), _frame_resp=resp)
        if not ref_skew:
            info.update(offset_sd_um=math.sqrt(info["offset_sd_um"] ** 2 + frames2),
                        offset_weight=evidence_weight(mean, math.sqrt(se * se + frames2), len(keep)))
    if len(keep) >= 2 and ref_skew:
        # the skew shift's frames' share is in the offset's own frame response (with its sign): not twice
        se = math.sqrt(info["offset_sd_um"] ** 2 + pooled_skew_var_um2(ref_skew, frames=False) + frames2)
        own = evidence_weight(mean, se, len(keep))  # the offset's own evidence, against its whole sd
        # curves measured skewed (weight >= 1/2: the evidence favours it) make the offset real; below that the
        # offset's own evidence decides, so symmetric curves keep their weight and band exactly
        asym = float(ref_skew.get("weight", 0.0) or 0.0)
        asym = asym if math.isfinite(asym) and asym >= 0.5 else 0.0
        info.update(offset_sd_um=se, offset_skew_sd_um=math.sqrt(shared2), offset_own_weight=own,
                    offset_weight=max(own, asym))
    if lifted is not None:
        # the band-pass skew now applied (measure.tiles records it under these keys before the offset's)
        info.update(bp_skew_weight=ref_skew["weight"], bp_skew_from_offset_weight=lifted)
    return shift_by_offset(main, info), info


def _diff_resp(a, b):
    """Frame response of a difference of two estimates (None where either is not known)."""
    return None if a is None or b is None else a - b


def _skew_from_offset(main: list[CurveFit], ref: list[CurveFit], ref_skew: dict, keep: list[int],
                      repeatability_um: float = 0.0):
    """(ref, ref_skew, w_offset or None): ``ref``'s pooled skew shift applied with the evidence weight of the
    offset between ``ref``'s symmetric *centres* and ``main``'s best foci where that is the larger (>= 1/2).

    Why: for a pupil with defocus alone the MTF at every frequency is symmetric about one focus, so the SML (a
    broad band) and the band-pass at fs peak together and every through-focus curve is symmetric. An SML that
    peaks apart from the band-pass's centres (the evidence weight of their pooled difference, as
    :func:`pooled_mean`) is evidence that the pupil is aberrated and the band-pass curves are skewed, whatever
    their own skew test says: on an F/6.9 lens (W040 0.8 waves, 54 µm steps) the offset was 6.3 µm at 17 sd while
    the band-pass curves' own skew evidence was 0.02-0.3 (the skew is a small part of a wide curve), so they kept
    their centres, 1.4-1.8 µm above the sharpest position, with a band of 0.5 µm. The converse (skew is evidence
    for the offset) is applied below in :func:`apply_measure_offset`. None when the own weight is already the
    larger.
    """
    w_now = float(ref_skew.get("weight", 0.0) or 0.0)
    d = [ref[i].z_centre_um - main[i].z_best_um for i in keep]
    sd = [math.hypot(ref[i].z_centre_sd_um, main[i].z_sigma_um) for i in keep]
    mean, se, w_off, a = _pooled(d, sd)  # (curves without a symmetric centre: NaN, left out)
    # the frames move the centres and the other measure apart in every tile at once (apply_measure_offset)
    frames2 = frames_var_um2(frames_response(a, [_diff_resp(ref[i].centre_resp, main[i].best_resp) for i in keep]),
                             repeatability_um)
    if frames2 > 0 and se > 0:
        w_off = evidence_weight(mean, math.sqrt(se * se + frames2), int(np.count_nonzero(a)))
    if not (w_off >= 0.5 and w_off > w_now):
        return ref, ref_skew, None
    out, info = apply_pooled_skew(ref, apply=bool(ref_skew.get("applied", True)), weight=w_off,
                                  repeatability_um=repeatability_um)
    return out, info, w_off


def shift_by_offset(main: list[CurveFit], info: dict) -> list[CurveFit]:
    """``main``'s accepted best foci moved by ``weight x offset`` of an :func:`apply_measure_offset` record
    (measured on these tiles or on others: quick effort's strip, :mod:`fieldcal.measure.fs_strip`).

    The tiles' sds are left as they are: the offset's error (:func:`offset_sd_um`) is one draw shared by every
    tile of the channel, which a fit that took it as each tile's own noise would average away; it joins the
    band as a field-wide term (``calibration.measure_offset_sd_um``, docs/fitting.md).
    """
    from dataclasses import replace as _replace
    w = float(info.get("offset_weight", 0.0))
    shift = w * float(info.get("offset_um", 0.0))
    resp = info.get("_frame_resp")  # the offset's frame response moves the best foci's too
    return [f if f.status != STATUS_OK else
            _replace(f, z_best_um=f.z_best_um + shift,
                     best_resp=(f.best_resp + w * resp if f.best_resp is not None and resp is not None and w
                                else f.best_resp))
            for f in main]


def offset_sd_um(info: dict) -> float:
    """1-sigma error of an applied ``weight x offset`` (µm): ``sqrt(w sd^2 + w (1 - w) mean^2)``, the offset's
    own uncertainty and whether it applies at all (evidence weight w)."""
    mean, se, weight = (float(info.get(k, 0.0)) for k in ("offset_um", "offset_sd_um", "offset_weight"))
    return math.sqrt(max(weight * se * se + weight * (1.0 - weight) * mean * mean, 0.0))


def _model_eval(model: str, u: np.ndarray, p: np.ndarray, free_p: np.ndarray):
    """Model values (T x n) and Jacobian (T x n x P) for parameter rows p (T x P)."""
    if model == "otf_sa":
        return spherical.model(u, *(p[:, i:i + 1] for i in range(5)))
    if model == "otf_sa_wave":  # free_p carries each curve's nu kappa = pi fs^2 lambda step (a constant)
        return spherical.wave_model(u, *(p[:, i:i + 1] for i in range(5)), free_p)
    if model == "otf":
        a, u0, kappa, b = (p[:, i:i + 1] for i in range(4))
        du = u - u0
        x = kappa * du
        d = defocus_d(x)
        dd = defocus_d_prime(x)
        f = a * d * d + b
        J = np.stack([d * d, -2.0 * a * d * dd * kappa, 2.0 * a * d * dd * du, np.ones_like(u)], axis=2)
        return f, J
    a, u0, w, pw, b = (p[:, i:i + 1] for i in range(5))
    t = (u - u0) / w
    L = 1.0 + t * t / pw
    lp = L ** -pw
    common = 2.0 * a * t * lp / L / w
    dpw = a * lp * (t * t / (pw * L) - np.log(L)) * free_p[:, None]
    f = a * lp + b
    J = np.stack([lp, common, common * t, dpw, np.ones_like(u)], axis=2)
    return f, J


def _fit_batch(z, V, pres, step, model, n_iter: int = 100, p_init: list | None = None,
               weights: list | None = None, nu=None):
    """Batched Levenberg-Marquardt over the windows of ``pres``; a :class:`_Fit` or None for each.

    Coordinates are normalised (u in steps from the sampled maximum, values / the maximum); the covariance
    is ``(J^T J)^-1`` scaled by the residual variance. ``p_init``: starting parameters per window (normalised
    coordinates), instead of the guesses from the data. ``weights``: per window, a weight per sample of the
    window on the residuals (default 1). ``nu``: per window, the ``"otf_sa_wave"`` model's ``c_nu``. ``z``,
    ``V``, ``step``: one grid (an array, a (T x n) array, a float) or each curve its own (lists and an array of
    steps, indexed by the windows' curve numbers: :func:`analyse_curve_list`).
    """
    T = len(pres)
    nmax = max(p.hi - p.lo + 1 for _, p in pres)
    u = np.zeros((T, nmax))
    y = np.zeros((T, nmax))
    w = np.zeros((T, nmax))
    scale = np.empty(T)
    p0 = []
    free_p = np.zeros(T) if nu is None else np.asarray(nu, dtype=np.float64)  # otf_sa_wave: nu per curve
    for j, (t, pre) in enumerate(pres):
        k = pre.hi - pre.lo + 1
        vt, zt, st = V[t], _zt(z, t), _st(step, t)  # one grid, or each curve its own (analyse_curve_list)
        sc = float(vt[pre.i_max])
        scale[j] = sc
        u[j, :k] = (zt[pre.lo:pre.hi + 1] - zt[pre.i_max]) / st
        u[j, k:] = u[j, k - 1]
        y[j, :k] = vt[pre.lo:pre.hi + 1] / sc
        w[j, :k] = 1.0 if weights is None else weights[j]
        hw = _half_width_units(vt, pre.i_max, pre.floor, pre.height, st, zt)
        a0, b0 = pre.height / sc, max(pre.floor / sc, 0.0)
        if p_init is not None:
            p0.append(list(p_init[j]))
        elif model == "otf":
            p0.append([a0, 0.0, _X_HALF_ENERGY / hw, b0])
        else:
            free_p[j] = 1.0 if k >= 8 else 0.0  # the shape exponent only when the window can support it
            p0.append([a0, 0.0, hw, 1.0, b0])
    p = np.array(p0, dtype=np.float64)
    P = p.shape[1]
    eye = np.eye(P)
    with np.errstate(all="ignore"):
        f, J = _model_eval(model, u, p, free_p)
        r = (f - y) * w
        cost = np.sum(r * r, axis=1)
        lam = np.full(T, 1e-3)
        a = np.arange(T)  # the curves still iterating: a converged curve's state no longer changes, so only
        for _ in range(n_iter):  # these are evaluated (a batch costs its curves' own iterations, not T x the most)
            Jw = J[a] * w[a, :, None]
            JtJ = np.einsum("tnp,tnq->tpq", Jw, Jw)
            g = np.einsum("tnp,tn->tp", Jw, r[a])
            dg = np.maximum(np.einsum("tpp->tp", JtJ), 1e-12)
            A = JtJ + (lam[a, None] * dg)[:, :, None] * eye + 1e-12 * eye
            pn = p[a] - _solve_spd(A, g)
            if model == "otf_sa_wave":  # its quadrature is chosen for the batch's largest x: every curve, as before
                p_all = p.copy()
                p_all[a] = pn
                fn, Jn = (v[a] for v in _model_eval(model, u, p_all, free_p))
            else:
                fn, Jn = _model_eval(model, u[a], pn, free_p[a])
            rn = (fn - y[a]) * w[a]
            cn = np.sum(rn * rn, axis=1)
            ca = cost[a]
            better = np.isfinite(cn) & (cn < ca) & np.all(np.isfinite(pn), axis=1)
            rel = np.where(better, (ca - cn) / np.maximum(ca, 1e-300), 0.0)
            b = a[better]
            p[b], r[b], J[b], cost[b] = pn[better], rn[better], Jn[better], cn[better]
            lam_a = np.where(better, np.maximum(lam[a] / 3.0, 1e-9), np.minimum(lam[a] * 4.0, 1e9))
            lam[a] = lam_a
            a = a[~((better & (rel < 1e-10)) | (lam_a >= 1e9))]
            if not a.size:
                break
        Jw = J * w[:, :, None]
        JtJ = np.einsum("tnp,tnq->tpq", Jw, Jw)
        if model == "peak":  # a fixed exponent: its (zero) column must not make the system singular
            JtJ[:, 3, 3] += 1.0 - free_p
        cov = np.linalg.pinv(JtJ, rcond=1e-13)
        # conditioning of the parameters that matter (a nearly Gaussian peak leaves p poorly determined,
        # which does not affect z0)
        keep = [i for i in range(P) if not (model == "peak" and i == 3)]
        cond = np.linalg.cond(JtJ[:, keep][:, :, keep])
        # Stage-position sensitivity: a frame recorded at z_k but taken at z_k + e_k changes sample k by
        # -J[k, u0] e_k, and u0 by c_k e_k with c_k = -(cov J^T)[u0, k] J[k, u0] (sum c_k = -1: a common
        # offset of every frame moves the peak by the same amount). sqrt(sum c_k^2) turns independent
        # per-frame position noise into best-focus noise.
        # The same response for every parameter (P x n per curve): d params / d e_k = -(cov J^T)[:, k] J[k, u0]
        # (:attr:`_Fit.sens`); row u0 is c. Functions of the parameters (a skewed model's peak) take their
        # gradient through it, so every estimator's frame response is that of its own fit (CurveFit.centre_resp).
        sens = np.einsum("tpq,tnq->tpn", cov, Jw) * (-Jw[:, None, :, 1])
        c = sens[:, 1, :]
        gain = np.sqrt(np.sum(c * c, axis=1))
    n_par = (P - (1.0 - free_p)) if model == "peak" else np.full(T, float(P))
    dof = w.sum(axis=1) - n_par
    out = []
    for j in range(T):
        pj = p[j].copy()
        if model not in ("otf_sa", "otf_sa_wave"):  # even in the width (otf_sa*: in (kappa, s) jointly, as the peak)
            pj[2] = abs(pj[2])
        ok = ((dof[j] > 0) and bool(np.all(np.isfinite(pj))) and pj[0] > 0.0
              and abs(pj[2]) > 1e-6 and bool(np.all(np.isfinite(cov[j]))) and cond[j] < 1e13)
        if model == "peak":
            ok = ok and 0.1 <= pj[3] <= 1e4
        if not ok:
            out.append(None)
            continue
        # an exact (noise-free) fit has zero residual: floor the variance at float precision, not zero
        s2 = max(cost[j] / dof[j], 1e-24)
        out.append(_Fit(pj, float(cov[j][1, 1] * s2), float(scale[j]), float(cost[j]), int(w[j].sum()),
                        float(gain[j]), cov[j] * s2, sens[j]))
    if model == "peak" and p_init is None:
        _refit_gaussian_limit(z, V, pres, step, p, free_p, out)
    return out


# The Pearson VII exponent at which a free fit that ran off to the Gaussian limit is refitted (its largest
# accepted value: L^-p -> exp(-t^2) there to 1e-4).
PEARSON_GAUSS_EXPONENT = 1e4


def _refit_gaussian_limit(z, V, pres, step, p, free_p, out) -> None:
    """Windows whose free Pearson VII exponent ran past its bounds, refitted in place with the exponent fixed at
    the Gaussian limit.

    Why: on a near-Gaussian peak the exponent is unidentified and LM walks it to +-1e3..1e4 (1 / p crosses 0:
    both signs are the Gaussian), which the bound check refused; the tile then fell back to the local cubic
    peak, whose sd (~0.08 step even without noise) is 4-10x the centre's real error. A quarter to a third of a
    flat lens's tiles did so on an isotropic texture (their sds 1.5-2.3 µm against 0.15 µm for their
    neighbours, real scatter ~0.45 µm), and one error scale over both groups then understated the good tiles'
    errors enough for a 0.06 µm/mm noise tilt to pass BIC. The Gaussian is the limit of the family, so this is
    the same model with its unidentified shape parameter at the value the data point to. Accepted only with a
    floor >= 0 (below).
    """
    redo = [j for j in range(len(pres)) if out[j] is None and free_p[j] and np.all(np.isfinite(p[j]))
            and p[j, 0] > 0.0 and abs(p[j, 3]) > PEARSON_GAUSS_EXPONENT / 10.0]
    if not redo:
        return
    init = [[p[j, 0], p[j, 1], abs(p[j, 2]), PEARSON_GAUSS_EXPONENT, p[j, 4]] for j in redo]
    for j, f in zip(redo, _fit_batch(z, V, [pres[j] for j in redo], step, "peak", p_init=init)):
        # A focus measure is an energy (>= 0): a negative floor means height, width and floor traded off (a
        # shallow peak broader than the window, amplitude ~50x the maximum) -- not resolved; keep the refusal.
        if f is not None and f.params[4] >= 0.0:
            out[j] = f


@dataclass
class _Fit:
    params: np.ndarray
    var_u0: float
    scale: float
    rss: float
    n: int
    stage_gain: float
    cov: np.ndarray | None = None  # residual-scaled parameter covariance
    # d params / d e_k (P x window points, u per u): how each parameter moves when the frame at window point k
    # was taken e_k away from where it is recorded (the model's slope there times the fit's gain, cov J^T)
    sens: np.ndarray | None = None


def _solve_spd(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched ``A x = b`` for damped normal equations (symmetric, positive definite by construction):
    Cholesky-free ``np.linalg.solve`` (about 5x faster than an SVD pseudo-inverse per iteration), falling back
    to the pseudo-inverse when a matrix of the batch is singular (non-finite rows give non-finite steps,
    rejected by the caller's cost test)."""
    try:
        x = np.linalg.solve(A, b[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        x = (np.linalg.pinv(A) @ b[:, :, None])[:, :, 0]
    return x


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


# x where D(x)^2 = 1/2, for the initial guess of the blur scale.
_X_HALF_ENERGY = disc_x_at_contrast(math.sqrt(0.5))


# ----------------------------------------------------------------------------- the band-pass's band, not fs
# Relative uncertainty of the two terms of :func:`band_peak_correction_um` (the parts of the expansion it cannot
# check on the stack): the effective-frequency shift comes from a local power law of the band energy x sharpness
# (fs_strip.effective_shift_ln), the curvature term from a parabola in ln f through three bands; the next terms
# (d3z/dln f^3, the peak of a sum of skewed curves not being the weighted mean of their peaks) are not measured.
# On band-pass curves built from the exact pupil OTF (W040 0.3-1.2 waves, F/4-F/8, 470-610 nm, texture spectra
# f^-2 and f^-3, two to three sampling phases) what the correction leaves is up to 0.6 x the first term (F/4,
# 1.2 waves) and 0.35 x the curvature term (F/8, 0.3 waves at 610 nm): half of each is the sd
# (tests/test_band_frequency.py checks the corrected peaks against it).
BAND_FIRST_ORDER_REL_SD = 0.5
BAND_CURVATURE_REL_SD = 0.5


def band_frequency_terms(lo: list[CurveFit], mid: list[CurveFit], hi: list[CurveFit],
                         half_span_ln: float, shared_sd_um: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict:
    """How the band-pass's peak moves with frequency, pooled over tiles: slope and curvature in ln f.

    ``lo``, ``mid``, ``hi``: the same tiles' band-pass fits at ``fs e^-h``, ``fs``, ``fs e^+h`` (h =
    ``half_span_ln``). Per tile the first difference ``(z_hi - z_lo) / 2h`` and the second difference
    ``(z_hi - 2 z_fs + z_lo) / h^2`` are pooled (:func:`pooled_mean`, Birge-inflated by their scatter).

    ``shared_sd_um`` (lo, fs, hi): the sd of an error every tile of a band shares (its pooled skew shift,
    :func:`apply_pooled_skew`), which the tiles' scatter cannot show: added in quadrature through the differences.

    Returns ``{"freq_slope_um", "freq_slope_sd_um", "freq_curv_um", "freq_curv_sd_um", "freq_n_tiles"}`` (µm per
    unit ln f and per unit ln f^2); without the fs fits (``mid`` empty) no curvature keys; {} with < 2 tiles.
    """
    e_lo, e_fs, e_hi = (float(v) for v in shared_sd_um)
    out: dict = {}
    both = [(a, b) for a, b in zip(lo, hi) if a.status == STATUS_OK and b.status == STATUS_OK]
    if len(both) < 2:
        return out
    d = np.array([b.z_best_um - a.z_best_um for a, b in both])
    sd = np.array([math.hypot(a.z_sigma_um, b.z_sigma_um) for a, b in both])
    m, se, _ = pooled_mean(d, sd)
    se = math.sqrt(se * se + e_lo * e_lo + e_hi * e_hi)
    out.update(freq_slope_um=m / (2.0 * half_span_ln), freq_slope_sd_um=se / (2.0 * half_span_ln),
               freq_n_tiles=float(len(both)))
    three = [(a, c, b) for a, c, b in zip(lo, mid, hi) if STATUS_OK == a.status == b.status == c.status]
    if len(three) >= 2:
        d2 = np.array([b.z_best_um - 2.0 * c.z_best_um + a.z_best_um for a, c, b in three])
        # the three bands' errors taken as independent: their overlap (they see the same texture) only lowers it
        sd2 = np.array([math.sqrt(a.z_sigma_um ** 2 + 4.0 * c.z_sigma_um ** 2 + b.z_sigma_um ** 2)
                        for a, c, b in three])
        m2, se2, _ = pooled_mean(d2, sd2)
        se2 = math.sqrt(se2 * se2 + e_lo * e_lo + 4.0 * e_fs * e_fs + e_hi * e_hi)
        out.update(freq_curv_um=m2 / half_span_ln ** 2, freq_curv_sd_um=se2 / half_span_ln ** 2)
    return out


def band_peak_correction_um(rec: dict, band_log_var: float) -> tuple[float, float]:
    """(correction, sd) in µm: what to add to a band-pass peak to get the sharpest position at fs itself.

    The log-Gabor ring weights the band energy by a Gaussian in ln f of variance ``V = band_log_var``; the
    measure's peak is, to first order in the spread of the peaks across the band, the mean of the peaks
    ``z(ln f)`` of the frequencies in it, weighted by that Gaussian x the band energy at the peak x the curve's
    sharpness (``f^t`` locally: a Gaussian of mean ``s = V t`` = ``freq_shift_ln``, variance V). With ``z`` a
    parabola in ln f (slope b, curvature c at fs) that mean is ``z + b s + c (V + s^2) / 2``; the slope measured
    between the side bands (which carry the same weighting) is ``b + c s``. So the correction is

        ``-b_meas s - c (V - s^2) / 2``.

    The curvature term is why: near diffraction (``fs lambda N`` ~ 0.3, F/8 at 80 cy/mm) the sharpest position
    has a turning point in frequency with spherical aberration (W040 0.3 waves: dz/dln f ~ 5 µm but d2z/dln f^2
    ~ 40-50 µm), and the band-pass peaks 0.05-0.1 scan step off the MTF(fs) peak where the slope alone says 0.02.
    Each term is applied with the evidence weight of its measured coefficient (``1 / (1 + O sqrt(n) exp(-chi2 /
    2))``, ``chi2 = (value / sd)^2``, as :func:`pooled_mean`): a lens without spherical aberration measures both
    as 0 within their sds and keeps its band-pass peak, not a noisy correction. The sd: each term's variance (the
    measured coefficient's sd through the formula, in quadrature with the expansion's model error,
    :data:`BAND_FIRST_ORDER_REL_SD`, :data:`BAND_CURVATURE_REL_SD` of the term) times its weight, plus ``w (1 - w)
    term^2`` (whether it applies at all). Without the curvature (a record from before, or too few tiles with all
    three bands) no correction: the first-order term is the sd (as before). 0 for a record without the slope.
    """
    s = float(rec.get("freq_shift_ln", 0.0) or 0.0)
    b = float(rec.get("freq_slope_um", 0.0) or 0.0)
    b_sd = float(rec.get("freq_slope_sd_um", 0.0) or 0.0)
    if not all(math.isfinite(v) for v in (s, b, b_sd)):
        return 0.0, 0.0
    c, c_sd = (float(rec.get(k, math.nan)) for k in ("freq_curv_um", "freq_curv_sd_um"))
    if not (math.isfinite(c) and math.isfinite(c_sd)):
        return 0.0, abs(s) * math.hypot(b, b_sd)
    n = max(float(rec.get("freq_n_tiles", 2.0) or 2.0), 1.0)
    k = 0.5 * (band_log_var - s * s)
    corr, var = 0.0, 0.0
    for term, term_sd, coef, coef_sd, rel in ((-b * s, abs(s) * b_sd, b, b_sd, BAND_FIRST_ORDER_REL_SD),
                                              (-c * k, abs(k) * c_sd, c, c_sd, BAND_CURVATURE_REL_SD)):
        chi2 = (coef / coef_sd) ** 2 if coef_sd > 0 else (math.inf if coef else 0.0)
        w = 1.0 / (1.0 + SKEW_PRIOR_ODDS * math.sqrt(n) * math.exp(-0.5 * min(chi2, 1400.0)))
        corr += w * term
        var += w * (term_sd ** 2 + (rel * term) ** 2) + w * (1.0 - w) * term * term
    return corr, math.sqrt(var)
