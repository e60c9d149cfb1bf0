"""Focus tolerance δ (half-width of the stage range keeping MTF(fs) within q of its peak) and MTF loss.

δ comes from the profile's measured through-focus width when it has one (``has_measured_tolerance``); otherwise
from the geometric defocus disc at the profile's F-number (:func:`fieldcal.optics.focus_tolerance_um`), and the
plan says which. Why the disc and not the pupil with diffraction (:func:`fieldcal.optics.model_tolerance_um`,
1.08-1.5x wider at F/2-F/8 and 60-80 cycles/mm): with nothing measured, the model must not claim more depth than
any lens of that F-number has, and a lens whose defocus blur is geometric (a large-aperture lens, or a renderer
that draws defocus as a disc or a Gaussian) has the disc's δ; the pupil's δ would leave its pixels outside the
tolerance (98.8 % on the 1080p triplet at quick, docs/benchmarks.md "bench_quickdelta"). The pupil model is the
upper bound a measured texture width is capped at (:func:`cap_texture_tolerance`), where the measurement says
how wide the lens really is. The MTF loss of a defocus ``dz`` at a
pixel with tolerance δ uses the geometric defocus disc's shape rescaled so that the loss is exactly q at
``|dz| = δ`` (so measured and modelled widths give consistent losses; the shape between 0 and δ is all it
takes from the disc).
The MTF criterion (fs, q) arrives as a :class:`fieldcal.optics.MTFCriterion`, validated where it is built.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special

from ..errors import ParameterError
from ..optics import LensModel, MTFCriterion, defocus_otf, focus_tolerance_um as disc_tolerance_um
from ..optics import model_tolerance_um as pupil_model_tolerance_um

MODEL_SOURCE = ("defocus model from the F-number: the geometric defocus disc, a lower bound on any lens of that "
                "F-number (no measured through-focus width)")
MEASURED_SOURCE = "measured through-focus width (profile)"


@dataclass(frozen=True)
class WidthBias:
    """How a measurement's through-focus width, converted to δ(fs, q), compares with the true δ on simulated
    lenses: the ratio (profile δ / true δ) is the largest of the ``lines`` ``intercept + slope * fs_px`` (one per
    simulator path: the upper envelope, so δ is not over-wide on either) with fs_px the calibration's fs in
    cycles per pixel (clipped to the measured ``fs_px_range``; an unknown fs_px takes the range's top, the
    narrowest δ), with a lens-to-lens relative sd ``rel_sd`` about its line. The plan divides by the ratio and carries
    ``rel_sd`` as δ's systematic uncertainty: one draw per lens, common to every pixel, that no fit to the
    lens's own tiles can see."""

    lines: tuple[tuple[float, float], ...]  # (intercept, slope per cycle/px)
    rel_sd: float
    fs_px_range: tuple[float, float]
    measured: str  # where the figures come from

    def factor(self, fs_cyc_per_px: float | None) -> float:
        lo, hi = self.fs_px_range
        f = hi if fs_cyc_per_px is None or not math.isfinite(fs_cyc_per_px) else min(max(fs_cyc_per_px, lo), hi)
        return max(a + b * f for a, b in self.lines)


