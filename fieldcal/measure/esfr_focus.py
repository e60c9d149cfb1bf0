"""Through-focus MTF(fs) of slanted edges: edge tracks across frames, best focus (sub-step) and tolerance.

* :func:`link_tracks` — the same physical edge in successive frames (z order), matched by position and
  direction (Hungarian assignment, so two nearby edges never swap).
* :func:`defocus_peak` — best focus of a track: the through-focus OTF of defocus and spherical aberration
  fitted to MTF(fs)^2 (:mod:`.throughfocus`, model "otf": ``a O(pi fs k (z - z0), s)^2 + b``, the texture
  path's band-pass models), its peak with s free averaged with the symmetric (s = 0) law's centre by the
  BIC evidence for s, so an aberrated (skewed) curve gives its sharpest position. Least squares on a model
  is unbiased however the scan samples the curve; a smoothing spline's maximum is not (below).
* :func:`through_focus_peak` — the maximum of a cubic smoothing spline through the samples (interpolating
  when the values are exact, ``s = n sigma^2`` for a known noise, else the noise from third differences). It
  is the smooth curve the measured tolerance is read from. Its maximum is *not* the best focus of a noisy
  curve: the roughness penalty lets the long sampled flank's slope run into the peak, moving the maximum
  towards the nearer scan end (+-2-3 µm, 0.1-0.15 step, on F/3.7 curves 1-2 depths of field from an end at
  MTF noise 0.01; docs/measurement.md "Through focus").
* :func:`tolerance_half_widths` — the measured depth of field: the distances from best focus to where the
  same smooth curve crosses ``(1 - q) * peak`` on each side (Brent's root in the bracketing sample interval);
  each side separately, so an asymmetric curve keeps its asymmetry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from .throughfocus import CurveRules

# The texture path's curve rules, except the flank test: a texture tile's flanks must fall to half height
# (its peak model has no fixed shape), while an MTF(fs) track follows the defocus law, whose blur rate the
# long flank measures; a curve whose highest sample is interior is located, and its sd says how well.
# Skew by the BIC weight alone (prior odds 1): the edge path fits the spherical-aberration model of MTF(fs)
# itself, whose peak is unbiased on a symmetric curve as well (defocus_peak), so no prior for symmetry is needed.
EDGE_CURVE_RULES = CurveRules(edge_flank=1.0, skew_prior_odds=1.0)
TOLERANCE_UNREACHED = "the scan ends before MTF(fs) falls by q on one side"


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
    """Best focus of one through-focus curve, and the smooth curve it was read from."""

    z_um: float
    sigma_um: float  # 1-sigma uncertainty of z_um (noise only; see docs/measurement.md for the model error)
    peak: float  # the smoothed curve's value at z_um
    n_used: int  # samples in the curve
    ok: bool
    reason: str
    curve: object = None  # callable z -> smoothed MTF(fs) (a scipy spline), None when not ok
    # best-focus sd per unit of independent per-frame stage-position noise (throughfocus.CurveFit.stage_gain)
    stage_gain: float = math.nan
    # the defocus law's half-width where MTF(fs) falls by q (its fitted blur rate), and the evidence weight for
    # skew that moved the best focus off the law's centre (0: the law holds; defocus_peak)
    law_width_um: float = math.nan
    skew_weight: float = math.nan


def _clean(z_um, values, sigma):
    z = np.asarray(z_um, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if z.shape != v.shape or z.ndim != 1:
        raise ParameterError("z and values must be 1-D arrays of the same length", field="values",
                             fix="give one MTF(fs) value per z position")
    good = np.isfinite(z) & np.isfinite(v)
    o = np.argsort(z[good], kind="stable")
    sig = None if sigma is None else np.broadcast_to(np.asarray(sigma, dtype=np.float64), z.shape)[good][o]
    return z[good][o], v[good][o], sig


def noise_from_differences(v: np.ndarray) -> float:
    """Sample noise of a smooth curve: robust RMS (MAD) of its third differences / sqrt(20)."""
    if v.size < 6:
        return 0.0
    d3 = np.diff(v, 3)
    return float(1.4826 * np.median(np.abs(d3 - np.median(d3))) / math.sqrt(20.0))


def smooth_curve(z: np.ndarray, v: np.ndarray, sigma: np.ndarray | None = None):
    """Cubic smoothing spline of a sampled curve: ``s = n sigma^2`` when the noise is known (an interpolating
    spline for sigma = 0), else the smoothing chosen by generalised cross-validation."""
    from scipy.interpolate import UnivariateSpline, make_smoothing_spline
    if sigma is not None:
        s = float(np.sum(np.asarray(sigma) ** 2))
        return UnivariateSpline(z, v, k=3, s=s)
    try:
        return make_smoothing_spline(z, v)
    except (ValueError, np.linalg.LinAlgError):  # degenerate GCV (e.g. exactly polynomial data): interpolate
        return UnivariateSpline(z, v, k=3, s=0.0)


def _spline_peak(spl, z: np.ndarray, k: int) -> float:
    """Maximum of ``spl`` within one sample of index ``k`` (fine grid + parabolic refinement); the scan's
    maximum if the spline's peak is not in that bracket."""
    zz = np.linspace(z[k - 1], z[k + 1], 201)
    sv = spl(zz)
    j = int(np.argmax(sv))
    if j in (0, zz.size - 1):
        zz = np.linspace(z[0], z[-1], 40 * z.size)
        sv = spl(zz)
        j = int(np.argmax(sv))
    if 0 < j < zz.size - 1:
        den = sv[j - 1] - 2 * sv[j] + sv[j + 1]
        if den < 0:
            return float(zz[j] + 0.5 * (sv[j - 1] - sv[j + 1]) / den * (zz[1] - zz[0]))
    return float(zz[j])



