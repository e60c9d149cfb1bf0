"""Through-focus MTF(fs) of slanted edges: edge tracks across frames, best focus (sub-step) and tolerance.

* :func:`link_tracks` — the same physical edge in successive frames (z order), matched by position and
  direction (Hungarian assignment, so two nearby edges never swap).
* :func:`defocus_peak` — best focus of a track: the through-focus law of defocus fitted to MTF(fs)^2
  (:mod:`.throughfocus`, model "otf": ``a D(pi fs k (z - z0))^2 + b``, the texture path's band-pass model),
  moved towards the smoothing spline's maximum by the evidence for skew, so an aberrated (skewed) curve
  still gives its sharpest position. Least squares on the law is unbiased however the scan samples the
  curve; a smoothing spline's maximum is not (below).
* :func:`analyse_tracks` — a channel's tracks together: the asymmetry ``s`` of spherical aberration (W040) is a
  property of the lens, so it is fitted jointly over the channel's tracks (:func:`track_shape`,
  :func:`pool_shape`, :func:`profile_shape`) and, where the data select it, each track's best focus is the peak
  of the law with that ``s`` (:func:`shaped_track`; the exact pupil OTF at high ``fs lambda N``), its tolerance
  the law's own (1 - q) crossings; else :func:`analyse_track` (the symmetric law) per track.
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
EDGE_CURVE_RULES = CurveRules(edge_flank=1.0)
TOLERANCE_UNREACHED = "the scan ends before MTF(fs) falls by q on one side"


def link_tracks(frame: np.ndarray, x_px: np.ndarray, y_px: np.ndarray, angle_deg: np.ndarray, z_um: np.ndarray,
                *, max_shift_px: float = 6.0, max_turn_deg: float = 4.0,
                length_px: np.ndarray | None = None) -> np.ndarray:
    """Track id of each detection: detections of consecutive frames (in z order) within ``max_shift_px`` across
    the edge and ``max_turn_deg`` in direction whose segments overlap by at least half the shorter one (along
    the edge within ``max(max_shift_px, max(L1, L2) / 2)``) are the same edge (optimal one-to-one assignment).
    A track may skip frames where the edge was not found (it is matched against its last position).

    Why two distances: a detection's position is the midpoint of the scan lines the e-SFR used, and which lines
    are usable changes with the blur, so the midpoint slides *along* the edge from frame to frame while the
    line itself moves only by the lens's breathing. With one radius of 6 px the 1920 x 1080 triplet's edges
    (46 scan lines) broke into two tracks wherever the midpoint slid 6-11 px: 62 junctions in G, each 0.05-0.8
    px across the edge, 1 frame apart (docs/measurement.md "Edge tracks"). ``length_px`` (each detection's
    edge length; None: the single radius ``max_shift_px``) sets the along-edge allowance. Two distinct
    collinear edges (the next segment of a split side, the next square's side) do not overlap: their midpoints
    are at least ``(L1 + L2) / 2`` apart, beyond the allowance."""
    from scipy.optimize import linear_sum_assignment

    frame = np.asarray(frame)
    x, y, ang, z = (np.asarray(v, dtype=np.float64) for v in (x_px, y_px, angle_deg, z_um))
    length = np.zeros(x.size) if length_px is None else np.nan_to_num(np.asarray(length_px, np.float64))
    track = np.full(frame.size, -1, dtype=np.int64)
    frames = sorted(set(frame.tolist()), key=lambda f: (float(np.mean(z[frame == f])), f))
    last: list[int] = []  # detection index of each track's latest member
    for f in frames:
        idx = np.flatnonzero(frame == f)
        if last:
            L = np.asarray(last)
            dx, dy = x[idx, None] - x[None, L], y[idx, None] - y[None, L]
            th = np.radians(ang[None, L])
            along = np.abs(dx * np.cos(th) + dy * np.sin(th))
            across = np.abs(-dx * np.sin(th) + dy * np.cos(th))
            allow = np.maximum(max_shift_px, 0.5 * np.maximum(length[idx, None], length[None, L]))
            turn = np.abs((ang[idx, None] - ang[None, L] + 90.0) % 180.0 - 90.0)
            ok = (across <= max_shift_px) & (along <= allow) & (turn <= max_turn_deg)
            cost = np.where(ok, np.hypot(across, along * (max_shift_px / allow)), 1e9)
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


def defocus_peak(z_um, mtf_fs, *, sigma=None, n_boot: int = 16, seed: int = 0, q: float = 0.05,
                 fit=None) -> FocusPeak:
    """Best focus of one MTF(fs) track: the through-focus law of defocus, moved to the sharpest position of a
    skewed curve by the evidence for skew.

    * **The law.** MTF(fs, z) = M0(fs) |D(pi fs k (z - z0))| for a disc of blur ``k |z - z0|`` (the static MTF
      M0 — pixel, diffraction, residual aberrations — only scales it), so MTF^2 is the texture path's band-pass
      model ``a D^2 + b`` (:func:`fieldcal.measure.throughfocus.analyse_curve`, ``b`` absorbs the noise's
      upward bias of a magnitude), fitted over the whole peak. Least squares on the law is unbiased however
      the scan samples the curve; a smoothing spline's maximum is not (module docstring). Its sd is the fit's
      residual-scaled covariance.
    * **Skew.** An aberrated curve is not symmetric: its sharpest position is the maximum of the smooth curve
      through the samples (:func:`through_focus_peak`), which follows any shape. The best focus moves from the
      law's centre towards it by the texture path's evidence for skew (``CurveFit.skew_weight``: the data's
      cubic skew in ln MTF^2 over the core against the law's own, with prior odds 10 for a symmetric curve),
      and the variance mixes both with their spread (as :func:`fieldcal.measure.throughfocus._finish`); the
      spline's own sd is a parametric bootstrap (``n_boot``). A symmetric noisy curve so keeps the law's
      unbiased centre (weight ~0.03), a clearly skewed one gets the spline's maximum (and, near a scan end,
      its bias back: the price of following a shape no law describes).

    The curve need only fall on both sides of its highest sample (:data:`EDGE_CURVE_RULES`): the law's blur
    rate comes from the sampled flanks, so a peak near a scan end is still located, with the larger sd its
    short side gives. ``sigma``: the noise of the values (None: from the third differences).

    ``law_width_um`` is the law's tolerance, ``x_q / (pi fs k)`` with ``|D(x_q)| = 1 - q``: the half-width
    where the *signal's* MTF(fs) falls by q (the floor ``b`` holds the noise's bias of MTF^2, which would
    otherwise flatten the curve), from the blur rate the whole peak fixes (fs only scales k: any units).
    ``fit``: the law's fit of this track from :func:`defocus_fits` (many tracks at once), else fitted here.
    """
    from .throughfocus import analyse_curve

    z, v, sig = _clean(z_um, mtf_fs, sigma)
    keep = np.concatenate([[True], np.diff(z) > 0])  # analyse_curve wants strictly increasing z
    z, v = z[keep], v[keep]
    if z.size < 5:
        return FocusPeak(math.nan, math.nan, math.nan, int(z.size), False, "fewer than 5 samples")
    # fs only scales the fitted blur rate k; the width x_q / (pi fs k) is the same in µm whatever fs is given
    if fit is None:
        fit = analyse_curve(z, v ** 2, "otf", 1.0, q, EDGE_CURVE_RULES)
    if fit.status != "ok":
        return FocusPeak(math.nan, math.nan, math.nan, int(z.size), False, f"defocus fit: {fit.status}")
    if not math.isfinite(fit.z_centre_um):
        return FocusPeak(fit.z_best_um, fit.z_sigma_um, math.nan, int(z.size), True, "ok")  # the local peak alone
    zc, var_c, w = fit.z_centre_um, fit.z_centre_sd_um ** 2, fit.skew_weight
    w = 0.0 if not math.isfinite(w) else w
    sig = np.full(z.size, noise_from_differences(v)) if sig is None else sig[keep]
    du, var_du = 0.0, 0.0
    k = int(np.argmax(v))
    if w > 1e-3 and 0 < k < z.size - 1:
        du = _spline_peak(smooth_curve(z, v, sig), z, k) - zc
        if n_boot > 1 and np.any(sig > 0):
            var_du = float(np.var(_bootstrap_spline_peaks(z, v, sig, n_boot, seed), ddof=1))
    zb = zc + w * du
    var = w * (var_du + ((1.0 - w) * du) ** 2) + (1.0 - w) * (var_c + (w * du) ** 2)
    return FocusPeak(float(zb), math.sqrt(var), math.nan, int(z.size), True, "ok", stage_gain=fit.stage_gain,
                     law_width_um=float(fit.width_um), skew_weight=float(w))


def defocus_fits(tracks, q: float = 0.05) -> list:
    """The defocus law's fit of each ``(z_um, mtf_fs)`` track as :func:`defocus_peak` makes it, all tracks in one
    batched call (:func:`fieldcal.measure.throughfocus.analyse_curve_list`; equal to one call per track to
    round-off); None for a track with fewer than 5 samples."""
    from .throughfocus import analyse_curve_list

    idx, curves = [], []
    for i, (z_um, mtf_fs) in enumerate(tracks):
        z, v = _increasing(z_um, mtf_fs)
        if z.size >= 5:
            idx.append(i)
            curves.append((z, v ** 2))
    out: list = [None] * len(tracks)
    for i, f in zip(idx, analyse_curve_list(curves, "otf", 1.0, q, EDGE_CURVE_RULES)):
        out[i] = f
    return out


def analyse_track(z_um, mtf_fs, q: float = 0.05, *, sigma=None, fit=None) -> TrackFocus:
    """Best focus (:func:`defocus_peak`, sub-step) and the tolerance half-widths of one edge track.

    The half-widths are the defocus law's (``FocusPeak.law_width_um``), moved towards the smoothed curve's own
    crossings (:func:`tolerance_half_widths`) by the same evidence for skew that moves the best focus: a
    symmetric curve keeps the law's width, a clearly skewed one its measured asymmetric sides. Why not the
    smoothed curve alone: the q = 5 % crossing lies within a step of the peak when the scan step is near the
    tolerance, where a smoothing spline's shape is set by its roughness penalty, not by the data — it read
    +4-7 % wide at 480x270 with 20 µm steps (step / tolerance 1.1-1.2), and a noisy magnitude's upward bias
    flattens it further; the law's blur rate comes from the whole peak, with the noise floor fitted apart.
    ``fit``: the law's fit from :func:`defocus_fits` (many tracks at once), else fitted here.
    """
    pk = through_focus_peak(z_um, mtf_fs, sigma=sigma, n_boot=0)
    law, w = math.nan, math.nan
    if pk.ok:  # the smooth curve's maximum value is the peak the tolerance is measured down from
        fp = defocus_peak(z_um, mtf_fs, sigma=sigma, q=q, fit=fit)
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


# --------------------------------------------------------------------------- spherical aberration, pooled
@dataclass(frozen=True)
class TrackShape:
    """One track's fit of the defocus + primary-SA law with the asymmetry ``s`` free (:func:`track_shape`)."""

    s: float  # s = 16 pi fs N W040 (dimensionless; sign with kappa > 0)
    var_s: float  # its residual-scaled variance
    n: int  # samples in the fit window
    kappa: float  # the fit's blur rate per step, pi fs k step (with c_nu, nu = c_nu / kappa)
    ok: bool
    noise_var: float = math.nan  # the fit's residual variance (MTF^2 over its sampled maximum)


