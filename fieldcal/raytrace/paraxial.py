"""Paraxial (y-nu) ray trace of a prescription: EFL, BFL, exit pupil, F-number.

This is the validation of the input table (does it describe the lens the user says it does?), not a
replacement for the real ray trace: best focus comes from the traced MTF (``bestfocus.py``), because
spherical aberration moves it tens of µm from the paraxial focus.

Conventions: object at infinity; distances in mm; a ray is (height y, reduced angle nu = n u). At a surface
of curvature c between media n and n': ``nu' = nu - y c (n' - n)``; then ``y += t nu' / n'``.
Aspheric terms do not act paraxially (only the vertex curvature does).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .prescription import LINE_D_NM, Prescription


@dataclass(frozen=True)
class ParaxialData:
    """First-order properties at one wavelength (mm)."""

    wavelength_nm: float
    efl_mm: float  # effective focal length
    bfl_mm: float  # last surface to paraxial focus
    image_distance_mm: float  # last surface to the stated image plane (the table's last thickness)
    entrance_pupil_diameter_mm: float | None  # for the stop semi-diameter given, or None
    exit_pupil_to_image_mm: float  # distance from the exit pupil to the stated image plane (> 0: pupil before it)
    paraxial_focus_shift_um: float  # paraxial focus relative to the stated image plane (+: behind it)


def _indices(rx: Prescription, wavelength_nm: float) -> list[float]:
    return [rx.index(i, wavelength_nm) for i in range(len(rx.surfaces))]


def trace(rx: Prescription, y0: float, nu0: float, wavelength_nm: float, start: int = 0,
          n_before: float = 1.0) -> tuple[float, float, float]:
    """Trace a paraxial ray from just before surface ``start`` to the last surface.

    Returns ``(y, nu, n)`` just after the last surface (height at it, reduced angle, medium index).
    """
    n_idx = _indices(rx, wavelength_nm)
    y, nu, n = float(y0), float(nu0), float(n_before)
    last = len(rx.surfaces) - 1
    for i in range(start, len(rx.surfaces)):
        s = rx.surfaces[i]
        n2 = n_idx[i]
        nu = nu - y * s.curvature_per_mm * (n2 - n)
        n = n2
        if i < last:
            y = y + s.thickness_mm * nu / n
    return y, nu, n


def paraxial(rx: Prescription, wavelength_nm: float = LINE_D_NM) -> ParaxialData:
    """EFL, BFL and the exit pupil of a prescription (object at infinity).

    Raises ``ValueError`` for an afocal system (no focus), which :func:`check_first_order` turns into a
    user error.
    """
    y, nu, n = trace(rx, 1.0, 0.0, wavelength_nm)
    if abs(nu) < 1e-12:
        raise ValueError("afocal system: a ray parallel to the axis leaves parallel")
    efl = -1.0 / nu  # u' = nu/n = -y0/f' with n = 1 in image space
    bfl = -y * n / nu
    # Exit pupil: image of the stop by the surfaces after it. Chief ray through the stop centre (y = 0).
    yc, nuc, nc = _trace_from_stop(rx, wavelength_nm)
    # Where the chief ray (extended backward in image space) crosses the axis: the exit pupil.
    exit_from_last = -yc * nc / nuc if abs(nuc) > 1e-15 else -math.inf  # +: after the last surface
    exit_to_image = rx.image_distance_mm - exit_from_last
    return ParaxialData(
        wavelength_nm=float(wavelength_nm), efl_mm=float(efl), bfl_mm=float(bfl),
        image_distance_mm=float(rx.image_distance_mm), entrance_pupil_diameter_mm=None,
        exit_pupil_to_image_mm=float(exit_to_image),
        paraxial_focus_shift_um=float((bfl - rx.image_distance_mm) * 1000.0))


def _trace_from_stop(rx: Prescription, wavelength_nm: float) -> tuple[float, float, float]:
    """Chief ray leaving the stop centre at a small angle, traced to just after the last surface."""
    k = rx.stop_index
    n_idx = _indices(rx, wavelength_nm)
    n = n_idx[k]
    nu = 0.01 * n  # any small angle: paraxial rays are linear in it
    y = rx.surfaces[k].thickness_mm * nu / n
    last = len(rx.surfaces) - 1
    for i in range(k + 1, len(rx.surfaces)):
        s = rx.surfaces[i]
        nu = nu - y * s.curvature_per_mm * (n_idx[i] - n)
        n = n_idx[i]
        if i < last:
            y = y + s.thickness_mm * nu / n
    if k == last:  # the stop is the last surface: the exit pupil is the stop itself
        return 0.0, nu, n
    return y, nu, n


def entrance_pupil_diameter_mm(rx: Prescription, f_number: float, wavelength_nm: float = LINE_D_NM) -> float:
    """Entrance pupil diameter giving image-space F-number ``f_number`` (= EFL / EPD) for an object at infinity."""
    return paraxial(rx, wavelength_nm).efl_mm / float(f_number)


def chromatic_focus_shift_um(rx: Prescription, wavelengths_nm) -> np.ndarray:
    """Paraxial focus of each wavelength relative to the d line (µm): the longitudinal colour."""
    ref = paraxial(rx, LINE_D_NM).bfl_mm
    return np.array([(paraxial(rx, w).bfl_mm - ref) * 1000.0 for w in wavelengths_nm])
