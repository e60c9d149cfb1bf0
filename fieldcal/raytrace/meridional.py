"""Real (finite) ray trace of on-axis meridional rays through a prescription, numpy only: spherical aberration.

The paraxial trace (``paraxial.py``) gives the paraxial focus; spherical aberration moves the sharpest position
tens of µm from it, which only real rays show. This traces rays parallel to the axis (object at infinity) at
pupil heights ``rho * EPD / 2`` through every surface (standard or even asphere, exact intersection by Newton
iteration, vector Snell's law), measures where each crosses the axis (the longitudinal aberration LA(rho)
relative to the paraxial focus) and turns it into the wavefront coefficients the wave-optics simulator uses
(``fieldcal/simulate/wave.py``): with ``eps = -2 N dW/drho`` and ``eps = LA rho / (2 N)`` at the paraxial
plane, ``W = -(1 / 4N^2) int LA rho drho``, so ``LA = L2 rho^2 + L4 rho^4`` gives ``W040 = -L2 / (16 N^2)``
and ``W060 = -L4 / (24 N^2)``. On axis only (no field), so no coma or astigmatism.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .paraxial import paraxial
from .prescription import LINE_D_NM, Prescription, Surface


def _sag(s: Surface, r: float) -> float:
    c, k = s.curvature_per_mm, s.conic
    a4, a6, a8 = s.aspheric
    z = c * r * r / (1.0 + math.sqrt(max(1.0 - (1.0 + k) * c * c * r * r, 0.0))) if c else 0.0
    return z + a4 * r ** 4 + a6 * r ** 6 + a8 * r ** 8


def _slope(s: Surface, r: float) -> float:
    c, k = s.curvature_per_mm, s.conic
    a4, a6, a8 = s.aspheric
    d = c * r / math.sqrt(1.0 - (1.0 + k) * c * c * r * r) if c else 0.0
    return d + 4 * a4 * r ** 3 + 6 * a6 * r ** 5 + 8 * a8 * r ** 7


def axis_crossing_um(rx: Prescription, height_mm: float, wavelength_nm: float) -> float:
    """Where a ray entering parallel to the axis at ``height_mm`` crosses the axis after the last surface (µm
    from the stated image plane, + away from the lens)."""
    y, z, dy, dz = float(height_mm), -1.0, 0.0, 1.0
    n1, zv = 1.0, 0.0
    for i, s in enumerate(rx.surfaces):
        n2 = rx.index(i, wavelength_nm)
        t = (zv - z) / dz
        for _ in range(60):  # Newton on z(t) - zv - sag(y(t)) = 0
            yy = y + t * dy
            f = z + t * dz - zv - _sag(s, yy)
            step = f / (dz - _slope(s, yy) * dy)
            t -= step
            if abs(step) < 1e-13:
                break
        y, z = y + t * dy, z + t * dz
        ny, nz = -_slope(s, y), 1.0
        norm = math.hypot(ny, nz)
        ny, nz = ny / norm, nz / norm
        mu, ci = n1 / n2, dy * ny + dz * nz
        root = 1.0 - mu * mu * (1.0 - ci * ci)
        if root < 0:
            raise ValueError(f"total internal reflection at surface {s.label} for a ray at {height_mm} mm")
        g = math.sqrt(root) - mu * ci
        dy, dz = mu * dy + g * ny, mu * dz + g * nz
        n1 = n2
        zv += s.thickness_mm
    return (z - y * dz / dy - zv) * 1000.0


@dataclass(frozen=True)
class SphericalAberration:
    """On-axis spherical aberration of a prescription at one wavelength (µm)."""

    wavelength_nm: float
    f_number: float
    paraxial_focus_um: float  # from the stated image plane, + away from the lens
    rho: tuple[float, ...]
    la_um: tuple[float, ...]  # real-ray axis crossing minus paraxial focus
    w040_um: float
    w060_um: float


def spherical_aberration(rx: Prescription, wavelength_nm: float, f_number: float, n_rays: int = 20,
                         epd_wavelength_nm: float = LINE_D_NM) -> SphericalAberration:
    """Trace ``n_rays`` pupil zones (rho 0.05..1) and fit LA = L2 rho^2 + L4 rho^4 (module docstring).

    The entrance pupil is EFL(d line) / N, fixed over wavelength, as in ``bestfocus.py``.
    """
    epd = paraxial(rx, epd_wavelength_nm).efl_mm / f_number
    par = paraxial(rx, wavelength_nm).paraxial_focus_shift_um
    rho = np.linspace(0.05, 1.0, n_rays)
    la = np.array([axis_crossing_um(rx, r * epd / 2.0, wavelength_nm) for r in rho]) - par
    (l2, l4), *_ = np.linalg.lstsq(np.stack([rho ** 2, rho ** 4], axis=1), la, rcond=None)
    n2 = f_number * f_number
    return SphericalAberration(float(wavelength_nm), float(f_number), float(par), tuple(map(float, rho)),
                               tuple(map(float, la)), float(-l2 / (16.0 * n2)), float(-l4 / (24.0 * n2)))