@dataclass(frozen=True)
class PooledShape:
    """The asymmetry ``s`` of a channel's through-focus MTF(fs) curves, pooled over its tracks (:func:`pool_shape`).

    ``selected`` says whether the channel's data show it (BIC): if not, each track keeps the symmetric law
    (:func:`analyse_track`). ``c_nu`` (``pi fs^2 lambda step``) is set when the exact (diffraction) OTF is the
    model (:func:`fieldcal.measure.spherical.wave_model`), NaN for the geometric-optics one."""

    s: float
    sd: float
    n_tracks: int
    weight: float  # BIC weight of s != 0 over the channel's samples (of the inverse-variance mean; selection)
    selected: bool
    c_nu: float = math.nan
    # the law at the pooled s (set by :func:`with_curve`): nu = fs lambda N (NaN: geometric optics), where
    # |O(x, s)| peaks and falls to (1 - q) of its peak, and O(x) as a cubic spline (the fits' model)
    nu: float = math.nan
    x_peak: float = math.nan
    x_left: float = math.nan
    x_right: float = math.nan
    curve: object = None
    # d(best focus, in steps)/ds of a track refitted at another s (the pooled s's share of each track's sd;
    # smaller than d x_peak / ds / kappa: u0 and kappa follow the data's peak)
    dz_ds: float = 0.0
    # d(symmetric law's reading - sharpest position, in steps)/ds about s = 0, for a channel read with s = 0
    # (symmetric_reading_sensitivity; unmodelled_asymmetry_sd_um)
    sym_dz_ds: float = 0.0
    # the e-SFR's Hamming window, r = (1 / 2h) / fs (h its half-length in px, fs in cycles/px; 0: none): the law
    # fitted is the one the window reads (:func:`windowed_law`), its peak and crossings the lens's own
    window_r: float = 0.0
    # nu = fs lambda N from the channel's blur rate (NaN: unknown), also where the law is not selected
    nu_data: float = math.nan

    def to_dict(self) -> dict:
        return {"s": self.s, "sd": self.sd, "n_tracks": self.n_tracks, "weight": self.weight,
                "selected": self.selected, "model": "ray" if math.isnan(self.nu) else "wave", "nu": self.nu,
                "x_peak": self.x_peak, "dz_ds_step": self.dz_ds,
                "symmetric_dz_ds_step": self.sym_dz_ds, "window_r": self.window_r}


def _law(x: np.ndarray, s: float, nu: float) -> np.ndarray:
    """Signed O(x, s) of the law relative to its diffraction-free value at x = 0: the geometric-optics integral
    (``nu`` NaN) or the exact pupil OTF at ``nu`` times the aberration-free MTF at ``nu`` (which
    :func:`~fieldcal.measure.spherical.wave_otf` divides out; kept here because the window mixes frequencies)."""
    from . import spherical

    x = np.asarray(x, dtype=np.float64)
    if math.isnan(nu):
        return spherical.sa_otf(x, s)[0]
    o = spherical.wave_otf(x.reshape(1, -1), np.array([s]), np.array([nu]))[0][0].reshape(x.shape)
    v = min(abs(nu), 1.0)  # the aberration-free MTF at nu = f / cut-off
    return o * (2.0 / math.pi) * (math.acos(v) - v * math.sqrt(1.0 - v * v))