def _bootstrap_spline_peaks(z: np.ndarray, base: np.ndarray, sig: np.ndarray, n_boot: int, seed) -> np.ndarray:
    """Smoothing-spline peaks of ``n_boot`` curves ``base + N(0, sig)``: the spread of the spline's maximum."""
    rng = np.random.default_rng(seed)
    peaks = []
    for _ in range(n_boot):
        vb = base + rng.normal(0.0, 1.0, z.size) * sig
        kb = int(np.clip(np.argmax(vb), 1, z.size - 2))
        peaks.append(_spline_peak(smooth_curve(z, vb, sig), z, kb))
    return np.asarray(peaks)

def through_focus_peak(z_um, values, *, sigma=None, n_boot: int = 24, seed: int = 0) -> FocusPeak:
    """Sub-step maximum of a sampled through-focus curve; no symmetry assumed.

    The curve is a cubic smoothing spline through the samples (:func:`smooth_curve`); best focus is its
    maximum near the highest sample. The uncertainty is a parametric bootstrap: ``n_boot`` copies of the
    smoothed curve plus noise of the given ``sigma`` (else the spline's residual scatter), each smoothed and
    maximised the same way; their standard deviation. It covers noise only: a curve shape the spline cannot
    follow adds a bias it does not see (docs/measurement.md).

    Parameters
    ----------
    z_um, values : 1-D arrays (any order; NaN samples ignored).
    sigma : float or array, optional
        1-sigma noise of the values (0 for exact values); unknown -> smoothing by cross-validation.
    n_boot, seed : bootstrap size and seed (deterministic).
    """
    z, v, sig = _clean(z_um, values, sigma)
    if z.size < 5:
        return FocusPeak(math.nan, math.nan, math.nan, int(z.size), False, "fewer than 5 samples")
    k = int(np.argmax(v))
    if k == 0 or k == z.size - 1:
        return FocusPeak(float(z[k]), math.nan, float(v[k]), int(z.size), False, "maximum at the end of the scan")
    if sig is None:  # noise unknown: from the third differences (blind to a curve's slope and curvature)
        sig = np.full(z.size, noise_from_differences(v))
    spl = smooth_curve(z, v, sig)
    zbest = _spline_peak(spl, z, k)
    peak = float(spl(zbest))
    fit = spl(z)
    s = sig
    sz = 0.0
    if n_boot > 1 and np.any(s > 0):
        sz = float(np.std(_bootstrap_spline_peaks(z, fit, sig, n_boot, seed), ddof=1))
    return FocusPeak(zbest, sz, peak, int(z.size), True, "ok", spl)