# Measured with ``benchmarks/bench_plan_coverage.py`` (docs/benchmarks.md "bench_plan_coverage", the analysis in
# docs/planning.md "Measured tolerance") after the tile widths' window correction (fit/width_window.py: a tile
# on a curved field sums pixels focused at different z, which widened its curve by up to 12 % at the corners):
# the triplet and 6 random lenses, F/1.7-F/3.8, both simulator paths (geometric and wave optics, with and
# without spherical aberration), fs = 0.1-0.4 cycles/px, q = 0.05, 34 texture calibrations (one more, a
# scan reaching only 1 δ past the field's range at 0.1 cycles/px, read 1.038 and is left out). The ratio rises
# with fs in cycles/px, 0.92-0.94 at 0.1 to 1.035-1.07 at 0.4; a band-pass model (the log-Gabor ring over a
# 1/f^2 scene with the pixel aperture, fitted as the measurement fits it) gives 0.94 -> 1.02 of that rise.
# Lines: geometric 0.898 + 0.376 fs_px (residual sd 0.009), wave 0.888 + 0.465 fs_px (sd 0.013); before the
# window correction the lens-to-lens sd was 0.021-0.022 and the geometric line 0.905 + 0.407 fs_px. rel_sd:
# the wave line's residual sd and half the gap between the two paths at 0.3 cycles/px (0.0085) in quadrature,
# since a lens from neither simulator may sit anywhere between them. e-SFR widths measure MTF(fs) itself:
# 0.98-1.03 of the true δ.
TEXTURE_WIDTH = WidthBias(((0.898, 0.376), (0.888, 0.465)), 0.016, (0.1, 0.45),
                          "bench_plan_coverage: 34 texture calibrations after the window correction, fs "
                          "0.1-0.4 cycles/px, both optics paths")
ESFR_WIDTH = WidthBias(((1.0, 0.0),), 0.02, (0.05, 0.45),
                       "bench_plan_coverage: e-SFR calibrations, fs 0.1-0.4 cycles/px, both optics paths")
ESFR_SOURCE = MEASURED_SOURCE + f" from slanted edges (e-SFR), ± {ESFR_WIDTH.rel_sd:.0%} lens to lens"


def texture_source(factor: float, capped: float = 0.0) -> str:
    cap = (f"; at most the aberration-free pupil's δ at the F-number ({capped:.0%} of the field's points capped)"
           if capped > 0 else "; at most the aberration-free pupil's δ at the F-number")
    return (MEASURED_SOURCE + f" from the texture focus measure, / {factor:.3f} (its measured bias at the "
            f"calibration's fs), ± {TEXTURE_WIDTH.rel_sd:.0%} lens to lens" + cap)


def cap_texture_tolerance(tol_um, model_um: float) -> tuple[np.ndarray, float]:
    """A texture profile's δ capped at the aberration-free pupil's δ at the F-number, and the share capped.

    Why: a texture tile's band-pass curve is a sum of MTF(f; z)² over a band of frequencies, orientations and
    the tile's pixels. Everything that sum adds beyond one pixel's MTF(fs; z) only widens the curve: best
    focus spread over the tile (corrected in fit/width_window.py where the tile can tell its width), tangential
    and sagittal foci split by astigmatism inside every pixel (the orientation average of an elliptical
    defocus disc, 4-10 % wider at T - S = 2-3 δ), and a band weighted to lower frequencies by the pixel
    aperture and any in-focus blur the larger it is in pixels (at 1920 x 1080 the triplet's in-focus blur is 3x
    wider in pixels than at 640 px). None of these narrows δ, so a texture width above the aberration-free δ
    cannot be told from one of those spreads, and the model is the honest value there. The model is the
    pupil's own through-focus MTF(fs) with diffraction (:func:`fieldcal.optics.model_tolerance_um`), at the
    short end of the channel's band: the geometric defocus disc it replaced sits 1.1-1.6x below the true δ at
    F/2.8-F/8 and 80 cycles/mm, and capped measured widths there (sessions 8-9: 5 frames for an optimum of 3
    at F/5.6). Aberrations can make a lens's δ wider than the model; the cap then costs frames, never
    coverage."""
    tol = np.asarray(tol_um, dtype=np.float64)
    if not (math.isfinite(model_um) and model_um > 0):
        return tol, 0.0
    over = np.isfinite(tol) & (tol > model_um)
    return np.where(over, model_um, tol), float(np.mean(over)) if over.size else 0.0


def check_confidence(p) -> float | None:
    if p is None:
        return None
    try:
        pp = float(p)
    except (TypeError, ValueError):
        pp = math.nan
    if not math.isfinite(pp) or not (0.0 < pp < 1.0):
        raise ParameterError(f"confidence {p!r} must be in (0, 1)", field="confidence", fix="give e.g. --confidence 0.95")
    return pp


