"""Magnification and shift vs sensor position, per channel, and lateral colour (weighted least squares).

Model (t = (z - z_ref) / z_scale, z_scale = half the measured z range)::

    m_c(z) - 1 = sum_{k=1..K} b_ck t^k          shift_c(z) = sum_{k=1..K} d_ck t^k   (x and y separately)

No constant term: by definition (DESIGN.md) the frame at z_ref has m = 1 and no shift. K = 1 (linear:
focus breathing of a non-telecentric lens, a stage axis tilted against the optical axis) unless the
quadratic lowers BIC (error scale profiled out). Covariances are scaled by the Birge ratio max(1, chi2/dof), so underestimated
per-frame sigmas widen the uncertainty instead of hiding it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .data import FitError

GEOMETRY_FIT_FORMAT = "fieldcal-geometry-fit/1"


@dataclass(frozen=True)
class GeometryData:
    """Per-frame, per-channel measurements relative to the frame at ``z_ref_um``.

    ``colour_scale``/``colour_scale_sigma``: scale of this channel about the optical centre relative to the
    reference channel in the same frame (NaN when not measured).
    """

    z_um: np.ndarray
    channel: np.ndarray
    magnification: np.ndarray
    mag_sigma: np.ndarray
    shift_x_px: np.ndarray
    shift_y_px: np.ndarray
    shift_sigma_px: np.ndarray
    colour_scale: np.ndarray | None = None
    colour_scale_sigma: np.ndarray | None = None

    @classmethod
    def from_arrays(cls, z_um, channel, magnification, mag_sigma, shift_x_px, shift_y_px, shift_sigma_px,
                    colour_scale=None, colour_scale_sigma=None, source=None) -> "GeometryData":
        ch = np.asarray(channel).astype(str).ravel()
        n = ch.size

        def arr(name, v, positive=False, allow_nan=False):
            a = np.asarray(v, dtype=np.float64).ravel()
            if a.size != n:
                raise FitError(f"column '{name}' has {a.size} rows, 'channel' has {n}", path=source, field=name,
                               fix="give every geometry column one value per frame and channel")
            bad = np.isinf(a) if allow_nan else ~np.isfinite(a)
            if bad.any():
                raise FitError(f"column '{name}' has non-finite values", path=source, field=name,
                               fix="drop frames whose geometry could not be measured")
            if positive and (a[np.isfinite(a)] <= 0).any():
                raise FitError(f"column '{name}' must be > 0", path=source, field=name,
                               fix="uncertainties are positive numbers")
            return a

        cs = None if colour_scale is None else arr("colour_scale", colour_scale, allow_nan=True)
        css = None if colour_scale_sigma is None else arr("colour_scale_sigma", colour_scale_sigma, True, True)
        return cls(arr("z_um", z_um), ch, arr("magnification", magnification, True), arr("mag_sigma", mag_sigma, True),
                   arr("shift_x_px", shift_x_px), arr("shift_y_px", shift_y_px),
                   arr("shift_sigma_px", shift_sigma_px, True), cs, css)


@dataclass(frozen=True)
class PolyFit:
    """y(t) = sum_{k=1..K} coef[k-1] t^k with covariance; t = (z - z_ref) / z_scale."""

    coef: np.ndarray
    cov: np.ndarray
    chi2_dof: float

    def value(self, t):
        P = np.stack([t ** k for k in range(1, self.coef.size + 1)], axis=-1)
        return P @ self.coef

    def sd(self, t):
        P = np.stack([t ** k for k in range(1, self.coef.size + 1)], axis=-1)
        return np.sqrt(np.clip(np.einsum("...i,ij,...j->...", P, self.cov, P), 0.0, None))

    def to_dict(self):
        return {"coef": self.coef.tolist(), "cov": self.cov.tolist(), "chi2_dof": float(self.chi2_dof)}

    @classmethod
    def from_dict(cls, d):
        return cls(np.asarray(d["coef"], float), np.asarray(d["cov"], float), float(d["chi2_dof"]))


def _wls(t, y, sigma, order) -> tuple[PolyFit, float]:
    """Weighted LS through the origin; returns the fit and its BIC."""
    P = np.stack([t ** k for k in range(1, order + 1)], axis=1) / sigma[:, None]
    b = y / sigma
    coef, *_ = np.linalg.lstsq(P, b, rcond=None)
    r = b - P @ coef
    dof = max(1, t.size - order)
    chi2 = float(r @ r)
    birge = max(1.0, chi2 / dof)
    cov = np.linalg.pinv(P.T @ P) * birge
    # Gaussian likelihood with the error scale profiled out: the choice does not depend on how well the
    # per-frame sigmas were estimated (they may be too small by a common factor).
    bic = t.size * math.log(max(chi2, 1e-300) / t.size) + order * math.log(t.size)
    return PolyFit(coef, cov, chi2 / dof), bic


def _select(t, y, sigma, max_order) -> tuple[PolyFit, list[dict]]:
    table = []
    best = None
    for k in range(1, max_order + 1):
        if t.size < k + 2:
            break
        f, bic = _wls(t, y, sigma, k)
        table.append({"order": k, "bic": bic, "chi2_dof": f.chi2_dof})
        if best is None or bic < best[0]:
            best = (bic, f)
    return best[1], table


@dataclass
class GeometryFit:
    """Per-channel magnification(z) and shift(z) about z_ref, with uncertainties; lateral-colour scales."""

    z_ref_um: float
    z_scale_um: float
    mag: dict[str, PolyFit]
    shift_x: dict[str, PolyFit]
    shift_y: dict[str, PolyFit]
    colour: dict[str, tuple[float, float]] = field(default_factory=dict)  # (scale, sd) vs reference channel
    reference_channel: str | None = None
    diagnostics: dict = field(default_factory=dict)

    def _t(self, z_um):
        return (np.asarray(z_um, dtype=np.float64) - self.z_ref_um) / self.z_scale_um

    def _get(self, d, ch):
        if ch is None:
            ch = self.reference_channel or next(iter(d))
        if ch not in d:
            raise FitError(f"no geometry for channel '{ch}' (have {', '.join(d)})", field="channel",
                           fix=f"use one of {', '.join(d)}")
        return d[ch]

    def magnification(self, z_um, channel: str | None = None):
        """Image scale at z relative to z_ref (1 at z_ref)."""
        return 1.0 + self._get(self.mag, channel).value(self._t(z_um))

    def magnification_sd(self, z_um, channel: str | None = None):
        return self._get(self.mag, channel).sd(self._t(z_um))

    def shift_px(self, z_um, channel: str | None = None):
        """(dx, dy) image shift in px at z relative to z_ref."""
        t = self._t(z_um)
        return self._get(self.shift_x, channel).value(t), self._get(self.shift_y, channel).value(t)

    def shift_sd_px(self, z_um, channel: str | None = None):
        t = self._t(z_um)
        return self._get(self.shift_x, channel).sd(t), self._get(self.shift_y, channel).sd(t)

    def lateral_colour_scale(self, channel: str) -> float:
        """Scale of ``channel`` about the optical centre relative to the reference channel (1.0 if unmeasured)."""
        return float(self.colour.get(channel, (1.0, 0.0))[0])

    def to_dict(self) -> dict[str, Any]:
        return {"format": GEOMETRY_FIT_FORMAT, "z_ref_um": self.z_ref_um, "z_scale_um": self.z_scale_um,
                "reference_channel": self.reference_channel,
                "magnification": {c: f.to_dict() for c, f in self.mag.items()},
                "shift_x_px": {c: f.to_dict() for c, f in self.shift_x.items()},
                "shift_y_px": {c: f.to_dict() for c, f in self.shift_y.items()},
                "lateral_colour": {c: {"scale": v[0], "sd": v[1]} for c, v in self.colour.items()},
                "diagnostics": self.diagnostics}

    @classmethod
    def from_dict(cls, d: dict[str, Any], path=None) -> "GeometryFit":
        from ..errors import SpecError
        if not isinstance(d, dict) or d.get("format") != GEOMETRY_FIT_FORMAT:
            raise SpecError(f"not a {GEOMETRY_FIT_FORMAT} block", path=path, field="geometry",
                            fix="write it with GeometryFit.to_dict()")
        try:
            return cls(float(d["z_ref_um"]), float(d["z_scale_um"]),
                       {c: PolyFit.from_dict(v) for c, v in d["magnification"].items()},
                       {c: PolyFit.from_dict(v) for c, v in d["shift_x_px"].items()},
                       {c: PolyFit.from_dict(v) for c, v in d["shift_y_px"].items()},
                       {c: (float(v["scale"]), float(v["sd"])) for c, v in d.get("lateral_colour", {}).items()},
                       d.get("reference_channel"), dict(d.get("diagnostics", {})))
        except (KeyError, TypeError, ValueError) as e:
            raise SpecError(f"malformed geometry fit ({e})", path=path, field="geometry",
                            fix="regenerate the profile") from None


def fit_geometry(data: GeometryData, z_ref_um: float, reference_channel: str | None = None,
                 max_order: int = 2, source: str | None = None) -> GeometryFit:
    """Fit magnification/shift vs z per channel (linear, quadratic if BIC prefers it) and lateral colour."""
    chans = list(dict.fromkeys(data.channel.tolist()))
    if not chans:
        raise FitError("no geometry measurements", path=source, field="frames",
                       fix="measure magnification/shift on at least 3 frames")
    span = float(np.max(np.abs(data.z_um - z_ref_um)))
    if not span > 0:
        raise FitError("all geometry frames are at z_ref", path=source, field="z_um",
                       fix="measure frames across the stack's z range")
    ref = reference_channel or ("G" if "G" in chans else chans[0])
    mag, sx, sy, diag = {}, {}, {}, {}
    for c in chans:
        m = data.channel == c
        t = (data.z_um[m] - z_ref_um) / span
        # frames at z_ref carry no information about the slope (their values are 1 / 0 by definition)
        use = np.abs(t) > 1e-12
        if use.sum() < 2:
            raise FitError(f"channel {c} has {int(use.sum())} frames away from z_ref; need at least 2",
                           path=source, field="z_um", fix="measure geometry on more frames")
        t = t[use]
        mag[c], tm = _select(t, data.magnification[m][use] - 1.0, data.mag_sigma[m][use], max_order)
        sx[c], tx = _select(t, data.shift_x_px[m][use], data.shift_sigma_px[m][use], max_order)
        sy[c], ty = _select(t, data.shift_y_px[m][use], data.shift_sigma_px[m][use], max_order)
        diag[c] = {"n_frames": int(use.sum()), "magnification": tm, "shift_x": tx, "shift_y": ty}
    colour = {}
    if data.colour_scale is not None:
        sig = data.colour_scale_sigma if data.colour_scale_sigma is not None else np.full(len(data.z_um), np.nan)
        for c in chans:
            m = (data.channel == c) & np.isfinite(data.colour_scale)
            if not m.any():
                continue
            s = sig[m]
            s = np.where(np.isfinite(s), s, np.nanmedian(s) if np.isfinite(s).any() else 1e-3)
            w = 1.0 / s ** 2
            mean = float(np.sum(w * data.colour_scale[m]) / np.sum(w))
            chi2 = float(np.sum(w * (data.colour_scale[m] - mean) ** 2))
            birge = max(1.0, chi2 / max(1, m.sum() - 1))
            colour[c] = (mean, float(math.sqrt(birge / np.sum(w))))
        colour.setdefault(ref, (1.0, 0.0))
    return GeometryFit(float(z_ref_um), span, mag, sx, sy, colour, ref, diag)