def tolerance_half_widths(z_um, values, q: float, peak: FocusPeak) -> tuple[float, float]:
    """(left, right) distances (µm) from ``peak.z_um`` to where the smoothed curve falls to
    ``(1 - q) * peak.peak`` (Brent's root in the first sample interval where the curve is below).

    NaN on a side where the scan ends before the curve falls that far, and on both when the smoothed curve at
    ``peak.z_um`` is already below the threshold (a best focus read by the defocus law where the smoothed
    curve's own maximum lies more than the tolerance away: no half-width is measured from there).
    """
    from scipy.optimize import brentq

    if not 0.0 < q < 1.0:
        raise ParameterError(f"q = {q} outside (0, 1)", field="q", fix="give the MTF loss as a fraction, e.g. 0.05")
    z, v, _ = _clean(z_um, values, None)
    if not peak.ok or peak.curve is None:
        return math.nan, math.nan
    spl = peak.curve
    thr = (1.0 - q) * peak.peak
    zp = peak.z_um
    if not float(spl(zp)) >= thr:
        return math.nan, math.nan
    out = []
    for direction in (-1, 1):
        side = z[z < zp][::-1] if direction < 0 else z[z > zp]
        prev, found = zp, math.nan
        for zj in side:
            if spl(zj) < thr:
                a, b = min(prev, zj), max(prev, zj)
                found = brentq(lambda t: float(spl(t) - thr), a, b)
                break
            prev = zj
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
    stage_gain: float = math.nan  # best-focus sd per unit of per-frame stage-position noise

    @property
    def depth_um(self) -> float:
        """Total depth of the tolerance interval, left + right."""
        return self.tol_left_um + self.tol_right_um


def _model_misfit(z: np.ndarray, v: np.ndarray, sig: np.ndarray) -> bool:
    """Whether the spherical-aberration model leaves residuals the known noise ``sig`` of MTF(fs) cannot
    explain: its fit's chi2 beyond ``dof + 4 sqrt(2 dof)`` (~3.4 sd of a chi2; the noise of MTF^2 is 2 MTF
    sig). Noise-free values (sig = 0) are taken as exact to 1e-6 of the peak."""
    from .throughfocus import _fit_batch, _precheck

    e = v * v
    pre = _precheck(z, e, EDGE_CURVE_RULES)
    if not hasattr(pre, "lo"):
        return False
    step = float(np.median(np.diff(z)))
    sym = _fit_batch(z, e[None], [(0, pre)], step, "otf")[0]
    if sym is None:
        return False
    p = sym.params
    sa = _fit_batch(z, e[None], [(0, pre)], step, "otf_sa", p_init=[[p[0], p[1], p[2], 0.0, p[3]]])[0]
    if sa is None or sa.n <= 5:
        return False
    w = slice(pre.lo, pre.hi + 1)
    s = np.maximum(sig[w], 1e-6 * float(np.max(v)))
    var_e = float(np.mean((2.0 * v[w] * s) ** 2 + 2.0 * s ** 4))
    dof = sa.n - 5
    return sa.rss * sa.scale ** 2 / var_e > dof + 4.0 * math.sqrt(2.0 * dof)


def defocus_peak(z_um, mtf_fs, *, sigma=None, q: float = 0.05, n_boot: int = 16) -> FocusPeak:
    """Best focus of one MTF(fs) track: the sharpest position of the through-focus OTF of defocus and primary
    spherical aberration fitted to the samples, weighed against the symmetric law by the evidence for skew.

    * **The law.** MTF(fs, z) = M0(fs) |O(pi fs k (z - z0), s)| (:mod:`.spherical`: a disc of blur ``k |z - z0|``
      with W040 in ``s = 16 pi fs N W040``; the static MTF M0 — pixel, diffraction, in-focus blur — only
      scales it). An e-SFR track measures exactly this, so MTF^2 is fitted with the texture path's band-pass
      models (:func:`fieldcal.measure.throughfocus.analyse_curve`, ``"otf"``; ``b`` absorbs the noise's upward
      bias of a magnitude): s = 0, the symmetric law ``a D^2 + b`` whose centre is its peak, and s free, whose
      peak (:func:`.spherical.peak_u`) is not its centre — SA puts a bright core on one side of focus, so the
      centre of the curve lies off its maximum by up to its half-maximum asymmetry. Least squares on a model
      of the whole peak is unbiased however the scan samples the curve; a smoothing spline's maximum is not
      (module docstring).
    * **Evidence.** The best focus is the two peaks averaged by the BIC weight of s != 0,
      ``w = 1 / (1 + sqrt(n) exp(-chi2 / 2))`` with ``chi2`` the drop of the residual sum of squares over the
      s-free fit's residual variance (the noise measured from the track itself; equal prior odds,
      :data:`EDGE_CURVE_RULES`), and the variance mixes both (each from its fit's residual-scaled covariance,
      the skewed peak's by the delta method, so the uncertainty of s is in it) with their spread. A symmetric
      curve's noise-fitted s is zero-mean, so its skewed peak is unbiased too: the weight only trades variance.

    ``sigma`` (the noise of the values, when known) lets the model be tested: a curve it cannot describe within
    that noise (:func:`_model_misfit`; no lens, e.g. a blur rate that jumps at focus) gets the maximum of the
    smooth curve through its samples instead (:func:`through_focus_peak`, sd by a parametric bootstrap of
    ``n_boot`` curves), which follows any shape. Without ``sigma`` the noise is the fit's own residual.

    The curve need only fall on both sides of its highest sample (:data:`EDGE_CURVE_RULES`): the blur rate
    comes from the sampled flanks, so a peak near a scan end is still located, with the larger sd its short
    side gives.

    ``law_width_um`` is the symmetric law's tolerance, ``x_q / (pi fs k)`` with ``|D(x_q)| = 1 - q``: the
    half-width where the *signal's* MTF(fs) falls by q (the floor ``b`` holds the noise's bias of MTF^2, which
    would otherwise flatten the curve), from the blur rate the whole peak fixes (fs only scales k: any units).
    """
    from .throughfocus import analyse_curve

    z, v, sig = _clean(z_um, mtf_fs, sigma)
    keep = np.concatenate([[True], np.diff(z) > 0])  # analyse_curve wants strictly increasing z
    z, v = z[keep], v[keep]
    sig = None if sig is None else sig[keep]
    if z.size < 5:
        return FocusPeak(math.nan, math.nan, math.nan, int(z.size), False, "fewer than 5 samples")
    # fs only scales the fitted blur rate k; the width x_q / (pi fs k) is the same in µm whatever fs is given
    fit = analyse_curve(z, v ** 2, "otf", 1.0, q, EDGE_CURVE_RULES)
    if fit.status != "ok":
        return FocusPeak(math.nan, math.nan, math.nan, int(z.size), False, f"defocus fit: {fit.status}")
    if sig is not None and _model_misfit(z, v, sig):  # a shape no lens model describes: the curve's own maximum
        pk = through_focus_peak(z, v, sigma=sig, n_boot=n_boot)
        return FocusPeak(pk.z_um, pk.sigma_um, math.nan, int(z.size), pk.ok, pk.reason, stage_gain=fit.stage_gain,
                         law_width_um=float(fit.width_um), skew_weight=1.0)
    w = fit.skew_weight
    return FocusPeak(float(fit.z_best_um), float(fit.z_sigma_um), math.nan, int(z.size), True, "ok",
                     stage_gain=fit.stage_gain, law_width_um=float(fit.width_um),
                     skew_weight=float(w) if math.isfinite(w) else 0.0)