def windowed_law(x, s: float, nu: float, r: float) -> np.ndarray:
    """The law as the e-SFR reads it: ``(a0 O(f) + a1 (O(f + D) + O(f - D))) / (a0 + 2 a1 O(D))`` at f = fs.

    Physics: the e-SFR multiplies the line-spread function by a Hamming window ``a0 + 2 a1 cos(pi d / h)``
    (a0 = 0.54, a1 = 0.23; d from the LSF's centroid, h the half-length: :func:`fieldcal.measure.esfr.esfr_regions`)
    before its FFT, and normalises at DC. A cosine times the LSF is the OTF shifted by +-D = 1 / (2h) in
    frequency, so the measured MTF(fs) mixes the OTF at fs, fs + D and fs - D, over a DC value that falls as the
    blur widens. Defocus is the law's ``x = pi f k dz``, and x, ``s = 16 pi f N W040`` and ``nu = f lambda N``
    all scale with f, so each tap is the law at ``(1 + t) (x, s, nu)`` with ``t = 0, +-r`` (``r = D / fs``) and the
    DC term at ``r (x, s, nu)``. A wider blur loses more of its tails to the window: the curve's flanks read high,
    and a law fitted over them reads the tolerance wide (clean-room F/5.6-F/8 edges with h = 8 px: 5 %) and,
    with spherical aberration (whose sharpest position moves with f), best focus off. The pixel aperture and other
    static transfer are taken flat over fs +- D (their slope enters at second order). ``r = 0``: the law itself."""
    x = np.asarray(x, dtype=np.float64)
    if not r > 0:
        return _law(x, s, nu)
    a0, a1 = 0.54, 0.23

    def at(t: float):
        return _law(x * t, s * t, nu * t if math.isfinite(nu) else nu)

    num = a0 * at(1.0) + a1 * (at(1.0 + r) + at(1.0 - r))
    return num / (a0 + 2.0 * a1 * at(r))


def _tabulate(s: float, nu: float, r: float = 0.0):
    """O(x, s) (at ``nu``: the exact pupil OTF; NaN: geometric optics), as the e-SFR's window reads it (``r``,
    :func:`windowed_law`; 0: none), as a cubic spline over the x a fit window reaches."""
    from scipy.interpolate import CubicSpline

    x_max = 12.0 + 2.0 * abs(s)
    # 10 nodes per unit of x: the law varies on a scale of ~1, so the cubic spline is within 1e-6 of it (40 per
    # unit gained nothing measurable and cost 4x the pupil OTF evaluations of the window's four laws)
    xg = np.linspace(-x_max, x_max, int(10 * x_max) + 1)
    return CubicSpline(xg, windowed_law(xg, s, nu, r))


def with_curve(shape: PooledShape, q: float, nu: float = math.nan) -> PooledShape:
    """``shape`` with its law tabulated: O(x, s) at the pooled s (and ``nu``: the exact pupil OTF, one nu for
    the channel since the F-number is the lens's) as a cubic spline over the x a fit window reaches, and its
    :func:`model_points`. Not selected where the law has no interior peak or crossing."""
    from dataclasses import replace

    xp, xl, xr = model_points(shape.s, q, nu)
    if not all(math.isfinite(t) for t in (xp, xl, xr)):
        return replace(shape, selected=False)
    return replace(shape, nu=float(nu), x_peak=xp, x_left=xl, x_right=xr,
                   curve=_tabulate(shape.s, nu, shape.window_r))


