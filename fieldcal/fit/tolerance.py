"""Focus-tolerance model: how far from best focus contrast at fs stays within q of its peak, over the field.

Input: per-tile through-focus half-widths ``width_um`` measured at the calibration's MTF criterion (fs_cal, q_cal),
an :class:`fieldcal.optics.MTFCriterion` (saved as ``fs_cal_cyc_per_mm`` and ``q_cal``).
Per channel, a smooth model in the normalised radius about the sensor centre,
``w_c = w_c0 [+ w_c1 rho^2 [+ w_cx x + w_cy y]]`` (x, y, rho in units of the half-diagonal; each richer model
kept only if it lowers BIC), fitted robustly (SciPy ``least_squares`` with a soft-L1 loss: a few tiles with
a misjudged width do not drag the field). The linear terms are a decentred rho^2 field:
``c1 |r - d|^2 = c1 rho^2 - 2 c1 d . r + c1 |d|^2``, so the optical centre of the widths is fitted as linear
coefficients whose uncertainty the coefficient covariance carries. Why not centre the model on the surface's
optical centre: that is a MAP nuisance parameter of another model, often poorly determined (on the simulated
centred triplet at 320x180 it landed up to 46 px off the frame centre, differently in two scans of one lens),
and a width field fitted about it was taken as exact, so ``profile diff`` flagged the two scans' tolerances.

Conversion to other (fs, q) assumes the measured curve keeps its shape in defocus:

* shape "defocus-disc" (default): contrast(dz) = 2 J1(x)/x with x = pi fs |dz| / N (geometric defocus),
  so the half-width is x_q / (pi fs / N) with 2 J1(x_q)/x_q = 1 - q;
* shape "gaussian": contrast(dz) = exp(-dz^2 / 2 sigma^2 (fs)), half-width sigma sqrt(-2 ln(1 - q)).

Both give  w(fs, q) = w(fs_cal, q_cal) * (g(q) / g(q_cal)) * (fs_cal / fs)  (the 1/fs geometric-defocus law).

That law is the limit of low ``fs lambda N``; with diffraction δ changes less with fs (at F/8 and 80 cycles/mm
halving fs multiplies δ by ~1.5, not 2, so the 1/fs law would put a plan at 40 cycles/mm 30 % wide of the
truth). A fit that knows its F-number (``f_number``, set by the calibration from the stack) converts the
"defocus-disc" shape by the aberration-free pupil's own ratio instead
(:func:`fieldcal.optics.model_tolerance_ratio`: the smaller of its two band ends' ratios, so the converted width
errs narrow); at the calibration's own (fs, q) the width is the measured one either way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize

from ..errors import ParameterError
from ..optics import MTFCriterion, disc_x_at_contrast, model_tolerance_ratio, valid_q
from .data import FitError, ImageGeometry, TileData

TOLERANCE_FIT_FORMAT = "fieldcal-tolerance-fit/1"
SHAPES = ("defocus-disc", "gaussian")
#: the width models by number of coefficients: constant, + rho^2, + decentring (x, y)
MODEL_TERMS = {1: "w0", 2: "w0 + w1 rho^2", 4: "w0 + w1 rho^2 + wx x + wy y"}
#: domains of the width fit's residual (``fit_tolerance``): µm, or the defocus law's curvature 1 / w^2
RESIDUALS = ("width", "curvature")


def shape_factor(q: float, shape: str = "defocus-disc") -> float:
    """g(q): half-width in units of the shape's defocus scale (see module docstring)."""
    q = valid_q(q)
    if shape == "gaussian":
        return math.sqrt(-2.0 * math.log1p(-q))
    if shape == "defocus-disc":
        return disc_x_at_contrast(1.0 - q)
    raise ParameterError(f"unknown tolerance shape {shape!r}", field="shape", fix=f"use one of {SHAPES}")