def analyse_track(z_um, mtf_fs, q: float = 0.05, *, sigma=None) -> TrackFocus:
    """Best focus (:func:`defocus_peak`, sub-step) and the tolerance half-widths of one edge track.

    The half-widths are the defocus law's (``FocusPeak.law_width_um``), moved towards the smoothed curve's own
    crossings (:func:`tolerance_half_widths`, measured from the same best focus) by the same evidence for skew
    that moves the best focus: a symmetric curve keeps the law's width, a clearly skewed one its measured
    asymmetric sides. ``sigma``: the noise of the values (:func:`defocus_peak`). Why not the
    smoothed curve alone: the q = 5 % crossing lies within a step of the peak when the scan step is near the
    tolerance, where a smoothing spline's shape is set by its roughness penalty, not by the data — it read
    +4-7 % wide at 480x270 with 20 µm steps (step / tolerance 1.1-1.2), and a noisy magnitude's upward bias
    flattens it further; the law's blur rate comes from the whole peak, with the noise floor fitted apart.
    """
    pk = through_focus_peak(z_um, mtf_fs, sigma=sigma, n_boot=0)
    law, w = math.nan, math.nan
    if pk.ok:  # the smooth curve's maximum value is the peak the tolerance is measured down from
        fp = defocus_peak(z_um, mtf_fs, sigma=sigma, q=q)
        pk = FocusPeak(fp.z_um, fp.sigma_um, pk.peak, pk.n_used, fp.ok, fp.reason, pk.curve if fp.ok else None,
                       fp.stage_gain)
        law, w = fp.law_width_um, (0.0 if not math.isfinite(fp.skew_weight) else fp.skew_weight)
    left, right = tolerance_half_widths(z_um, mtf_fs, q, pk)
    if pk.ok and math.isfinite(law) and law > 0:
        # a side the smoothed curve never crosses keeps the law's width while the law holds (w < 1/2)
        left, right = (w * s + (1.0 - w) * law if math.isfinite(s) else (law if w < 0.5 else math.nan)
                       for s in (left, right))
    reason = pk.reason
    if pk.ok and not (math.isfinite(left) and math.isfinite(right)):
        reason = TOLERANCE_UNREACHED
    return TrackFocus(pk.z_um, pk.sigma_um, pk.peak, left, right, pk.ok and reason == "ok", reason, pk.stage_gain)
