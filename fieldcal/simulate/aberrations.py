"""The optional ``aberrations`` block of a ``fieldcal-lens/1`` spec: wavefront terms for the wave-optics path.

Only the wave-optics renderer (:mod:`fieldcal.simulate.wave`, ``--optics wave``) reads it; the geometric path
ignores it. Every term is a wavefront (optical path difference) coefficient whose value at normalised field
height ``rho`` is a polynomial ``c(rho) = sum_k a_k rho**k`` (``a_0`` first), in waves at
``reference_wavelength_nm`` or in µm. Pupil coordinates are normalised (``rho_p`` in [0, 1], azimuth ``theta``),
``phi`` is the azimuth of the field point about the optical centre (the tangential direction):

* ``spherical``   -> ``W040 rho_p**4`` (Seidel primary spherical; > 0 = under-corrected, the usual positive lens:
  marginal rays focus nearer the lens than paraxial ones);
* ``spherical6``  -> ``W060 rho_p**6`` (secondary spherical, e.g. from aspheres);
* ``coma``        -> ``W131 rho_p**3 cos(theta - phi)``;
* ``astigmatism`` -> ``Wast rho_p**2 cos(2 (theta - phi))`` (astigmatism without its focus part, so the lens's
  surface stays the mean focus: tangential - sagittal focus separation is ``-16 N**2 Wast``). It adds to the
  channel's ``astigmatism_um``, which the wave path turns into the same term.

``channels`` optionally overrides terms per channel (``{"R": {"spherical": [0.54]}, ...}``: spherochromatism),
``spectral_response`` optionally replaces a channel's default band (docs/simulator.md) by ``[[nm, weight], ...]``.
docs/lens-spec.md documents the block; docs/simulator.md the conventions (defocus sign, focus reference).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from fieldcal.errors import SpecError

TERMS = ("spherical", "spherical6", "coma", "astigmatism")
UNITS = ("waves", "um")


@dataclass(frozen=True)
class Aberrations:
    """Field-dependent wavefront coefficients (polynomials in normalised field height)."""

    unit: str = "waves"
    reference_wavelength_nm: float = 546.1
    spherical: tuple[float, ...] = ()
    spherical6: tuple[float, ...] = ()
    coma: tuple[float, ...] = ()
    astigmatism: tuple[float, ...] = ()
    spectral_response: dict[str, tuple[tuple[float, float], ...]] = field(default_factory=dict)
    channels: dict[str, dict[str, tuple[float, ...]]] = field(default_factory=dict)  # per-channel term overrides

    def for_channel(self, name: str) -> "Aberrations":
        """The terms that hold for one channel (its overrides applied)."""
        over = self.channels.get(name)
        return replace(self, channels={}, **over) if over else self

    def _um(self, coeffs: tuple[float, ...], rho) -> np.ndarray:
        r = np.asarray(rho, dtype=np.float64)
        v = np.zeros_like(r)
        for a in reversed(coeffs):  # Horner
            v = v * r + a
        scale = self.reference_wavelength_nm * 1e-3 if self.unit == "waves" else 1.0
        return v * scale

    def w040_um(self, rho) -> np.ndarray:
        """Spherical aberration W040 (µm of wavefront) at normalised field height rho."""
        return self._um(self.spherical, rho)

    def w060_um(self, rho) -> np.ndarray:
        """Secondary spherical aberration W060 (µm) at rho."""
        return self._um(self.spherical6, rho)

    def w131_um(self, rho) -> np.ndarray:
        """Coma W131 (µm) at rho."""
        return self._um(self.coma, rho)

    def wast_um(self, rho) -> np.ndarray:
        """Astigmatism coefficient of ``rho_p**2 cos 2(theta - phi)`` (µm) at rho (not counting astigmatism_um)."""
        return self._um(self.astigmatism, rho)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"unit": self.unit, "reference_wavelength_nm": self.reference_wavelength_nm}
        for t in TERMS:
            if getattr(self, t):
                d[t] = list(getattr(self, t))
        if self.channels:
            d["channels"] = {k: {t: list(v) for t, v in o.items()} for k, o in self.channels.items()}
        if self.spectral_response:
            d["spectral_response"] = {k: [list(p) for p in v] for k, v in self.spectral_response.items()}
        return d


def parse_aberrations(d: Any, path=None, channel_names: tuple[str, ...] = ()) -> Aberrations:
    """Validate an ``aberrations`` block (SpecError naming the file, the field and the fix)."""
    def err(fld, what, fix):
        return SpecError(what, path=path, field=f"aberrations{fld}", fix=fix)

    if not isinstance(d, dict):
        raise err("", "must be an object", "e.g. {\"unit\": \"waves\", \"spherical\": [0.5]} (docs/lens-spec.md)")
    known = {"unit", "reference_wavelength_nm", "spectral_response", "channels", *TERMS}
    unknown = sorted(set(d) - known)
    if unknown:
        raise err(f".{unknown[0]}", f"unknown key {unknown[0]!r}",
                  f"use only {', '.join(sorted(known))} (docs/lens-spec.md)")
    unit = d.get("unit", "waves")
    if unit not in UNITS:
        raise err(".unit", f"unknown unit {unit!r}", "use \"waves\" (at reference_wavelength_nm) or \"um\"")
    lam = d.get("reference_wavelength_nm", 546.1)
    if isinstance(lam, bool) or not isinstance(lam, (int, float)) or not (math.isfinite(lam) and 200 <= lam <= 2000):
        raise err(".reference_wavelength_nm", f"must be a wavelength in nm (200..2000), got {lam!r}", "e.g. 546.1")
    def poly(v, fld):
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v]  # a constant
        if (not isinstance(v, list) or len(v) > 8
                or not all(isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) for a in v)):
            raise err(fld, f"must be a list of at most 8 finite numbers (coefficients of rho^0, rho^1, ...), "
                           f"got {v!r}", "e.g. [0.5] (constant) or [0, 0, 0.3] (growing as rho^2)")
        return tuple(float(a) for a in v)

    terms = {t: poly(d.get(t, []), f".{t}") for t in TERMS}
    per = d.get("channels", {})
    if not isinstance(per, dict):
        raise err(".channels", "must be an object {channel: {term: [...]}}", "e.g. {\"R\": {\"spherical\": [0.54]}}")
    overrides: dict[str, dict[str, tuple[float, ...]]] = {}
    for ch, o in per.items():
        fld = f".channels.{ch}"
        if channel_names and ch not in channel_names:
            raise err(fld, f"no channel {ch!r} in this lens", f"use one of {', '.join(channel_names)}")
        if not isinstance(o, dict) or not set(o) <= set(TERMS):
            raise err(fld, f"must be an object with only {', '.join(TERMS)}", "e.g. {\"spherical\": [0.54]}")
        overrides[str(ch)] = {t: poly(v, f"{fld}.{t}") for t, v in o.items()}
    bands: dict[str, tuple[tuple[float, float], ...]] = {}
    sr = d.get("spectral_response", {})
    if not isinstance(sr, dict):
        raise err(".spectral_response", "must be an object {channel: [[nm, weight], ...]}",
                  "e.g. {\"G\": [[520, 0.25], [546, 0.5], [570, 0.25]]}")
    for ch, pts in sr.items():
        fld = f".spectral_response.{ch}"
        if channel_names and ch not in channel_names:
            raise err(fld, f"no channel {ch!r} in this lens", f"use one of {', '.join(channel_names)}")
        ok = isinstance(pts, list) and 1 <= len(pts) <= 16 and all(
            isinstance(p, list) and len(p) == 2
            and all(isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) for a in p)
            and 200 <= p[0] <= 2000 and p[1] >= 0 for p in pts)
        if not ok or sum(p[1] for p in pts) <= 0:
            raise err(fld, "must be 1 to 16 pairs [wavelength_nm (200..2000), weight >= 0] with a positive sum",
                      "e.g. [[520, 0.25], [546, 0.5], [570, 0.25]]")
        bands[str(ch)] = tuple((float(a), float(b)) for a, b in pts)
    return Aberrations(unit=unit, reference_wavelength_nm=float(lam), spectral_response=bands, channels=overrides,
                       **terms)