@dataclass
class ToleranceFit:
    """Per-channel tolerance model over the field; ``tolerance_um(x, y, ch, fs, q)`` converts (fs, q)."""

    geometry: ImageGeometry
    centre_px: tuple[float, float]
    calibrated_at: MTFCriterion               # the (fs, q) the widths were measured at
    shape: str
    coef_um: dict[str, list[float]]          # w_c0 [, w_c1] in µm
    residual_sd_um: dict[str, float] = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)
    #: image-side F-number of the stack (None: unknown; (fs, q) then convert by the geometric law)
    f_number: float | None = None
    #: the stack's recorded wavelength per channel (nm), if any (else the channels' nominal bands)
    wavelength_nm: dict | None = None

    def _rho2(self, x_px, y_px):
        r = self.geometry.half_diagonal_px
        return ((np.asarray(x_px, float) - self.centre_px[0]) ** 2 + (np.asarray(y_px, float) - self.centre_px[1]) ** 2) / r ** 2

    def design(self, x_px, y_px, n_coef: int) -> np.ndarray:
        """(..., n_coef) design of the width model with ``n_coef`` coefficients (1, 2 or 4) at pixels."""
        x, y = np.broadcast_arrays(np.asarray(x_px, float), np.asarray(y_px, float))
        r = self.geometry.half_diagonal_px
        terms = [np.ones_like(x), self._rho2(x, y), (x - self.centre_px[0]) / r, (y - self.centre_px[1]) / r]
        if n_coef not in MODEL_TERMS:
            raise ParameterError(f"a width model has {n_coef} coefficients", field="tolerance.coef_um",
                                 fix=f"give {', '.join(map(str, MODEL_TERMS))} coefficients per channel")
        return np.stack(terms[:n_coef], axis=-1)

    def width_cal_um(self, x_px, y_px, channel: str):
        """Fitted half-width (µm) at the calibration's (fs, q)."""
        if channel not in self.coef_um:
            raise ParameterError(f"no tolerance model for channel '{channel}'", field="channel",
                                 fix=f"use one of {', '.join(self.coef_um)}")
        c = np.asarray(self.coef_um[channel], dtype=np.float64)
        w = self.design(x_px, y_px, c.size) @ c
        return np.maximum(w, 1e-3 * c[0] if c[0] > 0 else 1e-6)  # a width is positive

    def tolerance_um(self, x_px, y_px, channel: str, fs_cyc_per_mm: float, q: float):
        """Half-width (µm) of the defocus range where MTF(fs) stays within q of its peak."""
        crit, cal = MTFCriterion(fs_cyc_per_mm, q), self.calibrated_at
        if self.f_number and self.shape == "defocus-disc":
            scale = model_tolerance_ratio(crit, cal, float(self.f_number), channel, self.wavelength_nm)
        else:
            scale = (shape_factor(crit.q, self.shape) / shape_factor(cal.q, self.shape)
                     * (cal.fs_cyc_per_mm / crit.fs_cyc_per_mm))
        return self.width_cal_um(x_px, y_px, channel) * scale

    def to_dict(self) -> dict[str, Any]:
        return {"format": TOLERANCE_FIT_FORMAT, "geometry": self.geometry.to_dict(),
                "centre_px": list(self.centre_px), "fs_cal_cyc_per_mm": self.calibrated_at.fs_cyc_per_mm,
                "q_cal": self.calibrated_at.q, "shape": self.shape, "coef_um": self.coef_um,
                "residual_sd_um": self.residual_sd_um, "diagnostics": self.diagnostics,
                **({"f_number": float(self.f_number)} if self.f_number else {}),
                **({"wavelength_nm": dict(self.wavelength_nm)} if self.wavelength_nm else {})}

    @classmethod
    def from_dict(cls, d: dict[str, Any], path=None) -> "ToleranceFit":
        from ..errors import SpecError
        if not isinstance(d, dict) or d.get("format") != TOLERANCE_FIT_FORMAT:
            raise SpecError(f"not a {TOLERANCE_FIT_FORMAT} block", path=path, field="tolerance",
                            fix="write it with ToleranceFit.to_dict()")
        try:
            return cls(ImageGeometry.from_dict(d["geometry"]), tuple(d["centre_px"]),
                       MTFCriterion(float(d["fs_cal_cyc_per_mm"]), float(d["q_cal"])), str(d["shape"]),
                       {c: [float(v) for v in cs] for c, cs in d["coef_um"].items()},
                       dict(d.get("residual_sd_um", {})), dict(d.get("diagnostics", {})),
                       _positive_or_none(d.get("f_number")),
                       dict(d["wavelength_nm"]) if isinstance(d.get("wavelength_nm"), dict) else None)
        except (KeyError, TypeError, ValueError, ParameterError) as e:
            raise SpecError(f"malformed tolerance fit ({e})", path=path, field="tolerance",
                            fix="regenerate the profile") from None


def _positive_or_none(v) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) and f > 0 else None