def width_bias(profile) -> tuple[WidthBias, float] | None:
    """The width measurement's bias record of a calibrated profile with measured widths and its factor at the
    calibration's fs (cycles/px); None for models, truths and synthetic profiles (their δ is exact). Profiles
    that do not say how they measured are texture."""
    if not bool(getattr(profile, "has_measured_tolerance", False)):
        return None
    cal = getattr(profile, "calibration", None)
    if not isinstance(cal, dict):
        return None
    bias = ESFR_WIDTH if cal.get("measurement", "focus-measure") == "esfr" else TEXTURE_WIDTH
    fs_px = None
    try:
        fs_px = float(cal["fs_cyc_per_mm"]) * float(profile.pixel_pitch_um) / 1000.0
    except (KeyError, TypeError, ValueError, AttributeError):
        pass
    return bias, bias.factor(fs_px)


def channel_model_tolerance_um(profile: LensModel, channel: str, crit: MTFCriterion) -> float:
    """The model δ (µm) of ``channel`` at the profile's F-number: the aberration-free pupil with diffraction at
    the stack's recorded wavelength (``profile.optics["wavelength_nm"]``), else the channel band's short end."""
    optics = getattr(profile, "optics", None)
    recorded = optics.get("wavelength_nm") if isinstance(optics, dict) else None
    return pupil_model_tolerance_um(crit, float(profile.f_number), channel, recorded)


def tolerance_um(profile: LensModel, x, y, channel: str, crit: MTFCriterion) -> tuple[np.ndarray, str]:
    """Per-pixel δ (µm) and where it came from. Non-finite or non-positive values fall back to the model.

    A calibrated profile's measured widths are divided by their measurement's bias (:func:`width_bias`)."""
    shape = np.broadcast(np.asarray(x), np.asarray(y)).shape
    measured = bool(profile.has_measured_tolerance)
    tol = np.asarray(profile.focus_tolerance_um(x, y, channel, crit.fs_cyc_per_mm, crit.q), dtype=np.float64)
    tol = np.broadcast_to(tol, shape).copy()
    measured_src = MEASURED_SOURCE
    wb = width_bias(profile)
    if wb is not None:
        bias, factor = wb
        tol = tol / factor
        if bias is ESFR_WIDTH:
            measured_src = ESFR_SOURCE
        else:
            tol, capped = cap_texture_tolerance(tol, channel_model_tolerance_um(profile, channel, crit))
            measured_src = texture_source(factor, capped)
    bad = ~np.isfinite(tol) | (tol <= 0)
    if bad.all():
        return np.full(shape, disc_tolerance_um(crit, float(profile.f_number))), MODEL_SOURCE
    if bad.any():
        tol[bad] = disc_tolerance_um(crit, float(profile.f_number))
        return tol, (measured_src + "; model where not measured") if measured else MODEL_SOURCE
    return tol, measured_src if measured else MODEL_SOURCE


def tolerance_sd_um(profile: LensModel, x, y, channel: str, crit: MTFCriterion, tol_um) -> np.ndarray:
    """sd (µm) of the plan's δ at each point: the width fit's standard error (the profile's
    ``focus_tolerance_sd_um``, tiles independent) and the measurement's lens-to-lens systematic
    (``rel_sd`` of :func:`width_bias`) in quadrature. 0 where δ is exact (models, truths)."""
    tol = np.asarray(tol_um, dtype=np.float64)
    if not bool(getattr(profile, "has_measured_tolerance", False)):
        return np.zeros_like(tol)
    wb = width_bias(profile)
    rel_sd, factor = (wb[0].rel_sd, wb[1]) if wb is not None else (0.0, 1.0)
    stat = np.zeros_like(tol)
    sd_fn = getattr(profile, "focus_tolerance_sd_um", None)
    if callable(sd_fn):
        stat = np.broadcast_to(np.asarray(sd_fn(x, y, channel, crit.fs_cyc_per_mm, crit.q), dtype=np.float64),
                               tol.shape) / factor
        stat = np.nan_to_num(stat, nan=0.0, posinf=0.0)
    return np.hypot(stat, rel_sd * tol)