def _peak_sensitivity(tracks, shape: PooledShape, q: float, n_tracks: int = 8) -> float:
    """Median over up to ``n_tracks`` tracks of d(best focus in steps)/ds: each refitted at s +- the pooled sd."""
    h = max(shape.sd, 1e-3) if math.isfinite(shape.sd) else 0.1
    lo, hi = (with_curve(_with_s(shape, shape.s + d), q, shape.nu) for d in (-h, h))
    if not (lo.selected and hi.selected):
        return 0.0
    d = []
    for z, v in tracks[:: max(1, len(tracks) // n_tracks)][:n_tracks]:
        a, b = shaped_track(z, v, lo, q), shaped_track(z, v, hi, q)
        if a.ok and b.ok:
            step = float(np.median(np.diff(np.sort(np.asarray(z, float)))))
            d.append((b.z_best_um - a.z_best_um) / (2.0 * h * step))
    return float(np.median(np.abs(d))) if d else 0.0


def _with_s(shape: PooledShape, s: float) -> PooledShape:
    """``shape`` at another s (its law not yet tabulated: :func:`with_curve`)."""
    from dataclasses import replace
    return replace(shape, s=float(s), curve=None)


def _window(z: np.ndarray, v: np.ndarray):
    """The fit window of the track's MTF^2 (the texture path's rules, :data:`EDGE_CURVE_RULES`) or None."""
    from .throughfocus import _precheck

    pre = _precheck(z, v * v, EDGE_CURVE_RULES)
    return pre if hasattr(pre, "lo") else None


def _increasing(z_um, mtf_fs):
    z, v, _ = _clean(z_um, mtf_fs, None)
    keep = np.concatenate([[True], np.diff(z) > 0])
    return z[keep], v[keep]


def c_nu_of(fs_cyc_per_um: float, wavelength_um: float, step_um: float) -> float:
    """``nu kappa = pi fs^2 lambda step`` of :func:`fieldcal.measure.spherical.wave_model` (``nu = fs lambda N``)."""
    return math.pi * fs_cyc_per_um ** 2 * wavelength_um * step_um


def _symmetric_start(z: np.ndarray, v: np.ndarray):
    """The track's window, MTF^2, median step and the symmetric law's fit there (the start of every shaped fit);
    None when the window or the fit fails."""
    from .throughfocus import _fit_batch

    pre = _window(z, v)
    if pre is None:
        return None
    e = v * v
    step = float(np.median(np.diff(z)))
    sym = _fit_batch(z, e[None], [(0, pre)], step, "otf")[0]
    return None if sym is None else (pre, e, step, sym)


def track_shape(z_um, mtf_fs, c_nu: float = math.nan) -> TrackShape:
    """Fit MTF(fs)^2 of one track with the through-focus OTF of defocus + primary SA, ``s`` free
    (:func:`fieldcal.measure.spherical.model`, or with ``c_nu`` the exact pupil OTF,
    :func:`~fieldcal.measure.spherical.wave_model`; started from the symmetric law's fit): the track's evidence
    for the lens's asymmetry, pooled over the channel by :func:`pool_shape`. One track alone determines ``s``
    poorly: it trades against the blur rate and the centre (sd(s) ~ 1 at MTF noise 0.01)."""
    return track_shapes([(z_um, mtf_fs)], c_nu)[0]


def track_shapes(tracks, c_nu: float = math.nan) -> list[TrackShape]:
    """:func:`track_shape` of every ``(z_um, mtf_fs)`` track, the fits of all tracks batched (one
    :func:`fieldcal.measure.throughfocus._fit_batch` per model, each track on its own z: the same numbers as one
    call per track, at a fraction of the per-call overhead)."""
    from .throughfocus import _fit_batch

    zs, es, steps, pres, out = [], [], [], [], []
    for i, (z_um, mtf_fs) in enumerate(tracks):
        z, v = _increasing(z_um, mtf_fs)
        out.append(TrackShape(math.nan, math.nan, int(z.size), math.nan, False))
        pre = _window(z, v) if z.size >= 6 else None  # the window of the symmetric start (_symmetric_start)
        zs.append(z)
        es.append(v * v)
        steps.append(float(np.median(np.diff(z))) if pre is not None else math.nan)
        if pre is not None:
            pres.append((i, pre))
    if not pres:
        return out
    step = np.array(steps)
    sym = _fit_batch(zs, es, pres, step, "otf")
    sub = [pr for pr, f in zip(pres, sym) if f is not None]
    p0 = [[p[0], p[1], p[2], 0.0, p[3]] for p in (f.params for f in sym if f is not None)]
    sa = _fit_batch(zs, es, sub, step, "otf_sa", p_init=p0) if sub else []
    if math.isfinite(c_nu):  # the exact model track by track: its quadrature is chosen for the batch's largest x
        sa = [None if f is None else _fit_batch(zs, es, [sub[k]], step, "otf_sa_wave", p_init=[list(f.params)],
                                                nu=[c_nu])[0] for k, f in enumerate(sa)]
    for (i, _), f in zip(sub, sa):
        if f is None or f.n <= 5 or f.cov is None:
            continue
        sgn = 1.0 if f.params[2] > 0 else -1.0  # (kappa, s) and (-kappa, -s) are one curve: kappa > 0
        s, var = sgn * float(f.params[3]), float(f.cov[3, 3])
        ok = math.isfinite(s) and math.isfinite(var) and var > 0
        out[i] = TrackShape(s, var, int(f.n), abs(float(f.params[2])), bool(ok), float(f.rss) / (f.n - 5))
    return out


def pool_shape(shapes, c_nu: float = math.nan, clip: float = 4.0) -> PooledShape:
    """The channel's asymmetry: the inverse-variance mean of its tracks' ``s`` (:func:`track_shape`).

    Physics: W040, and so ``s = 16 pi fs N W040``, is a property of the lens that varies slowly over the field
    (constant for primary SA), and an edge's MTF across it sees the same W040 whatever the astigmatism (the
    cross-axis defocus cancels in the pupil's autocorrelation along the edge normal). Tracks beyond ``clip``
    robust sds of the median are left out (a false peak, a blended shape); no track weighs more than 4x the
    median track (an exact-looking curve's own sd is too small); the sd is scaled by the Birge ratio when the
    tracks scatter more than their sds say (the field varies, or the model is approximate). Selection: the BIC
    weight ``w = 1 / (1 + sqrt(n) exp(-chi2 / 2))`` of one parameter over the channel's ``n`` samples,
    ``chi2 = (s / sd)^2``; the pooled law is used when w > 1/2."""
    sh = [t for t in shapes if t.ok]
    if len(sh) < 3:
        return PooledShape(math.nan, math.nan, len(sh), 0.0, False, c_nu)
    s = np.array([t.s for t in sh])
    var = np.array([t.var_s for t in sh])
    n = np.array([t.n for t in sh])
    med = float(np.median(s))
    mad = 1.4826 * float(np.median(np.abs(s - med)))
    keep = np.abs(s - med) <= clip * max(mad, 1e-9)
    s, var, n = s[keep], var[keep], n[keep]
    var = np.maximum(var, 0.25 * float(np.median(var)))
    w = 1.0 / var
    mean = float(np.sum(w * s) / np.sum(w))
    sd = math.sqrt(1.0 / float(np.sum(w)))
    if s.size > 1:
        sd *= math.sqrt(max(float(np.sum(w * (s - mean) ** 2)) / (s.size - 1), 1.0))
    chi2 = (mean / sd) ** 2
    weight = 1.0 / (1.0 + math.sqrt(float(n.sum())) * math.exp(-0.5 * min(chi2, 1400.0)))
    return PooledShape(mean, sd, int(s.size), float(weight), bool(weight > 0.5), c_nu)


def _otf(x, s: float, nu: float):
    """|O(x, s)| of the pooled law: the geometric-optics integral, or the exact pupil OTF at ``nu``."""
    from . import spherical

    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    if math.isnan(nu):
        return np.abs(spherical.sa_otf(x, s)[0])
    return np.abs(spherical.wave_otf(x[None, :], np.array([s]), np.array([nu]))[0][0])


def model_points(s: float, q: float, nu: float = math.nan) -> tuple[float, float, float]:
    """(x_peak, x_left, x_right) of ``|O(x, s)|`` (x = pi fs k (z - z0)): where it peaks, and where it falls to
    ``(1 - q)`` of that peak on each side (first crossing outward on a fine grid, then Brent's root)."""
    from scipy.optimize import brentq

    span = 6.0 + 1.5 * abs(s)
    xg = np.linspace(-span, span, 1201)
    og = _otf(xg, s, nu)
    j = int(np.argmax(og))
    if j in (0, xg.size - 1):
        return math.nan, math.nan, math.nan
    from scipy.optimize import minimize_scalar

    xp = float(minimize_scalar(lambda t: -float(_otf(t, s, nu)[0]), bounds=(xg[j - 1], xg[j + 1]),
                               method="bounded", options={"xatol": 1e-9}).x)
    thr = (1.0 - q) * float(_otf(xp, s, nu)[0])
    out = []
    for side in (xg[:j][::-1], xg[j + 1:]):
        below = np.flatnonzero(_otf(side, s, nu) < thr) if side.size else []
        if len(below) == 0:
            out.append(math.nan)
            continue
        b = float(side[below[0]])
        a = float(side[below[0] - 1]) if below[0] > 0 else xp
        out.append(brentq(lambda t: float(_otf(t, s, nu)[0]) - thr, min(a, b), max(a, b), xtol=1e-10))
    return xp, out[0], out[1]


def _fixed_shape_fit(z: np.ndarray, v: np.ndarray, shape: PooledShape):
    """Least squares of ``a O(kappa (u - u0))^2 + b`` with O the channel's tabulated law (``shape.curve``) on
    the track's window (coordinates of :func:`fieldcal.measure.throughfocus._fit_batch`: u in steps from the
    sampled maximum, MTF^2 over its value there): (a, u0, kappa, b), their residual-scaled covariance, the z
    and value scale, the step and the stage gain; None when it fails."""
    from scipy.optimize import least_squares

    start = _symmetric_start(z, v)
    if start is None:
        return None
    pre, e, step, sym = start
    sl = slice(pre.lo, pre.hi + 1)
    zc, sc = float(z[pre.i_max]), float(e[pre.i_max])
    u = (z[sl] - zc) / step
    y = e[sl] / sc
    a0, u00, k0, b0 = (float(x) for x in sym.params)
    O, dO = shape.curve, shape.curve.derivative()

    def ev(p):
        du = u - p[1]
        x = p[2] * du
        o, do = O(x), dO(x)
        g = 2.0 * p[0] * o * do
        return p[0] * o * o + p[3], np.stack([o * o, -g * p[2], g * du, np.ones_like(u)], axis=-1)

    # the symmetric law's centre is near the skewed law's peak, which lies x_peak / kappa from its u0
    k0 = abs(k0)
    p0 = [a0 / max(float(O(shape.x_peak)) ** 2, 1e-6), u00 - shape.x_peak / k0, k0, b0]
    r = least_squares(lambda p: ev(p)[0] - y, p0, jac=lambda p: ev(p)[1], method="lm", x_scale="jac")
    p = r.x
    dof = u.size - 4
    x_lim = float(O.x[-1])
    if not (r.success and dof > 0 and np.all(np.isfinite(p)) and p[0] > 0 and p[2] > 1e-6
            and np.all(np.abs(p[2] * (u - p[1])) < x_lim)):
        return None
    J = ev(p)[1]
    cov0 = np.linalg.pinv(J.T @ J, rcond=1e-13)
    s2 = max(float(r.fun @ r.fun) / dof, 1e-24)
    c = -(cov0[1, :] @ J.T) * J[:, 1]  # stage gain, as throughfocus._fit_batch
    return p, cov0 * s2, zc, sc, step, float(np.sqrt(np.sum(c * c))), float(r.fun @ r.fun)


def shaped_track(z_um, mtf_fs, shape: PooledShape, q: float = 0.05) -> TrackFocus:
    """Best focus and tolerance of one track under its channel's pooled asymmetry (:func:`pool_shape`).

    The track is fitted with ``a O(kappa (u - u0), s)^2 + b``, s fixed at the pooled value (a, u0, kappa, b
    free: as well conditioned as the symmetric law). Its best focus is the model's peak ``u0 + x_peak /
    kappa`` — the sharpest position, the paper's definition — and its tolerance the model's own ``(1 - q)``
    crossings (:func:`model_points`), as the symmetric law's width is its ``x_q / kappa``. The sd is the delta
    method over (u0, kappa) with the fit's residual-scaled covariance; the pooled s's share is common to the
    channel's tracks and goes to the field-wide term (:func:`law_common_mode`)."""
    z, v = _increasing(z_um, mtf_fs)
    fail = TrackFocus(math.nan, math.nan, math.nan, math.nan, math.nan, False, "defocus fit: fit_failed")
    if z.size < 5:
        return TrackFocus(math.nan, math.nan, math.nan, math.nan, math.nan, False, "fewer than 5 samples")
    fit = _fixed_shape_fit(z, v, shape)
    if fit is None:
        return fail
    (a, u0, kappa, _), cov, zc, sc, step, gain, _ = fit
    xp, xl, xr = shape.x_peak, shape.x_left, shape.x_right
    u_pk = u0 + xp / kappa
    g = np.array([0.0, 1.0, -xp / kappa ** 2, 0.0])
    # the pooled s's error moves every track of the channel alike: a field-wide term (law_common_mode), not
    # the track's own noise
    var = float(g @ cov @ g)
    z_pk = zc + u_pk * step
    if not (z[0] < z_pk < z[-1]):
        return TrackFocus(z_pk, math.nan, math.nan, math.nan, math.nan, False, "maximum at the end of the scan")
    peak = math.sqrt(a * sc) * abs(float(shape.curve(xp)))  # MTF(fs) at the peak: sqrt of the MTF^2 law
    return TrackFocus(z_pk, math.sqrt(var) * step, peak, (xp - xl) / kappa * step, (xr - xp) / kappa * step,
                      True, "ok", gain)  # dimensionless, as throughfocus._fit_batch


def profile_shape(tracks, shapes, shape: PooledShape, nu: float = math.nan, max_tracks: int = 48,
                  n_grid: int = 9) -> PooledShape:
    """The pooled ``s`` refined as the joint least-squares estimate: the channel's chi^2 (each track's fixed-s
    residual sum of squares over its own noise variance, :func:`track_shape`) profiled over a grid of s about
    the inverse-variance mean, its vertex and the sd where it rises by 1.

    Why: a single track's ``s`` is a strongly nonlinear estimate (sd ~1-3 at MTF noise 0.01), and its own
    variance shrinks with |s|, so the inverse-variance mean of such estimates overshoots (by ~30 % on
    exact-pupil curves at nu = 0.24-0.34); the joint fit shares one s over all the tracks' samples, which is
    what the physics says. The ``max_tracks`` tracks with the best-determined s take part (cost)."""
    from dataclasses import replace
    from types import SimpleNamespace

    idx = [i for i, t in enumerate(shapes) if t.ok and t.noise_var > 0]
    idx = sorted(idx, key=lambda i: shapes[i].var_s)[:max_tracks]
    if len(idx) < 3:
        return shape
    half = max(3.0 * shape.sd, 0.3 * abs(shape.s), 0.5)
    grid = shape.s + np.linspace(-half, half, n_grid)
    chi2 = np.zeros(n_grid)
    good = np.ones(len(idx), bool)
    rss = np.full((n_grid, len(idx)), np.nan)
    for g, sg in enumerate(grid):
        curve = _tabulate(float(sg), nu, shape.window_r)
        xs = curve.x
        xp = float(xs[int(np.argmax(np.abs(curve(xs))))])
        ns = SimpleNamespace(curve=curve, x_peak=xp)
        for k, i in enumerate(idx):
            z, v = _increasing(*tracks[i])
            fit = _fixed_shape_fit(z, v, ns)
            if fit is None:
                good[k] = False
            else:
                rss[g, k] = fit[6]
    if good.sum() < 3:
        return shape
    nv = np.array([shapes[i].noise_var for i in idx])[good]
    chi2 = np.sum(rss[:, good] / nv, axis=1)
    j = int(np.clip(np.argmin(chi2), 1, n_grid - 2))
    c = np.polyfit(grid[j - 1:j + 2] - grid[j], chi2[j - 1:j + 2], 2)
    if not c[0] > 0:
        return shape
    s_hat = float(grid[j] - c[1] / (2.0 * c[0]))
    if not grid[0] <= s_hat <= grid[-1]:
        return shape
    sd = math.sqrt(1.0 / c[0])
    return replace(shape, s=s_hat, sd=sd)


def channel_shape(tracks, q: float = 0.05, *, fs_cyc_per_um: float = math.nan,
                  wavelength_um: float = math.nan, window_r: float = 0.0) -> PooledShape:
    """The pooled spherical-aberration asymmetry of a channel's edge tracks (``(z_um, mtf_fs)`` pairs), ready for
    :func:`shaped_track` when selected.

    Each track's ``s`` is fitted (:func:`track_shape`), pooled (:func:`pool_shape`) and, if selected, refined by
    the joint fit (:func:`profile_shape`) and tabulated (:func:`with_curve`). The law is the geometric-optics
    OTF of defocus + W040 where ``nu = fs lambda N`` is low, and the exact pupil OTF (diffraction included,
    :mod:`fieldcal.optics.pupil` via :func:`fieldcal.measure.spherical.wave_otf`) from
    :data:`fieldcal.measure.spherical.WAVE_MIN_NU` up, where the ray law's peak is off (given ``fs`` in
    cycles/µm and the channel's wavelength). ``window_r``: the e-SFR window's frequency shift over fs
    (:func:`window_r_of`), so the law fitted is the one the e-SFR reads (:func:`windowed_law`); with a window and a
    skew the exact law is used at any nu (the window's taps at other frequencies need diffraction's frequency
    dependence, which the ray law's fitted s holds at fs only)."""
    from dataclasses import replace

    from . import spherical

    c_nu, nu_data = math.nan, math.nan
    shapes = track_shapes(tracks)
    if math.isfinite(fs_cyc_per_um) and math.isfinite(wavelength_um) and tracks:
        steps = [float(np.median(np.diff(np.sort(np.asarray(z, float))))) for z, _ in tracks if len(z) > 1]
        kap = [t.kappa for t in shapes if t.ok]
        if steps and kap:
            cn = c_nu_of(fs_cyc_per_um, wavelength_um, float(np.median(steps)))
            if window_r > 0:
                nu_data = nu_of_width(_ray_x_q(q) * float(np.median(steps)) / float(np.median(kap)), q,
                                      fs_cyc_per_um, wavelength_um)
            # the exact law also wherever the window is read and the channel is skewed: the window mixes the
            # OTF at fs, (1 +- r) fs and r fs (windowed_law), and only the exact law carries the frequency
            # dependence of diffraction. The ray law's s absorbs diffraction at fs alone, so its taps at the
            # other frequencies are wrong: on the clean room's exact sa05-f2.8 curves (nu 0.11-0.12, W040 0.5
            # waves, r = 0.26) the windowed ray law read s = -1.6 for the true -3.0 and every peak +0.05 step
            # high, the exact law -0.006 step (docs/benchmarks.md bench_edge_bias_s18)
            if cn / float(np.median(kap)) >= spherical.WAVE_MIN_NU or (window_r > 0 and pool_shape(shapes).selected):
                c_nu = cn
                shapes = track_shapes(tracks, c_nu)
    shape = replace(pool_shape(shapes, c_nu), window_r=max(float(window_r), 0.0), nu_data=float(nu_data))
    kap = [t.kappa for t in shapes if t.ok]
    nu = c_nu / float(np.median(kap)) if math.isfinite(c_nu) and kap else math.nan
    if math.isfinite(shape.sd) and shape.sd > 0:
        # should the channel be read with s = 0 (not selected here, or not in every channel: track_foci), how far
        # that reading falls from the sharpest position per unit of s (unmodelled_asymmetry_sd_um)
        shape = replace(shape, sym_dz_ds=symmetric_reading_sensitivity(tracks, shape.sd, nu, shape.window_r))
    if shape.selected:
        shape = with_curve(profile_shape(tracks, shapes, shape, nu), q, nu)
        if shape.selected:
            shape = replace(shape, dz_ds=_peak_sensitivity(tracks, shape, q))
    return shape


def symmetric_reading_sensitivity(tracks, h: float, nu: float = math.nan, window_r: float = 0.0,
                                  n_tracks: int = 8) -> float:
    """|d(symmetric law's reading - sharpest position)/ds| in steps, about s = 0: a forward model.

    For up to ``n_tracks`` of the channel's tracks, the law with asymmetry ``+-h`` (as the e-SFR's window reads
    it, :func:`windowed_law`; ``nu``: the exact pupil OTF, NaN the ray law) is sampled at the track's own
    frames with the track's own fitted centre and blur rate, read by the symmetric law
    (:func:`symmetric_centre_um`) and compared with that law's sharpest position (:func:`model_points`). The
    symmetric fit follows most of the peak's move (its centre tracks the data), so this is far smaller than
    the peak's own d x_peak / ds / kappa (0.036 against 1.05 steps per unit s at a one-step tolerance), and it
    depends on where the frames fall: hence the track's own samples. Median of the absolute slopes."""
    if not (math.isfinite(h) and h > 0):
        return 0.0
    peaks = {}
    for sgn in (-1.0, 1.0):
        xp = model_points(sgn * h, 0.05, nu)[0]
        if not math.isfinite(xp):
            return 0.0
        peaks[sgn] = xp
    d = []
    for z, v in tracks[:: max(1, len(tracks) // n_tracks)][:n_tracks]:
        z, v = _increasing(z, v)
        start = _symmetric_start(z, v) if z.size >= 5 else None
        if start is None:
            continue
        pre, _, step, sym = start
        a = math.sqrt(max(float(sym.params[0]) * sym.scale, 1e-12))
        zc = float(z[pre.i_max] + float(sym.params[1]) * step)
        k_um = abs(float(sym.params[2])) / step  # x per µm
        if not k_um > 0:
            continue
        e = []
        for sgn in (-1.0, 1.0):
            # the law placed so that its sharpest position is the track's centre: the reading's offset from it
            x = k_um * (z - zc) + peaks[sgn]
            zs = symmetric_centre_um(z, a * np.abs(windowed_law(x, sgn * h, nu, window_r)))
            e.append(zs - zc)
        if all(math.isfinite(t) for t in e):
            d.append((e[1] - e[0]) / (2.0 * h * step))
    return float(np.median(np.abs(d))) if d else 0.0


def analyse_tracks(tracks, q: float = 0.05, *, fs_cyc_per_um: float = math.nan, wavelength_um: float = math.nan,
                   shape: PooledShape | None = None) -> tuple[list[TrackFocus], PooledShape]:
    """Best focus and tolerance of a channel's edge tracks (``(z_um, mtf_fs)`` pairs), with the asymmetry of
    spherical aberration pooled over them (:func:`channel_shape`, or the given ``shape``).

    Where the channel's data select it, every track gets its peak and tolerance from the law with that ``s``
    (:func:`shaped_track`), else from the symmetric law (:func:`analyse_track`, whose width on a symmetric
    curve is what :func:`fieldcal.measure.edge_tiles.track_width_model` models), its width freed of the e-SFR
    window's widening (:func:`window_width_ratio`)."""
    from dataclasses import replace

    if shape is None:
        shape = channel_shape(tracks, q, fs_cyc_per_um=fs_cyc_per_um, wavelength_um=wavelength_um)
    if not shape.selected:  # the law's fits of every track in one batch (defocus_fits)
        out = [analyse_track(z, v, q, fit=f) for (z, v), f in zip(tracks, defocus_fits(tracks, q))]
        if shape.window_r > 0:  # the symmetric law does not see the e-SFR window: its width read, corrected
            w = [t.depth_um / 2 for t in out if t.ok and t.depth_um > 0]
            steps = [float(np.median(np.diff(np.sort(np.asarray(z, float))))) for z, _ in tracks if len(z) > 1]
            ratio = (window_width_ratio(float(np.median(steps)), float(np.median(w)), q, shape.window_r,
                                        shape.nu_data) if w and steps else 1.0)
            out = [replace(t, tol_left_um=t.tol_left_um / ratio, tol_right_um=t.tol_right_um / ratio)
                   for t in out]
        return out, shape
    out = []
    for z, v in tracks:
        tk = shaped_track(z, v, shape, q)
        if not tk.ok and tk.reason.startswith("defocus fit"):
            tk = analyse_track(z, v, q)  # the shaped fit failed: the symmetric law's reading
        out.append(tk)
    return out, shape


def window_r_of(window_half_px: float, fs_cy_per_px: float) -> float:
    """``r = D / fs`` of :func:`windowed_law`: the e-SFR window's frequency shift ``D = 1 / (2 h)`` (h its
    half-length in px) over fs (cycles/px); 0 when either is unknown."""
    h, f = float(window_half_px), float(fs_cy_per_px)
    return 1.0 / (2.0 * h * f) if (math.isfinite(h) and h > 0 and math.isfinite(f) and f > 0) else 0.0


def window_width_ratio(step_um: float, width_um: float, q: float, r: float, nu: float = math.nan) -> float:
    """How wide :func:`analyse_track` (the symmetric law) reads a symmetric track through the e-SFR window:
    its width on the windowed law (:func:`windowed_law`, s = 0, at ``nu``; NaN: the geometric disc) over its
    width on the law itself, both sampled at the stack's step about a peak of half-width ``width_um`` (two
    sampling phases averaged, as :func:`fieldcal.measure.edge_tiles.track_width_model`). The read width is
    near the windowed one, so ``width_um`` is refined once by the ratio. 1 when ``r`` is 0 or a read fails."""
    if not (r > 0 and math.isfinite(step_um) and step_um > 0 and math.isfinite(width_um) and width_um > 0):
        return 1.0
    nu = nu if (math.isfinite(nu) and 0 < nu < 1) else math.nan
    _, _, xq = model_points(0.0, q, nu)
    if not math.isfinite(xq):
        return 1.0

    def read(delta: float, rr: float) -> float:
        out = []
        for phase in (0.0, 0.5):
            z = np.arange(-6.0 * delta, 6.0 * delta + step_um, step_um) + phase * step_um
            v = np.abs(windowed_law(xq * z / delta, 0.0, nu, rr))
            tk = analyse_track(z, 0.5 * v, q)
            out.append(0.5 * (tk.tol_left_um + tk.tol_right_um) if tk.ok else math.nan)
        return float(np.mean(out))

    ratio = 1.0
    for _ in range(2):
        delta = width_um / ratio
        w0, w1 = read(delta, 0.0), read(delta, r)
        if not (math.isfinite(w0) and math.isfinite(w1) and w0 > 0):
            return 1.0
        ratio = w1 / w0
    return float(ratio)


def _ray_x_q(q: float) -> float:
    """x where the geometric defocus law ``|O(x, 0)|`` falls to ``1 - q`` (the disc's ``x_q``)."""
    from ..optics.defocus import disc_x_at_contrast
    return float(disc_x_at_contrast(1.0 - float(q)))


def nu_of_width(width_um: float, q: float, fs_cyc_per_um: float, wavelength_um: float) -> float:
    """``nu = fs lambda N`` of the aberration-free pupil whose δ(fs, q) with diffraction is ``width_um``
    (:func:`fieldcal.optics.defocus.pupil_tolerance_um`; Brent's root in N). The blur rate a geometric law fits to
    a curve widened by diffraction reads N high (by 50 % at nu = 0.3); its width does not. NaN when the width is
    below the geometric δ at any N or the inputs are not finite."""
    from scipy.optimize import brentq

    from ..optics.defocus import _pupil_tolerance_um

    fs_mm, lam_nm = 1e3 * float(fs_cyc_per_um), 1e3 * float(wavelength_um)
    if not all(math.isfinite(v) and v > 0 for v in (width_um, q, fs_mm, lam_nm)):
        return math.nan

    def excess(nu: float) -> float:
        return _pupil_tolerance_um(fs_mm, float(q), nu / (fs_cyc_per_um * wavelength_um), lam_nm) - width_um

    lo, hi = 1e-3, 0.9
    if excess(lo) > 0 or excess(hi) < 0:
        return math.nan
    return float(brentq(excess, lo, hi, xtol=2e-3))


# --------------------------------------------------------------------------- field-wide error of the peaks
@dataclass(frozen=True)
class CommonMode:
    """The error a channel's edge peaks share whatever the edge (1 sigma, µm), measured on its tracks
    (:func:`law_common_mode`): no fit of a surface over the field can see it, so the band adds it at every
    point (:meth:`fieldcal.fit.discrepancy.Discrepancy.set_common_mode`)."""

    sd_um: float  # the total: the three terms below in quadrature
    law_um: float  # the law's own error: 0 (the shaped - symmetric gap is recorded as shift_um, not an error)
    shape_um: float  # the pooled asymmetry's own sd moved to the peak: dz/ds x sd(s)
    shift_um: float  # the median (shaped - symmetric) peak itself (signed; 0 under the symmetric law)
    n_tracks: int
    frames_um: float = 0.0  # the frames' shared error: delete-one-frame jackknife of the channel's mean peak

    def to_dict(self) -> dict:
        return {"sd_um": self.sd_um, "law_um": self.law_um, "shape_um": self.shape_um, "shift_um": self.shift_um,
                "frames_um": self.frames_um, "n_tracks": self.n_tracks}


def _leverages(z: np.ndarray, pre, params: np.ndarray, step: float) -> np.ndarray:
    """Leverage ``h_kk`` of each sample of a symmetric-law fit's window (``J (J^T J)^-1 J^T``, the fit's own
    coordinates: :func:`fieldcal.measure.throughfocus._fit_batch`)."""
    from .throughfocus import _model_eval

    u = (z[pre.lo:pre.hi + 1] - z[pre.i_max]) / step
    _, J = _model_eval("otf", u[None, :], np.asarray(params, float)[None, :], np.zeros(1))
    J = J[0]
    h = np.einsum("ij,jk,ik->i", J, np.linalg.pinv(J.T @ J), J)
    return np.clip(h, 0.0, 1.0)


def frame_jackknife_sd_um(tracks, max_jump_steps: float = 5.0) -> tuple[float, int]:
    """(sd µm, tracks used) of the error the frames share: a delete-one-frame jackknife of the channel's mean
    symmetric-law centre, less what the tracks' independent noise gives it.

    Deleting frame k moves track i's centre by ``D_ik`` (the law refitted with that sample's weight 0: one
    batched fit of every track and deletion), times ``1 - h_ik`` (Hinkley's weighted jackknife: a sample of
    leverage h moves a least-squares fit by 1 / (1 - h) times its influence when deleted; unweighted, the
    jackknife read a frame-level error 1.7x too large on defocus-law tracks, tests/test_edge_common_mode.py). The channel mean moves by ``I_k = mean_i D_ik``; the jackknife
    variance of the mean is ``(K-1)/K sum_k (I_k - mean I)^2``. Independent noise of the tracks adds
    ``(K-1)/K sum_k sum_i D_ik^2 / N^2`` to it (the cross terms vanish in expectation); what is left is the
    covariance of different tracks' responses to one frame: an error of that frame seen by every edge (the
    renderer's or the scene's frame-level error, a stage step, flicker the normalisation left, the law's misfit
    at the sampling phase the field's peaks share). A refit that jumps by more than ``max_jump_steps`` (a lost
    peak) is left out."""
    from .throughfocus import _fit_batch

    groups: dict[tuple, list[np.ndarray]] = {}
    for z, v in tracks:
        z, v = _increasing(z, v)
        if z.size >= 6:
            groups.setdefault(tuple(np.round(z, 6)), []).append(v)
    if not groups:
        return 0.0, 0
    z_all = np.unique(np.concatenate([np.asarray(k) for k in groups]))
    rows = []
    for key, vs in groups.items():
        z = np.asarray(key)
        step = float(np.median(np.diff(z)))
        pres, wts, owner, drop, E = [], [], [], [], []
        for v in vs:
            pre = _window(z, v)
            if pre is None:
                continue
            t = len(E)
            E.append(v * v)
            k = pre.hi - pre.lo + 1
            for j in range(-1, k):
                w = np.ones(k)
                if j >= 0:
                    w[j] = 0.0
                pres.append((t, pre))
                wts.append(w)
                owner.append(t)
                drop.append(pre.lo + j if j >= 0 else -1)
        if not E:
            continue
        fits = _fit_batch(z, np.asarray(E), pres, step, "otf", weights=wts)
        zc = np.array([z[p.i_max] + f.params[1] * step if f is not None else np.nan for (_, p), f in zip(pres, fits)])
        owner_a, drop_a = np.asarray(owner), np.asarray(drop)
        base = np.full(len(E), np.nan)
        lev: dict[int, np.ndarray] = {}
        for i in np.flatnonzero(drop_a < 0):
            if fits[i] is None:
                continue
            base[owner_a[i]] = zc[i]
            lev[int(owner_a[i])] = _leverages(z, pres[i][1], fits[i].params, step)
        D = np.zeros((len(E), z_all.size))
        col = np.searchsorted(z_all, z)
        for i in np.flatnonzero(drop_a >= 0):
            d = zc[i] - base[owner_a[i]]
            if math.isfinite(d) and abs(d) <= max_jump_steps * step:
                # Hinkley's weighted jackknife: a deleted sample's effect is 1 / (1 - h) times its influence
                D[owner_a[i], col[drop_a[i]]] = d * (1.0 - lev[int(owner_a[i])][drop_a[i] - pres[i][1].lo])
        rows.append(D[np.isfinite(base)])
    D = np.concatenate(rows) if rows else np.zeros((0, z_all.size))
    n, K = D.shape
    if n < 3 or K < 3:
        return 0.0, n
    c = (K - 1) / K
    mean_k = D.mean(axis=0)
    v_jk = c * float(np.sum((mean_k - mean_k.mean()) ** 2))
    v_noise = c * float(np.sum(D * D)) / n ** 2
    return math.sqrt(max(v_jk - v_noise, 0.0)), n


def symmetric_centre_um(z_um, mtf_fs) -> float:
    """The symmetric defocus law's centre of one track (µm; the fit every shaped fit starts from,
    :func:`_symmetric_start`), NaN where it fails."""
    z, v = _increasing(z_um, mtf_fs)
    start = _symmetric_start(z, v) if z.size >= 5 else None
    if start is None:
        return math.nan
    pre, _, step, sym = start
    return float(z[pre.i_max] + float(sym.params[1]) * step)


def unmodelled_asymmetry_sd_um(tracks, shape: PooledShape) -> float:
    """The field-wide error (1 sigma, µm) the symmetric law leaves when it is used although the channel's curves
    are known to be symmetric only to within the pooled asymmetry's sd: ``|dz/ds| x sd(s)``.

    Every track of the channel is read with ``s = 0``; the pooled fit (:func:`pool_shape`) bounds the
    asymmetry to ``+- sd``, and the sharpest position of a curve with asymmetry ``s`` lies ``dz/ds x s`` from the
    symmetric law's reading (``shape.sym_dz_ds``, probed about ``s = 0`` on the channel's own tracks:
    :func:`symmetric_reading_sensitivity`) — the same for every track: a field-wide error that no fit of the
    surface sees, and no frame jackknife either (it is not noise). Where the pooled law *is* selected the peak is
    read at ``s`` and the same ``dz/ds x sd`` is its share (``shape_um`` of :func:`law_common_mode`): one rule
    for both.
    The estimate ``s`` itself is not added: a channel whose ``s`` is significant but is read symmetric (the
    law is used only where every channel selects it) showed s = 1.3 +- 0.36 on fieldcal's geometric renderer,
    which has no spherical aberration, with its symmetric peaks right to 0.1 µm (``|dz/ds| s`` = 0.64 µm): an
    asymmetry of the curve that the primary-SA law misreads as a move of the peak."""
    if shape.selected or not (math.isfinite(shape.sd) and shape.sd > 0 and math.isfinite(shape.sym_dz_ds)):
        return 0.0
    steps = [float(np.median(np.diff(np.sort(np.asarray(z, float))))) for z, _ in tracks if len(z) > 1]
    if not steps:
        return 0.0
    return abs(shape.sym_dz_ds) * shape.sd * float(np.median(steps))


def law_common_mode(tracks, results, shape: PooledShape) -> CommonMode:
    """The field-wide error of a channel's track peaks, measured on the tracks themselves.

    Every track's peak is read through one law from the same frames, so an error of the law or of a frame
    moves them all alike, and a surface fit takes it for the surface. Three parts are measured on the stack:

    * **the frames**: :func:`frame_jackknife_sd_um`, what the tracks' peaks share of each frame's error;

    * **the law** (recorded, **not added** since the session-10 merge, see the comment in the code): where the
      channel's curves select spherical aberration's asymmetric law
      (:func:`shaped_track`), the peak it reads lies ``Delta`` from the symmetric law's centre
      (:func:`symmetric_centre_um`; ``Delta`` the median over the tracks: the same for every track up to its
      noise). Both laws fit the same samples and estimate the same sharpest position, and a real lens's curve
      need follow neither exactly (higher-order aberration, the wavelength mix, the pupil's apodisation). Two
      estimates of one quantity, neither known to be right: their spread about their mean, ``|Delta| / 2``, is
      the sd of the law's error. Under the symmetric law ``Delta`` is 0 by construction, and its own error
      on a symmetric curve is the sampling's, which the field's different phases average (docs/measurement.md
      "The band's field-wide term").
    * **the pooled asymmetry**: ``s`` is one number for the channel; its sd moves every peak by
      ``dz/ds x sd(s)`` (``shape.dz_ds``, in steps).

    Parameters
    ----------
    tracks : sequence of (z_um, mtf_fs) arrays, the channel's tracks.
    results : the :class:`TrackFocus` of each (:func:`analyse_tracks`), same order.
    shape : the channel's :class:`PooledShape`, as used for ``results``.
    """
    frames, n_fr = frame_jackknife_sd_um(tracks)
    if not shape.selected:
        sh = unmodelled_asymmetry_sd_um(tracks, shape)
        return CommonMode(math.hypot(sh, frames), 0.0, sh, 0.0, n_fr, frames)
    d, steps = [], []
    for (z, v), tk in zip(tracks, results):
        if not (tk.ok or tk.reason == TOLERANCE_UNREACHED) or not math.isfinite(tk.z_best_um):
            continue
        zs = symmetric_centre_um(z, v)
        if math.isfinite(zs):
            d.append(tk.z_best_um - zs)
            steps.append(float(np.median(np.diff(np.sort(np.asarray(z, float))))))
    if not d:
        return CommonMode(frames, 0.0, 0.0, 0.0, n_fr, frames)
    shift = float(np.median(d))
    # Not an error: under spherical aberration the symmetric law's centre is not an estimate of the sharpest
    # position, so the gap to it is the asymmetry the shaped law corrects, not the shaped law's error. Carried as
    # |shift| / 2 it made the clean-room renderer's SA edge bands 4-13x their errors once the e-SFR window was
    # modelled (sa08 half-width / RMS 12.6, coverage 1.00). Recorded (shift_um), not added.
    law = 0.0
    sh = abs(shape.dz_ds * shape.sd) * float(np.median(steps)) if math.isfinite(shape.sd) else 0.0
    return CommonMode(math.sqrt(law * law + sh * sh + frames * frames), law, sh, shift, len(d), frames)


def pool_frame_term(common: dict) -> dict:
    """The channels' :class:`CommonMode` with one frame term for all of them: the root mean square of their
    jackknife estimates (:func:`frame_jackknife_sd_um`).

    The frames are the stack's, so an error of a frame (its stage position, its exposure, the scene's motion)
    reaches every channel of it; one channel's jackknife has only about as many degrees of freedom as the
    track's window has frames, and clipped at 0 it reads nothing as often as twice the truth. The channels'
    mean variance is the better estimate of the frames' share in each."""
    from dataclasses import replace

    if not common:
        return dict(common)
    f2 = float(np.mean([v.frames_um ** 2 for v in common.values()]))
    out = {}
    for c, v in common.items():
        tot = math.sqrt(max(v.law_um ** 2 + v.shape_um ** 2 + f2, 0.0))
        out[c] = replace(v, frames_um=math.sqrt(f2), sd_um=tot)
    return out