def fit_tolerance(tiles: TileData, geometry: ImageGeometry, calibrated_at: MTFCriterion,
                  centre_px: tuple[float, float] | None = None, shape: str = "defocus-disc",
                  min_tiles: int = 4, source: str | None = None, shared_channels: bool = False,
                  f_number: float | None = None, wavelength_nm: dict | None = None,
                  residuals: str = "width") -> ToleranceFit:
    """Fit the per-channel width model from tiles whose ``width_um`` was measured at ``calibrated_at``.

    ``f_number`` (and the stack's recorded ``wavelength_nm`` per channel, if any) let the fit convert its widths
    to another (fs, q) with diffraction (module docstring); without them it uses the geometric law.

    ``shared_channels``: also try one width model for every channel (:func:`_shared_model`) and keep it when
    its BIC beats the per-channel models'. For widths that measure the defocus law itself (slanted-edge
    MTF(fs) through focus): its blur rate is the aperture's, 1/N, at every wavelength, so the channels' δ
    differ only where an aberration makes them, and the data say whether they do.

    ``residuals``: the domain the robust fit measures misfit in (:data:`RESIDUALS`). "width" (µm) for widths
    whose error is symmetric in µm; "curvature" for widths read by the defocus law's fitted blur rate k
    (``w = x_q / (pi fs k)``): the data fix the peak's curvature ``a k^2`` (linear in the samples), so the error
    is symmetric in ``1 / w^2`` and skewed in w — a flat, noisy track reads 2-5x wide, never as far narrow. On
    slanted-edge stacks of 7-9 frames at a step near δ (random lenses 4 and 7 of bench_edge_calibration) the
    tracks' widths had quantiles 0.79 / 1.02 / 1.92 of the true δ (10 / 50 / 90 %), their 1 / w^2 0.27 / 0.97 /
    1.62: a fit in µm read δ 3-5 % wide, one in curvature within 1 %. The model stays linear in w (same
    coefficients, same conversion); only the residual is ``(w_ref / model)^2 - (w_ref / w)^2``, scaled by its
    MAD.
    """
    if residuals not in RESIDUALS:
        raise ParameterError(f"unknown residual domain {residuals!r}", field="residuals",
                             fix=f"use one of {RESIDUALS}")
    shape_factor(calibrated_at.q, shape)  # validates the shape
    centre = centre_px if centre_px is not None else geometry.centre_px
    probe = ToleranceFit(geometry, (float(centre[0]), float(centre[1])), calibrated_at, shape, {})
    coef, rsd, diag = {}, {}, {}
    fit_terms = []
    for c in tiles.channels:
        m = (tiles.channel == c) & np.isfinite(tiles.width_um)
        if m.sum() < min_tiles:
            raise FitError(f"channel {c} has {int(m.sum())} tiles with a measured width; need {min_tiles}",
                           path=source, field="width_um", fix="measure through-focus widths on more tiles")
        w = tiles.width_um[m]
        med = float(np.median(w))
        misfit = _misfit(w, residuals)
        cands = []
        for n_coef in MODEL_TERMS:
            if m.sum() < n_coef + 2 or not _spanned(tiles.x_px[m], tiles.y_px[m], geometry, n_coef):
                continue
            A = probe.design(tiles.x_px[m], tiles.y_px[m], n_coef)
            res = optimize.least_squares(lambda p: misfit(A @ p), np.r_[med, np.zeros(n_coef - 1)],
                                         loss="soft_l1")
            rss = float(np.sum(res.fun ** 2))
            n = w.size
            bic = n * math.log(max(rss / n, 1e-300)) + n_coef * math.log(n)
            cands.append((bic, n_coef, res.x, float(np.std(A @ res.x - w))))
        bic, n_coef, x, sd = min(cands, key=lambda t: t[0])
        coef[c] = [float(v) for v in x]
        rsd[c] = sd
        diag[c] = {"n_tiles": int(m.sum()), "order": min(n_coef - 1, 1), "model": MODEL_TERMS[n_coef],
                   "bic": {int(k): b for b, k, *_ in cands}, "residuals": residuals}
        # the fit's log-likelihood term and size, for the BIC of all channels' data together (shared_channels)
        fit_terms.append((bic - n_coef * math.log(m.sum()), n_coef, int(m.sum())))
    n_all = sum(n for *_, n in fit_terms)
    per_channel_bic = sum(ll + k * math.log(n_all) for ll, k, _ in fit_terms)
    if shared_channels and len(tiles.channels) > 1:
        shared = _shared_model(tiles, probe, residuals)
        if shared is not None:
            s_bic, s_coef, s_sd, s_diag = shared
            diag["channels"] = {"rule": "one width model for every channel when its BIC is lower (the defocus "
                                        "law's blur rate is the aperture's at every wavelength)",
                                "bic_shared": s_bic, "bic_per_channel": per_channel_bic,
                                "shared": bool(s_bic < per_channel_bic), **s_diag}
            if s_bic < per_channel_bic:
                coef = {c: list(s_coef) for c in tiles.channels}
                rsd = {c: s_sd[c] for c in tiles.channels}
    return ToleranceFit(geometry, (float(centre[0]), float(centre[1])), calibrated_at, shape, coef, rsd, diag,
                        _positive_or_none(f_number), dict(wavelength_nm) if isinstance(wavelength_nm, dict) else None)


