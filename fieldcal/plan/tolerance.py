"""Focus tolerance δ (half-width of the stage range keeping MTF(fs) within q of its peak) and MTF loss.

δ comes from the profile's measured through-focus width when it has one (``has_measured_tolerance``); otherwise
from the geometric defocus model with the profile's F-number (:func:`fieldcal.optics.focus_tolerance_um`), and the
plan says which. The MTF loss of a defocus ``dz`` at a pixel with tolerance δ uses the defocus model's shape
rescaled so that the loss is exactly q at ``|dz| = δ`` (so measured and modelled widths give consistent losses).
The MTF criterion (fs, q) arrives as a :class:`fieldcal.optics.MTFCriterion`, validated where it is built.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import special

from ..errors import ParameterError
from ..optics import LensModel, MTFCriterion, defocus_otf, focus_tolerance_um as model_tolerance_um

MODEL_SOURCE = "defocus model from the F-number (no measured through-focus width)"
MEASURED_SOURCE = "measured through-focus width (profile)"
# Widths from the texture focus measure, converted to δ(fs, q) through the defocus shape, come out too wide
# against the true MTF tolerance: median ratio 1.011-1.050 on the triplet and two random lenses at 480x270
# (docs/benchmarks.md "bench_edge_calibration", --scene chart), 1.05-1.12 in issue 13's runs on other lenses,
# where plans left up to 6.5 % of pixels outside. Texture-measured δ is divided by this factor (the top of that
# range), so the plan errs towards one frame too many; e-SFR (slanted-edge) widths measure MTF(fs) itself
# (ratio 0.99-1.04) and are used as they are.
TEXTURE_WIDTH_BIAS = 1.12
TEXTURE_SOURCE = MEASURED_SOURCE + f" from the texture focus measure, / {TEXTURE_WIDTH_BIAS} (its measured bias)"


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


def tolerance_um(profile: LensModel, x, y, channel: str, crit: MTFCriterion) -> tuple[np.ndarray, str]:
    """Per-pixel δ (µm) and where it came from. Non-finite or non-positive values fall back to the model."""
    shape = np.broadcast(np.asarray(x), np.asarray(y)).shape
    model = model_tolerance_um(crit, float(profile.f_number))
    measured = bool(profile.has_measured_tolerance)
    tol = np.asarray(profile.focus_tolerance_um(x, y, channel, crit.fs_cyc_per_mm, crit.q), dtype=np.float64)
    tol = np.broadcast_to(tol, shape).copy()
    measured_src = MEASURED_SOURCE
    if measured and _texture_widths(profile):
        tol = tol / TEXTURE_WIDTH_BIAS
        measured_src = TEXTURE_SOURCE
    bad = ~np.isfinite(tol) | (tol <= 0)
    if bad.all():
        return np.full(shape, model), MODEL_SOURCE
    if bad.any():
        tol[bad] = model
        return tol, (measured_src + "; model where not measured") if measured else MODEL_SOURCE
    return tol, measured_src if measured else MODEL_SOURCE


def _texture_widths(profile) -> bool:
    """True for a calibrated profile whose widths came from the texture focus measure (not slanted edges)."""
    cal = getattr(profile, "calibration", None)
    return isinstance(cal, dict) and cal.get("measurement", "focus-measure") != "esfr"


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
    """1 - MTF(fs, dz)/MTF(fs, 0) with the defocus model rescaled to reach q at |dz| = tol_um."""
    tol_model = model_tolerance_um(crit, f_number)
    tol = np.maximum(np.asarray(tol_um, dtype=np.float64), 1e-12)
    dz_eff = np.asarray(dz_um, dtype=np.float64) * (tol_model / tol)
    return 1.0 - np.abs(defocus_otf(crit.fs_cyc_per_mm, dz_eff, f_number))


def coverage_probability(z_frame, z_map, tol, sigma) -> np.ndarray:
    """P(|z_frame - z_true| <= tol) for z_true ~ N(z_map, sigma^2) (sigma = 0: certain)."""
    z_frame = np.asarray(z_frame, dtype=np.float64)
    z_map = np.asarray(z_map, dtype=np.float64)
    tol = np.asarray(tol, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    d = z_frame - z_map
    certain = (np.abs(d) <= tol + 1e-9).astype(np.float64)
    s = np.where(sigma > 0, sigma, 1.0)
    p = special.ndtr((d + tol) / s) - special.ndtr((d - tol) / s)
    return np.where(sigma > 0, p, certain)


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