def lower_tolerance_um(tol_um, tol_sd_um, level: float) -> np.ndarray:
    """Lower end of δ's central ``level`` credible interval (Gaussian), at least 0."""
    zq = special.ndtri(0.5 + 0.5 * level)
    return np.maximum(np.asarray(tol_um, dtype=np.float64) - zq * np.asarray(tol_sd_um, dtype=np.float64), 0.0)


def band_halfwidth_um(profile, x, y, channel: str, z_map, level: float) -> np.ndarray:
    """Half-width of the credible band about the MAP surface (the larger side, so the shrink is symmetric)."""
    lo, hi = profile.best_focus_interval_um(x, y, channel, level=level)
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    u = np.maximum(hi - z_map, z_map - lo)
    return np.maximum(np.nan_to_num(u, nan=0.0, posinf=np.inf), 0.0)


def sigma_from_halfwidth(u, level: float) -> np.ndarray:
    """Gaussian σ whose central ``level`` interval has half-width u."""
    zq = special.ndtri(0.5 + 0.5 * level)
    return np.asarray(u, dtype=np.float64) / zq


def mtf_loss(dz_um, tol_um, crit: MTFCriterion, f_number: float) -> np.ndarray:
    """1 - MTF(fs, dz)/MTF(fs, 0) with the defocus disc's shape rescaled to reach q at |dz| = tol_um."""
    tol_model = disc_tolerance_um(crit, f_number)
    tol = np.maximum(np.asarray(tol_um, dtype=np.float64), 1e-12)
    dz_eff = np.asarray(dz_um, dtype=np.float64) * (tol_model / tol)
    return 1.0 - np.abs(defocus_otf(crit.fs_cyc_per_mm, dz_eff, f_number))


def coverage_probability(z_frame, z_map, tol, sigma, tol_sd=0.0, n_nodes: int = 9) -> np.ndarray:
    """P(|z_frame - Z| <= Δ) for Z ~ N(z_map, sigma^2) and Δ ~ N(tol, tol_sd^2) independent (sigma = 0:
    certain position; tol_sd = 0: exact δ). Over Δ by Gauss-Hermite quadrature, Δ clipped at 0."""
    z_frame = np.asarray(z_frame, dtype=np.float64)
    z_map = np.asarray(z_map, dtype=np.float64)
    tol = np.asarray(tol, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    tol_sd = np.asarray(tol_sd, dtype=np.float64)
    d = z_frame - z_map
    s = np.where(sigma > 0, sigma, 1.0)

    def p_at(t):
        certain = (np.abs(d) <= t + 1e-9).astype(np.float64)
        p = special.ndtr((d + t) / s) - special.ndtr((d - t) / s)
        return np.where(sigma > 0, p, certain)

    if not np.any(tol_sd > 0):
        return p_at(tol)
    nodes, w = np.polynomial.hermite_e.hermegauss(n_nodes)
    w = w / w.sum()
    out = np.zeros(np.broadcast(d, tol, tol_sd, sigma).shape)
    for ti, wi in zip(nodes, w):
        out += wi * p_at(np.maximum(tol + tol_sd * ti, 0.0))
    return out


def expected_mtf_loss(z_frame, z_map, tol, sigma, crit: MTFCriterion, f_number: float, n_nodes: int = 21):
    """E[MTF loss] over z_true ~ N(z_map, sigma^2) by Gauss-Hermite quadrature."""
    t, w = np.polynomial.hermite_e.hermegauss(n_nodes)
    w = w / w.sum()
    d = np.asarray(z_frame, dtype=np.float64) - np.asarray(z_map, dtype=np.float64)
    s = np.asarray(sigma, dtype=np.float64)
    out = np.zeros(np.broadcast(d, s).shape)
    for ti, wi in zip(t, w):
        out += wi * mtf_loss(d - s * ti, tol, crit, f_number)
    return out