#: widths per channel a quick calibration needs before its tolerance model replaces the defocus model. Quick's
#: widths come from the band-pass strip (measure/fs_strip.py, sized for 12 tiles): on a 1920x1080 triplet only
#: 4-5 of its 14 tiles per channel kept a width (the rest had more focus spread than width,
#: fit/width_window.py), δ's standard error was 17 %, and the plan paid for it with 48 frames where the model
#: (and the optimum) took 38. Frames up to ~0.4 MP band-pass every tile row and keep dozens.
MIN_QUICK_WIDTHS = 12

#: share of the frame's width and height the widths' tiles must span for the decentring terms (wx x + wy y)
MIN_SPAN_FOR_TILT = 0.5


def _spanned(x_px, y_px, geometry: ImageGeometry, n_coef: int) -> bool:
    """Whether tiles at (x_px, y_px) span the model with ``n_coef`` coefficients: the linear (decentring) terms
    need widths across at least :data:`MIN_SPAN_FOR_TILT` of the frame in x and in y. Quick effort's widths come
    from one strip of tiles through the middle (measure/fs_strip.py), where a tilt across the strip is not
    measured and would be extrapolated to the corners from a few tiles' noise; the constant and rho^2 terms
    are (the strip runs from the centre to the frame's sides)."""
    if n_coef < 4:
        return True
    x = np.asarray(x_px, dtype=np.float64)
    y = np.asarray(y_px, dtype=np.float64)
    if x.size == 0:
        return False
    return bool(np.ptp(x) >= MIN_SPAN_FOR_TILT * geometry.width_px
                and np.ptp(y) >= MIN_SPAN_FOR_TILT * geometry.height_px)


def _misfit(w: np.ndarray, residuals: str = "width"):
    """The scaled residual of a width model's values against widths ``w`` (``fit_tolerance``'s ``residuals``):
    in µm, or in the curvature ``(w_ref / w)^2`` (w_ref the median width), each over its own MAD."""
    w = np.asarray(w, dtype=np.float64)
    med = float(np.median(w))
    if residuals == "curvature":
        u = (med / w) ** 2
        mu = float(np.median(u))
        scale = max(1.4826 * float(np.median(np.abs(u - mu))), 1e-3 * mu)
        floor = 1e-3 * med  # a model width is positive: its curvature stays finite

        return lambda model: ((med / np.maximum(model, floor)) ** 2 - u) / scale
    scale = max(1.4826 * float(np.median(np.abs(w - med))), 1e-3 * med)
    return lambda model: (model - w) / scale


def _shared_model(tiles: TileData, probe: ToleranceFit, residuals: str = "width"):
    """(BIC, coefficients, residual sd per channel, diagnostics) of the best width model shared by every
    channel, or None. Each channel keeps its own noise scale (the soft-L1 scale and the BIC's variance are per
    channel, as in the per-channel fits), so its BIC compares with the per-channel fits' on all channels' data
    together (their log-likelihood terms summed, every coefficient penalised by ln of the total count): the
    same data, only the coefficients are shared."""
    parts = []
    for c in tiles.channels:
        m = (tiles.channel == c) & np.isfinite(tiles.width_um)
        w = tiles.width_um[m]
        parts.append((c, m, w, _misfit(w, residuals)))
    n_tot = sum(w.size for _, _, w, _ in parts)
    med_all = float(np.median(np.concatenate([w for _, _, w, _ in parts])))
    best = None
    for n_coef in MODEL_TERMS:
        if min(w.size for _, _, w, _ in parts) < n_coef + 2:
            continue
        if not all(_spanned(tiles.x_px[m], tiles.y_px[m], probe.geometry, n_coef) for _, m, _, _ in parts):
            continue
        designs = [probe.design(tiles.x_px[m], tiles.y_px[m], n_coef) for _, m, _, _ in parts]

        def scaled(p):
            return np.concatenate([fn(A @ p) for A, (_, _, _, fn) in zip(designs, parts)])

        res = optimize.least_squares(scaled, np.r_[med_all, np.zeros(n_coef - 1)], loss="soft_l1")
        bic, sd = n_coef * math.log(n_tot), {}
        for A, (c, _, w, fn) in zip(designs, parts):
            r = fn(A @ res.x)
            bic += w.size * math.log(max(float(np.sum(r * r)) / w.size, 1e-300))
            sd[c] = float(np.std(A @ res.x - w))
        if best is None or bic < best[0]:
            best = (bic, [float(v) for v in res.x], sd, {"shared_model": MODEL_TERMS[n_coef]})
    return best
