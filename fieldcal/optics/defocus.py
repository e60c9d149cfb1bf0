"""Through-focus optics of a simple lens: geometric defocus, diffraction, residual blur, focus tolerance.

Physics, not simulation: the simulator renders with it, the profile answers with it when it has no measured
widths, the planner derives tolerances and MTF losses from it, the through-focus curve fits use its shape.

The OTF at spatial frequency f (cycles/mm) and defocus dz (µm) is the product of

* geometric defocus: a uniform disc of diameter ``b = |dz| / N`` (image-side F-number N) whose OTF is
  ``2 J1(x) / x`` with ``x = pi b f`` (goes negative: contrast reversal);
* diffraction: the incoherent MTF of a circular pupil, cut-off ``1 / (lambda N)``;
* residual aberrations at best focus: a Gaussian of RMS ``residual_blur_um``.

The product is exact at focus and at large defocus and a few-percent approximation between (Stokseth 1969
gives the full defocused-diffraction OTF); docs/simulator.md states this. Only the first factor depends on
dz, so the focus tolerance δ(fs, q) solves ``2 J1(x)/x = 1 - q``.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy import special

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # for the annotation only: criterion.py uses this module
    from .criterion import MTFCriterion

# Default wavelengths (nm) of the usual channels: the C, e and F lines (Y: a monochrome sensor, e line).
DEFAULT_WAVELENGTH_NM = {"R": 656.3, "G": 546.1, "B": 486.1, "Y": 546.1}

#: First zero of J1: 2 J1(x)/x falls monotonically from 1 to 0 on [0, DISC_FIRST_ZERO].
DISC_FIRST_ZERO = float(special.jn_zeros(1, 1)[0])


def default_wavelength_nm(channel: str) -> float:
    """Wavelength (nm) a channel stands for when nothing else says (550 nm for unknown names)."""
    return DEFAULT_WAVELENGTH_NM.get(channel, 550.0)


def disc_otf(x):
    """``2 J1(x) / x`` (1 at x = 0): the OTF of a uniform disc at ``x = pi * diameter * f``."""
    x = np.asarray(x, dtype=np.float64)
    small = np.abs(x) < 1e-4
    xs = np.where(small, 1.0, x)  # guard the 0/0 at focus; the series is exact to 1e-17 there
    return np.where(small, 1.0 - x * x / 8.0, 2.0 * special.j1(xs) / xs)


def disc_otf_derivative(x):
    """d/dx of ``2 J1(x) / x``, which is ``-2 J2(x) / x``.

    J2 by the recurrence ``J2 = 2 J1 / x - J0`` (``special.jv(2, .)``, the general order, is 10x slower and this
    sits in the curve fits' inner loop); below |x| = 0.1, where the recurrence cancels, its series
    ``x^2/8 - x^4/96 + x^6/3072`` (next term 5e-11 of it there).
    """
    x = np.asarray(x, dtype=np.float64)
    small = np.abs(x) < 0.1
    xs = np.where(small, 1.0, x)
    x2 = x * x
    series = -2.0 * x * (1.0 / 8.0 - x2 * (1.0 / 96.0 - x2 / 3072.0))  # -2 J2(x) / x
    return np.where(small, series, -2.0 * (2.0 * special.j1(xs) / xs - special.j0(xs)) / xs)


def defocus_otf(f_cyc_per_mm, defocus_um, f_number: float):
    """Geometric-optics OTF of a uniform blur disc of diameter ``|dz| / N``."""
    b_mm = np.abs(np.asarray(defocus_um, dtype=np.float64)) / float(f_number) / 1000.0
    return disc_otf(np.pi * b_mm * np.asarray(f_cyc_per_mm, dtype=np.float64))


def diffraction_mtf(f_cyc_per_mm, wavelength_nm: float, f_number: float):
    """Incoherent MTF of an aberration-free circular pupil."""
    fc = 1.0 / (wavelength_nm * 1e-6 * f_number)  # cycles/mm
    v = np.clip(np.abs(np.asarray(f_cyc_per_mm, dtype=np.float64)) / fc, 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(v) - v * np.sqrt(1.0 - v * v))


def gaussian_mtf(f_cyc_per_mm, sigma_um: float):
    """MTF of a Gaussian blur of RMS ``sigma_um``."""
    s_mm = sigma_um / 1000.0
    f = np.asarray(f_cyc_per_mm, dtype=np.float64)
    return np.exp(-2.0 * (np.pi * s_mm * f) ** 2)


def through_focus_otf(f_cyc_per_mm, defocus_um, f_number: float, wavelength_nm: float,
                      residual_blur_um: float = 0.0):
    """Signed OTF of the model: geometric defocus x diffraction x residual blur (module docstring)."""
    return (defocus_otf(f_cyc_per_mm, defocus_um, f_number)
            * diffraction_mtf(f_cyc_per_mm, wavelength_nm, f_number)
            * gaussian_mtf(f_cyc_per_mm, residual_blur_um))


@functools.lru_cache(maxsize=128)
def disc_x_at_contrast(level: float) -> float:
    """x in (0, DISC_FIRST_ZERO] where ``2 J1(x)/x = level`` (the monotonic branch).

    As level -> 0 the target drops below the rounding floor of the function near the first zero, where a
    bracket would not change sign: the root is then the zero itself (the contrast is lost entirely there).
    """
    level = float(level)
    if not (level < 1.0):
        return 0.0
    if level <= float(disc_otf(DISC_FIRST_ZERO - 1e-9)):
        return DISC_FIRST_ZERO
    from scipy import optimize  # here, not at import: ~0.1 s of every command's start-up

    return float(optimize.brentq(lambda t: float(disc_otf(t)) - level, 1e-12, DISC_FIRST_ZERO - 1e-9,
                                 xtol=1e-14))


def focus_tolerance_um(criterion: MTFCriterion, f_number: float) -> float:
    """Defocus |dz| (µm) at which MTF(fs) has fallen to ``1 - q`` of its in-focus value.

    Solves ``2 J1(x)/x = 1 - q`` with ``x = pi (dz / N) fs``. Check: fs = 80 cycles/mm, q = 0.05, F/2 gives
    5.08 µm; ray tracing the paper's triplet gives -5.4/+6.1 µm on axis (docs/raytrace.md).
    """
    x = disc_x_at_contrast(1.0 - criterion.q)
    return float(x / (math.pi * criterion.fs_cyc_per_mm) * float(f_number) * 1000.0)
