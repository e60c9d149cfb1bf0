"""Focus-tolerance model: how far from best focus contrast at fs stays within q of its peak, over the field.

Input: per-tile through-focus half-widths ``width_um`` measured at the calibration's MTF criterion (fs_cal, q_cal),
an :class:`fieldcal.optics.MTFCriterion` (saved as ``fs_cal_cyc_per_mm`` and ``q_cal``).
Per channel, a smooth model in the normalised radius, ``w_c(rho) = w_c0 [+ w_c1 rho^2]`` (the rho^2 term
kept only if it lowers BIC), fitted robustly (SciPy ``least_squares`` with a soft-L1 loss: a few tiles with
a misjudged width do not drag the field).

Conversion to other (fs, q) assumes the measured curve keeps its shape in defocus:

* shape "defocus-disc" (default): contrast(dz) = 2 J1(x)/x with x = pi fs |dz| / N (geometric defocus),
  so the half-width is x_q / (pi fs / N) with 2 J1(x_q)/x_q = 1 - q;
* shape "gaussian": contrast(dz) = exp(-dz^2 / 2 sigma^2 (fs)), half-width sigma sqrt(-2 ln(1 - q)).

Both give  w(fs, q) = w(fs_cal, q_cal) * (g(q) / g(q_cal)) * (fs_cal / fs)  (the 1/fs geometric-defocus law).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize

from ..errors import ParameterError
from ..optics import MTFCriterion, disc_x_at_contrast, valid_q
from .data import FitError, ImageGeometry, TileData

TOLERANCE_FIT_FORMAT = "fieldcal-tolerance-fit/1"
SHAPES = ("defocus-disc", "gaussian")


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

    def _rho2(self, x_px, y_px):
        r = self.geometry.half_diagonal_px
        return ((np.asarray(x_px, float) - self.centre_px[0]) ** 2 + (np.asarray(y_px, float) - self.centre_px[1]) ** 2) / r ** 2

    def width_cal_um(self, x_px, y_px, channel: str):
        """Fitted half-width (µm) at the calibration's (fs, q)."""
        if channel not in self.coef_um:
            raise ParameterError(f"no tolerance model for channel '{channel}'", field="channel",
                                 fix=f"use one of {', '.join(self.coef_um)}")
        c = self.coef_um[channel]
        r2 = self._rho2(x_px, y_px)
        w = c[0] + (c[1] * r2 if len(c) > 1 else 0.0 * r2)
        return np.maximum(w, 1e-3 * c[0] if c[0] > 0 else 1e-6)  # a width is positive

    def tolerance_um(self, x_px, y_px, channel: str, fs_cyc_per_mm: float, q: float):
        """Half-width (µm) of the defocus range where MTF(fs) stays within q of its peak."""
        crit, cal = MTFCriterion(fs_cyc_per_mm, q), self.calibrated_at
        scale = (shape_factor(crit.q, self.shape) / shape_factor(cal.q, self.shape)
                 * (cal.fs_cyc_per_mm / crit.fs_cyc_per_mm))
        return self.width_cal_um(x_px, y_px, channel) * scale

    def to_dict(self) -> dict[str, Any]:
        return {"format": TOLERANCE_FIT_FORMAT, "geometry": self.geometry.to_dict(),
                "centre_px": list(self.centre_px), "fs_cal_cyc_per_mm": self.calibrated_at.fs_cyc_per_mm,
                "q_cal": self.calibrated_at.q, "shape": self.shape, "coef_um": self.coef_um,
                "residual_sd_um": self.residual_sd_um, "diagnostics": self.diagnostics}

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
                       dict(d.get("residual_sd_um", {})), dict(d.get("diagnostics", {})))
        except (KeyError, TypeError, ValueError, ParameterError) as e:
            raise SpecError(f"malformed tolerance fit ({e})", path=path, field="tolerance",
                            fix="regenerate the profile") from None


def fit_tolerance(tiles: TileData, geometry: ImageGeometry, calibrated_at: MTFCriterion,
                  centre_px: tuple[float, float] | None = None, shape: str = "defocus-disc",
                  min_tiles: int = 4, source: str | None = None) -> ToleranceFit:
    """Fit the per-channel width model from tiles whose ``width_um`` was measured at ``calibrated_at``."""
    shape_factor(calibrated_at.q, shape)  # validates the shape
    centre = centre_px if centre_px is not None else geometry.centre_px
    R = geometry.half_diagonal_px
    coef, rsd, diag = {}, {}, {}
    for c in tiles.channels:
        m = (tiles.channel == c) & np.isfinite(tiles.width_um)
        if m.sum() < min_tiles:
            raise FitError(f"channel {c} has {int(m.sum())} tiles with a measured width; need {min_tiles}",
                           path=source, field="width_um", fix="measure through-focus widths on more tiles")
        w = tiles.width_um[m]
        r2 = ((tiles.x_px[m] - centre[0]) ** 2 + (tiles.y_px[m] - centre[1]) ** 2) / R ** 2
        med = float(np.median(w))
        f_scale = max(1.4826 * float(np.median(np.abs(w - med))), 1e-3 * med)
        cands = []
        for order in (0, 1):
            if m.sum() < order + 3:
                continue
            A = np.stack([r2 ** k for k in range(order + 1)], axis=1)
            res = optimize.least_squares(lambda p: (A @ p - w) / f_scale, np.r_[med, np.zeros(order)],
                                         loss="soft_l1")
            rss = float(np.sum(res.fun ** 2))
            n = w.size
            bic = n * math.log(max(rss / n, 1e-300)) + (order + 1) * math.log(n)
            cands.append((bic, order, res.x, float(np.std(A @ res.x - w))))
        bic, order, x, sd = min(cands, key=lambda t: t[0])
        coef[c] = [float(v) for v in x]
        rsd[c] = sd
        diag[c] = {"n_tiles": int(m.sum()), "order": order, "bic": {int(o): b for b, o, *_ in cands}}
    return ToleranceFit(geometry, (float(centre[0]), float(centre[1])), calibrated_at, shape, coef, rsd, diag)
